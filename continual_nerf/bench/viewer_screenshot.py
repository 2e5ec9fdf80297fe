"""The README's picture of the live viewer: continual-ngp training on the demo scene, seen in headless Chromium once
a few tasks have ended.

    python -m continual_nerf.bench.viewer_screenshot [--output docs/viewer.png]

Trains the README's quick-start run (5 tasks x 60 iterations) with the viewer at its defaults, opens the page, waits
until `--after-task` tasks have ended and the render has settled, and writes a small palette PNG. Needs Debian's
chromium and websocket-client.
"""

from __future__ import annotations

import io
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import tyro
from nerfstudio.utils.rich_utils import CONSOLE
from PIL import Image

from continual_nerf.bench.browser import DevTools, wait_for
from continual_nerf.bench.live_viewer import LiveViewerRun, train_while, viewer_url
from continual_nerf.core.continual_trainer import ContinualTrainer


@dataclass
class ViewerScreenshot(LiveViewerRun):
    """A screenshot of the live viewer during a continual-ngp run on the demo scene."""

    output: Path = Path("docs/viewer.png")
    """Where the PNG goes."""
    after_task: int = 3
    """Take it once this many tasks have ended (their frustums and accuracy rows are shown)."""
    settle_seconds: float = 20.0
    """Seconds the page is left to render after that task ends."""
    colours: int = 256
    """Palette size of the PNG (at most 256): keeps the file small."""
    window_size: str = "1200,800"
    """Chromium's window (width,height)."""

    def drive(self, trainer: ContinualTrainer, profile: Path) -> None:
        browser = DevTools(profile, window_size=self.window_size)
        try:
            browser.navigate(viewer_url(trainer))
            accuracy = trainer.pipeline.accuracy
            wait_for(f"task {self.after_task} to end", lambda: len(accuracy.psnr) >= self.after_task, timeout=3600)
            time.sleep(self.settle_seconds)
            self.save(browser.screenshot_png())
        finally:
            browser.close()

    def save(self, png: bytes) -> None:
        image = Image.open(io.BytesIO(png)).convert("RGB").quantize(colors=self.colours)
        self.output.parent.mkdir(parents=True, exist_ok=True)
        image.save(self.output, optimize=True)
        CONSOLE.print(f"{self.output}: {self.output.stat().st_size // 1024} KiB")

    def main(self) -> None:
        with tempfile.TemporaryDirectory() as scratch:
            trainer = self.set_up(Path(scratch), num_tasks=5, iterations_per_task=60)  # the README's quick start
            train_while(trainer, lambda: self.drive(trainer, Path(scratch) / "chromium-profile"))


def entrypoint() -> None:
    tyro.cli(ViewerScreenshot).main()


if __name__ == "__main__":
    entrypoint()
