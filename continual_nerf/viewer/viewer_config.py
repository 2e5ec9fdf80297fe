"""The viewer's options for the continual methods: nerfstudio's ViewerConfig with other defaults, plus the panel's."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

from nerfstudio.configs.base_config import ViewerConfig

DEFAULT_MAX_RES = 64
"""Max res of the live render. nerfstudio renders a still view at this size while holding training's lock; on a
2-core CPU 64 kept training at >= 80% of its speed and 128 did not (`python -m continual_nerf.bench.viewer_cost`
measures it)."""
DEFAULT_TRAIN_UTIL = 0.95
"""Share of the time nerfstudio's render scheduling leaves training (measured with DEFAULT_MAX_RES)."""


@dataclass
class ContinualViewerConfig(ViewerConfig):
    """nerfstudio's viewer, set up for watching tasks arrive: the released cameras in view, a light live render."""

    websocket_host: str = "127.0.0.1"
    """Address the viewer listens on: this machine only (reach it through ssh -L); 0.0.0.0 opens it to the network."""
    num_rays_per_chunk: int = 1 << 13
    """Rays rendered at once by the viewer."""
    default_composite_depth: bool = False
    """Start with "Composite depth" on: the render then hides the cameras behind walls (off keeps them in view)."""
    camera_frustum_scale: Optional[float] = None  # type: ignore[assignment]
    """Size of the task frustums in viser units; None: a fraction of the extent of the trajectory known at the start."""
    max_res: int = DEFAULT_MAX_RES
    """Start value of the render's "Max res" slider (nerfstudio's 512 stalls training on a CPU; raise it on a GPU)."""
    train_util: float = DEFAULT_TRAIN_UTIL
    """Start value of the "Train Util" slider: the share of time nerfstudio's render scheduling leaves training."""
    follow_newest_task: bool = False
    """Move the browser's view to each task as it is released (a checkbox in the panel; on for streaming)."""
