"""The split of a trajectory into contiguous tasks with held-out test frames."""

import re

import numpy as np
import pytest

from continual_nerf.core.continual_datamanager import ContinualDataManagerConfig
from continual_nerf.core.task_split import split_into_tasks
from continual_nerf.errors import ContinualConfigError


@pytest.mark.parametrize("num_frames,num_tasks,interval", [(120, 10, 8), (37, 5, 8), (10, 5, 2), (9, 1, 3)])
def test_split_is_contiguous_ordered_complete_and_holds_out_test_frames(num_frames, num_tasks, interval):
    split = split_into_tasks(num_frames, num_tasks, interval)
    assert split.num_tasks == num_tasks
    everything = np.sort(np.concatenate([split.all_train_frames(), split.all_test_frames()]))
    assert np.array_equal(everything, np.arange(num_frames)), "every frame is in exactly one set"
    assert not set(split.all_train_frames()) & set(split.all_test_frames()), "test frames are never trained on"
    assert np.all(np.diff(split.all_train_frames()) > 0), "training frames stay in capture order"
    spans = [np.concatenate([tr, te]) for tr, te in zip(split.train_frames, split.test_frames)]
    for task, span in enumerate(spans):
        assert np.array_equal(np.sort(span), np.arange(span.min(), span.max() + 1)), "a task is a contiguous span"
        assert len(split.test_frames[task]) >= 1 and len(split.train_frames[task]) >= 1
        if task:
            assert span.min() == spans[task - 1].max() + 1, "tasks follow each other in capture order"
    sizes = [len(t) for t in split.train_frames]
    assert max(sizes) - min(sizes) <= 2, "tasks are of near-equal size"


def test_every_interval_th_frame_of_a_task_is_held_out():
    split = split_into_tasks(40, 2, 8)
    assert split.test_frames[0].tolist() == [0, 8, 16]
    assert split.test_frames[1].tolist() == [20, 28, 36]
    assert split.test_task_of_frame().tolist() == [0, 0, 0, 1, 1, 1]


@pytest.mark.parametrize(
    "num_frames,num_tasks,interval,message",
    [
        (
            10,
            6,
            8,
            "the capture: 10 frames are too few for --pipeline.datamanager.num-tasks 6: a task needs 2 frames, "
            "one to train on and one to test on; use at most 5 tasks",
        ),
        (
            1,
            1,
            8,
            "the capture: 1 frame is too few for --pipeline.datamanager.num-tasks 1: a task needs 2 frames, one "
            "to train on and one to test on; too few for any task",
        ),
        (0, 2, 8, "the dataset has no frames"),
    ],
)
def test_bad_splits_are_one_line_errors(num_frames, num_tasks, interval, message):
    with pytest.raises(ContinualConfigError, match=re.escape(message)) as error:
        split_into_tasks(num_frames, num_tasks, interval)
    assert "\n" not in str(error.value)


@pytest.mark.parametrize(
    "options, message",
    [
        ({"num_tasks": 0}, "--pipeline.datamanager.num-tasks must be at least 1, got 0"),
        ({"test_interval": 1}, "--pipeline.datamanager.test-interval must be at least 2"),
        ({"iterations_per_task": 0}, "--pipeline.datamanager.iterations-per-task must be at least 1, got 0"),
        ({"seconds_per_task": -1.0}, "--pipeline.datamanager.seconds-per-task must be positive, got -1.0"),
        ({"train_num_rays_per_batch": 0}, "--pipeline.datamanager.train-num-rays-per-batch must be at least 1"),
    ],
)
def test_bad_task_options_are_one_line_errors_at_set_up(options, message):
    config = ContinualDataManagerConfig(**options)
    with pytest.raises(ContinualConfigError, match=message) as error:
        config.setup(device="cpu")
    assert "\n" not in str(error.value)


def test_cameras_of_one_instant_stay_in_one_task_and_are_held_out_together():
    # 3 cameras x 7 instants: 21 images, a task boundary by image count would cut instant 3
    time_group = np.repeat(np.arange(7), 3)
    split = split_into_tasks(21, 2, 3, time_group=time_group)
    for frames in (*split.train_frames, *split.test_frames):
        assert len(frames) % 3 == 0
    # instants 0-3 form task 1 (instants 0 and 3 held out), instants 4-6 task 2 (instant 4 held out)
    assert split.train_frames[0].tolist() == [3, 4, 5, 6, 7, 8]
    assert split.test_frames[0].tolist() == [0, 1, 2, 9, 10, 11]
    assert split.train_frames[1].tolist() == list(range(15, 21))
    assert split.test_frames[1].tolist() == [12, 13, 14]
