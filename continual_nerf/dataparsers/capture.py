"""What every real-capture dataparser shares: frame selection, pose checks, image sizes and scene normalisation.

A reader turns its dataset into `CaptureFrames` (metric camera-to-world poses in nerfstudio's OpenGL
convention, in capture order); `capture_outputs` turns those into nerfstudio's DataparserOutputs.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Dict, List, Literal, Optional, Tuple, Type

import numpy as np
import torch
from nerfstudio.cameras import camera_utils
from nerfstudio.cameras.cameras import Cameras, CameraType
from nerfstudio.data.dataparsers.base_dataparser import DataParserConfig, DataparserOutputs
from nerfstudio.data.scene_box import SceneBox
from nerfstudio.utils.rich_utils import CONSOLE
from PIL import Image, UnidentifiedImageError

from continual_nerf.errors import ContinualConfigError, DatasetError
from continual_nerf.metadata_keys import (
    DEPTH_FILENAMES,
    DEPTH_INTRINSICS,
    DEPTH_UNIT_SCALE_FACTOR,
    FISHEYE_CROP_RADIUS,
    HELD_OUT,
)
from continual_nerf.validated_config import ValidatedConfig

OrientationMethod = Literal["pca", "up", "vertical", "none"]
"""nerfstudio's auto_orient_and_center_poses methods."""

OPENCV_TO_OPENGL = np.diag([1.0, -1.0, -1.0, 1.0])
"""Right-multiplied onto an OpenCV camera-to-world matrix (looks down +z, +y down) gives OpenGL's."""

PRINCIPAL_POINT_MARGIN = 0.1
"""How far outside the image a principal point may lie, as a fraction of the image's width or height."""

ASPECT_TOLERANCE = 0.01
"""Relative difference of width/height ratios up to which images count as a resized copy of the calibrated ones
(ScanNet's 640x480 copies of its 1296x968 colour images differ by 0.4%)."""


@dataclass
class CaptureDataParserConfig(ValidatedConfig, DataParserConfig):
    """Options every real-capture dataparser has."""

    _target: Type = field(default_factory=lambda: None)
    """The dataparser a capture format's config builds (this base builds none)."""
    data: Path = Path()
    """Folder (or file) of the capture."""
    frame_stride: int = 1
    """Keep every n-th frame of the capture (the paper uses 100 to 300 frames per trajectory)."""
    max_frames: Optional[int] = None
    """Keep at most this many frames, from the start of the capture, after the stride."""
    downscale_factor: int = 1
    """Divide image width and height by this factor when the images are loaded."""
    orientation_method: OrientationMethod = "up"
    """How nerfstudio's auto_orient_and_center_poses turns the scene before it is scaled."""
    scene_scale: float = 1.0
    """Extra factor on top of the automatic scale that fits all camera centres into [-1, 1]."""

    def validate(self) -> None:
        super().validate()
        for name in ("frame_stride", "downscale_factor"):
            if getattr(self, name) < 1:
                raise ContinualConfigError(f"--{name.replace('_', '-')} must be at least 1, got {getattr(self, name)}")
        if self.max_frames is not None and self.max_frames < 1:
            raise ContinualConfigError(f"--max-frames must be at least 1, got {self.max_frames}")


class CaptureOutputs(DataparserOutputs):
    """DataparserOutputs whose `dataparser_transform` is float64 and maps the capture's own world coordinates (tens of
    km for a drive, where float32 keeps centimetres at best) into the box; poses mapped back to the world (ns-export's
    world frame) are computed in float64, whatever dtype they come in."""

    def transform_poses_to_original_space(
        self, poses: torch.Tensor, camera_convention: Literal["opengl", "opencv"] = "opencv"
    ) -> torch.Tensor:
        return super().transform_poses_to_original_space(poses.double(), camera_convention)


@dataclass
class CaptureFrames:
    """Frames of a capture in capture order, in metric world units."""

    image_filenames: List[Path]
    camera_to_worlds: np.ndarray
    """(N, 4, 4) float64 camera-to-world, OpenGL convention."""
    fx: np.ndarray
    fy: np.ndarray
    cx: np.ndarray
    cy: np.ndarray
    width: np.ndarray
    height: np.ndarray
    distortion: Optional[np.ndarray] = None
    """(N, 6) nerfstudio distortion parameters [k1, k2, k3, k4, p1, p2] ((N, 12) for FISHEYE624), or None for
    undistorted images."""
    time_group: Optional[np.ndarray] = None
    """(N,) capture instant of each image for multi-camera rigs: images of one instant stay in one task."""
    camera_id: Optional[np.ndarray] = None
    """(N,) which camera of a rig took each image (None: cameras told apart by their intrinsics)."""
    camera_type: Optional[np.ndarray] = None
    """(N,) nerfstudio CameraType value of each image (None: every image perspective)."""
    mask_filenames: Optional[List[Path]] = None
    """Per image a single-channel mask, 0 where its pixels must not train (None: every pixel trains)."""
    fisheye_crop_radius: Optional[np.ndarray] = None
    """(N,) radius in pixels around each image's centre outside which its pixels must not train (inf: none), at the
    images' size before --downscale-factor (None: every image trains whole)."""
    held_out: Optional[np.ndarray] = None
    """(N,) bool, the images the capture names for testing only (None: the datamanager holds out every n-th)."""
    depth_filenames: Optional[List[Optional[Path]]] = None
    """Per image its depth map (z-depth), None for an image that has none (None: the capture has no depth)."""
    depth_intrinsics: Optional[np.ndarray] = None
    """(N, 6) fx, fy, cx, cy, width, height of each image's depth camera (None: the depth maps share the colour
    camera's intrinsics, scaled to their size)."""
    depth_unit_scale_factor: float = 1.0
    """Metres one unit of the depth maps is (ScanNet's millimetres: 1e-3, TUM's: 1/5000)."""

    def __len__(self) -> int:
        return len(self.image_filenames)

    def select(self, keep: np.ndarray) -> "CaptureFrames":
        """The frames at indices `keep`, in that order."""
        picked = {
            name: getattr(self, name)[keep] for name in ("camera_to_worlds", "fx", "fy", "cx", "cy", "width", "height")
        }
        optional = {
            name: None if getattr(self, name) is None else getattr(self, name)[keep]
            for name in (
                "distortion", "time_group", "camera_id", "camera_type", "fisheye_crop_radius", "held_out",
                "depth_intrinsics",
            )
        }  # fmt: skip
        masks = None if self.mask_filenames is None else [self.mask_filenames[i] for i in keep]
        depths = None if self.depth_filenames is None else [self.depth_filenames[i] for i in keep]
        return replace(
            self,
            image_filenames=[self.image_filenames[i] for i in keep],
            mask_filenames=masks,
            depth_filenames=depths,
            **optional,
            **picked,
        )


def check_pose(matrix: np.ndarray, source: str) -> None:
    """Reject a pose with NaN/inf entries or whose rotation block is not a rotation."""
    if not np.isfinite(matrix).all():
        raise DatasetError(f"{source}: pose has NaN or infinite entries")
    rotation = matrix[:3, :3]
    if not (
        np.allclose(rotation @ rotation.T, np.eye(3), atol=1e-3) and np.isclose(np.linalg.det(rotation), 1.0, atol=1e-3)
    ):
        raise DatasetError(f"{source}: pose is not a rigid transform (its 3x3 block is not a rotation)")


def check_intrinsics(fx: float, fy: float, cx: float, cy: float, width: float, height: float, source: str) -> None:
    """The one check of every parser's intrinsics: focal lengths finite and positive, image size whole and positive,
    principal point finite and inside the image or near it. A NaN, zero or far-off value trains on wrong rays."""
    whole = np.isfinite([width, height]).all() and width == int(width) and height == int(height)
    if not (whole and width >= 1 and height >= 1):
        raise DatasetError(f"{source}: image size w={width:g} h={height:g} must be whole numbers of at least 1")
    if not (np.isfinite([fx, fy]).all() and fx > 0 and fy > 0):
        raise DatasetError(f"{source}: focal lengths must be finite and positive, got fx={fx:g} fy={fy:g}")
    inside = all(
        np.isfinite(centre) and -PRINCIPAL_POINT_MARGIN * size <= centre <= (1 + PRINCIPAL_POINT_MARGIN) * size
        for centre, size in ((cx, width), (cy, height))
    )
    if not inside:
        raise DatasetError(
            f"{source}: principal point cx={cx:g} cy={cy:g} lies outside the {width:g}x{height:g} image "
            "(intrinsics of another image size?)"
        )


def fit_calibration(
    intrinsics: Tuple[float, float, float, float],
    calibrated_size: Tuple[int, int],
    size: Tuple[int, int],
    source: str,
) -> Tuple[float, float, float, float]:
    """fx, fy, cx, cy of a calibration made for images of `calibrated_size`, for images of `size`: scaled per axis
    (and said in one line) when the images are a resized copy; another aspect ratio is a one-line error."""
    if tuple(size) == tuple(calibrated_size):
        return intrinsics
    (width, height), (calibrated_width, calibrated_height) = size, calibrated_size
    images = f"{source}: the images are {width}x{height} pixels, the calibration is for {calibrated_width}x{calibrated_height}"
    if abs((width / height) / (calibrated_width / calibrated_height) - 1) > ASPECT_TOLERANCE:
        raise DatasetError(f"{images}, another aspect ratio: not a resized copy; give these images' intrinsics")
    scale_x, scale_y = width / calibrated_width, height / calibrated_height
    CONSOLE.print(
        f"{images}: intrinsics scaled by {scale_x:.4g} x {scale_y:.4g}", style="yellow", markup=False, soft_wrap=True
    )
    fx, fy, cx, cy = intrinsics
    return fx * scale_x, fy * scale_y, cx * scale_x, cy * scale_y


def image_size(path: Path) -> Tuple[int, int]:
    """Width and height from the image header (PIL does not decode the pixels for this)."""
    try:
        with Image.open(path) as image:
            return image.size
    except (OSError, UnidentifiedImageError) as error:
        raise DatasetError(f"{path}: cannot read image ({str(error).splitlines()[0]})") from None


def select_frames(frames: CaptureFrames, config: CaptureDataParserConfig) -> CaptureFrames:
    """Apply the stride and the frame cap; an empty selection is an error naming the capture."""
    keep = np.arange(0, len(frames), config.frame_stride)
    if config.max_frames is not None:
        keep = keep[: config.max_frames]
    if len(keep) == 0:
        raise DatasetError(f"{config.data}: the capture has no usable frames")
    return frames.select(keep)


def fit_into_box(
    camera_to_worlds: np.ndarray, orientation_method: OrientationMethod, scene_scale: float
) -> Tuple[np.ndarray, float]:
    """A (3, 4) float64 transform and a scale that centre, orient and fit (N, 4, 4) `camera_to_worlds` into
    +-scene_scale (a scale of scene_scale when every camera stands at one point)."""
    # recentre in float64 first: nerfstudio's orientation runs in float32, and world coordinates can be kilometres
    origin = camera_to_worlds[:, :3, 3].mean(axis=0)
    recentred = camera_to_worlds.copy()
    recentred[:, :3, 3] -= origin
    # nerfstudio 1.1.5's "pca" flips whole poses instead of two axes; the transform it returns is right
    _, rotation = camera_utils.auto_orient_and_center_poses(
        torch.from_numpy(recentred).float(),
        method=orientation_method,
        center_method="none",  # type: ignore[arg-type]
    )
    translate = np.eye(4)
    translate[:3, 3] = -origin
    transform = rotation.double().numpy() @ translate
    extent = float(np.abs((transform @ camera_to_worlds)[:, :3, 3]).max())
    return transform, scene_scale / extent if extent > 1e-6 else scene_scale


def fitted_poses(camera_to_worlds: np.ndarray, transform: np.ndarray, scale: float) -> torch.Tensor:
    """(N, 3, 4) float32 camera-to-world matrices in the box: `transform` applied in float64, positions scaled."""
    poses = transform @ camera_to_worlds
    poses[:, :, 3] *= scale
    return torch.from_numpy(poses).float()


def capture_outputs(frames: CaptureFrames, config: CaptureDataParserConfig) -> DataparserOutputs:
    """Select, orient, centre and scale the frames into nerfstudio's box; DataparserOutputs in capture order."""
    frames = select_frames(frames, config)
    transform, scale = fit_into_box(frames.camera_to_worlds, config.orientation_method, config.scene_scale)
    distortion = None if frames.distortion is None else torch.from_numpy(frames.distortion).float()
    camera_type = (
        CameraType.PERSPECTIVE if frames.camera_type is None else torch.from_numpy(frames.camera_type).long()[:, None]
    )
    cameras = Cameras(
        camera_to_worlds=fitted_poses(frames.camera_to_worlds, transform, scale),
        fx=torch.from_numpy(frames.fx).float()[:, None],
        fy=torch.from_numpy(frames.fy).float()[:, None],
        cx=torch.from_numpy(frames.cx).float()[:, None],
        cy=torch.from_numpy(frames.cy).float()[:, None],
        width=torch.from_numpy(frames.width).long()[:, None],
        height=torch.from_numpy(frames.height).long()[:, None],
        distortion_params=distortion,
        camera_type=camera_type,
    )
    masked = "" if frames.mask_filenames is None else ", each with its mask"
    tested = "" if frames.held_out is None else f", {int(frames.held_out.sum())} of them named for testing"
    CONSOLE.log(f"{config.data}: {len(frames)} frames in capture order{tested}{masked}{cropped(frames)}{depth(frames)}")
    return CaptureOutputs(
        image_filenames=frames.image_filenames,
        mask_filenames=frames.mask_filenames,
        cameras=cameras,
        scene_box=SceneBox(aabb=torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]]) * 1.5),
        dataparser_transform=torch.from_numpy(transform),
        dataparser_scale=scale,
        metadata=_metadata(frames, config),
    )


def cropped(frames: CaptureFrames) -> str:
    """What the log says of the frames' fisheye circles."""
    radii = frames.fisheye_crop_radius
    circled = np.array([]) if radii is None else radii[np.isfinite(radii)]
    if not len(circled):
        return ""
    return (
        f", {len(circled)} fisheye frames trained within {circled.min():g} px of the image centre (fisheye_crop_radius)"
    )


def depth(frames: CaptureFrames) -> str:
    """What the log says of the frames' depth maps."""
    if frames.depth_filenames is None:
        return ""
    count = sum(filename is not None for filename in frames.depth_filenames)
    return f", {count} with a depth map" if count < len(frames) else ", each with its depth map"


def _metadata(frames: CaptureFrames, config: CaptureDataParserConfig) -> Dict[str, Any]:
    """What the continual datamanager reads besides cameras: the image downscale, the capture instants, which
    camera took each image, the fisheye circles its pixels train within, the images named for testing and the depth
    maps."""
    metadata: Dict[str, Any] = {"image_scale_factor": 1.0 / config.downscale_factor}
    for key in ("time_group", "camera_id"):
        value = getattr(frames, key)
        if value is not None:
            metadata[key] = torch.from_numpy(np.asarray(value)).long()
    if frames.fisheye_crop_radius is not None:
        metadata[FISHEYE_CROP_RADIUS] = torch.from_numpy(frames.fisheye_crop_radius).double()
    if frames.held_out is not None:
        metadata[HELD_OUT] = torch.from_numpy(frames.held_out).bool()
    if frames.depth_filenames is not None:
        metadata[DEPTH_FILENAMES] = frames.depth_filenames
        metadata[DEPTH_UNIT_SCALE_FACTOR] = frames.depth_unit_scale_factor
    if frames.depth_intrinsics is not None:
        metadata[DEPTH_INTRINSICS] = torch.from_numpy(frames.depth_intrinsics).double()
    return metadata
