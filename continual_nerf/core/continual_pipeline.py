"""The continual pipeline: owns the continual state (open task, budget, replay oracle, accuracy matrix) and switches
tasks inside nerfstudio's Trainer loop, through training callbacks, so `ns-train` drives everything."""

from __future__ import annotations

import dataclasses
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Dict, List, Literal, Mapping, Optional, Tuple, Type

import torch
from nerfstudio.cameras.rays import RayBundle
from nerfstudio.engine.callbacks import TrainingCallback, TrainingCallbackAttributes, TrainingCallbackLocation
from nerfstudio.engine.optimizers import Optimizers
from nerfstudio.engine.trainer import Trainer
from nerfstudio.pipelines.base_pipeline import VanillaPipeline, VanillaPipelineConfig
from nerfstudio.utils import writer
from nerfstudio.utils.rich_utils import CONSOLE
from rich.markup import escape
from torch.cuda.amp.grad_scaler import GradScaler

from continual_nerf.core import distributed
from continual_nerf.core.accuracy_matrix import AccuracyMatrix, DepthRow
from continual_nerf.core.change_guard import GuardCount, OpenTaskView, open_task_view
from continual_nerf.core.color_transform_fit import fit_open_task_color_transforms
from continual_nerf.core.continual_datamanager import ContinualDataManager, ContinualDataManagerConfig
from continual_nerf.core.depth_maps import DEPTH_KEY
from continual_nerf.core.depth_model import ContinualNGPDepthModelConfig, euclidean_depth_maps, trains_on_depth
from continual_nerf.core.distillation_loss import REPLAY_SKIPPED, REPLAY_WEIGHTS, distilled_rays
from continual_nerf.core.distributed import TaskDecision
from continual_nerf.core.evaluation import AlignedEvalCameras, FrameScores, PoseAlignment, evaluate_frames
from continual_nerf.core.experience_replay import ExperienceReplayBuffer
from continual_nerf.core.ngp_model import ContinualNGPModel, ContinualNGPModelConfig
from continual_nerf.core.replay_oracle import ReplayOracle, depth_target, surface_distance
from continual_nerf.core.sessions import (
    SESSIONS_KEY,
    SessionRecord,
    model_options,
    options_differing,
    size_difference,
    task_ranges,
    with_earlier_rows,
)
from continual_nerf.core.task_budget import TaskBudget, TaskState
from continual_nerf.errors import ContinualConfigError
from continual_nerf.nerfstudio_compat import (
    model_keys_of_one_process,
    model_state_of,
    trained_model,
    world_size_for_vanilla_pipeline,
    wrap_model,
)
from continual_nerf.validated_config import ValidatedConfig

ORACLE_PREFIX = "replay_oracle.model."
"""State-dict keys of the replay oracle's frozen copy in a checkpoint."""
CONTINUE_OPTION = "--pipeline.continue-with-new-capture"
"""The option that starts a new session from a loaded run (a resume command leaves it out)."""
MODEL_PREFIX = "_model."
"""State-dict keys of the model in a checkpoint (nerfstudio's VanillaPipeline)."""
BUFFER_STATE = "replay_buffer._extra_state"
"""State-dict key of the experience replay buffer in a checkpoint."""
BASE_LR_KEY = "continual_base_lr"
"""Key of a parameter group's configured learning rate, which --pipeline.lr-decay-per-task scales."""
POSE_GROUP = "camera_opt"
"""nerfacto's parameter group of the pose corrections."""


@dataclass
class ContinualPipelineConfig(ValidatedConfig, VanillaPipelineConfig):
    """Trains task after task; evaluates every task seen so far at the end of each."""

    _target: Type = field(default_factory=lambda: ContinualPipeline)
    datamanager: ContinualDataManagerConfig = field(default_factory=ContinualDataManagerConfig)
    """Splits the trajectory into tasks and serves the released tasks' rays and pixels."""
    model: ContinualNGPModelConfig = field(default_factory=ContinualNGPModelConfig)
    """The hash-grid model trained with Eq. 4."""
    lr_decay_per_task: float = 1.0
    """Factor every learning rate falls to, exponentially, over each task's budget, restarting at the next task;
    1 keeps it constant (the paper)."""
    lr_decay_start: float = 0.0
    """Share of each task's budget spent at the configured rate before --pipeline.lr-decay-per-task starts (0: the
    rate falls from the task's start)."""
    pose_lr_decay_per_task: float = 0.1
    """Factor the pose corrections' learning rate (--pipeline.model.camera-optimizer.mode) falls to over each task's
    budget instead: a task's frames refine anew, from --optimizers.camera-opt.optimizer.lr down to a tenth of it; 1 keeps
    it constant."""
    pose_refinement_start: float = 0.0
    """Share of each task's budget before its frames' pose corrections start to learn (their rate then falls over the
    rest of the task): the field first learns what the new frames show, so that the corrections do not chase it."""
    test_pose_alignment_steps: int = 0
    """Before a test frame is measured, fit its pose to its image for this many steps with the field frozen (BARF's
    test-time pose alignment, for poses with errors of their own per image); 0 measures it from its given pose."""
    continue_with_new_capture: bool = False
    """With --load-dir (or --load-checkpoint): go on learning the capture given now as a new session, its tasks after
    the loaded run's, the loaded model the replay oracle of every earlier task; the earlier capture is never read
    again. Off: --load-dir resumes the loaded run on its own capture."""
    relearn_proposal_networks: bool = False
    """At a later session's start, nerfacto's proposal networks (which place the field's samples along each ray) start
    again from their initial weights and learn the scene anew from the field, with fresh optimizer moments: the loaded
    ones give few samples to space the earlier session saw empty, where an object moved in is then learned slowly. The
    replay oracle keeps the loaded ones. Off: they go on from the loaded run's (a later session of an unchanged scene
    loses less)."""
    restart_optimizer_moments: bool = False
    """At a later session's start, every optimizer's moments (Adam's running averages of the gradients and of their
    squares) start again from zero: the loaded ones average the earlier session's gradients, and a field that must
    unlearn what changed learns the new state sooner without them. Off: they go on from the loaded run's."""
    change_guard: Literal["later-sessions", "every-task", "off"] = "later-sessions"
    """Skip replayed rays of earlier sessions' tasks whose surface an open-task frame sees changed (the new images
    win where they see a change): in a continued run's later sessions, in every task (of every earlier task), or never
    (the paper)."""
    change_threshold: float = 0.1
    """Mean absolute colour difference (0-1) between an open-task frame and the replay oracle's render of it above
    which (and above 3x the task's median difference) the change guard counts the frame's pixel as showing a change,
    if the earlier frame nearest its surface also saw that surface differ from the pixel by as much."""
    change_emphasis: float = 0.25
    """Share of the open task's rays the change guard draws from the pixels it found changed, while it runs (the
    new images' change learned in the task's budget), at most 8x their share of the task's pixels; 0: the open task's
    rays uniform over its pixels."""

    def validate(self) -> None:
        super().validate()
        for name in ("lr_decay_per_task", "pose_lr_decay_per_task"):
            value = getattr(self, name)
            if not 0 < value <= 1:
                raise ContinualConfigError(f"--pipeline.{name.replace('_', '-')} must be in (0, 1], got {value}")
        if self.test_pose_alignment_steps < 0:
            raise ContinualConfigError(
                f"--pipeline.test-pose-alignment-steps must be at least 0, got {self.test_pose_alignment_steps}"
            )
        if not 0 <= self.change_emphasis < 1:
            raise ContinualConfigError(f"--pipeline.change-emphasis must be in [0, 1), got {self.change_emphasis}")
        if not 0 < self.change_threshold < 1:
            raise ContinualConfigError(f"--pipeline.change-threshold must be in (0, 1), got {self.change_threshold}")
        for name in ("lr_decay_start", "pose_refinement_start"):
            value = getattr(self, name)
            if not 0 <= value < 1:
                raise ContinualConfigError(f"--pipeline.{name.replace('_', '-')} must be in [0, 1), got {value}")
        learns_per_frame = isinstance(self.model, ContinualNGPModelConfig) and self.model.learns_per_frame
        if learns_per_frame and not self.datamanager.frames_known_at_start():
            raise ContinualConfigError(
                "--pipeline.model.use-appearance-embedding, --pipeline.model.use-color-transform and "
                "--pipeline.model.camera-optimizer.mode need every frame known when training starts; this datamanager "
                "receives frames while it trains"
            )
        if trains_on_depth(self.model) and not self.datamanager.frames_known_at_start():
            raise ContinualConfigError(
                "a model that trains on depth (continual-ngp-depth) needs a finished capture's depth maps; this "
                "datamanager receives frames, without depth, while it trains"
            )


@dataclass(frozen=True)
class ContinualStatus:
    """What a continual run shows its user (the viewer's panel reads it): a snapshot, not a live view."""

    current_task: int
    """Index of the open task (0-based)."""
    known_tasks: int
    """Tasks known so far; while a capture is still running it counts the task being captured and may grow."""
    capture_running: bool
    """Whether more tasks may still arrive."""
    progress: str
    """The open task's budget: what is left, or what training does once it is spent."""
    psnr_rows: List[List[Optional[float]]]
    """The accuracy matrix so far: test PSNR per task after each finished task (None: not available)."""
    mean_psnr: List[float]
    """Mean test PSNR over the test frames of the tasks seen, after each finished task."""
    finished: bool
    """Whether the run has trained its last task."""
    depth_rows: List[List[Optional[float]]] = field(default_factory=list)
    """The accuracy matrix's depth errors so far: absolute relative error per task after each finished task (None: no
    test frame with depth); empty for a capture without depth maps."""


class ContinualPipeline(VanillaPipeline):
    """VanillaPipeline plus the continual state and the task switch."""

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
        # the datamanager reads the open task's depth maps only for a model that trains on them
        datamanager = dataclasses.replace(config.datamanager, train_depth=trains_on_depth(config.model))
        config = dataclasses.replace(config, datamanager=datamanager)
        super().__init__(
            config, device, test_mode, world_size_for_vanilla_pipeline(device, world_size), local_rank, grad_scaler
        )
        if world_size > 1 and self.world_size == 1:  # CPU processes: DDP without nerfstudio's CUDA device_ids
            wrap_model(self, distributed.data_parallel)
            self.world_size = world_size
        options = config.datamanager
        self.task = TaskState()
        self.budget = TaskBudget(iterations=options.iterations_per_task, seconds=options.seconds_per_task)
        self.replay_oracle = ReplayOracle(options.train_num_rays_per_batch)
        self.replay_buffer = ExperienceReplayBuffer(
            options.replay_buffer_fraction, options.replay_buffer_pixels, options.replay_buffer_keeps == "renders"
        )
        if self.replay_buffer.enabled:
            self.datamanager.replay_buffer = self.replay_buffer
            if distributed.is_main():
                total = self.datamanager.total_train_pixels() if options.frames_known_at_start() else None
                CONSOLE.print(self.replay_buffer.describe(total), markup=False, soft_wrap=True)
        self.accuracy = AccuracyMatrix(num_tasks=self.known_tasks)
        self._clock_started = 0.0
        self.task.current = self.datamanager.released_task = self.datamanager.earlier_tasks
        self.open_task_view: Optional[OpenTaskView] = None
        """What the open task's frames show where the oracle renders otherwise (the change guard); None: not built."""
        self.guard_count = GuardCount()
        self._said_unavailable = False
        # the first task has no earlier one to start from; a continued run's first task starts once its model is loaded
        self._open_frame_parameters(start=False)

    @property
    def replays(self) -> bool:
        """Whether past tasks' rays are supervised by the replay oracle (Eq. 4)."""
        return self.datamanager.config.replay and not self.datamanager.config.joint

    @property
    def known_tasks(self) -> int:
        """Tasks known so far: available ones, plus the one being captured while a capture runs."""
        return self.datamanager.tasks_available() + (0 if self.datamanager.capture_finished else 1)

    @property
    def is_last_task(self) -> bool:
        return self.datamanager.capture_finished and self.task.current == self.datamanager.tasks_available() - 1

    def request_next_task(self) -> None:
        """End the open task after the current iteration, whatever is left of its budget (the viewer's button)."""
        self.budget.request_next_task()

    def status(self) -> ContinualStatus:
        progress = self.budget.progress_text()
        if self.budget.spent() and not self.budget.next_task_requested:
            progress = self.datamanager.waiting_text()
        return ContinualStatus(
            current_task=self.task.current,
            known_tasks=self.known_tasks,
            capture_running=not self.datamanager.capture_finished,
            progress=progress,
            psnr_rows=[list(row) for row in self.accuracy.psnr],
            mean_psnr=list(self.accuracy.mean_psnr),
            finished=self.accuracy.finished,
            depth_rows=[list(row) for row in self.accuracy.depth_abs_rel],
        )

    def get_train_loss_dict(self, step: int):
        return self._train_loss_dict(step, trained_model(self))

    def local_train_loss_dict(self, step: int):
        """A training batch's losses through the unwrapped model: no gradient all-reduce follows its backward."""
        return self._train_loss_dict(step, self.model)

    def _train_loss_dict(self, step: int, model: torch.nn.Module):
        if self.guards_replay and self.config.change_emphasis > 0:
            self._emphasise_change()
        ray_bundle, batch = self.datamanager.next_train(step)
        self.add_replay_targets(ray_bundle, batch)
        model_outputs = model(ray_bundle)
        if self.distills_replay_weights:
            self.add_replay_weights(model_outputs, batch)
        metrics_dict = self.model.get_metrics_dict(model_outputs, batch)
        loss_dict = self.model.get_loss_dict(model_outputs, batch, metrics_dict)
        return model_outputs, loss_dict, metrics_dict

    @property
    def distills_replay_depth(self) -> bool:
        """Whether replayed rays get the oracle's rendered depth as their depth target
        (--pipeline.model.distill-replay-depth)."""
        model = self.config.model
        return isinstance(model, ContinualNGPDepthModelConfig) and model.distill_replay_depth

    @property
    def distills_replay_weights(self) -> bool:
        """Whether replayed rays' weights along the ray are distilled too (--pipeline.model.replay-weights-loss-mult)."""
        model = self.config.model
        return isinstance(model, ContinualNGPModelConfig) and model.replay_weights_loss_mult > 0

    def add_replay_weights(self, outputs: Dict[str, Any], batch: Dict[str, Any]) -> None:
        """The oracle's weights (REPLAY_WEIGHTS) at the model's samples along the replayed rays it teaches."""
        if "is_replay" not in batch:
            return
        distilled = distilled_rays(batch["is_replay"], batch.get(REPLAY_SKIPPED))
        if not distilled.any():
            return
        samples = outputs["ray_samples_list"][-1]
        batch[REPLAY_WEIGHTS] = self.replay_oracle.weights_at(samples[distilled.to(samples.frustums.origins.device)])

    def add_replay_targets(self, ray_bundle: RayBundle, batch: Dict[str, Any]) -> None:
        """Fill the targets of replayed rays with the colours the frozen oracle renders for them (Eq. 4), and their
        depth targets with its rendered depth when it distils depth too; with the change guard on, mark those whose
        surface an open-task frame sees changed (REPLAY_SKIPPED), which teach neither."""
        is_replay = batch["is_replay"]
        if not is_replay.any():
            return
        image = batch["image"]
        replayed = ray_bundle[is_replay.to(image.device)]
        outputs = self.replay_oracle.outputs(replayed)
        image[is_replay] = outputs["rgb"].to(image.dtype)
        if self.distills_replay_depth:
            depth = depth_target(outputs, replayed, euclidean_depth_maps(self.config.model))
            batch[DEPTH_KEY][is_replay] = depth.to(batch[DEPTH_KEY].dtype)
        if not self.guards_replay:
            return
        distance = surface_distance(outputs)
        assert distance is not None, "hash-grid models render depth"
        view = self._open_task_view()
        rays = (replayed.origins, replayed.directions, distance)
        crossing = view.crosses_change(*(tensor.detach().float().cpu() for tensor in rays))
        skipped = torch.zeros_like(is_replay)
        skipped[is_replay] = crossing.to(is_replay.device) & self._of_earlier_session(batch["indices"][is_replay, 0])
        batch[REPLAY_SKIPPED] = skipped
        if self.distills_replay_depth:
            batch[DEPTH_KEY][skipped] = 0.0  # no depth target where the surface changed
        self.guard_count.replayed += int(is_replay.sum())
        self.guard_count.skipped += int(skipped.sum())

    def _of_earlier_session(self, frames: torch.Tensor) -> torch.Tensor:
        """(N,) whether each of `frames` belongs to a task of an earlier session than the open task's: the open
        session's closed tasks saw the scene as it is now, and their replay teaches it (every task's with
        --pipeline.change-guard every-task)."""
        if self.config.change_guard == "every-task":
            return torch.ones_like(frames, dtype=torch.bool)
        datamanager = self.datamanager
        return (datamanager.train_dataset.task_of_frame[frames.cpu()] < datamanager.earlier_tasks).to(frames.device)

    def _guarded_frames(self, task: int) -> torch.Tensor:
        """The frames of tasks before `task` whose replay the change guard may skip: the views a change is measured
        against."""
        task_of_frame = self.datamanager.train_dataset.task_of_frame
        frames = torch.arange(len(task_of_frame))
        return frames[(task_of_frame < task) & self._of_earlier_session(frames)]

    @property
    def guards_replay(self) -> bool:
        """Whether the change guard checks the open task's replayed rays (--pipeline.change-guard): it places their
        surfaces with the depth the hash-grid models render (the NeRF baseline renders none), once there is an oracle
        (the first task has nothing to replay)."""
        guard = self.config.change_guard
        later_session = self.datamanager.session_of_task(self.task.current) > 0
        chosen = guard == "every-task" or (guard == "later-sessions" and later_session)
        return chosen and self.replays and self.replay_oracle.ready and isinstance(self.model, ContinualNGPModel)

    def _emphasise_change(self) -> None:
        """Have the datamanager draw --pipeline.change-emphasis of the open task's rays from the pixels the guard
        finds changed (built before the task's first batch, so that a resumed run draws the same rays)."""
        self.datamanager.open_if_released()
        view = self._open_task_view()
        self.datamanager.emphasise(view.task, view.changed_pixels, self.config.change_emphasis)

    def _open_task_view(self) -> OpenTaskView:
        """The open task's view for the change guard, rendered by the oracle once the task's pixels are read."""
        task = self.datamanager.data_task
        if self.open_task_view is None or self.open_task_view.task != task:
            datamanager = self.datamanager
            self.open_task_view = open_task_view(
                task,
                datamanager.train_dataset,
                lambda indices: datamanager.train_ray_generator(indices.to(self.device)),
                self._render_with_distance,
                self.config.change_threshold,
                datamanager.config.train_num_rays_per_batch,
                self._guarded_frames(task),
            )
            self.guard_count = GuardCount()
        return self.open_task_view

    def _render_with_distance(self, ray_bundle: RayBundle) -> Tuple[torch.Tensor, torch.Tensor]:
        rgb, distance = self.replay_oracle.render_with_distance(ray_bundle)
        assert distance is not None, "the guard runs for models that render depth"
        return rgb, distance

    def get_training_callbacks(
        self, training_callback_attributes: TrainingCallbackAttributes
    ) -> List[TrainingCallback]:
        trainer, optimizers = training_callback_attributes.trainer, training_callback_attributes.optimizers
        assert trainer is not None and optimizers is not None
        before = TrainingCallbackLocation.BEFORE_TRAIN_ITERATION
        decay = [TrainingCallback([before], self._decay_learning_rates, args=[optimizers])]
        pose_schedule = self.config.pose_lr_decay_per_task < 1 or self.config.pose_refinement_start > 0
        decays = self.config.lr_decay_per_task < 1 or (pose_schedule and POSE_GROUP in optimizers.optimizers)
        return super().get_training_callbacks(training_callback_attributes) + [
            *(decay if decays else []),
            TrainingCallback([before], self._start_clock),
            TrainingCallback([TrainingCallbackLocation.AFTER_TRAIN_ITERATION], self._after_iteration, args=[trainer]),
            TrainingCallback([TrainingCallbackLocation.AFTER_TRAIN], self._print_summary),
        ]

    def _decay_learning_rates(self, optimizers: Optimizers, step: int) -> None:
        """Every learning rate at its configured value times lr_decay_per_task ** (progress through the task after
        lr_decay_start), the pose corrections' 0 before pose_refinement_start, then times pose_lr_decay_per_task **
        (progress through the rest of the task)."""
        progress = self.budget.progress()
        for name, optimizer in optimizers.optimizers.items():
            if name == POSE_GROUP:
                start = self.config.pose_refinement_start
                factor = 0.0 if progress < start else _falling(self.config.pose_lr_decay_per_task, progress, start)
            else:
                factor = _falling(self.config.lr_decay_per_task, progress, self.config.lr_decay_start)
            for group in optimizer.param_groups:
                group.setdefault(BASE_LR_KEY, group["lr"])  # in the optimizer's state: a resumed run keeps it
                group["lr"] = group[BASE_LR_KEY] * factor

    def _start_clock(self, step: int) -> None:
        self._clock_started = time.perf_counter()

    def _stop_clock(self) -> float:
        if self.device.type == "cuda":
            torch.cuda.synchronize(self.device)  # CUDA kernels run asynchronously: count them in their iteration
        return time.perf_counter() - self._clock_started

    def _after_iteration(self, trainer: Trainer, step: int) -> None:
        """Count the iteration into the budget; once it is spent and the next task is there, end the open task.

        With several processes rank 0 decides and the others follow, so that all switch at the same step.
        """
        self.budget.count(self._stop_clock())
        decision = distributed.decided_by_main(
            self._decide(trainer) if distributed.is_main() else TaskDecision.CONTINUE, self.device
        )
        if decision == TaskDecision.CONTINUE:
            return
        if distributed.is_main():
            self.evaluate_seen_tasks(step, trainer.base_dir)
        if decision == TaskDecision.LAST_TASK_DONE:
            self.close_task()  # its final checkpoint can go on learning a later capture
            trainer.stop_training = True
        else:
            self.open_next_task()
            if distributed.is_main():
                CONSOLE.print(f"[bold]Task {self.task.current + 1}/{self.known_tasks} starts at step {step + 1}")
        trainer.save_checkpoint(step)
        distributed.barrier()  # the other ranks wait while rank 0 evaluates and checkpoints

    def _decide(self, trainer: Trainer) -> TaskDecision:
        if not self.budget.spent():
            return TaskDecision.CONTINUE
        if not self.datamanager.await_next_task(self.budget.next_task_requested, trainer.train_lock):
            return TaskDecision.CONTINUE  # a capture still running: the released tasks train until the next arrives
        return TaskDecision.LAST_TASK_DONE if self.is_last_task else TaskDecision.NEXT_TASK

    def before_task_switch(self) -> None:
        """Runs at the end of every task, the last included, while its pixels are still readable (e.g. EWC's Fisher)."""

    def close_task(self) -> None:
        """What the open task leaves while its pixels are readable: the baseline's estimates (EWC's Fisher), the replay
        buffer's share of its pixels."""
        self.before_task_switch()
        if self.replay_buffer.enabled:
            self._keep_pixels_of_closing_task()
        if self.guards_replay and distributed.is_main():
            share = 100 * self.guard_count.share()
            CONSOLE.print(
                f"Change guard: {share:.1f} % of task {self.task.current + 1}'s replayed rays skipped (an open-task "
                "frame sees their surface changed)"
            )

    def open_next_task(self) -> None:
        """Close the open task, freeze the model as the replay oracle and release the next task."""
        self.close_task()
        self.freeze_oracle()
        self.open_task(self.task.current + 1)

    def freeze_oracle(self) -> None:
        """The model as it is now becomes the replay oracle of every task so far."""
        if self.replays:
            distributed.copy_from_main(self.model, self.device)  # every rank's oracle: rank 0's weights, bit for bit
            self.replay_oracle.update(self.model)

    def open_task(self, task: int) -> None:
        """Release `task` with its whole budget, reading its pixels now; its frames' parameters start to learn."""
        self.task.current = task
        self.budget.start_task()
        self.datamanager.release(task)
        self._open_frame_parameters(start=True)

    def _open_frame_parameters(self, start: bool) -> None:
        """Let the model learn the appearance codes and pose corrections of the open task's frames only."""
        if not isinstance(self.model, ContinualNGPModel):
            return
        self.model.open_task(self.datamanager.data_task, start)
        if start and self.datamanager.data_task > 0 and self.model.fits_color_transforms:
            self._fit_color_transforms(self.model)

    def _fit_color_transforms(self, model: ContinualNGPModel) -> None:
        """Start the open task's colour transforms at its frames' exposure (see color_transform_fit); `release` has read
        the task's pixels."""
        fitted = fit_open_task_color_transforms(model, self.datamanager)
        distributed.copy_from_main(model, self.device)  # every rank starts the task at rank 0's fit
        if distributed.is_main():
            CONSOLE.print(f"Task {self.datamanager.data_task + 1}/{self.known_tasks} opens with {fitted}")

    def _keep_pixels_of_closing_task(self) -> None:
        flat, rgb = self.datamanager.open_task_pixels()
        total = self.datamanager.total_train_pixels()
        if self.replay_buffer.keeps_renders:
            self.freeze_oracle()  # renders as the oracle will: training-mode samples, each frame's code and pose
            self.replay_buffer.add_task(self.task.current, flat, rgb, total, render=self._render_for_buffer)
        else:  # a model that trains on depth keeps it with the pixels
            self.replay_buffer.add_task(self.task.current, flat, rgb, total, self.datamanager.open_task_depths(flat))
        if not distributed.is_main():
            return  # every rank keeps its own random share; rank 0's is checkpointed
        CONSOLE.print(
            f"Replay buffer: {len(self.replay_buffer)} pixels of {self.task.current + 1} tasks, "
            f"{self.replay_buffer.nbytes / 2**20:.2f} MiB"
        )

    def _render_for_buffer(self, flat: torch.Tensor) -> torch.Tensor:
        """The oracle's colours (N, 3) for flat pixel numbers, a training batch's worth of rays at a time."""
        colours = [torch.empty(0, 3, device=self.device)]
        for chunk in torch.split(flat, self.config.datamanager.train_num_rays_per_batch):
            ray_bundle = self.datamanager.train_ray_generator(self.datamanager.ray_indices(chunk))
            colours.append(self.replay_oracle.render(ray_bundle))
        return torch.cat(colours)

    @property
    def pose_alignment(self) -> PoseAlignment:
        """How test frames' poses are fitted before they are measured (--pipeline.test-pose-alignment-steps)."""
        return PoseAlignment(self.config.test_pose_alignment_steps)

    def get_average_eval_image_metrics(
        self, step: Optional[int] = None, output_path: Optional[Path] = None, get_std: bool = False
    ):
        loader = self.datamanager.fixed_indices_eval_dataloader
        if self.config.test_pose_alignment_steps:
            loader = AlignedEvalCameras(loader, self.model, self.pose_alignment)
        return self.get_average_image_metrics(loader, "eval", step, output_path, get_std)

    def evaluate_seen_tasks(self, step: int, output_dir: Path) -> None:
        """Append row `current task` of the accuracy matrix, log it and write it to `output_dir`. An earlier session's
        task none of whose test images can be read any more has no value (None: not available)."""
        row_psnr, row_ssim, mean_psnr, depth = self._measure_seen_tasks()
        self.accuracy.num_tasks = self.known_tasks  # grows while a capture folder is still being written
        self.accuracy.add_row(row_psnr, row_ssim, mean_psnr, step, depth)
        path = self.accuracy.write(output_dir)
        writer.put_dict(
            name="Continual PSNR per task",
            scalar_dict={f"task_{j + 1}": v for j, v in enumerate(row_psnr) if v is not None},
            step=step,
        )
        writer.put_scalar(name="Continual mean PSNR", scalar=mean_psnr, step=step)
        if depth is not None and depth.mean_abs_rel is not None:
            writer.put_scalar(name="Continual mean depth abs rel", scalar=depth.mean_abs_rel, step=step)
        CONSOLE.print(
            f"[bold]Task {self.task.current + 1}/{self.known_tasks} done[/bold] at step {step}: "
            f"test PSNR per task {_format_row(row_psnr)}, mean {mean_psnr:.2f} dB"
            f"{'' if depth is None else _format_depth(depth)} ({path})"
        )

    def _measure_seen_tasks(
        self,
    ) -> Tuple[List[Optional[float]], List[Optional[float]], float, Optional[DepthRow]]:
        """Test PSNR and SSIM of every task released so far (None where none of its test images is left), the mean
        PSNR over their test frames (NaN when none is left) and, for a capture with depth maps, their depth errors."""
        datamanager = self.datamanager
        seen_frames = datamanager.seen_test_frames()
        available = set(datamanager.eval_dataset.available_frames())
        frames = torch.tensor([frame for frame in seen_frames.tolist() if frame in available], dtype=torch.long)
        seen = range(int(datamanager.test_task_of_frame()[seen_frames].max()) + 1)  # every task when training jointly
        depth_maps = datamanager.eval_dataset.depth_maps
        if not len(frames):  # a stopped earlier session whose every test image is gone
            self._say_unavailable(list(seen))
            depth = None if depth_maps is None else DepthRow([None] * len(seen), [None] * len(seen), None, None)
            return [None] * len(seen), [None] * len(seen), float("nan"), depth
        self.eval()
        scores = evaluate_frames(
            self.model,
            datamanager.eval_dataset,
            frames.tolist(),
            self.pose_alignment,
            depth_maps,
            euclidean_depth_maps(self.config.model),
        )
        self.train()
        tasks = datamanager.test_task_of_frame()[frames]
        row_psnr = [_mean_or_none(scores.psnr[tasks == j]) for j in seen]
        row_ssim = [_mean_or_none(scores.ssim[tasks == j]) for j in seen]
        self._say_unavailable([j for j in seen if row_psnr[j] is None])
        depth = None if depth_maps is None else depth_row(scores, tasks, seen)
        return row_psnr, row_ssim, float(scores.psnr.mean()), depth

    def _say_unavailable(self, tasks: List[int]) -> None:
        """Say once that earlier sessions' tasks have no test image left to measure."""
        if not tasks or self._said_unavailable:
            return
        self._said_unavailable = True
        first = self.datamanager.task_split.test_frames[tasks[0]][0]
        CONSOLE.print(
            f"Tasks {task_ranges(tasks)} (earlier sessions): their test images are gone "
            f"({self.datamanager.train_dataparser_outputs.image_filenames[first]}, ...): not available in the accuracy "
            "matrix",
            markup=False,
            soft_wrap=True,
        )

    def _print_summary(self, step: int) -> None:
        if not distributed.is_main():
            return  # rank 0 alone evaluates
        if not self.accuracy.psnr:
            CONSOLE.print("[bold yellow]No task finished: no accuracy matrix to report.")
            return
        state = "final" if self.accuracy.finished else f"after task {len(self.accuracy.psnr)} (run stopped early)"
        CONSOLE.print(f"[bold green]Continual results, {state}:")
        CONSOLE.print(f"Per-task test PSNR: {_format_row(self.accuracy.psnr[-1])}")
        CONSOLE.print(f"Mean test PSNR over all test frames: {self.accuracy.mean_psnr[-1]:.2f} dB")
        if self.accuracy.depth_abs_rel:
            CONSOLE.print(f"Per-task test depth abs rel: {_format_errors(self.accuracy.depth_abs_rel[-1], '.3f')}")
            abs_rel, rmse = self.accuracy.mean_depth_abs_rel[-1], self.accuracy.mean_depth_rmse[-1]
            CONSOLE.print(f"Mean test depth abs rel {_optional(abs_rel, '.3f')}, RMSE {_optional(rmse, '.3f')} m")

    def load_state_dict(self, state_dict: Mapping[str, Any], strict: Optional[bool] = None):
        has_oracle = any(key.startswith(ORACLE_PREFIX) for key in state_dict)
        if has_oracle and not self.replay_oracle.ready:
            self.replay_oracle.update(self.model)  # builds the copy the saved weights go into
        elif not has_oracle and self.replay_oracle.ready:
            # a weights-only checkpoint of a task's end, where the oracle had just become the model
            state_dict = {**state_dict, **oracle_from_model(state_dict)}
        result = super().load_state_dict(state_dict, strict)
        self._open_frame_parameters(start=False)  # the loaded task continues with the loaded codes and poses
        return result

    def checkpoint_state_dict(self) -> Dict[str, Any]:
        """The state dict with the model's keys as one process has them (no DDP `module.`): any number of processes
        resumes from it, and ns-eval / ns-render read it."""
        return model_keys_of_one_process(self, self.state_dict())

    def get_extra_state(self) -> Dict[str, Any]:
        # the task, its progress and the accuracy matrix so far: a resumed run continues where this one stopped and
        # its accuracy_matrix.json keeps the rows measured before the crash
        return {
            "task": self.task.state(),
            "budget": self.budget.state(),
            "schedule": self.datamanager.schedule(),
            "accuracy": asdict(self.accuracy),
            SESSIONS_KEY: self.sessions_record().state(),
        }

    def sessions_record(self) -> SessionRecord:
        """Every session so far, this one's up to its open task: what a later capture's session continues from."""
        return self.datamanager.sessions_record(self.task.current + 1, model_options(self.config.model))

    def continue_session(self, state: Dict[str, Any], step: int) -> None:
        """Start this capture's first task from a checkpoint of the earlier sessions (`state`, at `step`): its model
        with the earlier frames' rows, as the replay oracle of every earlier task, its replay buffer and accuracy rows;
        the earlier sessions' open task, whatever was left of it, closed."""
        earlier = self.datamanager.earlier
        assert earlier is not None, "a continued run records its earlier sessions"
        self.load_earlier_model(state, step, earlier.num_train_frames)
        if BUFFER_STATE in state and self.replay_buffer.enabled:
            self.replay_buffer.set_extra_state(state[BUFFER_STATE])
        extra = state["_extra_state"]
        self.accuracy = AccuracyMatrix(**extra["accuracy"])
        self.accuracy.num_tasks = self.known_tasks
        self.accuracy.finished, self.accuracy.status = False, "training"
        self.budget.load_state(extra["budget"])
        self._measure_stopped_task(step)
        self.freeze_oracle()
        self.task.current = self.datamanager.released_task = self.datamanager.earlier_tasks
        self.datamanager.open_released_task()
        self.open_task(self.task.current)

    def _measure_stopped_task(self, step: int) -> None:
        """A run stopped in the middle of a task has no row for it: measured now, as the task closes."""
        earlier_tasks = self.datamanager.earlier_tasks
        if len(self.accuracy.psnr) >= earlier_tasks:
            return
        self.task.current = self.datamanager.released_task = earlier_tasks - 1
        row_psnr, row_ssim, mean_psnr, depth = self._measure_seen_tasks()
        self.accuracy.add_row(row_psnr, row_ssim, mean_psnr, step, depth)

    def load_earlier_model(self, state: Dict[str, Any], step: int, earlier_rows: int) -> None:
        """Load the model of an earlier session's checkpoint (`state`, at `step`) whose first `earlier_rows` per-frame
        rows are this run's earlier training frames'; a model of another size is a one-line error naming how."""
        model_state = {key[len(MODEL_PREFIX) :]: value for key, value in state.items() if key.startswith(MODEL_PREFIX)}
        current = self.model.state_dict()
        rows = self.model.per_frame_state_keys() if isinstance(self.model, ContinualNGPModel) else []
        difference = size_difference(model_state, current, rows)
        if difference is not None:
            earlier = self.datamanager.earlier
            saved = earlier.model_options if earlier is not None else {}
            options = options_differing(saved, model_options(self.config.model))
            raise ContinualConfigError(
                f"its model differs in size from this run's ({'; '.join(options) or difference}): continue with the "
                "model options it was trained with"
            )
        self.model.update_to_step(step)
        self.model.load_state_dict(with_earlier_rows(model_state, current, rows, earlier_rows))

    def set_extra_state(self, state: Dict[str, Any]) -> None:
        self.datamanager.check_resumable(state["schedule"])
        self.task.load_state(state["task"])
        self.budget.load_state(state["budget"])
        self.accuracy = AccuracyMatrix(**state["accuracy"])
        self.datamanager.resume_at(self.task.current)


def oracle_from_model(state_dict: Mapping[str, Any]) -> Dict[str, Any]:
    """The replay oracle's keys of a pipeline state dict, holding the model's weights."""
    return {ORACLE_PREFIX + key: value for key, value in model_state_of(state_dict).items()}


def _format_row(values: List[Optional[float]]) -> str:
    """A row of the accuracy matrix as rich prints it ("n/a": not available)."""
    return f"{_format_errors(values, '.2f')} dB"


def _mean_or_none(values: torch.Tensor) -> Optional[float]:
    return float(values.mean()) if len(values) else None


def _optional(value: Optional[float], spec: str) -> str:
    return "n/a" if value is None else format(value, spec)


def _format_errors(values: List[Optional[float]], spec: str) -> str:
    """A row of values as rich prints it ("n/a": none)."""
    return escape("[" + ", ".join(_optional(value, spec) for value in values) + "]")


def _format_depth(depth: DepthRow) -> str:
    return (
        f"; depth abs rel per task {_format_errors(depth.abs_rel, '.3f')}, mean {_optional(depth.mean_abs_rel, '.3f')}"
        f", RMSE {_optional(depth.mean_rmse, '.3f')} m"
    )


def _mean_of_finite(values: torch.Tensor) -> Optional[float]:
    """The mean of the values that are not NaN (frames with depth); None when there is none."""
    finite = values[~torch.isnan(values)]
    return float(finite.mean()) if len(finite) else None


def depth_row(scores: FrameScores, tasks: torch.Tensor, seen: range) -> DepthRow:
    """The accuracy matrix's depth errors of one row: per task the mean over its test frames with depth."""
    return DepthRow(
        abs_rel=[_mean_of_finite(scores.depth_abs_rel[tasks == j]) for j in seen],
        rmse=[_mean_of_finite(scores.depth_rmse[tasks == j]) for j in seen],
        mean_abs_rel=_mean_of_finite(scores.depth_abs_rel),
        mean_rmse=_mean_of_finite(scores.depth_rmse),
    )


def _falling(factor: float, progress: float, start: float) -> float:
    """`factor` ** (share of the task after `start` that has passed): 1 until `start`, `factor` at the task's end."""
    return factor ** (max(progress - start, 0.0) / (1 - start))
