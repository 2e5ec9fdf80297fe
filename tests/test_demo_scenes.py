"""The built-in scenes: the room (one camera) and the street (a three-camera rig, tasks split by instant)."""

from __future__ import annotations

import numpy as np
import torch
from helpers import DEMO_CACHE
from PIL import Image

from continual_nerf.core.task_split import split_into_tasks
from continual_nerf.dataparsers.continual_demo_dataparser import ContinualDemoDataParserConfig


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
