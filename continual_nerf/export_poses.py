"""`continual-nerf-export-poses`: a continual run's trajectory with the poses it refined, as nerfstudio's
transforms.json, to compare with the capture's own poses or to train on again.

    continual-nerf-export-poses --load-config outputs/<experiment>/continual-ngp/<timestamp>/config.yml \\
        --output-dir refined

Every frame of the trajectory is written in capture order, in the capture's own (metric) coordinates (for a run
continued on later captures: every session's frames, in the first session's world coordinates): a training frame with
its pose correction, a test frame with the correction of the training frame it is evaluated with (the
nearest one of its task and camera). A run without pose refinement writes the poses the dataparser returned.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Dict, List

import numpy as np
import torch
import tyro
from nerfstudio.cameras.cameras import CameraType
from nerfstudio.models.nerfacto import NerfactoModel
from nerfstudio.utils.eval_utils import eval_setup
from nerfstudio.utils.rich_utils import CONSOLE

from continual_nerf.atomic_files import write_text_atomically
from continual_nerf.core.continual_datamanager import ContinualDataManager
from continual_nerf.core.per_frame import TRAINING_FRAME, refined_poses
from continual_nerf.dataparsers.transforms_json import CAMERA_MODEL_OF_TYPE, DISTORTION_KEYS
from continual_nerf.metadata_keys import FISHEYE_CROP_RADIUS, HELD_OUT
from continual_nerf.nerfstudio_compat import without_lpips


def trajectory_poses(datamanager: ContinualDataManager, model: NerfactoModel) -> torch.Tensor:
    """(N, 3, 4) camera-to-world matrices of every frame in capture order, in the dataparser's box, refined."""
    split = datamanager.task_split
    train_cameras, test_cameras = datamanager.train_dataset.cameras, datamanager.eval_dataset.cameras
    assert test_cameras.metadata is not None, "test frames know their nearest training frame"
    poses = torch.zeros((len(datamanager.train_dataparser_outputs.image_filenames), 3, 4))
    train_frames = torch.arange(len(train_cameras))
    poses[split.all_train_frames()] = refined_poses(model.camera_optimizer, train_cameras, train_frames)
    nearest = test_cameras.metadata[TRAINING_FRAME].view(-1)
    poses[split.all_test_frames()] = refined_poses(model.camera_optimizer, test_cameras, nearest)
    return poses


def transforms_json(datamanager: ContinualDataManager, model: NerfactoModel) -> Dict[str, Any]:
    """nerfstudio's transforms.json of the trajectory: per frame its image, refined pose, intrinsics and mask; the
    fisheye frames' crop radius and the frames named for testing for the whole file, as the capture's gave them."""
    outputs = datamanager.train_dataparser_outputs
    poses = outputs.transform_poses_to_original_space(trajectory_poses(datamanager, model), camera_convention="opengl")
    cameras = outputs.cameras
    models = [CAMERA_MODEL_OF_TYPE[CameraType(kind)] for kind in cameras.camera_type.view(-1).tolist()]
    frames: List[Dict[str, Any]] = []
    for index, filename in enumerate(outputs.image_filenames):
        camera_to_world = np.eye(4)
        camera_to_world[:3] = poses[index].double().numpy()
        frame = {
            "file_path": str(Path(filename).resolve()),
            "transform_matrix": camera_to_world.tolist(),
            "fl_x": float(cameras.fx[index]),
            "fl_y": float(cameras.fy[index]),
            "cx": float(cameras.cx[index]),
            "cy": float(cameras.cy[index]),
            "w": int(cameras.width[index]),
            "h": int(cameras.height[index]),
        }
        if len(set(models)) > 1:  # nerfstudio reads the file's camera_model only; continual-nerfstudio a frame's too
            frame["camera_model"] = models[index]
        if cameras.distortion_params is not None:
            distortion = cameras.distortion_params[index].tolist()
            if len(distortion) == len(DISTORTION_KEYS):
                frame.update(zip(DISTORTION_KEYS, distortion))
            else:  # FISHEYE624's 12 parameters
                frame["distortion_params"] = distortion
        mask = None if outputs.mask_filenames is None else outputs.mask_filenames[index]
        if mask is not None:  # an earlier session's frame keeps its mask in the run's record, not in a file
            frame["mask_path"] = str(Path(mask).resolve())
        frames.append(frame)
    meta: Dict[str, Any] = {"camera_model": models[0], "frames": frames}
    radii = outputs.metadata.get(FISHEYE_CROP_RADIUS)
    if radii is not None:  # one file-wide value, kept by the fisheye frames only (inf on the others)
        meta[FISHEYE_CROP_RADIUS] = float(radii[torch.isfinite(radii)][0])
    held_out = outputs.metadata.get(HELD_OUT)
    if held_out is not None:  # the frames the capture named for testing stay test frames when trained on again
        meta["test_filenames"] = [frame["file_path"] for frame, tested in zip(frames, held_out.tolist()) if tested]
    return meta


@dataclass
class ExportPoses:
    """Write a continual run's poses, refined where the run refined them, as a transforms.json in capture order."""

    load_config: Path
    """The run's config.yml (its latest checkpoint is read)."""
    output_dir: Path = Path("refined-poses")
    """Folder the transforms.json is written to; its file paths point at the capture's images."""

    def main(self) -> None:
        with without_lpips():  # nerfacto-family models build LPIPS at set-up, which would download weights
            _, pipeline, _, _ = eval_setup(self.load_config, test_mode="test")
        datamanager, model = pipeline.datamanager, pipeline.model
        if not (isinstance(datamanager, ContinualDataManager) and isinstance(model, NerfactoModel)):
            raise SystemExit(
                f"continual-nerf-export-poses: {self.load_config} is not a run of a hash-grid continual method"
            )
        path = self.output_dir / "transforms.json"
        write_text_atomically(path, json.dumps(transforms_json(datamanager, model), indent=1))
        refined = "refined poses" if model.camera_optimizer.config.mode != "off" else "poses (the run refined none)"
        CONSOLE.print(
            f"[bold green]{len(datamanager.train_dataparser_outputs.image_filenames)} frames' {refined}: {path}"
        )


def entrypoint() -> None:
    tyro.cli(ExportPoses).main()


if __name__ == "__main__":
    entrypoint()
