"""The streaming datamanager: tasks open as frames arrive in a capture folder that is still being written.

Batch mode cuts a finished trajectory into `num_tasks` tasks; here the `continual-stream` dataparser cuts the
capture as it grows (every `--frames-per-task` frames, or at a `.task` marker) and this datamanager releases those
tasks one by one, with the batch mode's held-out test frames, replay oracle and budget. A task ends when its
budget is spent and the next task has arrived; until then training refines the released tasks or waits.
"""

from __future__ import annotations

import time
from contextlib import contextmanager
from dataclasses import dataclass, field
from threading import Lock
from typing import Any, Dict, Iterator, List, Literal, Type

import numpy as np
from nerfstudio.configs.dataparser_configs import AnnotatedDataParserUnion
from nerfstudio.engine.callbacks import TrainingCallback, TrainingCallbackAttributes, TrainingCallbackLocation
from nerfstudio.model_components.ray_generators import RayGenerator
from nerfstudio.models.base_model import Model
from nerfstudio.utils.rich_utils import CONSOLE

from continual_nerf.continual_datamanager import ContinualDataManager, ContinualDataManagerConfig, subset_outputs
from continual_nerf.continual_dataset import ContinualDataset
from continual_nerf.dataparsers.stream_dataparser import StreamDataParser, StreamDataParserConfig, StreamFrame
from continual_nerf.errors import ContinualConfigError
from continual_nerf.task_schedule import TaskSplit, split_into_tasks


@dataclass
class StreamingDataManagerConfig(ContinualDataManagerConfig):
    """Releases a capture folder's tasks as they arrive (continual-stream) instead of cutting a finished trajectory."""

    _target: Type = field(default_factory=lambda: StreamingDataManager)
    """The datamanager this config builds."""
    dataparser: AnnotatedDataParserUnion = field(default_factory=StreamDataParserConfig)
    """Must be continual-stream: the capture folder, how it is cut into tasks, the fixed pose transform."""
    num_tasks: int = 0
    """Stop after this many tasks even while the capture goes on (0: train until the capture's end marker)."""
    idle: Literal["refine", "wait"] = "refine"
    """Budget spent, next task not here yet: keep training the released tasks, or wait (the viewer stays live)."""

    def validate(self) -> None:
        super().validate()
        if not isinstance(self.dataparser, StreamDataParserConfig):
            raise ContinualConfigError(
                f"continual-ngp-stream reads a capture folder: use the continual-stream dataparser, "
                f"not {type(self.dataparser).__name__}"
            )
        if self.num_tasks < 0:
            raise ContinualConfigError(
                f"--pipeline.datamanager.num-tasks must be 0 (no limit) or more, got {self.num_tasks}"
            )
        if self.joint:
            raise ContinualConfigError(
                "--pipeline.datamanager.joint needs every task from the start; a capture has not sent them yet"
            )

    def max_num_iterations(self) -> int:
        """The capture decides how many tasks there are: a generous cap."""
        return 10**9


@contextmanager
def released(lock: Lock) -> Iterator[None]:
    """Let go of a lock this thread holds for a while (the Trainer runs callbacks under its train lock)."""
    lock.release()
    try:
        yield
    finally:
        lock.acquire()


class StreamingDataManager(ContinualDataManager):
    """ContinualDataManager whose tasks come from a growing capture folder; datasets grow task by task."""

    config: StreamingDataManagerConfig
    dataparser: StreamDataParser

    def __init__(self, config: StreamingDataManagerConfig, *args: Any, **kwargs: Any) -> None:
        self.frames: List[StreamFrame] = []
        """Frames of the released tasks, in capture order; dataset frame numbers index into it."""
        self._train_frames: List[np.ndarray] = []
        self._test_frames: List[np.ndarray] = []
        self._last_poll = 0.0
        self._idle_reported = False
        super().__init__(config, *args, **kwargs)

    @property
    def released_tasks(self) -> int:
        return len(self._train_frames)

    @property
    def available_tasks(self) -> int:
        """Tasks complete in the capture folder, at most --num-tasks."""
        count = len(self.dataparser.tasks)
        return min(count, self.config.num_tasks) if self.config.num_tasks else count

    @property
    def capture_finished(self) -> bool:
        """No task will follow the available ones: the capture ended, or --num-tasks is reached."""
        return self.dataparser.ended or 0 < self.config.num_tasks <= len(self.dataparser.tasks)

    @property
    def num_tasks(self) -> int:
        """Tasks known so far, counting the one being captured while the capture goes on."""
        return self.available_tasks + (0 if self.capture_finished else 1)

    def next_task_ready(self) -> bool:
        return self.available_tasks > self.current_task + 1

    def _release(self, frames: List[StreamFrame]) -> None:
        """Append a task; its held-out test frames follow the batch rule (every test_interval-th from its start)."""
        split = split_into_tasks(len(frames), 1, self.config.test_interval)
        start = len(self.frames)
        self._train_frames.append(split.train_frames[0] + start)
        self._test_frames.append(split.test_frames[0] + start)
        self.frames.extend(frames)
        self.task_split = TaskSplit(train_frames=tuple(self._train_frames), test_frames=tuple(self._test_frames))
        self.train_dataparser_outputs = self.dataparser.outputs(self.frames)

    def create_train_dataset(self) -> ContinualDataset:
        if not self.frames:
            # training starts on the first task; ns-eval, ns-render and ns-viewer see every task there is
            if self.test_mode != "val":
                self.dataparser.poll()
            for task in range(1 if self.test_mode == "val" else self.available_tasks):
                self._release(self.dataparser.tasks[task])
        return ContinualDataset(
            subset_outputs(self.train_dataparser_outputs, self.task_split.all_train_frames()),
            self.task_split.train_task_of_frame(),
            scale_factor=self._image_scale(),
            for_training=self.test_mode == "val",
        )

    def open_next_task(self, model: Model) -> None:
        """Grow the datasets by the next task, then release it as the batch mode does."""
        self._release(self.dataparser.tasks[self.released_tasks])
        self.train_dataset = self.create_train_dataset()
        self.eval_dataset = self.create_eval_dataset()
        self.setup_eval()
        super().open_next_task(model)
        self.train_ray_generator = RayGenerator(self.train_dataset.cameras.to(self.device))
        self._idle_reported = False

    def budget_spent(self) -> bool:
        """The open task ends once its budget is spent and the next task has arrived (or none will)."""
        return super().budget_spent() and self._next_task_arrived()

    def get_training_callbacks(self, attributes: TrainingCallbackAttributes) -> List[TrainingCallback]:
        assert attributes.trainer is not None
        # the pipeline gathers these before its own, so they run before its budget check in every iteration
        location = TrainingCallbackLocation.AFTER_TRAIN_ITERATION
        return [TrainingCallback([location], self._follow_capture, args=[attributes.trainer.train_lock])]

    def _next_task_arrived(self) -> bool:
        """Whether the open task may end; "Next task now" closes the task being captured early."""
        if self.next_task_requested and not self.next_task_ready():
            self.dataparser.close_task()
        return self.next_task_ready() or self.capture_finished

    def _follow_capture(self, train_lock: Lock, step: int) -> None:
        """Read new frames every --poll-seconds; with the budget spent and no next task, refine or wait."""
        if time.monotonic() - self._last_poll >= self.dataparser.config.poll_seconds:
            self.dataparser.poll()
            self._last_poll = time.monotonic()
        if self._next_task_arrived() or not ContinualDataManager.budget_spent(self):
            return
        if self.config.idle == "wait":
            folder = self.dataparser.config.data
            CONSOLE.log(f"Task {self.current_task + 1}: budget spent, waiting for frames in {folder}")
            with released(train_lock):  # the viewer renders under the train lock
                self.dataparser.wait_until(self._next_task_arrived)
            self._last_poll = time.monotonic()
        elif not self._idle_reported:
            CONSOLE.log(f"Task {self.current_task + 1}: budget spent, refining until the next task's frames arrive")
            self._idle_reported = True

    def schedule(self) -> Dict[str, int]:
        # the capture folder, not options, decides the tasks and their frames
        return {"test_interval": self.config.test_interval}

    def set_extra_state(self, state: Dict[str, Any]) -> None:
        if self.test_mode == "val" and int(state["current_task"]) > 0:
            raise ContinualConfigError("continual-ngp-stream cannot resume training from a checkpoint after task 1")
        super().set_extra_state(state)
