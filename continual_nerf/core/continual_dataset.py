"""Training frames whose pixels can be read only while their task is open."""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Dict, Iterable, List, Optional, Tuple

import numpy as np
import numpy.typing as npt
import torch
from nerfstudio.cameras.cameras import Cameras
from nerfstudio.data.dataparsers.base_dataparser import DataparserOutputs
from nerfstudio.data.datasets.base_dataset import InputDataset
from nerfstudio.data.utils.data_utils import get_image_mask_tensor_from_path
from PIL import Image, UnidentifiedImageError
from torch import Tensor

from continual_nerf.core.depth_maps import DEPTH_KEY, DIRECTIONS_NORM, METRES_PER_SCENE_UNIT, DepthMaps, directions_norm
from continual_nerf.core.per_frame import FRAME_CAMERA, FRAME_TASK
from continual_nerf.core.valid_pixels import ValidPixels, inside_circle
from continual_nerf.errors import DatasetError, first_line
from continual_nerf.metadata_keys import FISHEYE_CROP_RADIUS
from continual_nerf.nerfstudio_compat import cameras_as_parsed
from continual_nerf.untrusted_files import check_regular

IMAGE_MODES = ("L", "RGB", "RGBA")
"""PIL modes of the images nerfstudio's InputDataset decodes correctly."""

MASK_MODES = ("1", "L")
"""PIL modes of the masks read: one channel, 1-bit or 8-bit."""


class ClosedTaskError(PermissionError):
    """Raised when pixels of a task that is not open are requested."""


class ContinualDataset(InputDataset):
    """An InputDataset that serves pixels of the open task only.

    Camera rays (poses and intrinsics) of every frame stay available: the continual setting allows
    rays of past tasks. Pixels of a task are loaded when it opens and dropped when it closes; reading
    a frame of any other task raises ClosedTaskError, which is what keeps old images out of training.
    The task and camera of every frame are in its metadata, which nerfstudio hands to the model. Masks and fisheye
    circles, when the capture has them, decide which pixels `draw_pixels` may draw, for the open task and for replay
    alike. A model that trains on depth gets the open task's depth maps with its pixels (`serve_depth`), read and
    dropped with them.
    """

    def __init__(
        self,
        dataparser_outputs: DataparserOutputs,
        task_of_frame: np.ndarray,
        scale_factor: float = 1.0,
        for_training: bool = True,
        camera_of_frame: Optional[np.ndarray] = None,
        serve_depth: bool = False,
    ):
        # nerfstudio's InputDataset would read each mask into its frame's batch, at the image's full size only; masks
        # are read here instead (read_mask), into the record of the pixels training may draw
        super().__init__(dataclasses.replace(dataparser_outputs, mask_filenames=None), scale_factor=scale_factor)
        masks = dataparser_outputs.mask_filenames
        self.mask_filenames: Optional[List[Optional[Path]]] = None if masks is None else list(masks)
        """Per frame a mask, 0 where its pixels never train (None: every pixel trains; a frame's None: its pixels all
        train, or an earlier session's frame, whose mask is recorded)."""
        self.earlier_frames = 0
        """Frames of a continued run's earlier sessions, first in the dataset: their images may be gone."""
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
        radii = dataparser_outputs.metadata.get(FISHEYE_CROP_RADIUS)
        self.crop_radius: Optional[Tensor] = None if radii is None else radii.double() * scale_factor
        """Per frame the radius (loaded pixels) around its centre outside which its pixels never train (inf: none);
        None: no frame has one."""
        cropped = self.crop_radius is not None or self.mask_filenames is not None
        self.valid_pixels = ValidPixels(self.pixel_offsets) if cropped else None
        """Which pixels of the released tasks their masks and circles let train; None without either."""
        self.depth_maps = DepthMaps.of(dataparser_outputs, self.cameras)
        """The capture's depth maps; None when it has none."""
        self.serve_depth = serve_depth
        """Whether the open task's depth maps are read with its pixels (for a model that trains on depth)."""
        self.task_depths: Optional[Tensor] = None
        """z-depth of the open task's pixels (P,) in scene units, 0 where there is none; None unless serve_depth."""
        self.metadata[METRES_PER_SCENE_UNIT] = 1.0 / float(dataparser_outputs.dataparser_scale)

    def frames_of_task(self, task: int) -> torch.Tensor:
        return torch.nonzero(self.task_of_frame == task).view(-1)

    def open(self, task: int) -> None:
        """Close the open task (dropping its pixels and depth) and load the pixels of `task` (and its depth)."""
        self.close()
        self.open_task = task
        images = [self.get_image_float32(int(i))[..., :3].reshape(-1, 3) for i in self.frames_of_task(task)]
        self.task_pixels = torch.cat(images)
        if self.serve_depth:
            self.task_depths = torch.cat([self.get_depth(int(i)).reshape(-1) for i in self.frames_of_task(task)])
        if self.valid_pixels is not None:
            self._record_valid_pixels(task)

    def _record_valid_pixels(self, task: int) -> None:
        """Record the pixels of `task` that may train, and of the closed tasks before it not recorded yet (when a run
        resumes)."""
        assert self.valid_pixels is not None
        for earlier in range(task + 1):
            frames = self.frames_of_task(earlier).tolist()
            if all(self.valid_pixels.recorded(frame) for frame in frames):
                continue
            for frame in frames:
                self.valid_pixels.record(frame, self.trainable_pixels(frame))
            if self.valid_pixels.count(*self.task_pixel_range(earlier)) == 0:
                assert self.mask_filenames is not None, "a circle keeps its centre pixel: only masks leave none"
                circles = "" if self.crop_radius is None else " inside its fisheye circle"
                raise DatasetError(
                    f"{self.mask_filenames[frames[0]]}: this and every other mask of task {earlier + 1}'s training "
                    f"frames is 0 everywhere{circles}: the task has no pixel to train on"
                )

    def trainable_pixels(self, frame: int) -> Tensor:
        """(H, W) bool of the frame as loaded: True where its mask (if any) is nonzero and inside its fisheye circle
        (if any)."""
        width, height = int(self.cameras.width[frame]), int(self.cameras.height[frame])
        unmasked = self.mask_filenames is None or self.mask_filenames[frame] is None
        valid = torch.ones((height, width), dtype=torch.bool) if unmasked else read_mask(self, frame)
        if self.crop_radius is not None and torch.isfinite(self.crop_radius[frame]):
            valid &= inside_circle(width, height, float(self.crop_radius[frame]))
        return valid

    def draw_pixels(self, low: int, high: int, num: int, generator: Optional[torch.Generator] = None) -> Tensor:
        """`num` flat pixel numbers drawn uniformly in [low, high), a range of whole frames of released tasks, over
        the pixels their masks and circles let train."""
        if self.valid_pixels is None:
            return torch.randint(low, high, (num,), generator=generator)
        return self.valid_pixels.sample(low, high, num, generator)

    def keep_earlier_sessions(self, frames: int, bits: Optional[Tensor], counts: Optional[Tensor]) -> None:
        """The first `frames` frames are an earlier session's: their images may be gone, and the pixels their masks
        and circles let train are `bits` and `counts` (ValidPixels' record of them, None: every pixel trains)."""
        self.earlier_frames = frames
        if bits is None or counts is None:
            if self.valid_pixels is not None:  # this capture has masks or circles; the earlier sessions had neither
                for frame in range(frames):
                    self.valid_pixels.record(frame, self.trainable_pixels(frame))
            return
        if self.valid_pixels is None:
            self.valid_pixels = ValidPixels(self.pixel_offsets)
        self.valid_pixels.bits[: len(bits)] = bits
        self.valid_pixels.valid_per_frame[: len(counts)] = counts

    def close(self) -> None:
        """Drop the open task's pixels and depth; no task's pixels are readable afterwards."""
        self.task_pixels = None
        self.task_depths = None
        self.open_task = None

    def check_open(self, image_idx: int) -> None:
        """Refuse to read a frame of a task that is not open (while training)."""
        task = int(self.task_of_frame[image_idx])
        if self.for_training and task != self.open_task:
            raise ClosedTaskError(
                f"frame {image_idx} ({self.image_filenames[image_idx]}) belongs to task {task + 1}; "
                f"only the open task's pixels are readable (open: {None if self.open_task is None else self.open_task + 1})"
            )

    def get_numpy_image(self, image_idx: int) -> npt.NDArray[np.uint8]:
        self.check_open(image_idx)
        if not self.for_training and image_idx < self.earlier_frames:
            return read_image_if_kept(self, image_idx)
        return read_image(self, image_idx)

    def get_depth(self, image_idx: int) -> Tensor:
        """(H, W) z-depth of the frame's pixels as loaded, scene units, 0 where there is none; its task must be open."""
        assert self.depth_maps is not None, "the capture has depth maps"
        self.check_open(image_idx)
        return self.depth_maps.read(image_idx)

    def open_task_pixel_range(self) -> tuple[int, int]:
        """Flat pixel numbers [start, end) covered by the open task."""
        assert self.open_task is not None, "no task is open"
        return self.task_pixel_range(self.open_task)

    def task_pixel_range(self, task: int) -> tuple[int, int]:
        """Flat pixel numbers [start, end) covered by `task`."""
        frames = self.frames_of_task(task)
        return int(self.pixel_offsets[frames[0]]), int(self.pixel_offsets[frames[-1] + 1])


class TestFrameDataset(InputDataset):
    """Held-out test frames: read by the evaluation only, never by training. Each frame's batch holds its depth map
    when the capture has them (nerfstudio's `depth_image`, and its rays' `directions_norm`: the model's depth metrics
    read them)."""

    earlier_frames = 0
    """Test frames of a continued run's earlier sessions, first in the dataset: their images may be gone."""

    def __init__(self, dataparser_outputs: DataparserOutputs, scale_factor: float = 1.0):
        super().__init__(dataparser_outputs, scale_factor=scale_factor)
        self.depth_maps = DepthMaps.of(dataparser_outputs, self.cameras)
        """The test frames' depth maps; None when the capture has none."""

    def get_numpy_image(self, image_idx: int) -> npt.NDArray[np.uint8]:
        if image_idx < self.earlier_frames:
            return read_image_if_kept(self, image_idx)
        return read_image(self, image_idx)

    def get_metadata(self, data: Dict) -> Dict:
        if self.depth_maps is None:
            return {}
        frame = data["image_idx"]
        # z-depth, and what turns the model's distances along rays into it
        return {
            DEPTH_KEY: self.depth_maps.read(frame)[..., None],
            DIRECTIONS_NORM: directions_norm(self.cameras, frame),
        }

    def available_frames(self) -> List[int]:
        """The frames whose images can be read: every frame but an earlier session's whose image is gone."""
        filenames = self.image_filenames
        return [frame for frame in range(len(self)) if frame >= self.earlier_frames or Path(filenames[frame]).is_file()]


GONE_NOTICE: List[Path] = []
"""The first image of an earlier session found gone (ns-render and ns-viewer say it once)."""


def read_image_if_kept(dataset: InputDataset, image_idx: int) -> npt.NDArray[np.uint8]:
    """An earlier session's image, or a black one of its camera's size when it is gone (ns-render renders those frames
    all the same; evaluation measures only the frames whose images are there)."""
    filename = Path(dataset.image_filenames[image_idx])
    if filename.exists():
        return read_image(dataset, image_idx)
    if not GONE_NOTICE:
        GONE_NOTICE.append(filename)
        print(f"{filename}: gone (an earlier session's image): its frame is shown against a black image", flush=True)
    return np.zeros((int(dataset.cameras.height[image_idx]), int(dataset.cameras.width[image_idx]), 3), np.uint8)


def read_image(dataset: InputDataset, image_idx: int) -> npt.NDArray[np.uint8]:
    """nerfstudio's image read, with a missing, unreadable, truncated or mis-sized file reported by name in one line."""
    filename = dataset.image_filenames[image_idx]
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


def header(filename: Path, kind: str) -> Tuple[Tuple[int, int], str]:
    """Size and mode of an image or mask file from its header alone; an unreadable one is a one-line error."""
    try:
        check_regular(filename)
        with Image.open(filename) as image:
            return image.size, image.mode
    except (OSError, UnidentifiedImageError, Image.DecompressionBombError) as error:
        raise DatasetError(f"{filename}: cannot read {kind} ({first_line(error)})") from None


def check_image_headers(dataset: InputDataset, frames: Iterable[int]) -> None:
    """Check from the file headers alone, without decoding pixels, that each of `frames` is an 8-bit image of its
    camera's size."""
    for frame in frames:
        filename = dataset.image_filenames[frame]
        size, mode = header(filename, "image")
        # nerfstudio reads other modes wrongly (palette indices as grey) or not at all (16-bit, two channels)
        if mode not in IMAGE_MODES:
            raise DatasetError(f"{filename}: image mode {mode} is not supported (8-bit {', '.join(IMAGE_MODES)} only)")
        check_size(filename, size, cameras_as_parsed(dataset), frame)


def check_mask_headers(dataset: ContinualDataset, frames: Iterable[int]) -> None:
    """Check from the file headers alone that each of `frames` has a one-channel mask of its image's size (a frame
    without one, of an earlier session, has nothing to check)."""
    for frame in frames:
        if dataset.mask_filenames is not None and dataset.mask_filenames[frame] is not None:
            mask_size(dataset, frame)


def mask_filename(dataset: ContinualDataset, frame: int) -> Path:
    filename = None if dataset.mask_filenames is None else dataset.mask_filenames[frame]
    assert filename is not None, "the frame has a mask file"
    return filename


def mask_size(dataset: ContinualDataset, frame: int) -> Tuple[int, int]:
    """Width and height of the frame's mask, checked: one channel, of its image's size before or after the dataset's
    downscale."""
    filename = mask_filename(dataset, frame)
    size, mode = header(filename, "mask")
    if mode not in MASK_MODES:
        raise DatasetError(f"{filename}: mask mode {mode} is not supported (one channel: 8-bit L or 1-bit)")
    cameras = cameras_as_parsed(dataset)
    full = int(cameras.width[frame]), int(cameras.height[frame])
    loaded = int(dataset.cameras.width[frame]), int(dataset.cameras.height[frame])
    if tuple(size) not in (full, loaded):
        downscaled = "" if loaded == full else f" ({loaded[0]}x{loaded[1]} after --downscale-factor)"
        raise DatasetError(
            f"{filename}: mask is {size[0]}x{size[1]} pixels, its image {full[0]}x{full[1]}{downscaled} "
            "(a mask has its image's size)"
        )
    return size


def read_mask(dataset: ContinualDataset, frame: int) -> Tensor:
    """The frame's mask as its image is loaded, (H, W) bool, True where pixels train: a mask of the image's full size
    is downscaled with the image, one of the downscaled size is read as it is."""
    filename = mask_filename(dataset, frame)
    loaded = int(dataset.cameras.width[frame]), int(dataset.cameras.height[frame])
    scale = 1.0 if mask_size(dataset, frame) == loaded else dataset.scale_factor
    try:
        return get_image_mask_tensor_from_path(filename, scale_factor=scale)[..., 0]
    except (OSError, ValueError, Image.DecompressionBombError) as error:
        raise DatasetError(f"{filename}: cannot read mask ({first_line(error)})") from None


def check_size(filename: Path, size: Tuple[int, int], cameras: Cameras, frame: int) -> None:
    expected = int(cameras.width[frame]), int(cameras.height[frame])
    if tuple(size) != expected:
        raise DatasetError(
            f"{filename}: image is {size[0]}x{size[1]} pixels, its camera {expected[0]}x{expected[1]} "
            "(every image of a camera must have the camera's size)"
        )
