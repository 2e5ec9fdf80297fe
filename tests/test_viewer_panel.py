"""What the viewer and the log show, checked without a browser: the framing view, the frustum size, the panel's texts
and pictures, the streaming default, no ETA where no end is known."""

from __future__ import annotations

import base64
import io
import re

import numpy as np
import pytest
import torch
from helpers import demo_parser, tiny_config
from matplotlib.backends.backend_agg import FigureCanvasAgg
from nerfstudio.cameras.cameras import Cameras
from nerfstudio.utils.writer import EventName
from PIL import Image

from continual_nerf.core.continual_pipeline import ContinualStatus
from continual_nerf.method_configs import continual_ngp, continual_ngp_stream
from continual_nerf.nerfstudio_compat import VISER_NERFSTUDIO_SCALE_RATIO
from continual_nerf.viewer.continual_panel import PICTURES, accuracy_rows, mean_psnr_text, task_text
from continual_nerf.viewer.pictures import (
    CSS_DPI,
    DEPTH_ALT,
    DISPLAY_WIDTH,
    PANEL_DPI,
    accuracy_figure,
    accuracy_markdown,
    legend_markdown,
)
from continual_nerf.viewer.task_cameras import camera_positions, framing_view, frustum_scale


class Trajectory:
    """Just what the framing reads of a dataset: cameras along x, looking along +y, z up; two tasks far apart."""

    def __init__(self, xs) -> None:
        poses = torch.zeros(len(xs), 3, 4)
        # OpenGL camera axes in world coordinates: x right, y up (world z), z backwards (world -y)
        poses[:, :, 0] = torch.tensor([1.0, 0.0, 0.0])
        poses[:, :, 1] = torch.tensor([0.0, 0.0, 1.0])
        poses[:, :, 2] = torch.tensor([0.0, -1.0, 0.0])
        poses[:, 0, 3] = torch.as_tensor(xs, dtype=torch.float32)
        self.cameras = Cameras(camera_to_worlds=poses, fx=10.0, fy=10.0, cx=8.0, cy=6.0, width=16, height=12)

    def __len__(self) -> int:
        return len(self.cameras)


def in_view(position: np.ndarray, look_at: np.ndarray, points: np.ndarray, fov: float) -> bool:
    axis = (look_at - position) / np.linalg.norm(look_at - position)
    rays = (points - position) / np.linalg.norm(points - position, axis=1, keepdims=True)
    return bool((np.degrees(np.arccos(np.clip(rays @ axis, -1, 1))) < np.degrees(fov) / 2).all())


@pytest.mark.parametrize("frames", [range(10), range(5), range(5, 10)])
def test_the_framing_view_has_the_framed_cameras_in_its_field_of_view_from_above_and_behind(frames):
    trajectory = Trajectory(list(np.linspace(-1, 0, 5)) + list(np.linspace(6, 7, 5)))  # a streaming run's far task
    view = framing_view(trajectory, frames, fov=1.0)
    positions = camera_positions(trajectory, frames)
    assert in_view(view.position, view.look_at, positions, fov=1.0)
    assert np.allclose(view.up, [0, 0, 1]) and view.position[2] > positions[:, 2].max(), "from above"
    assert view.position[1] < positions[:, 1].min(), "from behind the cameras, which look along +y"
    if frames == range(5, 10):
        assert not in_view(view.position, view.look_at, camera_positions(trajectory, range(1)), fov=0.5)


def test_frustums_are_sized_by_the_trajectory():
    short, long = Trajectory([0.0, 1.0]), Trajectory([0.0, 10.0])
    assert frustum_scale(long) == pytest.approx(10 * frustum_scale(short))
    assert frustum_scale(short) == pytest.approx(0.04 * VISER_NERFSTUDIO_SCALE_RATIO)


def png_of(markdown: str) -> Image.Image:
    data = re.fullmatch(r"!\[[^]]*\]\(data:image/png;base64,([^)]*)\)", markdown)
    assert data, markdown[:80]
    return Image.open(io.BytesIO(base64.b64decode(data.group(1))))


def test_the_pictures_are_pngs_in_markdown_as_wide_as_the_panel_shows_them():
    png_width = DISPLAY_WIDTH * PANEL_DPI // CSS_DPI
    assert png_of(legend_markdown(12)).size[0] == png_width
    picture = png_of(accuracy_markdown([[20.0], [19.0, 22.5], [18.0, 21.0, 25.0]], 5))
    assert picture.size[0] == png_width and picture.size[1] < 1.5 * png_width


@pytest.mark.parametrize("num_tasks", [2, 5, 9, 12])
def test_the_accuracy_picture_writes_readable_values_that_fit_their_cells_and_names_the_unit(num_tasks):
    figure = accuracy_figure([[20.0 + i + j for j in range(i + 1)] for i in range(num_tasks)], num_tasks)
    renderer = FigureCanvasAgg(figure).get_renderer()
    figure.draw(renderer)
    css_pixels = DISPLAY_WIDTH / (figure.get_figwidth() * figure.dpi)  # per figure pixel, as the panel shows it
    matrix, colour_bar = figure.axes
    column = matrix.get_window_extent(renderer).width / num_tasks * css_pixels
    values = matrix.texts
    assert len(values) == (num_tasks * (num_tasks + 1) // 2 if num_tasks <= 9 else 0), "written while they fit"
    for value in values:
        assert value.get_fontsize() / 72 * figure.dpi * css_pixels >= 13, "a font whose digits are 9 px high or more"
        assert value.get_window_extent(renderer).width * css_pixels < column, value.get_text()
    assert "(dB)" in colour_bar.get_xlabel()


def test_the_accuracy_picture_switches_to_depth_errors_where_there_are_some():
    with_depth = ContinualStatus(1, 3, False, "", [[20.0], [19.0, 22.0]], [20.0, 20.5], False, [[0.1], [0.12, None]])
    assert accuracy_rows(with_depth, PICTURES[0]) == ([[20.0], [19.0, 22.0]], False)
    assert accuracy_rows(with_depth, PICTURES[1]) == ([[0.1], [0.12, None]], True)
    without = ContinualStatus(1, 3, False, "", [[20.0]], [20.0], False)
    assert accuracy_rows(without, PICTURES[1]) == ([[20.0]], False), "a capture without depth keeps PSNR"
    picture = accuracy_markdown(with_depth.depth_rows, 3, depth=True)
    assert picture.startswith(f"![{DEPTH_ALT}]") and png_of(picture).size[0] == DISPLAY_WIDTH * PANEL_DPI // CSS_DPI
    colour_bar = accuracy_figure(with_depth.depth_rows, 3, depth=True).axes[1]
    assert colour_bar.get_xlabel() == "depth abs rel"


def test_panel_texts():
    status = ContinualStatus(1, 3, True, "", [[20.0]], [20.0], False)
    assert task_text(status) == "2 of 3+ (capture running)"
    assert mean_psnr_text([]) == "measured when task 1 ends"
    assert mean_psnr_text([20.0, 21.234]) == "21.23 dB after task 2"


def test_streaming_follows_the_newest_task_by_default():
    assert continual_ngp_stream.config.viewer.follow_newest_task
    assert not continual_ngp.config.viewer.follow_newest_task


def test_no_eta_when_the_run_has_no_known_end(tmp_path):
    config = tiny_config(tmp_path / "outputs", demo_parser(), num_tasks=2)
    config.pipeline.datamanager.seconds_per_task = 1.0
    trainer = config.setup(local_rank=0, world_size=1)
    trainer.setup()
    assert EventName.ETA not in config.logging.local_writer.stats_to_track
