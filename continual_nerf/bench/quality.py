"""How close each recipe comes to the joint upper bound, on both built-in scenes.

    python -m continual_nerf.bench.quality [--scenes room street] [--settings 5x240 10x120] [--output-dir ...]
        [--variants "NAME=METHOD OPTIONS" ...]

For every scene (the demo room and the demo street) and every setting (tasks x iterations per task, or tasks x
seconds per task with an `s` suffix: `5x20s`), trains continual-ngp with its defaults, continual-ngp with the
paper's recipe, continual-ngp with experience replay at 1 % and 5 % of the pixels and with every pixel kept (the most
any replay can give: what the data's arrival in tasks alone costs), iNGP-Incre and the joint bound, each through
nerfstudio's Trainer, and prints per run: final mean test PSNR, per-task spread of the final row, the largest drop
of a task from its best, each task's PSNR right after its own training (the mean of the accuracy matrix's diagonal:
what a task learned before later tasks could take any of it), mean SSIM and training seconds.
Finished runs are read back, not trained again, so an interrupted benchmark resumes. `results.md` in the output
folder holds the tables.
`--variants` adds recipes of your own: a registered method with ns-train options, e.g.
`--variants "table 2^19=continual-ngp --pipeline.model.log2-hashmap-size 19"`.
"""

from __future__ import annotations

import dataclasses
import json
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Dict, List, Literal, Optional, Tuple

import tyro
from nerfstudio.utils.rich_utils import CONSOLE
from rich.table import Table

from continual_nerf.atomic_files import write_text_atomically
from continual_nerf.bench.demo_runs import DemoBenchmark, check_names, parse_variant
from continual_nerf.core.accuracy_matrix import ACCURACY_MATRIX_FILENAME, AccuracyMatrix
from continual_nerf.core.continual_trainer import ContinualTrainerConfig
from continual_nerf.dataparsers.continual_demo_dataparser import ContinualDemoDataParserConfig
from continual_nerf.method_configs import CONTINUAL_NGP, CONTINUAL_NGP_INCRE, CONTINUAL_NGP_JOINT, CONTINUAL_NGP_PAPER
from continual_nerf.recipes import quiet_config, train_like_ns_train

Variant = Callable[[ContinualTrainerConfig], ContinualTrainerConfig]
Recipe = Tuple[ContinualTrainerConfig, Optional[Variant]]


def _with_buffer(fraction: float, **options: float) -> Variant:
    """Experience replay of a `fraction` of the training pixels, with other datamanager `options`."""

    def variant(config: ContinualTrainerConfig) -> ContinualTrainerConfig:
        config.pipeline.datamanager = dataclasses.replace(
            config.pipeline.datamanager, replay_buffer_fraction=fraction, **options
        )
        return config

    return variant


EVERY_PIXEL = 1.0
"""A replay buffer fraction that keeps every pixel of every closed task."""


def _learning_rates_of(source: ContinualTrainerConfig) -> Variant:
    def variant(config: ContinualTrainerConfig) -> ContinualTrainerConfig:
        config.pipeline.lr_decay_per_task = source.pipeline.lr_decay_per_task
        config.pipeline.lr_decay_start = source.pipeline.lr_decay_start
        return config

    return variant


RECIPES: Dict[str, Recipe] = {
    "continual-ngp": (CONTINUAL_NGP, None),
    "continual-ngp, paper recipe": (CONTINUAL_NGP_PAPER, None),
    "continual-ngp, ER 1 %": (CONTINUAL_NGP, _with_buffer(0.01)),
    "continual-ngp, ER 5 %": (CONTINUAL_NGP, _with_buffer(0.05)),
    # keeps what the continual setting forbids keeping: how far the tasks' arrival alone leaves a run from the bound
    "every pixel kept": (CONTINUAL_NGP, _with_buffer(EVERY_PIXEL, replay_buffer_share=1.0)),
    "iNGP-Incre": (CONTINUAL_NGP_INCRE, None),
    # the bound trains as continual-ngp does, every image at once: its rates fall over each task's last quarter too
    "joint (upper bound)": (CONTINUAL_NGP_JOINT, _learning_rates_of(CONTINUAL_NGP)),
}
"""What the benchmark trains, by the name its tables give it: a registered config and a change to it."""


@dataclass(frozen=True)
class Setting:
    """Tasks and the per-task budget, written `5x240` (iterations) or `5x20s` (training seconds)."""

    num_tasks: int
    iterations: Optional[int]
    seconds: Optional[float]

    @classmethod
    def parse(cls, text: str) -> "Setting":
        tasks, budget = text.lower().split("x")
        if budget.endswith("s"):
            return cls(int(tasks), None, float(budget[:-1]))
        return cls(int(tasks), int(budget), None)

    def __str__(self) -> str:
        budget = f"{self.seconds:g} s" if self.seconds is not None else f"{self.iterations} iterations"
        return f"{self.num_tasks} {'task' if self.num_tasks == 1 else 'tasks'} x {budget}"

    @property
    def key(self) -> str:
        return (
            f"{self.num_tasks}x{self.seconds:g}s" if self.seconds is not None else f"{self.num_tasks}x{self.iterations}"
        )


@dataclass(frozen=True)
class RunSummary:
    """What the tables show of one run."""

    final_mean_psnr: float
    """Mean test PSNR over all test frames after the last task."""
    spread: float
    """Largest minus smallest task PSNR of the final row."""
    largest_drop: float
    """Largest fall of a task from its best PSNR (in any row) to its final PSNR."""
    mean_ssim: float
    """Mean over tasks of the final row's SSIM."""
    train_seconds: float
    """Training seconds of the whole run (the pipeline's clock)."""
    iterations: int
    """Training iterations of the whole run (fewer with timed tasks where a step costs more)."""
    final_row: List[float]
    """Final test PSNR per task."""
    after_own_task: Optional[float] = None
    """Mean over tasks of each task's test PSNR right after its own training (the accuracy matrix's diagonal); None
    for a joint run, whose tasks all train from the start."""

    @classmethod
    def read(cls, path: Path) -> "RunSummary":
        """A run's summary.json; one written before after_own_task existed takes it from the run's accuracy matrix."""
        saved = json.loads(path.read_text())
        if "after_own_task" not in saved:
            matrices = list(path.parent.rglob(ACCURACY_MATRIX_FILENAME))
            saved["after_own_task"] = after_own_task(AccuracyMatrix.read(matrices[0])) if len(matrices) == 1 else None
        return cls(**saved)

    @classmethod
    def of(cls, matrix: AccuracyMatrix, train_seconds: float) -> "RunSummary":
        final = matrix.psnr[-1]
        best = [max(row[j] for row in matrix.psnr if len(row) > j) for j in range(len(final))]
        return cls(
            final_mean_psnr=matrix.mean_psnr[-1],
            spread=max(final) - min(final),
            largest_drop=max(b - f for b, f in zip(best, final)),
            mean_ssim=sum(matrix.ssim[-1]) / len(matrix.ssim[-1]),
            train_seconds=train_seconds,
            iterations=matrix.steps[-1] + 1,
            final_row=final,
            after_own_task=after_own_task(matrix),
        )


def after_own_task(matrix: AccuracyMatrix) -> Optional[float]:
    """The mean of the accuracy matrix's diagonal; None when its first row already measures every task (joint)."""
    if len(matrix.psnr[0]) > 1:
        return None
    return sum(row[-1] for row in matrix.psnr) / len(matrix.psnr)


@dataclass
class QualityBenchmark(DemoBenchmark):
    """Trains every recipe on both built-in scenes at each setting and prints how each compares to the joint bound."""

    scenes: Tuple[Literal["room", "street"], ...] = ("room", "street")
    """Built-in scenes to measure on (continual-demo --scene)."""
    settings: Tuple[str, ...] = ("5x240", "10x120")
    """Tasks x budget per task: iterations (5x240) or training seconds (5x20s)."""
    recipes: Tuple[str, ...] = tuple(RECIPES)
    """Which of the recipes to train (names as the tables print them)."""
    variants: Tuple[str, ...] = ()
    """More recipes, each NAME=METHOD OPTIONS: a registered method and ns-train options (the setting's own datamanager
    options, e.g. --pipeline.datamanager.num-tasks, are the benchmark's)."""
    output_dir: Path = Path("outputs/bench-quality")
    """Runs, results.json and results.md; finished runs found here are not trained again."""

    def main(self) -> None:
        check_names("recipes", self.recipes, RECIPES)
        recipes = {name: RECIPES[name] for name in self.recipes}
        folders = set(map(folder_name, RECIPES))
        for name, config in map(parse_variant, self.variants):
            if folder_name(name) in folders:  # two names, one run folder: one would read the other's runs
                raise SystemExit(f"--variants {name}: a recipe has that name (or run folder) already")
            folders.add(folder_name(name))
            recipes[name] = (config, None)
        results: Dict[str, Dict[str, Dict[str, dict]]] = {}
        for scene in self.scenes:
            for setting in map(Setting.parse, self.settings):
                runs = {name: self.run(scene, setting, name, recipe) for name, recipe in recipes.items()}
                results.setdefault(scene, {})[setting.key] = {n: dataclasses.asdict(r) for n, r in runs.items()}
                self.print_table(scene, setting, runs)
        write_text_atomically(self.output_dir / "results.json", json.dumps(results, indent=1))
        write_text_atomically(self.output_dir / "results.md", markdown(results))
        CONSOLE.print(f"[bold green]Tables: {self.output_dir / 'results.md'}")

    def run(self, scene: str, setting: Setting, name: str, recipe: Recipe) -> RunSummary:
        """The recipe's run at this scene and setting: read back if it finished before, trained otherwise."""
        folder = self.output_dir / "runs" / scene / setting.key / folder_name(name)
        summary_path = folder / "summary.json"
        if summary_path.exists():
            return RunSummary.read(summary_path)
        config = self.config(scene, setting, recipe, folder)
        CONSOLE.print(f"[bold]{scene}, {setting}: training {name}")
        trainer = train_like_ns_train(config)
        matrix = AccuracyMatrix.read(config.get_base_dir() / ACCURACY_MATRIX_FILENAME)
        summary = RunSummary.of(matrix, trainer.pipeline.budget.total_seconds)
        write_text_atomically(summary_path, json.dumps(dataclasses.asdict(summary), indent=1))
        return summary

    def config(self, scene: str, setting: Setting, recipe: Recipe, folder: Path) -> ContinualTrainerConfig:
        base, variant = recipe
        config = quiet_config(
            base,
            folder,
            device=self.device,
            dataparser=ContinualDemoDataParserConfig(data=self.data, scene=scene),  # type: ignore[arg-type]
            num_tasks=setting.num_tasks,
            iterations_per_task=setting.iterations or 1,  # unused when the tasks are timed
            seconds_per_task=setting.seconds,
            train_num_rays_per_batch=self.rays_per_batch,
        )
        config.save_only_latest_checkpoint = True
        return variant(config) if variant is not None else config

    def print_table(self, scene: str, setting: Setting, runs: Dict[str, RunSummary]) -> None:
        table = Table(title=f"{scene}, {setting}, {self.rays_per_batch} rays per batch")
        for column in TABLE_COLUMNS:
            table.add_column(column, justify="right")
        for name, run in runs.items():
            table.add_row(*table_row(name, run, runs.get("joint (upper bound)")))
        CONSOLE.print(table)


def folder_name(recipe: str) -> str:
    """The folder of a recipe's runs: its name without spaces or path separators."""
    return re.sub(r"[^\w.^%()-]", "", recipe.replace(",", "_"))


TABLE_COLUMNS = (
    "recipe", "final mean PSNR (dB)", "vs joint (dB)", "per-task spread (dB)", "largest drop from best (dB)",
    "right after own task (dB)", "mean SSIM", "training s", "iterations",
)  # fmt: skip


def table_row(name: str, run: RunSummary, joint: Optional[RunSummary]) -> List[str]:
    gap = f"{run.final_mean_psnr - joint.final_mean_psnr:+.2f}" if joint is not None else "n/a"
    return [
        name, f"{run.final_mean_psnr:.2f}", gap, f"{run.spread:.2f}", f"{run.largest_drop:.2f}",
        decibels(run.after_own_task),
        f"{run.mean_ssim:.3f}", f"{run.train_seconds:.0f}", str(run.iterations),
    ]  # fmt: skip


def decibels(value: Optional[float]) -> str:
    """A table cell of a PSNR that a run may not have."""
    return "n/a" if value is None else f"{value:.2f}"


def markdown(results: Dict[str, Dict[str, Dict[str, dict]]]) -> str:
    lines = ["# Quality against the joint bound (`python -m continual_nerf.bench.quality`)", ""]
    for scene, by_setting in results.items():
        for key, runs in by_setting.items():
            summaries = {name: RunSummary(**run) for name, run in runs.items()}
            lines += [f"## {scene}, {Setting.parse(key)}", "", "| " + " | ".join(TABLE_COLUMNS) + " |"]
            lines.append("|" + "---|" * len(TABLE_COLUMNS))
            joint = summaries.get("joint (upper bound)")
            lines += ["| " + " | ".join(table_row(name, run, joint)) + " |" for name, run in summaries.items()]
            lines.append("")
    return "\n".join(lines)


def entrypoint() -> None:
    tyro.cli(QualityBenchmark).main()


if __name__ == "__main__":
    entrypoint()
