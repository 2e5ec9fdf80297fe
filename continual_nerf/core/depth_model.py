"""continual-ngp-depth's model: continual-ngp's hash grid trained on depth maps too, with depth-nerfacto's losses.

nerfstudio's DS-NeRF or URF depth loss (`depth_loss`, applied as depth-nerfacto applies it: to every proposal round
and the field, with its sigma and its schedule) on the rays a batch gives a depth target (`depth_image` above 0): the
open task's pixels that have a depth measurement, stored pixels of a replay buffer, and, with
--pipeline.model.distill-replay-depth, replayed rays with the depth the replay oracle renders. Every other ray has 0
and adds nothing: depth-nerfacto's losses mask it out. Replayed rays distil the oracle's weights along the ray by
default (--pipeline.model.replay-weights-loss-mult), so the geometry a task's depth maps taught holds after it closes.
Depth is z-depth (depth maps as sensors record them), turned into distance along each ray with the ray's direction
norm (`is_euclidean_depth` False).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Dict, Type

from nerfstudio.model_components.losses import DepthLossType
from nerfstudio.models.base_model import ModelConfig
from nerfstudio.models.depth_nerfacto import DepthNerfactoModel, DepthNerfactoModelConfig

from continual_nerf.core.ngp_model import ContinualNGPModel, ContinualNGPModelConfig
from continual_nerf.errors import ContinualConfigError
from continual_nerf.nerfstudio_compat import depth_sigma, set_depth_sigma

DEPTH_SIGMA_KEY = "depth_sigma"
"""Extra-state key of the depth losses' sigma, which depth-nerfacto's schedule decays batch by batch."""


@dataclass
class ContinualNGPDepthModelConfig(ContinualNGPModelConfig, DepthNerfactoModelConfig):
    """continual-ngp's model plus depth-nerfacto's depth supervision; every depth-nerfacto option applies. Depths and
    sigmas are in scene units: metres times the dataparser's scale."""

    _target: Type = field(default_factory=lambda: ContinualNGPDepthModel)
    depth_loss_mult: float = 0.1
    """Lambda of the depth loss (depth-nerfacto's 1e-3 barely moves a task's geometry in a few hundred iterations)."""
    depth_sigma: float = 1e-4
    """Uncertainty around depth values in scene units (metres times the dataparser's scale); DS-NeRF reads it as a
    variance (1e-4: 0.01 scene units, 10 cm in the demo room), URF as a width."""
    starting_depth_sigma: float = 0.2
    """Uncertainty around depth values at the start of training when should_decay_sigma, in scene units."""
    depth_loss_type: DepthLossType = DepthLossType.DS_NERF
    """Depth loss: DS_NERF (DS-NeRF) or URF (Urban Radiance Fields); SPARSENERF_RANKING needs nerfstudio's pair
    sampler and pseudo-depth, which continual training does not draw."""
    replay_weights_loss_mult: float = 0.03
    """Lambda of the geometry distillation: replayed rays' weights along the ray pulled to the replay oracle's, so a
    closed task's surfaces stay where its depth maps put them; 0: replayed rays teach colour only."""
    distill_replay_depth: bool = False
    """Give replayed rays the depth the replay oracle renders as their depth target, as their colour; off: only the
    open task's pixels (and a replay buffer's) carry depth."""

    def validate(self) -> None:
        super().validate()
        if self.depth_loss_type not in (DepthLossType.DS_NERF, DepthLossType.URF):
            raise ContinualConfigError(
                f"--pipeline.model.depth-loss-type {self.depth_loss_type.name} is not supported: the ranking loss "
                "needs nerfstudio's pair sampler and pseudo-depth; use DS_NERF or URF"
            )
        if not self.depth_loss_mult >= 0:
            raise ContinualConfigError(
                f"--pipeline.model.depth-loss-mult must not be negative, got {self.depth_loss_mult}"
            )
        for name in ("depth_sigma", "starting_depth_sigma"):
            if not getattr(self, name) > 0:
                raise ContinualConfigError(
                    f"--pipeline.model.{name.replace('_', '-')} must be positive, got {getattr(self, name)}"
                )
        if not 0 < self.sigma_decay_rate <= 1:
            raise ContinualConfigError(
                f"--pipeline.model.sigma-decay-rate must be in (0, 1], got {self.sigma_decay_rate}"
            )


def trains_on_depth(model: ModelConfig) -> bool:
    """Whether a model of this config needs the training batches' depth targets."""
    return isinstance(model, ContinualNGPDepthModelConfig)


def euclidean_depth_maps(model: ModelConfig) -> bool:
    """Whether the depth maps hold distances along rays rather than z-depth (a depth model's is_euclidean_depth; every
    continual dataparser's sensors record z-depth)."""
    return isinstance(model, ContinualNGPDepthModelConfig) and model.is_euclidean_depth


class ContinualNGPDepthModel(ContinualNGPModel, DepthNerfactoModel):
    """ContinualNGPModel whose metrics and losses add depth-nerfacto's depth loss (DepthNerfactoModel's methods, next in
    line after ContinualNGPModel's)."""

    config: ContinualNGPDepthModelConfig

    def get_extra_state(self) -> Dict[str, Any]:
        # the sigma schedule's state: a resumed run goes on from the sigma the interrupted one had reached
        return {**super().get_extra_state(), DEPTH_SIGMA_KEY: depth_sigma(self)}

    def set_extra_state(self, state: Dict[str, Any]) -> None:
        super().set_extra_state(state)
        set_depth_sigma(self, state[DEPTH_SIGMA_KEY])
