"""What an open viewer page costs training: continual-ngp's iterations per second with no page open, and with a
page at several render settings ("Max res", "Train Util"), measured in one run.

    python -m continual_nerf.bench.viewer_cost [--settings 512:0.85 256:0.95] [--rounds 3] [--phase-seconds 40]

continual-ngp trains on the demo scene with the viewer on 127.0.0.1, through nerfstudio's own Trainer loop (which
schedules the viewer's renders). Two kinds of page: a remote one (a websocket client that asks for renders and
draws nothing: what a browser on another machine, through ssh -L, costs the training machine) at each setting, and
a headless Chromium on the same machine (software WebGL: what a browser beside training costs) at
`--browser-settings`. Phases take turns, round after round, so that a change in the machine's load hits them alike;
each is compared with the no-page phase of its round. Needs Debian's chromium and websocket-client.
"""

from __future__ import annotations

import statistics
import tempfile
import threading
import time
from bisect import bisect_left
from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, List, Optional, Tuple

import tyro
from nerfstudio.engine.callbacks import TrainingCallback, TrainingCallbackLocation
from nerfstudio.utils.rich_utils import CONSOLE
from nerfstudio.viewer.viewer import Viewer
from rich.table import Table

from continual_nerf.bench.browser import DevTools, wait_for
from continual_nerf.bench.live_viewer import LiveViewerRun, train_while, viewer_url
from continual_nerf.core.continual_trainer import ContinualTrainer
from continual_nerf.nerfstudio_compat import set_render_defaults, viewer_camera_message, viewer_render_rays_per_second
from continual_nerf.viewer.task_cameras import framing_view

CLOSED = "no page"
"""The phase without a page: the viewer runs, nobody looks (as fast as no viewer: nerfstudio renders for pages)."""
REMOTE_ASPECT = 1.4
"""Width over height of the remote page's view (about a 1000x700 browser window less the panel)."""
Setting = Tuple[int, float]


class RemotePage:
    """A page on another machine, as the training machine sees it: it sends one camera pose and takes every render
    the viewer sends, without decoding or drawing them."""

    def __init__(self, port: int, camera: bytes) -> None:
        import websocket  # the test extra's

        self.socket = websocket.create_connection(f"ws://127.0.0.1:{port}", timeout=10, suppress_origin=True)
        self.socket.send_binary(camera)
        self.thread = threading.Thread(target=self._drain, daemon=True)
        self.thread.start()

    def _drain(self) -> None:
        try:
            while self.socket.recv():
                pass
        except Exception:  # noqa: BLE001 - closed by close(), or by the server shutting down
            return

    def close(self) -> None:
        self.socket.close()
        self.thread.join(timeout=10)


@dataclass
class StepClock:
    """When each training iteration started and ended (inside the Trainer's train lock, which renders take too)."""

    starts: List[float] = field(default_factory=list)
    ends: List[float] = field(default_factory=list)

    def start(self, step: int) -> None:
        self.starts.append(time.perf_counter())

    def end(self, step: int) -> None:
        self.ends.append(time.perf_counter())

    def rate(self, start: float, end: float) -> float:
        """Iterations per second that ended in [start, end)."""
        return (bisect_left(self.ends, end) - bisect_left(self.ends, start)) / (end - start)

    def share(self, start: float, end: float) -> float:
        """Share of [start, end) spent inside training iterations. Other processes' load slows iterations and
        everything else alike, so this compares phases where iterations per second, on a shared machine, cannot."""
        spans = zip(self.starts, self.ends)
        return sum(max(0.0, min(b, end) - max(a, start)) for a, b in spans) / (end - start)


@dataclass
class ViewerCostBenchmark(LiveViewerRun):
    """Training iterations per second with the viewer's page closed and open at each render setting."""

    settings: Tuple[str, ...] = ("512:0.85", "256:0.95", "128:0.95")
    """Render settings "max_res:train_util" to measure with the remote page (nerfstudio's defaults are 512:0.85)."""
    browser_settings: Tuple[str, ...] = ("512:0.85", "128:0.95")
    """Render settings to measure with Chromium on this machine."""
    rounds: int = 2
    """Rounds of phases (no page, then each page and setting)."""
    settle_seconds: float = 30.0
    """Seconds after a page opens that are not counted: loading, and the first full-resolution render, which holds
    training while it runs (its length is the render's pixels over the render speed reported)."""
    phase_seconds: float = 60.0
    """Seconds counted per phase: training with the page open and still, as while watching it."""
    render_speeds: tyro.conf.Suppress[Dict[str, List[float]]] = field(default_factory=dict)
    """The viewer's render speed (rays/s) at the end of each phase with a page."""

    def phases(self) -> List[Tuple[str, Optional[Setting]]]:
        """One round: no page, the remote page at each setting, Chromium at each browser setting."""

        def parse(setting: str) -> Setting:
            res, util = setting.split(":")
            return int(res), float(util)

        remote = [("remote", parse(setting)) for setting in self.settings]
        return [("none", None), *remote, *[("chromium", parse(setting)) for setting in self.browser_settings]]

    def drive(
        self, trainer: ContinualTrainer, clock: StepClock, rates: Dict[str, List[Tuple[float, float]]], profile: Path
    ) -> None:
        """Open and close the pages phase by phase, recording iterations per second."""
        viewer = trainer.viewer_state
        assert isinstance(viewer, Viewer)
        dataset = trainer.pipeline.datamanager.train_dataset
        view = framing_view(dataset, range(len(dataset)), fov=1.0)
        camera = viewer_camera_message(view.position, view.look_at, view.up, 1.0, REMOTE_ASPECT)
        port = trainer.config.viewer.websocket_port or 0
        browser = DevTools(profile, window_size=self.window_size)
        try:
            wait_for("training to start", lambda: len(clock.ends) > 3, timeout=600)
            for round_number in range(self.rounds):
                for page, setting in self.phases():
                    name = CLOSED if setting is None else f"{page}, {setting[0]} px, util {setting[1]:g}"
                    remote = None
                    if setting is not None:
                        set_render_defaults(viewer, *setting)
                    if page == "remote":
                        remote = RemotePage(port, camera)
                    elif page == "chromium":
                        browser.navigate(viewer_url(trainer))
                    start = time.perf_counter() + self.settle_seconds
                    time.sleep(self.settle_seconds + self.phase_seconds)
                    end = start + self.phase_seconds
                    rates.setdefault(name, []).append((clock.rate(start, end), clock.share(start, end)))
                    render = viewer_render_rays_per_second()
                    if setting is not None and render is not None:
                        self.render_speeds.setdefault(name, []).append(render)
                    iterations, share = rates[name][-1]
                    CONSOLE.log(f"round {round_number + 1}: {name}: {iterations:.2f} it/s, {100 * share:.0f}% training")
                    if remote is not None:
                        remote.close()
                    browser.navigate("about:blank")
        finally:
            browser.close()

    def measure(self, output_dir: Path) -> Dict[str, List[Tuple[float, float]]]:
        trainer = self.set_up(output_dir, num_tasks=10, iterations_per_task=10**8)  # the benchmark ends it
        clock = StepClock()
        trainer.callbacks.insert(0, TrainingCallback([TrainingCallbackLocation.BEFORE_TRAIN_ITERATION], clock.start))
        trainer.callbacks.append(TrainingCallback([TrainingCallbackLocation.AFTER_TRAIN_ITERATION], clock.end))
        rates: Dict[str, List[Tuple[float, float]]] = {}
        train_while(trainer, lambda: self.drive(trainer, clock, rates, output_dir / "chromium-profile"))
        return rates

    def report(self, rates: Dict[str, List[Tuple[float, float]]]) -> None:
        """Medians over the rounds; each phase's share of time in training relative to the no-page phase's share
        of its round is the speed training keeps with that page open."""
        table = Table(title=f"continual-ngp training with a viewer page open, {self.device}")
        columns = ("page", "iterations/s", "time in training", "speed kept vs no page", "render rays/s")
        for column in columns:
            table.add_column(column, justify="right")
        closed = rates[CLOSED]
        for name, values in rates.items():
            kept = statistics.median(share / base for (_, share), (_, base) in zip(values, closed))
            render = self.render_speeds.get(name)
            table.add_row(
                name,
                f"{statistics.median(rate for rate, _ in values):.2f}",
                f"{100 * statistics.median(share for _, share in values):.0f}%",
                f"{100 * kept:.0f}%",
                f"{statistics.median(render):,.0f}" if render else "-",
            )
        CONSOLE.print(table)

    def main(self) -> None:
        with tempfile.TemporaryDirectory() as scratch:
            self.report(self.measure(Path(scratch)))


def entrypoint() -> None:
    tyro.cli(ViewerCostBenchmark).main()


if __name__ == "__main__":
    entrypoint()
