"""What the commands show in a terminal: ns-train's short summary first, no warnings about nerfstudio's own code,
nothing about tiny-cuda-nn on a CPU, and Ctrl-C ending a run or the viewer with 130 and at most one line."""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import List

import numpy as np
import pytest
import websocket
from helpers import (
    RUN_TIMEOUT,
    SUBPROCESS_ENV,
    demo_parser,
    finish,
    ns_train_command,
    run_ns_train,
    tiny_config,
    train,
    wait_while_running,
)

from continual_nerf.bench.browser import free_port, viewer_answers
from continual_nerf.nerfstudio_compat import NERFSTUDIO_WARNINGS, viewer_camera_message

pytestmark = pytest.mark.slow  # runs ns-train

RAISED_WHILE_NS_TRAIN_IMPORTS = {
    "`torch.jit.script` is deprecated",
    "`torch.cuda.amp.custom_fwd(args...)` is deprecated",
    "`torch.cuda.amp.custom_bwd(args...)` is deprecated",
}
"""Raised while ns-train imports nerfstudio, before it loads any plugin: no plugin can keep them out of its terminal."""


def test_a_cpu_run_starts_with_a_summary_and_shows_no_warning_about_nerfstudio_s_code(tmp_path):
    options = ["--pipeline.datamanager.num-tasks", "3", "--pipeline.datamanager.iterations-per-task", "2"]
    options += ["--pipeline.model.compile", "True"]  # torch.compile logs about CUDA on a CPU machine
    run = run_ns_train(ns_train_command(tmp_path, "terminal", options, ["continual-demo"]))
    assert run.returncode == 0, run.stderr[-3000:]
    lines = run.stdout.splitlines()
    assert lines[0].startswith("continual-ngp: 3 tasks x 2 iterations on cpu; data: continual-demo, ")
    assert (
        lines[1]
        == f"Run folder: {tmp_path / 'unnamed' / 'continual-ngp' / 'terminal'} (config.yml there holds every option)"
    )
    assert "ContinualTrainerConfig(" not in run.stdout, "nerfstudio's dump of every option stays in config.yml"
    assert "tcnn" not in run.stdout, "tiny-cuda-nn cannot run on a CPU: nothing to say about it"
    warned = set(re.findall(r"Warning: (.*?)\. ", run.stderr))
    assert warned <= RAISED_WHILE_NS_TRAIN_IMPORTS, f"warnings the plugin could have kept out: {warned}"
    assert {message for _, message, _ in NERFSTUDIO_WARNINGS} >= RAISED_WHILE_NS_TRAIN_IMPORTS
    assert "No CUDA runtime is found" not in run.stderr


def test_ctrl_c_while_a_capture_s_first_task_is_awaited_ends_with_130_and_one_line(tmp_path):
    command = ns_train_command(tmp_path, "waiting", [], ["continual-stream", "--data", str(tmp_path / "capture")])
    command[command.index("continual-ngp")] = "continual-ngp-stream"
    with (tmp_path / "stdout.txt").open("w") as stdout, (tmp_path / "stderr.txt").open("w") as stderr:
        run = subprocess.Popen(command, stdout=stdout, stderr=stderr, env=SUBPROCESS_ENV, start_new_session=True)
        wait_while_running(run, lambda: "Waiting for the first task" in read(tmp_path / "stdout.txt"), "it waits")
        os.killpg(run.pid, signal.SIGINT)  # as Ctrl-C in a terminal: to every process of the run
        finish(run, "the interrupted run")
    assert run.returncode == 130
    assert said(read(tmp_path / "stderr.txt")) == ["Stopped by SIGINT; the checkpoints written so far are kept"]


def test_ctrl_c_while_the_viewer_renders_ends_with_130_not_an_abort(tmp_path):
    """A render thread still in torch code when the interpreter shuts down aborts the process (SIGABRT, 134)."""
    port = free_port()
    viewer = ["--vis", "viewer", "--viewer.websocket-port", str(port), "--viewer.websocket-host", "127.0.0.1"]
    command = ns_train_command(tmp_path, "rendering", [*viewer, "--start-paused", "True"], ["continual-demo"])
    with (tmp_path / "stdout.txt").open("w") as stdout, (tmp_path / "stderr.txt").open("w") as stderr:
        run = subprocess.Popen(command, stdout=stdout, stderr=stderr, env=SUBPROCESS_ENV, start_new_session=True)
        wait_while_running(run, lambda: viewer_answers(port), "the viewer answers")
        page = websocket.create_connection(f"ws://127.0.0.1:{port}", timeout=30, suppress_origin=True)
        moving = threading.Thread(target=move_the_camera, args=[page, run], daemon=True)
        moving.start()
        try:
            time.sleep(4)
            os.killpg(run.pid, signal.SIGINT)  # while the viewer renders the moving camera's view
            finish(run, "the interrupted run")
        finally:
            moving.join()
            page.close()
    stderr_text = read(tmp_path / "stderr.txt")
    assert run.returncode == 130, stderr_text[-2000:]
    assert len(said(stderr_text)) == 1 and "SIGINT" in said(stderr_text)[0]


def move_the_camera(page: websocket.WebSocket, run: subprocess.Popen) -> None:
    """Send the viewer a camera on the move until `run` ends: it renders after each message, one render after the
    other."""
    turn = 0
    while run.poll() is None:
        angle = turn / 10
        position = np.array([np.cos(angle), np.sin(angle), 0.5])
        try:
            page.send_binary(viewer_camera_message(position, np.zeros(3), np.array([0, 0, 1.0]), 1.0, 1.4))
        except OSError:  # the viewer has gone with the run
            return
        turn += 1
        time.sleep(0.05)


def read(path: Path) -> str:
    return path.read_text() if path.exists() else ""


def said(stderr: str) -> List[str]:
    """The lines of `stderr` that are not the warnings raised while ns-train imports nerfstudio (nor their source)."""
    return [
        line for line in stderr.splitlines() if line.strip() and not line.startswith(" ") and "Warning: " not in line
    ]


def test_ctrl_c_ends_the_finished_run_viewer_with_130_and_no_traceback(tmp_path):
    config = tiny_config(tmp_path / "outputs", demo_parser(), num_tasks=2, iterations_per_task=2)
    train(config)
    port = free_port()
    viewer = Path(sys.executable).with_name("continual-nerf-viewer")
    command = [str(viewer), "--load-config", str(config.get_base_dir() / "config.yml"), "--viewer.websocket-port"]
    with (tmp_path / "stderr.txt").open("w") as stderr:
        run = subprocess.Popen([*command, str(port)], stdout=subprocess.DEVNULL, stderr=stderr, env=SUBPROCESS_ENV)
        wait_while_running(run, lambda: viewer_answers(port), "the viewer answers")
        run.send_signal(signal.SIGINT)
        finish(run, "the viewer after Ctrl-C")
    assert run.returncode == 130
    assert said(read(tmp_path / "stderr.txt")) == [], "Ctrl-C is how it ends: nothing to explain"


def test_the_default_device_without_a_gpu_is_one_line_saying_to_add_the_cpu_option(tmp_path):
    command = ns_train_command(tmp_path, "no-gpu", [], ["continual-demo"])
    device = command.index("--machine.device-type")
    del command[device : device + 2]  # the README's command for one's own images names no device
    run = run_ns_train(command)
    assert run.returncode != 0
    assert said(run.stderr) == [
        "continual-ngp: error: --machine.device-type cuda (the default): torch finds no CUDA GPU here; add "
        "--machine.device-type cpu to train on the CPU"
    ]
    assert not (tmp_path / "unnamed").exists(), "a run that cannot start leaves no run folder"


def test_the_demo_scene_s_options_are_in_its_subcommand_s_help():
    ns_train = str(Path(sys.executable).with_name("ns-train"))
    shown = subprocess.run(
        [ns_train, "continual-ngp", "continual-demo", "--help"],
        capture_output=True,
        text=True,
        timeout=RUN_TIMEOUT,
        check=False,
    )
    assert shown.returncode == 0, shown.stderr[-2000:]
    assert "--num-frames" in shown.stdout and "--scene" in shown.stdout
