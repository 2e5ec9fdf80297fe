"""Checkpoints and results files survive a kill during a save, load with weights_only=True, and resume exactly."""

from __future__ import annotations

import errno
import os
import subprocess
from pathlib import Path
from typing import BinaryIO, Callable, Optional

import pytest
import torch
from helpers import (
    Killed,
    demo_parser,
    fill_the_disk_at_checkpoint,
    flip_tensor_bytes,
    kill_in_the_middle_of_save,
    tiny_config,
)
from nerfstudio.engine.callbacks import TrainingCallback, TrainingCallbackLocation
from nerfstudio.scripts.train import train_loop

from continual_nerf.atomic_files import write_atomically, write_text_atomically
from continual_nerf.checkpoints import read_checkpoint
from continual_nerf.core.accuracy_matrix import ACCURACY_MATRIX_FILENAME, AccuracyMatrix
from continual_nerf.core.continual_pipeline import ORACLE_PREFIX
from continual_nerf.core.continual_trainer import ContinualTrainerConfig
from continual_nerf.errors import CheckpointError, OutputError


def three_tasks(run_dir: Path, timestamp: str) -> ContinualTrainerConfig:
    config = tiny_config(run_dir, demo_parser(num_frames=18), num_tasks=3, iterations_per_task=4)
    config.timestamp = timestamp
    config.steps_per_save = 10**9  # checkpoints at the end of each task only: steps 3, 7, 11
    config.save_config()
    return config


def run(config: ContinualTrainerConfig) -> AccuracyMatrix:
    """ns-train's own training function (it seeds from config.machine.seed); returns the run's accuracy matrix."""
    train_loop(local_rank=0, world_size=1, config=config)
    return AccuracyMatrix.read(config.get_base_dir() / ACCURACY_MATRIX_FILENAME)


@pytest.mark.slow
def test_a_kill_during_a_save_leaves_the_last_complete_checkpoint_and_the_run_resumes_exactly(
    run_dir, monkeypatch, single_thread
):
    uninterrupted = run(three_tasks(run_dir, "uninterrupted"))

    killed = three_tasks(run_dir, "killed")
    with monkeypatch.context() as patch:
        kill_in_the_middle_of_save(patch, save_number=2)  # the checkpoint at the end of task 2
        with pytest.raises(Killed):
            train_loop(local_rank=0, world_size=1, config=killed)
    checkpoint_dir = killed.get_checkpoint_dir()
    assert [path.name for path in checkpoint_dir.iterdir()] == ["step-000000003.ckpt"], "no partial file beside it"
    state = torch.load(checkpoint_dir / "step-000000003.ckpt", map_location="cpu", weights_only=True)
    assert state["step"] == 3 and state["pipeline"]["_extra_state"]["task"]["current"] == 1
    after_kill = AccuracyMatrix.read(killed.get_base_dir() / ACCURACY_MATRIX_FILENAME)
    assert (len(after_kill.psnr), after_kill.finished, after_kill.status) == (2, False, "training")

    resumed = three_tasks(run_dir, "resumed")
    resumed.load_dir = checkpoint_dir
    matrix = run(resumed)
    assert matrix.finished and matrix.status == "finished" and matrix.steps == uninterrupted.steps == [3, 7, 11]
    assert matrix.psnr == uninterrupted.psnr and matrix.ssim == uninterrupted.ssim, (
        "model, oracle, optimizers, task progress and RNGs all come back: the resumed run is the uninterrupted one"
    )
    assert sorted(path.name for path in resumed.get_checkpoint_dir().iterdir()) == [
        "step-000000007.ckpt",
        "step-000000011.ckpt",
    ]


def test_a_kill_while_a_results_file_is_written_leaves_the_previous_file(tmp_path):
    path = tmp_path / ACCURACY_MATRIX_FILENAME
    write_text_atomically(path, '{"psnr": [[20.0]]}')

    def half_then_killed(file: BinaryIO) -> None:
        file.write(b'{"psnr": [[20.0], [19.')
        raise Killed

    with pytest.raises(Killed):
        write_atomically(path, half_then_killed)
    assert path.read_text() == '{"psnr": [[20.0]]}'
    assert [p.name for p in tmp_path.iterdir()] == [ACCURACY_MATRIX_FILENAME]


def test_temporary_checkpoint_files_live_outside_the_checkpoint_folder(run_dir, monkeypatch):
    config = three_tasks(run_dir, "temporary")
    trainer = config.setup(local_rank=0, world_size=1)
    trainer.setup()
    renamed = []
    replace = os.replace

    def recording_replace(source, target) -> None:
        renamed.append((Path(source), Path(target)))
        replace(source, target)

    monkeypatch.setattr(os, "replace", recording_replace)
    trainer.save_checkpoint(0)
    # a SIGKILL mid-save leaves the temporary file behind: ns-eval and --load-dir parse every name in the folder
    assert renamed == [
        (
            config.get_base_dir() / f".step-000000000.ckpt.partial-{os.getpid()}",
            config.get_checkpoint_dir() / "step-000000000.ckpt",
        )
    ]
    assert [path.name for path in config.get_checkpoint_dir().iterdir()] == ["step-000000000.ckpt"]


def test_bytes_flipped_inside_a_tensor_are_caught_by_the_archive_crc_before_loading(tmp_path):
    path = tmp_path / "step-000000001.ckpt"
    weights = torch.arange(100_000, dtype=torch.float32)
    torch.save({"step": 1, "pipeline": {"field": weights}, "optimizers": {}, "scalers": {}}, path)
    assert torch.equal(read_checkpoint(path)["pipeline"]["field"], weights)
    path.write_bytes(flip_tensor_bytes(path.read_bytes()))
    loaded = torch.load(path, map_location="cpu", weights_only=True)["pipeline"]["field"]
    assert not torch.equal(loaded, weights), "torch.load alone reads the corrupt tensor without a word"
    with pytest.raises(CheckpointError) as raised:
        read_checkpoint(path)
    assert str(raised.value) == (
        f"{path}: corrupt checkpoint (step-000000001/data/0 does not match its CRC-32); "
        "resume from another with --load-step"
    )


@pytest.mark.parametrize(
    "code, cause",
    [
        (errno.ENOSPC, "no space left on the device"),
        (errno.EROFS, "read-only file system"),
        (errno.EACCES, "permission denied: the folder is read-only for this user"),
    ],
)
def test_a_failed_write_names_the_file_and_the_cause_and_keeps_the_previous_file(tmp_path, code, cause):
    path = tmp_path / ACCURACY_MATRIX_FILENAME
    write_text_atomically(path, '{"psnr": [[20.0]]}')

    def half_then_fails(file: BinaryIO) -> None:
        file.write(b'{"psnr": [[20.0], [19.')
        raise OSError(code, os.strerror(code))

    with pytest.raises(OutputError) as raised:
        write_atomically(path, half_then_fails)
    assert str(raised.value) == f"{path}: cannot be written ({cause})"
    assert path.read_text() == '{"psnr": [[20.0]]}'
    assert [p.name for p in tmp_path.iterdir()] == [ACCURACY_MATRIX_FILENAME], "no temporary file left"


def ends_with_one_line(config: ContinualTrainerConfig, after_iteration: Optional[Callable[[int], None]] = None) -> str:
    """The line a run (its config saved) ends with, set up and trained as ns-train does."""
    with pytest.raises(SystemExit) as exit_info:
        trainer = config.setup(local_rank=0, world_size=1)
        trainer.setup()
        if after_iteration is not None:
            trainer.callbacks.append(
                TrainingCallback([TrainingCallbackLocation.AFTER_TRAIN_ITERATION], after_iteration)
            )
        trainer.train()
    line = exit_info.value.code
    assert isinstance(line, str) and line.startswith("continual-ngp: error: ") and "\n" not in line
    return line


def assert_step_3_intact(config: ContinualTrainerConfig, status: str) -> None:
    checkpoints = [path.name for path in config.get_checkpoint_dir().iterdir()]
    assert checkpoints == ["step-000000003.ckpt"], "the previous checkpoint is all there is"
    assert read_checkpoint(config.get_checkpoint_dir() / "step-000000003.ckpt")["step"] == 3, "and it is intact"
    assert not list(config.get_base_dir().glob(".*.partial-*")), "no temporary file left"
    assert AccuracyMatrix.read(config.get_base_dir() / ACCURACY_MATRIX_FILENAME).status == status


@pytest.mark.slow
def test_a_full_disk_during_a_save_is_one_line_and_the_previous_checkpoint_stays(run_dir, monkeypatch):
    config = three_tasks(run_dir, "full-disk")
    fill_the_disk_at_checkpoint(monkeypatch, save_number=2)  # the checkpoint at the end of task 2
    line = ends_with_one_line(config)
    checkpoint = config.get_checkpoint_dir() / "step-000000007.ckpt"
    assert line.endswith(f"{checkpoint}: cannot be written (no space left on the device)")
    assert_step_3_intact(config, "failed")


@pytest.mark.slow
@pytest.mark.skipif(os.geteuid() == 0, reason="root writes into read-only folders (run as another user to test this)")
def test_a_run_folder_made_read_only_mid_run_is_one_line_and_the_previous_checkpoint_stays(run_dir):
    config = three_tasks(run_dir, "read-only")
    folders = [config.get_base_dir(), config.get_checkpoint_dir()]

    def read_only_after_task_1(step: int) -> None:
        if step == 4:
            for folder in folders:
                folder.chmod(0o555)

    try:
        line = ends_with_one_line(config, read_only_after_task_1)
    finally:
        for folder in folders:
            folder.chmod(0o755)
    assert line.endswith(": cannot be written (permission denied: the folder is read-only for this user)")
    assert f"{config.get_base_dir()}" in line
    assert_step_3_intact(config, "training")  # a read-only folder cannot record "failed" either


def test_temporary_files_a_killed_save_left_are_removed_at_the_next_start(run_dir, capsys):
    killed = three_tasks(run_dir, "killed")
    dead = subprocess.Popen(["true"])
    dead.wait()
    stale = killed.get_base_dir() / f".step-000000003.ckpt.partial-{dead.pid}"
    in_progress = killed.get_base_dir() / f".accuracy_matrix.json.partial-{os.getpid()}"
    stale.touch()  # the 0-byte file a SIGKILL during a save leaves
    in_progress.touch()
    resumed = tiny_config(run_dir, demo_parser(num_frames=18), num_tasks=3, iterations_per_task=4)
    resumed.timestamp = "resumed"
    resumed.load_dir = killed.get_checkpoint_dir()
    resumed.save_config()  # the start of ns-train
    assert not stale.exists() and in_progress.exists(), "only files of processes no longer running are removed"
    assert f"Removed {stale}, left by a save that was killed" in capsys.readouterr().out


@pytest.mark.slow
def test_a_closed_tasks_checkpoint_keeps_the_weights_only_and_loads_with_the_oracle_as_its_model(
    run_dir, single_thread
):
    config = three_tasks(run_dir, "slim")
    config.steps_per_save = 2  # checkpoints mid-task too, which only resuming needs
    run(config)
    checkpoint_dir = config.get_checkpoint_dir()
    assert sorted(path.name for path in checkpoint_dir.iterdir()) == [
        "step-000000003.ckpt", "step-000000007.ckpt", "step-000000011.ckpt",
    ], "the tasks' ends only: mid-task checkpoints go once a later one is saved"  # fmt: skip
    closed, latest = (
        read_checkpoint(checkpoint_dir / "step-000000003.ckpt"),
        read_checkpoint(checkpoint_dir / "step-000000011.ckpt"),
    )
    assert closed["weights_only"] and not closed["optimizers"] and "rng" not in closed
    assert not any(key.startswith(ORACLE_PREFIX) for key in closed["pipeline"])
    assert any(key.startswith(ORACLE_PREFIX) for key in latest["pipeline"]) and latest["optimizers"]
    size = {path.name: path.stat().st_size for path in checkpoint_dir.iterdir()}
    assert size["step-000000003.ckpt"] < size["step-000000011.ckpt"] / 3, "the model alone: no oracle nor Adam moments"

    pipeline = config.pipeline.setup(device="cpu", test_mode="test")
    pipeline.load_pipeline(latest["pipeline"], latest["step"])  # the oracle is built, as in the run viewer
    pipeline.load_pipeline(closed["pipeline"], closed["step"])
    oracle = pipeline.replay_oracle.model.state_dict()
    weights = {name: value for name, value in pipeline.model.state_dict().items() if isinstance(value, torch.Tensor)}
    assert weights, "the model has weights to compare"
    for name, value in weights.items():
        assert torch.equal(oracle[name], value), name
        assert torch.equal(value, closed["pipeline"]["_model." + name]), name


@pytest.mark.slow
def test_resuming_from_a_closed_tasks_weights_only_checkpoint_is_one_line_naming_the_latest(run_dir, single_thread):
    config = three_tasks(run_dir, "slim-resume")
    run(config)
    again = three_tasks(run_dir, "slim-resume-again")
    again.load_dir, again.load_step = config.get_checkpoint_dir(), 3
    with pytest.raises(SystemExit, match="keeps the model's weights of a finished task only, .* step-000000011.ckpt"):
        train_loop(local_rank=0, world_size=1, config=again)
