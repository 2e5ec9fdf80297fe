"""The continual-learning accuracy matrix R[i][j]: PSNR on task j's test frames after training task i (and, for a
capture with depth maps, the rendered depth's error on them)."""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import List, Literal, Optional

from continual_nerf.atomic_files import write_text_atomically

ACCURACY_MATRIX_FILENAME = "accuracy_matrix.json"

RunStatus = Literal["training", "finished", "failed", "interrupted"]


@dataclass(frozen=True)
class DepthRow:
    """A row's depth errors: per task the mean over its test frames that have depth (None: none has), and the mean
    over every such frame of the tasks seen."""

    abs_rel: List[Optional[float]]
    rmse: List[Optional[float]]
    mean_abs_rel: Optional[float]
    mean_rmse: Optional[float]


@dataclass
class AccuracyMatrix:
    """Rows are appended as tasks end; row i holds tasks 1..i+1."""

    num_tasks: int
    psnr: List[List[Optional[float]]] = field(default_factory=list)
    """psnr[i][j]: mean PSNR (dB) over task j's test frames after training task i; None (null): not available, the
    test images of task j (an earlier session's) were gone."""
    ssim: List[List[Optional[float]]] = field(default_factory=list)
    """ssim[i][j]: mean SSIM over task j's test frames after training task i (None: not available)."""
    mean_psnr: List[float] = field(default_factory=list)
    """Mean PSNR over all test frames of the tasks seen after task i (those whose images are there)."""
    steps: List[int] = field(default_factory=list)
    """Training step at which each row was measured."""
    depth_abs_rel: List[List[Optional[float]]] = field(default_factory=list)
    """depth_abs_rel[i][j]: mean absolute relative error of the rendered z-depth over task j's test frames after
    training task i, over the pixels with depth (None: no test frame of the task has depth); no rows when the capture
    has no depth maps (and in files written before depth was measured)."""
    depth_rmse: List[List[Optional[float]]] = field(default_factory=list)
    """depth_rmse[i][j]: mean root mean square error (metres) of the rendered z-depth, as depth_abs_rel."""
    mean_depth_abs_rel: List[Optional[float]] = field(default_factory=list)
    """Mean absolute relative depth error over all test frames with depth of the tasks seen after task i."""
    mean_depth_rmse: List[Optional[float]] = field(default_factory=list)
    """Mean depth RMSE (metres) over all test frames with depth of the tasks seen after task i."""
    finished: bool = False
    """Whether every task was trained; a run cut short leaves this false."""
    status: RunStatus = "training"
    """training: tasks remain (a killed run stays so); finished: every task trained; failed: ended by an error;
    interrupted: stopped by Ctrl-C or SIGTERM after saving a checkpoint to resume from."""

    def add_row(
        self,
        psnr: List[Optional[float]],
        ssim: List[Optional[float]],
        mean_psnr: float,
        step: int,
        depth: Optional[DepthRow] = None,
    ) -> None:
        self.psnr.append(psnr)
        self.ssim.append(ssim)
        self.mean_psnr.append(mean_psnr)
        self.steps.append(step)
        if depth is not None:
            for earlier in self.psnr[len(self.depth_abs_rel) : -1]:  # an earlier session's capture had no depth maps
                self._add_depth(DepthRow([None] * len(earlier), [None] * len(earlier), None, None))
            self._add_depth(depth)
        self.finished = len(self.psnr) == self.num_tasks
        self.status = "finished" if self.finished else "training"

    def _add_depth(self, depth: DepthRow) -> None:
        self.depth_abs_rel.append(depth.abs_rel)
        self.depth_rmse.append(depth.rmse)
        self.mean_depth_abs_rel.append(depth.mean_abs_rel)
        self.mean_depth_rmse.append(depth.mean_rmse)

    def write(self, directory: Path) -> Path:
        """Write atomically (temporary file, then rename) so a kill never leaves a half-written file."""
        path = directory / ACCURACY_MATRIX_FILENAME
        write_text_atomically(path, json.dumps(asdict(self), indent=2))
        return path

    @classmethod
    def read(cls, path: Path) -> "AccuracyMatrix":
        return cls(**json.loads(path.read_text()))
