"""nerfstudio's Trainer, with the iteration count derived from the task budget and one-line errors for bad input."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal, Type

from nerfstudio.engine.trainer import Trainer, TrainerConfig

from continual_nerf.errors import ContinualNerfError


@dataclass
class ContinualTrainerConfig(TrainerConfig):
    """TrainerConfig whose max_num_iterations follows from num_tasks x the per-task budget."""

    _target: Type = field(default_factory=lambda: ContinualTrainer)


class ContinualTrainer(Trainer):
    """Runs nerfstudio's training loop unchanged; the pipeline's callbacks switch tasks and stop it."""

    config: ContinualTrainerConfig

    def setup(self, test_mode: Literal["test", "val", "inference"] = "val") -> None:
        self.config.max_num_iterations = self.config.pipeline.datamanager.max_num_iterations()
        try:
            super().setup(test_mode)
        except ContinualNerfError as error:
            raise SystemExit(f"{self.config.method_name}: error: {error}") from None

    def train(self) -> None:
        try:
            super().train()
        except ContinualNerfError as error:  # for instance an image of a task released mid-run cannot be read
            raise SystemExit(f"{self.config.method_name}: error: {error}") from None
