"""Depth maps of RGB-D captures, as the datasets serve them: read from their files and put on the colour pixels.

A depth map holds z-depth (distance along the camera's optical axis) in the units of its file; the dataparser says
how many metres one unit is (`depth_unit_scale_factor`, nerfstudio's key), and depth is served in scene units
(metres times the dataparser's scale), as nerfstudio's DepthDataset serves it and as the poses are. 0 marks a pixel
without depth, as nerfstudio's depth losses read it: zero, negative and non-finite values of a file all become 0.

A depth camera may differ from the colour camera in size and intrinsics (ScanNet: 640x480 depth beside 1296x968
colour). Both look from one centre along one axis, so each colour pixel takes the depth sample its ray meets: the
depth pixel at the same normalised image coordinates, the nearest one (interpolating would blend a foreground and a
background depth into one that is neither). Colour pixels outside the depth camera's view get 0.
"""

from __future__ import annotations

import math
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable, Iterator, List, Optional, Tuple

import numpy as np
import torch
from nerfstudio.cameras.cameras import Cameras
from nerfstudio.data.dataparsers.base_dataparser import DataparserOutputs
from PIL import Image, UnidentifiedImageError
from torch import Tensor

from continual_nerf.errors import DatasetError, first_line
from continual_nerf.metadata_keys import DEPTH_FILENAMES, DEPTH_INTRINSICS, DEPTH_UNIT_SCALE_FACTOR
from continual_nerf.untrusted_files import check_regular

DEPTH_IMAGE_MODES = ("I;16", "I;16B", "I", "F")
"""PIL modes of depth images: one channel of 16-bit or 32-bit integers or floats (8-bit would be a picture of depth)."""
NUMPY_SUFFIX = ".npy"
"""Depth maps stored as numpy arrays (as nerfstudio reads them too)."""
EDGE_TOLERANCE = 1e-6
"""Depth pixels by which a colour pixel's centre may miss an edge between two depth pixels and still count as on it."""
DEPTH_KEY = "depth_image"
"""Batch key of the (.., 1) z-depth targets in scene units, 0 where there is none: nerfstudio's depth models read it."""
DIRECTIONS_NORM = "directions_norm"
"""Ray bundle metadata (and model output) key of each ray direction's length in camera coordinates with unit z, as
nerfstudio's cameras generate it: distance along the ray over z-depth."""
METRES_PER_SCENE_UNIT = "metres_per_scene_unit"
"""Key of the training dataset's metadata (which nerfstudio hands to the model): 1 / the dataparser's scale."""


@dataclass(frozen=True)
class Pinhole:
    """Intrinsics of a camera for images of one size, in pixels."""

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int

    def resized(self, width: int, height: int) -> "Pinhole":
        """The same camera for images resized to `width` x `height`."""
        sx, sy = width / self.width, height / self.height
        return Pinhole(self.fx * sx, self.fy * sy, self.cx * sx, self.cy * sy, width, height)

    @classmethod
    def of_camera(cls, cameras: Cameras, frame: int) -> "Pinhole":
        fx, fy, cx, cy = (float(getattr(cameras, name)[frame]) for name in ("fx", "fy", "cx", "cy"))
        return cls(fx, fy, cx, cy, int(cameras.width[frame]), int(cameras.height[frame]))

    @classmethod
    def of_row(cls, row: Tensor) -> "Pinhole":
        """From fx, fy, cx, cy, width, height."""
        fx, fy, cx, cy, width, height = row.tolist()
        return cls(fx, fy, cx, cy, int(width), int(height))


def _nearest(count: int, focal: float, centre: float, depth_focal: float, depth_centre: float) -> np.ndarray:
    """Per colour pixel along one axis (centres at i + 0.5, as nerfstudio casts rays), the index of the depth pixel
    its ray falls in; out of range where it falls outside the depth map."""
    normalised = (np.arange(count) + 0.5 - centre) / focal
    # a centre on the edge between two depth pixels (a depth map a whole multiple of the image's size) takes the second
    # one, whatever the rounding of the arithmetic before
    return np.floor(normalised * depth_focal + depth_centre + EDGE_TOLERANCE).astype(np.int64)


def resample(depth: np.ndarray, depth_camera: Pinhole, colour_camera: Pinhole) -> np.ndarray:
    """(colour height, colour width) float32: for each colour pixel the value of the depth pixel its ray falls in, 0
    outside the depth map. `depth_camera` describes `depth` as it is (its size)."""
    columns = _nearest(colour_camera.width, colour_camera.fx, colour_camera.cx, depth_camera.fx, depth_camera.cx)
    rows = _nearest(colour_camera.height, colour_camera.fy, colour_camera.cy, depth_camera.fy, depth_camera.cy)
    inside_columns = (columns >= 0) & (columns < depth.shape[1])
    inside_rows = (rows >= 0) & (rows < depth.shape[0])
    values = depth[np.clip(rows, 0, depth.shape[0] - 1)[:, None], np.clip(columns, 0, depth.shape[1] - 1)[None, :]]
    return np.where(inside_rows[:, None] & inside_columns[None, :], values, 0).astype(np.float32)


@contextmanager
def reading_depth_file(path: Path) -> Iterator[None]:
    """Turn what can go wrong while reading the depth map `path` into a one-line error naming it."""
    try:
        check_regular(path)  # a FIFO put there would block the reader
        yield
    except DatasetError:
        raise
    except FileNotFoundError:
        raise DatasetError(f"{path}: depth map missing") from None
    except (OSError, ValueError, EOFError, UnidentifiedImageError, Image.DecompressionBombError) as error:
        raise DatasetError(f"{path}: cannot read depth map ({first_line(error)})") from None


def check_depth_mode(path: Path, image: Image.Image) -> None:
    if image.mode not in DEPTH_IMAGE_MODES:
        raise DatasetError(
            f"{path}: depth map mode {image.mode} is not supported (one channel of 16-bit integers or 32-bit floats, "
            "or a .npy array)"
        )


def check_depth_shape(path: Path, shape: Tuple[int, ...]) -> None:
    if len(shape) != 2 or min(shape) == 0:
        raise DatasetError(f"{path}: a depth map is one channel of numbers, found an array of shape {shape}")


def read_depth_file(path: Path) -> np.ndarray:
    """A depth map file's values, (H, W) float64 in its own units: a one-channel 16/32-bit image or a .npy array; a
    missing, unreadable or many-channel file is a one-line error naming it."""
    with reading_depth_file(path):
        if path.suffix == NUMPY_SUFFIX:
            values = np.load(path, allow_pickle=False)
        else:
            with Image.open(path) as image:
                check_depth_mode(path, image)
                values = np.asarray(image)
    check_depth_shape(path, values.shape)
    if not np.issubdtype(values.dtype, np.number):
        raise DatasetError(f"{path}: a depth map holds numbers, found {values.dtype} values")
    return values.astype(np.float64)


def depth_file_size(path: Path) -> Tuple[int, int]:
    """Width and height of a depth map from its header alone, checked as read_depth_file checks it."""
    with reading_depth_file(path):
        if path.suffix == NUMPY_SUFFIX:
            shape = np.load(path, mmap_mode="r", allow_pickle=False).shape
        else:
            with Image.open(path) as image:
                check_depth_mode(path, image)
                shape = image.size[::-1]
    check_depth_shape(path, shape)
    return shape[1], shape[0]


class DepthMaps:
    """The depth maps of a dataset's frames, each read on request, aligned with the frame's colour pixels as they are
    loaded (after any downscale) and in scene units."""

    def __init__(self, outputs: DataparserOutputs, cameras: Cameras) -> None:
        self.filenames: List[Optional[Path]] = list(outputs.metadata[DEPTH_FILENAMES])
        """Per frame its depth map; None for a frame without one (every pixel without depth)."""
        self.scene_units_per_file_unit = float(outputs.metadata.get(DEPTH_UNIT_SCALE_FACTOR, 1.0)) * float(
            outputs.dataparser_scale
        )
        self.metres_per_scene_unit = 1.0 / float(outputs.dataparser_scale)
        self.calibrated_cameras = outputs.cameras
        """The colour cameras as the dataparser gives them: a depth map without intrinsics of its own shares theirs."""
        self.cameras = cameras
        """The colour cameras as the dataset loads the images."""
        self.intrinsics: Optional[Tensor] = outputs.metadata.get(DEPTH_INTRINSICS)

    @classmethod
    def of(cls, outputs: DataparserOutputs, cameras: Cameras) -> Optional["DepthMaps"]:
        """The capture's depth maps; None when it has none."""
        if outputs.metadata.get(DEPTH_FILENAMES) is None:
            return None
        return cls(outputs, cameras)

    def depth_camera(self, frame: int, size: Tuple[int, int]) -> Pinhole:
        """The depth camera of `frame` for a depth map of `size` (width, height)."""
        if self.intrinsics is None:
            calibrated = Pinhole.of_camera(self.calibrated_cameras, frame)
        else:
            calibrated = Pinhole.of_row(self.intrinsics[frame])
        return calibrated.resized(*size)

    def read(self, frame: int) -> Tensor:
        """(H, W) float32 z-depth of each colour pixel of `frame` as loaded, in scene units, 0 where there is none."""
        colour = Pinhole.of_camera(self.cameras, frame)
        filename = self.filenames[frame]
        if filename is None:
            return torch.zeros((colour.height, colour.width))
        values = read_depth_file(filename) * self.scene_units_per_file_unit
        values[~(np.isfinite(values) & (values > 0))] = 0.0
        height, width = values.shape
        return torch.from_numpy(resample(values, self.depth_camera(frame, (width, height)), colour))

    def check_headers(self, frames: Iterable[int]) -> None:
        """Each of `frames`' depth maps is there and readable as a depth map (from its header alone)."""
        for frame in frames:
            filename = self.filenames[frame]
            if filename is not None:
                depth_file_size(filename)


def directions_norm(cameras: Cameras, frame: int) -> Tensor:
    """(H, W, 1) length in camera coordinates of each pixel's ray direction with unit z, as nerfstudio's cameras
    generate it (distortion included): a rendered distance along the ray over it is z-depth."""
    return cameras[frame : frame + 1].generate_rays(camera_indices=0, keep_shape=True).metadata[DIRECTIONS_NORM]


def depth_errors(rendered: Tensor, truth: Tensor, metres_per_scene_unit: float) -> Tuple[float, float]:
    """Absolute relative error and RMSE (metres) of rendered z-depth against `truth` (same shape, scene units, 0 where
    there is none) over the pixels with depth; NaN for both when there is none."""
    valid = truth > 0
    if not bool(valid.any()):
        return math.nan, math.nan
    predicted, expected = rendered[valid].double(), truth[valid].double()
    abs_rel = float(((predicted - expected).abs() / expected).mean())
    rmse = float((predicted - expected).pow(2).mean().sqrt()) * metres_per_scene_unit
    return abs_rel, rmse
