"""Pictures shared by the experiments report and the viewer: the task colours and the accuracy-matrix heat map."""

from __future__ import annotations

from typing import Optional, Sequence, Tuple

import numpy as np
from matplotlib import colormaps
from matplotlib.axes import Axes
from matplotlib.image import AxesImage


def task_colour(task: int) -> Tuple[int, int, int]:
    """RGB colour of a task (0-based) in the viewer's frustums and every picture: matplotlib's tab10, cycling."""
    red, green, blue, _ = colormaps["tab10"](task % 10)
    return int(red * 255), int(green * 255), int(blue * 255)


def task_colour_float(task: int) -> Tuple[float, float, float]:
    red, green, blue = task_colour(task)
    return red / 255, green / 255, blue / 255


def draw_accuracy_matrix(
    axes: Axes,
    psnr: Sequence[Sequence[Optional[float]]],
    num_tasks: int,
    value_format: Optional[str] = "{:.1f}",
    value_size: float = 7,
    colour_map: str = "viridis",
) -> AxesImage:
    """Heat map of R[i][j] (PSNR of task j after training task i; or another measure, coloured by `colour_map`) on
    `axes`, blank above the diagonal for unseen tasks and where a value is None, the values written in the cells in
    `value_format` (None: not written; neither beyond 12 tasks), in black on the bright end of the colour map, and the
    task numbers in the task colours."""
    matrix = np.full((max(len(psnr), 1), num_tasks), np.nan)
    for i, row in enumerate(psnr):
        matrix[i, : len(row)] = np.array(row, dtype=float)  # None: nothing measured
    image = axes.imshow(matrix, cmap=colour_map, aspect="auto")
    if value_format is not None and num_tasks <= 12:
        bright = np.asarray(image.norm(matrix)) > 0.6
        for (i, j), value in np.ndenumerate(matrix):
            if not np.isnan(value):
                colour = "black" if bright[i, j] else "white"
                axes.text(j, i, value_format.format(value), ha="center", va="center", color=colour, fontsize=value_size)
    axes.set_xticks(range(num_tasks), [str(j + 1) for j in range(num_tasks)])
    axes.set_yticks(range(len(matrix)), [str(i + 1) for i in range(len(matrix))])
    for j, label in enumerate(axes.get_xticklabels()):
        label.set_color(task_colour_float(j))
        label.set_fontweight("bold")
    axes.set_xlabel("test task j")
    axes.set_ylabel("after task i")
    return image
