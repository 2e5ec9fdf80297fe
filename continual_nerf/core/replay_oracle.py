"""The replay oracle: one frozen copy of the model, replaced at the end of every task (paper, section 4.3)."""

from __future__ import annotations

from typing import Dict, Optional, Tuple

import torch
from nerfstudio.cameras.rays import RayBundle, RaySamples
from nerfstudio.models.base_model import Model
from torch import nn

from continual_nerf.compilation import warm_up
from continual_nerf.core.depth_maps import DIRECTIONS_NORM
from continual_nerf.core.ngp_model import ContinualNGPModelConfig
from continual_nerf.core.per_frame import TRAINING_FRAME
from continual_nerf.nerfstudio_compat import sample_rays_as_in_training

MIN_ACCUMULATION = 0.5
"""Opacity a replayed ray needs for the oracle's rendered depth to be a depth target (distill_replay_depth)."""


class ReplayOracle(nn.Module):
    """Renders pseudo ground truth for rays of past tasks from a frozen copy of the model.

    Exactly one copy exists: the first `update` builds it from the model's config, later ones
    overwrite its weights in place, so memory does not grow with the number of tasks.
    """

    def __init__(self, rays_per_batch: int = 1024) -> None:
        super().__init__()
        self.model: Optional[Model] = None
        self.rays_per_batch = rays_per_batch
        """Training batch size: the copy is compiled for batches of its order when it is built."""

    @property
    def ready(self) -> bool:
        return self.model is not None

    def update(self, model: Model) -> None:
        """Freeze a copy of `model` as the oracle, replacing the previous one."""
        if self.model is None:
            # a built nerfstudio model cannot be deep-copied; a second one from the same config can load its state
            config = model.config
            if isinstance(config, ContinualNGPModelConfig):  # same weights, rendered with fewer samples per ray
                config = config.replay_oracle_config()
            self.model = config.setup(scene_box=model.scene_box, num_train_data=model.num_train_data, **model.kwargs)
            self.model.to(model.device)
            self.model.requires_grad_(False)  # before compiling: compiled code is specialised on it
            warm_up(self.model, self.rays_per_batch, with_gradients=False)
        self.model.load_state_dict(model.state_dict())
        self.train()

    def train(self, mode: bool = True) -> "ReplayOracle":
        """The copy is never trained, whatever the pipeline does; but it samples along rays as the student does while it
        trains (jittered samples, the training near plane). The student learns the targets in training mode: targets
        rendered as evaluation renders would teach it the gap between the two renders (e.g. whatever density lies
        before the near plane, which training never sees), and the gap compounds from one copy to the next."""
        super().train(False)
        if self.model is not None:
            sample_rays_as_in_training(self.model)
        return self

    @torch.no_grad()
    def render(self, ray_bundle: RayBundle) -> torch.Tensor:
        """Colour (N, 3) the frozen copy renders along each ray, each ray with the appearance code and refined pose of
        the frame it came from, as training rendered that frame."""
        return self.outputs(ray_bundle)["rgb"]

    @torch.no_grad()
    def render_with_distance(self, ray_bundle: RayBundle) -> Tuple[torch.Tensor, Optional[torch.Tensor]]:
        """`render`'s colour and `surface_distance` along each ray."""
        outputs = self.outputs(ray_bundle)
        return outputs["rgb"], surface_distance(outputs)

    @torch.no_grad()
    def render_with_depth(self, ray_bundle: RayBundle, euclidean: bool = False) -> Tuple[torch.Tensor, torch.Tensor]:
        """Colour (N, 3) as `render`, and the `depth_target` (N, 1) of each ray."""
        outputs = self.outputs(ray_bundle)
        return outputs["rgb"], depth_target(outputs, ray_bundle, euclidean)

    @torch.no_grad()
    def weights_at(self, ray_samples: RaySamples) -> torch.Tensor:
        """The weights (N, S, 1) the frozen copy's density gives `ray_samples` (the model's own samples along replayed
        rays): where along each ray the oracle puts the light, at the points the model is trained at."""
        assert self.model is not None, "the replay oracle is used before the first task ended"
        density, _ = getattr(self.model, "field").get_density(ray_samples)
        return ray_samples.get_weights(density)

    @torch.no_grad()
    def outputs(self, ray_bundle: RayBundle) -> Dict[str, torch.Tensor]:
        """What the frozen copy renders along each ray (as `render` renders it): its model's outputs."""
        assert self.model is not None, "the replay oracle is used before the first task ended"
        assert ray_bundle.camera_indices is not None, "replayed rays carry their training frame"
        ray_bundle.metadata[TRAINING_FRAME] = ray_bundle.camera_indices
        return self.model(ray_bundle)


def surface_distance(outputs: Dict[str, torch.Tensor]) -> Optional[torch.Tensor]:
    """The distance (N,) along each ray to the surface the oracle renders (its median depth), None for a model that
    renders no depth."""
    depth = outputs.get("depth")
    return None if depth is None else depth.view(-1)


def depth_target(outputs: Dict[str, torch.Tensor], ray_bundle: RayBundle, euclidean: bool = False) -> torch.Tensor:
    """The depth (N, 1) the oracle renders along each ray: its expected depth as z-depth (or, `euclidean`, as distance
    along the ray, as the depth maps hold it), 0 (no depth target) where less than half of the ray's light comes from
    a surface it has learned."""
    depth = outputs["expected_depth"]
    if not euclidean:
        depth = depth / ray_bundle.metadata[DIRECTIONS_NORM]
    return torch.where(outputs["accumulation"] >= MIN_ACCUMULATION, depth, 0.0)
