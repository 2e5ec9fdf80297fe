"""`continual-nerfstudio`: order, poses and intrinsics of generated transforms.json and COLMAP captures."""

from __future__ import annotations

import json
from pathlib import Path
from typing import List

import numpy as np
import pytest
import torch
from helpers import (
    HEIGHT,
    NUMBERS,
    SHUFFLE,
    WIDTH,
    arc_poses,
    edit_transforms,
    masked_capture,
    numbered_frames,
    original_poses,
    tiny_config,
    train,
    write_colmap_text,
    write_transforms,
)
from nerfstudio.cameras.cameras import CAMERA_MODEL_TO_TYPE, Cameras, CameraType
from nerfstudio.data.dataparsers.base_dataparser import DataparserOutputs
from nerfstudio.data.utils import colmap_parsing_utils as colmap
from nerfstudio.model_components.ray_generators import RayGenerator

from continual_nerf.core.continual_datamanager import ContinualDataManager, camera_ids
from continual_nerf.core.task_split import split_capture
from continual_nerf.dataparsers import ordered_capture_dataparser as parser_module
from continual_nerf.dataparsers.ordered_capture_dataparser import OrderedCaptureDataParserConfig
from continual_nerf.dataparsers.transforms_json import CAMERA_MODELS, FISHEYE624_DISTORTION
from continual_nerf.errors import ContinualConfigError, DatasetError
from continual_nerf.export_poses import transforms_json


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


FISHEYE_DISTORTION = {"k1": 0.1, "k2": -0.02, "k3": 0.003, "k4": -0.0004}
"""OPENCV_FISHEYE's k1..k4, which nerfstudio keeps in the first four slots of distortion_params."""


def types_by_name(outputs: DataparserOutputs) -> dict:
    return dict(zip(names(outputs), (CameraType(kind) for kind in outputs.cameras.camera_type.view(-1).tolist())))


def test_camera_models_are_read_per_frame_into_nerfstudios_camera_types(tmp_path):
    frames = numbered_frames(arc_poses())
    frames[1]["camera_model"] = "EQUIRECTANGULAR"  # frame_4
    frames[2].update({"camera_model": "PINHOLE", "k1": 0.0, "k2": 0.0, "k3": 0.0, "k4": 0.0})  # frame_6
    folder = write_transforms(tmp_path / "fisheye", frames, camera_model="OPENCV_FISHEYE", **FISHEYE_DISTORTION)
    outputs = parse(folder)
    special = {"frame_4.png": CameraType.EQUIRECTANGULAR, "frame_6.png": CameraType.PERSPECTIVE}
    assert types_by_name(outputs) == {name: special.get(name, CameraType.FISHEYE) for name in names(outputs)}
    distortion = outputs.cameras.distortion_params
    assert distortion is not None
    fisheye = [name not in special for name in names(outputs)]
    assert np.allclose(distortion[fisheye].numpy(), [*FISHEYE_DISTORTION.values(), 0.0, 0.0])
    assert np.allclose(distortion[names(outputs).index("frame_6.png")].numpy(), 0.0)
    cameras = camera_ids(outputs)
    assert len(set(cameras[fisheye].tolist())) == 1 and len(set(cameras.tolist())) == 3, "one camera per type"


def test_colmap_fisheye_cameras_are_fisheye(tmp_path):
    model = write_colmap_text(tmp_path / "scene")
    fisheye = " ".join(str(value) for value in FISHEYE_DISTORTION.values())
    (model / "cameras.txt").write_text(
        f"1 OPENCV_FISHEYE {WIDTH} {HEIGHT} 30 31 16 12 {fisheye}\n2 PINHOLE {WIDTH} {HEIGHT} 30 31 16 12\n"
    )
    outputs = parse(model)
    camera_1 = slice(0, None, 2)  # even frames
    assert outputs.cameras.camera_type[camera_1].flatten().tolist() == [CameraType.FISHEYE.value] * 5
    assert outputs.cameras.camera_type[1::2].flatten().tolist() == [CameraType.PERSPECTIVE.value] * 5
    distortion = outputs.cameras.distortion_params
    assert distortion is not None
    assert np.allclose(distortion[camera_1].numpy(), [*FISHEYE_DISTORTION.values(), 0.0, 0.0])


def test_fisheye624_takes_twelve_parameters_and_one_calibration(numbered):
    edit_transforms(
        numbered, **{f"frame_{n}": {"camera_model": "FISHEYE624", "distortion_params": [0.0] * 12} for n in NUMBERS}
    )
    outputs = parse(numbered)
    assert set(types_by_name(outputs).values()) == {CameraType.FISHEYE624}
    distortion = outputs.cameras.distortion_params
    assert distortion is not None and distortion.shape == (10, 12), "kept when zero: FISHEYE624 rays need it"
    edit_transforms(numbered, frame_8={"distortion_params": [0.01] * 12})
    assert error_of(numbered) == (
        f"{numbered / 'transforms.json'} frame images/frame_8.png: a FISHEYE624 capture needs the calibration of "
        "images/frame_2.png on every frame (nerfstudio unprojects a batch of FISHEYE624 rays with its first ray's)"
    )


@pytest.mark.parametrize("model", CAMERA_MODEL_TO_TYPE)
def test_the_models_accepted_are_those_nerfstudio_generates_rays_of_single_pixels_for(model):
    kind = CAMERA_MODEL_TO_TYPE[model]
    parameters = FISHEYE624_DISTORTION if kind == CameraType.FISHEYE624 else 6
    cameras = Cameras(
        camera_to_worlds=torch.eye(4)[:3].repeat(2, 1, 1),
        fx=30.0,
        fy=31.0,
        cx=16.0,
        cy=12.0,
        width=WIDTH,
        height=HEIGHT,
        distortion_params=torch.full((2, parameters), 0.01),
        camera_type=kind,
    )
    try:  # pixels of two frames, as a training batch draws them
        rays = RayGenerator(cameras)(torch.tensor([[0, 3, 5], [1, 10, 20], [0, 20, 30]]))
        generated = bool(torch.isfinite(rays.directions).all())
    except (IndexError, RuntimeError):
        generated = False
    assert generated == (model in CAMERA_MODELS)


def test_a_fisheye_capture_trains_on_fisheye_rays(tmp_path, run_dir):
    folder = write_transforms(tmp_path / "fisheye", numbered_frames(arc_poses()), camera_model="OPENCV_FISHEYE")
    parser = OrderedCaptureDataParserConfig(data=folder)
    manager = tiny_config(run_dir, parser, num_tasks=2).pipeline.datamanager.setup(device="cpu")
    assert isinstance(manager, ContinualDataManager)
    rays, batch = manager.next_train(0)
    cameras = manager.train_dataset.cameras
    frame, y, x = batch["indices"].unbind(-1)
    # undistorted, nerfstudio's fisheye turns a ray from the optical axis by its normalised radius (a pinhole: atan)
    radius = torch.hypot(
        (x + 0.5 - cameras.cx[frame, 0]) / cameras.fx[frame, 0], (y + 0.5 - cameras.cy[frame, 0]) / cameras.fy[frame, 0]
    )
    axis = -cameras.camera_to_worlds[frame, :, 2]
    angle = torch.atan2(torch.linalg.cross(rays.directions, axis).norm(dim=-1), (rays.directions * axis).sum(-1))
    assert torch.allclose(angle, radius, atol=1e-4)
    assert float((radius - torch.atan(radius)).max()) > 0.05, "the batch holds rays a pinhole would turn less"


def error_of(data: Path, error: type = DatasetError, **options) -> str:
    """The one-line message parsing `data` fails with."""
    with pytest.raises(error) as raised:
        parse(data, **options)
    message = str(raised.value)
    assert "\n" not in message
    return message


def crop_radii(outputs: DataparserOutputs) -> dict:
    """Each frame's fisheye crop radius in the dataparser's metadata, by image name (inf: not cropped)."""
    return dict(zip(names(outputs), outputs.metadata["fisheye_crop_radius"].tolist()))


def test_the_fisheye_crop_radius_reaches_the_fisheye_frames_only(tmp_path):
    frames = numbered_frames(arc_poses())
    for frame in frames[2::4]:  # frame_6 and frame_14
        frame["camera_model"] = "OPENCV_FISHEYE"
    mixed = write_transforms(tmp_path / "mixed", frames, fisheye_crop_radius=707.5)
    assert crop_radii(parse(mixed, frame_stride=2)) == {
        "frame_2.png": np.inf,
        "frame_6.png": 707.5,
        "frame_10.png": np.inf,
        "frame_14.png": 707.5,
        "frame_18.png": np.inf,
    }
    perspective = write_transforms(tmp_path / "perspective", numbered_frames(arc_poses()), fisheye_crop_radius=707.5)
    assert "fisheye_crop_radius" not in parse(perspective).metadata, "ignored without fisheye frames, as nerfstudio"
    null = write_transforms(tmp_path / "null", frames, fisheye_crop_radius=None)
    assert "fisheye_crop_radius" not in parse(null).metadata, "null: no radius, as nerfstudio reads it"


@pytest.mark.parametrize("radius", [0, -3.5, float("inf"), float("nan"), "wide", True, [8]])
def test_a_crop_radius_that_is_not_a_positive_finite_number_is_a_one_line_error(tmp_path, radius):
    folder = write_transforms(
        tmp_path / "fisheye", numbered_frames(arc_poses()), camera_model="OPENCV_FISHEYE", fisheye_crop_radius=radius
    )
    assert error_of(folder) == (
        f"{folder / 'transforms.json'}: fisheye_crop_radius must be a positive finite number of pixels, got {radius!r}"
    )


def split_names(outputs: DataparserOutputs, num_tasks: int) -> tuple:
    """Training and test image names of every task of the continual split of `outputs`."""
    split = split_capture(outputs, num_tasks, test_interval=4)
    image_names = np.array(names(outputs))
    return [list(image_names[f]) for f in split.train_frames], [list(image_names[f]) for f in split.test_frames]


def test_the_split_lists_name_the_test_frames_and_the_frames_that_train(tmp_path):
    listed = write_transforms(
        tmp_path / "listed",
        numbered_frames(arc_poses()),
        train_filenames=[f"images/frame_{number}.png" for number in (2, 4, 10, 12, 14, 18)],
        val_filenames=["./images/frame_6.png"],  # nerfstudio's lists may spell a path differently
        test_filenames=["images/frame_16.png"],
    )
    outputs = parse(listed)
    assert names(outputs) == [f"frame_{number}.png" for number in (2, 4, 6, 10, 12, 14, 16, 18)], "frame_8, 20 unlisted"
    assert outputs.metadata["held_out"].tolist() == [False, False, True, False, False, False, True, False]
    train_names, test_names = split_names(outputs, num_tasks=2)
    assert test_names == [["frame_6.png"], ["frame_16.png"]], "the listed frames, not every 4th"
    assert train_names == [
        ["frame_2.png", "frame_4.png", "frame_10.png"],
        ["frame_12.png", "frame_14.png", "frame_18.png"],
    ]
    unlisted = parse(write_transforms(tmp_path / "unlisted", numbered_frames(arc_poses())))
    assert "held_out" not in unlisted.metadata
    assert split_names(unlisted, num_tasks=2)[1] == [["frame_2.png", "frame_10.png"], ["frame_12.png", "frame_20.png"]]


def test_test_lists_without_a_train_list_train_every_other_frame(tmp_path):
    listed = write_transforms(tmp_path / "listed", numbered_frames(arc_poses()), test_filenames=["images/frame_8.png"])
    outputs = parse(listed, frame_stride=1)
    assert len(names(outputs)) == len(NUMBERS)
    train_names, test_names = split_names(outputs, num_tasks=1)
    assert test_names == [["frame_8.png"]] and len(train_names[0]) == len(NUMBERS) - 1
    with pytest.raises(ContinualConfigError) as raised:
        split_capture(outputs, 2, test_interval=4)
    assert str(raised.value) == (
        "--pipeline.datamanager.num-tasks 2: task 2 holds none of the frames the capture names for testing "
        "(test_filenames); every task needs training and test frames: use fewer tasks"
    )


def test_a_task_of_listed_test_frames_only_is_a_one_line_error(tmp_path):
    tested = [f"images/frame_{number}.png" for number in NUMBERS[:5]]  # every frame of task 1 of 2
    outputs = parse(write_transforms(tmp_path / "listed", numbered_frames(arc_poses()), test_filenames=tested))
    with pytest.raises(ContinualConfigError) as raised:
        split_capture(outputs, 2, test_interval=4)
    assert str(raised.value) == (
        "--pipeline.datamanager.num-tasks 2: task 1 holds only frames the capture names for testing "
        "(test_filenames); every task needs training and test frames: use fewer tasks"
    )


@pytest.mark.parametrize(
    "lists, expected",
    [
        ({"test_filenames": ["images/frame_99.png"]}, "test_filenames names images/frame_99.png, which is no frame's"),
        ({"val_filenames": "images/frame_2.png"}, "val_filenames must be a list of file paths"),
        (
            {"train_filenames": ["images/frame_2.png"], "test_filenames": ["images/frame_2.png"]},
            "images/frame_2.png is in train_filenames and in val_filenames or test_filenames; a test frame never",
        ),
    ],
)
def test_bad_split_lists_are_one_line_errors(tmp_path, lists, expected):
    folder = write_transforms(tmp_path / "listed", numbered_frames(arc_poses()), **lists)
    assert error_of(folder).startswith(f"{folder / 'transforms.json'}: {expected}")


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
    edit_transforms(numbered, frame_4={"camera_model": "KANNALA"})
    assert error_of(numbered).startswith(
        f"{frame_4}: camera model KANNALA is not supported (supported: SIMPLE_PINHOLE, "
    )
    for model in ("VR180_L", "OMNIDIRECTIONALSTEREO_R"):
        edit_transforms(numbered, frame_4={"camera_model": model})
        expected = f"{frame_4}: camera model {model} cannot train: nerfstudio generates its rays for whole images only"
        assert error_of(numbered).startswith(expected)
    edit_transforms(numbered, frame_4={"camera_model": "FISHEYE624", "distortion_params": [0.1] * 6})
    assert error_of(numbered) == f"{frame_4}: FISHEYE624 needs distortion_params of 12 numbers"
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
    model = write_colmap_text(tmp_path / "fov")
    fov = f"1 FOV {WIDTH} {HEIGHT} 30 31 16 12 0.1\n2 PINHOLE {WIDTH} {HEIGHT} 30 31 16 12\n"
    (model / "cameras.txt").write_text(fov)
    message = error_of(model)
    assert message.startswith(f"{model / 'cameras.txt'} camera 1: camera model FOV is not supported")
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


@pytest.mark.slow
def test_a_run_tests_on_the_frames_the_capture_lists_for_testing_and_never_trains_on_them(tmp_path, run_dir):
    tested = ["images/frame_4.png", "images/frame_14.png", "images/frame_18.png"]
    listed = write_transforms(tmp_path / "listed", numbered_frames(arc_poses()), test_filenames=tested)
    config = tiny_config(run_dir, OrderedCaptureDataParserConfig(data=listed), num_tasks=2, iterations_per_task=2)
    pipeline = train(config).pipeline
    datamanager = pipeline.datamanager
    assert [path.name for path in datamanager.eval_dataset.image_filenames] == [Path(name).name for name in tested]
    assert not {Path(name).name for name in tested} & {path.name for path in datamanager.train_dataset.image_filenames}
    assert [len(row) for row in pipeline.accuracy.psnr] == [1, 2], "every task measured on its listed frames"
    exported = transforms_json(datamanager, pipeline.model)  # what continual-nerf-export-poses writes
    (tmp_path / "exported").mkdir()
    (tmp_path / "exported" / "transforms.json").write_text(json.dumps(exported))
    reread = parse(tmp_path / "exported")
    assert [name for name, tested in zip(names(reread), reread.metadata["held_out"]) if tested] == [
        Path(name).name for name in tested
    ], "trained on again, the export tests on the same frames"


@pytest.mark.slow
def test_short_continual_run_on_a_fisheye_capture_with_masks(tmp_path, run_dir, single_thread):
    capture = masked_capture(
        tmp_path / "capture", camera_model="OPENCV_FISHEYE", fisheye_crop_radius=10.5, **FISHEYE_DISTORTION
    )
    config = tiny_config(run_dir, OrderedCaptureDataParserConfig(data=capture), num_tasks=2, iterations_per_task=2)
    pipeline = train(config).pipeline
    datamanager = pipeline.datamanager
    assert len(pipeline.accuracy.psnr) == 2 and np.isfinite(pipeline.accuracy.psnr[-1]).all(), "trained and evaluated"
    assert bool((datamanager.eval_dataset.cameras.camera_type == CameraType.FISHEYE.value).all())
    exported = transforms_json(datamanager, pipeline.model)  # what continual-nerf-export-poses writes
    assert exported["camera_model"] == "OPENCV_FISHEYE" and exported["fisheye_crop_radius"] == 10.5
    (tmp_path / "exported").mkdir()
    (tmp_path / "exported" / "transforms.json").write_text(json.dumps(exported))
    reread = parse(tmp_path / "exported")
    assert set(types_by_name(reread).values()) == {CameraType.FISHEYE}
    assert set(crop_radii(reread).values()) == {10.5}, "the export's fisheye frames are cropped alike"
    assert reread.mask_filenames is not None
    assert [path.name for path in reread.mask_filenames] == [f"frame_{number}.png" for number in NUMBERS]
