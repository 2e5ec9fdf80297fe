"""The task split: a capture trajectory cut into temporally contiguous tasks (paper, section 3)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np
from nerfstudio.data.dataparsers.base_dataparser import DataparserOutputs

from continual_nerf.errors import ContinualConfigError, plural
from continual_nerf.metadata_keys import HELD_OUT


@dataclass(frozen=True)
class TaskSplit:
    """Which frames of a trajectory (indices in capture order) each task trains and tests on."""

    train_frames: tuple[np.ndarray, ...]
    """Per task, the training frames, in capture order."""
    test_frames: tuple[np.ndarray, ...]
    """Per task, the held-out test frames inside the task's span."""

    @property
    def num_tasks(self) -> int:
        return len(self.train_frames)

    def train_task_of_frame(self) -> np.ndarray:
        """Task index of every training frame, in training-frame order."""
        return np.concatenate([np.full(len(f), t) for t, f in enumerate(self.train_frames)])

    def test_task_of_frame(self) -> np.ndarray:
        """Task index of every test frame, in test-frame order."""
        return np.concatenate([np.full(len(f), t) for t, f in enumerate(self.test_frames)])

    def all_train_frames(self) -> np.ndarray:
        return np.concatenate(self.train_frames)

    def all_test_frames(self) -> np.ndarray:
        return np.concatenate(self.test_frames)


def split_into_tasks(
    num_frames: int,
    num_tasks: int,
    test_interval: int,
    time_group: Optional[np.ndarray] = None,
    held_out: Optional[np.ndarray] = None,
    source: str = "the capture",
) -> TaskSplit:
    """Cut frames 0..num_frames-1 into num_tasks contiguous spans of near-equal length.

    Inside each span, every test_interval-th frame (counting from the span's first frame) is held
    out for testing, so every task has test frames and every test frame lies in its task's span.
    With `time_group` (frames captured at the same instant by several cameras share a value, in
    capture order), spans and held-out frames are counted in instants: a task holds every camera's
    images of its time span and a held-out instant is held out in every camera. With `held_out`
    (a flag per frame) the flagged frames are the test frames, and every task needs one. `source` names the capture
    in errors.
    """
    if num_frames < 1:
        raise ContinualConfigError("the dataset has no frames: nothing to split into tasks")
    groups = np.arange(num_frames) if time_group is None else np.unique(np.asarray(time_group), return_inverse=True)[1]
    spans = np.array_split(np.arange(groups.max() + 1), num_tasks)
    if min(len(span) for span in spans) < 2:
        raise ContinualConfigError(
            too_few_for_tasks(source, num_tasks, num_frames, None if time_group is None else int(groups.max()) + 1)
        )
    if held_out is None:
        tested = np.isin(groups, np.concatenate([span[::test_interval] for span in spans]))
    else:
        tested = np.asarray(held_out, dtype=bool)
    train, test = [], []
    for task, span in enumerate(spans):
        frames = np.nonzero(np.isin(groups, span))[0]
        if tested[frames].all() or not tested[frames].any():
            raise ContinualConfigError(
                f"--pipeline.datamanager.num-tasks {num_tasks}: task {task + 1} holds "
                f"{'only' if tested[frames].all() else 'none of the'} frames the capture names for testing "
                "(test_filenames); every task needs training and test frames: use fewer tasks"
            )
        train.append(frames[~tested[frames]])
        test.append(frames[tested[frames]])
    return TaskSplit(train_frames=tuple(train), test_frames=tuple(test))


def too_few_for_tasks(source: str, num_tasks: int, num_frames: int, instants: Optional[int]) -> str:
    """Why `num_frames` frames (taken at `instants` rig instants, if a rig took them) cannot form `num_tasks` tasks."""
    unit, count = ("frame", num_frames) if instants is None else ("rig instant", instants)
    held = plural(count, unit) + ("" if instants is None else f" ({plural(num_frames, 'image')})")
    most = count // 2
    advice = f"use at most {plural(most, 'task')}" if most else "too few for any task"
    return (
        f"{source}: {held} {'is' if count == 1 else 'are'} too few for --pipeline.datamanager.num-tasks {num_tasks}: "
        f"a task needs 2 {unit}s, one to train on and one to test on; {advice}"
    )


def split_capture(
    outputs: DataparserOutputs, num_tasks: int, test_interval: int, source: str = "the capture"
) -> TaskSplit:
    """`split_into_tasks` of a dataparser's frames, with the rig instants and test frames its metadata names;
    `source` names the capture in errors."""
    metadata = outputs.metadata
    return split_into_tasks(
        len(outputs.image_filenames),
        num_tasks,
        test_interval,
        time_group=metadata.get("time_group"),
        held_out=metadata.get(HELD_OUT),
        source=source,
    )


def nearest_train_frames(split: TaskSplit, instants: np.ndarray, cameras: np.ndarray) -> np.ndarray:
    """For every test frame (in test-frame order), the training frame (in training-frame order) of its task taken by
    its camera nearest to it in time (any camera's when its camera has no training frame in the task).

    `instants` and `cameras` give the capture instant and camera of every frame of the trajectory.
    """
    train_frames = split.all_train_frames()
    train_task = split.train_task_of_frame()
    nearest = []
    for test_frame, task in zip(split.all_test_frames(), split.test_task_of_frame()):
        candidates = np.nonzero(train_task == task)[0]
        same_camera = candidates[cameras[train_frames[candidates]] == cameras[test_frame]]
        if len(same_camera):
            candidates = same_camera
        distance = np.abs(instants[train_frames[candidates]] - instants[test_frame])
        nearest.append(candidates[np.argmin(distance)])
    return np.array(nearest, dtype=np.int64)
