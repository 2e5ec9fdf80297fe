"""A continual run with the live viewer, trained in the main thread (as `ns-train` trains: the model is compiled for
it) while another thread drives a browser page; shared by the viewer's cost benchmark and the README's screenshot."""

from __future__ import annotations

import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, List, Literal

from continual_nerf.bench.browser import free_port, viewer_answers, wait_for
from continual_nerf.bench.demo_runs import on_demo
from continual_nerf.core.continual_trainer import ContinualTrainer, ContinualTrainerConfig
from continual_nerf.dataparsers.continual_demo_dataparser import ContinualDemoDataParserConfig
from continual_nerf.method_configs import CONTINUAL_NGP
from continual_nerf.recipes import set_up_like_ns_train


@dataclass
class LiveViewerRun:
    """A continual-ngp run on the demo scene with the viewer, and the Chromium window that looks at it."""

    window_size: str = "1000,700"
    """Chromium's window (width,height): the render's aspect and size follow it."""
    device: Literal["cpu", "cuda"] = "cpu"
    """Device to train on."""
    data: Path = Path("data/continual-demo")
    """Where the demo scene is generated (and reused from)."""

    def set_up(self, output_dir: Path, **datamanager: Any) -> ContinualTrainer:
        """continual-ngp on the demo scene, with the given datamanager options and the viewer, set up."""
        demo = ContinualDemoDataParserConfig(data=self.data)
        return viewer_trainer(on_demo(CONTINUAL_NGP, demo, self.device, output_dir, **datamanager))


def viewer_trainer(config: ContinualTrainerConfig) -> ContinualTrainer:
    """`config` set up with the viewer on a free port of 127.0.0.1, answering once this returns."""
    config.vis = "viewer"
    config.viewer.websocket_port = free_port()
    config.viewer.quit_on_train_completion = True
    config.save_config()
    trainer = set_up_like_ns_train(config)
    wait_for("the viewer to answer", lambda: viewer_answers(config.viewer.websocket_port or 0))
    return trainer


def viewer_url(trainer: ContinualTrainer) -> str:
    return f"http://127.0.0.1:{trainer.config.viewer.websocket_port}"


def train_while(trainer: ContinualTrainer, drive: Callable[[], None]) -> None:
    """Train in this thread while `drive` runs in another; training stops when `drive` returns or fails, and what
    `drive` raised is raised here."""
    failure: List[BaseException] = []

    def driver() -> None:
        try:
            drive()
        except BaseException as error:  # raised again in the training thread, below
            failure.append(error)
        finally:
            trainer.stop_training = True

    thread = threading.Thread(target=driver)
    thread.start()
    try:
        trainer.train()
    finally:
        trainer.stop_training = True
        thread.join()
        trainer.shutdown()
    if failure:
        raise failure[0]
