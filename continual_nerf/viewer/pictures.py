"""The panel's pictures, drawn with matplotlib and shown as markdown images: the task colours' legend and the
accuracy matrix. Figures are built without pyplot, so drawing from the viewer's threads touches no global state."""

from __future__ import annotations

import base64
import io
from typing import Optional, Sequence

from matplotlib.figure import Figure
from matplotlib.patches import Rectangle

from continual_nerf.plots import draw_accuracy_matrix, task_colour_float

ACCURACY_ALT = "accuracy matrix, PSNR (dB)"
"""Alt text of the accuracy picture (what a browser shows when it cannot draw it)."""
DEPTH_ALT = "accuracy matrix, depth abs rel"
"""Alt text of the accuracy picture of the rendered depth's error."""
PANEL_DPI = 100
"""Pixels per inch of the pictures: the panel is about 300 pixels wide."""


def png_markdown(figure: Figure, alt: str) -> str:
    """`figure` as a markdown image holding its PNG (a data URL: nothing to serve, nothing to fetch)."""
    buffer = io.BytesIO()
    figure.savefig(buffer, format="png", dpi=PANEL_DPI, facecolor="white")
    return f"![{alt}](data:image/png;base64,{base64.b64encode(buffer.getvalue()).decode('ascii')})"


def legend_markdown(num_tasks: int) -> str:
    """One coloured square per task, numbered: the colours of the frustums and of the accuracy picture's columns."""
    columns = min(num_tasks, 10)
    rows = -(-num_tasks // columns)
    figure = Figure(figsize=(3.0, 0.3 * rows + 0.1))
    axes = figure.add_axes((0, 0, 1, 1))
    for task in range(num_tasks):
        x, y = task % columns, rows - 1 - task // columns
        axes.add_patch(Rectangle((x + 0.05, y + 0.15), 0.4, 0.7, color=task_colour_float(task)))
        axes.text(x + 0.5, y + 0.5, str(task + 1), va="center", fontsize=8)
    axes.set_xlim(0, columns)
    axes.set_ylim(0, rows)
    axes.axis("off")
    return png_markdown(figure, "task colours")


def accuracy_markdown(psnr: Sequence[Sequence[Optional[float]]], num_tasks: int, depth: bool = False) -> str:
    """The accuracy matrix so far as a heat map: test PSNR of task j (columns) after training task i (rows); with
    `depth`, the rendered depth's absolute relative error instead (darker is better)."""
    figure = Figure(figsize=(3.0, 0.9 + 0.25 * max(len(psnr), 2)), layout="constrained")
    axes = figure.add_subplot()
    measure = {"value_format": ".3f", "colour_map": "viridis_r"} if depth else {}
    image = draw_accuracy_matrix(axes, psnr, num_tasks, **measure)
    axes.tick_params(labelsize=7)
    axes.xaxis.label.set_fontsize(7)
    axes.yaxis.label.set_fontsize(7)
    figure.colorbar(image, ax=axes, fraction=0.05, pad=0.02).ax.tick_params(labelsize=6)
    return png_markdown(figure, DEPTH_ALT if depth else ACCURACY_ALT)
