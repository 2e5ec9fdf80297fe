"""The paper's experiments in one command: every method on one scene, one report folder (Tables 1-4, Fig. 6).

    python -m continual_nerf.experiments [options] [dataparser, e.g. continual-demo --num-frames 64]
    continual-nerf-experiments --help

Every run trains through nerfstudio's Trainer in this process, into <output-dir>/runs/<run>/. A run
whose accuracy_matrix.json says finished is never trained again, so running the same command again
resumes a partly finished report; a run cut short is trained again in a new folder beside the old one.
"""

from __future__ import annotations

import copy
import dataclasses
import json
import shlex
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Dict, List, Literal, Optional, Tuple

import numpy as np
import torch
import tyro
from nerfstudio.configs.base_config import InstantiateConfig
from nerfstudio.configs.dataparser_configs import AnnotatedDataParserUnion, all_dataparsers
from nerfstudio.engine.callbacks import TrainingCallback, TrainingCallbackLocation
from nerfstudio.models.nerfacto import NerfactoModelConfig
from nerfstudio.plugins.registry import discover_methods
from nerfstudio.utils import writer
from nerfstudio.utils.rich_utils import CONSOLE
from PIL import Image
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TaskID, TextColumn, TimeElapsedColumn
from rich.table import Table

from continual_nerf import report
from continual_nerf.accuracy_matrix import ACCURACY_MATRIX_FILENAME, AccuracyMatrix
from continual_nerf.atomic_files import write_text_atomically
from continual_nerf.continual_trainer import ContinualTrainer, ContinualTrainerConfig
from continual_nerf.dataparsers.continual_demo_dataparser import ContinualDemoDataParserConfig
from continual_nerf.errors import ContinualConfigError, ContinualNerfError, first_line
from continual_nerf.nerf_model import ContinualNeRFModelConfig
from continual_nerf.task_schedule import split_into_tasks

PROG = "continual-nerf-experiments"
RUNS_DIR = "runs"
RUN_RECORD = "experiment_run.json"
"""Per run: training seconds of every task, wall time, and the probe view rendered at every task end."""
SETTINGS_FILE = "settings.json"
"""The settings that make runs comparable; a report folder only ever holds runs made with the same ones."""
PAPER_TABLE1 = (
    "continual-ngp", "continual-ngp-incre", "continual-ngp-ewc", "continual-nerf-incre", "continual-nerf-meil",
    "continual-ngp-joint", "continual-nerf-joint",
)  # fmt: skip


@dataclass(frozen=True)
class RunSpec:
    """One training run: a method, a number of tasks and a per-task budget (iterations or seconds)."""

    method: str
    num_tasks: int
    iterations_per_task: Optional[int]
    seconds_per_task: Optional[float] = None

    @property
    def key(self) -> str:
        budget = f"{self.seconds_per_task:g}s" if self.seconds_per_task is not None else f"{self.iterations_per_task}it"
        return f"{self.method}_{self.num_tasks}tasks_{budget}"


@dataclass
class Plan:
    """The runs behind each table; a run several tables need is trained once."""

    table1: List[RunSpec]
    table2: List[RunSpec]
    table3: List[RunSpec]

    def runs(self) -> List[RunSpec]:
        return list(dict.fromkeys(self.table1 + self.table2 + self.table3))

    def keys(self) -> Dict[str, List[str]]:
        """Run keys per table, as results.json lists them."""
        return {
            "table1": [spec.key for spec in self.table1],
            "table2": [spec.key for spec in self.table2],
            "table3": [spec.key for spec in self.table3],
        }


def continual_methods() -> Dict[str, ContinualTrainerConfig]:
    """Every registered nerfstudio method that trains task by task (this plugin's and any other's)."""
    methods, _ = discover_methods()
    return {name: config for name, config in methods.items() if isinstance(config, ContinualTrainerConfig)}


def cpu_sized(model: InstantiateConfig) -> InstantiateConfig:
    """The same kind of model, small enough that the default report trains in minutes on a CPU."""
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
    methods: Tuple[str, ...] = PAPER_TABLE1
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
    time_budget_methods: Tuple[str, ...] = ("continual-ngp", "continual-nerf-meil")
    """Methods of Table 2."""
    task_counts: Tuple[int, ...] = (2, 5, 10)
    """Numbers of tasks of Table 3 (paper: 2, 5, 10, 20); none skips Table 3."""
    task_count_methods: Tuple[str, ...] = ("continual-ngp",)
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
    """Seed of torch's random generator at the start of every run."""

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
        self.train_missing_runs(plan, methods)
        results = self.write_report(plan, methods, command)
        self.print_table1(results)
        return results

    def plan(self, methods: Dict[str, ContinualTrainerConfig]) -> Plan:
        """The runs of every table, after checking the options that define them."""
        self.check_options(methods)

        def budget(method: str) -> Dict[str, Any]:
            factor = self.implicit_budget_factor if _is_implicit(methods[method]) else 1.0
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
                split_into_tasks(
                    num_frames, spec.num_tasks, self.test_interval, time_group=outputs.metadata.get("time_group")
                )
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

    def run_config(self, spec: RunSpec, base: ContinualTrainerConfig) -> ContinualTrainerConfig:
        """The method's registered configuration with this report's scene, budget, size and output folder."""
        config = copy.deepcopy(base)
        config.machine.device_type = self.device
        config.vis = "tensorboard"
        config.output_dir = self.output_dir / RUNS_DIR
        config.experiment_name = spec.key
        # the pipeline evaluates every seen task at each task end; nerfstudio's periodic evaluations only cost time
        config.steps_per_eval_batch = config.steps_per_eval_image = config.steps_per_eval_all_images = 10**9
        config.save_only_latest_checkpoint = True  # enough to resume, render or evaluate the run; saves disk
        config.logging.local_writer.enable = False  # this command shows the progress
        config.pipeline.datamanager = dataclasses.replace(
            config.pipeline.datamanager,
            dataparser=copy.deepcopy(self.dataparser),
            num_tasks=spec.num_tasks,
            iterations_per_task=spec.iterations_per_task or 1,  # unused when the tasks are timed
            seconds_per_task=spec.seconds_per_task,
            test_interval=self.test_interval,
            train_num_rays_per_batch=self.rays_per_batch,
        )
        if self.model_size == "cpu":
            config.pipeline.model = cpu_sized(config.pipeline.model)
        config.set_timestamp()
        return config

    def train_missing_runs(self, plan: Plan, methods: Dict[str, ContinualTrainerConfig]) -> None:
        runs = plan.runs()
        missing = [spec for spec in runs if find_finished_run(self.output_dir, spec) is None]
        CONSOLE.print(
            f"[bold]{len(runs) - len(missing)} of {len(runs)} runs already finished in {self.output_dir}; "
            f"training {len(missing)}"
        )
        progress = Progress(
            TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(), console=CONSOLE
        )
        with progress:
            overall = progress.add_task("runs", total=len(missing))
            for spec in missing:
                bar = progress.add_task(spec.key, total=spec.num_tasks)
                self.train_run(self.run_config(spec, methods[spec.method]), progress, bar)
                progress.update(bar, visible=False)
                progress.advance(overall)

    def train_run(self, config: ContinualTrainerConfig, progress: Progress, bar: TaskID) -> None:
        """Train one run as `ns-train` would, with a RunMonitor recording times and probe renders."""
        started = time.perf_counter()
        torch.manual_seed(self.seed)
        writer.EVENT_WRITERS.clear()  # nerfstudio's writers are global: this run must not log into an earlier run's
        config.save_config()
        trainer = config.setup(local_rank=0, world_size=1)
        trainer.setup()
        monitor = RunMonitor(trainer, self.probe_task, progress, bar)
        trainer.train()
        monitor.finish(time.perf_counter() - started)

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


def _is_implicit(config: ContinualTrainerConfig) -> bool:
    """Whether the method's model is the fully implicit NeRF (the paper gives those a longer budget)."""
    return isinstance(config.pipeline.model, ContinualNeRFModelConfig)


class RunMonitor:
    """Callbacks added to one run's Trainer: an iteration clock, progress, and the probe view at every task end."""

    def __init__(self, trainer: ContinualTrainer, probe_task: int, progress: Progress, bar: TaskID) -> None:
        self.trainer, self.progress, self.bar = trainer, progress, bar
        self.pipeline = trainer.pipeline
        self.probe_frame = int(torch.nonzero(self.pipeline.datamanager.test_task_of_frame() == probe_task - 1)[0])
        self.record: Dict[str, Any] = {
            "task_train_seconds": [],
            "wall_seconds": None,
            "renders": [],
            "ground_truth": None,
        }
        self._started = 0.0
        self._seconds = 0.0
        self._first_iteration = True
        before, after = TrainingCallbackLocation.BEFORE_TRAIN_ITERATION, TrainingCallbackLocation.AFTER_TRAIN_ITERATION
        # the clock stops before the pipeline's task end runs, so evaluation and checkpoints do not count as training
        trainer.callbacks = [
            TrainingCallback([before], self._start_clock),
            TrainingCallback([after], self._stop_clock),
            *trainer.callbacks,
            TrainingCallback([after], self._after_iteration),
        ]

    def _start_clock(self, step: int) -> None:
        self._started = time.perf_counter()

    def _stop_clock(self, step: int) -> None:
        if self._first_iteration:  # not counted: the first iteration in a process carries torch's start-up cost
            self._first_iteration = False
            return
        self._seconds += time.perf_counter() - self._started

    def _after_iteration(self, step: int) -> None:
        datamanager = self.pipeline.datamanager
        tasks_done = len(self.pipeline.accuracy.psnr)
        if tasks_done > len(self.record["task_train_seconds"]):
            self.record["task_train_seconds"].append(self._seconds)
            self._seconds = 0.0
            self._save_probe_render(tasks_done)
            self.write()
        task = min(datamanager.current_task + 1, datamanager.num_tasks)
        description = f"{self.trainer.config.experiment_name}: task {task}/{datamanager.num_tasks}"
        self.progress.update(
            self.bar, completed=tasks_done, description=f"{description}, iteration {datamanager.task_iterations}"
        )

    @torch.no_grad()
    def _save_probe_render(self, tasks_done: int) -> None:
        dataset, model = self.pipeline.datamanager.eval_dataset, self.pipeline.model
        camera = dataset.cameras[self.probe_frame : self.probe_frame + 1].to(model.device)
        model.eval()
        rendered = model.get_outputs_for_camera(camera)["rgb"].clamp(0, 1)
        model.train()
        name = f"task_renders/after_task_{tasks_done:02d}.png"
        _save_png(rendered, self.trainer.base_dir / name)
        self.record["renders"].append(name)
        if self.record["ground_truth"] is None:
            self.record["ground_truth"] = "task_renders/ground_truth.png"
            _save_png(
                dataset.get_image_float32(self.probe_frame)[..., :3],
                self.trainer.base_dir / self.record["ground_truth"],
            )

    def write(self) -> None:
        write_text_atomically(self.trainer.base_dir / RUN_RECORD, json.dumps(self.record, indent=1))

    def finish(self, wall_seconds: float) -> None:
        self.record["wall_seconds"] = wall_seconds
        self.write()


def _save_png(image: torch.Tensor, path: Path) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray((image.cpu().numpy() * 255).round().astype(np.uint8)).save(path)


def find_finished_run(report_dir: Path, spec: RunSpec) -> Optional[Path]:
    """The newest folder of `spec` whose accuracy matrix says finished, if any."""
    matrices = sorted((report_dir / RUNS_DIR / spec.key).glob(f"*/*/{ACCURACY_MATRIX_FILENAME}"))
    finished = [path.parent for path in matrices if AccuracyMatrix.read(path).finished]
    return finished[-1] if finished else None


def load_run(report_dir: Path, spec: RunSpec, run_dir: Path, joint: bool) -> report.Run:
    """A finished run as results.json keeps it; paths relative to the report folder."""
    matrix = AccuracyMatrix.read(run_dir / ACCURACY_MATRIX_FILENAME)
    record_path = run_dir / RUN_RECORD
    record = json.loads(record_path.read_text()) if record_path.exists() else {}
    task_seconds = record.get("task_train_seconds", [])
    relative = run_dir.relative_to(report_dir)
    return {
        "key": spec.key,
        "method": spec.method,
        "joint": joint,
        "num_tasks": spec.num_tasks,
        "iterations_per_task": spec.iterations_per_task,
        "seconds_per_task": spec.seconds_per_task,
        "run_dir": str(relative),
        "psnr": matrix.psnr,
        "ssim": matrix.ssim,
        "mean_psnr": matrix.mean_psnr,
        "steps": matrix.steps,
        "task_train_seconds": task_seconds,
        # a run killed between its last evaluation and its record has no complete timing: reported as n/a
        "train_seconds": sum(task_seconds) if len(task_seconds) == spec.num_tasks else None,
        "wall_seconds": record.get("wall_seconds"),
        "renders": [str(relative / name) for name in record.get("renders", [])],
        "ground_truth": str(relative / record["ground_truth"]) if record.get("ground_truth") else None,
    }


def entrypoint() -> None:
    tyro.extras.set_accent_color("bright_yellow")
    config = tyro.cli(ExperimentsConfig, prog=PROG, description=__doc__.splitlines()[0])
    config.main(command=shlex.join([PROG, *sys.argv[1:]]))


if __name__ == "__main__":
    entrypoint()
