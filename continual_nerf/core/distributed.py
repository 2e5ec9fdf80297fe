"""The continual state across processes, when nerfstudio's launcher runs one per device (`--machine.num-devices N`).

nerfstudio wraps the model in DistributedDataParallel, which all-reduces the gradients of every step: each rank
trains on its own rays and all hold the same weights. What DDP does not cover is decided here: rank 0 alone ends
tasks (timed budgets, the viewer's buttons and a streaming capture are seen differently by every rank), evaluates,
writes and checkpoints; the others follow its decisions, which it broadcasts every step. With one process every
helper returns at once.
"""

from __future__ import annotations

import time
from enum import IntEnum
from typing import Callable, Dict, Union

import torch
import torch.distributed as dist
from nerfstudio.engine.trainer import Trainer
from nerfstudio.utils import comms
from torch import Tensor, nn
from torch.nn.parallel import DistributedDataParallel

PAUSE_POLL_SECONDS = 0.2
"""How often rank 0 tells the other ranks whether the viewer still pauses training."""


class TaskDecision(IntEnum):
    """What rank 0 decided at the end of an iteration, for every rank to do."""

    CONTINUE = 0
    """The open task trains on."""
    NEXT_TASK = 1
    """The open task ends; the next one opens."""
    LAST_TASK_DONE = 2
    """The last task ended: the run stops."""


def is_distributed() -> bool:
    return comms.get_world_size() > 1


def is_main() -> bool:
    """Whether this process evaluates, writes results and checkpoints and serves the viewer (global rank 0)."""
    return comms.is_main_process()


def _collective_device(device: Union[str, torch.device]) -> torch.device:
    # NCCL communicates CUDA tensors only; gloo CPU tensors
    return torch.device(device) if dist.get_backend() == dist.Backend.NCCL else torch.device("cpu")


def decided_by_main(value: int, device: Union[str, torch.device]) -> int:
    """Rank 0's `value`, on every rank: the others pass anything and get rank 0's."""
    if not is_distributed():
        return value
    tensor = torch.tensor([value], dtype=torch.long, device=_collective_device(device))
    dist.broadcast(tensor, src=0)
    return int(tensor.item())


def barrier() -> None:
    """Wait until every rank is here (the task switch, while rank 0 evaluates and checkpoints)."""
    if is_distributed():
        comms.synchronize()


@torch.no_grad()
def copy_from_main(module: nn.Module, device: Union[str, torch.device]) -> None:
    """Overwrite every parameter and buffer of `module` (on `device`) with rank 0's, bit for bit (its extra state,
    such as the proposal sampler's step counters, follows the steps, which all ranks share)."""
    if not is_distributed():
        return
    collective_device = _collective_device(device)
    tensors = [value for value in module.state_dict().values() if isinstance(value, Tensor)]
    for tensor in tensors:
        staged = tensor.to(collective_device)  # the tensor itself when it is there already
        dist.broadcast(staged, src=0)
        if staged is not tensor:
            tensor.copy_(staged)


@torch.no_grad()
def averaged_over_ranks(tensors: Dict[str, Tensor]) -> Dict[str, Tensor]:
    """The mean over ranks of each tensor (in place): a per-rank estimate becomes one of N times the samples."""
    if is_distributed():
        world_size = comms.get_world_size()
        for tensor in tensors.values():
            dist.all_reduce(tensor, op=dist.ReduceOp.SUM)
            tensor.div_(world_size)
    return tensors


def data_parallel(model: nn.Module) -> nn.Module:
    """The model wrapped as nerfstudio wraps it on CUDA, for CPU processes (DDP takes no device_ids for those)."""
    return DistributedDataParallel(model, find_unused_parameters=True)


def hold_while_paused(trainer: Trainer, paused: Callable[[], bool], step: int) -> None:
    """Keep every rank here while the viewer (on rank 0) pauses training: `paused()` says so on rank 0.

    Rank 0 would otherwise wait in nerfstudio's loop while the others block in the next step's gradient all-reduce,
    which the process group's timeout ends. Here rank 0 keeps telling them, every PAUSE_POLL_SECONDS, whether the
    pause goes on, with the train lock released so that the viewer renders.
    """
    if not is_distributed():
        return
    device = trainer.pipeline.device
    while decided_by_main(int(is_main() and paused()), device):
        trainer.train_lock.release()  # held around the training callbacks; the viewer renders under it
        try:
            time.sleep(PAUSE_POLL_SECONDS)
        finally:
            trainer.train_lock.acquire()
