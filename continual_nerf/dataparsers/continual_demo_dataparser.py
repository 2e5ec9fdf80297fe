"""`continual-demo`: a procedurally generated room with exact poses and exact depth, rendered once and cached on disk;
optionally with what a real capture adds (exposure changes, camera colour responses, pose errors, a depth sensor's
flaws: `demo_capture.py`)."""

from __future__ import annotations

import dataclasses
import json
import math
import os
import shutil
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Dict, List, Literal, Optional, Type

import numpy as np
import torch
from nerfstudio.cameras.cameras import Cameras, CameraType
from nerfstudio.data.dataparsers.base_dataparser import DataParser, DataParserConfig, DataparserOutputs
from nerfstudio.data.scene_box import SceneBox
from PIL import Image

from continual_nerf.dataparsers import demo_capture, demo_scene, demo_street
from continual_nerf.dataparsers.demo_capture import DepthSensor, PoseNoiseKind
from continual_nerf.errors import ContinualConfigError
from continual_nerf.metadata_keys import DEPTH_FILENAMES, DEPTH_UNIT_SCALE_FACTOR
from continual_nerf.validated_config import ValidatedConfig

DemoScene = Literal["room", "street", "rooms", "long-street"]
SceneChange = Literal["none", "object-moved", "wall-repainted"]
"""What a later session finds changed in the scene."""
DEFAULT_FRAMES: Dict[str, int] = {"room": 120, "street": 120, "rooms": 480, "long-street": 480}
"""Capture instants of each scene when --num-frames is not given: the long scenes keep the short ones' density."""
RIGS = ("street", "long-street")
"""Scenes captured by the three-camera rig."""


@dataclass
class ContinualDemoDataParserConfig(ValidatedConfig, DataParserConfig):
    """A generated scene with exact poses (no download): a camera walking along a room, or a three-camera vehicle
    driving down a street."""

    _target: Type = field(default_factory=lambda: ContinualDemoDataParser)
    """The dataparser this config builds."""
    data: Path = Path("data/continual-demo")
    """Folder the rendered scene is written to, and reused from when it already holds the same scene."""
    scene: DemoScene = "room"
    """room: one camera walks along a corridor-room; street: a vehicle's front, front-left and front-right cameras;
    rooms and long-street: long captures, four rooms in a row and a street five times as long, never revisited."""
    num_frames: Optional[int] = None
    """Capture instants along the path, in capture order (one image each in the rooms, three in the streets); None: 120
    for room and street, 480 for rooms and long-street."""
    width: int = 64
    """Image width in pixels."""
    height: int = 48
    """Image height in pixels."""
    fov_degrees: float = 70.0
    """Horizontal field of view of the camera."""
    seed: int = 0
    """Seed of the object layout and of the wobble of the camera path."""
    exposure_strength: float = 0.0
    """Exposure and white balance change along the capture: gains within 1 +- this (0.3: +-30 %), jumping at the start
    of each of --exposure-segments parts and drifting smoothly in between; 0: every frame exposed alike."""
    exposure_segments: int = 10
    """Parts of the capture, in capture order, each with its own exposure (the number of tasks: a jump at each task
    boundary)."""
    camera_response_strength: float = 0.0
    """Each camera records colour with its own response: per-channel gains within 1 +- this, a gamma within 1 +- half of
    it (the street's three cameras then disagree); 0: identical cameras."""
    pose_noise_degrees: float = 0.0
    """Root mean square rotation error of the poses the parser returns (the images stay rendered from the true
    poses)."""
    pose_noise_translation: float = 0.0
    """Root mean square position error of the poses the parser returns, as a fraction of the trajectory's length."""
    pose_noise_kind: PoseNoiseKind = "smooth"
    """How the pose errors vary along the capture: smooth (drift, latency: VIO, motion capture) or drawn anew for
    every instant (each image registered on its own: COLMAP)."""
    change: SceneChange = "none"
    """The scene as a later session finds it: object-moved (a crate, in the street a parked car, near the middle of
    the path moved along the wall the camera looks at) or wall-repainted (a stretch of that wall, or facade, painted
    over); none: as it was."""
    laps: int = 1
    """Times the camera walks the path (the vehicle drives the street), each lap's instants after the last's; with
    --change the last lap finds the scene changed: a first and a later session in one capture (the joint bound's)."""
    start_instant: int = 0
    """First capture instant returned: a capture cut into sessions (instants before it belong to an earlier one)."""
    end_instant: Optional[int] = None
    """Capture instant the returned frames stop before (None: the end of the path)."""
    depth_noise: float = 0.0
    """Depth maps with a sensor's noise: its standard deviation in metres at 1 m, growing with the square of the depth
    (a Kinect: about 0.0015); 0: exact depth."""
    depth_max_range: float = math.inf
    """Metres beyond which the depth maps hold no depth (0), as a sensor's range ends (Kinect, Structure Sensor: 4 to
    5 m); inf: no limit."""
    depth_edge_holes: int = 0
    """Pixels on either side of a depth discontinuity (an object's edge) without depth (0), as structured-light
    sensors leave them."""
    depth_dropout: float = 0.0
    """Share of pixels without depth (0), at random."""

    def validate(self) -> None:
        super().validate()
        for name in ("num_frames", "width", "height", "exposure_segments", "laps"):
            value = getattr(self, name)
            if value is not None and value < 1:
                raise ContinualConfigError(f"continual-demo --{name.replace('_', '-')} must be at least 1, got {value}")
        if not 0 < self.fov_degrees < 180:
            raise ContinualConfigError(f"continual-demo --fov-degrees must be in (0, 180), got {self.fov_degrees}")
        for name in ("exposure_strength", "camera_response_strength"):
            value = getattr(self, name)
            if not 0 <= value < 1:
                raise ContinualConfigError(f"continual-demo --{name.replace('_', '-')} must be in [0, 1), got {value}")
        instants = self.frames * self.laps
        end = instants if self.end_instant is None else self.end_instant
        if not 0 <= self.start_instant < end <= instants:
            raise ContinualConfigError(
                f"continual-demo --start-instant {self.start_instant} --end-instant {self.end_instant}: must cut a part "
                f"of the capture's {instants} instants (0 <= start < end <= {instants})"
            )
        for name in ("pose_noise_degrees", "pose_noise_translation", "depth_noise", "depth_edge_holes"):
            value = getattr(self, name)
            if not value >= 0:
                raise ContinualConfigError(
                    f"continual-demo --{name.replace('_', '-')} must not be negative, got {value}"
                )
        if not self.depth_max_range > 0:
            raise ContinualConfigError(f"continual-demo --depth-max-range must be positive, got {self.depth_max_range}")
        if not 0 <= self.depth_dropout < 1:
            raise ContinualConfigError(f"continual-demo --depth-dropout must be in [0, 1), got {self.depth_dropout}")

    @property
    def frames(self) -> int:
        """Capture instants along the path: --num-frames, or the scene's default."""
        return self.num_frames if self.num_frames is not None else DEFAULT_FRAMES[self.scene]

    @property
    def changes_colour(self) -> bool:
        """Whether the images differ from the exact renders (exposure or camera responses)."""
        return self.exposure_strength > 0 or self.camera_response_strength > 0

    @property
    def depth_sensor(self) -> DepthSensor:
        """The flaws the depth maps have (none: exact depth)."""
        return DepthSensor(self.depth_noise, self.depth_max_range, self.depth_edge_holes, self.depth_dropout)


@dataclass(frozen=True)
class DemoCapture:
    """The generated scene and its images' exact poses, capture instants and cameras, in capture order."""

    scene: demo_scene.Scene
    poses: np.ndarray
    """(N, 3, 4) camera-to-world matrices, OpenGL convention, metres."""
    instants: np.ndarray
    """(N,) capture instant of each image (the street's three cameras share one)."""
    cameras: np.ndarray
    """(N,) camera of each image: 0 in the room; 0, 1, 2 (front, front-left, front-right) in the street."""
    last_lap_scene: Optional[demo_scene.Scene] = None
    """The scene the last lap sees when it differs from the first laps' (--change with --laps); None: `scene`."""
    last_lap_start: int = 0
    """The first image of the last lap."""

    def scene_of(self, image: int) -> demo_scene.Scene:
        """The scene as image `image` sees it."""
        if self.last_lap_scene is not None and image >= self.last_lap_start:
            return self.last_lap_scene
        return self.scene


class ContinualDemoDataParser(DataParser):
    """Renders the demo room with its own ray caster; every split returns the whole trajectory."""

    config: ContinualDemoDataParserConfig

    def _scene_folder(self) -> Path:
        c = self.config
        changed = "" if c.change == "none" else f"_{c.change}"
        laps = "" if c.laps == 1 else f"_laps{c.laps}"
        return c.data / (
            f"{c.scene}_{c.width}x{c.height}_{c.frames}frames_fov{c.fov_degrees:g}_seed{c.seed}{changed}{laps}"
        )

    def _focal(self) -> float:
        return self.config.width / 2 / np.tan(np.deg2rad(self.config.fov_degrees) / 2)

    def capture(self) -> DemoCapture:
        """The scene and its images' exact poses, instants and cameras: --laps times the path, the last lap seeing the
        scene as --change leaves it."""
        lap = self._lap()
        changed = self._changed(lap.scene)
        laps = self.config.laps
        if laps == 1:
            return dataclasses.replace(lap, scene=changed)
        per_lap = int(lap.instants.max()) + 1
        return DemoCapture(
            lap.scene,
            np.concatenate([lap.poses] * laps),
            np.concatenate([lap.instants + k * per_lap for k in range(laps)]),
            np.tile(lap.cameras, laps),
            last_lap_scene=changed,
            last_lap_start=(laps - 1) * len(lap.poses),
        )

    def _lap(self) -> DemoCapture:
        """One walk of the path through the scene as it was."""
        rng = np.random.default_rng(self.config.seed)
        count, scene_name = self.config.frames, self.config.scene
        if scene_name in RIGS:
            length = demo_street.LONG_STREET_LENGTH if scene_name == "long-street" else None
            scene = demo_street.street(rng) if length is None else demo_street.street(rng, length)
            poses, instants = (
                demo_street.rig_path(count, rng) if length is None else demo_street.rig_path(count, rng, length)
            )
            cameras = np.tile(np.arange(len(demo_street.CAMERA_YAWS)), count)
            return DemoCapture(scene, poses, instants, cameras)
        num_rooms = demo_scene.ROOMS if scene_name == "rooms" else 1
        scene = demo_scene.rooms(rng) if scene_name == "rooms" else demo_scene.room(rng)
        frames = np.arange(count)
        path = demo_scene.camera_path(count, rng, num_rooms)
        return DemoCapture(scene, path, frames, np.zeros_like(frames))

    def _changed(self, scene: demo_scene.Scene) -> demo_scene.Scene:
        """The scene as --change leaves it (after the whole layout is drawn: nothing else moves)."""
        street = self.config.scene in RIGS
        if self.config.change == "object-moved":
            return demo_street.with_car_moved(scene) if street else demo_scene.with_object_moved(scene)
        if self.config.change == "wall-repainted":
            return demo_street.with_facade_repainted(scene) if street else demo_scene.with_wall_repainted(scene)
        return scene

    def returned_frames(self, capture: DemoCapture) -> np.ndarray:
        """The frames of the instants --start-instant to --end-instant, in capture order."""
        c = self.config
        end = c.frames * c.laps if c.end_instant is None else c.end_instant
        return np.nonzero((capture.instants >= c.start_instant) & (capture.instants < end))[0]

    def _render_scene(self, folder: Path, capture: DemoCapture) -> None:
        """Render every frame into `folder` (and its transforms.json, exact poses)."""
        c = self.config
        (folder / "images").mkdir(parents=True)
        focal = self._focal()
        frames = []
        for i, c2w in enumerate(capture.poses):
            image = demo_scene.render_view(
                c2w, focal, focal, c.width / 2, c.height / 2, c.width, c.height, capture.scene_of(i)
            )
            Image.fromarray(image).save(folder / "images" / f"frame_{i:05d}.png")
            frames.append(
                {"file_path": f"images/frame_{i:05d}.png", "transform_matrix": np.vstack([c2w, [0, 0, 0, 1]]).tolist()}
            )
        transforms = {"fl_x": focal, "fl_y": focal, "cx": c.width / 2, "cy": c.height / 2, "w": c.width, "h": c.height}
        (folder / "transforms.json").write_text(json.dumps({**transforms, "frames": frames}, indent=1))

    def _render_depth(self, folder: Path, capture: DemoCapture) -> None:
        """Every frame's z-depth in metres as --depth-* says the sensor records it, frame_<i>.npy in `folder`."""
        c = self.config
        folder.mkdir(parents=True)
        focal = self._focal()
        rng = demo_capture.effect_rng(c.seed, demo_capture.DEPTH_STREAM)
        for i, c2w in enumerate(capture.poses):
            exact = demo_scene.render_depth(
                c2w, focal, focal, c.width / 2, c.height / 2, c.width, c.height, capture.scene_of(i)
            )
            depth = exact if c.depth_sensor.exact else demo_capture.sensed_depth(exact, c.depth_sensor, rng)
            np.save(folder / f"frame_{i:05d}.npy", depth)

    def _depth_folder(self, scene_folder: Path) -> Path:
        return scene_folder / "_".join(filter(None, ("depth", self.config.depth_sensor.name())))

    def _captured_folder(self, scene_folder: Path) -> Path:
        c = self.config
        exposure = f"exposure{c.exposure_strength:g}x{c.exposure_segments}" if c.exposure_strength > 0 else ""
        response = f"response{c.camera_response_strength:g}" if c.camera_response_strength > 0 else ""
        return scene_folder / "_".join(filter(None, ("captured", exposure, response)))

    def frame_gains(self, capture: DemoCapture) -> np.ndarray:
        """(N, 3) exposure and white-balance gain of every image (ones with --exposure-strength 0)."""
        c = self.config
        if c.exposure_strength == 0:
            return np.ones((len(capture.poses), 3))
        rng = demo_capture.effect_rng(c.seed, demo_capture.EXPOSURE_STREAM)
        gains = demo_capture.exposure_gains(
            int(capture.instants.max()) + 1, c.exposure_segments, c.exposure_strength, rng
        )
        return gains[capture.instants]

    def camera_responses(self, capture: DemoCapture) -> List[demo_capture.CameraResponse]:
        """Every camera's colour response (neutral with --camera-response-strength 0)."""
        c = self.config
        num_cameras = int(capture.cameras.max()) + 1
        if c.camera_response_strength == 0:
            return [demo_capture.NEUTRAL] * num_cameras
        rng = demo_capture.effect_rng(c.seed, demo_capture.RESPONSE_STREAM)
        return demo_capture.camera_responses(num_cameras, c.camera_response_strength, rng)

    def _write_captured_images(self, scene_folder: Path, folder: Path, capture: DemoCapture) -> None:
        """The exact renders as the capture's cameras record them, at each frame's exposure."""
        folder.mkdir(parents=True)
        gains, responses = self.frame_gains(capture), self.camera_responses(capture)
        for i, camera in enumerate(capture.cameras):
            exact = np.asarray(Image.open(scene_folder / "images" / f"frame_{i:05d}.png"))
            image = demo_capture.captured(exact, gains[i], responses[camera])
            Image.fromarray(image).save(folder / f"frame_{i:05d}.png")

    def returned_poses(self, capture: DemoCapture) -> np.ndarray:
        """The poses the parser returns: the exact ones, with --pose-noise-* errors when set."""
        c = self.config
        if c.pose_noise_degrees == 0 and c.pose_noise_translation == 0:
            return capture.poses
        rng = demo_capture.effect_rng(c.seed, demo_capture.POSE_STREAM)
        return demo_capture.noisy_poses(
            capture.poses, capture.instants, c.pose_noise_degrees, c.pose_noise_translation, rng, c.pose_noise_kind
        )

    def _generate_dataparser_outputs(self, split: str = "train", **kwargs) -> DataparserOutputs:
        c = self.config
        capture = self.capture()
        scene, poses = capture.scene, self.returned_poses(capture)
        folder = self._scene_folder()
        if not (folder / "transforms.json").exists():
            write_folder(folder, lambda partial: self._render_scene(partial, capture))
        images = folder / "images"
        if c.changes_colour:
            images = self._captured_folder(folder)
            if not images.exists():
                write_folder(images, lambda partial: self._write_captured_images(folder, partial, capture))
        depth = self._depth_folder(folder)
        if not depth.exists():  # a scene rendered before the demo had depth gets it now, its images kept
            write_folder(depth, lambda partial: self._render_depth(partial, capture))
        centre = (scene.lo + scene.hi) / 2
        scale = 2.0 / float((scene.hi - scene.lo).max())  # the scene's longest side spans nerfstudio's [-1, 1] box
        kept = self.returned_frames(capture)
        poses, capture = (
            poses[kept],
            dataclasses.replace(capture, instants=capture.instants[kept], cameras=capture.cameras[kept]),
        )
        scaled = poses.copy()
        scaled[:, :, 3] = (poses[:, :, 3] - centre) * scale
        focal = self._focal()
        cameras = Cameras(
            camera_to_worlds=torch.from_numpy(scaled).float(),
            fx=focal,
            fy=focal,
            cx=c.width / 2,
            cy=c.height / 2,
            width=c.width,
            height=c.height,
            camera_type=CameraType.PERSPECTIVE,
        )
        transform = torch.eye(4)[:3]
        transform[:, 3] = torch.from_numpy(-centre).float()
        rig = {"time_group": capture.instants, "camera_id": capture.cameras} if c.scene in RIGS else {}
        metadata: Dict[str, Any] = {key: torch.from_numpy(value).long() for key, value in rig.items()}
        metadata[DEPTH_FILENAMES] = [depth / f"frame_{i:05d}.npy" for i in kept]
        metadata[DEPTH_UNIT_SCALE_FACTOR] = 1.0  # metres
        return DataparserOutputs(
            image_filenames=[images / f"frame_{i:05d}.png" for i in kept],
            cameras=cameras,
            scene_box=SceneBox(aabb=torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])),
            dataparser_transform=transform,
            dataparser_scale=scale,
            metadata=metadata,
        )


def write_folder(folder: Path, fill: Callable[[Path], None]) -> None:
    """`fill` a temporary folder beside `folder`, then rename it into place (another process may have been first)."""
    partial = folder.with_name(f"{folder.name}.partial-{os.getpid()}")
    shutil.rmtree(partial, ignore_errors=True)
    fill(partial)
    if folder.exists():
        shutil.rmtree(partial)
    else:
        os.replace(partial, folder)
