"""Two processes on nerfstudio's launcher (gloo on CPU, DDP): the continual state stays one run's."""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path
from typing import Any, Dict, List, cast

import pytest
import torch
import torch.multiprocessing
from helpers import (
    RANK_RECORDS,
    RUN_TIMEOUT,
    SUBPROCESS_ENV,
    collectives_probe,
    demo_parser,
    finish,
    tiny_config,
    train,
    two_process_command,
    two_process_run,
    two_process_run_dir,
    wait_while_running,
)

from continual_nerf.checkpoints import checkpoint_steps, read_checkpoint
from continual_nerf.core.accuracy_matrix import ACCURACY_MATRIX_FILENAME, AccuracyMatrix
from continual_nerf.dataparsers.capture_folder import CaptureTasks, StreamFrame
from continual_nerf.dataparsers.stream_dataparser import StreamDataParserConfig
from continual_nerf.errors import ContinualConfigError

pytestmark = pytest.mark.slow  # trains models in subprocesses

NUM_TASKS, ITERATIONS_PER_TASK = 3, 3


def test_every_rank_follows_rank_0_and_averages_estimates(tmp_path: Path):
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    torch.multiprocessing.spawn(collectives_probe, args=(port, tmp_path), nprocs=2)
    main, other = (torch.load(tmp_path / f"rank{rank}.pt", weights_only=False) for rank in (0, 1))
    assert main["decided"] == other["decided"] == 10  # rank 0's decision
    assert torch.equal(main["averaged"], torch.ones(2)) and torch.equal(other["averaged"], torch.ones(2))  # (0+2)/2
    assert all(torch.equal(main["weights"][key], other["weights"][key]) for key in main["weights"])


def records(run_dir: Path, rank: int) -> Dict[str, Any]:
    return json.loads((run_dir / RANK_RECORDS / f"rank{rank}.json").read_text())


@pytest.fixture(scope="module")
def two_process_output(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A tiny 3-task run of continual-ngp with two processes."""
    output_dir = tmp_path_factory.mktemp("two-processes")
    run = two_process_run(output_dir, num_tasks=NUM_TASKS, iterations_per_task=ITERATIONS_PER_TASK)
    assert run.returncode == 0, run.stderr[-3000:]
    (output_dir / "stdout.txt").write_text(run.stdout)
    return output_dir


def test_rank_0_alone_speaks_for_the_run(two_process_output: Path):
    printed = (two_process_output / "stdout.txt").read_text()
    for line in ("Saving checkpoints to", "No Nerfstudio checkpoint to load", "Training Finished", "Task 2/3 starts"):
        assert printed.count(line) == 1, f"{line!r} printed {printed.count(line)} times"


def test_two_processes_train_every_task_into_one_accuracy_matrix(two_process_output: Path):
    run_dir = two_process_run_dir(two_process_output)
    accuracy = AccuracyMatrix.read(run_dir / ACCURACY_MATRIX_FILENAME)
    assert accuracy.finished and len(accuracy.psnr) == NUM_TASKS
    assert accuracy.steps == [ITERATIONS_PER_TASK * (task + 1) - 1 for task in range(NUM_TASKS)]
    main, other = records(run_dir, 0), records(run_dir, 1)
    assert main["accuracy_rows"] == NUM_TASKS and other["accuracy_rows"] == 0  # rank 0 alone evaluates
    assert main["last_step"] == other["last_step"]
    checkpoint = read_checkpoint(max(checkpoint_steps(run_dir / "nerfstudio_models").values()))
    assert not [key for key in checkpoint["pipeline"] if ".module." in key]  # the unwrapped model, as one process
    ns_eval = [str(Path(sys.executable).with_name("ns-eval")), "--load-config", str(run_dir / "config.yml")]
    evaluated = subprocess.run(
        [*ns_eval, "--output-path", str(run_dir / "eval.json")], env=SUBPROCESS_ENV, check=False, timeout=RUN_TIMEOUT
    )
    assert evaluated.returncode == 0 and "psnr" in json.loads((run_dir / "eval.json").read_text())["results"]


def test_both_ranks_hold_the_same_oracle_after_every_switch(two_process_output: Path):
    records_dir = two_process_run_dir(two_process_output) / RANK_RECORDS
    for switch in range(1, NUM_TASKS):
        main = torch.load(records_dir / f"oracle-rank0-switch{switch}.pt", weights_only=False)
        other = torch.load(records_dir / f"oracle-rank1-switch{switch}.pt", weights_only=False)
        tensors = [key for key, value in main.items() if isinstance(value, torch.Tensor)]
        assert tensors and all(torch.equal(main[key], other[key]) for key in tensors)


def test_a_two_process_checkpoint_resumes_in_one_process(tmp_path: Path, single_thread):
    # a run that stops one step before its last task ends: its latest checkpoint is one to resume
    stopped = two_process_run(tmp_path / "two", num_tasks=2, iterations_per_task=3, max_num_iterations=5)
    assert stopped.returncode == 0, stopped.stderr[-3000:]
    run_dir = two_process_run_dir(tmp_path / "two")
    config = tiny_config(tmp_path / "resumed", demo_parser(), num_tasks=2, iterations_per_task=3)
    config.load_dir = run_dir / "nerfstudio_models"
    trainer = train(config)
    resumed = AccuracyMatrix.read(trainer.base_dir / ACCURACY_MATRIX_FILENAME)
    two_processes = AccuracyMatrix.read(run_dir / ACCURACY_MATRIX_FILENAME)
    assert not two_processes.finished and two_processes.steps == [2]
    assert resumed.finished and resumed.steps == [2, 5]
    assert resumed.psnr[0] == two_processes.psnr[0]  # the row measured before the checkpoint is kept


def test_a_seconds_budget_switches_both_ranks_at_the_same_step(tmp_path: Path):
    # rank 1 sleeps outside its clock, so rank 0 (waiting for it in the gradient all-reduce) spends its budget in
    # fewer steps: left to itself, rank 1 would switch later
    run = two_process_run(tmp_path, num_tasks=2, seconds_per_task=1.5, slow_rank=1, slow_seconds=0.3)
    assert run.returncode == 0, run.stderr[-3000:]
    run_dir = two_process_run_dir(tmp_path)
    main, other = records(run_dir, 0)["switches"], records(run_dir, 1)["switches"]
    assert len(main) == len(other) == 1
    assert main[0]["step"] == other[0]["step"]
    assert main[0]["seconds_done"] >= 1.5 > other[0]["seconds_done"]  # rank 0 decided; rank 1 followed


def test_a_viewer_pause_longer_than_the_timeout_holds_both_ranks(tmp_path: Path):
    # nerfstudio's loop would stop rank 0 alone, and rank 1 would give up in the next all-reduce after 10 s
    run = two_process_run(tmp_path, timeout_seconds=10, num_tasks=2, iterations_per_task=3, pausing_seconds=15)
    assert run.returncode == 0, run.stderr[-3000:]
    run_dir = two_process_run_dir(tmp_path)
    # asked for after step 1, the pause starts at the end of step 2, which every rank reaches, and lasts
    assert records(run_dir, 0)["step_when_resumed"] == 2, "training held at step 2 for the whole pause"
    assert records(run_dir, 0)["last_step"] == records(run_dir, 1)["last_step"] == 5


@pytest.mark.parametrize("dying_rank", [1, 0])
def test_a_dying_rank_ends_the_run_with_one_line_and_marks_it_failed(tmp_path: Path, dying_rank: int):
    run = two_process_run(tmp_path, timeout_seconds=20, num_tasks=2, iterations_per_task=20, dying_rank=dying_rank)
    assert run.returncode != 0
    reported = f"process {dying_rank} terminated with signal SIGKILL; the other processes were stopped"
    assert [line for line in run.stderr.splitlines() if ": error:" in line] == [f"continual-ngp: error: {reported}"], (
        "the other process, whose connection to it closed, says nothing"
    )
    assert "Traceback" not in run.stderr
    accuracy = AccuracyMatrix.read(two_process_run_dir(tmp_path) / ACCURACY_MATRIX_FILENAME)
    assert accuracy.status == "failed", "the run folder says the run did not end well"


def test_start_paused_is_refused_with_several_processes(tmp_path: Path):
    config = tiny_config(tmp_path, demo_parser())
    config.start_paused = True
    config.machine.num_devices = 2
    with pytest.raises(ContinualConfigError, match="--start-paused needs one process"):
        config.validate()


def test_ctrl_c_stops_both_ranks_at_one_step_that_rank_0_saves(tmp_path: Path):
    command = two_process_command(tmp_path, num_tasks=2, iterations_per_task=10**4)
    # its own session: Ctrl-C in a terminal reaches the launching process and both ranks alike
    run = subprocess.Popen(command, env=SUBPROCESS_ENV, stderr=subprocess.PIPE, text=True, start_new_session=True)
    results = two_process_run_dir(tmp_path) / ACCURACY_MATRIX_FILENAME
    wait_while_running(run, results.exists, "rank 0 writes its results, as training starts")
    time.sleep(5)
    os.killpg(run.pid, signal.SIGINT)
    _, stderr = finish(run, "the interrupted two-process run")
    assert run.returncode == 130, stderr[-3000:]
    assert "continual-ngp: interrupted by SIGINT: step " in stderr and "Traceback" not in stderr
    assert AccuracyMatrix.read(results).status == "interrupted"
    assert checkpoint_steps(two_process_run_dir(tmp_path) / "nerfstudio_models")


def test_a_rank_cuts_the_capture_where_rank_0_cut_it(tmp_path: Path):
    capture = CaptureTasks(StreamDataParserConfig(data=tmp_path))
    frames = cast(List[StreamFrame], [f"{index:06d}.json" for index in range(10)])
    # rank 0 closed task 2 after 4 frames ("Next task now"); this rank read on, and --frames-per-task closed it at 6
    capture.tasks, capture.collecting = [frames[:3], frames[3:9]], frames[9:]
    assert capture.frames_from(1) == 7
    capture.cut_task(1, 4)
    assert capture.tasks == [frames[:3], frames[3:7]] and capture.collecting == frames[7:]
