"""Shared fixtures: tiny continual-ngp configurations that train in seconds on a CPU."""

from __future__ import annotations

import dataclasses
import os
import sys
from pathlib import Path
from typing import Callable, List, Sequence

import numpy as np
import pytest
import torch
from nerfstudio.data.dataparsers.base_dataparser import transform_poses_to_original_space
from nerfstudio.data.dataparsers.base_dataparser import DataParserConfig

from continual_nerf.continual_trainer import ContinualTrainer, ContinualTrainerConfig
from continual_nerf.dataparsers.continual_demo_dataparser import ContinualDemoDataParserConfig
from continual_nerf.method_configs import continual_ngp

DEMO_CACHE = Path(__file__).parent / ".cache" / "continual-demo"


def tiny_config(
    output_dir: Path,
    dataparser: DataParserConfig,
    num_tasks: int = 2,
    iterations_per_task: int = 3,
    rays_per_batch: int = 256,
    replay: bool = True,
    small_model: bool = True,
    compile: bool = False,
) -> ContinualTrainerConfig:
    """continual-ngp on CPU with tensorboard only (no viewer) and, by default, a small hash grid, eager (compiling
    costs more than the few steps of a test save; tests/test_performance.py checks compiled = eager)."""
    config = dataclasses.replace(continual_ngp.config)
    config.machine.device_type = "cpu"
    config.vis = "tensorboard"
    config.output_dir = output_dir
    config.steps_per_eval_batch = 10**9
    config.steps_per_eval_image = 10**9
    config.logging.local_writer.enable = False
    pipeline = dataclasses.replace(config.pipeline)
    pipeline.datamanager = dataclasses.replace(
        pipeline.datamanager,
        dataparser=dataparser,
        num_tasks=num_tasks,
        iterations_per_task=iterations_per_task,
        train_num_rays_per_batch=rays_per_batch,
        replay=replay,
    )
    pipeline.model = dataclasses.replace(pipeline.model, compile=compile)
    if small_model:
        pipeline.model = dataclasses.replace(
            pipeline.model, num_levels=8, log2_hashmap_size=14, max_res=128, num_nerf_samples_per_ray=16,
            num_proposal_samples_per_ray=(32,), eval_num_rays_per_chunk=4096,
        )
    config.pipeline = pipeline
    config.set_timestamp()
    return config


def demo_parser(num_frames: int = 16, width: int = 24, height: int = 18, seed: int = 0) -> ContinualDemoDataParserConfig:
    return ContinualDemoDataParserConfig(data=DEMO_CACHE, num_frames=num_frames, width=width, height=height, seed=seed)


def ns_train_command(output_dir: Path, timestamp: str, options: Sequence[str], dataparser: Sequence[str]) -> List[str]:
    """`ns-train continual-ngp` with tiny_config's settings (CPU, tensorboard, small hash grid, 256 rays), then
    `options`, then the dataparser subcommand and its options."""
    tiny = {
        "machine.device-type": "cpu", "vis": "tensorboard", "output-dir": output_dir, "timestamp": timestamp,
        "steps-per-eval-batch": 10**9, "steps-per-eval-image": 10**9, "logging.local-writer.enable": False,
        "pipeline.model.num-levels": 8, "pipeline.model.log2-hashmap-size": 14, "pipeline.model.max-res": 128,
        "pipeline.model.num-nerf-samples-per-ray": 16, "pipeline.model.num-proposal-samples-per-ray": 32,
        "pipeline.model.eval-num-rays-per-chunk": 4096, "pipeline.datamanager.train-num-rays-per-batch": 256,
        "pipeline.model.compile": False,
    }
    flags = [item for name, value in tiny.items() for item in (f"--{name}", str(value))]
    return [str(Path(sys.executable).with_name("ns-train")), "continual-ngp", *flags, *options, *dataparser]


SUBPROCESS_ENV = {**os.environ, "OMP_NUM_THREADS": "1"}
"""One thread per training subprocess: two processes with two threads each on two busy cores run ten times slower."""


def original_poses(outputs) -> np.ndarray:
    """Undo the dataparser's orientation, centring and scale: metric OpenGL camera-to-world (N, 3, 4)."""
    poses = transform_poses_to_original_space(
        outputs.cameras.camera_to_worlds.double(),
        outputs.dataparser_transform.double(),
        outputs.dataparser_scale,
        "opengl",
    )
    return poses.numpy()


def train(config: ContinualTrainerConfig, seed: int = 0) -> ContinualTrainer:
    """Set up and run nerfstudio's Trainer as `ns-train` does; returns it for inspection."""
    torch.manual_seed(seed)
    config.save_config()
    trainer = config.setup(local_rank=0, world_size=1)
    trainer.setup()
    trainer.train()
    return trainer


@pytest.fixture
def single_thread():
    """In-process training on one thread, as the training subprocesses run (SUBPROCESS_ENV)."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


@pytest.fixture
def run_dir(tmp_path: Path) -> Path:
    return tmp_path / "outputs"


@pytest.fixture
def tiny() -> Callable[..., ContinualTrainerConfig]:
    return tiny_config
