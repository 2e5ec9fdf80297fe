"""PSNR and SSIM of a model on held-out test frames."""

from __future__ import annotations

from typing import List, Tuple

import torch
from nerfstudio.data.datasets.base_dataset import InputDataset
from nerfstudio.models.base_model import Model
from torchmetrics.functional.image import peak_signal_noise_ratio, structural_similarity_index_measure


@torch.no_grad()
def evaluate_frames(model: Model, dataset: InputDataset, frames: List[int]) -> Tuple[torch.Tensor, torch.Tensor]:
    """Per-frame PSNR (dB) and SSIM of full renders of `frames` against their images."""
    psnrs, ssims = [], []
    for frame in frames:
        camera = dataset.cameras[frame : frame + 1].to(model.device)
        rendered = model.get_outputs_for_camera(camera)["rgb"].clamp(0, 1)
        truth = dataset.get_image_float32(frame)[..., :3].to(rendered.device)
        rendered, truth = rendered.permute(2, 0, 1)[None], truth.permute(2, 0, 1)[None]
        psnrs.append(peak_signal_noise_ratio(rendered, truth, data_range=1.0))
        ssims.append(structural_similarity_index_measure(rendered, truth, data_range=1.0))
    return torch.stack(psnrs).cpu(), torch.stack(ssims).cpu()
