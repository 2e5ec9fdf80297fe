"""Reading a capture folder that another process is still writing: its protocol, and its frames cut into tasks.

The capture protocol (what `continual-nerf-replay-capture` writes, and what a live capture process must write):

- A frame is an image file anywhere inside the folder plus `<sequence>.json` in the folder itself: one frame of
  nerfstudio's transforms.json, i.e. `file_path` (relative to the folder), `transform_matrix` (camera-to-world,
  OpenGL convention) and the intrinsics `fl_x`, `fl_y`, `cx`, `cy`, `w`, `h` (optional `camera_model` and
  distortion `k1` ... `p2`).
- Write the image first, then the JSON under a temporary name (`<sequence>.json.tmp`) and rename it to
  `<sequence>.json`: a frame exists once its JSON has its final name.
- An empty `<sequence>.task` closes the current task after the frames before it; `<sequence>.end` ends the capture.
- Sequence numbers increase in capture order (`000017.json`); a marker may reuse the number of the frame it follows.

Names that start with a dot or do not end in .json, .task or .end are ignored. A JSON that does not parse, or whose
image does not decode yet, is retried on the next poll and the entries after it wait, so capture order is kept.

The training run answers in one file of its own, `.training`: the number (0-based) of the task it trains, rewritten
whenever a task starts training. A capture process may pace itself by it (`continual-nerf-replay-capture
--wait-for-training` writes a task's frames once the task before it trains); a folder the run cannot write into
simply gets no answer.

The folder is another process's output and is read as untrusted input: only regular files whose real path lies
inside the folder are opened (no absolute `file_path`, no `..` out of it, no symlink leading elsewhere, no FIFO), and
a frame that can never be used (such a path, an image too large to decode, JSON over 1 MiB or nested too deeply,
intrinsics that are not finite, positive and inside the image, an image of another size than the frame says) is
skipped with one warning line naming it; training goes on.
"""

from __future__ import annotations

import contextlib
import json
import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Callable, Dict, List, Literal, Optional, Set, Tuple, Union

import numpy as np
import torch
from nerfstudio.cameras.cameras import Cameras, CameraType
from nerfstudio.data.dataparsers.base_dataparser import DataparserOutputs
from nerfstudio.data.scene_box import SceneBox
from nerfstudio.utils.rich_utils import CONSOLE
from PIL import Image

from continual_nerf.dataparsers.capture import CaptureOutputs, fit_into_box, fitted_poses
from continual_nerf.dataparsers.transforms_json import natural_key, parse_intrinsics, transforms_pose
from continual_nerf.errors import DatasetError, first_line
from continual_nerf.interrupts import INTERRUPTS
from continual_nerf.untrusted_files import open_inside, real_path_inside

if TYPE_CHECKING:
    from continual_nerf.dataparsers.stream_dataparser import StreamDataParserConfig

MAX_FRAME_JSON_BYTES = 1 << 20
"""A frame JSON holds a few hundred bytes; a larger file is not read into memory."""

TRAINING_FILE = ".training"
"""The file in the capture folder where the training run says which task it trains (a dot name: never an entry)."""

ENTRY_RANK = {".json": 0, ".task": 1, ".end": 2}
"""Entry kinds by file suffix; at equal sequence numbers a frame comes before the marker that follows it."""


@dataclass(frozen=True)
class StreamFrame:
    """One frame of the capture, as its JSON describes it."""

    name: str
    """File name of the frame's JSON in the capture folder."""
    image: Path
    """The frame's image file."""
    camera_to_world: np.ndarray
    """(4, 4) float64, OpenGL convention, in the capture's own world units."""
    intrinsics: np.ndarray
    """fx, fy, cx, cy, width, height."""
    distortion: np.ndarray
    """nerfstudio distortion parameters [k1, k2, k3, k4, p1, p2]."""


@dataclass(frozen=True)
class StreamMarker:
    """A `.task` or `.end` marker file."""

    name: str
    """File name of the marker in the capture folder."""
    kind: Literal["task", "end"]
    """task: the frames before it form a task; end: the capture is over."""


class NotReady(Exception):
    """An entry that is still being written: read again on the next poll."""


def announce_training(folder: Path, task: int) -> None:
    """Say in `folder`'s TRAINING_FILE that task `task` trains now; the folder is another process's, so no existing
    name is written through (a symlink there is replaced, not followed), and a folder that refuses it is left as is."""
    temporary = folder / f"{TRAINING_FILE}.{os.getpid()}.tmp"
    try:
        descriptor = os.open(temporary, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW, 0o644)
        with os.fdopen(descriptor, "w") as file:
            file.write(f"{task}\n")
        os.replace(temporary, folder / TRAINING_FILE)
    except OSError:
        with contextlib.suppress(OSError):
            temporary.unlink()


def trained_task(folder: Path) -> Optional[int]:
    """The task a training run on `folder` says it trains, if it said one."""
    try:
        return int((folder / TRAINING_FILE).read_text())
    except (OSError, ValueError):
        return None


def check_image(image: Path, folder: Path, intrinsics: np.ndarray) -> None:
    """Decode `image` (a regular file inside `folder`) completely; a missing or truncated file is not ready, a wrong
    size or a decompression bomb is an error."""
    width, height = int(intrinsics[4]), int(intrinsics[5])  # whole numbers: parse_intrinsics checked them
    try:
        with open_inside(image, folder) as file, Image.open(file) as picture:
            if picture.size != (width, height):  # checked before decoding: the header says what the pixels hold
                raise DatasetError(
                    f"image {image} is {picture.size[0]}x{picture.size[1]} pixels, the frame says w={width} h={height}"
                )
            picture.load()
    except DatasetError:  # a ValueError, which PIL raises for a file cut short too
        raise
    except Image.DecompressionBombError as error:
        raise DatasetError(f"image {image} is too large to decode ({first_line(error)})") from None
    except FileNotFoundError:
        raise NotReady(f"{image} does not exist yet") from None
    except (OSError, SyntaxError, ValueError) as error:  # PIL's errors for a file cut short
        raise NotReady(f"{image} does not decode yet ({first_line(error)})") from None


def read_json(path: Path, folder: Path) -> object:
    """The content of a frame JSON: a regular file inside `folder`; half-written JSON is not ready yet."""
    try:
        with open_inside(path, folder) as file:
            content = file.read(MAX_FRAME_JSON_BYTES + 1)
        if len(content) > MAX_FRAME_JSON_BYTES:
            raise DatasetError(f"{path}: larger than {MAX_FRAME_JSON_BYTES >> 20} MiB, not a frame JSON; not read")
        return json.loads(content.decode())
    except DatasetError:  # a ValueError, as json's errors are
        raise
    except FileNotFoundError:  # replaced or removed by the writer since the folder was listed
        raise NotReady(f"{path} is gone") from None
    except (json.JSONDecodeError, UnicodeDecodeError, OSError) as error:
        raise NotReady(f"not valid JSON yet ({first_line(error)})") from None
    except (RecursionError, ValueError) as error:  # nested too deeply, numbers too long: no complete file parses
        raise DatasetError(f"{path}: not a usable frame JSON ({first_line(error)})") from None


def read_frame(path: Path, folder: Path) -> StreamFrame:
    """A frame JSON and a check that its image, a regular file inside `folder`, decodes."""
    frame = read_json(path, folder)
    if not isinstance(frame, dict) or not isinstance(frame.get("file_path"), str):
        raise DatasetError(f"{path}: a frame needs a `file_path` string (nerfstudio's transforms.json frame format)")
    source = str(path)
    intrinsics, distortion, kind = parse_intrinsics(frame, source)
    if kind != CameraType.PERSPECTIVE:  # the stream's datasets grow task by task as perspective cameras
        model = frame.get("camera_model")
        raise DatasetError(f"{source}: camera model {model} is not supported here (a capture folder: perspective only)")
    camera_to_world = transforms_pose(frame.get("transform_matrix"), source)
    try:
        image = real_path_inside(folder / frame["file_path"], folder)  # the file checked is the file trained on
        check_image(image, folder, intrinsics)
    except DatasetError as error:
        raise DatasetError(f"{source}: {error}") from None
    return StreamFrame(path.name, image, camera_to_world, intrinsics, distortion)


def read_entry(path: Path, folder: Path) -> Union[StreamFrame, StreamMarker]:
    if path.suffix == ".json":
        return read_frame(path, folder)
    return StreamMarker(path.name, "task" if path.suffix == ".task" else "end")


def warn(message: str) -> None:
    """One warning line; markup off, since names and messages come from the capture folder."""
    CONSOLE.print(message, style="bold yellow", markup=False, soft_wrap=True)


def entry_key(name: str) -> Tuple[list, int]:
    stem, suffix = os.path.splitext(name)
    return natural_key(stem), ENTRY_RANK[suffix]


class CaptureWatcher:
    """Reads a capture folder's entries in sequence order, each once, and each only when completely written."""

    def __init__(self, folder: Path, unreadable_timeout: float) -> None:
        self.folder = folder
        self.unreadable_timeout = unreadable_timeout
        self.done: Set[str] = set()
        """Entries already read or skipped."""
        self.failing_since: Dict[str, float] = {}
        """When each entry that is not ready yet was first tried."""

    def _unread_names(self) -> List[str]:
        try:
            names = os.listdir(self.folder)
        except FileNotFoundError:  # the capture process has not created it yet
            return []
        entries = [n for n in names if not n.startswith(".") and os.path.splitext(n)[1] in ENTRY_RANK]
        return sorted((n for n in entries if n not in self.done), key=entry_key)

    def _give_up(self, name: str, reason: NotReady) -> bool:
        """Whether an entry has been unreadable for longer than the timeout (then it is skipped, with a warning)."""
        first_try = self.failing_since.setdefault(name, time.monotonic())
        if not (self.unreadable_timeout and time.monotonic() - first_try >= self.unreadable_timeout):
            return False
        warn(f"{self.folder / name}: still unreadable after {self.unreadable_timeout:g} s ({reason}); skipped")
        return True

    def new_entries(self) -> List[Union[StreamFrame, StreamMarker]]:
        """Entries completed since the last call, in sequence order, up to the first one still being written."""
        ready = []
        for name in self._unread_names():
            try:
                ready.append(read_entry(self.folder / name, self.folder))
            except NotReady as reason:
                if not self._give_up(name, reason):
                    break  # later entries wait, so the capture order is kept
            except DatasetError as error:  # the capture is another process's input: a bad frame never stops training
                warn(f"{error}; frame skipped")
            self.done.add(name)
            self.failing_since.pop(name, None)
        return ready


def read_transform_file(path: Path) -> Tuple[np.ndarray, float]:
    """The `transform` and `scale` of a nerfstudio dataparser_transforms.json."""
    try:
        content = json.loads(path.read_text())
        transform = np.array(content["transform"], dtype=np.float64)[:3]
        scale = float(content["scale"])
    except FileNotFoundError:
        raise DatasetError(f"{path}: transform file does not exist") from None
    except (json.JSONDecodeError, UnicodeDecodeError, KeyError, TypeError, ValueError) as error:
        raise DatasetError(f"{path}: not a dataparser_transforms.json with `transform` and `scale` ({error})") from None
    if transform.shape != (3, 4) or not np.isfinite(transform).all() or not scale > 0:
        raise DatasetError(f"{path}: `transform` must be a finite 3x4 (or 4x4) matrix and `scale` positive")
    return transform, scale


class CaptureTasks:
    """Cuts the frames arriving in a capture folder into tasks and maps their poses with one fixed transform.

    `poll` collects what arrived; `tasks` are the complete tasks, `collecting` the frames of the task still being
    captured, `ended` says the capture is over. The streaming datamanager releases `tasks` one by one.
    """

    def __init__(self, config: StreamDataParserConfig) -> None:
        self.config = config
        self.watcher = CaptureWatcher(config.data, config.unreadable_timeout)
        self.tasks: List[List[StreamFrame]] = []
        """Complete tasks, in capture order."""
        self.collecting: List[StreamFrame] = []
        """Frames of the task still being captured."""
        self.ended = False
        """Whether the end marker (or --max-frames) was reached: no frame is read after it."""
        self.frames_arrived = 0
        self.frames_kept = 0
        self.transform: Optional[np.ndarray] = None
        """(3, 4) float64 world-to-scene transform, fixed once the first task is complete."""
        self.scale = 1.0

    def poll(self) -> None:
        """Take the entries completed since the last poll, closing tasks as the frame count and the markers say."""
        for entry in [] if self.ended else self.watcher.new_entries():
            if isinstance(entry, StreamFrame):
                self._add(entry)
            elif entry.kind == "task":
                self._close_at_marker(entry.name)
            else:
                self._end(entry.name)
            if self.ended:
                return

    def _add(self, frame: StreamFrame) -> None:
        self.frames_arrived += 1
        if (self.frames_arrived - 1) % self.config.frame_stride:
            return
        self.collecting.append(frame)
        self.frames_kept += 1
        if self.config.frames_per_task and len(self.collecting) >= self.config.frames_per_task:
            self.close_task()
        if self.config.max_frames is not None and self.frames_kept >= self.config.max_frames:
            self._end("--max-frames")

    def close_task(self) -> bool:
        """Close the task being captured; False with fewer than 2 frames (a task needs a training and a test frame)."""
        if len(self.collecting) < 2:
            return False
        self.tasks.append(self.collecting)
        self.collecting = []
        return True

    def frames_from(self, task: int) -> int:
        """Frames read so far from task `task` on, the one being captured included."""
        return sum(len(frames) for frames in self.tasks[task:]) + len(self.collecting)

    def cut_task(self, task: int, frames: int) -> None:
        """Make task `task` the next `frames` frames from its start, as another process cut it; the rest is being
        captured."""
        pending = [frame for frames_of_task in self.tasks[task:] for frame in frames_of_task] + self.collecting
        del self.tasks[task:]
        self.tasks.append(pending[:frames])
        self.collecting = pending[frames:]

    def _close_at_marker(self, marker: str) -> None:
        if not self.close_task() and self.collecting:
            warn(f"{marker}: a task needs 2 frames; {self.collecting[0].name} joins the next task")

    def _end(self, reason: str) -> None:
        self.close_task()
        if self.collecting:
            warn(f"{self.collecting[0].name}: the last frame alone is too few for a task; not used")
        self.ended = True
        count = sum(len(task) for task in self.tasks)
        CONSOLE.log(
            f"{self.config.data}: capture ended ({reason}): {len(self.tasks)} tasks, {count} frames", markup=False
        )

    def wait_until(self, done: Callable[[], bool]) -> None:
        """Poll every --poll-seconds (sleeping in between) until `done()`, the end of the capture or Ctrl-C (which
        the trainer answers at the next iteration)."""
        self.poll()
        while not done() and not self.ended and not INTERRUPTS.pending():
            time.sleep(self.config.poll_seconds)
            self.poll()

    def fix_transform(self, first_task: List[StreamFrame]) -> None:
        """Set the pose transform once: later poses must not move the scene the model has learnt."""
        if self.transform is not None:
            return
        if self.config.normalization == "file":
            assert self.config.transform_file is not None
            self.transform, self.scale = read_transform_file(self.config.transform_file)
        elif self.config.normalization == "first-task":
            poses = np.stack([frame.camera_to_world for frame in first_task])
            method, scene_scale = self.config.orientation_method, self.config.scene_scale
            self.transform, self.scale = fit_into_box(poses, method, scene_scale)
        else:
            self.transform, self.scale = np.eye(4)[:3], 1.0

    def wait_for_first_task(self) -> None:
        """Block until the first task is complete; one line when the capture ends before it."""
        self.poll()
        if not self.tasks and not self.ended:
            CONSOLE.log(f"Waiting for the first task's frames in {self.config.data.resolve()}")
            self.wait_until(lambda: bool(self.tasks))
        if not self.tasks:
            raise DatasetError(f"{self.config.data}: the capture ended before its first task was complete (2 frames)")
        self.fix_transform(self.tasks[0])

    def outputs(self, frames: List[StreamFrame]) -> DataparserOutputs:
        """DataparserOutputs of `frames` (in this order) with the fixed transform."""
        assert self.transform is not None, "the transform is fixed when the first task is complete"
        poses = fitted_poses(np.stack([frame.camera_to_world for frame in frames]), self.transform, self.scale)
        intrinsics = torch.from_numpy(np.stack([frame.intrinsics for frame in frames])).float()
        distortion = np.stack([frame.distortion for frame in frames])
        bound = self.config.scene_box_bound
        return CaptureOutputs(
            image_filenames=[frame.image for frame in frames],
            cameras=Cameras(
                camera_to_worlds=poses,
                fx=intrinsics[:, 0:1],
                fy=intrinsics[:, 1:2],
                cx=intrinsics[:, 2:3],
                cy=intrinsics[:, 3:4],
                width=intrinsics[:, 4:5].long(),
                height=intrinsics[:, 5:6].long(),
                # undistorted captures skip nerfstudio's iterative undistortion of every ray
                distortion_params=torch.from_numpy(distortion).float() if distortion.any() else None,
                camera_type=CameraType.PERSPECTIVE,
            ),
            scene_box=SceneBox(aabb=torch.tensor([[-bound] * 3, [bound] * 3], dtype=torch.float32)),
            dataparser_transform=torch.from_numpy(self.transform),
            dataparser_scale=self.scale,
            metadata={"image_scale_factor": 1.0 / self.config.downscale_factor},
        )
