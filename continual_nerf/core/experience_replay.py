"""Experience replay (optional): a bounded buffer of real pixels of closed tasks, kept beside the replay oracle.

The paper keeps no image. With `--pipeline.datamanager.replay-buffer-size` above 0, a task's end puts a uniform
random subset of its training pixels into the buffer (CLNeRF's experience replay; neural SLAM keeps keyframe pixels
the same way); every closed task keeps an equal share of the buffer's capacity. Rays drawn from the buffer are
supervised by their stored colours (and depth, when the model trains on depth), the rest of the replay by the
oracle. The pipeline owns the buffer, so it is in every checkpoint.
"""

from __future__ import annotations

from typing import Any, Dict, Optional, Tuple

import torch
from torch import Tensor, nn


class ExperienceReplayBuffer(nn.Module):
    """Flat pixel numbers (the training frames' numbering, from which the datamanager regenerates rays) and 8-bit
    colours of closed tasks, at most `capacity(total)` of them, an equal share per task."""

    def __init__(self, size: float) -> None:
        super().__init__()
        self.size = size
        """Pixels to keep: below 1 a fraction of the capture's training pixels, otherwise a count."""
        self.flat = torch.empty(0, dtype=torch.long)
        self.rgb = torch.empty(0, 3, dtype=torch.uint8)
        self.task = torch.empty(0, dtype=torch.long)
        self.depth: Optional[Tensor] = None
        """z-depth (scene units, 0: none) of each stored pixel, when the tasks closed with depth; None otherwise."""

    def __len__(self) -> int:
        return len(self.flat)

    @property
    def enabled(self) -> bool:
        return self.size > 0

    @property
    def nbytes(self) -> int:
        tensors = (self.flat, self.rgb, self.task) + (() if self.depth is None else (self.depth,))
        return sum(tensor.numel() * tensor.element_size() for tensor in tensors)

    def capacity(self, total_pixels: int) -> int:
        """Pixels the buffer holds at most, for a capture of `total_pixels` training pixels."""
        return int(round(self.size * total_pixels)) if self.size < 1 else int(self.size)

    @torch.no_grad()
    def add_task(self, task: int, flat: Tensor, rgb: Tensor, total_pixels: int, depth: Optional[Tensor] = None) -> None:
        """Keep a uniform random subset of closed task `task`'s pixels (`flat`, colours in [0, 1], `depth` when the
        model trains on it) and shrink the earlier tasks' shares, so that each of the tasks closed so far keeps
        capacity / (task + 1) pixels."""
        shares = _equal_shares(self.capacity(total_pixels), task + 1)
        # entries are stored in random order, so the first n of a task are a uniform random subset of its pixels
        kept = [torch.nonzero(self.task == j).view(-1)[: shares[j]] for j in range(task)]
        keep = torch.cat(kept) if kept else torch.empty(0, dtype=torch.long)
        chosen = torch.randperm(len(flat))[: shares[task]]
        self.flat = torch.cat([self.flat[keep], flat[chosen].cpu()])
        self.rgb = torch.cat([self.rgb[keep], (rgb[chosen].cpu().clamp(0, 1) * 255).round().to(torch.uint8)])
        self.task = torch.cat([self.task[keep], torch.full((len(chosen),), task, dtype=torch.long)])
        if depth is not None:
            kept_depth = torch.zeros(len(keep)) if self.depth is None else self.depth[keep]
            self.depth = torch.cat([kept_depth, depth[chosen].cpu().float()])

    def sample(self, num: int) -> Tuple[Tensor, Tensor, Optional[Tensor]]:
        """`num` stored pixels drawn uniformly: their flat numbers, colours in [0, 1] and depth (None: not kept)."""
        picked = torch.randint(0, len(self.flat), (num,))
        depth = None if self.depth is None else self.depth[picked]
        return self.flat[picked], self.rgb[picked].float() / 255, depth

    def tasks_held(self) -> Dict[int, int]:
        """Pixels held per closed task."""
        tasks, counts = torch.unique(self.task, return_counts=True)
        return dict(zip(tasks.tolist(), counts.tolist()))

    def get_extra_state(self) -> Dict[str, Any]:
        return {
            "flat": self.flat,
            "rgb": self.rgb,
            "task": self.task,
            **({} if self.depth is None else {"depth": self.depth}),
        }

    def set_extra_state(self, state: Dict[str, Any]) -> None:
        self.flat, self.rgb, self.task = state["flat"], state["rgb"], state["task"]
        self.depth = state.get("depth")


def _equal_shares(capacity: int, num_tasks: int) -> list:
    """`capacity` split over `num_tasks`, the earliest tasks taking the remainder."""
    return [capacity // num_tasks + (1 if j < capacity % num_tasks else 0) for j in range(num_tasks)]
