"""Eq. 4: pixels supervise the open task's rays, the oracle's colours the replayed ones, over one batch; with
--pipeline.model.replay-weights-loss-mult (continual-ngp-depth's default), the oracle's weights along the replayed rays
too."""

import dataclasses

import torch
from helpers import demo_parser, tiny_config
from nerfstudio.data.scene_box import SceneBox

from continual_nerf.compilation import random_rays
from continual_nerf.core.distillation_loss import distillation_loss, weights_distillation_loss
from continual_nerf.core.ngp_model import ContinualNGPModelConfig
from continual_nerf.method_configs import CONTINUAL_NGP, CONTINUAL_NGP_DEPTH
from continual_nerf.recipes import small_model


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


def test_the_distillation_term_is_scaled_by_its_lambda_and_the_open_tasks_term_is_not():
    config = small_model(ContinualNGPModelConfig(compile=False))
    model = config.setup(scene_box=SceneBox(aabb=torch.tensor([[-1.0] * 3, [1.0] * 3])), num_train_data=1)
    model.train()
    torch.manual_seed(0)
    outputs = model(random_rays(model, 32))
    batch = {"image": torch.rand(32, 3), "is_replay": torch.arange(32) % 2 == 0}
    terms = {}
    for mult in (1.0, 3.0):
        model.config = dataclasses.replace(model.config, distillation_loss_mult=mult)
        terms[mult] = model.get_loss_dict(outputs, batch, model.get_metrics_dict(outputs, batch))
    assert terms[1.0]["distillation_loss"] > 0
    torch.testing.assert_close(terms[3.0]["distillation_loss"], 3 * terms[1.0]["distillation_loss"])
    torch.testing.assert_close(terms[3.0]["rgb_loss"], terms[1.0]["rgb_loss"])
    assert CONTINUAL_NGP.pipeline.model.distillation_loss_mult == 1.0, "the paper's Eq. 4 by default"


def test_the_weights_term_is_the_squared_distance_of_the_distilled_rays_over_the_whole_batch():
    weights = torch.tensor([[[0.2], [0.8]], [[0.5], [0.5]], [[0.0], [1.0]]], requires_grad=True)
    target = torch.tensor([[[0.1], [0.7]], [[0.5], [0.0]]])  # the oracle's, for the two distilled rays
    distilled = torch.tensor([True, False, True])
    loss = weights_distillation_loss(weights, target, distilled)
    assert torch.isclose(loss, torch.tensor((0.01 + 0.01 + 0.25 + 1.0) / 3))
    loss.backward()
    assert weights.grad is not None
    assert (weights.grad[1] == 0).all(), "a ray the oracle does not teach gets no gradient"
    assert (weights.grad[distilled] != 0).all()


def test_replayed_rays_take_the_oracles_weights_at_the_models_own_samples(run_dir):
    config = tiny_config(run_dir, demo_parser(), num_tasks=2)
    config.pipeline.model = dataclasses.replace(config.pipeline.model, replay_weights_loss_mult=1.0)
    trainer = config.setup(local_rank=0, world_size=1)
    trainer.setup()
    pipeline = trainer.pipeline
    pipeline.datamanager.next_train(0)
    pipeline.open_next_task()  # task 1 closes: the oracle is the model as it is
    _, losses, _ = pipeline.get_train_loss_dict(0)
    assert losses["weights_distillation_loss"] == 0.0, "a model equal to its oracle puts the light where it does"
    with torch.no_grad():
        for parameter in pipeline.model.field.parameters():
            parameter.add_(0.05 * torch.randn_like(parameter))
    outputs, losses, _ = pipeline.get_train_loss_dict(0)
    assert losses["weights_distillation_loss"] > 0
    (gradient,) = torch.autograd.grad(losses["weights_distillation_loss"], outputs["weights_list"][-1])
    assert gradient.abs().sum() > 0


def test_the_oracle_renders_and_weighs_with_autograd_off(run_dir, monkeypatch):
    trainer = tiny_config(run_dir, demo_parser(), num_tasks=2).setup(local_rank=0, world_size=1)
    trainer.setup()
    pipeline = trainer.pipeline
    pipeline.datamanager.next_train(0)
    pipeline.open_next_task()
    oracle = pipeline.replay_oracle
    grad_enabled = []
    for module, name in ((oracle.model, "forward"), (oracle.model.field, "get_density")):
        original = getattr(module, name)
        monkeypatch.setattr(
            module, name, lambda *a, f=original, **k: grad_enabled.append(torch.is_grad_enabled()) or f(*a, **k)
        )
    ray_bundle, batch = pipeline.datamanager.next_train(0)
    replayed = ray_bundle[batch["is_replay"]]
    oracle.outputs(replayed)
    outputs = pipeline.model(replayed)
    oracle.weights_at(outputs["ray_samples_list"][-1])
    assert grad_enabled and not any(grad_enabled), "the frozen copy never builds a graph for a training step's backward"


def test_continual_ngp_depth_distils_geometry_and_colour_only_continual_ngp_does_not():
    assert CONTINUAL_NGP_DEPTH.pipeline.model.replay_weights_loss_mult > 0
    assert CONTINUAL_NGP.pipeline.model.replay_weights_loss_mult == 0
