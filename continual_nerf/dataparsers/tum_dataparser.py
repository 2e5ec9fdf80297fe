"""`continual-tum`: a TUM RGB-D sequence in capture order, each image posed from the motion-capture ground truth.

Ground truth (~100 Hz) and images (~30 Hz) come from different clocks, so every image is associated with
a pose by timestamp: the nearest pose within a tolerance, or slerp/lerp between the two poses around it. Depth maps
(depth.txt, depth/*.png: 16-bit, 5000 per metre, registered to the colour images) run on the depth camera's clock:
each image takes the depth map nearest in time within the same tolerance, as TUM's associate.py pairs them.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import List, Literal, Optional, Tuple, Type

import numpy as np
from nerfstudio.data.dataparsers.base_dataparser import DataParser, DataparserOutputs
from nerfstudio.utils.rich_utils import CONSOLE

from continual_nerf.dataparsers.capture import (
    OPENCV_TO_OPENGL,
    CaptureDataParserConfig,
    CaptureFrames,
    capture_outputs,
    check_intrinsics,
    check_pose,
    fit_calibration,
    image_size,
)
from continual_nerf.errors import ContinualConfigError, DatasetError


@dataclass(frozen=True)
class SensorCalibration:
    """Pinhole intrinsics in pixels and distortion in OpenCV order (k1, k2, p1, p2, k3), as TUM lists them."""

    fx: float
    fy: float
    cx: float
    cy: float
    distortion: Tuple[float, float, float, float, float]


SENSORS = {
    "freiburg1": SensorCalibration(517.3, 516.5, 318.6, 255.3, (0.2624, -0.9531, -0.0054, 0.0026, 1.1633)),
    "freiburg2": SensorCalibration(520.9, 521.0, 325.1, 249.7, (0.2312, -0.7849, -0.0033, -0.0001, 0.9172)),
    # freiburg3 images were undistorted before release
    "freiburg3": SensorCalibration(535.4, 539.2, 320.1, 247.6, (0.0, 0.0, 0.0, 0.0, 0.0)),
}
ROS_DEFAULT = SensorCalibration(525.0, 525.0, 319.5, 239.5, (0.0, 0.0, 0.0, 0.0, 0.0))
CALIBRATED_SIZE = (640, 480)
"""Width and height of the images every sensor calibration above is for (TUM's own images)."""
DEPTH_FACTOR = 5000.0
"""Depth values per metre of TUM's depth PNGs."""


@dataclass
class ContinualTumDataParserConfig(CaptureDataParserConfig):
    """A TUM RGB-D sequence in capture order: rgb.txt images posed from groundtruth.txt by timestamp."""

    _target: Type = field(default_factory=lambda: ContinualTumDataParser)
    """The dataparser this config builds."""
    data: Path = Path("data/tum/rgbd_dataset_freiburg1_desk")
    """Sequence folder (rgb.txt, groundtruth.txt, rgb/); freiburg1/2/3 in its name picks the sensor calibration."""
    association: Literal["nearest", "interpolate"] = "nearest"
    """Pose of an image: the nearest ground-truth pose, or slerp/lerp between the two poses around its timestamp (its
    depth map is the nearest one either way: depth maps are not interpolated)."""
    max_time_difference: float = 0.02
    """Seconds from an image to its nearest ground-truth pose beyond which the image is dropped, and to its nearest
    depth map beyond which it trains without depth."""
    fx: Optional[float] = None
    """Focal length in x in pixels of the images as they are, instead of the sensor's."""
    fy: Optional[float] = None
    """Focal length in y in pixels of the images as they are, instead of the sensor's."""
    cx: Optional[float] = None
    """Principal point x in pixels of the images as they are, instead of the sensor's."""
    cy: Optional[float] = None
    """Principal point y in pixels of the images as they are, instead of the sensor's."""
    distortion: Optional[Tuple[float, float, float, float, float]] = None
    """Distortion k1 k2 p1 p2 k3 (OpenCV order, as TUM lists it) instead of the sensor's; zeros if undistorted."""

    def validate(self) -> None:
        super().validate()
        if not self.max_time_difference >= 0:
            raise ContinualConfigError(
                f"continual-tum --max-time-difference must be >= 0 seconds, got {self.max_time_difference}"
            )
        for name in ("fx", "fy", "cx", "cy"):
            value = getattr(self, name)
            if value is not None and not value > 0:
                raise ContinualConfigError(f"continual-tum --{name} must be positive, got {value}")


@dataclass
class Trajectory:
    """Ground-truth poses in time order: position and unit quaternion (x, y, z, w) of the colour camera."""

    times: np.ndarray
    positions: np.ndarray
    quaternions: np.ndarray


def read_rows(path: Path, columns: int) -> List[Tuple[int, List[str]]]:
    """Fields of every non-comment line of a TUM list file, with 1-based line numbers."""
    if not path.is_file():
        raise DatasetError(f"{path}: missing")
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as error:
        raise DatasetError(f"{path}: cannot read as text ({str(error).splitlines()[0]})") from None
    rows = []
    for number, line in enumerate(text.splitlines(), start=1):
        # TUM's own tools accept commas and tabs as separators too
        fields = line.replace(",", " ").split()
        if not fields or fields[0].startswith("#"):
            continue
        if len(fields) != columns:
            raise DatasetError(f"{path}, line {number}: expected {columns} fields, found {len(fields)}")
        rows.append((number, fields))
    if not rows:
        raise DatasetError(f"{path}: no entries")
    return rows


def parse_numbers(path: Path, number: int, fields: List[str]) -> List[float]:
    """The fields of line `number` as floats, or an error naming the file and line."""
    try:
        return [float(value) for value in fields]
    except ValueError:
        raise DatasetError(f"{path}, line {number}: expected numbers, found {' '.join(fields)!r}") from None


def read_groundtruth(path: Path) -> Trajectory:
    """`timestamp tx ty tz qx qy qz qw` lines (scalar last); quaternions are normalised, zero length is an error."""
    rows = read_rows(path, 8)
    values = np.array([parse_numbers(path, number, fields) for number, fields in rows], dtype=np.float64)
    lines = np.array([number for number, _ in rows])
    not_finite = np.flatnonzero(~np.isfinite(values).all(axis=1))
    if len(not_finite):
        raise DatasetError(f"{path}, line {lines[not_finite[0]]}: pose has NaN or infinite entries")
    norms = np.linalg.norm(values[:, 4:8], axis=1)
    zero = np.flatnonzero(norms < 1e-9)
    if len(zero):
        raise DatasetError(f"{path}, line {lines[zero[0]]}: quaternion qx qy qz qw has zero length")
    order = np.argsort(values[:, 0], kind="stable")
    return Trajectory(
        times=values[order, 0],
        positions=values[order, 1:4],
        quaternions=values[order, 4:8] / norms[order, None],
    )


def quaternion_to_matrix(q: np.ndarray) -> np.ndarray:
    """(N, 4) unit quaternions, scalar last, to (N, 3, 3) rotation matrices."""
    x, y, z, w = q.T
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], axis=-1),
            np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], axis=-1),
            np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], axis=-1),
        ],
        axis=-2,
    )


def slerp(q0: np.ndarray, q1: np.ndarray, weight: np.ndarray) -> np.ndarray:
    """Spherical interpolation between unit quaternions (N, 4), along the shorter arc."""
    dot = np.sum(q0 * q1, axis=1)
    q1 = np.where(dot[:, None] < 0, -q1, q1)
    angle = np.arccos(np.clip(np.abs(dot), 0.0, 1.0))
    sin_angle = np.sin(angle)
    # nearly equal quaternions: sin(angle) vanishes and plain lerp is exact enough
    tiny = sin_angle < 1e-9
    safe = np.where(tiny, 1.0, sin_angle)
    a = np.where(tiny, 1 - weight, np.sin((1 - weight) * angle) / safe)
    b = np.where(tiny, weight, np.sin(weight * angle) / safe)
    q = a[:, None] * q0 + b[:, None] * q1
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def associate(
    trajectory: Trajectory, image_times: np.ndarray, tolerance: float, interpolate: bool
) -> Tuple[np.ndarray, np.ndarray]:
    """Which images get a pose (mask) and their (M, 4, 4) OpenCV camera-to-world matrices.

    An image needs a ground-truth pose within `tolerance` seconds; interpolation also needs poses on both sides.
    """
    times = trajectory.times
    after = np.searchsorted(times, image_times)
    before, after = np.clip(after - 1, 0, len(times) - 1), np.clip(after, 0, len(times) - 1)
    span = times[after] - times[before]
    weight = np.clip((image_times - times[before]) / np.where(span > 0, span, 1.0), 0.0, 1.0)
    gap = np.minimum(np.abs(image_times - times[before]), np.abs(image_times - times[after]))
    posed = gap <= tolerance
    if interpolate:
        posed &= (image_times >= times[0]) & (image_times <= times[-1])
    else:
        weight = np.round(weight)
    before, after, weight = before[posed], after[posed], weight[posed]
    poses = np.tile(np.eye(4), (len(weight), 1, 1))
    poses[:, :3, :3] = quaternion_to_matrix(
        slerp(trajectory.quaternions[before], trajectory.quaternions[after], weight)
    )
    positions = trajectory.positions
    poses[:, :3, 3] = (1 - weight[:, None]) * positions[before] + weight[:, None] * positions[after]
    return posed, poses


def nearest_within(times: np.ndarray, targets: np.ndarray, tolerance: float) -> np.ndarray:
    """Per target time, the index of the nearest of the sorted `times`, or -1 when none is within `tolerance`."""
    after = np.clip(np.searchsorted(times, targets), 0, len(times) - 1)
    before = np.clip(after - 1, 0, len(times) - 1)
    nearest = np.where(np.abs(times[before] - targets) <= np.abs(times[after] - targets), before, after)
    return np.where(np.abs(times[nearest] - targets) <= tolerance, nearest, -1)


def listing(names: List[str], limit: int = 4) -> str:
    """The first few names of a long list, for a one-line message."""
    shown = ", ".join(names[:limit])
    return shown if len(names) <= limit else f"{shown}, ... ({len(names)} in all)"


class ContinualTumDataParser(DataParser):
    """Reads a TUM RGB-D sequence; every split returns the whole trajectory (the datamanager splits it into tasks)."""

    config: ContinualTumDataParserConfig

    def _calibration(self, size: Tuple[int, int]) -> SensorCalibration:
        """The sensor's calibration from the folder name, scaled to images of `size` (TUM's are 640x480), with the
        user's overrides (in pixels of these images) applied."""
        c = self.config
        match = re.search(r"freiburg[123]", c.data.resolve().name)
        sensor = SENSORS.get(match.group(0)) if match else None
        overrides = {"fx": c.fx, "fy": c.fy, "cx": c.cx, "cy": c.cy, "distortion": c.distortion}
        if sensor is None:
            sensor = ROS_DEFAULT
            if any(value is None for value in overrides.values()):
                CONSOLE.print(
                    f"{c.data}: no freiburg1/2/3 in the folder name; using the ROS default intrinsics fx=fy=525.0, "
                    "cx=319.5, cy=239.5, no distortion, where --fx/--fy/--cx/--cy/--distortion are not set",
                    style="bold yellow",
                    markup=False,
                    soft_wrap=True,
                )
        pinhole = (sensor.fx, sensor.fy, sensor.cx, sensor.cy)
        if any(overrides[name] is None for name in ("fx", "fy", "cx", "cy")):
            pinhole = fit_calibration(pinhole, CALIBRATED_SIZE, size, f"{c.data} (sensor calibration)")
        sensor = SensorCalibration(*pinhole, sensor.distortion)
        return SensorCalibration(
            **{name: getattr(sensor, name) if value is None else value for name, value in overrides.items()}
        )

    def _read_images(self, rgb_file: Path) -> Tuple[np.ndarray, List[Path], np.ndarray]:
        """Timestamps, files and line numbers of the images a list file (rgb.txt, depth.txt) names, in time order."""
        rows = read_rows(rgb_file, 2)
        times = np.array([parse_numbers(rgb_file, number, fields[:1])[0] for number, fields in rows])
        order = np.argsort(times, kind="stable")
        files = [self.config.data / rows[i][1][1] for i in order]
        return times[order], files, np.array([rows[i][0] for i in order])

    def _depth_maps(self, image_times: np.ndarray) -> Optional[List[Optional[Path]]]:
        """Per image the depth map nearest in time within --max-time-difference (None for an image without one);
        None when the sequence has no depth.txt."""
        c = self.config
        depth_file = c.data / "depth.txt"
        if not depth_file.exists():
            return None
        depth_times, depth_files, depth_lines = self._read_images(depth_file)
        nearest = nearest_within(depth_times, image_times, c.max_time_difference)
        for index in np.unique(nearest[nearest >= 0]):
            if not depth_files[index].is_file():
                raise DatasetError(
                    f"{depth_files[index]}: depth map missing (listed in {depth_file}, line {depth_lines[index]})"
                )
        if (nearest < 0).any():
            CONSOLE.print(
                f"{depth_file}: {int((nearest < 0).sum())} of {len(nearest)} images have no depth map within "
                f"{c.max_time_difference} s and train without depth",
                style="bold yellow",
                markup=False,
                soft_wrap=True,
            )
        return [depth_files[index] if index >= 0 else None for index in nearest]

    def _posed_images(self) -> Tuple[List[Path], np.ndarray, np.ndarray]:
        """The images that get a ground-truth pose, in time order, their OpenCV camera-to-world matrices and their
        timestamps."""
        c = self.config
        rgb_file, groundtruth_file = c.data / "rgb.txt", c.data / "groundtruth.txt"
        image_times, image_files, image_lines = self._read_images(rgb_file)
        trajectory = read_groundtruth(groundtruth_file)
        posed, poses = associate(trajectory, image_times, c.max_time_difference, c.association == "interpolate")
        if not posed.any():
            raise DatasetError(
                f"{groundtruth_file}: no image in {rgb_file.name} has a pose within {c.max_time_difference} s "
                f"(poses span {trajectory.times[0]:.3f}-{trajectory.times[-1]:.3f} s, "
                f"images {image_times[0]:.3f}-{image_times[-1]:.3f} s)"
            )
        if not posed.all():
            dropped = [f.name for f, p in zip(image_files, posed) if not p]
            CONSOLE.print(
                f"{rgb_file}: dropping {len(dropped)} of {len(posed)} images with no ground-truth pose "
                f"within {c.max_time_difference} s ({c.association}): {listing(dropped)}",
                style="bold yellow",
                markup=False,
                soft_wrap=True,
            )
        kept = [f for f, p in zip(image_files, posed) if p]
        for image, line in zip(kept, image_lines[posed]):
            if not image.is_file():
                raise DatasetError(f"{image}: missing (listed in {rgb_file}, line {line})")
        for pose, time in zip(poses, image_times[posed]):
            check_pose(pose, f"{groundtruth_file} at time {time:.6f}")
        return kept, poses, image_times[posed]

    def _generate_dataparser_outputs(self, split: str = "train", **kwargs) -> DataparserOutputs:
        c = self.config
        if not c.data.is_dir():
            raise DatasetError(f"{c.data}: no such folder")
        images, poses, times = self._posed_images()
        CONSOLE.log(
            f"{c.data}: TUM RGB-D sequence, {len(images)} images posed by {c.association} timestamp", markup=False
        )
        frames = self._frames(images, poses)
        depth_maps = self._depth_maps(times)
        if depth_maps is not None:
            # TUM's depth images are registered to the colour images: they share the colour camera's intrinsics
            frames = replace(frames, depth_filenames=depth_maps, depth_unit_scale_factor=1.0 / DEPTH_FACTOR)
        return capture_outputs(frames, c)

    def _frames(self, image_files: List[Path], poses_opencv: np.ndarray) -> CaptureFrames:
        """CaptureFrames with the sensor's (or the user's) calibration; size from the first image's header."""
        width, height = image_size(image_files[0])
        calibration = self._calibration((width, height))
        fx, fy, cx, cy = calibration.fx, calibration.fy, calibration.cx, calibration.cy
        check_intrinsics(fx, fy, cx, cy, width, height, f"{self.config.data} (intrinsics)")
        count = len(image_files)
        k1, k2, p1, p2, k3 = calibration.distortion
        distorted = any(calibration.distortion)
        return CaptureFrames(
            image_filenames=image_files,
            camera_to_worlds=poses_opencv @ OPENCV_TO_OPENGL,
            fx=np.full(count, fx),
            fy=np.full(count, fy),
            cx=np.full(count, cx),
            cy=np.full(count, cy),
            width=np.full(count, width, dtype=np.int64),
            height=np.full(count, height, dtype=np.int64),
            # nerfstudio orders distortion as [k1, k2, k3, k4, p1, p2]
            distortion=np.tile([k1, k2, k3, 0.0, p1, p2], (count, 1)) if distorted else None,
        )
