"""Training the experiments' runs: each through nerfstudio's Trainer in this process, with its record of training
seconds per task and the probe view rendered after every task; finished runs are found and read back."""

from __future__ import annotations

import copy
import json
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Dict, Literal, Optional

import numpy as np
import torch
from nerfstudio.configs.base_config import InstantiateConfig
from nerfstudio.engine.callbacks import TrainingCallback, TrainingCallbackLocation
from nerfstudio.utils.rich_utils import CONSOLE
from PIL import Image
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TaskID, TextColumn, TimeElapsedColumn

from continual_nerf.atomic_files import write_text_atomically
from continual_nerf.core.accuracy_matrix import ACCURACY_MATRIX_FILENAME, AccuracyMatrix
from continual_nerf.core.continual_trainer import ContinualTrainer, ContinualTrainerConfig
from continual_nerf.experiments import report
from continual_nerf.experiments.plan import Plan, RunSpec
from continual_nerf.recipes import quiet_config, set_up_like_ns_train

RUNS_DIR = "runs"
RUN_RECORD = "experiment_run.json"
"""Per run: training seconds of every task, wall time, and the probe view rendered at every task end."""


@dataclass(frozen=True)
class RunSettings:
    """What every run of one report shares besides its method, task count and budget."""

    dataparser: InstantiateConfig
    """The scene."""
    report_dir: Path
    """The report folder; runs go to its runs/ folder."""
    test_interval: int
    """Every test_interval-th frame of each task is held out for testing."""
    rays_per_batch: int
    """Rays per training batch."""
    small: bool
    """Shrink every model to CPU size."""
    device: Literal["cpu", "cuda"]
    """Device every run trains on."""
    seed: int
    """Seed of the random generators at the start of every run."""
    probe_task: int
    """Task (1-based) whose first test view is rendered after every task."""


def run_config(spec: RunSpec, base: ContinualTrainerConfig, settings: RunSettings) -> ContinualTrainerConfig:
    """The method's registered configuration with the report's scene, budget, size and output folder."""
    config = quiet_config(
        base,
        settings.report_dir / RUNS_DIR,
        device=settings.device,
        small=settings.small,
        dataparser=copy.deepcopy(settings.dataparser),
        num_tasks=spec.num_tasks,
        iterations_per_task=spec.iterations_per_task or 1,  # unused when the tasks are timed
        seconds_per_task=spec.seconds_per_task,
        test_interval=settings.test_interval,
        train_num_rays_per_batch=settings.rays_per_batch,
    )
    config.experiment_name = spec.key
    config.machine.seed = settings.seed
    config.save_only_latest_checkpoint = True  # enough to resume, render or evaluate the run; saves disk
    return config


def train_missing_runs(plan: Plan, methods: Dict[str, ContinualTrainerConfig], settings: RunSettings) -> None:
    """Train every run of `plan` that has no finished folder yet, with a progress bar per run."""
    runs = plan.runs()
    missing = [spec for spec in runs if find_finished_run(settings.report_dir, spec) is None]
    CONSOLE.print(
        f"[bold]{len(runs) - len(missing)} of {len(runs)} runs already finished in {settings.report_dir}; "
        f"training {len(missing)}"
    )
    progress = Progress(
        TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(), console=CONSOLE
    )
    with progress:
        overall = progress.add_task("runs", total=len(missing))
        for spec in missing:
            bar = progress.add_task(spec.key, total=spec.num_tasks)
            train_run(run_config(spec, methods[spec.method], settings), settings.probe_task, progress, bar)
            progress.update(bar, visible=False)
            progress.advance(overall)


def train_run(config: ContinualTrainerConfig, probe_task: int, progress: Progress, bar: TaskID) -> None:
    """Train one run as `ns-train` would, with a RunMonitor recording times and probe renders."""
    started = time.perf_counter()
    config.save_config()
    trainer = set_up_like_ns_train(config)
    monitor = RunMonitor(trainer, probe_task, progress, bar)
    trainer.train()
    monitor.finish(time.perf_counter() - started)


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
        self._seconds_at_task_start = 0.0
        trainer.callbacks.append(
            TrainingCallback([TrainingCallbackLocation.AFTER_TRAIN_ITERATION], self._after_iteration)
        )

    def _after_iteration(self, step: int) -> None:
        pipeline = self.pipeline
        tasks_done = len(pipeline.accuracy.psnr)
        if tasks_done > len(self.record["task_train_seconds"]):
            # the pipeline's clock: training iterations only, not evaluation, checkpoints or task switches
            seconds = pipeline.budget.total_seconds
            self.record["task_train_seconds"].append(seconds - self._seconds_at_task_start)
            self._seconds_at_task_start = seconds
            self._save_probe_render(tasks_done)
            self.write()
        description = f"{self.trainer.config.experiment_name}: task {pipeline.task.current + 1}/{pipeline.known_tasks}"
        self.progress.update(
            self.bar, completed=tasks_done, description=f"{description}, iteration {pipeline.budget.iterations_done}"
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
