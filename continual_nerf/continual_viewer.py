"""nerfstudio's viser viewer during a continual run: the released tasks' cameras and a continual-learning panel.

nerfstudio's `Viewer.init_scene` draws a frustum, with its image, for every training frame at the start; in the
continual setting the frames of later tasks have not arrived yet and the pixels of closed tasks are gone. Here the
frustums of a task appear when it is released, in the task's colour; the open task's are drawn larger and carry
their images, which are dropped (the frustums redrawn plain) when the task closes, like its pixels. The panel shows the open task, its progress and the latest accuracy-matrix row, and has the two
controls "Next task now" and "Pause after this task". Everything else (live render, render and export tabs,
pause/resume) is nerfstudio's viewer unchanged.
"""

from __future__ import annotations

import dataclasses
import math
import time
from functools import partial
from typing import TYPE_CHECKING, Dict, List, Optional, Tuple

import numpy as np
import torch
import viser
import viser.transforms as vtf
from matplotlib import colormaps
from nerfstudio.engine.callbacks import TrainingCallback, TrainingCallbackLocation
from nerfstudio.utils.rich_utils import CONSOLE
from nerfstudio.viewer.viewer import VISER_NERFSTUDIO_SCALE_RATIO, Viewer
from nerfstudio.viewer.viewer_elements import ViewerButton, ViewerCheckbox, ViewerElement, ViewerText

from continual_nerf.continual_datamanager import ContinualDataManager
from continual_nerf.continual_dataset import ContinualDataset
from continual_nerf.streaming_datamanager import StreamingDataManager

if TYPE_CHECKING:
    from nerfstudio.engine.trainer import Trainer

    from continual_nerf.continual_pipeline import ContinualPipeline

OPEN_TASK_SCALE = 1.6
"""Frustums of the open task are drawn this much larger than those of earlier tasks."""
THUMBNAIL_HEIGHT = 100
"""Height in pixels of the images shown in the open task's frustums (nerfstudio's viewer uses 100 too)."""
REFRESH_SECONDS = 0.25
"""The panel's progress is rewritten at most this often."""
PANEL_LABEL = "Continual learning"
"""Title of the panel's folder in the viewer."""


def task_colour(task: int) -> Tuple[int, int, int]:
    """RGB colour of a task's frustums: matplotlib's tab10, cycling."""
    red, green, blue, _ = colormaps["tab10"](task % 10)
    return int(red * 255), int(green * 255), int(blue * 255)


def open_task_thumbnail(dataset: ContinualDataset, frame: int) -> np.ndarray:
    """A frame of the open task as a small uint8 image, cut from the pixels the dataset already holds."""
    start, _ = dataset.open_task_pixel_range()
    first, last = int(dataset.pixel_offsets[frame]) - start, int(dataset.pixel_offsets[frame + 1]) - start
    height, width = int(dataset.cameras.height[frame]), int(dataset.cameras.width[frame])
    image = dataset.task_pixels[first:last].view(height, width, 3).permute(2, 0, 1)[None]
    if height > THUMBNAIL_HEIGHT:
        image = torch.nn.functional.interpolate(image, scale_factor=THUMBNAIL_HEIGHT / height, mode="area")
    return (image[0].permute(1, 2, 0).clamp(0, 1) * 255).to(torch.uint8).cpu().numpy()


class TaskCameras:
    """Frustums of the released tasks' training frames in the viewer, kept in nerfstudio's `camera_handles`."""

    def __init__(self, viewer: Viewer, num_frames: int) -> None:
        self.viewer = viewer
        limit = viewer.config.max_num_display_images
        self.stride = 1 if limit < 0 else max(1, math.ceil(num_frames / max(limit, 1)))
        """Every stride-th frame is drawn, so that at most max_num_display_images are (as nerfstudio does)."""
        self.styles: Dict[int, Tuple[bool, bool]] = {}
        """Tasks drawn so far, and how: (highlighted, with images)."""

    def show(self, dataset: ContinualDataset, current_task: int) -> None:
        """Draw tasks 1..current_task + 1; redraw those whose style changed (highlight, images once loaded)."""
        for task in range(current_task + 1):
            # images only while the dataset holds the task's pixels; it loads them at the task's first batch
            style = (task in (current_task, dataset.open_task), task == dataset.open_task)
            if self.styles.get(task) != style:
                for frame in dataset.frames_of_task(task).tolist():
                    if frame % self.stride == 0:
                        self._draw(dataset, frame, task, *style)
                self.styles[task] = style

    def _draw(self, dataset: ContinualDataset, frame: int, task: int, highlighted: bool, with_image: bool) -> None:
        viewer = self.viewer
        camera = dataset.cameras[frame]
        camera_to_world = camera.camera_to_worlds.cpu().numpy()
        # nerfstudio's cameras look down -z (OpenGL); viser's frustums look down +z (OpenCV)
        rotation = vtf.SO3.from_matrix(camera_to_world[:3, :3]) @ vtf.SO3.from_x_radians(np.pi)
        height, width = float(camera.height), float(camera.width)
        handle = viewer.viser_server.scene.add_camera_frustum(
            name=f"/cameras/camera_{frame:05d}",  # nerfstudio's names: redrawing replaces the node
            fov=float(2 * np.arctan(height / 2 / float(camera.fy))),
            aspect=width / height,
            scale=viewer.config.camera_frustum_scale * (OPEN_TASK_SCALE if highlighted else 1.0),
            color=task_colour(task),
            image=open_task_thumbnail(dataset, frame) if with_image else None,
            wxyz=rotation.wxyz,
            position=camera_to_world[:3, 3] * VISER_NERFSTUDIO_SCALE_RATIO,
            visible=viewer.hide_images.visible,  # "Hide Train Cams" hides the frustums of later tasks too
        )
        handle.on_click(partial(self._look_through, frame))
        viewer.camera_handles[frame] = handle
        viewer.original_c2w[frame] = camera_to_world

    def _look_through(self, frame: int, event: viser.SceneNodePointerEvent[viser.CameraFrustumHandle]) -> None:
        """Clicking a frustum moves the browser's camera onto it, as in nerfstudio's viewer."""
        with event.client.atomic():
            event.client.camera.position = event.target.position
            event.client.camera.wxyz = event.target.wxyz
        self.viewer.current_camera_idx = frame


def task_text(datamanager: ContinualDataManager) -> str:
    """"k of N"; while a capture is still running, N counts the task being captured and may grow."""
    text = f"{datamanager.current_task + 1} of {datamanager.num_tasks}"
    if isinstance(datamanager, StreamingDataManager) and not datamanager.capture_finished:
        return f"{text}+ (capture running)"
    return text


def progress_text(datamanager: ContinualDataManager) -> str:
    """Iterations done, or seconds left, of the open task's budget; what training does once it is spent."""
    config = datamanager.config
    if datamanager.next_task_requested:
        return "ending the task (next task now)"
    if not ContinualDataManager.budget_spent(datamanager):
        if config.seconds_per_task is not None:
            left = max(config.seconds_per_task - datamanager.task_seconds, 0.0)
            return f"{left:.0f} s left of {config.seconds_per_task:g} s"
        return f"iteration {datamanager.task_iterations} of {config.iterations_per_task}"
    if isinstance(datamanager, StreamingDataManager):
        doing = "refining" if datamanager.config.idle == "refine" else "waiting"
        arrived = len(datamanager.dataparser.collecting)
        return f"budget spent, {doing} until the next task arrives ({arrived} frames so far)"
    return "budget spent"


def psnr_text(psnr_rows: List[List[float]]) -> str:
    """The latest accuracy-matrix row: test PSNR of every task seen so far."""
    if not psnr_rows:
        return "measured when task 1 ends"
    return f"after task {len(psnr_rows)}: " + " | ".join(f"{value:.2f}" for value in psnr_rows[-1])


class ContinualPanel:
    """The viewer's "Continual learning" folder, and the frustums of the released tasks.

    The elements are nerfstudio ViewerElements. The panel is a plain object, not an nn.Module, so nerfstudio's
    scan for "Custom Elements" passes it by; it installs its elements itself, above the viewer's tabs.
    Without a viewer (--vis tensorboard) it does nothing visible and its controls are never pressed.
    """

    def __init__(self, pipeline: ContinualPipeline) -> None:
        self.pipeline = pipeline
        self.task = ViewerText("Task", "", disabled=True, hint="Open task, of the tasks known so far")
        self.progress = ViewerText("Progress", "", disabled=True, hint="Budget of the open task")
        self.psnr = ViewerText("Test PSNR (dB)", "", disabled=True, hint="Latest accuracy-matrix row: PSNR per task")
        self.next_task = ViewerButton("Next task now", cb_hook=lambda _: pipeline.datamanager.request_next_task())
        self.pause_after_task = ViewerCheckbox(
            "Pause after this task", False, hint="Pause training when the open task ends; Resume Training goes on"
        )
        self.viewer: Optional[Viewer] = None
        self.cameras: Optional[TaskCameras] = None
        self.shown: Optional[Tuple[int, Optional[int]]] = None
        """(current task, task whose pixels the dataset holds) when the frustums were last drawn."""
        self._refreshed = 0.0

    @property
    def elements(self) -> Tuple[ViewerElement, ...]:
        return (self.task, self.progress, self.psnr, self.next_task, self.pause_after_task)

    def attach(self, viewer: Viewer, trainer: Trainer) -> None:
        """Set up `viewer`'s scene with the released tasks only, and install the panel."""
        datamanager = self.pipeline.datamanager
        # asked to draw no frustum, Viewer.init_scene reads no pixels and sets up the rest of the scene state
        config = viewer.config
        viewer.config = dataclasses.replace(config, max_num_display_images=0)
        try:
            viewer.init_scene(train_dataset=datamanager.train_dataset, train_state=trainer.training_state)
        finally:
            viewer.config = config
        self.viewer = viewer
        self.cameras = TaskCameras(viewer, len(datamanager.train_dataset))
        # between nerfstudio's status lines and its tabs, so it shows without scrolling
        with viewer.viser_server.gui.add_folder(PANEL_LABEL, order=viewer.stats_markdown.order + 0.5):
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
        datamanager = self.pipeline.datamanager
        shown = self.shown
        if (datamanager.current_task, datamanager.train_dataset.open_task) != shown:
            self._show_task()
            if shown is not None and datamanager.current_task != shown[0]:
                self._pause_if_asked(trainer)
        elif time.monotonic() - self._refreshed >= REFRESH_SECONDS:
            self.refresh()

    def _after_training(self, step: int) -> None:
        self.refresh()
        self.progress.value = "training finished"

    def _show_task(self) -> None:
        datamanager = self.pipeline.datamanager
        self.shown = (datamanager.current_task, datamanager.train_dataset.open_task)
        if self.cameras is not None:
            self.cameras.show(datamanager.train_dataset, datamanager.current_task)
        self.refresh()

    def _pause_if_asked(self, trainer: Trainer) -> None:
        """At a task boundary, pause the Trainer when "Pause after this task" is ticked (then untick it)."""
        if self.viewer is None or not self.pause_after_task.value or trainer.stop_training:
            return
        trainer.training_state = "paused"
        if self.viewer.pause_train.visible:  # show nerfstudio's "Resume Training" in place of "Pause Training"
            self.viewer.toggle_pause_button()
        self.pause_after_task.value = False
        task = self.pipeline.datamanager.current_task
        CONSOLE.print(f"[bold]Paused before task {task + 1}: press Resume Training in the viewer to go on")

    def refresh(self) -> None:
        """Rewrite the panel's texts from the datamanager and the accuracy matrix."""
        datamanager = self.pipeline.datamanager
        self.task.value = task_text(datamanager)
        self.progress.value = progress_text(datamanager)
        self.psnr.value = psnr_text(self.pipeline.accuracy.psnr)
        self._refreshed = time.monotonic()
