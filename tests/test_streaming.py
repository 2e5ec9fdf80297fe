"""Streaming ingestion: a capture folder written while continual-ngp-stream trains on it."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import List, Optional

import numpy as np
import pytest
from helpers import RUN_TIMEOUT, demo_parser, replayed, stream_config
from nerfstudio.engine.callbacks import TrainingCallback, TrainingCallbackLocation

from continual_nerf.core.continual_pipeline import ContinualPipeline
from continual_nerf.dataparsers.capture_folder import TRAINING_FILE, CaptureWatcher, announce_training, trained_task
from continual_nerf.dataparsers.stream_dataparser import StreamDataParserConfig
from continual_nerf.errors import ContinualConfigError, ContinualNerfError, DatasetError
from continual_nerf.streaming.replay_capture import ReplayCaptureConfig, frame_json, replay, write_frame, write_marker
from continual_nerf.streaming.streaming_datamanager import StreamingDataManagerConfig

NUM_FRAMES = 20
BUDGET = 3
"""Iterations per task."""
FRAMES_PER_TASK = 6
MARKER_AFTER = 14
"""A `.task` marker after frame 14 closes the third task early."""
EXPECTED_TASKS = [range(0, 6), range(6, 12), range(12, 15), range(15, 20)]
HALF_WRITTEN_JSON = 3
"""Written in place, not renamed: the reader first sees a truncated JSON."""
TRUNCATED_IMAGE = 8
"""Its JSON is renamed into place before the image is complete."""


def demo_frames(num_frames: int = NUM_FRAMES):
    """The demo room's images and cameras, the source every capture in these tests replays."""
    config = demo_parser(num_frames=num_frames)
    return config.setup().get_dataparser_outputs(split="train")


def frame_name(index: int) -> str:
    return f"{index:06d}.json"


class CaptureWriter(threading.Thread):
    """Writes the demo frames into `folder`, misbehaving on purpose on some of them.

    The first frame of every later task waits until the training run is `ahead` iterations into the task before
    it, so that the run has spent its budget and is refining or waiting when the frames arrive.
    """

    def __init__(self, folder: Path, ahead: int) -> None:
        super().__init__(daemon=True)
        self.folder = folder
        self.ahead = ahead
        self.source = demo_frames()
        self.pipeline: Optional[ContinualPipeline] = None
        """Set once training is set up (set-up itself waits for the first task)."""
        self.error: Optional[BaseException] = None

    def run(self) -> None:
        try:
            self._write_all()
        except BaseException as error:  # surfaced by the test, not lost in the thread
            self.error = error

    def _write_all(self) -> None:
        (self.folder / "images").mkdir(parents=True)
        (self.folder / "000001.json.tmp").write_text("{")  # a temporary name that is never renamed
        (self.folder / ".000002.json").write_text("{")  # nor is a hidden file read
        starts = {task.start: number for number, task in enumerate(EXPECTED_TASKS)}
        for index in range(NUM_FRAMES):
            if index in starts and starts[index] > 0:
                self._wait_for_training_in_task(starts[index] - 1)
            image, frame = Path(self.source.image_filenames[index]), frame_json(self.source.cameras, index)
            if index == HALF_WRITTEN_JSON:
                self._half_written_json(index, image, frame)
            elif index == TRUNCATED_IMAGE:
                self._truncated_image(index, image, frame)
            else:
                write_frame(self.folder, index, image, frame)
            if index == MARKER_AFTER:
                write_marker(self.folder, index, "task")
        write_marker(self.folder, NUM_FRAMES - 1, "end")

    def _wait_for_training_in_task(self, task: int) -> None:
        deadline = time.monotonic() + RUN_TIMEOUT  # a hang, not a slow machine
        while not (
            self.pipeline is not None
            and self.pipeline.task.current == task
            and self.pipeline.budget.iterations_done >= self.ahead
        ):
            assert time.monotonic() < deadline, f"training never got {self.ahead} iterations into task {task + 1}"
            time.sleep(0.02)

    def _half_written_json(self, index: int, image: Path, frame: dict) -> None:
        shutil.copyfile(image, self.folder / "images" / f"{index:06d}.png")
        text = json.dumps({"file_path": f"images/{index:06d}.png", **frame})
        target = self.folder / frame_name(index)
        target.write_text(text[: len(text) // 2])
        time.sleep(0.3)
        target.write_text(text)

    def _truncated_image(self, index: int, image: Path, frame: dict) -> None:
        content = image.read_bytes()
        target = self.folder / "images" / f"{index:06d}.png"
        target.write_bytes(content[: len(content) // 2])
        (self.folder / frame_name(index)).write_text(json.dumps({"file_path": f"images/{target.name}", **frame}))
        time.sleep(0.3)
        target.write_bytes(content)


def frames_of_tasks(datamanager) -> List[List[str]]:
    """Per released task, the JSON names of its training and test frames, in capture order."""
    split = datamanager.task_split
    return [
        [datamanager.frames[i].name for i in sorted(np.concatenate([train, test]).tolist())]
        for train, test in zip(split.train_frames, split.test_frames)
    ]


@pytest.mark.slow
@pytest.mark.parametrize("idle", ["refine", "wait"])
def test_tasks_open_in_order_as_frames_arrive_and_every_frame_is_used_once(tmp_path, idle):
    capture = tmp_path / "capture"
    # refining trains on past the budget until the next frames come; waiting stops at the budget
    writer = CaptureWriter(capture, ahead=2 * BUDGET if idle == "refine" else BUDGET)
    config = stream_config(tmp_path / "outputs", capture, idle, FRAMES_PER_TASK, BUDGET)
    config.save_config()
    writer.start()
    trainer = config.setup(local_rank=0, world_size=1)
    trainer.setup()
    writer.pipeline = trainer.pipeline
    trainer.train()
    writer.join(timeout=30)
    assert writer.error is None, writer.error

    datamanager = trainer.pipeline.datamanager
    assert frames_of_tasks(datamanager) == [[frame_name(i) for i in task] for task in EXPECTED_TASKS]
    used = [name for task in frames_of_tasks(datamanager) for name in task]
    assert used == [frame_name(i) for i in range(NUM_FRAMES)], "no frame lost, none used twice, capture order kept"
    train_files = set(datamanager.train_dataset.image_filenames)
    assert not train_files & set(datamanager.eval_dataset.image_filenames), "held-out frames are never trained on"

    accuracy = trainer.pipeline.accuracy
    assert [len(row) for row in accuracy.psnr] == [1, 2, 3, 4] and accuracy.finished
    assert trainer.step == accuracy.steps[-1], "the run ends at the step the capture's last task ended"
    checkpoints = sorted(path.name for path in trainer.checkpoint_dir.iterdir())
    assert checkpoints == [f"step-{step:09d}.ckpt" for step in accuracy.steps], "one per task end, none past it"
    iterations_per_task = np.diff([-1] + accuracy.steps).tolist()
    if idle == "wait":
        assert iterations_per_task == [BUDGET] * 4, "waiting trains exactly the budget on each task"
    else:
        assert min(iterations_per_task[:3]) >= 2 * BUDGET, "refining went on while the next frames were awaited"


@pytest.mark.slow
def test_replay_command_writes_the_protocol_and_the_stream_reads_back_the_same_cameras(tmp_path):
    script = Path(sys.executable).with_name("continual-nerf-replay-capture")
    assert subprocess.run([script, "--help"], check=False, capture_output=True).returncode == 0, (
        "installed by `pip install -e .`"
    )
    capture = tmp_path / "capture"
    replay(ReplayCaptureConfig(output=capture, fps=0, task_every=5, dataparser=demo_parser(num_frames=12)))
    assert sorted(p.name for p in capture.iterdir() if p.suffix != ".json") == [
        "000004.task",
        "000009.task",
        "000011.end",
        "images",
    ]
    parser = StreamDataParserConfig(data=capture, frames_per_task=0, normalization="none").setup()
    outputs = parser.get_dataparser_outputs(split="train")
    assert [len(task) for task in parser.capture.tasks] == [5, 5, 2] and parser.capture.ended
    source = demo_frames(num_frames=12).cameras
    assert np.allclose(outputs.cameras.camera_to_worlds, source.camera_to_worlds, atol=1e-6)
    assert np.allclose(outputs.cameras.fx, source.fx) and (outputs.cameras.width == source.width).all()
    with pytest.raises(DatasetError, match="already holds a capture"):
        replay(ReplayCaptureConfig(output=capture, fps=0, dataparser=demo_parser(num_frames=12)))


def test_watcher_keeps_capture_order_behind_an_unreadable_entry_and_skips_it_only_after_the_timeout(tmp_path):
    capture = replayed(tmp_path)
    image = capture / "images" / "000002.png"
    content = image.read_bytes()
    image.write_bytes(content[:40])
    watcher = CaptureWatcher(capture, unreadable_timeout=0.3)
    assert [entry.name for entry in watcher.new_entries()] == ["000000.json", "000001.json"]
    assert watcher.new_entries() == [], "000003 waits behind the truncated 000002"
    time.sleep(0.35)
    assert [entry.name for entry in watcher.new_entries()] == ["000003.json", "000004.json", "000005.json"]
    image.write_bytes(content)
    assert watcher.new_entries() == [], "a skipped entry is never read again"


def test_frames_with_bad_content_are_skipped_with_one_warning_line_each(tmp_path, capsys):
    capture = replayed(tmp_path, num_frames=4)
    capsys.readouterr()
    (capture / "000001.json").write_text(json.dumps({"transform_matrix": np.eye(4).tolist()}))
    frame = json.loads((capture / "000002.json").read_text())
    (capture / "000002.json").write_text(json.dumps({**frame, "w": frame["w"] * 2}))
    entries = CaptureWatcher(capture, unreadable_timeout=0).new_entries()
    assert [entry.name for entry in entries] == ["000000.json", "000003.json"]
    lines = capsys.readouterr().out.splitlines()
    assert lines == [
        f"{capture / '000001.json'}: a frame needs a `file_path` string (nerfstudio's transforms.json frame format); "
        "frame skipped",
        f"{capture / '000002.json'}: image {(capture / 'images' / '000002.png').resolve()} is 24x18 pixels, "
        "the frame says w=48 h=18; frame skipped",
    ]


def test_the_pose_transform_is_fixed_by_the_first_task_and_later_frames_do_not_move_it(tmp_path):
    capture = replayed(tmp_path, num_frames=12)
    parser = StreamDataParserConfig(data=capture, frames_per_task=4).setup()
    first = parser.get_dataparser_outputs(split="train")
    assert len(parser.capture.tasks) == 3
    centres = first.cameras.camera_to_worlds[:4, :, 3]
    assert np.isclose(float(centres.abs().max()), 1.0), "the first task's cameras fill the unit box"
    assert np.allclose(
        parser.capture.outputs(parser.capture.tasks[0]).cameras.camera_to_worlds, first.cameras.camera_to_worlds[:4]
    )
    transforms = tmp_path / "dataparser_transforms.json"
    first.save_dataparser_transform(transforms)
    from_file = StreamDataParserConfig(data=capture, frames_per_task=4, normalization="file", transform_file=transforms)
    again = from_file.setup().get_dataparser_outputs(split="train")
    assert np.allclose(again.cameras.camera_to_worlds, first.cameras.camera_to_worlds, atol=1e-5)


def test_bad_stream_options_are_one_line_errors(tmp_path):
    with pytest.raises(ContinualConfigError, match="--frames-per-task must be 0 .* got 1"):
        StreamDataParserConfig(data=tmp_path, frames_per_task=1).setup()
    with pytest.raises(ContinualConfigError, match="--normalization file needs --transform-file"):
        StreamDataParserConfig(data=tmp_path, normalization="file").setup()
    with pytest.raises(ContinualConfigError, match="use the continual-stream dataparser, not ContinualDemoDataParser"):
        StreamingDataManagerConfig(dataparser=demo_parser()).validate()


def test_a_capture_that_ends_before_its_first_task_is_an_error(tmp_path):
    capture = tmp_path / "capture"
    replay(ReplayCaptureConfig(output=capture, fps=0, dataparser=demo_parser(num_frames=1)))
    with pytest.raises(DatasetError, match="the capture ended before its first task was complete"):
        StreamDataParserConfig(data=capture).setup().get_dataparser_outputs(split="train")


def test_next_task_now_closes_the_task_being_captured(tmp_path):
    capture = tmp_path / "capture"
    replay(
        ReplayCaptureConfig(output=capture, fps=0, task_every=3, end_marker=False, dataparser=demo_parser(num_frames=7))
    )
    parser = StreamDataParserConfig(data=capture, frames_per_task=0, normalization="none")
    config = StreamingDataManagerConfig(dataparser=parser, iterations_per_task=10**6, replay=False, test_interval=2)
    datamanager = config.setup(device="cpu", test_mode="val")
    lock = threading.Lock()
    assert datamanager.tasks_available() == 2 and len(datamanager.capture.collecting) == 1
    assert datamanager.await_next_task(requested=False, train_lock=lock), "task 2 has arrived"
    datamanager.release(1)
    assert not datamanager.capture_finished, "the task being captured will follow"
    assert not datamanager.await_next_task(requested=True, train_lock=lock), "one frame is too few to close a task"
    write_frame(capture, 7, Path(demo_frames(num_frames=8).image_filenames[7]), frame_json(demo_frames(8).cameras, 7))
    datamanager.capture.poll()
    assert datamanager.await_next_task(requested=True, train_lock=lock), "Next task now closes frames 6 and 7"
    assert datamanager.tasks_available() == 3
    datamanager.release(2)
    assert [len(task) for task in frames_of_tasks(datamanager)] == [3, 3, 2]


@pytest.mark.slow
def test_waiting_for_training_streams_each_task_in_while_the_task_before_it_trains(tmp_path):
    capture = tmp_path / "capture"
    writer = ReplayCaptureConfig(
        output=capture, fps=0, task_every=4, wait_for_training=True, dataparser=demo_parser(num_frames=12)
    )
    thread = threading.Thread(target=replay, args=[writer], daemon=True)
    thread.start()
    config = stream_config(tmp_path / "outputs", capture, "wait", frames_per_task=4, iterations_per_task=3)
    config.save_config()
    trainer = config.setup(local_rank=0, world_size=1)
    trainer.setup()
    written_when_training_started: List[int] = []

    def count_frames(step: int) -> None:
        if step == 0:
            written_when_training_started.append(len(list(capture.glob("*.json"))))

    trainer.callbacks.append(TrainingCallback([TrainingCallbackLocation.BEFORE_TRAIN_ITERATION], count_frames))
    trainer.train()
    thread.join(timeout=RUN_TIMEOUT)
    assert written_when_training_started == [4], "as fast as it may write, the writer waited: only task 1 was there"
    assert [len(row) for row in trainer.pipeline.accuracy.psnr] == [1, 2, 3], "tasks 2 and 3 arrived while it trained"
    assert not thread.is_alive()


def test_waiting_for_training_needs_tasks_of_known_frames(tmp_path):
    with pytest.raises(ContinualNerfError, match="--wait-for-training needs --task-every"):
        replay(ReplayCaptureConfig(output=tmp_path, wait_for_training=True, dataparser=demo_parser(num_frames=4)))


def test_the_training_run_s_answer_is_its_own_file_written_without_following_a_link(tmp_path):
    (tmp_path / "elsewhere.txt").write_text("kept")
    (tmp_path / TRAINING_FILE).symlink_to(tmp_path / "elsewhere.txt")
    announce_training(tmp_path, 2)
    assert trained_task(tmp_path) == 2 and not (tmp_path / TRAINING_FILE).is_symlink()
    assert (tmp_path / "elsewhere.txt").read_text() == "kept"
    assert CaptureWatcher(tmp_path, unreadable_timeout=0).new_entries() == [], "never read as an entry"
