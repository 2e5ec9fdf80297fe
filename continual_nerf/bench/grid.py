"""The grid runner the quality and real-capture benchmarks share: recipes (ns-train arguments) x scenes x settings on
the demo scenes, each run trained through nerfstudio's Trainer once and read back afterwards.

A recipe is what a user would type after `ns-train`: a registered continual method, its options, and optionally
`continual-demo` with the demo's options (`continual-ngp --pipeline.model.use-color-transform True continual-demo
--exposure-strength 0.3`). The grid sets what it varies itself: the scene, the number of tasks and the budget per
task, the rays per batch and the device. A run's folder keeps `summary.json` with the arguments, rays per batch and
device it was trained with; a later benchmark reads a finished run back when it asks for the same and refuses the
folder otherwise.
"""

from __future__ import annotations

import dataclasses
import json
import re
import shlex
import subprocess
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Dict, List, Optional, Sequence, Tuple

from nerfstudio.engine.callbacks import TrainingCallback, TrainingCallbackLocation
from nerfstudio.utils.rich_utils import CONSOLE

from continual_nerf.atomic_files import write_text_atomically
from continual_nerf.bench.demo_runs import DemoBenchmark, recipe_config
from continual_nerf.bench.memory import MIB, peak_resident_bytes
from continual_nerf.bench.run_pool import run_pool
from continual_nerf.core.accuracy_matrix import ACCURACY_MATRIX_FILENAME, AccuracyMatrix
from continual_nerf.core.continual_trainer import ContinualTrainer, ContinualTrainerConfig
from continual_nerf.dataparsers.continual_demo_dataparser import ContinualDemoDataParserConfig
from continual_nerf.recipes import quiet_config, set_up_like_ns_train

DEMO = "continual-demo"
"""The dataparser subcommand a recipe may end with, followed by the demo's options."""
SUMMARY_FILENAME = "summary.json"
"""What a finished run's folder keeps of it for the tables."""


@dataclass(frozen=True)
class Setting:
    """Tasks and the per-task budget, written `5x240` (iterations) or `5x20s` (training seconds)."""

    num_tasks: int
    iterations: Optional[int]
    seconds: Optional[float]

    @classmethod
    def parse(cls, text: str) -> "Setting":
        match = re.fullmatch(r"(\d+)x(\d+(?:\.\d*)?)(s?)", text.strip().lower())
        if match is None or int(match[1]) < 1:
            raise SystemExit(f"--settings {text!r}: expected TASKSxITERATIONS (5x240) or TASKSxSECONDSs (5x20s)")
        if match[3]:
            return cls(int(match[1]), None, float(match[2]))
        return cls(int(match[1]), int(float(match[2])), None)

    def __str__(self) -> str:
        budget = f"{self.seconds:g} s" if self.seconds is not None else f"{self.iterations} iterations"
        return f"{self.num_tasks} {'task' if self.num_tasks == 1 else 'tasks'} x {budget}"

    @property
    def key(self) -> str:
        return (
            f"{self.num_tasks}x{self.seconds:g}s" if self.seconds is not None else f"{self.num_tasks}x{self.iterations}"
        )


Prepare = Callable[[ContinualTrainer], None]
"""What a recipe does to its set-up trainer before training (functions of a module: runs train in processes of their
own)."""
Measure = Callable[[ContinualTrainer], Dict[str, float]]
"""What a recipe measures of its trained run beyond the accuracy matrix."""


@dataclass(frozen=True)
class Recipe:
    """A named configuration: ns-train arguments, and what training and measuring it needs beyond nerfstudio's."""

    name: str
    """The name its table rows give it."""
    arguments: Tuple[str, ...]
    """METHOD [OPTIONS] [continual-demo OPTIONS], as after `ns-train`."""
    prepare: Optional[Prepare] = None
    """Changes the set-up trainer before it trains, where nerfstudio's options cannot say it."""
    measure: Optional[Measure] = None
    """Numbers of the trained run kept beside its summary."""

    @classmethod
    def of(
        cls, name: str, command: str, prepare: Optional[Prepare] = None, measure: Optional[Measure] = None
    ) -> "Recipe":
        return cls(name, tuple(shlex.split(command)), prepare, measure)


def parse_recipe(text: str) -> Recipe:
    """`NAME=METHOD OPTIONS` (a benchmark's --variants): a recipe of the user's own, checked by parsing it."""
    name, equals, command = text.partition("=")
    if not equals or not name.strip() or not command.strip():
        raise SystemExit(
            f"--variants {text!r}: expected NAME=METHOD [OPTIONS], e.g. 'lr=continual-ngp --pipeline.lr-decay-per-task 0.3'"
        )
    recipe = Recipe.of(name.strip(), command)
    recipe_config(recipe.arguments, option=f"--variants {recipe.name}")
    return recipe


def split_at_demo(words: Sequence[str]) -> Tuple[List[str], List[str]]:
    """The method's options and the demo's (after the word continual-demo) of ns-train arguments."""
    if DEMO in words:
        at = list(words).index(DEMO)
        return list(words[:at]), list(words[at + 1 :])
    return list(words), []


def with_options(arguments: Sequence[str], options: Sequence[str]) -> List[str]:
    """`arguments` with `options` (every run's ns-train options, each possibly with continual-demo ones) put in: the
    method's options before the dataparser subcommand, the demo's after it."""
    head, demo = split_at_demo(arguments)
    for option in options:
        extra_head, extra_demo = split_at_demo(shlex.split(option))
        head, demo = head + extra_head, demo + extra_demo
    return head + ([DEMO, *demo] if demo or DEMO in arguments else [])


def folder_name(recipe: str) -> str:
    """The folder of a recipe's runs: its name without spaces or path separators."""
    return re.sub(r"[^\w.^%()-]", "", recipe.replace(",", "_").replace("|", "_"))


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
    final_row: List[Optional[float]]
    """Final test PSNR per task (None: not available, an earlier session's test images were gone)."""
    after_own_task: Optional[float]
    """Mean over tasks of each task's test PSNR right after its own training (the accuracy matrix's diagonal); None
    for a joint run, whose tasks all train from the start."""
    seconds_per_task: List[float] = field(default_factory=list)
    """Training seconds of each task (the pipeline's clock: training iterations only)."""
    peak_mib_per_task: List[float] = field(default_factory=list)
    """Peak resident memory of the run's process by the end of each task, MiB."""
    extras: Dict[str, float] = field(default_factory=dict)
    """What the recipe measured beyond the accuracy matrix (pose errors, ...)."""
    commit: str = "unknown"
    """The commit of the code the run trained with."""
    final_depth_abs_rel: Optional[float] = None
    """Mean absolute relative depth error over all test frames with depth after the last task; None without depth."""
    final_depth_rmse: Optional[float] = None
    """Mean depth RMSE (metres) over all test frames with depth after the last task; None without depth."""
    depth_growth: Optional[List[Optional[float]]] = None
    """Per task, how far its depth error (abs rel) rose from right after its own training to the end: final / own - 1
    (0.2: 20 % worse; the geometry it forgot). None without depth, or for a joint run."""

    @classmethod
    def of(
        cls,
        matrix: AccuracyMatrix,
        train_seconds: float,
        tasks: Optional["TaskRecord"] = None,
        extras: Optional[Dict[str, float]] = None,
        commit: str = "unknown",
    ) -> "RunSummary":
        final = matrix.psnr[-1]
        measured = {j: value for j, value in enumerate(final) if value is not None}
        best = {j: max(v for v in column(matrix, j)) for j in measured}
        ssim = [value for value in matrix.ssim[-1] if value is not None]
        return cls(
            final_mean_psnr=matrix.mean_psnr[-1],
            spread=max(measured.values()) - min(measured.values()),
            largest_drop=max(best[j] - value for j, value in measured.items()),
            mean_ssim=sum(ssim) / len(ssim),
            train_seconds=train_seconds,
            iterations=matrix.steps[-1] + 1,
            final_row=final,
            after_own_task=after_own_task(matrix),
            seconds_per_task=list(tasks.seconds) if tasks is not None else [],
            peak_mib_per_task=list(tasks.peak_mib) if tasks is not None else [],
            extras=dict(extras or {}),
            commit=commit,
            final_depth_abs_rel=matrix.mean_depth_abs_rel[-1] if matrix.mean_depth_abs_rel else None,
            final_depth_rmse=matrix.mean_depth_rmse[-1] if matrix.mean_depth_rmse else None,
            depth_growth=depth_growth(matrix),
        )


def column(matrix: AccuracyMatrix, task: int) -> List[float]:
    """Task `task`'s PSNR in every row that measured it."""
    return [value for row in matrix.psnr if len(row) > task for value in [row[task]] if value is not None]


def after_own_task(matrix: AccuracyMatrix) -> Optional[float]:
    """The mean of the accuracy matrix's diagonal; None when its first row already measures every task (joint)."""
    if len(matrix.psnr[0]) > 1:
        return None
    diagonal = [value for row in matrix.psnr for value in [row[-1]] if value is not None]
    return sum(diagonal) / len(diagonal)


def depth_growth(matrix: AccuracyMatrix) -> Optional[List[Optional[float]]]:
    """Per task its final depth error over the one right after its own training, minus 1 (None where either is
    missing); None without depth rows, or when the first row already measures every task (joint)."""
    rows = matrix.depth_abs_rel
    if not rows or len(rows[0]) > 1:
        return None
    own = [row[-1] for row in rows]
    return [None if not first or last is None else last / first - 1 for first, last in zip(own, rows[-1])]


def decibels(value: Optional[float]) -> str:
    """A table cell of a PSNR that a run may not have."""
    return "n/a" if value is None else f"{value:.2f}"


@dataclass(frozen=True)
class Run:
    """One cell of a grid: a recipe on a scene at a setting, with the arguments it trains with."""

    scene: str
    setting: Setting
    recipe: Recipe
    arguments: Tuple[str, ...]
    folder: Path

    @property
    def summary_path(self) -> Path:
        return self.folder / SUMMARY_FILENAME


def source_commit() -> str:
    """The commit the benchmark's code is at ("unknown" outside a git checkout), written beside every run."""
    try:
        found = subprocess.run(
            ["git", "describe", "--always", "--dirty"],
            cwd=Path(__file__).parent,
            capture_output=True,
            text=True,
            check=True,
        )
    except (OSError, subprocess.CalledProcessError):
        return "unknown"
    return found.stdout.strip()


@dataclass
class Grid(DemoBenchmark):
    """Options every grid benchmark has: every run's ns-train options, where runs go and how many train at once."""

    options: Tuple[str, ...] = ()
    """ns-train options for every run, as after `ns-train METHOD` (e.g. --machine.seed 1
    --optimizers.camera-opt.optimizer.lr 3e-4); continual-demo options after the word continual-demo."""
    jobs: int = 1
    """Runs trained at once, each in a process of its own with cores / jobs threads (unless OMP_NUM_THREADS is set)."""
    output_dir: Path = Path("outputs/bench")
    """Runs, results.json and results.md; finished runs of the same arguments found here are not trained again."""

    def runs(self, scene: str, setting: Setting, recipes: Sequence[Recipe]) -> List[Run]:
        """The grid's cells of `recipes` on `scene` at `setting`."""
        return [
            Run(
                scene,
                setting,
                recipe,
                tuple(with_options(recipe.arguments, self.options)),
                self.output_dir / "runs" / scene / setting.key / folder_name(recipe.name),
            )
            for recipe in recipes
        ]

    def config(self, run: Run) -> ContinualTrainerConfig:
        """The run's ns-train config on its demo scene, with the setting's tasks and budget."""
        # the benchmark's rays per batch, unless the recipe sets its own
        config = recipe_config(run.arguments, f"recipe {run.recipe.name!r}", rays_per_batch=self.rays_per_batch)
        demo = config.pipeline.datamanager.dataparser
        if not isinstance(demo, ContinualDemoDataParserConfig):
            raise SystemExit(f"recipe {run.recipe.name!r}: the benchmark trains on {DEMO}, not another dataparser")
        # the demo's exposure changes jump at each task boundary
        demo = dataclasses.replace(demo, data=self.data, scene=run.scene, exposure_segments=run.setting.num_tasks)  # type: ignore[arg-type]
        config = quiet_config(
            config,
            run.folder,
            device=self.device,
            dataparser=demo,
            num_tasks=run.setting.num_tasks,
            iterations_per_task=run.setting.iterations or 1,  # unused when the tasks are timed
            seconds_per_task=run.setting.seconds,
        )
        config.save_only_latest_checkpoint = True
        return config

    def summaries(self, runs: Sequence[Run]) -> List[RunSummary]:
        """Every run's summary: read back where it finished before, trained otherwise, each in a fresh process of its
        own (`--jobs` at once), so that its memory is its own."""
        configs = [self.config(run) for run in runs]  # every recipe is checked before anything trains
        expected = [trained_with(config) for config in configs]
        pending = [(run, config) for run, config, e in zip(runs, configs, expected) if finished(run, e) is None]
        if pending:
            with run_pool(self.jobs) as pool:
                list(pool.map(train_run, *zip(*pending)))
        return [read_summary(run, e) for run, e in zip(runs, expected)]


OLDER_RUNS: Dict[str, Any] = {"rays_per_batch": 1024, "device": "cpu"}
"""What a run whose file predates recording it was trained with: every benchmark's defaults then."""


def trained_with(config: ContinualTrainerConfig) -> Dict[str, Any]:
    """What a run of `config` is trained with that its arguments do not say: the benchmark's rays per batch (or the
    recipe's own) and device."""
    return {
        "rays_per_batch": config.pipeline.datamanager.train_num_rays_per_batch,
        "device": config.machine.device_type,
    }


def recorded_training(saved: Dict[str, Any]) -> Dict[str, Any]:
    """The rays per batch and device a run's file records, OLDER_RUNS' where the file predates them."""
    return {key: saved.get(key, older) for key, older in OLDER_RUNS.items()}


def refuse_other_training(path: Path, trained: Sequence[Dict[str, Any]], expected: Sequence[Dict[str, Any]]) -> None:
    """One line naming `path` if a finished run (one record per session) was trained otherwise than `expected`."""
    if list(trained) != list(expected):
        raise SystemExit(
            f"{path}: trained with {described(trained)}, not {described(expected)}; choose another --output-dir"
        )


def described(records: Sequence[Dict[str, Any]]) -> str:
    return "; ".join(f"{record['rays_per_batch']} rays per batch on {record['device']}" for record in records)


def finished(run: Run, expected: Dict[str, Any]) -> Optional[RunSummary]:
    """The run's summary if it finished with the same arguments and `expected` training; a folder trained otherwise is
    refused."""
    if not run.summary_path.exists():
        return None
    return read_summary(run, expected)


def read_summary(run: Run, expected: Dict[str, Any]) -> RunSummary:
    saved = json.loads(run.summary_path.read_text())
    if tuple(saved.get("arguments", ())) != run.arguments:
        raise SystemExit(
            f"{run.summary_path}: trained as `{shlex.join(saved.get('arguments', []))}`, not "
            f"`{shlex.join(run.arguments)}`; choose another --output-dir"
        )
    refuse_other_training(run.summary_path, [recorded_training(saved)], [expected])
    return RunSummary(**saved["summary"])


class TaskRecord:
    """Each task's training seconds and the process's peak memory by its end, recorded as the run trains."""

    def __init__(self, trainer: ContinualTrainer) -> None:
        self.pipeline = trainer.pipeline
        self.seconds: List[float] = []
        self.peak_mib: List[float] = []
        self._seconds_before = 0.0
        trainer.callbacks.append(TrainingCallback([TrainingCallbackLocation.AFTER_TRAIN_ITERATION], self.after_step))

    def after_step(self, step: int) -> None:
        """After the pipeline's own callbacks: a task that ended at this step has its row in the accuracy matrix."""
        if len(self.pipeline.accuracy.psnr) > len(self.seconds):
            total = self.pipeline.budget.total_seconds
            self.seconds.append(total - self._seconds_before)
            self._seconds_before = total
            self.peak_mib.append(peak_resident_bytes() / MIB)


def train_run(run: Run, config: ContinualTrainerConfig) -> None:
    """Train one run in this process, as ns-train does, and write its summary."""
    commit = source_commit()  # the code this process imports now, whatever is checked out by the time it finishes
    CONSOLE.print(f"[bold]{run.scene}, {run.setting}: training {run.recipe.name}")
    config.save_config()
    trainer = set_up_like_ns_train(config)
    tasks = TaskRecord(trainer)
    if run.recipe.prepare is not None:
        run.recipe.prepare(trainer)
    trainer.train()
    matrix = AccuracyMatrix.read(config.get_base_dir() / ACCURACY_MATRIX_FILENAME)
    extras = run.recipe.measure(trainer) if run.recipe.measure is not None else {}
    summary = RunSummary.of(matrix, trainer.pipeline.budget.total_seconds, tasks, extras, commit)
    saved = {
        "arguments": list(run.arguments),
        **trained_with(config),
        "summary": dataclasses.asdict(summary),
    }
    write_text_atomically(run.summary_path, json.dumps(saved, indent=1))
