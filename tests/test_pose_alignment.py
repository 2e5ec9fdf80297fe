"""--pipeline.test-pose-alignment-steps: each test frame's pose is fitted to its image, with the field frozen, before
it is measured (the accuracy matrix and ns-eval alike), and fitting changes nothing of the training."""

from __future__ import annotations

import math
from typing import Dict

import pytest
import torch
from helpers import demo_parser, tiny_config, train
from nerfstudio.cameras.cameras import Cameras
from nerfstudio.cameras.lie_groups import exp_map_SO3xR3
from nerfstudio.cameras.rays import RayBundle
from torch import Tensor, nn

from continual_nerf.core.accuracy_matrix import ACCURACY_MATRIX_FILENAME, AccuracyMatrix
from continual_nerf.core.evaluation import AlignedEvalCameras, PoseAlignment, evaluate_frames
from continual_nerf.errors import ContinualConfigError


class ColourOfRay(nn.Module):
    """A model whose colour changes smoothly with each ray's direction and origin: a pose error shows in its render."""

    def __init__(self) -> None:
        super().__init__()
        rows = [[9.0, 3.0, -6.0, 5.0, -3.0, 2.0], [-3.0, 8.0, 3.0, 2.0, 5.0, -3.0], [3.0, -5.0, 6.0, -2.0, 2.0, 5.0]]
        self.weights = nn.Parameter(torch.tensor(rows))

    @property
    def device(self) -> torch.device:
        return self.weights.device

    def forward(self, rays: RayBundle) -> Dict[str, Tensor]:
        features = torch.cat([rays.directions, rays.origins], dim=-1)
        return {"rgb": 0.5 + 0.5 * torch.sin(features @ self.weights.T)}

    @torch.no_grad()
    def get_outputs_for_camera(self, camera: Cameras) -> Dict[str, Tensor]:
        return self(camera.generate_rays(camera_indices=0, keep_shape=True))


class FrameImages:
    """The two things evaluate_frames reads of a dataset: its cameras and each frame's image."""

    def __init__(self, cameras: Cameras, images: Tensor) -> None:
        self.cameras, self.images = cameras, images

    def get_image_float32(self, frame: int) -> Tensor:
        return self.images[frame]


def camera(pose: Tensor) -> Cameras:
    return Cameras(camera_to_worlds=pose[None], fx=40.0, fy=40.0, cx=24.0, cy=18.0, width=48, height=36)


def off_by(pose: Tensor, tangent: list) -> Tensor:
    """`pose` turned about its centre and moved as the evaluation moves a camera."""
    error = exp_map_SO3xR3(torch.tensor([tangent]))[0]
    return torch.cat([error[:, :3] @ pose[:, :3], (pose[:, 3] + error[:, 3])[:, None]], dim=1)


def frames_with_pose_errors():
    """A model, test frames rendered from true poses, and the same frames' cameras with 2 degrees and 0.05 errors."""
    model = ColourOfRay()
    true = [torch.eye(4)[:3], off_by(torch.eye(4)[:3], [0.0, 0.0, 0.0, 0.3, -0.2, 0.1])]
    images = torch.stack([model.get_outputs_for_camera(camera(pose))["rgb"] for pose in true])
    errors = [[0.03, -0.02, 0.01, 0.02, 0.0, -0.01], [-0.01, 0.01, 0.03, 0.0, 0.02, 0.01]]
    given = Cameras(
        camera_to_worlds=torch.stack([off_by(pose, error) for pose, error in zip(true, errors)]),
        fx=40.0,
        fy=40.0,
        cx=24.0,
        cy=18.0,
        width=48,
        height=36,
    )
    return model, FrameImages(given, images)


def test_a_test_frame_with_a_pose_error_is_measured_from_its_fitted_pose():
    model, frames = frames_with_pose_errors()
    as_given = evaluate_frames(model, frames, [0, 1]).psnr  # type: ignore[arg-type]
    aligned = evaluate_frames(model, frames, [0, 1], PoseAlignment(steps=150)).psnr  # type: ignore[arg-type]
    assert (as_given < 30).all(), as_given
    assert (aligned > 40).all(), aligned
    assert model.weights.grad is None, "fitting a pose must not leave gradients on the model's weights"


def test_zero_steps_measure_from_the_given_pose():
    model, frames = frames_with_pose_errors()
    as_given = evaluate_frames(model, frames, [0, 1]).psnr  # type: ignore[arg-type]
    zero = evaluate_frames(model, frames, [0, 1], PoseAlignment(steps=0)).psnr  # type: ignore[arg-type]
    assert torch.equal(as_given, zero)


def test_ns_evals_cameras_are_fitted_to_their_images():
    model, frames = frames_with_pose_errors()
    loader = [(frames.cameras[i : i + 1], {"image": frames.images[i], "image_idx": i}) for i in range(2)]
    aligned = AlignedEvalCameras(loader, model, PoseAlignment(steps=150))  # type: ignore[arg-type]
    assert len(aligned) == 2
    for (fitted, batch), index in zip(aligned, range(2)):
        rendered = model.get_outputs_for_camera(fitted)["rgb"]
        error = float(((rendered - batch["image"]) ** 2).mean())
        assert -10 * math.log10(error) > 40, index


def same(first, second) -> bool:
    return torch.equal(first, second) if isinstance(first, Tensor) else first == second


@pytest.mark.slow  # two short runs
def test_fitting_test_poses_changes_nothing_of_the_training(tmp_path, single_thread):
    runs = {}
    for steps in (0, 3):
        config = tiny_config(tmp_path / f"steps-{steps}", demo_parser())
        config.pipeline.test_pose_alignment_steps = steps
        trainer = train(config)
        matrix = AccuracyMatrix.read(config.get_base_dir() / ACCURACY_MATRIX_FILENAME)
        runs[steps] = (trainer.pipeline.model.state_dict(), matrix)
        # ns-eval measures what the accuracy matrix measures (one test frame per task here)
        assert trainer.pipeline.get_average_eval_image_metrics()["psnr"] == pytest.approx(
            matrix.mean_psnr[-1], abs=1e-3
        )
    (plain, plain_matrix), (aligned, aligned_matrix) = runs[0], runs[3]
    assert plain.keys() == aligned.keys()
    differ = [key for key in plain if not same(plain[key], aligned[key])]
    assert not differ, f"training differs with test poses fitted: {differ}"
    assert len(aligned_matrix.psnr) == len(plain_matrix.psnr) == 2
    assert aligned_matrix.psnr != plain_matrix.psnr, "the fitted poses were not the ones measured"


def test_a_negative_number_of_alignment_steps_is_a_one_line_error(run_dir):
    config = tiny_config(run_dir, demo_parser())
    config.pipeline.test_pose_alignment_steps = -1
    with pytest.raises(ContinualConfigError, match=r"--pipeline.test-pose-alignment-steps must be at least 0, got -1"):
        config.pipeline.setup(device="cpu")
