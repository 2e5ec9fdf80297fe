"""Where the open task's colour transforms start: fitted to its images against what the model already renders.

An exposure or white-balance jump at a task switch (auto-exposure moving on between two stretches of a capture)
leaves the new frames' transforms, started at the previous task's, far from their images. Learning closes that gap
only over many iterations, and meanwhile pulls the field's colours toward the new exposure where earlier tasks saw
the same surfaces, which replay then has to undo. At the switch the model renders the open task's frames from what
earlier tasks taught it; a per-channel gain between that render and the frames' pixels, robust to the parts of the
frames no earlier task saw, starts each transform at its frame's exposure. A frame that shows mostly what no earlier
task saw (the later frames of a task, which move into new ground) gives no such gain: what the model renders there is
a guess, and its ratios cluster wherever the guess's colour puts them. Such a frame starts at the gain of its camera's
nearest frame that does.
"""

from __future__ import annotations

from dataclasses import dataclass, field

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
MIN_AGREEMENT = 0.25
"""Share of a frame's usable pixels, in every channel, within the kernel's width of the frame's gain for the gain to be
read from the frame: below it the frame shows mostly what no earlier task saw."""


def log_gain_mode(log_ratios: Tensor) -> Tensor:
    """The most common value of `log_ratios` (N,): mean shift from their median, so that pixels showing what the
    model has not seen yet (scattered ratios) do not pull the gain the seen ones agree on."""
    mode = log_ratios.median()
    for _ in range(MEAN_SHIFT_STEPS):
        weights = torch.exp(-0.5 * ((log_ratios - mode) / LOG_GAIN_BANDWIDTH) ** 2)
        mode = (weights * log_ratios).sum() / weights.sum().clamp_min(1e-12)
    return mode


@dataclass
class Fit:
    """The gains transform rows start at: read from the rows' own frames, or borrowed from a nearby frame's."""

    fitted: dict[int, Tensor] = field(default_factory=dict)
    """Gain (3,) by row, read from the row's own frames."""
    borrowed: dict[int, Tensor] = field(default_factory=dict)
    """Gain (3,) by row, that of its camera's nearest fitted frame."""

    @property
    def gains(self) -> dict[int, Tensor]:
        return {**self.fitted, **self.borrowed}


def usable_log_ratios(rendered: Tensor, recorded: Tensor) -> tuple[Tensor, Tensor]:
    """Log of `recorded` over `rendered` (N, 3) and which of them a gain can be read from (N, 3)."""
    low, high = USABLE_RANGE
    usable = (rendered > low) & (rendered < high) & (recorded > low) & (recorded < high)
    return torch.log(recorded.clamp_min(low)) - torch.log(rendered.clamp_min(low)), usable


def gain_of(log_ratios: Tensor, pixels: Tensor) -> tuple[Tensor, float] | None:
    """The per-channel gain (3,) of `pixels` (N, 3 usable) and the least share of a channel's pixels that agree with
    it; None if a channel has too few."""
    if int(pixels.sum(dim=0).min()) < MIN_PIXELS:
        return None
    modes = [log_gain_mode(log_ratios[pixels[:, c], c]) for c in range(3)]
    agreement = min(
        float(((log_ratios[pixels[:, c], c] - modes[c]).abs() < LOG_GAIN_BANDWIDTH).float().mean()) for c in range(3)
    )
    return torch.stack(modes).exp(), agreement


def frames_that_show_the_gain(log_ratios: Tensor, usable: Tensor, frames: Tensor) -> Tensor:
    """The frames among `frames` (N,) whose pixels agree on a gain (MIN_AGREEMENT)."""
    agreeing = []
    for frame in frames.unique().tolist():
        read = gain_of(log_ratios, (frames == frame)[:, None] & usable)
        if read is not None and read[1] >= MIN_AGREEMENT:
            agreeing.append(frame)
    return torch.tensor(agreeing, dtype=torch.long)


def fit_gains(rendered: Tensor, recorded: Tensor, frames: Tensor, rows: Tensor, cameras: Tensor) -> Fit:
    """Per transform row (of pixels (N, 3) of `frames`, `rows` and `cameras`, N each): the per-channel gain (3,) that
    takes `rendered` to `recorded`, read from the row's frames whose pixels agree on one; a row without such a frame
    takes the gain of its camera's frame nearest in time that has one, and without any keeps its start."""
    log_ratios, usable = usable_log_ratios(rendered, recorded)
    agreeing = frames_that_show_the_gain(log_ratios, usable, frames)
    fit = Fit()
    for row in rows.unique().tolist():
        read = gain_of(log_ratios, ((rows == row) & torch.isin(frames, agreeing))[:, None] & usable)
        if read is not None:
            fit.fitted[row] = read[0]
    for row in rows.unique().tolist():
        if row not in fit.fitted and (nearest := nearest_agreeing_row(row, frames, rows, cameras, fit)) is not None:
            fit.borrowed[row] = fit.fitted[nearest]
    return fit


def nearest_agreeing_row(row: int, frames: Tensor, rows: Tensor, cameras: Tensor, fit: Fit) -> int | None:
    """The fitted row of the frame nearest in time (training frames are numbered in capture order) to `row`'s first
    frame among its camera's fitted frames; None if its camera has none."""
    first = int(frames[rows == row].min())
    camera = cameras[rows == row][0]
    candidates = (cameras == camera) & torch.isin(rows, torch.tensor(list(fit.fitted), dtype=torch.long))
    if not candidates.any():
        return None
    nearest = int((frames[candidates] - first).abs().argmin())
    return int(rows[candidates][nearest])


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
    rows, cameras = transforms.code_of_frame.cpu()[frames], model.camera_of_frame.cpu()[frames]
    fit = fit_gains(rendered, recorded, frames, rows, cameras)
    for row, gain in fit.gains.items():
        transforms.transforms[row] = gain.to(transforms.transforms.device)[:, None] * transforms.transforms[row]
    return fit_summary(fit, num_rows=len(rows.unique()))


def fit_summary(fit: Fit, num_rows: int) -> str:
    """E.g. "gains x0.71 to x0.78 fitted to 9 of 24 colour transforms, 15 more from their camera's nearest fitted
    frame" (the mean over channels of each)."""
    if not fit.fitted:
        return f"no colour transform fitted: too few pixels agree on a gain in all {num_rows}"
    means = torch.stack(list(fit.gains.values())).mean(dim=1)
    borrowed = f", {len(fit.borrowed)} more from their camera's nearest fitted frame" if fit.borrowed else ""
    fitted = f"fitted to {len(fit.fitted)} of {num_rows} colour transforms"
    return f"gains x{means.min():.2f} to x{means.max():.2f} {fitted}{borrowed}"
