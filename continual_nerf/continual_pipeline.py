"""The continual pipeline: switches tasks inside nerfstudio's Trainer loop and keeps the accuracy matrix."""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Dict, List, Literal, Mapping, Optional, Type

from nerfstudio.engine.callbacks import TrainingCallback, TrainingCallbackAttributes, TrainingCallbackLocation
from nerfstudio.engine.trainer import Trainer
from nerfstudio.pipelines.base_pipeline import VanillaPipeline, VanillaPipelineConfig
from nerfstudio.utils import writer
from nerfstudio.utils.rich_utils import CONSOLE
from torch.cuda.amp.grad_scaler import GradScaler

from continual_nerf.accuracy_matrix import AccuracyMatrix
from continual_nerf.continual_datamanager import ContinualDataManager, ContinualDataManagerConfig
from continual_nerf.continual_model import ContinualNGPModelConfig
from continual_nerf.continual_viewer import ContinualPanel
from continual_nerf.evaluation import evaluate_frames

ORACLE_PREFIX = "datamanager.replay_oracle.model."


@dataclass
class ContinualPipelineConfig(VanillaPipelineConfig):
    """Trains task after task; evaluates every task seen so far at the end of each."""

    _target: Type = field(default_factory=lambda: ContinualPipeline)
    datamanager: ContinualDataManagerConfig = field(default_factory=ContinualDataManagerConfig)
    """Splits the trajectory into tasks and holds the replay oracle."""
    model: ContinualNGPModelConfig = field(default_factory=ContinualNGPModelConfig)
    """The hash-grid model trained with Eq. 4."""


class ContinualPipeline(VanillaPipeline):
    """VanillaPipeline plus the task switch, run as training callbacks so `ns-train` drives everything."""

    config: ContinualPipelineConfig
    datamanager: ContinualDataManager

    def __init__(
        self,
        config: ContinualPipelineConfig,
        device: str,
        test_mode: Literal["test", "val", "inference"] = "val",
        world_size: int = 1,
        local_rank: int = 0,
        grad_scaler: Optional[GradScaler] = None,
    ):
        super().__init__(config, device, test_mode, world_size, local_rank, grad_scaler)
        self.accuracy = AccuracyMatrix(num_tasks=self.datamanager.num_tasks)
        self._step_started = 0.0
        self.continual_panel = ContinualPanel(self)
        """The viewer's continual-learning panel and per-task camera frustums."""

    def get_training_callbacks(self, training_callback_attributes: TrainingCallbackAttributes) -> List[TrainingCallback]:
        trainer = training_callback_attributes.trainer
        assert trainer is not None
        return super().get_training_callbacks(training_callback_attributes) + [
            TrainingCallback([TrainingCallbackLocation.BEFORE_TRAIN_ITERATION], self._start_clock),
            TrainingCallback(
                [TrainingCallbackLocation.AFTER_TRAIN_ITERATION], self._end_task_if_budget_spent, args=[trainer]
            ),
            TrainingCallback([TrainingCallbackLocation.AFTER_TRAIN], self._print_summary),
        ] + self.continual_panel.training_callbacks(trainer)

    def _start_clock(self, step: int) -> None:
        self._step_started = time.perf_counter()

    def _end_task_if_budget_spent(self, trainer: Trainer, step: int) -> None:
        datamanager = self.datamanager
        datamanager.task_seconds += time.perf_counter() - self._step_started
        if not datamanager.budget_spent():
            return
        self.evaluate_seen_tasks(step, trainer.base_dir)
        if datamanager.is_last_task:
            trainer.stop_training = True
        else:
            self.consolidate_task()
            datamanager.open_next_task(self.model)
            CONSOLE.print(f"[bold]Task {datamanager.current_task + 1}/{datamanager.num_tasks} released at step {step + 1}")
        trainer.save_checkpoint(step)

    def consolidate_task(self) -> None:
        """Runs at the end of every task but the last, while its pixels are still readable (EWC's Fisher)."""

    def evaluate_seen_tasks(self, step: int, output_dir: Path) -> None:
        """Append row `current task` of the accuracy matrix, log it and write it to `output_dir`."""
        datamanager = self.datamanager
        frames = datamanager.seen_test_frames()
        self.eval()
        psnr, ssim = evaluate_frames(self.model, datamanager.eval_dataset, frames.tolist())
        self.train()
        tasks = datamanager.test_task_of_frame()[frames]
        seen = range(int(tasks.max()) + 1)  # the tasks released so far; every task when training jointly
        row_psnr = [float(psnr[tasks == j].mean()) for j in seen]
        row_ssim = [float(ssim[tasks == j].mean()) for j in seen]
        self.accuracy.num_tasks = datamanager.num_tasks  # grows while a capture folder is still being written
        self.accuracy.add_row(row_psnr, row_ssim, float(psnr.mean()), step)
        path = self.accuracy.write(output_dir)
        writer.put_dict(
            name="Continual PSNR per task", scalar_dict={f"task_{j + 1}": v for j, v in enumerate(row_psnr)}, step=step
        )
        writer.put_scalar(name="Continual mean PSNR", scalar=float(psnr.mean()), step=step)
        CONSOLE.print(
            f"[bold]Task {datamanager.current_task + 1}/{datamanager.num_tasks} done[/bold] at step {step + 1}: "
            f"test PSNR per task {_format_row(row_psnr)}, mean {float(psnr.mean()):.2f} dB ({path})"
        )

    def _print_summary(self, step: int) -> None:
        if not self.accuracy.psnr:
            CONSOLE.print("[bold yellow]No task finished: no accuracy matrix to report.")
            return
        state = "final" if self.accuracy.finished else f"after task {len(self.accuracy.psnr)} (run stopped early)"
        CONSOLE.print(f"[bold green]Continual results, {state}:")
        CONSOLE.print(f"Per-task test PSNR: {_format_row(self.accuracy.psnr[-1])}")
        CONSOLE.print(f"Mean test PSNR over all test frames: {self.accuracy.mean_psnr[-1]:.2f} dB")

    def load_state_dict(self, state_dict: Mapping[str, Any], strict: Optional[bool] = None):
        if any(key.startswith(ORACLE_PREFIX) for key in state_dict) and not self.datamanager.replay_oracle.ready:
            self.datamanager.replay_oracle.update(self.model)  # builds the copy the saved weights go into
        return super().load_state_dict(state_dict, strict)

    def get_extra_state(self) -> Dict[str, Any]:
        # in the checkpoint, so a resumed run's accuracy_matrix.json keeps the rows measured before the crash
        return {"accuracy": asdict(self.accuracy)}

    def set_extra_state(self, state: Dict[str, Any]) -> None:
        self.accuracy = AccuracyMatrix(**state["accuracy"])


def _format_row(values: List[float]) -> str:
    return "[" + ", ".join(f"{value:.2f}" for value in values) + "] dB"

