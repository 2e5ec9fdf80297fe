"""continual-ngp's hash-grid model: nerfstudio's hash-grid field and proposal sampler with the paper's sizes, trained with Eq. 4."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Dict, Tuple, Type

import torch
from nerfstudio.cameras.camera_optimizers import CameraOptimizerConfig
from nerfstudio.models.nerfacto import NerfactoModel, NerfactoModelConfig

from continual_nerf.compilation import compile_model, stop_input_gradients
from continual_nerf.core.distillation_loss import distillation_loss
from continual_nerf.errors import ContinualConfigError
from continual_nerf.nerfstudio_compat import proposal_sampler_state, set_proposal_sampler_state, without_lpips
from continual_nerf.validated_config import ValidatedConfig


@dataclass
class ContinualNGPModelConfig(ValidatedConfig, NerfactoModelConfig):
    """Hash grid + small MLP with the paper's hyperparameters (section 5.1); every nerfacto option still applies."""

    _target: Type = field(default_factory=lambda: ContinualNGPModel)
    num_levels: int = 16
    """Number of levels of the hash grid (paper: 16)."""
    base_res: int = 16
    """Resolution of the coarsest hash grid level (paper: 16)."""
    max_res: int = 512
    """Resolution of the finest hash grid level (paper: 512)."""
    log2_hashmap_size: int = 17
    """log2 of the hash table size per level (paper: 2^17)."""
    features_per_level: int = 2
    """Features per hash grid level (paper: 2)."""
    num_proposal_iterations: int = 1
    """Number of proposal-network sampling rounds before the field's samples."""
    num_proposal_samples_per_ray: Tuple[int, ...] = (64,)
    """Samples per ray for each proposal round."""
    num_nerf_samples_per_ray: int = 32
    """Samples per ray the field is evaluated at."""
    use_appearance_embedding: bool = False
    """Per-image appearance codes; off because images of future tasks have no code to learn yet."""
    camera_optimizer: CameraOptimizerConfig = field(default_factory=lambda: CameraOptimizerConfig(mode="off"))
    """Pose refinement; off because the paper trains on ground-truth poses."""
    compile: bool = True
    """Run the hash grids and MLPs through torch.compile (eager, after a one-line notice, where it cannot compile)."""
    detach_sample_positions: bool = True
    """Skip the gradient with respect to the field's sample positions: nerfacto computes it for normals only."""
    replay_sample_fraction: float = 1.0
    """Fraction of the samples per ray (every proposal round and the field) the replay oracle renders targets with:
    1 renders them as the model does; 0.5 halves the oracle's cost and loses fidelity that compounds over tasks."""

    def validate(self) -> None:
        super().validate()
        if not self.replay_sample_fraction > 0:
            raise ContinualConfigError(
                f"--pipeline.model.replay-sample-fraction must be positive, got {self.replay_sample_fraction}"
            )
        if self.eval_num_rays_per_chunk < 1:  # nerfstudio would train a whole task, then fail at its evaluation
            raise ContinualConfigError(
                f"--pipeline.model.eval-num-rays-per-chunk must be at least 1, got {self.eval_num_rays_per_chunk}"
            )

    def replay_oracle_config(self) -> ContinualNGPModelConfig:
        """The config the replay oracle's frozen copy is built with: the same weights, fewer samples per ray."""

        def scaled(num_samples: int) -> int:
            return max(1, round(num_samples * self.replay_sample_fraction))

        return dataclasses.replace(
            self,
            num_proposal_samples_per_ray=tuple(scaled(n) for n in self.num_proposal_samples_per_ray),
            num_nerf_samples_per_ray=scaled(self.num_nerf_samples_per_ray),
        )


class ContinualNGPModel(NerfactoModel):
    """Nerfacto's field, sampler and renderers; the loss splits into Eq. 4's pixel and distillation terms."""

    config: ContinualNGPModelConfig

    def populate_modules(self) -> None:
        # nothing may download at run time, and this model reports PSNR and SSIM only
        with without_lpips():
            super().populate_modules()
        if self.config.compile:
            compile_model(self)
        if self.config.detach_sample_positions and not self.config.predict_normals:
            stop_input_gradients(
                self.field.mlp_base
            )  # outside the compiled forward, so its graph has no input gradient

    def get_loss_dict(self, outputs, batch, metrics_dict=None) -> Dict[str, torch.Tensor]:
        loss_dict = super().get_loss_dict(outputs, batch, metrics_dict)
        if "is_replay" in batch:
            del loss_dict["rgb_loss"]
            loss_dict.update(distillation_loss(outputs["rgb"], batch["image"].to(self.device), batch["is_replay"]))
        return loss_dict

    def get_image_metrics_and_images(
        self, outputs: Dict[str, torch.Tensor], batch: Dict[str, torch.Tensor]
    ) -> Tuple[Dict[str, float], Dict[str, torch.Tensor]]:
        metrics_dict, images_dict = super().get_image_metrics_and_images(outputs, batch)
        del metrics_dict["lpips"]
        return metrics_dict, images_dict

    def get_extra_state(self) -> Dict[str, int]:
        # the proposal sampler's counters decide whether its networks are updated at a step; a checkpoint keeps them
        # so that a resumed run trains exactly as the uninterrupted one
        return proposal_sampler_state(self)

    def set_extra_state(self, state: Dict[str, int]) -> None:
        set_proposal_sampler_state(self, state)
