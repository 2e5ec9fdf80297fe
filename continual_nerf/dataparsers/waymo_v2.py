"""Waymo Open Dataset v2: one Apache Parquet file per component and segment, read with pyarrow column by column.

A v2 root holds camera_image/, camera_calibration/ and vehicle_pose/, each with a `<segment>.parquet`. The
camera images are indexed from their small columns; the JPEG column is read later, for the chosen images only.
"""

from __future__ import annotations

from pathlib import Path
from typing import Dict, Optional, Sequence, Tuple

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from continual_nerf.atomic_files import write_bytes_atomically
from continual_nerf.dataparsers.waymo_index import (
    CAMERA_NAMES,
    Calibration,
    ImageIndex,
    SegmentIndex,
    choose_cameras,
    transform_matrix,
)
from continual_nerf.errors import DatasetError

COMPONENTS = ("camera_image", "camera_calibration", "vehicle_pose")
TIMESTAMP = "key.frame_timestamp_micros"
CAMERA = "key.camera_name"
IMAGE = "[CameraImageComponent].image"
IMAGE_POSE = "[CameraImageComponent].pose.transform"
VEHICLE_POSE = "[VehiclePoseComponent].world_from_vehicle.transform"
INTRINSIC = tuple(
    f"[CameraCalibrationComponent].intrinsic.{name}"
    for name in ("f_u", "f_v", "c_u", "c_v", "k1", "k2", "p1", "p2", "k3")
)
EXTRINSIC = "[CameraCalibrationComponent].extrinsic.transform"
WIDTH = "[CameraCalibrationComponent].width"
HEIGHT = "[CameraCalibrationComponent].height"
IMAGE_BATCH_ROWS = 8
"""Camera images decoded from Parquet at a time while the cache is filled."""


def open_parquet(path: Path, columns: Sequence[str]) -> pq.ParquetFile:
    """A Parquet file that has `columns`; a missing file or column is a one-line error naming the file."""
    if not path.is_file():
        raise DatasetError(f"{path}: file not found")
    try:
        parquet = pq.ParquetFile(path)
    except (pa.ArrowException, OSError) as error:
        raise DatasetError(f"{path}: not a readable Parquet file ({str(error).splitlines()[0]})") from None
    missing = [name for name in columns if name not in parquet.schema_arrow.names]
    if missing:
        raise DatasetError(f"{path}: missing column {missing[0]}")
    return parquet


def read_columns(parquet: pq.ParquetFile, path: Path, columns: Sequence[str]) -> pa.Table:
    try:
        return parquet.read(columns=list(columns))
    except (pa.ArrowException, OSError) as error:
        raise DatasetError(f"{path}: cannot read {', '.join(columns)} ({str(error).splitlines()[0]})") from None


def read_vehicle_poses(path: Path) -> Tuple[np.ndarray, np.ndarray]:
    """Frame timestamps (microseconds, increasing) and float64 vehicle-to-world poses of a v2 vehicle_pose file."""
    columns = [TIMESTAMP, VEHICLE_POSE]
    table = read_columns(open_parquet(path, columns), path, columns)
    timestamps = np.array(table.column(TIMESTAMP).to_pylist(), dtype=np.int64)
    poses = [
        transform_matrix(values, f"{path} (timestamp {t})")
        for t, values in zip(timestamps, table.column(VEHICLE_POSE).to_pylist())
    ]
    if not poses:
        raise DatasetError(f"{path}: holds no poses")
    order = np.argsort(timestamps, kind="stable")
    return timestamps[order], np.stack(poses)[order]


def read_calibrations(path: Path) -> Dict[str, Calibration]:
    columns = [CAMERA, *INTRINSIC, EXTRINSIC, WIDTH, HEIGHT]
    calibrations = {}
    for row in read_columns(open_parquet(path, columns), path, columns).to_pylist():
        name = CAMERA_NAMES.get(row[CAMERA])
        if name is not None:
            calibrations[name] = Calibration(
                intrinsic=np.array([row[column] for column in INTRINSIC], dtype=np.float64),
                camera_to_vehicle=transform_matrix(row[EXTRINSIC], f"{path} ({name} extrinsic)"),
                width=int(row[WIDTH]),
                height=int(row[HEIGHT]),
            )
    return calibrations


def segment_name(root: Path, segment: Optional[str]) -> str:
    if segment is not None:
        return segment
    folder = root / "camera_image"
    if not folder.is_dir():
        raise DatasetError(f"{folder}: folder not found (a Waymo v2 root holds {', '.join(COMPONENTS)})")
    names = sorted(path.stem for path in folder.glob("*.parquet"))
    if len(names) != 1:
        raise DatasetError(f"{folder}: holds {len(names)} segments, choose one with --segment")
    return names[0]


def index_images(path: Path, cameras: Sequence[str], vehicle_pose_path: Path) -> ImageIndex:
    """The chosen cameras' images of a camera_image file, from its small columns (the JPEG column is not read)."""
    parquet = open_parquet(path, [TIMESTAMP, CAMERA, IMAGE])
    has_image_pose = IMAGE_POSE in parquet.schema_arrow.names
    table = read_columns(parquet, path, [TIMESTAMP, CAMERA] + ([IMAGE_POSE] if has_image_pose else []))
    vehicle_times, vehicle_poses = read_vehicle_poses(vehicle_pose_path)
    vehicle_pose_at = dict(zip(vehicle_times.tolist(), vehicle_poses))
    image_poses = table.column(IMAGE_POSE).to_pylist() if has_image_pose else [None] * len(table)
    index = ImageIndex()
    for timestamp, number, image_pose in zip(
        table.column(TIMESTAMP).to_pylist(), table.column(CAMERA).to_pylist(), image_poses
    ):
        camera = CAMERA_NAMES.get(number)
        if camera is None or camera not in cameras:
            continue
        if image_pose is not None:  # the pose at the image's own time beats the frame's
            pose = transform_matrix(image_pose, f"{path} ({camera} at {timestamp})")
        elif timestamp in vehicle_pose_at:
            pose = vehicle_pose_at[timestamp]
        else:
            raise DatasetError(
                f"{path}: the {camera} image at {timestamp} has no pose, neither its own nor in {vehicle_pose_path}"
            )
        index.add(timestamp, camera, pose)
    return index


def index_segment(root: Path, segment: Optional[str], cameras: Optional[Sequence[str]]) -> SegmentIndex:
    """Calibrations and the chosen cameras' images (None: every calibrated camera's) of a segment under a v2 root
    (segment None: its only segment)."""
    name = segment_name(root, segment)
    image_path, calibration_path, vehicle_pose_path = (root / component / f"{name}.parquet" for component in COMPONENTS)
    calibrations = read_calibrations(calibration_path)
    chosen = choose_cameras(calibrations, cameras, calibration_path)
    return SegmentIndex(name, image_path, calibrations, chosen, index_images(image_path, chosen, vehicle_pose_path))


def cache_images(path: Path, missing: Dict[Tuple[int, str], Path]) -> None:
    """Write the missing JPEGs, reading only the row groups that hold them, a few images at a time."""
    parquet = pq.ParquetFile(path)
    keys = read_columns(parquet, path, [TIMESTAMP, CAMERA])
    rows = [
        row
        for row, (timestamp, number) in enumerate(
            zip(keys.column(TIMESTAMP).to_pylist(), keys.column(CAMERA).to_pylist())
        )
        if (timestamp, CAMERA_NAMES.get(number)) in missing
    ]
    group_ends = np.cumsum([parquet.metadata.row_group(i).num_rows for i in range(parquet.num_row_groups)])
    groups = sorted(set(np.searchsorted(group_ends, rows, side="right").tolist()))
    batches = parquet.iter_batches(batch_size=IMAGE_BATCH_ROWS, row_groups=groups, columns=[TIMESTAMP, CAMERA, IMAGE])
    try:
        for batch in batches:
            for timestamp, number, jpeg in zip(
                *(batch.column(name).to_pylist() for name in (TIMESTAMP, CAMERA, IMAGE))
            ):
                target = missing.get((timestamp, CAMERA_NAMES.get(number, "")))
                if target is not None:
                    write_bytes_atomically(target, jpeg)  # the cache is reused: never a short file in it
    except pa.ArrowException as error:
        raise DatasetError(f"{path}: cannot read {IMAGE} ({str(error).splitlines()[0]})") from None
