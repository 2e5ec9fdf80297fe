"""The streaming datamanager: tasks open as frames arrive in a capture folder that is still being written.

Batch mode cuts a finished trajectory into `num_tasks` tasks; here the `continual-stream` dataparser cuts the
capture as it grows (every `--frames-per-task` frames, or at a `.task` marker) and this datamanager serves those
tasks one by one, with the batch mode's held-out test frames; the pipeline's replay oracle and budget are the same.
A task ends when its budget is spent and the next task has arrived; until then training refines the released
tasks or waits.
"""

from __future__ import annotations

import time
from contextlib import contextmanager
from dataclasses import dataclass, field
from threading import Lock
from typing import Any, Dict, Iterator, List, Literal, Optional, Type

import numpy as np
import tyro
from nerfstudio.configs.dataparser_configs import AnnotatedDataParserUnion
from nerfstudio.engine.callbacks import TrainingCallback, TrainingCallbackAttributes, TrainingCallbackLocation
from nerfstudio.model_components.ray_generators import RayGenerator
from nerfstudio.utils.rich_utils import CONSOLE

from continual_nerf.core import distributed
from continual_nerf.core.continual_datamanager import ContinualDataManager, ContinualDataManagerConfig
from continual_nerf.core.continual_dataset import ContinualDataset
from continual_nerf.core.task_split import TaskSplit, split_into_tasks
from continual_nerf.dataparsers.capture_folder import CaptureTasks, StreamFrame, announce_training
from continual_nerf.dataparsers.stream_dataparser import StreamDataParser, StreamDataParserConfig
from continual_nerf.errors import ContinualConfigError


@dataclass
class StreamingDataManagerConfig(ContinualDataManagerConfig):
    """Releases a capture folder's tasks as they arrive (continual-stream) instead of cutting a finished trajectory."""

    _target: Type = field(default_factory=lambda: StreamingDataManager)
    """The datamanager this config builds."""
    dataparser: AnnotatedDataParserUnion = field(default_factory=StreamDataParserConfig)
    """Must be continual-stream: the capture folder, how it is cut into tasks, the fixed pose transform."""
    num_tasks: tyro.conf.Suppress[int] = 1
    """Not used: the capture decides the tasks (--pipeline.datamanager.max-tasks caps them)."""
    max_tasks: int = 0
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
        if self.max_tasks < 0:
            raise ContinualConfigError(
                f"--pipeline.datamanager.max-tasks must be 0 (no limit) or more, got {self.max_tasks}"
            )
        if self.joint:
            raise ContinualConfigError(
                "--pipeline.datamanager.joint needs every task from the start; a capture has not sent them yet"
            )

    def frames_known_at_start(self) -> bool:
        """Frames keep arriving while training runs: no per-frame codes or poses for frames not there yet."""
        return False

    def describe_tasks(self) -> str:
        at_most = f", at most {self.max_tasks}" if self.max_tasks else ""
        return f"tasks as the capture sends them{at_most}, {self.task_budget_text()} each"

    def budgeted_iterations(self) -> Optional[int]:
        """The capture decides how many tasks there are."""
        return None


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
        self._announced: Optional[int] = None
        """The task the capture folder was last told trains (rank 0 tells it)."""
        super().__init__(config, *args, **kwargs)

    @property
    def capture(self) -> CaptureTasks:
        """The capture folder's frames, cut into tasks as they arrive."""
        return self.dataparser.capture

    @property
    def num_tasks(self) -> int:
        """Tasks released so far (the datasets hold their frames), a continued run's earlier sessions' first."""
        return self.earlier_tasks + len(self._train_frames)

    def tasks_available(self) -> int:
        """Tasks complete in the capture folder, at most --max-tasks, after the earlier sessions' tasks."""
        count = len(self.capture.tasks)
        return self.earlier_tasks + (min(count, self.config.max_tasks) if self.config.max_tasks else count)

    @property
    def capture_finished(self) -> bool:
        """No task will follow the available ones: the capture ended, or --max-tasks is reached."""
        return self.capture.ended or 0 < self.config.max_tasks <= len(self.capture.tasks)

    def _next_task_ready(self) -> bool:
        return self.tasks_available() > self.released_task + 1

    def _append_task(self, frames: List[StreamFrame]) -> None:
        """Append a task; its held-out test frames follow the batch rule (every test_interval-th from its start)."""
        split = split_into_tasks(len(frames), 1, self.config.test_interval)
        start = len(self.frames)
        self._train_frames.append(split.train_frames[0] + start)
        self._test_frames.append(split.test_frames[0] + start)
        self.frames.extend(frames)
        self.task_split = TaskSplit(train_frames=tuple(self._train_frames), test_frames=tuple(self._test_frames))
        self.train_dataparser_outputs = self.capture.outputs(self.frames)
        if self.earlier is not None:  # a continued run: its earlier sessions' tasks come first
            self._join_earlier_sessions(self.earlier)

    def create_train_dataset(self) -> ContinualDataset:
        if not self.frames:
            # training starts on the first task; ns-eval, ns-render and ns-viewer see every task there is
            if self.test_mode != "val":
                self.capture.poll()
            for task in range(1 if self.test_mode == "val" else self.tasks_available() - self.earlier_tasks):
                self._append_task(self.capture.tasks[task])
        return self.dataset_of_trajectory()

    def release(self, task: int) -> None:
        """Grow the datasets by the tasks up to `task`, then release it as the batch mode does."""
        if distributed.is_distributed():
            self._cut_as_main_did(task)
        while self.num_tasks <= task:
            self._append_task(self.capture.tasks[self.num_tasks - self.earlier_tasks])
        self.train_dataset = self.create_train_dataset()
        self.eval_dataset = self.create_eval_dataset()
        self.setup_eval()
        super().release(task)
        self.train_ray_generator = RayGenerator(self.train_dataset.cameras.to(self.device))
        self._idle_reported = False

    def _cut_as_main_did(self, task: int) -> None:
        """Rank 0 found `task` complete: read the capture until it is here too, and cut it where rank 0 did (the
        frames reach every process in the same order, but not at the same time, and "Next task now" cuts early)."""
        main = distributed.is_main()
        task -= self.earlier_tasks  # the capture's own numbering
        frames = distributed.decided_by_main(len(self.capture.tasks[task]) if main else 0, self.device)
        if not main:
            self.capture.wait_until(lambda: self.capture.frames_from(task) >= frames)
            self.capture.cut_task(task, frames)

    def resume_at(self, task: int) -> None:
        if self.test_mode == "val" and task > self.earlier_tasks:
            raise ContinualConfigError(
                f"continual-ngp-stream cannot resume training from a checkpoint after task {self.earlier_tasks + 1}"
            )
        super().resume_at(task)

    def get_training_callbacks(self, attributes: TrainingCallbackAttributes) -> List[TrainingCallback]:
        # the pipeline gathers these before its own, so new frames are read before its budget check
        location = TrainingCallbackLocation.AFTER_TRAIN_ITERATION
        return [TrainingCallback([location], self._poll_capture)]

    def _poll_capture(self, step: int) -> None:
        """Tell the capture folder which task trains once it has trained an iteration; read new frames every
        --poll-seconds."""
        if self._announced != self.released_task and distributed.is_main():
            announce_training(self.capture.config.data, self.released_task)
            self._announced = self.released_task
        if time.monotonic() - self._last_poll >= self.capture.config.poll_seconds:
            self.capture.poll()
            self._last_poll = time.monotonic()

    def await_next_task(self, requested: bool, train_lock: Lock) -> bool:
        """Whether the next task (or the capture's end) is there; "Next task now" closes the task being captured.

        With the budget spent and no next task: with --idle wait, wait for it here (the viewer stays live); with
        --idle refine, say so once and let the released tasks train on.
        """
        if requested and not self._next_task_ready():
            self.capture.close_task()
        if self._next_task_ready() or self.capture_finished:
            return True
        if self.config.idle == "wait":
            CONSOLE.log(
                f"Task {self.released_task + 1}: budget spent, waiting for frames in {self.capture.config.data}"
            )
            with released(train_lock):  # the viewer renders under the train lock
                self.capture.wait_until(lambda: self._next_task_ready() or self.capture_finished)
            self._last_poll = time.monotonic()
            return self._next_task_ready() or self.capture_finished  # not when Ctrl-C ended the wait
        if not self._idle_reported:
            CONSOLE.log(f"Task {self.released_task + 1}: budget spent, refining until the next task's frames arrive")
            self._idle_reported = True
        return False

    def waiting_text(self) -> str:
        doing = "refining" if self.config.idle == "refine" else "waiting"
        return f"budget spent, {doing} until the next task arrives ({len(self.capture.collecting)} frames so far)"

    def schedule(self) -> Dict[str, int]:
        # the capture folder, not options, decides the tasks and their frames
        return {"test_interval": self.config.test_interval}
