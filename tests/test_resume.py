"""A run killed in the middle of a task resumes with `--load-dir` and ends as the uninterrupted run does."""

from __future__ import annotations

import re
import shutil
import signal
import subprocess
from pathlib import Path

import pytest
import yaml
from helpers import (
    SUBPROCESS_ENV,
    demo_parser,
    ns_train_command,
    run_ns_train,
    signal_when_saved,
    stopped_run,
    tiny_config,
    train,
)
from nerfstudio.scripts.train import train_loop

from continual_nerf.core.accuracy_matrix import ACCURACY_MATRIX_FILENAME, AccuracyMatrix
from continual_nerf.core.task_split import split_into_tasks

pytestmark = pytest.mark.slow  # trains models, runs subprocesses or a browser

NUM_FRAMES, WIDTH, HEIGHT = 18, 24, 18
NUM_TASKS, ITERATIONS_PER_TASK, STEPS_PER_SAVE = 3, 20, 25
"""Task 2 spans steps 20..39, so the periodic save of step 25 is a checkpoint in the middle of it."""


def demo_scene_copy(folder: Path) -> Path:
    """A private copy of the demo scene, whose images the test may delete."""
    parser = demo_parser(num_frames=NUM_FRAMES, width=WIDTH, height=HEIGHT)
    parser.setup().get_dataparser_outputs("train")  # renders the scene into the shared cache if it is not there yet
    scene = next(parser.data.glob(f"room_{WIDTH}x{HEIGHT}_{NUM_FRAMES}frames_*"))
    shutil.copytree(scene, folder / scene.name)
    return folder


def command(output_dir: Path, data: Path, timestamp: str, *options: str) -> list:
    return ns_train_command(
        output_dir,
        timestamp,
        [
            "--pipeline.datamanager.num-tasks",
            str(NUM_TASKS),
            "--pipeline.datamanager.iterations-per-task",
            str(ITERATIONS_PER_TASK),
            "--steps-per-save",
            str(STEPS_PER_SAVE),
            *options,
        ],
        [
            "continual-demo",
            "--data",
            str(data),
            "--num-frames",
            str(NUM_FRAMES),
            "--width",
            str(WIDTH),
            "--height",
            str(HEIGHT),
        ],
    )


def test_a_run_killed_mid_task_resumes_to_the_uninterrupted_result(tmp_path, single_thread):
    outputs, data = tmp_path / "outputs", demo_scene_copy(tmp_path / "scene")
    killed_dir = outputs / "unnamed" / "continual-ngp" / "killed"
    with (tmp_path / "killed.log").open("w") as log:
        killed = subprocess.Popen(command(outputs, data, "killed"), stdout=log, stderr=log, env=SUBPROCESS_ENV)
        signal_when_saved(killed, killed_dir / "nerfstudio_models" / f"step-{STEPS_PER_SAVE:09d}.ckpt", signal.SIGKILL)
        killed.wait()
    assert killed.returncode == -signal.SIGKILL
    before_kill = AccuracyMatrix.read(killed_dir / ACCURACY_MATRIX_FILENAME)
    assert (before_kill.status, before_kill.finished, len(before_kill.psnr)) == ("training", False, 1), (
        "killed during task 2: the folder says the run did not finish"
    )
    checkpoints = sorted(path.name for path in (killed_dir / "nerfstudio_models").iterdir())
    assert checkpoints == [f"step-{ITERATIONS_PER_TASK - 1:09d}.ckpt", f"step-{STEPS_PER_SAVE:09d}.ckpt"]

    # pixels of a closed task are never needed again: delete task 1's training images before resuming
    for frame in split_into_tasks(NUM_FRAMES, NUM_TASKS, test_interval=8).train_frames[0]:
        next(data.glob(f"*/images/frame_{frame:05d}.png")).unlink()
    resumed = run_ns_train(command(outputs, data, "resumed", "--load-dir", str(killed_dir / "nerfstudio_models")))
    assert resumed.returncode == 0, resumed.stderr[-3000:]
    loaded = killed_dir / "nerfstudio_models" / f"step-{STEPS_PER_SAVE:09d}.ckpt"
    assert f"Resumingfrom{loaded}" in "".join(resumed.stdout.split()), "rich wraps long lines"
    after_resume = AccuracyMatrix.read(killed_dir.with_name("resumed") / ACCURACY_MATRIX_FILENAME)
    assert after_resume.psnr[0] == before_kill.psnr[0], "the row measured before the kill is carried over"

    # the same run without the kill, from the killed run's own config.yml, in-process as ns-train runs it
    config = yaml.load((killed_dir / "config.yml").read_text(), Loader=yaml.Loader)
    config.timestamp = "uninterrupted"
    config.pipeline.datamanager.dataparser.data = demo_parser().data  # the intact scene
    train_loop(local_rank=0, world_size=1, config=config)
    uninterrupted = AccuracyMatrix.read(config.get_base_dir() / ACCURACY_MATRIX_FILENAME)

    assert after_resume.finished and after_resume.status == "finished"
    assert after_resume.steps == uninterrupted.steps == [19, 39, 59]
    pairs = zip(after_resume.psnr, uninterrupted.psnr)
    differences = [abs(a - b) for row_a, row_b in pairs for a, b in zip(row_a, row_b)]
    assert [len(row) for row in after_resume.psnr] == [1, 2, 3] and max(differences) <= 0.3, (
        f"resumed {after_resume.psnr} vs uninterrupted {uninterrupted.psnr}"
    )


def test_a_resumed_run_counts_its_progress_and_eta_to_the_run_s_last_step(tmp_path, capsys, single_thread):
    parser = demo_parser(num_frames=NUM_FRAMES, width=WIDTH, height=HEIGHT)
    stopped = tiny_config(tmp_path / "stopped", parser, num_tasks=2, iterations_per_task=3)
    resumed = tiny_config(tmp_path / "resumed", parser, num_tasks=2, iterations_per_task=3)
    resumed.load_checkpoint = stopped_run(stopped, last_step=2)  # the end of task 1
    resumed.logging.local_writer.enable = True
    resumed.logging.steps_per_log, resumed.logging.local_writer.max_log_size = 1, 0  # every step, one line each
    capsys.readouterr()
    train(resumed)
    shown = re.findall(r"^(\d+) \(([\d.]+)%\)\s+\S+.*?\s{2,}(\S.*?)\s{2,}", capsys.readouterr().out, re.MULTILINE)
    steps = {int(step): float(done) for step, done, _ in shown}
    assert steps[3] == pytest.approx(50.0) and steps[5] == pytest.approx(83.33), "% of the run's 6 steps"
    assert not [eta for _, _, eta in shown if " h" in eta], "no ETA of hours for three steps left"
