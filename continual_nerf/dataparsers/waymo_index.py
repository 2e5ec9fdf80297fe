"""What a Waymo reader (v1 TFRecord or v2 Parquet) finds in a segment: calibrations and every image with its pose.

The readers fill a `SegmentIndex` from the small fields of their files; `continual-waymo` then picks the images
to use and asks the reader for the JPEGs of only those.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, List, Literal, Optional, Sequence, Union

import numpy as np
from nerfstudio.utils.rich_utils import CONSOLE

from continual_nerf.dataparsers.capture import check_intrinsics, check_pose
from continual_nerf.errors import DatasetError

CameraName = Literal["FRONT", "FRONT_LEFT", "FRONT_RIGHT", "SIDE_LEFT", "SIDE_RIGHT"]
CAMERA_IDS: Dict[str, int] = {"FRONT": 1, "FRONT_LEFT": 2, "FRONT_RIGHT": 3, "SIDE_LEFT": 4, "SIDE_RIGHT": 5}
"""Waymo's CameraName enum."""
CAMERA_NAMES: Dict[int, str] = {number: name for name, number in CAMERA_IDS.items()}


@dataclass
class Calibration:
    """One camera's calibration, as the segment stores it."""

    intrinsic: np.ndarray
    """[f_u, f_v, c_u, c_v, k1, k2, p1, p2, k3]."""
    camera_to_vehicle: np.ndarray
    """(4, 4) extrinsic, Waymo camera axes (x forward, y left, z up)."""
    width: int
    height: int


@dataclass
class ImageIndex:
    """Every image of the chosen cameras in a data file, in file order, with its vehicle pose."""

    timestamps: List[int] = field(default_factory=list)
    cameras: List[str] = field(default_factory=list)
    poses: List[np.ndarray] = field(default_factory=list)

    def add(self, timestamp: int, camera: str, pose: np.ndarray) -> None:
        self.timestamps.append(timestamp)
        self.cameras.append(camera)
        self.poses.append(pose)


@dataclass
class SegmentIndex:
    """A segment as a reader indexed it, before any image is chosen or cached."""

    name: str
    """Segment (context) name; the image cache keeps the segment's JPEGs in a folder of this name."""
    images_file: Path
    """The file that holds the JPEGs; errors about the segment's images name it."""
    calibrations: Dict[str, Calibration]
    cameras: List[str]
    """The cameras used, in the order their images follow one another at each timestamp."""
    images: ImageIndex


def transform_matrix(values: Optional[Union[Sequence[float], np.ndarray]], source: str) -> np.ndarray:
    """A row-major 4x4 transform of 16 values, as float64, checked to be rigid."""
    if values is None or len(values) != 16:
        raise DatasetError(f"{source}: a transform needs 16 values, got {0 if values is None else len(values)}")
    matrix = np.asarray(values, dtype=np.float64).reshape(4, 4)
    check_pose(matrix, source)
    return matrix


def choose_cameras(calibrations: Dict[str, Calibration], cameras: Optional[Sequence[str]], source: Path) -> List[str]:
    """The chosen cameras (None: every camera the segment is calibrated for, said in one line), each with a
    calibration whose intrinsics are sound."""
    if cameras is None:
        cameras = [name for name in CAMERA_IDS if name in calibrations]
        used = f"{source}: using the segment's cameras {', '.join(cameras)} (--cameras chooses)"
        CONSOLE.print(used, markup=False, soft_wrap=True)
    uncalibrated = [name for name in cameras if name not in calibrations]
    if uncalibrated:
        raise DatasetError(f"{source}: no calibration for camera {uncalibrated[0]}")
    for name in cameras:
        calibration = calibrations[name]
        fx, fy, cx, cy = calibration.intrinsic[:4]
        check_intrinsics(fx, fy, cx, cy, calibration.width, calibration.height, f"{source} ({name} calibration)")
    return list(cameras)
