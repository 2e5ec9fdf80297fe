"""Task release, pixel isolation and the replay oracle (owned by the pipeline), on the demo scene."""

import numpy as np
import pytest
import torch
from helpers import demo_parser, tiny_config
from PIL import Image

from continual_nerf.core.continual_dataset import ClosedTaskError
from continual_nerf.core.replay_oracle import ReplayOracle


@pytest.fixture
def trainer(run_dir):
    config = tiny_config(run_dir, demo_parser(num_frames=18), num_tasks=3)
    trainer = config.setup(local_rank=0, world_size=1)
    trainer.setup()
    return trainer


def _file_pixels(dataset, frame: int) -> torch.Tensor:
    return torch.from_numpy(np.asarray(Image.open(dataset.image_filenames[frame]), dtype=np.float32) / 255.0)


def test_held_out_frames_are_not_training_frames(trainer):
    datamanager = trainer.pipeline.datamanager
    train_files = set(datamanager.train_dataset.image_filenames)
    test_files = set(datamanager.eval_dataset.image_filenames)
    assert train_files and test_files and not train_files & test_files
    assert len(train_files) + len(test_files) == 18


def test_batches_of_a_task_hold_only_its_pixels_and_closed_tasks_are_unreadable(trainer):
    datamanager = trainer.pipeline.datamanager
    dataset = datamanager.train_dataset
    for task in range(datamanager.num_tasks):
        _, batch = datamanager.next_train(0)
        own = batch["indices"][~batch["is_replay"]]
        assert set(dataset.task_of_frame[own[:, 0]].tolist()) == {task}
        for (frame, y, x), colour in zip(own.tolist(), batch["image"][~batch["is_replay"]]):
            assert torch.allclose(colour, _file_pixels(dataset, frame)[y, x], atol=1e-6)
        if task:
            assert batch["is_replay"].any(), "replay rays are sampled over all released tasks"
            assert set(dataset.task_of_frame[batch["indices"][batch["is_replay"], 0]].tolist()) <= set(range(task))
        assert dataset.task_pixels.shape[0] == int(
            (dataset.cameras.width * dataset.cameras.height)[dataset.task_of_frame == task].sum()
        ), "only the open task's pixels are held"
        for other in range(datamanager.num_tasks):
            if other != task:
                with pytest.raises(ClosedTaskError, match=f"belongs to task {other + 1}"):
                    dataset.get_numpy_image(int(dataset.frames_of_task(other)[0]))
        if task + 1 < datamanager.num_tasks:
            trainer.pipeline.open_next_task()


def test_replayed_targets_are_the_frozen_oracles_colours(trainer):
    pipeline = trainer.pipeline
    pipeline.open_next_task()
    ray_bundle, batch = pipeline.datamanager.next_train(0)
    torch.manual_seed(0)
    pipeline.add_replay_targets(ray_bundle, batch)
    replay = batch["is_replay"]
    assert replay.any() and (~replay).any()
    torch.manual_seed(0)  # the oracle samples along its rays as training does: jittered
    expected = pipeline.replay_oracle.render(ray_bundle[replay])
    assert torch.allclose(batch["image"][replay], expected, atol=1e-6)


def test_the_oracle_renders_its_targets_as_training_renders_the_student(trainer):
    pipeline = trainer.pipeline
    pipeline.open_next_task()  # the oracle is the student as it is now
    pipeline.train()
    ray_bundle, _ = pipeline.datamanager.next_train(0)
    torch.manual_seed(0)
    with torch.no_grad():
        trained = pipeline.model(ray_bundle)["rgb"]
    torch.manual_seed(0)
    target = pipeline.replay_oracle.render(ray_bundle)
    assert torch.allclose(target, trained, atol=1e-5)
    torch.manual_seed(1)
    assert not torch.equal(pipeline.replay_oracle.render(ray_bundle), target), (
        "samples jitter from batch to batch, as in training"
    )
    pipeline.eval()
    with torch.no_grad():
        evaluated = pipeline.model(ray_bundle)["rgb"]
    assert not torch.equal(evaluated, target), "evaluation's fixed samples render other colours"


def test_oracle_is_frozen_during_a_step_and_only_one_copy_exists(trainer):
    pipeline = trainer.pipeline
    pipeline.open_next_task()
    oracle = pipeline.replay_oracle.model
    before = {name: p.detach().clone() for name, p in oracle.named_parameters()}
    student_before = {name: p.detach().clone() for name, p in pipeline.model.named_parameters()}
    trainer.train_iteration(step=0)
    assert all(not p.requires_grad and p.grad is None for p in oracle.parameters())
    assert all(torch.equal(p, before[name]) for name, p in oracle.named_parameters())
    assert any(not torch.equal(p, student_before[name]) for name, p in pipeline.model.named_parameters()), (
        "the student did learn in that step"
    )
    assert not oracle.training
    pipeline.open_next_task()
    assert pipeline.replay_oracle.model is oracle, "the oracle is replaced in place, not duplicated"
    assert sum(isinstance(m, ReplayOracle) for m in pipeline.modules()) == 1
    assert sum(m is oracle or m is pipeline.model for m in pipeline.modules()) == 2
    assert all(torch.equal(p, q) for p, q in zip(oracle.parameters(), pipeline.model.parameters())), (
        "the new oracle is the model as it was at the end of the task"
    )


def test_without_replay_batches_come_from_the_open_task_only(run_dir):
    config = tiny_config(run_dir, demo_parser(num_frames=18), num_tasks=3, replay=False)
    trainer = config.setup(local_rank=0, world_size=1)
    trainer.setup()
    datamanager = trainer.pipeline.datamanager
    trainer.pipeline.open_next_task()
    _, batch = datamanager.next_train(0)
    assert not batch["is_replay"].any()
    assert set(datamanager.train_dataset.task_of_frame[batch["indices"][:, 0]].tolist()) == {1}
    assert not trainer.pipeline.replay_oracle.ready
