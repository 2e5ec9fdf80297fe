"""continual-tum on a generated sequence in TUM RGB-D's own layout, with a known continuous trajectory."""

from __future__ import annotations

import json
from pathlib import Path
from typing import List

import numpy as np
import pytest
from helpers import (
    HEIGHT,
    IMAGE_TIMES,
    POSE_TIMES,
    START,
    WIDTH,
    original_poses,
    pose_at,
    tiny_config,
    train,
    write_sequence,
)
from PIL import Image

from continual_nerf.dataparsers.tum_dataparser import ContinualTumDataParserConfig
from continual_nerf.errors import ContinualConfigError, DatasetError

OPENCV_TO_OPENGL = np.diag([1.0, -1.0, -1.0, 1.0])


def parse(data: Path, **options):
    return ContinualTumDataParserConfig(data=data, **options).setup().get_dataparser_outputs(split="train")


def opengl(poses: List[np.ndarray]) -> np.ndarray:
    return (np.stack(poses) @ OPENCV_TO_OPENGL)[:, :3, :4]


def console_text(capsys) -> str:
    return " ".join(capsys.readouterr().out.split())


@pytest.fixture
def sequence(tmp_path) -> Path:
    return write_sequence(tmp_path / "rgbd_dataset_freiburg1_desk")


def test_nearest_association_poses_order_and_dropped_images(sequence, capsys):
    outputs = parse(sequence)
    kept = IMAGE_TIMES[3:]
    assert outputs.image_filenames == [sequence / "rgb" / f"{t:.6f}.png" for t in kept]
    nearest = [POSE_TIMES[np.argmin(np.abs(POSE_TIMES - t))] for t in kept]
    assert np.allclose(original_poses(outputs), opengl([pose_at(t) for t in nearest]), atol=1e-5)
    text = console_text(capsys)
    assert (
        f"{sequence / 'rgb.txt'}: dropping 3 of 12 images with no ground-truth pose within 0.02 s (nearest): " in text
    )
    assert f"{IMAGE_TIMES[0]:.6f}.png, {IMAGE_TIMES[1]:.6f}.png, {IMAGE_TIMES[2]:.6f}.png" in text


def test_interpolation_recovers_the_pose_at_each_image_time(sequence):
    outputs = parse(sequence, association="interpolate")
    kept = IMAGE_TIMES[3:]
    assert len(outputs.image_filenames) == len(kept)
    assert np.allclose(original_poses(outputs), opengl([pose_at(t) for t in kept]), atol=1e-5)


def test_images_beyond_the_ground_truth_span_are_not_interpolated(tmp_path):
    # last pose 0.002 s before the last image: near enough for nearest, but nothing to interpolate towards
    folder = write_sequence(tmp_path / "rgbd_dataset_freiburg1_xyz", pose_times=START + np.arange(38) / 100)
    assert len(parse(folder).image_filenames) == 12
    assert len(parse(folder, association="interpolate").image_filenames) == 11


def test_quaternions_are_scalar_last_and_normalised(tmp_path):
    """qx qy qz qw = (0, 0, s, s), scaled: 90 degrees about z, so the camera's +x axis points along world +y."""
    lines = [f"{START + i * 0.01:.6f} {i} 0 0 0 0 3 3" for i in range(20)]
    folder = write_sequence(
        tmp_path / "rgbd_dataset_freiburg2_desk", image_times=START + np.arange(5) / 30, groundtruth_lines=lines
    )
    rotations = original_poses(parse(folder))[:, :3, :3]
    assert np.allclose(rotations[:, :, 0], [0, 1, 0], atol=1e-6), "camera x (right) along world +y"
    assert np.allclose(rotations[:, :, 2], [0, 0, -1], atol=1e-6), "OpenCV +z forward along world +z: OpenGL +z is -z"


def test_rgb_txt_out_of_time_order_is_read_in_capture_order(sequence):
    rgb_file = sequence / "rgb.txt"
    lines = rgb_file.read_text().splitlines()
    rgb_file.write_text("\n".join(lines[:3] + lines[3:][::-1]) + "\n")
    outputs = parse(sequence)
    assert outputs.image_filenames == [sequence / "rgb" / f"{t:.6f}.png" for t in IMAGE_TIMES[3:]]


def resize_images(folder: Path, size) -> None:
    """Replace the sequence's images by plain ones of `size` (width, height), as a resized copy would have."""
    for image in (folder / "rgb").iterdir():
        Image.new("RGB", size, (90, 120, 150)).save(image)


@pytest.mark.parametrize(
    "sensor,intrinsics,distortion",
    [
        ("freiburg1", (517.3, 516.5, 318.6, 255.3), (0.2624, -0.9531, 1.1633, 0.0, -0.0054, 0.0026)),
        ("freiburg2", (520.9, 521.0, 325.1, 249.7), (0.2312, -0.7849, 0.9172, 0.0, -0.0033, -0.0001)),
        ("freiburg3", (535.4, 539.2, 320.1, 247.6), None),
        ("kinect", (525.0, 525.0, 319.5, 239.5), None),
    ],
)
def test_intrinsics_and_distortion_follow_the_sensor_in_the_folder_name(
    tmp_path, capsys, sensor, intrinsics, distortion
):
    folder = write_sequence(tmp_path / f"rgbd_dataset_{sensor}_desk")
    resize_images(folder, (640, 480))  # the sensor's own image size
    cameras = parse(folder).cameras
    for values, expected in zip((cameras.fx, cameras.fy, cameras.cx, cameras.cy), intrinsics):
        assert np.allclose(values.numpy(), expected)
    assert (cameras.width == 640).all() and (cameras.height == 480).all(), "size from the image header"
    if distortion is None:
        assert cameras.distortion_params is None
    else:
        assert np.allclose(cameras.distortion_params.numpy(), distortion), "nerfstudio order [k1, k2, k3, k4, p1, p2]"
    text = console_text(capsys)
    assert ("no freiburg1/2/3 in the folder name; using the ROS default intrinsics" in text) == (sensor == "kinect")
    assert "intrinsics scaled" not in text


def test_a_resized_copy_gets_the_sensor_intrinsics_scaled_and_says_so(tmp_path, capsys):
    folder = write_sequence(tmp_path / "rgbd_dataset_freiburg3_desk")
    resize_images(folder, (96, 72))
    cameras = parse(folder).cameras
    scale = 96 / 640
    expected = (535.4 * scale, 539.2 * scale, 320.1 * scale, 247.6 * scale)
    for values, value in zip((cameras.fx, cameras.fy, cameras.cx, cameras.cy), expected):
        assert np.allclose(values.numpy(), value)
    assert (cameras.width == 96).all() and (cameras.height == 72).all()
    assert (
        f"{folder} (sensor calibration): the images are 96x72 pixels, the calibration is for 640x480: "
        "intrinsics scaled by 0.15 x 0.15"
    ) in console_text(capsys)


def test_images_of_another_aspect_ratio_are_a_one_line_error(tmp_path):
    folder = write_sequence(tmp_path / "rgbd_dataset_freiburg3_desk")
    resize_images(folder, (96, 96))
    message = (
        f"{folder} (sensor calibration): the images are 96x96 pixels, the calibration is for 640x480, "
        "another aspect ratio: not a resized copy; give these images' intrinsics"
    )
    with pytest.raises(DatasetError) as raised:
        parse(folder)
    assert str(raised.value) == message
    assert len(parse(folder, fx=14.4, fy=14.4, cx=48.0, cy=48.0).image_filenames) == 9, "unless every value is given"


def test_user_intrinsics_are_for_the_images_as_they_are(tmp_path, capsys):
    folder = write_sequence(tmp_path / "my_capture")
    cameras = parse(folder, fx=30.0, fy=31.0, cx=16.0, cy=12.5, distortion=(0.1, -0.2, 0.003, 0.004, 0.05)).cameras
    assert np.allclose(cameras.fx.numpy(), 30.0) and np.allclose(cameras.fy.numpy(), 31.0)
    assert np.allclose(cameras.cx.numpy(), 16.0) and np.allclose(cameras.cy.numpy(), 12.5)
    assert np.allclose(cameras.distortion_params.numpy(), [0.1, -0.2, 0.05, 0.0, 0.003, 0.004])
    text = console_text(capsys)
    assert "ROS default" not in text and "intrinsics scaled" not in text
    fr1 = parse(write_sequence(tmp_path / "rgbd_dataset_freiburg1_room"), fx=40.0).cameras
    assert np.allclose(fr1.fx.numpy(), 40.0), "a given value is kept"
    assert np.allclose(fr1.fy.numpy(), 516.5 * WIDTH / 640), "the sensor's others are scaled to the 32x24 images"


def test_a_principal_point_outside_the_images_is_a_one_line_error(sequence):
    with pytest.raises(DatasetError) as raised:
        parse(sequence, cx=500.0)
    assert str(raised.value) == (
        f"{sequence} (intrinsics): principal point cx=500 cy=12.765 lies outside the {WIDTH}x{HEIGHT} image "
        "(intrinsics of another image size?)"
    )


def test_zero_length_quaternion_names_the_file_and_line(sequence):
    groundtruth = sequence / "groundtruth.txt"
    lines = groundtruth.read_text().splitlines()
    lines[8] = " ".join(lines[8].split()[:4] + ["0", "0", "0", "0"])
    groundtruth.write_text("\n".join(lines) + "\n")
    with pytest.raises(DatasetError, match=f"^{groundtruth}, line 9: quaternion qx qy qz qw has zero length$"):
        parse(sequence)


def test_no_image_near_any_pose_is_an_error(tmp_path):
    folder = write_sequence(tmp_path / "rgbd_dataset_freiburg1_desk", pose_times=START + 10 + np.arange(20) / 100)
    with pytest.raises(
        DatasetError, match=f"^{folder / 'groundtruth.txt'}: no image in rgb.txt has a pose within 0.02 s"
    ):
        parse(folder)


def test_the_tolerance_is_a_config_field(sequence):
    with pytest.raises(DatasetError, match="no image in rgb.txt has a pose within 0.001 s"):
        parse(sequence, max_time_difference=0.001)
    assert len(parse(sequence, max_time_difference=0.2).image_filenames) == 12


@pytest.mark.parametrize(
    "remove,message",
    [
        ("", "no such folder"),
        ("rgb.txt", "missing"),
        ("groundtruth.txt", "missing"),
    ],
)
def test_missing_folder_or_list_files_are_named(tmp_path, sequence, remove, message):
    if remove:
        (sequence / remove).unlink()
        target = sequence / remove
        data = sequence
    else:
        target = data = tmp_path / "nowhere"
    with pytest.raises(DatasetError, match=f"^{target}: {message}$"):
        parse(data)


def test_missing_image_names_it_and_its_rgb_txt_line(sequence):
    image = sequence / "rgb" / f"{IMAGE_TIMES[5]:.6f}.png"
    image.unlink()
    with pytest.raises(DatasetError, match=f"^{image}: missing \\(listed in {sequence / 'rgb.txt'}, line 9\\)$"):
        parse(sequence)


@pytest.mark.parametrize(
    "file,line,message",
    [
        ("groundtruth.txt", "1305031102.2 1 2 3 0 0 0", "line 6: expected 8 fields, found 7"),
        (
            "groundtruth.txt",
            "1305031102.2 1 2 x 0 0 0 1",
            "line 6: expected numbers, found '1305031102.2 1 2 x 0 0 0 1'",
        ),
        ("groundtruth.txt", "1305031102.2 1 2 nan 0 0 0 1", "line 6: pose has NaN or infinite entries"),
        ("rgb.txt", "soon rgb/a.png", "line 6: expected numbers, found 'soon'"),
    ],
)
def test_malformed_lines_name_the_file_and_line(sequence, file, line, message):
    path = sequence / file
    lines = path.read_text().splitlines()
    lines[5] = line
    path.write_text("\n".join(lines) + "\n")
    with pytest.raises(DatasetError, match=f"^{path}, {message}$"):
        parse(sequence)


@pytest.mark.parametrize(
    "options,message",
    [
        ({"max_time_difference": -0.1}, "--max-time-difference must be >= 0 seconds, got -0.1"),
        ({"fx": 0.0}, "--fx must be positive, got 0.0"),
        ({"max_frames": 0}, "--max-frames must be at least 1, got 0"),
    ],
)
def test_bad_options_are_config_errors(sequence, options, message):
    with pytest.raises(ContinualConfigError, match=message):
        parse(sequence, **options)


@pytest.mark.slow
def test_short_continual_ngp_run_on_a_distorted_sequence(sequence):
    # freiburg1's distortion with intrinsics scaled to the 32x24 fixture images
    parser = ContinualTumDataParserConfig(data=sequence, association="interpolate", fx=25.9, fy=25.8, cx=15.9, cy=12.8)
    config = tiny_config(sequence.parent / "outputs", parser, num_tasks=2, iterations_per_task=2)
    trainer = train(config)
    datamanager = trainer.pipeline.datamanager
    assert trainer.pipeline.task.current == 1
    assert datamanager.train_dataset.cameras.distortion_params is not None
    transforms = json.loads((trainer.base_dir / "dataparser_transforms.json").read_text())
    assert transforms["scale"] == pytest.approx(datamanager.train_dataparser_outputs.dataparser_scale)
