"""`continual-nerfstudio`: order, poses and intrinsics of generated transforms.json and COLMAP captures."""

from __future__ import annotations

import json
from pathlib import Path
from typing import List

import numpy as np
import pytest
from helpers import (
    HEIGHT,
    NUMBERS,
    SHUFFLE,
    WIDTH,
    arc_poses,
    edit_transforms,
    numbered_frames,
    original_poses,
    tiny_config,
    train,
    write_colmap_text,
    write_transforms,
)
from nerfstudio.data.dataparsers.base_dataparser import DataparserOutputs
from nerfstudio.data.utils import colmap_parsing_utils as colmap

from continual_nerf.dataparsers import ordered_capture_dataparser as parser_module
from continual_nerf.dataparsers.ordered_capture_dataparser import OrderedCaptureDataParserConfig
from continual_nerf.errors import ContinualConfigError, DatasetError


def parse(data: Path, **options) -> DataparserOutputs:
    return OrderedCaptureDataParserConfig(data=data, **options).setup().get_dataparser_outputs("train")


def names(outputs: DataparserOutputs) -> List[str]:
    return [path.name for path in outputs.image_filenames]


@pytest.fixture
def logged(monkeypatch) -> List[str]:
    """The parser's log lines about the capture order."""
    lines: List[str] = []

    def log(message: object, *args, **kwargs) -> None:
        if "capture order from" in str(message):
            lines.append(str(message))

    monkeypatch.setattr(parser_module.CONSOLE, "log", log)
    return lines


@pytest.fixture
def numbered(tmp_path) -> Path:
    return write_transforms(tmp_path / "numbered", numbered_frames(arc_poses()))


def test_transforms_json_is_ordered_by_numbers_in_file_names(numbered, logged):
    outputs = parse(numbered)
    assert names(outputs) == [f"frame_{number}.png" for number in NUMBERS]
    assert np.allclose(original_poses(outputs), arc_poses()[:, :3], atol=1e-4)
    cameras = outputs.cameras
    assert cameras.fx.flatten().tolist() == [30.0] * 10 and cameras.fy.flatten().tolist() == [31.0] * 10
    assert cameras.cx.flatten().tolist() == [16.0] * 10 and cameras.cy.flatten().tolist() == [12.0] * 10
    assert cameras.width.flatten().tolist() == [WIDTH] * 10 and cameras.height.flatten().tolist() == [HEIGHT] * 10
    assert cameras.distortion_params is None
    assert any("natural sort" in line and "--order auto" in line for line in logged)
    assert names(parse(numbered / "transforms.json")) == names(outputs), "the json file itself is accepted too"


def test_file_order_is_kept_when_forced_or_when_names_have_no_numbers(tmp_path, numbered, logged):
    assert names(parse(numbered, order="file")) == [f"frame_{NUMBERS[i]}.png" for i in SHUFFLE]
    assert "order the file lists" in logged[-1] and "auto" not in logged[-1]
    letters = "abcdefghij"
    frames = numbered_frames(arc_poses())
    lettered = [dict(frame, file_path=f"images/{letter}.png") for letter, frame in zip(letters, frames)]
    outputs = parse(write_transforms(tmp_path / "lettered", lettered))
    assert names(outputs) == [f"{letters[i]}.png" for i in SHUFFLE]
    assert "order the file lists" in logged[-1] and "--order auto" in logged[-1]


@pytest.mark.parametrize("key", ["time", "timestamp"])
def test_timestamps_order_the_capture_and_per_frame_intrinsics_are_read(tmp_path, key, logged):
    # timestamps run against the file-name numbers, so only a timestamp order puts the poses back
    poses = arc_poses()
    frames = numbered_frames(poses[::-1])
    for i, frame in enumerate(frames):
        frame.update({key: 1305031102.5 - 0.033 * i, "fl_x": 20.0 + i, "k1": 0.01 * i, "p2": 0.002})
    folder = write_transforms(tmp_path / "timed", frames)
    outputs = parse(folder)
    assert names(outputs) == [f"frame_{number}.png" for number in NUMBERS[::-1]]
    assert np.allclose(original_poses(outputs), poses[:, :3], atol=1e-4)
    assert np.allclose(outputs.cameras.fx.flatten().numpy(), 20.0 + np.arange(10)[::-1])
    distortion = outputs.cameras.distortion_params.numpy()
    assert np.allclose(distortion[:, 0], 0.01 * np.arange(10)[::-1]) and np.allclose(distortion[:, 5], 0.002)
    assert np.allclose(distortion[:, 1:5], 0.0)
    assert "timestamps" in logged[-1]
    assert names(parse(folder, order="filename")) == [f"frame_{number}.png" for number in NUMBERS]
    assert "natural sort" in logged[-1] and "auto" not in logged[-1]


def test_colmap_text_model_recovers_order_poses_and_intrinsics(tmp_path, logged):
    model = write_colmap_text(tmp_path / "scene")
    outputs = parse(model)
    assert names(outputs) == [f"{number:06d}.png" for number in NUMBERS]
    assert outputs.image_filenames[0] == tmp_path / "scene" / "images" / "000002.png"
    assert np.allclose(original_poses(outputs), arc_poses()[:, :3], atol=1e-4)
    cameras = outputs.cameras
    pinhole, opencv = slice(0, None, 2), slice(1, None, 2)
    assert cameras.fx[pinhole].flatten().tolist() == [30.0] * 5 and cameras.fx[opencv].flatten().tolist() == [28.0] * 5
    assert cameras.fy[pinhole].flatten().tolist() == [31.0] * 5 and cameras.cy[opencv].flatten().tolist() == [11.5] * 5
    distortion = cameras.distortion_params.numpy()
    assert np.allclose(distortion[pinhole], 0.0)
    assert np.allclose(distortion[opencv], [0.1, -0.05, 0.0, 0.0, 0.001, 0.002])
    assert "natural sort" in logged[-1]
    assert names(parse(tmp_path / "scene")) == names(outputs), "a scene folder with sparse/0 is accepted too"


def test_colmap_binary_model_reads_like_the_text_one(tmp_path):
    text_model = write_colmap_text(tmp_path / "scene")
    binary_model = tmp_path / "scene" / "sparse" / "1"
    binary_model.mkdir()
    colmap.write_cameras_binary(colmap.read_cameras_text(text_model / "cameras.txt"), binary_model / "cameras.bin")
    colmap.write_images_binary(colmap.read_images_text(text_model / "images.txt"), binary_model / "images.bin")
    text, binary = parse(text_model, order="file"), parse(binary_model, order="file")
    assert names(binary) == names(text) == [f"{NUMBERS[i]:06d}.png" for i in SHUFFLE]
    assert np.allclose(original_poses(binary), original_poses(text), atol=1e-5)


def error_of(data: Path, error: type = DatasetError, **options) -> str:
    """The one-line message parsing `data` fails with."""
    with pytest.raises(error) as raised:
        parse(data, **options)
    message = str(raised.value)
    assert "\n" not in message
    return message


def test_missing_folder_and_folder_without_a_capture(tmp_path):
    assert error_of(tmp_path / "nowhere") == f"{tmp_path / 'nowhere'}: no such capture folder or file"
    assert error_of(tmp_path).startswith(f"{tmp_path}: holds neither transforms.json nor a COLMAP model (")


def test_missing_image_file(numbered):
    (numbered / "images" / "frame_10.png").unlink()
    image, transforms = numbered / "images" / "frame_10.png", numbered / "transforms.json"
    assert error_of(numbered) == f"{image}: image listed in {transforms} does not exist"


@pytest.mark.parametrize(
    "pose, expected",
    [
        ([[float("nan")] * 4] * 4, "pose has NaN or infinite entries"),
        ((2 * np.eye(4)).tolist(), "pose is not a rigid transform"),
        ([1, 2, 3], "transform_matrix must be a 4x4 or 3x4 matrix"),
    ],
)
def test_bad_transform_matrix(numbered, pose, expected):
    edit_transforms(numbered, frame_6={"transform_matrix": pose})
    assert error_of(numbered).startswith(f"{numbered / 'transforms.json'} frame images/frame_6.png: {expected}")


def test_duplicate_timestamps_when_ordering_by_timestamp(numbered):
    edit_transforms(numbered, **{f"frame_{number}": {"time": float(number)} for number in NUMBERS})
    edit_transforms(numbered, frame_4={"time": 1.5}, frame_8={"time": 1.5})
    message = error_of(numbered)
    assert message.startswith(f"{numbered / 'transforms.json'}: frames images/frame_")
    assert message.endswith("have the same timestamp 1.5; use --order filename or --order file")
    assert len(parse(numbered, order="filename").image_filenames) == 10


def test_order_timestamp_needs_a_number_on_every_frame(numbered):
    message = error_of(numbered, order="timestamp")
    assert message.startswith(f"{numbered / 'transforms.json'} frame images/frame_")
    assert message.endswith(": has no `time` or `timestamp` (needed by --order timestamp)")
    edit_transforms(numbered, **{f"frame_{number}": {"time": number} for number in NUMBERS})
    edit_transforms(numbered, frame_6={"time": "soon"})
    expected = f"{numbered / 'transforms.json'} frame images/frame_6.png: timestamp 'soon' is not a finite number"
    assert error_of(numbered) == expected


def test_bad_intrinsics_and_camera_models(numbered):
    frame_4 = f"{numbered / 'transforms.json'} frame images/frame_4.png"
    edit_transforms(numbered, frame_4={"camera_model": "OPENCV_FISHEYE"})
    assert error_of(numbered).startswith(f"{frame_4}: camera model OPENCV_FISHEYE is not supported (perspective only: ")
    edit_transforms(numbered, frame_4={"camera_model": "OPENCV", "distortion_params": [0.1, 0.2]})
    assert error_of(numbered).startswith(f"{frame_4}: distortion_params must hold 6 numbers [")
    meta = edit_transforms(numbered, frame_4={"distortion_params": None})
    del meta["fl_x"]
    (numbered / "transforms.json").write_text(json.dumps(meta))
    assert error_of(numbered).endswith(": fl_x missing (set per frame or once for the whole file)")


@pytest.mark.parametrize(
    "values, expected",
    [
        ({"fl_x": float("nan")}, "focal lengths must be finite and positive, got fx=nan fy=31"),
        ({"fl_y": 0}, "focal lengths must be finite and positive, got fx=30 fy=0"),
        ({"fl_x": -30.0}, "focal lengths must be finite and positive, got fx=-30 fy=31"),
        (
            {"cx": float("inf")},
            "principal point cx=inf cy=12 lies outside the 32x24 image (intrinsics of another image size?)",
        ),
        (
            {"cy": 200.0},
            "principal point cx=16 cy=200 lies outside the 32x24 image (intrinsics of another image size?)",
        ),
        ({"w": float("nan")}, "image size w=nan h=24 must be whole numbers of at least 1"),
        ({"h": 0}, "image size w=32 h=0 must be whole numbers of at least 1"),
        ({"k1": float("nan")}, "distortion parameters must be finite numbers"),
    ],
)
def test_intrinsics_are_checked_as_every_parser_checks_them(numbered, values, expected):
    edit_transforms(numbered, frame_8=values)
    assert error_of(numbered) == f"{numbered / 'transforms.json'} frame images/frame_8.png: {expected}"


def test_unreadable_json_and_json_without_frames(tmp_path):
    (tmp_path / "transforms.json").write_text('{"frames": [')
    assert error_of(tmp_path).startswith(f"{tmp_path / 'transforms.json'}: not valid JSON (")
    (tmp_path / "transforms.json").write_text('{"fl_x": 30}')
    assert error_of(tmp_path) == f"{tmp_path / 'transforms.json'}: has no `frames` list"


def test_bad_colmap_models(tmp_path):
    model = write_colmap_text(tmp_path / "zero", ["1 0 0 0 0 0 0 0 1 000002.png"])
    assert error_of(model) == f"{model / 'images.txt'} image 000002.png: rotation quaternion has zero length"
    model = write_colmap_text(tmp_path / "no_camera", ["1 1 0 0 0 0 0 0 7 000002.png"])
    expected = f"{model / 'images.txt'}: image 000002.png uses camera 7, which {model / 'cameras.txt'} lacks"
    assert error_of(model) == expected
    model = write_colmap_text(tmp_path / "fisheye")
    fisheye = f"1 OPENCV_FISHEYE {WIDTH} {HEIGHT} 30 31 16 12 0 0 0 0\n2 PINHOLE {WIDTH} {HEIGHT} 30 31 16 12\n"
    (model / "cameras.txt").write_text(fisheye)
    message = error_of(model)
    assert message.startswith(f"{model / 'cameras.txt'} camera 1: camera model OPENCV_FISHEYE is not supported")
    colmap.write_images_binary(colmap.read_images_text(model / "images.txt"), model / "images.bin")
    colmap.write_cameras_binary(colmap.read_cameras_text(model / "cameras.txt"), model / "cameras.bin")
    (model / "images.bin").write_bytes((model / "images.bin").read_bytes()[:100])
    assert error_of(model).startswith(f"{model / 'images.bin'}: not a readable COLMAP file (error: unpack requires")


def test_colmap_images_folder(tmp_path):
    model = write_colmap_text(tmp_path / "scene")
    (tmp_path / "scene" / "images").rename(tmp_path / "photos")
    assert error_of(model) == f"{model}: no images folder next to this COLMAP model; set --images-dir"
    assert len(parse(model, images_dir=tmp_path / "photos").image_filenames) == 10
    assert error_of(model, images_dir=tmp_path / "nowhere") == f"{tmp_path / 'nowhere'}: images folder does not exist"


def test_unknown_order_is_an_option_error(numbered):
    assert error_of(numbered, ContinualConfigError, order="random") == (
        "--order must be one of auto, timestamp, filename, file, got random"
    )


@pytest.mark.slow
def test_short_continual_run_on_a_transforms_json_capture(numbered, run_dir):
    config = tiny_config(run_dir, OrderedCaptureDataParserConfig(data=numbered), num_tasks=2, iterations_per_task=2)
    trainer = train(config)
    datamanager = trainer.pipeline.datamanager
    assert datamanager.num_tasks == 2 and trainer.pipeline.task.current == 1
    frames = datamanager.train_dataset.image_filenames + datamanager.eval_dataset.image_filenames
    assert sorted(path.name for path in frames) == sorted(f"frame_{number}.png" for number in NUMBERS)
    assert (trainer.base_dir / "dataparser_transforms.json").is_file()
