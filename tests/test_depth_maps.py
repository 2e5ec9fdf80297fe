"""Depth maps of every RGB-D format, read and put on the colour pixels they belong to, in the poses' units; their
flaws and broken files."""

from __future__ import annotations

import json
import math
import re
from pathlib import Path

import numpy as np
import pytest
import torch
from helpers import (
    HEIGHT,
    IMAGE_TIMES,
    NUMBERS,
    SCANNET_DEPTH_INTRINSIC,
    SCANNET_DEPTH_SIZE,
    WIDTH,
    arc_poses,
    demo_parser,
    depth_millimetres,
    edit_transforms,
    numbered_frames,
    scannet_poses,
    tum_depth_metres,
    with_depth_maps,
    write_exported,
    write_sens,
    write_sequence,
    write_transforms,
)
from nerfstudio.cameras.cameras import Cameras
from nerfstudio.data.dataparsers.base_dataparser import DataparserOutputs
from PIL import Image

from continual_nerf.core.accuracy_matrix import AccuracyMatrix
from continual_nerf.core.continual_dataset import TestFrameDataset as FrameDataset
from continual_nerf.core.depth_maps import Pinhole, depth_errors, read_depth_file, resample
from continual_nerf.dataparsers import demo_capture, demo_scene
from continual_nerf.dataparsers.demo_capture import DepthSensor
from continual_nerf.dataparsers.ordered_capture_dataparser import OrderedCaptureDataParserConfig
from continual_nerf.dataparsers.scannet_dataparser import ContinualScanNetDataParserConfig
from continual_nerf.dataparsers.tum_dataparser import ContinualTumDataParserConfig
from continual_nerf.errors import DatasetError
from continual_nerf.metadata_keys import DEPTH_FILENAMES

COLUMNS, ROWS = np.meshgrid(np.arange(WIDTH), np.arange(HEIGHT))
"""Every colour pixel's column and row."""


def metres(outputs: DataparserOutputs, scale_factor: float = 1.0) -> np.ndarray:
    """(N, H, W) depth of every frame's colour pixels as training reads it, back in metres (the dataparser's scale
    undone); 0 where there is none."""
    dataset = FrameDataset(outputs, scale_factor=scale_factor)
    assert dataset.depth_maps is not None, "the capture has depth maps"
    return np.stack([dataset.depth_maps.read(i).numpy() for i in range(len(dataset))]) / outputs.dataparser_scale


# ---- putting a depth map on the colour pixels ----


def test_a_depth_camera_of_other_size_and_intrinsics_is_sampled_through_both():
    colour = Pinhole(28.0, 29.0, 15.5, 11.5, 32, 24)
    # half the size, and its principal point two depth pixels further right: the colour image's right edge is beyond it
    depth_camera = Pinhole(14.0, 14.5, 7.75 + 2, 5.75, 16, 12)
    depth = np.arange(16 * 12, dtype=np.float64).reshape(12, 16) + 1
    aligned = resample(depth, depth_camera, colour)
    column = COLUMNS // 2 + 2  # the depth pixel each colour pixel's ray falls in
    expected = np.where(column < 16, depth[ROWS // 2, np.minimum(column, 15)], 0.0)
    assert aligned.shape == (24, 32) and np.array_equal(aligned, expected)
    assert (aligned[:, 28:] == 0).all() and (aligned[:, :28] > 0).all()


def test_the_same_camera_at_another_size_is_a_nearest_resize():
    colour = Pinhole(30.0, 30.0, 16.0, 12.0, 32, 24)
    depth = np.random.default_rng(0).uniform(1, 2, (48, 64))
    aligned = resample(depth, colour.resized(64, 48), colour)
    assert np.allclose(aligned, depth[2 * ROWS + 1, 2 * COLUMNS + 1]), "each colour pixel takes the depth at its centre"


def test_zero_negative_and_non_finite_depths_are_pixels_without_depth(tmp_path):
    values = np.array([[1.5, 0.0, -2.0], [np.nan, np.inf, -np.inf]], dtype=np.float32)
    folder = write_transforms(tmp_path / "capture", numbered_frames(arc_poses()), w=3, h=2, cx=1.5, cy=1.0)
    for number in NUMBERS:
        np.save(folder / f"depth_{number}.npy", values)
        edit_transforms(folder, **{f"frame_{number}": {"depth_file_path": f"depth_{number}.npy"}})
    for number in NUMBERS:  # the images as the intrinsics say
        Image.new("RGB", (3, 2)).save(folder / "images" / f"frame_{number}.png")
    outputs = OrderedCaptureDataParserConfig(data=folder, depth_unit_scale_factor=1.0).setup().get_dataparser_outputs()
    read = metres(outputs)
    assert np.allclose(read, [[1.5, 0, 0], [0, 0, 0]]), "only finite positive depths are depths"


# ---- the formats ----


def test_scannet_exported_depth_of_another_size_and_intrinsics_lands_on_its_colour_pixels(tmp_path):
    intrinsic = SCANNET_DEPTH_INTRINSIC.copy()
    intrinsic[0, 2] += 2  # the depth camera's principal point two depth pixels right of the colour camera's
    folder = write_exported(tmp_path / "scene", scannet_poses(3), depth_intrinsic=intrinsic)
    outputs = ContinualScanNetDataParserConfig(data=folder).setup().get_dataparser_outputs()
    assert outputs.metadata[DEPTH_FILENAMES] == [folder / "depth" / f"{i}.png" for i in range(3)]
    column = COLUMNS // 2 + 2
    for i, read in enumerate(metres(outputs)):
        expected = depth_millimetres(i, *SCANNET_DEPTH_SIZE)[ROWS // 2, np.minimum(column, 15)] / 1000
        assert np.allclose(read, np.where(column < 16, expected, 0.0), atol=1e-5), "millimetres, scaled as the poses"


def test_scannet_exported_folder_without_depth_has_none(tmp_path):
    outputs = ContinualScanNetDataParserConfig(data=write_exported(tmp_path / "scene", scannet_poses(3))).setup()
    assert DEPTH_FILENAMES not in outputs.get_dataparser_outputs().metadata


@pytest.mark.parametrize("compression", [0, 1], ids=["raw_ushort", "zlib_ushort"])
def test_sens_depth_frames_are_extracted_and_aligned(tmp_path, compression):
    sens = tmp_path / "scene.sens"
    write_sens(sens, scannet_poses(4), lost=(2,), depth_compression=compression)
    outputs = ContinualScanNetDataParserConfig(data=sens, frame_stride=2).setup().get_dataparser_outputs()
    cache = tmp_path / "scene_sens_frames" / "depth"
    assert sorted(path.name for path in cache.iterdir()) == ["0.png", "3.png"], "the selected frames' only"
    expected = ((ROWS // 2) * SCANNET_DEPTH_SIZE[0] + COLUMNS // 2) / 1000  # its values: millimetres in flat order
    assert np.allclose(metres(outputs), expected, atol=1e-5) and (metres(outputs)[:, 0, 0] == 0).all()


def test_sens_depth_compressed_otherwise_is_a_one_line_error(tmp_path):
    sens = tmp_path / "scene.sens"
    write_sens(sens, scannet_poses(2), depth_compression=2)
    with pytest.raises(DatasetError, match=f"^{sens}: depth frames are occi_ushort-compressed; only raw_ushort and"):
        ContinualScanNetDataParserConfig(data=sens).setup().get_dataparser_outputs()


def tum_times(outputs: DataparserOutputs) -> np.ndarray:
    """The timestamps of the frames' images (their file names)."""
    return np.array([float(path.stem) for path in outputs.image_filenames])


def test_tum_depth_maps_are_the_nearest_in_time_within_the_tolerance(tmp_path, capsys):
    # the depth camera's own clock: 7 ms after or 12 ms before each image, none near image 6, and one extra map 25 ms
    # after image 6 that is nearer image 7 than image 6 is within tolerance (but image 7's own is nearer still)
    own = {i: IMAGE_TIMES[i] + (0.007 if i % 2 else -0.012) for i in range(12) if i != 6}
    depth_times = np.sort([*own.values(), IMAGE_TIMES[6] + 0.025])
    sequence = write_sequence(tmp_path / "rgbd_dataset_freiburg1_desk", depth_times=depth_times)
    outputs = ContinualTumDataParserConfig(data=sequence).setup().get_dataparser_outputs()
    images = [int(np.argmin(np.abs(IMAGE_TIMES - t))) for t in tum_times(outputs)]
    assert 6 in images and len(images) == 9, "images 3 to 11 have a pose"
    for image, read in zip(images, metres(outputs)):
        if image == 6:
            assert (read == 0).all(), "no depth map within 0.02 s: the image trains without depth"
        else:
            place = int(np.searchsorted(depth_times, own[image]))
            assert np.allclose(read, tum_depth_metres(place), atol=1e-6), f"image {image}: 5000 per metre"
    assert "1 of 9 images have no depth map within 0.02 s" in " ".join(capsys.readouterr().out.split())
    wider = ContinualTumDataParserConfig(data=sequence, max_time_difference=0.03).setup().get_dataparser_outputs()
    wider_images = [int(np.argmin(np.abs(IMAGE_TIMES - t))) for t in tum_times(wider)]  # image 2 gets a pose too
    place = int(np.searchsorted(depth_times, IMAGE_TIMES[6] + 0.025))
    assert np.allclose(metres(wider)[wider_images.index(6)], tum_depth_metres(place)), "the poses' tolerance"


def test_tum_without_depth_txt_has_no_depth(tmp_path):
    outputs = ContinualTumDataParserConfig(data=write_sequence(tmp_path / "fr1")).setup().get_dataparser_outputs()
    assert DEPTH_FILENAMES not in outputs.metadata


def test_transforms_depth_file_path_of_another_size_in_its_units(tmp_path):
    folder = with_depth_maps(write_transforms(tmp_path / "capture", numbered_frames(arc_poses())), 16, 12)
    parser = OrderedCaptureDataParserConfig(data=folder, downscale_factor=2)
    outputs = parser.setup().get_dataparser_outputs()
    read = metres(outputs, scale_factor=0.5)  # the colour images load at 16x12, as the depth maps are
    for index, frame in enumerate(read):
        assert np.allclose(frame, depth_millimetres(index, 16, 12) / 1000, atol=1e-5), "nerfstudio's 1e-3 by default"
    tenths = OrderedCaptureDataParserConfig(data=folder, depth_unit_scale_factor=1e-4).setup().get_dataparser_outputs()
    assert np.allclose(metres(tenths)[0, 0, 0], 0.1), "--depth-unit-scale-factor: metres per unit"


def test_transforms_depth_on_some_frames_only_is_a_one_line_error(tmp_path):
    folder = with_depth_maps(write_transforms(tmp_path / "capture", numbered_frames(arc_poses())))
    meta = json.loads((folder / "transforms.json").read_text())
    del next(frame for frame in meta["frames"] if frame["file_path"] == "images/frame_8.png")["depth_file_path"]
    (folder / "transforms.json").write_text(json.dumps(meta))
    message = "frame images/frame_8.png: has no depth_file_path while other frames have one (give every frame a depth"
    with pytest.raises(DatasetError, match=re.escape(message)):
        OrderedCaptureDataParserConfig(data=folder).setup().get_dataparser_outputs()


def test_demo_depth_is_exact_z_depth(tmp_path):
    outputs = demo_parser(num_frames=6, width=24, height=18).setup().get_dataparser_outputs()
    read = metres(outputs)
    assert read.shape == (6, 18, 24) and (read > 0).all()
    # a camera facing a wall square on: every pixel's z-depth is the wall's distance, whatever its ray's slant
    wall = demo_scene.Scene(lo=np.array([-10.0, -30, -30]), hi=np.array([1.0, 30, 30]), crates=[], surface=lambda *a: 0)
    facing = np.array([[0.0, 0, 1, 0], [0, 1, 0, 0], [-1, 0, 0, 0]])  # looks down world -x (OpenGL: camera -z)
    assert np.allclose(demo_scene.render_depth(facing, 20, 20, 12, 9, 24, 18, wall), 10.0, atol=1e-5)


def test_demo_depth_sensor_flaws():
    rng = np.random.default_rng(0)
    depth = np.full((40, 60), 1.0)
    depth[:, 30:] = 4.0  # a step: an object's edge between x = 29 and 30
    sensed = demo_capture.sensed_depth(depth, DepthSensor(noise=0.01, max_range=5, edge_holes=2, dropout=0.1), rng)
    holes = sensed == 0
    assert holes[:, 28:32].all() and not holes[:, 27].all() and not holes[:, 32].all(), "2 pixels either side"
    assert 0.05 < holes[:, :20].mean() < 0.15, "a tenth of the pixels at random"
    near, far = sensed[:, :20][sensed[:, :20] > 0] - 1, sensed[:, 40:][sensed[:, 40:] > 0] - 4
    assert 12 < far.std() / near.std() < 20, "noise grows with the square of the depth"
    assert (demo_capture.sensed_depth(depth, DepthSensor(max_range=3), rng)[:, 30:] == 0).all(), "beyond its range"
    assert np.array_equal(demo_capture.sensed_depth(depth, DepthSensor(), rng), depth), "exact without flaws"


def test_demo_depth_options_make_their_own_maps_beside_the_exact_ones():
    parser = demo_parser(num_frames=6, width=24, height=18)
    exact = metres(parser.setup().get_dataparser_outputs())
    parser.depth_max_range, parser.depth_dropout = 3.0, 0.2
    flawed_outputs = parser.setup().get_dataparser_outputs()
    flawed = metres(flawed_outputs)
    assert flawed_outputs.metadata[DEPTH_FILENAMES][0].parent.name == "depth_range3_dropout0.2"
    assert (flawed[exact > 3] == 0).all() and (flawed == 0).mean() > (exact > 3).mean()
    assert np.allclose(flawed[flawed > 0], exact[flawed > 0]), "no noise asked for"


# ---- broken depth files ----


@pytest.mark.parametrize(
    "write, message",
    [
        (lambda path: None, "depth map missing"),
        (lambda path: path.write_bytes(b"not a png"), "cannot read depth map (cannot identify image file"),
        (lambda path: Image.new("RGB", (4, 3)).save(path), "depth map mode RGB is not supported"),
        (lambda path: path.write_bytes(Path(__file__).read_bytes()[:0]), "cannot read depth map"),
    ],
    ids=["missing", "garbage", "8-bit-colour", "empty"],
)
def test_a_broken_depth_map_is_a_one_line_error_naming_it(tmp_path, write, message):
    path = tmp_path / "depth.png"
    write(path)
    with pytest.raises(DatasetError) as raised:
        read_depth_file(path)
    assert str(raised.value).startswith(f"{path}: {message}") and "\n" not in str(raised.value)


def test_a_depth_array_of_many_channels_is_a_one_line_error(tmp_path):
    path = tmp_path / "depth.npy"
    np.save(path, np.ones((3, 4, 2), dtype=np.float32))
    with pytest.raises(
        DatasetError, match=r"depth.npy: a depth map is one channel of numbers, found an array of shape"
    ):
        read_depth_file(path)


# ---- measuring depth ----


def test_depth_errors_over_the_pixels_with_depth():
    truth = torch.tensor([[2.0, 0.0], [4.0, 1.0]])
    rendered = torch.tensor([[2.2, 9.0], [3.6, 1.0]])
    abs_rel, rmse = depth_errors(rendered, truth, metres_per_scene_unit=10.0)
    assert abs_rel == pytest.approx((0.1 + 0.1 + 0.0) / 3)
    assert rmse == pytest.approx(10 * math.sqrt((0.04 + 0.16) / 3)), "in metres"
    assert all(math.isnan(value) for value in depth_errors(rendered, torch.zeros(2, 2), 1.0))


def test_an_accuracy_matrix_written_before_depth_reads(tmp_path):
    path = tmp_path / "accuracy_matrix.json"
    written = {"num_tasks": 2, "psnr": [[20.0]], "ssim": [[0.5]], "mean_psnr": [20.0], "steps": [9]}
    path.write_text(json.dumps({**written, "finished": False, "status": "training"}))
    matrix = AccuracyMatrix.read(path)
    assert matrix.psnr == [[20.0]] and matrix.depth_abs_rel == [] and matrix.mean_depth_rmse == []


def test_cameras_without_depth_intrinsics_share_the_colour_cameras():
    cameras = Cameras(camera_to_worlds=torch.eye(4)[None, :3], fx=10.0, fy=11.0, cx=8.0, cy=6.0, width=16, height=12)
    assert Pinhole.of_camera(cameras, 0).resized(8, 6) == Pinhole(5.0, 5.5, 4.0, 3.0, 8, 6)
