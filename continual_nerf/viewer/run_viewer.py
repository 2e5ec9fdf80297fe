"""`continual-nerf-viewer`: a finished or stopped continual run in the viewer, task by task.

    continual-nerf-viewer --load-config outputs/<experiment>/continual-ngp/<timestamp>/config.yml

nerfstudio's viewer (live render, render and export tabs) on 127.0.0.1, plus a "Continual learning" panel: the
training cameras in their task colours, the accuracy matrix, and a task slider that loads the checkpoint written at
the end of each task, so forgetting (or its absence) shows in the same view.
"""

from __future__ import annotations

import signal
import time
from dataclasses import dataclass, field
from pathlib import Path
from threading import Condition, Lock, Thread
from typing import Any, Dict, Optional

import tyro
import viser
from nerfstudio.cameras.cameras import Cameras
from nerfstudio.pipelines.base_pipeline import Pipeline
from nerfstudio.utils.eval_utils import eval_setup
from nerfstudio.utils.rich_utils import CONSOLE
from nerfstudio.viewer.viewer import Viewer
from nerfstudio.viewer.viewer_elements import ViewerSlider, ViewerText

from continual_nerf.checkpoints import read_checkpoint
from continual_nerf.core.accuracy_matrix import ACCURACY_MATRIX_FILENAME, AccuracyMatrix
from continual_nerf.core.continual_datamanager import ContinualDataManager
from continual_nerf.core.continual_dataset import ContinualDataset
from continual_nerf.core.continual_pipeline import ContinualPipeline
from continual_nerf.core.sessions import SessionRecord
from continual_nerf.errors import ContinualNerfError
from continual_nerf.interrupts import EXIT_CODES
from continual_nerf.nerfstudio_compat import (
    disable_training_buttons,
    init_scene_without_frustums,
    panel_order,
    rerender,
    set_render_defaults,
    show_step,
    stop_rendering_at_exit,
    viewer_answering_when_ready,
    watch_viewer_renders,
    without_lpips,
)
from continual_nerf.viewer.continual_panel import PANEL_LABEL, TaskPictures, frame_view, mean_psnr_text
from continual_nerf.viewer.task_cameras import TaskCameras, framing_view
from continual_nerf.viewer.viewer_config import ContinualViewerConfig

CHECKPOINT_LABEL = "Checkpoint:"
"""Start of the panel's line naming the checkpoint the render comes from."""
LOADING = "loading"
"""What the checkpoint line adds while the checkpoint loads."""
RENDERING = "rendering its view"
"""What the checkpoint line adds while the view of the checkpoint just loaded renders."""


def checkpoint_text(path: Optional[Path], task: int) -> str:
    """The checkpoint written at the end of `task` (0-based), by file name: the line wraps before the name."""
    if path is None:
        return f"none written at the end of task {task + 1}"
    return f"end of task {task + 1}, {path.name}"


def task_checkpoints(
    checkpoint_dir: Path, accuracy: AccuracyMatrix, earlier: Optional[SessionRecord] = None
) -> Dict[int, Path]:
    """The checkpoint written at the end of each task (0-based), by the step of its accuracy-matrix row; for the tasks
    of a continued run's earlier sessions, where their runs wrote it."""
    paths = {task: checkpoint_dir / f"step-{step:09d}.ckpt" for task, step in enumerate(accuracy.steps)}
    for task, name in enumerate(earlier.task_checkpoints if earlier is not None else []):
        paths[task] = Path(name)  # "" where its run's checkpoint was not known: no file
    return {task: path for task, path in paths.items() if path.is_file()}


class TaskTravel:
    """The finished run's panel: a task slider loading that task's checkpoint, its cameras, pictures and mean.

    Checkpoints load in a thread of their own, the latest choice first, so the page answers while one loads; the
    "Checkpoint:" line says what is shown, and whether its checkpoint is loading or its view still rendering.
    """

    def __init__(
        self,
        viewer: Viewer,
        pipeline: Pipeline,
        lock: Lock,
        accuracy: AccuracyMatrix,
        checkpoint_dir: Path,
        options: ContinualViewerConfig,
    ) -> None:
        self.viewer = viewer
        self.pipeline = pipeline
        self.lock = lock
        """The viewer renders under this lock; weights are swapped under it too."""
        self.accuracy = accuracy
        datamanager = pipeline.datamanager
        self.earlier = datamanager.earlier if isinstance(datamanager, ContinualDataManager) else None
        """A continued run's earlier sessions: their tasks' checkpoints are their runs'."""
        self.checkpoints = task_checkpoints(checkpoint_dir, accuracy, self.earlier)
        dataset = pipeline.datamanager.train_dataset
        assert isinstance(dataset, ContinualDataset)
        self.dataset = dataset
        last = max(self.checkpoints) + 1
        self.slider = ViewerSlider(
            "Task",
            last,
            1,
            max(len(accuracy.steps), 2),  # viser's slider needs a range
            1,
            cb_hook=lambda slider: self.request(int(slider.value) - 1),
            disabled=len(accuracy.steps) < 2,
            hint="Load the checkpoint written at the end of this task",
        )
        self.mean_psnr = ViewerText("Mean test PSNR", "", disabled=True, hint="Over the tasks seen after this task")
        self.requested: Optional[int] = None
        """The task chosen last and not loaded yet."""
        self.wake = Condition()
        self.rendering: Optional[str] = None
        """What the checkpoint line says once the view of the checkpoint just loaded has rendered at Max res."""
        init_scene_without_frustums(viewer, dataset, "completed")
        set_render_defaults(viewer, options.max_res, options.train_util)
        self.cameras = TaskCameras(viewer, dataset, options.camera_frustum_scale)
        server = viewer.viser_server
        with server.gui.add_folder(PANEL_LABEL, order=panel_order(viewer)):
            self.slider.install(server)
            self.checkpoint = server.gui.add_markdown("")
            self.pictures = TaskPictures(server)
            self.mean_psnr.install(server)
        server.on_client_connect(self._frame_new_client)
        disable_training_buttons(viewer)
        watch_viewer_renders(pipeline.model, self._rendered)
        self.show_task(last - 1)
        Thread(target=self._load_requested, daemon=True).start()

    def _frame_new_client(self, client: viser.ClientHandle) -> None:
        frame_view(client, framing_view(self.dataset, range(len(self.dataset)), client.camera.fov))

    def request(self, task: int) -> None:
        """Show `task` (0-based) as soon as the loader thread is free; a later request replaces this one."""
        path = self.checkpoints.get(task)
        self._say(checkpoint_text(path, task) + (f", {LOADING}" if path is not None else ""))
        with self.wake:
            self.requested = task
            self.wake.notify()

    def _load_requested(self) -> None:
        while True:
            with self.wake:
                while self.requested is None:
                    self.wake.wait()
                task, self.requested = self.requested, None
            self.show_task(task)

    def show_task(self, task: int) -> None:
        """Render from the checkpoint of the end of `task` (0-based) and show what was known then."""
        path = self.checkpoints.get(task)
        if path is None:
            self._say(checkpoint_text(path, task))
            return
        shown = checkpoint_text(path, task)
        self.rendering = None  # a render ending now shows the weights that are being replaced
        self._say(f"{shown}, {LOADING}")
        try:
            state = read_checkpoint(path)
        except ContinualNerfError as error:
            self._say(f"{shown}, could not be read (see the terminal)")
            CONSOLE.print(f"continual-nerf-viewer: {error}", markup=False, soft_wrap=True)
            return
        rerender(self.viewer)  # interrupts a render in progress: it holds the lock the weights are swapped under
        with self.lock:  # renders end under it too: none ends between the swap and what the line says of it
            self._load(task, state)
            if self.viewer.viser_server.get_clients():  # a browser is open: its view renders with these weights
                self.rendering = shown
                self._say(f"{shown}, {RENDERING} at Max res {self.viewer.control_panel.max_res}")
            else:
                self._say(shown)
        self.mean_psnr.value = mean_psnr_text(self.accuracy.mean_psnr[: task + 1])
        self.pictures.show(self.accuracy.num_tasks, self.accuracy.psnr[: task + 1])
        self.cameras.show(self.dataset, task)
        show_step(self.viewer, int(state["step"]))
        rerender(self.viewer)

    def _load(self, task: int, state: Dict[str, Any]) -> None:
        """The weights of the checkpoint of `task`'s end: an earlier session's model has rows for its frames only."""
        earlier, pipeline = self.earlier, self.pipeline
        if earlier is None or task >= earlier.num_tasks or not isinstance(pipeline, ContinualPipeline):
            pipeline.load_pipeline(state["pipeline"], state["step"])
            return
        rows = earlier.train_frames_of_sessions(earlier.session_of_task(task) + 1)
        pipeline.load_earlier_model(state["pipeline"], int(state["step"]), rows)

    def _rendered(self, camera: Cameras, completed: bool) -> None:
        """A render ended: once the new checkpoint's view has rendered at Max res, the line stops saying rendering."""
        shown = self.rendering
        full_size = max(int(camera.width.max()), int(camera.height.max())) >= self.viewer.control_panel.max_res
        if shown is not None and completed and full_size:
            self.rendering = None
            self._say(shown)

    def _say(self, text: str) -> None:
        self.checkpoint.content = f"{CHECKPOINT_LABEL} {text}"


@dataclass
class ContinualRunViewer:
    """Open a finished or stopped continual run in the viewer, with a task slider over its per-task checkpoints."""

    load_config: Path
    """The run's config.yml: outputs/<experiment>/<method>/<timestamp>/config.yml."""
    viewer: ContinualViewerConfig = field(default_factory=ContinualViewerConfig)
    """Viewer options; it listens on 127.0.0.1 (--viewer.websocket-host 0.0.0.0 opens it to the network)."""

    def start(self) -> TaskTravel:
        """Load the run and start the viewer with its panel; returns once the viewer answers."""
        with without_lpips():  # nerfstudio's models build LPIPS at set-up, which would download weights
            config, pipeline, _, _ = eval_setup(self.load_config, test_mode="test")
        base_dir = self.load_config.parent
        accuracy_path = base_dir / ACCURACY_MATRIX_FILENAME
        if not accuracy_path.is_file():
            raise ContinualNerfError(f"{accuracy_path}: not found; is {self.load_config} a continual run's config?")
        accuracy = AccuracyMatrix.read(accuracy_path)
        datamanager = pipeline.datamanager
        earlier = datamanager.earlier if isinstance(datamanager, ContinualDataManager) else None
        if not task_checkpoints(config.get_checkpoint_dir(), accuracy, earlier):
            raise ContinualNerfError(f"{config.get_checkpoint_dir()}: no checkpoint written at the end of a task")
        lock = Lock()
        with viewer_answering_when_ready():  # the page answers once it shows the panel
            viewer = Viewer(
                self.viewer,
                log_filename=base_dir / self.viewer.relative_log_filename,
                datapath=pipeline.datamanager.get_datapath(),
                pipeline=pipeline,
                train_lock=lock,
            )
            stop_rendering_at_exit(viewer)
            travel = TaskTravel(viewer, pipeline, lock, accuracy, config.get_checkpoint_dir(), self.viewer)
        CONSOLE.print(viewer.viewer_info[0])
        return travel

    def main(self) -> None:
        try:
            self.start()
            CONSOLE.print("Use ctrl+c to quit", justify="center")
            while True:
                time.sleep(1.0)
        except ContinualNerfError as error:
            raise SystemExit(f"continual-nerf-viewer: error: {error}") from None
        except KeyboardInterrupt:
            raise SystemExit(EXIT_CODES[signal.SIGINT]) from None  # Ctrl-C is how it ends: no traceback


def entrypoint() -> None:
    # booleans as `--option True/False`, as ns-train and ns-viewer take them
    tyro.cli(tyro.conf.FlagConversionOff[ContinualRunViewer]).main()


if __name__ == "__main__":
    entrypoint()
