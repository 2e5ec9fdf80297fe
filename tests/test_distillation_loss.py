"""Eq. 4: pixels supervise the open task's rays, the oracle's colours the replayed ones, over one batch."""

import torch

from continual_nerf.core.distillation_loss import distillation_loss


def test_each_term_sums_its_own_rays_squared_error_over_the_whole_batch():
    pred = torch.tensor([[0.0, 0.0, 0.0], [1.0, 1.0, 1.0], [0.5, 0.5, 0.5], [0.2, 0.4, 0.6]])
    target = torch.tensor([[0.3, 0.0, 0.0], [1.0, 1.0, 0.4], [0.5, 0.5, 0.5], [0.2, 0.4, 0.0]])
    is_replay = torch.tensor([False, True, False, True])
    terms = distillation_loss(pred, target, is_replay)
    # per-ray mean over the 3 channels, summed per term, divided by all 4 rays of the batch
    assert torch.isclose(terms["rgb_loss"], torch.tensor((0.09 / 3 + 0.0) / 4))
    assert torch.isclose(terms["distillation_loss"], torch.tensor((0.36 / 3 + 0.36 / 3) / 4))


def test_the_two_terms_add_up_to_the_mean_squared_error_of_the_batch():
    generator = torch.Generator().manual_seed(0)
    pred, target = torch.rand(64, 3, generator=generator), torch.rand(64, 3, generator=generator)
    is_replay = torch.rand(64, generator=generator) < 0.7
    terms = distillation_loss(pred, target, is_replay)
    torch.testing.assert_close(
        terms["rgb_loss"] + terms["distillation_loss"], torch.nn.functional.mse_loss(pred, target)
    )


def test_a_batch_without_replay_has_a_zero_distillation_term_and_gradients_reach_every_ray():
    pred = torch.rand(8, 3, requires_grad=True)
    target = torch.rand(8, 3)
    terms = distillation_loss(pred, target, torch.zeros(8, dtype=torch.bool))
    assert terms["distillation_loss"].item() == 0.0
    (terms["rgb_loss"] + terms["distillation_loss"]).backward()
    assert pred.grad is not None and (pred.grad.abs().sum(dim=-1) > 0).all()
