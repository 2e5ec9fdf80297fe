"""continual-waymo: the real Waymo files, generated v1 (.tfrecord) and v2 (Parquet) segments, and bad input."""

from __future__ import annotations

import json
import struct
from pathlib import Path
from typing import List, Optional

import numpy as np
import pyarrow.parquet as pq
import pytest
import torch
from helpers import (
    CAMERAS,
    EXTRINSICS,
    NUM_TIMES,
    SEGMENT,
    SIZES,
    TIMES,
    corrupt,
    doubles,
    field,
    fixture_pose,
    intrinsic,
    reference_crc32c,
    reference_masked,
    tfrecord,
    tiny_config,
    train,
    v1_frame,
    varint,
    vehicle_pose,
    write_v1,
    write_v2,
)
from PIL import Image

from continual_nerf.core.continual_datamanager import ContinualDataManagerConfig
from continual_nerf.dataparsers.tfrecord import Message, crc32c, masked_crc32c
from continual_nerf.dataparsers.waymo_dataparser import WaymoDataParserConfig, capture_frames, read_segment
from continual_nerf.dataparsers.waymo_index import CAMERA_IDS
from continual_nerf.dataparsers.waymo_v2 import IMAGE, INTRINSIC, VEHICLE_POSE, WIDTH, read_vehicle_poses
from continual_nerf.errors import ContinualConfigError, DatasetError

WAYMO = Path(__file__).parent / "data" / "waymo"
"""Real Waymo Open Dataset files (origin and licence in its README.md)."""
REAL_V1 = WAYMO / "v1_one_frame_five_cameras.tfrecord"
REAL_V2_VEHICLE_POSE = WAYMO / "v2_vehicle_pose_199_frames.parquet"


# ---- what the generated segments must read back as (captures.py writes them) ----


def expected_camera_to_world(pose: np.ndarray, camera: str) -> np.ndarray:
    """OpenGL camera-to-world in world coordinates, written out from the axis facts: GL x = -y_cam, GL y = z_cam,
    GL z = -x_cam."""
    waymo = pose @ EXTRINSICS[camera]
    gl = np.eye(4)
    gl[:3, 0], gl[:3, 1], gl[:3, 2] = -waymo[:3, 1], waymo[:3, 2], -waymo[:3, 0]
    gl[:3, 3] = waymo[:3, 3]
    return gl


def assert_known_segment(config: WaymoDataParserConfig, pose_of, times: List[int], cameras: List[str]) -> None:
    """Images in time order with every camera at each time, cameras in config order, known poses and intrinsics."""
    segment = read_segment(config)
    frames = capture_frames(segment)
    assert segment.timestamps.tolist() == [TIMES[i] for i in times for _ in cameras]
    assert segment.cameras == [camera for _ in times for camera in cameras]
    expected = [expected_camera_to_world(pose_of(i, camera), camera) for i in times for camera in cameras]
    np.testing.assert_allclose(frames.camera_to_worlds, np.stack(expected), atol=1e-6)
    calibrations = np.array([intrinsic(camera) for _ in times for camera in cameras])
    np.testing.assert_allclose(np.stack([frames.fx, frames.fy, frames.cx, frames.cy], axis=1), calibrations[:, :4])
    np.testing.assert_allclose(frames.distortion, calibrations[:, [4, 5, 8, 8, 6, 7]] * [1, 1, 1, 0, 1, 1])
    for path, camera, timestamp in zip(frames.image_filenames, segment.cameras, segment.timestamps):
        with Image.open(path) as image:
            colour = np.asarray(image.convert("RGB"))[2, 2]
        assert abs(int(colour[0]) - 40 * CAMERA_IDS[camera]) < 8
        assert abs(int(colour[1]) - 30 * TIMES.index(timestamp)) < 8
    np.testing.assert_array_equal(frames.width, [SIZES[camera][0] for camera in segment.cameras])
    np.testing.assert_array_equal(frames.height, [SIZES[camera][1] for camera in segment.cameras])


def config(data: Path, cache: Optional[Path], **options) -> WaymoDataParserConfig:
    return WaymoDataParserConfig(data=data, image_cache=cache, **options)


# ---- the real files ----


def test_real_v1_frame_has_five_cameras_as_formats_md_describes(tmp_path):
    segment = read_segment(config(REAL_V1, tmp_path))
    assert segment.cameras == CAMERAS and len(set(segment.timestamps.tolist())) == 1
    axes = {
        "FRONT": (1, 0, 0),
        "FRONT_LEFT": (0.72, 0.70, 0),
        "FRONT_RIGHT": (0.71, -0.70, 0),
        "SIDE_LEFT": (0, 1, 0),
        "SIDE_RIGHT": (0, -1, 0),
    }
    frames = capture_frames(segment)
    vehicle = segment.vehicle_to_world[0]
    for camera, c2w in zip(segment.cameras, frames.camera_to_worlds):
        extrinsic = segment.calibrations[camera].camera_to_vehicle
        np.testing.assert_allclose(extrinsic[:3, 0], axes[camera], atol=0.04)
        assert extrinsic[2, 3] == pytest.approx(2.1, abs=0.05)
        in_vehicle = np.linalg.inv(vehicle) @ c2w
        np.testing.assert_allclose(-in_vehicle[:3, 2], axes[camera], atol=0.04)  # OpenGL looks down -z
    np.testing.assert_allclose(segment.vehicle_to_world[0, :3, 3], (-25211, 42391, -161), atol=1.0)
    np.testing.assert_allclose(segment.calibrations["FRONT"].intrinsic[:4], (2044.5, 2044.5, 949.6, 633.2), atol=0.05)
    for path, camera, width, height in zip(frames.image_filenames, segment.cameras, frames.width, frames.height):
        with Image.open(path) as image:  # reads the JPEG header only
            assert image.format == "JPEG"
            assert image.size == (width, height) == ((1920, 886) if camera.startswith("SIDE") else (1920, 1280))


def test_a_one_instant_record_says_it_has_too_few_instants_for_any_task(tmp_path):
    datamanager = ContinualDataManagerConfig(dataparser=config(REAL_V1, tmp_path), num_tasks=1)
    with pytest.raises(ContinualConfigError) as error:
        datamanager.setup(device="cpu")
    assert str(error.value) == (
        f"{REAL_V1}: 1 rig instant (5 images) is too few for --pipeline.datamanager.num-tasks 1: a task needs 2 rig "
        "instants, one to train on and one to test on; too few for any task"
    )


def test_real_v2_vehicle_poses_in_time_order():
    timestamps, poses = read_vehicle_poses(REAL_V2_VEHICLE_POSE)
    assert timestamps.shape == (199,) and poses.shape == (199, 4, 4) and poses.dtype == np.float64
    assert (np.diff(timestamps) > 0).all()
    np.testing.assert_allclose(poses[:, 3], np.tile([0, 0, 0, 1.0], (199, 1)))


# ---- generated segments ----


def test_crc32c_matches_its_definition():
    assert crc32c(b"123456789") == 0xE3069283
    rng = np.random.default_rng(1)
    for size in (0, 1, 3, 8, 255, 256, 257, 1000, 4099):
        data = rng.integers(0, 256, size, dtype=np.uint8).tobytes()
        assert crc32c(data) == reference_crc32c(data) and masked_crc32c(data) == reference_masked(data)


def test_protobuf_reader_reads_every_wire_type():
    data = field(1, 300) + field(1, 2**64 - 5) + doubles(2, [1.5, -2.0], packed=False) + doubles(2, [3.0], packed=True)
    data += varint(3 << 3 | 5) + struct.pack("<f", 1.0) + field(4, b"text") + field(5, field(1, 7))
    message = Message(data, "test")
    assert message.integer(1) == -5 and message.integer(9, default=4) == 4
    assert message.doubles(2).tolist() == [1.5, -2.0, 3.0]
    assert bytes(message.blob(4)) == b"text" and message.message(5).integer(1) == 7 and message.has(3)


def test_v2_segment_gives_known_poses_in_time_order_with_all_cameras(tmp_path):
    data = write_v2(tmp_path / "waymo")
    assert_known_segment(config(data, tmp_path / "cache"), fixture_pose, list(range(NUM_TIMES)), CAMERAS)


def test_v2_without_image_poses_uses_vehicle_poses(tmp_path):
    data = write_v2(tmp_path / "waymo", image_poses=False)
    assert_known_segment(
        config(data, tmp_path / "cache"), lambda i, camera: vehicle_pose(i), list(range(NUM_TIMES)), CAMERAS
    )


def test_v1_segment_gives_known_poses_in_time_order_with_all_cameras(tmp_path):
    data = write_v1(tmp_path / "segment.tfrecord", times=[3, 0, 1, 2, 5, 4])
    assert_known_segment(config(data, tmp_path / "cache"), fixture_pose, list(range(NUM_TIMES)), CAMERAS)


@pytest.mark.parametrize("version", ["v1", "v2"])
def test_stride_and_cap_act_on_timestamps_and_only_chosen_images_are_cached(tmp_path, version):
    data = write_v1(tmp_path / "segment.tfrecord") if version == "v1" else write_v2(tmp_path / "waymo")
    options = {"frame_stride": 2, "max_frames": 2, "cameras": ("SIDE_LEFT", "FRONT")}
    assert_known_segment(config(data, tmp_path / "cache", **options), fixture_pose, [0, 2], ["SIDE_LEFT", "FRONT"])
    assert sorted(p.name for p in (tmp_path / "cache" / SEGMENT).iterdir()) == sorted(
        f"{TIMES[i]}_{camera}.jpg" for i in (0, 2) for camera in ("SIDE_LEFT", "FRONT")
    )


@pytest.mark.parametrize("version", ["v1", "v2"])
def test_the_image_cache_is_written_once_and_reused(tmp_path, version):
    data = write_v1(tmp_path / "segment.tfrecord") if version == "v1" else write_v2(tmp_path / "waymo")
    first = read_segment(config(data, None, max_frames=2))
    cache = data.parent / f"{data.name}-images" / SEGMENT
    assert first.image_filenames[0].parent == cache  # the default cache sits beside the data
    stamps = {path: path.stat().st_mtime_ns for path in first.image_filenames}
    first.image_filenames[0].unlink()
    (cache / "junk.jpg.partial-1").write_bytes(b"half")  # what a killed run leaves behind
    second = read_segment(config(data, None, max_frames=2))
    assert second.image_filenames == first.image_filenames and first.image_filenames[0].exists()
    assert all(path.stat().st_mtime_ns == stamp for path, stamp in list(stamps.items())[1:])


def test_parser_outputs_are_the_segment_normalised(tmp_path):
    parser_config = config(write_v2(tmp_path / "waymo"), tmp_path / "cache")
    outputs = parser_config.setup().get_dataparser_outputs(split="test")
    metric = capture_frames(read_segment(parser_config)).camera_to_worlds
    normalised = outputs.cameras.camera_to_worlds.double().numpy()
    # one rigid motion and one scale for the whole segment: relative poses survive, lengths scale
    relative = np.linalg.inv(metric[0]) @ metric
    np.testing.assert_allclose(normalised[0, :, :3].T @ normalised[:, :, :3], relative[:, :3, :3], atol=1e-5)
    offsets = np.linalg.norm(normalised[:, :, 3] - normalised[0, :, 3], axis=1)
    np.testing.assert_allclose(
        offsets, outputs.dataparser_scale * np.linalg.norm(relative[:, :3, 3], axis=1), atol=1e-5
    )
    assert outputs.cameras.distortion_params.shape == (NUM_TIMES * len(CAMERAS), 6)
    names = capture_frames(read_segment(parser_config))
    assert outputs.metadata["camera_id"].tolist() == names.camera_id.tolist(), "which camera took each image"
    assert set(outputs.metadata["camera_id"].tolist()) == {CAMERA_IDS[name] for name in CAMERAS}


def test_the_stored_transform_maps_back_to_waymo_world_coordinates(tmp_path):
    """Exported geometry lands in world coordinates: the saved transform is the whole one, in float64."""
    outputs = config(write_v2(tmp_path / "waymo"), tmp_path / "cache").setup().get_dataparser_outputs(split="train")
    world = np.stack([expected_camera_to_world(fixture_pose(i, c), c) for i in range(NUM_TIMES) for c in CAMERAS])
    assert np.abs(world[:, :3, 3]).max() > 25000, "tens of km from Waymo's world origin"
    assert outputs.dataparser_transform.dtype == torch.float64
    # as ns-export --save-world-frame maps points back: float32 poses in, the stored transform applied
    back = outputs.transform_poses_to_original_space(outputs.cameras.camera_to_worlds, "opengl").numpy()
    np.testing.assert_allclose(back, world[:, :3], atol=1e-4)
    # as any other tool would from the run's dataparser_transforms.json
    outputs.save_dataparser_transform(tmp_path / "dataparser_transforms.json")
    saved = json.loads((tmp_path / "dataparser_transforms.json").read_text())
    to_box = np.vstack([np.array(saved["transform"]), [0, 0, 0, 1]])
    in_box = outputs.cameras.camera_to_worlds.double().numpy()
    in_box[:, :, 3] /= saved["scale"]
    np.testing.assert_allclose(np.linalg.inv(to_box) @ np.concatenate([in_box, world[:, 3:]], axis=1), world, atol=1e-4)


# ---- bad input ----


def expect_error(error_type, message: str, parser_config: WaymoDataParserConfig) -> None:
    with pytest.raises(error_type) as raised:
        parser_config.setup().get_dataparser_outputs(split="train")
    assert str(raised.value) == message and "\n" not in message


def test_missing_folder_and_files_are_named(tmp_path):
    expect_error(
        DatasetError, f"{tmp_path / 'nowhere'}: no such file or folder", config(tmp_path / "nowhere", tmp_path)
    )
    (tmp_path / "empty").mkdir()
    expect_error(
        DatasetError,
        f"{tmp_path / 'empty' / 'camera_image'}: folder not found "
        "(a Waymo v2 root holds camera_image, camera_calibration, vehicle_pose)",
        config(tmp_path / "empty", tmp_path),
    )
    data = write_v2(tmp_path / "waymo")
    missing = data / "vehicle_pose" / f"{SEGMENT}.parquet"
    missing.unlink()
    expect_error(DatasetError, f"{missing}: file not found", config(data, tmp_path))


@pytest.mark.parametrize(
    "component, column",
    [
        ("camera_image", IMAGE),
        ("camera_calibration", WIDTH),
        ("camera_calibration", INTRINSIC[4]),
        ("vehicle_pose", VEHICLE_POSE),
    ],
)
def test_parquet_file_missing_a_column_is_named(tmp_path, component, column):
    data = write_v2(tmp_path / "waymo", skip_columns={component: column})
    expect_error(DatasetError, f"{data / component / SEGMENT}.parquet: missing column {column}", config(data, tmp_path))


@pytest.mark.parametrize("version", ["v1", "v2"])
def test_by_default_the_cameras_the_segment_has_are_used_and_logged(tmp_path, capsys, version):
    cameras = ["FRONT", "SIDE_LEFT"]
    if version == "v1":
        data = tmp_path / "segment.tfrecord"
        data.write_bytes(tfrecord([v1_frame(i, cameras) for i in range(NUM_TIMES)]))
        calibrated_in = data
    else:
        data = write_v2(tmp_path / "waymo", cameras=cameras)
        calibrated_in = data / "camera_calibration" / f"{SEGMENT}.parquet"
    assert_known_segment(config(data, tmp_path / "cache"), fixture_pose, list(range(NUM_TIMES)), cameras)
    logged = " ".join(capsys.readouterr().out.split())
    assert f"{calibrated_in}: using the segment's cameras FRONT, SIDE_LEFT (--cameras chooses)" in logged
    expect_error(
        DatasetError,
        f"{calibrated_in}: no calibration for camera FRONT_LEFT",
        config(data, tmp_path, cameras=("FRONT", "FRONT_LEFT")),
    )


@pytest.mark.parametrize(
    "column, value, message",
    [
        (0, 0.0, "focal lengths must be finite and positive, got fx=0 fy=23"),
        (2, float("nan"), "principal point cx=nan cy=6 lies outside the 16x12 image"),
    ],
)
def test_bad_intrinsics_of_a_chosen_camera_are_named(tmp_path, column, value, message):
    data = write_v2(tmp_path / "waymo")
    path = data / "camera_calibration" / f"{SEGMENT}.parquet"
    table = pq.read_table(path)
    values = table.column(INTRINSIC[column]).to_pylist()
    values[CAMERAS.index("FRONT_LEFT")] = value
    pq.write_table(table.set_column(table.schema.get_field_index(INTRINSIC[column]), INTRINSIC[column], [values]), path)
    with pytest.raises(DatasetError) as raised:
        config(data, tmp_path).setup().get_dataparser_outputs(split="train")
    assert str(raised.value).startswith(f"{path} (FRONT_LEFT calibration): {message}")
    assert len(read_segment(config(data, tmp_path, cameras=("FRONT",))).image_filenames) == NUM_TIMES, (
        "only the chosen cameras' calibrations matter"
    )


def test_corrupt_tfrecord_length_and_data_are_named(tmp_path):
    path = write_v1(tmp_path / "segment.tfrecord", times=[0, 1])
    second = 12 + len(v1_frame(0, CAMERAS)) + 4
    corrupt(path, second + 1)  # the second record's length
    expect_error(
        DatasetError, f"{path}: record 1 has a corrupt length (its CRC does not match)", config(path, tmp_path)
    )
    write_v1(path, times=[0, 1])
    corrupt(path, second + 9)  # the second record's length CRC
    expect_error(
        DatasetError, f"{path}: record 1 has a corrupt length (its CRC does not match)", config(path, tmp_path)
    )
    write_v1(path, times=[0, 1])
    corrupt(path, second + 12 + 500)  # a byte inside the second record's data
    expect_error(DatasetError, f"{path}: record 1 has corrupt data (its CRC does not match)", config(path, tmp_path))


@pytest.mark.parametrize(
    "keep, message",
    [(5, "header: 5 of 12 bytes"), (12 + 100, "data: 100 of {size} bytes"), (12, "data: 0 of {size} bytes")],
)
def test_truncated_tfrecord_is_named(tmp_path, keep, message):
    path = write_v1(tmp_path / "segment.tfrecord", times=[0, 1])
    size = len(v1_frame(1, CAMERAS))
    second = 12 + len(v1_frame(0, CAMERAS)) + 4
    path.write_bytes(path.read_bytes()[: second + keep])
    expect_error(DatasetError, f"{path}: record 1 is truncated ({message.format(size=size)})", config(path, tmp_path))


def test_truncated_data_crc_is_named(tmp_path):
    path = write_v1(tmp_path / "segment.tfrecord", times=[0])
    path.write_bytes(path.read_bytes()[:-2])
    expect_error(DatasetError, f"{path}: record 0 is truncated (data CRC: 2 of 4 bytes)", config(path, tmp_path))


def test_malformed_protobuf_in_a_sound_record_is_named(tmp_path):
    path = tmp_path / "segment.tfrecord"
    path.write_bytes(tfrecord([field(1, field(2, b"\x08\x81"))]))
    expect_error(
        DatasetError, f"{path} record 0 field 1 field 2: malformed protobuf (truncated varint)", config(path, tmp_path)
    )


def test_other_files_and_bad_camera_options_are_refused(tmp_path):
    other = tmp_path / "poses.parquet"
    other.write_bytes(b"PAR1")
    expect_error(
        DatasetError,
        f"{other}: neither a .tfrecord file (Waymo v1) nor a Waymo v2 root folder",
        config(other, tmp_path),
    )
    data = write_v1(tmp_path / "segment.tfrecord", times=[0])
    expect_error(
        ContinualConfigError,
        "--cameras names a camera twice: FRONT FRONT",
        config(data, tmp_path, cameras=("FRONT", "FRONT")),
    )
    expect_error(ContinualConfigError, "--cameras must name at least one camera", config(data, tmp_path, cameras=()))


# ---- training ----


@pytest.mark.slow
def test_short_continual_ngp_run_on_a_v2_segment(tmp_path):
    # 5 timestamps x 5 cameras: a split by image count would cut the third timestamp's cameras apart
    parser_config = config(write_v2(tmp_path / "waymo"), tmp_path / "cache", max_frames=5)
    trainer = train(tiny_config(tmp_path / "outputs", parser_config, num_tasks=2, iterations_per_task=2))
    datamanager = trainer.pipeline.datamanager
    assert trainer.pipeline.task.current == 1
    # each task spans its timestamps with every camera's images of them
    tasks = datamanager.task_split.train_frames + datamanager.task_split.test_frames
    files = datamanager.train_dataparser_outputs.image_filenames
    times = [{int(files[i].name.split("_")[0]) for i in np.concatenate(tasks[t::2])} for t in range(2)]
    assert times == [set(TIMES[:3]), set(TIMES[3:5])]
    cameras = [{files[i].stem.split("_", 1)[1] for i in np.concatenate(tasks[t::2])} for t in range(2)]
    assert cameras == [set(CAMERAS), set(CAMERAS)]
