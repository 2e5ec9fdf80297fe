"""How continual-ngp trains on a capture with a real camera's flaws, with and without the feature that answers each.

    python -m continual_nerf.bench.real_capture [--scenes room street] [--setting 5x240] [--captures ...]
        [--features ...] [--options "NS-TRAIN OPTIONS"] [--jobs 1] [--output-dir ...]

On the demo room: the clean capture, the same images with exposure and white balance changing by +-30 % (a jump at
every task boundary, a drift within), and the clean images with poses off by 1 degree and 1 % of the trajectory's
length (smooth along the capture, or drawn anew per image); on the demo street: the clean capture and its three cameras
each with its own colour response (+-20 %). Each is trained with continual-ngp's defaults ("off") and with the features
that answer its flaw; the clean room also with each feature on, to see what a feature costs where it has nothing to
fix. The table gives every run's final mean test PSNR beside the clean capture's and, for pose errors and pose
refinement, the rotation and translation errors of the training poses before and after refinement (each trajectory
first moved by the rigid motion that fits it best onto the true one: where the whole trajectory lies is not
observable). `--options` gives every run more ns-train options (a seed, a learning rate, test poses fitted with
--pipeline.test-pose-alignment-steps 50, ...). Finished runs are read back, not trained again, so an interrupted
benchmark resumes; results.md in the output folder holds the tables.
"""

from __future__ import annotations

import dataclasses
import json
import shlex
from dataclasses import dataclass
from pathlib import Path
from typing import Dict, List, Literal, Mapping, Tuple

import numpy as np
import torch
import tyro
from nerfstudio.models.nerfacto import NerfactoModel
from nerfstudio.utils.rich_utils import CONSOLE
from rich.table import Table

from continual_nerf.atomic_files import write_text_atomically
from continual_nerf.bench.demo_runs import check_names
from continual_nerf.bench.grid import DEMO, Grid, Recipe, Run, RunSummary, Setting, decibels
from continual_nerf.core.continual_trainer import ContinualTrainer, ContinualTrainerConfig
from continual_nerf.core.ngp_model import COLOR_TRANSFORM_GROUP, ContinualNGPModel, ContinualNGPModelConfig
from continual_nerf.core.per_frame import refined_poses
from continual_nerf.dataparsers.continual_demo_dataparser import ContinualDemoDataParserConfig
from continual_nerf.dataparsers.demo_capture import pose_errors, trajectory_length

Scene = Literal["room", "street"]

CAPTURES: Dict[str, str] = {
    "clean": "",
    "exposure +-30 %": "--exposure-strength 0.3",
    "poses off 1 deg, 1 %": "--pose-noise-degrees 1 --pose-noise-translation 0.01",
    "poses off 1 deg, 1 %, independent": "--pose-noise-degrees 1 --pose-noise-translation 0.01 "
    "--pose-noise-kind independent",
    "camera responses +-20 %": "--camera-response-strength 0.2",
}
"""continual-demo's options of each flaw (the exposure jumps at each task boundary)."""

TRANSFORMS_NOT_FITTED = (
    "--pipeline.model.use-color-transform True --pipeline.model.appearance-codes image "
    "--pipeline.model.color-transform-start previous-task"
)
"""A colour transform per image that starts each task at the previous task's, without the fit."""
TRUE_EXPOSURE = "colour transform at the true exposure, a bound"
"""Not a feature: every frame's transform held at the exposure and white balance the demo recorded it with, what
learned transforms can at best reach."""
POSE_REFINEMENT = "--pipeline.model.camera-optimizer.mode SO3xR3"
"""nerfacto's pose refinement, one correction per training image."""
FEATURES: Dict[str, str] = {
    "off": "",
    "codes per image": "--pipeline.model.use-appearance-embedding True --pipeline.model.appearance-codes image",
    "codes per camera and task": "--pipeline.model.use-appearance-embedding True "
    "--pipeline.model.appearance-codes camera-task",
    "colour transform per image": "--pipeline.model.use-color-transform True --pipeline.model.appearance-codes image",
    "colour transform per camera and task": "--pipeline.model.use-color-transform True "
    "--pipeline.model.appearance-codes camera-task",
    "colour transform per image, not fitted": TRANSFORMS_NOT_FITTED,
    "codes and colour transform per image": "--pipeline.model.use-appearance-embedding True "
    "--pipeline.model.use-color-transform True --pipeline.model.appearance-codes image",
    "pose refinement": POSE_REFINEMENT,
    "pose refinement from mid-task": f"{POSE_REFINEMENT} --pipeline.pose-refinement-start 0.5",
    # the transforms are given (train_at_true_exposure), not learned
    TRUE_EXPOSURE: f"{TRANSFORMS_NOT_FITTED} --optimizers.{COLOR_TRANSFORM_GROUP}.optimizer.lr 0",
}
"""continual-ngp's ns-train options of each feature."""

RUNS: Dict[str, List[Tuple[str, str]]] = {
    "room": [
        ("clean", "off"),
        ("clean", "codes per image"),
        ("clean", "colour transform per image"),
        ("clean", "pose refinement"),
        ("clean", "pose refinement from mid-task"),
        ("exposure +-30 %", "off"),
        ("exposure +-30 %", "codes per image"),
        ("exposure +-30 %", "codes per camera and task"),
        ("exposure +-30 %", "colour transform per image"),
        ("exposure +-30 %", "colour transform per camera and task"),
        ("exposure +-30 %", "colour transform per image, not fitted"),
        ("exposure +-30 %", TRUE_EXPOSURE),
        ("exposure +-30 %", "codes and colour transform per image"),
        ("poses off 1 deg, 1 %", "off"),
        ("poses off 1 deg, 1 %", "pose refinement"),
        ("poses off 1 deg, 1 %", "pose refinement from mid-task"),
        ("poses off 1 deg, 1 %, independent", "off"),
        ("poses off 1 deg, 1 %, independent", "pose refinement"),
        ("poses off 1 deg, 1 %, independent", "pose refinement from mid-task"),
    ],
    "street": [
        ("clean", "off"),
        ("camera responses +-20 %", "off"),
        ("camera responses +-20 %", "codes per image"),
        ("camera responses +-20 %", "codes per camera and task"),
        ("camera responses +-20 %", "colour transform per image"),
        ("camera responses +-20 %", "colour transform per camera and task"),
        ("camera responses +-20 %", "codes and colour transform per image"),
    ],
}
"""(capture, feature) pairs trained on each scene."""
REFERENCE = ("clean", "off")
"""Every scene's reference run: the clean capture, no feature."""


POSE_ERRORS = ("rotation_before", "rotation_after", "translation_before", "translation_after")
"""The extras of a run whose pose errors are reported: root mean square rotation errors (degrees) and translation errors
(percent of the trajectory's length) of the training poses before and after refinement, after the best rigid fit."""


def fitted_onto(poses: np.ndarray, true: np.ndarray) -> np.ndarray:
    """(N, 3, 4) `poses` moved by the rigid motion that best fits their camera centres and axes onto `true`'s."""
    centre, true_centre = poses[:, :, 3].mean(axis=0), true[:, :, 3].mean(axis=0)
    spread = np.sqrt(((true[:, :, 3] - true_centre) ** 2).sum(axis=-1).mean())
    # least squares over centres and camera axes (at the trajectory's spread), whose cross-covariance gives the rotation
    covariance = (true[:, :, 3] - true_centre).T @ (poses[:, :, 3] - centre)
    covariance += spread**2 * np.einsum("nij,nkj->ik", true[:, :, :3], poses[:, :, :3])
    u, _, vt = np.linalg.svd(covariance)
    rotation = u @ np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt))]) @ vt
    fitted = poses.copy()
    fitted[:, :, :3] = rotation @ poses[:, :, :3]
    fitted[:, :, 3] = (poses[:, :, 3] - centre) @ rotation.T + true_centre
    return fitted


def rms_errors(poses: np.ndarray, true: np.ndarray, length: float) -> Tuple[float, float]:
    """Root mean square rotation (degrees) and position (percent of `length`) errors after the best rigid fit."""
    degrees, distances = pose_errors(fitted_onto(poses, true), true)
    return float(np.sqrt((degrees**2).mean())), float(100 * np.sqrt((distances**2).mean()) / length)


def demo_of(config: ContinualTrainerConfig) -> ContinualDemoDataParserConfig:
    demo = config.pipeline.datamanager.dataparser
    assert isinstance(demo, ContinualDemoDataParserConfig), "the grid trains on continual-demo"
    return demo


def reports_pose_errors(config: ContinualTrainerConfig) -> bool:
    """Whether a run's table row gives pose errors: its capture has pose errors, or it refines poses (on exact poses,
    how far refinement moves them)."""
    demo, model = demo_of(config), config.pipeline.model
    noisy = demo.pose_noise_degrees > 0 or demo.pose_noise_translation > 0
    return noisy or (isinstance(model, ContinualNGPModelConfig) and model.refines_poses)


def training_pose_errors(trainer: ContinualTrainer) -> Dict[str, float]:
    """The training frames' pose errors before and after the run refined them (POSE_ERRORS), where reported."""
    if not reports_pose_errors(trainer.config):
        return {}
    datamanager, model = trainer.pipeline.datamanager, trainer.pipeline.model
    assert isinstance(model, NerfactoModel)
    cameras = datamanager.train_dataset.cameras
    given = cameras.camera_to_worlds.double().numpy()
    refined = refined_poses(model.camera_optimizer, cameras, torch.arange(len(cameras)))
    exact = dataclasses.replace(demo_of(trainer.config), pose_noise_degrees=0.0, pose_noise_translation=0.0)
    true_all = exact.setup().get_dataparser_outputs("train").cameras.camera_to_worlds.double().numpy()
    true = true_all[datamanager.task_split.all_train_frames()]
    length = trajectory_length(true_all[:, :, 3])
    (rotation_before, translation_before), (rotation_after, translation_after) = (
        rms_errors(given, true, length),
        rms_errors(refined.double().numpy(), true, length),
    )
    return dict(zip(POSE_ERRORS, (rotation_before, rotation_after, translation_before, translation_after)))


def _keep_rows(task: int, tasks: torch.Tensor, cameras: torch.Tensor) -> None:
    """A task switch leaves the transforms as they are."""


def hold_true_exposure(trainer: ContinualTrainer) -> None:
    """Hold every training frame's colour transform at the gains the demo recorded the frame with (exposure and white
    balance; a clipped pixel stays clipped) for the whole run."""
    model, datamanager = trainer.pipeline.model, trainer.pipeline.datamanager
    assert isinstance(model, ContinualNGPModel) and model.color_transforms is not None
    parser = demo_of(trainer.config).setup()
    gains = torch.as_tensor(parser.frame_gains(parser.capture()), dtype=torch.float32)
    frames = torch.as_tensor(datamanager.task_split.all_train_frames())
    with torch.no_grad():
        model.color_transforms.transforms.copy_(torch.diag_embed(gains[frames]) @ torch.eye(3, 4))
    model.color_transforms.start_task = _keep_rows
    model.open_task(datamanager.data_task, start=False)  # rows outside the open task are restored to these


def recipe(capture: str, feature: str) -> Recipe:
    """continual-ngp with `feature` on the demo with `capture`'s flaw, named "capture | feature"."""
    return Recipe.of(
        f"{capture} | {feature}",
        f"continual-ngp {FEATURES[feature]} {DEMO} {CAPTURES[capture]}",
        prepare=hold_true_exposure if feature == TRUE_EXPOSURE else None,
        measure=training_pose_errors,
    )


@dataclass
class RealCaptureBenchmark(Grid):
    """Trains continual-ngp on the demo with each flaw of a real capture, each answering feature off and on."""

    scenes: Tuple[Scene, ...] = ("room", "street")
    """Built-in scenes to measure on (continual-demo --scene): the room with exposure changes and pose errors, the
    street with its cameras' colour responses."""
    setting: str = "5x240"
    """Tasks x budget per task: iterations (5x240) or training seconds (5x20s)."""
    features: Tuple[str, ...] = tuple(FEATURES)
    """Which features' runs to train (names as the tables print them); the clean capture's run with none is always
    trained, as every table's reference."""
    captures: Tuple[str, ...] = tuple(CAPTURES)
    """Which captures' runs to train (names as the tables print them); the clean capture's run with no feature is
    always trained, as every table's reference."""
    output_dir: Path = Path("outputs/bench-real-capture")
    """Runs, results.json and results.md; finished runs of the same arguments found here are not trained again."""

    def pairs(self, scene: str) -> List[Tuple[str, str]]:
        """The scene's chosen (capture, feature) pairs, its reference among them."""
        return [
            pair for pair in RUNS[scene] if pair == REFERENCE or (pair[0] in self.captures and pair[1] in self.features)
        ]

    def measure(self) -> Dict[str, Dict[str, RunSummary]]:
        """Every scene's chosen runs by "capture | feature", trained where not finished before."""
        check_names("features", self.features, FEATURES)
        check_names("captures", self.captures, CAPTURES)
        setting = Setting.parse(self.setting)
        runs = {
            scene: self.runs(scene, setting, [recipe(*pair) for pair in self.pairs(scene)]) for scene in self.scenes
        }
        # the references last: a benchmark of other features running beside this one may be training them already
        ordered = sorted((run for scene_runs in runs.values() for run in scene_runs), key=is_reference)
        summaries = dict(zip(ordered, self.summaries(ordered)))
        return {scene: {run.recipe.name: summaries[run] for run in scene_runs} for scene, scene_runs in runs.items()}

    def title(self, scene: str) -> str:
        options = f", {shlex.join(self.options)}" if self.options else ""
        return f"{scene}, {Setting.parse(self.setting)}, {self.rays_per_batch} rays per batch{options}"

    def main(self) -> None:
        results = self.measure()
        for scene, runs in results.items():
            print_table(self.title(scene), runs)
        saved = {
            scene: {name: dataclasses.asdict(run) for name, run in runs.items()} for scene, runs in results.items()
        }
        write_text_atomically(self.output_dir / "results.json", json.dumps(saved, indent=1))
        lines = ["# Real-capture flaws (`python -m continual_nerf.bench.real_capture`)", ""]
        for scene, runs in results.items():
            lines += [f"## {self.title(scene)}", "", *markdown_table(runs), ""]
        write_text_atomically(self.output_dir / "results.md", "\n".join(lines))
        CONSOLE.print(f"[bold green]Tables: {self.output_dir / 'results.md'}")


def is_reference(run: Run) -> bool:
    return run.recipe.name == " | ".join(REFERENCE)


TABLE_COLUMNS = (
    "capture", "feature", "final mean PSNR (dB)", "vs clean, off (dB)", "right after own task (dB)",
    "rotation error (deg) before -> after", "translation error (% of length) before -> after", "training s",
)  # fmt: skip


def table_row(name: str, run: RunSummary, clean: RunSummary) -> List[str]:
    capture, feature = name.split(" | ")
    errors = run.extras
    rotation = f"{errors['rotation_before']:.2f} -> {errors['rotation_after']:.2f}" if errors else ""
    translation = f"{errors['translation_before']:.2f} -> {errors['translation_after']:.2f}" if errors else ""
    final = run.final_mean_psnr
    return [
        capture, feature, f"{final:.2f}", f"{final - clean.final_mean_psnr:+.2f}", decibels(run.after_own_task),
        rotation, translation, f"{run.train_seconds:.0f}",
    ]  # fmt: skip


def print_table(title: str, runs: Mapping[str, RunSummary]) -> None:
    table = Table(title=title)
    for column in TABLE_COLUMNS:
        table.add_column(column, justify="right")
    for name, run in runs.items():
        table.add_row(*table_row(name, run, runs[" | ".join(REFERENCE)]))
    CONSOLE.print(table)


def markdown_table(runs: Mapping[str, RunSummary]) -> List[str]:
    clean = runs[" | ".join(REFERENCE)]
    lines = ["| " + " | ".join(TABLE_COLUMNS) + " |", "|" + "---|" * len(TABLE_COLUMNS)]
    return lines + ["| " + " | ".join(table_row(name, run, clean)) + " |" for name, run in runs.items()]


def entrypoint() -> None:
    tyro.cli(RealCaptureBenchmark).main()


if __name__ == "__main__":
    entrypoint()
