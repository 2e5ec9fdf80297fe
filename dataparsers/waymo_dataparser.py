"""`continual-waymo`: a Waymo Open Dataset segment as one trajectory, in time order, across its cameras.

Version 2 (a dataset root with camera_image/, camera_calibration/ and vehicle_pose/ Parquet files) is
read with pyarrow, column by column; version 1 (a `.tfrecord` of `Frame` protobufs) with the project's
own TFRecord and protobuf reader. The JPEGs inside the files are written once to an image cache so
nerfstudio loads them lazily like any image file.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, List, Literal, Optional, Sequence, Tuple, Type

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
from nerfstudio.data.dataparsers.base_dataparser import DataParser, DataparserOutputs

from continual_nerf.atomic_files import write_bytes_atomically
from continual_nerf.dataparsers.capture import CaptureDataParserConfig, CaptureFrames, capture_outputs, check_pose
from continual_nerf.dataparsers.tfrecord import Message, read_records
from continual_nerf.errors import ContinualConfigError, DatasetError

CameraName = Literal["FRONT", "FRONT_LEFT", "FRONT_RIGHT", "SIDE_LEFT", "SIDE_RIGHT"]
CAMERA_IDS: Dict[str, int] = {"FRONT": 1, "FRONT_LEFT": 2, "FRONT_RIGHT": 3, "SIDE_LEFT": 4, "SIDE_RIGHT": 5}
"""Waymo's CameraName enum."""
CAMERA_NAMES: Dict[int, str] = {number: name for name, number in CAMERA_IDS.items()}

WAYMO_CAMERA_TO_OPENGL = np.array([[0, 0, -1, 0], [-1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 0, 1]], dtype=np.float64)
"""Right-multiplied onto a Waymo camera-to-world (x forward, y left, z up) gives OpenGL's (x right, y up, z back)."""

V2_COMPONENTS = ("camera_image", "camera_calibration", "vehicle_pose")
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


@dataclass
class WaymoDataParserConfig(CaptureDataParserConfig):
    """A Waymo Open Dataset segment (v2 Parquet root or v1 .tfrecord), all chosen cameras in time order."""

    _target: Type = field(default_factory=lambda: WaymoDataParser)
    data: Path = Path("data/waymo")
    """A v2 root (camera_image/, camera_calibration/, vehicle_pose/ of <segment>.parquet) or a v1 .tfrecord file."""
    segment: Optional[str] = None
    """Segment (context name) to read from a v2 root; None reads the only segment there."""
    cameras: Tuple[CameraName, ...] = ("FRONT", "FRONT_LEFT", "FRONT_RIGHT", "SIDE_LEFT", "SIDE_RIGHT")
    """Cameras to use; at each timestamp their images follow one another in this order."""
    image_cache: Optional[Path] = None
    """Folder the JPEGs inside the data are written to once and reused from; None: <data>-images beside the data."""
    frame_stride: int = 1
    """Keep every n-th timestamp of the segment (all chosen cameras of it)."""
    max_frames: Optional[int] = None
    """Keep at most this many timestamps, from the start of the segment, after the stride."""

    def check_options(self) -> None:
        super().check_options()
        if not self.cameras:
            raise ContinualConfigError("--cameras must name at least one camera")
        unknown = [name for name in self.cameras if name not in CAMERA_IDS]
        if unknown:
            raise ContinualConfigError(f"--cameras: unknown camera {unknown[0]} (known: {', '.join(CAMERA_IDS)})")
        if len(set(self.cameras)) != len(self.cameras):
            raise ContinualConfigError(f"--cameras names a camera twice: {' '.join(self.cameras)}")


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
class WaymoSegment:
    """The selected images of a segment: time order, and the chosen cameras in config order at each timestamp."""

    calibrations: Dict[str, Calibration]
    timestamps: np.ndarray
    """(N,) frame timestamp of each image, microseconds."""
    cameras: List[str]
    vehicle_to_world: np.ndarray
    """(N, 4, 4) float64 vehicle pose of each image, in world coordinates (tens of km)."""
    image_filenames: List[Path]


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


def transform_matrix(values: Optional[Sequence[float]], source: str) -> np.ndarray:
    """A row-major 4x4 transform of 16 values, as float64, checked to be rigid."""
    if values is None or len(values) != 16:
        raise DatasetError(f"{source}: a transform needs 16 values, got {0 if values is None else len(values)}")
    matrix = np.asarray(values, dtype=np.float64).reshape(4, 4)
    check_pose(matrix, source)
    return matrix


def select_images(index: ImageIndex, config: WaymoDataParserConfig, source: Path) -> np.ndarray:
    """Positions in `index` of the images to use: stride and cap act on timestamps, every camera of one is kept."""
    kept = set(np.unique(index.timestamps)[:: config.frame_stride][: config.max_frames].tolist())
    rank = {name: i for i, name in enumerate(config.cameras)}
    chosen = sorted(
        (i for i, timestamp in enumerate(index.timestamps) if timestamp in kept),
        key=lambda i: (index.timestamps[i], rank[index.cameras[i]]),
    )
    if not chosen:
        raise DatasetError(f"{source}: no images of the cameras {', '.join(config.cameras)}")
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


def segment_of(
    index: ImageIndex, chosen: np.ndarray, calibrations: Dict[str, Calibration], folder: Path
) -> WaymoSegment:
    return WaymoSegment(
        calibrations=calibrations,
        timestamps=np.array([index.timestamps[i] for i in chosen], dtype=np.int64),
        cameras=[index.cameras[i] for i in chosen],
        vehicle_to_world=np.stack([index.poses[i] for i in chosen]),
        image_filenames=[image_filename(folder, index.timestamps[i], index.cameras[i]) for i in chosen],
    )


def missing_images(segment: WaymoSegment) -> Dict[Tuple[int, str], Path]:
    """Cache files not written yet, by (timestamp, camera)."""
    keys = zip(segment.timestamps.tolist(), segment.cameras, segment.image_filenames)
    return {(timestamp, camera): path for timestamp, camera, path in keys if not path.exists()}


# ---- version 2: Parquet ----


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


def read_v2_calibrations(path: Path, cameras: Sequence[str]) -> Dict[str, Calibration]:
    columns = [CAMERA, *INTRINSIC, EXTRINSIC, WIDTH, HEIGHT]
    calibrations = {}
    for row in read_columns(open_parquet(path, columns), path, columns).to_pylist():
        name = CAMERA_NAMES.get(row[CAMERA])
        if name in cameras:
            calibrations[name] = Calibration(
                intrinsic=np.array([row[column] for column in INTRINSIC], dtype=np.float64),
                camera_to_vehicle=transform_matrix(row[EXTRINSIC], f"{path} ({name} extrinsic)"),
                width=int(row[WIDTH]),
                height=int(row[HEIGHT]),
            )
    check_calibrated(calibrations, cameras, path)
    return calibrations


def check_calibrated(calibrations: Dict[str, Calibration], cameras: Sequence[str], source: Path) -> None:
    uncalibrated = [name for name in cameras if name not in calibrations]
    if uncalibrated:
        raise DatasetError(f"{source}: no calibration for camera {uncalibrated[0]}")


def v2_segment_name(root: Path, segment: Optional[str]) -> str:
    if segment is not None:
        return segment
    folder = root / "camera_image"
    if not folder.is_dir():
        raise DatasetError(f"{folder}: folder not found (a Waymo v2 root holds {', '.join(V2_COMPONENTS)})")
    names = sorted(path.stem for path in folder.glob("*.parquet"))
    if len(names) != 1:
        raise DatasetError(f"{folder}: holds {len(names)} segments, choose one with --segment")
    return names[0]


def index_v2_images(path: Path, cameras: Sequence[str], vehicle_pose_path: Path) -> ImageIndex:
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
        if camera not in cameras:
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


def cache_v2_images(path: Path, missing: Dict[Tuple[int, str], Path]) -> None:
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
                target = missing.get((timestamp, CAMERA_NAMES.get(number)))
                if target is not None:
                    write_bytes_atomically(target, jpeg)  # the cache is reused: never a short file in it
    except pa.ArrowException as error:
        raise DatasetError(f"{path}: cannot read {IMAGE} ({str(error).splitlines()[0]})") from None


def read_v2(config: WaymoDataParserConfig) -> WaymoSegment:
    root = config.data
    name = v2_segment_name(root, config.segment)
    image_path, calibration_path, vehicle_pose_path = (
        root / component / f"{name}.parquet" for component in V2_COMPONENTS
    )
    calibrations = read_v2_calibrations(calibration_path, config.cameras)
    index = index_v2_images(image_path, config.cameras, vehicle_pose_path)
    segment = segment_of(index, select_images(index, config, image_path), calibrations, cache_folder(config, name))
    missing = missing_images(segment)
    if missing:
        cache_v2_images(image_path, missing)
    return segment


# ---- version 1: TFRecord of Frame protobufs (field numbers of waymo-open-dataset's dataset.proto) ----


def v1_transform(transform: Message) -> np.ndarray:
    """A `Transform` message: field 1, 16 doubles, row-major."""
    return transform_matrix(transform.doubles(1), transform.source)


def read_v1_calibrations(context: Message, cameras: Sequence[str], path: Path) -> Dict[str, Calibration]:
    """`Context.camera_calibrations` (2): name 1, intrinsic 2, extrinsic 3, width 4, height 5."""
    calibrations = {}
    for calibration in context.messages(2):
        name = CAMERA_NAMES.get(calibration.integer(1))
        if name not in cameras:
            continue
        intrinsic = calibration.doubles(2)
        if len(intrinsic) != 9:
            raise DatasetError(f"{calibration.source}: {name} has {len(intrinsic)} intrinsic values, expected 9")
        calibrations[name] = Calibration(
            intrinsic=intrinsic,
            camera_to_vehicle=v1_transform(calibration.message(3)),
            width=calibration.integer(4),
            height=calibration.integer(5),
        )
    check_calibrated(calibrations, cameras, path)
    return calibrations


def index_v1_frame(frame: Message, cameras: Sequence[str], index: ImageIndex) -> None:
    """`Frame`: timestamp_micros 2, pose 3, images 4 (`CameraImage`: name 1, image 2, pose 3)."""
    timestamp = frame.integer(2)
    for image in frame.messages(4):
        camera = CAMERA_NAMES.get(image.integer(1))
        if camera not in cameras:
            continue
        if not (image.has(3) or frame.has(3)):
            raise DatasetError(
                f"{frame.source}: the {camera} image at {timestamp} has no pose, neither its own nor the frame's"
            )
        # the pose at the image's own time beats the frame's
        index.add(timestamp, camera, v1_transform(image.message(3) if image.has(3) else frame.message(3)))


def cache_v1_images(path: Path, missing: Dict[Tuple[int, str], Path]) -> None:
    for number, record in enumerate(read_records(path)):
        frame = Message(record, f"{path} record {number}")
        timestamp = frame.integer(2)
        for image in frame.messages(4):
            target = missing.get((timestamp, CAMERA_NAMES.get(image.integer(1))))
            if target is not None:
                write_bytes_atomically(target, image.blob(2))


def read_v1(config: WaymoDataParserConfig) -> WaymoSegment:
    """Two passes over the records: poses and calibrations first, then only the JPEGs the cache lacks."""
    path = config.data
    index = ImageIndex()
    calibrations, name = None, path.stem
    for number, record in enumerate(read_records(path)):
        frame = Message(record, f"{path} record {number}")
        if calibrations is None:  # every frame repeats the segment's context
            context = frame.message(1)
            name = bytes(context.blob(1)).decode() or name
            calibrations = read_v1_calibrations(context, config.cameras, path)
        index_v1_frame(frame, config.cameras, index)
    if calibrations is None:
        raise DatasetError(f"{path}: holds no records")
    segment = segment_of(index, select_images(index, config, path), calibrations, cache_folder(config, name))
    missing = missing_images(segment)
    if missing:
        cache_v1_images(path, missing)
    return segment


def read_segment(config: WaymoDataParserConfig) -> WaymoSegment:
    """The selected images of the segment at config.data, a v2 root folder or a v1 .tfrecord file."""
    data = config.data
    if data.is_dir():
        return read_v2(config)
    if data.is_file() and data.suffix == ".tfrecord":
        return read_v1(config)
    if data.is_file():
        raise DatasetError(f"{data}: neither a .tfrecord file (Waymo v1) nor a Waymo v2 root folder")
    raise DatasetError(f"{data}: no such file or folder")


def capture_frames(segment: WaymoSegment) -> CaptureFrames:
    """Camera-to-world in OpenGL convention, recentred on the first image's vehicle position in float64."""
    vehicle_to_world = segment.vehicle_to_world.copy()
    vehicle_to_world[:, :3, 3] -= segment.vehicle_to_world[0, :3, 3]
    calibrations = [segment.calibrations[name] for name in segment.cameras]
    camera_to_vehicle = np.stack([calibration.camera_to_vehicle for calibration in calibrations])
    intrinsic = np.stack([calibration.intrinsic for calibration in calibrations])
    f_u, f_v, c_u, c_v, k1, k2, p1, p2, k3 = intrinsic.T
    return CaptureFrames(
        image_filenames=segment.image_filenames,
        camera_to_worlds=vehicle_to_world @ camera_to_vehicle @ WAYMO_CAMERA_TO_OPENGL,
        fx=f_u,
        fy=f_v,
        cx=c_u,
        cy=c_v,
        width=np.array([calibration.width for calibration in calibrations]),
        height=np.array([calibration.height for calibration in calibrations]),
        distortion=np.stack([k1, k2, k3, np.zeros_like(k1), p1, p2], axis=1),
        time_group=segment.timestamps,
    )


class WaymoDataParser(DataParser):
    """Reads a Waymo segment; every split returns the whole trajectory, which the continual datamanager splits."""

    config: WaymoDataParserConfig

    def _generate_dataparser_outputs(self, split: str = "train", **kwargs) -> DataparserOutputs:
        self.config.check_options()
        frames = capture_frames(read_segment(self.config))
        # the stride and the cap already acted on timestamps; applied again they would act on single images
        return capture_outputs(frames, dataclasses.replace(self.config, frame_stride=1, max_frames=None))
