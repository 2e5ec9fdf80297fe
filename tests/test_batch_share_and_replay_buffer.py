"""The open task's share of each batch, and the experience-replay buffer of real pixels of closed tasks."""

from __future__ import annotations

import math
import re

import numpy as np
import pytest
import torch
import yaml
from helpers import demo_parser, stopped_run, tiny_config, train
from PIL import Image

from continual_nerf.core.continual_dataset import ClosedTaskError
from continual_nerf.core.continual_trainer import ContinualTrainerConfig
from continual_nerf.core.experience_replay import ExperienceReplayBuffer
from continual_nerf.errors import ContinualConfigError


def set_up(run_dir, num_tasks: int = 3, **datamanager):
    config = tiny_config(run_dir, demo_parser(num_frames=18), num_tasks=num_tasks)
    for name, value in datamanager.items():
        setattr(config.pipeline.datamanager, name, value)
    trainer = config.setup(local_rank=0, world_size=1)
    trainer.setup()
    return trainer


def open_rays(batch) -> int:
    return int((~batch["is_replay"]).sum())


@pytest.mark.parametrize("share", [0.5, 0.25, "sqrt"])
def test_the_batch_holds_the_configured_share_of_open_task_rays(run_dir, share):
    trainer = set_up(run_dir, current_task_fraction=share)
    pipeline, datamanager = trainer.pipeline, trainer.pipeline.datamanager
    rays = datamanager.config.train_num_rays_per_batch
    _, batch = datamanager.next_train(0)
    assert open_rays(batch) == rays, "task 1 has nothing to replay"
    for task in (1, 2):
        pipeline.open_next_task()
        _, batch = datamanager.next_train(0)
        expected = 1 / math.sqrt(task + 1) if share == "sqrt" else share
        assert open_rays(batch) == round(rays * expected)
        replayed_frames = batch["indices"][batch["is_replay"], 0]
        assert set(datamanager.train_dataset.task_of_frame[replayed_frames].tolist()) <= set(range(task))


def second_task_open(run_dir):
    """The datamanager of a run whose second task is open, half of each batch its rays, and its pixel range."""
    trainer = set_up(run_dir, current_task_fraction=0.5)
    datamanager = trainer.pipeline.datamanager
    trainer.pipeline.open_next_task()
    datamanager.open_if_released()
    return (datamanager, *datamanager.train_dataset.open_task_pixel_range())


def test_the_emphasised_share_of_the_open_tasks_rays_is_drawn_from_the_emphasised_pixels(run_dir):
    datamanager, start, end = second_task_open(run_dir)
    emphasised = torch.arange(start, end, 8)  # an eighth of the task's pixels: up to all its rays (8x its share)
    datamanager.emphasise(1, emphasised, 0.25)
    flat = datamanager.sample_pixels(1024)
    open_part, replayed = flat[:512], flat[512:]
    assert bool(torch.isin(open_part[-128:], emphasised).all()), "a quarter of the open task's 512 rays"
    assert bool(((open_part >= start) & (open_part < end)).all()) and bool((replayed < start).all())
    datamanager.emphasise(0, emphasised, 0.25)
    assert int(torch.isin(datamanager.sample_pixels(1024), emphasised).sum()) < 128, "a closed task's emphasis: none"


def test_a_few_emphasised_pixels_take_at_most_8x_their_share_of_the_open_tasks_rays(run_dir):
    datamanager, start, end = second_task_open(run_dir)
    emphasised = torch.arange(start, end, 64)  # 1/64 of the task's pixels: an eighth of its rays, not a quarter
    datamanager.emphasise(1, emphasised, 0.25)
    open_part = datamanager.sample_pixels(1024)[:512]
    assert bool(torch.isin(open_part[-round(512 * 8 * len(emphasised) / (end - start)) :], emphasised).all())
    assert int(torch.isin(open_part, emphasised).sum()) < 128, "uniform drawing adds about 8 more, not 64"


def test_uniform_sampling_is_the_papers_rule(run_dir):
    trainer = set_up(run_dir, current_task_fraction="uniform")
    pipeline, datamanager = trainer.pipeline, trainer.pipeline.datamanager
    pipeline.open_next_task()
    pipeline.open_next_task()
    torch.manual_seed(0)
    start, end = datamanager.train_dataset.open_task_pixel_range()
    flat = datamanager.sample_pixels(4096)
    torch.manual_seed(0)
    assert torch.equal(flat, torch.randint(0, end, (4096,))), "one uniform draw over every released pixel"


def test_buffer_keeps_an_equal_random_share_of_each_closed_task_and_never_exceeds_its_size():
    buffer = ExperienceReplayBuffer(pixels=30)
    tasks = [torch.arange(0, 100), torch.arange(100, 140), torch.arange(140, 400)]
    for task, flat in enumerate(tasks):
        colours = (flat.float() / 400)[:, None].expand(-1, 3)
        buffer.add_task(task, flat, colours, total_pixels=400)
        assert len(buffer) <= 30
        assert buffer.tasks_held() == {j: 30 // (task + 1) for j in range(task + 1)}
        for j, pixels in enumerate(tasks[: task + 1]):
            held = buffer.flat[buffer.task == j]
            assert bool(torch.isin(held, pixels).all()) and len(held.unique()) == len(held), "distinct pixels of j"
    assert torch.equal(buffer.rgb[:, 0], (buffer.flat.float() / 400 * 255).round().to(torch.uint8))
    assert ExperienceReplayBuffer(fraction=0.05).capacity(400) == 20, "a share of the training pixels"
    assert ExperienceReplayBuffer(fraction=1.0).capacity(400) == 400, "1: every pixel, not one"
    assert ExperienceReplayBuffer(pixels=1).capacity(400) == 1, "a count of pixels"


@pytest.mark.slow
def test_a_run_with_the_buffer_holds_closed_tasks_pixels_only_and_resumes_with_the_same_buffer(run_dir, tmp_path):
    config = tiny_config(run_dir, demo_parser(num_frames=18), num_tasks=3, iterations_per_task=3)
    config.pipeline.datamanager.replay_buffer_fraction = 0.02
    trainer = train(config)
    buffer, datamanager = trainer.pipeline.replay_buffer, trainer.pipeline.datamanager
    dataset = datamanager.train_dataset
    capacity = buffer.capacity(datamanager.total_train_pixels())
    assert 0 < len(buffer) <= capacity and set(buffer.tasks_held()) == {0, 1, 2}, (
        "every task's: the last one's too, closed as the run ends (a later session replays it)"
    )
    frames = torch.searchsorted(dataset.pixel_offsets, buffer.flat, right=True) - 1
    assert torch.equal(dataset.task_of_frame[frames], buffer.task), "each pixel is stored under its own task"
    for flat, frame, rgb in list(zip(buffer.flat.tolist(), frames.tolist(), buffer.rgb))[:20]:
        local = flat - int(dataset.pixel_offsets[frame])
        width = int(dataset.cameras.width[frame])
        image = np.array(Image.open(dataset.image_filenames[frame]))  # a writable copy for torch
        assert torch.equal(rgb, torch.from_numpy(image[local // width, local % width, :3])), "the pixel's own colour"

    def with_buffer(name: str) -> ContinualTrainerConfig:
        run = tiny_config(tmp_path / name, demo_parser(num_frames=18), num_tasks=3, iterations_per_task=3)
        run.pipeline.datamanager.replay_buffer_fraction = 0.02
        return run

    resumed = with_buffer("resumed")
    resumed.load_checkpoint = stopped_run(with_buffer("stopped"), last_step=5)  # the end of task 2
    again = train(resumed).pipeline.replay_buffer
    for name in ("flat", "rgb", "task"):
        assert torch.equal(getattr(again, name), getattr(buffer, name)), f"the resumed run's buffer {name} differs"


def test_batches_with_the_buffer_take_stored_pixels_and_still_read_no_closed_task_image(run_dir):
    trainer = set_up(run_dir, replay_buffer_fraction=0.1, replay_buffer_share=0.5)
    pipeline, datamanager = trainer.pipeline, trainer.pipeline.datamanager
    datamanager.next_train(0)  # task 1 opens at its first batch
    pipeline.open_next_task()
    _, batch = datamanager.next_train(0)
    closed = datamanager.train_dataset.task_of_frame[batch["indices"][:, 0]] == 0
    stored = closed & ~batch["is_replay"]
    assert stored.any() and (closed & batch["is_replay"]).any(), "task 1's rays: stored pixels and oracle targets"
    with pytest.raises(ClosedTaskError):
        datamanager.train_dataset.get_numpy_image(0)


def test_a_buffer_of_renders_keeps_what_the_model_renders_as_the_task_closes_not_the_captured_pixels(run_dir):
    trainer = set_up(run_dir, replay_buffer_fraction=0.1, replay_buffer_keeps="renders")
    pipeline, datamanager = trainer.pipeline, trainer.pipeline.datamanager
    datamanager.next_train(0)  # task 1 opens at its first batch
    captured = dict(zip(*(part.tolist() for part in datamanager.open_task_pixels())))
    pipeline.open_next_task()
    buffer = pipeline.replay_buffer
    assert set(buffer.tasks_held()) == {0} and len(buffer) == buffer.capacity(datamanager.total_train_pixels())
    rays = datamanager.train_ray_generator(datamanager.ray_indices(buffer.flat))
    rendered = pipeline.replay_oracle.render(rays)  # the oracle is the model as task 1 closed
    stored = buffer.rgb.float() / 255
    pixels = torch.tensor([captured[flat] for flat in buffer.flat.tolist()])
    assert (stored - rendered).abs().mean() < 0.01, "the renders, up to 8 bits and the samples' jitter"
    assert (stored - pixels).abs().mean() > 0.05, "not the captured colours"


@pytest.mark.parametrize(
    "options, message",
    [
        ({"current_task_fraction": 0.0}, "current-task-fraction must be uniform, sqrt or a share in (0, 1]"),
        ({"current_task_fraction": 1.5}, "current-task-fraction must be uniform, sqrt or a share in (0, 1]"),
        ({"replay_buffer_fraction": -1.0}, "replay-buffer-fraction must be in [0, 1] (a share of the training pixels;"),
        ({"replay_buffer_fraction": 1.5}, "replay-buffer-fraction must be in [0, 1]"),
        ({"replay_buffer_pixels": -1}, "replay-buffer-pixels must be 0 or more, got -1"),
        (
            {"replay_buffer_fraction": 0.5, "replay_buffer_pixels": 1000},
            "replay-buffer-fraction 0.5 and --pipeline.datamanager.replay-buffer-pixels 1000 both size the replay "
            "buffer: give one",
        ),
        ({"replay_buffer_pixels": 100, "replay": False}, "needs replay; this run has --pipeline.datamanager.replay"),
        ({"replay_buffer_share": 1.5}, "replay-buffer-share must be in [0, 1]"),
        ({"replay_buffer_keeps": "renders"}, "replay-buffer-keeps renders needs a replay buffer: give"),
    ],
)
def test_bad_share_and_buffer_options_are_one_line_errors(run_dir, options, message):
    config = tiny_config(run_dir, demo_parser(num_frames=18))
    for name, value in options.items():
        setattr(config.pipeline.datamanager, name, value)
    with pytest.raises(ContinualConfigError, match=message.replace("(", r"\(").replace("[", r"\[")) as error:
        config.pipeline.datamanager.setup(device="cpu")
    assert "\n" not in str(error.value)


@pytest.mark.parametrize(
    "options, line",
    [
        ({"replay_buffer_fraction": 1.0}, "Replay buffer: keeps every training pixel (6,480) of every closed task"),
        ({"replay_buffer_pixels": 1}, "Replay buffer: keeps 1 of the 6,480 training pixels (0.02%), an equal share"),
        ({"replay_buffer_fraction": 0.1}, "Replay buffer: keeps 648 of the 6,480 training pixels (10.00%), an equal"),
    ],
)
def test_the_run_says_at_start_how_many_pixels_its_buffer_keeps(run_dir, capsys, options, line):
    set_up(run_dir, **options)
    assert line in capsys.readouterr().out


def test_a_config_yml_with_the_former_buffer_size_loads_into_the_fraction_or_the_count(run_dir):
    written = yaml.dump(tiny_config(run_dir, demo_parser(num_frames=18)))
    assert "replay_buffer_fraction: 0.0\n" in written and "replay_buffer_pixels: 0\n" in written
    for size, fraction, pixels in (("0.02", 0.02, 0), ("5000.0", 0.0, 5000)):
        former = written.replace("replay_buffer_fraction: 0.0\n", f"replay_buffer_size: {size}\n")
        former = re.sub(r"\n *replay_buffer_pixels: 0\n", "\n", former)
        datamanager = yaml.load(former, Loader=yaml.Loader).pipeline.datamanager
        assert (datamanager.replay_buffer_fraction, datamanager.replay_buffer_pixels) == (fraction, pixels)
        assert not hasattr(datamanager, "replay_buffer_size")
