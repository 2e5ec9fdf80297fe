"""The change guard: a replayed ray is skipped when an open-task frame sees the point it ends at in a cell whose colour
differs from what the replay oracle renders there, unless that point is hidden behind the oracle's surface; such a
cell counts only where an earlier frame saw its surface in another colour."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
import torch
from helpers import demo_parser, tiny_config

from continual_nerf.core import change_guard
from continual_nerf.core.change_guard import (
    OpenTaskView,
    Pinholes,
    cell_grid,
    open_task_view,
    pixels_of_cells,
    seen_otherwise,
)
from continual_nerf.core.continual_datamanager import ContinualDataManager
from continual_nerf.core.continual_pipeline import ContinualPipelineConfig
from continual_nerf.errors import ContinualConfigError
from continual_nerf.recipes import set_up_like_ns_train


def one_camera_view() -> OpenTaskView:
    """A 10x10 pinhole camera at the origin looking down -z, every cell's surface 5 away, its left half changed."""
    changed = torch.zeros(10, 10, dtype=torch.bool)
    changed[:, :5] = True
    return OpenTaskView(
        task=0,
        cameras=Pinholes(
            frames=torch.tensor([0]),
            rotations=torch.eye(3)[None],
            centres=torch.zeros(1, 3),
            intrinsics=torch.tensor([[10.0, 10.0, 5.0, 5.0]]),
            sizes=torch.tensor([[10.0, 10.0]]),
        ),
        strides=torch.tensor([1]),
        grid_widths=torch.tensor([10]),
        cell_offsets=torch.tensor([0]),
        distances=torch.full((100,), 5.0),
        changed=changed.reshape(-1),
        changed_pixels=torch.nonzero(changed.reshape(-1)).view(-1),
    )


def test_a_point_seen_in_a_changed_cell_is_observed_changed_and_a_hidden_or_unseen_one_is_not():
    points = torch.tensor(
        [
            [-1.0, 0.0, -4.0],  # in front of the surface, in a changed cell
            [-1.0, 0.0, -8.0],  # the same cell, behind the surface the oracle renders there
            [1.0, 0.0, -4.0],  # an unchanged cell
            [-1.0, 0.0, 4.0],  # behind the camera
            [-10.0, 0.0, -1.0],  # outside the image
        ]
    )
    assert one_camera_view().observed_changed(points).tolist() == [True, False, False, False, False]


def test_a_frames_cells_cover_it_with_at_most_the_maximum_number_of_cells():
    stride, rows, columns = cell_grid(640, 480)
    assert len(rows) * len(columns) <= 1024 and stride == 18 and rows[0] == columns[0] == 9
    assert cell_grid(24, 18)[0] == 1, "a small frame: every pixel a cell"


def test_cells_whose_pixels_differ_from_the_render_are_the_changed_ones(tmp_path, monkeypatch):
    monkeypatch.setattr(change_guard, "seen_otherwise", lambda points, *_: torch.ones(len(points), dtype=torch.bool))
    config = tiny_config(tmp_path, demo_parser(num_frames=8), num_tasks=2).pipeline.datamanager
    manager = config.setup(device="cpu")
    assert isinstance(manager, ContinualDataManager)
    dataset = manager.train_dataset
    dataset.open(1)
    start, _ = dataset.open_task_pixel_range()
    assert dataset.task_pixels is not None
    pixels = dataset.task_pixels

    def render(indices: torch.Tensor):
        """The open task's own pixels, but every pixel of the frame's left third repainted."""
        flat = dataset.pixel_offsets[indices[:, 0]] + indices[:, 1] * 24 + indices[:, 2]
        rgb = pixels[flat - start].clone()
        rgb[indices[:, 2] < 8] = torch.tensor([1.0, 0.0, 1.0])
        return rgb, torch.full((len(indices),), 2.0)

    def rays_of(indices: torch.Tensor):
        return SimpleNamespace(
            origins=torch.zeros(len(indices), 3), directions=torch.zeros(len(indices), 3), at=indices
        )

    earlier = dataset.frames_of_task(0)
    view = open_task_view(1, dataset, rays_of, lambda rays: render(rays.at), 0.1, 100, earlier)  # type: ignore
    frames = dataset.frames_of_task(1)
    assert view.task == 1 and len(view.cameras.centres) == len(frames) and len(view.changed) == len(frames) * 24 * 18
    columns = torch.arange(24).repeat(18 * len(frames))
    difference = (pixels.view(len(frames), 18, 24, 3)[..., :8, :] - torch.tensor([1.0, 0.0, 1.0])).abs().mean(-1)
    expected = np.zeros((len(frames), 18, 24), dtype=bool)
    expected[..., :8] = (difference > 0.1).numpy()
    assert bool(view.changed[columns >= 8].logical_not().all()), "the rest renders as the frames show it"
    assert torch.equal(view.changed, torch.from_numpy(expected.reshape(-1))), "the left third, where the paint differs"
    assert torch.equal(view.distances, torch.full_like(view.distances, 2.0))
    changed_flat = start + torch.nonzero(torch.from_numpy(expected.reshape(-1))).view(-1)
    assert torch.equal(view.changed_pixels.sort().values, changed_flat), "one pixel per cell: the changed ones"


def pinhole_rays(cameras: Pinholes, cells: torch.Tensor) -> SimpleNamespace:
    """Rays through the centres of pixels `cells` ((N, 3) frame, y, x) of unrotated pinhole `cameras`."""
    fx, fy, cx, cy = cameras.intrinsics[cells[:, 0]].unbind(-1)
    x, y = cells[:, 2] + 0.5, cells[:, 1] + 0.5
    directions = torch.stack([(x - cx) / fx, -(y - cy) / fy, -torch.ones_like(fx)], dim=-1)
    return SimpleNamespace(
        origins=cameras.centres[cells[:, 0]], directions=directions / directions.norm(dim=-1)[:, None]
    )


def test_a_candidate_is_a_change_only_where_the_finest_earlier_frame_saw_its_surface_otherwise():
    """Two earlier 10x10 cameras looking down -z at a wall at z = -5, from z = 0 and from z = 2 (pixels of 0.5 and 0.7
    there); the oracle renders the wall red on the left half from the nearer one, blue everywhere from the farther."""
    cameras = Pinholes(
        frames=torch.tensor([0, 1]),
        rotations=torch.eye(3).expand(2, 3, 3),
        centres=torch.tensor([[0.0, 0.0, 0.0], [0.0, 0.0, 2.0]]),
        intrinsics=torch.tensor([[10.0, 10.0, 5.0, 5.0]]).expand(2, 4),
        sizes=torch.tensor([[10.0, 10.0]]).expand(2, 2),
    )
    red, blue = torch.tensor([1.0, 0.0, 0.0]), torch.tensor([0.0, 0.0, 1.0])

    def render(rays: SimpleNamespace):
        distance = (rays.origins[:, 2] + 5) / -rays.directions[:, 2]
        left = (rays.origins[:, 2] == 0) & (rays.directions[:, 0] < 0)
        return torch.where(left[:, None], red, blue), distance

    points = torch.tensor(
        [
            [-1.0, 0.0, -5.0],  # on the wall, red from the nearer camera: the open task's blue is a change
            [-1.0, 0.0, -5.0],  # the same, but the open task sees it red as the earlier frame did
            [1.0, 0.0, -5.0],  # the right half: blue from both
            [-1.0, 0.0, -8.0],  # behind the wall: no earlier frame saw it
            [-30.0, 0.0, -5.0],  # outside both images: new ground
            [-1.0, 0.0, -5.0],  # the first, but the open task's pixel there is 0.2: detail the earlier frames missed
        ]
    )
    colours = torch.stack([blue, red, blue, blue, blue, blue])
    footprints = torch.tensor([0.5, 0.5, 0.5, 0.5, 0.5, 0.2])
    rays = lambda cells: pinhole_rays(cameras, cells)  # noqa: E731
    found = seen_otherwise(points, colours, footprints, cameras, rays, render, 0.1, 2)  # type: ignore
    assert found.tolist() == [True, False, False, False, False, False]
    assert len(seen_otherwise(points[:0], colours[:0], footprints[:0], cameras, rays, render, 0.1, 2)) == 0  # type: ignore


def test_a_changed_cells_pixels_are_its_whole_block_inside_its_frame():
    frames = SimpleNamespace(width=torch.tensor([[10], [10]]), height=torch.tensor([[7], [7]]))
    dataset = SimpleNamespace(cameras=frames, pixel_offsets=torch.tensor([0, 70]), valid_pixels=None)
    cells = torch.tensor([[1, 4, 4], [0, 6, 9]])  # centres of a 3x3 cell of frame 2, and a cell at frame 1's corner
    pixels = pixels_of_cells(dataset, cells, torch.tensor([3, 3]))  # type: ignore[arg-type]
    block = [70 + y * 10 + x for y in range(3, 6) for x in range(3, 6)]
    assert sorted(pixels.tolist()) == sorted([*block, 6 * 10 + 9]), "the corner cell clipped to the frame's pixel"
    assert len(pixels_of_cells(dataset, cells[:0], torch.tensor([], dtype=torch.long))) == 0  # type: ignore[arg-type]


def test_a_ray_crossing_what_a_frame_sees_changed_is_skipped_though_its_end_is_not_seen():
    view = one_camera_view()
    # from beside the camera, through (-1, 0, -4) (a changed cell, before its surface), to an end no cell sees
    origin, end = torch.tensor([[-3.0, 0.0, -4.0]]), torch.tensor([[1.0, 0.0, -4.0]])
    direction = (end - origin) / (end - origin).norm()
    assert not view.observed_changed(end).item()
    assert view.crosses_change(origin, direction, (end - origin).norm(dim=-1)).item()
    assert not view.crosses_change(end, torch.tensor([[0.0, 1.0, 0.0]]), torch.tensor([1.0])).item()


def test_the_every_task_guard_waits_for_the_first_oracle(tmp_path):
    config = tiny_config(tmp_path, demo_parser(num_frames=8), num_tasks=2)
    config.pipeline.change_guard = "every-task"
    pipeline = set_up_like_ns_train(config).pipeline
    assert not pipeline.guards_replay, "the first task has nothing to replay and no oracle to render its frames"
    pipeline.get_train_loss_dict(0)  # a quarter of its rays would be drawn from changes the oracle found
    pipeline.open_next_task()
    assert pipeline.guards_replay


@pytest.mark.parametrize("share", [-0.1, 1.0])
def test_a_change_emphasis_outside_its_range_is_one_line(share):
    with pytest.raises(ContinualConfigError, match=rf"^--pipeline.change-emphasis must be in \[0, 1\), got {share}$"):
        ContinualPipelineConfig(change_emphasis=share).validate()
