"""The paper's baselines as registered methods: each trains task by task, EWC's penalty and Fisher, joint training."""

from pathlib import Path

import pytest
import torch
from helpers import demo_parser, train
from nerfstudio.cameras.rays import RayBundle
from nerfstudio.data.scene_box import SceneBox

from continual_nerf.baselines.ewc import EWCPenalty, estimate_fisher
from continual_nerf.baselines.nerf_model import ContinualNeRFModelConfig
from continual_nerf.core.accuracy_matrix import ACCURACY_MATRIX_FILENAME, AccuracyMatrix
from continual_nerf.core.continual_trainer import ContinualTrainerConfig
from continual_nerf.experiments.plan import PAPER_TABLE1, continual_methods
from continual_nerf.recipes import quiet_config


def tiny_method(
    method: str, output_dir: Path, num_tasks: int = 2, iterations_per_task: int = 3
) -> ContinualTrainerConfig:
    """A registered method (found through nerfstudio's entry points) on a tiny demo scene, CPU, small model."""
    return quiet_config(
        continual_methods()[method], output_dir, small=True, dataparser=demo_parser(num_frames=16),
        num_tasks=num_tasks, iterations_per_task=iterations_per_task, train_num_rays_per_batch=128,
    )  # fmt: skip


def test_every_paper_method_is_registered_with_nerfstudio():
    assert set(PAPER_TABLE1) <= set(continual_methods())


@pytest.mark.slow
@pytest.mark.parametrize("method", PAPER_TABLE1)
def test_method_trains_two_tasks_and_writes_its_accuracy_matrix(run_dir, method):
    config = tiny_method(method, run_dir)
    trainer = train(config)
    matrix = AccuracyMatrix.read(config.get_base_dir() / ACCURACY_MATRIX_FILENAME)
    assert matrix.finished and matrix.steps == [2, 5]
    joint = config.pipeline.datamanager.joint
    assert [len(row) for row in matrix.psnr] == ([2, 2] if joint else [1, 2]), (
        "joint runs test every task from the start"
    )
    assert all(5.0 < value < 60.0 for row in matrix.psnr for value in row)
    oracle = trainer.pipeline.replay_oracle
    assert oracle.ready == config.pipeline.datamanager.replay, "only the replay methods keep a frozen copy"


def test_ewc_penalty_is_zero_at_the_reference_and_grows_away_from_it():
    parameters = {"grid.table": torch.randn(50, 2), "mlp.weight": torch.randn(4, 4)}
    penalty = EWCPenalty(parameters)
    fisher = {name: torch.rand_like(value) + 0.1 for name, value in parameters.items()}
    penalty.consolidate(fisher, parameters)
    assert penalty.active and penalty(parameters).item() == 0.0
    previous = 0.0
    for scale in (1e-3, 1e-2, 1e-1, 1.0):
        moved = {name: value + scale for name, value in parameters.items()}
        value = penalty(moved).item()
        assert value > previous
        previous = value
    expected = sum((fisher[name] * scale**2).sum() for name in parameters)
    assert previous == pytest.approx(expected.item(), rel=1e-5), "sum F (phi - phi_ref)^2 at an offset of 1"


@pytest.fixture(scope="module")
def ewc_run(tmp_path_factory):
    """A 2-task EWC run: its trainer and the checkpoint written when task 1 was consolidated."""
    config = tiny_method("continual-ngp-ewc", tmp_path_factory.mktemp("ewc") / "outputs", iterations_per_task=4)
    trainer = train(config)
    return trainer, config


def test_fisher_is_non_negative_and_non_zero_where_the_task_touched(ewc_run):
    trainer, _ = ewc_run
    model = trainer.pipeline.model
    # the last task too, at the run's end: a later session goes on from the final checkpoint
    assert int(model.ewc.num_consolidated) == 2, "every task consolidated"
    fisher = dict(model.ewc.fisher.named_buffers())
    assert all((value >= 0).all() for value in fisher.values())
    assert all(value.sum() > 0 for value in fisher.values()), "every parameter tensor gets gradients from task 1"
    (table,) = [value for name, value in fisher.items() if name.startswith("field__") and name.endswith("hash_table")]
    touched = (table > 0).float().mean().item()
    assert 0.0 < touched < 1.0, f"only the hash entries task 1's rays reach have information (got {touched:.3f})"


def test_fisher_matches_squared_gradients_of_the_loss():
    weight = torch.nn.Parameter(torch.tensor([1.0, -2.0, 0.0]))
    inputs = [torch.tensor([1.0, 2.0, 0.0]), torch.tensor([3.0, 0.0, 0.0])]
    batches = iter(inputs)
    fisher = estimate_fisher({"w": weight}, lambda: (weight * next(batches)).sum(), num_batches=2)
    assert torch.allclose(fisher["w"], (inputs[0] ** 2 + inputs[1] ** 2) / 2)
    assert weight.grad is None, "the optimizers' gradients are untouched"


def test_ewc_state_is_in_the_checkpoint_and_loads_back(ewc_run, tmp_path):
    trainer, config = ewc_run
    saved = trainer.pipeline.model.ewc.state_dict()
    checkpoints = sorted(config.get_checkpoint_dir().glob("step-*.ckpt"))
    state = torch.load(checkpoints[-1], map_location="cpu", weights_only=False)["pipeline"]
    assert any(key.startswith("_model.ewc.fisher.") for key in state) and any(".ewc.reference." in key for key in state)
    fresh = tiny_method("continual-ngp-ewc", tmp_path / "fresh").setup(local_rank=0, world_size=1)
    fresh.setup()
    assert not fresh.pipeline.model.ewc.active
    fresh.pipeline.load_pipeline(state, step=0)
    for name, value in fresh.pipeline.model.ewc.state_dict().items():
        assert torch.equal(value, saved[name]), name


def test_ewc_loss_appears_after_the_first_task(ewc_run):
    trainer, _ = ewc_run
    with torch.no_grad():  # as training moves the model away from the consolidated reference
        for parameter in trainer.pipeline.model.field.parameters():
            parameter.add_(1e-3)
    _, loss_dict, _ = trainer.pipeline.get_train_loss_dict(step=0)
    assert loss_dict["ewc_loss"].item() > 0.0, "the model moved away from the tasks' reference"


def test_joint_batches_draw_pixels_of_every_task(run_dir):
    config = tiny_method("continual-ngp-joint", run_dir, num_tasks=3)
    trainer = config.setup(local_rank=0, world_size=1)
    trainer.setup()
    datamanager = trainer.pipeline.datamanager
    _, batch = datamanager.next_train(0)
    true_task = torch.as_tensor(datamanager.task_split.train_task_of_frame())
    assert set(true_task[batch["indices"][:, 0]].tolist()) == {0, 1, 2}
    assert not batch["is_replay"].any()
    assert len(datamanager.seen_test_frames()) == len(datamanager.eval_dataset), "every task is tested from the start"
    trainer.pipeline.open_next_task()
    assert not trainer.pipeline.replay_oracle.ready
    assert datamanager.train_dataset.task_pixels.shape[0] == int(datamanager.train_dataset.pixel_offsets[-1])


def test_nerf_model_builds_offline_with_the_configured_mlp():
    config = ContinualNeRFModelConfig(base_mlp_num_layers=3, base_mlp_layer_width=48, skip_connections=(1,))
    model = config.setup(scene_box=SceneBox(aabb=torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])), num_train_data=4)
    for field in (model.field_coarse, model.field_fine):
        assert [layer.out_features for layer in field.mlp_base.layers] == [48, 48, 48]
    model.eval()
    outputs = model(_rays(8))
    assert outputs["rgb"].shape == (8, 3) and torch.equal(outputs["rgb"], outputs["rgb_fine"])


def _rays(count: int) -> RayBundle:
    directions = torch.nn.functional.normalize(torch.randn(count, 3), dim=-1)
    return RayBundle(origins=torch.zeros(count, 3), directions=directions, pixel_area=torch.full((count, 1), 1e-4),
                     camera_indices=torch.zeros(count, 1, dtype=torch.long))  # fmt: skip
