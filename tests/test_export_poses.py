"""`continual-nerf-export-poses`: a run's trajectory as nerfstudio's transforms.json, refined where it was refined."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
import torch
from helpers import demo_parser, tiny_config, train
from nerfstudio.cameras.camera_optimizers import CameraOptimizerConfig

from continual_nerf.dataparsers.ordered_capture_dataparser import OrderedCaptureDataParserConfig
from continual_nerf.export_poses import ExportPoses

pytestmark = pytest.mark.slow  # trains models, runs subprocesses or a browser

NUM_FRAMES = 16


def exported(config: Path, output: Path) -> dict:
    ExportPoses(load_config=config, output_dir=output).main()  # continual-nerf-export-poses, in this process
    return json.loads((output / "transforms.json").read_text())


def poses_of(transforms: dict) -> np.ndarray:
    return np.array([frame["transform_matrix"] for frame in transforms["frames"]])[:, :3]


def test_export_writes_the_returned_poses_moved_by_the_refinement(tmp_path, single_thread):
    parser = dataclasses.replace(
        demo_parser(num_frames=NUM_FRAMES), pose_noise_degrees=1.0, pose_noise_translation=0.01
    )
    config = tiny_config(tmp_path / "outputs", parser, num_tasks=2, iterations_per_task=4)
    config.pipeline.model = dataclasses.replace(
        config.pipeline.model, camera_optimizer=CameraOptimizerConfig(mode="SO3xR3")
    )
    trainer = train(config)
    transforms = exported(config.get_base_dir() / "config.yml", tmp_path / "refined")

    outputs = trainer.pipeline.datamanager.train_dataparser_outputs
    returned = outputs.transform_poses_to_original_space(outputs.cameras.camera_to_worlds, "opengl").double().numpy()
    assert [frame["file_path"] for frame in transforms["frames"]] == [str(p.resolve()) for p in outputs.image_filenames]
    poses = poses_of(transforms)
    # the demo's box is the metric scene shifted and scaled: a correction turns the rotation and shifts the centre
    train_frames = trainer.pipeline.datamanager.task_split.all_train_frames()
    corrections = trainer.pipeline.model.camera_optimizer(torch.arange(len(train_frames))).detach().double().numpy()
    np.testing.assert_allclose(
        poses[train_frames, :, :3], corrections[:, :, :3] @ returned[train_frames, :, :3], atol=1e-5
    )
    shift = poses[train_frames, :, 3] - returned[train_frames, :, 3]
    np.testing.assert_allclose(shift, corrections[:, :, 3] / outputs.dataparser_scale, atol=1e-5)
    assert np.abs(shift).max() > 0, "the run refined the poses"
    assert transforms["frames"][0]["w"] == 24 and transforms["frames"][0]["fl_x"] > 0

    reread = OrderedCaptureDataParserConfig(data=tmp_path / "refined").setup().get_dataparser_outputs("train")
    assert len(reread.image_filenames) == NUM_FRAMES, "continual-nerfstudio reads the export"


def test_a_run_without_refinement_exports_the_poses_it_was_given(tmp_path, single_thread):
    config = tiny_config(tmp_path / "outputs", demo_parser(num_frames=NUM_FRAMES), num_tasks=2, iterations_per_task=2)
    trainer = train(config)
    transforms = exported(config.get_base_dir() / "config.yml", tmp_path / "exported")
    scene = json.loads(
        (
            trainer.pipeline.datamanager.train_dataparser_outputs.image_filenames[0].parent.parent / "transforms.json"
        ).read_text()
    )
    np.testing.assert_allclose(poses_of(transforms), poses_of(scene), atol=1e-5)
