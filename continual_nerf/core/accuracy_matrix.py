"""The continual-learning accuracy matrix R[i][j]: PSNR on task j's test frames after training task i."""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import List, Literal, Optional

from continual_nerf.atomic_files import write_text_atomically

ACCURACY_MATRIX_FILENAME = "accuracy_matrix.json"

RunStatus = Literal["training", "finished", "failed", "interrupted"]


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
    finished: bool = False
    """Whether every task was trained; a run cut short leaves this false."""
    status: RunStatus = "training"
    """training: tasks remain (a killed run stays so); finished: every task trained; failed: ended by an error;
    interrupted: stopped by Ctrl-C or SIGTERM after saving a checkpoint to resume from."""

    def add_row(self, psnr: List[Optional[float]], ssim: List[Optional[float]], mean_psnr: float, step: int) -> None:
        self.psnr.append(psnr)
        self.ssim.append(ssim)
        self.mean_psnr.append(mean_psnr)
        self.steps.append(step)
        self.finished = len(self.psnr) == self.num_tasks
        self.status = "finished" if self.finished else "training"

    def write(self, directory: Path) -> Path:
        """Write atomically (temporary file, then rename) so a kill never leaves a half-written file."""
        path = directory / ACCURACY_MATRIX_FILENAME
        write_text_atomically(path, json.dumps(asdict(self), indent=2))
        return path

    @classmethod
    def read(cls, path: Path) -> "AccuracyMatrix":
        return cls(**json.loads(path.read_text()))
