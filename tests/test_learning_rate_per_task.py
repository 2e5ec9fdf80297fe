"""--pipeline.lr-decay-per-task: learning rates fall over each task's budget and restart at the next task."""

from __future__ import annotations

import pytest
from helpers import demo_parser, tiny_config
from nerfstudio.engine.callbacks import TrainingCallbackLocation

from continual_nerf.errors import ContinualConfigError


def learning_rates(trainer) -> list:
    return [group["lr"] for optimizer in trainer.optimizers.optimizers.values() for group in optimizer.param_groups]


def run_callbacks(trainer, step: int, location: TrainingCallbackLocation) -> None:
    for callback in trainer.callbacks:
        callback.run_callback_at_location(step, location=location)


def test_learning_rates_decay_within_a_task_and_restart_at_the_next(run_dir):
    config = tiny_config(run_dir, demo_parser(), num_tasks=2, iterations_per_task=4)
    config.pipeline.lr_decay_per_task = 0.1
    config.save_config()
    trainer = config.setup(local_rank=0, world_size=1)
    trainer.setup()
    base = learning_rates(trainer)
    factors = []
    for step in range(8):  # nerfstudio's loop: callbacks before, the iteration, callbacks after
        run_callbacks(trainer, step, TrainingCallbackLocation.BEFORE_TRAIN_ITERATION)
        factors.append([lr / lr_0 for lr, lr_0 in zip(learning_rates(trainer), base)])
        trainer.train_iteration(step)
        run_callbacks(trainer, step, TrainingCallbackLocation.AFTER_TRAIN_ITERATION)
    expected = [0.1 ** (i / 4) for i in range(4)] * 2
    for factor, value in zip(factors, expected):
        assert factor == pytest.approx([value] * len(base)), "0.1 ** progress within each task, 1 again at task 2"


def test_a_decay_outside_0_1_is_a_one_line_error(run_dir):
    config = tiny_config(run_dir, demo_parser())
    config.pipeline.lr_decay_per_task = 0.0
    with pytest.raises(ContinualConfigError, match=r"--pipeline.lr-decay-per-task must be in \(0, 1\], got 0.0"):
        config.pipeline.setup(device="cpu")
