"""Sessions: a trained run goes on learning a later capture of the same scene (`--pipeline.continue-with-new-capture`).

A session is one capture, cut into its own tasks. A continued run's trajectory is the earlier sessions' frames followed
by the new capture's, and their tasks come first: the loaded model is the replay oracle of every one of them. Their
images may be gone (the continual setting itself), so everything those tasks need travels in every checkpoint as a
`SessionRecord`: their cameras in the run's world frame, their held-out test frames, the pixels their masks let train
(one bit per pixel), the world frame itself (the first session's dataparser transform, scale and scene box) and where
each task's checkpoint was written. Per-frame appearance codes, colour transforms and pose corrections are rows of the
model's state dict: the continued model is built for every frame and loads the earlier rows (`with_earlier_rows`).

A later capture is put in the first session's world frame: its poses are mapped back to its own world coordinates
(its dataparser's transform and scale undone) and through the first session's transform and scale, so captures in one
world (ScanNet/TUM/Waymo world coordinates, a COLMAP model extended by registering new images) line up.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Dict, List, Mapping, Optional, Sequence, Tuple

import numpy as np
import torch
from nerfstudio.cameras.cameras import Cameras
from nerfstudio.data.dataparsers.base_dataparser import DataparserOutputs, transform_poses_to_original_space
from nerfstudio.data.scene_box import SceneBox
from torch import Tensor

from continual_nerf.atomic_files import write_atomically
from continual_nerf.core.task_split import TaskSplit
from continual_nerf.core.valid_pixels import ValidPixels
from continual_nerf.errors import CheckpointError, ContinualConfigError, DatasetError
from continual_nerf.metadata_keys import DEPTH_FILENAMES, DEPTH_INTRINSICS, FISHEYE_CROP_RADIUS, HELD_OUT

SESSIONS_FILENAME = "earlier_sessions.pt"
"""A continued run's file in its run folder: the earlier sessions' record, read when its datamanager is set up
(ns-train, ns-eval, ns-render, the viewers)."""
SESSIONS_KEY = "sessions"
"""Key of the record in the pipeline's extra state (every checkpoint)."""
OUTSIDE_FACTOR = 2.0
"""A later capture's camera lies far outside the scene box when it is farther from the box's centre, along an axis,
than this many times the box's half size there."""
CAMERA_FIELDS = ("camera_to_worlds", "fx", "fy", "cx", "cy", "width", "height", "camera_type")
"""Tensors of nerfstudio's Cameras a record keeps (with distortion_params, which may be None)."""


@dataclass
class SessionRecord:
    """A run's sessions as a later session needs them, without their images: the frames in trajectory order, in the
    run's world frame, and their tasks."""

    cameras: Dict[str, Tensor]
    """nerfstudio Cameras tensors (CAMERA_FIELDS, (N, ...)) as the dataparsers gave them, poses in the run's box."""
    distortion_params: Optional[Tensor]
    """(N, 6) or (N, 12) distortion, or None when no frame has any."""
    image_filenames: List[str]
    """Every frame's image, where it was read from (it may be gone)."""
    camera_id: Tensor
    """(N,) which camera took each frame."""
    instants: Tensor
    """(N,) capture instant of each frame, increasing from session to session."""
    fisheye_crop_radius: Optional[Tensor]
    """(N,) radius outside which a frame's pixels never train (inf: none), or None when no frame has one."""
    train_frames: List[Tensor]
    """Per task, its training frames (trajectory indices)."""
    test_frames: List[Tensor]
    """Per task, its held-out test frames (trajectory indices)."""
    valid_bits: Optional[Tensor]
    """ValidPixels' bits of the training frames (in task order), or None when no frame has a mask or circle."""
    valid_counts: Optional[Tensor]
    """ValidPixels' count of valid pixels per training frame, with valid_bits."""
    image_scale: float
    """The scale the images were loaded at (datamanager resolution scale times the dataparser's downscale)."""
    dataparser_transform: Tensor
    """(3, 4) float64: the first session's dataparser transform, the run's world frame."""
    dataparser_scale: float
    """The first session's dataparser scale."""
    scene_box: Tensor
    """(2, 3) the scene box the model was built for."""
    tasks_per_session: List[int]
    """Tasks of each session, in order."""
    first_steps: List[int]
    """The training step each session started at."""
    next_step: int
    """The step the session after the recorded ones starts at (-1 in a checkpoint's record: its step tells)."""
    task_checkpoints: List[str]
    """Per task, the checkpoint written at its end ("" where none is known)."""
    data: List[str]
    """Per session, the capture it was read from."""
    model_options: Dict[str, Any] = field(default_factory=dict)
    """The model's options (plain values): a continued run's model must be of the same size."""

    @property
    def num_tasks(self) -> int:
        return len(self.train_frames)

    @property
    def num_frames(self) -> int:
        return len(self.image_filenames)

    @property
    def num_train_frames(self) -> int:
        return int(sum(len(frames) for frames in self.train_frames))

    def train_frames_of_sessions(self, count: int) -> int:
        """Training frames of the first `count` sessions (rows of their per-frame tables)."""
        tasks = int(sum(self.tasks_per_session[:count]))
        return int(sum(len(frames) for frames in self.train_frames[:tasks]))

    @property
    def num_test_frames(self) -> int:
        return int(sum(len(frames) for frames in self.test_frames))

    def session_of_task(self, task: int) -> int:
        """The session (0-based) task `task` belongs to (the one after the recorded ones for later tasks)."""
        ends = np.cumsum(self.tasks_per_session)
        return int(np.searchsorted(ends, task, side="right"))

    def first_sessions(self, count: int) -> "SessionRecord":
        """The record of the first `count` sessions."""
        tasks = int(sum(self.tasks_per_session[:count]))
        kept = restricted(self, tasks)
        return dataclasses.replace(
            kept,
            tasks_per_session=self.tasks_per_session[:count],
            first_steps=self.first_steps[:count],
            next_step=self.first_steps[count],
            data=self.data[:count],
        )

    def state(self) -> Dict[str, Any]:
        """Tensors and plain values only: a checkpoint loads with weights_only=True."""
        state = dataclasses.asdict(self)
        state["model_options"] = {key: _plain(value) for key, value in self.model_options.items()}
        return state

    @classmethod
    def from_state(cls, state: Mapping[str, Any]) -> "SessionRecord":
        names = {item.name for item in dataclasses.fields(cls)}
        return cls(**{key: value for key, value in state.items() if key in names})

    def save(self, path: Path) -> None:
        write_atomically(path, lambda file: torch.save(self.state(), file))

    @classmethod
    def load(cls, path: Path) -> "SessionRecord":
        """The record a continued run keeps in its run folder; a missing or unreadable one is a one-line error."""
        if not path.is_file():
            raise CheckpointError(f"{path}: not found (a continued run's record of its earlier sessions)")
        try:
            return cls.from_state(torch.load(path, map_location="cpu", weights_only=True))
        except Exception as error:  # noqa: BLE001 - whatever is wrong with the file, it is one line
            raise CheckpointError(f"{path}: not a record of earlier sessions ({type(error).__name__})") from None


def _plain(value: Any) -> Any:
    """A config value as weights_only pickling accepts it: numbers, strings, booleans, None and tuples of them."""
    if isinstance(value, (bool, int, float, str)) or value is None:
        return value
    if isinstance(value, (tuple, list)):
        return tuple(_plain(item) for item in value)
    return str(value)


def model_options(model_config: Any) -> Dict[str, Any]:
    """The model config's plain options (numbers, strings, booleans, tuples) and its camera optimizer's mode."""
    options = {
        item.name: _plain(getattr(model_config, item.name))
        for item in dataclasses.fields(model_config)
        if isinstance(getattr(model_config, item.name), (bool, int, float, str, tuple))
    }
    camera_optimizer = getattr(model_config, "camera_optimizer", None)
    if camera_optimizer is not None:
        options["camera_optimizer.mode"] = camera_optimizer.mode
    return options


def restricted(record: SessionRecord, num_tasks: int) -> SessionRecord:
    """`record` with its first `num_tasks` tasks only: the frames of later tasks (never trained) dropped."""
    train, test = record.train_frames[:num_tasks], record.test_frames[:num_tasks]
    kept = torch.unique(torch.cat([*train, *test])) if num_tasks else torch.zeros(0, dtype=torch.long)
    renumber = torch.full((record.num_frames,), -1, dtype=torch.long)
    renumber[kept] = torch.arange(len(kept))
    train_count = int(sum(len(frames) for frames in train))
    bits, counts = record.valid_bits, record.valid_counts
    if bits is not None and counts is not None:
        counts = counts[:train_count]
        pixels = (record.cameras["width"] * record.cameras["height"]).view(-1)[torch.cat([*train])] if train else None
        byte_count = int(((pixels + 7) // 8).sum()) if pixels is not None else 0
        bits = bits[:byte_count]
    return dataclasses.replace(
        record,
        cameras={key: value[kept] for key, value in record.cameras.items()},
        distortion_params=None if record.distortion_params is None else record.distortion_params[kept],
        image_filenames=[record.image_filenames[i] for i in kept.tolist()],
        camera_id=record.camera_id[kept],
        instants=record.instants[kept],
        fisheye_crop_radius=None if record.fisheye_crop_radius is None else record.fisheye_crop_radius[kept],
        train_frames=[renumber[frames] for frames in train],
        test_frames=[renumber[frames] for frames in test],
        valid_bits=bits,
        valid_counts=counts,
        task_checkpoints=record.task_checkpoints[:num_tasks],
    )


@dataclass(frozen=True)
class SessionContext:
    """What a record of a trajectory needs beyond its frames and split."""

    image_scale: float
    tasks_per_session: List[int]
    first_steps: List[int]
    task_checkpoints: List[str]
    data: List[str]
    model_options: Dict[str, Any]


def record_of(
    outputs: DataparserOutputs,
    split: TaskSplit,
    camera_id: np.ndarray,
    instants: np.ndarray,
    valid_pixels: Optional[ValidPixels],
    context: SessionContext,
) -> SessionRecord:
    """The record of a whole trajectory (every session's frames, as the datamanager joined them) and its split."""
    cameras = outputs.cameras
    radius = outputs.metadata.get(FISHEYE_CROP_RADIUS)
    train_count = sum(len(frames) for frames in split.train_frames)
    bits = counts = None
    if valid_pixels is not None:
        counts = valid_pixels.valid_per_frame[:train_count].clone()
        bits = valid_pixels.bits[: int(valid_pixels.byte_offsets[train_count])].clone()
    return SessionRecord(
        cameras={name: getattr(cameras, name).clone() for name in CAMERA_FIELDS},
        distortion_params=None if cameras.distortion_params is None else cameras.distortion_params.clone(),
        image_filenames=[str(path) for path in outputs.image_filenames],
        camera_id=torch.as_tensor(camera_id, dtype=torch.long),
        instants=torch.as_tensor(instants, dtype=torch.long),
        fisheye_crop_radius=None if radius is None else torch.as_tensor(radius).double().clone(),
        train_frames=[torch.as_tensor(frames, dtype=torch.long) for frames in split.train_frames],
        test_frames=[torch.as_tensor(frames, dtype=torch.long) for frames in split.test_frames],
        valid_bits=bits,
        valid_counts=counts,
        image_scale=float(context.image_scale),
        dataparser_transform=outputs.dataparser_transform.double().clone(),
        dataparser_scale=float(outputs.dataparser_scale),
        scene_box=outputs.scene_box.aabb.clone(),
        tasks_per_session=list(context.tasks_per_session),
        first_steps=list(context.first_steps),
        next_step=-1,
        task_checkpoints=list(context.task_checkpoints),
        data=list(context.data),
        model_options=dict(context.model_options),
    )


def in_world_frame(outputs: DataparserOutputs, record: SessionRecord) -> DataparserOutputs:
    """A later capture's outputs in the run's world frame: its poses mapped back to its own world coordinates and
    through the first session's dataparser transform and scale; the first session's scene box."""
    transform, scale = record.dataparser_transform, record.dataparser_scale
    own_transform = outputs.dataparser_transform.double()
    same = own_transform.shape == transform.shape and torch.equal(own_transform, transform)
    cameras = outputs.cameras
    if not (same and float(outputs.dataparser_scale) == scale):  # the demo's frame is the scene's: nothing to map
        world = transform_poses_to_original_space(
            cameras.camera_to_worlds.double(), own_transform, float(outputs.dataparser_scale), "opengl"
        )
        poses = transform[:, :3] @ world
        poses[:, :, 3] = (poses[:, :, 3] + transform[:, 3]) * scale
        cameras = _with_poses(cameras, poses.float())
    return dataclasses.replace(
        outputs,
        cameras=cameras,
        dataparser_transform=transform.to(outputs.dataparser_transform.dtype),
        dataparser_scale=scale,
        scene_box=SceneBox(aabb=record.scene_box.clone()),
    )


def _with_poses(cameras: Cameras, poses: Tensor) -> Cameras:
    return Cameras(
        camera_to_worlds=poses,
        fx=cameras.fx,
        fy=cameras.fy,
        cx=cameras.cx,
        cy=cameras.cy,
        width=cameras.width,
        height=cameras.height,
        distortion_params=cameras.distortion_params,
        camera_type=cameras.camera_type,
        times=cameras.times,
        metadata=cameras.metadata,
    )


def check_inside_scene_box(outputs: DataparserOutputs, data: str) -> None:
    """A one-line error when cameras of a later capture (in the run's world frame) lie far outside the scene box."""
    aabb = outputs.scene_box.aabb.double()
    centre, half = aabb.mean(dim=0), (aabb[1] - aabb[0]) / 2
    positions = outputs.cameras.camera_to_worlds[:, :, 3].double()
    reach = ((positions - centre).abs() / half).max(dim=-1).values
    outside = reach > OUTSIDE_FACTOR
    if not outside.any():
        return
    farthest = int(reach.argmax())
    where = ", ".join(f"{value:.2f}" for value in positions[farthest].tolist())
    box = " x ".join(f"[{low:g}, {high:g}]" for low, high in zip(aabb[0].tolist(), aabb[1].tolist()))
    raise DatasetError(
        f"{data}: {int(outside.sum())} of {len(positions)} cameras lie far outside the scene box the model was "
        f"trained in ({box}, after the first session's dataparser transform), the farthest at ({where}), "
        f"{float(reach[farthest]):.1f} times the box's half size from its centre: are its poses in the first "
        "capture's world coordinates? (--pipeline.datamanager.accept-cameras-outside-scene-box True trains on it)"
    )


def joined_camera_ids(record: SessionRecord, outputs: DataparserOutputs, own: np.ndarray) -> np.ndarray:
    """Camera of every frame of the joined trajectory: the recorded ones, then the later capture's (`own`: its
    dataparser's ids, or ids by intrinsics), a camera with an earlier camera's intrinsics taking that camera's id
    unless the dataparser names its cameras."""
    earlier = record.camera_id.numpy()
    if "camera_id" in outputs.metadata:
        return np.concatenate([earlier, own])
    recorded = {}
    for frame, camera in enumerate(earlier.tolist()):
        recorded.setdefault(_intrinsics_key(record.cameras, frame), camera)
    later_cameras = {name: getattr(outputs.cameras, name) for name in CAMERA_FIELDS}
    next_id = int(earlier.max()) + 1 if len(earlier) else 0
    ids, fresh = [], {}
    for frame, camera in enumerate(own.tolist()):
        key = _intrinsics_key(later_cameras, frame)
        if key in recorded:
            ids.append(recorded[key])
        else:
            ids.append(fresh.setdefault(camera, next_id + len(fresh)))
    return np.concatenate([earlier, np.asarray(ids, dtype=np.int64)])


def _intrinsics_key(cameras: Mapping[str, Tensor], frame: int) -> Tuple[float, ...]:
    return tuple(float(cameras[name][frame]) for name in ("fx", "fy", "cx", "cy", "width", "height", "camera_type"))


def joined(
    record: SessionRecord,
    outputs: DataparserOutputs,
    split: TaskSplit,
    camera_id: np.ndarray,
    instants: np.ndarray,
) -> Tuple[DataparserOutputs, TaskSplit]:
    """The trajectory of a continued run: the recorded frames, then the later capture's (`outputs`, in the run's world
    frame, with its own `split`, cameras and capture instants); the per-frame metadata the datamanager reads joined
    (cameras, capture instants, fisheye circles, test frames, depth maps), masks and depth maps None where a frame has
    none (the earlier sessions' depth maps are not recorded)."""
    earlier_count = record.num_frames
    cameras = outputs.cameras
    distortion = _joined_optional(record.distortion_params, cameras.distortion_params, earlier_count, len(cameras))
    joined_cameras = Cameras(
        **{name: torch.cat([record.cameras[name], getattr(cameras, name)]) for name in CAMERA_FIELDS},  # type: ignore[arg-type]
        distortion_params=distortion,
    )
    radius = _joined_optional(
        record.fisheye_crop_radius,
        outputs.metadata.get(FISHEYE_CROP_RADIUS),
        earlier_count,
        len(cameras),
        fill=float("inf"),
    )
    held_out = torch.zeros(earlier_count + len(cameras), dtype=torch.bool)
    held_out[torch.cat([*record.test_frames, *(torch.as_tensor(f) + earlier_count for f in split.test_frames)])] = True
    metadata: Dict[str, Any] = {
        key: value for key, value in outputs.metadata.items() if key not in ("camera_id", "time_group")
    }
    metadata.update(
        camera_id=torch.as_tensor(joined_camera_ids(record, outputs, camera_id), dtype=torch.long),
        time_group=torch.cat([record.instants, torch.as_tensor(instants) + _next_instant(record)]).long(),
    )
    metadata[HELD_OUT] = held_out
    if radius is not None:
        metadata[FISHEYE_CROP_RADIUS] = radius
    depth_filenames = outputs.metadata.get(DEPTH_FILENAMES)
    if depth_filenames is not None:
        metadata[DEPTH_FILENAMES] = [None] * earlier_count + list(depth_filenames)
    depth_intrinsics = _joined_optional(None, outputs.metadata.get(DEPTH_INTRINSICS), earlier_count, len(cameras))
    if depth_intrinsics is not None:
        metadata[DEPTH_INTRINSICS] = depth_intrinsics
    masks = outputs.mask_filenames
    joined_outputs = dataclasses.replace(
        outputs,
        image_filenames=[Path(name) for name in record.image_filenames] + list(outputs.image_filenames),
        cameras=joined_cameras,
        mask_filenames=None if masks is None else [None] * earlier_count + list(masks),  # type: ignore[list-item]
        metadata=metadata,
    )
    joined_split = TaskSplit(
        train_frames=(*split_frames(record.train_frames), *(f + earlier_count for f in split.train_frames)),
        test_frames=(*split_frames(record.test_frames), *(f + earlier_count for f in split.test_frames)),
    )
    return joined_outputs, joined_split


def split_frames(frames: Sequence[Tensor]) -> Tuple[np.ndarray, ...]:
    return tuple(np.asarray(f.numpy(), dtype=np.int64) for f in frames)


def _next_instant(record: SessionRecord) -> int:
    return int(record.instants.max()) + 1 if len(record.instants) else 0


def _joined_optional(
    earlier: Optional[Tensor], later: Optional[Tensor], earlier_count: int, later_count: int, fill: float = 0.0
) -> Optional[Tensor]:
    """Two sessions' per-frame tensors joined, a session without one filled with `fill` (None when neither has)."""
    if earlier is None and later is None:
        return None
    shape = (earlier if earlier is not None else later).shape[1:]  # type: ignore[union-attr]
    first = earlier if earlier is not None else torch.full((earlier_count, *shape), fill)
    second = later if later is not None else torch.full((later_count, *shape), fill)
    if first.shape[1:] != second.shape[1:]:
        raise DatasetError(
            f"the earlier sessions have {first.shape[1:]} distortion parameters per frame, this capture {second.shape[1:]}"
        )
    return torch.cat([first.to(second.dtype), second])


def with_earlier_rows(
    state: Mapping[str, Any], current: Mapping[str, Any], rows: Sequence[str], earlier_rows: int
) -> Dict[str, Any]:
    """`state` (a checkpoint's model) with every per-frame tensor in `rows` as the current model holds it: the first
    `earlier_rows` rows (the earlier sessions' training frames) as saved, the later frames' as the current model has
    them (codes and corrections at their start)."""
    grown = dict(state)
    for key in rows:
        saved = state[key]
        if saved.shape[0] < earlier_rows:
            raise CheckpointError(f"{key} holds {saved.shape[0]} frames' rows, the earlier sessions {earlier_rows}")
        value = current[key].detach().clone()
        value[:earlier_rows] = saved[:earlier_rows].to(value.dtype)
        grown[key] = value
    return grown


def size_difference(state: Mapping[str, Any], current: Mapping[str, Any], rows: Sequence[str]) -> Optional[str]:
    """The first tensor a checkpoint's model and this run's model do not share in name and shape (per-frame rows
    aside), as a short description, or None when they fit."""
    for key in sorted(set(state) ^ set(current)):
        where = "the checkpoint's model" if key in state else "this run's model"
        return f"{key} only in {where}"
    for key in sorted(state):
        if not isinstance(state[key], Tensor) or key in rows:
            continue
        if state[key].shape != current[key].shape:
            there, here = ("x".join(map(str, tensor.shape)) or "scalar" for tensor in (state[key], current[key]))
            return f"{key} is {there} in the checkpoint, {here} here"
    return None


def options_differing(saved: Mapping[str, Any], now: Mapping[str, Any]) -> List[str]:
    """`--pipeline.model.<option> A there, B here` for every recorded model option that differs."""
    return [
        f"--pipeline.model.{key.replace('_', '-')} {saved[key]} there, {now[key]} here"
        for key in sorted(saved)
        if key in now and saved[key] != now[key]
    ]


def grow_optimizer_state(state: Dict[str, Any], optimizer: torch.optim.Optimizer) -> Dict[str, Any]:
    """An earlier session's optimizer state dict for `optimizer`, this session's: its moments (Adam's exp_avg, ...),
    those of per-frame parameters, which have fewer rows than the parameters now, grown with zero rows for the later
    frames (as a parameter that has not moved yet); the hyperparameters (learning rates, ...) `optimizer` was built
    with, which this session's options set, and nothing else of the earlier session's groups (such as the base rate
    --pipeline.lr-decay-per-task scales)."""
    parameters = [parameter for group in optimizer.param_groups for parameter in group["params"]]
    groups = [
        {**group, "params": saved["params"]} for saved, group in zip(state["param_groups"], optimizer.param_groups)
    ]
    grown = {**state, "state": dict(state["state"]), "param_groups": groups}
    for index, moments in state["state"].items():
        if index >= len(parameters):
            continue
        parameter = parameters[index]
        grown["state"][index] = {
            name: _grown(value, parameter) if isinstance(value, Tensor) else value for name, value in moments.items()
        }
    return grown


def _grown(value: Tensor, parameter: Tensor) -> Tensor:
    if value.dim() == 0 or value.shape == parameter.shape or value.shape[1:] != parameter.shape[1:]:
        return value
    rows = torch.zeros_like(parameter, dtype=value.dtype, device=value.device)
    rows[: value.shape[0]] = value
    return rows


def checkpoint_record(state: Mapping[str, Any], path: Path) -> Optional[SessionRecord]:
    """The sessions record of a checkpoint's run (None for a checkpoint written before runs kept one)."""
    extra = state["pipeline"].get("_extra_state", {})
    saved = extra.get(SESSIONS_KEY) if isinstance(extra, dict) else None
    if saved is None:
        return None
    try:
        return SessionRecord.from_state(saved)
    except TypeError as error:
        raise CheckpointError(f"{path}: its record of sessions is incomplete ({error})") from None


def task_checkpoints(record: SessionRecord, state: Mapping[str, Any], path: Path) -> List[str]:
    """The record's checkpoint of every task's end, those of the checkpoint's own session's tasks found beside it (by
    the step of their accuracy-matrix rows)."""
    steps = state["pipeline"]["_extra_state"]["accuracy"]["steps"]
    found = list(record.task_checkpoints)
    first = record.num_tasks - (record.tasks_per_session[-1] if record.tasks_per_session else 0)
    for task in range(first, min(record.num_tasks, len(steps))):
        candidate = path.parent / f"step-{steps[task]:09d}.ckpt"
        if candidate.is_file():
            found[task] = str(candidate.resolve())
    return found


def same_capture(record: SessionRecord, filenames: Sequence[Path]) -> bool:
    """Whether the last recorded session read the images `filenames` (a capture is its files)."""
    last_tasks = record.tasks_per_session[-1] if record.tasks_per_session else 0
    if not last_tasks:
        return False
    first = int(torch.cat([*record.train_frames[-last_tasks:], *record.test_frames[-last_tasks:]]).min())
    recorded = [Path(name).resolve() for name in record.image_filenames[first:]]
    return recorded == [Path(name).resolve() for name in filenames][: len(recorded)]


def check_image_scale(record: SessionRecord, image_scale: float) -> None:
    if not np.isclose(record.image_scale, image_scale):
        raise ContinualConfigError(
            f"--downscale-factor / --pipeline.datamanager.camera-res-scale-factor: the earlier sessions loaded their "
            f"images at {record.image_scale:g} of their size, this capture at {image_scale:g}; continue at the same scale"
        )


def task_ranges(tasks: Sequence[int]) -> str:
    """0-based tasks as 1-based numbers and ranges: "1-3, 5"."""
    runs: List[List[int]] = []
    for task in sorted(tasks):
        if runs and runs[-1][-1] == task - 1:
            runs[-1].append(task)
        else:
            runs.append([task])
    return ", ".join(f"{run[0] + 1}" if len(run) == 1 else f"{run[0] + 1}-{run[-1] + 1}" for run in runs)
