"""A trained run goes on learning a later capture (--pipeline.continue-with-new-capture): its tasks after the earlier
ones, the earlier capture never read again (its folder removed here), the earlier tasks' rays, masks, codes and
transforms as they were, one world frame, one-line refusals."""

from __future__ import annotations

import dataclasses
import json
import shlex
import shutil
import subprocess
import sys
from pathlib import Path
from typing import Dict, Tuple

import numpy as np
import pytest
import torch
import yaml
from helpers import (
    SUBPROCESS_ENV,
    arc_poses,
    ctrl_c_when_saved,
    demo_parser,
    masked_capture,
    ns_train_command,
    numbered_frames,
    original_poses,
    replayed,
    run_ns_train,
    stream_config,
    tiny_config,
    train,
    write_transforms,
)
from nerfstudio.cameras.camera_optimizers import CameraOptimizerConfig
from nerfstudio.engine.callbacks import TrainingCallbackLocation
from nerfstudio.scripts.train import train_loop

from continual_nerf.bench.browser import free_port
from continual_nerf.checkpoints import find_checkpoint, read_checkpoint
from continual_nerf.core.accuracy_matrix import ACCURACY_MATRIX_FILENAME, AccuracyMatrix
from continual_nerf.core.continual_pipeline import CONTINUE_OPTION, MODEL_PREFIX
from continual_nerf.core.continual_trainer import ContinualTrainer, ContinualTrainerConfig
from continual_nerf.core.distillation_loss import REPLAY_SKIPPED
from continual_nerf.core.ngp_model import ContinualNGPModel
from continual_nerf.core.sessions import SESSIONS_FILENAME, SessionRecord
from continual_nerf.dataparsers.ordered_capture_dataparser import OrderedCaptureDataParserConfig
from continual_nerf.export_poses import ExportPoses
from continual_nerf.interrupts import resume_command
from continual_nerf.method_configs import CONTINUAL_NGP_INCRE
from continual_nerf.recipes import set_up_like_ns_train
from continual_nerf.streaming.replay_capture import ReplayCaptureConfig, replay
from continual_nerf.viewer.run_viewer import ContinualRunViewer
from continual_nerf.viewer.viewer_config import ContinualViewerConfig

NUM_FRAMES = 16
"""Instants of the demo room the tests cut into two sessions of 8."""


def session(run_dir: Path, data: Path, timestamp: str, first: bool, **options) -> ContinualTrainerConfig:
    """A tiny continual-ngp run on half of the demo room, copied to `data`: the first half, or the second."""
    cut = {"end_instant": NUM_FRAMES // 2} if first else {"start_instant": NUM_FRAMES // 2}
    parser = dataclasses.replace(demo_parser(num_frames=NUM_FRAMES), data=data, **cut)
    config = tiny_config(run_dir, parser, num_tasks=2, iterations_per_task=3, **options)
    config.timestamp = timestamp
    return config


def continued(config: ContinualTrainerConfig, earlier: ContinualTrainerConfig) -> ContinualTrainerConfig:
    """`config` going on from `earlier`'s latest checkpoint on its own capture."""
    config.load_dir = earlier.get_checkpoint_dir()
    config.pipeline.continue_with_new_capture = True
    return config


def set_up(config: ContinualTrainerConfig) -> ContinualTrainer:
    """The trainer ns-train would train `config` with, set up (its earlier sessions recorded), not trained."""
    config.save_config()
    return set_up_like_ns_train(config)


def folder_state(folder: Path) -> Dict[str, Tuple[int, int]]:
    return {str(path): (path.stat().st_size, path.stat().st_mtime_ns) for path in folder.rglob("*") if path.is_file()}


@pytest.fixture(scope="module")
def two_sessions(tmp_path_factory) -> Tuple[ContinualTrainerConfig, ContinualTrainerConfig, Dict[str, Tuple[int, int]]]:
    """A first session on the room's first half, then a second on the other half with the first's folder removed;
    the first run's folder as it was before the second started."""
    root = tmp_path_factory.mktemp("sessions")
    first = session(root / "outputs", root / "first", "first", first=True)
    train(first)
    shutil.rmtree(root / "first")
    before = folder_state(first.get_base_dir())
    second = continued(session(root / "outputs", root / "second", "second", first=False), first)
    train(second)
    return first, second, before


@pytest.mark.slow
def test_a_finished_run_learns_a_later_capture_with_the_earlier_capture_removed(two_sessions):
    first, second, before = two_sessions
    earlier = AccuracyMatrix.read(first.get_base_dir() / ACCURACY_MATRIX_FILENAME)
    matrix = AccuracyMatrix.read(second.get_base_dir() / ACCURACY_MATRIX_FILENAME)
    assert matrix.finished and matrix.num_tasks == 4
    assert matrix.psnr[:2] == earlier.psnr and matrix.steps[:2] == earlier.steps, "the earlier rows are kept"
    assert matrix.steps == [2, 5, 8, 11], "the steps go on from the first session's"
    assert [row[:2] for row in matrix.psnr[2:]] == [[None, None]] * 2, "its test images are gone: not available"
    assert all(value is not None and value > 5 for row in matrix.psnr[2:] for value in row[2:])
    assert matrix.depth_abs_rel[:2] == earlier.depth_abs_rel and len(matrix.depth_abs_rel) == 4
    assert [row[:2] for row in matrix.depth_abs_rel[2:]] == [[None, None]] * 2, "earlier depth maps are not recorded"
    assert all(value is not None for row in matrix.depth_abs_rel[2:] for value in row[2:]), "the new capture's depth"
    assert folder_state(first.get_base_dir()) == before, "the earlier run's folder is left as it was"
    saved = yaml.load((second.get_base_dir() / "config.yml").read_text(), Loader=yaml.Loader)
    assert saved.pipeline.datamanager.earlier_sessions == second.get_base_dir() / SESSIONS_FILENAME
    record = SessionRecord.load(second.get_base_dir() / SESSIONS_FILENAME)
    assert (record.num_tasks, record.tasks_per_session, record.next_step) == (2, [2], 6)


@pytest.mark.slow
def test_ns_eval_ns_render_the_viewer_and_export_poses_read_a_continued_run(two_sessions, tmp_path):
    first, second, _ = two_sessions
    config = second.get_base_dir() / "config.yml"
    bin_dir = Path(sys.executable).parent
    evaluated = subprocess.run(
        [str(bin_dir / "ns-eval"), "--load-config", str(config), "--output-path", str(tmp_path / "eval.json")],
        check=False, capture_output=True, text=True, timeout=300, env=SUBPROCESS_ENV,
    )  # fmt: skip
    assert evaluated.returncode == 0, evaluated.stderr[-2000:]
    assert json.loads((tmp_path / "eval.json").read_text())["results"]["psnr"] > 5.0, "over the test images still there"
    render = [str(bin_dir / "ns-render"), "dataset", "--load-config", str(config), "--output-path",
              str(tmp_path / "renders"), "--split", "train", "--rendered-output-names", "rgb"]  # fmt: skip
    rendered = subprocess.run(render, check=False, capture_output=True, text=True, timeout=300, env=SUBPROCESS_ENV)
    assert rendered.returncode == 0, rendered.stderr[-2000:]
    renders = [path for path in (tmp_path / "renders").rglob("*") if path.suffix in (".jpg", ".png")]
    assert len(renders) == 6 + 6, "both sessions' training frames"
    assert "gone (an earlier session's image)" in rendered.stdout

    transforms = ExportPoses(load_config=config, output_dir=tmp_path / "exported")
    transforms.main()
    frames = json.loads((tmp_path / "exported" / "transforms.json").read_text())["frames"]
    room = demo_parser(num_frames=NUM_FRAMES).setup()
    truth = room.returned_poses(room.capture())
    assert np.allclose([frame["transform_matrix"][:3] for frame in frames], truth, atol=1e-4), (
        "every session's frames, in the first session's world"
    )

    travel = ContinualRunViewer(config, viewer=ContinualViewerConfig(websocket_port=free_port())).start()
    try:
        assert travel.slider.max == 4 and sorted(travel.checkpoints) == [0, 1, 2, 3], "the slider spans both sessions"
        travel.show_task(0)  # the first session's checkpoint, in its own run folder
        end_of_task_1 = read_checkpoint(travel.checkpoints[0])["pipeline"]
        for name, value in travel.pipeline.model.state_dict().items():
            if isinstance(value, torch.Tensor):
                assert torch.equal(value, end_of_task_1[f"_model.{name}"]), name
        assert travel.checkpoints[0].parent == first.get_checkpoint_dir().resolve()
    finally:
        travel.viewer.viser_server.stop()


@pytest.mark.slow
def test_a_continued_run_is_continued_again_as_a_third_session(two_sessions, tmp_path):
    _, second, _ = two_sessions
    third = session(tmp_path / "outputs", tmp_path / "third", "third", first=False)
    third.pipeline.datamanager.dataparser = dataclasses.replace(
        third.pipeline.datamanager.dataparser,
        change="object-moved",  # type: ignore[call-arg]
    )
    trainer = train(continued(third, second))
    matrix = trainer.pipeline.accuracy
    assert matrix.finished and matrix.num_tasks == 6 and matrix.steps[4:] == [14, 17]
    assert trainer.pipeline.datamanager.sessions_record(6, {}).tasks_per_session == [2, 2, 2]


class EverythingChanged:
    """A change guard's view of the open task that sees every replayed ray cross a change."""

    task = 3
    changed_pixels = torch.zeros(0, dtype=torch.long)

    def crosses_change(self, origins: torch.Tensor, directions: torch.Tensor, distances: torch.Tensor) -> torch.Tensor:
        return torch.ones(len(origins), dtype=torch.bool)


@pytest.mark.slow
def test_the_change_guard_skips_earlier_sessions_replay_only(two_sessions, tmp_path, monkeypatch):
    first, _, _ = two_sessions
    trainer = set_up(continued(session(tmp_path / "outputs", tmp_path / "later", "later", first=False), first))
    pipeline, datamanager = trainer.pipeline, trainer.pipeline.datamanager
    datamanager.next_train(0)
    pipeline.open_next_task()  # task 4: tasks 1-2 are the first session's, task 3 this session's
    monkeypatch.setattr(pipeline, "_open_task_view", EverythingChanged)
    ray_bundle, batch = datamanager.next_train(0)
    pipeline.add_replay_targets(ray_bundle, batch)
    replayed_tasks = datamanager.train_dataset.task_of_frame[batch["indices"][:, 0]]
    replay, skipped = batch["is_replay"], batch[REPLAY_SKIPPED]
    assert set(replayed_tasks[replay].tolist()) == {0, 1, 2}
    assert torch.equal(skipped, replay & (replayed_tasks < 2)), "the later session's own closed task keeps its replay"


@pytest.mark.slow
def test_a_run_stopped_mid_task_goes_on_with_that_task_closed_and_measured(tmp_path):
    first = session(tmp_path / "outputs", tmp_path / "first", "first", first=True)
    first.max_num_iterations = 5  # task 2 (steps 3..5) stops after two of its steps
    train(first)
    stopped = AccuracyMatrix.read(first.get_base_dir() / ACCURACY_MATRIX_FILENAME)
    assert len(stopped.psnr) == 1 and not stopped.finished
    second = continued(session(tmp_path / "outputs", tmp_path / "second", "second", first=False), first)
    matrix = train(second).pipeline.accuracy
    assert [len(row) for row in matrix.psnr] == [1, 2, 3, 4] and matrix.finished
    assert matrix.psnr[0] == stopped.psnr[0] and matrix.steps[1] == 4, "task 2 closed where the first run stopped"
    assert all(value is not None for row in matrix.psnr for value in row), "the first capture is still there"


def masked_session(run_dir: Path, capture: Path, timestamp: str) -> ContinualTrainerConfig:
    """A tiny run on a transforms.json capture with masks, learning appearance codes, colour transforms and pose
    corrections."""
    config = tiny_config(run_dir, OrderedCaptureDataParserConfig(data=capture), num_tasks=2, iterations_per_task=3)
    config.pipeline.model = dataclasses.replace(
        config.pipeline.model,
        use_appearance_embedding=True,
        use_color_transform=True,
        camera_optimizer=CameraOptimizerConfig(mode="SO3xR3"),
    )
    config.timestamp = timestamp
    return config


PER_FRAME = (
    "field.embedding_appearance.embedding.weight",
    "color_transforms.transforms",
    "camera_optimizer.pose_adjustment",
)


PROPOSAL_NETWORKS = "proposal_networks."
"""State-dict keys of nerfacto's proposal networks in the model."""


@pytest.mark.slow
def test_a_later_session_trains_with_its_own_learning_rates_and_the_earlier_moments(two_sessions, tmp_path):
    first, _, _ = two_sessions
    config = continued(session(tmp_path / "outputs", tmp_path / "later", "later", first=False), first)
    fields = config.optimizers["fields"]
    config.optimizers["fields"] = {**fields, "optimizer": dataclasses.replace(fields["optimizer"], lr=0.02)}
    trainer = set_up(config)
    before, first_step = (
        TrainingCallbackLocation.BEFORE_TRAIN_ITERATION,
        trainer.pipeline.datamanager.session_first_step,
    )
    for callback in trainer.callbacks:  # the learning rates' schedule too starts from this session's
        callback.run_callback_at_location(first_step, before)
    optimizer = trainer.optimizers.optimizers["fields"]
    assert [group["lr"] for group in optimizer.param_groups] == [0.02], "the earlier session's 0.01 came back"
    assert optimizer.state, "the moments are the earlier session's"


@pytest.mark.slow
@pytest.mark.parametrize("relearn", [True, False])
def test_a_later_session_relearns_the_proposal_networks_when_told_to(two_sessions, tmp_path, relearn):
    first, _, _ = two_sessions
    saved = read_checkpoint(find_checkpoint(first.get_checkpoint_dir(), None))["pipeline"]
    config = continued(session(tmp_path / "outputs", tmp_path / "later", "later", first=False), first)
    config.pipeline.relearn_proposal_networks = relearn
    trainer = set_up(config)
    model, oracle = trainer.pipeline.model, trainer.pipeline.replay_oracle.model
    assert oracle is not None

    def proposal_parameters(module: torch.nn.Module) -> Dict[str, torch.Tensor]:
        return {key: value for key, value in module.named_parameters() if key.startswith(PROPOSAL_NETWORKS)}

    loaded = {key: saved[MODEL_PREFIX + key] for key in proposal_parameters(model)}
    assert loaded and all(torch.equal(value, loaded[key]) for key, value in proposal_parameters(oracle).items())
    same = [torch.equal(value, loaded[key]) for key, value in proposal_parameters(model).items()]
    assert not any(same) if relearn else all(same)
    moments = trainer.optimizers.optimizers["proposal_networks"].state
    has_moments = [parameter in moments for parameter in proposal_parameters(model).values()]
    assert not any(has_moments) if relearn else all(has_moments)
    assert trainer.optimizers.optimizers["fields"].state, "the field goes on with its moments"


@pytest.mark.slow
@pytest.mark.parametrize("restart", [True, False])
def test_a_later_session_restarts_the_optimizer_moments_when_told_to(two_sessions, tmp_path, restart):
    first, _, _ = two_sessions
    config = continued(session(tmp_path / "outputs", tmp_path / "later", "later", first=False), first)
    config.pipeline.restart_optimizer_moments = restart
    saved = read_checkpoint(find_checkpoint(first.get_checkpoint_dir(), None))["pipeline"]
    trainer = set_up(config)
    moments = [optimizer.state for optimizer in trainer.optimizers.optimizers.values()]
    assert not any(moments) if restart else all(moments), "moments left" if restart else "the loaded moments lost"
    weights = dict(trainer.pipeline.model.named_parameters())
    assert all(torch.equal(value, saved[MODEL_PREFIX + key]) for key, value in weights.items()), "the weights stay"


@pytest.mark.slow
def test_the_earlier_tasks_rays_masks_codes_and_transforms_are_bit_identical_after_loading(tmp_path):
    first = masked_session(tmp_path / "outputs", masked_capture(tmp_path / "first"), "first")
    trained = train(first)
    shutil.rmtree(tmp_path / "first")
    later = write_transforms(tmp_path / "later", numbered_frames(arc_poses(20)[10:]))
    trainer = set_up(continued(masked_session(tmp_path / "outputs", later, "second"), first))

    before, after = trained.pipeline.datamanager, trainer.pipeline.datamanager
    count = len(before.train_dataset)
    for name in ("camera_to_worlds", "fx", "fy", "cx", "cy", "width", "height", "camera_type"):
        assert torch.equal(
            getattr(after.train_dataset.cameras, name)[:count], getattr(before.train_dataset.cameras, name)
        )
    pixels = int(before.train_dataset.pixel_offsets[-1])
    indices = before.ray_indices(torch.arange(0, pixels, 7))
    rays_before, rays_after = before.train_ray_generator(indices), after.train_ray_generator(indices)
    assert torch.equal(rays_before.origins, rays_after.origins)
    assert torch.equal(rays_before.directions, rays_after.directions)
    valid_before, valid_after = before.train_dataset.valid_pixels, after.train_dataset.valid_pixels
    assert valid_before is not None and valid_after is not None
    flat = torch.arange(pixels)
    assert torch.equal(valid_before.contains(flat), valid_after.contains(flat)), "the masks, as one bit per pixel"
    assert torch.equal(
        before.eval_dataset.cameras.camera_to_worlds,
        after.eval_dataset.cameras.camera_to_worlds[: len(before.eval_dataset)],
    ), "the held-out test frames"

    model_before, model_after = trained.pipeline.model.state_dict(), trainer.pipeline.model.state_dict()
    model = trainer.pipeline.model
    assert isinstance(model, ContinualNGPModel) and set(PER_FRAME) <= set(model.per_frame_state_keys())
    for key, value in model_before.items():
        if key in model.per_frame_state_keys():
            assert model_after[key].shape[0] == len(after.train_dataset) > count
            assert torch.equal(model_after[key][:count], value[:count]), key
        elif isinstance(value, torch.Tensor):
            assert torch.equal(model_after[key], value), key
    oracle = trainer.pipeline.replay_oracle.model
    assert oracle is not None, "the loaded model is the replay oracle of the earlier tasks"
    for key, value in oracle.state_dict().items():
        if isinstance(value, torch.Tensor) and value.dim():  # per-frame rows: the earlier frames' as saved
            assert torch.equal(value[:count], model_before[key][:count]), key

    trainer.train()  # the earlier rows stay as they were while the new capture trains
    model_trained = trainer.pipeline.model.state_dict()
    for key in PER_FRAME:
        assert torch.equal(model_trained[key][:count], model_before[key]), key


def same_world_captures(tmp_path: Path, shift: float = 0.0) -> Tuple[Path, Path, np.ndarray, np.ndarray]:
    """Two transforms.json captures in one world: an arc, and the arc going on (shifted by `shift` metres in x)."""
    poses = arc_poses(20)
    earlier, later = poses[:10], poses[10:].copy()
    later[:, 0, 3] += shift
    first = write_transforms(tmp_path / "first", numbered_frames(earlier))
    second = write_transforms(tmp_path / "second", numbered_frames(later))
    return first, second, earlier, later


def transforms_run(run_dir: Path, capture: Path, timestamp: str, **options) -> ContinualTrainerConfig:
    config = tiny_config(run_dir, OrderedCaptureDataParserConfig(data=capture), iterations_per_task=2, **options)
    config.timestamp = timestamp
    return config


@pytest.fixture(scope="module")
def first_transforms_run(tmp_path_factory) -> Tuple[ContinualTrainerConfig, Path, np.ndarray, np.ndarray]:
    root = tmp_path_factory.mktemp("world")
    first, second, earlier, later = same_world_captures(root)
    config = transforms_run(root / "outputs", first, "first")
    train(config)
    return config, second, earlier, later


@pytest.mark.slow
def test_the_continuation_keeps_the_first_runs_world_frame(first_transforms_run, tmp_path):
    first, second, earlier, later = first_transforms_run
    trainer = set_up(continued(transforms_run(tmp_path / "outputs", second, "second"), first))
    datamanager = trainer.pipeline.datamanager
    outputs = datamanager.train_dataparser_outputs
    world = original_poses(outputs)
    # every frame, the earlier session's included, maps back to the pose its capture gave it: the same world point
    assert np.allclose(world[:10], earlier[:, :3], atol=1e-5) and np.allclose(world[10:], later[:, :3], atol=1e-5)
    own = OrderedCaptureDataParserConfig(data=second).setup().get_dataparser_outputs("train")
    assert not np.allclose(own.cameras.camera_to_worlds.numpy(), outputs.cameras.camera_to_worlds[10:].numpy()), (
        "the later capture is not recentred on its own"
    )
    trainer.train()
    saved, first_saved = (
        (config.get_base_dir() / "dataparser_transforms.json").read_text() for config in (trainer.config, first)
    )
    assert saved == first_saved, "the chain is the first run's: its transform and scale"


@pytest.mark.slow
def test_a_capture_far_outside_the_scene_box_is_one_line_unless_accepted(first_transforms_run, tmp_path):
    first, _, _, _ = first_transforms_run
    _, far, _, _ = same_world_captures(tmp_path / "far", shift=1000.0)
    config = continued(transforms_run(tmp_path / "outputs", far, "far"), first)
    with pytest.raises(SystemExit) as exit_info:
        set_up(config)
    message = str(exit_info.value.code)
    assert "\n" not in message and message.startswith(f"continual-ngp: error: {far}: 10 of 10 cameras lie far outside")
    assert "--pipeline.datamanager.accept-cameras-outside-scene-box True" in message
    accepted = continued(transforms_run(tmp_path / "outputs", far, "accepted"), first)
    accepted.pipeline.datamanager.accept_cameras_outside_scene_box = True
    assert set_up(accepted).pipeline.datamanager.earlier_tasks == 2


@pytest.mark.slow
def test_another_method_or_a_model_of_another_size_is_refused_with_one_line(first_transforms_run, tmp_path):
    first, second, _, _ = first_transforms_run
    other = continued(transforms_run(tmp_path / "outputs", second, "incre", method=CONTINUAL_NGP_INCRE), first)
    with pytest.raises(SystemExit) as exit_info:
        set_up(other)
    assert str(exit_info.value.code).endswith(
        "a checkpoint of continual-ngp, not of continual-ngp-incre; resume it with ns-train continual-ngp"
    )
    bigger = continued(transforms_run(tmp_path / "outputs", second, "bigger"), first)
    bigger.pipeline.model.log2_hashmap_size = 16
    with pytest.raises(SystemExit) as exit_info:
        set_up(bigger)
    message = str(exit_info.value.code)
    assert "\n" not in message and "--pipeline.model.log2-hashmap-size 15 there, 16 here" in message


@pytest.mark.slow
def test_the_capture_it_already_trains_or_no_run_to_continue_is_refused_with_one_line(first_transforms_run, tmp_path):
    first, _, _, _ = first_transforms_run
    same = continued(
        transforms_run(tmp_path / "outputs", Path(first.pipeline.datamanager.dataparser.data), "same"), first
    )
    with pytest.raises(SystemExit) as exit_info:
        set_up(same)
    assert "its last session was trained on" in str(exit_info.value.code)
    into_its_folder = continued(transforms_run(tmp_path / "outputs", tmp_path / "unused", "first"), first)
    into_its_folder.output_dir = first.output_dir
    with pytest.raises(SystemExit, match="already holds a run"):
        into_its_folder.save_config()
    alone = transforms_run(tmp_path / "outputs", Path(first.pipeline.datamanager.dataparser.data), "alone")
    alone.pipeline.continue_with_new_capture = True
    with pytest.raises(SystemExit) as exit_info:
        set_up(alone)
    assert str(exit_info.value.code).endswith(
        "--pipeline.continue-with-new-capture needs the run to continue: --load-dir <run>/nerfstudio_models"
    )


@pytest.mark.slow
def test_a_closed_tasks_weights_only_checkpoint_is_refused_naming_the_latest(first_transforms_run, tmp_path):
    first, second, _, _ = first_transforms_run
    config = continued(transforms_run(tmp_path / "outputs", second, "slim"), first)
    steps = sorted(read_checkpoint(path)["step"] for path in first.get_checkpoint_dir().glob("step-*.ckpt"))
    config.load_step = steps[0]  # the end of task 1: its weights alone once task 2's checkpoint was saved
    with pytest.raises(SystemExit) as exit_info:
        set_up(config)
    message = str(exit_info.value.code)
    assert "\n" not in message and "keeps the model's weights of a finished task only" in message
    assert message.endswith(f"the latest, step-{steps[-1]:09d}.ckpt")


@pytest.mark.slow
def test_a_continued_run_interrupted_and_resumed_ends_as_the_uninterrupted_continuation(tmp_path):
    outputs = tmp_path / "outputs"
    first = session(outputs, tmp_path / "first", "first", first=True)
    first.pipeline.datamanager.iterations_per_task = 8  # steps 0..15
    train(first)
    shutil.rmtree(tmp_path / "first")
    options = [
        *("--pipeline.datamanager.num-tasks", "2", "--pipeline.datamanager.iterations-per-task", "8"),
        *("--steps-per-save", "20"),  # the continuation's task 3 spans steps 16..23
        *("--load-dir", str(first.get_checkpoint_dir()), CONTINUE_OPTION, "True"),
    ]
    size = ("--num-frames", str(NUM_FRAMES), "--width", "24", "--height", "18")
    demo = ["continual-demo", "--data", str(tmp_path / "second"), *size, "--start-instant", str(NUM_FRAMES // 2)]
    command = ns_train_command(outputs, "interrupted", options, demo)
    folder = outputs / "unnamed" / "continual-ngp" / "interrupted"
    stderr = ctrl_c_when_saved(command, folder / "nerfstudio_models" / f"step-{20:09d}.ckpt", tmp_path / "ctrl-c.log")
    resume = stderr.strip().splitlines()[-1].split(" saved; resume with: ")[1]
    assert CONTINUE_OPTION not in resume and f"--load-dir {folder / 'nerfstudio_models'}" in resume
    resumed = run_ns_train([command[0], *shlex.split(resume)[1:]])
    assert resumed.returncode == 0, resumed.stderr[-3000:]
    after_resume = AccuracyMatrix.read(folder / ACCURACY_MATRIX_FILENAME)

    config = yaml.load((folder / "config.yml").read_text(), Loader=yaml.Loader)
    config.timestamp = "uninterrupted"  # from the first session's checkpoint, as the interrupted run started
    config.load_dir, config.pipeline.continue_with_new_capture = first.get_checkpoint_dir(), True
    config.save_config()  # as ns-train does before its training loop
    train_loop(local_rank=0, world_size=1, config=config)
    uninterrupted = AccuracyMatrix.read(config.get_base_dir() / ACCURACY_MATRIX_FILENAME)
    assert after_resume.status == "finished" and after_resume.steps == uninterrupted.steps == [7, 15, 23, 31]
    assert [row[:2] for row in after_resume.psnr[2:]] == [[None, None]] * 2
    pairs = zip(after_resume.psnr[2:], uninterrupted.psnr[2:])
    differences = [abs(a - b) for ra, rb in pairs for a, b in zip(ra[2:], rb[2:])]
    assert max(differences) <= 0.3, f"resumed {after_resume.psnr} vs uninterrupted {uninterrupted.psnr}"


@pytest.mark.slow
def test_the_stream_goes_on_learning_a_new_capture_folder(tmp_path):
    first = stream_config(tmp_path / "outputs", replayed(tmp_path / "first", end_marker=True), "wait", 6, 3)
    first.timestamp = "first"
    train(first)
    shutil.rmtree(tmp_path / "first")
    later = dataclasses.replace(demo_parser(num_frames=12), start_instant=6)
    capture = tmp_path / "later" / "capture"
    replay(ReplayCaptureConfig(output=capture, fps=0, end_marker=True, dataparser=later))
    second = continued(stream_config(tmp_path / "outputs", capture, "wait", 6, 3), first)
    second.timestamp = "second"
    trainer = train(second)
    matrix = trainer.pipeline.accuracy
    # the stream's task may train on until its end marker is read
    assert matrix.finished and matrix.num_tasks == 2 and matrix.steps[0] == 2 and matrix.steps[1] >= 5
    assert matrix.psnr[1][0] is None and matrix.psnr[1][1] is not None, "the first capture folder is gone"
    assert trainer.pipeline.datamanager.earlier_tasks == 1


def test_the_resume_command_of_a_continued_run_leaves_the_new_session_option_out():
    argv = ["/venv/bin/ns-train", "continual-ngp", "--load-dir", "a/nerfstudio_models", CONTINUE_OPTION, "True",
            "continual-demo", "--data", "later"]  # fmt: skip
    assert resume_command(Path("b/nerfstudio_models"), argv, dropped=[CONTINUE_OPTION]) == (
        "ns-train continual-ngp --load-dir b/nerfstudio_models continual-demo --data later"
    )


@pytest.mark.slow
def test_a_finished_run_resumed_without_the_option_says_how_to_continue_it(first_transforms_run, tmp_path):
    first, second, _, _ = first_transforms_run
    resumed = transforms_run(tmp_path / "outputs", second, "resumed")
    resumed.load_dir = first.get_checkpoint_dir()
    with pytest.raises(SystemExit) as exit_info:
        set_up(resumed)
    assert str(exit_info.value.code).endswith(
        "its run already trained all 2 tasks (to go on learning a later capture, add "
        "--pipeline.continue-with-new-capture True)"
    )
