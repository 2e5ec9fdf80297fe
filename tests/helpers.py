"""Shared test helpers: tiny continual-ngp configurations that train in seconds on a CPU and how to run them, and
the captures the tests write, each in its dataset's own layout with known poses (transforms.json and COLMAP models,
ScanNet exported folder and .sens, TUM RGB-D, Waymo v1 TFRecord and v2 Parquet), and their poses read back.
"""

from __future__ import annotations

import contextlib
import dataclasses
import errno
import functools
import io
import json
import os
import signal
import struct
import subprocess
import sys
import threading
import time
import zipfile
import zlib
from datetime import timedelta
from pathlib import Path
from typing import Any, BinaryIO, Callable, Dict, List, Optional, Sequence, Tuple

import numpy as np
import psutil
import pyarrow as pa
import pyarrow.parquet as pq
import torch
from nerfstudio.data.dataparsers.base_dataparser import (
    DataParserConfig,
    DataparserOutputs,
    transform_poses_to_original_space,
)
from nerfstudio.data.utils import colmap_parsing_utils as colmap
from nerfstudio.engine.callbacks import TrainingCallback, TrainingCallbackLocation
from PIL import Image

from continual_nerf.core.continual_trainer import ContinualTrainer, ContinualTrainerConfig
from continual_nerf.core.ngp_model import ContinualNGPModelConfig
from continual_nerf.dataparsers import waymo_v2
from continual_nerf.dataparsers.capture import OPENCV_TO_OPENGL
from continual_nerf.dataparsers.continual_demo_dataparser import ContinualDemoDataParserConfig
from continual_nerf.dataparsers.stream_dataparser import StreamDataParserConfig
from continual_nerf.dataparsers.waymo_index import CAMERA_IDS
from continual_nerf.method_configs import CONTINUAL_NGP
from continual_nerf.nerfstudio_compat import seed_like_ns_train
from continual_nerf.recipes import quiet_config, train_like_ns_train
from continual_nerf.streaming.replay_capture import ReplayCaptureConfig, replay
from continual_nerf.streaming.streaming_datamanager import StreamingDataManagerConfig

DEMO_CACHE = Path(__file__).parent / ".cache" / "continual-demo"
"""The demo scenes the tests render, kept between test runs (rendering is the slow part of a tiny run)."""

SUBPROCESS_ENV = {**os.environ, "OMP_NUM_THREADS": "1"}
"""One thread per training subprocess: two processes with two threads each on two busy cores run ten times slower."""

RUN_TIMEOUT = 600.0
"""Seconds a test's subprocess may take before it counts as hung: generous, as two busy cores make runs slow."""


def tiny_config(
    output_dir: Path,
    dataparser: DataParserConfig,
    num_tasks: int = 2,
    iterations_per_task: int = 3,
    rays_per_batch: int = 256,
    replay: Optional[bool] = None,
    small_model: bool = True,
    compile: bool = False,
    method: ContinualTrainerConfig = CONTINUAL_NGP,
) -> ContinualTrainerConfig:
    """`method` (continual-ngp by default) on CPU with tensorboard only (no viewer) and, by default, a small model,
    eager (compiling costs more than the few steps of a test save; tests/test_performance.py checks compiled = eager);
    `replay` None keeps the method's own."""
    config = quiet_config(
        method,
        output_dir,
        small=small_model,
        dataparser=dataparser,
        num_tasks=num_tasks,
        iterations_per_task=iterations_per_task,
        train_num_rays_per_batch=rays_per_batch,
        replay=method.pipeline.datamanager.replay if replay is None else replay,
    )
    if isinstance(config.pipeline.model, ContinualNGPModelConfig):  # the NeRF baselines do not compile
        config.pipeline.model = dataclasses.replace(config.pipeline.model, compile=compile)
    return config


def demo_parser(
    num_frames: int = 16, width: int = 24, height: int = 18, seed: int = 0
) -> ContinualDemoDataParserConfig:
    return ContinualDemoDataParserConfig(data=DEMO_CACHE, num_frames=num_frames, width=width, height=height, seed=seed)


def stream_config(
    run_dir: Path, capture: Path, idle: str, frames_per_task: int, iterations_per_task: int
) -> ContinualTrainerConfig:
    """continual-ngp-stream reading `capture` (polled every 0.05 s, poses as written), with tiny_config's settings and
    an even smaller model."""
    parser = StreamDataParserConfig(
        data=capture, frames_per_task=frames_per_task, poll_seconds=0.05, normalization="none", unreadable_timeout=0
    )
    config = tiny_config(run_dir, parser, iterations_per_task=iterations_per_task, rays_per_batch=64)
    config.pipeline.datamanager = StreamingDataManagerConfig(
        dataparser=parser,
        iterations_per_task=iterations_per_task,
        train_num_rays_per_batch=64,
        test_interval=4,
        idle=idle,  # type: ignore[arg-type]
    )
    config.pipeline.model = dataclasses.replace(
        config.pipeline.model,
        num_levels=4,
        log2_hashmap_size=10,
        max_res=32,
        num_nerf_samples_per_ray=8,
        num_proposal_samples_per_ray=(16,),
    )
    config.method_name = "continual-ngp-stream"
    return config


def replayed(tmp_path: Path, num_frames: int = 6, end_marker: bool = False) -> Path:
    """A capture folder holding the demo room's first `num_frames` frames, as continual-nerf-replay-capture writes."""
    capture = tmp_path / "capture"
    replay(
        ReplayCaptureConfig(output=capture, fps=0, end_marker=end_marker, dataparser=demo_parser(num_frames=num_frames))
    )
    return capture


def ns_train_command(output_dir: Path, timestamp: str, options: Sequence[str], dataparser: Sequence[str]) -> List[str]:
    """`ns-train continual-ngp` with tiny_config's settings (CPU, tensorboard, small hash grid, 256 rays), then
    `options`, then the dataparser subcommand and its options."""
    tiny = {
        "machine.device-type": "cpu",
        "vis": "tensorboard",
        "output-dir": output_dir,
        "timestamp": timestamp,
        "steps-per-eval-batch": 10**9,
        "steps-per-eval-image": 10**9,
        "logging.local-writer.enable": False,
        "pipeline.model.num-levels": 8,
        "pipeline.model.log2-hashmap-size": 15,
        "pipeline.model.max-res": 128,
        "pipeline.model.num-nerf-samples-per-ray": 16,
        "pipeline.model.num-proposal-samples-per-ray": 32,
        "pipeline.model.eval-num-rays-per-chunk": 4096,
        "pipeline.datamanager.train-num-rays-per-batch": 256,
        "pipeline.model.compile": False,
    }
    flags = [item for name, value in tiny.items() for item in (f"--{name}", str(value))]
    return [str(Path(sys.executable).with_name("ns-train")), "continual-ngp", *flags, *options, *dataparser]


def run_ns_train(command: Sequence[str]) -> subprocess.CompletedProcess:
    """Run an ns-train command line to its end (one thread), capturing its output as text."""
    run = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=SUBPROCESS_ENV)
    stdout, stderr = finish(run, "ns-train")
    return subprocess.CompletedProcess(command, run.returncode, stdout, stderr)


def signal_when_saved(process: subprocess.Popen, checkpoint: Path, number: int) -> None:
    """Send signal `number` to `process` as soon as `checkpoint` appears (complete: checkpoints are renamed into
    place)."""
    wait_while_running(process, checkpoint.exists, f"{checkpoint.name} is saved")
    os.kill(process.pid, number)


def ctrl_c_when_saved(command: List[str], checkpoint: Path, log_path: Path) -> str:
    """Run `command` (an ns-train run), press Ctrl-C as soon as `checkpoint` is saved; checks it ends with 130 and
    returns its stderr (also kept at `log_path`)."""
    with log_path.open("w+") as log:
        process = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=log, env=SUBPROCESS_ENV)
        signal_when_saved(process, checkpoint, signal.SIGINT)
        assert process.wait(timeout=RUN_TIMEOUT) == 130
        log.seek(0)
        return log.read()


def wait_while_running(process: subprocess.Popen, done: Callable[[], bool], what: str) -> None:
    """Wait until `done()`; the test fails if `process` ends first, or is still running without it after RUN_TIMEOUT
    seconds (a hang)."""
    deadline = time.monotonic() + RUN_TIMEOUT
    while not done():
        assert process.poll() is None, f"the run ended (exit {process.returncode}) before {what}"
        assert time.monotonic() < deadline, f"still running after {RUN_TIMEOUT:g} s, a hang, and not yet {what}"
        time.sleep(0.01)


def train(config: ContinualTrainerConfig) -> ContinualTrainer:
    """Train `config` in this process as `ns-train` does (seeded with --machine.seed); returns the trainer."""
    return train_like_ns_train(config)


def stopped_run(config: ContinualTrainerConfig, last_step: int) -> Path:
    """Train `config` as a run stopped after `last_step` (as Ctrl-C or a lost machine leaves one); returns its latest
    checkpoint, the one to resume (a closed task's earlier checkpoints keep the model's weights only)."""
    config.max_num_iterations = last_step + 1
    train(config)
    return config.get_checkpoint_dir() / f"step-{last_step:09d}.ckpt"


WIDTH, HEIGHT = 32, 24
"""Image size of the transforms.json, COLMAP, ScanNet and TUM captures (each Waymo camera has its own, SIZES)."""


def original_poses(outputs: DataparserOutputs) -> np.ndarray:
    """Undo the dataparser's orientation, centring and scale: metric OpenGL camera-to-world (N, 3, 4)."""
    poses = transform_poses_to_original_space(
        outputs.cameras.camera_to_worlds.double(),
        outputs.dataparser_transform.double(),
        outputs.dataparser_scale,
        "opengl",
    )
    return poses.numpy()


def rotation(axis: np.ndarray, angle: float) -> np.ndarray:
    """Rodrigues' formula."""
    axis = axis / np.linalg.norm(axis)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * k @ k


# ---- transforms.json and COLMAP (continual-nerfstudio) ----

NUMBERS = [2 * (i + 1) for i in range(10)]
"""File-name numbers 2..20 in capture order: a string sort would put frame_10 before frame_2."""
SHUFFLE = [7, 2, 9, 0, 5, 3, 8, 1, 6, 4]
"""Order in which the generated files list the frames (indices into the capture order)."""


def arc_poses(count: int = len(NUMBERS)) -> np.ndarray:
    """OpenGL camera-to-world matrices on a rising arc, each looking at the origin."""
    poses = []
    for i in range(count):
        angle = 0.4 * i
        position = np.array([3 * np.cos(angle), 3 * np.sin(angle), 0.5 + 0.1 * i])
        back = position / np.linalg.norm(position)
        right = np.cross([0.0, 0.0, 1.0], back)
        right /= np.linalg.norm(right)
        pose = np.eye(4)
        pose[:3, :3] = np.stack([right, np.cross(back, right), back], axis=1)
        pose[:3, 3] = position
        poses.append(pose)
    return np.stack(poses)


def write_images(folder: Path, names: List[str]) -> None:
    rng = np.random.default_rng(0)
    for name in names:
        (folder / name).parent.mkdir(parents=True, exist_ok=True)
        Image.fromarray(rng.integers(0, 255, (HEIGHT, WIDTH, 3), dtype=np.uint8)).save(folder / name)


def write_transforms(folder: Path, frames: List[Dict], **shared) -> Path:
    """transforms.json listing `frames` in the SHUFFLE order, with their images."""
    folder.mkdir(parents=True, exist_ok=True)
    write_images(folder, [frame["file_path"] for frame in frames])
    listed = [frames[i] for i in SHUFFLE]
    defaults = {"fl_x": 30.0, "fl_y": 31.0, "cx": 16.0, "cy": 12.0, "w": WIDTH, "h": HEIGHT}
    (folder / "transforms.json").write_text(json.dumps({**defaults, **shared, "frames": listed}))
    return folder


def numbered_frames(poses: np.ndarray) -> List[Dict]:
    return [
        {"file_path": f"images/frame_{number}.png", "transform_matrix": pose.tolist()}
        for number, pose in zip(NUMBERS, poses)
    ]


def edit_transforms(folder: Path, **frame_changes: Dict) -> Dict:
    """Update frames of the folder's transforms.json by image number (frame_<number>.png); returns the file's dict."""
    path = folder / "transforms.json"
    meta = json.loads(path.read_text())
    for frame in meta["frames"]:
        frame.update(frame_changes.get(Path(frame["file_path"]).stem, {}))
    path.write_text(json.dumps(meta))
    return meta


def depth_millimetres(index: int, width: int = WIDTH, height: int = HEIGHT) -> np.ndarray:
    """(height, width) uint16 depth map of frame `index`, in millimetres: 1 m + 100 mm per frame + 1 mm per pixel in
    flat order, so that every value tells its frame and pixel."""
    return (1000 + 100 * index + np.arange(width * height)).reshape(height, width).astype(np.uint16)


def with_depth_maps(folder: Path, width: int = WIDTH, height: int = HEIGHT) -> Path:
    """A transforms.json capture (write_transforms) given a 16-bit millimetre depth map per frame, depth/frame_<n>.png
    (depth_file_path, as ns-process-data record3d writes it), of `width` x `height`."""
    (folder / "depth").mkdir(exist_ok=True)
    changes = {}
    for index, number in enumerate(NUMBERS):
        Image.fromarray(depth_millimetres(index, width, height)).save(folder / "depth" / f"frame_{number}.png")
        changes[f"frame_{number}"] = {"depth_file_path": f"depth/frame_{number}.png"}
    edit_transforms(folder, **changes)
    return folder


ALL_MASKED = 6
"""frame_6 (a training frame of task 1 when the capture is cut into 2 tasks) is masked out everywhere."""


def mask_of(number: int) -> np.ndarray:
    """frame_<number>'s mask, 32x24: 255 where its pixels train; a band on the left and a block differ per frame."""
    mask = np.full((HEIGHT, WIDTH), 255, dtype=np.uint8)
    mask[:, : 4 + number % 7] = 0
    mask[number % 5 : number % 5 + 6, 20:28] = 0
    if number == ALL_MASKED:
        mask[:] = 0
    return mask


def shrink(mask: np.ndarray, factor: int) -> np.ndarray:
    """The mask as nerfstudio's mask reader downscales it (nearest)."""
    size = (mask.shape[1] // factor, mask.shape[0] // factor)
    return np.array(Image.fromarray(mask).resize(size, resample=Image.Resampling.NEAREST))


def masked_capture(folder: Path, factor: int = 1, **shared) -> Path:
    """write_transforms' 10-frame capture (`shared`: file-wide keys) with a mask per frame under masks/ (mask_of), each
    `factor` times smaller than its image."""
    frames = numbered_frames(arc_poses())
    for frame in frames:
        frame["mask_path"] = frame["file_path"].replace("images/", "masks/")
    capture = write_transforms(folder, frames, **shared)
    (capture / "masks").mkdir()
    for number in NUMBERS:
        Image.fromarray(shrink(mask_of(number), factor)).save(capture / "masks" / f"frame_{number}.png")
    return capture


def colmap_line(image_id: int, camera_to_world: np.ndarray, camera_id: int, name: str) -> str:
    """An images.txt pose line: OpenCV world-to-camera as COLMAP's scalar-first quaternion and translation."""
    world_to_camera = np.linalg.inv(camera_to_world @ OPENCV_TO_OPENGL)
    qvec, tvec = colmap.rotmat2qvec(world_to_camera[:3, :3]), world_to_camera[:3, 3]
    return " ".join(str(v) for v in [image_id, *qvec, *tvec, camera_id, name])


def write_colmap_text(scene: Path, image_lines: Optional[List[str]] = None) -> Path:
    """<scene>/sparse/0 with a PINHOLE camera (even frames) and an OPENCV camera (odd frames), images shuffled."""
    model = scene / "sparse" / "0"
    model.mkdir(parents=True)
    image_names = [f"{number:06d}.png" for number in NUMBERS]
    write_images(scene / "images", image_names)
    poses = arc_poses()
    (model / "cameras.txt").write_text(
        "# Camera list with one line of data per camera:\n"
        f"1 PINHOLE {WIDTH} {HEIGHT} 30 31 16 12\n"
        f"2 OPENCV {WIDTH} {HEIGHT} 28 29 15.5 11.5 0.1 -0.05 0.001 0.002\n"
    )
    if image_lines is None:
        image_lines = [colmap_line(i + 1, poses[i], 1 + i % 2, image_names[i]) for i in SHUFFLE]
    # every image line is followed by its (here empty) line of 2D points
    (model / "images.txt").write_text("# Image list\n" + "".join(f"{line}\n\n" for line in image_lines))
    (model / "points3D.txt").write_text("# 3D point list\n")
    return model


# ---- ScanNet: SensReader's exported folder and the raw .sens file ----

SCANNET_INTRINSIC = np.array([[28.0, 0, 15.5, 0], [0, 29.0, 11.5, 0], [0, 0, 1, 0], [0, 0, 0, 1]])
"""Colour intrinsics of the generated scenes' 32x24 images, as the .sens header holds them."""
SCANNET_COLOUR_SIZE = (1296, 968)
"""ScanNet's colour camera: an exported folder's intrinsic_color.txt is for images of this size."""
EXPORTED_INTRINSIC = (
    np.diag([SCANNET_COLOUR_SIZE[0] / WIDTH, SCANNET_COLOUR_SIZE[1] / HEIGHT, 1, 1]) @ SCANNET_INTRINSIC
)
"""intrinsic_color.txt of the generated exported folders: the colour camera's, whose 32x24 copies are the images."""


def scannet_poses(count: int, seed: int = 0) -> np.ndarray:
    """OpenCV camera-to-world poses along a path, each turned differently (metres)."""
    rng = np.random.default_rng(seed)
    poses = np.tile(np.eye(4), (count, 1, 1))
    for i in range(count):
        poses[i, :3, :3] = rotation(rng.normal(size=3), rng.uniform(0.2, 2.5))
        poses[i, :3, 3] = [0.4 * i + 1.0, np.sin(i), 1.5 + 0.1 * i]
    return poses


def jpeg_bytes(index: int) -> bytes:
    rng = np.random.default_rng(index)
    pixels = rng.integers(0, 255, size=(HEIGHT, WIDTH, 3), dtype=np.uint8)
    buffer = io.BytesIO()
    Image.fromarray(pixels).save(buffer, format="JPEG")
    return buffer.getvalue()


SCANNET_DEPTH_SIZE = (WIDTH // 2, HEIGHT // 2)
"""The generated scenes' depth maps: half the colour images' size (ScanNet's: 640x480 beside 1296x968 colour)."""
SCANNET_DEPTH_INTRINSIC = np.diag([0.5, 0.5, 1, 1]) @ SCANNET_INTRINSIC
"""The depth camera of the generated scenes: the colour camera at half the size, so colour pixel (u, v) sees depth
pixel (u // 2, v // 2)."""


def write_exported(
    folder: Path, poses: np.ndarray, lost: tuple = (), depth_intrinsic: Optional[np.ndarray] = None
) -> Path:
    """SensReader's export: color/<i>.jpg, pose/<i>.txt, intrinsic/intrinsic_color.txt; the colour images are 32x24
    copies of the colour camera's. With `depth_intrinsic`, also depth/<i>.png (depth_millimetres, 16x12) and
    intrinsic/intrinsic_depth.txt."""
    for sub in ("color", "pose", "intrinsic"):
        (folder / sub).mkdir(parents=True, exist_ok=True)
    np.savetxt(folder / "intrinsic" / "intrinsic_color.txt", EXPORTED_INTRINSIC)
    for i, pose in enumerate(poses):
        (folder / "color" / f"{i}.jpg").write_bytes(jpeg_bytes(i))
        np.savetxt(folder / "pose" / f"{i}.txt", np.full((4, 4), -np.inf) if i in lost else pose)
    if depth_intrinsic is not None:
        (folder / "depth").mkdir(exist_ok=True)
        np.savetxt(folder / "intrinsic" / "intrinsic_depth.txt", depth_intrinsic)
        for i in range(len(poses)):
            Image.fromarray(depth_millimetres(i, *SCANNET_DEPTH_SIZE)).save(folder / "depth" / f"{i}.png")
    return folder


def write_sens(
    path: Path,
    poses: np.ndarray,
    lost: tuple = (),
    color_compression: int = 2,
    depth_compression: int = 1,
    sparse_depth_bytes: Optional[int] = None,
    intrinsic: np.ndarray = SCANNET_INTRINSIC,
    sparse_depth_frame: int = 0,
) -> Dict[int, bytes]:
    """A .sens file per the format: header, then per frame pose, timestamps, sizes, colour and depth bytes (every
    depth frame the same: millimetres 0, 1, 2, ... in flat order, seen by SCANNET_DEPTH_INTRINSIC).

    `sparse_depth_bytes` gives frame `sparse_depth_frame` a depth block of that size left as a hole (a sparse file),
    so a reader that loads the depth bytes instead of seeking past them shows in its memory use.
    """
    depth_w, depth_h = SCANNET_DEPTH_SIZE
    depth = np.arange(depth_w * depth_h, dtype=np.uint16).tobytes()  # millimetres: 0 at the first pixel (no depth)
    depth = zlib.compress(depth) if depth_compression == 1 else depth
    name = b"StructureSensor"
    colours = {i: jpeg_bytes(i) for i in range(len(poses))}
    with path.open("wb") as sens:
        sens.write(struct.pack("<I", 4) + struct.pack("<Q", len(name)) + name)
        for matrix in (intrinsic, np.eye(4), SCANNET_DEPTH_INTRINSIC, np.eye(4)):
            sens.write(struct.pack("<16f", *matrix.astype(np.float32).ravel()))
        sens.write(struct.pack("<ii", color_compression, depth_compression))
        sens.write(struct.pack("<IIII", WIDTH, HEIGHT, depth_w, depth_h))
        sens.write(struct.pack("<f", 1000.0) + struct.pack("<Q", len(poses)))
        for i, pose in enumerate(poses):
            matrix = np.full((4, 4), -np.inf) if i in lost else pose
            depth_size = sparse_depth_bytes if (sparse_depth_bytes and i == sparse_depth_frame) else len(depth)
            sens.write(struct.pack("<16f", *matrix.astype(np.float32).ravel()))
            sens.write(struct.pack("<QQ", 1000 * i, 1000 * i + 3) + struct.pack("<QQ", len(colours[i]), depth_size))
            sens.write(colours[i])
            if depth_size == len(depth):
                sens.write(depth)
            else:
                sens.seek(depth_size, 1)
    return colours


# ---- TUM RGB-D: rgb.txt, groundtruth.txt and rgb/ ----

START = 1305031102.0
"""Timestamps are seconds since the Unix epoch, as in the dataset."""
AXIS = np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8])
"""The camera turns about this axis at a constant rate."""
IMAGE_TIMES = START + 0.0047 + np.arange(12) / 30
"""30 Hz images; the first three come before the ground truth starts."""
POSE_TIMES = START + 0.1 + np.arange(51) / 100
"""100 Hz ground truth from 0.1 s to 0.6 s."""


def angle_at(t: float) -> float:
    return 0.3 + 2.0 * (t - START)


def pose_at(t: float) -> np.ndarray:
    """OpenCV camera-to-world at time t: constant velocity, constant turn rate about a fixed axis."""
    pose = np.eye(4)
    pose[:3, :3] = rotation(AXIS, angle_at(t))
    pose[:3, 3] = [1.0 + 2.0 * (t - START), -0.5 + 1.0 * (t - START), 1.2 - 0.8 * (t - START)]
    return pose


def groundtruth_line(t: float, scale: float = 1.0) -> str:
    """`timestamp tx ty tz qx qy qz qw`, scalar last; `scale` makes the quaternion non-unit."""
    half = angle_at(t) / 2
    quaternion = scale * np.array([*(AXIS * np.sin(half)), np.cos(half)])
    return " ".join(f"{v:.9f}" for v in [t, *pose_at(t)[:3, 3], *quaternion])


TUM_DEPTH_FACTOR = 5000
"""TUM's depth PNGs: 5000 per metre."""


def tum_depth_metres(index: int) -> float:
    """The (constant) depth of the `index`-th depth map write_sequence writes: 1 m + 10 cm per map."""
    return 1.0 + 0.1 * index


def write_sequence(
    folder: Path,
    image_times: np.ndarray = IMAGE_TIMES,
    pose_times: np.ndarray = POSE_TIMES,
    groundtruth_lines: Optional[List[str]] = None,
    depth_times: Optional[np.ndarray] = None,
) -> Path:
    """rgb/<t>.png, rgb.txt and groundtruth.txt with the dataset's three comment lines each; with `depth_times`, also
    depth/<t>.png (uniform tum_depth_metres of its place in depth_times, 16-bit, 5000 per metre) and depth.txt."""
    if depth_times is not None:
        (folder / "depth").mkdir(parents=True)
        depth_lines = ["# depth maps", "# file: 'rgbd_dataset.bag'", "# timestamp filename"]
        for i, t in enumerate(depth_times):
            value = round(tum_depth_metres(i) * TUM_DEPTH_FACTOR)
            Image.fromarray(np.full((HEIGHT, WIDTH), value, dtype=np.uint16)).save(folder / "depth" / f"{t:.6f}.png")
            depth_lines.append(f"{t:.6f} depth/{t:.6f}.png")
        (folder / "depth.txt").write_text("\n".join(depth_lines) + "\n")
    (folder / "rgb").mkdir(parents=True)
    rgb_lines = ["# color images", "# file: 'rgbd_dataset.bag'", "# timestamp filename"]
    for i, t in enumerate(image_times):
        pixels = np.random.default_rng(i).integers(0, 255, size=(HEIGHT, WIDTH, 3), dtype=np.uint8)
        Image.fromarray(pixels).save(folder / "rgb" / f"{t:.6f}.png")
        rgb_lines.append(f"{t:.6f} rgb/{t:.6f}.png")
    (folder / "rgb.txt").write_text("\n".join(rgb_lines) + "\n")
    header = ["# ground truth trajectory", "# file: 'rgbd_dataset.bag'", "# timestamp tx ty tz qx qy qz qw"]
    body = groundtruth_lines if groundtruth_lines is not None else [groundtruth_line(t) for t in pose_times]
    (folder / "groundtruth.txt").write_text("\n".join(header + body) + "\n")
    return folder


# ---- Waymo: a segment of known geometry, as v2 Parquet files or a v1 .tfrecord ----

SEGMENT = "4242_000_020_000"
CAMERAS = list(CAMERA_IDS)
WORLD_ORIGIN = np.array([-25211.0, 42391.0, -161.0])
"""Where the generated segments drive: world coordinates as large as Waymo's."""
NUM_TIMES = 6
TIMES = [1_553_735_853_000_000 + 100_000 * i for i in range(NUM_TIMES)]


def rotation_z(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def rigid(rotation: np.ndarray, translation) -> np.ndarray:
    matrix = np.eye(4)
    matrix[:3, :3], matrix[:3, 3] = rotation, translation
    return matrix


def vehicle_pose(i: int) -> np.ndarray:
    """The vehicle drives forward while it turns left."""
    return rigid(rotation_z(0.05 * i + 0.3), WORLD_ORIGIN + [2.0 * i, 0.4 * i, 0.01 * i])


def image_pose(i: int, camera: str) -> np.ndarray:
    """Each camera's own pose: the vehicle a few cm further on (rolling shutter), different per camera."""
    return rigid(rotation_z(0.05 * i + 0.3), WORLD_ORIGIN + [2.0 * i + 0.01 * CAMERA_IDS[camera], 0.4 * i, 0.01 * i])


EXTRINSICS = {
    "FRONT": rigid(rotation_z(0.0), [1.5, 0.0, 2.1]),
    "FRONT_LEFT": rigid(rotation_z(np.pi / 4), [1.5, 0.1, 2.1]),
    "FRONT_RIGHT": rigid(rotation_z(-np.pi / 4), [1.5, -0.1, 2.1]),
    "SIDE_LEFT": rigid(rotation_z(np.pi / 2), [1.4, 0.1, 2.1]),
    "SIDE_RIGHT": rigid(rotation_z(-np.pi / 2), [1.4, -0.1, 2.1]),
}
SIZES = {
    "FRONT": (16, 12),
    "FRONT_LEFT": (16, 12),
    "FRONT_RIGHT": (16, 12),
    "SIDE_LEFT": (16, 8),
    "SIDE_RIGHT": (16, 8),
}


def intrinsic(camera: str) -> List[float]:
    """[f_u, f_v, c_u, c_v, k1, k2, p1, p2, k3], different per camera."""
    width, height = SIZES[camera]
    n = CAMERA_IDS[camera]
    return [20.0 + n, 21.0 + n, width / 2 + 0.1 * n, height / 2, 0.01 * n, -0.002, 0.001, -0.001, 0.0005 * n]


def jpeg(camera: str, i: int) -> bytes:
    """A tiny image whose colour encodes camera and time."""
    buffer = io.BytesIO()
    Image.new("RGB", SIZES[camera], (40 * CAMERA_IDS[camera], 30 * i, 128)).save(buffer, format="JPEG")
    return buffer.getvalue()


def fixture_pose(i: int, camera: str) -> np.ndarray:
    """Both fixtures give every image its own pose but SIDE_LEFT's at time 1, which takes the frame's."""
    return vehicle_pose(i) if (i, camera) == (1, "SIDE_LEFT") else image_pose(i, camera)


# v2: Parquet with Waymo's column names


def transform_column(matrices: List[Optional[np.ndarray]], fixed_size: bool = True) -> pa.Array:
    """16 doubles per row; Waymo writes fixed-size lists, which pyarrow cannot read back with nulls in them."""
    values = [None if m is None else m.ravel().tolist() for m in matrices]
    return pa.array(values, type=pa.list_(pa.float64(), 16 if fixed_size else -1))


def write_v2(
    root: Path,
    skip_columns: Optional[Dict[str, str]] = None,
    image_poses: bool = True,
    cameras: Sequence[str] = CAMERAS,
) -> Path:
    """A v2 root of one segment of `cameras`: camera images shuffled over several row groups, one image without its
    own pose."""
    rows = [(i, camera) for i in range(NUM_TIMES) for camera in cameras]
    rows = [rows[k] for k in np.random.default_rng(0).permutation(len(rows))]
    own_pose = [image_poses and (i, camera) != (1, "SIDE_LEFT") for i, camera in rows]
    images = {
        "key.segment_context_name": pa.array([SEGMENT] * len(rows)),
        waymo_v2.TIMESTAMP: pa.array([TIMES[i] for i, _ in rows], type=pa.int64()),
        "key.camera_name": pa.array([CAMERA_IDS[camera] for _, camera in rows], type=pa.int8()),
        waymo_v2.IMAGE: pa.array([jpeg(camera, i) for i, camera in rows], type=pa.binary()),
        waymo_v2.IMAGE_POSE: transform_column(
            [image_pose(i, c) if own else None for (i, c), own in zip(rows, own_pose)], False
        ),
        "[CameraImageComponent].pose_timestamp": pa.array([TIMES[i] / 1e6 for i, _ in rows]),
    }
    calibration = {
        "key.segment_context_name": pa.array([SEGMENT] * len(cameras)),
        "key.camera_name": pa.array([CAMERA_IDS[camera] for camera in cameras], type=pa.int8()),
        **{name: pa.array([intrinsic(camera)[k] for camera in cameras]) for k, name in enumerate(waymo_v2.INTRINSIC)},
        waymo_v2.EXTRINSIC: transform_column([EXTRINSICS[camera] for camera in cameras]),
        waymo_v2.WIDTH: pa.array([SIZES[camera][0] for camera in cameras], type=pa.int32()),
        waymo_v2.HEIGHT: pa.array([SIZES[camera][1] for camera in cameras], type=pa.int32()),
        "[CameraCalibrationComponent].rolling_shutter_direction": pa.array([2] * len(cameras), type=pa.int8()),
    }
    poses = {
        "key.segment_context_name": pa.array([SEGMENT] * NUM_TIMES),
        waymo_v2.TIMESTAMP: pa.array(TIMES[::-1], type=pa.int64()),
        waymo_v2.VEHICLE_POSE: transform_column([vehicle_pose(i) for i in reversed(range(NUM_TIMES))]),
    }
    for component, columns in (("camera_image", images), ("camera_calibration", calibration), ("vehicle_pose", poses)):
        if not image_poses and component == "camera_image":
            del columns[waymo_v2.IMAGE_POSE]
        columns.pop((skip_columns or {}).get(component, ""), None)
        (root / component).mkdir(parents=True, exist_ok=True)
        pq.write_table(pa.table(columns), root / component / f"{SEGMENT}.parquet", row_group_size=7)
    return root


# v1: TFRecord framing and protobuf bytes written by hand


def reference_crc32c(data: bytes) -> int:
    """Bit by bit, straight from the definition (reflected Castagnoli polynomial)."""
    crc = 0xFFFFFFFF
    for byte in data:
        crc ^= byte
        for _ in range(8):
            crc = (crc >> 1) ^ (0x82F63B78 if crc & 1 else 0)
    return crc ^ 0xFFFFFFFF


def reference_masked(data: bytes) -> int:
    crc = reference_crc32c(data)
    return (((crc >> 15) | (crc << 17)) + 0xA282EAD8) & 0xFFFFFFFF


def varint(value: int) -> bytes:
    out = bytearray()
    while True:
        out.append(value & 0x7F | (0x80 if value > 0x7F else 0))
        value >>= 7
        if not value:
            return bytes(out)


def field(number: int, payload) -> bytes:
    """A varint field for an int, a length-delimited one for bytes."""
    if isinstance(payload, int):
        return varint(number << 3) + varint(payload)
    return varint(number << 3 | 2) + varint(len(payload)) + payload


def doubles(number: int, values, packed: bool) -> bytes:
    values = [float(v) for v in values]
    if packed:
        return field(number, struct.pack(f"<{len(values)}d", *values))
    return b"".join(varint(number << 3 | 1) + struct.pack("<d", v) for v in values)


def transform(matrix: np.ndarray) -> bytes:
    return doubles(1, matrix.ravel(), packed=True)


def v1_frame(i: int, cameras: List[str]) -> bytes:
    """A Frame: context with calibrations (intrinsics not packed, as in real files), pose, images, unknown fields."""
    calibrations = b"".join(
        field(
            2,
            field(1, CAMERA_IDS[c])
            + doubles(2, intrinsic(c), packed=False)
            + field(3, transform(EXTRINSICS[c]))
            + field(4, SIZES[c][0])
            + field(5, SIZES[c][1])
            + field(6, 2),
        )
        for c in cameras
    )
    images = b"".join(
        field(
            4,
            field(1, CAMERA_IDS[c])
            + field(2, jpeg(c, i))
            + (b"" if (i, c) == (1, "SIDE_LEFT") else field(3, transform(image_pose(i, c))))
            + doubles(5, [TIMES[i] / 1e6], packed=False),
        )
        for c in reversed(cameras)
    )
    lasers = field(5, field(1, 1) + field(2, bytes(300)))
    return (
        field(1, field(1, SEGMENT.encode()) + calibrations)
        + field(2, TIMES[i])
        + field(3, transform(vehicle_pose(i)))
        + images
        + lasers
    )


def tfrecord(records: List[bytes]) -> bytes:
    out = b""
    for data in records:
        length = struct.pack("<Q", len(data))
        out += length + struct.pack("<I", reference_masked(length)) + data + struct.pack("<I", reference_masked(data))
    return out


def write_v1(path: Path, times: Sequence[int] = range(NUM_TIMES)) -> Path:
    path.write_bytes(tfrecord([v1_frame(i, CAMERAS) for i in times]))
    return path


def corrupt(path: Path, offset: int) -> None:
    data = bytearray(path.read_bytes())
    data[offset] ^= 0x01
    path.write_bytes(bytes(data))


# ---- several processes (nerfstudio's launcher, gloo on CPU) ----

RANK_RECORDS = "rank-records"
"""Folder of a multi-process test run where each rank writes what it did (recorded_train_loop)."""


def launch_two_processes(config: ContinualTrainerConfig, timeout_seconds: float, **recording: Any) -> None:
    """What `ns-train --machine.num-devices 2` does with `config`: save it, then nerfstudio's `launch` with its
    process-group timeout shortened; every rank runs recorded_train_loop with `recording`'s options."""
    from nerfstudio.scripts import train

    config.machine.num_devices = 2
    config.save_config()  # routes the processes through the plugin's worker, as ns-train's main does
    train.launch(
        main_func=functools.partial(recorded_train_loop, **recording),
        num_devices_per_machine=2,
        config=config,
        timeout=timedelta(seconds=timeout_seconds),
        device_type=config.machine.device_type,
    )


def recorded_train_loop(
    local_rank: int,
    world_size: int,
    config: ContinualTrainerConfig,
    global_rank: int = 0,
    slow_rank: int = -1,
    slow_seconds: float = 0.0,
    dying_rank: int = -1,
    pausing_seconds: float = 0.0,
) -> None:
    """nerfstudio's train_loop (seeded per rank, set up, trained) that records, at each task switch, the step, this
    rank's budget and the replay oracle's weights; `slow_rank` sleeps `slow_seconds` after each iteration, outside
    the budget's clock; `dying_rank` kills itself after its second iteration; `pausing_seconds`: rank 0 is paused
    for that long, as by the viewer's button, the moment its second iteration's callbacks are done."""
    seed_like_ns_train(config.machine.seed + global_rank)
    trainer = config.setup(local_rank=local_rank, world_size=world_size)
    trainer.setup()
    pipeline = trainer.pipeline
    records_dir = trainer.base_dir / RANK_RECORDS
    records_dir.mkdir(parents=True, exist_ok=True)
    switches: List[Dict[str, Any]] = []
    open_next_task = pipeline.open_next_task

    def recorded_switch() -> None:
        budget = pipeline.budget
        switches.append({"step": trainer.step, "seconds_done": budget.seconds_done, "seconds": budget.seconds})
        open_next_task()
        oracle = pipeline.replay_oracle.model
        assert oracle is not None
        torch.save(oracle.state_dict(), records_dir / f"oracle-rank{global_rank}-switch{len(switches)}.pt")

    setattr(pipeline, "open_next_task", recorded_switch)
    after = [TrainingCallbackLocation.AFTER_TRAIN_ITERATION]
    if global_rank == slow_rank:
        trainer.callbacks.append(TrainingCallback(after, lambda step: time.sleep(slow_seconds)))
    if global_rank == dying_rank:
        trainer.callbacks.append(TrainingCallback(after, _die_after_second_iteration))
    pause: Dict[str, int] = {}
    if global_rank == 0 and pausing_seconds:  # after every callback of the trainer's own
        trainer.callbacks.append(TrainingCallback(after, functools.partial(_pause, trainer, pausing_seconds, pause)))
    trainer.train()
    summary = {"switches": switches, "accuracy_rows": len(pipeline.accuracy.psnr), "last_step": trainer.step, **pause}
    (records_dir / f"rank{global_rank}.json").write_text(json.dumps(summary))


def _pause(trainer: ContinualTrainer, seconds: float, pause: Dict[str, int], step: int) -> None:
    """At step 1, pause `trainer` now and resume it `seconds` later from another thread, as the viewer's buttons do;
    `pause` records the step training was at when it resumed."""

    def resume() -> None:
        time.sleep(seconds)
        pause["step_when_resumed"] = trainer.step
        trainer.training_state = "training"

    if step == 1:
        trainer.training_state = "paused"
        threading.Thread(target=resume, daemon=True).start()


def _die_after_second_iteration(step: int) -> None:
    if step == 1:
        os.kill(os.getpid(), signal.SIGKILL)


def two_process_command(output_dir: Path, timeout_seconds: float = 60.0, **options: Any) -> List[str]:
    """launch_two_processes in a fresh interpreter (as ns-train runs), with tiny_config's options and `options`:
    datamanager options, and recorded_train_loop's (slow_rank, slow_seconds, dying_rank)."""
    script = "import json, sys; sys.path.insert(0, sys.argv[1]); import helpers; helpers.launch_from_json(sys.argv[2])"
    arguments = json.dumps({"output_dir": str(output_dir), "timeout_seconds": timeout_seconds, **options})
    return [sys.executable, "-c", script, str(Path(__file__).parent), arguments]


def two_process_run(output_dir: Path, timeout_seconds: float = 60.0, **options: Any) -> "subprocess.CompletedProcess":
    """two_process_command, run to its end (a hang fails the test once RUN_TIMEOUT has passed)."""
    command = two_process_command(output_dir, timeout_seconds, **options)
    run = subprocess.Popen(command, env=SUBPROCESS_ENV, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    stdout, stderr = finish(run, "the two-process run")
    return subprocess.CompletedProcess(command, run.returncode, stdout, stderr)


def finish(process: subprocess.Popen, what: str, timeout: float = RUN_TIMEOUT) -> Tuple[str, str]:
    """The process's output once it has ended; a process still running after `timeout` seconds is a hang: it is
    killed and the test fails saying so."""
    try:
        return process.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        kill_with_its_children(process)
        _, stderr = process.communicate(timeout=60)
        raise AssertionError(
            f"{what} still ran after {timeout:g} s, a hang; its last output: {stderr[-2000:]}"
        ) from None


def kill_with_its_children(process: subprocess.Popen) -> None:
    """Kill `process` and every process it started: a training process it spawned would otherwise keep the output
    pipes open, and reading them to their end would wait for ever."""
    with contextlib.suppress(psutil.NoSuchProcess):  # it may end meanwhile, and so may each child
        for child in psutil.Process(process.pid).children(recursive=True):
            with contextlib.suppress(psutil.NoSuchProcess):
                child.kill()
    process.kill()


def launch_from_json(arguments: str) -> None:
    """two_process_run's side in the fresh interpreter."""
    options = json.loads(arguments)
    recorded = ("slow_rank", "slow_seconds", "dying_rank", "pausing_seconds")
    recording = {name: options.pop(name) for name in recorded if name in options}
    timeout_seconds = options.pop("timeout_seconds")
    config = tiny_config(Path(options.pop("output_dir")), demo_parser(), **options.pop("tiny", {}))
    config.max_num_iterations = options.pop("max_num_iterations", None)
    config.pipeline.datamanager = dataclasses.replace(config.pipeline.datamanager, **options)
    config.timestamp = "two-processes"
    launch_two_processes(config, timeout_seconds, **recording)


def two_process_run_dir(output_dir: Path) -> Path:
    return output_dir / "unnamed" / "continual-ngp" / "two-processes"


def collectives_probe(rank: int, port: int, output_dir: Path) -> None:
    """One of two gloo processes: what continual_nerf.core.distributed's helpers give this rank, into rank<r>.pt."""
    import torch.distributed as dist

    from continual_nerf.core import distributed

    dist.init_process_group("gloo", init_method=f"tcp://127.0.0.1:{port}", world_size=2, rank=rank)
    torch.manual_seed(rank)  # different weights on each rank
    module = torch.nn.Linear(3, 2)
    distributed.copy_from_main(module, "cpu")
    results = {
        "decided": distributed.decided_by_main(10 + rank, "cpu"),
        "averaged": distributed.averaged_over_ranks({"fisher": torch.full((2,), 2.0 * rank)})["fisher"],
        "weights": module.state_dict(),
    }
    torch.save(results, output_dir / f"rank{rank}.pt")
    dist.destroy_process_group()


class Killed(BaseException):
    """Stands in for SIGKILL: nothing in the run catches it, so no clean-up code runs after it."""


def kill_in_the_middle_of_save(monkeypatch, save_number: int) -> None:
    """The `save_number`-th torch.save writes half of its bytes, then the process 'dies'."""
    real_save, calls = torch.save, []

    def save(obj, file, *args, **kwargs) -> None:
        calls.append(file)
        if len(calls) < save_number:
            return real_save(obj, file, *args, **kwargs)
        buffer = io.BytesIO()
        real_save(obj, buffer)
        file.write(buffer.getvalue()[: len(buffer.getvalue()) // 2])
        raise Killed

    monkeypatch.setattr(torch, "save", save)


def flip_tensor_bytes(checkpoint: bytes) -> bytes:
    """A torch.save archive with four bytes flipped in the middle of its largest tensor's data: a valid zip whose
    tensors torch.load reads without a word, one member's CRC-32 wrong."""
    with zipfile.ZipFile(io.BytesIO(checkpoint)) as archive:
        member = max((info for info in archive.infolist() if "/data/" in info.filename), key=lambda i: i.file_size)
    name_length, extra_length = struct.unpack("<HH", checkpoint[member.header_offset + 26 : member.header_offset + 30])
    middle = member.header_offset + 30 + name_length + extra_length + member.file_size // 2
    flipped = bytearray(checkpoint)
    for offset in range(middle, middle + 4):
        flipped[offset] ^= 0x5A
    return bytes(flipped)


class FullDisk(io.RawIOBase):
    """A file on a disk that fills up after `room` bytes: a write beyond raises OSError(ENOSPC), as the OS's does."""

    def __init__(self, file: BinaryIO, room: int) -> None:
        super().__init__()
        self.file = file
        self.room = room

    def writable(self) -> bool:
        return True

    def write(self, data) -> int:
        if len(data) > self.room:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        self.room -= len(data)
        return self.file.write(data)


def fill_the_disk_at_checkpoint(monkeypatch, save_number: int = 1) -> None:
    """From the `save_number`-th torch.save on, the disk is full after 1000 bytes of the checkpoint (torch's zip
    writer meets the OSError and raises its own RuntimeError, as on a real full disk)."""
    real_save, calls = torch.save, []

    def save(obj, file, *args, **kwargs) -> None:
        calls.append(file)
        real_save(obj, file if len(calls) < save_number else FullDisk(file, room=1000), *args, **kwargs)

    monkeypatch.setattr(torch, "save", save)
