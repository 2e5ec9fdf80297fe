"""The change guard: replay must not teach the old state of what the open task's frames see changed.

A later session may find the scene changed (an object moved, a wall repainted). Its images must win where they see the
change, yet replay renders the earlier state from the frozen oracle and teaches it back. When a task opens, the oracle
renders the open task's frames on a coarse grid of cells (colour and the distance to the surface), and a cell whose
colour differs from the frame's pixel there by more than a threshold, and well more than the task's cells typically
do, is a candidate. It counts as changed only if the earlier frame that sees the surface the oracle renders there
finest sees that surface, unhidden, in another colour than the open task's pixel, and with pixels at most twice as
large there as the open task's: a candidate no earlier frame saw is new ground, one earlier frames saw only from far
is detail the oracle never learned, and one an earlier frame saw as the open task does is a view the oracle renders
badly; replay teaches none of them anything the new images contradict (a later session of an unchanged scene then
keeps nearly all its replay). A replayed ray ends where the oracle's depth puts it; when that point, seen from an
open-task frame, falls in a changed cell and is not hidden there behind the surface the oracle renders in that cell,
the frame observes that point differently than the earlier tasks did, and the ray is skipped; so is a ray that
crosses, on its way there, a point an open-task frame sees changed in front of the oracle's surface (an object moved
into what was empty space). Points no open-task frame sees keep their replay: what the new images do not show keeps
what the earlier session taught.

Projection treats every camera as a pinhole (distortion is ignored for the point's cell).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable, Tuple

import torch
from nerfstudio.cameras.cameras import Cameras
from nerfstudio.cameras.rays import RayBundle
from torch import Tensor

from continual_nerf.core.continual_dataset import ContinualDataset

MAX_CELLS = 1024
"""Cells per open-task frame at most: a frame's grid strides over its pixels so that it has no more."""
CONTRAST = 3.0
"""A changed cell also differs by this many times the open task's median difference: where the oracle renders every
cell about as badly (a model still learning, ground no earlier task saw), nothing stands out as changed."""
SAMPLES_ALONG_RAY = 8
"""Points a replayed ray is checked at, evenly up to where it ends: a ray whose end no open-task frame sees changed may
still cross space they see changed (an object moved into what was empty)."""
VISIBILITY_TOLERANCE = 0.1
"""A point counts as seen in a cell when it is no farther than the cell's surface by this share of its distance."""
SEED = 0
"""The seed the oracle's jittered samples are drawn with while it renders the cells (training's generators untouched):
a run resumed mid-task finds the same cells changed."""

MAX_FOOTPRINT_RATIO = 2.0
"""An earlier frame vouches for a change only where its pixel covers at most this many times the open task's pixel at
the surface: a surface earlier frames saw only from far was learned blurred, and its detail in a close new view is
not a change."""
PROJECTIONS_AT_ONCE = 1 << 20
"""Point-camera pairs projected at once while looking for the earlier frame that sees a changed cell's surface
finest."""


Render = Callable[[RayBundle], Tuple[Tensor, Tensor]]
"""Colour (N, 3) and distance along the ray to the surface (N,) the oracle renders for rays of training frames."""


@dataclass
class Pinholes:
    """Frames as pinhole cameras (distortion ignored)."""

    frames: Tensor
    """(F,) their frame numbers."""
    rotations: Tensor
    """(F, 3, 3) camera-to-world rotations (OpenGL: the camera looks along -z)."""
    centres: Tensor
    """(F, 3) camera centres."""
    intrinsics: Tensor
    """(F, 4) fx, fy, cx, cy."""
    sizes: Tensor
    """(F, 2) width and height."""

    @staticmethod
    def of(cameras: Cameras, frames: Tensor) -> Pinholes:
        poses = cameras.camera_to_worlds[frames].float()
        return Pinholes(
            frames=frames,
            rotations=poses[:, :, :3],
            centres=poses[:, :, 3],
            intrinsics=torch.cat([cameras.fx, cameras.fy, cameras.cx, cameras.cy], dim=-1)[frames].float(),
            sizes=torch.cat([cameras.width, cameras.height], dim=-1)[frames].float(),
        )

    def project(self, points: Tensor) -> Tuple[Tensor, Tensor, Tensor, Tensor]:
        """Pixel coordinates u, v (N, F) of `points` (N, 3) in the F cameras, whether each lies in front of the
        camera and inside its image, and its distance from the camera centre."""
        relative = points[:, None, :] - self.centres[None]  # (N, F, 3)
        local = torch.einsum("fji,nfj->nfi", self.rotations, relative)  # R^T (p - c)
        depth = -local[..., 2]
        in_front = depth > 1e-6
        depth = depth.clamp_min(1e-6)
        fx, fy, cx, cy = self.intrinsics.unbind(-1)
        u = cx + fx * local[..., 0] / depth
        v = cy - fy * local[..., 1] / depth
        width, height = self.sizes.unbind(-1)
        inside = in_front & (u >= 0) & (u < width) & (v >= 0) & (v < height)
        return u, v, inside, relative.norm(dim=-1)

    def footprints(self, distances: Tensor, cameras: Tensor) -> Tensor:
        """The side of a pixel of the cameras numbered `cameras` at `distances` (broadcast with them) from them."""
        return distances / self.intrinsics[cameras, 0]

    def finest_view(self, points: Tensor) -> Tuple[Tensor, Tensor, Tensor, Tensor]:
        """For each of `points` (M, 3): the index of the camera that has it inside its image with the smallest pixel
        footprint there (-1: none), the pixel (row, column) it falls in there and its distance from that camera."""
        finest, rows, columns, distances = [], [], [], []
        step = max(1, PROJECTIONS_AT_ONCE // max(1, len(self.centres)))
        for begin in range(0, len(points), step):
            chunk = points[begin : begin + step]
            u, v, inside, distance = self.project(chunk)
            footprint = self.footprints(distance, torch.arange(len(self.centres))).masked_fill(~inside, math.inf)
            best = footprint.argmin(dim=1)
            each = torch.arange(len(chunk))
            finest.append(torch.where(inside[each, best], best, -1))
            rows.append(v[each, best].floor().long())
            columns.append(u[each, best].floor().long())
            distances.append(distance[each, best])
        if not finest:
            empty = torch.zeros(0, dtype=torch.long)
            return empty, empty, empty, torch.zeros(0)
        return torch.cat(finest), torch.cat(rows), torch.cat(columns), torch.cat(distances)


@dataclass
class OpenTaskView:
    """The open task's frames on their grids of cells: their pinhole cameras, what the oracle renders in each cell
    (the distance to its surface) and which cells show something else than the oracle renders."""

    task: int
    cameras: Pinholes
    """The open task's frames (of the loaded images)."""
    strides: Tensor
    """(F,) pixels per cell side."""
    grid_widths: Tensor
    """(F,) cells per row."""
    cell_offsets: Tensor
    """(F,) index of each frame's first cell."""
    distances: Tensor
    """(C,) distance from the camera to the surface the oracle renders in each cell."""
    changed: Tensor
    """(C,) whether the cell's pixel differs from the oracle's colour by more than the threshold."""
    changed_pixels: Tensor
    """Flat pixel numbers of every trainable pixel of the changed cells (the open task's, in the dataset's order)."""

    def crosses_change(self, origins: Tensor, directions: Tensor, distances: Tensor) -> Tensor:
        """(N,) whether rays (origins and directions (N, 3)) cross, before the surface they end at `distances` (N,)
        away, a point an open-task frame sees changed (`observed_changed` at SAMPLES_ALONG_RAY points along each)."""
        fractions = torch.arange(1, SAMPLES_ALONG_RAY + 1, dtype=distances.dtype) / SAMPLES_ALONG_RAY
        along = distances[:, None] * fractions[None]
        points = origins[:, None] + directions[:, None] * along[..., None]
        return self.observed_changed(points.reshape(-1, 3)).view(-1, SAMPLES_ALONG_RAY).any(dim=1)

    def observed_changed(self, points: Tensor) -> Tensor:
        """(N,) whether an open-task frame sees each of `points` (N, 3) in a changed cell, not hidden behind the
        surface the oracle renders there."""
        if len(points) == 0 or len(self.cameras.centres) == 0:
            return torch.zeros(len(points), dtype=torch.bool, device=points.device)
        u, v, inside, distance = self.cameras.project(points)
        column = (u.clamp(0, None).floor().long() // self.strides).clamp(max=self.grid_widths - 1)
        row = v.clamp(0, None).floor().long() // self.strides
        cell = (self.cell_offsets + row * self.grid_widths + column).clamp(0, len(self.changed) - 1)
        seen = distance <= self.distances[cell] * (1 + VISIBILITY_TOLERANCE)
        return (inside & seen & self.changed[cell]).any(dim=1)


def cell_grid(width: int, height: int) -> Tuple[int, Tensor, Tensor]:
    """A frame's cells: the stride and the pixel rows and columns of the cells' centres."""
    stride = max(1, math.ceil(math.sqrt(width * height / MAX_CELLS)))
    return stride, torch.arange(stride // 2, height, stride), torch.arange(stride // 2, width, stride)


@torch.no_grad()
def open_task_view(
    task: int,
    dataset: ContinualDataset,
    rays_of: Callable[[Tensor], RayBundle],
    render: Render,
    threshold: float,
    chunk: int,
    earlier_frames: Tensor,
) -> OpenTaskView:
    """Render the open task's frames (its pixels loaded in `dataset`) on their cells with the oracle (`render`, of
    the rays `rays_of` gives for (frame, y, x) indices) and compare them with the pixels there; a cell counts as
    changed only where one of `earlier_frames` saw its surface otherwise (`seen_otherwise`)."""
    frames = dataset.frames_of_task(task)
    start, _ = dataset.open_task_pixel_range()
    assert dataset.task_pixels is not None, "the open task's pixels are loaded"
    cameras = dataset.cameras
    indices, strides, grid_widths, offsets = [], [], [], []
    for frame in frames.tolist():
        width, height = int(cameras.width[frame]), int(cameras.height[frame])
        stride, rows, columns = cell_grid(width, height)
        y, x = torch.meshgrid(rows, columns, indexing="ij")
        offsets.append(sum(len(i) for i in indices))
        indices.append(torch.stack([torch.full_like(y, frame), y, x], dim=-1).reshape(-1, 3))
        strides.append(stride)
        grid_widths.append(len(columns))
    cells = torch.cat(indices)
    flat = dataset.pixel_offsets[cells[:, 0]] + cells[:, 1] * cameras.width.view(-1)[cells[:, 0]] + cells[:, 2]
    pixels = dataset.task_pixels[flat - start].float()
    colours, distances, points = render_pixels(cells, rays_of, render, chunk)
    difference = (colours - pixels).abs().mean(dim=-1)
    changed = (difference > threshold) & (difference > CONTRAST * difference.median())
    if dataset.valid_pixels is not None:  # a masked-out pixel shows nothing the open task learns
        changed &= dataset.valid_pixels.contains(flat)
    candidates = torch.nonzero(changed).view(-1)
    open_cameras = Pinholes.of(cameras, frames)
    cell_cameras = torch.repeat_interleave(torch.arange(len(frames)), torch.tensor([len(i) for i in indices]))
    footprints = open_cameras.footprints(distances[candidates], cell_cameras[candidates])
    earlier = Pinholes.of(cameras, earlier_frames)
    confirmed = seen_otherwise(
        points[candidates], pixels[candidates], footprints, earlier, rays_of, render, threshold, chunk
    )
    changed[candidates] = confirmed
    changed_pixels = pixels_of_cells(dataset, cells[changed], torch.tensor(strides)[cell_cameras[changed]])
    return OpenTaskView(
        task=task,
        cameras=open_cameras,
        strides=torch.tensor(strides),
        grid_widths=torch.tensor(grid_widths),
        cell_offsets=torch.tensor(offsets),
        distances=distances,
        changed=changed,
        changed_pixels=changed_pixels,
    )


def seen_otherwise(
    points: Tensor,
    pixels: Tensor,
    footprints: Tensor,
    earlier: Pinholes,
    rays_of: Callable[[Tensor], RayBundle],
    render: Render,
    threshold: float,
    chunk: int,
) -> Tensor:
    """(M,) whether the earlier frame that sees each of `points` (M, 3) (the surfaces the oracle renders in the open
    task's candidate cells) finest sees it, unhidden, in another colour than `pixels` (M, 3) (the open task's pixels
    there), as the oracle renders that frame, with pixels at most MAX_FOOTPRINT_RATIO times `footprints` (M,) (the
    open task's pixel sides there). Where the oracle renders the open task's view badly but no earlier frame saw the
    place (new ground), saw it only from far (detail it never learned) or saw it as the open task does (a viewpoint
    the oracle generalises to poorly), replay teaches nothing the new images contradict: not a change."""
    confirmed = torch.zeros(len(points), dtype=torch.bool)
    finest, rows, columns, distances = earlier.finest_view(points)
    resolved = earlier.footprints(distances, finest.clamp_min(0)) <= MAX_FOOTPRINT_RATIO * footprints
    viewed = torch.nonzero((finest >= 0) & resolved).view(-1)
    if len(viewed) == 0:
        return confirmed
    camera = finest[viewed]
    cells = torch.stack([earlier.frames[camera], rows[viewed], columns[viewed]], dim=-1)
    rendered, distance, _ = render_pixels(cells, rays_of, render, chunk)
    expected = distances[viewed]
    unhidden = (distance - expected).abs() <= VISIBILITY_TOLERANCE * expected
    differs = (rendered - pixels[viewed]).abs().mean(dim=-1) > threshold
    confirmed[viewed] = unhidden & differs
    return confirmed


def render_pixels(
    cells: Tensor, rays_of: Callable[[Tensor], RayBundle], render: Render, chunk: int
) -> Tuple[Tensor, Tensor, Tensor]:
    """The oracle's colour (N, 3), distance to its surface (N,) and that surface point (N, 3) through the pixels
    `cells` ((N, 3) frame, y, x), its jittered samples drawn with the guard's own SEED."""
    colours, distances, points = [], [], []
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(SEED)
        for begin in range(0, len(cells), chunk):
            rays = rays_of(cells[begin : begin + chunk])
            rgb, distance = render(rays)
            distance = distance.float().view(-1).cpu()
            origins, directions = rays.origins.float().cpu(), rays.directions.float().cpu()
            colours.append(rgb.float().cpu())
            distances.append(distance)
            points.append(origins + directions * distance[:, None])
    if not colours:
        return torch.zeros(0, 3), torch.zeros(0), torch.zeros(0, 3)
    return torch.cat(colours), torch.cat(distances), torch.cat(points)


def pixels_of_cells(dataset: ContinualDataset, cells: Tensor, strides: Tensor) -> Tensor:
    """Flat pixel numbers of the trainable pixels in the cells centred at `cells` ((N, 3) frame, y, x) whose
    sides are `strides` (N,) pixels."""
    if len(cells) == 0:
        return torch.zeros(0, dtype=torch.long)
    frame, y, x = cells.unbind(-1)
    step = torch.arange(int(strides.max()))
    rows = ((y // strides) * strides)[:, None, None] + step[None, :, None]
    columns = ((x // strides) * strides)[:, None, None] + step[None, None, :]
    width = dataset.cameras.width.view(-1)[frame].long()[:, None, None]
    height = dataset.cameras.height.view(-1)[frame].long()[:, None, None]
    within = step[None, :] < strides[:, None]  # (N, S): the offsets inside each cell's side
    inside = within[:, :, None] & within[:, None, :] & (rows < height) & (columns < width)
    flat = (dataset.pixel_offsets[frame][:, None, None] + rows * width + columns)[inside]
    if dataset.valid_pixels is not None:
        flat = flat[dataset.valid_pixels.contains(flat)]
    return flat


@dataclass
class GuardCount:
    """Replayed rays of the open task so far, and how many of them the guard skipped."""

    replayed: int = 0
    skipped: int = 0

    def share(self) -> float:
        return self.skipped / self.replayed if self.replayed else 0.0
