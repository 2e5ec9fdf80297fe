"""`continual-scannet`: a ScanNet scene in capture order, from SensReader's exported folder or its raw `.sens` file.

A `.sens` file holds several GB of frames: it is read streaming (headers and poses only, seeking past the
image bytes), and the JPEG bytes and depth frames of the selected frames are copied once into a cache folder (depth
as 16-bit PNGs, as SensReader exports them) so the images load lazily from disk like those of an exported folder.
Depth maps are z-depth in millimetres (a .sens file's depth shift says), taken by the depth camera (its own
intrinsics and size, 640x480) from the colour camera's pose.
"""

from __future__ import annotations

import io
import os
import struct
import zlib
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import BinaryIO, List, Optional, Sequence, Tuple, Type

import numpy as np
from nerfstudio.data.dataparsers.base_dataparser import DataParser, DataparserOutputs
from nerfstudio.utils.rich_utils import CONSOLE
from PIL import Image

from continual_nerf.atomic_files import write_bytes_atomically
from continual_nerf.dataparsers.capture import (
    OPENCV_TO_OPENGL,
    CaptureDataParserConfig,
    CaptureFrames,
    capture_outputs,
    check_intrinsics,
    check_pose,
    fit_calibration,
    image_size,
    select_frames,
)
from continual_nerf.errors import ContinualConfigError, DatasetError

SENS_VERSION = 4
SENS_CALIBRATION = struct.Struct("<64f2i4IfQ")
"""After version and sensor name: colour/depth intrinsics and extrinsics, compressions, sizes, depth shift, frames."""
SENS_FRAME = struct.Struct("<16f4Q")
"""Per-frame header: camera-to-world, colour and depth timestamps, colour and depth byte counts."""
COLOR_COMPRESSION = {-1: "unknown", 0: "raw", 1: "png", 2: "jpeg"}
DEPTH_COMPRESSION = {-1: "unknown", 0: "raw_ushort", 1: "zlib_ushort", 2: "occi_ushort"}
RAW_USHORT, ZLIB_USHORT = 0, 1
"""The depth compressions read: uint16 values as they are, or zlib-compressed."""
MILLIMETRE = 1e-3
"""Metres per unit of an exported folder's depth PNGs (SensReader writes the .sens values, millimetres)."""


@dataclass
class ContinualScanNetDataParserConfig(CaptureDataParserConfig):
    """A ScanNet scene in capture order: SensReader's exported folder or the raw `<scene>.sens` file."""

    _target: Type = field(default_factory=lambda: ContinualScanNetDataParser)
    """The dataparser this config builds."""
    data: Path = Path("data/scannet/scene0101_00")
    """Exported scene folder (color/, pose/, intrinsic/), a raw `<scene>.sens` file, or a folder holding one."""
    sens_frames_cache: Optional[Path] = None
    """Folder the colour JPEGs of a .sens file are extracted to (default: `<scene>_sens_frames/` beside it)."""
    intrinsic_size: Tuple[int, int] = (1296, 968)
    """Width and height of the colour images an exported folder's intrinsic_color.txt is for (ScanNet's colour camera;
    resized copies get scaled intrinsics). A .sens file's header holds its own."""

    def validate(self) -> None:
        super().validate()
        if min(self.intrinsic_size) < 1:
            raise ContinualConfigError(
                f"--intrinsic-size must be a width and height of at least 1, got {self.intrinsic_size}"
            )


@dataclass
class SensFrame:
    """Where one frame's colour JPEG and depth frame sit in a .sens file, and its pose."""

    index: int
    camera_to_world: np.ndarray
    """(4, 4) float64 camera-to-world, OpenCV convention, metres."""
    color_offset: int
    color_size: int
    depth_size: int
    """Bytes of the depth frame, which follows the colour bytes."""

    @property
    def depth_offset(self) -> int:
        return self.color_offset + self.color_size


@dataclass
class SensDepth:
    """A .sens file's depth camera: intrinsics, size, compression and the units of its values."""

    intrinsic: np.ndarray
    width: int
    height: int
    compression: int
    shift: float
    """Depth values per metre (1000: millimetres)."""


@dataclass
class SensIndex:
    """What a streaming pass over a .sens file learns: calibration, image size and every frame's pose."""

    intrinsic_color: np.ndarray
    width: int
    height: int
    frames: List[SensFrame]
    depth: SensDepth


def index_ranges(indices: Sequence[int]) -> str:
    """`[3, 4, 5, 9]` -> `3-5, 9`: names many frames in one short line."""
    ranges: List[List[int]] = []
    for index in indices:
        if ranges and index == ranges[-1][1] + 1:
            ranges[-1][1] = index
        else:
            ranges.append([index, index])
    return ", ".join(str(a) if a == b else f"{a}-{b}" for a, b in ranges)


def tracking_lost(pose: np.ndarray) -> bool:
    """ScanNet marks frames where its tracker lost the camera with -inf pose entries."""
    return bool(np.isneginf(pose).any())


def warn_lost_frames(source: Path, lost: List[int]) -> None:
    """One warning line naming every frame skipped for a lost pose."""
    if lost:
        frames = f"{index_ranges(lost)} ({len(lost)} in all)"
        message = f"{source}: skipping frames whose pose is -inf (tracking lost): {frames}"
        # markup off: a path may hold square brackets
        CONSOLE.print(message, style="bold yellow", markup=False, soft_wrap=True)


def read_matrix(path: Path) -> np.ndarray:
    """A whitespace-separated 4x4 text matrix (a pose or an intrinsic file)."""
    if not path.is_file():
        raise DatasetError(f"{path}: missing")
    try:
        matrix = np.loadtxt(path, dtype=np.float64, ndmin=2)
    except ValueError as error:
        raise DatasetError(f"{path}: not a 4x4 matrix of numbers ({str(error).splitlines()[0]})") from None
    if matrix.shape != (4, 4):
        raise DatasetError(f"{path}: expected a 4x4 matrix, found shape {matrix.shape[0]}x{matrix.shape[1]}")
    return matrix


def pinhole(intrinsic: np.ndarray) -> Tuple[float, float, float, float]:
    """fx, fy, cx, cy of a 4x4 intrinsic matrix."""
    return float(intrinsic[0, 0]), float(intrinsic[1, 1]), float(intrinsic[0, 2]), float(intrinsic[1, 2])


def build_frames(
    image_filenames: List[Path],
    poses_opencv: List[np.ndarray],
    intrinsics: Tuple[float, float, float, float],
    size: Tuple[int, int],
    source: str,
) -> CaptureFrames:
    """CaptureFrames of one camera with shared, checked intrinsics; poses converted to OpenGL."""
    check_intrinsics(*intrinsics, *size, source)
    count = len(image_filenames)
    camera_to_worlds = np.stack(poses_opencv) @ OPENCV_TO_OPENGL

    def repeat(value: float) -> np.ndarray:
        return np.full(count, value, dtype=np.float64)

    fx, fy, cx, cy = intrinsics
    return CaptureFrames(
        image_filenames=image_filenames,
        camera_to_worlds=camera_to_worlds,
        fx=repeat(fx),
        fy=repeat(fy),
        cx=repeat(cx),
        cy=repeat(cy),
        width=repeat(size[0]).astype(np.int64),
        height=repeat(size[1]).astype(np.int64),
    )


def depth_intrinsics(intrinsic: np.ndarray, size: Tuple[int, int], count: int, source: str) -> np.ndarray:
    """(count, 6) fx, fy, cx, cy, width, height of the depth camera, checked, for every frame."""
    check_intrinsics(*pinhole(intrinsic), *size, source)
    return np.tile([*pinhole(intrinsic), *size], (count, 1))


def with_exported_depth(frames: CaptureFrames, folder: Path) -> CaptureFrames:
    """`frames` with depth/<i>.png beside every color/<i>.jpg and the depth camera of intrinsic_depth.txt, when the
    folder has depth/ (SensReader's --export_depth_images); unchanged otherwise."""
    depth_dir = folder / "depth"
    if not depth_dir.is_dir():
        return frames
    depth_files = [depth_dir / f"{image.stem}.png" for image in frames.image_filenames]
    for path in depth_files:
        if not path.is_file():
            raise DatasetError(f"{path}: depth map missing (the scene has {depth_dir}, with a depth map per frame)")
    intrinsic_file = folder / "intrinsic" / "intrinsic_depth.txt"
    intrinsics = depth_intrinsics(
        read_matrix(intrinsic_file), image_size(depth_files[0]), len(frames), str(intrinsic_file)
    )
    return replace(frames, depth_filenames=depth_files, depth_intrinsics=intrinsics, depth_unit_scale_factor=MILLIMETRE)


def read_exported_folder(folder: Path, intrinsic_size: Tuple[int, int]) -> CaptureFrames:
    """color/<i>.jpg with pose/<i>.txt in numeric order of i (and depth/<i>.png when there); frames with a -inf pose
    are skipped; intrinsics for images of `intrinsic_size`, scaled to the images' size."""
    color_dir, pose_dir = folder / "color", folder / "pose"
    for required in (color_dir, pose_dir):
        if not required.is_dir():
            raise DatasetError(f"{required}: missing folder (an exported ScanNet scene has color/, pose/, intrinsic/)")
    intrinsic_file = folder / "intrinsic" / "intrinsic_color.txt"
    intrinsic = read_matrix(intrinsic_file)
    # SensReader writes 0.jpg, 1.jpg, ... without padding: a string sort would put 10 before 2
    images = sorted((p for p in color_dir.glob("*.jpg") if p.stem.isdigit()), key=lambda p: int(p.stem))
    if not images:
        raise DatasetError(f"{color_dir}: no colour frames named <index>.jpg")
    kept, poses, lost = [], [], []
    for image in images:
        pose_file = pose_dir / f"{image.stem}.txt"
        pose = read_matrix(pose_file)
        if tracking_lost(pose):
            lost.append(int(image.stem))
            continue
        check_pose(pose, str(pose_file))
        kept.append(image)
        poses.append(pose)
    warn_lost_frames(pose_dir, lost)
    if not kept:
        raise DatasetError(f"{pose_dir}: every frame's pose is -inf (tracking lost)")
    size = image_size(kept[0])
    CONSOLE.log(f"{folder}: exported ScanNet scene, {len(kept)} frames with a pose", markup=False)
    intrinsics = fit_calibration(pinhole(intrinsic), intrinsic_size, size, str(intrinsic_file))
    return with_exported_depth(build_frames(kept, poses, intrinsics, size, str(intrinsic_file)), folder)


def read_exact(sens: BinaryIO, size: int, path: Path, what: str) -> bytes:
    """`size` bytes, or an error saying the file ends inside `what`."""
    data = sens.read(size)
    if len(data) < size:
        raise DatasetError(f"{path}: truncated .sens file (it ends inside {what})")
    return data


def read_sens_index(path: Path) -> SensIndex:
    """One streaming pass: the header, then each frame's pose and byte counts, seeking past the image bytes."""
    try:
        sens_file = path.open("rb")
    except OSError as error:
        raise DatasetError(f"{path}: cannot open ({error.strerror})") from None
    file_size = path.stat().st_size
    with sens_file as sens:
        (version,) = struct.unpack("<I", read_exact(sens, 4, path, "the header"))
        if version != SENS_VERSION:
            raise DatasetError(
                f"{path}: not a ScanNet .sens file of version {SENS_VERSION} (version field is {version})"
            )
        (name_length,) = struct.unpack("<Q", read_exact(sens, 8, path, "the header"))
        if name_length > file_size:
            raise DatasetError(
                f"{path}: truncated .sens file (sensor name of {name_length} bytes in a {file_size}-byte file)"
            )
        sens.seek(name_length, os.SEEK_CUR)
        calibration = SENS_CALIBRATION.unpack(read_exact(sens, SENS_CALIBRATION.size, path, "the header"))
        intrinsic_color = np.array(calibration[:16], dtype=np.float64).reshape(4, 4)
        intrinsic_depth = np.array(calibration[32:48], dtype=np.float64).reshape(4, 4)
        color_compression, depth_compression, width, height, depth_width, depth_height, shift, num_frames = calibration[
            64:
        ]
        if color_compression != 2:
            kind = COLOR_COMPRESSION.get(color_compression, f"code {color_compression}")
            raise DatasetError(
                f"{path}: colour frames are {kind}-compressed; only jpeg colour .sens files are supported"
            )
        depth = SensDepth(intrinsic_depth, depth_width, depth_height, depth_compression, shift)
        check_sens_depth(path, depth)
        frames = []
        for index in range(num_frames):
            values = SENS_FRAME.unpack(read_exact(sens, SENS_FRAME.size, path, f"frame {index} of {num_frames}"))
            color_offset = sens.tell()
            color_size, depth_size = values[18], values[19]
            end = color_offset + color_size + depth_size
            if end > file_size:
                raise DatasetError(
                    f"{path}: truncated .sens file "
                    f"(frame {index} of {num_frames} needs {end} bytes, the file has {file_size})"
                )
            pose = np.array(values[:16], dtype=np.float64).reshape(4, 4)
            frames.append(SensFrame(index, pose, color_offset, color_size, depth_size))
            sens.seek(end)
    return SensIndex(intrinsic_color, width, height, frames, depth)


def check_sens_depth(path: Path, depth: SensDepth) -> None:
    """A depth camera whose frames can be read: a known compression, a size and a positive depth shift."""
    if depth.compression not in (RAW_USHORT, ZLIB_USHORT):
        kind = DEPTH_COMPRESSION.get(depth.compression, f"code {depth.compression}")
        raise DatasetError(
            f"{path}: depth frames are {kind}-compressed; only raw_ushort and zlib_ushort depth can be read "
            "(export the scene with ScanNet's SensReader and point --data at the folder)"
        )
    if min(depth.width, depth.height) < 1 or not (np.isfinite(depth.shift) and depth.shift > 0):
        raise DatasetError(
            f"{path} header: depth frames of {depth.width}x{depth.height} pixels with depth shift {depth.shift:g} "
            "(the size must be at least 1x1, the shift positive)"
        )


def decode_depth(path: Path, frame: SensFrame, depth: SensDepth, data: bytes) -> np.ndarray:
    """(height, width) uint16 depth frame from its bytes in the .sens file; a frame of the wrong size is an error."""
    expected = depth.width * depth.height * 2
    try:
        raw = zlib.decompressobj().decompress(data, expected + 1) if depth.compression == ZLIB_USHORT else data
    except zlib.error as error:
        raise DatasetError(f"{path}: frame {frame.index}'s depth frame is not zlib data ({error})") from None
    if len(raw) != expected:
        raise DatasetError(
            f"{path}: frame {frame.index}'s depth frame holds {len(raw)} bytes, a {depth.width}x{depth.height} "
            f"uint16 depth frame {expected}"
        )
    return np.frombuffer(raw, dtype="<u2").reshape(depth.height, depth.width)


def max_depth_bytes(depth: SensDepth) -> int:
    """The most bytes a depth frame can take: its uint16 values, a little more when zlib could not compress them."""
    raw = depth.width * depth.height * 2
    return raw if depth.compression == RAW_USHORT else raw + raw // 1000 + 64


def png_bytes(depth: np.ndarray) -> bytes:
    buffer = io.BytesIO()
    Image.fromarray(depth).save(buffer, format="PNG")
    return buffer.getvalue()


def is_cached(target: Path, size: int) -> bool:
    """Files appear in the cache only by rename, so one of the right size is a complete copy."""
    return target.is_file() and target.stat().st_size == size


def cached_jpeg(cache: Path, frame: SensFrame) -> Path:
    """Named like SensReader's export, so both layouts share file names."""
    return cache / f"{frame.index}.jpg"


def cached_depth(cache: Path, frame: SensFrame) -> Path:
    """Named like SensReader's export (depth/<i>.png)."""
    return cache / "depth" / f"{frame.index}.png"


def extract_depth_frames(path: Path, cache: Path, frames: List[SensFrame], depth: SensDepth) -> None:
    """Decode each frame's depth frame from the .sens file into its cache PNG, unless already there (files appear
    in the cache only by rename: one that is there is complete)."""
    missing = [frame for frame in frames if frame.depth_size and not cached_depth(cache, frame).is_file()]
    if not missing:
        return
    CONSOLE.log(f"{path}: extracting {len(missing)} depth frames to {cache / 'depth'}", markup=False)
    with path.open("rb") as sens:
        for frame in missing:
            if frame.depth_size > max_depth_bytes(depth):
                raise DatasetError(
                    f"{path}: frame {frame.index}'s depth frame takes {frame.depth_size} bytes, more than a "
                    f"{depth.width}x{depth.height} {DEPTH_COMPRESSION[depth.compression]} frame can"
                )
            sens.seek(frame.depth_offset)
            values = decode_depth(path, frame, depth, sens.read(frame.depth_size))
            try:
                cached_depth(cache, frame).parent.mkdir(parents=True, exist_ok=True)
                write_bytes_atomically(cached_depth(cache, frame), png_bytes(values))
            except OSError as error:
                raise DatasetError(
                    f"{cache}: cannot write the extracted depth frames ({error.strerror or error})"
                ) from None


def extract_colour_frames(path: Path, cache: Path, frames: List[SensFrame]) -> None:
    """Copy each frame's JPEG bytes from the .sens file to its cache file, unless already there."""
    missing = [frame for frame in frames if not is_cached(cached_jpeg(cache, frame), frame.color_size)]
    if not missing:
        return
    CONSOLE.log(f"{path}: extracting {len(missing)} colour frames to {cache}", markup=False)
    try:
        cache.mkdir(parents=True, exist_ok=True)
        with path.open("rb") as sens:
            for frame in missing:
                target = cached_jpeg(cache, frame)
                sens.seek(frame.color_offset)
                # a killed extraction leaves at most a partial file, never a short JPEG under the final name
                write_bytes_atomically(target, sens.read(frame.color_size))
    except OSError as error:
        raise DatasetError(f"{cache}: cannot write the extracted colour frames ({error.strerror or error})") from None


def find_source(data: Path) -> Path:
    """The exported folder or the .sens file that `data` names."""
    if data.is_file():
        if data.suffix != ".sens":
            raise DatasetError(f"{data}: neither a .sens file nor an exported ScanNet folder")
        return data
    if not data.is_dir():
        raise DatasetError(f"{data}: no such file or folder")
    if (data / "color").is_dir():
        return data
    sens_files = sorted(data.glob("*.sens"))
    if len(sens_files) != 1:
        found = "no .sens file" if not sens_files else f"{len(sens_files)} .sens files"
        raise DatasetError(f"{data}: no color/ folder and {found}; point --data at an exported scene or one .sens file")
    return sens_files[0]


class ContinualScanNetDataParser(DataParser):
    """Reads a ScanNet scene; every split returns the whole trajectory (the datamanager splits it into tasks)."""

    config: ContinualScanNetDataParserConfig

    def _sens_cache(self, sens_path: Path) -> Path:
        if self.config.sens_frames_cache is not None:
            return self.config.sens_frames_cache
        return sens_path.with_name(f"{sens_path.stem}_sens_frames")

    def _read_sens(self, path: Path) -> CaptureFrames:
        """Frames of a .sens file whose images are extracted to the cache, for the selected frames only."""
        index = read_sens_index(path)
        cache = self._sens_cache(path)
        usable = [frame for frame in index.frames if not tracking_lost(frame.camera_to_world)]
        warn_lost_frames(path, [frame.index for frame in index.frames if tracking_lost(frame.camera_to_world)])
        if not usable:
            raise DatasetError(f"{path}: every frame's pose is -inf (tracking lost)")
        for frame in usable:
            check_pose(frame.camera_to_world, f"{path} frame {frame.index}")
        by_file = {cached_jpeg(cache, frame): frame for frame in usable}
        frames = build_frames(
            list(by_file),
            [frame.camera_to_world for frame in usable],
            pinhole(index.intrinsic_color),
            (index.width, index.height),
            f"{path} header",
        )
        depth = index.depth
        frames = replace(
            frames,
            depth_filenames=[cached_depth(cache, frame) if frame.depth_size else None for frame in usable],
            depth_intrinsics=depth_intrinsics(
                depth.intrinsic, (depth.width, depth.height), len(usable), f"{path} header"
            ),
            depth_unit_scale_factor=1.0 / depth.shift,
        )
        CONSOLE.log(f"{path}: ScanNet .sens file, {len(usable)} frames with a pose", markup=False)
        selected = [by_file[target] for target in select_frames(frames, self.config).image_filenames]
        extract_colour_frames(path, cache, selected)
        extract_depth_frames(path, cache, selected, depth)
        return frames

    def _generate_dataparser_outputs(self, split: str = "train", **kwargs) -> DataparserOutputs:
        source = find_source(self.config.data)
        if source.is_file():
            frames = self._read_sens(source)
        else:
            frames = read_exported_folder(source, self.config.intrinsic_size)
        return capture_outputs(frames, self.config)
