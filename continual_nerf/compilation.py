"""torch.compile for the hash grids and MLPs of a nerfacto-family model, with an eager fallback.

Compiled code is attached to a module's `forward` only: the modules, their parameters and their
state-dict keys stay nerfstudio's (no `_orig_mod.` prefix), so checkpoints, ns-eval, ns-render and the
replay oracle's copy see the same model whether or not it was compiled.
"""

from __future__ import annotations

import contextlib
import contextvars
import functools
import threading
from typing import Any, Callable, Iterator

import torch
from nerfstudio.cameras.rays import RayBundle
from nerfstudio.models.nerfacto import NerfactoModel
from nerfstudio.utils.external import TCNN_EXISTS
from nerfstudio.utils.rich_utils import CONSOLE
from torch import nn

from continual_nerf.errors import first_line
from continual_nerf.nerfstudio_compat import (
    hot_modules,
    proposal_sampler_state,
    replace_forward,
    set_proposal_sampler_state,
)


class CompiledForward:
    """A module's forward run through torch.compile, or eager once compiling has failed anywhere.

    torch.compile compiles at the first call, so that is where a missing C++ compiler or Triton, or an
    unsupported Python, shows: the first failure prints one line and every compiled forward runs eager
    from then on.
    """

    failed = False
    """Set for every instance by the first failure: one notice, and no half-compiled model."""

    def __init__(self, eager: Callable[..., Any], name: str) -> None:
        self.eager = eager
        self.name = name
        self.compiled: Callable[..., Any] = eager
        try:
            # dynamic: replayed rays and evaluation chunks change the batch size from call to call
            self.compiled = torch.compile(eager, dynamic=True)
        except Exception as error:  # noqa: BLE001 - whatever stops compilation, eager still runs
            self._fail(error)

    def _fail(self, error: Exception) -> None:
        if not CompiledForward.failed:
            CONSOLE.print(
                f"[yellow]torch.compile unavailable ({self.name}: {first_line(error)}); running the model eager"
            )
        CompiledForward.failed = True

    def __call__(self, *args: Any, **kwargs: Any) -> Any:
        # the viewer renders from its own thread; compiling there could race the training thread's compilation
        if CompiledForward.failed or threading.current_thread() is not threading.main_thread():
            return self.eager(*args, **kwargs)
        try:
            return self.compiled(*args, **kwargs)
        except Exception as error:  # noqa: BLE001 - an error of the model itself raises again from eager
            self._fail(error)
            return self.eager(*args, **kwargs)


def compile_model(model: NerfactoModel) -> None:
    """Run the hot modules of `model` through torch.compile (falling back to eager if it cannot compile)."""
    if model.config.implementation == "tcnn" and TCNN_EXISTS:
        CONSOLE.print("tiny-cuda-nn's fused kernels run the hash grids and MLPs: nothing to compile")
        return
    for module in hot_modules(model):
        replace_forward(module, CompiledForward(module.forward, type(module).__name__))


def is_compiled(model: nn.Module) -> bool:
    """Whether `model` is a nerfacto-family model whose hot modules run compiled code (compiling has not failed)."""
    if not isinstance(model, NerfactoModel) or CompiledForward.failed:
        return False
    return isinstance(model.field.mlp_head.forward, CompiledForward)


def random_rays(model: NerfactoModel, num_rays: int) -> RayBundle:
    """Rays from the scene box's centre in random directions, on the model's device."""
    directions = torch.nn.functional.normalize(torch.randn(num_rays, 3, device=model.device), dim=-1)
    return RayBundle(
        origins=model.scene_box.get_center().to(model.device).expand(num_rays, 3),
        directions=directions,
        pixel_area=torch.full((num_rays, 1), 1e-6, device=model.device),
        camera_indices=torch.zeros(num_rays, 1, dtype=torch.long, device=model.device),
    )


def warm_up(
    model: nn.Module, num_rays: int, with_gradients: bool = True, progress: Callable[[str], None] = lambda part: None
) -> None:
    """Compile now rather than in the first training steps, so that a timed task (--seconds-per-task) counts training.

    Renders `num_rays` rays (the training batch: compiled code is specialised on size ranges) with gradients (a
    training step) and without (proposal rounds that skip their update, evaluation, the replay oracle); the
    parameters, their gradients, the proposal sampler's counters and the random generators are left as they were.
    `progress` is told which part is compiling ("training pass 1 of 2", ...), for the viewer's panel.
    """
    if not isinstance(model, NerfactoModel) or not is_compiled(model):
        return
    CONSOLE.print("Compiling the hash grids and MLPs (torch.compile)...")
    was_training = model.training
    counters = proposal_sampler_state(model)
    devices = [model.device] if model.device.type == "cuda" else []
    with torch.random.fork_rng(devices=devices):
        passes = 2 if with_gradients else 1
        if with_gradients:
            progress(f"training pass 1 of {passes}")
            model.train()
            model(random_rays(model, num_rays))["rgb"].sum().backward()
            model.zero_grad(set_to_none=True)
        progress(f"rendering pass {passes} of {passes}")
        with torch.no_grad():
            model.eval()
            model(random_rays(model, num_rays))
    model.train(was_training)
    set_proposal_sampler_state(model, counters)


KEEP_INPUT_GRADIENTS: contextvars.ContextVar[bool] = contextvars.ContextVar("keep_input_gradients", default=False)
"""Set within `input_gradients()`: modules that stop_input_gradients detached keep their input's gradient."""


def stop_input_gradients(module: nn.Module) -> None:
    """Detach the input of `module`: autograd then skips the gradient with respect to it (except within
    `input_gradients()`)."""
    forward = module.forward

    @functools.wraps(forward)
    def detached_forward(in_tensor: torch.Tensor) -> torch.Tensor:
        return forward(in_tensor if KEEP_INPUT_GRADIENTS.get() else in_tensor.detach())

    replace_forward(module, detached_forward)


@contextlib.contextmanager
def input_gradients() -> Iterator[None]:
    """Within it, gradients flow through the inputs that stop_input_gradients detaches: fitting a test frame's pose
    needs the gradient with respect to the sample positions."""
    token = KEEP_INPUT_GRADIENTS.set(True)
    try:
        yield
    finally:
        KEEP_INPUT_GRADIENTS.reset(token)
