"""Per-frame parameters in the continual setting: appearance codes and pose corrections.

A frame's appearance code and pose correction are learned while its task is open and stay bit-identical once it has
closed. Rays of closed tasks are rendered with them (by the model and by the replay oracle alike), and a test frame is
rendered with those of the training frame of its task and camera nearest to it in time.
"""

from __future__ import annotations

from typing import Literal, Sequence

import torch
from nerfstudio.cameras.camera_optimizers import CameraOptimizer
from nerfstudio.cameras.cameras import Cameras
from nerfstudio.cameras.rays import RayBundle
from nerfstudio.field_components.embedding import Embedding
from torch import Tensor, nn

TRAINING_FRAME = "training_frame"
"""Ray metadata: the training frame whose appearance code and refined pose a ray is rendered with outside training
(replayed rays in the oracle, test frames); training rays carry their frame as camera_indices."""
FRAME_TASK = "continual_task"
"""Training dataset metadata the model reads: the task of every training frame."""
FRAME_CAMERA = "continual_camera"
"""Training dataset metadata the model reads: which camera of a rig took every training frame."""

AppearanceGroups = Literal["image", "camera-task"]
"""What one appearance code covers: one training image, or every image one camera took in one task."""


def code_of_frame(tasks: Tensor, cameras: Tensor, groups: AppearanceGroups) -> Tensor:
    """The row of the code table each training frame looks its code up in: its own (image), or that of the first
    frame its camera took in its task (camera-task)."""
    frames = torch.arange(len(tasks))
    if groups == "image":
        return frames
    _, group = torch.unique(tasks * (int(cameras.max()) + 1) + cameras, return_inverse=True)
    first = torch.full((int(group.max()) + 1,), len(frames)).scatter_reduce(0, group, frames, reduce="amin")
    return first[group]


@torch.no_grad()
def start_from_previous_task(table: Tensor, code_of_frame: Tensor, task: int, tasks: Tensor, cameras: Tensor) -> None:
    """Start `table`'s rows of `task` at the row each camera's last frame had in the task before: the best guess of an
    exposure that drifts."""
    for camera in cameras[tasks == task].unique():
        before = torch.nonzero((tasks == task - 1) & (cameras == camera)).view(-1)
        if len(before):
            rows = code_of_frame[(tasks == task) & (cameras == camera)]
            table[rows] = table[code_of_frame[before[-1]]].clone()


class FrameCodes(Embedding):
    """nerfacto's appearance embedding looked up per training frame through `code_of_frame`; codes start at zero."""

    code_of_frame: Tensor

    def __init__(self, code_of_frame: Tensor, dim: int) -> None:
        super().__init__(len(code_of_frame), dim)
        self.register_buffer("code_of_frame", code_of_frame)
        nn.init.zeros_(self.embedding.weight)

    def forward(self, in_tensor: Tensor) -> Tensor:
        return super().forward(self.code_of_frame[in_tensor])

    def start_task(self, task: int, tasks: Tensor, cameras: Tensor) -> None:
        """Start the codes of `task` at those of the task before (`start_from_previous_task`)."""
        start_from_previous_task(self.embedding.weight, self.code_of_frame, task, tasks, cameras)


class FrameColorTransforms(nn.Module):
    """An affine colour transform of the rendered colour per training frame, looked up through `code_of_frame`.

    Exposure, white balance and a camera's gain scale each channel of the recorded value, which a 3 x 3 matrix and an
    offset express exactly (a gamma curve commutes with the scaling); the field keeps one colour per point for every
    frame. A camera response that differs by a gamma is beyond it (the codes, which the colour MLP reads, can learn it).
    """

    code_of_frame: Tensor

    def __init__(self, code_of_frame: Tensor) -> None:
        super().__init__()
        self.register_buffer("code_of_frame", code_of_frame)
        self.transforms = nn.Parameter(torch.eye(3, 4).repeat(len(code_of_frame), 1, 1))
        """(frames, 3, 4) matrix and offset of every row; rows start as the identity."""

    def forward(self, rgb: Tensor, frames: Tensor) -> Tensor:
        """`rgb` (N, 3) as training frames `frames` (N,) record it."""
        transforms = self.transforms[self.code_of_frame[frames]]
        return (transforms[:, :, :3] @ rgb[:, :, None])[:, :, 0] + transforms[:, :, 3]

    def start_task(self, task: int, tasks: Tensor, cameras: Tensor) -> None:
        """Start the transforms of `task` at those of the task before (`start_from_previous_task`)."""
        start_from_previous_task(self.transforms, self.code_of_frame, task, tasks, cameras)


class OpenTaskRows:
    """Puts every row of per-frame parameters outside the open task back to its value when the task opened.

    Masking gradients would not be enough: replayed rays send gradients to closed tasks' rows, and Adam keeps moving a
    parameter whose gradient is zero for as long as its momentum lasts. Restoring after every optimizer step keeps
    those rows bit-identical whatever the optimizer does.
    """

    def __init__(self, parameters: Sequence[Tensor], task_of_row: Tensor) -> None:
        self.parameters = parameters
        """Parameters whose first dimension is indexed by training frame."""
        self.task_of_row = task_of_row
        """Task of every row (training frame)."""
        self.closed = torch.zeros_like(task_of_row, dtype=torch.bool)
        self.saved: Sequence[Tensor] = []

    def open(self, task: int) -> None:
        """Only rows of `task` may change from now on."""
        self.closed = self.task_of_row != task
        self.saved = [parameter.detach().clone() for parameter in self.parameters]

    @torch.no_grad()
    def restore(self) -> None:
        for parameter, saved in zip(self.parameters, self.saved):
            closed = self.closed.to(parameter.device)
            parameter[closed] = saved[closed]


def refine_rays(camera_optimizer: CameraOptimizer, ray_bundle: RayBundle) -> None:
    """Move rays as the camera optimizer moves their frame's camera, as nerfacto moves training rays."""
    if camera_optimizer.config.mode == "off":
        return
    assert ray_bundle.camera_indices is not None, "rays of a training frame carry its index"
    # nerfstudio's apply_to_raybundle squeezes the indices, which fails for a single ray
    corrections = camera_optimizer(ray_bundle.camera_indices.view(-1))
    ray_bundle.origins = ray_bundle.origins + corrections[:, :3, 3]
    ray_bundle.directions = (corrections[:, :3, :3] @ ray_bundle.directions[..., None])[..., 0]


@torch.no_grad()
def refined_poses(camera_optimizer: CameraOptimizer, cameras: Cameras, frames: Tensor) -> Tensor:
    """(N, 3, 4) camera-to-world matrices of `cameras` moved by the pose corrections of training frames `frames` (N,):
    a training frame's own, or for a test frame its nearest training frame's, as the evaluation renders it."""
    poses = []
    for index, frame in enumerate(frames.tolist()):
        camera = cameras[index : index + 1]
        camera.metadata = {"cam_idx": frame}  # the training frame whose correction nerfstudio applies
        poses.append(camera_optimizer.apply_to_camera(camera)[0].cpu())
    return torch.stack(poses) if poses else torch.zeros((0, 3, 4))
