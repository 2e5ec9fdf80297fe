"""How continual-ngp trains on a capture with a real camera's flaws, with and without the feature that answers each.

    python -m continual_nerf.bench.real_capture [--scenes room street] [--setting 5x240] [--output-dir ...]

On the demo room: the clean capture, the same images with exposure and white balance changing by +-30 % (a jump at
every task boundary, a drift within), and the clean images with poses off by 1 degree and 1 % of the trajectory's
length (smooth along the capture); on the demo street: the clean capture and its three cameras each with its own
colour response (+-20 %). Each is trained with continual-ngp's defaults ("off") and with the feature that answers its
flaw: appearance codes (per image, or per camera and task) or pose refinement; the clean room also with each feature
on, to see what a feature costs where it has nothing to fix. The table gives every run's final mean test PSNR beside
the clean capture's and, for pose errors and pose refinement, the rotation and translation errors of the training poses
before and after refinement (each trajectory first moved by the rigid motion that fits it best onto the true one:
where the whole trajectory lies is not observable). Finished runs are read back, not trained again, so an interrupted
benchmark resumes; results.md in the output folder holds the tables.
"""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Dict, List, Literal, Optional, Tuple

import numpy as np
import torch
import tyro
from nerfstudio.cameras.camera_optimizers import CameraOptimizerConfig
from nerfstudio.models.nerfacto import NerfactoModel
from nerfstudio.utils.rich_utils import CONSOLE
from rich.table import Table

from continual_nerf.atomic_files import write_text_atomically
from continual_nerf.bench.demo_runs import DemoBenchmark, check_names
from continual_nerf.bench.quality import RunSummary, Setting, decibels
from continual_nerf.core.accuracy_matrix import ACCURACY_MATRIX_FILENAME, AccuracyMatrix
from continual_nerf.core.continual_pipeline import POSE_GROUP
from continual_nerf.core.continual_trainer import ContinualTrainer, ContinualTrainerConfig
from continual_nerf.core.ngp_model import COLOR_TRANSFORM_GROUP, ContinualNGPModel, ContinualNGPModelConfig
from continual_nerf.core.per_frame import refined_poses
from continual_nerf.dataparsers.continual_demo_dataparser import ContinualDemoDataParserConfig
from continual_nerf.dataparsers.demo_capture import pose_errors, trajectory_length
from continual_nerf.method_configs import CONTINUAL_NGP
from continual_nerf.recipes import quiet_config, set_up_like_ns_train, train_like_ns_train

Scene = Literal["room", "street"]

CAPTURES: Dict[str, Dict[str, Any]] = {
    "clean": {},
    "exposure +-30 %": {"exposure_strength": 0.3},
    "poses off 1 deg, 1 %": {"pose_noise_degrees": 1.0, "pose_noise_translation": 0.01},
    "poses off 1 deg, 1 %, independent": {
        "pose_noise_degrees": 1.0,
        "pose_noise_translation": 0.01,
        "pose_noise_kind": "independent",
    },
    "camera responses +-20 %": {"camera_response_strength": 0.2},
}
"""The demo's capture options of each flaw (exposure segments follow the number of tasks)."""

TRANSFORMS_NOT_FITTED: Dict[str, Any] = {
    "use_color_transform": True,
    "appearance_codes": "image",
    "color_transform_start": "previous-task",
}
"""A colour transform per image that starts each task at the previous task's, without the fit."""
TRUE_EXPOSURE = "colour transform at the true exposure, a bound"
"""Not a feature: every frame's transform held at the exposure and white balance the demo recorded it with, what
learned transforms can at best reach."""
POSE_REFINEMENT: Dict[str, Any] = {"camera_optimizer": CameraOptimizerConfig(mode="SO3xR3")}
"""nerfacto's pose refinement, one correction per training image."""
FEATURES: Dict[str, Dict[str, Any]] = {
    "off": {},
    "codes per image": {"use_appearance_embedding": True, "appearance_codes": "image"},
    "codes per camera and task": {"use_appearance_embedding": True, "appearance_codes": "camera-task"},
    "colour transform per image": {"use_color_transform": True, "appearance_codes": "image"},
    "colour transform per camera and task": {"use_color_transform": True, "appearance_codes": "camera-task"},
    "colour transform per image, not fitted": TRANSFORMS_NOT_FITTED,
    "codes and colour transform per image": {
        "use_appearance_embedding": True,
        "use_color_transform": True,
        "appearance_codes": "image",
    },
    "pose refinement": POSE_REFINEMENT,
    "pose refinement from mid-task": POSE_REFINEMENT,  # and the pipeline's start (PIPELINE_OPTIONS)
    TRUE_EXPOSURE: TRANSFORMS_NOT_FITTED,  # and held at the true gains (train_at_true_exposure)
}
"""continual-ngp's model options of each feature."""
PIPELINE_OPTIONS: Dict[str, Dict[str, Any]] = {"pose refinement from mid-task": {"pose_refinement_start": 0.5}}
"""continual-ngp's pipeline options of the features that have some."""

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


@dataclass(frozen=True)
class PoseErrors:
    """Root mean square errors of the training poses against the true ones, after the best rigid fit."""

    rotation_before: float
    """Degrees, the poses the parser returned."""
    rotation_after: float
    """Degrees, the poses after refinement (the returned ones when the run did not refine)."""
    translation_before: float
    """Percent of the trajectory's length, the returned poses."""
    translation_after: float
    """Percent of the trajectory's length, after refinement."""


@dataclass(frozen=True)
class CaptureRun:
    """What the table shows of one run."""

    quality: RunSummary
    """Final PSNR, per-task spread, PSNR right after each task's own training, training time, ..."""
    poses: Optional[PoseErrors]
    """Training pose errors, for captures with pose errors and for runs that refine poses."""

    @classmethod
    def read(cls, path: Path) -> "CaptureRun":
        saved = json.loads(path.read_text())
        poses = saved["poses"] and PoseErrors(**saved["poses"])
        # summaries written before RunSummary had it keep after_own_task beside it
        quality = RunSummary(**{"after_own_task": saved.get("after_own_task"), **saved["quality"]})
        return cls(quality=quality, poses=poses)


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


def reports_pose_errors(demo: ContinualDemoDataParserConfig, config: ContinualTrainerConfig) -> bool:
    """Whether a run's table row gives pose errors: its capture has pose errors, or it refines poses (on exact poses,
    how far refinement moves them)."""
    noisy = demo.pose_noise_degrees > 0 or demo.pose_noise_translation > 0
    model = config.pipeline.model
    return noisy or (isinstance(model, ContinualNGPModelConfig) and model.refines_poses)


def training_pose_errors(trainer: ContinualTrainer, demo: ContinualDemoDataParserConfig) -> PoseErrors:
    """The training frames' pose errors before and after the run refined them."""
    datamanager, model = trainer.pipeline.datamanager, trainer.pipeline.model
    assert isinstance(model, NerfactoModel)
    cameras = datamanager.train_dataset.cameras
    given = cameras.camera_to_worlds.double().numpy()
    refined = refined_poses(model.camera_optimizer, cameras, torch.arange(len(cameras)))
    exact = dataclasses.replace(demo, pose_noise_degrees=0.0, pose_noise_translation=0.0)
    true_all = exact.setup().get_dataparser_outputs("train").cameras.camera_to_worlds.double().numpy()
    true = true_all[datamanager.task_split.all_train_frames()]
    length = trajectory_length(true_all[:, :, 3])
    (rotation_before, translation_before), (rotation_after, translation_after) = (
        rms_errors(given, true, length),
        rms_errors(refined.double().numpy(), true, length),
    )
    return PoseErrors(rotation_before, rotation_after, translation_before, translation_after)


@dataclass
class RealCaptureBenchmark(DemoBenchmark):
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
    small_model: bool = False
    """A hash grid small enough to train in minutes on a CPU: a quick look, not the measurement."""
    seed: int = 42
    """nerfstudio's --machine.seed of every run (42, nerfstudio's default): another seed, another --output-dir."""
    test_pose_alignment_steps: int = 0
    """--pipeline.test-pose-alignment-steps of every run: each test frame's pose fitted to its image before it is
    measured, for captures whose poses have errors of their own per image; another value, another --output-dir."""
    color_transform_lr: Optional[float] = None
    """--optimizers.color-transforms.optimizer.lr of every run that learns colour transforms (unset: continual-ngp's);
    another value, another --output-dir."""
    pose_lr: Optional[float] = None
    """--optimizers.camera-opt.optimizer.lr of every run that refines poses (unset: continual-ngp's); another value,
    another --output-dir."""
    pose_lr_decay_per_task: Optional[float] = None
    """--pipeline.pose-lr-decay-per-task of every run that refines poses (unset: continual-ngp's); another value,
    another --output-dir."""
    output_dir: Path = Path("outputs/bench-real-capture")
    """Runs, results.json and results.md; finished runs found here are not trained again."""

    def main(self) -> None:
        check_names("features", self.features, FEATURES)
        check_names("captures", self.captures, CAPTURES)
        results = {scene: self.run_scene(scene) for scene in self.scenes}
        for scene, runs in results.items():
            self.print_table(scene, runs)
        saved = {scene: {key: dataclasses.asdict(run) for key, run in runs.items()} for scene, runs in results.items()}
        write_text_atomically(self.output_dir / "results.json", json.dumps(saved, indent=1))
        write_text_atomically(self.output_dir / "results.md", self.markdown(results))
        CONSOLE.print(f"[bold green]Tables: {self.output_dir / 'results.md'}")

    def run_scene(self, scene: Scene) -> Dict[str, CaptureRun]:
        """The scene's runs of the chosen features and its reference run, by "capture | feature"."""
        chosen = [(c, f) for c, f in RUNS[scene] if c in self.captures and f in self.features and (c, f) != REFERENCE]
        # the reference last: a benchmark of other features running beside this one may be training it already
        runs = {pair: self.run(scene, *pair) for pair in [*chosen, REFERENCE]}
        return {" | ".join(pair): runs[pair] for pair in RUNS[scene] if pair in runs}

    def demo(self, scene: Scene, capture: str) -> ContinualDemoDataParserConfig:
        options = {**CAPTURES[capture], "exposure_segments": Setting.parse(self.setting).num_tasks}
        return ContinualDemoDataParserConfig(data=self.data, scene=scene, **options)  # type: ignore[arg-type]

    def run(self, scene: Scene, capture: str, feature: str) -> CaptureRun:
        """The run of `feature` on `scene`'s `capture`: read back if it finished before, trained otherwise."""
        name = f"{capture}_{feature}".replace(" ", "-").replace(",", "").replace("%", "pc").replace("+-", "")
        folder = self.output_dir / "runs" / scene / Setting.parse(self.setting).key / name
        summary_path = folder / "summary.json"
        if summary_path.exists():
            return CaptureRun.read(summary_path)
        demo = self.demo(scene, capture)
        config = self.config(demo, feature, folder)
        CONSOLE.print(f"[bold]{scene}, {capture}: training continual-ngp, {feature}")
        trainer = train_at_true_exposure(config, demo) if feature == TRUE_EXPOSURE else train_like_ns_train(config)
        matrix = AccuracyMatrix.read(config.get_base_dir() / ACCURACY_MATRIX_FILENAME)
        run = CaptureRun(
            quality=RunSummary.of(matrix, trainer.pipeline.budget.total_seconds),
            poses=training_pose_errors(trainer, demo) if reports_pose_errors(demo, config) else None,
        )
        write_text_atomically(summary_path, json.dumps(dataclasses.asdict(run), indent=1))
        return run

    def config(self, demo: ContinualDemoDataParserConfig, feature: str, folder: Path) -> ContinualTrainerConfig:
        setting = Setting.parse(self.setting)
        config = quiet_config(
            CONTINUAL_NGP,
            folder,
            device=self.device,
            small=self.small_model,
            dataparser=demo,
            num_tasks=setting.num_tasks,
            iterations_per_task=setting.iterations or 1,  # unused when the tasks are timed
            seconds_per_task=setting.seconds,
            train_num_rays_per_batch=self.rays_per_batch,
        )
        config.save_only_latest_checkpoint = True
        config.machine.seed = self.seed
        config.pipeline.model = dataclasses.replace(config.pipeline.model, **FEATURES[feature])
        config.pipeline = dataclasses.replace(
            config.pipeline,
            test_pose_alignment_steps=self.test_pose_alignment_steps,
            **PIPELINE_OPTIONS.get(feature, {}),
        )
        if self.pose_lr_decay_per_task is not None:
            config.pipeline.pose_lr_decay_per_task = self.pose_lr_decay_per_task
        if feature == TRUE_EXPOSURE:  # the transforms are given, not learned
            config.optimizers = group_at_rate(config.optimizers, COLOR_TRANSFORM_GROUP, 0.0)
        elif self.color_transform_lr is not None:
            config.optimizers = group_at_rate(config.optimizers, COLOR_TRANSFORM_GROUP, self.color_transform_lr)
        if self.pose_lr is not None:
            config.optimizers = group_at_rate(config.optimizers, POSE_GROUP, self.pose_lr)
        return config

    def title(self, scene: str) -> str:
        aligned = (
            f", test poses fitted in {self.test_pose_alignment_steps} steps" if self.test_pose_alignment_steps else ""
        )
        return f"{scene}, {Setting.parse(self.setting)}, {self.rays_per_batch} rays per batch{aligned}"

    def print_table(self, scene: str, runs: Dict[str, CaptureRun]) -> None:
        table = Table(title=self.title(scene))
        for column in TABLE_COLUMNS:
            table.add_column(column, justify="right")
        for key, run in runs.items():
            table.add_row(*table_row(key, run, runs[" | ".join(REFERENCE)]))
        CONSOLE.print(table)

    def markdown(self, results: Dict[str, Dict[str, CaptureRun]]) -> str:
        lines = ["# Real-capture flaws (`python -m continual_nerf.bench.real_capture`)", ""]
        for scene, runs in results.items():
            lines += [f"## {self.title(scene)}", "", "| " + " | ".join(TABLE_COLUMNS) + " |"]
            lines.append("|" + "---|" * len(TABLE_COLUMNS))
            lines += [
                "| " + " | ".join(table_row(key, run, runs[" | ".join(REFERENCE)])) + " |" for key, run in runs.items()
            ]
            lines.append("")
        return "\n".join(lines)


def group_at_rate(optimizers: Dict[str, Any], name: str, lr: float) -> Dict[str, Any]:
    """`optimizers` with parameter group `name` at learning rate `lr`, the rest of its optimizer as configured."""
    group = optimizers[name]
    return {**optimizers, name: {**group, "optimizer": dataclasses.replace(group["optimizer"], lr=lr)}}


TABLE_COLUMNS = (
    "capture", "feature", "final mean PSNR (dB)", "vs clean, off (dB)", "right after own task (dB)",
    "rotation error (deg) before -> after", "translation error (% of length) before -> after", "training s",
)  # fmt: skip


def _keep_rows(task: int, tasks: torch.Tensor, cameras: torch.Tensor) -> None:
    """A task switch leaves the transforms as they are."""


def train_at_true_exposure(config: ContinualTrainerConfig, demo: ContinualDemoDataParserConfig) -> ContinualTrainer:
    """Train with every training frame's colour transform at the gains the demo recorded the frame with (exposure and
    white balance; a clipped pixel stays clipped), held there for the whole run."""
    config.save_config()
    trainer = set_up_like_ns_train(config)
    model, datamanager = trainer.pipeline.model, trainer.pipeline.datamanager
    assert isinstance(model, ContinualNGPModel) and model.color_transforms is not None
    parser = demo.setup()
    gains = torch.as_tensor(parser.frame_gains(parser.capture()), dtype=torch.float32)
    frames = torch.as_tensor(datamanager.task_split.all_train_frames())
    with torch.no_grad():
        model.color_transforms.transforms.copy_(torch.diag_embed(gains[frames]) @ torch.eye(3, 4))
    model.color_transforms.start_task = _keep_rows
    model.open_task(datamanager.data_task, start=False)  # rows outside the open task are restored to these
    trainer.train()
    return trainer


def table_row(key: str, run: CaptureRun, clean: CaptureRun) -> List[str]:
    capture, feature = key.split(" | ")
    poses = run.poses
    rotation = "" if poses is None else f"{poses.rotation_before:.2f} -> {poses.rotation_after:.2f}"
    translation = "" if poses is None else f"{poses.translation_before:.2f} -> {poses.translation_after:.2f}"
    final = run.quality.final_mean_psnr
    return [
        capture, feature, f"{final:.2f}", f"{final - clean.quality.final_mean_psnr:+.2f}",
        decibels(run.quality.after_own_task), rotation, translation, f"{run.quality.train_seconds:.0f}",
    ]  # fmt: skip


def entrypoint() -> None:
    tyro.cli(RealCaptureBenchmark).main()


if __name__ == "__main__":
    entrypoint()
