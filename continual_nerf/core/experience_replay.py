"""Experience replay (optional): a bounded buffer of real pixels of closed tasks, kept beside the replay oracle.

The paper keeps no image. With `--pipeline.datamanager.replay-buffer-fraction` (a share of the training pixels) or
`--pipeline.datamanager.replay-buffer-pixels` (a count) above 0, a task's end puts a uniform random subset of its
training pixels into the buffer (CLNeRF's experience replay; neural SLAM keeps keyframe pixels
the same way); every closed task keeps an equal share of the buffer's capacity. Rays drawn from the buffer are
supervised by their stored colours (and depth, when the model trains on depth), the rest of the replay by the
oracle. With `--pipeline.datamanager.replay-buffer-keeps renders` the stored colours are the model's renders of those
pixels as their task closes, not the captured ones: the targets of a closed task stay what it reached, while the
oracle's drift a little at every task switch. The pipeline owns the buffer, so it is in every checkpoint.
"""

from __future__ import annotations

from typing import Any, Callable, Dict, Optional, Tuple

import torch
from torch import Tensor, nn


class ExperienceReplayBuffer(nn.Module):
    """Flat pixel numbers (the training frames' numbering, from which the datamanager regenerates rays) and 8-bit
    colours of closed tasks, at most `capacity(total)` of them, an equal share per task."""

    def __init__(self, fraction: float = 0.0, pixels: int = 0, keeps_renders: bool = False) -> None:
        super().__init__()
        self.fraction = fraction
        """Pixels to keep, as a share of the capture's training pixels (0 to 1)."""
        self.pixels = pixels
        """Pixels to keep, as a count (instead of `fraction`)."""
        self.keeps_renders = keeps_renders
        """Whether the pipeline stores the model's renders of the kept pixels instead of their captured colours."""
        self.flat = torch.empty(0, dtype=torch.long)
        self.rgb = torch.empty(0, 3, dtype=torch.uint8)
        self.task = torch.empty(0, dtype=torch.long)
        self.depth: Optional[Tensor] = None
        """z-depth (scene units, 0: none) of each stored pixel, when the tasks closed with depth; None otherwise."""

    def __len__(self) -> int:
        return len(self.flat)

    @property
    def enabled(self) -> bool:
        return self.fraction > 0 or self.pixels > 0

    @property
    def nbytes(self) -> int:
        tensors = (self.flat, self.rgb, self.task) + (() if self.depth is None else (self.depth,))
        return sum(tensor.numel() * tensor.element_size() for tensor in tensors)

    def capacity(self, total_pixels: int) -> int:
        """Pixels the buffer holds at most, for a capture of `total_pixels` training pixels."""
        return min(self.pixels, total_pixels) if self.pixels else int(round(self.fraction * total_pixels))

    def describe(self, total_pixels: Optional[int]) -> str:
        """What the buffer keeps, in one line; `total_pixels`: the capture's training pixels (None: still arriving)."""
        kept = self._describe_share(total_pixels)
        return f"{kept}, as the model renders them when their task closes" if self.keeps_renders else kept

    def _describe_share(self, total_pixels: Optional[int]) -> str:
        if total_pixels is None:
            kept = f"{self.pixels:,} pixels" if self.pixels else f"{self.fraction:.2%} of the training pixels"
            return f"Replay buffer: keeps {kept} of the closed tasks, an equal share each"
        capacity = self.capacity(total_pixels)
        if capacity >= total_pixels:
            return f"Replay buffer: keeps every training pixel ({total_pixels:,}) of every closed task"
        return (
            f"Replay buffer: keeps {capacity:,} of the {total_pixels:,} training pixels "
            f"({capacity / total_pixels:.2%}), an equal share per closed task"
        )

    @torch.no_grad()
    def add_task(
        self,
        task: int,
        flat: Tensor,
        rgb: Tensor,
        total_pixels: int,
        depth: Optional[Tensor] = None,
        render: Optional[Callable[[Tensor], Tensor]] = None,
    ) -> None:
        """Keep a uniform random subset of closed task `task`'s pixels (`flat`, colours in [0, 1], `depth` when the
        model trains on it) and shrink the earlier tasks' shares, so that each of the tasks closed so far keeps
        capacity / (task + 1) pixels. With `render` (flat numbers to colours) the kept colours are its, not `rgb`'s."""
        shares = _equal_shares(self.capacity(total_pixels), task + 1)
        # entries are stored in random order, so the first n of a task are a uniform random subset of its pixels
        kept = [torch.nonzero(self.task == j).view(-1)[: shares[j]] for j in range(task)]
        keep = torch.cat(kept) if kept else torch.empty(0, dtype=torch.long)
        chosen = torch.randperm(len(flat))[: shares[task]]
        colours = rgb[chosen] if render is None else render(flat[chosen])
        self.flat = torch.cat([self.flat[keep], flat[chosen].cpu()])
        self.rgb = torch.cat([self.rgb[keep], (colours.cpu().clamp(0, 1) * 255).round().to(torch.uint8)])
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
