"""continual-scannet on generated scenes: SensReader's exported folder and a .sens file written byte for byte."""

from __future__ import annotations

import json
import re
import struct
import tracemalloc
from pathlib import Path
from typing import List

import numpy as np
import pytest
from helpers import (
    HEIGHT,
    SCANNET_INTRINSIC,
    WIDTH,
    original_poses,
    scannet_poses,
    tiny_config,
    train,
    write_exported,
    write_sens,
)
from PIL import Image

from continual_nerf.dataparsers.scannet_dataparser import ContinualScanNetDataParserConfig
from continual_nerf.errors import ContinualConfigError, DatasetError

OPENCV_TO_OPENGL = np.diag([1.0, -1.0, -1.0, 1.0])


def parse(data: Path, **options):
    return ContinualScanNetDataParserConfig(data=data, **options).setup().get_dataparser_outputs(split="train")


def expected_poses(poses: np.ndarray, frames: List[int]) -> np.ndarray:
    return (poses[frames] @ OPENCV_TO_OPENGL)[:, :3, :4]


def console_text(capsys) -> str:
    return " ".join(capsys.readouterr().out.split())


def assert_intrinsics(outputs) -> None:
    cameras = outputs.cameras
    assert np.allclose(cameras.fx.numpy(), 28.0) and np.allclose(cameras.fy.numpy(), 29.0)
    assert np.allclose(cameras.cx.numpy(), 15.5) and np.allclose(cameras.cy.numpy(), 11.5)
    assert (cameras.width == WIDTH).all() and (cameras.height == HEIGHT).all()
    assert cameras.distortion_params is None


def test_exported_folder_poses_intrinsics_numeric_order_and_lost_frames(tmp_path, capsys):
    poses = scannet_poses(12)
    folder = write_exported(tmp_path / "scene0101_00", poses, lost=(3, 7, 8))
    outputs = parse(folder)
    kept = [0, 1, 2, 4, 5, 6, 9, 10, 11]
    # numeric order: a string sort would give 0, 1, 10, 11, 2, ...
    assert [int(p.stem) for p in outputs.image_filenames] == kept
    assert all(p.parent == folder / "color" for p in outputs.image_filenames)
    assert np.allclose(original_poses(outputs), expected_poses(poses, kept), atol=1e-5)
    assert_intrinsics(outputs)
    assert "skipping frames whose pose is -inf (tracking lost): 3, 7-8 (3 in all)" in console_text(capsys)


def test_a_resized_exported_copy_gets_the_colour_intrinsics_scaled_and_says_so(tmp_path, capsys):
    folder = write_exported(tmp_path / "scene", scannet_poses(3))
    assert_intrinsics(parse(folder))  # the colour camera's 1296x968 intrinsics, scaled to the 32x24 copies
    intrinsic_file = folder / "intrinsic" / "intrinsic_color.txt"
    assert (
        f"{intrinsic_file}: the images are 32x24 pixels, the calibration is for 1296x968: intrinsics scaled by "
        "0.02469 x 0.02479"
    ) in console_text(capsys)
    np.savetxt(intrinsic_file, SCANNET_INTRINSIC)
    assert_intrinsics(parse(folder, intrinsic_size=(WIDTH, HEIGHT)))
    assert "intrinsics scaled" not in console_text(capsys), "images of the calibrated size keep the intrinsics"


def test_exported_images_of_another_aspect_ratio_are_a_one_line_error(tmp_path):
    folder = write_exported(tmp_path / "scene", scannet_poses(3))
    for i in range(3):
        Image.new("RGB", (32, 32)).save(folder / "color" / f"{i}.jpg")
    message = (
        f"{folder / 'intrinsic' / 'intrinsic_color.txt'}: the images are 32x32 pixels, the calibration is for "
        "1296x968, another aspect ratio: not a resized copy; give these images' intrinsics"
    )
    with pytest.raises(DatasetError, match=f"^{re.escape(message)}$"):
        parse(folder)


@pytest.mark.parametrize(
    "entry, value, message",
    [
        ((0, 0), float("nan"), "focal lengths must be finite and positive, got fx=nan fy=29"),
        ((1, 1), -29.0, "focal lengths must be finite and positive, got fx=28 fy=-29"),
        ((0, 2), float("inf"), "principal point cx=inf cy=11.5 lies outside the 32x24 image"),
    ],
)
def test_bad_intrinsics_are_named(tmp_path, entry, value, message):
    folder = write_exported(tmp_path / "scene", scannet_poses(3))
    intrinsic = SCANNET_INTRINSIC.copy()
    intrinsic[entry] = value
    intrinsic_file = folder / "intrinsic" / "intrinsic_color.txt"
    np.savetxt(intrinsic_file, intrinsic)
    with pytest.raises(DatasetError, match=f"^{intrinsic_file}: {message}"):
        parse(folder, intrinsic_size=(WIDTH, HEIGHT))
    sens = tmp_path / "scene.sens"
    write_sens(sens, scannet_poses(3), intrinsic=intrinsic)
    with pytest.raises(DatasetError, match=f"^{sens} header: {message}"):
        parse(sens)


def test_width_and_height_come_from_the_image_header(tmp_path):
    folder = write_exported(tmp_path / "scene", scannet_poses(3))
    for i in range(3):
        Image.new("RGB", (1296, 968)).save(folder / "color" / f"{i}.jpg")
    cameras = parse(folder).cameras
    assert (cameras.width == 1296).all() and (cameras.height == 968).all()


def test_poses_point_the_camera_along_opencv_z(tmp_path):
    """A camera looking down world +x in OpenCV terms looks down world +x in nerfstudio's (OpenGL -z) too."""
    look_x = np.eye(4)
    look_x[:3, :3] = np.array([[0, 0, 1], [-1, 0, 0], [0, -1, 0]])  # columns: cam x, y, z in world
    poses = np.stack([look_x.copy() for _ in range(3)])
    poses[:, :3, 3] = [[0, 0, 0], [1, 0, 0], [2, 1, 0]]
    outputs = parse(write_exported(tmp_path / "scene", poses), orientation_method="none")
    viewing = -original_poses(outputs)[:, :3, 2]
    assert np.allclose(viewing, [1, 0, 0], atol=1e-6)


@pytest.mark.parametrize("point_at", ["file", "folder"])
def test_sens_file_matches_the_written_poses_intrinsics_and_images(tmp_path, capsys, point_at):
    poses = scannet_poses(12, seed=1)
    sens = tmp_path / "scene0146_00" / "scene0146_00.sens"
    sens.parent.mkdir()
    colours = write_sens(sens, poses, lost=(5,))
    outputs = parse(sens if point_at == "file" else sens.parent)
    kept = [i for i in range(12) if i != 5]
    cache = tmp_path / "scene0146_00" / "scene0146_00_sens_frames"
    assert outputs.image_filenames == [cache / f"{i}.jpg" for i in kept]
    assert all(path.read_bytes() == colours[int(path.stem)] for path in outputs.image_filenames)
    assert np.allclose(original_poses(outputs), expected_poses(poses, kept), atol=1e-5)
    assert_intrinsics(outputs)
    assert "skipping frames whose pose is -inf (tracking lost): 5 (1 in all)" in console_text(capsys)


def test_sens_raw_depth_and_a_chosen_cache_folder(tmp_path):
    sens = tmp_path / "scene.sens"
    write_sens(sens, scannet_poses(4), depth_compression=0)
    cache = tmp_path / "elsewhere" / "frames"
    outputs = parse(sens, sens_frames_cache=cache)
    assert outputs.image_filenames == [cache / f"{i}.jpg" for i in range(4)]
    assert all(path.is_file() for path in outputs.image_filenames)


def test_sens_extracts_only_the_selected_frames_once_and_repairs_incomplete_ones(tmp_path):
    sens = tmp_path / "scene.sens"
    colours = write_sens(sens, scannet_poses(12))
    cache = tmp_path / "scene_sens_frames"
    outputs = parse(sens, frame_stride=3, max_frames=3)
    assert [p.name for p in outputs.image_filenames] == ["0.jpg", "3.jpg", "6.jpg"]
    assert sorted(p.name for p in cache.iterdir()) == ["0.jpg", "3.jpg", "6.jpg", "depth"]
    assert sorted(p.name for p in (cache / "depth").iterdir()) == ["0.png", "3.png", "6.png"]
    inodes = {p.name: p.stat().st_ino for p in cache.iterdir()}
    (cache / "3.jpg").write_bytes(colours[3][:20])  # as if another tool had been killed mid-copy
    parse(sens, frame_stride=3, max_frames=3)
    assert (cache / "3.jpg").read_bytes() == colours[3]
    assert all((cache / name).stat().st_ino == inodes[name] for name in ("0.jpg", "6.jpg")), "complete files are reused"
    assert sorted(p.name for p in cache.iterdir()) == ["0.jpg", "3.jpg", "6.jpg", "depth"], "no partial files are left"


def test_sens_is_read_streaming_not_whole(tmp_path):
    sens = tmp_path / "big.sens"
    gigabyte = 1 << 30
    write_sens(sens, scannet_poses(3), sparse_depth_bytes=gigabyte, sparse_depth_frame=1)
    if sens.stat().st_blocks * 512 > 64 << 20:
        pytest.skip("this filesystem has no sparse files")
    tracemalloc.start()
    outputs = parse(sens, frame_stride=2)  # frame 1, whose depth block is the 1 GB hole, is not selected
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    assert len(outputs.image_filenames) == 2
    assert peak < 32 << 20, f"parsing a 1 GB .sens allocated {peak / 2**20:.0f} MB"


def _truncate(path: Path, size: int) -> None:
    with path.open("r+b") as f:
        f.truncate(size)


HEADER_SIZE = 4 + 8 + len(b"StructureSensor") + 4 * 64 + 8 + 16 + 4 + 8


@pytest.mark.parametrize(
    "cut_to,message",
    [
        (HEADER_SIZE - 10, r"truncated \.sens file \(it ends inside the header\)"),
        (HEADER_SIZE + 50, r"truncated \.sens file \(it ends inside frame 0 of 4\)"),
        (-30, r"truncated \.sens file \(frame 3 of 4 needs \d+ bytes, the file has \d+\)"),
    ],
)
def test_truncated_sens_file_is_named(tmp_path, cut_to, message):
    sens = tmp_path / "scene.sens"
    write_sens(sens, scannet_poses(4))
    _truncate(sens, cut_to if cut_to > 0 else sens.stat().st_size + cut_to)
    with pytest.raises(DatasetError, match=f"^{sens}: {message}$"):
        parse(sens)


@pytest.mark.parametrize("compression,kind", [(1, "png"), (0, "raw"), (-1, "unknown")])
def test_sens_colour_other_than_jpeg_is_refused(tmp_path, compression, kind):
    sens = tmp_path / "scene.sens"
    write_sens(sens, scannet_poses(2), color_compression=compression)
    with pytest.raises(DatasetError, match=f"{sens}: colour frames are {kind}-compressed; only jpeg"):
        parse(sens)


def test_sens_of_another_version_is_refused(tmp_path):
    sens = tmp_path / "scene.sens"
    write_sens(sens, scannet_poses(2))
    with sens.open("r+b") as f:
        f.write(struct.pack("<I", 3))
    with pytest.raises(DatasetError, match=f"{sens}: not a ScanNet .sens file of version 4 \\(version field is 3\\)"):
        parse(sens)


def test_missing_paths_are_named(tmp_path):
    with pytest.raises(DatasetError, match=f"{tmp_path / 'nowhere'}: no such file or folder"):
        parse(tmp_path / "nowhere")
    (tmp_path / "empty").mkdir()
    with pytest.raises(DatasetError, match="empty: no color/ folder and no .sens file"):
        parse(tmp_path / "empty")
    (tmp_path / "notes.txt").write_text("hello")
    with pytest.raises(DatasetError, match="notes.txt: neither a .sens file nor an exported ScanNet folder"):
        parse(tmp_path / "notes.txt")


def test_missing_parts_of_an_exported_folder_are_named(tmp_path):
    folder = write_exported(tmp_path / "scene", scannet_poses(5))
    (folder / "pose" / "4.txt").unlink()
    with pytest.raises(DatasetError, match=f"^{folder / 'pose' / '4.txt'}: missing$"):
        parse(folder)
    (folder / "intrinsic" / "intrinsic_color.txt").unlink()
    with pytest.raises(DatasetError, match=f"^{folder / 'intrinsic' / 'intrinsic_color.txt'}: missing$"):
        parse(folder)
    for sub in (folder / "pose").iterdir():
        sub.unlink()
    (folder / "pose").rmdir()
    with pytest.raises(DatasetError, match=f"^{folder / 'pose'}: missing folder"):
        parse(folder)


@pytest.mark.parametrize(
    "content,message",
    [
        ("1 0 0 0\n0 1 0 0\n0 0 1 0\n", "expected a 4x4 matrix, found shape 3x4"),
        ("1 0 0 0\n0 one 0 0\n0 0 1 0\n0 0 0 1\n", "not a 4x4 matrix of numbers"),
        ("1 0 0 nan\n0 1 0 0\n0 0 1 0\n0 0 0 1\n", "pose has NaN or infinite entries"),
        ("1 0 0 0\n0 1 0 0\n0 0 1 inf\n0 0 0 1\n", "pose has NaN or infinite entries"),
        ("2 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 0 1\n", r"pose is not a rigid transform"),
    ],
)
def test_bad_pose_files_are_named(tmp_path, content, message):
    folder = write_exported(tmp_path / "scene", scannet_poses(4))
    (folder / "pose" / "2.txt").write_text(content)
    with pytest.raises(DatasetError, match=f"^{folder / 'pose' / '2.txt'}: {message}"):
        parse(folder)


def test_bad_sens_pose_and_all_lost_are_named(tmp_path):
    sens = tmp_path / "scene.sens"
    poses = scannet_poses(3)
    poses[1, :3, :3] *= 2
    write_sens(sens, poses)
    with pytest.raises(DatasetError, match=f"{sens} frame 1: pose is not a rigid transform"):
        parse(sens)
    write_sens(sens, scannet_poses(3), lost=(0, 1, 2))
    with pytest.raises(DatasetError, match=f"{sens}: every frame's pose is -inf"):
        parse(sens)


def test_bad_options_are_config_errors(tmp_path):
    folder = write_exported(tmp_path / "scene", scannet_poses(3))
    with pytest.raises(ContinualConfigError, match="--frame-stride must be at least 1"):
        parse(folder, frame_stride=0)
    with pytest.raises(ContinualConfigError, match=r"--intrinsic-size must be a width and height of at least 1"):
        parse(folder, intrinsic_size=(0, 968))


@pytest.mark.slow
def test_short_continual_ngp_run_on_a_sens_file(tmp_path):
    sens = tmp_path / "scene0160_00.sens"
    write_sens(sens, scannet_poses(10, seed=2))
    config = tiny_config(
        tmp_path / "outputs", ContinualScanNetDataParserConfig(data=sens), num_tasks=2, iterations_per_task=2
    )
    trainer = train(config)
    datamanager = trainer.pipeline.datamanager
    assert trainer.pipeline.task.current == 1
    assert all(p.parent == tmp_path / "scene0160_00_sens_frames" for p in datamanager.train_dataset.image_filenames)
    transforms = json.loads((trainer.base_dir / "dataparser_transforms.json").read_text())
    assert transforms["scale"] == pytest.approx(datamanager.train_dataparser_outputs.dataparser_scale)
