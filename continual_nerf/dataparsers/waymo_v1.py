"""Waymo Open Dataset v1: a `.tfrecord` of `Frame` protobufs, read without TensorFlow (see tfrecord.py).

Field numbers are those of waymo-open-dataset's dataset.proto. A segment is read in two passes over its
records: poses and calibrations first, then the JPEGs of only the chosen images the cache lacks.
"""

from __future__ import annotations

from pathlib import Path
from typing import Dict, List, Optional, Sequence, Tuple

import numpy as np

from continual_nerf.atomic_files import write_bytes_atomically
from continual_nerf.dataparsers.tfrecord import Message, read_records
from continual_nerf.dataparsers.waymo_index import (
    CAMERA_NAMES,
    Calibration,
    ImageIndex,
    SegmentIndex,
    choose_cameras,
    transform_matrix,
)
from continual_nerf.errors import DatasetError


def read_transform(transform: Message) -> np.ndarray:
    """A `Transform` message: field 1, 16 doubles, row-major."""
    return transform_matrix(transform.doubles(1), transform.source)


def read_calibrations(context: Message) -> Dict[str, Calibration]:
    """`Context.camera_calibrations` (2): name 1, intrinsic 2, extrinsic 3, width 4, height 5."""
    calibrations = {}
    for calibration in context.messages(2):
        name = CAMERA_NAMES.get(calibration.integer(1))
        if name is None:
            continue
        intrinsic = calibration.doubles(2)
        if len(intrinsic) != 9:
            raise DatasetError(f"{calibration.source}: {name} has {len(intrinsic)} intrinsic values, expected 9")
        calibrations[name] = Calibration(
            intrinsic=intrinsic,
            camera_to_vehicle=read_transform(calibration.message(3)),
            width=calibration.integer(4),
            height=calibration.integer(5),
        )
    return calibrations


def index_frame(frame: Message, cameras: Sequence[str], index: ImageIndex) -> None:
    """`Frame`: timestamp_micros 2, pose 3, images 4 (`CameraImage`: name 1, image 2, pose 3)."""
    timestamp = frame.integer(2)
    for image in frame.messages(4):
        camera = CAMERA_NAMES.get(image.integer(1))
        if camera is None or camera not in cameras:
            continue
        if not (image.has(3) or frame.has(3)):
            raise DatasetError(
                f"{frame.source}: the {camera} image at {timestamp} has no pose, neither its own nor the frame's"
            )
        # the pose at the image's own time beats the frame's
        index.add(timestamp, camera, read_transform(image.message(3) if image.has(3) else frame.message(3)))


def index_segment(path: Path, cameras: Optional[Sequence[str]]) -> SegmentIndex:
    """Calibrations and the chosen cameras' images (None: every calibrated camera's) of a .tfrecord file's records."""
    index = ImageIndex()
    calibrations: Optional[Dict[str, Calibration]] = None
    chosen: List[str] = []
    name = path.stem
    for number, record in enumerate(read_records(path)):
        frame = Message(record, f"{path} record {number}")
        if calibrations is None:  # every frame repeats the segment's context
            context = frame.message(1)
            name = bytes(context.blob(1)).decode() or name
            calibrations = read_calibrations(context)
            chosen = choose_cameras(calibrations, cameras, path)
        index_frame(frame, chosen, index)
    if calibrations is None:
        raise DatasetError(f"{path}: holds no records")
    return SegmentIndex(name, path, calibrations, chosen, index)


def cache_images(path: Path, missing: Dict[Tuple[int, str], Path]) -> None:
    for number, record in enumerate(read_records(path)):
        frame = Message(record, f"{path} record {number}")
        timestamp = frame.integer(2)
        for image in frame.messages(4):
            target = missing.get((timestamp, CAMERA_NAMES.get(image.integer(1), "")))
            if target is not None:
                write_bytes_atomically(target, image.blob(2))
