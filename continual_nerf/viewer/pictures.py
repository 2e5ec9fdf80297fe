"""The panel's pictures, drawn with matplotlib and shown as markdown images: the task colours' legend and the
accuracy matrix. Figures are built without pyplot, so drawing from the viewer's threads touches no global state.

The panel shows a picture DISPLAY_WIDTH CSS pixels wide (viser's panel at its default width): drawn that wide at
CSS_DPI, a font of n points shows n * CSS_DPI / 72 CSS pixels high; the PNG has PANEL_DPI / CSS_DPI pixels per CSS
pixel, sharp on high-density screens too.
"""

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
DISPLAY_WIDTH = 240
"""CSS pixels the panel shows its pictures at."""
CSS_DPI = 100
"""Figure inches to CSS pixels: the figures are DISPLAY_WIDTH / CSS_DPI inches wide."""
PANEL_DPI = 200
"""Pixels per inch of the PNGs: two pixels per CSS pixel."""
VALUE_POINTS = 10.0
"""Font size of the accuracy values in the cells: about 14 CSS pixels, digits about 10 pixels high."""
LABEL_POINTS = 9.0
"""Font size of the axes' labels, ticks and the legend's numbers."""
PSNR_LABEL = "test PSNR (dB)"
"""Label of the accuracy picture's colour bar."""
DEPTH_LABEL = "depth abs rel"
"""Label of the depth picture's colour bar."""


def png_markdown(figure: Figure, alt: str) -> str:
    """`figure` as a markdown image holding its PNG (a data URL: nothing to serve, nothing to fetch)."""
    buffer = io.BytesIO()
    figure.savefig(buffer, format="png", dpi=PANEL_DPI, facecolor="white")
    return f"![{alt}](data:image/png;base64,{base64.b64encode(buffer.getvalue()).decode('ascii')})"


def legend_markdown(num_tasks: int) -> str:
    """One coloured square per task, numbered: the colours of the frustums and of the accuracy picture's columns."""
    columns = min(num_tasks, 10)
    rows = -(-num_tasks // columns)
    figure = Figure(figsize=(DISPLAY_WIDTH / CSS_DPI, 0.3 * rows + 0.1), dpi=CSS_DPI)
    axes = figure.add_axes((0, 0, 1, 1))
    for task in range(num_tasks):
        x, y = task % columns, rows - 1 - task // columns
        axes.add_patch(Rectangle((x + 0.05, y + 0.15), 0.4, 0.7, color=task_colour_float(task)))
        axes.text(x + 0.5, y + 0.5, str(task + 1), va="center", fontsize=LABEL_POINTS)
    axes.set_xlim(0, columns + 0.3)  # room for the last column's two-digit number
    axes.set_ylim(0, rows)
    axes.axis("off")
    return png_markdown(figure, "task colours")


def value_format(num_tasks: int, depth: bool = False) -> Optional[str]:
    """How the cells' values are written at the panel's width: with decimals, in whole dB, or not at all (the colour
    bar reads them) once the tasks' columns are too narrow."""
    if num_tasks <= 5:
        return "{:.2f}" if depth else "{:.1f}"
    return None if depth or num_tasks > 9 else "{:.0f}"


def accuracy_figure(psnr: Sequence[Sequence[Optional[float]]], num_tasks: int, depth: bool = False) -> Figure:
    """The accuracy matrix so far as a heat map: test PSNR of task j (columns) after training task i (rows), the
    tasks' numbers on top and the colour bar, in dB, below; with `depth`, the rendered depth's absolute relative
    error instead (darker is better)."""
    figure = Figure(figsize=(DISPLAY_WIDTH / CSS_DPI, 1.3 + 0.3 * max(len(psnr), 2)), dpi=CSS_DPI, layout="constrained")
    axes = figure.add_subplot()
    axes.xaxis.tick_top()  # before drawing, which colours the visible task numbers
    axes.xaxis.set_label_position("top")
    colour_map = "viridis_r" if depth else "viridis"
    image = draw_accuracy_matrix(axes, psnr, num_tasks, value_format(num_tasks, depth), VALUE_POINTS, colour_map)
    axes.tick_params(labelsize=LABEL_POINTS)
    axes.xaxis.label.set_fontsize(LABEL_POINTS)
    axes.yaxis.label.set_fontsize(LABEL_POINTS)
    colour_bar = figure.colorbar(image, ax=axes, location="bottom", fraction=0.08, pad=0.03, aspect=30)
    colour_bar.set_label(DEPTH_LABEL if depth else PSNR_LABEL, fontsize=LABEL_POINTS)
    colour_bar.ax.tick_params(labelsize=LABEL_POINTS)
    return figure


def accuracy_markdown(psnr: Sequence[Sequence[Optional[float]]], num_tasks: int, depth: bool = False) -> str:
    """The accuracy picture (`accuracy_figure`) as a markdown image."""
    return png_markdown(accuracy_figure(psnr, num_tasks, depth), DEPTH_ALT if depth else ACCURACY_ALT)
