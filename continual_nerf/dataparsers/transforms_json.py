"""nerfstudio's transforms.json frame format, shared by every reader and writer of it.

`continual-nerfstudio` reads whole transforms.json files (and COLMAP cameras, as the same keys), the
`continual-stream` capture folder holds one transforms.json frame per file, and the replay-capture command writes them.
"""

from __future__ import annotations

import math
import re
from typing import Any, List, Mapping, Optional, Tuple

import numpy as np
from nerfstudio.cameras.cameras import CAMERA_MODEL_TO_TYPE, CameraType

from continual_nerf.dataparsers.capture import check_intrinsics, check_pose
from continual_nerf.errors import DatasetError
from continual_nerf.metadata_keys import FISHEYE_CROP_RADIUS

INTRINSIC_KEYS = ("fl_x", "fl_y", "cx", "cy", "w", "h")
"""transforms.json intrinsics every frame needs, from the frame itself or from the whole file."""

DISTORTION_KEYS = ("k1", "k2", "k3", "k4", "p1", "p2")
"""transforms.json distortion keys, in the order of nerfstudio's distortion_params."""

RAY_GENERATION_ONLY_FOR_WHOLE_IMAGES = (
    CameraType.OMNIDIRECTIONALSTEREO_L,
    CameraType.OMNIDIRECTIONALSTEREO_R,
    CameraType.VR180_L,
    CameraType.VR180_R,
)
"""Camera types nerfstudio 1.1.5 generates rays for only as whole images (rendering); for the single pixels of many
frames a training batch draws it fails, so their captures cannot train."""

CAMERA_MODELS = tuple(
    name for name, kind in CAMERA_MODEL_TO_TYPE.items() if kind not in RAY_GENERATION_ONLY_FOR_WHOLE_IMAGES
)
"""transforms.json camera models the capture dataparsers train on: nerfstudio's, but for those above."""

CAMERA_MODEL_OF_TYPE = {**{kind: name for name, kind in CAMERA_MODEL_TO_TYPE.items()}, CameraType.PERSPECTIVE: "OPENCV"}
"""The transforms.json camera model written for each camera type (OPENCV: its keys hold every perspective model's)."""

FISHEYE624_DISTORTION = 12
"""Distortion parameters of nerfstudio's FISHEYE624 model (6 radial, 2 tangential, 4 thin-prism), given as
`distortion_params`; every other model takes the 6 of DISTORTION_KEYS."""

CROPPED_CAMERA_TYPES = (CameraType.FISHEYE, CameraType.FISHEYE624)
"""Camera types whose frames transforms.json's `fisheye_crop_radius` crops, as in nerfstudio's parser (frames of other
types ignore it)."""


def camera_type(values: Mapping[str, Any], source: str) -> CameraType:
    """nerfstudio's camera type of the transforms.json `camera_model` (OPENCV when absent)."""
    model = values.get("camera_model", "OPENCV")
    if model in CAMERA_MODELS:
        return CAMERA_MODEL_TO_TYPE[model]
    if model in CAMERA_MODEL_TO_TYPE:
        raise DatasetError(
            f"{source}: camera model {model} cannot train: nerfstudio generates its rays for whole images only "
            f"(supported: {', '.join(CAMERA_MODELS)})"
        )
    raise DatasetError(f"{source}: camera model {model} is not supported (supported: {', '.join(CAMERA_MODELS)})")


def parse_intrinsics(values: Mapping[str, Any], source: str) -> Tuple[np.ndarray, np.ndarray, CameraType]:
    """Checked intrinsics, distortion and camera type from transforms.json-style keys."""
    kind = camera_type(values, source)
    missing = [key for key in INTRINSIC_KEYS if key not in values]
    if missing:
        raise DatasetError(f"{source}: {', '.join(missing)} missing (set per frame or once for the whole file)")
    try:
        intrinsics = np.array([float(values[key]) for key in INTRINSIC_KEYS])
        distortion = np.array(
            values.get("distortion_params") or [values.get(key, 0.0) for key in DISTORTION_KEYS], dtype=np.float64
        )
    except (TypeError, ValueError, OverflowError):
        raise DatasetError(f"{source}: intrinsics and distortion must be numbers") from None
    if kind == CameraType.FISHEYE624:
        if distortion.shape != (FISHEYE624_DISTORTION,):
            raise DatasetError(f"{source}: FISHEYE624 needs distortion_params of {FISHEYE624_DISTORTION} numbers")
    elif distortion.shape != (len(DISTORTION_KEYS),):
        raise DatasetError(f"{source}: distortion_params must hold 6 numbers {list(DISTORTION_KEYS)}")
    if not np.isfinite(distortion).all():
        raise DatasetError(f"{source}: distortion parameters must be finite numbers")
    check_intrinsics(*intrinsics, source=source)
    return intrinsics, distortion, kind


def fisheye_crop_radius(meta: Mapping[str, Any], source: str) -> Optional[float]:
    """The file's checked `fisheye_crop_radius` (a positive finite number of pixels), None when it has none: the
    radius around the image centre of the circle fisheye images train within (`ns-process-data aria` and the Eyeful
    Tower download write it)."""
    value = meta.get(FISHEYE_CROP_RADIUS)
    if value is None:  # absent or null, which nerfstudio reads alike
        return None
    try:
        radius = math.nan if isinstance(value, bool) else float(value)
    except (TypeError, ValueError, OverflowError):
        radius = math.nan
    if not (math.isfinite(radius) and radius > 0):
        raise DatasetError(f"{source}: {FISHEYE_CROP_RADIUS} must be a positive finite number of pixels, got {value!r}")
    return radius


def transforms_pose(value: Any, source: str) -> np.ndarray:
    """A transforms.json transform_matrix (OpenGL camera-to-world, 4x4 or 3x4) as a checked 4x4 matrix."""
    try:
        matrix = np.array(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise DatasetError(f"{source}: transform_matrix is not a matrix of numbers") from None
    if matrix.shape not in ((4, 4), (3, 4)):
        raise DatasetError(f"{source}: transform_matrix must be a 4x4 or 3x4 matrix, got shape {matrix.shape}")
    camera_to_world = np.eye(4)
    camera_to_world[:3] = matrix[:3]
    check_pose(camera_to_world, source)
    return camera_to_world


def natural_key(name: str) -> List[Any]:
    """Sort key comparing digit runs as numbers; re.split alternates text and digits, so types always line up."""
    return [int(chunk) if position % 2 else chunk for position, chunk in enumerate(re.split(r"(\d+)", name))]
