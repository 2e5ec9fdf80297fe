"""continual-ngp's hash-grid model: nerfstudio's hash-grid field and proposal sampler with the paper's sizes, trained with Eq. 4."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import Dict, List, Literal, Optional, Tuple, Type

import torch
from nerfstudio.cameras.camera_optimizers import CameraOptimizerConfig
from nerfstudio.cameras.rays import RayBundle
from nerfstudio.engine.callbacks import TrainingCallback, TrainingCallbackAttributes, TrainingCallbackLocation
from nerfstudio.models.nerfacto import NerfactoModel, NerfactoModelConfig
from torch.nn import Parameter

from continual_nerf.compilation import compile_model, stop_input_gradients
from continual_nerf.core.depth_maps import DEPTH_KEY, DIRECTIONS_NORM, METRES_PER_SCENE_UNIT, depth_errors
from continual_nerf.core.distillation_loss import (
    REPLAY_SKIPPED,
    REPLAY_WEIGHTS,
    distillation_loss,
    distilled_rays,
    weights_distillation_loss,
)
from continual_nerf.core.per_frame import (
    FRAME_CAMERA,
    FRAME_TASK,
    TRAINING_FRAME,
    AppearanceGroups,
    FrameCodes,
    FrameColorTransforms,
    OpenTaskRows,
    code_of_frame,
    refine_rays,
)
from continual_nerf.errors import ContinualConfigError
from continual_nerf.nerfstudio_compat import (
    appearance_codes,
    codes_looked_up_per_ray,
    proposal_sampler_state,
    set_appearance_codes,
    set_proposal_sampler_state,
    without_lpips,
)
from continual_nerf.validated_config import ValidatedConfig

COLOR_TRANSFORM_GROUP = "color_transforms"
"""Optimizer parameter group of the colour transforms (--optimizers.color-transforms.optimizer.lr)."""


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
    """Appearance codes (exposure, white balance, camera response): one per --appearance-codes group, learned while its
    task is open, frozen when it closes; off: the paper."""
    use_color_transform: bool = False
    """An affine colour transform of the rendered colour (exposure, white balance, camera gain) per --appearance-codes
    group, learned while its task is open, frozen when it closes; the field keeps one colour for all; off: the paper."""
    color_transform_start: Literal["previous-task", "fitted"] = "fitted"
    """Where the open task's colour transforms start: the previous task's (same camera), or those times a per-channel
    gain fitted between the model's render of the task's frames and their pixels (an exposure jump at the switch); a
    frame showing mostly what no earlier task saw takes its camera's nearest fitted frame's gain."""
    appearance_codes: AppearanceGroups = "image"
    """What one appearance code or colour transform covers: one training image, or every image one camera took in
    one task."""
    camera_optimizer: CameraOptimizerConfig = field(default_factory=lambda: CameraOptimizerConfig(mode="off"))
    """Pose refinement (SO3xR3 or SE3): the open task's frames get learnable pose corrections, frozen when it closes;
    off: the paper, which trains on ground-truth poses."""
    compile: bool = True
    """Run the hash grids and MLPs through torch.compile (eager, after a one-line notice, where it cannot compile)."""
    detach_sample_positions: bool = True
    """Skip the gradient with respect to the field's sample positions: nerfacto computes it for normals only (and pose
    refinement, which keeps it)."""
    near_plane_metres: float = 2.0
    """Farthest the near plane may lie from the camera, in the capture's units (metres for every continual parser but
    a COLMAP model's): --pipeline.model.near-plane is in scene units, and a capture scaled down to fit its scene box (a
    long drive) would put nerfacto's 0.05 tens of metres out, past the facades beside the road."""
    finest_cell_metres: Optional[float] = 0.5
    """Largest edge of the finest hash-grid cell, in the capture's units (metres for every continual parser but a
    COLMAP model's): where a capture scaled down to fit its scene box (a long drive) would give --pipeline.model.max-res
    coarser cells, the finest resolution is raised to it, as instant-ngp's grows with its aabb_scale (same table,
    memory and step time); None keeps max-res."""
    replay_sample_fraction: float = 1.0
    """Fraction of the samples per ray (every proposal round and the field) the replay oracle renders targets with:
    1 renders them as the model does; 0.5 halves the oracle's cost and loses fidelity that compounds over tasks."""
    distillation_loss_mult: float = 1.0
    """Lambda of Eq. 4's distillation term: replayed rays' squared colour error against the replay oracle, beside the
    open task's pixels. Above 1, closed tasks follow the oracle more closely at the cost of the open task's share of
    each step, which a capture in many tasks (each closed task replayed by few rays) forgets less with. 1: the paper."""
    replay_weights_loss_mult: float = 0.0
    """Lambda of the geometry distillation: replayed rays' weights along the ray pulled to those the replay oracle's
    density gives at the same samples (squared error), so closed tasks' surfaces stay where they were. It pays where
    depth maps made each task's geometry right as it closed (continual-ngp-depth's default); from colour alone it holds
    early tasks' rough geometry that later tasks would correct. 0: colour only (the paper)."""

    def validate(self) -> None:
        super().validate()
        if not self.replay_sample_fraction > 0:
            raise ContinualConfigError(
                f"--pipeline.model.replay-sample-fraction must be positive, got {self.replay_sample_fraction}"
            )
        if not self.distillation_loss_mult > 0:
            raise ContinualConfigError(
                f"--pipeline.model.distillation-loss-mult must be positive (--pipeline.datamanager.replay False turns "
                f"replay off), got {self.distillation_loss_mult}"
            )
        if not self.replay_weights_loss_mult >= 0:
            raise ContinualConfigError(
                f"--pipeline.model.replay-weights-loss-mult must not be negative, got {self.replay_weights_loss_mult}"
            )
        if not self.near_plane_metres > 0:
            raise ContinualConfigError(
                f"--pipeline.model.near-plane-metres must be positive, got {self.near_plane_metres}"
            )
        if self.finest_cell_metres is not None and not self.finest_cell_metres > 0:
            raise ContinualConfigError(
                f"--pipeline.model.finest-cell-metres must be positive or None, got {self.finest_cell_metres}"
            )
        if self.eval_num_rays_per_chunk < 1:  # nerfstudio would train a whole task, then fail at its evaluation
            raise ContinualConfigError(
                f"--pipeline.model.eval-num-rays-per-chunk must be at least 1, got {self.eval_num_rays_per_chunk}"
            )

    @property
    def refines_poses(self) -> bool:
        """Whether the model learns pose corrections (--pipeline.model.camera-optimizer.mode)."""
        return self.camera_optimizer.mode != "off"

    @property
    def learns_per_frame(self) -> bool:
        """Whether the model learns parameters per training frame (appearance codes, colour transforms, pose
        corrections)."""
        return self.use_appearance_embedding or self.use_color_transform or self.refines_poses

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
    """Nerfacto's field, sampler and renderers; the loss splits into Eq. 4's pixel and distillation terms. Appearance
    codes and pose corrections, when on, are learned for the open task's frames only."""

    config: ContinualNGPModelConfig

    def populate_modules(self) -> None:
        # a copy: the run's config keeps the options as the user gave them
        self.config = dataclasses.replace(self.config, max_res=self._finest_resolution())
        # nothing may download at run time, and this model reports PSNR and SSIM only
        with without_lpips():
            super().populate_modules()
        self.collider.near_plane = self._near_plane()
        if self.config.compile:
            compile_model(self)
        # pose gradients flow through the sample positions
        if self.config.detach_sample_positions and not self.config.predict_normals and not self.config.refines_poses:
            stop_input_gradients(
                self.field.mlp_base
            )  # outside the compiled forward, so its graph has no input gradient
        self.task_of_frame, self.camera_of_frame = self._frame_tasks_and_cameras()
        codes = code_of_frame(self.task_of_frame, self.camera_of_frame, self.config.appearance_codes)
        if self.config.use_appearance_embedding:
            set_appearance_codes(self.field, FrameCodes(codes, self.config.appearance_embed_dim))
        self.color_transforms = FrameColorTransforms(codes) if self.config.use_color_transform else None
        self.open_task_rows: Optional[OpenTaskRows] = None
        """Keeps closed tasks' codes, colour transforms and pose corrections as they were; None without any."""
        if self.config.learns_per_frame:
            self.open_task_rows = OpenTaskRows(self._per_frame_parameters(), self.task_of_frame)

    def _near_plane(self) -> float:
        """nerfacto's near plane in scene units, brought in to --pipeline.model.near-plane-metres where the capture's
        scale makes it farther (a model built without the dataset's scale keeps nerfacto's)."""
        metres_per_unit = self._metres_per_unit()
        if metres_per_unit is None:
            return self.config.near_plane
        return min(self.config.near_plane, self.config.near_plane_metres / metres_per_unit)

    def _finest_resolution(self) -> int:
        """max-res, raised where the capture's scale makes its cells larger than --pipeline.model.finest-cell-metres
        (a model built without the dataset's scale keeps max-res)."""
        metres_per_unit = self._metres_per_unit()
        if metres_per_unit is None or self.config.finest_cell_metres is None:
            return self.config.max_res
        # nerfacto's grid spans the contracted space, [-2, 2] scene units, or the scene box without contraction
        extent = float((self.scene_box.aabb[1] - self.scene_box.aabb[0]).max())
        grid_units = extent if self.config.disable_scene_contraction else 4.0
        cells = math.ceil(grid_units * metres_per_unit / self.config.finest_cell_metres)
        return max(self.config.max_res, cells)

    def _metres_per_unit(self) -> Optional[float]:
        """The capture's units per scene unit, None for a model built without the dataset's scale."""
        metres_per_unit = (self.kwargs.get("metadata") or {}).get(METRES_PER_SCENE_UNIT)
        return None if metres_per_unit is None else float(metres_per_unit)

    def _frame_tasks_and_cameras(self) -> Tuple[torch.Tensor, torch.Tensor]:
        """Task and camera of every training frame, from the training dataset's metadata (one task and one camera
        when the model is built without it)."""
        metadata = self.kwargs.get("metadata") or {}
        zeros = torch.zeros(self.num_train_data, dtype=torch.long)
        return metadata.get(FRAME_TASK, zeros).long(), metadata.get(FRAME_CAMERA, zeros).long()

    def _per_frame_parameters(self) -> List[torch.Tensor]:
        codes = appearance_codes(self.field)
        return [
            *([codes.embedding.weight] if isinstance(codes, FrameCodes) else []),
            *([self.color_transforms.transforms] if self.color_transforms is not None else []),
            *(self.camera_optimizer.parameters()),
        ]

    def per_frame_state_keys(self) -> List[str]:
        """State-dict keys of the tensors that hold one row per training frame (codes, colour transforms, pose
        corrections and their code_of_frame lookups): a model of a longer trajectory holds more rows."""
        per_frame = {id(parameter) for parameter in self._per_frame_parameters()}
        return [
            key
            for key, value in self.state_dict(keep_vars=True).items()
            if id(value) in per_frame or key.endswith("code_of_frame")
        ]

    @property
    def fits_color_transforms(self) -> bool:
        """Whether a task's colour transforms start fitted to its frames (--pipeline.model.color-transform-start)."""
        return self.color_transforms is not None and self.config.color_transform_start == "fitted"

    def open_task(self, task: int, start: bool) -> None:
        """From now on only `task`'s codes, colour transforms and pose corrections change; `start`: the task opens now
        (rather than a resumed run continuing it), and its codes and transforms start from the previous task's."""
        codes = appearance_codes(self.field)
        if start and isinstance(codes, FrameCodes):
            codes.start_task(task, self.task_of_frame, self.camera_of_frame)
        if start and self.color_transforms is not None:
            self.color_transforms.start_task(task, self.task_of_frame, self.camera_of_frame)
        if self.open_task_rows is not None:
            self.open_task_rows.open(task)

    def get_training_callbacks(
        self, training_callback_attributes: TrainingCallbackAttributes
    ) -> List[TrainingCallback]:
        callbacks = super().get_training_callbacks(training_callback_attributes)
        if self.open_task_rows is None:
            return callbacks
        # first of the callbacks after an iteration: nothing may see a closed task's row moved by the optimizer step
        return [
            TrainingCallback([TrainingCallbackLocation.AFTER_TRAIN_ITERATION], self._restore_closed_rows)
        ] + callbacks

    def _restore_closed_rows(self, step: int) -> None:
        assert self.open_task_rows is not None
        self.open_task_rows.restore()

    def get_param_groups(self) -> Dict[str, List[Parameter]]:
        param_groups = super().get_param_groups()
        if self.color_transforms is not None:
            param_groups[COLOR_TRANSFORM_GROUP] = list(self.color_transforms.parameters())
        return param_groups

    def get_outputs(self, ray_bundle: RayBundle):
        frames = ray_bundle.metadata.get(TRAINING_FRAME)
        if self.training or frames is None:
            outputs = super().get_outputs(ray_bundle)
        else:
            # a training frame's rays outside training (replay, test frames): rendered as training renders that frame,
            # with its appearance code and refined pose, which nerfacto applies only while training (and its colour
            # transform, applied below in and outside training alike)
            ray_bundle.camera_indices = frames.long()
            refine_rays(self.camera_optimizer, ray_bundle)
            with codes_looked_up_per_ray(self.field):
                outputs = super().get_outputs(ray_bundle)
        if self.color_transforms is not None and (self.training or frames is not None):
            outputs["rgb"] = self._as_recorded(outputs["rgb"], ray_bundle)
        return outputs

    def _as_recorded(self, rgb: torch.Tensor, ray_bundle: RayBundle) -> torch.Tensor:
        """`rgb` through the colour transform of each ray's training frame."""
        assert self.color_transforms is not None
        assert ray_bundle.camera_indices is not None, "rays of a training frame carry its index"
        recorded = self.color_transforms(rgb, ray_bundle.camera_indices.view(-1))
        return recorded if self.training else recorded.clamp(0.0, 1.0)  # nerfstudio clamps outside training only

    def get_loss_dict(self, outputs, batch, metrics_dict=None) -> Dict[str, torch.Tensor]:
        loss_dict = super().get_loss_dict(outputs, batch, metrics_dict)
        if "is_replay" in batch:
            del loss_dict["rgb_loss"]
            terms = distillation_loss(
                outputs["rgb"], batch["image"].to(self.device), batch["is_replay"], batch.get(REPLAY_SKIPPED)
            )
            terms["distillation_loss"] = self.config.distillation_loss_mult * terms["distillation_loss"]
            loss_dict.update(terms)
        if REPLAY_WEIGHTS in batch:
            distilled = distilled_rays(batch["is_replay"], batch.get(REPLAY_SKIPPED))
            loss = weights_distillation_loss(outputs["weights_list"][-1], batch[REPLAY_WEIGHTS], distilled)
            loss_dict["weights_distillation_loss"] = self.config.replay_weights_loss_mult * loss
        return loss_dict

    def get_image_metrics_and_images(
        self, outputs: Dict[str, torch.Tensor], batch: Dict[str, torch.Tensor]
    ) -> Tuple[Dict[str, float], Dict[str, torch.Tensor]]:
        metrics_dict, images_dict = super().get_image_metrics_and_images(outputs, batch)
        del metrics_dict["lpips"]
        if DEPTH_KEY in batch:  # a capture with depth maps: how far the rendered geometry is from them (ns-eval)
            metres = float(self.kwargs["metadata"][METRES_PER_SCENE_UNIT])
            rendered = outputs["depth"]
            # distances along rays to z-depth, unless the depth maps hold such distances (a depth model's is_euclidean_depth)
            if not getattr(self.config, "is_euclidean_depth", False):
                rendered = rendered / batch[DIRECTIONS_NORM].to(rendered.device)
            truth = batch[DEPTH_KEY].to(rendered.device)
            metrics_dict["depth_abs_rel"], metrics_dict["depth_rmse"] = depth_errors(rendered, truth, metres)
        return metrics_dict, images_dict

    def get_extra_state(self) -> Dict[str, int]:
        # the proposal sampler's counters decide whether its networks are updated at a step; a checkpoint keeps them
        # so that a resumed run trains exactly as the uninterrupted one
        return proposal_sampler_state(self)

    def set_extra_state(self, state: Dict[str, int]) -> None:
        set_proposal_sampler_state(self, state)
