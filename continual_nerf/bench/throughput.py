"""Training throughput of continual-ngp against nerfstudio's nerfacto, and the replay oracle's overhead.

    python -m continual_nerf.bench.throughput [--device cpu] [--steps 20] [--rays-per-batch 1024]

All figures come from one process on one device, timing nerfstudio's own Trainer.train_iteration.
"""

from __future__ import annotations

import dataclasses
import statistics
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Dict, Literal

import torch
import tyro
from nerfstudio.models.nerfacto import NerfactoModelConfig
from nerfstudio.utils.rich_utils import CONSOLE
from rich.table import Table

from continual_nerf.continual_model import without_lpips
from continual_nerf.continual_trainer import ContinualTrainer, ContinualTrainerConfig
from continual_nerf.dataparsers.continual_demo_dataparser import ContinualDemoDataParserConfig
from continual_nerf.method_configs import continual_ngp


@dataclass
class ThroughputBenchmark:
    """Times training steps of each configuration after a warm-up, all at the same batch size."""

    device: Literal["cpu", "cuda"] = "cpu"
    """Device to train on."""
    steps: int = 20
    """Timed training steps per configuration (after the warm-up)."""
    warmup_steps: int = 3
    """Untimed steps first, so one-off costs (allocation, compilation) are not counted."""
    rays_per_batch: int = 1024
    """Rays per training batch for every configuration (the paper's 1024)."""
    num_tasks: int = 10
    """Tasks of the demo trajectory; continual-ngp is timed in the last task, where 90% of rays are replayed."""
    data: Path = Path("data/continual-demo")
    """Where the demo scene is generated (and reused from)."""

    def trainer_config(self, replay: bool, output_dir: Path) -> ContinualTrainerConfig:
        config = dataclasses.replace(continual_ngp.config, vis="tensorboard", output_dir=output_dir)
        config.machine.device_type = self.device
        config.pipeline = dataclasses.replace(config.pipeline)
        config.pipeline.datamanager = dataclasses.replace(
            config.pipeline.datamanager,
            dataparser=ContinualDemoDataParserConfig(data=self.data),
            num_tasks=self.num_tasks,
            train_num_rays_per_batch=self.rays_per_batch,
            replay=replay,
        )
        config.set_timestamp()
        return config

    def median_step_seconds(self, trainer: ContinualTrainer) -> float:
        for step in range(self.warmup_steps):
            trainer.train_iteration(step)
        seconds = []
        for step in range(self.warmup_steps, self.warmup_steps + self.steps):
            start = time.perf_counter()
            trainer.train_iteration(step)
            if self.device == "cuda":
                torch.cuda.synchronize()
            seconds.append(time.perf_counter() - start)
        return statistics.median(seconds)

    def time_config(self, config: ContinualTrainerConfig, in_last_task: bool) -> float:
        trainer = config.setup(local_rank=0, world_size=1)
        with without_lpips():  # nerfacto builds LPIPS at set-up, which would download weights
            trainer.setup()
        datamanager = trainer.pipeline.datamanager
        while in_last_task and not datamanager.is_last_task:
            datamanager.open_next_task(trainer.pipeline.model)
        return self.median_step_seconds(trainer)

    def main(self) -> None:
        with tempfile.TemporaryDirectory() as scratch:
            output_dir = Path(scratch)
            nerfacto = self.trainer_config(replay=False, output_dir=output_dir)
            nerfacto.pipeline.model = NerfactoModelConfig(eval_num_rays_per_chunk=1 << 13)
            nerfacto.pipeline.datamanager.num_tasks = 1
            runs: Dict[str, Callable[[], float]] = {
                "continual-ngp (replay)": lambda: self.time_config(self.trainer_config(True, output_dir), True),
                "continual-ngp (replay off)": lambda: self.time_config(self.trainer_config(False, output_dir), True),
                "nerfacto": lambda: self.time_config(nerfacto, False),
            }
            seconds = {name: run() for name, run in runs.items()}
        self.report(seconds)

    def report(self, seconds: Dict[str, float]) -> None:
        table = Table(title=f"Training throughput on {self.device}, {self.rays_per_batch} rays per batch")
        for column in ("configuration", "median step (ms)", "rays/s", "vs nerfacto"):
            table.add_column(column, justify="right")
        for name, value in seconds.items():
            ratio = seconds["nerfacto"] / value
            table.add_row(name, f"{value * 1e3:.0f}", f"{self.rays_per_batch / value:,.0f}", f"{ratio:.2f}x")
        CONSOLE.print(table)
        overhead = seconds["continual-ngp (replay)"] / seconds["continual-ngp (replay off)"]
        CONSOLE.print(f"Replay overhead in task {self.num_tasks} of {self.num_tasks}: {overhead:.2f}x the step without replay")


def entrypoint() -> None:
    tyro.cli(ThroughputBenchmark).main()


if __name__ == "__main__":
    entrypoint()
