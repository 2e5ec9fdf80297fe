"""The viewer's "Continual learning" panel: the open task, its progress, the latest accuracy-matrix row, and the
controls "Next task now" and "Pause after this task". Everything else (live render, render and export tabs,
pause/resume) is nerfstudio's viewer unchanged.

The Trainer builds the panel when the viewer runs (as nerfstudio's Trainer builds its viewer); the panel reads the
pipeline's `ContinualStatus` and never imports the pipeline.
"""

from __future__ import annotations

import time
from typing import TYPE_CHECKING, Callable, List, Optional, Tuple

from nerfstudio.engine.callbacks import TrainingCallback, TrainingCallbackLocation
from nerfstudio.utils.rich_utils import CONSOLE
from nerfstudio.viewer.viewer import Viewer
from nerfstudio.viewer.viewer_elements import ViewerButton, ViewerCheckbox, ViewerElement, ViewerText

from continual_nerf.core.continual_dataset import ContinualDataset
from continual_nerf.nerfstudio_compat import init_scene_without_frustums, panel_order, show_resume_button
from continual_nerf.viewer.task_cameras import TaskCameras

if TYPE_CHECKING:
    from nerfstudio.engine.trainer import Trainer

    from continual_nerf.core.continual_pipeline import ContinualStatus

REFRESH_SECONDS = 0.25
"""The panel's progress is rewritten at most this often."""
PANEL_LABEL = "Continual learning"
"""Title of the panel's folder in the viewer."""


def task_text(status: ContinualStatus) -> str:
    """ "k of N"; while a capture is still running, N counts the task being captured and may grow."""
    text = f"{status.current_task + 1} of {status.known_tasks}"
    return f"{text}+ (capture running)" if status.capture_running else text


def psnr_text(psnr_rows: List[List[float]]) -> str:
    """The latest accuracy-matrix row: test PSNR of every task seen so far."""
    if not psnr_rows:
        return "measured when task 1 ends"
    return f"after task {len(psnr_rows)}: " + " | ".join(f"{value:.2f}" for value in psnr_rows[-1])


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
    ) -> None:
        self.status = status
        self.dataset = dataset
        """The training dataset: a streaming run replaces it whenever a task arrives."""
        self.task = ViewerText("Task", "", disabled=True, hint="Open task, of the tasks known so far")
        self.progress = ViewerText("Progress", "", disabled=True, hint="Budget of the open task")
        self.psnr = ViewerText("Test PSNR (dB)", "", disabled=True, hint="Latest accuracy-matrix row: PSNR per task")
        self.next_task = ViewerButton("Next task now", cb_hook=lambda _: request_next_task())
        self.pause_after_task = ViewerCheckbox(
            "Pause after this task", False, hint="Pause training when the open task ends; Resume Training goes on"
        )
        self.viewer: Optional[Viewer] = None
        self.cameras: Optional[TaskCameras] = None
        self.shown: Optional[Tuple[int, Optional[int]]] = None
        """(open task, task whose pixels the dataset holds) when the frustums were last drawn."""
        self._refreshed = 0.0

    @property
    def elements(self) -> Tuple[ViewerElement, ...]:
        return (self.task, self.progress, self.psnr, self.next_task, self.pause_after_task)

    def attach(self, viewer: Viewer, trainer: Trainer) -> None:
        """Set up `viewer`'s scene with the released tasks only, and install the panel."""
        init_scene_without_frustums(viewer, self.dataset(), trainer.training_state)
        self.viewer = viewer
        self.cameras = TaskCameras(viewer, len(self.dataset()))
        # between nerfstudio's status lines and its tabs, so it shows without scrolling
        with viewer.viser_server.gui.add_folder(PANEL_LABEL, order=panel_order(viewer)):
            for element in self.elements:
                element.install(viewer.viser_server)
        self._show_task()

    def training_callbacks(self, trainer: Trainer) -> List[TrainingCallback]:
        """Callbacks to run after the pipeline's task switch in every iteration."""
        return [
            TrainingCallback([TrainingCallbackLocation.AFTER_TRAIN_ITERATION], self._after_iteration, args=[trainer]),
            TrainingCallback([TrainingCallbackLocation.AFTER_TRAIN], self._after_training),
        ]

    def _after_iteration(self, trainer: Trainer, step: int) -> None:
        shown = self.shown
        if (self.status().current_task, self.dataset().open_task) != shown:
            self._show_task()
            if shown is not None and self.status().current_task != shown[0]:
                self._pause_if_asked(trainer)
        elif time.monotonic() - self._refreshed >= REFRESH_SECONDS:
            self.refresh()

    def _after_training(self, step: int) -> None:
        self.refresh()
        self.progress.value = "training finished"

    def _show_task(self) -> None:
        current_task, dataset = self.status().current_task, self.dataset()
        self.shown = (current_task, dataset.open_task)
        if self.cameras is not None:
            self.cameras.show(dataset, current_task)
        self.refresh()

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
        """Rewrite the panel's texts from the pipeline's status."""
        status = self.status()
        self.task.value = task_text(status)
        self.progress.value = status.progress
        self.psnr.value = psnr_text(status.psnr_rows)
        self._refreshed = time.monotonic()
