"""The continual datamanager: serves the pixels and rays of the released tasks, one task's images at a time.

The pipeline decides which task is open (`release`); every training batch samples rays uniformly over all
pixels of the tasks released so far (over the open task alone without replay). Rays of the open task carry
their pixels (and, for a model that trains on depth, their depth); rays of earlier tasks are marked `is_replay`, for
the pipeline's replay oracle to supervise (Eq. 4).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from pathlib import Path
from threading import Lock
from typing import Any, Dict, Literal, Optional, Tuple, Type, Union

import numpy as np
import torch
import tyro
from nerfstudio.cameras.cameras import Cameras
from nerfstudio.cameras.rays import RayBundle
from nerfstudio.configs.dataparser_configs import AnnotatedDataParserUnion
from nerfstudio.data.datamanagers.base_datamanager import VanillaDataManager, VanillaDataManagerConfig
from nerfstudio.data.dataparsers.base_dataparser import DataparserOutputs
from nerfstudio.data.dataparsers.blender_dataparser import BlenderDataParserConfig
from nerfstudio.data.pixel_samplers import PixelSamplerConfig
from nerfstudio.data.utils.dataloaders import FixedIndicesEvalDataloader, RandIndicesEvalDataloader
from nerfstudio.model_components.ray_generators import RayGenerator

from continual_nerf.core.continual_dataset import (
    ContinualDataset,
    TestFrameDataset,
    check_image_headers,
    check_mask_headers,
)
from continual_nerf.core.depth_maps import DEPTH_KEY
from continual_nerf.core.experience_replay import ExperienceReplayBuffer
from continual_nerf.core.per_frame import TRAINING_FRAME
from continual_nerf.core.sessions import (
    SessionContext,
    SessionRecord,
    check_image_scale,
    check_inside_scene_box,
    in_world_frame,
    joined,
    record_of,
    restricted,
)
from continual_nerf.core.task_split import TaskSplit, nearest_train_frames, split_capture
from continual_nerf.errors import ContinualConfigError, DatasetError, plural
from continual_nerf.validated_config import ValidatedConfig

MAX_EMPHASIS_RATE = 8.0
"""The change guard's emphasis draws a changed pixel at most this many times as often as drawing uniformly over the
open task's pixels would: a few cells found changed (where nothing changed, the oracle's errors the guard lets through)
take few of the open task's rays."""


@dataclass
class ContinualDataManagerConfig(ValidatedConfig, VanillaDataManagerConfig):
    """Splits the dataparser's trajectory into tasks and serves them to the model one at a time."""

    _target: Type = field(default_factory=lambda: ContinualDataManager)
    # nerfstudio's default; the registered methods (method_configs.py) read continual-demo unless told otherwise
    dataparser: AnnotatedDataParserUnion = field(default_factory=BlenderDataParserConfig)
    """Dataparser that reads the trajectory; its train split, in capture order, is the whole trajectory."""
    num_tasks: int = 10
    """Number of temporally contiguous tasks the trajectory is split into (paper: 10)."""
    test_interval: int = 8
    """Every test_interval-th frame of each task is held out for evaluation and never trained on (a capture whose
    transforms.json lists test_filenames holds out those instead)."""
    iterations_per_task: int = 1000
    """Training iterations per task; the run has num_tasks x iterations_per_task iterations."""
    seconds_per_task: Optional[float] = None
    """Wall-clock training seconds per task (the paper's time-constrained setting); overrides iterations_per_task."""
    replay: bool = True
    """Supervise rays of past tasks with the frozen copy of the model (Eq. 4); off trains each task alone."""
    joint: bool = False
    """Non-continual upper bound (iNGP*, NeRF*): every task's pixels sampled from the start; same budget and tests."""
    current_task_fraction: Union[float, Literal["uniform", "sqrt"]] = 0.5
    """Share of each batch drawn from the open task: a fixed share, sqrt (1/sqrt(k) in task k), or uniform over all
    released pixels (the paper: ~1/k in task k); the rest replays earlier tasks."""
    replay_buffer_fraction: float = 0.0
    """Experience replay: real pixels of closed tasks kept, as a share of the training pixels from 0 to 1 (1 keeps
    every pixel); 0 keeps none (the paper)."""
    replay_buffer_pixels: int = 0
    """Experience replay by count: real pixels of closed tasks kept, instead of
    --pipeline.datamanager.replay-buffer-fraction; 0 keeps none."""
    replay_buffer_share: float = 0.5
    """Share of the replayed rays drawn from the replay buffer while it holds pixels; the oracle renders the rest."""
    replay_buffer_keeps: Literal["pixels", "renders"] = "pixels"
    """What the replay buffer keeps for its chosen pixels: their captured colours, or the colours the model renders for
    them as their task closes (no captured pixel kept; targets that do not drift as later oracles replace it)."""
    # nerfstudio's options for image-based sampling: batches here are drawn from the released tasks' pixels
    masks_on_gpu: tyro.conf.Suppress[bool] = False
    """Not used: batches are drawn from the released tasks' pixels."""
    images_on_gpu: tyro.conf.Suppress[bool] = False
    """Not used: batches are drawn from the released tasks' pixels."""
    train_num_images_to_sample_from: tyro.conf.Suppress[int] = -1
    """Not used: batches are drawn from every pixel of the released tasks."""
    train_num_times_to_repeat_images: tyro.conf.Suppress[int] = -1
    """Not used: batches are drawn from every pixel of the released tasks."""
    eval_num_images_to_sample_from: tyro.conf.Suppress[int] = -1
    """Not used: evaluation covers the released tasks' test frames."""
    eval_num_times_to_repeat_images: tyro.conf.Suppress[int] = -1
    """Not used: evaluation covers the released tasks' test frames."""
    eval_image_indices: tyro.conf.Suppress[Optional[Tuple[int, ...]]] = (0,)
    """Not used: evaluation covers the released tasks' test frames."""
    patch_size: tyro.conf.Suppress[int] = 1
    """Not used: rays are sampled one pixel at a time."""
    pixel_sampler: tyro.conf.Suppress[PixelSamplerConfig] = field(default_factory=PixelSamplerConfig)
    """Not used: the datamanager samples the released tasks' pixels itself."""
    accept_cameras_outside_scene_box: bool = False
    """A run continued on a later capture (--pipeline.continue-with-new-capture): train on it even where its cameras
    lie far outside the scene box the model was trained in (the scene grew); off: that is an error (its poses are
    likely in another world frame)."""
    earlier_sessions: tyro.conf.Suppress[Optional[Path]] = None
    """Set by ns-train when a run continues earlier sessions: the file in its run folder recording their frames (from
    the checkpoint it continues); None: the capture is the run's first session."""
    train_depth: tyro.conf.Suppress[bool] = False
    """Serve the open task's depth maps with its pixels: the pipeline sets it when its model trains on depth."""

    def validate(self) -> None:
        super().validate()
        if self.num_tasks < 1:
            raise ContinualConfigError(f"--pipeline.datamanager.num-tasks must be at least 1, got {self.num_tasks}")
        if self.test_interval < 2:
            raise ContinualConfigError(
                "--pipeline.datamanager.test-interval must be at least 2 (1 would hold out every frame), "
                f"got {self.test_interval}"
            )
        if self.seconds_per_task is not None and not self.seconds_per_task > 0:
            raise ContinualConfigError(
                f"--pipeline.datamanager.seconds-per-task must be positive, got {self.seconds_per_task}"
            )
        if self.seconds_per_task is None and self.iterations_per_task < 1:
            raise ContinualConfigError(
                f"--pipeline.datamanager.iterations-per-task must be at least 1, got {self.iterations_per_task}"
            )
        if isinstance(self.current_task_fraction, float) and not 0 < self.current_task_fraction <= 1:
            raise ContinualConfigError(
                "--pipeline.datamanager.current-task-fraction must be uniform, sqrt or a share in (0, 1], "
                f"got {self.current_task_fraction}"
            )
        self._validate_replay_buffer()
        if self.joint and self.earlier_sessions is not None:
            raise ContinualConfigError(
                "--pipeline.datamanager.joint trains on every image at once: it cannot continue earlier sessions, "
                "whose images are not kept"
            )
        if not 0 <= self.replay_buffer_share <= 1:
            raise ContinualConfigError(
                f"--pipeline.datamanager.replay-buffer-share must be in [0, 1], got {self.replay_buffer_share}"
            )
        if self.train_num_rays_per_batch < 1:
            raise ContinualConfigError(
                f"--pipeline.datamanager.train-num-rays-per-batch must be at least 1, got {self.train_num_rays_per_batch}"
            )

    def _validate_replay_buffer(self) -> None:
        fraction, pixels, option = self.replay_buffer_fraction, self.replay_buffer_pixels, "--pipeline.datamanager."
        if not 0 <= fraction <= 1:
            raise ContinualConfigError(
                f"{option}replay-buffer-fraction must be in [0, 1] (a share of the training pixels; "
                f"{option}replay-buffer-pixels takes a count), got {fraction:g}"
            )
        if pixels < 0:
            raise ContinualConfigError(f"{option}replay-buffer-pixels must be 0 or more, got {pixels}")
        if fraction > 0 and pixels > 0:
            raise ContinualConfigError(
                f"{option}replay-buffer-fraction {fraction:g} and {option}replay-buffer-pixels {pixels} both size the "
                "replay buffer: give one"
            )
        if (fraction > 0 or pixels > 0) and not self.replay:
            raise ContinualConfigError(
                f"the replay buffer ({option}replay-buffer-fraction or -pixels) needs replay; this run has "
                f"{option}replay False"
            )
        if self.replay_buffer_keeps == "renders" and fraction == 0 and pixels == 0:
            raise ContinualConfigError(
                f"{option}replay-buffer-keeps renders needs a replay buffer: give {option}replay-buffer-fraction or "
                f"{option}replay-buffer-pixels above 0"
            )

    def __setstate__(self, state: Dict[str, Any]) -> None:
        # a config.yml from before the two options: `replay_buffer_size`, a share below 1 and a count from 1 up
        size = state.pop("replay_buffer_size", 0)
        self.__dict__.update(state)
        if size:
            self.replay_buffer_fraction, self.replay_buffer_pixels = (size, 0) if size < 1 else (0.0, int(size))

    def frames_known_at_start(self) -> bool:
        """Whether every training frame is known when training starts (per-frame codes and poses need it)."""
        return True

    def task_budget_text(self) -> str:
        """One task's budget, in words (1000 iterations, 20 s)."""
        if self.seconds_per_task is not None:
            return f"{self.seconds_per_task:g} s"
        return plural(self.iterations_per_task, "iteration")

    def describe_tasks(self) -> str:
        """The tasks and their budget, in words (3 tasks x 1000 iterations)."""
        return f"{plural(self.num_tasks, 'task')} x {self.task_budget_text()}"

    def budgeted_iterations(self) -> Optional[int]:
        """Iterations the whole task budget takes, or None when tasks are timed (or, streaming, counted by the capture)."""
        if self.seconds_per_task is not None:
            return None
        return self.num_tasks * self.iterations_per_task


def subset_outputs(outputs: DataparserOutputs, frames: np.ndarray) -> DataparserOutputs:
    """The dataparser outputs restricted to `frames`, per-frame metadata included."""
    num_frames = len(outputs.image_filenames)
    index = torch.as_tensor(frames, dtype=torch.long)

    def pick(value: Any) -> Any:
        if isinstance(value, list) and len(value) == num_frames:
            return [value[i] for i in frames]
        if isinstance(value, torch.Tensor) and value.shape[:1] == (num_frames,):
            return value[index]
        return value

    return dataclasses.replace(
        outputs,
        image_filenames=pick(outputs.image_filenames),
        cameras=outputs.cameras[index],
        mask_filenames=None if outputs.mask_filenames is None else pick(outputs.mask_filenames),
        metadata={key: pick(value) for key, value in outputs.metadata.items()},
    )


def camera_ids(outputs: DataparserOutputs) -> np.ndarray:
    """Which camera took each frame: the dataparser's `camera_id`, else frames with the same intrinsics (and camera
    type) are one camera."""
    if "camera_id" in outputs.metadata:
        return np.asarray(outputs.metadata["camera_id"], dtype=np.int64)
    cameras = outputs.cameras
    intrinsics = torch.cat(
        [cameras.fx, cameras.fy, cameras.cx, cameras.cy, cameras.width, cameras.height, cameras.camera_type], dim=-1
    )
    return np.unique(intrinsics.double().numpy(), axis=0, return_inverse=True)[1].reshape(-1)


def capture_instants(outputs: DataparserOutputs) -> np.ndarray:
    """The capture instant of each frame: the dataparser's `time_group` (a rig), else its place in capture order."""
    time_group = outputs.metadata.get("time_group")
    return np.arange(len(outputs.image_filenames)) if time_group is None else np.asarray(time_group)


class ContinualDataManager(VanillaDataManager):
    """Serves the released tasks' rays and the open task's pixels; the pixels of closed tasks are never read again."""

    config: ContinualDataManagerConfig
    train_dataset: ContinualDataset
    eval_dataset: TestFrameDataset
    task_split: TaskSplit

    def __init__(
        self,
        config: ContinualDataManagerConfig,
        device: Union[torch.device, str] = "cpu",
        test_mode: Literal["test", "val", "inference"] = "val",
        world_size: int = 1,
        local_rank: int = 0,
        **kwargs,
    ):
        self.released_task = 0
        """The open task: its pixels and the rays of every task up to it are served."""
        self.replay_buffer: Optional[ExperienceReplayBuffer] = None
        """Stored pixels of closed tasks the pipeline keeps (experience replay); None keeps none."""
        self.emphasis: Tuple[int, torch.Tensor, float] = (-1, torch.zeros(0, dtype=torch.long), 0.0)
        """The task, the pixels of it and the share of its rays drawn from them (the change guard's emphasis)."""
        path = config.earlier_sessions
        self.earlier: Optional[SessionRecord] = None if path is None else SessionRecord.load(path)
        """The earlier sessions of a continued run (their tasks come first); None: this capture is the first."""
        super().__init__(config, device, test_mode, world_size, local_rank, **kwargs)

    @property
    def earlier_tasks(self) -> int:
        """Tasks of the earlier sessions, which come before this capture's."""
        return 0 if self.earlier is None else self.earlier.num_tasks

    @property
    def session_first_step(self) -> int:
        """The training step this capture's session starts at (0 for a run's first session)."""
        return 0 if self.earlier is None else self.earlier.next_step

    def session_of_task(self, task: int) -> int:
        """The session (0-based) `task` belongs to."""
        return 0 if self.earlier is None else self.earlier.session_of_task(task)

    def capture_name(self) -> str:
        """The capture this session reads, as messages name it."""
        return str(self.config.data or getattr(self.config.dataparser, "data", "the capture"))

    @property
    def num_tasks(self) -> int:
        """Tasks the trajectory is split into."""
        return self.task_split.num_tasks

    def tasks_available(self) -> int:
        """Tasks whose frames are there to be released: every task of the split."""
        return self.num_tasks

    @property
    def capture_finished(self) -> bool:
        """Whether no task will follow the available ones (a finished trajectory: always)."""
        return True

    @property
    def data_task(self) -> int:
        """The train dataset's task whose pixels are open: the released one, or with joint the one of every frame."""
        return 0 if self.config.joint else self.released_task

    def _image_scale(self) -> float:
        """The datamanager's resolution scale times the dataparser's downscale (capture parsers set one)."""
        return self.config.camera_res_scale_factor * self.train_dataparser_outputs.metadata.get(
            "image_scale_factor", 1.0
        )

    def create_train_dataset(self) -> ContinualDataset:
        self.task_split = split_capture(
            self.train_dataparser_outputs, self.config.num_tasks, self.config.test_interval, self.capture_name()
        )
        if self.earlier is not None:
            self._join_earlier_sessions(self.earlier)
        return self.dataset_of_trajectory()

    def dataset_of_trajectory(self) -> ContinualDataset:
        """The training frames of the trajectory (`train_dataparser_outputs` and `task_split`), task by task."""
        outputs = self.train_dataparser_outputs
        task_of_frame = self.task_split.train_task_of_frame()
        frames = self.task_split.all_train_frames()
        dataset = ContinualDataset(
            subset_outputs(outputs, frames),
            np.zeros_like(task_of_frame) if self.config.joint else task_of_frame,  # joint: one task holds every frame
            scale_factor=self._image_scale(),
            for_training=self.test_mode == "val",
            camera_of_frame=camera_ids(outputs)[frames],
            serve_depth=self.config.train_depth,
        )
        if self.earlier is not None:
            earlier = self.earlier
            dataset.keep_earlier_sessions(earlier.num_train_frames, earlier.valid_bits, earlier.valid_counts)
        if dataset.serve_depth and dataset.depth_maps is None:
            raise DatasetError(
                f"{self.capture_name()}: has no depth maps (ScanNet depth/, TUM depth.txt, transforms.json "
                "depth_file_path) for the model to train on; train continual-ngp instead"
            )
        return dataset

    def _join_earlier_sessions(self, earlier: SessionRecord) -> None:
        """Put this capture in the run's world frame after the earlier sessions' frames, its tasks after theirs."""
        check_image_scale(earlier, self._image_scale())
        outputs = in_world_frame(self.train_dataparser_outputs, earlier)
        if not self.config.accept_cameras_outside_scene_box:
            check_inside_scene_box(outputs, self.capture_name())
        self.train_dataparser_outputs, self.task_split = joined(
            earlier, outputs, self.task_split, camera_ids(outputs), capture_instants(outputs)
        )

    def sessions_record(self, released_tasks: int, model_options: Dict[str, Any]) -> SessionRecord:
        """The record of every session so far, this one's up to its `released_tasks` (tasks never released are
        dropped): what a later session continuing from a checkpoint of this run needs."""
        earlier = self.earlier
        this_session = released_tasks - self.earlier_tasks
        context = SessionContext(
            image_scale=self._image_scale(),
            tasks_per_session=[*(earlier.tasks_per_session if earlier else []), this_session],
            first_steps=[*(earlier.first_steps if earlier else []), self.session_first_step],
            task_checkpoints=[*(earlier.task_checkpoints if earlier else []), *[""] * this_session],
            data=[*(earlier.data if earlier else []), self.capture_name()],
            model_options=model_options,
        )
        outputs = self.train_dataparser_outputs
        record = record_of(
            outputs,
            self.task_split,
            camera_ids(outputs),
            capture_instants(outputs),
            self.train_dataset.valid_pixels,
            context,
        )
        return restricted(record, released_tasks)

    def create_eval_dataset(self) -> TestFrameDataset:
        """The test frames; each is rendered with the appearance code and pose correction of the training frame of
        its task and camera nearest to it in time (its cameras' TRAINING_FRAME metadata reaches the rays)."""
        outputs = self.train_dataparser_outputs
        # evaluation measures whole frames, masked pixels too, as nerfstudio's nerfacto does
        test_outputs = dataclasses.replace(
            subset_outputs(outputs, self.task_split.all_test_frames()), mask_filenames=None
        )
        nearest = nearest_train_frames(self.task_split, capture_instants(outputs), camera_ids(outputs))
        test_outputs.cameras.metadata = {TRAINING_FRAME: torch.from_numpy(nearest)[:, None]}
        dataset = TestFrameDataset(test_outputs, scale_factor=self._image_scale())
        dataset.earlier_frames = 0 if self.earlier is None else self.earlier.num_test_frames
        return dataset

    def setup_train(self) -> None:
        # no task opens here: a resumed run learns its task from the checkpoint, and must not read closed tasks' pixels
        self.train_ray_generator = RayGenerator(self.train_dataset.cameras.to(self.device))

    def setup_eval(self) -> None:
        self.eval_ray_generator = RayGenerator(self.eval_dataset.cameras.to(self.device))
        # ns-eval and ns-render read these; they cover the test frames of every task whose images are there
        self.fixed_indices_eval_dataloader = FixedIndicesEvalDataloader(
            self.eval_dataset,
            image_indices=tuple(self.eval_dataset.available_frames()),  # type: ignore[arg-type]  # nerfstudio: Tuple[int, ...]
            device=self.device,
        )
        self.eval_dataloader = RandIndicesEvalDataloader(self.eval_dataset, device=self.device)

    def test_task_of_frame(self) -> torch.Tensor:
        return torch.as_tensor(self.task_split.test_task_of_frame(), dtype=torch.long)

    def seen_test_frames(self) -> torch.Tensor:
        """Test frames of the tasks released so far (of every task when joint)."""
        last_seen = self.num_tasks - 1 if self.config.joint else self.released_task
        return torch.nonzero(self.test_task_of_frame() <= last_seen).view(-1)

    def release(self, task: int) -> None:
        """Close the open task (its pixels are dropped) and open `task`, reading its pixels now."""
        self.released_task = task
        if self.train_dataset.open_task != self.data_task:  # with joint, every frame stays open
            self.train_dataset.open(self.data_task)

    def resume_at(self, task: int) -> None:
        """Training (re)starts in `task`: its pixels are read at the first batch, once its images are checked."""
        self.released_task = task
        self.train_dataset.close()

    def await_next_task(self, requested: bool, train_lock: Lock) -> bool:
        """Whether the task after the open one (or the end of the run) is there: a finished trajectory has it."""
        return True

    def waiting_text(self) -> str:
        """What training does once the open task's budget is spent, as the viewer shows it."""
        return "budget spent"

    def open_task_share(self) -> Optional[float]:
        """Share of a batch drawn from the open task; None: uniform over all released pixels (the paper)."""
        share = self.config.current_task_fraction
        if share == "uniform":
            return None
        return 1 / math.sqrt(self.released_task + 1) if share == "sqrt" else float(share)

    def sample_pixels(self, num_rays: int) -> torch.Tensor:
        """Flat pixel numbers: the open task's first, then the earlier tasks' (uniformly over their pixels), in the
        share --current-task-fraction sets; the open task's alone without replay. Pixels masked out are never drawn."""
        start, end = self.train_dataset.open_task_pixel_range()
        draw = self.train_dataset.draw_pixels
        if not (self.config.replay and self.released_task > 0):
            return self._draw_open_task(start, end, num_rays)
        share = self.open_task_share()
        if share is None:
            return draw(0, end, num_rays)
        num_open = round(num_rays * share)
        return torch.cat([self._draw_open_task(start, end, num_open), draw(0, start, num_rays - num_open)])

    def ray_indices(self, flat: torch.Tensor) -> torch.Tensor:
        """(camera, y, x) of flat pixel numbers."""
        offsets = self.train_dataset.pixel_offsets
        frame = torch.searchsorted(offsets, flat, right=True) - 1
        local = flat - offsets[frame]
        width = self.train_dataset.cameras.width.view(-1)[frame].long()
        return torch.stack([frame, local // width, local % width], dim=-1)

    def open_if_released(self) -> None:
        """Open the released task unless it is open (its pixels read)."""
        if self.train_dataset.open_task != self.data_task:
            self.open_released_task()

    def emphasise(self, task: int, pixels: torch.Tensor, share: float) -> None:
        """Draw `share` of task `task`'s rays from `pixels` (flat pixel numbers of its frames) while it is open."""
        self.emphasis = (task, pixels, share)

    def _draw_open_task(self, start: int, end: int, num: int) -> torch.Tensor:
        """`num` flat pixel numbers of the open task, uniformly over its pixels but for the emphasised share."""
        draw = self.train_dataset.draw_pixels
        task, pixels, share = self.emphasis
        if task != self.data_task or len(pixels) == 0:
            return draw(start, end, num)
        share = min(share, MAX_EMPHASIS_RATE * len(pixels) / (end - start))
        num_emphasised = round(num * share)
        chosen = pixels[torch.randint(len(pixels), (num_emphasised,))]
        return torch.cat([draw(start, end, num - num_emphasised), chosen])

    def open_released_task(self) -> None:
        """Open the task training starts or resumes in, once the images still to be read are known to be readable."""
        later_tasks = torch.nonzero(self.train_dataset.task_of_frame >= self.data_task).view(-1)
        check_image_headers(self.train_dataset, later_tasks.tolist())
        available = self.eval_dataset.available_frames()
        check_image_headers(self.eval_dataset, available)
        if self.train_dataset.serve_depth and self.train_dataset.depth_maps is not None:
            self.train_dataset.depth_maps.check_headers(later_tasks.tolist())
        if self.eval_dataset.depth_maps is not None:  # the accuracy matrix measures depth on every test frame
            self.eval_dataset.depth_maps.check_headers(available)
        if self.train_dataset.mask_filenames is not None:  # closed tasks' too: a resumed run reads them again
            check_mask_headers(self.train_dataset, range(len(self.train_dataset)))
        self.train_dataset.open(self.data_task)

    def next_train(self, step: int) -> Tuple[RayBundle, Dict]:
        """Rays drawn over the released tasks; `image` holds the open task's pixels where `is_replay` is false, and
        `depth_image` (when the model trains on depth) their depth, 0 (none) on replayed rays."""
        self.open_if_released()
        self.train_count += 1
        flat = self.sample_pixels(self.config.train_num_rays_per_batch)
        start, _ = self.train_dataset.open_task_pixel_range()
        is_replay = flat < start
        current = ~is_replay
        pixels = self.train_dataset.task_pixels
        assert pixels is not None, "the open task's pixels are read above"
        image = torch.empty((len(flat), 3), device=self.device)
        image[current] = pixels[flat[current] - start].to(self.device)
        depth = self._open_task_depths(flat, current, start)
        if self.replay_buffer is not None and len(self.replay_buffer):
            self._draw_from_replay_buffer(flat, image, is_replay, depth)
        indices = self.ray_indices(flat)
        ray_bundle = self.train_ray_generator(indices)
        batch = {"image": image, "indices": indices, "is_replay": is_replay}
        if depth is not None:
            batch[DEPTH_KEY] = depth[:, None]
        return ray_bundle, batch

    def _open_task_depths(self, flat: torch.Tensor, current: torch.Tensor, start: int) -> Optional[torch.Tensor]:
        """Per ray (N,) the depth of its pixel where it is one of the open task's, 0 (no depth target) elsewhere; None
        when the model does not train on depth."""
        depths = self.train_dataset.task_depths
        if depths is None:
            return None
        depth = torch.zeros(len(flat), device=self.device)
        depth[current] = depths[flat[current] - start].to(self.device)
        return depth

    def _draw_from_replay_buffer(
        self, flat: torch.Tensor, image: torch.Tensor, is_replay: torch.Tensor, depth: Optional[torch.Tensor]
    ) -> None:
        """Turn --replay-buffer-share of the replayed rays into rays of stored pixels, supervised by their colours (and
        their depth, when the buffer keeps it)."""
        assert self.replay_buffer is not None
        replayed = torch.nonzero(is_replay).view(-1)
        chosen = replayed[: round(len(replayed) * self.config.replay_buffer_share)]
        stored_flat, stored_rgb, stored_depth = self.replay_buffer.sample(len(chosen))
        flat[chosen] = stored_flat
        image[chosen] = stored_rgb.to(image.device)
        is_replay[chosen] = False
        if depth is not None and stored_depth is not None:
            depth[chosen] = stored_depth.to(depth.device)

    def open_task_pixels(self) -> Tuple[torch.Tensor, torch.Tensor]:
        """Flat pixel numbers and colours of the open task's pixels that train, unmasked (what a replay buffer keeps a
        subset of at its end)."""
        start, end = self.train_dataset.open_task_pixel_range()
        pixels, valid_pixels = self.train_dataset.task_pixels, self.train_dataset.valid_pixels
        assert pixels is not None
        if valid_pixels is None:
            return torch.arange(start, end), pixels
        valid = valid_pixels.contains(torch.arange(start, end))
        return torch.arange(start, end)[valid], pixels[valid]

    def open_task_depths(self, flat: torch.Tensor) -> Optional[torch.Tensor]:
        """Depth of the open task's pixels `flat` (as open_task_pixels numbers them); None unless depth is served."""
        depths = self.train_dataset.task_depths
        if depths is None:
            return None
        start, _ = self.train_dataset.open_task_pixel_range()
        return depths[flat - start]

    def total_train_pixels(self) -> int:
        return int(self.train_dataset.pixel_offsets[-1])

    def _eval_frame(self, step: int) -> int:
        frames = self.seen_test_frames()
        return int(frames[step % len(frames)])

    def next_eval(self, step: int) -> Tuple[RayBundle, Dict]:
        """A batch of rays of one test frame of a released task."""
        self.eval_count += 1
        frame = self._eval_frame(self.eval_count)
        image = self.eval_dataset.get_image_float32(frame)[..., :3]
        height, width = image.shape[:2]
        flat = torch.randint(0, height * width, (self.config.eval_num_rays_per_batch,))
        indices = torch.stack([torch.full_like(flat, frame), flat // width, flat % width], dim=-1)
        batch = {"image": image.view(-1, 3)[flat].to(self.device), "indices": indices}
        return self.eval_ray_generator(indices), batch

    def next_eval_image(self, step: int) -> Tuple[Cameras, Dict]:
        """One whole test frame of a released task."""
        self.eval_count += 1
        frame = self._eval_frame(self.eval_count)
        return self.eval_dataset.cameras[frame : frame + 1].to(self.device), self.eval_dataset[frame]

    def schedule(self) -> Dict[str, int]:
        """What the task split follows from; a checkpoint resumes only into the same split."""
        return {
            "num_tasks": self.num_tasks,
            "test_interval": self.config.test_interval,
            "num_frames": len(self.train_dataparser_outputs.image_filenames),
        }

    def check_resumable(self, saved: Dict[str, int]) -> None:
        """Refuse a checkpoint whose tasks were split differently, naming what differs."""
        for key, value in self.schedule().items():
            if saved[key] != value:
                option = f"--pipeline.datamanager.{key.replace('_', '-')}"
                what = "frames in the dataset" if key == "num_frames" else option
                raise ContinualConfigError(f"{what}: the checkpoint was trained with {saved[key]}, this run {value}")
