"""The continual methods' Trainer: the core's ContinualTrainer with the continual panel in nerfstudio's live viewer.

The method configs (method_configs.py) use this trainer, so that `ns-train continual-ngp` shows the panel; the core
knows nothing of the viewer's panel, which reads the pipeline's `ContinualStatus`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Optional, Type

from nerfstudio.viewer.viewer import Viewer

from continual_nerf.core.continual_trainer import ContinualTrainer, ContinualTrainerConfig
from continual_nerf.viewer.continual_panel import ContinualPanel
from continual_nerf.viewer.viewer_config import ContinualViewerConfig


@dataclass
class LiveViewerTrainerConfig(ContinualTrainerConfig):
    """ContinualTrainerConfig whose viewer shows the continual panel."""

    _target: Type = field(default_factory=lambda: LiveViewerTrainer)
    viewer: ContinualViewerConfig = field(default_factory=ContinualViewerConfig)
    """nerfstudio's viewer with the continual panel: the released tasks' cameras, the accuracy matrix, controls."""


class LiveViewerTrainer(ContinualTrainer):
    """ContinualTrainer that builds the continual panel when the viewer runs (as nerfstudio's Trainer builds its
    viewer) and installs it before the viewer's page first answers."""

    config: LiveViewerTrainerConfig
    panel: Optional[ContinualPanel] = None
    """The viewer's continual-learning panel, when the viewer runs."""

    def extend_viewer(self, viewer: Viewer) -> None:
        pipeline = self.pipeline
        self.panel = ContinualPanel(
            pipeline.status,
            pipeline.request_next_task,
            lambda: pipeline.datamanager.train_dataset,
            self.config.viewer,
            paused=lambda: self.training_state == "paused" or self.pause_requested,
        )
        self.panel.install(viewer, self.training_state)
        self.callbacks += self.panel.training_callbacks(self)

    def show_stage(self, stage: str) -> None:
        if self.panel is not None:
            self.panel.show_stage(stage)

    def training_state_changed(self) -> None:
        if self.panel is not None:  # nerfstudio's Pause / Resume buttons: the panel says so while the loop waits
            self.panel.refresh()

    def _init_viewer_state(self) -> None:
        # nerfstudio's init_scene shows every training frame with its pixels; only released tasks may be shown, and
        # the panel drew them when it was installed at set-up
        if self.panel is None:
            super()._init_viewer_state()
