"""The built-in scenes: the room (one camera) and the street (a three-camera rig, tasks split by instant)."""

from __future__ import annotations

import colorsys
import dataclasses
from pathlib import Path
from typing import List, Tuple

import numpy as np
import pytest
import torch
from helpers import DEMO_CACHE
from PIL import Image

from continual_nerf.core.task_split import split_into_tasks
from continual_nerf.dataparsers import demo_capture, demo_scene
from continual_nerf.dataparsers.continual_demo_dataparser import ContinualDemoDataParserConfig
from continual_nerf.errors import ContinualConfigError


def street(num_frames: int = 8):
    config = ContinualDemoDataParserConfig(data=DEMO_CACHE, scene="street", num_frames=num_frames, width=24, height=18)
    return config.setup().get_dataparser_outputs(split="train")


def test_the_street_rig_takes_three_images_per_instant_45_degrees_apart():
    outputs = street()
    assert len(outputs.image_filenames) == 24
    assert outputs.metadata["time_group"].tolist() == [i // 3 for i in range(24)]
    poses = outputs.cameras.camera_to_worlds
    forward = -poses[:, :, 2]  # OpenGL cameras look down -z
    for instant in range(8):
        front, left, right = forward[3 * instant : 3 * instant + 3]
        angles = [
            float(torch.rad2deg(torch.arccos((front @ other) / (front.norm() * other.norm()))))
            for other in (left, right)
        ]
        assert np.allclose(angles, 45.0, atol=0.5), "front-left and front-right are 45 degrees off the front camera"
        assert torch.allclose(poses[3 * instant, :, 3], poses[3 * instant + 2, :, 3]), "one rig: one position"
        assert float(torch.cross(front, left, dim=0)[2]) > 0 > float(torch.cross(front, right, dim=0)[2]), (
            "left is left"
        )
    x = poses[::3, 0, 3]
    assert bool((x[1:] > x[:-1]).all()), "the vehicle drives forward along the street"
    assert float(poses[:, :, 3].abs().max()) <= 1.0, "the street fits nerfstudio's box"


def test_the_street_is_split_by_instant_so_a_task_holds_every_camera_of_its_span():
    outputs = street()
    split = split_into_tasks(len(outputs.image_filenames), 2, 3, time_group=outputs.metadata["time_group"].numpy())
    for frames in (*split.train_frames, *split.test_frames):
        assert len(frames) % 3 == 0
    first_task = np.concatenate([split.train_frames[0], split.test_frames[0]])
    assert sorted(first_task.tolist()) == list(range(12)), "task 1: the first four instants, all three cameras"


def test_street_images_differ_along_the_street_and_between_cameras():
    outputs = street()
    images = [np.asarray(Image.open(path), dtype=np.float32) for path in outputs.image_filenames]
    assert images[0].shape == (18, 24, 3)
    assert np.abs(images[0] - images[1]).mean() > 10, "front and front-left see different things"
    assert np.abs(images[0] - images[21]).mean() > 10, "the start and the end of the street look different"


def demo(num_frames: int = 8, **options) -> ContinualDemoDataParserConfig:
    return ContinualDemoDataParserConfig(data=DEMO_CACHE, num_frames=num_frames, width=24, height=18, **options)


def pixels(path) -> np.ndarray:
    return np.asarray(Image.open(path), dtype=np.float64)


def test_exposure_scales_each_frame_by_its_gain_and_jumps_between_segments():
    clean, exposed = demo(), demo(exposure_strength=0.3, exposure_segments=2)
    clean_outputs = clean.setup().get_dataparser_outputs("train")
    parser = exposed.setup()
    outputs = parser.get_dataparser_outputs("train")
    gains = parser.frame_gains(parser.capture())
    assert torch.equal(outputs.cameras.camera_to_worlds, clean_outputs.cameras.camera_to_worlds), "same poses"
    for frame, gain in enumerate(gains):
        # the same pose, exposed differently: every unsaturated pixel is the exact one times the frame's gain
        exact, captured = pixels(clean_outputs.image_filenames[frame]), pixels(outputs.image_filenames[frame])
        unsaturated = exact * gain < 254.5
        assert np.abs(captured - exact * gain)[unsaturated].max() <= 0.5
    assert gains.min() >= (1 - 0.3) * (1 - 0.1) * (1 - 0.06) and gains.max() <= (1 + 0.3) * (1 + 0.1) * (1 + 0.06)
    within = max(np.abs(np.diff(gains[:4], axis=0)).max(), np.abs(np.diff(gains[4:], axis=0)).max())
    assert np.abs(gains[4] - gains[3]).max() > 3 * within, "a jump where the second segment starts, drift within"


def test_each_camera_of_the_rig_has_its_own_colour_response():
    clean, responding = demo(scene="street"), demo(scene="street", camera_response_strength=0.2)
    clean_outputs = clean.setup().get_dataparser_outputs("train")
    parser = responding.setup()
    outputs = parser.get_dataparser_outputs("train")
    responses = parser.camera_responses(parser.capture())
    assert len(responses) == 3 and outputs.metadata["camera_id"].tolist() == [0, 1, 2] * 8
    for frame, camera in enumerate(outputs.metadata["camera_id"].tolist()):
        exact, captured = pixels(clean_outputs.image_filenames[frame]), pixels(outputs.image_filenames[frame])
        response = responses[camera]
        expected = np.clip(response.gain * (exact / 255) ** response.gamma, 0, 1) * 255
        assert np.abs(captured - expected).max() <= 0.5
    gains = np.stack([response.gain for response in responses])
    assert np.abs(gains[:, None] - gains[None]).max() > 0.1, "the cameras do not see colour alike"


def noisy_demo_poses(kind: str) -> Tuple[np.ndarray, np.ndarray, List[Path], List[Path]]:
    """The true and the returned training poses of the demo with 1 degree and 1 % pose noise of `kind`, and the
    image files of each."""
    clean_outputs = demo(num_frames=120).setup().get_dataparser_outputs("train")
    options = {"pose_noise_degrees": 1.0, "pose_noise_translation": 0.01, "pose_noise_kind": kind}
    outputs = demo(num_frames=120, **options).setup().get_dataparser_outputs("train")
    true, noisy = clean_outputs.cameras.camera_to_worlds, outputs.cameras.camera_to_worlds
    return true.double().numpy(), noisy.double().numpy(), clean_outputs.image_filenames, outputs.image_filenames


def assert_set_amounts(degrees: np.ndarray, distances: np.ndarray, true: np.ndarray) -> None:
    assert np.sqrt((degrees**2).mean()) == pytest.approx(1.0, rel=1e-3)
    length = demo_capture.trajectory_length(true[:, :, 3])
    assert np.sqrt((distances**2).mean()) / length == pytest.approx(0.01, rel=1e-3)


def test_pose_noise_moves_the_returned_poses_by_the_set_amounts_and_leaves_the_images_exact():
    true, noisy, clean_images, images = noisy_demo_poses("smooth")
    assert images == clean_images, "images stay rendered from the true poses"
    degrees, distances = demo_capture.pose_errors(noisy, true)
    assert_set_amounts(degrees, distances, true)
    assert np.abs(np.diff(degrees)).max() < 0.3 * degrees.max(), "smooth along the capture, as drift is"


def test_independent_pose_noise_has_the_set_amounts_and_no_correlation_between_neighbouring_frames():
    true, noisy, _, _ = noisy_demo_poses("independent")
    degrees, distances = demo_capture.pose_errors(noisy, true)
    assert_set_amounts(degrees, distances, true)
    shifts = noisy[:, :, 3] - true[:, :, 3]
    neighbours = np.corrcoef(shifts[:-1].ravel(), shifts[1:].ravel())[0, 1]
    assert abs(neighbours) < 0.3, "each instant's error is drawn on its own, as when each image is registered alone"


def test_the_rig_shares_one_pose_error_per_instant():
    clean_outputs = demo(scene="street").setup().get_dataparser_outputs("train")
    outputs = demo(scene="street", pose_noise_translation=0.02).setup().get_dataparser_outputs("train")
    shift = (outputs.cameras.camera_to_worlds - clean_outputs.cameras.camera_to_worlds)[:, :, 3].view(8, 3, 3)
    assert torch.allclose(shift, shift[:, :1].expand(8, 3, 3), atol=1e-6) and shift.abs().max() > 1e-3


@pytest.mark.parametrize(("scene", "cameras", "default_frames"), [("rooms", 1, 480), ("long-street", 3, 480)])
def test_the_long_scenes_never_revisit_and_every_task_has_train_and_test_frames(scene, cameras, default_frames):
    config = ContinualDemoDataParserConfig(data=DEMO_CACHE, scene=scene, num_frames=40, width=16, height=12)
    assert dataclasses.replace(config, num_frames=None).frames == default_frames
    outputs = config.setup().get_dataparser_outputs(split="train")
    assert len(outputs.image_filenames) == 40 * cameras
    x = outputs.cameras.camera_to_worlds[::cameras, 0, 3]
    assert bool((x[1:] > x[:-1]).all()), "the path only goes forward: no place is seen again later"
    assert float(outputs.cameras.camera_to_worlds[:, :, 3].abs().max()) <= 1.0, "it fits nerfstudio's box"
    groups = outputs.metadata["time_group"].numpy() if cameras > 1 else None
    split = split_into_tasks(len(outputs.image_filenames), 10, 4, time_group=groups)
    assert all(len(frames) > 0 for frames in (*split.train_frames, *split.test_frames))


def test_the_long_scenes_are_longer_than_the_short_ones_and_look_different_along_them():
    short = demo(scene="room").setup().capture().scene
    long = demo(scene="rooms").setup().capture().scene
    assert float(long.hi[0] - long.lo[0]) >= 3.5 * float(short.hi[0] - short.lo[0])
    outputs = demo(num_frames=16, scene="rooms").setup().get_dataparser_outputs(split="train")
    first, last = pixels(outputs.image_filenames[0]), pixels(outputs.image_filenames[-1])
    assert np.abs(first - last).mean() > 10, "the last room does not look like the first"


def test_the_vectorised_hue_gives_colorsys_colours_to_the_last_bit():
    hues = np.random.default_rng(0).uniform(0.0, 0.999, size=(50, 7))
    expected = np.array([colorsys.hsv_to_rgb(h, 0.55, 0.95) for h in hues.ravel()]).reshape(50, 7, 3)
    assert np.array_equal(demo_scene.hsv_to_rgb(hues, 0.55, 0.95), expected)


@pytest.mark.parametrize("scene", ["room", "street"])
@pytest.mark.parametrize("change", ["object-moved", "wall-repainted"])
def test_a_later_session_finds_one_region_changed_and_the_rest_as_it_was(scene, change):
    before, after = (
        ContinualDemoDataParserConfig(data=DEMO_CACHE, scene=scene, num_frames=8, width=24, height=18, change=kind)
        .setup()
        .get_dataparser_outputs("train")
        for kind in ("none", change)
    )
    assert torch.equal(before.cameras.camera_to_worlds, after.cameras.camera_to_worlds), "the same path"
    assert torch.equal(before.dataparser_transform, after.dataparser_transform), "the same world frame"
    changed = [
        (pixels(a) != pixels(b)).any(axis=-1).mean() for a, b in zip(before.image_filenames, after.image_filenames)
    ]
    assert max(changed) > 0.02, "some frames see the change"
    assert max(changed) < 0.5 and sum(share == 0 for share in changed) >= len(changed) // 4, "a region, not the scene"


def test_start_and_end_instants_cut_a_capture_into_sessions():
    whole = demo(num_frames=8).setup().get_dataparser_outputs("train")
    parts = [demo(num_frames=8, start_instant=0, end_instant=5), demo(num_frames=8, start_instant=5)]
    first, second = (part.setup().get_dataparser_outputs("train") for part in parts)
    assert first.image_filenames + second.image_filenames == whole.image_filenames
    joined = torch.cat([first.cameras.camera_to_worlds, second.cameras.camera_to_worlds])
    assert torch.equal(joined, whole.cameras.camera_to_worlds)
    with pytest.raises(ContinualConfigError, match="--start-instant 5 --end-instant 5"):
        demo(num_frames=8, start_instant=5, end_instant=5).setup()


def test_two_laps_see_the_scene_as_it_was_then_as_it_changed():
    both = demo(num_frames=8, laps=2, change="object-moved").setup().get_dataparser_outputs("train")
    before = demo(num_frames=8).setup().get_dataparser_outputs("train")
    after = demo(num_frames=8, change="object-moved").setup().get_dataparser_outputs("train")
    assert len(both.image_filenames) == 16
    assert torch.equal(both.cameras.camera_to_worlds, torch.cat([before.cameras.camera_to_worlds] * 2))
    for lap, state in enumerate((before, after)):
        for index, path in enumerate(state.image_filenames):
            assert np.array_equal(pixels(both.image_filenames[8 * lap + index]), pixels(path))
