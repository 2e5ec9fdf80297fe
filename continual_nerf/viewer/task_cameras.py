"""The released tasks' training cameras in nerfstudio's viser viewer, one colour per task.

nerfstudio's `Viewer.init_scene` draws a frustum, with its image, for every training frame at the start; in the
continual setting the frames of later tasks have not arrived yet and the pixels of closed tasks are gone. Here the
frustums of a task appear when it is released, in the task's colour; the open task's are drawn larger and carry
their images, which are dropped (the frustums redrawn plain) when the task closes, like its pixels.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import partial
from typing import Dict, List, Optional, Sequence, Tuple

import numpy as np
import torch
import viser
import viser.transforms as vtf
from nerfstudio.viewer.viewer import Viewer

from continual_nerf.core.continual_dataset import ContinualDataset
from continual_nerf.nerfstudio_compat import (
    VISER_NERFSTUDIO_SCALE_RATIO,
    register_frustum,
    remove_frustum,
    set_current_camera,
    training_cameras_shown,
)
from continual_nerf.plots import task_colour


@dataclass(frozen=True)
class View:
    """A browser camera pose in viser's units: where it is, what it looks at, which way is up."""

    position: np.ndarray
    look_at: np.ndarray
    up: np.ndarray


OPEN_TASK_SCALE = 1.6
"""Frustums of the open task are drawn this much larger than those of earlier tasks."""
THUMBNAIL_HEIGHT = 100
"""Height in pixels of the images shown in the open task's frustums (nerfstudio's viewer uses 100 too)."""
FRUSTUM_FRACTION = 0.04
"""Automatic frustum size: this fraction of the largest side of the box around the trajectory's cameras."""
VIEW_MARGIN = 1.3
"""The framing view leaves this much room around the cameras it frames."""


def camera_positions(dataset: ContinualDataset, frames: Sequence[int]) -> np.ndarray:
    """Positions (N, 3) of `frames`' cameras in viser's units."""
    return dataset.cameras.camera_to_worlds[list(frames), :, 3].cpu().numpy() * VISER_NERFSTUDIO_SCALE_RATIO


def frustum_scale(dataset: ContinualDataset) -> float:
    """A frustum size that shows at the trajectory's scale: a fraction of the box around its cameras."""
    positions = camera_positions(dataset, range(len(dataset)))
    extent = float((positions.max(axis=0) - positions.min(axis=0)).max())
    return max(FRUSTUM_FRACTION * extent, 1e-3)


def framing_view(dataset: ContinualDataset, frames: Sequence[int], fov: float) -> View:
    """A view from above and behind `frames`' cameras that has them all in a field of view of `fov` radians.

    "Up" is the cameras' mean up axis; the view looks along their mean viewing direction, tilted down 50 degrees,
    so the frustums are seen from behind, over the surfaces they look at.
    """
    rotations = dataset.cameras.camera_to_worlds[list(frames), :, :3].cpu().numpy()
    up = _unit(rotations[:, :, 1].mean(axis=0), fallback=np.array([0.0, 0.0, 1.0]))
    forward = -rotations[:, :, 2].mean(axis=0)  # OpenGL cameras look down -z
    forward = _unit(forward - np.dot(forward, up) * up, fallback=_perpendicular(up))
    positions = camera_positions(dataset, frames)
    centre = (positions.max(axis=0) + positions.min(axis=0)) / 2
    radius = max(float(np.linalg.norm(positions - centre, axis=1).max()), 1.0)
    distance = VIEW_MARGIN * radius / np.tan(fov / 2)
    tilt = np.deg2rad(50)
    direction = np.cos(tilt) * forward - np.sin(tilt) * up  # from the view towards the cameras
    return View(position=centre - distance * direction, look_at=centre, up=up)


def _unit(vector: np.ndarray, fallback: np.ndarray) -> np.ndarray:
    """`vector` scaled to length 1, or `fallback` where it has none (cameras looking every way at once)."""
    norm = float(np.linalg.norm(vector))
    return fallback if norm < 1e-6 else vector / norm


def _perpendicular(up: np.ndarray) -> np.ndarray:
    """A unit vector perpendicular to the unit vector `up`: the world axis least aligned with it, made orthogonal."""
    axis = np.eye(3)[int(np.argmin(np.abs(up)))]
    axis = axis - np.dot(axis, up) * up
    return axis / np.linalg.norm(axis)


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

    def __init__(self, viewer: Viewer, dataset: ContinualDataset, scale: Optional[float]) -> None:
        self.viewer = viewer
        self.scale = frustum_scale(dataset) if scale is None else scale
        """Size of the frustums of closed tasks, fixed at the start so that a growing trajectory keeps its look."""
        self.styles: Dict[int, Tuple[bool, bool]] = {}
        """Tasks drawn so far, and how: (highlighted, with images)."""
        self.frames: Dict[int, List[int]] = {}
        """The frames drawn of each task."""

    def show(self, dataset: ContinualDataset, current_task: int) -> None:
        """Draw tasks 1..current_task + 1 and no later one; redraw those whose style changed (highlight, images)."""
        for task in [task for task in self.styles if task > current_task]:
            for frame in self.frames.pop(task):
                remove_frustum(self.viewer, frame)
            del self.styles[task]
        for task in range(current_task + 1):
            # images only while the dataset holds the task's pixels; it loads them at the task's first batch
            style = (task in (current_task, dataset.open_task), task == dataset.open_task)
            if self.styles.get(task) != style:
                if task not in self.frames:
                    self.frames[task] = dataset.frames_of_task(task).tolist()[:: self._stride(len(dataset))]
                for frame in self.frames[task]:
                    self._draw(dataset, frame, task, *style)
                self.styles[task] = style

    def _stride(self, num_frames: int) -> int:
        """Draw every stride-th frame of a new task, so that about max_num_display_images are drawn in all (as
        nerfstudio does); a trajectory that grows while it trains thins out its later tasks."""
        limit = self.viewer.config.max_num_display_images
        return 1 if limit < 0 else max(1, math.ceil(num_frames / max(limit, 1)))

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
            scale=self.scale * (OPEN_TASK_SCALE if highlighted else 1.0),
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
