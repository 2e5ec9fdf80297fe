"""The released tasks' training cameras in nerfstudio's viser viewer, one colour per task.

nerfstudio's `Viewer.init_scene` draws a frustum, with its image, for every training frame at the start; in the
continual setting the frames of later tasks have not arrived yet and the pixels of closed tasks are gone. Here the
frustums of a task appear when it is released, in the task's colour; the open task's are drawn larger and carry
their images, which are dropped (the frustums redrawn plain) when the task closes, like its pixels.
"""

from __future__ import annotations

import math
from functools import partial
from typing import Dict, Tuple

import numpy as np
import torch
import viser
import viser.transforms as vtf
from matplotlib import colormaps
from nerfstudio.viewer.viewer import Viewer

from continual_nerf.core.continual_dataset import ContinualDataset
from continual_nerf.nerfstudio_compat import (
    VISER_NERFSTUDIO_SCALE_RATIO,
    register_frustum,
    set_current_camera,
    training_cameras_shown,
)

OPEN_TASK_SCALE = 1.6
"""Frustums of the open task are drawn this much larger than those of earlier tasks."""
THUMBNAIL_HEIGHT = 100
"""Height in pixels of the images shown in the open task's frustums (nerfstudio's viewer uses 100 too)."""


def task_colour(task: int) -> Tuple[int, int, int]:
    """RGB colour of a task's frustums: matplotlib's tab10, cycling."""
    red, green, blue, _ = colormaps["tab10"](task % 10)
    return int(red * 255), int(green * 255), int(blue * 255)


def open_task_thumbnail(dataset: ContinualDataset, frame: int) -> np.ndarray:
    """A frame of the open task as a small uint8 image, cut from the pixels the dataset already holds."""
    assert dataset.task_pixels is not None, "thumbnails are cut from the open task's pixels"
    start, _ = dataset.open_task_pixel_range()
    first, last = int(dataset.pixel_offsets[frame]) - start, int(dataset.pixel_offsets[frame + 1]) - start
    height, width = int(dataset.cameras.height[frame]), int(dataset.cameras.width[frame])
    image = dataset.task_pixels[first:last].view(height, width, 3).permute(2, 0, 1)[None]
    if height > THUMBNAIL_HEIGHT:
        image = torch.nn.functional.interpolate(image, scale_factor=THUMBNAIL_HEIGHT / height, mode="area")
    return (image[0].permute(1, 2, 0).clamp(0, 1) * 255).to(torch.uint8).cpu().numpy()


class TaskCameras:
    """Frustums of the released tasks' training frames in the viewer, kept in nerfstudio's camera handles."""

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
            visible=training_cameras_shown(viewer),  # "Hide Train Cams" hides the frustums of later tasks too
        )
        handle.on_click(partial(self._look_through, frame))
        register_frustum(viewer, frame, handle, camera_to_world)

    def _look_through(self, frame: int, event: viser.SceneNodePointerEvent[viser.CameraFrustumHandle]) -> None:
        """Clicking a frustum moves the browser's camera onto it, as in nerfstudio's viewer."""
        with event.client.atomic():
            event.client.camera.position = event.target.position
            event.client.camera.wxyz = event.target.wxyz
        set_current_camera(self.viewer, frame)
