"""--pipeline.lr-decay-per-task, --pipeline.lr-decay-start, --pipeline.pose-lr-decay-per-task and
--pipeline.pose-refinement-start: learning rates fall over (the end of) each task's budget and restart at the next
task."""

from __future__ import annotations

import pytest
from helpers import demo_parser, tiny_config
from nerfstudio.cameras.camera_optimizers import CameraOptimizerConfig
from nerfstudio.engine.callbacks import TrainingCallbackLocation

from continual_nerf.errors import ContinualConfigError
from continual_nerf.method_configs import CONTINUAL_NGP_INCRE, CONTINUAL_NGP_JOINT, CONTINUAL_NGP_PAPER


def learning_rates(trainer) -> dict:
    return {name: optimizer.param_groups[0]["lr"] for name, optimizer in trainer.optimizers.optimizers.items()}


def run_callbacks(trainer, step: int, location: TrainingCallbackLocation) -> None:
    for callback in trainer.callbacks:
        callback.run_callback_at_location(step, location=location)


def factors_over_two_tasks(config, iterations_per_task: int = 4) -> dict:
    """Each optimizer's learning rate over its configured one, before each step of 2 tasks."""
    config.save_config()
    trainer = config.setup(local_rank=0, world_size=1)
    trainer.setup()
    base = learning_rates(trainer)
    factors = {name: [] for name in base}
    for step in range(2 * iterations_per_task):  # nerfstudio's loop: callbacks before, the iteration, callbacks after
        run_callbacks(trainer, step, TrainingCallbackLocation.BEFORE_TRAIN_ITERATION)
        for name, lr in learning_rates(trainer).items():
            factors[name].append(lr / base[name])
        trainer.train_iteration(step)
        run_callbacks(trainer, step, TrainingCallbackLocation.AFTER_TRAIN_ITERATION)
    return factors


def test_learning_rates_decay_within_a_task_and_restart_at_the_next(run_dir):
    config = tiny_config(run_dir, demo_parser(), num_tasks=2, iterations_per_task=4)
    config.pipeline.lr_decay_per_task, config.pipeline.lr_decay_start = 0.1, 0.0
    expected = [0.1 ** (i / 4) for i in range(4)] * 2
    for factors in factors_over_two_tasks(config).values():
        assert factors == pytest.approx(expected), "0.1 ** progress within each task, 1 again at task 2"


def test_learning_rates_hold_until_the_decay_start_then_fall_to_the_same_factor(run_dir):
    config = tiny_config(run_dir, demo_parser(), num_tasks=2, iterations_per_task=4)
    config.pipeline.lr_decay_per_task = 0.1
    config.pipeline.lr_decay_start = 0.5
    expected = [1.0, 1.0, 1.0, 0.1**0.5] * 2
    for factors in factors_over_two_tasks(config).values():
        assert factors == pytest.approx(expected), "constant for the first half of each task, then 0.1 ** (2 p - 1)"


def test_continual_ngp_lowers_its_rates_over_each_tasks_last_quarter_and_the_papers_recipes_do_not(run_dir):
    config = tiny_config(run_dir, demo_parser(), num_tasks=2, iterations_per_task=8)
    for factors in factors_over_two_tasks(config, iterations_per_task=8).values():
        assert factors == pytest.approx([1.0] * 7 + [0.1**0.5] + [1.0] * 7 + [0.1**0.5])
    for paper in (CONTINUAL_NGP_PAPER, CONTINUAL_NGP_INCRE, CONTINUAL_NGP_JOINT):
        assert paper.pipeline.lr_decay_per_task == 1.0, f"{paper.method_name}: the paper's constant rates"


def test_pose_corrections_learning_rate_decays_on_its_own(run_dir):
    config = tiny_config(run_dir, demo_parser(), num_tasks=2, iterations_per_task=4)
    config.pipeline.model.camera_optimizer = CameraOptimizerConfig(mode="SO3xR3")
    config.pipeline.lr_decay_per_task = 1.0
    factors = factors_over_two_tasks(config)
    assert factors.pop("camera_opt") == pytest.approx([0.1 ** (i / 4) for i in range(4)] * 2), "the default 0.1"
    assert all(values == [1.0] * 8 for values in factors.values()), "the others as --pipeline.lr-decay-per-task says"


def test_pose_corrections_wait_for_the_refinement_start_then_fall_over_the_rest_of_the_task(run_dir):
    config = tiny_config(run_dir, demo_parser(), num_tasks=2, iterations_per_task=4)
    config.pipeline.model.camera_optimizer = CameraOptimizerConfig(mode="SO3xR3")
    config.pipeline.lr_decay_per_task, config.pipeline.pose_refinement_start = 1.0, 0.5
    factors = factors_over_two_tasks(config)
    assert factors.pop("camera_opt") == pytest.approx([0.0, 0.0, 1.0, 0.1**0.5] * 2)
    assert all(values == [1.0] * 8 for values in factors.values()), "the field learns from each task's start"


def test_a_decay_outside_0_1_is_a_one_line_error(run_dir):
    config = tiny_config(run_dir, demo_parser())
    config.pipeline.lr_decay_per_task = 0.0
    with pytest.raises(ContinualConfigError, match=r"--pipeline.lr-decay-per-task must be in \(0, 1\], got 0.0"):
        config.pipeline.setup(device="cpu")


@pytest.mark.parametrize("option", ["lr_decay_start", "pose_refinement_start"])
def test_a_start_outside_0_1_is_a_one_line_error(run_dir, option):
    config = tiny_config(run_dir, demo_parser())
    setattr(config.pipeline, option, 1.0)
    flag = "--pipeline." + option.replace("_", "-")
    with pytest.raises(ContinualConfigError, match=rf"{flag} must be in \[0, 1\), got 1.0"):
        config.pipeline.setup(device="cpu")
