"""What python -m continual_nerf.bench.real_capture measures: pose errors after the rigid motion that fits best, and\nthe bound of colour transforms at the true exposure."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from helpers import DEMO_CACHE, demo_parser, rotation
from PIL import Image

from continual_nerf.bench.grid import Setting
from continual_nerf.bench.real_capture import (
    FEATURES,
    TRUE_EXPOSURE,
    RealCaptureBenchmark,
    fitted_onto,
    hold_true_exposure,
    recipe,
    reports_pose_errors,
    rms_errors,
)
from continual_nerf.core.ngp_model import COLOR_TRANSFORM_GROUP
from continual_nerf.dataparsers import demo_capture
from continual_nerf.method_configs import CONTINUAL_NGP
from continual_nerf.recipes import set_up_like_ns_train


def config_of(bench: RealCaptureBenchmark, capture: str, feature: str, scene: str = "room"):
    (run,) = bench.runs(scene, Setting.parse(bench.setting), [recipe(capture, feature)])
    return bench.config(run)


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
    assert reports_pose_errors(config_of(bench, capture, feature)) == reported


def test_every_runs_options_reach_every_run(tmp_path):
    bench = RealCaptureBenchmark(
        data=tmp_path / "data",
        output_dir=tmp_path / "bench",
        options=("--machine.seed 7 --optimizers.camera-opt.optimizer.lr 1e-4",),
    )
    config = config_of(bench, "poses off 1 deg, 1 %", "pose refinement")
    assert config.machine.seed == 7
    assert config.optimizers["camera_opt"]["optimizer"].lr == 1e-4
    assert config.optimizers["fields"]["optimizer"].lr == CONTINUAL_NGP.optimizers["fields"]["optimizer"].lr


@pytest.mark.parametrize("feature", list(FEATURES))
def test_every_feature_parses_into_a_config_the_run_validates(tmp_path, feature):
    bench = RealCaptureBenchmark(data=tmp_path / "data", output_dir=tmp_path / "bench")
    config = config_of(bench, "exposure +-30 %", feature)
    config.pipeline.validate()
    model = config.pipeline.model
    assert model.refines_poses == ("pose refinement" in feature)
    assert config.pipeline.pose_refinement_start == (0.5 if feature.endswith("from mid-task") else 0.0)
    assert model.use_color_transform == ("colour transform" in feature)
    assert model.use_appearance_embedding == ("codes" in feature)
    transform_rate = config.optimizers[COLOR_TRANSFORM_GROUP]["optimizer"].lr
    assert (transform_rate == 0.0) == (feature == TRUE_EXPOSURE), "the bound's transforms stay at the recorded gains"
    demo = config.pipeline.datamanager.dataparser
    assert demo.exposure_strength == 0.3 and demo.exposure_segments == 5, "a jump at each of the 5 tasks' boundaries"


def test_the_bound_holds_every_transform_at_the_gains_its_frame_was_recorded_with(tmp_path, single_thread):
    bench = RealCaptureBenchmark(
        data=DEMO_CACHE,
        output_dir=tmp_path,
        setting="2x3",
        rays_per_batch=64,
        options=("--pipeline.model.num-levels 4 --pipeline.model.log2-hashmap-size 12 continual-demo --num-frames 16 "
                 "--width 24 --height 18",),
    )  # fmt: skip
    config = config_of(bench, "exposure +-30 %", TRUE_EXPOSURE)
    exposed = config.pipeline.datamanager.dataparser
    assert exposed.exposure_segments == 2
    config.save_config()
    trainer = set_up_like_ns_train(config)
    hold_true_exposure(trainer)
    trainer.train()
    transforms = trainer.pipeline.model.color_transforms.transforms.detach()
    assert torch.equal(transforms[:, :, 3], torch.zeros(len(transforms), 3)), "gains, no offsets"
    gains = transforms[:, :, :3].diagonal(dim1=1, dim2=2)
    assert gains.std(dim=0).min() > 0.01, "the frames were recorded at different gains and keep them after training"
    clean = demo_parser(num_frames=16).setup().get_dataparser_outputs("train").image_filenames
    recorded = exposed.setup().get_dataparser_outputs("train").image_filenames
    frames = trainer.pipeline.datamanager.task_split.all_train_frames()
    for row in (0, len(frames) - 1):  # the first and last training frames: a gain of each task
        exact = np.asarray(Image.open(clean[frames[row]]), dtype=np.float64)[..., :3] / 255
        seen = np.asarray(Image.open(recorded[frames[row]]), dtype=np.float64)[..., :3] / 255
        unclipped = (seen < 0.98) & (exact > 0.1)
        ratios = [np.median(seen[..., c][unclipped[..., c]] / exact[..., c][unclipped[..., c]]) for c in range(3)]
        np.testing.assert_allclose(ratios, gains[row].numpy(), rtol=0.02)


def test_only_the_chosen_captures_and_features_train_beside_the_reference(tmp_path):
    bench = RealCaptureBenchmark(
        data=tmp_path / "data",
        output_dir=tmp_path / "bench",
        captures=("poses off 1 deg, 1 %",),
        features=("pose refinement",),
    )
    assert bench.pairs("room") == [("clean", "off"), ("poses off 1 deg, 1 %", "pose refinement")]


def test_an_unknown_capture_is_refused_in_one_line(tmp_path):
    bench = RealCaptureBenchmark(data=tmp_path / "data", output_dir=tmp_path / "bench", captures=("fog",))
    with pytest.raises(SystemExit, match="--captures: unknown fog"):
        bench.main()
