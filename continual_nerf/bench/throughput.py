"""Training throughput of continual-ngp against nerfstudio's nerfacto, and the replay oracle's overhead.

    python -m continual_nerf.bench.throughput [--device cpu] [--steps 20] [--rays-per-batch 1024]

Every configuration is set up in one process on one device and timed with nerfstudio's own
Trainer.train_iteration, in turns (one step of each, again and again), so that a change in the machine's
load hits all of them alike. Ratios are medians over the turns of the ratio within a turn.
"""

from __future__ import annotations

import statistics
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, List, Literal, Tuple

import torch
import tyro
from nerfstudio.utils.rich_utils import CONSOLE
from rich.table import Table

from continual_nerf.bench.demo_runs import nerfacto_on_demo, on_demo, recipe_config
from continual_nerf.bench.grid import parse_recipe
from continual_nerf.core.continual_trainer import ContinualTrainer, ContinualTrainerConfig
from continual_nerf.dataparsers.continual_demo_dataparser import ContinualDemoDataParserConfig
from continual_nerf.method_configs import CONTINUAL_NGP, CONTINUAL_NGP_INCRE, CONTINUAL_NGP_PAPER
from continual_nerf.recipes import set_up_like_ns_train

REPLAY, PAPER, REPLAY_OFF, NERFACTO = "continual-ngp", "continual-ngp-paper", "continual-ngp-incre", "nerfacto"


@dataclass
class Throughput:
    """Step times of every configuration, measured in the same turns."""

    rays_per_batch: Dict[str, int] = field(default_factory=dict)
    """Rays per training batch of each configuration."""
    first_step: Dict[str, float] = field(default_factory=dict)
    """Seconds of each configuration's first step, one-off costs (compilation) included."""
    steps: Dict[str, List[float]] = field(default_factory=dict)
    """Seconds of each timed step, turn by turn."""
    replayed_share: Dict[str, float] = field(default_factory=dict)
    """Share of each replaying configuration's batch drawn from earlier tasks, in the timed task."""

    def median(self, name: str) -> float:
        return statistics.median(self.steps[name])

    def ratio(self, numerator: str, denominator: str) -> float:
        """Median over the turns of numerator's step time / denominator's."""
        return statistics.median(a / b for a, b in zip(self.steps[numerator], self.steps[denominator]))

    def report(self, device: str, num_tasks: int) -> None:
        table = Table(title=f"Training throughput on {device}")
        columns = (
            "configuration",
            "rays per batch",
            "first step (s)",
            "median step (ms)",
            "rays/s",
            "speed vs nerfacto",
        )
        for column in columns:
            table.add_column(column, justify="right")
        for name in self.steps:
            table.add_row(
                name,
                f"{self.rays_per_batch[name]}",
                f"{self.first_step[name]:.1f}",
                f"{self.median(name) * 1e3:.0f}",
                f"{self.rays_per_batch[name] / self.median(name):,.0f}",
                f"{self.ratio(NERFACTO, name):.2f}x",
            )
        CONSOLE.print(table)
        for name, share in self.replayed_share.items():
            CONSOLE.print(
                f"Replay overhead of {name} in task {num_tasks} of {num_tasks} ({100 * share:.0f}% of rays replayed): "
                f"{self.ratio(name, REPLAY_OFF):.2f}x the step without replay"
            )


@dataclass
class ThroughputBenchmark:
    """Times training steps of each configuration after a warm-up, all at --rays-per-batch but a variant that sets its
    own."""

    device: Literal["cpu", "cuda"] = "cpu"
    """Device to train on."""
    steps: int = 20
    """Timed training steps per configuration (after the warm-up)."""
    warmup_steps: int = 3
    """Untimed steps first, so one-off costs (allocation, compilation) are not counted."""
    rays_per_batch: int = 1024
    """Rays per training batch (the paper's 1024); a variant that sets --pipeline.datamanager.train-num-rays-per-batch
    is timed at its own."""
    num_tasks: int = 10
    """Tasks of the demo trajectory; continual methods are timed in the last task (half its rays replayed with
    continual-ngp's defaults, 90% with the paper's uniform batches at 10 tasks)."""
    data: Path = Path("data/continual-demo")
    """Where the demo scene is generated (and reused from)."""
    variants: Tuple[str, ...] = ()
    """More configurations to time, each NAME=METHOD OPTIONS: a registered method and ns-train options (e.g.
    "table 2^19=continual-ngp --pipeline.model.log2-hashmap-size 19")."""

    def configs(self, output_dir: Path) -> Dict[str, ContinualTrainerConfig]:
        """continual-ngp with its defaults, with the paper's recipe and without replay (continual-ngp-incre), and
        nerfacto; then the variants."""
        demo = ContinualDemoDataParserConfig(data=self.data)
        options = {"num_tasks": self.num_tasks, "train_num_rays_per_batch": self.rays_per_batch}
        configs = {
            REPLAY: on_demo(CONTINUAL_NGP, demo, self.device, output_dir, **options),
            PAPER: on_demo(CONTINUAL_NGP_PAPER, demo, self.device, output_dir, **options),
            REPLAY_OFF: on_demo(CONTINUAL_NGP_INCRE, demo, self.device, output_dir, **options),
            NERFACTO: nerfacto_on_demo(demo, self.device, output_dir, **options),
        }
        for recipe in map(parse_recipe, self.variants):
            if recipe.name in configs:
                raise SystemExit(f"--variants {recipe.name}: a configuration has that name already")
            config = recipe_config(recipe.arguments, f"--variants {recipe.name}", rays_per_batch=self.rays_per_batch)
            configs[recipe.name] = on_demo(config, demo, self.device, output_dir, num_tasks=self.num_tasks)
        return configs

    def last_task_trainer(self, config: ContinualTrainerConfig) -> ContinualTrainer:
        trainer = set_up_like_ns_train(config)
        while not trainer.pipeline.is_last_task:
            trainer.pipeline.open_next_task()
        return trainer

    def step_seconds(self, trainer: ContinualTrainer, step: int) -> float:
        start = time.perf_counter()
        trainer.train_iteration(step)
        if self.device == "cuda":
            torch.cuda.synchronize()
        return time.perf_counter() - start

    def measure(self, output_dir: Path) -> Throughput:
        """Step times of every configuration; their run folders go to `output_dir`, which must outlive the process's
        tensorboard writers (nerfstudio keeps them globally)."""
        configs = self.configs(output_dir)
        result = Throughput()
        trainers = {name: self.last_task_trainer(config) for name, config in configs.items()}
        for name in (REPLAY, PAPER):  # against continual-ngp-incre: a variant may differ from it in more than replay
            result.replayed_share[name] = replayed_share(trainers[name])
        for name, trainer in trainers.items():
            result.rays_per_batch[name] = configs[name].pipeline.datamanager.train_num_rays_per_batch
            result.first_step[name] = self.step_seconds(trainer, 0)
            for step in range(1, self.warmup_steps):
                trainer.train_iteration(step)
            result.steps[name] = []
        for step in range(self.warmup_steps, self.warmup_steps + self.steps):
            for name, trainer in trainers.items():
                result.steps[name].append(self.step_seconds(trainer, step))
        return result

    def main(self) -> None:
        with tempfile.TemporaryDirectory() as scratch:
            self.measure(Path(scratch)).report(self.device, self.num_tasks)


def replayed_share(trainer: ContinualTrainer) -> float:
    """Share of the open task's batches drawn from earlier tasks: the configured one, or their share of the pixels."""
    datamanager = trainer.pipeline.datamanager
    share = datamanager.open_task_share()
    if share is not None:
        return 1 - share
    return 1 - len(datamanager.open_task_pixels()[0]) / datamanager.total_train_pixels()


def entrypoint() -> None:
    tyro.cli(ThroughputBenchmark).main()


if __name__ == "__main__":
    entrypoint()
