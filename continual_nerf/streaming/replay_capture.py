"""continual-nerf-replay-capture: write a dataset into a capture folder frame by frame, as a live capture would.

A recorded drive or scan replayed this way lets `ns-train continual-ngp-stream` (and its viewer) be watched while
tasks stream in. Frames follow the continual-stream protocol (continual_nerf/dataparsers/capture_folder.py).
The poses written are the dataparser's, already fitted into its scene box: read them with `--normalization none`.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Dict, Literal

import numpy as np
import tyro
from nerfstudio.cameras.cameras import Cameras, CameraType
from nerfstudio.configs.dataparser_configs import AnnotatedDataParserUnion
from nerfstudio.utils.rich_utils import CONSOLE

from continual_nerf.dataparsers.capture_folder import ENTRY_RANK, TRAINING_FILE, trained_task
from continual_nerf.dataparsers.continual_demo_dataparser import ContinualDemoDataParserConfig
from continual_nerf.dataparsers.transforms_json import DISTORTION_KEYS
from continual_nerf.errors import ContinualNerfError, DatasetError
from continual_nerf.interrupts import EXIT_CODES

TRAINING_POLL_SECONDS = 0.2
"""How often --wait-for-training looks at what the training run trains."""


@dataclass
class ReplayCaptureConfig:
    """Replays a dataset's training frames, in order, into a capture folder at a given frame rate."""

    output: Path = Path("capture")
    """Capture folder to write into; it must not hold frames or markers yet."""
    fps: float = 2.0
    """Frames written per second (0: as fast as possible)."""
    task_every: int = 0
    """Write a `.task` marker after every this many frames (0: none; the reader's --frames-per-task cuts the tasks)."""
    end_marker: bool = True
    """Write the `.end` marker after the last frame, so the training run ends with the capture."""
    wait_for_training: bool = False
    """Write each task's frames (--task-every) only once the training run reading the folder trains the task before
    it: the tasks then stream in while it trains, as a live capture's would, however long its set-up takes."""
    dataparser: AnnotatedDataParserUnion = field(default_factory=ContinualDemoDataParserConfig)
    """Dataset to replay: any registered dataparser (the built-in demo room by default)."""


def frame_json(cameras: Cameras, index: int) -> Dict[str, Any]:
    """Camera `index` as one frame of nerfstudio's transforms.json, intrinsics included (no file_path yet)."""
    camera = cameras[index]
    if int(camera.camera_type) != CameraType.PERSPECTIVE.value:
        kind = CameraType(int(camera.camera_type)).name
        raise DatasetError(f"frame {index}: only perspective cameras can be replayed, got {kind}")
    camera_to_world = np.eye(4)
    camera_to_world[:3] = camera.camera_to_worlds.cpu().numpy()
    frame: Dict[str, Any] = {
        "transform_matrix": camera_to_world.tolist(),
        "fl_x": float(camera.fx),
        "fl_y": float(camera.fy),
        "cx": float(camera.cx),
        "cy": float(camera.cy),
        "w": int(camera.width),
        "h": int(camera.height),
    }
    if camera.distortion_params is not None and bool(camera.distortion_params.any()):
        frame.update(zip(DISTORTION_KEYS, camera.distortion_params.view(-1).tolist()))
    return frame


def write_frame(folder: Path, sequence: int, image: Path, frame: Dict[str, Any]) -> None:
    """One frame by the protocol: the image first, then its JSON under a temporary name, renamed into place."""
    name = f"{sequence:06d}"
    target = folder / "images" / f"{name}{image.suffix.lower()}"
    target.parent.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(image, target)
    temporary = folder / f"{name}.json.tmp"
    temporary.write_text(json.dumps({"file_path": f"images/{target.name}", **frame}))
    os.replace(temporary, folder / f"{name}.json")


def write_marker(folder: Path, sequence: int, kind: Literal["task", "end"]) -> None:
    """A marker after frame `sequence`: `.task` closes the task there, `.end` ends the capture."""
    (folder / f"{sequence:06d}.{kind}").touch()


def check_empty(folder: Path) -> None:
    if folder.is_dir() and any(os.path.splitext(name)[1] in ENTRY_RANK for name in os.listdir(folder)):
        raise DatasetError(f"{folder}: already holds a capture; choose another --output or empty it")


def wait_for_training(folder: Path, task: int) -> None:
    """Wait until the training run on `folder` trains task `task` (0-based) or a later one."""
    CONSOLE.log(f"Task {task + 2} waits until a training run on {folder} (continual-ngp-stream) trains task {task + 1}")
    while True:
        trained = trained_task(folder)
        if trained is not None and trained >= task:
            return
        time.sleep(TRAINING_POLL_SECONDS)


def replay(config: ReplayCaptureConfig) -> None:
    if config.fps < 0 or config.task_every < 0:
        raise ContinualNerfError(
            f"--fps and --task-every must be 0 or positive, got {config.fps:g} and {config.task_every}"
        )
    if config.wait_for_training and not config.task_every:
        raise ContinualNerfError("--wait-for-training needs --task-every: the frames of a task")
    check_empty(config.output)
    (config.output / TRAINING_FILE).unlink(missing_ok=True)  # an earlier run's answer is not this run's
    outputs = config.dataparser.setup().get_dataparser_outputs(split="train")
    count = len(outputs.image_filenames)
    pace = f"at {config.fps:g} frames/s" if config.fps else "as fast as possible"
    CONSOLE.log(f"Replaying {count} frames into {config.output} {pace}")
    started = next_write = time.monotonic()
    for index, image in enumerate(outputs.image_filenames):
        if config.wait_for_training and index and index % config.task_every == 0:
            wait_for_training(config.output, index // config.task_every - 1)
            next_write = max(next_write, time.monotonic())  # the pace starts again from here
        time.sleep(max(0.0, next_write - time.monotonic()))
        next_write += 1 / config.fps if config.fps else 0.0
        write_frame(config.output, index, Path(image), frame_json(outputs.cameras, index))
        if config.task_every and (index + 1) % config.task_every == 0 and index + 1 < count:
            write_marker(config.output, index, "task")
    if config.end_marker:
        write_marker(config.output, count - 1, "end")
    CONSOLE.log(f"Wrote {count} frames to {config.output} in {time.monotonic() - started:.1f} s")


def entrypoint() -> None:
    """Console script `continual-nerf-replay-capture`."""
    config = tyro.cli(ReplayCaptureConfig, description=__doc__)
    try:
        replay(config)
    except ContinualNerfError as error:
        raise SystemExit(f"continual-nerf-replay-capture: error: {error}") from None
    except KeyboardInterrupt:
        raise SystemExit(EXIT_CODES[signal.SIGINT]) from None  # Ctrl-C stops the replay: the frames written stay


if __name__ == "__main__":
    entrypoint()
