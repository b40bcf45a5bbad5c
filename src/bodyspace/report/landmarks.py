"""Documentation figures of a measurement set: where its landmarks are, by name.

``landmark_figure`` draws a body front and side with every landmark of a set as a dot and
its name in a column beside the body, joined by a leader line (docs/measurements_landmark_names.png
is ``landmark_figure("docs/measurements_landmark_names.png")``). Surface landmarks (one vertex)
are filled dots; weighted landmarks (joint centres inside the body) are open rings.

The drawing itself (shaded mesh, projection, atomic PNG write) is ``report.render``'s.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

import numpy as np

from bodyspace.data.template import load_template
from bodyspace.measure.definitions import MeasurementSet, load_measurement_set
from bodyspace.report.render import draw_mesh, new_figure, project, save_png
from bodyspace.synth.phenotype import PhenotypeModel

SURFACE_COLOR = "#c0392b"
JOINT_COLOR = "#1f5fa8"


def spread_labels(anchors: np.ndarray, gap: float, lo: float, hi: float) -> np.ndarray:
    """Label heights (K,) near ``anchors`` (K,), at least ``gap`` apart, inside [lo, hi].

    Order is kept (so leader lines do not cross): sorted anchors are pushed up where they
    crowd, then down from the top bound, and the block is centred where it has room.
    """
    a = np.asarray(anchors, dtype=float)
    order = np.argsort(a, kind="stable")
    y = a[order].copy()
    for i in range(1, len(y)):
        y[i] = max(y[i], y[i - 1] + gap)
    if len(y) and y[-1] > hi:
        y[-1] = hi
        for i in range(len(y) - 2, -1, -1):
            y[i] = min(y[i], y[i + 1] - gap)
    if len(y) and y[0] < lo:
        y += lo - y[0]
    out = np.empty_like(y)
    out[order] = y
    return out


def landmark_figure(path: str | os.PathLike, mset: MeasurementSet | None = None,
                    vertices: np.ndarray | None = None, faces: np.ndarray | None = None,
                    dpi: float = 110, title: str | None = None) -> Path:
    """Write a PNG of ``vertices`` (V, 3) (default: the template's mean body) front and side with
    each landmark of ``mset`` (default: the shipped hm08 set) as a labelled dot; returns ``path``.

    Front: the person's left is on the image right; left landmarks are labelled in the right
    column, right ones in the left column, mid-line ones on the side with room. Side (the left
    profile): mid-line and left landmarks (the right ones mirror them).
    """
    mset = load_measurement_set() if mset is None else mset
    if vertices is None or faces is None:
        template = load_template()
        vertices = PhenotypeModel(template).vertices({})[0] if vertices is None else vertices
        faces = template.faces if faces is None else faces
    v = np.asarray(vertices, dtype=float)
    L = mset.landmark_matrix(len(v))
    pts = np.asarray(L @ v)
    names = list(mset.landmarks)
    joint = np.array([len(ids) > 1 for ids, _ in mset.landmarks.values()])

    body_h = float(v[:, 1].max() - v[:, 1].min())
    label_w, lead = 0.45, 0.22             # metres of text column and of leader line past the body
    xys = {view: project(v, view)[0] for view in ("front", "side")}
    half = {view: 0.5 * float(xy[:, 0].max() - xy[:, 0].min()) for view, xy in xys.items()}
    x_side = half["front"] + 2 * (lead + label_w) + 0.1 + half["side"]
    x_lim = (-(half["front"] + lead + label_w), x_side + half["side"] + lead + label_w)
    y_lim = (-0.16, body_h * 1.04)
    width_in = 15.0
    height_in = width_in * (y_lim[1] - y_lim[0]) / (x_lim[1] - x_lim[0]) / 0.94
    fig = new_figure(width_in, height_in, dpi)
    ax = fig.add_axes((0.0, 0.0, 1.0, 0.94))
    ax.set_axis_off()
    fs = 8.5
    gap = 0.032 * body_h                   # label spacing
    for view, x_shift in (("front", 0.0), ("side", x_side)):
        xy = xys[view]
        off = np.array([x_shift - 0.5 * (xy[:, 0].min() + xy[:, 0].max()), -xy[:, 1].min()])
        draw_mesh(ax, v, faces, view, offset=off)
        p2 = project(pts, view)[0] + off
        if view == "front":
            # image right = the person's left
            side = np.where([n.endswith("_l") for n in names], 1, np.where([n.endswith("_r") for n in names], -1, 0))
            mids = np.flatnonzero(side == 0)
            # mid-line names alternate to balance the columns, by height
            for k, i in enumerate(mids[np.argsort(-p2[mids, 1])]):
                side[i] = 1 if k % 2 == 0 else -1
            show = np.arange(len(names))
        else:
            show = np.flatnonzero([not n.endswith("_r") for n in names])
            # The face points to the image left: landmarks on the front of their limb or torso
            # (left of the local centre line at their height) are labelled left, the rest right.
            side = np.ones(len(names), dtype=int)
            for i in show:
                near = (np.abs(v[:, 1] - pts[i, 1]) < 0.015) & (np.abs(v[:, 0] - pts[i, 0]) < 0.12)
                centre = 0.5 * (xy[near, 0].min() + xy[near, 0].max()) + off[0] if near.any() else x_shift
                side[i] = -1 if p2[i, 0] < centre - 0.01 else 1
        for s in (-1, 1):
            idx = show[side[show] == s]
            if not len(idx):
                continue
            col_x = x_shift + s * (half[view] + lead)
            ys = spread_labels(p2[idx, 1], gap, 0.02, body_h * 1.02)
            for i, y in zip(idx, ys):
                color = JOINT_COLOR if joint[i] else SURFACE_COLOR
                ax.plot([p2[i, 0], col_x - s * 0.01], [p2[i, 1], y], color=color, linewidth=0.6,
                        alpha=0.8, zorder=4)
                ax.text(col_x, y, names[i], ha="left" if s > 0 else "right", va="center", fontsize=fs,
                        color=color, zorder=5)
        for i in show:
            if joint[i]:
                ax.plot(*p2[i], marker="o", markersize=6, markerfacecolor="white", markeredgecolor=JOINT_COLOR,
                        markeredgewidth=1.6, zorder=6)
            else:
                ax.plot(*p2[i], marker="o", markersize=5, color=SURFACE_COLOR, markeredgecolor="white",
                        markeredgewidth=0.6, zorder=6)
        caption = ("front: the person's left on the image right" if view == "front"
                   else "side: left profile (right landmarks mirror the left)")
        ax.text(x_shift, -0.04, caption, ha="center", va="top", fontsize=fs + 1)
    ax.plot([], [], "o", color=SURFACE_COLOR, label="surface landmark (one vertex)")
    ax.plot([], [], "o", markerfacecolor="white", markeredgecolor=JOINT_COLOR, markeredgewidth=1.6,
            label="joint centre (weighted vertex set, inside the body)")
    ax.legend(loc="lower center", bbox_to_anchor=(0.5, -0.005), ncol=2, fontsize=fs + 0.5, frameon=False)
    ax.set_xlim(*x_lim)
    ax.set_ylim(*y_lim)
    ax.set_aspect("equal")
    fig.suptitle(title or f"landmarks of {Path(mset.source).name} ({len(names)})", fontsize=fs + 4)
    return save_png(fig, path, dpi)


if __name__ == "__main__":      # python -m bodyspace.report.landmarks [out.png]
    print(landmark_figure(sys.argv[1] if len(sys.argv) > 1 else "docs/measurements_landmark_names.png"))
