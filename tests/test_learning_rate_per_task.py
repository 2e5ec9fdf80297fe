"""--pipeline.lr-decay-per-task and --pipeline.pose-lr-decay-per-task: learning rates fall over each task's budget and
restart at the next task."""

from __future__ import annotations

import pytest
from helpers import demo_parser, tiny_config
from nerfstudio.cameras.camera_optimizers import CameraOptimizerConfig
from nerfstudio.engine.callbacks import TrainingCallbackLocation

from continual_nerf.errors import ContinualConfigError


def learning_rates(trainer) -> dict:
    return {name: optimizer.param_groups[0]["lr"] for name, optimizer in trainer.optimizers.optimizers.items()}


def run_callbacks(trainer, step: int, location: TrainingCallbackLocation) -> None:
    for callback in trainer.callbacks:
        callback.run_callback_at_location(step, location=location)


def factors_over_two_tasks(config) -> dict:
    """Each optimizer's learning rate over its configured one, before each of the 8 steps of 2 tasks."""
    config.save_config()
    trainer = config.setup(local_rank=0, world_size=1)
    trainer.setup()
    base = learning_rates(trainer)
    factors = {name: [] for name in base}
    for step in range(8):  # nerfstudio's loop: callbacks before, the iteration, callbacks after
        run_callbacks(trainer, step, TrainingCallbackLocation.BEFORE_TRAIN_ITERATION)
        for name, lr in learning_rates(trainer).items():
            factors[name].append(lr / base[name])
        trainer.train_iteration(step)
        run_callbacks(trainer, step, TrainingCallbackLocation.AFTER_TRAIN_ITERATION)
    return factors


def test_learning_rates_decay_within_a_task_and_restart_at_the_next(run_dir):
    config = tiny_config(run_dir, demo_parser(), num_tasks=2, iterations_per_task=4)
    config.pipeline.lr_decay_per_task = 0.1
    expected = [0.1 ** (i / 4) for i in range(4)] * 2
    for factors in factors_over_two_tasks(config).values():
        assert factors == pytest.approx(expected), "0.1 ** progress within each task, 1 again at task 2"


def test_pose_corrections_learning_rate_decays_on_its_own(run_dir):
    config = tiny_config(run_dir, demo_parser(), num_tasks=2, iterations_per_task=4)
    config.pipeline.model.camera_optimizer = CameraOptimizerConfig(mode="SO3xR3")
    factors = factors_over_two_tasks(config)
    assert factors.pop("camera_opt") == pytest.approx([0.1 ** (i / 4) for i in range(4)] * 2), "the default 0.1"
    assert all(values == [1.0] * 8 for values in factors.values()), "the others stay constant (the paper)"


def test_a_decay_outside_0_1_is_a_one_line_error(run_dir):
    config = tiny_config(run_dir, demo_parser())
    config.pipeline.lr_decay_per_task = 0.0
    with pytest.raises(ContinualConfigError, match=r"--pipeline.lr-decay-per-task must be in \(0, 1\], got 0.0"):
        config.pipeline.setup(device="cpu")
