"""Appearance codes and pose corrections in the continual setting: learned while their task is open, bit-identical
after it closes, rendered per replayed ray by the oracle, kept by a resumed run, and given to test frames from the
nearest training frame of their task and camera."""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Dict

import numpy as np
import pytest
import torch
from helpers import DEMO_CACHE, demo_parser, stopped_run, tiny_config, train
from nerfstudio.cameras.camera_optimizers import CameraOptimizerConfig
from nerfstudio.cameras.cameras import Cameras
from nerfstudio.data.dataparsers.base_dataparser import DataparserOutputs
from nerfstudio.data.scene_box import SceneBox

from continual_nerf.compilation import random_rays
from continual_nerf.core.color_transform_fit import (
    fit_gains,
    fit_open_task_color_transforms,
    fit_summary,
    render_open_task_pixels,
)
from continual_nerf.core.continual_datamanager import ContinualDataManagerConfig, camera_ids
from continual_nerf.core.continual_pipeline import ContinualPipelineConfig
from continual_nerf.core.ngp_model import ContinualNGPModel, ContinualNGPModelConfig
from continual_nerf.core.per_frame import (
    FRAME_CAMERA,
    FRAME_TASK,
    TRAINING_FRAME,
    OpenTaskRows,
    code_of_frame,
    refine_rays,
    start_from_previous_task,
)
from continual_nerf.core.replay_oracle import ReplayOracle
from continual_nerf.core.task_split import nearest_train_frames, split_into_tasks
from continual_nerf.dataparsers.continual_demo_dataparser import ContinualDemoDataParserConfig
from continual_nerf.errors import ContinualConfigError
from continual_nerf.recipes import small_model
from continual_nerf.streaming.streaming_datamanager import StreamingDataManagerConfig

SCENE_BOX = SceneBox(aabb=torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]]))
CODES = "_model.field.embedding_appearance.embedding.weight"
POSES = "_model.camera_optimizer.pose_adjustment"
TRANSFORMS = "_model.color_transforms.transforms"


def model_with_codes_and_poses(tasks, cameras, **options) -> ContinualNGPModel:
    config = small_model(
        ContinualNGPModelConfig(
            compile=False,
            use_appearance_embedding=True,
            camera_optimizer=CameraOptimizerConfig(mode="SO3xR3"),
            **options,
        )
    )
    metadata = {FRAME_TASK: torch.tensor(tasks), FRAME_CAMERA: torch.tensor(cameras)}
    model = config.setup(scene_box=SCENE_BOX, num_train_data=len(tasks), metadata=metadata)
    assert isinstance(model, ContinualNGPModel)
    return model


def test_a_code_covers_one_image_or_one_cameras_images_of_one_task():
    tasks, cameras = torch.tensor([0, 0, 0, 0, 1, 1, 1, 1]), torch.tensor([0, 1, 0, 1, 0, 1, 0, 1])
    assert code_of_frame(tasks, cameras, "image").tolist() == list(range(8))
    assert code_of_frame(tasks, cameras, "camera-task").tolist() == [0, 1, 0, 1, 4, 5, 4, 5]


def test_a_task_starts_from_the_last_row_each_camera_had_in_the_task_before():
    tasks, cameras = torch.tensor([0, 0, 0, 0, 1, 1, 1]), torch.tensor([0, 1, 0, 1, 0, 1, 2])
    table = torch.arange(7.0)[:, None].repeat(1, 2)
    start_from_previous_task(table, code_of_frame(tasks, cameras, "image"), 1, tasks, cameras)
    # camera 0's last frame of task 0 is frame 2, camera 1's frame 3; camera 2 is new and keeps its row
    assert table[:, 0].tolist() == [0, 1, 2, 3, 2, 3, 6]


def test_a_colour_transform_scales_what_its_frame_records_and_the_oracle_applies_each_rays_own():
    model = model_with_codes_and_poses(tasks=[0, 0, 1], cameras=[0, 0, 0], use_color_transform=True)
    rays = random_rays(model, 64)
    with torch.no_grad():
        identity = model.color_transforms.transforms[0].clone()
        model.color_transforms.transforms[2, :, :3] *= torch.tensor([0.5, 1.0, 0.25])
        model.color_transforms.transforms[2, :, 3] = 0.1
        model.field.embedding_appearance.embedding.weight.zero_()  # one code: the transforms alone tell frames apart
    assert torch.equal(identity, torch.eye(3, 4)), "a transform starts as the identity"
    oracle = ReplayOracle()
    oracle.update(model)

    def render(frames: torch.Tensor) -> torch.Tensor:
        return oracle.render(dataclasses.replace(rays, camera_indices=frames[:, None], metadata={}))

    frame_0, frame_2 = render(torch.zeros(64, dtype=torch.long)), render(torch.full((64,), 2))
    expected = (frame_0 * torch.tensor([0.5, 1.0, 0.25]) + 0.1).clamp(0.0, 1.0)
    torch.testing.assert_close(frame_2, expected)
    mixed = torch.arange(64) % 2 * 2
    torch.testing.assert_close(render(mixed), torch.where(mixed[:, None] == 0, frame_0, frame_2))


def test_closed_rows_stay_bit_identical_under_adam_momentum():
    codes = torch.nn.Parameter(torch.zeros(4, 3))
    rows = OpenTaskRows([codes], task_of_row=torch.tensor([0, 0, 1, 1]))
    optimizer = torch.optim.Adam([codes], lr=0.1)
    rows.open(0)
    for _ in range(3):
        optimizer.zero_grad()
        (codes - 1).pow(2).sum().backward()
        optimizer.step()
        rows.restore()
    assert torch.equal(codes[2:], torch.zeros(2, 3)), "a task not open yet does not move"
    rows.open(1)
    task_1 = codes[:2].detach().clone()
    for _ in range(3):
        optimizer.zero_grad()
        codes[2:].pow(2).sum().backward()  # no gradient for task 1's rows, whose momentum would still move them
        optimizer.step()
        rows.restore()
    assert torch.equal(codes[:2], task_1) and not torch.equal(codes[2:], torch.zeros(2, 3))


def test_the_oracle_renders_each_replayed_ray_with_its_own_frames_code_and_refined_pose():
    model = model_with_codes_and_poses(tasks=[0, 0, 1, 1], cameras=[0, 0, 0, 0])
    with torch.no_grad():
        codes = model.field.embedding_appearance.embedding.weight
        codes.copy_(torch.randn_like(codes))
        codes[1] = codes[0]  # frames 0 and 1 look alike; frame 1 alone has a pose correction
        model.camera_optimizer.pose_adjustment[1] = torch.tensor([0.05, -0.02, 0.03, 0.02, -0.04, 0.01])
    oracle = ReplayOracle()
    oracle.update(model)
    rays = random_rays(model, 64)

    def render(frames: torch.Tensor, bundle=rays) -> torch.Tensor:
        return oracle.render(dataclasses.replace(bundle, camera_indices=frames[:, None], metadata={}))

    frame_0, frame_2 = render(torch.zeros(64, dtype=torch.long)), render(torch.full((64,), 2))
    assert (frame_0 - frame_2).abs().max() > 1e-3, "frames 0 and 2 have different codes"
    mixed = torch.arange(64) % 2 * 2  # a batch of replayed rays from frames 0 and 2, interleaved
    torch.testing.assert_close(render(mixed), torch.where(mixed[:, None] == 0, frame_0, frame_2))
    # frame 1: frame 0's code, rays moved by frame 1's pose correction
    moved = dataclasses.replace(rays, camera_indices=torch.ones(64, 1, dtype=torch.long))
    moved.origins, moved.directions = moved.origins.clone(), moved.directions.clone()
    correction = model.camera_optimizer(torch.tensor([1]))[0].detach()
    moved.origins = moved.origins + correction[:, 3]
    moved.directions = moved.directions @ correction[:, :3].T
    torch.testing.assert_close(
        render(torch.ones(64, dtype=torch.long)), render(torch.zeros(64, dtype=torch.long), moved)
    )


def test_rays_are_refined_as_nerfacto_refines_training_rays():
    model = model_with_codes_and_poses(tasks=[0, 0, 0], cameras=[0, 0, 0])
    with torch.no_grad():
        model.camera_optimizer.pose_adjustment.copy_(0.05 * torch.randn(3, 6))
    rays = random_rays(model, 12)
    rays.camera_indices = (torch.arange(12) % 3)[:, None]
    ours, nerfstudios = dataclasses.replace(rays), dataclasses.replace(rays)
    refine_rays(model.camera_optimizer, ours)
    model.camera_optimizer.apply_to_raybundle(nerfstudios)
    torch.testing.assert_close(ours.origins, nerfstudios.origins)
    torch.testing.assert_close(ours.directions, nerfstudios.directions)


def test_each_test_frame_takes_the_nearest_training_frame_of_its_task_and_camera():
    instants = np.repeat(np.arange(8), 2)  # a two-camera rig, 8 instants
    cameras = np.tile([0, 1], 8)
    split = split_into_tasks(16, 2, test_interval=3, time_group=instants)
    # task 1: instants 0-3, instants 0 and 3 held out; task 2: instants 4-7, instants 4 and 7 held out
    assert split.all_test_frames().tolist() == [0, 1, 6, 7, 8, 9, 14, 15]
    train_frames = split.all_train_frames()
    nearest = train_frames[nearest_train_frames(split, instants, cameras)]
    # instant 3 is as near to instant 4 (task 2) as to instant 2: its own task's frame; each camera its own
    assert nearest.tolist() == [2, 3, 4, 5, 10, 11, 12, 13]


def test_frames_with_the_same_intrinsics_are_one_camera_unless_the_parser_says():
    cameras = Cameras(
        camera_to_worlds=torch.eye(4)[:3].expand(3, 3, 4),
        fx=torch.tensor([[30.0], [40.0], [30.0]]),
        fy=30.0,
        cx=16.0,
        cy=12.0,
        width=32,
        height=24,
    )
    outputs = DataparserOutputs(image_filenames=[Path("a"), Path("b"), Path("c")], cameras=cameras)
    assert camera_ids(outputs).tolist() == [0, 1, 0]
    outputs.metadata["camera_id"] = torch.tensor([5, 5, 7])
    assert camera_ids(outputs).tolist() == [5, 5, 7]


def test_test_frames_render_with_their_nearest_training_frames_code_and_colour_transform():
    datamanager = ContinualDataManagerConfig(dataparser=demo_parser(num_frames=16), num_tasks=2).setup(device="cpu")
    eval_cameras = datamanager.eval_dataset.cameras
    nearest = eval_cameras.metadata[TRAINING_FRAME].view(-1)  # type: ignore[index]
    train_frames = datamanager.task_split.all_train_frames()
    assert train_frames[nearest].tolist() == [1, 9], "test frames 0 and 8 open their tasks: frames 1 and 9"
    dataset = datamanager.train_dataset
    model = model_with_codes_and_poses(
        dataset.metadata[FRAME_TASK].tolist(), dataset.metadata[FRAME_CAMERA].tolist(), use_color_transform=True
    )
    model.eval()

    def rendered() -> torch.Tensor:
        return model.get_outputs_for_camera(eval_cameras[1:2])["rgb"]

    for table in (model.field.embedding_appearance.embedding.weight, model.color_transforms.transforms):
        before = rendered()
        with torch.no_grad():
            table[int(nearest[0])] += 0.2  # another test frame's code or transform
        torch.testing.assert_close(rendered(), before)
        with torch.no_grad():
            table[int(nearest[1])] += 0.2
        assert (rendered() - before).abs().max() > 1e-3
    # ns-eval and the viewer's eval images take their cameras from these loaders: the metadata comes along
    loaded = [camera.metadata[TRAINING_FRAME].item() for camera, _ in datamanager.fixed_indices_eval_dataloader]
    assert loaded == nearest.tolist()


def test_a_gain_is_fitted_from_the_pixels_that_agree_not_from_what_the_model_has_not_seen():
    generator = torch.Generator().manual_seed(0)
    rendered = 0.1 + 0.6 * torch.rand(3000, 3, generator=generator)
    recorded = rendered * torch.tensor([0.7, 1.2, 0.9])
    unseen = torch.arange(3000) % 10 < 4  # 40 % of the pixels show what no earlier task saw
    recorded[unseen] = torch.rand(int(unseen.sum()), 3, generator=generator)
    recorded[:100] = 1.0  # clipped: no gain can be read from them
    frames = torch.arange(3000) % 2
    frames[-20:] = 2  # too few pixels
    cameras = torch.zeros(3000, dtype=torch.long)
    cameras[-20:] = 1  # and no other frame of its camera to borrow from
    fit = fit_gains(rendered, recorded, frames, rows=frames, cameras=cameras)
    assert set(fit.fitted) == {0, 1} and not fit.borrowed, "a row without enough usable pixels keeps its start"
    assert fit_summary(fit, num_rows=3) == "gains x0.93 to x0.93 fitted to 2 of 3 colour transforms"
    for gain in fit.fitted.values():
        torch.testing.assert_close(gain, torch.tensor([0.7, 1.2, 0.9]), atol=0.01, rtol=0)


def test_a_frame_that_shows_mostly_new_ground_takes_its_cameras_nearest_fitted_frames_gain():
    generator = torch.Generator().manual_seed(0)
    frames = torch.arange(4000) // 500  # eight frames in capture order, two cameras taking turns
    cameras = frames % 2
    rendered = 0.1 + 0.6 * torch.rand(4000, 3, generator=generator)
    gains = torch.tensor([[0.7, 1.2, 0.9], [1.1, 1.0, 0.8]])[cameras]
    recorded = rendered * gains
    unseen_share = torch.tensor([0.0, 0.1, 0.2, 0.3, 0.9, 0.9, 0.9, 0.9])[frames]  # later frames move into new ground
    unseen = torch.rand(4000, generator=generator) < unseen_share
    # where the model has seen nothing it renders a flat guess: those ratios spread around a wrong gain
    rendered[unseen] = 0.5
    recorded[unseen] = 0.2 + 0.4 * torch.rand(int(unseen.sum()), 3, generator=generator)
    fit = fit_gains(rendered, recorded, frames, rows=frames, cameras=cameras)
    assert set(fit.fitted) == {0, 1, 2, 3} and set(fit.borrowed) == {4, 5, 6, 7}
    for frame, gain in fit.gains.items():
        torch.testing.assert_close(gain, gains[frames == frame][0], atol=0.01, rtol=0)
    assert fit_summary(fit, num_rows=8).endswith(
        "fitted to 4 of 8 colour transforms, 4 more from their camera's nearest fitted frame"
    )


def test_the_open_tasks_colour_transforms_start_at_its_frames_exposure():
    datamanager = ContinualDataManagerConfig(dataparser=demo_parser(num_frames=16), num_tasks=2).setup(device="cpu")
    dataset = datamanager.train_dataset
    model = model_with_codes_and_poses(
        dataset.metadata[FRAME_TASK].tolist(), dataset.metadata[FRAME_CAMERA].tolist(), use_color_transform=True
    )
    datamanager.release(1)
    before = model.color_transforms.transforms.detach().clone()
    rendered, _, frames = render_open_task_pixels(model, datamanager)
    start, end = dataset.open_task_pixel_range()
    all_pixels = torch.arange(start, end)
    task_frames = dataset.frames_of_task(1)
    gains = 0.5 + 0.4 * torch.rand(len(dataset), 3)  # each frame of the open task recorded at its own exposure
    with torch.no_grad():
        model.eval()
        rays = datamanager.train_ray_generator(datamanager.ray_indices(all_pixels))
        rays.metadata[TRAINING_FRAME] = rays.camera_indices
        exact = model(rays)["rgb"]
    dataset.task_pixels = exact * gains[rays.camera_indices.view(-1)]
    assert fit_open_task_color_transforms(model, datamanager).endswith(
        f"fitted to {len(dataset.frames_of_task(1))} of {len(dataset.frames_of_task(1))} colour transforms"
    )
    after = model.color_transforms.transforms.detach()
    assert set(frames.tolist()) == set(task_frames.tolist()), "every frame of the open task is rendered"
    assert len(rendered) == len(frames)
    assert torch.equal(after[dataset.frames_of_task(0)], before[dataset.frames_of_task(0)]), "closed rows stay"
    for frame in task_frames.tolist():
        torch.testing.assert_close(after[frame], torch.diag(gains[frame]) @ torch.eye(3, 4), atol=0.01, rtol=0)


@pytest.mark.parametrize("option", ["use_appearance_embedding", "use_color_transform"])
def test_codes_transforms_and_poses_need_every_frame_from_the_start(option):
    pipeline = ContinualPipelineConfig(
        datamanager=StreamingDataManagerConfig(), model=ContinualNGPModelConfig(**{option: True})
    )
    with pytest.raises(ContinualConfigError, match="need every frame known when training starts"):
        pipeline.validate()


# ---- training runs ----


def with_codes_and_poses(config, groups: str = "image"):
    config.pipeline.model = dataclasses.replace(
        config.pipeline.model,
        use_appearance_embedding=True,
        use_color_transform=True,
        appearance_codes=groups,
        camera_optimizer=CameraOptimizerConfig(mode="SO3xR3"),
    )
    return config


def per_frame_state(checkpoint: Path) -> Dict[str, torch.Tensor]:
    state = torch.load(checkpoint, map_location="cpu", weights_only=True)["pipeline"]
    return {key: state[key] for key in (CODES, TRANSFORMS, POSES)}


@pytest.mark.slow
@pytest.mark.parametrize("groups", ["image", "camera-task"])
def test_a_closed_tasks_codes_and_pose_corrections_never_change_again(run_dir, groups, single_thread):
    parser = demo_parser(num_frames=24)
    config = with_codes_and_poses(tiny_config(run_dir, parser, num_tasks=3, iterations_per_task=6), groups)
    trainer = train(config)
    tasks = trainer.pipeline.datamanager.train_dataset.task_of_frame
    checkpoints = sorted(config.get_checkpoint_dir().glob("step-*.ckpt"))
    after_task = [per_frame_state(path) for path in checkpoints]
    assert len(after_task) == 3
    for key in (CODES, TRANSFORMS, POSES):
        task_1 = after_task[0][key][tasks == 0]
        untouched = torch.eye(3, 4) if key == TRANSFORMS else torch.zeros(())
        assert (task_1 - untouched).abs().sum() > 0, "task 1 learned its codes, transforms and corrections while open"
        for later in after_task[1:]:
            assert torch.equal(later[key][tasks == 0], task_1), f"{key}: task 1's rows moved after it closed"
        assert torch.equal(after_task[2][key][tasks == 1], after_task[1][key][tasks == 1])
    state = torch.load(checkpoints[-1], map_location="cpu", weights_only=True)["pipeline"]
    oracle_codes = state[CODES.replace("_model.", "replay_oracle.model.")]
    assert torch.equal(oracle_codes[tasks <= 1], after_task[2][CODES][tasks <= 1]), "the oracle has the same codes"


@pytest.mark.slow
def test_a_resumed_run_keeps_the_codes_and_corrections_and_ends_as_the_uninterrupted_run(tmp_path, single_thread):
    parser = demo_parser(num_frames=16)

    def config(name: str):
        run = with_codes_and_poses(tiny_config(tmp_path / name, parser, num_tasks=2, iterations_per_task=4))
        run.deterministic = True
        return run

    whole = config("whole")
    train(whole)
    end_of_task_1 = stopped_run(config("stopped"), last_step=3)
    resumed = config("resumed")
    resumed.load_checkpoint = end_of_task_1
    trainer = train(resumed)
    tasks = trainer.pipeline.datamanager.train_dataset.task_of_frame
    saved, final = per_frame_state(end_of_task_1), per_frame_state(next(resumed.get_checkpoint_dir().glob("*.ckpt")))
    uninterrupted = per_frame_state(whole.get_checkpoint_dir() / "step-000000007.ckpt")
    for key in (CODES, TRANSFORMS, POSES):
        assert torch.equal(final[key][tasks == 0], saved[key][tasks == 0]), "task 1's rows came back unchanged"
        assert torch.equal(final[key], uninterrupted[key]), "task 2 continued from the saved rows"


def test_demo_street_rig_reaches_the_model_as_cameras():
    parser = ContinualDemoDataParserConfig(data=DEMO_CACHE, scene="street", num_frames=8, width=24, height=18)
    datamanager = ContinualDataManagerConfig(dataparser=parser, num_tasks=2).setup(device="cpu")
    dataset = datamanager.train_dataset
    assert set(dataset.metadata[FRAME_CAMERA].tolist()) == {0, 1, 2}
    assert dataset.metadata[FRAME_TASK].tolist() == dataset.task_of_frame.tolist()
