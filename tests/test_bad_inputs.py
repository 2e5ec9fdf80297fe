"""A corpus of broken inputs: options, dataparsers' files, checkpoints to resume from, an occupied run folder.

Each one ends the run with a single line naming the option or file at fault and a non-zero exit, and leaves
every file of an earlier run as it was. Most run in-process through ContinualTrainer as `ns-train` drives it;
a few run through the real `ns-train`, which must print no traceback.
"""

from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import subprocess
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Dict, Iterator, List, Literal, Optional, Tuple

import numpy as np
import pytest
from helpers import (
    CAMERAS,
    DEMO_CACHE,
    IMAGE_TIMES,
    SUBPROCESS_ENV,
    arc_poses,
    corrupt,
    demo_parser,
    edit_transforms,
    ns_train_command,
    numbered_frames,
    scannet_poses,
    tiny_config,
    train,
    v1_frame,
    write_sens,
    write_sequence,
    write_transforms,
    write_v1,
)
from nerfstudio.data.dataparsers.base_dataparser import DataParserConfig
from nerfstudio.utils import writer
from PIL import Image

from continual_nerf.core.accuracy_matrix import ACCURACY_MATRIX_FILENAME, AccuracyMatrix
from continual_nerf.core.continual_trainer import ContinualTrainerConfig
from continual_nerf.dataparsers.continual_demo_dataparser import ContinualDemoDataParserConfig
from continual_nerf.dataparsers.ordered_capture_dataparser import OrderedCaptureDataParserConfig
from continual_nerf.dataparsers.scannet_dataparser import ContinualScanNetDataParserConfig
from continual_nerf.dataparsers.stream_dataparser import StreamDataParserConfig
from continual_nerf.dataparsers.tum_dataparser import ContinualTumDataParserConfig
from continual_nerf.dataparsers.waymo_dataparser import WaymoDataParserConfig
from continual_nerf.errors import ContinualConfigError


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


# ---- builders ----


def corpus_run(parser: DataParserConfig, num_tasks: int = 2, **datamanager_options) -> ContinualTrainerConfig:
    config = tiny_config(Path("outputs"), parser, num_tasks=num_tasks, iterations_per_task=2)
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


def earlier_run_config(num_tasks: int = 2) -> ContinualTrainerConfig:
    return corpus_run(demo_parser(num_frames=16), num_tasks=num_tasks)


def earlier_checkpoints(context: Context) -> Path:
    return context.earlier / "nerfstudio_models"


def resume(
    message: Callable[[Path], str],
    load_dir: Callable[[Context], Path] = earlier_checkpoints,
    load_step: Optional[int] = None,
    num_tasks: int = 2,
    **model_options,
) -> Build:
    """The earlier run's config (with `num_tasks` and `model_options` changed) resuming from `load_dir`."""

    def build(context: Context) -> Tuple[ContinualTrainerConfig, str]:
        config = earlier_run_config(num_tasks)
        config.pipeline.model = dataclasses.replace(config.pipeline.model, **model_options)
        config.load_dir, config.load_step = load_dir(context), load_step
        return config, message(config.load_dir)

    return build


def truncated_checkpoint(context: Context) -> Path:
    folder = context.scratch / "nerfstudio_models"
    folder.mkdir()
    original = context.earlier / "nerfstudio_models" / "step-000000001.ckpt"
    (folder / original.name).write_bytes(original.read_bytes()[:5000])
    return folder


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
        "num-tasks-too-many", option("--pipeline.datamanager.num-tasks 9 is too large for 12 frames", num_tasks=9)
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
        "rays-per-batch-0",
        option("--pipeline.datamanager.train-num-rays-per-batch must be at least 1, got 0", train_num_rays_per_batch=0),
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
    BadInput("scannet-truncated-sens", truncated_sens),
    BadInput("waymo-corrupt-record", corrupt_tfrecord),
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


@pytest.mark.parametrize("case", CORPUS, ids=[case.name for case in CORPUS])
def test_bad_input_ends_with_one_line_and_leaves_earlier_runs_alone(case: BadInput, earlier: Path, tmp_path):
    before = digest(earlier)
    config, message = case.build(Context(scratch=tmp_path, earlier=earlier))
    config.output_dir = earlier.parents[2]
    if config.timestamp != earlier.name:
        config.timestamp = case.name
    line = exit_line(config)
    assert isinstance(line, str), "a SystemExit with a message exits with status 1"
    assert line.startswith("continual-ngp: error: ") and "\n" not in line
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
    checkpoints = truncated_checkpoint(context)
    tasks = ["--pipeline.datamanager.num-tasks", "2", "--pipeline.datamanager.iterations-per-task", "2"]
    return [
        (
            "num-tasks-0",
            ["--pipeline.datamanager.num-tasks", "0", *demo],
            "--pipeline.datamanager.num-tasks must be at least 1, got 0",
        ),
        ("truncated-image-released-mid-run", [*tasks, "continual-nerfstudio", "--data", str(capture)], image_line),
        (
            "resume-truncated-checkpoint",
            [
                *tasks,
                "--load-dir",
                str(checkpoints),
                "continual-demo",
                "--data",
                str(DEMO_CACHE),
                "--num-frames",
                "16",
                "--width",
                "24",
                "--height",
                "18",
            ],
            f"{checkpoints / 'step-000000001.ckpt'}: not a readable checkpoint (",
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
