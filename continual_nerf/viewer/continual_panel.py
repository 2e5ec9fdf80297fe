"""The viewer's "Continual learning" panel: the open task and its progress (or the set-up stage before training),
the task colours, the accuracy matrix as a picture with the latest mean PSNR, and the controls "Next task now",
"Pause after this task" and "Follow the newest task". Everything else (live render, render and export tabs,
pause/resume) is nerfstudio's viewer.

The viewer's trainer (live_trainer.py) builds the panel when the viewer runs (as nerfstudio's Trainer builds its
viewer) and installs it before the viewer's page first answers; the panel reads the pipeline's `ContinualStatus` and
never imports the pipeline.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import TYPE_CHECKING, Callable, List, Optional, Sequence, Tuple

import viser
from nerfstudio.engine.callbacks import TrainingCallback, TrainingCallbackLocation
from nerfstudio.utils.rich_utils import CONSOLE
from nerfstudio.viewer.viewer import Viewer
from nerfstudio.viewer.viewer_elements import ViewerButton, ViewerCheckbox, ViewerDropdown, ViewerElement, ViewerText

from continual_nerf.core.continual_dataset import ContinualDataset
from continual_nerf.nerfstudio_compat import (
    disable_training_buttons,
    init_scene_without_frustums,
    panel_order,
    set_render_defaults,
    show_resume_button,
    show_step,
)
from continual_nerf.viewer.pictures import accuracy_markdown, legend_markdown
from continual_nerf.viewer.task_cameras import TaskCameras, View, framing_view
from continual_nerf.viewer.viewer_config import ContinualViewerConfig

if TYPE_CHECKING:
    from nerfstudio.engine.trainer import Trainer

    from continual_nerf.core.continual_pipeline import ContinualStatus

REFRESH_SECONDS = 0.25
"""The panel's progress is rewritten at most this often."""
PANEL_LABEL = "Continual learning"
"""Title of the panel's folder in the viewer."""
PROGRESS_LABEL = "Progress:"
"""Start of the panel's progress line."""
FINISHED = "training finished"
"""The progress line once training has ended."""
PAUSED = "paused"
"""Start of the progress line while training is paused."""
NO_ROW_YET = "measured when task 1 ends"
"""What the accuracy fields say before the first task has ended."""
MARKDOWN_ROOT = Path(__file__).parent
"""viser warns about markdown without an image root; the pictures are data URLs, read from nowhere."""
PICTURES = ("test PSNR", "depth abs rel")
"""What the accuracy picture can show: the tasks' test PSNR, or their rendered depth's error (captures with depth)."""


def task_text(status: ContinualStatus) -> str:
    """ "k of N"; while a capture is still running, N counts the task being captured and may grow."""
    text = f"{status.current_task + 1} of {status.known_tasks}"
    return f"{text}+ (capture running)" if status.capture_running else text


def mean_psnr_text(mean_psnr: Sequence[float]) -> str:
    """The latest mean test PSNR over the tasks seen so far."""
    if not mean_psnr:
        return NO_ROW_YET
    return f"{mean_psnr[-1]:.2f} dB after task {len(mean_psnr)}"


def accuracy_rows(status: ContinualStatus, picture: str) -> Tuple[List[List[Optional[float]]], bool]:
    """The rows the accuracy picture draws, and whether they are depth errors: PSNR unless depth is chosen and the
    capture has depth maps."""
    depth = picture == PICTURES[1] and bool(status.depth_rows)
    return (status.depth_rows if depth else [list(row) for row in status.psnr_rows]), depth


def frame_view(client: viser.ClientHandle, view: View) -> None:
    """Move a browser's camera to `view`."""
    with client.atomic():
        client.camera.up_direction = view.up
        client.camera.position = view.position
        client.camera.look_at = view.look_at


class TaskPictures:
    """The legend of the task colours and the accuracy-matrix heat map, redrawn only when they change."""

    def __init__(self, server: viser.ViserServer) -> None:
        self.legend = server.gui.add_markdown("", image_root=MARKDOWN_ROOT)
        self.accuracy = server.gui.add_markdown("", image_root=MARKDOWN_ROOT)
        self._drawn: Tuple[int, Optional[Sequence[Sequence[Optional[float]]]], bool] = (0, None, False)

    def show(self, num_tasks: int, psnr_rows: Sequence[Sequence[Optional[float]]], depth: bool = False) -> None:
        """Draw the rows of PSNR (or, `depth`, of depth errors) that changed since the last drawing."""
        drawn_tasks, drawn_rows, drawn_depth = self._drawn
        if num_tasks != drawn_tasks:
            self.legend.content = legend_markdown(num_tasks)
        if psnr_rows and (psnr_rows != drawn_rows or num_tasks != drawn_tasks or depth != drawn_depth):
            self.accuracy.content = accuracy_markdown(psnr_rows, num_tasks, depth)
        self._drawn = (num_tasks, psnr_rows, depth)


class ContinualPanel:
    """The viewer's "Continual learning" folder, and the frustums of the released tasks.

    The elements are nerfstudio ViewerElements. The panel is a plain object, not an nn.Module, so nerfstudio's
    scan for "Custom Elements" passes it by; it installs its elements itself, above the viewer's tabs.
    """

    def __init__(
        self,
        status: Callable[[], ContinualStatus],
        request_next_task: Callable[[], None],
        dataset: Callable[[], ContinualDataset],
        options: ContinualViewerConfig,
        paused: Callable[[], bool] = lambda: False,
    ) -> None:
        self.status = status
        self.paused = paused
        """Whether training is paused (nerfstudio's Pause Training, "Pause after this task"), or about to pause."""
        self.dataset = dataset
        """The training dataset: a streaming run replaces it whenever a task arrives."""
        self.options = options
        self.task = ViewerText("Task", "", disabled=True, hint="Open task, of the tasks known so far")
        self.mean_psnr = ViewerText(
            "Mean test PSNR", NO_ROW_YET, disabled=True, hint="Over the test frames of every task seen so far"
        )
        self.picture = ViewerDropdown(
            "Accuracy picture",
            PICTURES[0],
            list(PICTURES),
            cb_hook=lambda _: self.refresh(),
            hint="What the accuracy matrix shows: test PSNR, or the rendered depth's error (captures with depth maps)",
        )
        self.next_task = ViewerButton("Next task now", cb_hook=lambda _: request_next_task())
        self.pause_after_task = ViewerCheckbox(
            "Pause after this task", False, hint="Pause training when the open task ends; Resume Training goes on"
        )
        self.follow = ViewerCheckbox(
            "Follow the newest task",
            options.follow_newest_task,
            cb_hook=lambda _: self._follow(),
            hint="Move the view to each task as it is released",
        )
        self.progress: Optional[viser.GuiMarkdownHandle] = None
        """Set-up stage, then the open task's budget: a markdown line, which wraps where a text field would cut."""
        self.viewer: Optional[Viewer] = None
        self.cameras: Optional[TaskCameras] = None
        self.pictures: Optional[TaskPictures] = None
        self.shown: Optional[Tuple[int, Optional[int]]] = None
        """(open task, task whose pixels the dataset holds) when the frustums were last drawn."""
        self.stage: Optional[str] = None
        """What set-up is doing while training has not started; None once it has."""
        self.finished = False
        """Whether training has ended."""
        self._refreshed = 0.0

    @property
    def elements(self) -> Tuple[ViewerElement, ...]:
        return (self.task, self.mean_psnr, self.picture, self.next_task, self.pause_after_task, self.follow)

    def install(self, viewer: Viewer, training_state: str) -> None:
        """Set up `viewer`'s scene with the released tasks only, and install the panel (as soon as the viewer runs)."""
        dataset = self.dataset()
        init_scene_without_frustums(viewer, dataset, training_state)
        set_render_defaults(viewer, self.options.max_res, self.options.train_util)
        self.viewer = viewer
        self.cameras = TaskCameras(viewer, dataset, self.options.camera_frustum_scale)
        server = viewer.viser_server
        # between nerfstudio's status lines and its tabs, so it shows without scrolling
        with server.gui.add_folder(PANEL_LABEL, order=panel_order(viewer)):
            self.task.install(server)
            self.progress = server.gui.add_markdown("")
            self.pictures = TaskPictures(server)
            for element in self.elements[1:]:
                element.install(server)
        server.on_client_connect(self._frame_new_client)
        self._show_task()

    def show_stage(self, stage: Optional[str]) -> None:
        """Say what set-up is doing (the Trainer calls this before training starts); None: training has started."""
        self.stage = stage
        self.refresh()

    def training_callbacks(self, trainer: Trainer) -> List[TrainingCallback]:
        """Callbacks to run after the pipeline's task switch in every iteration."""
        return [
            TrainingCallback([TrainingCallbackLocation.AFTER_TRAIN_ITERATION], self._after_iteration, args=[trainer]),
            TrainingCallback([TrainingCallbackLocation.AFTER_TRAIN], self._after_training),
        ]

    def _after_iteration(self, trainer: Trainer, step: int) -> None:
        self.stage = None
        shown, current_task = self.shown, self.status().current_task
        task_changed = (current_task, self.dataset().open_task) != shown
        if not task_changed and time.monotonic() - self._refreshed < REFRESH_SECONDS:
            return
        if task_changed:
            self._show_task()
            if shown is not None and current_task != shown[0]:
                self._follow()
                self._pause_if_asked(trainer)
        else:
            self.refresh()
        if self.viewer is not None:
            show_step(self.viewer, step)

    def _after_training(self, step: int) -> None:
        self.finished = True
        self.refresh()
        for control in (self.next_task, self.pause_after_task, self.follow):
            control.set_disabled(True)
        if self.viewer is not None:
            show_step(self.viewer, step)
            disable_training_buttons(self.viewer)

    def _show_task(self) -> None:
        current_task, dataset = self.status().current_task, self.dataset()
        self.shown = (current_task, dataset.open_task)
        if self.cameras is not None:
            self.cameras.show(dataset, current_task)
        self.refresh()

    def _view(self, client: viser.ClientHandle) -> View:
        """The newest task's cameras when following it, else every camera known so far."""
        dataset = self.dataset()
        frames = range(len(dataset))
        if self.follow.value:
            frames = dataset.frames_of_task(self.status().current_task).tolist()
        return framing_view(dataset, frames, client.camera.fov)

    def _frame_new_client(self, client: viser.ClientHandle) -> None:
        frame_view(client, self._view(client))

    def _follow(self) -> None:
        if self.viewer is None or not self.follow.value:
            return
        for client in self.viewer.viser_server.get_clients().values():
            frame_view(client, self._view(client))

    def _pause_if_asked(self, trainer: Trainer) -> None:
        """At a task boundary, pause the Trainer when "Pause after this task" is ticked (then untick it)."""
        if self.viewer is None or not self.pause_after_task.value or trainer.stop_training:
            return
        trainer.training_state = "paused"
        show_resume_button(self.viewer)
        self.pause_after_task.value = False
        CONSOLE.print(
            f"[bold]Paused before task {self.status().current_task + 1}: press Resume Training in the viewer to go on"
        )

    def refresh(self) -> None:
        """Rewrite the panel's texts and pictures from the pipeline's status."""
        status = self.status()
        self.task.value = task_text(status)
        self._show_progress(self._progress_text(status.progress))
        self.mean_psnr.value = mean_psnr_text(status.mean_psnr)
        if self.pictures is not None:
            self.pictures.show(status.known_tasks, *accuracy_rows(status, self.picture.value))
        self._refreshed = time.monotonic()

    def _progress_text(self, progress: str) -> str:
        """The progress line: set-up stage, the open task's budget, or that training is paused or finished."""
        if self.finished:
            return FINISHED
        if self.paused() and self.stage is not None:
            return f"{PAUSED} before training starts; Resume Training starts it"
        if self.paused():
            return f"{PAUSED} ({progress}); Resume Training goes on"
        return progress if self.stage is None else f"setting up: {self.stage}"

    def _show_progress(self, text: str) -> None:
        if self.progress is not None:
            self.progress.content = f"{PROGRESS_LABEL} {text}"
