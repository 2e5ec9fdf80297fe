"""`continual-demo`: a procedurally generated room with exact poses, rendered once and cached on disk."""

from __future__ import annotations

import json
import os
import shutil
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal, Optional, Tuple, Type

import numpy as np
import torch
from nerfstudio.cameras.cameras import Cameras, CameraType
from nerfstudio.data.dataparsers.base_dataparser import DataParser, DataParserConfig, DataparserOutputs
from nerfstudio.data.scene_box import SceneBox
from PIL import Image

from continual_nerf.dataparsers import demo_scene, demo_street
from continual_nerf.errors import ContinualConfigError
from continual_nerf.validated_config import ValidatedConfig


@dataclass
class ContinualDemoDataParserConfig(ValidatedConfig, DataParserConfig):
    """A generated scene with exact poses (no download): a camera walking along a room, or a three-camera vehicle
    driving down a street."""

    _target: Type = field(default_factory=lambda: ContinualDemoDataParser)
    """The dataparser this config builds."""
    data: Path = Path("data/continual-demo")
    """Folder the rendered scene is written to, and reused from when it already holds the same scene."""
    scene: Literal["room", "street"] = "room"
    """room: one camera walks along a corridor-room; street: a vehicle's front, front-left and front-right cameras."""
    num_frames: int = 120
    """Capture instants along the path, in capture order (one image each in the room, three in the street)."""
    width: int = 64
    """Image width in pixels."""
    height: int = 48
    """Image height in pixels."""
    fov_degrees: float = 70.0
    """Horizontal field of view of the camera."""
    seed: int = 0
    """Seed of the object layout and of the wobble of the camera path."""

    def validate(self) -> None:
        super().validate()
        for name in ("num_frames", "width", "height"):
            value = getattr(self, name)
            if value < 1:
                raise ContinualConfigError(f"continual-demo --{name.replace('_', '-')} must be at least 1, got {value}")
        if not 0 < self.fov_degrees < 180:
            raise ContinualConfigError(f"continual-demo --fov-degrees must be in (0, 180), got {self.fov_degrees}")


class ContinualDemoDataParser(DataParser):
    """Renders the demo room with its own ray caster; every split returns the whole trajectory."""

    config: ContinualDemoDataParserConfig

    def _scene_folder(self) -> Path:
        c = self.config
        return c.data / f"{c.scene}_{c.width}x{c.height}_{c.num_frames}frames_fov{c.fov_degrees:g}_seed{c.seed}"

    def _focal(self) -> float:
        return self.config.width / 2 / np.tan(np.deg2rad(self.config.fov_degrees) / 2)

    def _scene_and_poses(self) -> Tuple[demo_scene.Scene, np.ndarray, Optional[np.ndarray]]:
        """The scene, the camera-to-world matrices of its images in capture order, and their capture instants
        (None when there is one image per instant)."""
        rng = np.random.default_rng(self.config.seed)
        if self.config.scene == "street":
            scene = demo_street.street(rng)
            poses, instants = demo_street.rig_path(self.config.num_frames, rng)
            return scene, poses, instants
        scene = demo_scene.room(rng)
        return scene, demo_scene.camera_path(self.config.num_frames, rng), None

    def _render_scene(self, folder: Path, poses: np.ndarray, scene: demo_scene.Scene) -> None:
        """Render every frame into a temporary folder, then rename it into place."""
        c = self.config
        partial = folder.with_name(f"{folder.name}.partial-{os.getpid()}")
        shutil.rmtree(partial, ignore_errors=True)
        (partial / "images").mkdir(parents=True)
        focal = self._focal()
        frames = []
        for i, c2w in enumerate(poses):
            image = demo_scene.render_view(c2w, focal, focal, c.width / 2, c.height / 2, c.width, c.height, scene)
            Image.fromarray(image).save(partial / "images" / f"frame_{i:05d}.png")
            frames.append(
                {"file_path": f"images/frame_{i:05d}.png", "transform_matrix": np.vstack([c2w, [0, 0, 0, 1]]).tolist()}
            )
        transforms = {"fl_x": focal, "fl_y": focal, "cx": c.width / 2, "cy": c.height / 2, "w": c.width, "h": c.height}
        (partial / "transforms.json").write_text(json.dumps({**transforms, "frames": frames}, indent=1))
        if folder.exists():
            shutil.rmtree(partial)
        else:
            os.replace(partial, folder)

    def _generate_dataparser_outputs(self, split: str = "train", **kwargs) -> DataparserOutputs:
        c = self.config
        scene, poses, instants = self._scene_and_poses()
        folder = self._scene_folder()
        if not (folder / "transforms.json").exists():
            self._render_scene(folder, poses, scene)
        centre = (scene.lo + scene.hi) / 2
        scale = 2.0 / float((scene.hi - scene.lo).max())  # the scene's longest side spans nerfstudio's [-1, 1] box
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
        return DataparserOutputs(
            image_filenames=[folder / "images" / f"frame_{i:05d}.png" for i in range(len(poses))],
            cameras=cameras,
            scene_box=SceneBox(aabb=torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])),
            dataparser_transform=transform,
            dataparser_scale=scale,
            metadata={} if instants is None else {"time_group": torch.from_numpy(instants).long()},
        )
