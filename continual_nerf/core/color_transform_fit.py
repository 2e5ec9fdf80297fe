"""Where the open task's colour transforms start: fitted to its images against what the model already renders.

An exposure or white-balance jump at a task switch (auto-exposure moving on between two stretches of a capture)
leaves the new frames' transforms, started at the previous task's, far from their images. Learning closes that gap
only over many iterations, and meanwhile pulls the field's colours toward the new exposure where earlier tasks saw
the same surfaces, which replay then has to undo. At the switch the model renders the open task's frames from what
earlier tasks taught it; a per-channel gain between that render and the frames' pixels, robust to the parts of the
frames no earlier task saw, starts each transform at its frame's exposure.
"""

from __future__ import annotations

import torch
from torch import Tensor

from continual_nerf.core.continual_datamanager import ContinualDataManager
from continual_nerf.core.ngp_model import ContinualNGPModel
from continual_nerf.core.per_frame import TRAINING_FRAME

PIXELS_PER_FRAME = 256
"""Pixels of every open-task frame rendered for the fit."""
MIN_PIXELS = 32
"""A transform row with fewer usable pixels keeps its start."""
USABLE_RANGE = (0.02, 0.98)
"""Pixels (recorded and rendered) inside this range: dark ones' ratios are noise, clipped ones' are not gains."""
LOG_GAIN_BANDWIDTH = 0.05
"""Width of the kernel the mode of the log ratios is found with (about 5 % in gain)."""
MEAN_SHIFT_STEPS = 20
"""Mean-shift iterations from the median (each moves by less than the kernel's width; 20 settle well within 1 %)."""


def log_gain_mode(log_ratios: Tensor) -> Tensor:
    """The most common value of `log_ratios` (N,): mean shift from their median, so that pixels showing what the
    model has not seen yet (scattered ratios) do not pull the gain the seen ones agree on."""
    mode = log_ratios.median()
    for _ in range(MEAN_SHIFT_STEPS):
        weights = torch.exp(-0.5 * ((log_ratios - mode) / LOG_GAIN_BANDWIDTH) ** 2)
        mode = (weights * log_ratios).sum() / weights.sum().clamp_min(1e-12)
    return mode


def fit_gains(rendered: Tensor, recorded: Tensor, rows: Tensor) -> dict[int, Tensor]:
    """Per transform row (`rows`, N, of pixels (N, 3)): the per-channel gain (3,) that takes `rendered` to
    `recorded`; rows without enough usable pixels in a channel are left out."""
    low, high = USABLE_RANGE
    usable = (rendered > low) & (rendered < high) & (recorded > low) & (recorded < high)
    log_ratios = torch.log(recorded.clamp_min(low)) - torch.log(rendered.clamp_min(low))
    gains: dict[int, Tensor] = {}
    for row in rows.unique().tolist():
        in_row = (rows == row)[:, None] & usable
        if int(in_row.sum(dim=0).min()) < MIN_PIXELS:
            continue
        gains[row] = torch.stack([log_gain_mode(log_ratios[in_row[:, c], c]) for c in range(3)]).exp()
    return gains


@torch.no_grad()
def render_open_task_pixels(
    model: ContinualNGPModel, datamanager: ContinualDataManager
) -> tuple[Tensor, Tensor, Tensor]:
    """Colour the model renders (through each frame's colour transform) and records at `PIXELS_PER_FRAME` pixels of
    every open-task frame (on average; none a mask leaves out), and the frame of each; the pixels are drawn with their
    own generator, so that the run's random stream, and with it an exact resume, stays as without the fit."""
    dataset = datamanager.train_dataset
    task = dataset.open_task
    assert task is not None and dataset.task_pixels is not None, "the open task's pixels are read"
    start, end = dataset.open_task_pixel_range()
    generator = torch.Generator().manual_seed(task)
    flat = dataset.draw_pixels(start, end, PIXELS_PER_FRAME * len(dataset.frames_of_task(task)), generator=generator)
    recorded = dataset.task_pixels[flat - start].float()
    indices = datamanager.ray_indices(flat)
    was_training = model.training
    model.eval()
    rendered = []
    chunk = model.config.eval_num_rays_per_chunk
    for first in range(0, len(flat), chunk):
        rays = datamanager.train_ray_generator(indices[first : first + chunk])
        rays.metadata[TRAINING_FRAME] = rays.camera_indices
        rendered.append(model(rays)["rgb"].cpu().float())
    model.train(was_training)
    return torch.cat(rendered), recorded, indices[:, 0]


@torch.no_grad()
def fit_open_task_color_transforms(model: ContinualNGPModel, datamanager: ContinualDataManager) -> str:
    """Scale each open-task frame's colour transform by the gain fitted between the model's render and its pixels;
    returns a line saying what was fitted."""
    transforms = model.color_transforms
    assert transforms is not None, "the model has colour transforms"
    rendered, recorded, frames = render_open_task_pixels(model, datamanager)
    rows = transforms.code_of_frame[frames]
    gains = fit_gains(rendered, recorded, rows)
    for row, gain in gains.items():
        transforms.transforms[row] = gain.to(transforms.transforms.device)[:, None] * transforms.transforms[row]
    return fit_summary(gains, num_rows=len(rows.unique()))


def fit_summary(gains: dict[int, Tensor], num_rows: int) -> str:
    """E.g. "gains x0.71 to x0.78 fitted to 24 of 24 colour transforms" (the mean over channels of each)."""
    if not gains:
        return f"no colour transform fitted: too few usable pixels in all {num_rows}"
    means = torch.stack(list(gains.values())).mean(dim=1)
    return f"gains x{means.min():.2f} to x{means.max():.2f} fitted to {len(gains)} of {num_rows} colour transforms"
