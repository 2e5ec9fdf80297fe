"""The configurations the benchmarks compare: registered methods on the demo scene, and nerfstudio's nerfacto."""

from __future__ import annotations

import copy
import dataclasses
from pathlib import Path
from typing import Any, Literal

from nerfstudio.configs.method_configs import method_configs as nerfstudio_methods

from continual_nerf.continual_model import without_lpips
from continual_nerf.continual_trainer import ContinualTrainer, ContinualTrainerConfig
from continual_nerf.dataparsers.continual_demo_dataparser import ContinualDemoDataParserConfig
from continual_nerf.method_configs import continual_ngp

Device = Literal["cpu", "cuda"]


def on_demo(
    config: ContinualTrainerConfig,
    demo: ContinualDemoDataParserConfig,
    device: Device,
    output_dir: Path,
    **datamanager: Any,
) -> ContinualTrainerConfig:
    """A copy of `config` training on the `demo` scene, logging to tensorboard only, with datamanager options."""
    config = copy.deepcopy(config)
    config.vis = "tensorboard"
    config.output_dir = output_dir
    config.machine.device_type = device
    config.logging.local_writer.enable = False
    config.pipeline.datamanager = dataclasses.replace(config.pipeline.datamanager, dataparser=demo, **datamanager)
    config.set_timestamp()
    return config


def nerfacto_on_demo(
    demo: ContinualDemoDataParserConfig, device: Device, output_dir: Path, **datamanager: Any
) -> ContinualTrainerConfig:
    """nerfstudio's registered nerfacto (model and optimizers) fed by the same datamanager, all images open at once."""
    nerfacto = nerfstudio_methods["nerfacto"]
    config = on_demo(continual_ngp.config, demo, device, output_dir, replay=False, joint=True, **datamanager)
    config.method_name = "nerfacto"
    config.pipeline.model = copy.deepcopy(nerfacto.pipeline.model)
    config.optimizers = copy.deepcopy(nerfacto.optimizers)
    return config


def set_up(config: ContinualTrainerConfig) -> ContinualTrainer:
    """nerfstudio's Trainer for `config`, set up as `ns-train` sets it up (offline)."""
    trainer = config.setup(local_rank=0, world_size=1)
    with without_lpips():  # nerfacto builds LPIPS at set-up, which would download weights
        trainer.setup()
    return trainer
