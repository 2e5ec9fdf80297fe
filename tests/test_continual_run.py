"""Whole continual runs on the demo scene, through nerfstudio's Trainer, ns-eval and ns-render."""

import json
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from helpers import demo_parser, tiny_config, train

from continual_nerf.checkpoints import WEIGHTS_ONLY
from continual_nerf.core.accuracy_matrix import ACCURACY_MATRIX_FILENAME, AccuracyMatrix

pytestmark = pytest.mark.slow  # trains models, runs subprocesses or a browser


def test_replay_keeps_task_1_that_training_without_replay_forgets(run_dir, capsys):
    parser = demo_parser(num_frames=24, width=32, height=24)
    first_task_psnr = {}
    for replay in (True, False):
        trainer = train(
            tiny_config(run_dir, parser, num_tasks=3, iterations_per_task=80, rays_per_batch=512, replay=replay)
        )
        first_task_psnr[replay] = trainer.pipeline.accuracy.psnr[-1][0]
    margin = first_task_psnr[True] - first_task_psnr[False]
    with capsys.disabled():
        print(
            f"\ntask 1 PSNR after 3 tasks: replay {first_task_psnr[True]:.2f} dB, "
            f"no replay {first_task_psnr[False]:.2f} dB, margin {margin:.2f} dB"
        )
    assert margin > 1.0


@pytest.fixture(scope="module")
def finished_run(tmp_path_factory) -> Path:
    """A 2-task run; returns its run directory (the one holding config.yml)."""
    output = tmp_path_factory.mktemp("finished") / "outputs"
    config = tiny_config(output, demo_parser(num_frames=16), num_tasks=2, iterations_per_task=4)
    train(config)
    return config.get_base_dir()


def test_accuracy_matrix_and_a_checkpoint_per_task_are_written(finished_run):
    matrix = AccuracyMatrix.read(finished_run / ACCURACY_MATRIX_FILENAME)
    assert matrix.finished and matrix.num_tasks == 2
    assert [len(row) for row in matrix.psnr] == [1, 2] and [len(row) for row in matrix.ssim] == [1, 2]
    assert all(5.0 < value < 60.0 for row in matrix.psnr for value in row)
    assert matrix.steps == [3, 7]
    checkpoints = sorted((finished_run / "nerfstudio_models").glob("step-*.ckpt"))
    assert [c.name for c in checkpoints] == ["step-000000003.ckpt", "step-000000007.ckpt"]
    closed, latest = (torch.load(c, map_location="cpu", weights_only=False) for c in checkpoints)
    assert closed[WEIGHTS_ONLY] and not closed["optimizers"], "a closed task's checkpoint keeps the weights only"
    assert not any(key.startswith("replay_oracle.") for key in closed["pipeline"]), "its oracle equals its model"
    assert closed["pipeline"]["_extra_state"]["task"]["current"] == 1, "task 2 was released at that point"
    assert any(key.startswith("replay_oracle.model.") for key in latest["pipeline"]), "the latest one resumes"
    assert set(latest["optimizers"]) == {"proposal_networks", "fields"} and not latest.get(WEIGHTS_ONLY)
    assert (finished_run / "dataparser_transforms.json").exists()


def test_ns_eval_and_ns_render_work_on_the_run(finished_run, tmp_path):
    bin_dir = Path(sys.executable).parent
    output = tmp_path / "eval.json"
    subprocess.run(
        [str(bin_dir / "ns-eval"), "--load-config", str(finished_run / "config.yml"), "--output-path", str(output)],
        check=True,
        capture_output=True,
        text=True,
        timeout=300,
    )
    results = json.loads(output.read_text())["results"]
    assert results["psnr"] > 5.0 and 0.0 < results["ssim"] <= 1.0
    render = subprocess.run(
        [
            str(bin_dir / "ns-render"),
            "dataset",
            "--load-config",
            str(finished_run / "config.yml"),
            "--output-path",
            str(tmp_path / "renders"),
            "--split",
            "train",
            "--rendered-output-names",
            "rgb",
        ],
        check=False,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert render.returncode == 0, render.stderr[-2000:]
    assert len(list((tmp_path / "renders").rglob("*.jpg")) + list((tmp_path / "renders").rglob("*.png"))) == 14, (
        "the 14 training frames"
    )


def test_a_wall_clock_budget_per_task_ends_each_task_and_the_run(run_dir):
    config = tiny_config(run_dir, demo_parser(num_frames=12), num_tasks=2)
    config.pipeline.datamanager.seconds_per_task = 1.0
    trainer = train(config)
    matrix = trainer.pipeline.accuracy
    assert matrix.finished and len(matrix.psnr) == 2
    assert matrix.steps[1] > matrix.steps[0], "task 2 trained for its own second"
    assert trainer.step == matrix.steps[1], "the run ends at its last task's last step"
    assert checkpoint_names(config) == [f"step-{step:09d}.ckpt" for step in matrix.steps], "no checkpoint past it"


def test_a_run_its_tasks_end_before_max_num_iterations_ends_at_its_last_trained_step(run_dir):
    config = tiny_config(run_dir, demo_parser(num_frames=12), num_tasks=2, iterations_per_task=2)
    config.max_num_iterations = 50
    trainer = train(config)
    assert trainer.pipeline.accuracy.steps == [1, 3] and trainer.step == 3
    assert checkpoint_names(config) == ["step-000000001.ckpt", "step-000000003.ckpt"], "none of step 4, never trained"


def checkpoint_names(config) -> list:
    return sorted(path.name for path in config.get_checkpoint_dir().iterdir())
