"""Data-parallel continual-ngp on nerfstudio's launcher: throughput and final quality with 1 and N processes.

    python -m continual_nerf.bench.distributed [--processes 1 2] [--device cpu] [--num-tasks 3]
        [--iterations-per-task 40] [--rays-per-batch 512]

Every process count trains the same run with `ns-train continual-ngp --machine.num-devices N` (one process per
device, gloo on CPU, NCCL on CUDA, DistributedDataParallel) at the same batch per process and the same number of
steps, so N processes train on N times the rays. Printed side by side: the training seconds (rank 0's task-budget
clock: training iterations only, no set-up, evaluation or checkpoints), rays per second over all processes, the
final mean test PSNR, the open task's pixels each process holds, and the peak resident memory of the largest process.
"""

from __future__ import annotations

import json
import subprocess
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import List, Tuple

import tyro
from nerfstudio.utils.rich_utils import CONSOLE
from rich.table import Table

from continual_nerf.bench.demo_runs import DemoBenchmark
from continual_nerf.checkpoints import checkpoint_steps, read_checkpoint
from continual_nerf.core.accuracy_matrix import ACCURACY_MATRIX_FILENAME, AccuracyMatrix
from continual_nerf.core.task_split import split_into_tasks
from continual_nerf.dataparsers.continual_demo_dataparser import ContinualDemoDataParserConfig
from continual_nerf.recipes import NEVER

PEAK_MEMORY = (
    "import resource, subprocess, sys; code = subprocess.run(sys.argv[1:]).returncode; "
    "print(resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss); sys.exit(code)"
)
"""Runs a command and prints the peak resident memory (KiB) of the largest process it started, launched ones too."""


@dataclass(frozen=True)
class Measured:
    """One run's numbers."""

    processes: int
    training_seconds: float
    rays_per_second: float
    final_mean_psnr: float
    peak_rss_mib: float


@dataclass
class DistributedBenchmark(DemoBenchmark):
    """Trains continual-ngp on the demo with each process count in turn, through ns-train."""

    processes: Tuple[int, ...] = (1, 2)
    """Process counts (--machine.num-devices) to compare."""
    num_tasks: int = 3
    """Tasks of the demo trajectory."""
    iterations_per_task: int = 40
    """Training iterations per task, the same for every process count."""
    rays_per_batch: int = 512
    """Rays per batch of each process: N processes train on N times as many per step."""

    def command(self, processes: int, output_dir: Path) -> List[str]:
        options = {
            "machine.device-type": self.device,
            "machine.num-devices": processes,
            "vis": "tensorboard",
            "output-dir": output_dir,
            "timestamp": f"{processes}-processes",
            "steps-per-eval-batch": NEVER,
            "steps-per-eval-image": NEVER,
            "steps-per-eval-all-images": NEVER,
            "logging.local-writer.enable": False,
            "pipeline.model.compile": False,  # its set-up cost would be paid by every process
            "pipeline.datamanager.num-tasks": self.num_tasks,
            "pipeline.datamanager.iterations-per-task": self.iterations_per_task,
            "pipeline.datamanager.train-num-rays-per-batch": self.rays_per_batch,
        }
        flags = [item for name, value in options.items() for item in (f"--{name}", str(value))]
        ns_train = str(Path(sys.executable).with_name("ns-train"))
        return [ns_train, "continual-ngp", *flags, "continual-demo", "--data", str(self.data)]

    def run(self, processes: int, output_dir: Path) -> Measured:
        CONSOLE.print(f"[bold]Training with {processes} process(es)...")
        command = [sys.executable, "-c", PEAK_MEMORY, *self.command(processes, output_dir)]
        done = subprocess.run(command, check=False, capture_output=True, text=True)
        if done.returncode != 0:
            raise SystemExit(f"{processes} processes: {done.stderr.strip().splitlines()[-1]}")
        run_dir = next(output_dir.glob(f"*/continual-ngp/{processes}-processes"))
        accuracy = AccuracyMatrix.read(run_dir / ACCURACY_MATRIX_FILENAME)
        final = read_checkpoint(max(checkpoint_steps(run_dir / "nerfstudio_models").items())[1])
        seconds = float(final["pipeline"]["_extra_state"]["budget"]["total_seconds"])
        steps = self.num_tasks * self.iterations_per_task
        return Measured(
            processes=processes,
            training_seconds=seconds,
            rays_per_second=processes * self.rays_per_batch * steps / seconds,
            final_mean_psnr=accuracy.mean_psnr[-1],
            peak_rss_mib=int(done.stdout.strip().splitlines()[-1]) / 1024,
        )

    def open_task_pixels_mib(self) -> float:
        """The largest task's training pixels (float32 RGB): what every process holds while the task is open."""
        outputs = ContinualDemoDataParserConfig(data=self.data).setup().get_dataparser_outputs("train")
        pixels = (outputs.cameras.width * outputs.cameras.height).view(-1)
        split = split_into_tasks(len(pixels), self.num_tasks, test_interval=8)
        return max(int(pixels[frames].sum()) for frames in split.train_frames) * 3 * 4 / 2**20

    def report(self, results: List[Measured]) -> None:
        steps = self.num_tasks * self.iterations_per_task
        table = Table(
            title=f"continual-ngp on the demo, {self.device}: {self.num_tasks} tasks x {self.iterations_per_task} "
            f"steps, {self.rays_per_batch} rays per process and step"
        )
        columns = ("processes", "rays per step", "training s", "rays/s", "final mean PSNR (dB)", "peak RSS (MiB)")
        for column in columns:
            table.add_column(column, justify="right")
        for result in results:
            table.add_row(
                str(result.processes),
                str(result.processes * self.rays_per_batch),
                f"{result.training_seconds:.1f}",
                f"{result.rays_per_second:,.0f}",
                f"{result.final_mean_psnr:.2f}",
                f"{result.peak_rss_mib:.0f}",
            )
        CONSOLE.print(table)
        CONSOLE.print(
            f"{steps} steps per run. Every process holds the open task's pixels (replicated): "
            f"{self.open_task_pixels_mib():.2f} MiB here. Results: "
            + json.dumps([result.__dict__ for result in results])
        )

    def main(self) -> None:
        with tempfile.TemporaryDirectory() as scratch:
            self.report([self.run(processes, Path(scratch) / str(processes)) for processes in self.processes])


def entrypoint() -> None:
    tyro.cli(DistributedBenchmark).main()


if __name__ == "__main__":
    entrypoint()
