"""Which training pixels may be drawn, when a capture has masks (transforms.json `mask_path`: 0 = never train) or
fisheye circles (its `fisheye_crop_radius`: pixels outside never train).

A mask says which rays are valid, not what the image shows, so the record is kept for closed tasks too: replay must
not draw a masked-out ray either (the oracle's render there is meaningless). It is one bit per pixel (1/96 of the
open task's float32 colours; 78 MB for 300 frames of 1920x1080), each frame's bits starting at a byte, filled from a
task's mask files and circles when the task opens (a resumed run reads the closed tasks' masks again). Pixels are
drawn by rejection against it: uniform flat pixel numbers in a range, keeping the valid ones until there are enough.
"""

from __future__ import annotations

import math
from typing import Optional

import numpy as np
import torch
from torch import Tensor

MAX_CANDIDATES = 1 << 20
"""Candidates drawn at most per rejection round (a capture masked almost everywhere takes more rounds, not memory)."""


def inside_circle(width: int, height: int, radius: float) -> Tensor:
    """(height, width) bool: the pixels less than `radius` from the image centre, placed and measured as nerfstudio
    does (the centre at pixel (width // 2, height // 2); the full-image datamanager's fisheye mask)."""
    x = torch.arange(width, dtype=torch.float64) - width // 2
    y = torch.arange(height, dtype=torch.float64) - height // 2
    return x[None, :] ** 2 + y[:, None] ** 2 < radius**2


class ValidPixels:
    """Validity bits over the flat pixel numbering of the training frames (`pixel_offsets`, as ContinualDataset's)."""

    def __init__(self, pixel_offsets: Tensor) -> None:
        self.pixel_offsets = pixel_offsets
        counts = pixel_offsets.diff()
        self.byte_offsets = torch.cat([torch.zeros(1, dtype=torch.long), ((counts + 7) // 8).cumsum(0)])
        """Start of every frame's bits in `bits`, in bytes."""
        self.bits = torch.zeros(int(self.byte_offsets[-1]), dtype=torch.uint8)
        """Bit i % 8 of byte byte_offsets[frame] + i // 8 is set when pixel i of the frame may be drawn."""
        self.valid_per_frame = torch.full((len(counts),), -1, dtype=torch.long)
        """Valid pixels of each frame; -1 until its mask is recorded."""

    @property
    def nbytes(self) -> int:
        return self.bits.numel() + self.valid_per_frame.numel() * self.valid_per_frame.element_size()

    def recorded(self, frame: int) -> bool:
        return bool(self.valid_per_frame[frame] >= 0)

    def record(self, frame: int, mask: Tensor) -> None:
        """Store `frame`'s mask (its pixels in flat order, nonzero = valid)."""
        valid = mask.reshape(-1).bool().numpy()
        assert len(valid) == int(self.pixel_offsets[frame + 1] - self.pixel_offsets[frame]), "one value per pixel"
        packed = np.packbits(valid, bitorder="little")
        self.bits[int(self.byte_offsets[frame]) : int(self.byte_offsets[frame + 1])] = torch.from_numpy(packed)
        self.valid_per_frame[frame] = int(valid.sum())

    def count(self, low: int, high: int) -> int:
        """Valid pixels among flat numbers [low, high), which start and end at frames whose masks are recorded."""
        first, last = torch.searchsorted(self.pixel_offsets, torch.tensor([low, high])).tolist()
        assert self.pixel_offsets[first] == low and self.pixel_offsets[last] == high, "a range of whole frames"
        counts = self.valid_per_frame[first:last]
        assert bool((counts >= 0).all()), "the range's masks are recorded"
        return int(counts.sum())

    def contains(self, flat: Tensor) -> Tensor:
        """Whether each of the flat pixel numbers `flat` may be drawn."""
        frame = torch.searchsorted(self.pixel_offsets, flat, right=True) - 1
        local = flat - self.pixel_offsets[frame]
        byte = self.bits[self.byte_offsets[frame] + local // 8].long()
        return (byte >> (local % 8)) & 1 == 1

    def sample(self, low: int, high: int, num: int, generator: Optional[torch.Generator] = None) -> Tensor:
        """`num` flat pixel numbers drawn uniformly over the valid ones in [low, high) (which must hold one)."""
        valid = self.count(low, high)
        assert valid > 0 or num == 0, "a range without a valid pixel"
        drawn = [torch.empty(0, dtype=torch.long)]
        needed = num
        while needed > 0:
            # enough candidates to yield `needed` valid ones on average
            size = min(math.ceil(needed * (high - low) / valid), MAX_CANDIDATES)
            candidates = torch.randint(low, high, (size,), generator=generator)
            kept = candidates[self.contains(candidates)][:needed]
            drawn.append(kept)
            needed -= len(kept)
        return torch.cat(drawn)
