"""Every place the plugin relies on nerfstudio internals (private attributes, methods or behaviours of 1.1.5).

The rest of the package goes through nerfstudio's public classes and its documented extension points (configs with
`_target`, entry points, training callbacks, ViewerElements). What is here may change in another nerfstudio
release: each item says what it depends on, and tests/test_nerfstudio_compat.py fails loudly if one stops holding.
pyproject.toml pins nerfstudio==1.1.5 until a newer release has passed those tests.
"""

from __future__ import annotations

import asyncio
import atexit
import dataclasses
import logging
import os
import re
import signal
import sys
import threading
import time
import warnings
import weakref
from contextlib import ExitStack, contextmanager
from datetime import timedelta
from typing import Any, Callable, Dict, Iterator, List, Literal, Mapping, Optional, Tuple, Type
from unittest import mock

import msgspec
import numpy as np
import torch
import torch.distributed as dist
import torchmetrics.image.lpip
import viser.transforms as vtf
import websockets.server
from nerfstudio.cameras.cameras import Cameras
from nerfstudio.data.datasets.base_dataset import InputDataset
from nerfstudio.engine.trainer import Trainer
from nerfstudio.field_components.embedding import Embedding
from nerfstudio.fields.nerfacto_field import NerfactoField
from nerfstudio.model_components.ray_samplers import Sampler
from nerfstudio.model_components.scene_colliders import SceneCollider
from nerfstudio.models.base_model import Model
from nerfstudio.models.depth_nerfacto import DepthNerfactoModel
from nerfstudio.models.nerfacto import NerfactoModel
from nerfstudio.pipelines.base_pipeline import VanillaPipeline
from nerfstudio.utils import profiler, writer
from nerfstudio.viewer.viewer import VISER_NERFSTUDIO_SCALE_RATIO, Viewer
from torch import nn
from torch.multiprocessing import ProcessExitedException, ProcessRaisedException
from websockets.legacy.server import serve as legacy_serve

from continual_nerf.errors import first_line
from continual_nerf.interrupts import EXIT_CODES

__all__ = ["VISER_NERFSTUDIO_SCALE_RATIO"]

TrainingState = Literal["training", "paused", "completed"]


class _LPIPSNotComputed(nn.Module):
    """Stands in for torchmetrics' LPIPS, whose construction downloads AlexNet weights."""

    def __init__(self, **_: object) -> None:
        super().__init__()

    def forward(self, *_: torch.Tensor) -> torch.Tensor:
        return torch.tensor(float("nan"))


@contextmanager
def without_lpips() -> Iterator[None]:
    """Build nerfacto-family and vanilla NeRF models offline.

    Depends on: `NerfactoModel.populate_modules` and `NeRFModel.populate_modules` importing
    `LearnedPerceptualImagePatchSimilarity` from `torchmetrics.image.lpip` inside the method and building it there
    (which downloads AlexNet weights). Patched for the duration of the set-up only.
    """
    with mock.patch.object(torchmetrics.image.lpip, "LearnedPerceptualImagePatchSimilarity", _LPIPSNotComputed):
        yield


NERFSTUDIO_WARNINGS: Tuple[Tuple[Type[Warning], str, str], ...] = (
    (FutureWarning, "`torch.jit.script` is deprecated", "torch.jit._script"),
    (FutureWarning, "`torch.cuda.amp.custom_fwd(args...)` is deprecated", "nerfstudio.field_components.activations"),
    (FutureWarning, "`torch.cuda.amp.custom_bwd(args...)` is deprecated", "nerfstudio.field_components.activations"),
    (FutureWarning, "`torch.cuda.amp.GradScaler(args...)` is deprecated", "nerfstudio.engine.trainer"),
    (UserWarning, "Using a non-tuple sequence for multidimensional indexing", "nerfstudio.cameras.cameras"),
    (UserWarning, "Converting a tensor with requires_grad=True to a scalar", "nerfstudio.utils.writer"),
)
"""Warnings nerfstudio 1.1.5's own code raises on this torch, every run (its deprecated calls, its camera indexing, its
writer's loss logging): category, start of the message, module they are raised from (torch.jit._script: nerfstudio's
@torch.jit.script functions)."""

CPU_WARNINGS: Tuple[Tuple[Type[Warning], str, str], ...] = (
    (UserWarning, "torch.cuda.amp.GradScaler is enabled, but CUDA is not available", "torch.cuda.amp.grad_scaler"),
)
"""On CPU: nerfstudio's Trainer builds a CUDA GradScaler for mixed precision, which it turns off there (and says so)."""


def quiet_nerfstudio_warnings(on_cpu: bool) -> None:
    """Keep the warnings nerfstudio's code raises (NERFSTUDIO_WARNINGS, CPU_WARNINGS on CPU) out of the terminal, each
    matched by category, message and module: in this process, and in the processes it starts (as -W options, which
    also cover the warnings they raise while importing nerfstudio). On CPU, torch's log line that no CUDA runtime is
    found (when torch.compile loads its C++ tools) is left out too.

    Depends on: the messages and modules listed, as nerfstudio 1.1.5 raises them on this torch.
    """
    for category, message, module in NERFSTUDIO_WARNINGS + (CPU_WARNINGS if on_cpu else ()):
        warnings.filterwarnings("ignore", re.escape(message), category, re.escape(module) + r"\Z")
        option = f"ignore:{message}:{category.__name__}:{module}"  # the same filter, as python -W takes it
        if option not in sys.warnoptions:
            sys.warnoptions.append(option)
    if on_cpu:
        logging.getLogger("torch.utils.cpp_extension").setLevel(logging.ERROR)


def proposal_sampler_state(model: NerfactoModel) -> Dict[str, int]:
    """The proposal sampler's counters, which decide whether its networks are updated at a step.

    Depends on: `ProposalNetworkSampler._step` and `._steps_since_update` (private). A checkpoint keeps them so a
    resumed run trains exactly as the uninterrupted one; warm-up restores them so compiling costs no update.
    """
    sampler = model.proposal_sampler
    return {"proposal_step": sampler._step, "proposal_steps_since_update": sampler._steps_since_update}


def set_proposal_sampler_state(model: NerfactoModel, state: Dict[str, int]) -> None:
    model.proposal_sampler._step = int(state["proposal_step"])
    model.proposal_sampler._steps_since_update = int(state["proposal_steps_since_update"])


def depth_sigma(model: DepthNerfactoModel) -> float:
    """The depth losses' sigma as it stands, which depth-nerfacto decays at every training batch (should_decay_sigma).

    Depends on: `DepthNerfactoModel.depth_sigma`, a tensor attribute (not a buffer: no checkpoint keeps it) that
    `_get_sigma` (private) replaces by the decayed value at each call. A checkpoint keeps it so that a resumed run
    continues the schedule where the interrupted one stopped.
    """
    return float(model.depth_sigma)


def set_depth_sigma(model: DepthNerfactoModel, sigma: float) -> None:
    model.depth_sigma = torch.tensor([sigma])


def sample_rays_as_in_training(model: nn.Module) -> None:
    """Let `model` place its samples along rays as it does while it trains, whatever mode the rest of it is in: the
    samplers jitter and the collider keeps the near plane (nerfstudio moves it to 0 outside training).

    Depends on: nerfstudio's ray samplers (`Sampler` subclasses) jittering and its colliders (`SceneCollider`
    subclasses) applying the near plane when their own `training` flag is set, and nothing else in them reading it.
    """
    for module in model.modules():
        if isinstance(module, (Sampler, SceneCollider)):
            module.train()


def hot_modules(model: NerfactoModel) -> List[nn.Module]:
    """The modules every sample passes through: hash grids with their MLPs, colour MLP, encodings, contraction.

    Depends on: the attribute names of `NerfactoField` (mlp_base, mlp_head, direction_encoding, spatial_distortion)
    and `HashMLPDensityField` (mlp_base, or encoding + linear with use_linear).
    """
    field = model.field
    modules = [field.mlp_base, field.mlp_head, field.direction_encoding]
    for network in model.proposal_networks:
        modules += [network.mlp_base] if not network.use_linear else [network.encoding, network.linear]
    if field.spatial_distortion is not None:  # one instance, shared with the proposal networks
        modules.append(field.spatial_distortion)
    return modules


def appearance_codes(field: NerfactoField) -> Optional[Embedding]:
    """The field's appearance embedding (None without one).

    Depends on: `NerfactoField.embedding_appearance`, indexed by the ray samples' camera indices while training.
    """
    return field.embedding_appearance


def set_appearance_codes(field: NerfactoField, codes: Embedding) -> None:
    """Make the field look its appearance codes up in `codes` (an embedding of the same size and dimension)."""
    field.embedding_appearance = codes


@contextmanager
def codes_looked_up_per_ray(field: NerfactoField) -> Iterator[None]:
    """Outside training, let `field` give every ray its own frame's appearance code (it gives all the mean code).

    Depends on: `NerfactoField.get_outputs` reading `self.training` only to choose between per-ray codes and their
    mean (and for transient embeddings, which nerfacto never turns on); the field's submodules keep their own flags.
    """
    if field.embedding_appearance is None:
        yield
        return
    was_training = field.training
    field.training = True
    try:
        yield
    finally:
        field.training = was_training


def replace_forward(module: nn.Module, forward: Callable[..., Any]) -> None:
    """Run `forward` instead of the module's own: parameters and state-dict keys stay nerfstudio's.

    Depends on: nerfstudio calling these modules through `module(...)` (nn.Module.__call__ looks up `forward` on the
    instance first), never through `type(module).forward`.
    """
    module.forward = forward  # type: ignore[method-assign]


def seed_like_ns_train(seed: int) -> None:
    """Seed Python's, numpy's and torch's generators as `ns-train` seeds rank 0.

    Depends on: `nerfstudio.scripts.train._set_random_seed` (private), which `train_loop` calls before set-up.
    """
    # imported here: nerfstudio.scripts.train discovers the plugins' methods, and this module is imported by them
    from nerfstudio.scripts.train import _set_random_seed

    _set_random_seed(seed)


def set_resume_step(trainer: Trainer, start_step: int) -> None:
    """Make nerfstudio's loop continue at `start_step` and end where the uninterrupted run ends.

    Depends on: `Trainer.train` running `range(self._start_step, self._start_step + max_num_iterations)`: nerfstudio
    1.1.5 counts max_num_iterations from the resumed step (later releases count from 0, which this would then cut
    short; the resume test catches it).
    """
    trainer._start_step = start_step
    trainer.config.max_num_iterations -= start_step


def count_progress_to(last_step: int) -> None:
    """Make the terminal's progress (% done) and ETA count towards `last_step`, the run's last step plus one.

    Depends on: `writer.setup_local_writer` storing the Trainer's max_num_iterations as `GLOBAL_BUFFER["max_iter"]`,
    which the local writer divides the step by for "% done" and `writer.put_time` subtracts the step from for the ETA;
    after `set_resume_step` that count starts at the resumed step, not at 0.
    """
    writer.GLOBAL_BUFFER["max_iter"] = last_step


def forget_empty_profile() -> None:
    """Drop nerfstudio's profile of this process if it timed nothing (set-up ended before training did a step), so
    that the process ends without an empty "Printing profiling stats" heading.

    Depends on: `nerfstudio.utils.profiler.PROFILER`, the list `Trainer.setup` puts the run's Profiler in and whose
    first one `flush_profiler` (called by ns-train's launch as it returns) prints, and `Profiler.profiler_dict`.
    """
    if profiler.PROFILER and not profiler.PROFILER[0].profiler_dict:
        profiler.PROFILER.clear()


def first_step(trainer: Trainer) -> int:
    """The step this process's training loop starts at: 0, or the one after the checkpoint a run resumed from.

    Depends on: `Trainer._start_step` (private), where `Trainer.train` starts its loop.
    """
    return trainer._start_step


def leave_pause(trainer: Trainer) -> None:
    """Let nerfstudio's loop go on to its next iteration if the viewer has paused it.

    Depends on: `Trainer.train` sleeping while `training_state == "paused"` and going on once it is "training", as
    the viewer's Resume button sets it.
    """
    if trainer.training_state == "paused":
        trainer.training_state = "training"


def init_scene_without_frustums(viewer: Viewer, train_dataset: InputDataset, train_state: str) -> None:
    """Set up `viewer`'s scene (scene box, training state, ...) without drawing a frustum per training image.

    Depends on: `Viewer.init_scene` drawing `config.max_num_display_images` frustums, reading their pixels, and
    doing nothing else per image. The continual panel draws the released tasks' frustums itself.
    """
    config = viewer.config
    viewer.config = dataclasses.replace(config, max_num_display_images=0)
    try:
        viewer.init_scene(train_dataset=train_dataset, train_state=train_state)  # type: ignore[arg-type]
    finally:
        viewer.config = config


def register_frustum(viewer: Viewer, frame: int, handle: Any, camera_to_world: np.ndarray) -> None:
    """Record a frustum where nerfstudio's viewer keeps its own, so "Hide Train Cams" and camera updates reach it.

    Depends on: `Viewer.camera_handles` and `Viewer.original_c2w`, dicts keyed by training-frame index.
    """
    viewer.camera_handles[frame] = handle
    viewer.original_c2w[frame] = camera_to_world


def set_current_camera(viewer: Viewer, frame: int) -> None:
    """Tell the viewer the browser looks through training frame `frame` (as a click on its frustum does).

    Depends on: `Viewer.current_camera_idx`, which nerfstudio's own frustum click handler sets.
    """
    viewer.current_camera_idx = frame


def training_cameras_shown(viewer: Viewer) -> bool:
    """Whether the viewer shows training cameras now. Depends on: `Viewer.hide_images`, the "Hide Train Cams" button,
    which is visible while the cameras are shown."""
    return bool(viewer.hide_images.visible)


def panel_order(viewer: Viewer) -> float:
    """GUI order just below nerfstudio's status lines, above its tabs. Depends on: `Viewer.stats_markdown`."""
    return viewer.stats_markdown.order + 0.5


def show_resume_button(viewer: Viewer) -> None:
    """Show "Resume Training" where "Pause Training" was, after the plugin paused the Trainer itself.

    Depends on: `Viewer.pause_train` and `Viewer.toggle_pause_button`, nerfstudio's pause/resume button pair.
    """
    if viewer.pause_train.visible:
        viewer.toggle_pause_button()


def world_size_for_vanilla_pipeline(device: str, world_size: int) -> int:
    """The world size to hand `VanillaPipeline.__init__`: 1 for CPU processes, whose model the plugin wraps itself.

    Depends on: `VanillaPipeline.__init__` wrapping the model in `DDP(model, device_ids=[local_rank])` and calling
    `dist.barrier(device_ids=[local_rank])` when world_size > 1, both refused for a CPU model under gloo, and using
    world_size for nothing else (its datamanager only sizes dataloader workers with it).
    """
    return world_size if torch.device(device).type == "cuda" else 1


_nerfstudio_launch: List[Callable[..., None]] = []
"""nerfstudio's `launch`, once `launch_processes_here` has replaced it."""
_when_a_process_fails: List[Callable[[], None]] = []
"""What the launching process does when a process fails (the run folder then says the run failed)."""

PEER_CLOSED = ("Connection closed by peer", "Connection reset by peer", "Broken pipe")
"""gloo's words for a connection another process closed by ending (its collectives then fail in every process)."""

PEER_LOST_EXIT = 75
"""Exit status of a process whose collective failed because another process ended: the launcher names that one."""


class ProcessFailed(Exception):
    """A process's one-line error, for the launching process to print (the process itself prints nothing)."""


def launch_processes_here(when_a_process_fails: Callable[[], None]) -> None:
    """Route `ns-train --machine.num-devices N` (N > 1) through `process_worker` and `launch_reporting_one_line`;
    `when_a_process_fails` runs in the launching process when a process ends by an error or a signal.

    Depends on: `nerfstudio.scripts.train.main` calling `config.save_config()` right before `launch(...)` (with
    keyword arguments), and `main` and `launch` looking up `launch` and `_distributed_worker` among the module's
    globals when they run. mp.spawn pickles the worker by name: the spawned processes import it from this module.
    """
    from nerfstudio.scripts import train

    _when_a_process_fails[:] = [when_a_process_fails]
    if not _nerfstudio_launch:
        _nerfstudio_launch.append(train.launch)
        train.launch = launch_reporting_one_line
        train._distributed_worker = process_worker


def launch_reporting_one_line(**launch_arguments: Any) -> None:
    """nerfstudio's `launch`; a failed process ends the run with one line (mp.spawn has stopped the others).

    Ctrl-C reaches the processes too, and they answer it (process 0 checkpoints the step and prints how to resume):
    the launching process ignores it meanwhile, as nerfstudio's launch would stop them at once, and then exits with
    their code. torch's warning that it stops the other processes is left out: the one line says so.
    """
    answered_by_processes = signal.signal(signal.SIGINT, signal.SIG_IGN)
    spawn_log = logging.getLogger("torch.multiprocessing.spawn")
    spawn_level = spawn_log.level
    spawn_log.setLevel(logging.ERROR)
    try:
        _nerfstudio_launch[0](**launch_arguments)
    except (ProcessExitedException, ProcessRaisedException) as error:
        if isinstance(error, ProcessExitedException) and error.exit_code in EXIT_CODES.values():
            raise SystemExit(error.exit_code) from None
        for when_failed in _when_a_process_fails:
            when_failed()
        raise SystemExit(failed_process_line(error, launch_arguments["config"].method_name)) from None
    finally:
        spawn_log.setLevel(spawn_level)
        signal.signal(signal.SIGINT, answered_by_processes)


def failed_process_line(error: Exception, method: str) -> str:
    """The one line that says why the processes stopped: the failed process's own line (ProcessFailed), else how it
    ended.

    Depends on: torch's mp.spawn putting a failed process's traceback (whose last line is "<exception type>: <its
    message>") into ProcessRaisedException's message, and ProcessExitedException's first line saying how it ended.
    """
    if isinstance(error, ProcessRaisedException):
        last_line = str(error).strip().splitlines()[-1]
        reported = f"{ProcessFailed.__module__}.{ProcessFailed.__qualname__}: "
        if last_line.startswith(reported):
            return last_line[len(reported) :]
        return f"{method}: error: process {error.error_index}: {last_line}; the other processes were stopped"
    if isinstance(error, ProcessExitedException) and error.exit_code == PEER_LOST_EXIT:
        how = f"process {error.error_index} lost its connection to another process"
    else:
        how = first_line(error)
    return f"{method}: error: {how}; the other processes were stopped"


def lost_a_peer(error: BaseException) -> bool:
    """Whether `error` is a collective failing because another process ended: that process's end is the cause.

    Depends on: gloo's messages for a closed connection (PEER_CLOSED), as torch raises them in a RuntimeError.
    """
    return isinstance(error, RuntimeError) and any(words in str(error) for words in PEER_CLOSED)


def process_worker(
    local_rank: int,
    main_func: Callable[..., Any],
    world_size: int,
    num_devices_per_machine: int,
    machine_rank: int,
    dist_url: str,
    config: Any,
    timeout: timedelta,
    device_type: Literal["cpu", "cuda", "mps"] = "cuda",
) -> Any:
    """nerfstudio's `_distributed_worker` (process group, local group, `main_func`), which on CPU skips its CUDA
    checks; an error is handed to the launching process as one line naming its rank (ProcessFailed), and a process
    that failed only because another one ended (its connection to it closed) exits quietly: the launcher names that
    one. A process that exits by its own decision (Ctrl-C, answered by every rank at one step) destroys its process
    group first, as nerfstudio's worker does after training: one left alive may abort the interpreter's exit (gloo's
    threads still hold its work), and the launcher would report a SIGABRT instead of the interrupt. DDP's reducer
    may keep the group alive even so: the ranks other than 0 (which save and log nothing) leave without the
    interpreter's finalization.

    Depends on: `_distributed_worker` taking these arguments and asserting `torch.cuda.is_available()` and
    `num_devices_per_machine <= torch.cuda.device_count()` before it calls `main_func`, whatever the device type.
    """
    from nerfstudio.scripts.train import _distributed_worker

    cuda_checks = ExitStack()
    if device_type != "cuda":
        cuda_checks.enter_context(mock.patch.object(torch.cuda, "is_available", return_value=True))
        cuda_checks.enter_context(mock.patch.object(torch.cuda, "device_count", return_value=num_devices_per_machine))

    def train_without_cuda_checks(*args: Any) -> Any:
        cuda_checks.close()  # training sees the machine as it is
        return main_func(*args)

    rank = machine_rank * num_devices_per_machine + local_rank
    try:
        with cuda_checks:
            return _distributed_worker(
                local_rank, train_without_cuda_checks, world_size, num_devices_per_machine, machine_rank, dist_url,
                config, timeout, device_type,
            )  # fmt: skip
    except SystemExit as exit_:
        if isinstance(exit_.code, str):  # a one-line error of the plugin's (bad input, a file it cannot write)
            raise ProcessFailed(exit_.code) from None
        if dist.is_initialized():
            dist.destroy_process_group()
        if rank != 0:  # DDP's reducer may keep the group alive, whose gloo threads can abort the interpreter's exit
            sys.stdout.flush()
            sys.stderr.flush()
            os._exit(exit_.code or 0)
        raise
    except Exception as error:
        if lost_a_peer(error):
            raise SystemExit(PEER_LOST_EXIT) from None
        line = f"{config.method_name}: error: process {rank}: {first_line(error)}; the other processes were stopped"
        raise ProcessFailed(line) from None


def remove_frustum(viewer: Viewer, frame: int) -> None:
    """Take a frustum drawn by `register_frustum` out of the scene and out of the viewer's camera handles.

    Depends on: `Viewer.camera_handles` and `Viewer.original_c2w`, as `register_frustum`.
    """
    viewer.camera_handles.pop(frame).remove()
    viewer.original_c2w.pop(frame)


def set_render_defaults(viewer: Viewer, max_res: int, train_util: float) -> None:
    """Start the viewer's "Max res" and "Train Util" sliders at other values than nerfstudio's 512 and 0.85.

    Depends on: `ControlPanel._max_res` and `._train_util` (private ViewerSliders), which the render thread
    (`RenderStateMachine._calculate_image_res`) and `Viewer.update_scene` read through `max_res` / `train_util`.
    """
    viewer.control_panel._max_res.value = max_res
    viewer.control_panel._train_util.value = train_util


RENDER_STOP_SECONDS = 30.0
"""How long the process waits at exit for each render thread to end (an interrupted render ends within a line)."""

_rendering_viewers: "weakref.WeakSet[Viewer]" = weakref.WeakSet()
"""Viewers whose render threads `stop_rendering` ends when the process exits."""


def stop_rendering_at_exit(viewer: Viewer) -> None:
    """End `viewer`'s render threads before the process exits, whatever ends it: a render thread still running torch
    code while the interpreter shuts down aborts the process ("terminate called without an active exception"). A
    browser still sending as the process exits is not answered, and not reported (see quiet_viewer_connections)."""
    if not _rendering_viewers:
        atexit.register(_stop_every_viewer_rendering)
        threading._register_atexit(quiet_viewer_connections)  # type: ignore[attr-defined]
    _rendering_viewers.add(viewer)


def quiet_viewer_connections() -> None:
    """Log nothing more of the viewers' websocket connections. As the interpreter exits it shuts down every thread
    pool, viser's too; a browser message arriving after that fails its connection handler, which websockets reports
    with a traceback ("cannot schedule new futures after shutdown"), after the process's last line.

    Depends on: viser 0.2.7's `infra.WebsockServer` handing each incoming message to its ThreadPoolExecutor from the
    connection handler; websockets' legacy server logging a failed handler to the `websockets.server` logger; Python
    (3.9 on) stopping thread pools from a `threading._register_atexit` callback, which runs callbacks registered later
    first: this one, registered once a viewer exists, before the pools stop."""
    logging.getLogger("websockets.server").disabled = True


def _stop_every_viewer_rendering() -> None:
    for viewer in list(_rendering_viewers):
        stop_rendering(viewer)
    _rendering_viewers.clear()


def stop_rendering(viewer: Viewer) -> None:
    """Stop and wait for the render threads of `viewer` (one per browser), interrupting a render under way.

    Depends on: `Viewer.render_statemachines` (a RenderStateMachine thread per client) and RenderStateMachine's
    `running` (its loop's condition), `interrupt_render_flag` (ends a render at its next Python line) and
    `render_trigger` (the event its loop waits on).
    """
    machines = list(viewer.render_statemachines.values())
    for machine in machines:
        machine.running = False
        machine.interrupt_render_flag = True
        machine.render_trigger.set()
    for machine in machines:
        if has_started(machine, RENDER_STOP_SECONDS):  # once started it sees `running` off and ends
            machine.join(timeout=RENDER_STOP_SECONDS)


def has_started(thread: threading.Thread, seconds: float) -> bool:
    """Whether `thread` has started, waiting up to `seconds` for it: nerfstudio's Viewer.handle_new_client stores a
    browser's render thread in `render_statemachines` before it starts it, and a thread not started cannot be joined."""
    deadline = time.monotonic() + seconds
    while thread.ident is None:
        if time.monotonic() > deadline:
            return False
        time.sleep(0.01)
    return True


def show_step(viewer: Viewer, step: int) -> None:
    """Write `step` into nerfstudio's "Step:" status line, which nerfstudio itself updates only when it renders.

    Depends on: `Viewer.update_step`, which rewrites the first line of `Viewer.stats_markdown`.
    """
    viewer.update_step(step)


def disable_training_buttons(viewer: Viewer) -> None:
    """Grey out nerfstudio's "Pause Training" / "Resume Training" once training has ended (they would do nothing).

    Depends on: `Viewer.pause_train` and `Viewer.resume_train`, viser button handles.
    """
    viewer.pause_train.disabled = True
    viewer.resume_train.disabled = True


def rerender(viewer: Viewer) -> None:
    """Render every connected browser's view again (after the model's weights changed under the viewer).

    Depends on: `Viewer._trigger_rerender` (private), which nerfstudio's own controls call.
    """
    viewer._trigger_rerender()


TRAINER_OVERRIDES = ("_load_checkpoint", "_init_viewer_state", "_check_viewer_warnings", "_after_train")
"""Private methods of nerfstudio's `Trainer` that `ContinualTrainer` overrides: resuming (`_load_checkpoint`), the
viewer's start-up note (`_check_viewer_warnings`, called by `setup` right after the viewer starts) and the end of
training (`_after_train`, called by `train` after its loop, which it leaves with `Trainer.step` one past the last step
trained when the pipeline stopped it: the loop sets `step` before it checks `stop_training`); `LiveViewerTrainer`
overrides the viewer's scene (`_init_viewer_state`, called at the start of `train`)."""


def viewer_camera_message(
    position: np.ndarray, look_at: np.ndarray, up: np.ndarray, fov: float, aspect: float
) -> bytes:
    """The bytes a browser sends the viewer when its camera is at `position` looking at `look_at` (viser units), so
    that a page without a browser can ask for renders.

    Depends on: viser 0.2.7's wire format: `viser._messages.ViewerCameraMessage` (OpenCV camera, +z forward) as its
    `as_serializable_dict()`, msgpack-encoded (client API version 0).
    """
    from viser import _messages

    forward = (look_at - position) / np.linalg.norm(look_at - position)
    down = -(up - np.dot(up, forward) * forward)
    down = down / np.linalg.norm(down)
    rotation = vtf.SO3.from_matrix(np.stack([np.cross(down, forward), down, forward], axis=1))
    message = _messages.ViewerCameraMessage(
        wxyz=tuple(float(v) for v in rotation.wxyz),  # type: ignore[arg-type]
        position=tuple(float(v) for v in position),  # type: ignore[arg-type]
        fov=fov,
        aspect=aspect,
        look_at=tuple(float(v) for v in look_at),  # type: ignore[arg-type]
        up_direction=tuple(float(v) for v in up),  # type: ignore[arg-type]
    )
    return msgspec.msgpack.encode(message.as_serializable_dict())


def viewer_render_rays_per_second() -> Optional[float]:
    """The viewer's render speed, averaged over its latest renders, or None before the first one.

    Depends on: `nerfstudio.utils.writer.GLOBAL_BUFFER["events"]`, where the viewer's render thread puts
    `EventName.VIS_RAYS_PER_SEC` (and `Viewer.update_scene` reads it to space its renders).
    """
    event = writer.GLOBAL_BUFFER.get("events", {}).get(writer.EventName.VIS_RAYS_PER_SEC.value)
    return None if event is None else float(event["avg"])


class DeferredPauseTrainer(Trainer):
    """nerfstudio's Trainer whose pause can wait for the end of the running iteration (`pause_waits`), and which says
    when its training state changes (`training_state_changed`).

    Depends on: `Trainer.__init__` assigning `self.training_state`, the viewer's Pause / Resume buttons assigning it
    from the viewer's thread (`Viewer._toggle_training_state`), and `Trainer.train` waiting before each iteration
    while it is "paused": a property stands in for nerfstudio's attribute.
    """

    pause_requested = False
    """A pause asked for while `pause_waits()`: it starts at the end of the iteration (`pause_now`)."""
    _training_state: TrainingState

    @property
    def training_state(self) -> TrainingState:
        return self._training_state

    @training_state.setter
    def training_state(self, state: TrainingState) -> None:
        if state == "paused" and self.pause_waits():
            self.pause_requested = True
        else:
            self._training_state = state
        self.training_state_changed()

    def pause_waits(self) -> bool:
        """Whether a pause waits for the end of the running iteration instead of stopping the loop before the next."""
        return False

    def training_state_changed(self) -> None:
        """Called whenever `training_state` is assigned or a requested pause starts, from the thread that did it."""

    def pause_now(self) -> bool:
        """Whether training pauses (or stays paused) from this iteration's end: a requested pause starts here."""
        if self.pause_requested:
            self._training_state = "paused"
            self.pause_requested = False
            self.training_state_changed()
        return self._training_state == "paused" and not self.stop_training


def wrap_model(pipeline: VanillaPipeline, wrap: Callable[[nn.Module], nn.Module]) -> None:
    """Make the pipeline train `wrap(model)` (the CPU processes' DDP wrapper); `pipeline.model` stays the model.

    Depends on: `VanillaPipeline` keeping the model it trains in `_model` (where nerfstudio puts its own DDP wrapper on
    CUDA) and its `model` property unwrapping a wrapper's `module`.
    """
    pipeline._model = wrap(pipeline._model)  # type: ignore[assignment]


def trained_model(pipeline: VanillaPipeline) -> nn.Module:
    """The model as training calls it: with several processes, the DDP wrapper whose backward all-reduces gradients.

    Depends on: `VanillaPipeline._model`, as `wrap_model`.
    """
    return pipeline._model


def model_state_of(pipeline_state: Mapping[str, Any]) -> Dict[str, Any]:
    """The model's part of a pipeline's state dict, keyed as the model's own state dict.

    Depends on: `VanillaPipeline` registering its model as `_model` (state-dict keys `_model.`).
    """
    prefix = "_model."
    return {key[len(prefix) :]: value for key, value in pipeline_state.items() if key.startswith(prefix)}


def model_keys_of_one_process(pipeline: VanillaPipeline, state: Mapping[str, Any]) -> Dict[str, Any]:
    """The pipeline's state dict `state` with the model's keys as one process has them (no DDP `module.`).

    Depends on: `VanillaPipeline` registering its model as `_model` (state-dict keys `_model.`) and DDP keeping the
    wrapped model as `module`.
    """
    if pipeline.model is pipeline._model:
        return dict(state)
    wrapped = "_model.module."
    return {("_model." + key[len(wrapped) :] if key.startswith(wrapped) else key): v for key, v in state.items()}


def cameras_as_parsed(dataset: InputDataset) -> Cameras:
    """The dataset's cameras as the dataparser gave them: the sizes of the image files, before the dataset's
    downscale (`dataset.cameras` has that applied).

    Depends on: `InputDataset` keeping the DataparserOutputs it was built from in `_dataparser_outputs`.
    """
    return dataset._dataparser_outputs.cameras


@contextmanager
def viewer_answering_when_ready() -> Iterator[None]:
    """Viser servers started inside the context hold every request (the page and its websocket) until it exits: a
    browser that opens the viewer meanwhile waits, then gets the page as complete as the context built it.

    Depends on: viser 0.2.7's `infra.WebsockServer` serving its page and its websocket through
    `websockets.server.serve(..., process_request=...)` (an alias of websockets' legacy server), called while its `ViserServer`
    is constructed. Held requests have no handshake timeout (websockets' is 10 s; set-up may take longer).
    """
    ready = threading.Event()

    def serve_when_ready(*args: Any, process_request: Optional[Callable[..., Any]] = None, **kwargs: Any) -> Any:
        async def when_ready(path: str, headers: Any) -> Any:
            while not ready.is_set():
                await asyncio.sleep(0.05)
            return None if process_request is None else await process_request(path, headers)

        return legacy_serve(*args, **{**kwargs, "process_request": when_ready, "open_timeout": None})

    try:
        with mock.patch.object(websockets.server, "serve", serve_when_ready):
            yield
    finally:
        ready.set()


def watch_viewer_renders(model: Model, rendered: Callable[[Cameras, bool], None]) -> None:
    """Call `rendered(camera, completed)` after each render the viewer makes with `model`; `completed` is False for a
    render the viewer interrupted (the camera moved, a rerender was asked for).

    Depends on: the viewer's render thread (`RenderStateMachine._render_img`) rendering through
    `viewer.get_model().get_outputs_for_camera(camera, obb_box=...)`, looked up on the model instance, and raising out
    of it to interrupt a render.
    """
    render = model.get_outputs_for_camera

    def render_and_say(camera: Cameras, **options: Any) -> Dict[str, torch.Tensor]:
        completed = False
        try:
            outputs = render(camera, **options)
            completed = True
            return outputs
        finally:
            rendered(camera, completed)

    model.get_outputs_for_camera = render_and_say  # type: ignore[method-assign]
