"""The same seed gives the same task split and, on CPU, the same training losses."""

from __future__ import annotations

import dataclasses
from typing import List, Tuple

import numpy as np
import pytest
import torch
from helpers import demo_parser, tiny_config
from nerfstudio.scripts.train import train_loop

from continual_nerf.core.continual_trainer import ContinualTrainer
from continual_nerf.core.task_split import TaskSplit

pytestmark = pytest.mark.slow  # trains models, runs subprocesses or a browser


@pytest.fixture(autouse=True)
def restore_algorithms():
    """--deterministic sets process-wide state; later tests must not run at its speed."""
    yield
    torch.use_deterministic_algorithms(False)


def first_losses(run_dir, monkeypatch, seed: int, steps: int = 20) -> Tuple[TaskSplit, List[float]]:
    """Task split and the losses of all `steps` steps (2 tasks, the second one replaying) of a --deterministic run."""
    config = tiny_config(run_dir, demo_parser(num_frames=16), num_tasks=2, iterations_per_task=steps // 2)
    config.machine = dataclasses.replace(config.machine, seed=seed)  # the method's MachineConfig is shared
    config.deterministic = True
    config.timestamp = f"seed{seed}-run{len(list(run_dir.glob('*/*/*')))}"
    trainers, losses = [], []
    train_iteration = ContinualTrainer.train_iteration

    def recording(trainer: ContinualTrainer, step: int):
        loss, loss_dict, metrics_dict = train_iteration(trainer, step)
        trainers.append(trainer)
        losses.append(float(loss))
        return loss, loss_dict, metrics_dict

    with monkeypatch.context() as patch:
        patch.setattr(ContinualTrainer, "train_iteration", recording)
        train_loop(local_rank=0, world_size=1, config=config)  # ns-train's function: seeds python, numpy and torch
    return trainers[0].pipeline.datamanager.task_split, losses


def test_same_seed_same_split_and_losses_other_seed_other_losses(run_dir, monkeypatch, single_thread):
    split, losses = first_losses(run_dir, monkeypatch, seed=42)
    split_again, losses_again = first_losses(run_dir, monkeypatch, seed=42)
    _, other_seed_losses = first_losses(run_dir, monkeypatch, seed=43, steps=2)
    assert len(losses) == 20
    assert all(
        np.array_equal(a, b)
        for a, b in zip(split.train_frames + split.test_frames, split_again.train_frames + split_again.test_frames)
    )
    assert losses == losses_again, "bit-identical on CPU"
    assert abs(other_seed_losses[0] - losses[0]) > 1e-3 * losses[0], "the seed does drive initialisation and rays"
