"""The fully implicit baselines' model: nerfstudio's vanilla NeRF (frequency encoding + MLP), trained with Eq. 4."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Dict, Literal, Tuple, Type, cast

import torch
from nerfstudio.fields.vanilla_nerf_field import NeRFField
from nerfstudio.model_components.scene_colliders import AABBBoxCollider
from nerfstudio.models.vanilla_nerf import NeRFModel, VanillaModelConfig
from nerfstudio.utils import misc

from continual_nerf.core.continual_pipeline import ContinualPipelineConfig
from continual_nerf.core.distillation_loss import REPLAY_SKIPPED, distillation_loss
from continual_nerf.errors import ContinualConfigError
from continual_nerf.nerfstudio_compat import without_lpips
from continual_nerf.validated_config import ValidatedConfig


@dataclass
class ContinualNeRFModelConfig(ValidatedConfig, VanillaModelConfig):
    """Vanilla NeRF (coarse + fine MLP) with configurable MLP sizes; nerfstudio's defaults, the paper used 8 x 512."""

    _target: Type = field(default_factory=lambda: ContinualNeRFModel)
    base_mlp_num_layers: int = 8
    """Layers of the MLP from encoded position to density and feature (paper and nerfstudio: 8)."""
    base_mlp_layer_width: int = 256
    """Width of that MLP (nerfstudio: 256; the paper used 512 to match the hash grid's parameter count)."""
    skip_connections: Tuple[int, ...] = (4,)
    """Layers of that MLP that see the encoded position again (NeRF: the fifth)."""
    head_mlp_num_layers: int = 2
    """Layers of the MLP from feature and encoded direction to colour."""
    head_mlp_layer_width: int = 128
    """Width of the colour MLP."""
    near_plane: float = 0.05
    """Samples start this far from the camera and end where the ray leaves the scene box."""
    background_color: Literal["last_sample", "black", "white"] = "last_sample"
    """Colour behind the last sample (no random: replayed targets are rendered without it); as nerfacto's default."""

    def validate(self) -> None:
        super().validate()
        if self.eval_num_rays_per_chunk < 1:  # nerfstudio would train a whole task, then fail at its evaluation
            raise ContinualConfigError(
                f"--pipeline.model.eval-num-rays-per-chunk must be at least 1, got {self.eval_num_rays_per_chunk}"
            )
        layers = self.base_mlp_num_layers
        if not all(1 <= skip <= layers - 2 for skip in self.skip_connections):
            # nerfstudio's MLP builds the wider layer only there, and fails at the first batch otherwise
            raise ContinualConfigError(
                f"--pipeline.model.skip-connections must lie between 1 and --pipeline.model.base-mlp-num-layers - 2 "
                f"({layers - 2}), got {' '.join(map(str, self.skip_connections))}"
            )


class ContinualNeRFModel(NeRFModel):
    """nerfstudio's NeRFModel with the MLP sizes of its config, a scene-box collider and Eq. 4's loss."""

    config: ContinualNeRFModelConfig

    def populate_modules(self) -> None:
        # nothing may download at run time, and this model reports PSNR and SSIM only
        with without_lpips():
            super().populate_modules()
        # NeRFModel builds its fields with fixed sizes; rebuild them with the configured ones, same encodings
        self.field_coarse = self._make_field()
        self.field_fine = self._make_field()
        # the scenes are normalised into the scene box, so it bounds every ray better than fixed near/far planes
        self.collider = AABBBoxCollider(self.scene_box, near_plane=self.config.near_plane)

    def _make_field(self) -> NeRFField:
        assert self.field_coarse is not None
        return NeRFField(
            position_encoding=self.field_coarse.position_encoding,
            direction_encoding=self.field_coarse.direction_encoding,
            base_mlp_num_layers=self.config.base_mlp_num_layers,
            base_mlp_layer_width=self.config.base_mlp_layer_width,
            head_mlp_num_layers=self.config.head_mlp_num_layers,
            head_mlp_layer_width=self.config.head_mlp_layer_width,
            skip_connections=cast(
                Tuple[int], self.config.skip_connections
            ),  # nerfstudio annotates any length as Tuple[int]
        )

    def get_outputs(self, ray_bundle) -> Dict[str, torch.Tensor]:
        outputs = super().get_outputs(ray_bundle)
        outputs["rgb"] = outputs["rgb_fine"]  # the colour the evaluation and the replay oracle read
        return outputs

    def get_loss_dict(self, outputs, batch, metrics_dict=None) -> Dict[str, torch.Tensor]:
        if "is_replay" not in batch:
            return super().get_loss_dict(outputs, batch, metrics_dict)
        image = batch["image"].to(self.device)
        loss_dict = {}
        for level in ("coarse", "fine"):
            terms = distillation_loss(outputs[f"rgb_{level}"], image, batch["is_replay"], batch.get(REPLAY_SKIPPED))
            loss_dict.update({f"{name}_{level}": value for name, value in terms.items()})
        return misc.scale_dict(loss_dict, self.config.loss_coefficients)

    def get_image_metrics_and_images(self, outputs, batch) -> Tuple[Dict[str, float], Dict[str, torch.Tensor]]:
        metrics_dict, images_dict = super().get_image_metrics_and_images(outputs, batch)
        del metrics_dict["fine_lpips"]
        return metrics_dict, images_dict


@dataclass
class ContinualNeRFPipelineConfig(ContinualPipelineConfig):
    """The continual pipeline with the vanilla NeRF model (NeRF-Incre, MEIL-NeRF, NeRF*)."""

    model: ContinualNeRFModelConfig = field(default_factory=ContinualNeRFModelConfig)
    """The frequency-encoding MLP trained with Eq. 4."""
