"""Shared test helpers: tiny continual-ngp configurations that train in seconds on a CPU, and how to run them."""

from __future__ import annotations

import dataclasses
import os
import sys
from pathlib import Path
from typing import List, Sequence

from nerfstudio.data.dataparsers.base_dataparser import DataParserConfig

from continual_nerf.core.continual_trainer import ContinualTrainer, ContinualTrainerConfig
from continual_nerf.dataparsers.continual_demo_dataparser import ContinualDemoDataParserConfig
from continual_nerf.method_configs import continual_ngp
from continual_nerf.recipes import quiet_config, train_like_ns_train

DEMO_CACHE = Path(__file__).parent / ".cache" / "continual-demo"
"""The demo scenes the tests render, kept between test runs (rendering is the slow part of a tiny run)."""

SUBPROCESS_ENV = {**os.environ, "OMP_NUM_THREADS": "1"}
"""One thread per training subprocess: two processes with two threads each on two busy cores run ten times slower."""


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
    config = quiet_config(
        continual_ngp.config,
        output_dir,
        small=small_model,
        dataparser=dataparser,
        num_tasks=num_tasks,
        iterations_per_task=iterations_per_task,
        train_num_rays_per_batch=rays_per_batch,
        replay=replay,
    )
    config.pipeline.model = dataclasses.replace(config.pipeline.model, compile=compile)
    return config


def demo_parser(num_frames: int = 16, width: int = 24, height: int = 18, seed: int = 0) -> ContinualDemoDataParserConfig:
    return ContinualDemoDataParserConfig(data=DEMO_CACHE, num_frames=num_frames, width=width, height=height, seed=seed)


def ns_train_command(output_dir: Path, timestamp: str, options: Sequence[str], dataparser: Sequence[str]) -> List[str]:
    """`ns-train continual-ngp` with tiny_config's settings (CPU, tensorboard, small hash grid, 256 rays), then
    `options`, then the dataparser subcommand and its options."""
    tiny = {
        "machine.device-type": "cpu", "vis": "tensorboard", "output-dir": output_dir, "timestamp": timestamp,
        "steps-per-eval-batch": 10**9, "steps-per-eval-image": 10**9, "logging.local-writer.enable": False,
        "pipeline.model.num-levels": 8, "pipeline.model.log2-hashmap-size": 15, "pipeline.model.max-res": 128,
        "pipeline.model.num-nerf-samples-per-ray": 16, "pipeline.model.num-proposal-samples-per-ray": 32,
        "pipeline.model.eval-num-rays-per-chunk": 4096, "pipeline.datamanager.train-num-rays-per-batch": 256,
        "pipeline.model.compile": False,
    }
    flags = [item for name, value in tiny.items() for item in (f"--{name}", str(value))]
    return [str(Path(sys.executable).with_name("ns-train")), "continual-ngp", *flags, *options, *dataparser]


def train(config: ContinualTrainerConfig) -> ContinualTrainer:
    """Train `config` in this process as `ns-train` does (seeded with --machine.seed); returns the trainer."""
    return train_like_ns_train(config)
