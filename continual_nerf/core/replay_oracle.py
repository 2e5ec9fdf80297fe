"""The replay oracle: one frozen copy of the model, replaced at the end of every task (paper, section 4.3)."""

from __future__ import annotations

from typing import Optional, Tuple

import torch
from nerfstudio.cameras.rays import RayBundle
from nerfstudio.models.base_model import Model
from torch import nn

from continual_nerf.compilation import warm_up
from continual_nerf.core.ngp_model import ContinualNGPModelConfig
from continual_nerf.core.per_frame import TRAINING_FRAME
from continual_nerf.nerfstudio_compat import sample_rays_as_in_training


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
        return self.render_with_distance(ray_bundle)[0]

    @torch.no_grad()
    def render_with_distance(self, ray_bundle: RayBundle) -> Tuple[torch.Tensor, Optional[torch.Tensor]]:
        """`render`'s colour and the distance (N,) along each ray to the surface the copy renders (its median depth),
        None for a model that renders no depth."""
        assert self.model is not None, "the replay oracle is used before the first task ended"
        assert ray_bundle.camera_indices is not None, "replayed rays carry their training frame"
        ray_bundle.metadata[TRAINING_FRAME] = ray_bundle.camera_indices
        outputs = self.model(ray_bundle)
        depth = outputs.get("depth")
        return outputs["rgb"], None if depth is None else depth.view(-1)
