"""One command, one run, one device: throughput, replay overhead, memory over tasks and PSNR against time.

    python -m continual_nerf.bench.performance [--device cpu] [--output-dir outputs/bench]

1. training throughput of continual-ngp with and without replay (continual-ngp-incre) and
   nerfstudio's nerfacto at the same batch size, timed in turns in this process (continual_nerf.bench.throughput);
2. peak resident memory after 2 and after 20 tasks of the same length, in a fresh process
   (continual_nerf.bench.memory);
3. test PSNR over all test frames of the demo scene against training wall-clock time, per method, as a
   PNG; with --lever-reference (default) also continual-ngp with the oracle at half the samples and with every
   speed lever off, whose final mean PSNR the defaults must stay within 0.2 dB of.
"""

from __future__ import annotations

import copy
import dataclasses
import json
import subprocess
import sys
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, List, Literal

import matplotlib
import tyro
from nerfstudio.engine.callbacks import TrainingCallback, TrainingCallbackLocation
from nerfstudio.utils.rich_utils import CONSOLE
from rich.table import Table

from continual_nerf.bench.demo_runs import nerfacto_on_demo, on_demo
from continual_nerf.bench.memory import MIB, TaskMemory
from continual_nerf.bench.throughput import ThroughputBenchmark
from continual_nerf.core.continual_trainer import ContinualTrainerConfig
from continual_nerf.core.evaluation import evaluate_frames
from continual_nerf.dataparsers.continual_demo_dataparser import ContinualDemoDataParserConfig
from continual_nerf.method_configs import CONTINUAL_NGP, CONTINUAL_NGP_INCRE
from continual_nerf.recipes import set_up_like_ns_train

matplotlib.use("Agg")  # the PNG only; no display needed
import matplotlib.pyplot as plt

LEVERS_OFF = "continual-ngp, speed levers off"
HALF_ORACLE = "continual-ngp, oracle at half the samples"


def with_model_options(config: ContinualTrainerConfig, experiment_name: str, **model: object) -> ContinualTrainerConfig:
    """`config` with some model options changed, in its own run folder next to continual-ngp's."""
    config = copy.deepcopy(config)
    config.experiment_name = experiment_name
    config.pipeline.model = dataclasses.replace(config.pipeline.model, **model)
    return config


def lever_references(config: ContinualTrainerConfig) -> Dict[str, ContinualTrainerConfig]:
    """continual-ngp with the oracle rendering at half the model's samples, and with every speed lever off (eager,
    nerfstudio's position gradients): the PSNR cost of the cheaper oracle, and of compilation and detaching."""
    return {
        HALF_ORACLE: with_model_options(config, "half-oracle", replay_sample_fraction=0.5),
        LEVERS_OFF: with_model_options(
            config, "speed-levers-off", compile=False, detach_sample_positions=False, replay_sample_fraction=1.0
        ),
    }


@dataclass
class PSNRCurve:
    """Test PSNR over all test frames against training seconds (evaluation, checkpoints and task switches excluded)."""

    seconds: List[float] = field(default_factory=list)
    """Training seconds at each evaluation."""
    psnr: List[float] = field(default_factory=list)
    """Mean PSNR (dB) over all test frames at each evaluation."""


def train_with_psnr_curve(config: ContinualTrainerConfig, eval_every: int) -> PSNRCurve:
    """Train `config` with nerfstudio's loop, evaluating every test frame every `eval_every` steps and at the end."""
    trainer = set_up_like_ns_train(config)
    curve = PSNRCurve()

    def evaluate(step: int) -> None:
        if (step + 1) % eval_every and not trainer.stop_training:
            return
        pipeline = trainer.pipeline
        pipeline.eval()
        test_frames = pipeline.datamanager.eval_dataset
        psnr, _ = evaluate_frames(pipeline.model, test_frames, list(range(len(test_frames))))
        pipeline.train()
        curve.seconds.append(pipeline.budget.total_seconds)  # the pipeline's clock counts training iterations only
        curve.psnr.append(float(psnr.mean()))

    trainer.callbacks.append(TrainingCallback([TrainingCallbackLocation.AFTER_TRAIN_ITERATION], evaluate))
    trainer.train()
    return curve


@dataclass
class PerformanceBenchmark:
    """Throughput, replay overhead, memory over tasks and PSNR against time, in one run on one device."""

    device: Literal["cpu", "cuda"] = "cpu"
    """Device every measurement runs on."""
    rays_per_batch: int = 1024
    """Rays per training batch of every method (the paper's 1024)."""
    steps: int = 20
    """Timed training steps per configuration for the throughput (after the warm-up)."""
    memory_tasks: int = 20
    """Tasks of the memory run; its peak memory after task 2 and after this task are compared."""
    memory_iterations_per_task: int = 10
    """Training iterations per task of the memory run."""
    curve_tasks: int = 5
    """Tasks of the PSNR-against-time runs (the README's demo: 5 tasks of 60 iterations)."""
    curve_iterations_per_task: int = 60
    """Training iterations per task of the PSNR-against-time runs."""
    curve_eval_every: int = 60
    """Steps between two evaluations of every test frame on the PSNR curves."""
    lever_reference: bool = True
    """Also train continual-ngp with the oracle at half the samples, and with every speed lever off: their PSNR cost."""
    data: Path = Path("data/continual-demo")
    """Where the demo scene is generated (and reused from)."""
    output_dir: Path = Path("outputs/bench")
    """Folder the PSNR-against-time PNG (and the memory run's records) are written to."""

    def throughput(self, scratch: Path) -> None:
        benchmark = ThroughputBenchmark(
            device=self.device, steps=self.steps, rays_per_batch=self.rays_per_batch, data=self.data
        )
        benchmark.measure(scratch).report(self.device, benchmark.num_tasks)

    def memory(self) -> None:
        """Run the memory benchmark in a fresh process: the peak must not include this process's other runs."""
        records_path = self.output_dir / "memory.json"
        with tempfile.TemporaryDirectory() as scratch:
            command = [
                sys.executable, "-m", "continual_nerf.bench.memory",
                "--num-tasks", str(self.memory_tasks),
                "--iterations-per-task", str(self.memory_iterations_per_task),
                "--device", self.device, "--data", str(self.data),
                "--output-dir", scratch, "--output", str(records_path),
            ]  # fmt: skip
            run = subprocess.run(command, capture_output=True, text=True, check=False)
        if run.returncode != 0:
            raise SystemExit(f"the memory run failed:\n{run.stderr[-3000:]}")
        records = [TaskMemory(**record) for record in json.loads(records_path.read_text())]
        after_2, after_last = records[1], records[-1]
        CONSOLE.print(
            f"Peak resident memory after 2 tasks {after_2.peak_resident_bytes / MIB:.0f} MiB, after {after_last.task} "
            f"tasks {after_last.peak_resident_bytes / MIB:.0f} MiB: "
            f"{after_last.peak_resident_bytes / after_2.peak_resident_bytes:.3f}x "
            f"(live tensors {after_2.live_tensor_bytes / MIB:.1f} -> {after_last.live_tensor_bytes / MIB:.1f} MiB)"
        )

    def curve_configs(self, output_dir: Path) -> Dict[str, ContinualTrainerConfig]:
        demo = ContinualDemoDataParserConfig(data=self.data)
        options = {
            "num_tasks": self.curve_tasks,
            "iterations_per_task": self.curve_iterations_per_task,
            "train_num_rays_per_batch": self.rays_per_batch,
        }
        configs = {"continual-ngp": on_demo(CONTINUAL_NGP, demo, self.device, output_dir, **options)}
        if self.lever_reference:
            configs.update(lever_references(configs["continual-ngp"]))
        configs["continual-ngp-incre"] = on_demo(CONTINUAL_NGP_INCRE, demo, self.device, output_dir, **options)
        configs["nerfacto (all images at once)"] = nerfacto_on_demo(demo, self.device, output_dir, **options)
        return configs

    def psnr_curves(self, scratch: Path) -> None:
        configs = self.curve_configs(scratch)
        curves = {name: train_with_psnr_curve(config, self.curve_eval_every) for name, config in configs.items()}
        table = Table(title=f"Demo scene, {self.curve_tasks} tasks x {self.curve_iterations_per_task} iterations")
        for column in ("method", "training seconds", "final mean test PSNR (dB)"):
            table.add_column(column, justify="right")
        for name, curve in curves.items():
            table.add_row(name, f"{curve.seconds[-1]:.0f}", f"{curve.psnr[-1]:.2f}")
        CONSOLE.print(table)
        if self.lever_reference:
            final = {name: curve.psnr[-1] for name, curve in curves.items()}
            CONSOLE.print(
                "Speed levers' effect on the final mean PSNR: "
                f"oracle at half the samples {final[HALF_ORACLE] - final['continual-ngp']:+.2f} dB, "
                f"compile + detached sample positions {final['continual-ngp'] - final[LEVERS_OFF]:+.2f} dB"
            )
        CONSOLE.print(f"PSNR against training time: {self.plot(curves)}")

    def plot(self, curves: Dict[str, PSNRCurve]) -> Path:
        figure, axes = plt.subplots(figsize=(7, 4.5))
        for name, curve in curves.items():
            axes.plot(curve.seconds, curve.psnr, marker="o", markersize=3, label=name)
        axes.set_xlabel(f"training wall-clock seconds ({self.device})")
        axes.set_ylabel("test PSNR over all test frames (dB)")
        axes.set_title("continual-nerf demo scene")
        axes.set_xscale("log")  # seconds for continual-ngp, minutes for nerfacto
        axes.grid(alpha=0.3, which="both")
        axes.legend()
        path = self.output_dir / "psnr_vs_time.png"
        figure.tight_layout()
        figure.savefig(path, dpi=120)
        plt.close(figure)
        return path

    def main(self) -> None:
        self.output_dir.mkdir(parents=True, exist_ok=True)
        # one scratch folder for every run of this process: nerfstudio's tensorboard writers are global and outlive runs
        with tempfile.TemporaryDirectory() as scratch:
            self.throughput(Path(scratch))
            self.memory()
            self.psnr_curves(Path(scratch))


def entrypoint() -> None:
    tyro.cli(PerformanceBenchmark).main()


if __name__ == "__main__":
    entrypoint()
