"""How close each recipe comes to the joint upper bound, on both built-in scenes.

    python -m continual_nerf.bench.quality [--scenes room street] [--settings 5x240 10x120] [--recipes ...]
        [--variants "NAME=METHOD OPTIONS" ...] [--options "NS-TRAIN OPTIONS"] [--jobs 1] [--output-dir ...]

For every scene and every setting (tasks x iterations per task, or tasks x seconds per task with an `s` suffix:
`5x20s`), trains each recipe through nerfstudio's Trainer and prints per run: final mean test PSNR, its gap to the
joint bound, per-task spread of the final row, the largest drop of a task from its best, each task's PSNR right after
its own training (the mean of the accuracy matrix's diagonal: what a task learned before later tasks could take any of
it), mean SSIM and training seconds. Finished runs are read back, not trained again, so an interrupted benchmark
resumes. `results.md` in the output folder holds the tables.
"""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Dict, List, Mapping, Optional, Tuple

import tyro
from matplotlib.figure import Figure
from nerfstudio.utils.rich_utils import CONSOLE
from rich.table import Table

from continual_nerf.atomic_files import write_text_atomically
from continual_nerf.bench.demo_runs import check_names
from continual_nerf.bench.grid import Grid, Recipe, RunSummary, Setting, decibels, folder_name, parse_recipe
from continual_nerf.dataparsers.continual_demo_dataparser import DemoScene
from continual_nerf.method_configs import CONTINUAL_NGP

JOINT = "joint (upper bound)"
"""The recipe every other is compared with."""

FALLING_RATES = (
    f"--pipeline.lr-decay-per-task {CONTINUAL_NGP.pipeline.lr_decay_per_task} "
    f"--pipeline.lr-decay-start {CONTINUAL_NGP.pipeline.lr_decay_start}"
)
"""continual-ngp's learning rates falling over each task's last quarter, for the bounds that train as it does."""
SENSOR_FLAWS = "--depth-noise 0.0015 --depth-max-range 4 --depth-edge-holes 1 --depth-dropout 0.05"
"""continual-demo's depth maps as a Kinect-like sensor records them: noise growing with depth, nothing beyond 4 m, holes
at edges and at random."""
STEREO_FLAWS = "--depth-noise 0.0007 --depth-max-range 40 --depth-edge-holes 1 --depth-dropout 0.1"
"""continual-demo's depth maps as a car's stereo rig measures them (a KITTI-like 0.54 m baseline and 720 px focal length
at a quarter pixel of disparity error): noise growing with the square of depth, nothing beyond 40 m, holes at edges
where one camera does not see, a tenth of the pixels unmatched."""
RECIPES: Dict[str, str] = {
    "continual-ngp": "continual-ngp",
    "continual-ngp, paper recipe": "continual-ngp-paper",
    "continual-ngp, ER 1 %": "continual-ngp --pipeline.datamanager.replay-buffer-fraction 0.01",
    "continual-ngp, ER 5 %": "continual-ngp --pipeline.datamanager.replay-buffer-fraction 0.05",
    "continual-ngp, distillation x2": "continual-ngp --pipeline.model.distillation-loss-mult 2",
    # the open task keeps its 512 rays a step, the closed tasks get 1536 instead of 512
    "continual-ngp, 3x replayed rays": "continual-ngp --pipeline.datamanager.train-num-rays-per-batch 2048 "
    "--pipeline.datamanager.current-task-fraction 0.25",
    # keeps what the continual setting forbids keeping: how far the tasks' arrival alone leaves a run from the bound
    "every pixel kept": "continual-ngp --pipeline.datamanager.replay-buffer-fraction 1 "
    "--pipeline.datamanager.replay-buffer-share 1.0",
    "iNGP-Incre": "continual-ngp-incre",
    "continual-ngp-depth": "continual-ngp-depth",
    "continual-ngp-depth, sensor flaws": f"continual-ngp-depth continual-demo {SENSOR_FLAWS}",
    "continual-ngp-depth, stereo flaws": f"continual-ngp-depth continual-demo {STEREO_FLAWS}",
    "continual-ngp-depth, geometry not distilled": "continual-ngp-depth --pipeline.model.replay-weights-loss-mult 0",
    # the bound trains as continual-ngp does, every image at once: its rates fall over each task's last quarter too
    JOINT: f"continual-ngp-joint {FALLING_RATES}",
    "joint, depth": f"continual-ngp-depth --pipeline.datamanager.joint True --pipeline.datamanager.replay False "
    f"{FALLING_RATES}",
}
"""What the benchmark trains, by the name its tables give it: ns-train arguments."""

Results = Dict[str, Dict[str, Dict[str, RunSummary]]]
"""Run summaries by scene, setting key and recipe name."""


@dataclass
class QualityBenchmark(Grid):
    """Trains every recipe on both built-in scenes at each setting and prints how each compares to the joint bound."""

    scenes: Tuple[DemoScene, ...] = ("room", "street")
    """Built-in scenes to measure on (continual-demo --scene): the long captures rooms and long-street too."""
    settings: Tuple[str, ...] = ("5x240", "10x120")
    """Tasks x budget per task: iterations (5x240) or training seconds (5x20s)."""
    recipes: Tuple[str, ...] = tuple(RECIPES)
    """Which of the recipes to train (names as the tables print them)."""
    variants: Tuple[str, ...] = ()
    """More recipes, each NAME=METHOD OPTIONS: a registered method and ns-train options (the setting's tasks and budget
    are the benchmark's)."""
    output_dir: Path = Path("outputs/bench-quality")
    """Runs, results.json and results.md; finished runs of the same arguments found here are not trained again."""

    def chosen_recipes(self) -> List[Recipe]:
        check_names("recipes", self.recipes, RECIPES)
        recipes = [Recipe.of(name, RECIPES[name]) for name in self.recipes]
        folders = set(map(folder_name, RECIPES))
        for recipe in map(parse_recipe, self.variants):
            if folder_name(recipe.name) in folders:  # two names, one run folder: one would read the other's runs
                raise SystemExit(f"--variants {recipe.name}: a recipe has that name (or run folder) already")
            folders.add(folder_name(recipe.name))
            recipes.append(recipe)
        return recipes

    def measure(self) -> Results:
        """Every chosen recipe's summary on every scene at every setting, trained where not finished before."""
        recipes = self.chosen_recipes()
        cells = [(scene, Setting.parse(text)) for scene in self.scenes for text in self.settings]
        runs = [run for scene, setting in cells for run in self.runs(scene, setting, recipes)]
        summaries = iter(self.summaries(runs))
        results: Results = {}
        for scene, setting in cells:
            results.setdefault(scene, {})[setting.key] = {recipe.name: next(summaries) for recipe in recipes}
        return results

    def main(self) -> None:
        results = self.measure()
        for scene, by_setting in results.items():
            for key, runs in by_setting.items():
                print_table(f"{scene}, {Setting.parse(key)}, {self.rays_per_batch} rays per batch", runs)
        saved = {
            s: {k: {n: dataclasses.asdict(r) for n, r in runs.items()} for k, runs in b.items()}
            for s, b in results.items()
        }
        write_text_atomically(self.output_dir / "results.json", json.dumps(saved, indent=1))
        write_text_atomically(
            self.output_dir / "results.md", markdown(results, "python -m continual_nerf.bench.quality")
        )
        plot_quality(results, self.output_dir / "results.png")
        CONSOLE.print(f"[bold green]Tables: {self.output_dir / 'results.md'}, plot: {self.output_dir / 'results.png'}")


TABLE_COLUMNS = (
    "recipe", "final mean PSNR (dB)", "vs joint (dB)", "per-task spread (dB)", "largest drop from best (dB)",
    "right after own task (dB)", "mean SSIM", "depth abs rel", "largest depth error growth", "training s",
    "iterations", "s per task, first -> last", "peak MiB, first -> last task",
)  # fmt: skip


def table_row(name: str, run: RunSummary, joint: Optional[RunSummary]) -> List[str]:
    gap = f"{run.final_mean_psnr - joint.final_mean_psnr:+.2f}" if joint is not None else "n/a"
    return [
        name, f"{run.final_mean_psnr:.2f}", gap, f"{run.spread:.2f}", f"{run.largest_drop:.2f}",
        decibels(run.after_own_task), f"{run.mean_ssim:.3f}", optional(run.final_depth_abs_rel, "{:.3f}"),
        optional(largest(run.depth_growth), "{:+.0%}"), f"{run.train_seconds:.0f}", str(run.iterations),
        first_to_last(run.seconds_per_task, "{:.1f}"), first_to_last(run.peak_mib_per_task, "{:.0f}"),
    ]  # fmt: skip


def optional(value: Optional[float], form: str) -> str:
    """A table cell of a number a run may not have."""
    return "n/a" if value is None else form.format(value)


def largest(values: Optional[List[Optional[float]]]) -> Optional[float]:
    """The largest of the values a run has (None where it has none)."""
    known = [value for value in values or [] if value is not None]
    return max(known) if known else None


def first_to_last(values: List[float], form: str) -> str:
    """A per-task quantity's first and last value (n/a for runs measured before it was recorded)."""
    return f"{form.format(values[0])} -> {form.format(values[-1])}" if values else "n/a"


def plot_quality(results: Results, path: Path) -> None:
    """Final mean test PSNR against the number of tasks, or against the iterations per task where every setting has
    the same number of tasks (the paper's "instant" axis); one panel per scene, one line per recipe and budget."""
    scenes = list(results)
    figure = Figure(figsize=(5.5 * len(scenes), 4.0), layout="constrained")
    for axes, scene in zip(figure.subplots(1, len(scenes), squeeze=False)[0], scenes):
        settings = [Setting.parse(key) for key in results[scene]]
        ticks = set()
        for recipe in results[scene][settings[0].key]:
            for label, points in series(settings, lambda s: results[scene][s.key][recipe].final_mean_psnr).items():
                x, psnr = zip(*sorted(points))
                axes.plot(x, psnr, marker="o", label=f"{recipe}{label}")
                ticks.update(x)
        axes.set_xscale("log", base=2)
        # the measured settings as ticks, not powers of 2
        axes.set_xticks(sorted(ticks), [f"{tick:g}" for tick in sorted(ticks)])
        axes.minorticks_off()
        axes.set_xlabel("tasks" if len({s.num_tasks for s in settings}) > 1 else "iterations per task")
        axes.set_ylabel("final mean test PSNR (dB)")
        axes.set_title(scene)
        axes.legend(fontsize=7)
    figure.savefig(path, dpi=120)


def series(settings: List[Setting], value: Callable[[Setting], float]) -> Dict[str, List[Tuple[float, float]]]:
    """The settings' points (x, value) by line: against the tasks, a line per budget per task (or per total budget
    where every setting has its own); against the budget per task where the tasks are the same."""
    if len({s.num_tasks for s in settings}) == 1:
        return {"": [(float(s.key.split("x")[1].rstrip("s")), value(s)) for s in settings]}
    by_task_budget = len({s.key.split("x")[1] for s in settings}) < len(settings)
    lines: Dict[str, List[Tuple[float, float]]] = {}
    for setting in settings:
        budget = setting.key.split("x")[1] + " per task" if by_task_budget else f"{total(setting)} in all"
        lines.setdefault(f" ({budget})", []).append((float(setting.num_tasks), value(setting)))
    return lines


def total(setting: Setting) -> str:
    """A setting's whole budget: iterations, or seconds."""
    if setting.seconds is not None:
        return f"{setting.num_tasks * setting.seconds:g} s"
    return f"{setting.num_tasks * (setting.iterations or 0)} iterations"


def print_table(title: str, runs: Mapping[str, RunSummary]) -> None:
    table = Table(title=title)
    for column in TABLE_COLUMNS:
        table.add_column(column, justify="right")
    for name, run in runs.items():
        table.add_row(*table_row(name, run, runs.get(JOINT)))
    CONSOLE.print(table)


def markdown_table(runs: Mapping[str, RunSummary]) -> List[str]:
    lines = ["| " + " | ".join(TABLE_COLUMNS) + " |", "|" + "---|" * len(TABLE_COLUMNS)]
    return lines + ["| " + " | ".join(table_row(name, run, runs.get(JOINT))) + " |" for name, run in runs.items()]


def markdown(results: Results, command: str) -> str:
    lines = [f"# Quality against the joint bound (`{command}`)", ""]
    for scene, by_setting in results.items():
        for key, runs in by_setting.items():
            lines += [f"## {scene}, {Setting.parse(key)}", "", *markdown_table(runs), ""]
    return "\n".join(lines)


def entrypoint() -> None:
    tyro.cli(QualityBenchmark).main()


if __name__ == "__main__":
    entrypoint()
