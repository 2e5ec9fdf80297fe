"""Training frames whose pixels can be read only while their task is open."""

from __future__ import annotations

from pathlib import Path
from typing import Iterable, Optional, Tuple

import numpy as np
import numpy.typing as npt
import torch
from nerfstudio.cameras.cameras import Cameras
from nerfstudio.data.dataparsers.base_dataparser import DataparserOutputs
from nerfstudio.data.datasets.base_dataset import InputDataset
from PIL import Image, UnidentifiedImageError

from continual_nerf.core.per_frame import FRAME_CAMERA, FRAME_TASK
from continual_nerf.errors import DatasetError, first_line
from continual_nerf.untrusted_files import check_regular

IMAGE_MODES = ("L", "RGB", "RGBA")
"""PIL modes of the images nerfstudio's InputDataset decodes correctly."""


class ClosedTaskError(PermissionError):
    """Raised when pixels of a task that is not open are requested."""


class ContinualDataset(InputDataset):
    """An InputDataset that serves pixels of the open task only.

    Camera rays (poses and intrinsics) of every frame stay available: the continual setting allows
    rays of past tasks. Pixels of a task are loaded when it opens and dropped when it closes; reading
    a frame of any other task raises ClosedTaskError, which is what keeps old images out of training.
    The task and camera of every frame are in its metadata, which nerfstudio hands to the model.
    """

    def __init__(
        self,
        dataparser_outputs: DataparserOutputs,
        task_of_frame: np.ndarray,
        scale_factor: float = 1.0,
        for_training: bool = True,
        camera_of_frame: Optional[np.ndarray] = None,
    ):
        super().__init__(dataparser_outputs, scale_factor=scale_factor)
        self.task_of_frame = torch.as_tensor(task_of_frame, dtype=torch.long)
        self.metadata[FRAME_TASK] = self.task_of_frame
        cameras = np.zeros_like(task_of_frame) if camera_of_frame is None else camera_of_frame
        self.metadata[FRAME_CAMERA] = torch.as_tensor(cameras, dtype=torch.long)
        self.for_training = for_training
        """False once training is over (ns-eval, ns-render, ns-viewer): then every frame is readable."""
        self.open_task: Optional[int] = None
        self.task_pixels: Optional[torch.Tensor] = None
        """Pixels of the open task's frames, flattened and concatenated in frame order (P, 3)."""
        pixel_counts = (self.cameras.width * self.cameras.height).view(-1).long()
        self.pixel_offsets = torch.cat([torch.zeros(1, dtype=torch.long), pixel_counts.cumsum(0)])
        """Start of every frame in the flat pixel numbering of all training frames; last entry is the total."""

    def frames_of_task(self, task: int) -> torch.Tensor:
        return torch.nonzero(self.task_of_frame == task).view(-1)

    def open(self, task: int) -> None:
        """Close the open task (dropping its pixels) and load the pixels of `task`."""
        self.task_pixels = None
        self.open_task = task
        images = [self.get_image_float32(int(i))[..., :3].reshape(-1, 3) for i in self.frames_of_task(task)]
        self.task_pixels = torch.cat(images)

    def close(self) -> None:
        """Drop the open task's pixels; no task's pixels are readable afterwards."""
        self.task_pixels = None
        self.open_task = None

    def get_numpy_image(self, image_idx: int) -> npt.NDArray[np.uint8]:
        task = int(self.task_of_frame[image_idx])
        if self.for_training and task != self.open_task:
            raise ClosedTaskError(
                f"frame {image_idx} ({self._dataparser_outputs.image_filenames[image_idx]}) belongs to task {task + 1}; "
                f"only the open task's pixels are readable (open: {None if self.open_task is None else self.open_task + 1})"
            )
        return read_image(self, image_idx)

    def open_task_pixel_range(self) -> tuple[int, int]:
        """Flat pixel numbers [start, end) covered by the open task."""
        assert self.open_task is not None, "no task is open"
        frames = self.frames_of_task(self.open_task)
        return int(self.pixel_offsets[frames[0]]), int(self.pixel_offsets[frames[-1] + 1])


class TestFrameDataset(InputDataset):
    """Held-out test frames: read by the evaluation only, never by training."""

    def get_numpy_image(self, image_idx: int) -> npt.NDArray[np.uint8]:
        return read_image(self, image_idx)


def read_image(dataset: InputDataset, image_idx: int) -> npt.NDArray[np.uint8]:
    """nerfstudio's image read, with a missing, unreadable, truncated or mis-sized file reported by name in one line."""
    filename = dataset._dataparser_outputs.image_filenames[image_idx]
    try:
        check_regular(filename)  # nerfstudio opens the file by name: a FIFO put there would block it
        image = InputDataset.get_numpy_image(dataset, image_idx)
    except DatasetError:
        raise
    except (OSError, UnidentifiedImageError, ValueError, AssertionError, Image.DecompressionBombError) as error:
        raise DatasetError(f"{filename}: cannot read image ({first_line(error)})") from None
    # the flat pixel numbering of a task assumes every image has its camera's size
    check_size(filename, (image.shape[1], image.shape[0]), dataset.cameras, image_idx)
    return image


def check_image_headers(dataset: InputDataset, frames: Iterable[int]) -> None:
    """Check from the file headers alone, without decoding pixels, that each of `frames` is an 8-bit image of its
    camera's size."""
    for frame in frames:
        filename = dataset._dataparser_outputs.image_filenames[frame]
        try:
            check_regular(filename)
            with Image.open(filename) as image:
                size, mode = image.size, image.mode
        except (OSError, UnidentifiedImageError, Image.DecompressionBombError) as error:
            raise DatasetError(f"{filename}: cannot read image ({first_line(error)})") from None
        # nerfstudio reads other modes wrongly (palette indices as grey) or not at all (16-bit, two channels)
        if mode not in IMAGE_MODES:
            raise DatasetError(f"{filename}: image mode {mode} is not supported (8-bit {', '.join(IMAGE_MODES)} only)")
        check_size(filename, size, dataset._dataparser_outputs.cameras, frame)


def check_size(filename: Path, size: Tuple[int, int], cameras: Cameras, frame: int) -> None:
    expected = int(cameras.width[frame]), int(cameras.height[frame])
    if tuple(size) != expected:
        raise DatasetError(
            f"{filename}: image is {size[0]}x{size[1]} pixels, its camera {expected[0]}x{expected[1]} "
            "(every image of a camera must have the camera's size)"
        )
