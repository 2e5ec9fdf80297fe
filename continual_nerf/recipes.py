"""Two recipes the experiments command, the benchmarks and the tests share: a small, quiet run configuration, and
training it in this process exactly as `ns-train` would."""

from __future__ import annotations

import copy
import dataclasses
from pathlib import Path
from typing import Any, Literal, TypeVar

from nerfstudio.configs.base_config import InstantiateConfig
from nerfstudio.models.nerfacto import NerfactoModelConfig
from nerfstudio.utils import writer

from continual_nerf.baselines.nerf_model import ContinualNeRFModelConfig
from continual_nerf.core.continual_trainer import ContinualTrainer, ContinualTrainerConfig
from continual_nerf.nerfstudio_compat import seed_like_ns_train, without_lpips

NEVER = 10**9
"""A step interval nerfstudio's periodic evaluations never reach: the pipeline evaluates at every task end."""

ModelConfig = TypeVar("ModelConfig", bound=InstantiateConfig)


def quiet_config(
    config: ContinualTrainerConfig,
    output_dir: Path,
    device: Literal["cpu", "cuda"] = "cpu",
    small: bool = False,
    **datamanager: Any,
) -> ContinualTrainerConfig:
    """A copy of `config` on `device` writing into `output_dir`, logging to tensorboard only, with no periodic
    evaluation and the given datamanager options; `small` shrinks the model to train in seconds on a CPU."""
    config = copy.deepcopy(config)
    config.machine.device_type = device
    config.vis = "tensorboard"
    config.output_dir = output_dir
    config.steps_per_eval_batch = config.steps_per_eval_image = config.steps_per_eval_all_images = NEVER
    config.logging.local_writer.enable = False
    config.pipeline.datamanager = dataclasses.replace(config.pipeline.datamanager, **datamanager)
    if small:
        config.pipeline.model = small_model(config.pipeline.model)
    config.set_timestamp()
    return config


def small_model(model: ModelConfig) -> ModelConfig:
    """The same kind of model, small enough to train a few tasks in minutes on a CPU."""
    if isinstance(model, NerfactoModelConfig):
        return dataclasses.replace(
            model, num_levels=8, log2_hashmap_size=15, max_res=128, num_proposal_samples_per_ray=(32,),
            num_nerf_samples_per_ray=16, eval_num_rays_per_chunk=4096,
        )  # fmt: skip
    if isinstance(model, ContinualNeRFModelConfig):
        return dataclasses.replace(
            model, base_mlp_num_layers=4, base_mlp_layer_width=128, skip_connections=(2,), head_mlp_num_layers=1,
            head_mlp_layer_width=64, num_coarse_samples=32, num_importance_samples=32, eval_num_rays_per_chunk=4096,
        )  # fmt: skip
    return model


def set_up_like_ns_train(config: ContinualTrainerConfig) -> ContinualTrainer:
    """nerfstudio's Trainer for `config`, seeded and set up as `ns-train` sets up rank 0 (offline)."""
    writer.EVENT_WRITERS.clear()  # nerfstudio's writers are global: this run must not log into an earlier run's
    seed_like_ns_train(config.machine.seed)
    trainer = config.setup(local_rank=0, world_size=1)
    with without_lpips():  # nerfstudio's nerfacto builds LPIPS at set-up, which would download weights
        trainer.setup()
    return trainer


def train_like_ns_train(config: ContinualTrainerConfig) -> ContinualTrainer:
    """Save the config, set up and train as `ns-train` does; returns the trainer for inspection."""
    config.save_config()
    trainer = set_up_like_ns_train(config)
    trainer.train()
    return trainer
