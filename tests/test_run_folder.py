"""A run's life in its folder: one run at a time holds the folder (a second start fails with one line, a killed run's
claim is taken over); Ctrl-C and SIGTERM save the current step, mark the run interrupted, print the command that
resumes it and exit 130 / 143, and the resumed run ends as the uninterrupted one."""

from __future__ import annotations

import errno
import os
import shlex
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
import yaml
from helpers import (
    SUBPROCESS_ENV,
    ctrl_c_when_saved,
    demo_parser,
    ns_train_command,
    run_ns_train,
    stream_config,
    tiny_config,
    train,
)
from nerfstudio.engine.callbacks import TrainingCallback, TrainingCallbackLocation
from nerfstudio.scripts.train import train_loop

from continual_nerf import run_lock
from continual_nerf.core.accuracy_matrix import ACCURACY_MATRIX_FILENAME, AccuracyMatrix
from continual_nerf.core.continual_trainer import ContinualTrainerConfig
from continual_nerf.errors import ContinualConfigError
from continual_nerf.interrupts import INTERRUPTS, Interrupts, resume_command
from continual_nerf.recipes import set_up_like_ns_train
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


def test_a_run_that_has_locked_but_not_yet_written_its_pid_is_named_once_it_has(tmp_path):
    """Started at once, the second run can meet the first between its lock and its PID: it waits for the PID."""
    path = tmp_path / LOCK_NAME
    descriptor = os.open(path, os.O_CREAT | os.O_RDWR, 0o644)
    run_lock.fcntl.flock(descriptor, run_lock.fcntl.LOCK_EX | run_lock.fcntl.LOCK_NB)
    writer = threading.Timer(0.1, lambda: os.pwrite(descriptor, b"4242\n", 0))
    writer.start()
    try:
        with pytest.raises(ContinualConfigError, match="is in use by another run \\(process 4242\\)"):
            claim_run_folder(tmp_path)
    finally:
        writer.join()
        os.close(descriptor)


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


# ---- Ctrl-C and SIGTERM ----


@pytest.mark.parametrize(
    "argv, expected",
    [
        (
            ["/venv/bin/ns-train", "continual-ngp", "--vis", "viewer", "continual-demo", "--data", "my scene"],
            "ns-train continual-ngp --load-dir /runs/x/nerfstudio_models --vis viewer continual-demo --data 'my scene'",
        ),
        (
            ["ns-train", "continual-ngp", "--load-dir", "old", "--load-step=7", "continual-tum", "--data", "d"],
            "ns-train continual-ngp --load-dir /runs/x/nerfstudio_models continual-tum --data d",
        ),
        (["/usr/bin/pytest", "tests"], "its ns-train command with --load-dir /runs/x/nerfstudio_models"),
    ],
)
def test_the_resume_command_is_the_run_s_own_with_load_dir(argv, expected):
    assert resume_command(Path("/runs/x/nerfstudio_models"), argv) == expected


def three_tasks(run_dir: Path, timestamp: str) -> ContinualTrainerConfig:
    config = tiny_config(run_dir, demo_parser(num_frames=18), num_tasks=3, iterations_per_task=4)
    config.timestamp = timestamp
    config.steps_per_save = 10**9  # checkpoints at the end of each task only: steps 3, 7, 11
    return config


def accuracy_of(config: ContinualTrainerConfig) -> AccuracyMatrix:
    return AccuracyMatrix.read(config.get_base_dir() / ACCURACY_MATRIX_FILENAME)


@pytest.mark.slow
def test_sigterm_saves_the_step_marks_the_run_interrupted_and_its_resume_ends_as_the_uninterrupted_run(
    run_dir, capsys, single_thread
):
    handlers = signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)
    uninterrupted = three_tasks(run_dir, "uninterrupted")
    train(uninterrupted)

    interrupted = three_tasks(run_dir, "interrupted")
    interrupted.save_config()
    trainer = set_up_like_ns_train(interrupted)

    def sigterm_during_step_5(step: int) -> None:
        if step == 5:  # task 2, between its checkpoints
            os.kill(os.getpid(), signal.SIGTERM)

    trainer.callbacks.append(TrainingCallback([TrainingCallbackLocation.AFTER_TRAIN_ITERATION], sigterm_during_step_5))
    capsys.readouterr()
    with pytest.raises(SystemExit) as exit_info:
        trainer.train()
    assert exit_info.value.code == 143
    checkpoints = interrupted.get_checkpoint_dir()
    assert capsys.readouterr().err.splitlines()[-1] == (
        f"continual-ngp: interrupted by SIGTERM: step 5 saved; resume with: its ns-train command with --load-dir "
        f"{checkpoints}"
    )
    assert sorted(path.name for path in checkpoints.iterdir()) == ["step-000000003.ckpt", "step-000000005.ckpt"]
    matrix = accuracy_of(interrupted)
    assert (matrix.status, matrix.finished, len(matrix.psnr)) == ("interrupted", False, 1)
    assert (signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)) == handlers, "handlers restored"
    assert not (interrupted.get_base_dir() / LOCK_NAME).exists(), "the folder is released"

    resumed = three_tasks(run_dir, "resumed")
    resumed.load_dir = checkpoints
    train(resumed)
    matrix = accuracy_of(resumed)
    assert matrix.status == "finished" and matrix.steps == accuracy_of(uninterrupted).steps == [3, 7, 11]
    assert matrix.psnr == accuracy_of(uninterrupted).psnr, "resumed from step 5, the run ends as the uninterrupted one"


NUM_FRAMES, NUM_TASKS, ITERATIONS_PER_TASK, STEPS_PER_SAVE = 18, 3, 8, 10
"""Task 2 spans steps 8..15: the periodic checkpoint of step 10 is written in the middle of it."""


@pytest.mark.slow
def test_ctrl_c_in_ns_train_saves_prints_the_resume_command_exits_130_and_that_command_finishes_the_run(tmp_path):
    outputs = tmp_path / "outputs"
    options = [
        *("--pipeline.datamanager.num-tasks", str(NUM_TASKS)),
        *("--pipeline.datamanager.iterations-per-task", str(ITERATIONS_PER_TASK)),
        *("--steps-per-save", str(STEPS_PER_SAVE)),
    ]
    demo = ["continual-demo", "--data", str(demo_parser().data), "--num-frames", str(NUM_FRAMES)]
    command = ns_train_command(outputs, "interrupted", options, demo)
    folder = outputs / "unnamed" / "continual-ngp" / "interrupted"
    checkpoint = folder / "nerfstudio_models" / f"step-{STEPS_PER_SAVE:09d}.ckpt"
    stderr = ctrl_c_when_saved(command, checkpoint, tmp_path / "interrupted.log")
    assert "Traceback" not in stderr and "KeyboardInterrupt" not in stderr, stderr[-3000:]
    line = stderr.strip().splitlines()[-1]
    said, resume = line.split(" saved; resume with: ")
    step = int(said.removeprefix("continual-ngp: interrupted by SIGINT: step "))
    assert STEPS_PER_SAVE <= step < NUM_TASKS * ITERATIONS_PER_TASK - 1
    assert (folder / "nerfstudio_models" / f"step-{step:09d}.ckpt").is_file()
    assert accuracy_of_folder(folder).status == "interrupted"
    expected = shlex.join(["ns-train", command[1], "--load-dir", str(folder / "nerfstudio_models"), *command[2:]])
    assert resume == expected, "the exact command: ns-train's own arguments, --load-dir after the method"

    resumed = run_ns_train([command[0], *shlex.split(resume)[1:]])
    assert resumed.returncode == 0, resumed.stderr[-3000:]
    after_resume = accuracy_of_folder(folder)  # the same --timestamp: it continues in its own folder

    config = yaml.load((folder / "config.yml").read_text(), Loader=yaml.Loader)
    config.timestamp, config.load_dir = "uninterrupted", None
    train_loop(local_rank=0, world_size=1, config=config)
    uninterrupted = accuracy_of_folder(config.get_base_dir())
    assert after_resume.status == "finished" and after_resume.steps == uninterrupted.steps == [7, 15, 23]
    differences = [abs(a - b) for ra, rb in zip(after_resume.psnr, uninterrupted.psnr) for a, b in zip(ra, rb)]
    assert max(differences) <= 0.3, f"resumed {after_resume.psnr} vs uninterrupted {uninterrupted.psnr}"


def accuracy_of_folder(folder: Path) -> AccuracyMatrix:
    return AccuracyMatrix.read(folder / ACCURACY_MATRIX_FILENAME)


def test_ctrl_c_while_a_run_sets_up_ends_it_at_once_with_one_line(tmp_path, capsys):
    """Set-up may wait long (here for a capture's first frames): Ctrl-C ends it with 130, no traceback."""
    config = stream_config(tmp_path / "outputs", tmp_path / "capture", "wait", frames_per_task=2, iterations_per_task=1)
    config.save_config()

    def ctrl_c_once_handled() -> None:
        while signal.getsignal(signal.SIGINT) != INTERRUPTS._handle:  # installed when set-up starts
            time.sleep(0.01)
        os.kill(os.getpid(), signal.SIGINT)

    threading.Thread(target=ctrl_c_once_handled, daemon=True).start()
    with pytest.raises(SystemExit) as exit_info:
        config.setup(local_rank=0, world_size=1).setup()  # waits for the first task's frames, which never come
    assert exit_info.value.code == 130
    assert capsys.readouterr().err.splitlines()[-1] == "Stopped by SIGINT; the checkpoints written so far are kept"
    assert signal.getsignal(signal.SIGINT) == signal.default_int_handler, "nerfstudio's own handler is back"


@pytest.mark.parametrize("answered", [False, True])
def test_a_signal_once_the_interrupt_is_answered_ends_the_process_without_another_line(answered, capsys):
    """With several processes the launcher stops the others once one has ended (SIGTERM): rank 0, having saved and
    said how to resume, ends without a second line; before it has, the signal is a user's second one and says so."""
    interrupts = Interrupts()
    interrupts.deferring, interrupts.received, interrupts.answered = True, signal.SIGINT, answered
    with pytest.raises(SystemExit) as exit_info:
        interrupts._handle(signal.SIGTERM, None)
    assert exit_info.value.code == 143
    said = [] if answered else ["Stopped by SIGTERM; the checkpoints written so far are kept"]
    assert capsys.readouterr().err.splitlines() == said
