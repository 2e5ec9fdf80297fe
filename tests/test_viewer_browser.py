"""The live viewer in a real browser: headless Chromium drives the continual panel of a CPU training run."""

from __future__ import annotations

import base64
import itertools
import json
import os
import shutil
import socket
import subprocess
import threading
import time
import urllib.request
from pathlib import Path
from typing import Any, Callable, Dict, Iterator, Optional

import numpy as np
import pytest
import websocket
from helpers import demo_parser, tiny_config
from viser._messages import CameraFrustumMessage

from continual_nerf.core.continual_trainer import ContinualTrainer
from continual_nerf.viewer.continual_panel import PANEL_LABEL
from continual_nerf.viewer.task_cameras import task_colour

pytestmark = pytest.mark.slow  # trains models, runs subprocesses or a browser

CHROMIUM = shutil.which("chromium") or "/usr/bin/chromium"
CHROMIUM_FLAGS = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--window-size=1200,800",
    "--remote-debugging-port=0",
]
"""Headless, offline, and with DevTools on a port Chromium picks (it writes it to <profile>/DevToolsActivePort)."""
NUM_TASKS = 3
PSNR = "Test PSNR (dB)"
"""Label of the panel's accuracy-matrix row."""

INPUT_BY_LABEL = """(label) => {
    const element = [...document.querySelectorAll('label')].find(l => l.textContent.trim() === label);
    if (!element) return null;
    return document.getElementById(element.htmlFor) || element.closest('.mantine-Flex-root').querySelector('input');
}"""
"""The GUI input viser labels with `label`: the label's target, else the input in the label's row."""


class DevTools:
    """Chromium driven through the DevTools protocol over its websocket (no browser download, no Playwright)."""

    def __init__(self, profile: Path) -> None:
        self.process = subprocess.Popen(
            [CHROMIUM, *CHROMIUM_FLAGS, f"--user-data-dir={profile}", "about:blank"],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
        port = self._devtools_port(profile / "DevToolsActivePort")
        pages = json.loads(urllib.request.urlopen(f"http://127.0.0.1:{port}/json/list", timeout=10).read())
        page = next(target for target in pages if target["type"] == "page")
        self.socket = websocket.create_connection(page["webSocketDebuggerUrl"], timeout=60, suppress_origin=True)
        self.ids = itertools.count(1)

    def _devtools_port(self, port_file: Path) -> int:
        deadline = time.monotonic() + 30
        while not (port_file.exists() and port_file.read_text().strip()):
            assert self.process.poll() is None, f"{CHROMIUM} exited with {self.process.returncode}"
            assert time.monotonic() < deadline, f"{CHROMIUM} did not open its DevTools port"
            time.sleep(0.1)
        return int(port_file.read_text().split()[0])

    def call(self, method: str, **params: Any) -> Dict[str, Any]:
        number = next(self.ids)
        self.socket.send(json.dumps({"id": number, "method": method, "params": params}))
        while True:
            message = json.loads(self.socket.recv())
            if message.get("id") == number:
                assert "error" not in message, f"{method}: {message['error']}"
                return message["result"]

    def evaluate(self, expression: str) -> Any:
        result = self.call("Runtime.evaluate", expression=expression, returnByValue=True)
        assert "exceptionDetails" not in result, result["exceptionDetails"]
        return result["result"].get("value")

    def input_value(self, label: str) -> Optional[str]:
        return self.evaluate(f"(() => {{ const i = ({INPUT_BY_LABEL})({json.dumps(label)}); return i && i.value; }})()")

    def input_checked(self, label: str) -> bool:
        return self.evaluate(f"({INPUT_BY_LABEL})({json.dumps(label)}).checked")

    def click_input(self, label: str) -> None:
        assert self.evaluate(f"(() => {{ ({INPUT_BY_LABEL})({json.dumps(label)}).click(); return true; }})()")

    def click_button(self, text: str) -> None:
        find = f"[...document.querySelectorAll('button')].find(b => b.textContent.trim() === {json.dumps(text)})"
        clicked = self.evaluate(f"(() => {{ const b = {find}; if (b) b.click(); return !!b; }})()")
        assert clicked, f"no button {text!r} on the page"

    def page_text(self) -> str:
        return self.evaluate("document.body.innerText")

    def screenshot(self, path: Path) -> None:
        path.write_bytes(base64.b64decode(self.call("Page.captureScreenshot", format="png")["data"]))

    def close(self) -> None:
        self.socket.close()
        self.process.terminate()
        self.process.wait(timeout=30)


def wait_for(what: str, condition: Callable[[], Any], timeout: float = 90.0) -> None:
    deadline = time.monotonic() + timeout
    while not condition():
        assert time.monotonic() < deadline, f"timed out after {timeout:g} s waiting for {what}"
        time.sleep(0.2)


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


@pytest.fixture
def chromium(tmp_path: Path) -> Iterator[DevTools]:
    if not os.access(CHROMIUM, os.X_OK):
        message = f"{CHROMIUM} not found: this test needs Debian's chromium (apt-get install -y chromium)"
        if os.environ.get("CONTINUAL_NERF_REQUIRE_BROWSER") == "1":  # CI installs it: there its absence is a failure
            pytest.fail(message)
        pytest.skip(message)
    browser = DevTools(tmp_path / "chromium-profile")
    yield browser
    browser.close()


@pytest.fixture
def live_run(tmp_path: Path) -> Iterator[ContinualTrainer]:
    """A CPU run with the viewer on 127.0.0.1, training in a thread; tasks end only when asked to."""
    config = tiny_config(
        tmp_path / "outputs",
        demo_parser(num_frames=24, width=32, height=24),
        num_tasks=NUM_TASKS,
        iterations_per_task=10**6,
        rays_per_batch=64,
    )
    config.vis = "viewer"
    config.viewer.websocket_port = free_port()
    config.viewer.quit_on_train_completion = True
    config.viewer.camera_frustum_scale = 1.0  # large enough to see in the screenshot
    config.viewer.default_composite_depth = False  # frustums drawn over the render, not hidden in it
    config.save_config()
    trainer = config.setup(local_rank=0, world_size=1)
    trainer.setup()
    failure: list = []
    thread = threading.Thread(target=lambda: _train(trainer, failure), daemon=True)
    thread.start()
    yield trainer
    trainer.stop_training = True
    thread.join(timeout=120)
    trainer.shutdown()
    assert not thread.is_alive() and not failure, failure


def _train(trainer: ContinualTrainer, failure: list) -> None:
    try:
        trainer.train()
    except BaseException as error:  # reported by the fixture
        failure.append(error)


def frustums(trainer: ContinualTrainer) -> Dict[str, CameraFrustumMessage]:
    """The camera frustums in the viser server's scene state: what every browser that connects is sent."""
    buffer = trainer.viewer_state.viser_server._websock_server._broadcast_buffer
    with buffer.buffer_lock:
        messages = list(buffer.message_from_id.values())
    return {m.name: m for m in messages if isinstance(m, CameraFrustumMessage) and m.name.startswith("/cameras/")}


def colour_number(task: int) -> int:
    red, green, blue = task_colour(task)
    return (red << 16) | (green << 8) | blue


def look_from_above(trainer: ContinualTrainer) -> None:
    for client in trainer.viewer_state.viser_server.get_clients().values():
        with client.atomic():
            client.camera.position = np.array([0.0, -14.0, 18.0])
            client.camera.look_at = np.zeros(3)


def test_panel_follows_tasks_and_its_controls_act_on_training(chromium, live_run, tmp_path):
    trainer = live_run
    datamanager = trainer.pipeline.datamanager
    dataset = datamanager.train_dataset
    frames_of = [set(dataset.frames_of_task(task).tolist()) for task in range(NUM_TASKS)]
    chromium.call("Page.navigate", url=f"http://127.0.0.1:{trainer.config.viewer.websocket_port}")
    wait_for("the panel to show task 1", lambda: chromium.input_value("Task") == f"1 of {NUM_TASKS}")
    assert PANEL_LABEL in chromium.page_text()
    assert len(frustums(trainer)) == len(frames_of[0]), "only task 1's cameras are released"

    chromium.click_button("Next task now")
    wait_for("the panel to show task 2", lambda: chromium.input_value("Task") == f"2 of {NUM_TASKS}")
    # the new task's images go into its frustums once its pixels are loaded, at its first batch
    wait_for(
        "task 2's frustums with images",
        lambda: all(
            message.image_binary is not None
            for name, message in frustums(trainer).items()
            if int(name.split("_")[-1]) in frames_of[1]
        ),
    )
    shown = frustums(trainer)
    assert {int(name.split("_")[-1]) for name in shown} == frames_of[0] | frames_of[1], "tasks 1 and 2, not 3"
    for name, message in shown.items():
        task = 0 if int(name.split("_")[-1]) in frames_of[0] else 1
        assert message.color == colour_number(task)
        assert (message.image_binary is not None) == (task == 1), "the open task is drawn with its images"
        assert message.scale > trainer.config.viewer.camera_frustum_scale or task == 0, "and larger"
    wait_for("task 1's PSNR in the panel", lambda: (chromium.input_value(PSNR) or "").startswith("after task 1: "))
    psnr = float(chromium.input_value(PSNR).split(": ")[1])
    assert psnr == pytest.approx(trainer.pipeline.accuracy.psnr[0][0], abs=0.01)
    look_from_above(trainer)
    time.sleep(3)  # the browser draws the moved view and a new render
    chromium.screenshot(tmp_path / "viewer_task2.png")

    chromium.click_input("Pause after this task")
    wait_for("the tick to reach the server", lambda: trainer.panel.pause_after_task.value)
    chromium.click_button("Next task now")
    wait_for("training to pause after task 2", lambda: trainer.training_state == "paused")
    wait_for("the panel to show task 3", lambda: chromium.input_value("Task") == f"3 of {NUM_TASKS}")
    assert len(frustums(trainer)) == sum(len(frames) for frames in frames_of)
    wait_for("nerfstudio's Resume Training button", lambda: "Resume Training" in chromium.page_text())
    step = trainer.step
    time.sleep(1.0)
    assert trainer.step == step and trainer.pipeline.budget.iterations_done == 0, "paused at the task boundary"
    assert not trainer.panel.pause_after_task.value, "a one-off: unticked once it paused"
    wait_for("the tick to clear on the page", lambda: not chromium.input_checked("Pause after this task"))
    chromium.screenshot(tmp_path / "viewer_paused_before_task3.png")
