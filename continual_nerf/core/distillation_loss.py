"""Eq. 4 of the paper: photometric loss on current-task rays plus distillation loss on past-task rays."""

from __future__ import annotations

from typing import Dict, Optional

import torch

REPLAY_SKIPPED = "replay_skipped"
"""Batch key: replayed rays the change guard skips (an open-task frame sees their surface changed)."""
REPLAY_WEIGHTS = "replay_weights"
"""Batch key: the replay oracle's weights (N, S, 1) at the model's samples along the distilled rays."""


def distilled_rays(is_replay: torch.Tensor, skipped: Optional[torch.Tensor] = None) -> torch.Tensor:
    """(N,) the replayed rays the oracle teaches: all of them but those the change guard skips."""
    return is_replay if skipped is None else is_replay & ~skipped.to(is_replay.device)


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
    distilled = distilled_rays(replay, skipped)
    return {
        "rgb_loss": squared_error[~replay].sum() / num_rays,
        "distillation_loss": squared_error[distilled].sum() / num_rays,
    }


def weights_distillation_loss(weights: torch.Tensor, target: torch.Tensor, distilled: torch.Tensor) -> torch.Tensor:
    """Geometry's share of the distillation: how far the model's weights (N, S, 1) along each distilled ray are from the
    oracle's `target` at the same samples (squared error summed over the ray: its gradient fades as they agree, where
    an L1's would keep pushing every sample), summed over those rays and divided by the whole batch size, as Eq. 4's
    terms are. Colour alone lets a closed task's surfaces drift wherever their colour still renders."""
    return (weights[distilled.to(weights.device)] - target).pow(2).sum() / max(1, weights.shape[0])
