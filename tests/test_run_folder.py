"""A run folder belongs to one run at a time: a second start into it fails with one line, a killed run's claim is
taken over."""

from __future__ import annotations

import errno
import os
import subprocess
import sys
from pathlib import Path

import pytest
import yaml
from helpers import SUBPROCESS_ENV, demo_parser, ns_train_command, tiny_config

from continual_nerf import run_lock
from continual_nerf.core.accuracy_matrix import ACCURACY_MATRIX_FILENAME, AccuracyMatrix
from continual_nerf.core.continual_trainer import ContinualTrainerConfig
from continual_nerf.errors import ContinualConfigError
from continual_nerf.run_lock import LOCK_NAME, claim_run_folder, release_run_folder

HOLD = (
    "import sys; from pathlib import Path; from continual_nerf.run_lock import claim_run_folder; "
    "claim_run_folder(Path(sys.argv[1])); print('held', flush=True); sys.stdin.read()"
)
"""A process that claims a run folder and holds it until its stdin closes (or it is killed)."""


def run_config(run_dir: Path) -> ContinualTrainerConfig:
    config = tiny_config(run_dir, demo_parser(num_frames=12), num_tasks=2, iterations_per_task=2)
    config.timestamp = "shared"
    return config


def holder_of(folder: Path) -> subprocess.Popen:
    holder = subprocess.Popen(
        [sys.executable, "-c", HOLD, str(folder)], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True
    )
    assert holder.stdout is not None and holder.stdout.readline() == "held\n"
    return holder


@pytest.mark.slow  # starts a subprocess, which imports no more than the lock's module
def test_a_folder_a_living_run_holds_refuses_a_start_and_a_killed_runs_claim_is_taken_over(run_dir, capsys):
    config = run_config(run_dir)
    folder = config.get_base_dir()
    holder = holder_of(folder)
    with pytest.raises(SystemExit) as exit_info:
        config.save_config()
    assert exit_info.value.code == (
        f"continual-ngp: error: {folder} is in use by another run (process {holder.pid}); choose another --timestamp "
        "or --experiment-name, or wait for that run to end"
    )
    assert not (folder / "config.yml").exists()

    holder.kill()  # as SIGKILL leaves it: the lock file stays, its lock is gone with the process
    holder.wait()
    assert (folder / LOCK_NAME).read_text() == f"{holder.pid}\n"
    capsys.readouterr()
    config.save_config()
    assert f"{folder}: process {holder.pid}, which held it, is no longer running" in capsys.readouterr().out
    assert (folder / LOCK_NAME).read_text() == f"{os.getpid()}\n" and (folder / "config.yml").exists()
    release_run_folder(folder)
    assert not (folder / LOCK_NAME).exists(), "released when the run ends"


@pytest.mark.parametrize("holder_alive", [True, False])
def test_without_file_locks_the_recorded_pid_decides(tmp_path, monkeypatch, holder_alive):
    """Some network file systems refuse flock: then the PID the lock file records is checked."""

    def no_locks(descriptor: int, operation: int) -> None:
        raise OSError(errno.ENOLCK, os.strerror(errno.ENOLCK))

    monkeypatch.setattr(run_lock.fcntl, "flock", no_locks)
    other = subprocess.Popen(["true"]) if not holder_alive else None
    if other is not None:
        other.wait()
    pid = os.getppid() if holder_alive else other.pid
    (tmp_path / LOCK_NAME).write_text(f"{pid}\n")
    if holder_alive:
        with pytest.raises(ContinualConfigError, match=f"is in use by another run \\(process {pid}\\)"):
            claim_run_folder(tmp_path)
    else:
        assert claim_run_folder(tmp_path) == pid
        release_run_folder(tmp_path)


@pytest.mark.slow
def test_two_ns_train_started_at_once_into_one_folder_leave_one_runs_results(tmp_path):
    outputs = tmp_path / "outputs"
    demo = ["continual-demo", "--data", str(demo_parser().data), "--num-frames", "12"]
    budgets = {"a": "2", "b": "3"}
    two_tasks = ["--pipeline.datamanager.num-tasks", "2"]
    processes = {
        name: subprocess.Popen(
            ns_train_command(
                outputs, "shared", [*two_tasks, "--pipeline.datamanager.iterations-per-task", budget], demo
            ),
            stdout=subprocess.DEVNULL,
            stderr=subprocess.PIPE,
            text=True,
            env=SUBPROCESS_ENV,
        )
        for name, budget in budgets.items()
    }
    results = {name: (process.wait(timeout=600), process.stderr.read()) for name, process in processes.items()}
    assert sorted(code for code, _ in results.values()) == [0, 1], results
    winner = next(name for name, (code, _) in results.items() if code == 0)
    loser_line = next(stderr for code, stderr in results.values() if code != 0).strip().splitlines()[-1]
    folder = outputs / "unnamed" / "continual-ngp" / "shared"
    # started at once, the second claim meets the first; started apart, it meets a finished run
    assert loser_line.startswith(f"continual-ngp: error: {folder} ")
    assert "is in use by another run (process " in loser_line or "already holds a run" in loser_line
    config = yaml.load((folder / "config.yml").read_text(), Loader=yaml.Loader)
    assert config.pipeline.datamanager.iterations_per_task == int(budgets[winner])
    steps = AccuracyMatrix.read(folder / ACCURACY_MATRIX_FILENAME).steps
    per_task = int(budgets[winner])
    assert steps == [per_task - 1, 2 * per_task - 1], "the results are the winner's, whole"
    checkpoints = sorted(path.name for path in (folder / "nerfstudio_models").iterdir())
    assert checkpoints == [f"step-{step:09d}.ckpt" for step in steps]
    assert not (folder / LOCK_NAME).exists()
