"""Memory of a continual run, task by task: what a flat memory in the number of tasks is checked against.

    python -m continual_nerf.bench.memory [--scene room] [--num-tasks 20] [--iterations-per-task 10] [--output memory.json]

trains continual-ngp on the demo scene (all its defaults, the replay oracle included) and prints, after
every task, the peak and current resident memory of the process and the bytes of all live tensors.
Run it in a fresh process: the peak covers everything the process did before.
"""

from __future__ import annotations

import dataclasses
import gc
import json
import resource
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import List, Literal, Optional

import psutil
import torch
import tyro
from nerfstudio.engine.callbacks import TrainingCallback, TrainingCallbackLocation
from nerfstudio.utils.rich_utils import CONSOLE
from torch._subclasses.fake_tensor import FakeTensor

from continual_nerf.bench.demo_runs import on_demo
from continual_nerf.core.continual_trainer import ContinualTrainer, ContinualTrainerConfig
from continual_nerf.dataparsers.continual_demo_dataparser import ContinualDemoDataParserConfig, DemoScene
from continual_nerf.method_configs import CONTINUAL_NGP
from continual_nerf.recipes import set_up_like_ns_train

MIB = 2**20


def peak_resident_bytes() -> int:
    """Highest resident memory of this process so far."""
    status = Path("/proc/self/status")
    if status.exists():  # Linux: ru_maxrss would start from the parent's peak, which execve keeps
        hwm = next(line for line in status.read_text().splitlines() if line.startswith("VmHWM:"))
        return int(hwm.split()[1]) * 1024
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss  # bytes on macOS


def resident_bytes() -> int:
    """Resident memory of this process now."""
    return psutil.Process().memory_info().rss


def live_tensor_bytes() -> int:
    """Bytes of the storages of every tensor Python can reach (each storage counted once), gradients excluded.

    Gradients live from a step's backward to the next step, and only for the networks that step updated
    (nerfacto's proposal networks skip steps): counted, they would make the total depend on the step.
    """
    with warnings.catch_warnings():
        # scanning every object touches deprecated torch aliases and non-leaf tensors' .grad: both only looked at
        warnings.simplefilter("ignore")
        tensors = [obj for obj in gc.get_objects() if isinstance(obj, torch.Tensor) and not isinstance(obj, FakeTensor)]
        gradients = {t.grad.untyped_storage().data_ptr() for t in tensors if t.grad is not None}
    storages = {t.untyped_storage().data_ptr(): t.untyped_storage().nbytes() for t in tensors if not t.is_meta}
    return sum(size for pointer, size in storages.items() if pointer not in gradients)


@dataclass
class TaskMemory:
    """Memory of the process right after a task ended (the next task's pixels and the new oracle in place)."""

    task: int
    """Number of tasks trained so far."""
    peak_resident_bytes: int
    """Highest resident memory of the process up to this point."""
    resident_bytes: int
    """Resident memory now."""
    live_tensor_bytes: int
    """Bytes of all tensors Python can reach now."""

    @classmethod
    def measure(cls, task: int) -> "TaskMemory":
        gc.collect()  # what is unreachable but not yet collected is no memory the run keeps
        return cls(task, peak_resident_bytes(), resident_bytes(), live_tensor_bytes())


class TaskMemoryRecorder:
    """A training callback appending a TaskMemory whenever nerfstudio's loop has just finished a task."""

    def __init__(self, trainer: ContinualTrainer) -> None:
        self.trainer = trainer
        self.records: List[TaskMemory] = []

    def callback(self) -> TrainingCallback:
        return TrainingCallback([TrainingCallbackLocation.AFTER_TRAIN_ITERATION], self.record_if_task_ended)

    def record_if_task_ended(self, step: int) -> None:
        # the pipeline's own callback runs first: it resets the count when it opens a task, and stops the run after the last
        if self.trainer.pipeline.budget.iterations_done == 0 or self.trainer.stop_training:
            self.records.append(TaskMemory.measure(len(self.records) + 1))


def train_recording_memory(config: ContinualTrainerConfig) -> List[TaskMemory]:
    """Run `config` through nerfstudio's Trainer; the memory after each of its tasks."""
    trainer = set_up_like_ns_train(config)
    recorder = TaskMemoryRecorder(trainer)
    trainer.callbacks.append(recorder.callback())  # after the pipeline's task switch
    trainer.train()
    return recorder.records


@dataclass
class MemoryBenchmark:
    """continual-ngp on the demo scene with many equal tasks; memory after each."""

    num_tasks: int = 20
    """Number of tasks; the demo trajectory is cut into this many equal spans."""
    iterations_per_task: int = 10
    """Training iterations per task."""
    scene: DemoScene = "room"
    """Demo scene to train on (long-street: the long capture, 480 frames)."""
    num_frames: Optional[int] = None
    """Frames of the demo trajectory (at least 2 per task: one trains, one tests); None: the scene's own."""
    device: Literal["cpu", "cuda"] = "cpu"
    """Device to train on."""
    data: Path = Path("data/continual-demo")
    """Where the demo scene is generated (and reused from)."""
    output_dir: Path = Path("outputs/bench-memory")
    """Run folder of the training (checkpoints, accuracy matrix)."""
    output: Optional[Path] = None
    """JSON file to write the per-task records to (for the performance benchmark)."""

    def trainer_config(self) -> ContinualTrainerConfig:
        demo = ContinualDemoDataParserConfig(data=self.data, scene=self.scene, num_frames=self.num_frames)
        options = {"num_tasks": self.num_tasks, "iterations_per_task": self.iterations_per_task}
        return on_demo(CONTINUAL_NGP, demo, self.device, self.output_dir, **options)

    def main(self) -> None:
        records = train_recording_memory(self.trainer_config())
        for record in records:
            CONSOLE.print(
                f"after task {record.task:2d}: peak resident {record.peak_resident_bytes / MIB:7.1f} MiB, "
                f"resident {record.resident_bytes / MIB:7.1f} MiB, live tensors {record.live_tensor_bytes / MIB:6.1f} MiB"
            )
        if self.output is not None:
            self.output.write_text(json.dumps([dataclasses.asdict(record) for record in records], indent=1))


def entrypoint() -> None:
    tyro.cli(MemoryBenchmark).main()


if __name__ == "__main__":
    entrypoint()
