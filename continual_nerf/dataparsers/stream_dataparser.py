"""`continual-stream`: frames read from a capture folder that another process is still writing.

The capture protocol and its reader live in continual_nerf/dataparsers/capture_folder.py; this module is its
nerfstudio dataparser (options and outputs) for `ns-train continual-ngp-stream continual-stream --data <folder>`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal, Optional, Type

from nerfstudio.data.dataparsers.base_dataparser import DataParser, DataparserOutputs

from continual_nerf.dataparsers.capture import CaptureDataParserConfig
from continual_nerf.dataparsers.capture_folder import CaptureTasks
from continual_nerf.errors import ContinualConfigError


@dataclass
class StreamDataParserConfig(CaptureDataParserConfig):
    """A capture folder that grows while training runs; its tasks close as frames arrive."""

    _target: Type = field(default_factory=lambda: StreamDataParser)
    """The dataparser this config builds."""
    data: Path = Path("capture")
    """Capture folder another process writes frames into (protocol: continual_nerf/dataparsers/capture_folder.py)."""
    frames_per_task: int = 20
    """A task closes once this many frames have arrived (0: only `.task` markers close tasks)."""
    poll_seconds: float = 0.5
    """Seconds between two looks at the capture folder."""
    unreadable_timeout: float = 60.0
    """An entry still unreadable after this many seconds is skipped with a warning (0: retry it forever)."""
    normalization: Literal["first-task", "file", "none"] = "first-task"
    """Fixed pose transform: fitted to the first task's cameras, read from --transform-file, or none (as written)."""
    transform_file: Optional[Path] = None
    """A dataparser_transforms.json (`transform` 3x4, `scale`) applied to every pose by --normalization file."""
    scene_scale: float = 1.0
    """Extra factor on the scale that fits the first task's camera centres into [-1, 1] (--normalization first-task)."""
    scene_box_bound: float = 1.0
    """Half side of the scene box; cameras that arrive later may leave it, nerfacto's scene contraction covers them."""

    def validate(self) -> None:
        super().validate()
        if self.frames_per_task < 0 or self.frames_per_task == 1:
            raise ContinualConfigError(
                "--frames-per-task must be 0 (markers only) or at least 2 (a training and a test frame), "
                f"got {self.frames_per_task}"
            )
        for name in ("poll_seconds", "scene_scale", "scene_box_bound"):
            if not getattr(self, name) > 0:
                raise ContinualConfigError(f"--{name.replace('_', '-')} must be positive, got {getattr(self, name)}")
        if self.unreadable_timeout < 0:
            raise ContinualConfigError(f"--unreadable-timeout must be 0 or positive, got {self.unreadable_timeout}")
        if self.normalization == "file" and self.transform_file is None:
            raise ContinualConfigError("--normalization file needs --transform-file (a dataparser_transforms.json)")


class StreamDataParser(DataParser):
    """A capture folder as a nerfstudio dataparser: the frames of the tasks complete so far (it waits for the first).

    The streaming datamanager reads later tasks from `capture` as they arrive.
    """

    config: StreamDataParserConfig

    def __init__(self, config: StreamDataParserConfig) -> None:
        super().__init__(config)
        self.capture = CaptureTasks(config)
        """The capture folder's frames, cut into tasks as they arrive."""

    def _generate_dataparser_outputs(self, split: str = "train", **kwargs) -> DataparserOutputs:
        """The frames of every task complete so far; waits for the first one."""
        self.capture.wait_for_first_task()
        return self.capture.outputs([frame for task in self.capture.tasks for frame in task])
