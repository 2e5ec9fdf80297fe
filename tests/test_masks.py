"""Per-frame masks of a transforms.json capture (`mask_path`) and its fisheye circle (`fisheye_crop_radius`): pixels
masked out or outside the circle never train, for the open task, for replay or in the replay buffer; bad masks are
one-line errors; evaluation still measures whole frames."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Callable, List, Tuple

import numpy as np
import pytest
import torch
from helpers import (
    ALL_MASKED,
    HEIGHT,
    NUMBERS,
    WIDTH,
    arc_poses,
    edit_transforms,
    mask_of,
    masked_capture,
    numbered_frames,
    shrink,
    tiny_config,
    write_transforms,
)
from nerfstudio.cameras.cameras import CameraType
from PIL import Image

from continual_nerf.core.continual_datamanager import ContinualDataManager
from continual_nerf.core.continual_dataset import ContinualDataset
from continual_nerf.core.experience_replay import ExperienceReplayBuffer
from continual_nerf.core.valid_pixels import ValidPixels
from continual_nerf.dataparsers.ordered_capture_dataparser import OrderedCaptureDataParserConfig
from continual_nerf.errors import DatasetError


def datamanager(capture: Path, run_dir: Path, downscale_factor: int = 1, **options) -> ContinualDataManager:
    parser = OrderedCaptureDataParserConfig(data=capture, downscale_factor=downscale_factor)
    config = tiny_config(run_dir, parser, num_tasks=2).pipeline.datamanager
    manager = dataclasses.replace(config, **options).setup(device="cpu")
    assert isinstance(manager, ContinualDataManager)
    return manager


def expected_valid(dataset: ContinualDataset, factor: int = 1) -> torch.Tensor:
    """Over the flat pixel numbering of the training frames: whether each pixel's mask lets it train."""
    masks = [shrink(mask_of(int(path.stem.split("_")[1])), factor) for path in dataset.image_filenames]
    return torch.from_numpy(np.concatenate([mask.reshape(-1) > 0 for mask in masks]))


def draws(manager: ContinualDataManager, batches: int = 10) -> torch.Tensor:
    return torch.cat([manager.sample_pixels(4096) for _ in range(batches)])


@pytest.mark.parametrize("share", [0.5, "uniform"])
def test_masked_out_pixels_are_never_drawn_for_the_open_task_nor_for_replay(tmp_path, share):
    torch.manual_seed(0)
    manager = datamanager(masked_capture(tmp_path / "capture"), tmp_path / "outputs", current_task_fraction=share)
    manager.next_train(0)  # opens task 1
    dataset = manager.train_dataset
    valid = expected_valid(dataset)
    assert 0 < int(valid.sum()) < len(valid)
    for task in (0, 1):
        if task:
            manager.release(1)
        start, end = dataset.open_task_pixel_range()
        flat = draws(manager)
        assert bool(valid[flat].all()), f"task {task + 1}: a masked-out pixel was drawn"
        replayed = flat < start
        assert bool(replayed.any()) == (task == 1), "task 2 replays task 1's pixels, task 1 has none to replay"
        # uniform over the valid pixels of each range: every frame in proportion to its valid pixels
        offsets = dataset.pixel_offsets
        for low, high, picked in ((start, end, flat[~replayed]), (0, start, flat[replayed])):
            if not len(picked):
                continue
            frames = torch.searchsorted(offsets, picked, right=True) - 1
            first, last = torch.searchsorted(offsets, torch.tensor([low, high])).tolist()
            counts = torch.tensor([int(valid[offsets[f] : offsets[f + 1]].sum()) for f in range(first, last)])
            drawn = torch.bincount(frames - first, minlength=last - first)
            assert torch.allclose(drawn / len(picked), counts / counts.sum(), atol=0.03)
    frame_6 = [i for i, path in enumerate(dataset.image_filenames) if path.stem == f"frame_{ALL_MASKED}"]
    assert frame_6 and int(dataset.task_of_frame[frame_6[0]]) == 0, "frame_6, masked everywhere, trained in task 1"


def test_a_batch_holds_the_open_tasks_pixels_where_its_masks_let_them_train(tmp_path):
    manager = datamanager(masked_capture(tmp_path / "capture"), tmp_path / "outputs")
    _, batch = manager.next_train(0)
    dataset = manager.train_dataset
    indices = batch["indices"]
    for (frame, y, x), colour in zip(indices.tolist()[:50], batch["image"]):
        assert mask_of(int(dataset.image_filenames[frame].stem.split("_")[1]))[y, x] > 0
        image = np.array(Image.open(dataset.image_filenames[frame]))
        assert torch.allclose(colour, torch.from_numpy(image[y, x] / 255).float()), "the ray carries its pixel"


def test_the_replay_buffer_keeps_no_masked_out_pixel(tmp_path):
    manager = datamanager(masked_capture(tmp_path / "capture"), tmp_path / "outputs")
    manager.next_train(0)
    dataset = manager.train_dataset
    valid = expected_valid(dataset)
    start, end = dataset.open_task_pixel_range()
    buffer = ExperienceReplayBuffer(pixels=end - start)  # room for every pixel of task 1
    flat, rgb = manager.open_task_pixels()
    buffer.add_task(0, flat, rgb, total_pixels=manager.total_train_pixels())
    assert sorted(buffer.flat.tolist()) == torch.nonzero(valid[start:end]).view(-1).add(start).tolist()
    manager.replay_buffer = buffer
    manager.release(1)
    _, batch = manager.next_train(0)
    from_buffer = (~batch["is_replay"]) & (dataset.task_of_frame[batch["indices"][:, 0]] == 0)
    assert bool(from_buffer.any()), "task 2's batch takes stored pixels of task 1"


def test_a_resumed_run_reads_the_closed_tasks_masks_again(tmp_path):
    torch.manual_seed(0)
    manager = datamanager(masked_capture(tmp_path / "capture"), tmp_path / "outputs")
    manager.resume_at(1)
    manager.next_train(0)
    dataset = manager.train_dataset
    assert dataset.open_task == 1 and dataset.valid_pixels is not None
    assert all(dataset.valid_pixels.recorded(frame) for frame in range(len(dataset)))
    start, _ = dataset.open_task_pixel_range()
    flat = draws(manager)
    assert bool((flat < start).any()) and bool(expected_valid(dataset)[flat].all())


@pytest.mark.parametrize("mask_factor", [1, 2], ids=["masks-of-full-size", "masks-of-downscaled-size"])
def test_masks_follow_the_downscaled_images(tmp_path, mask_factor):
    torch.manual_seed(0)
    capture = masked_capture(tmp_path / "capture", factor=mask_factor)
    manager = datamanager(capture, tmp_path / "outputs", downscale_factor=2)
    manager.next_train(0)
    manager.release(1)
    dataset = manager.train_dataset
    assert int(dataset.cameras.width[0]) == WIDTH // 2
    assert bool(expected_valid(dataset, factor=2)[draws(manager)].all())


def test_evaluation_reads_no_mask(tmp_path):
    manager = datamanager(masked_capture(tmp_path / "capture"), tmp_path / "outputs")
    assert manager.train_dataset.mask_filenames is not None and manager.train_dataparser_outputs.mask_filenames
    assert "mask" not in manager.eval_dataset[0], "test frames are measured whole, as nerfacto measures them"
    manager.next_train(0)
    assert "mask" not in manager.train_dataset.get_data(0), "masks reach training through the drawn pixels only"


def test_valid_pixels_are_one_bit_per_pixel():
    offsets = torch.tensor([0, 13, 13 + 64])
    valid = ValidPixels(offsets)
    assert valid.bits.numel() == 2 + 8, "each frame's bits start at a byte"
    first, second = torch.rand(13) > 0.5, torch.rand(64) > 0.9
    first[0] = second[0] = True
    valid.record(0, first)
    valid.record(1, second)
    assert torch.equal(valid.contains(torch.arange(77)), torch.cat([first, second]))
    assert valid.count(13, 77) == int(second.sum())
    assert bool(torch.cat([first, second])[valid.sample(0, 77, 1000)].all())


# ---- bad masks: one line naming the file ----


def missing_mask(capture: Path) -> Tuple[str, str]:
    (capture / "masks" / "frame_8.png").unlink()
    return "parse", f"{capture / 'masks' / 'frame_8.png'}: mask listed in {capture / 'transforms.json'} does not exist"


def frame_without_mask(capture: Path) -> Tuple[str, str]:
    meta = json.loads((capture / "transforms.json").read_text())
    del next(frame for frame in meta["frames"] if frame["file_path"].endswith("frame_12.png"))["mask_path"]
    (capture / "transforms.json").write_text(json.dumps(meta))
    return "parse", (
        f"{capture / 'transforms.json'} frame images/frame_12.png: has no mask_path while other frames have one "
        "(give every frame a mask, or none)"
    )


def garbage_mask(capture: Path) -> Tuple[str, str]:
    path = capture / "masks" / "frame_16.png"  # task 2's: every mask is checked before training starts
    path.write_bytes(b"not a png at all")
    return "start", f"{path}: cannot read mask (cannot identify image file"


def mask_of_another_size(capture: Path) -> Tuple[str, str]:
    path = capture / "masks" / "frame_4.png"
    Image.fromarray(np.zeros((16, 16), dtype=np.uint8)).save(path)
    return "start", f"{path}: mask is 16x16 pixels, its image 32x24 (a mask has its image's size)"


def colour_mask(capture: Path) -> Tuple[str, str]:
    path = capture / "masks" / "frame_4.png"
    Image.fromarray(np.zeros((HEIGHT, WIDTH, 3), dtype=np.uint8)).save(path)
    return "start", f"{path}: mask mode RGB is not supported (one channel: 8-bit L or 1-bit)"


def truncated_mask_of_task_2(capture: Path) -> Tuple[str, str]:
    path = capture / "masks" / "frame_16.png"  # its header stays readable: the pixels fail when task 2 opens
    Image.fromarray(np.random.default_rng(0).integers(0, 255, (HEIGHT, WIDTH), dtype=np.uint8)).save(path)
    path.write_bytes(path.read_bytes()[:-200])
    return "release", f"{path}: cannot read mask (image file is truncated"


def task_masked_everywhere(capture: Path) -> Tuple[str, str]:
    for number in (14, 16, 18, 20):  # task 2's training frames
        Image.fromarray(np.zeros((HEIGHT, WIDTH), dtype=np.uint8)).save(capture / "masks" / f"frame_{number}.png")
    return "release", (
        f"{capture / 'masks' / 'frame_14.png'}: this and every other mask of task 2's training frames is 0 everywhere: "
        "the task has no pixel to train on"
    )


BAD_MASKS: List[Callable[[Path], Tuple[str, str]]] = [
    missing_mask,
    frame_without_mask,
    garbage_mask,
    mask_of_another_size,
    colour_mask,
    truncated_mask_of_task_2,
    task_masked_everywhere,
]


@pytest.mark.parametrize("spoil", BAD_MASKS, ids=[spoil.__name__ for spoil in BAD_MASKS])
def test_bad_masks_are_one_line_errors_naming_the_file(tmp_path, spoil):
    capture = masked_capture(tmp_path / "capture")
    when, expected = spoil(capture)
    with pytest.raises(DatasetError) as raised:
        manager = datamanager(capture, tmp_path / "outputs")
        assert when != "parse", "the parser reports it"
        manager.next_train(0)
        assert when != "start", "checked before training starts"
        manager.release(1)
    message = str(raised.value)
    assert "\n" not in message and message.startswith(expected), message


def test_masks_come_with_the_frames_the_parser_keeps(tmp_path):
    capture = masked_capture(tmp_path / "capture")
    edit_transforms(capture, frame_6={"mask_path": "masks/frame_20.png"})  # kept by the stride, with its own mask
    parser = OrderedCaptureDataParserConfig(data=capture, frame_stride=2).setup()
    outputs = parser.get_dataparser_outputs("train")
    assert outputs.mask_filenames is not None
    assert [path.name for path in outputs.image_filenames] == [f"frame_{n}.png" for n in NUMBERS[::2]]
    assert [path.name for path in outputs.mask_filenames] == [
        "frame_2.png",
        "frame_20.png",
        "frame_10.png",
        "frame_14.png",
        "frame_18.png",
    ]


# ---- fisheye_crop_radius: fisheye frames train inside the circle only ----

RADIUS = 8.0
"""The captures' fisheye_crop_radius: a circle well inside the 32x24 images, around pixel (16, 12)."""

FISHEYE_MODELS = {
    "OPENCV_FISHEYE": {"camera_model": "OPENCV_FISHEYE"},
    "FISHEYE624": {"camera_model": "FISHEYE624", "distortion_params": [0.0] * 12},
}


def circle(width: int, height: int, radius: float) -> np.ndarray:
    """(height, width): whether each pixel lies less than `radius` from pixel (width // 2, height // 2), where
    nerfstudio's fisheye sampler centres its circle."""
    y, x = np.mgrid[:height, :width]
    return (x - width // 2) ** 2 + (y - height // 2) ** 2 < radius**2


def in_circle(dataset: ContinualDataset, radius: float) -> torch.Tensor:
    """Over the flat pixel numbering of the training frames: whether each pixel lies inside the circle of `radius`
    (loaded pixels) around its image's centre."""
    sizes = zip(dataset.cameras.width.view(-1).tolist(), dataset.cameras.height.view(-1).tolist())
    return torch.from_numpy(np.concatenate([circle(width, height, radius).reshape(-1) for width, height in sizes]))


def released_draws(manager: ContinualDataManager) -> torch.Tensor:
    """Many draws with task 2 open: half of them replay task 1's frames, so every training frame is drawn from."""
    manager.next_train(0)
    manager.release(1)
    return draws(manager)


@pytest.mark.parametrize("model", [*FISHEYE_MODELS, "OPENCV"])
def test_fisheye_pixels_outside_the_crop_radius_are_never_drawn(tmp_path, model):
    torch.manual_seed(0)
    shared = FISHEYE_MODELS.get(model, {"camera_model": model})
    capture = write_transforms(tmp_path / "capture", numbered_frames(arc_poses()), fisheye_crop_radius=RADIUS, **shared)
    manager = datamanager(capture, tmp_path / "outputs")
    dataset = manager.train_dataset
    flat = released_draws(manager)
    inside = in_circle(dataset, RADIUS)
    if model == "OPENCV":  # nerfstudio's rule: the radius crops fisheye frames only
        assert dataset.valid_pixels is None and not bool(inside[flat].all()), "a perspective frame trains whole"
        return
    assert bool(inside[flat].all()), "a pixel outside the fisheye circle was drawn"
    assert torch.equal(torch.unique(flat), torch.nonzero(inside).view(-1)), "every pixel inside it is drawn"
    _, batch = manager.next_train(1)
    _, y, x = batch["indices"].unbind(-1)
    assert bool(torch.from_numpy(circle(WIDTH, HEIGHT, RADIUS))[y, x].all()), "the batch's rays too"
    kept, _ = manager.open_task_pixels()  # what the replay buffer keeps a share of
    start, end = dataset.open_task_pixel_range()
    assert torch.equal(kept, torch.nonzero(inside[start:end]).view(-1) + start)


def test_only_the_fisheye_frames_of_a_capture_are_cropped(tmp_path):
    torch.manual_seed(0)
    frames = numbered_frames(arc_poses())
    for frame in frames[::2]:
        frame["camera_model"] = "OPENCV"
    capture = write_transforms(tmp_path / "capture", frames, camera_model="OPENCV_FISHEYE", fisheye_crop_radius=RADIUS)
    manager = datamanager(capture, tmp_path / "outputs")
    dataset = manager.train_dataset
    flat = released_draws(manager)
    frame = torch.searchsorted(dataset.pixel_offsets, flat, right=True) - 1
    fisheye = dataset.cameras.camera_type.view(-1)[frame] == CameraType.FISHEYE.value
    inside = in_circle(dataset, RADIUS)[flat]
    assert bool(fisheye.any()) and bool((~fisheye).any())
    assert bool(inside[fisheye].all()) and not bool(inside[~fisheye].all())


def test_the_crop_radius_scales_with_the_downscale_factor(tmp_path):
    torch.manual_seed(0)
    capture = write_transforms(
        tmp_path / "capture", numbered_frames(arc_poses()), camera_model="OPENCV_FISHEYE", fisheye_crop_radius=RADIUS
    )
    manager = datamanager(capture, tmp_path / "outputs", downscale_factor=2)
    dataset = manager.train_dataset
    flat = released_draws(manager)
    assert int(dataset.cameras.width[0]) == WIDTH // 2
    # the radius is in the listed images' pixels: half as many in the 16x12 images loaded
    assert torch.equal(torch.unique(flat), torch.nonzero(in_circle(dataset, RADIUS / 2)).view(-1))


def test_masks_and_the_fisheye_circle_both_apply(tmp_path):
    torch.manual_seed(0)
    capture = masked_capture(tmp_path / "capture", camera_model="OPENCV_FISHEYE", fisheye_crop_radius=RADIUS)
    manager = datamanager(capture, tmp_path / "outputs")
    dataset = manager.train_dataset
    flat = released_draws(manager)
    masked, inside = expected_valid(dataset), in_circle(dataset, RADIUS)
    assert bool((masked & ~inside).any()) and bool((inside & ~masked).any()), "each leaves out pixels the other keeps"
    assert torch.equal(torch.unique(flat), torch.nonzero(masked & inside).view(-1))


def test_a_task_masked_out_inside_its_fisheye_circle_is_a_one_line_error(tmp_path):
    capture = masked_capture(tmp_path / "capture", camera_model="OPENCV_FISHEYE", fisheye_crop_radius=RADIUS)
    outside = (~circle(WIDTH, HEIGHT, RADIUS)).astype(np.uint8) * 255
    for number in (14, 16, 18, 20):  # task 2's training frames: masks that keep only what the circle leaves out
        Image.fromarray(outside).save(capture / "masks" / f"frame_{number}.png")
    manager = datamanager(capture, tmp_path / "outputs")
    manager.next_train(0)
    with pytest.raises(DatasetError) as raised:
        manager.release(1)
    assert str(raised.value) == (
        f"{capture / 'masks' / 'frame_14.png'}: this and every other mask of task 2's training frames is 0 everywhere "
        "inside its fisheye circle: the task has no pixel to train on"
    )
