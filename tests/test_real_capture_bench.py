"""The pose errors python -m continual_nerf.bench.real_capture reports: after the rigid motion that fits best."""

from __future__ import annotations

import numpy as np
import pytest
from helpers import rotation

from continual_nerf.bench.real_capture import (
    FEATURES,
    RealCaptureBenchmark,
    fitted_onto,
    reports_pose_errors,
    rms_errors,
)
from continual_nerf.dataparsers import demo_capture


def trajectory(count: int = 30) -> np.ndarray:
    rng = np.random.default_rng(0)
    poses = np.zeros((count, 3, 4))
    for i in range(count):
        poses[i, :, :3] = rotation(rng.normal(size=3), rng.uniform(0, np.pi))
        poses[i, :, 3] = [0.1 * i, np.sin(i / 5), 0.2 * np.cos(i / 3)]
    return poses


def test_a_trajectory_moved_as_a_whole_has_no_error():
    true = trajectory()
    moved = true.copy()
    turn = rotation(np.array([1.0, 2.0, 0.5]), 0.7)
    moved[:, :, :3] = turn @ true[:, :, :3]
    moved[:, :, 3] = true[:, :, 3] @ turn.T + [3.0, -1.0, 2.0]
    np.testing.assert_allclose(fitted_onto(moved, true), true, atol=1e-9)
    assert rms_errors(moved, true, length=1.0) == pytest.approx((0.0, 0.0), abs=1e-5)


def test_errors_within_the_trajectory_remain():
    true = trajectory()
    rng = np.random.default_rng(1)
    noisy = demo_capture.noisy_poses(true, np.arange(len(true)), 2.0, 0.05, rng)
    length = demo_capture.trajectory_length(true[:, :, 3])
    degrees, percent = rms_errors(noisy, true, length)
    assert 0.3 < degrees < 3.0 and 0.5 < percent < 6.0, "the best fit removes only what the whole trajectory shares"


@pytest.mark.parametrize(
    ("capture", "feature", "reported"),
    [
        ("clean", "off", False),
        ("clean", "pose refinement", True),
        ("poses off 1 deg, 1 %", "off", True),
        ("exposure +-30 %", "codes per image", False),
    ],
)
def test_pose_errors_are_reported_for_noisy_poses_and_for_every_refining_run(tmp_path, capture, feature, reported):
    bench = RealCaptureBenchmark(data=tmp_path / "data", output_dir=tmp_path / "bench")
    demo = bench.demo("room", capture)
    assert reports_pose_errors(demo, bench.config(demo, feature, tmp_path / "run")) == reported


def test_every_run_trains_with_the_chosen_seed(tmp_path):
    bench = RealCaptureBenchmark(data=tmp_path / "data", output_dir=tmp_path / "bench", seed=7)
    demo = bench.demo("room", "clean")
    assert bench.config(demo, "off", tmp_path / "run").machine.seed == 7


@pytest.mark.parametrize("feature", list(FEATURES))
def test_every_feature_sets_model_options_the_run_validates(tmp_path, feature):
    bench = RealCaptureBenchmark(data=tmp_path / "data", output_dir=tmp_path / "bench")
    config = bench.config(bench.demo("room", "clean"), feature, tmp_path / "run")
    config.pipeline.validate()
    model = config.pipeline.model
    assert all(getattr(model, option) == value for option, value in FEATURES[feature].items())
