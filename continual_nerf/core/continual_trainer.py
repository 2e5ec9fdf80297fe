"""nerfstudio's Trainer, with the iteration count derived from the task budget, one-line errors for bad input,
atomic checkpoints, a resume (`--load-dir`) that continues a killed run where it stopped, and the continual
panel in the viewer."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Dict, Literal, Optional, Type

import torch
from nerfstudio.engine.callbacks import TrainingCallback, TrainingCallbackLocation
from nerfstudio.engine.trainer import Trainer, TrainerConfig
from nerfstudio.utils.decorators import check_main_thread
from nerfstudio.utils.rich_utils import CONSOLE
from nerfstudio.viewer.viewer import Viewer

from continual_nerf.checkpoints import (
    checkpoint_steps,
    find_checkpoint,
    read_checkpoint,
    restore_rng_states,
    rng_states,
    save_checkpoint_file,
)
from continual_nerf.compilation import warm_up
from continual_nerf.core import distributed
from continual_nerf.core.accuracy_matrix import ACCURACY_MATRIX_FILENAME
from continual_nerf.core.continual_pipeline import ContinualPipeline, ContinualPipelineConfig
from continual_nerf.errors import CheckpointError, ContinualConfigError, ContinualNerfError, first_line
from continual_nerf.nerfstudio_compat import launch_processes_here, set_resume_step
from continual_nerf.validated_config import ValidatedConfig
from continual_nerf.viewer.continual_panel import ContinualPanel

UNBOUNDED_ITERATIONS = 10**9
"""Iterations nerfstudio's loop is given when the tasks, not a count, end the run (timed or streamed tasks)."""


@dataclass
class ContinualTrainerConfig(ValidatedConfig, TrainerConfig):
    """TrainerConfig whose max_num_iterations follows from num_tasks x the per-task budget unless it is given."""

    _target: Type = field(default_factory=lambda: ContinualTrainer)
    pipeline: ContinualPipelineConfig = field(default_factory=ContinualPipelineConfig)
    """The continual pipeline: the task split, its datamanager, the model and the replay oracle."""
    max_num_iterations: Optional[int] = None  # type: ignore[assignment]
    """Cap on the run's training iterations; None: the task budget decides (num_tasks x iterations_per_task)."""
    deterministic: bool = False
    """Use torch's deterministic algorithms: a seed gives bit-identical losses on CPU, at up to twice the step time."""

    def validate(self) -> None:
        super().validate()
        if self.max_num_iterations is not None and self.max_num_iterations < 1:
            raise ContinualConfigError(f"--max-num-iterations must be at least 1, got {self.max_num_iterations}")
        if self.start_paused and self.machine.num_devices * self.machine.num_machines > 1:
            # the other processes would wait for rank 0's first step in a collective that times out
            raise ContinualConfigError("--start-paused needs one process: pause from the viewer once training runs")

    def setup(self, **kwargs: Any) -> Any:
        try:
            return super().setup(**kwargs)
        except ContinualNerfError as error:
            raise SystemExit(f"{self.method_name}: error: {error}") from None

    def resume_source(self) -> Optional[Path]:
        """The run folder this run resumes from, if any."""
        if self.load_dir is not None:
            return self.load_dir.parent
        return None if self.load_checkpoint is None else self.load_checkpoint.parent.parent

    def save_config(self) -> None:
        """nerfstudio's config.yml, refused in a folder holding another run's results: they would be overwritten.

        `ns-train` calls this just before it starts its processes: with several, they go through the plugin's worker
        (CPU processes, one-line errors).
        """
        if self.machine.num_devices * self.machine.num_machines > 1:
            launch_processes_here()
        base_dir = self.get_base_dir()
        source = self.resume_source()
        continuing_in_place = source is not None and source.resolve() == base_dir.resolve()
        holds_a_run = (base_dir / ACCURACY_MATRIX_FILENAME).exists() or (
            self.get_checkpoint_dir().is_dir() and checkpoint_steps(self.get_checkpoint_dir())
        )
        if holds_a_run and not continuing_in_place:
            raise SystemExit(
                f"{self.method_name}: error: {base_dir} already holds a run; choose another --timestamp or "
                f"--experiment-name, or continue that run with --load-dir {self.get_checkpoint_dir()}"
            )
        super().save_config()


class ContinualTrainer(Trainer):
    """Runs nerfstudio's training loop unchanged; the pipeline's callbacks switch tasks and stop it."""

    config: ContinualTrainerConfig
    pipeline: ContinualPipeline

    def __init__(self, config: ContinualTrainerConfig, local_rank: int = 0, world_size: int = 1) -> None:
        super().__init__(config, local_rank, world_size)
        self.panel: Optional[ContinualPanel] = None
        """The viewer's continual-learning panel, when the viewer runs."""

    def setup(self, test_mode: Literal["test", "val", "inference"] = "val") -> None:
        self.config.max_num_iterations = self._iterations_to_run()
        if self.config.deterministic:
            # the hash grid's gradients are scatter-adds run in parallel: their summation order varies the last bits
            torch.use_deterministic_algorithms(True, warn_only=True)
        try:
            super().setup(test_mode)
        except ContinualNerfError as error:
            raise SystemExit(f"{self.config.method_name}: error: {error}") from None
        warm_up(self.pipeline.model, self.config.pipeline.datamanager.train_num_rays_per_batch)
        if isinstance(self.viewer_state, Viewer) and not distributed.is_main():
            # nerfstudio starts a viewer in the first process of every machine; rank 0's alone is fed and obeyed
            self.viewer_state.viser_server.stop()
            self.viewer_state = None
        if isinstance(self.viewer_state, Viewer):
            pipeline = self.pipeline
            self.panel = ContinualPanel(
                pipeline.status, pipeline.request_next_task, lambda: pipeline.datamanager.train_dataset
            )
            self.callbacks += self.panel.training_callbacks(self)
        if distributed.is_distributed():  # last: a pause the panel starts at a task's end holds every rank
            location = TrainingCallbackLocation.AFTER_TRAIN_ITERATION
            self.callbacks.append(TrainingCallback([location], distributed.hold_while_paused, args=[self]))

    def _iterations_to_run(self) -> int:
        """The task budget's iterations (a generous cap when tasks are timed or streamed), or --max-num-iterations."""
        budgeted = self.config.pipeline.datamanager.budgeted_iterations()
        cap = self.config.max_num_iterations
        if cap is None:
            return budgeted if budgeted is not None else UNBOUNDED_ITERATIONS
        if budgeted is None or cap < budgeted:
            tasks_take = "" if budgeted is None else f" (its tasks take {budgeted})"
            CONSOLE.print(f"[bold yellow]--max-num-iterations {cap} may end the run before its last task{tasks_take}")
        return cap

    def train(self) -> None:
        accuracy = self.pipeline.accuracy
        main = distributed.is_main()  # rank 0 alone writes results
        if main:
            accuracy.write(self.base_dir)  # the run folder says "not finished" from the start, whenever it is killed
        try:
            super().train()
        except Exception as error:
            if main and not accuracy.finished:
                accuracy.status = "failed"
                accuracy.write(self.base_dir)
            if isinstance(error, ContinualNerfError):  # for instance an image of a task released mid-run
                raise SystemExit(f"{self.config.method_name}: error: {error}") from None
            raise

    def _load_checkpoint(self) -> None:
        """Resume from --load-dir (latest or --load-step) or --load-checkpoint: nerfstudio's states plus the RNGs."""
        if self.config.load_dir is not None:
            path = find_checkpoint(self.config.load_dir, self.config.load_step)
        elif self.config.load_checkpoint is not None:
            path = self.config.load_checkpoint
        else:
            return super()._load_checkpoint()
        state = read_checkpoint(path)
        self._load_states(state, path)
        pipeline = self.pipeline
        accuracy = pipeline.accuracy
        if accuracy.finished:
            raise CheckpointError(f"{path}: its run already trained all {accuracy.num_tasks} tasks")
        if distributed.is_main():  # the other ranks keep their own seeds (--machine.seed + rank): their rays differ
            restore_rng_states(state["rng"])
        set_resume_step(self, state["step"] + 1)
        CONSOLE.print(
            f"Resuming from {path} at step {self._start_step}: task {pipeline.task.current + 1}/"
            f"{pipeline.known_tasks}, {pipeline.budget.iterations_done} iterations into it"
        )

    def _load_states(self, state: Dict[str, Any], path: Path) -> None:
        """Load pipeline (model, oracle, task progress, accuracy matrix), optimizers, schedulers and grad scaler."""
        try:
            self.pipeline.load_pipeline(state["pipeline"], state["step"])
            self.optimizers.load_optimizers(state["optimizers"])
            if self.config.load_scheduler:
                self.optimizers.load_schedulers(state.get("schedulers", {}))
            self.grad_scaler.load_state_dict(state["scalers"])
        except ContinualNerfError as error:
            raise CheckpointError(f"{path}: {error}") from None
        except (RuntimeError, KeyError, ValueError) as error:
            raise CheckpointError(
                f"{path}: does not fit this run ({first_line(error)}); resume with the options it was trained with"
            ) from None

    @check_main_thread
    def save_checkpoint(self, step: int) -> None:
        """nerfstudio's checkpoint (file name and keys) plus the RNG states, renamed into place once complete."""
        path = self.checkpoint_dir / f"step-{step:09d}.ckpt"
        save_checkpoint_file(self.checkpoint_state(step), path)
        if self.config.save_only_latest_checkpoint:
            for older in checkpoint_steps(self.checkpoint_dir).values():
                if older != path:
                    older.unlink()

    def checkpoint_state(self, step: int) -> Dict[str, Any]:
        return {
            "step": step,
            "pipeline": self.pipeline.checkpoint_state_dict(),
            "optimizers": {name: optimizer.state_dict() for name, optimizer in self.optimizers.optimizers.items()},
            "schedulers": {name: scheduler.state_dict() for name, scheduler in self.optimizers.schedulers.items()},
            "scalers": self.grad_scaler.state_dict(),
            "rng": rng_states(),
        }

    def _init_viewer_state(self) -> None:
        # nerfstudio's init_scene shows every training frame with its pixels; only released tasks may be shown
        if isinstance(self.viewer_state, Viewer) and self.panel is not None:
            self.panel.attach(self.viewer_state, self)
        else:
            super()._init_viewer_state()
