"""PSNR and SSIM of a model on held-out test frames (and the rendered depth's error where the capture has depth maps),
optionally after fitting each test frame's pose to its image.

A capture whose poses carry errors of their own per image (COLMAP registers every image on its own) gives its test
frames errors no training frame shares: a render from the given pose then measures the pose error as much as the
field. Test-time pose alignment, the protocol of pose-refining NeRFs since BARF (Lin et al., 2021), fits a 6-DoF
correction of each test frame's pose to its image with the field frozen, then measures the render from the fitted
pose.
"""

from __future__ import annotations

import copy
import math
from dataclasses import dataclass
from typing import Any, Dict, Iterable, Iterator, List, Optional, Tuple

import torch
from nerfstudio.cameras.cameras import Cameras
from nerfstudio.cameras.lie_groups import exp_map_SO3xR3
from nerfstudio.data.datasets.base_dataset import InputDataset
from nerfstudio.models.base_model import Model
from nerfstudio.models.nerfacto import NerfactoModel
from torch import Tensor
from torchmetrics.functional.image import peak_signal_noise_ratio, structural_similarity_index_measure

from continual_nerf.compilation import input_gradients
from continual_nerf.core.depth_maps import DepthMaps, depth_errors, directions_norm
from continual_nerf.nerfstudio_compat import proposal_sampler_state, set_proposal_sampler_state


@dataclass(frozen=True)
class PoseAlignment:
    """How a test frame's pose is fitted to its image before it is measured."""

    steps: int
    """Adam steps on the frame's 6-DoF correction."""
    rays_per_step: int = 512
    """Pixels of the frame drawn at each step: plenty for six numbers."""
    lr: float = 2e-3
    """Starting rate, falling to a tenth over the steps."""


@dataclass(frozen=True)
class FrameScores:
    """Per test frame: PSNR (dB), SSIM and the rendered z-depth's errors (NaN for a frame without depth)."""

    psnr: Tensor
    ssim: Tensor
    depth_abs_rel: Tensor
    depth_rmse: Tensor
    """Metres."""


@torch.no_grad()
def evaluate_frames(
    model: Model,
    dataset: InputDataset,
    frames: List[int],
    alignment: Optional[PoseAlignment] = None,
    depth_maps: Optional[DepthMaps] = None,
    euclidean_depth: bool = False,
) -> FrameScores:
    """Per-frame PSNR (dB) and SSIM of full renders of `frames` against their images, each from its pose fitted to
    its image first when `alignment` is given; and the rendered depth's errors against `depth_maps`, when given (which
    hold z-depth, or distances along rays when `euclidean_depth`)."""
    psnrs, ssims, depth_scores = [], [], []
    for frame in frames:
        camera = dataset.cameras[frame : frame + 1].to(model.device)
        truth = dataset.get_image_float32(frame)[..., :3].to(model.device)
        if alignment is not None and alignment.steps > 0:
            camera = aligned_camera(model, camera, truth, alignment, seed=frame)
        outputs = model.get_outputs_for_camera(camera)
        rendered = outputs["rgb"].clamp(0, 1)
        rendered, truth = rendered.permute(2, 0, 1)[None], truth.permute(2, 0, 1)[None]
        psnrs.append(peak_signal_noise_ratio(rendered, truth, data_range=1.0))
        ssims.append(structural_similarity_index_measure(rendered, truth, data_range=1.0))
        depth_scores.append(frame_depth_errors(outputs, camera, depth_maps, frame, euclidean_depth))
    depth = torch.tensor(depth_scores, dtype=torch.float64).view(-1, 2)
    return FrameScores(torch.stack(psnrs).cpu(), torch.stack(ssims).cpu(), depth[:, 0], depth[:, 1])


def frame_depth_errors(
    outputs: Dict[str, Tensor], camera: Cameras, depth_maps: Optional[DepthMaps], frame: int, euclidean: bool = False
) -> Tuple[float, float]:
    """Absolute relative error and RMSE (metres) of the frame's rendered depth (NaN without depth maps or a depth
    output: the vanilla NeRF's is depth_fine)."""
    rendered = outputs.get("depth", outputs.get("depth_fine"))
    if depth_maps is None or rendered is None:
        return math.nan, math.nan
    if not euclidean:  # nerfstudio renders distance along unit rays; the ray's direction norm turns it into z-depth
        rendered = rendered / directions_norm(camera, 0).to(rendered.device)
    truth = depth_maps.read(frame)[..., None].to(rendered.device)
    return depth_errors(rendered, truth, depth_maps.metres_per_scene_unit)


def aligned_camera(model: Model, camera: Cameras, image: Tensor, alignment: PoseAlignment, seed: int) -> Cameras:
    """`camera` (one) turned about its centre and moved by the correction that makes the model's render of it match
    `image` (H, W, 3) best: every pixel's ray is turned and moved alike, as nerfacto's camera optimizer moves rays."""
    correction = fit_correction(model, camera, image, alignment, seed)
    pose = camera.camera_to_worlds[0]
    aligned = copy.copy(camera)
    aligned.camera_to_worlds = torch.cat(
        [correction[:, :3] @ pose[:, :3], (pose[:, 3] + correction[:, 3])[:, None]], 1
    )[None]
    return aligned


@torch.enable_grad()
def fit_correction(model: Model, camera: Cameras, image: Tensor, alignment: PoseAlignment, seed: int) -> Tensor:
    """(3, 4) rotation and translation of the rays of `camera` fitted by Adam on the colour error of random pixels;
    the model's weights are read, never changed."""
    rays = camera.generate_rays(camera_indices=0, keep_shape=True).flatten()
    pixels = image.reshape(-1, 3)
    tangent = torch.zeros(1, 6, device=image.device, requires_grad=True)
    optimizer = torch.optim.Adam([tangent], lr=alignment.lr)
    falling = torch.optim.lr_scheduler.ExponentialLR(optimizer, gamma=0.1 ** (1 / alignment.steps))
    # a generator of its own: fitting draws no number from the training's random streams
    generator = torch.Generator().manual_seed(seed)
    nerfacto = model if isinstance(model, NerfactoModel) else None
    sampler_state = proposal_sampler_state(nerfacto) if nerfacto is not None else {}
    for _ in range(alignment.steps):
        chosen = torch.randint(len(pixels), (alignment.rays_per_step,), generator=generator).to(image.device)
        batch = rays[chosen]
        correction = exp_map_SO3xR3(tangent)[0]
        batch.origins = batch.origins + correction[:3, 3]
        batch.directions = batch.directions @ correction[:3, :3].T
        with input_gradients():  # the pose's gradient flows through the sample positions
            loss = torch.nn.functional.mse_loss(model(batch)["rgb"], pixels[chosen])
            (gradient,) = torch.autograd.grad(loss, tangent)
        tangent.grad = gradient
        optimizer.step()
        falling.step()
    if nerfacto is not None:  # the proposal sampler counts calls: evaluation must not shift training's schedule
        set_proposal_sampler_state(nerfacto, sampler_state)
    return exp_map_SO3xR3(tangent.detach())[0]


class AlignedEvalCameras:
    """nerfstudio's eval dataloader (camera, batch pairs) with every camera's pose fitted to its image first, so that
    ns-eval and the eval images measure what the accuracy matrix measures."""

    def __init__(self, loader: Iterable[Tuple[Cameras, Dict[str, Any]]], model: Model, alignment: PoseAlignment):
        self.loader, self.model, self.alignment = loader, model, alignment

    def __len__(self) -> int:
        return len(self.loader)  # type: ignore[arg-type]

    def __iter__(self) -> Iterator[Tuple[Cameras, Dict[str, Any]]]:
        for camera, batch in self.loader:
            image = batch["image"][..., :3].to(self.model.device)
            yield aligned_camera(self.model, camera, image, self.alignment, seed=int(batch["image_idx"])), batch
