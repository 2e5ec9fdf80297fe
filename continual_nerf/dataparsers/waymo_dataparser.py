"""`continual-waymo`: a Waymo Open Dataset segment as one trajectory, in time order, across its cameras.

Version 2 (a dataset root with camera_image/, camera_calibration/ and vehicle_pose/ Parquet files) is
read by waymo_v2.py with pyarrow, column by column; version 1 (a `.tfrecord` of `Frame` protobufs) by
waymo_v1.py with the project's own TFRecord and protobuf reader. The JPEGs inside the files are written
once to an image cache so nerfstudio loads them lazily like any image file.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, List, Optional, Tuple, Type

import numpy as np
from nerfstudio.data.dataparsers.base_dataparser import DataParser, DataparserOutputs

from continual_nerf.dataparsers import waymo_v1, waymo_v2
from continual_nerf.dataparsers.capture import CaptureDataParserConfig, CaptureFrames, capture_outputs
from continual_nerf.dataparsers.waymo_index import CAMERA_IDS, Calibration, CameraName, ImageIndex, SegmentIndex
from continual_nerf.errors import ContinualConfigError, DatasetError

WAYMO_CAMERA_TO_OPENGL = np.array([[0, 0, -1, 0], [-1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 0, 1]], dtype=np.float64)
"""Right-multiplied onto a Waymo camera-to-world (x forward, y left, z up) gives OpenGL's (x right, y up, z back)."""


@dataclass
class WaymoDataParserConfig(CaptureDataParserConfig):
    """A Waymo Open Dataset segment (v2 Parquet root or v1 .tfrecord), all chosen cameras in time order."""

    _target: Type = field(default_factory=lambda: WaymoDataParser)
    """The dataparser this config builds."""
    data: Path = Path("data/waymo")
    """A v2 root (camera_image/, camera_calibration/, vehicle_pose/ of <segment>.parquet) or a v1 .tfrecord file."""
    segment: Optional[str] = None
    """Segment (context name) to read from a v2 root; None reads the only segment there."""
    cameras: Optional[Tuple[CameraName, ...]] = None
    """Cameras to use; at each timestamp their images follow one another in this order. None: every camera the
    segment is calibrated for, in Waymo's order (logged)."""
    image_cache: Optional[Path] = None
    """Folder the JPEGs inside the data are written to once and reused from; None: <data>-images beside the data."""
    frame_stride: int = 1
    """Keep every n-th timestamp of the segment (all chosen cameras of it)."""
    max_frames: Optional[int] = None
    """Keep at most this many timestamps, from the start of the segment, after the stride."""

    def validate(self) -> None:
        super().validate()
        if self.cameras is None:
            return
        if not self.cameras:
            raise ContinualConfigError("--cameras must name at least one camera")
        unknown = [name for name in self.cameras if name not in CAMERA_IDS]
        if unknown:
            raise ContinualConfigError(f"--cameras: unknown camera {unknown[0]} (known: {', '.join(CAMERA_IDS)})")
        if len(set(self.cameras)) != len(self.cameras):
            raise ContinualConfigError(f"--cameras names a camera twice: {' '.join(self.cameras)}")


@dataclass
class WaymoSegment:
    """The selected images of a segment: time order, and the chosen cameras in config order at each timestamp."""

    calibrations: Dict[str, Calibration]
    timestamps: np.ndarray
    """(N,) frame timestamp of each image, microseconds."""
    cameras: List[str]
    vehicle_to_world: np.ndarray
    """(N, 4, 4) float64 vehicle pose of each image, in world coordinates (tens of km)."""
    image_filenames: List[Path]


def select_images(index: ImageIndex, cameras: List[str], config: WaymoDataParserConfig, source: Path) -> np.ndarray:
    """Positions in `index` of the images to use: stride and cap act on timestamps, every camera of one is kept, in
    the order of `cameras`."""
    kept = set(np.unique(index.timestamps)[:: config.frame_stride][: config.max_frames].tolist())
    rank = {name: i for i, name in enumerate(cameras)}
    chosen = sorted(
        (i for i, timestamp in enumerate(index.timestamps) if timestamp in kept),
        key=lambda i: (index.timestamps[i], rank[index.cameras[i]]),
    )
    if not chosen:
        raise DatasetError(f"{source}: no images of the cameras {', '.join(cameras)}")
    pairs = [(index.timestamps[i], index.cameras[i]) for i in chosen]
    for previous, current in zip(pairs, pairs[1:]):
        if previous == current:
            raise DatasetError(f"{source}: two images of {current[1]} at timestamp {current[0]}")
    return np.array(chosen)


def cache_folder(config: WaymoDataParserConfig, segment: str) -> Path:
    """Where the segment's JPEGs go; made here so an unwritable place is reported before any work."""
    root = config.image_cache or config.data.parent / f"{config.data.name}-images"
    folder = root / segment
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as error:
        raise DatasetError(f"{folder}: cannot create the image cache ({error.strerror}); set --image-cache") from None
    return folder


def image_filename(folder: Path, timestamp: int, camera: str) -> Path:
    return folder / f"{timestamp}_{camera}.jpg"


def segment_of(index: SegmentIndex, chosen: np.ndarray, folder: Path) -> WaymoSegment:
    images = index.images
    return WaymoSegment(
        calibrations=index.calibrations,
        timestamps=np.array([images.timestamps[i] for i in chosen], dtype=np.int64),
        cameras=[images.cameras[i] for i in chosen],
        vehicle_to_world=np.stack([images.poses[i] for i in chosen]),
        image_filenames=[image_filename(folder, images.timestamps[i], images.cameras[i]) for i in chosen],
    )


def missing_images(segment: WaymoSegment) -> Dict[Tuple[int, str], Path]:
    """Cache files not written yet, by (timestamp, camera)."""
    keys = zip(segment.timestamps.tolist(), segment.cameras, segment.image_filenames)
    return {(timestamp, camera): path for timestamp, camera, path in keys if not path.exists()}


def read_segment(config: WaymoDataParserConfig) -> WaymoSegment:
    """The selected images of the segment at config.data, a v2 root folder or a v1 .tfrecord file."""
    data = config.data
    if data.is_dir():
        index = waymo_v2.index_segment(data, config.segment, config.cameras)
        cache_images = waymo_v2.cache_images
    elif data.is_file() and data.suffix == ".tfrecord":
        index = waymo_v1.index_segment(data, config.cameras)
        cache_images = waymo_v1.cache_images
    elif data.is_file():
        raise DatasetError(f"{data}: neither a .tfrecord file (Waymo v1) nor a Waymo v2 root folder")
    else:
        raise DatasetError(f"{data}: no such file or folder")
    chosen = select_images(index.images, index.cameras, config, index.images_file)
    segment = segment_of(index, chosen, cache_folder(config, index.name))
    missing = missing_images(segment)
    if missing:
        cache_images(index.images_file, missing)
    return segment


def capture_frames(segment: WaymoSegment) -> CaptureFrames:
    """Camera-to-world in OpenGL convention and Waymo's world coordinates (float64: the box fitting recentres them)."""
    calibrations = [segment.calibrations[name] for name in segment.cameras]
    camera_to_vehicle = np.stack([calibration.camera_to_vehicle for calibration in calibrations])
    intrinsic = np.stack([calibration.intrinsic for calibration in calibrations])
    f_u, f_v, c_u, c_v, k1, k2, p1, p2, k3 = intrinsic.T
    return CaptureFrames(
        image_filenames=segment.image_filenames,
        camera_to_worlds=segment.vehicle_to_world @ camera_to_vehicle @ WAYMO_CAMERA_TO_OPENGL,
        fx=f_u,
        fy=f_v,
        cx=c_u,
        cy=c_v,
        width=np.array([calibration.width for calibration in calibrations]),
        height=np.array([calibration.height for calibration in calibrations]),
        distortion=np.stack([k1, k2, k3, np.zeros_like(k1), p1, p2], axis=1),
        time_group=segment.timestamps,
        camera_id=np.array([CAMERA_IDS[name] for name in segment.cameras]),
    )


class WaymoDataParser(DataParser):
    """Reads a Waymo segment; every split returns the whole trajectory, which the continual datamanager splits."""

    config: WaymoDataParserConfig

    def _generate_dataparser_outputs(self, split: str = "train", **kwargs) -> DataparserOutputs:
        frames = capture_frames(read_segment(self.config))
        # the stride and the cap already acted on timestamps; applied again they would act on single images
        return capture_outputs(frames, dataclasses.replace(self.config, frame_stride=1, max_frames=None))
