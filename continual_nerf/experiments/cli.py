"""The paper's experiments in one command: every method on one scene, one report folder (Tables 1-4, Fig. 6).

    python -m continual_nerf.experiments [options] [dataparser, e.g. continual-demo --num-frames 64]
    continual-nerf-experiments --help

Every run trains through nerfstudio's Trainer in this process, into <output-dir>/runs/<run>/. A run
whose accuracy_matrix.json says finished is never trained again, so running the same command again
resumes a partly finished report; a run cut short is trained again in a new folder beside the old one.
"""

from __future__ import annotations

import dataclasses
import json
import shlex
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Dict, List, Literal, Optional, Tuple

import tyro
from nerfstudio.configs.base_config import InstantiateConfig
from nerfstudio.configs.dataparser_configs import AnnotatedDataParserUnion, all_dataparsers
from nerfstudio.utils.rich_utils import CONSOLE
from rich.table import Table

from continual_nerf.atomic_files import write_text_atomically
from continual_nerf.core.continual_trainer import ContinualTrainerConfig
from continual_nerf.core.task_split import split_capture
from continual_nerf.dataparsers.continual_demo_dataparser import ContinualDemoDataParserConfig
from continual_nerf.errors import ContinualConfigError, ContinualNerfError, first_line
from continual_nerf.experiments import report
from continual_nerf.experiments.plan import TABLE1, Plan, RunSpec, continual_methods, is_implicit
from continual_nerf.experiments.runner import RunSettings, find_finished_run, load_run, train_missing_runs

PROG = "continual-nerf-experiments"
SETTINGS_FILE = "settings.json"
"""The settings that make runs comparable; a report folder only ever holds runs made with the same ones."""


def _scene_name(dataparser: InstantiateConfig) -> str:
    names = [name for name, config in all_dataparsers.items() if type(config) is type(dataparser)]
    return names[0] if names else type(dataparser).__name__


def _jsonable(value: Any) -> Any:
    """A config as plain JSON values, so two settings can be compared after a round trip through a file."""
    return json.loads(json.dumps(dataclasses.asdict(value), default=str))


@dataclass
class ExperimentsConfig:
    """Trains the paper's methods on one scene and writes one report folder: Tables 1-4, Fig. 6, report.md."""

    dataparser: AnnotatedDataParserUnion = field(
        default_factory=lambda: ContinualDemoDataParserConfig(num_frames=64, width=40, height=30)
    )
    """Scene: any registered dataparser (a subcommand); by default a CPU-sized demo room."""
    output_dir: Path = Path("reports/continual-demo")
    """Report folder: report.md, results.json, figures/ and the runs/ they come from; rerunning resumes it."""
    methods: Tuple[str, ...] = TABLE1
    """Methods of Tables 1 and 4, Fig. 6, the accuracy matrices, the forgetting table and the render strip."""
    num_tasks: int = 5
    """Tasks the trajectory is split into for Tables 1, 2 and 4 (paper: 10)."""
    iterations_per_task: int = 60
    """Per-task budget in training iterations for Tables 1, 3 and 4."""
    seconds_per_task: Optional[float] = None
    """Per-task budget in training seconds for Tables 1, 3 and 4, instead of iterations."""
    implicit_budget_factor: float = 1.0
    """Multiplies the per-task budget of the NeRF-backbone methods in Tables 1, 3 and 4 (paper: 10 min vs 1 min)."""
    time_budgets: Tuple[float, ...] = (1.0, 4.0)
    """Per-task training seconds of Table 2 (paper, on a GPU: 1, 5 and 30); none skips Table 2."""
    time_budget_methods: Tuple[str, ...] = ("continual-ngp-paper", "continual-nerf-meil")
    """Methods of Table 2."""
    task_counts: Tuple[int, ...] = (2, 5, 10)
    """Numbers of tasks of Table 3 (paper: 2, 5, 10, 20); none skips Table 3."""
    task_count_methods: Tuple[str, ...] = ("continual-ngp-paper",)
    """Methods of Table 3."""
    probe_task: int = 2
    """Task whose test PSNR Fig. 6 follows and whose first test view the render strip shows (paper: 2)."""
    test_interval: int = 8
    """Every test_interval-th frame of each task is held out for testing."""
    rays_per_batch: int = 256
    """Rays per training batch in every run (paper: 1024)."""
    model_size: Literal["cpu", "paper"] = "cpu"
    """cpu: 8-level 2^15 hash grids, a 4 x 128 NeRF MLP, fewer samples per ray; paper: the registered sizes."""
    device: Literal["cpu", "cuda"] = "cpu"
    """Device every run trains on."""
    seed: int = 0
    """Seed of the random generators at the start of every run (as ns-train's --machine.seed)."""

    def main(self, command: str = PROG) -> Dict[str, Any]:
        """Check every option, train the runs not finished yet, write the report; returns results.json's content."""
        try:
            methods = continual_methods()
            plan = self.plan(methods)
            self.check_scene(plan)
            self.check_report_folder()
        except (ContinualNerfError, OSError) as error:
            raise SystemExit(f"{PROG}: error: {first_line(error)}") from None
        self.output_dir.mkdir(parents=True, exist_ok=True)
        if not (self.output_dir / SETTINGS_FILE).exists():
            write_text_atomically(self.output_dir / SETTINGS_FILE, json.dumps(self.comparable_settings(), indent=2))
        train_missing_runs(plan, methods, self.run_settings())
        results = self.write_report(plan, methods, command)
        self.print_table1(results)
        return results

    def plan(self, methods: Dict[str, ContinualTrainerConfig]) -> Plan:
        """The runs of every table, after checking the options that define them."""
        self.check_options(methods)

        def budget(method: str) -> Dict[str, Any]:
            factor = self.implicit_budget_factor if is_implicit(methods[method]) else 1.0
            if self.seconds_per_task is not None:
                return {"iterations_per_task": None, "seconds_per_task": self.seconds_per_task * factor}
            return {"iterations_per_task": max(1, round(self.iterations_per_task * factor))}

        timed, counted = dict.fromkeys(self.time_budget_methods), dict.fromkeys(self.task_count_methods)
        return Plan(
            table1=[RunSpec(m, self.num_tasks, **budget(m)) for m in dict.fromkeys(self.methods)],
            table2=[RunSpec(m, self.num_tasks, None, s) for s in self.time_budgets for m in timed],
            table3=[RunSpec(m, n, **budget(m)) for m in counted for n in self.task_counts],
        )  # fmt: skip

    def check_options(self, methods: Dict[str, ContinualTrainerConfig]) -> None:
        """One-line errors naming the option, before anything is trained or written."""
        if not self.methods:
            raise ContinualConfigError("--methods must name at least one method")
        for option in ("methods", "time_budget_methods", "task_count_methods"):
            for name in getattr(self, option):
                if name not in methods:
                    known = ", ".join(sorted(methods))
                    raise ContinualConfigError(
                        f"--{option.replace('_', '-')}: unknown method {name!r} (known: {known})"
                    )
        checks = [
            ("num-tasks", self.num_tasks, self.num_tasks >= 1, "must be at least 1"),
            ("iterations-per-task", self.iterations_per_task, self.iterations_per_task >= 1, "must be at least 1"),
            ("seconds-per-task", self.seconds_per_task, self.seconds_per_task is None or self.seconds_per_task > 0,
             "must be positive"),
            ("implicit-budget-factor", self.implicit_budget_factor, self.implicit_budget_factor > 0,
             "must be positive"),
            ("time-budgets", self.time_budgets, all(s > 0 for s in self.time_budgets), "must all be positive"),
            ("task-counts", self.task_counts, all(n >= 1 for n in self.task_counts), "must all be at least 1"),
            ("probe-task", self.probe_task, 1 <= self.probe_task <= self.num_tasks,
             f"must be between 1 and --num-tasks ({self.num_tasks})"),
            ("test-interval", self.test_interval, self.test_interval >= 2, "must be at least 2"),
            ("rays-per-batch", self.rays_per_batch, self.rays_per_batch >= 1, "must be at least 1"),
        ]  # fmt: skip
        for option, value, valid, requirement in checks:
            if not valid:
                shown = " ".join(f"{v:g}" for v in value) if isinstance(value, tuple) else value
                raise ContinualConfigError(f"--{option} {requirement}, got {shown}")

    def check_scene(self, plan: Plan) -> None:
        """Read the scene once (generating the demo room if needed) and check every run's split into tasks fits it."""
        outputs = self.dataparser.setup().get_dataparser_outputs(split="train")
        num_frames = len(outputs.image_filenames)
        for spec in plan.runs():
            try:
                split_capture(outputs, spec.num_tasks, self.test_interval)
            except ContinualConfigError as error:
                option = "--num-tasks" if spec.num_tasks == self.num_tasks else "--task-counts"
                raise ContinualConfigError(
                    f"{option} {spec.num_tasks} does not fit the scene's {num_frames} frames ({first_line(error)})"
                ) from None

    def comparable_settings(self) -> Dict[str, Any]:
        """What every run of one report must share for its numbers to be comparable."""
        return {
            "dataparser": _jsonable(self.dataparser),
            "test_interval": self.test_interval,
            "rays_per_batch": self.rays_per_batch,
            "model_size": self.model_size,
            "device": self.device,
            "seed": self.seed,
        }

    def check_report_folder(self) -> None:
        """Refuse a report folder whose runs were made with other settings: its results would be mixed or lost."""
        path = self.output_dir / SETTINGS_FILE
        if not path.exists():
            if self.output_dir.exists() and any(self.output_dir.iterdir()):
                raise ContinualConfigError(f"--output-dir {self.output_dir} is not empty and holds no {SETTINGS_FILE}")
            return
        saved, current = json.loads(path.read_text()), self.comparable_settings()
        differing = [key for key in current if saved.get(key) != current[key]]
        if differing:
            raise ContinualConfigError(
                f"--output-dir {self.output_dir} holds a report made with other {', '.join(differing)}; "
                "choose another --output-dir"
            )

    def run_settings(self) -> RunSettings:
        return RunSettings(
            dataparser=self.dataparser,
            report_dir=self.output_dir,
            test_interval=self.test_interval,
            rays_per_batch=self.rays_per_batch,
            small=self.model_size == "cpu",
            device=self.device,
            seed=self.seed,
            probe_task=self.probe_task,
        )

    def write_report(self, plan: Plan, methods: Dict[str, ContinualTrainerConfig], command: str) -> Dict[str, Any]:
        """results.json, the figures and report.md, all from the finished runs of `plan`."""
        runs = {}
        for spec in plan.runs():
            run_dir = find_finished_run(self.output_dir, spec)
            assert run_dir is not None, f"{spec.key} was trained above"
            runs[spec.key] = load_run(
                self.output_dir, spec, run_dir, bool(methods[spec.method].pipeline.datamanager.joint)
            )
        results: Dict[str, Any] = {"settings": self.report_settings(command), "plan": plan.keys()}
        results.update(report.summarize(runs, plan.keys(), self.probe_task))
        results["figures"] = self.plot(results, [runs[key] for key in plan.keys()["table1"]])
        results["runs"] = runs
        write_text_atomically(self.output_dir / "results.json", json.dumps(results, indent=1))
        write_text_atomically(self.output_dir / "report.md", report.markdown(results))
        return results

    def report_settings(self, command: str) -> Dict[str, Any]:
        if self.seconds_per_task is not None:
            budget = f"{self.seconds_per_task:g} s"
        else:
            budget = f"{self.iterations_per_task} iterations"
        if self.implicit_budget_factor != 1:
            budget += f" (x{self.implicit_budget_factor:g} for NeRF-backbone methods)"
        return {
            "command": command,
            "scene": _scene_name(self.dataparser),
            "num_tasks": self.num_tasks,
            "budget": budget,
            **self.comparable_settings(),
        }

    def plot(self, results: Dict[str, Any], main_runs: List[report.Run]) -> Dict[str, Any]:
        """Every figure of the report, from this report's runs; returns their paths relative to the report."""
        figures = {
            "fig6": f"figures/fig6_task{self.probe_task}_psnr.png",
            "accuracy_matrices": {run["method"]: f"figures/accuracy_matrix_{run['method']}.png" for run in main_runs},
            "render_strip": f"figures/task{self.probe_task}_view_strip.png",
        }
        report.plot_fig6(results["fig6"], self.output_dir / figures["fig6"])
        for run in main_runs:
            report.plot_accuracy_matrix(run, self.output_dir / figures["accuracy_matrices"][run["method"]])
        rendered = [run for run in main_runs if run["renders"]]  # a run killed before its first record has none
        if rendered:
            report.plot_render_strip(
                rendered, self.output_dir, self.probe_task, self.output_dir / figures["render_strip"]
            )
        else:
            figures["render_strip"] = None
        return figures

    def print_table1(self, results: Dict[str, Any]) -> None:
        table = Table(title=f"Table 1: final mean test PSNR ({results['settings']['scene']})")
        for column in ("method", "paper", "PSNR (dB)", "training time (s)"):
            table.add_column(column)
        for row in results["table1"]:
            table.add_row(
                row["method"],
                row["name"],
                report.number(row["final_mean_psnr"]),
                report.number(row["train_seconds"], 1),
            )
        CONSOLE.print(table)
        CONSOLE.print(f"[bold green]Report: {self.output_dir / 'report.md'}")


def entrypoint() -> None:
    tyro.extras.set_accent_color("bright_yellow")
    config = tyro.cli(ExperimentsConfig, prog=PROG, description=__doc__.splitlines()[0])
    config.main(command=shlex.join([PROG, *sys.argv[1:]]))


if __name__ == "__main__":
    entrypoint()
