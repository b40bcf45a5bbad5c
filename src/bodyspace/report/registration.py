"""The picture of a registration: the scan's points coloured by their distance to the fit."""

from __future__ import annotations

import os
import textwrap
from pathlib import Path

import matplotlib
import numpy as np
from matplotlib import cm, colors

from bodyspace.report.render import new_figure, save_png

__all__ = ["distance_figure", "MAX_SHOWN_MM"]

# Distances are coloured from 0 to this many millimetres (beyond: the last colour).
MAX_SHOWN_MM = 10.0


def distance_figure(points: np.ndarray, distance: np.ndarray, path: str | os.PathLike, *,
                    title: str = "", dpi: float = 110) -> Path:
    """Front and back views of scan points (P, 3) (metres, +Y up, +Z front) coloured by their
    distance (P,) metres to the registered surface; points drawn far to near so the nearest
    show. Writes the PNG at ``path`` and returns it."""
    p = np.asarray(points, dtype=float)
    d = np.asarray(distance, dtype=float) * 1000.0
    fig = new_figure(9.0, 8.0, dpi)
    norm = colors.Normalize(0.0, MAX_SHOWN_MM)
    cmap = matplotlib.colormaps["viridis"]
    lines = textwrap.fill(title, 110).splitlines() if title else []
    top = 0.92 - 0.022 * max(0, len(lines) - 1)         # the views start below every title line
    for k, (view, sign) in enumerate((("front", 1.0), ("back", -1.0))):
        ax = fig.add_axes([0.02 + 0.44 * k, 0.06, 0.42, top - 0.06])
        order = np.argsort(sign * p[:, 2])          # far first
        ax.scatter(sign * p[order, 0], p[order, 1], c=d[order], s=1.5, cmap=cmap, norm=norm, linewidths=0)
        ax.set_aspect("equal")
        ax.set_axis_off()
        ax.set_title(view, fontsize=10)
    cax = fig.add_axes([0.90, 0.15, 0.02, 0.7])
    bar = fig.colorbar(cm.ScalarMappable(norm=norm, cmap=cmap), cax=cax)
    bar.set_label("distance to the fit (mm)")
    if lines:
        fig.suptitle("\n".join(lines), fontsize=9)
    return save_png(fig, path, dpi)
