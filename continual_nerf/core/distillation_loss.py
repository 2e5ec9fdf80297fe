"""Eq. 4 of the paper: photometric loss on current-task rays plus distillation loss on past-task rays."""

from __future__ import annotations

from typing import Dict, Optional

import torch

REPLAY_SKIPPED = "replay_skipped"
"""Batch key: replayed rays the change guard skips (an open-task frame sees their surface changed)."""


def distillation_loss(
    pred_rgb: torch.Tensor,
    target_rgb: torch.Tensor,
    is_replay: torch.Tensor,
    skipped: Optional[torch.Tensor] = None,
) -> Dict[str, torch.Tensor]:
    """Split the squared error of a batch into its two terms of Eq. 4.

    `target_rgb` holds pixels for current-task rays and the oracle's colours for replayed rays; replayed rays marked
    `skipped` (the change guard's) teach nothing. Both terms are divided by the whole batch size, so their sum is the
    mean over rays sampled uniformly from all tasks seen so far, as the paper samples them.
    """
    squared_error = (pred_rgb - target_rgb).pow(2).sum(dim=-1) / pred_rgb.shape[-1]
    num_rays = max(1, squared_error.numel())
    replay = is_replay.to(squared_error.device)
    distilled = replay if skipped is None else replay & ~skipped.to(squared_error.device)
    return {
        "rgb_loss": squared_error[~replay].sum() / num_rays,
        "distillation_loss": squared_error[distilled].sum() / num_rays,
    }
