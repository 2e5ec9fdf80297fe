"""Every place the plugin relies on nerfstudio internals (private attributes, methods or behaviours of 1.1.5).

The rest of the package goes through nerfstudio's public classes and its documented extension points (configs with
`_target`, entry points, training callbacks, ViewerElements). What is here may change in another nerfstudio
release: each item says what it depends on, and tests/test_nerfstudio_compat.py fails loudly if one stops holding.
pyproject.toml pins nerfstudio==1.1.5 until a newer release has passed those tests.
"""

from __future__ import annotations

import dataclasses
from contextlib import ExitStack, contextmanager
from datetime import timedelta
from typing import Any, Callable, Dict, Iterator, List, Literal
from unittest import mock

import numpy as np
import torch
import torchmetrics.image.lpip
from nerfstudio.data.datasets.base_dataset import InputDataset
from nerfstudio.engine.trainer import Trainer
from nerfstudio.models.nerfacto import NerfactoModel
from nerfstudio.viewer.viewer import VISER_NERFSTUDIO_SCALE_RATIO, Viewer
from torch import nn
from torch.multiprocessing import ProcessExitedException, ProcessRaisedException

from continual_nerf.errors import first_line

__all__ = ["VISER_NERFSTUDIO_SCALE_RATIO"]


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


def launch_processes_here() -> None:
    """Route `ns-train --machine.num-devices N` (N > 1) through `process_worker` and `launch_reporting_one_line`.

    Depends on: `nerfstudio.scripts.train.main` calling `config.save_config()` right before `launch(...)` (with
    keyword arguments), and `main` and `launch` looking up `launch` and `_distributed_worker` among the module's
    globals when they run. mp.spawn pickles the worker by name: the spawned processes import it from this module.
    """
    from nerfstudio.scripts import train

    if not _nerfstudio_launch:
        _nerfstudio_launch.append(train.launch)
        train.launch = launch_reporting_one_line
        train._distributed_worker = process_worker


def launch_reporting_one_line(**launch_arguments: Any) -> None:
    """nerfstudio's `launch`; a failed process ends the run with one line (mp.spawn has stopped the others)."""
    try:
        _nerfstudio_launch[0](**launch_arguments)
    except (ProcessExitedException, ProcessRaisedException) as error:
        method = launch_arguments["config"].method_name
        raise SystemExit(f"{method}: error: {first_line(error)}; the other processes were stopped") from None


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
    checks; an error ends the process with one line naming its rank.

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
    except Exception as error:
        raise SystemExit(f"{config.method_name}: error: process {rank}: {first_line(error)}") from None
