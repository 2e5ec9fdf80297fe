"""continual-ngp-depth: the open task's depth in its batches and nowhere else, depth-nerfacto's loss on valid depth
only, depth kept by a replay buffer or distilled from the oracle, and a resumed run that ends as the uninterrupted
one."""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import List

import numpy as np
import pytest
import torch
from helpers import Killed, demo_parser, kill_in_the_middle_of_save, tiny_config, train
from nerfstudio.data.scene_box import SceneBox
from nerfstudio.scripts.train import train_loop

from continual_nerf.compilation import random_rays
from continual_nerf.core import depth_maps
from continual_nerf.core.accuracy_matrix import ACCURACY_MATRIX_FILENAME, AccuracyMatrix
from continual_nerf.core.continual_dataset import ClosedTaskError
from continual_nerf.core.continual_trainer import ContinualTrainer, ContinualTrainerConfig
from continual_nerf.core.depth_maps import DEPTH_KEY, DIRECTIONS_NORM
from continual_nerf.core.depth_model import ContinualNGPDepthModelConfig
from continual_nerf.core.distillation_loss import REPLAY_SKIPPED
from continual_nerf.method_configs import CONTINUAL_NGP_DEPTH
from continual_nerf.recipes import small_model


def depth_config(run_dir: Path, num_tasks: int = 3, iterations_per_task: int = 3, **model) -> ContinualTrainerConfig:
    config = tiny_config(
        run_dir, demo_parser(num_frames=18), num_tasks, iterations_per_task, method=CONTINUAL_NGP_DEPTH
    )
    config.pipeline.model = dataclasses.replace(config.pipeline.model, **model)
    return config


def set_up(config: ContinualTrainerConfig) -> ContinualTrainer:
    trainer = config.setup(local_rank=0, world_size=1)
    trainer.setup()
    return trainer


def test_open_task_rays_carry_their_pixels_depth_and_replayed_rays_none(run_dir):
    trainer = set_up(depth_config(run_dir))
    datamanager = trainer.pipeline.datamanager
    dataset = datamanager.train_dataset
    assert dataset.depth_maps is not None
    for task in range(datamanager.num_tasks):
        _, batch = datamanager.next_train(0)
        own = ~batch["is_replay"]
        for (frame, y, x), depth in zip(batch["indices"][own].tolist(), batch[DEPTH_KEY][own, 0]):
            assert depth == dataset.depth_maps.read(frame)[y, x] > 0, "the depth of the ray's pixel, scene units"
        assert (batch[DEPTH_KEY][batch["is_replay"]] == 0).all(), "replayed rays carry no depth target"
        assert task == 0 or batch["is_replay"].any()
        for other in set(range(datamanager.num_tasks)) - {task}:
            with pytest.raises(ClosedTaskError, match=f"belongs to task {other + 1}"):
                dataset.get_depth(int(dataset.frames_of_task(other)[0]))
        if task + 1 < datamanager.num_tasks:
            trainer.pipeline.open_next_task()


def test_colour_only_methods_read_no_training_depth(run_dir, monkeypatch):
    reads: List[Path] = []
    real_read = depth_maps.read_depth_file
    monkeypatch.setattr(depth_maps, "read_depth_file", lambda path: reads.append(path) or real_read(path))
    trainer = train(tiny_config(run_dir, demo_parser(num_frames=18), num_tasks=2))
    test_files = set(trainer.pipeline.datamanager.eval_dataset.depth_maps.filenames)
    assert reads and set(reads) <= test_files, "continual-ngp reads the test frames' depth, to measure it, only"
    assert trainer.pipeline.accuracy.depth_abs_rel, "and the accuracy matrix has its depth errors"
    metrics = trainer.pipeline.get_average_eval_image_metrics()  # what ns-eval reports
    assert np.isfinite([metrics["depth_abs_rel"], metrics["depth_rmse"], metrics["psnr"]]).all()
    assert metrics["depth_abs_rel"] == pytest.approx(trainer.pipeline.accuracy.mean_depth_abs_rel[-1], rel=1e-4)


def test_a_closed_tasks_depth_maps_are_never_read_again(run_dir, monkeypatch):
    reads: List[Path] = []
    real_read = depth_maps.read_depth_file
    monkeypatch.setattr(depth_maps, "read_depth_file", lambda path: reads.append(path) or real_read(path))
    trainer = train(depth_config(run_dir, num_tasks=3, iterations_per_task=2))
    dataset = trainer.pipeline.datamanager.train_dataset
    assert dataset.depth_maps is not None
    files_of_task = [
        {dataset.depth_maps.filenames[int(frame)] for frame in dataset.frames_of_task(task)} for task in range(3)
    ]
    train_reads = [path for path in reads if any(path in files for files in files_of_task)]
    task_of_read = [next(task for task, files in enumerate(files_of_task) if path in files) for path in train_reads]
    assert task_of_read == sorted(task_of_read), "a task's depth maps are read when it opens, never after it closed"
    assert sorted(train_reads) == sorted(path for files in files_of_task for path in files), "each once"


def test_invalid_depth_pixels_never_contribute_to_the_loss():
    config = small_model(ContinualNGPDepthModelConfig(compile=False))
    model = config.setup(scene_box=SceneBox(aabb=torch.tensor([[-1.0] * 3, [1.0] * 3])), num_train_data=1)
    model.train()
    torch.manual_seed(0)
    rays = random_rays(model, 64)
    rays.metadata[DIRECTIONS_NORM] = 1 + 0.3 * torch.rand(64, 1)  # z-depth to distance along the ray, as cameras give
    outputs = model(rays)
    depth = torch.rand(64, 1) + 0.2
    invalid = torch.arange(64) % 3 == 0  # pixels a sensor left without depth, and replayed rays: depth 0
    depth[invalid] = 0.0
    batch = {"image": torch.rand(64, 3), DEPTH_KEY: depth}
    loss = model.get_loss_dict(outputs, batch, model.get_metrics_dict(outputs, batch))["depth_loss"]
    gradients = torch.autograd.grad(loss, outputs["weights_list"])
    for gradient in gradients:
        assert (gradient[invalid] == 0).all(), "no gradient reaches a ray without depth"
        assert (gradient[~invalid].abs().sum(dim=(1, 2)) > 0).all(), "every ray with depth is pulled"


def test_the_replay_buffer_keeps_depth_with_its_pixels(run_dir):
    config = depth_config(run_dir)
    config.pipeline.datamanager = dataclasses.replace(
        config.pipeline.datamanager, replay_buffer_fraction=0.5, replay_buffer_share=1.0
    )
    trainer = set_up(config)
    pipeline = trainer.pipeline
    datamanager = pipeline.datamanager
    datamanager.next_train(0)  # opens task 1
    pipeline.open_next_task()
    assert pipeline.replay_buffer.depth is not None and len(pipeline.replay_buffer.depth) == len(pipeline.replay_buffer)
    _, batch = datamanager.next_train(0)
    dataset = datamanager.train_dataset
    stored = dataset.task_of_frame[batch["indices"][:, 0]] == 0
    assert stored.any() and not batch["is_replay"].any(), "every replayed ray comes from the buffer"
    assert dataset.depth_maps is not None
    for (frame, y, x), depth in zip(batch["indices"][stored].tolist(), batch[DEPTH_KEY][stored, 0]):
        assert depth == dataset.depth_maps.read(frame)[y, x] > 0, "the stored pixel's depth, kept when task 1 closed"


def test_replayed_rays_take_the_oracles_depth_when_it_is_distilled(run_dir):
    trainer = set_up(depth_config(run_dir, distill_replay_depth=True))
    pipeline = trainer.pipeline
    pipeline.datamanager.next_train(0)
    pipeline.open_next_task()
    ray_bundle, batch = pipeline.datamanager.next_train(0)
    torch.manual_seed(0)
    pipeline.add_replay_targets(ray_bundle, batch)
    replay = batch["is_replay"]
    torch.manual_seed(0)  # the oracle samples its rays as training does: jittered
    colour, depth = pipeline.replay_oracle.render_with_depth(ray_bundle[replay])
    assert torch.allclose(batch["image"][replay], colour, atol=1e-6)
    assert torch.allclose(batch[DEPTH_KEY][replay], depth, atol=1e-6) and (depth > 0).any()


class HalfChanged:
    """A change guard's view of the open task that sees every other ray cross a change."""

    def crosses_change(self, origins: torch.Tensor, directions: torch.Tensor, distances: torch.Tensor) -> torch.Tensor:
        return torch.arange(len(origins)) % 2 == 0


def test_replayed_rays_the_change_guard_skips_take_no_depth_target(run_dir, monkeypatch):
    trainer = set_up(depth_config(run_dir, distill_replay_depth=True))
    pipeline = trainer.pipeline
    pipeline.config.change_guard = "every-task"
    pipeline.datamanager.next_train(0)
    pipeline.open_next_task()
    monkeypatch.setattr(pipeline, "_open_task_view", HalfChanged)
    ray_bundle, batch = pipeline.datamanager.next_train(0)
    torch.manual_seed(0)
    pipeline.add_replay_targets(ray_bundle, batch)
    replay, skipped = batch["is_replay"], batch[REPLAY_SKIPPED]
    kept = ~skipped[replay]
    assert kept.any() and not kept.all()
    torch.manual_seed(0)
    _, depth = pipeline.replay_oracle.render_with_depth(ray_bundle[replay])
    assert torch.allclose(batch[DEPTH_KEY][replay][kept], depth[kept], atol=1e-6)
    assert bool((batch[DEPTH_KEY][skipped] == 0).all()), "a surface an open-task frame sees changed: no depth target"


@pytest.mark.slow
def test_a_depth_run_killed_mid_task_resumes_to_the_uninterrupted_result(run_dir, monkeypatch, single_thread):
    def config(timestamp: str) -> ContinualTrainerConfig:
        config = depth_config(run_dir, num_tasks=3, iterations_per_task=4, should_decay_sigma=True)
        config.pipeline.datamanager = dataclasses.replace(config.pipeline.datamanager, replay_buffer_fraction=0.2)
        config.timestamp, config.steps_per_save = timestamp, 5  # saves: steps 3 (task end), 5 (mid task 2), 7, ...
        config.save_config()
        return config

    def run(config: ContinualTrainerConfig) -> AccuracyMatrix:
        train_loop(local_rank=0, world_size=1, config=config)
        return AccuracyMatrix.read(config.get_base_dir() / ACCURACY_MATRIX_FILENAME)

    uninterrupted = run(config("uninterrupted"))
    killed = config("killed")
    with monkeypatch.context() as patch:
        kill_in_the_middle_of_save(patch, save_number=3)  # the save of step 7: step 5's is the last complete one
        with pytest.raises(Killed):
            train_loop(local_rank=0, world_size=1, config=killed)
    checkpoint = killed.get_checkpoint_dir() / "step-000000005.ckpt"
    state = torch.load(checkpoint, map_location="cpu", weights_only=True)
    assert state["pipeline"]["_extra_state"]["task"]["current"] == 1, "killed in the middle of task 2"
    sigma = state["pipeline"]["_model._extra_state"]["depth_sigma"]
    assert sigma < ContinualNGPDepthModelConfig().starting_depth_sigma, "the sigma schedule's state is saved"

    resumed = config("resumed")
    resumed.load_dir = killed.get_checkpoint_dir()
    matrix = run(resumed)
    assert matrix.steps == uninterrupted.steps == [3, 7, 11]
    assert matrix.psnr == uninterrupted.psnr and matrix.depth_abs_rel == uninterrupted.depth_abs_rel
    assert matrix.depth_rmse == uninterrupted.depth_rmse and len(matrix.depth_abs_rel) == 3
    assert np.isfinite(np.array(matrix.mean_depth_abs_rel, dtype=float)).all()
