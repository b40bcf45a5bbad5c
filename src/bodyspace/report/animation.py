"""Previews of an animation a person would rather look at than read: a filmstrip PNG (every
n-th frame, front and side) and an animated GIF, both headless (matplotlib Agg, Pillow).

The drawing is ``report.render``'s (orthographic, Lambert-shaded, painter's algorithm).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Callable, Sequence

import numpy as np
from PIL import Image

from bodyspace.atomic import WRITTEN_BY, atomic_path
from bodyspace.errors import ParameterError
from bodyspace.report.render import SKIN, contact_sheet, draw_mesh, new_figure, project

__all__ = ["GIF_COMMENT", "animated_gif", "filmstrip"]

# Written into every GIF's comment extension (is_own_file recognises it).
GIF_COMMENT = f"written by {WRITTEN_BY}"


def filmstrip(path: str | os.PathLike, frames: np.ndarray, faces: np.ndarray, labels: Sequence[str],
              title: str | None = None, ncols: int | None = None, views: Sequence[str] = ("front", "side"),
              panel_height: float = 2.0) -> Path:
    """A PNG of posed frames (N, V, 3) side by side, each in ``views``, on one scale with a
    height ruler (``render.contact_sheet``); ``labels`` (N,) captions; ``ncols`` per row (rows
    are e.g. one body each)."""
    return contact_sheet(np.asarray(frames), faces, path, labels=list(labels), views=tuple(views), title=title,
                         ncols=ncols, panel_height=panel_height)


def animated_gif(path: str | os.PathLike, frames: np.ndarray, faces: np.ndarray, frame_time: float,
                 view: str = "side", height_px: int = 320, title: str | None = None,
                 progress: Callable[[str, float], None] | None = None) -> Path:
    """An animated GIF of posed frames (N, V, 3) seen from ``view`` by a fixed camera framing
    every frame (the body walks across it), ``frame_time`` seconds per frame, looping; the
    floor y = 0 as a line. Written atomically; returns ``path``."""
    P = np.asarray(frames, dtype=float)
    if P.ndim != 3 or P.shape[2] != 3 or len(P) == 0:
        raise ParameterError(f"frames: shape {P.shape}, expected (N, V, 3) with at least one frame")
    if not (np.isfinite(frame_time) and frame_time > 0):
        raise ParameterError(f"frame_time: {frame_time!r}, expected a positive number of seconds")
    xy = np.concatenate([project(p, view)[0] for p in P])
    lo, hi = xy.min(axis=0), xy.max(axis=0)
    lo[1] = min(lo[1], 0.0)
    pad = 0.05 * float((hi - lo).max())
    lo, hi = lo - pad, hi + pad
    dpi = 100
    h_in = height_px / dpi
    w_in = max(h_in * (hi[0] - lo[0]) / (hi[1] - lo[1]), 0.5)
    images = []
    for i, p in enumerate(P):
        fig = new_figure(w_in, h_in, dpi)
        ax = fig.add_axes((0.0, 0.0, 1.0, 1.0))
        ax.set_axis_off()
        ax.plot([lo[0], hi[0]], [0.0, 0.0], color="0.55", linewidth=0.8, zorder=1)
        draw_mesh(ax, p, faces, view, color=SKIN)
        ax.set_xlim(lo[0], hi[0])
        ax.set_ylim(lo[1], hi[1])
        if title:
            ax.text(lo[0] + pad * 0.3, hi[1] - pad * 0.3, title, va="top", fontsize=8, color="0.3")
        fig.canvas.draw()
        rgba = np.asarray(fig.canvas.buffer_rgba())
        images.append(Image.fromarray(rgba[..., :3].copy()).convert("P", palette=Image.ADAPTIVE, colors=64))
        if progress is not None:
            progress(f"frame {i + 1} of {len(P)}", (i + 1) / len(P))
    path = Path(path)
    with atomic_path(path) as tmp:
        images[0].save(tmp, format="GIF", save_all=True, append_images=images[1:], loop=0,
                       duration=max(int(round(frame_time * 1000)), 20), comment=GIF_COMMENT.encode())
    return path
