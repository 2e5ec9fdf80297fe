"""The live viewer in a real browser: headless Chromium drives the continual panel of a CPU training run, from set-up
to the end of training, and the viewer of a finished run (continual-nerf-viewer) task by task."""

from __future__ import annotations

import io
import os
import threading
import time
from pathlib import Path
from typing import Dict, Iterator

import numpy as np
import pytest
import torch
from helpers import demo_parser, tiny_config, train
from PIL import Image
from viser._messages import CameraFrustumMessage, RemoveSceneNodeMessage

from continual_nerf.bench.browser import CHROMIUM, DevTools, free_port, viewer_answers, wait_for
from continual_nerf.checkpoints import read_checkpoint
from continual_nerf.core import continual_trainer
from continual_nerf.core.accuracy_matrix import ACCURACY_MATRIX_FILENAME, AccuracyMatrix
from continual_nerf.core.continual_trainer import ContinualTrainerConfig
from continual_nerf.plots import task_colour
from continual_nerf.viewer.continual_panel import FINISHED, PANEL_LABEL, PAUSED, PROGRESS_LABEL
from continual_nerf.viewer.live_trainer import LiveViewerTrainer
from continual_nerf.viewer.pictures import ACCURACY_ALT, DISPLAY_WIDTH
from continual_nerf.viewer.run_viewer import CHECKPOINT_LABEL, RENDERING, ContinualRunViewer
from continual_nerf.viewer.viewer_config import DEFAULT_MAX_RES, DEFAULT_TRAIN_UTIL, ContinualViewerConfig

pytestmark = pytest.mark.slow  # trains models, runs subprocesses or a browser

NUM_TASKS = 3


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


def live_config(tmp_path: Path) -> ContinualTrainerConfig:
    """A CPU run with the viewer (the continual methods' viewer defaults) on a free port; tasks end only when asked."""
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
    config.save_config()
    return config


class InThread:
    """A call run in a thread; `join` re-raises what it raised."""

    def __init__(self, call) -> None:
        self.failure: list = []
        self.thread = threading.Thread(target=self._run, args=[call], daemon=True)
        self.thread.start()

    def _run(self, call) -> None:
        try:
            call()
        except BaseException as error:  # re-raised by join
            self.failure.append(error)

    def join(self, timeout: float = 120) -> None:
        self.thread.join(timeout=timeout)
        assert not self.thread.is_alive(), "still running"
        if self.failure:
            raise self.failure[0]


def frustums(viewer) -> Dict[str, CameraFrustumMessage]:
    """The camera frustums in the viser server's scene state: what every browser that connects is sent."""
    buffer = viewer.viser_server._websock_server._broadcast_buffer
    with buffer.buffer_lock:
        messages = [buffer.message_from_id[number] for number in sorted(buffer.message_from_id)]
    shown: Dict[str, CameraFrustumMessage] = {}
    for message in messages:  # in the order sent: a removal cancels the frustum drawn before it
        if isinstance(message, CameraFrustumMessage) and message.name.startswith("/cameras/"):
            shown[message.name] = message
        elif isinstance(message, RemoveSceneNodeMessage):
            shown.pop(message.name, None)
    return shown


def colour_number(task: int) -> int:
    red, green, blue = task_colour(task)
    return (red << 16) | (green << 8) | blue


def pixels_of_colour(png: bytes, task: int, tolerance: int = 40) -> int:
    """Pixels of a screenshot within `tolerance` of the task's colour in every channel."""
    image = np.asarray(Image.open(io.BytesIO(png)).convert("RGB")).astype(int)
    return int((np.abs(image - np.array(task_colour(task))).max(axis=-1) <= tolerance).sum())


def line(chromium: DevTools, label: str) -> str:
    """The panel's line that starts with `label`, without it."""
    lines = [text for text in chromium.page_text().splitlines() if text.startswith(label)]
    return lines[0][len(label) :].strip() if lines else ""


def progress(chromium: DevTools) -> str:
    """The panel's progress line."""
    return line(chromium, PROGRESS_LABEL)


def test_live_viewer_from_set_up_to_the_end_of_training(chromium, tmp_path, monkeypatch):
    config = live_config(tmp_path)
    port = config.viewer.websocket_port
    url = f"http://127.0.0.1:{port}"
    viewer_started, panel_may_come = threading.Event(), threading.Event()
    page_saw_set_up = threading.Event()
    real_warm_up, real_extend_viewer = continual_trainer.warm_up, LiveViewerTrainer.extend_viewer

    def extend_viewer_once_checked(trainer, viewer):
        # set-up holds between nerfstudio's viewer and the panel while the test asks for the page
        viewer_started.set()
        assert panel_may_come.wait(timeout=120), "the test never let the panel come"
        real_extend_viewer(trainer, viewer)

    def warm_up_until_seen(model, num_rays, progress, **options):
        # set-up holds here, in the compile stage, until the page has shown it: no race with a fast set-up
        progress("training pass 1 of 2")
        assert page_saw_set_up.wait(timeout=120), "the page never showed the set-up stage"
        real_warm_up(model, num_rays, progress=progress, **options)

    monkeypatch.setattr(continual_trainer, "warm_up", warm_up_until_seen)
    monkeypatch.setattr(LiveViewerTrainer, "extend_viewer", extend_viewer_once_checked)
    trainer = config.setup(local_rank=0, world_size=1)
    set_up = InThread(trainer.setup)
    wait_for("nerfstudio's viewer to start", viewer_started.is_set)
    assert not viewer_answers(port), "the page answered before the continual panel was in it"
    panel_may_come.set()
    wait_for("the viewer to answer", lambda: viewer_answers(port))
    chromium.navigate(url)
    wait_for("the panel", lambda: PANEL_LABEL in chromium.page_text())
    # the continual defaults came before the panel: the page never shows nerfstudio's
    assert chromium.input_value("Max res") == str(DEFAULT_MAX_RES)
    assert chromium.input_value("Train Util") == str(DEFAULT_TRAIN_UTIL)
    wait_for("the panel in the set-up stage", lambda: progress(chromium).startswith("setting up: compiling"))
    assert PANEL_LABEL in chromium.page_text()
    assert chromium.input_value("Task") == f"1 of {NUM_TASKS}"
    chromium.screenshot(tmp_path / "viewer_set_up.png")
    page_saw_set_up.set()
    set_up.join()

    training = InThread(trainer.train)
    try:
        drive_live_run(chromium, trainer, tmp_path)
    finally:
        trainer.stop_training = True
        training.join()
        trainer.shutdown()


def drive_live_run(chromium: DevTools, trainer: LiveViewerTrainer, tmp_path: Path) -> None:
    dataset = trainer.pipeline.datamanager.train_dataset
    frames_of = [set(dataset.frames_of_task(task).tolist()) for task in range(NUM_TASKS)]
    wait_for("training to start", lambda: progress(chromium).startswith("iteration"))
    assert len(frustums(trainer.viewer_state)) == len(frames_of[0]), "only task 1's cameras are released"
    assert chromium.input_value("Mean test PSNR") == "measured when task 1 ends"

    chromium.click_button("Next task now")
    wait_for("the panel to show task 2", lambda: chromium.input_value("Task") == f"2 of {NUM_TASKS}")
    # the new task's images go into its frustums once its pixels are loaded, at its first batch
    wait_for(
        "task 2's frustums with images",
        lambda: all(
            message.image_binary is not None
            for name, message in frustums(trainer.viewer_state).items()
            if int(name.split("_")[-1]) in frames_of[1]
        ),
    )
    shown = frustums(trainer.viewer_state)
    assert {int(name.split("_")[-1]) for name in shown} == frames_of[0] | frames_of[1], "tasks 1 and 2, not 3"
    for name, message in shown.items():
        task = 0 if int(name.split("_")[-1]) in frames_of[0] else 1
        assert message.color == colour_number(task)
        assert (message.image_binary is not None) == (task == 1), "the open task is drawn with its images"
    wait_for("task 1's accuracy picture", lambda: ACCURACY_ALT in chromium.images())
    first_picture = chromium.images()[ACCURACY_ALT]
    assert chromium.image_width(ACCURACY_ALT) == DISPLAY_WIDTH, "shown at the width its fonts are sized for"
    mean = trainer.pipeline.accuracy.mean_psnr[0]
    assert chromium.input_value("Mean test PSNR") == f"{mean:.2f} dB after task 1"
    # the default view (framing the trajectory, frustums sized by it, not hidden by the render) shows both colours
    wait_for(
        "frustums of tasks 1 and 2 in the screenshot",
        lambda: min(pixels_of_colour(chromium.screenshot_png(), task) for task in (0, 1)) >= 20,
    )
    chromium.screenshot(tmp_path / "viewer_task2.png")

    chromium.click_button("Pause Training")
    wait_for("the progress line to say paused", lambda: progress(chromium).startswith(PAUSED))
    chromium.click_button("Resume Training")
    wait_for("the progress line to count iterations again", lambda: progress(chromium).startswith("iteration"))

    chromium.click_input("Pause after this task")
    wait_for("the tick to reach the server", lambda: trainer.panel.pause_after_task.value)
    chromium.click_button("Next task now")
    wait_for("training to pause after task 2", lambda: trainer.training_state == "paused")
    wait_for("the panel to show task 3", lambda: chromium.input_value("Task") == f"3 of {NUM_TASKS}")
    assert len(frustums(trainer.viewer_state)) == sum(len(frames) for frames in frames_of)
    wait_for("the accuracy picture of task 2", lambda: chromium.images().get(ACCURACY_ALT) != first_picture)
    wait_for("nerfstudio's Resume Training button", lambda: "Resume Training" in chromium.page_text())
    assert progress(chromium).startswith(PAUSED), "the progress line says training is paused"
    step = trainer.step
    time.sleep(1.0)
    assert trainer.step == step and trainer.pipeline.budget.iterations_done == 0, "paused at the task boundary"
    assert not trainer.panel.pause_after_task.value, "a one-off: unticked once it paused"
    wait_for("the tick to clear on the page", lambda: not chromium.input_checked("Pause after this task"))
    chromium.screenshot(tmp_path / "viewer_paused_before_task3.png")

    chromium.click_button("Resume Training")
    chromium.click_button("Next task now")  # the last task: training ends
    wait_for("the end of training", lambda: progress(chromium) == FINISHED)
    wait_for("the controls to be disabled", lambda: chromium.button_disabled("Next task now"))
    assert chromium.button_disabled("Pause Training")
    assert chromium.input_disabled("Pause after this task") and chromium.input_disabled("Follow the newest task")
    assert f"Step: {trainer.step}" in chromium.page_text(), "nerfstudio's step counter follows training"


def test_finished_run_viewer_loads_the_checkpoint_of_the_chosen_task(chromium, tmp_path):
    config = tiny_config(
        tmp_path / "outputs", demo_parser(num_frames=24, width=32, height=24), num_tasks=2, iterations_per_task=20
    )
    train(config)
    run_dir = config.get_base_dir()
    accuracy = AccuracyMatrix.read(run_dir / ACCURACY_MATRIX_FILENAME)
    options = ContinualViewerConfig(websocket_port=free_port())
    travel = ContinualRunViewer(run_dir / "config.yml", viewer=options).start()
    renders_released = threading.Event()
    render = travel.pipeline.model.get_outputs_for_camera

    def held_while_the_line_says_rendering(camera, **options):
        while travel.rendering is not None and not renders_released.is_set():  # the viewer can interrupt it here
            time.sleep(0.05)
        return render(camera, **options)

    travel.pipeline.model.get_outputs_for_camera = held_while_the_line_says_rendering

    def checkpoint_line() -> str:
        """The checkpoint line on the page and in the viewer, for a wait's message."""
        return f"page {line(chromium, CHECKPOINT_LABEL)!r}, viewer {travel.checkpoint.content!r}"

    try:
        chromium.navigate(f"http://127.0.0.1:{options.websocket_port}")
        wait_for("the task slider", lambda: chromium.input_value("Task") == "2", seen=checkpoint_line)
        assert line(chromium, CHECKPOINT_LABEL) == f"end of task 2, step-{accuracy.steps[1]:09d}.ckpt"
        assert not chromium.text_cut_off(CHECKPOINT_LABEL)
        assert ACCURACY_ALT in chromium.images()
        assert chromium.input_value("Mean test PSNR") == f"{accuracy.mean_psnr[1]:.2f} dB after task 2"
        assert {message.color for message in frustums(travel.viewer).values()} == {colour_number(0), colour_number(1)}
        wait_for("a render", lambda: "Resolution: 0x0px" not in chromium.page_text())
        time.sleep(3)  # the browser draws the render
        after_task_2 = chromium.screenshot_png()

        chromium.set_slider("Task", 1)
        task_1 = f"end of task 1, step-{accuracy.steps[0]:09d}.ckpt"
        wait_for(
            "the page to say task 1's view renders",
            lambda: line(chromium, CHECKPOINT_LABEL).startswith(f"{task_1}, {RENDERING}"),
            seen=checkpoint_line,
        )
        renders_released.set()
        wait_for(
            "the page to say task 1's view has rendered",
            lambda: line(chromium, CHECKPOINT_LABEL) == task_1,
            seen=checkpoint_line,
        )
        end_of_task_1 = read_checkpoint(run_dir / "nerfstudio_models" / f"step-{accuracy.steps[0]:09d}.ckpt")
        for name, value in travel.pipeline.model.state_dict().items():
            if isinstance(value, torch.Tensor):
                assert torch.equal(value, end_of_task_1["pipeline"][f"_model.{name}"]), name
        task_1_mean = f"{accuracy.mean_psnr[0]:.2f} dB after task 1"
        wait_for("task 1's mean on the page", lambda: chromium.input_value("Mean test PSNR") == task_1_mean)
        wait_for("task 1's render on the page", lambda: chromium.screenshot_png() != after_task_2)
        task_1_frames = set(travel.dataset.frames_of_task(0).tolist())
        wait_for(
            "the cameras of task 1 only",
            lambda: {int(name.split("_")[-1]) for name in frustums(travel.viewer)} == task_1_frames,
        )
    finally:
        travel.viewer.viser_server.stop()


def test_a_wait_that_times_out_says_what_it_saw_last():
    with pytest.raises(AssertionError, match="waiting for task 1; last seen: 'end of task 2'"):
        wait_for("task 1", lambda: False, timeout=0.5, seen=lambda: "end of task 2")
