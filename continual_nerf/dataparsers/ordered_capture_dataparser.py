"""`continual-nerfstudio`: a nerfstudio transforms.json or COLMAP capture (Tanks and Temples, ...) in capture order.

The capture order comes from the frames' timestamps, else the numbers in their image file names, else
the order the file lists them in; `--order` forces one, and the log says which one was used. Frames a transforms.json
names in val_filenames or test_filenames are the test frames of their tasks and never train.
"""

from __future__ import annotations

import json
import os
import re
import struct
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Callable, Dict, List, Literal, Optional, Set, Tuple, Type, get_args

import numpy as np
from nerfstudio.cameras.cameras import CameraType
from nerfstudio.data.dataparsers.base_dataparser import DataParser, DataparserOutputs
from nerfstudio.data.utils import colmap_parsing_utils as colmap
from nerfstudio.utils.rich_utils import CONSOLE

from continual_nerf.dataparsers.capture import (
    OPENCV_TO_OPENGL,
    CaptureDataParserConfig,
    CaptureFrames,
    capture_outputs,
    check_pose,
)
from continual_nerf.dataparsers.transforms_json import (
    CROPPED_CAMERA_TYPES,
    fisheye_crop_radius,
    natural_key,
    parse_intrinsics,
    transforms_pose,
)
from continual_nerf.errors import ContinualConfigError, DatasetError

Order = Literal["auto", "timestamp", "filename", "file"]

ORDER_DESCRIPTIONS = {
    "timestamp": "the frames' timestamps",
    "filename": "the numbers in the image file names (natural sort: frame_2 before frame_10)",
    "file": "the order the file lists the frames in",
}
"""How the log names each capture order."""

SPLIT_LISTS = ("train_filenames", "val_filenames", "test_filenames")
"""transforms.json keys naming the frames of nerfstudio's splits."""

TIMESTAMP_KEYS = ("timestamp", "time")
"""Per-frame keys of transforms.json read as the capture time; the first one present is used."""

COLMAP_PARAMETERS = {
    "SIMPLE_PINHOLE": ("f", "cx", "cy"),
    "PINHOLE": ("fl_x", "fl_y", "cx", "cy"),
    "SIMPLE_RADIAL": ("f", "cx", "cy", "k1"),
    "RADIAL": ("f", "cx", "cy", "k1", "k2"),
    "OPENCV": ("fl_x", "fl_y", "cx", "cy", "k1", "k2", "p1", "p2"),
    "OPENCV_FISHEYE": ("fl_x", "fl_y", "cx", "cy", "k1", "k2", "k3", "k4"),
}
"""transforms.json names of the parameters of the COLMAP camera models nerfstudio trains on, in COLMAP's order
(f: fl_x = fl_y)."""

COLMAP_READERS: Dict[str, Tuple[Callable, Callable]] = {
    ".bin": (colmap.read_cameras_binary, colmap.read_images_binary),
    ".txt": (colmap.read_cameras_text, colmap.read_images_text),
}
"""nerfstudio's readers of a COLMAP model's cameras and images files, by file extension (binary preferred)."""


@dataclass
class OrderedCaptureDataParserConfig(CaptureDataParserConfig):
    """A nerfstudio transforms.json or COLMAP capture (Tanks and Temples, ...) as one trajectory in capture order."""

    _target: Type = field(default_factory=lambda: OrderedCaptureDataParser)
    """The dataparser this config builds."""
    data: Path = Path()
    """transforms.json or its folder, a COLMAP model folder (cameras, images .bin/.txt) or a scene with sparse/0."""
    order: Order = "auto"
    """Capture order: frame timestamps (time/timestamp), file-name numbers or file order; auto: first available."""
    images_dir: Optional[Path] = None
    """Images of a COLMAP model; default: the `images` folder next to it (<scene>/images for <scene>/sparse/0)."""
    depth_unit_scale_factor: float = 1e-3
    """Metres one unit of the frames' depth maps (depth_file_path) is: 1e-3 for millimetres, as nerfstudio's parser."""

    def validate(self) -> None:
        super().validate()
        if self.order not in get_args(Order):
            raise ContinualConfigError(f"--order must be one of {', '.join(get_args(Order))}, got {self.order}")
        if not (np.isfinite(self.depth_unit_scale_factor) and self.depth_unit_scale_factor > 0):
            raise ContinualConfigError(
                f"--depth-unit-scale-factor must be a positive number of metres, got {self.depth_unit_scale_factor}"
            )


@dataclass
class ListedFrame:
    """A frame as the capture file lists it, before the capture order is known."""

    name: str
    """Image path as the file writes it; filename order sorts these."""
    image: Path
    camera_to_world: np.ndarray
    """(4, 4) float64, OpenGL convention."""
    intrinsics: np.ndarray
    """fx, fy, cx, cy, width, height."""
    distortion: np.ndarray
    """nerfstudio distortion parameters [k1, k2, k3, k4, p1, p2] (12 for FISHEYE624)."""
    camera_type: CameraType = CameraType.PERSPECTIVE
    """nerfstudio's camera type of the frame's camera model."""
    mask: Optional[Path] = None
    """The frame's `mask_path` (0: the pixel does not train), None when it has none."""
    depth: Optional[Path] = None
    """The frame's `depth_file_path` (z-depth), None when it has none."""
    crop_radius: Optional[float] = None
    """Radius (pixels) around the image centre outside which a fisheye frame's pixels do not train; None: none."""
    timestamp: Any = None
    """The frame's raw `timestamp`/`time` value, None when it has none; parsed only when ordering by time."""
    held_out: bool = False
    """Whether the file names the frame for testing (val_filenames, test_filenames): it never trains."""


def existing_file(path: Path, listed_in: Path, what: str = "image") -> Path:
    if not path.is_file():
        raise DatasetError(f"{path}: {what} listed in {listed_in} does not exist")
    return path


def check_everywhere_or_nowhere(frames: List[ListedFrame], source: Path) -> None:
    """nerfstudio's rule: a mask for every frame or for none (a frame without one would train on every pixel); and a
    depth map for every frame or for none, as nerfstudio's parser asserts."""
    for key, attribute, what in (("mask_path", "mask", "a mask"), ("depth_file_path", "depth", "a depth map")):
        without = [frame.name for frame in frames if getattr(frame, attribute) is None]
        if 0 < len(without) < len(frames):
            raise DatasetError(
                f"{source} frame {without[0]}: has no {key} while other frames have one (give every frame {what}, "
                "or none)"
            )


def read_transforms(path: Path) -> List[ListedFrame]:
    """The frames of a nerfstudio transforms.json, in file order."""
    try:
        meta = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as error:
        raise DatasetError(f"{path}: not valid JSON ({error})") from None
    frames = meta.get("frames") if isinstance(meta, dict) else None
    if not isinstance(frames, list) or not frames:
        raise DatasetError(f"{path}: has no `frames` list")
    shared = {key: value for key, value in meta.items() if key != "frames"}
    radius = fisheye_crop_radius(meta, str(path))
    listed = []
    for number, frame in enumerate(frames):
        if not isinstance(frame, dict) or "file_path" not in frame:
            raise DatasetError(f"{path}: frame {number} has no file_path")
        name = str(frame["file_path"])
        source = f"{path} frame {name}"
        # a frame's own intrinsics override the file-wide ones
        intrinsics, distortion, camera_type = parse_intrinsics({**shared, **frame}, source)
        mask, depth = frame.get("mask_path"), frame.get("depth_file_path")
        listed.append(
            ListedFrame(
                name=name,
                image=existing_file(path.parent / name, path),
                camera_to_world=transforms_pose(frame.get("transform_matrix"), source),
                intrinsics=intrinsics,
                distortion=distortion,
                camera_type=camera_type,
                mask=None if mask is None else existing_file(path.parent / str(mask), path, "mask"),
                depth=None if depth is None else existing_file(path.parent / str(depth), path, "depth map"),
                crop_radius=radius if camera_type in CROPPED_CAMERA_TYPES else None,
                timestamp=next((frame[key] for key in TIMESTAMP_KEYS if key in frame), None),
            )
        )
    check_everywhere_or_nowhere(listed, path)
    return apply_split_lists(meta, listed, path)


def split_list(meta: Dict[str, Any], key: str, path: Path) -> Optional[Set[str]]:
    """The normalised file paths of the file's `key` list (nerfstudio's train/val/test_filenames), None without one."""
    names = meta.get(key)
    if names is None:
        return None
    if not isinstance(names, list) or not all(isinstance(name, str) for name in names):
        raise DatasetError(f"{path}: {key} must be a list of file paths")
    return {os.path.normpath(name) for name in names}


def apply_split_lists(meta: Dict[str, Any], listed: List[ListedFrame], path: Path) -> List[ListedFrame]:
    """nerfstudio's split lists in the continual setting: frames in val_filenames or test_filenames are test frames
    and never train; with train_filenames, frames in none of the lists are left out."""
    lists = {key: split_list(meta, key, path) for key in SPLIT_LISTS}
    listed_names = [os.path.normpath(frame.name) for frame in listed]
    for key, names in lists.items():
        unknown = sorted((names or set()) - set(listed_names))
        if unknown:
            raise DatasetError(f"{path}: {key} names {unknown[0]}, which is no frame's file_path")
    tested = (lists["val_filenames"] or set()) | (lists["test_filenames"] or set())
    trained = lists["train_filenames"]
    both = sorted(tested & (trained or set()))
    if both:
        raise DatasetError(
            f"{path}: {both[0]} is in train_filenames and in val_filenames or test_filenames; a test frame never trains"
        )
    kept = set(listed_names) if trained is None else trained | tested
    return [replace(frame, held_out=name in tested) for frame, name in zip(listed, listed_names) if name in kept]


def colmap_model_files(folder: Path) -> Optional[Tuple[Path, Path]]:
    """The cameras and images files of a COLMAP model in `folder`, or None when it holds none."""
    for extension in COLMAP_READERS:
        cameras, images = folder / f"cameras{extension}", folder / f"images{extension}"
        if cameras.is_file() and images.is_file():
            return cameras, images
    return None


def read_colmap_file(reader: Callable[[Path], Dict[int, Any]], path: Path) -> Dict[int, Any]:
    try:
        return reader(path)
    except (struct.error, ValueError, IndexError, KeyError, UnicodeDecodeError) as error:
        raise DatasetError(f"{path}: not a readable COLMAP file ({type(error).__name__}: {error})") from None


def colmap_camera_values(camera: colmap.Camera) -> Dict[str, Any]:
    """A COLMAP camera as transforms.json keys, so both formats share parse_intrinsics."""
    values: Dict[str, Any] = dict(zip(COLMAP_PARAMETERS.get(camera.model, ()), camera.params))
    if "f" in values:
        values["fl_x"] = values["fl_y"] = values.pop("f")
    return {"camera_model": camera.model, "w": camera.width, "h": camera.height, **values}


def colmap_pose(image: colmap.Image, source: str) -> np.ndarray:
    """OpenGL camera-to-world of a COLMAP image, whose qvec/tvec are OpenCV world-to-camera."""
    length = np.linalg.norm(image.qvec)
    if length == 0:
        raise DatasetError(f"{source}: rotation quaternion has zero length")
    world_to_camera = np.eye(4)
    # text models round the unit quaternions COLMAP writes: renormalise before building the rotation
    world_to_camera[:3, :3] = colmap.qvec2rotmat(image.qvec / length)
    world_to_camera[:3, 3] = image.tvec
    check_pose(world_to_camera, source)
    camera_to_world = np.eye(4)
    camera_to_world[:3, :3] = world_to_camera[:3, :3].T
    camera_to_world[:3, 3] = -world_to_camera[:3, :3].T @ image.tvec
    return camera_to_world @ OPENCV_TO_OPENGL


def read_colmap(cameras_file: Path, images_file: Path, images_dir: Path) -> List[ListedFrame]:
    """The registered images of a COLMAP model, in file order."""
    read_cameras, read_images = COLMAP_READERS[cameras_file.suffix]
    cameras = read_colmap_file(read_cameras, cameras_file)
    images = read_colmap_file(read_images, images_file)
    if not images:
        raise DatasetError(f"{images_file}: the COLMAP model has no registered images")
    listed = []
    for image in images.values():
        if image.camera_id not in cameras:
            raise DatasetError(
                f"{images_file}: image {image.name} uses camera {image.camera_id}, which {cameras_file} lacks"
            )
        camera_source = f"{cameras_file} camera {image.camera_id}"
        values = colmap_camera_values(cameras[image.camera_id])
        intrinsics, distortion, camera_type = parse_intrinsics(values, camera_source)
        listed.append(
            ListedFrame(
                name=image.name,
                image=existing_file(images_dir / image.name, images_file),
                camera_to_world=colmap_pose(image, f"{images_file} image {image.name}"),
                intrinsics=intrinsics,
                distortion=distortion,
                camera_type=camera_type,
            )
        )
    return listed


def colmap_images_dir(model: Path, images_dir: Optional[Path]) -> Path:
    """The configured images folder, else the nearest `images` folder at or above the model folder."""
    if images_dir is not None:
        if not images_dir.is_dir():
            raise DatasetError(f"{images_dir}: images folder does not exist")
        return images_dir
    # COLMAP models sit in <scene>/sparse/0 (or <scene>/sparse) next to <scene>/images
    for folder in (model, model.parent, model.parent.parent):
        if (folder / "images").is_dir():
            return folder / "images"
    raise DatasetError(f"{model}: no images folder next to this COLMAP model; set --images-dir")


def read_listed_frames(config: OrderedCaptureDataParserConfig) -> Tuple[List[ListedFrame], Path]:
    """The capture's frames in file order, and the file that lists them."""
    data = config.data
    if not data.exists():
        raise DatasetError(f"{data}: no such capture folder or file")
    transforms = data if data.is_file() else data / "transforms.json"
    if transforms.suffix == ".json" and transforms.is_file():
        return read_transforms(transforms), transforms
    for model in (data, data / "sparse" / "0"):
        files = colmap_model_files(model)
        if files is not None:
            return read_colmap(*files, colmap_images_dir(model, config.images_dir)), files[1]
    raise DatasetError(
        f"{data}: holds neither transforms.json nor a COLMAP model (cameras, images .bin or .txt, here or in sparse/0)"
    )


def timestamps(frames: List[ListedFrame], source: Path) -> np.ndarray:
    """The frames' timestamps as numbers; a frame without one, or with a non-number, is an error."""
    values = []
    for frame in frames:
        if frame.timestamp is None:
            raise DatasetError(
                f"{source} frame {frame.name}: has no `time` or `timestamp` (needed by --order timestamp)"
            )
        try:
            value = float(frame.timestamp)
        except (TypeError, ValueError):
            value = np.nan
        if not np.isfinite(value):
            raise DatasetError(f"{source} frame {frame.name}: timestamp {frame.timestamp!r} is not a finite number")
        values.append(value)
    return np.array(values)


def timestamp_order(frames: List[ListedFrame], source: Path) -> np.ndarray:
    """Frame indices by increasing timestamp; equal timestamps leave the order undefined, so they are an error."""
    times = timestamps(frames, source)
    permutation = np.argsort(times, kind="stable")
    repeated = np.flatnonzero(np.diff(times[permutation]) == 0)
    if len(repeated):
        first, second = permutation[repeated[0]], permutation[repeated[0] + 1]
        raise DatasetError(
            f"{source}: frames {frames[first].name} and {frames[second].name} have the same timestamp "
            f"{float(times[first])!r}; use --order filename or --order file"
        )
    return permutation


def auto_order(frames: List[ListedFrame]) -> str:
    """Timestamps when every frame has one, else file-name numbers when every file name has one, else file order."""
    if all(frame.timestamp is not None for frame in frames):
        return "timestamp"
    if all(re.search(r"\d", Path(frame.name).name) for frame in frames):
        return "filename"
    return "file"


def capture_order(frames: List[ListedFrame], order: str, source: Path) -> np.ndarray:
    """Indices of `frames` in capture order; logs which order was used."""
    chosen = auto_order(frames) if order == "auto" else order
    if chosen == "timestamp":
        permutation = timestamp_order(frames, source)
    elif chosen == "filename":
        permutation = np.array(sorted(range(len(frames)), key=lambda index: natural_key(frames[index].name)))
    else:
        permutation = np.arange(len(frames))
    how = " (picked by --order auto)" if order == "auto" else ""
    CONSOLE.log(f"{source}: capture order from {ORDER_DESCRIPTIONS[chosen]}{how}")
    return permutation


def check_fisheye624(frames: List[ListedFrame], source: Path) -> None:
    """nerfstudio 1.1.5 unprojects every FISHEYE624 ray of a batch with the calibration of its first one, and a
    training batch draws pixels of many frames: every frame needs the first FISHEYE624 frame's calibration (another
    model's 6 distortion parameters could not stand beside its 12 either)."""
    first = next((frame for frame in frames if frame.camera_type == CameraType.FISHEYE624), None)
    if first is None:
        return
    for frame in frames:
        if calibration(frame) != calibration(first):
            raise DatasetError(
                f"{source} frame {frame.name}: a FISHEYE624 capture needs the calibration of {first.name} on every "
                "frame (nerfstudio unprojects a batch of FISHEYE624 rays with its first ray's)"
            )


def calibration(frame: ListedFrame) -> Tuple[CameraType, List[float], List[float]]:
    return frame.camera_type, frame.intrinsics.tolist(), frame.distortion.tolist()


def stack_frames(frames: List[ListedFrame], source: Path, depth_unit_scale_factor: float) -> CaptureFrames:
    check_fisheye624(frames, source)
    intrinsics = np.stack([frame.intrinsics for frame in frames])
    distortion = np.stack([frame.distortion for frame in frames])
    camera_type = np.array([frame.camera_type.value for frame in frames])
    masks = [frame.mask for frame in frames if frame.mask is not None]  # every frame's or none (read_transforms)
    depths = [frame.depth for frame in frames if frame.depth is not None]  # likewise
    radii = np.array([np.inf if frame.crop_radius is None else frame.crop_radius for frame in frames])
    held_out = np.array([frame.held_out for frame in frames])
    return CaptureFrames(
        image_filenames=[frame.image for frame in frames],
        camera_to_worlds=np.stack([frame.camera_to_world for frame in frames]),
        fx=intrinsics[:, 0],
        fy=intrinsics[:, 1],
        cx=intrinsics[:, 2],
        cy=intrinsics[:, 3],
        width=intrinsics[:, 4].astype(np.int64),
        height=intrinsics[:, 5].astype(np.int64),
        # undistorted captures skip nerfstudio's iterative undistortion of every ray; FISHEYE624 rays need its parameters
        distortion=distortion if distortion.any() or CameraType.FISHEYE624.value in camera_type else None,
        camera_type=camera_type,
        mask_filenames=masks or None,
        fisheye_crop_radius=radii if np.isfinite(radii).any() else None,
        held_out=held_out if held_out.any() else None,
        depth_filenames=list(depths) or None,
        depth_unit_scale_factor=depth_unit_scale_factor,
    )


class OrderedCaptureDataParser(DataParser):
    """Reads transforms.json or a COLMAP model; every split returns the whole trajectory in capture order."""

    config: OrderedCaptureDataParserConfig

    def _generate_dataparser_outputs(self, split: str = "train", **kwargs) -> DataparserOutputs:
        listed, source = read_listed_frames(self.config)
        permutation = capture_order(listed, self.config.order, source)
        frames = stack_frames([listed[index] for index in permutation], source, self.config.depth_unit_scale_factor)
        return capture_outputs(frames, self.config)
