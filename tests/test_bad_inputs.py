"""A corpus of broken inputs: options, dataparsers' files, checkpoints to resume from, an occupied run folder.

Each one ends the run with a single line naming the option or file at fault and a non-zero exit, and leaves
every file of an earlier run as it was. Most run in-process through ContinualTrainer as `ns-train` drives it;
a few run through the real `ns-train`, which must print no traceback.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import hashlib
import json
import os
import shutil
import struct
import subprocess
import threading
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Dict, Iterator, List, Literal, Optional, Tuple

import numpy as np
import pytest
from helpers import (
    CAMERAS,
    DEMO_CACHE,
    HEIGHT,
    IMAGE_TIMES,
    SCANNET_DEPTH_INTRINSIC,
    SUBPROCESS_ENV,
    WIDTH,
    arc_poses,
    corrupt,
    demo_parser,
    edit_transforms,
    fill_the_disk_at_checkpoint,
    flip_tensor_bytes,
    ns_train_command,
    numbered_frames,
    scannet_poses,
    stream_config,
    tiny_config,
    train,
    v1_frame,
    with_depth_maps,
    write_exported,
    write_sens,
    write_sequence,
    write_transforms,
    write_v1,
)
from nerfstudio.data.dataparsers.base_dataparser import DataParserConfig, DataparserOutputs
from nerfstudio.engine.callbacks import TrainingCallback, TrainingCallbackLocation
from nerfstudio.model_components.losses import DepthLossType
from nerfstudio.utils import writer
from PIL import Image

from continual_nerf.core.accuracy_matrix import ACCURACY_MATRIX_FILENAME, AccuracyMatrix
from continual_nerf.core.continual_trainer import ContinualTrainerConfig
from continual_nerf.core.depth_model import ContinualNGPDepthModelConfig
from continual_nerf.dataparsers.continual_demo_dataparser import ContinualDemoDataParserConfig
from continual_nerf.dataparsers.ordered_capture_dataparser import OrderedCaptureDataParserConfig
from continual_nerf.dataparsers.scannet_dataparser import ContinualScanNetDataParserConfig
from continual_nerf.dataparsers.stream_dataparser import StreamDataParserConfig
from continual_nerf.dataparsers.tum_dataparser import ContinualTumDataParserConfig
from continual_nerf.dataparsers.waymo_dataparser import WaymoDataParserConfig
from continual_nerf.errors import ContinualConfigError
from continual_nerf.method_configs import (
    CONTINUAL_NERF_MEIL,
    CONTINUAL_NGP,
    CONTINUAL_NGP_DEPTH,
    CONTINUAL_NGP_INCRE,
    continual_ngp_ewc,
    continual_ngp_joint,
)
from continual_nerf.streaming.replay_capture import frame_json, write_frame, write_marker


@dataclass
class Context:
    """Where a case builds its inputs."""

    scratch: Path
    """An empty folder of the case's own."""
    earlier: Path
    """Run folder of a finished 2-task run (checkpoints of steps 1 and 3) in the outputs folder every case writes to."""


Build = Callable[[Context], Tuple[ContinualTrainerConfig, str]]
"""A broken run's config (the test sets its outputs folder), and the text its error line must hold: the option or
the file at fault."""


@dataclass
class BadInput:
    name: str
    build: Build
    fails_in: Literal["setup", "train"] = "setup"
    """setup: before any training step; train: once training runs (an image is read when its task opens)."""
    environment: Optional[Callable[[pytest.MonkeyPatch], None]] = None
    """What goes wrong around the run rather than in its input (a disk that fills up), set up before it starts."""
    as_root: bool = True
    """Whether the case can happen to root (who writes into read-only folders)."""


# ---- builders ----


def corpus_run(
    parser: DataParserConfig, num_tasks: int = 2, method: ContinualTrainerConfig = CONTINUAL_NGP, **datamanager_options
) -> ContinualTrainerConfig:
    config = tiny_config(Path("outputs"), parser, num_tasks=num_tasks, iterations_per_task=2, method=method)
    config.pipeline.datamanager = dataclasses.replace(config.pipeline.datamanager, **datamanager_options)
    return config


def option(message: str, parser_options: Optional[Dict] = None, **datamanager_options) -> Build:
    """The 12-frame demo scene with bad datamanager or dataparser options."""
    parser = dataclasses.replace(demo_parser(num_frames=12, width=16, height=12), **(parser_options or {}))
    return lambda context: (corpus_run(parser, **datamanager_options), message)


def nerfstudio_capture(edit: Callable[[Path], str]) -> Build:
    """A 10-frame transforms.json capture (frame_2 ... frame_20, 32x24; task 2 trains on frame_14 ... frame_20),
    broken by `edit`, which returns the expected message."""

    def build(context: Context) -> Tuple[ContinualTrainerConfig, str]:
        folder = write_transforms(context.scratch / "capture", numbered_frames(arc_poses()))
        message = edit(folder)
        return corpus_run(OrderedCaptureDataParserConfig(data=folder)), message

    return build


def replace_image(folder: Path, number: int, pixels: np.ndarray) -> Path:
    path = folder / "images" / f"frame_{number}.png"
    Image.fromarray(pixels).save(path)
    return path


def garbage_image(folder: Path) -> str:
    path = folder / "images" / "frame_4.png"
    path.write_bytes(b"not a png at all")
    return f"{path}: cannot read image (cannot identify image file"


def truncated_image_of_task_2(folder: Path) -> str:
    path = folder / "images" / "frame_16.png"  # its header stays readable: the pixels fail when task 2 opens
    path.write_bytes(path.read_bytes()[:-200])
    return f"{path}: cannot read image (image file is truncated"


def sixteen_bit_image(folder: Path) -> str:
    path = replace_image(folder, 6, np.full((24, 32), 40000, dtype=np.uint16))
    return f"{path}: image mode I;16 is not supported (8-bit L, RGB, RGBA only)"


def nan_pose(folder: Path) -> str:
    edit_transforms(folder, frame_6={"transform_matrix": [[float("nan")] * 4] * 4})
    return f"{folder / 'transforms.json'} frame images/frame_6.png: pose has NaN or infinite entries"


def duplicate_timestamps(folder: Path) -> str:
    edit_transforms(folder, **{f"frame_{number}": {"time": float(number)} for number in range(2, 21, 2)})
    edit_transforms(folder, frame_4={"time": 1.5}, frame_8={"time": 1.5})
    return f"{folder / 'transforms.json'}: frames images/frame_"


def invalid_json(folder: Path) -> str:
    (folder / "transforms.json").write_text('{"frames": [')
    return f"{folder / 'transforms.json'}: not valid JSON"


def missing_capture(context: Context) -> Tuple[ContinualTrainerConfig, str]:
    folder = context.scratch / "nowhere"
    return corpus_run(OrderedCaptureDataParserConfig(data=folder)), f"{folder}: no such capture folder or file"


def tum_image_of_another_size(context: Context) -> Tuple[ContinualTrainerConfig, str]:
    sequence = write_sequence(context.scratch / "rgbd_dataset_freiburg1_desk")
    image = sequence / "rgb" / f"{IMAGE_TIMES[8]:.6f}.png"
    Image.fromarray(np.zeros((12, 16, 3), dtype=np.uint8)).save(image)
    return corpus_run(ContinualTumDataParserConfig(data=sequence)), f"{image}: image is 16x12 pixels, its camera 32x24"


def zero_focal_length(folder: Path) -> str:
    edit_transforms(folder, frame_6={"fl_x": 0})
    return f"{folder / 'transforms.json'} frame images/frame_6.png: focal lengths must be finite and positive"


def tum_resized_to_another_aspect_ratio(context: Context) -> Tuple[ContinualTrainerConfig, str]:
    sequence = write_sequence(context.scratch / "rgbd_dataset_freiburg1_desk")
    for image in (sequence / "rgb").iterdir():
        Image.new("RGB", (32, 32)).save(image)
    message = f"{sequence} (sensor calibration): the images are 32x32 pixels, the calibration is for 640x480"
    return corpus_run(ContinualTumDataParserConfig(data=sequence)), message


def depth_capture(edit: Callable[[Path], str]) -> Build:
    """nerfstudio_capture with a depth map per frame, trained by continual-ngp-depth, broken by `edit`."""

    def build(context: Context) -> Tuple[ContinualTrainerConfig, str]:
        folder = with_depth_maps(write_transforms(context.scratch / "capture", numbered_frames(arc_poses())))
        message = edit(folder)
        return corpus_run(OrderedCaptureDataParserConfig(data=folder), method=CONTINUAL_NGP_DEPTH), message

    return build


def colour_depth_map(folder: Path) -> str:
    path = folder / "depth" / "frame_4.png"
    Image.new("RGB", (WIDTH, HEIGHT)).save(path)
    return f"{path}: depth map mode RGB is not supported (one channel of 16-bit integers or 32-bit floats"


def truncated_depth_map_of_task_2(folder: Path) -> str:
    path = folder / "depth" / "frame_16.png"  # its header stays readable: the values fail when task 2 opens
    path.write_bytes(path.read_bytes()[:-200])
    return f"{path}: cannot read depth map ("


def depth_method_without_depth(context: Context) -> Tuple[ContinualTrainerConfig, str]:
    folder = write_transforms(context.scratch / "capture", numbered_frames(arc_poses()))
    config = corpus_run(OrderedCaptureDataParserConfig(data=folder), method=CONTINUAL_NGP_DEPTH)
    return config, f"{folder}: has no depth maps (ScanNet depth/, TUM depth.txt, transforms.json depth_file_path)"


def depth_method_on_a_stream(context: Context) -> Tuple[ContinualTrainerConfig, str]:
    config = stream_config(context.scratch / "runs", context.scratch / "capture", "wait", 4, 2)
    model = {f.name: getattr(config.pipeline.model, f.name) for f in dataclasses.fields(config.pipeline.model)}
    config.pipeline.model = ContinualNGPDepthModelConfig(**{k: v for k, v in model.items() if k != "_target"})
    return config, "a model that trains on depth (continual-ngp-depth) needs a finished capture's depth maps"


def scannet_depth_map_missing(context: Context) -> Tuple[ContinualTrainerConfig, str]:
    folder = write_exported(context.scratch / "scene0101_00", scannet_poses(6), depth_intrinsic=SCANNET_DEPTH_INTRINSIC)
    (folder / "depth" / "4.png").unlink()
    return corpus_run(ContinualScanNetDataParserConfig(data=folder)), f"{folder / 'depth' / '4.png'}: depth map missing"


def sens_occi_depth(context: Context) -> Tuple[ContinualTrainerConfig, str]:
    sens = context.scratch / "scene.sens"
    write_sens(sens, scannet_poses(4), depth_compression=2)
    message = f"{sens}: depth frames are occi_ushort-compressed; only raw_ushort and zlib_ushort depth can be read"
    return corpus_run(ContinualScanNetDataParserConfig(data=sens)), message


def scannet_intrinsics_nan(context: Context) -> Tuple[ContinualTrainerConfig, str]:
    folder = write_exported(context.scratch / "scene0101_00", scannet_poses(6))
    intrinsic_file = folder / "intrinsic" / "intrinsic_color.txt"
    intrinsic_file.write_text(intrinsic_file.read_text().replace("1.134000000000000000e+03", "nan", 1))
    message = f"{intrinsic_file}: focal lengths must be finite and positive, got fx=nan"
    return corpus_run(ContinualScanNetDataParserConfig(data=folder)), message


def tum_without_groundtruth(context: Context) -> Tuple[ContinualTrainerConfig, str]:
    sequence = write_sequence(context.scratch / "rgbd_dataset_freiburg1_desk")
    (sequence / "groundtruth.txt").unlink()
    return corpus_run(ContinualTumDataParserConfig(data=sequence)), str(sequence / "groundtruth.txt")


def truncated_sens(context: Context) -> Tuple[ContinualTrainerConfig, str]:
    sens = context.scratch / "scene.sens"
    write_sens(sens, scannet_poses(4))
    sens.write_bytes(sens.read_bytes()[:-30])
    return corpus_run(ContinualScanNetDataParserConfig(data=sens)), f"{sens}: truncated .sens file"


def corrupt_tfrecord(context: Context) -> Tuple[ContinualTrainerConfig, str]:
    segment = write_v1(context.scratch / "segment.tfrecord", times=[0, 1])
    corrupt(segment, 12 + len(v1_frame(0, CAMERAS)) + 4 + 12 + 500)  # a byte inside the second record's data
    parser = WaymoDataParserConfig(data=segment, image_cache=context.scratch / "cache")
    return corpus_run(parser), f"{segment}: record 1 has corrupt data (its CRC does not match)"


def with_model_options(config: ContinualTrainerConfig, **options: Any) -> ContinualTrainerConfig:
    config.pipeline.model = dataclasses.replace(config.pipeline.model, **options)
    return config


def earlier_run_config(
    num_tasks: int = 2, method: ContinualTrainerConfig = CONTINUAL_NGP, **datamanager_options
) -> ContinualTrainerConfig:
    return corpus_run(demo_parser(num_frames=16), num_tasks=num_tasks, method=method, **datamanager_options)


def earlier_checkpoints(context: Context) -> Path:
    return context.earlier / "nerfstudio_models"


def resume(
    message: Callable[[Path], str],
    load_dir: Callable[[Context], Path] = earlier_checkpoints,
    load_step: Optional[int] = None,
    num_tasks: int = 2,
    method: ContinualTrainerConfig = CONTINUAL_NGP,
    datamanager_options: Optional[Dict[str, Any]] = None,
    **model_options,
) -> Build:
    """The earlier run's config (with `num_tasks`, `method` and the options changed) resuming from `load_dir`."""

    def build(context: Context) -> Tuple[ContinualTrainerConfig, str]:
        config = earlier_run_config(num_tasks, method, **(datamanager_options or {}))
        config.pipeline.model = dataclasses.replace(config.pipeline.model, **model_options)
        config.load_dir, config.load_step = load_dir(context), load_step
        return config, message(config.load_dir)

    return build


def broken_copy(context: Context, name: str, damage: Callable[[bytes], bytes]) -> Path:
    """A checkpoint folder holding the earlier run's step-1 checkpoint, damaged."""
    folder = context.scratch / name / "nerfstudio_models"
    folder.mkdir(parents=True)
    original = context.earlier / "nerfstudio_models" / "step-000000001.ckpt"
    (folder / original.name).write_bytes(damage(original.read_bytes()))
    return folder


def truncated_checkpoint(context: Context) -> Path:
    return broken_copy(context, "truncated", lambda data: data[:5000])


def flipped_bytes_in_a_tensor(context: Context) -> Path:
    """Four bytes flipped inside the checkpoint's largest tensor (the hash grid)."""
    return broken_copy(context, "flipped", flip_tensor_bytes)


def read_only_output_folder(context: Context) -> Tuple[ContinualTrainerConfig, str]:
    folder = context.earlier.parents[2] / "read-only"
    folder.mkdir(mode=0o555)
    config = earlier_run_config()
    config.experiment_name = folder.name
    return config, f"{folder / 'continual-ngp'}: permission denied: the folder is read-only for this user"


def empty_folder(context: Context) -> Path:
    (context.scratch / "empty").mkdir()
    return context.scratch / "empty"


def reuse_earlier_folder(context: Context) -> Tuple[ContinualTrainerConfig, str]:
    config = earlier_run_config()
    config.timestamp = context.earlier.name
    return config, f"{context.earlier} already holds a run; choose another --timestamp"


CORPUS = [
    BadInput("num-tasks-0", option("--pipeline.datamanager.num-tasks must be at least 1, got 0", num_tasks=0)),
    BadInput(
        "num-tasks-too-many",
        option(
            ": 12 frames are too few for --pipeline.datamanager.num-tasks 9: a task needs 2 frames, one to train on "
            "and one to test on; use at most 6 tasks",
            num_tasks=9,
        ),
    ),
    BadInput(
        "budget-0-iterations",
        option("--pipeline.datamanager.iterations-per-task must be at least 1, got 0", iterations_per_task=0),
    ),
    BadInput(
        "budget-negative-seconds",
        option("--pipeline.datamanager.seconds-per-task must be positive, got -1.0", seconds_per_task=-1.0),
    ),
    BadInput("test-interval-1", option("--pipeline.datamanager.test-interval must be at least 2", test_interval=1)),
    BadInput(
        "near-plane-metres-0",
        lambda context: (
            with_model_options(earlier_run_config(), near_plane_metres=0.0),
            "--pipeline.model.near-plane-metres must be positive, got 0.0",
        ),
    ),
    BadInput(
        "finest-cell-metres-0",
        lambda context: (
            with_model_options(earlier_run_config(), finest_cell_metres=0.0),
            "--pipeline.model.finest-cell-metres must be positive or None, got 0.0",
        ),
    ),
    BadInput(
        "distillation-loss-mult-0",
        lambda context: (
            with_model_options(earlier_run_config(), distillation_loss_mult=0.0),
            "--pipeline.model.distillation-loss-mult must be positive (--pipeline.datamanager.replay False turns "
            "replay off), got 0.0",
        ),
    ),
    BadInput(
        "replay-weights-loss-mult-negative",
        lambda context: (
            with_model_options(earlier_run_config(), replay_weights_loss_mult=-0.1),
            "--pipeline.model.replay-weights-loss-mult must not be negative, got -0.1",
        ),
    ),
    BadInput(
        "rays-per-batch-0",
        option("--pipeline.datamanager.train-num-rays-per-batch must be at least 1, got 0", train_num_rays_per_batch=0),
    ),
    *(
        BadInput(
            f"eval-rays-per-chunk-{chunk}-{method.method_name}",
            lambda context, chunk=chunk, method=method: (
                with_model_options(earlier_run_config(method=method), eval_num_rays_per_chunk=chunk),
                f"--pipeline.model.eval-num-rays-per-chunk must be at least 1, got {chunk}",
            ),
        )
        for chunk, method in ((0, CONTINUAL_NGP), (-4096, CONTINUAL_NGP), (0, CONTINUAL_NERF_MEIL))
    ),
    BadInput("demo-no-frames", option("continual-demo --num-frames must be at least 1, got 0", {"num_frames": 0})),
    BadInput("demo-width-0", option("continual-demo --width must be at least 1, got 0", {"width": 0})),
    BadInput("missing-data-folder", missing_capture),
    BadInput("transforms-not-json", nerfstudio_capture(invalid_json)),
    BadInput("pose-with-nan", nerfstudio_capture(nan_pose)),
    BadInput("duplicate-timestamps", nerfstudio_capture(duplicate_timestamps)),
    BadInput("corrupt-image-bytes", nerfstudio_capture(garbage_image), fails_in="train"),
    BadInput("truncated-image-released-mid-run", nerfstudio_capture(truncated_image_of_task_2), fails_in="train"),
    BadInput("16-bit-image", nerfstudio_capture(sixteen_bit_image), fails_in="train"),
    BadInput("image-size-differs-in-one-camera", tum_image_of_another_size, fails_in="train"),
    BadInput("tum-missing-groundtruth", tum_without_groundtruth),
    BadInput("transforms-zero-focal-length", nerfstudio_capture(zero_focal_length)),
    BadInput("tum-resized-to-another-aspect-ratio", tum_resized_to_another_aspect_ratio),
    BadInput("scannet-intrinsics-nan", scannet_intrinsics_nan),
    BadInput("scannet-truncated-sens", truncated_sens),
    BadInput("waymo-corrupt-record", corrupt_tfrecord),
    BadInput("depth-map-of-colour", depth_capture(colour_depth_map), fails_in="train"),
    BadInput("truncated-depth-map-released-mid-run", depth_capture(truncated_depth_map_of_task_2), fails_in="train"),
    BadInput("depth-method-on-a-capture-without-depth", depth_method_without_depth),
    BadInput("depth-method-on-a-stream", depth_method_on_a_stream),
    BadInput("scannet-depth-map-missing", scannet_depth_map_missing),
    BadInput("scannet-sens-occi-depth", sens_occi_depth),
    BadInput(
        "depth-loss-ranking",
        lambda context: (
            with_model_options(
                earlier_run_config(method=CONTINUAL_NGP_DEPTH), depth_loss_type=DepthLossType.SPARSENERF_RANKING
            ),
            "--pipeline.model.depth-loss-type SPARSENERF_RANKING is not supported",
        ),
    ),
    BadInput(
        "resume-missing-folder",
        resume(lambda d: f"--load-dir {d}: no such folder", lambda context: context.scratch / "gone"),
    ),
    BadInput(
        "resume-no-checkpoint", resume(lambda d: f"--load-dir {d}: holds no step-*.ckpt checkpoint", empty_folder)
    ),
    BadInput(
        "resume-absent-step", resume(lambda d: f"--load-step 2: {d} has checkpoints of steps [1, 3]", load_step=2)
    ),
    BadInput(
        "resume-truncated-checkpoint",
        resume(lambda d: f"{d / 'step-000000001.ckpt'}: not a readable checkpoint", truncated_checkpoint),
    ),
    BadInput(
        "resume-other-num-tasks",
        resume(
            lambda d: f"{d / 'step-000000001.ckpt'}: --pipeline.datamanager.num-tasks: the checkpoint was trained with 2, "
            "this run 3",
            load_step=1,
            num_tasks=3,
        ),
    ),
    BadInput(
        "resume-other-model-size",
        resume(
            lambda d: f"{d / 'step-000000001.ckpt'}: does not fit this run (size mismatch for",
            load_step=1,
            log2_hashmap_size=13,
        ),
    ),
    BadInput(
        "resume-finished-run", resume(lambda d: f"{d / 'step-000000003.ckpt'}: its run already trained all 2 tasks")
    ),
    BadInput("run-folder-of-an-earlier-run", reuse_earlier_folder),
    BadInput(
        "disk-full-during-a-checkpoint",
        lambda context: (
            earlier_run_config(),
            "nerfstudio_models/step-000000001.ckpt: cannot be written (no space left on the device)",
        ),
        fails_in="train",
        environment=fill_the_disk_at_checkpoint,
    ),
    BadInput("read-only-output-folder", read_only_output_folder, as_root=False),
    BadInput(
        "resume-flipped-bytes-in-a-tensor",
        resume(lambda d: f"{d / 'step-000000001.ckpt'}: corrupt checkpoint (archive/data/", flipped_bytes_in_a_tensor),
    ),
    *(
        BadInput(
            f"resume-as-{method.method_name}",
            resume(
                lambda d,
                name=method.method_name: f"{d / 'step-000000001.ckpt'}: a checkpoint of continual-ngp, not of "
                f"{name}; resume it with ns-train continual-ngp",
                load_step=1,
                method=method,
            ),
        )
        for method in (CONTINUAL_NGP_INCRE, continual_ngp_ewc.config, continual_ngp_joint.config)
    ),
    BadInput(
        "resume-fewer-iterations-per-task",
        resume(
            lambda d: f"{d / 'step-000000001.ckpt'}: is at step 1, beyond the 2 iterations this run has "
            "(--pipeline.datamanager.iterations-per-task 1 for 2 tasks, or --max-num-iterations)",
            load_step=1,
            datamanager_options={"iterations_per_task": 1},
        ),
    ),
]


# ---- running them ----


@contextlib.contextmanager
def own_event_writers() -> Iterator[None]:
    """nerfstudio keeps tensorboard writers in a module list that only grows: give each in-process run its own, as
    each ns-train process has, so no run writes events into another run's folder."""
    earlier = list(writer.EVENT_WRITERS)
    writer.EVENT_WRITERS.clear()
    try:
        yield
    finally:
        for event_writer in writer.EVENT_WRITERS:
            event_writer.tb_writer.close()
        writer.EVENT_WRITERS[:] = earlier


def digest(folder: Path) -> Dict[str, str]:
    return {
        str(path.relative_to(folder)): hashlib.sha256(path.read_bytes()).hexdigest()
        for path in sorted(folder.rglob("*"))
        if path.is_file()
    }


@pytest.fixture(scope="module")
def earlier(tmp_path_factory) -> Path:
    config = earlier_run_config()
    config.output_dir, config.timestamp = tmp_path_factory.mktemp("corpus") / "outputs", "earlier"
    with own_event_writers():
        train(config)
    return config.get_base_dir()


def exit_line(config: ContinualTrainerConfig) -> object:
    """The SystemExit code of the run, set up and trained as ns-train does."""
    with pytest.raises(SystemExit) as exit_info, own_event_writers():
        config.save_config()
        trainer = config.setup(local_rank=0, world_size=1)
        trainer.setup()
        trainer.train()
    return exit_info.value.code


ROOT = pytest.mark.skipif(os.geteuid() == 0, reason="root writes into read-only folders (run as another user)")


@pytest.mark.parametrize(
    "case", [pytest.param(case, id=case.name, marks=[] if case.as_root else [ROOT]) for case in CORPUS]
)
def test_bad_input_ends_with_one_line_and_leaves_earlier_runs_alone(
    case: BadInput, earlier: Path, tmp_path, monkeypatch
):
    before = digest(earlier)
    config, message = case.build(Context(scratch=tmp_path, earlier=earlier))
    if case.environment is not None:
        case.environment(monkeypatch)
    config.output_dir = earlier.parents[2]
    if config.timestamp != earlier.name:
        config.timestamp = case.name
    line = exit_line(config)
    assert isinstance(line, str), "a SystemExit with a message exits with status 1"
    assert line.startswith(f"{config.method_name}: error: ") and "\n" not in line
    assert message in line
    assert digest(earlier) == before
    results = config.get_base_dir() / ACCURACY_MATRIX_FILENAME
    if case.fails_in == "train":
        assert AccuracyMatrix.read(results).status == "failed", "the folder says the run did not finish"
    elif config.get_base_dir() != earlier:
        assert not results.exists() and not list(config.get_base_dir().rglob("*.ckpt")), "nothing trained"


# ---- dataparser options, checked when the parser is set up ----

PARSER_OPTIONS = [
    (ContinualDemoDataParserConfig(num_frames=0), "continual-demo --num-frames must be at least 1, got 0"),
    (ContinualDemoDataParserConfig(fov_degrees=180.0), "continual-demo --fov-degrees must be in (0, 180), got 180.0"),
    (
        ContinualDemoDataParserConfig(exposure_strength=1.0),
        "continual-demo --exposure-strength must be in [0, 1), got 1.0",
    ),
    (
        ContinualDemoDataParserConfig(pose_noise_degrees=-1.0),
        "continual-demo --pose-noise-degrees must not be negative, got -1.0",
    ),
    (
        OrderedCaptureDataParserConfig(order="random"),
        "--order must be one of auto, timestamp, filename, file, got random",
    ),
    (ContinualScanNetDataParserConfig(downscale_factor=0), "--downscale-factor must be at least 1, got 0"),
    (ContinualTumDataParserConfig(max_frames=0), "--max-frames must be at least 1, got 0"),
    (ContinualTumDataParserConfig(cx=-1.0), "continual-tum --cx must be positive, got -1.0"),
    (WaymoDataParserConfig(cameras=("FRONT", "FRONT")), "--cameras names a camera twice: FRONT FRONT"),
    (StreamDataParserConfig(poll_seconds=0.0), "--poll-seconds must be positive, got 0.0"),
    (
        StreamDataParserConfig(normalization="file"),
        "--normalization file needs --transform-file (a dataparser_transforms.json)",
    ),
]


@pytest.mark.parametrize("parser, message", PARSER_OPTIONS, ids=[type(p).__name__ for p, _ in PARSER_OPTIONS])
def test_dataparser_options_fail_at_setup_before_any_data_is_read(parser: DataParserConfig, message: str):
    with pytest.raises(ContinualConfigError) as raised:
        parser.setup()  # the default data paths do not exist: reading them would fail differently
    assert str(raised.value) == message


# ---- through the real ns-train ----


def cli_cases(context: Context) -> List[Tuple[str, List[str], str]]:
    """(name, ns-train options then the dataparser and its options, what the last line it prints must start with)."""
    demo = ["continual-demo", "--data", str(DEMO_CACHE), "--num-frames", "12", "--width", "16", "--height", "12"]
    capture = write_transforms(context.scratch / "capture", numbered_frames(arc_poses()))
    image_line = truncated_image_of_task_2(capture)
    truncated, flipped = truncated_checkpoint(context), flipped_bytes_in_a_tensor(context)
    tasks = ["--pipeline.datamanager.num-tasks", "2", "--pipeline.datamanager.iterations-per-task", "2"]
    earlier_demo = [
        "continual-demo",
        "--data",
        str(DEMO_CACHE),
        "--num-frames",
        "16",
        "--width",
        "24",
        "--height",
        "18",
    ]
    return [
        (
            "num-tasks-0",
            ["--pipeline.datamanager.num-tasks", "0", *demo],
            "--pipeline.datamanager.num-tasks must be at least 1, got 0",
        ),
        ("truncated-image-released-mid-run", [*tasks, "continual-nerfstudio", "--data", str(capture)], image_line),
        (
            "resume-truncated-checkpoint",
            [*tasks, "--load-dir", str(truncated), *earlier_demo],
            f"{truncated / 'step-000000001.ckpt'}: not a readable checkpoint (",
        ),
        (
            "resume-flipped-bytes-in-a-tensor",
            [*tasks, "--load-dir", str(flipped), *earlier_demo],
            f"{flipped / 'step-000000001.ckpt'}: corrupt checkpoint (",
        ),
    ]


@pytest.mark.slow
def test_ns_train_prints_one_line_no_traceback_and_exits_non_zero(earlier: Path, tmp_path):
    before = digest(earlier)
    cases = cli_cases(Context(scratch=tmp_path, earlier=earlier))
    # started together: each one spends most of its time importing nerfstudio
    logs = {name: (tmp_path / f"{name}.log").open("w+") for name, _, _ in cases}
    processes = {
        name: subprocess.Popen(
            ns_train_command(earlier.parents[2], f"cli-{name}", options, []),
            stdout=subprocess.DEVNULL,
            stderr=logs[name],
            env=SUBPROCESS_ENV,
        )
        for name, options, _ in cases
    }
    for name, _, expected in cases:
        assert processes[name].wait(timeout=600) != 0, name
        logs[name].seek(0)
        stderr = logs[name].read()
        assert "Traceback" not in stderr, stderr[-3000:]
        assert stderr.strip().splitlines()[-1].startswith(f"continual-ngp: error: {expected}"), stderr[-3000:]
    assert digest(earlier) == before


# ---- streamed frames: the capture folder is another process's output, so a frame that can never be used is skipped
# with one warning line naming it, at start-up and mid-run, and training goes on ----

SOURCE_FRAMES = 12
"""The demo room's frames the capture folders below are written from (frame n shows source frame n mod 12)."""


@functools.lru_cache(maxsize=1)
def source_frames() -> DataparserOutputs:
    return demo_parser(num_frames=SOURCE_FRAMES).setup().get_dataparser_outputs(split="train")


def write_good_frame(capture: Path, number: int) -> None:
    source = source_frames()
    write_frame(capture, number, Path(source.image_filenames[number % SOURCE_FRAMES]), frame_json(source.cameras, 0))


def write_frame_json(capture: Path, number: int, **changes: Any) -> Path:
    """Frame `number`'s image as the protocol writes it, and its JSON with `changes`."""
    write_good_frame(capture, number)
    path = capture / f"{number:06d}.json"
    path.write_text(json.dumps({**json.loads(path.read_text()), **changes}))
    return path


def outside_folder(capture: Path) -> Path:
    """A folder beside the capture holding what a hostile frame points at: an image and a valid frame JSON."""
    folder = capture.parent / "outside"
    if not folder.is_dir():
        folder.mkdir()
        shutil.copyfile(source_frames().image_filenames[0], folder / "secret.png")
        (folder / "frame.json").write_text(
            json.dumps({"file_path": "images/000000.png", **frame_json(source_frames().cameras, 0)})
        )
    return folder


def png_header(width: int, height: int) -> bytes:
    """A PNG that announces `width` x `height` pixels in its header."""

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    header = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header) + chunk(b"IDAT", zlib.compress(b"\0")) + chunk(b"IEND", b"")


def absolute_image_path(capture: Path, number: int) -> str:
    write_frame_json(capture, number, file_path=str(outside_folder(capture) / "secret.png"))
    return "lies outside the capture folder"


def image_path_climbing_out(capture: Path, number: int) -> str:
    outside_folder(capture)
    write_frame_json(capture, number, file_path="images/../../outside/secret.png")
    return "lies outside the capture folder"


def image_symlink_out(capture: Path, number: int) -> str:
    write_good_frame(capture, number)
    image = capture / "images" / f"{number:06d}.png"
    image.unlink()
    image.symlink_to(outside_folder(capture) / "secret.png")
    return "lies outside the capture folder"


def folder_symlink_out(capture: Path, number: int) -> str:
    link = capture / "linked"
    if not link.is_symlink():
        link.symlink_to(outside_folder(capture), target_is_directory=True)
    write_frame_json(capture, number, file_path="linked/secret.png")
    return "lies outside the capture folder"


def json_symlink_out(capture: Path, number: int) -> str:
    (capture / f"{number:06d}.json").symlink_to(outside_folder(capture) / "frame.json")
    return "lies outside the capture folder"


def image_fifo(capture: Path, number: int) -> str:
    write_good_frame(capture, number)
    image = capture / "images" / f"{number:06d}.png"
    image.unlink()
    os.mkfifo(image)
    return "not a regular file (a FIFO); not read"


def image_folder(capture: Path, number: int) -> str:
    write_frame_json(capture, number, file_path="images")
    return "not a regular file (a folder); not read"


def json_fifo(capture: Path, number: int) -> str:
    os.mkfifo(capture / f"{number:06d}.json")
    return "not a regular file (a FIFO); not read"


def decompression_bomb(capture: Path, number: int) -> str:
    (capture / "images" / "bomb.png").write_bytes(png_header(100000, 100000))
    write_frame_json(capture, number, file_path="images/bomb.png", w=100000, h=100000)
    return "is too large to decode (Image size (10000000000 pixels) exceeds limit"


def deeply_nested_json(capture: Path, number: int) -> str:
    (capture / f"{number:06d}.json").write_text("[" * 100000 + "]" * 100000)
    return "not a usable frame JSON (maximum recursion depth exceeded"


def oversized_json(capture: Path, number: int) -> str:
    (capture / f"{number:06d}.json").write_text(" " * (2 << 20) + "{}")
    return "larger than 1 MiB, not a frame JSON; not read"


def intrinsics(message: str, **changes: Any) -> Callable[[Path, int], str]:
    """A frame whose intrinsics are changed by `changes`; its warning line holds `message`."""

    def write(capture: Path, number: int) -> str:
        write_frame_json(capture, number, **changes)
        return message

    return write


def file_path_not_a_string(capture: Path, number: int) -> str:
    write_frame_json(capture, number, file_path=["images", "000000.png"])
    return "a frame needs a `file_path` string"


def file_path_with_nul(capture: Path, number: int) -> str:
    write_frame_json(capture, number, file_path="images/\u0000.png")
    return "not a usable path (embedded null byte)"


HOSTILE_FRAMES: Dict[str, Callable[[Path, int], str]] = {
    "absolute-image-path": absolute_image_path,
    "image-path-climbing-out": image_path_climbing_out,
    "image-symlink-out": image_symlink_out,
    "folder-symlink-out": folder_symlink_out,
    "json-symlink-out": json_symlink_out,
    "image-fifo": image_fifo,
    "image-is-a-folder": image_folder,
    "json-fifo": json_fifo,
    "decompression-bomb": decompression_bomb,
    "deeply-nested-json": deeply_nested_json,
    "oversized-json": oversized_json,
    "width-nan": intrinsics("image size w=nan h=18 must be whole numbers of at least 1", w=float("nan")),
    "focal-nan": intrinsics("focal lengths must be finite and positive, got fx=nan", fl_x=float("nan")),
    "focal-zero": intrinsics("focal lengths must be finite and positive, got fx=0", fl_x=0),
    "focal-negative": intrinsics("focal lengths must be finite and positive, got fx=17.1378 fy=-20", fl_y=-20.0),
    "principal-point-infinite": intrinsics("principal point cx=inf cy=9 lies outside the 24x18 image", cx=float("inf")),
    "file-path-not-a-string": file_path_not_a_string,
    "file-path-with-nul": file_path_with_nul,
}
"""Writers of a frame that can never be used; each returns the text its warning line holds."""


def finishes(function: Callable[[], Any], seconds: float = 300.0) -> Any:
    """`function()`, run in a thread so a reader blocked on a FIFO fails the test instead of hanging the suite."""
    outcome: Dict[str, Any] = {}

    def run() -> None:
        try:
            outcome["value"] = function()
        except BaseException as error:
            outcome["error"] = error

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    thread.join(seconds)
    assert not thread.is_alive(), f"still blocked after {seconds:g} s"
    if "error" in outcome:
        raise outcome["error"]
    return outcome.get("value")


def skipped_lines(output: str, capture: Path, numbers: List[int]) -> Dict[int, List[str]]:
    """The warning lines naming each of the frames `numbers`."""
    lines = [line for line in output.splitlines() if line.endswith("; frame skipped")]
    return {
        number: [line for line in lines if line.startswith(f"{capture / f'{number:06d}.json'}: ")] for number in numbers
    }


@pytest.mark.parametrize("write", HOSTILE_FRAMES.values(), ids=HOSTILE_FRAMES.keys())
def test_a_hostile_frame_at_start_up_is_skipped_with_one_warning_line(write, tmp_path, capsys):
    capture = tmp_path / "capture"
    for number in range(5):
        if number == 2:
            expected = write(capture, number)
        else:
            write_good_frame(capture, number)
    write_marker(capture, 4, "end")
    capsys.readouterr()
    parser = StreamDataParserConfig(data=capture, frames_per_task=0, normalization="none").setup()
    outputs = finishes(lambda: parser.get_dataparser_outputs(split="train"))
    assert [[frame.name for frame in task] for task in parser.capture.tasks] == [
        [f"{number:06d}.json" for number in (0, 1, 3, 4)]
    ]
    (line,) = skipped_lines(capsys.readouterr().out, capture, [2])[2]
    assert expected in line
    real_capture = capture.resolve()
    assert all(Path(path).is_relative_to(real_capture) for path in outputs.image_filenames)


@pytest.mark.slow
def test_hostile_frames_arriving_mid_run_are_skipped_and_training_goes_on(tmp_path, capsys):
    """Task 1's frames are there at start; the rest, every hostile frame among them, arrive after the first step."""
    capture = tmp_path / "capture"
    for number in range(4):
        write_good_frame(capture, number)
    hostile = {4 + offset: write for offset, write in enumerate(HOSTILE_FRAMES.values())}
    good = [4 + len(hostile) + offset for offset in range(4)]
    expected: Dict[int, str] = {}

    def rest_of_the_capture(step: int) -> None:
        if step == 0:
            expected.update({number: write(capture, number) for number, write in hostile.items()})
            for number in good:
                write_good_frame(capture, number)
            write_marker(capture, good[-1], "end")

    config = stream_config(tmp_path / "outputs", capture, "wait", frames_per_task=4, iterations_per_task=2)
    config.save_config()
    with own_event_writers():
        trainer = config.setup(local_rank=0, world_size=1)
        trainer.setup()
        trainer.callbacks.append(
            TrainingCallback([TrainingCallbackLocation.AFTER_TRAIN_ITERATION], rest_of_the_capture)
        )
        finishes(trainer.train)
    matrix = AccuracyMatrix.read(config.get_base_dir() / ACCURACY_MATRIX_FILENAME)
    assert (matrix.status, len(matrix.psnr)) == ("finished", 2)
    used = [frame.name for frame in trainer.pipeline.datamanager.frames]
    assert used == [f"{number:06d}.json" for number in [0, 1, 2, 3, *good]]
    warnings = skipped_lines(capsys.readouterr().out, capture, list(hostile))
    for number, text in expected.items():
        assert len(warnings[number]) == 1 and text in warnings[number][0], (number, warnings[number])
