"""Headless, shaded pictures of body meshes and population histograms (matplotlib Agg).

No display and no GPU: faces are projected orthographically, culled, Lambert-shaded and drawn
far-to-near as one PolyCollection (painter's algorithm). Figures are built as bare
``matplotlib.figure.Figure`` objects on an Agg canvas, so importing or calling this module never
changes the user's pyplot backend or global figure list.

Views (camera frames; image x to the right, image y up, depth grows away from the camera):

=========  =====================================  =========  =========  =========
view       camera                                 image x    image y    depth
=========  =====================================  =========  =========  =========
``front``  at +Z looking toward -Z                +X         +Y         -Z
``back``   at -Z looking toward +Z                -X         +Y         +Z
``side``   at +X looking toward -X (left profile)  -Z         +Y         -X
``top``    at +Y looking down, front at bottom    +X         -Z         -Y
=========  =====================================  =========  =========  =========

So in ``front`` the person's left (+X) is on the image right, as in a photograph; in ``side``
the body's left side faces the camera and the face points to the image left.

Meshes are expected with outward, counter-clockwise faces (trimesh's convention); flipped faces
are culled as back faces.
"""

from __future__ import annotations

import math
import os
import textwrap
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.collections import PolyCollection
from matplotlib.figure import Figure

from bodyspace.atomic import PNG_METADATA, atomic_path
from bodyspace.errors import MeshError, ParameterError
from bodyspace.mesh.geometry import face_normals

SKIN = (0.80, 0.66, 0.55)

# Rows are the camera's (right, up, forward) in world coordinates; forward points away from
# the camera, so depth = p . forward grows with distance and the camera looks along forward.
_FRAMES = {
    "front": np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, -1.0]]),
    "back": np.array([[-1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]),
    "side": np.array([[0.0, 0.0, -1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]]),
    "top": np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, -1.0, 0.0]]),
}
VIEWS = tuple(_FRAMES)
# Views whose image y is world height: only these can stand on a common floor with a ruler.
_UPRIGHT = ("front", "back", "side")

# Light in camera coordinates (right, up, toward the camera): from the upper left and oblique
# enough that the relief reads (a light at the camera flattens the body to a silhouette).
DEFAULT_LIGHT = (-0.60, 0.70, 0.50)


# --------------------------------------------------------------------------------- validation

def _frame(view: str) -> np.ndarray:
    try:
        return _FRAMES[view]
    except (KeyError, TypeError):
        raise ParameterError(f"view: got {view!r}, expected one of {', '.join(VIEWS)}") from None


def _check_vertices(vertices, name: str = "vertices") -> np.ndarray:
    v = np.asarray(vertices, dtype=float)
    if v.ndim != 2 or v.shape[1] != 3:
        raise MeshError(f"{name}: shape {v.shape}, expected (V, 3)")
    if not np.isfinite(v).all():
        raise MeshError(f"{name}: contains NaN or infinity, expected finite coordinates")
    return v


def _check_faces(faces, n_vertices: int, name: str = "faces") -> np.ndarray:
    f = np.asarray(faces)
    if f.ndim != 2 or f.shape[1] != 3:
        raise MeshError(f"{name}: shape {f.shape}, expected (F, 3) triangles")
    if f.size and not np.issubdtype(f.dtype, np.integer):
        raise MeshError(f"{name}: dtype {f.dtype}, expected integer vertex indices")
    f = f.astype(np.intp, copy=False)
    if f.size and (f.min() < 0 or f.max() >= n_vertices):
        raise MeshError(f"{name}: indices span {f.min()}..{f.max()}, expected 0..{n_vertices - 1} "
                        f"for {n_vertices} vertices")
    return f


# ------------------------------------------------------------------------------ functional core

def project(vertices: np.ndarray, view: str = "front") -> tuple[np.ndarray, np.ndarray]:
    """Orthographic projection of ``vertices`` (V, 3) → image ``xy`` (V, 2) and ``depth`` (V,).

    Units are kept (metres in, metres out); larger depth is farther from the camera. See the
    module docstring for each view's axes.
    """
    v = _check_vertices(vertices)
    cam = v @ _frame(view).T                       # (V, 3): right, up, forward
    return cam[:, :2].copy(), cam[:, 2].copy()


def facing(vertices: np.ndarray, faces: np.ndarray, view: str = "front") -> np.ndarray:
    """Mask (F,) of faces turned toward the camera (the ones back-face culling keeps)."""
    v = _check_vertices(vertices)
    f = _check_faces(faces, len(v))
    forward = _frame(view)[2]
    # Unnormalized normals suffice for the sign; degenerate faces (zero area) are dropped.
    return face_normals(v, f, normalize=False) @ forward < 0.0


def _smooth_face_normals(v: np.ndarray, f: np.ndarray) -> np.ndarray:
    """Unit shading normals (F, 3): the mean of the corners' area-weighted vertex normals.

    A PolyCollection can only fill a face with one colour; taking that colour from averaged
    vertex normals instead of the flat face normal hides the facets (a cheap Gouraud stand-in).
    """
    fn = face_normals(v, f, normalize=False)                  # length = 2 * area
    idx = f.ravel()
    w = np.repeat(fn, 3, axis=0)                               # each face's normal, per corner
    vn = np.stack([np.bincount(idx, w[:, k], minlength=len(v)) for k in range(3)], axis=1)
    sn = vn[f].sum(axis=1)
    bad = np.linalg.norm(sn, axis=1) < 1e-300
    sn[bad] = fn[bad]                                          # isolated slivers: keep flat normal
    return sn / np.maximum(np.linalg.norm(sn, axis=1, keepdims=True), 1e-300)


def shade(vertices: np.ndarray, faces: np.ndarray, view: str = "front",
          light: Sequence[float] = DEFAULT_LIGHT, ambient: float = 0.25,
          smooth: bool = True) -> np.ndarray:
    """Lambert + ambient intensity (F,) in [0, 1]; back faces (culled) are NaN.

    ``light`` is a direction in camera coordinates (right, up, toward the camera), so the
    default lights every view from the camera's upper left. ``smooth`` shades with averaged
    vertex normals (see ``_smooth_face_normals``); culling always uses the true face normals.
    """
    v = _check_vertices(vertices)
    f = _check_faces(faces, len(v))
    if not 0.0 <= ambient <= 1.0:
        raise ParameterError(f"ambient: got {ambient}, expected a value in [0, 1]")
    lc = np.asarray(light, dtype=float)
    if lc.shape != (3,) or not np.isfinite(lc).all() or not np.linalg.norm(lc) > 0:
        raise ParameterError(f"light: got {light!r}, expected a non-zero 3-vector "
                             "(right, up, toward the camera)")
    frame = _frame(view)
    # Camera (right, up, toward-camera) to world: toward-camera is -forward.
    l_world = lc @ np.stack([frame[0], frame[1], -frame[2]])
    l_world /= np.linalg.norm(l_world)
    n = _smooth_face_normals(v, f) if smooth else face_normals(v, f)
    out = ambient + (1.0 - ambient) * np.clip(n @ l_world, 0.0, 1.0)
    out[~facing(v, f, view)] = np.nan
    return out


# ----------------------------------------------------------------------------------- drawing

def draw_mesh(ax, vertices: np.ndarray, faces: np.ndarray, view: str = "front",
              color: Sequence[float] = SKIN, offset: Sequence[float] = (0.0, 0.0),
              light: Sequence[float] = DEFAULT_LIGHT, ambient: float = 0.25,
              zorder: float = 2.0) -> PolyCollection:
    """Draw the shaded mesh into ``ax`` and return its PolyCollection.

    ``vertices`` (V, 3), ``faces`` (F, 3); ``offset`` (2,) shifts the picture in image units
    (metres). Culled faces are dropped and the rest drawn far-to-near (painter's algorithm by
    mean face depth). The axes' data limits are updated; aspect and limits are left to the
    caller (set ``ax.set_aspect("equal")`` for an undistorted body).
    """
    v = _check_vertices(vertices)
    f = _check_faces(faces, len(v))
    rgb = np.asarray(color, dtype=float)
    if rgb.shape != (3,):
        raise ParameterError(f"color: got {color!r}, expected an (r, g, b) triple in [0, 1]")
    xy, depth = project(v, view)
    xy += np.asarray(offset, dtype=float)
    intensity = shade(v, f, view, light=light, ambient=ambient)
    keep = np.flatnonzero(~np.isnan(intensity))
    order = keep[np.argsort(-depth[f[keep]].mean(axis=1), kind="stable")]   # far first
    polys = xy[f[order]]                                                     # (F', 3, 2)
    # Lambert is linear in light; ``color`` is a display (sRGB-like, gamma 2.2) colour, and
    # (c^2.2 * I)^(1/2.2) = c * I^(1/2.2): lit faces keep exactly ``color``, shadows stay open.
    fc = np.clip(rgb[None, :] * intensity[order, None] ** (1 / 2.2), 0.0, 1.0)
    fc = np.concatenate([fc, np.ones((len(fc), 1))], axis=1)
    # Edges in the face colour and no antialiasing: otherwise the background shows through
    # the half-covered pixels along every shared edge as a mesh of light seams.
    coll = PolyCollection(polys, facecolors=fc, edgecolors=fc, linewidths=0.25,
                          antialiaseds=False, zorder=zorder)
    ax.add_collection(coll, autolim=False)
    if len(polys):
        lo, hi = polys.reshape(-1, 2).min(axis=0), polys.reshape(-1, 2).max(axis=0)
        ax.update_datalim([lo, hi])
        ax.autoscale_view()
    return coll


def draw_polyline(ax, points3d: np.ndarray, view: str = "front",
                  offset: Sequence[float] = (0.0, 0.0), closed: bool = False, **style):
    """Overlay a 3-D polyline ``points3d`` (K, 3) projected like ``draw_mesh``; returns the Line2D.

    Drawn on top of the body (no occlusion test): a closed girth shows its back half through
    the body, which is usually what a measurement figure wants. ``style`` goes to ``ax.plot``.
    """
    p = np.asarray(points3d, dtype=float)
    if p.ndim != 2 or p.shape[1] != 3 or len(p) < 2:
        raise MeshError(f"points3d: shape {p.shape}, expected (K, 3) with K >= 2")
    xy, _ = project(p, view)
    xy += np.asarray(offset, dtype=float)
    if closed:
        xy = np.concatenate([xy, xy[:1]])
    kw = {"color": "#c0392b", "linewidth": 1.5, "zorder": 3.0, "solid_capstyle": "round"}
    kw.update(style)
    (line,) = ax.plot(xy[:, 0], xy[:, 1], **kw)
    return line


def new_figure(width_in: float, height_in: float, dpi: float) -> Figure:
    """A bare ``Figure`` of ``width_in`` x ``height_in`` inches on its own Agg canvas."""
    fig = Figure(figsize=(width_in, height_in), dpi=dpi)
    FigureCanvasAgg(fig)          # explicit Agg canvas: no pyplot, no display
    return fig


def save_png(fig: Figure, path: str | os.PathLike, dpi: float) -> Path:
    """Write ``fig`` as a PNG to ``path`` atomically (temporary name, then rename); returns ``path``."""
    path = Path(path)
    with atomic_path(path) as tmp:
        # The temporary name ends in .part, so the format must be given explicitly.
        fig.savefig(tmp, format="png", dpi=dpi, facecolor="white", metadata=PNG_METADATA)
    return path


# ------------------------------------------------------------------------------ contact sheet

def _as_mesh_list(meshes, faces) -> tuple[list[np.ndarray], list[np.ndarray]]:
    if isinstance(meshes, np.ndarray):
        if meshes.ndim == 2:
            raise MeshError(f"meshes: shape {meshes.shape}, expected (N, V, 3) or a sequence of "
                            "(V, 3); wrap a single mesh in a list")
        if meshes.ndim != 3 or meshes.shape[2] != 3:
            raise MeshError(f"meshes: shape {meshes.shape}, expected (N, V, 3)")
    vs = [_check_vertices(m, f"meshes[{i}]") for i, m in enumerate(meshes)]
    if not vs:
        raise MeshError("meshes: got 0 meshes, expected at least 1")
    f0 = np.asarray(faces) if isinstance(faces, np.ndarray) else None
    if f0 is not None or (len(faces) and np.ndim(faces[0]) == 1):
        fs = [np.asarray(faces)] * len(vs)                       # one face array shared by all
    else:
        if len(faces) != len(vs):
            raise MeshError(f"faces: got {len(faces)} face arrays for {len(vs)} meshes, expected "
                            "one shared (F, 3) array or one per mesh")
        fs = list(faces)
    fs = [_check_faces(f, len(v), f"faces for meshes[{i}]") for i, (v, f) in enumerate(zip(vs, fs))]
    return vs, fs


def contact_sheet(meshes, faces, path: str | os.PathLike, labels: Sequence[str] | None = None,
                  ncols: int | None = None, views: Sequence[str] = ("front",),
                  title: str | None = None, dpi: float = 120, color: Sequence[float] = SKIN,
                  panel_height: float = 2.4, polylines=None, ruler: bool = True,
                  max_inches: float = 30.0) -> Path:
    """Write a PNG of bodies in a grid, all on one scale, each with a caption; returns ``path``.

    ``meshes``: (N, V, 3) array or a sequence of (V_i, 3); ``faces``: one shared (F, 3) array
    or one per mesh. Each cell shows the body in every ``views`` entry side by side, stood on
    the row's floor line (its lowest point), so the tops compare as statures; with upright
    views a faint height ruler (0.25 m lines, labelled every 0.5 m) is drawn. ``ncols``
    defaults to a single line-up for up to 12 bodies, else 12 columns. ``panel_height`` is the
    tallest body's height in inches; the whole sheet is shrunk to fit ``max_inches`` on its
    longer side. ``polylines``: optional per-mesh sequences of (K, 3) point arrays (closed
    loops repeat their first point) overlaid in every view. The pixel size is exactly
    ``round(inches * dpi)``.
    """
    vs, fs = _as_mesh_list(meshes, faces)
    n = len(vs)
    views = (views,) if isinstance(views, str) else tuple(views)
    if not views:
        raise ParameterError("views: got an empty sequence, expected at least one view")
    for view in views:
        _frame(view)
    labels = [str(i) for i in range(n)] if labels is None else [str(s) for s in labels]
    if len(labels) != n:
        raise ParameterError(f"labels: got {len(labels)} labels for {n} meshes, expected {n}")
    if polylines is not None and len(polylines) != n:
        raise ParameterError(f"polylines: got {len(polylines)} entries for {n} meshes, "
                             f"expected {n} (use [] for none)")
    ncols = min(n, 12) if ncols is None else int(ncols)
    if ncols < 1:
        raise ParameterError(f"ncols: got {ncols}, expected a positive integer")
    ncols = min(ncols, n)
    nrows = math.ceil(n / ncols)

    # Every body in every view: image coordinates and bounding boxes (N, nv, 2).
    xys = [[project(v, view)[0] for view in views] for v in vs]
    lo = np.array([[xy.min(axis=0) for xy in row] for row in xys])
    hi = np.array([[xy.max(axis=0) for xy in row] for row in xys])
    ext = hi - lo
    body_h = max(float(ext[..., 1].max()), 1e-9)
    gap = 0.10 * body_h                              # between views and between cells
    slot_w = ext[..., 0].max(axis=0) + gap           # (nv,) one width per view, all cells alike
    cell_w = float(slot_w.sum()) + gap

    # Scale (metres per inch) from panel_height, then shrink everything if the sheet is huge.
    upright = ruler and all(view in _UPRIGHT for view in views)
    caption_in, ruler_in = 0.32, (0.45 if upright else 0.0)
    m_per_in = body_h / panel_height
    row_h_in = panel_height * 1.08 + caption_in
    w_in = ncols * cell_w / m_per_in + ruler_in
    # The title is wrapped to the sheet's width (a long one ran off both edges); the shrink
    # below scales the font and the sheet alike, so the characters a line holds are fixed here.
    title_lines = textwrap.wrap(title, max(20, int(w_in * 72 / (0.55 * 9.0 * 1.35)))) if title else []
    title_in = 0.45 + 0.24 * (len(title_lines) - 1) if title_lines else 0.0
    h_in = nrows * row_h_in + title_in
    shrink = min(1.0, max_inches / max(w_in, h_in))
    m_per_in /= shrink
    caption_in, title_in, ruler_in, row_h_in = (x * shrink for x in (caption_in, title_in,
                                                                      ruler_in, row_h_in))
    w_px = max(1, round(ncols * cell_w / m_per_in * dpi + ruler_in * dpi))
    h_px = max(1, round(nrows * row_h_in * dpi + title_in * dpi))
    fontsize = max(5.0, 9.0 * shrink)

    fig = new_figure(w_px / dpi, h_px / dpi, dpi)
    # One axes for the whole sheet in metres: a single scale across all panels by construction.
    data_w = w_px / dpi * m_per_in
    data_h = (h_px / dpi - title_in) * m_per_in
    ax = fig.add_axes((0.0, 0.0, 1.0, 1.0 - title_in * dpi / h_px))
    ax.set_axis_off()
    ax.set_xlim(0.0, data_w)
    ax.set_ylim(0.0, data_h)
    row_h = row_h_in * m_per_in
    caption_h = caption_in * m_per_in
    x_start = ruler_in * m_per_in

    for r in range(nrows):
        floor = data_h - (r + 1) * row_h + caption_h
        n_in_row = min(ncols, n - r * ncols)
        x_end = x_start + n_in_row * cell_w
        ax.plot([x_start, x_end], [floor, floor], color="0.55", linewidth=0.8, zorder=1)
        if upright:
            for k, y in enumerate(np.arange(0.25, body_h * 1.04, 0.25)):
                ax.plot([x_start, x_end], [floor + y] * 2, color="0.88", linewidth=0.5, zorder=0.5)
                if k % 2 == 1:
                    ax.text(x_start - 0.15 * gap, floor + y, f"{y:.1f} m", ha="right",
                            va="center", fontsize=fontsize * 0.8, color="0.45")
        for c in range(n_in_row):
            i = r * ncols + c
            x0 = x_start + c * cell_w + gap / 2
            for j, view in enumerate(views):
                cx = x0 + slot_w[:j].sum() + slot_w[j] / 2
                off = (cx - (lo[i, j, 0] + hi[i, j, 0]) / 2, floor - lo[i, j, 1])
                draw_mesh(ax, vs[i], fs[i], view, color=color, offset=off)
                for pts in (polylines[i] if polylines is not None else ()):
                    draw_polyline(ax, pts, view, offset=off, linewidth=1.2 * shrink)
            ax.text(x_start + (c + 0.5) * cell_w, floor - 0.12 * caption_h, labels[i],
                    ha="center", va="top", fontsize=fontsize, clip_on=False)
    # draw_mesh autoscaled while drawing; restore the exact sheet frame.
    ax.set_xlim(0.0, data_w)
    ax.set_ylim(0.0, data_h)
    if title:
        fig.suptitle("\n".join(title_lines), y=1.0 - 0.5 * title_in * dpi / h_px, va="center",
                     fontsize=fontsize * 1.35)
    return save_png(fig, path, dpi)


# --------------------------------------------------------------------------------- histograms

def _panel_values(panel: Mapping, i: int) -> tuple[np.ndarray | None, dict[str, np.ndarray]]:
    def vec(x, field):
        a = np.asarray(x, dtype=float)
        if a.ndim != 1:
            raise ParameterError(f"panels[{i}][{field}]: shape {a.shape}, expected a 1-D array")
        if not np.isfinite(a).all():
            raise ParameterError(f"panels[{i}][{field}]: contains NaN or infinity, expected "
                                 "finite values")
        return a

    if not isinstance(panel, Mapping):
        raise ParameterError(f"panels[{i}]: got {type(panel).__name__}, expected a dict")
    unknown = set(panel) - {"title", "values", "target_mean", "target_sd", "xlabel", "groups"}
    if unknown:
        raise ParameterError(f"panels[{i}]: unknown keys {sorted(unknown)}, expected title, "
                             "values, target_mean, target_sd, xlabel, groups")
    groups = {str(k): vec(g, f"'groups'][{k!r}") for k, g in (panel.get("groups") or {}).items()}
    if "values" not in panel and not groups:
        raise ParameterError(f"panels[{i}]: has neither 'values' nor 'groups', expected at "
                             "least one")
    values = vec(panel["values"], "'values'") if "values" in panel else None
    return values, groups


def histogram_figure(panels: Sequence[Mapping], path: str | os.PathLike,
                     title: str | None = None, dpi: float = 100, bins: int = 30,
                     panel_size: tuple[float, float] = (4.0, 3.0)) -> Path:
    """Write a PNG grid of histograms against survey targets; returns ``path``.

    Each panel dict: ``title``; ``values`` (n,) and/or ``groups`` {name: (n_k,)} (drawn as
    outlines on the same bins, with a legend; without ``values`` the filled bars pool them); optional ``target_mean``, ``target_sd``
    (vertical lines at mean and mean ± SD, plus the target normal density scaled to counts:
    n · bin width · pdf) and ``xlabel``. The grid has ceil(sqrt(P)) columns; the image is
    exactly ``panel_size`` inches per panel times ``dpi``.
    """
    panels = list(panels)
    if not panels:
        raise ParameterError("panels: got an empty list, expected at least one panel dict")
    parsed = [_panel_values(p, i) for i, p in enumerate(panels)]
    ncols = math.ceil(math.sqrt(len(panels)))
    nrows = math.ceil(len(panels) / ncols)
    fig = new_figure(ncols * panel_size[0], nrows * panel_size[1], dpi)
    fig.set_layout_engine("constrained")
    axes = fig.subplots(nrows, ncols, squeeze=False).ravel()
    for ax in axes[len(panels):]:
        ax.set_visible(False)

    for ax, panel, (values, groups) in zip(axes, panels, parsed):
        ax.set_title(str(panel.get("title", "")), fontsize=10)
        ax.set_xlabel(str(panel.get("xlabel", "")), fontsize=9)
        ax.set_ylabel("count", fontsize=9)
        ax.tick_params(labelsize=8)
        pooled = values if values is not None else np.concatenate(list(groups.values()))
        mean, sd = panel.get("target_mean"), panel.get("target_sd")
        if pooled.size == 0:
            ax.text(0.5, 0.5, "no data", transform=ax.transAxes, ha="center", va="center")
            continue
        lo, hi = float(pooled.min()), float(pooled.max())
        if mean is not None and sd is not None:
            # Show the target's ±3 SD range even when the sample misses part of it.
            lo, hi = min(lo, mean - 3 * sd), max(hi, mean + 3 * sd)
        if hi <= lo:
            lo, hi = lo - 0.5, hi + 0.5
        edges = np.linspace(lo, hi, bins + 1)
        # Filled bars are always the whole sample the target curve is scaled to; groups alone
        # are pooled for it, so the curve never looks twice as tall as the bars it describes.
        ax.hist(pooled, bins=edges, color="#9db4c8", edgecolor="white", linewidth=0.4,
                label=f"all (n={pooled.size})" if groups else None)
        for k, (name, g) in enumerate(groups.items()):
            ax.hist(g, bins=edges, histtype="step", linewidth=1.4, color=f"C{k + 1}",
                    label=f"{name} (n={g.size})")
        if mean is not None:
            ax.axvline(mean, color="k", linewidth=1.2)
            if sd is not None:
                for s in (-1, 1):
                    ax.axvline(mean + s * sd, color="k", linewidth=0.9, linestyle="--")
                if sd > 0:
                    x = np.linspace(lo, hi, 200)
                    pdf = np.exp(-0.5 * ((x - mean) / sd) ** 2) / (sd * math.sqrt(2 * math.pi))
                    ax.plot(x, pooled.size * (edges[1] - edges[0]) * pdf, color="#c0392b",
                            linewidth=1.5, label="target")
        # Observed vs target in numbers: the picture shows the shape, this settles small shifts.
        text = f"sample {pooled.mean():.3g} ± {pooled.std():.2g}"
        if mean is not None:
            text += f"\ntarget {mean:.3g}" + (f" ± {sd:.2g}" if sd is not None else "")
        ax.text(0.02, 0.97, text, transform=ax.transAxes, ha="left", va="top", fontsize=7.5,
                bbox={"facecolor": "white", "alpha": 0.8, "edgecolor": "none", "pad": 1.5})
        if groups or (mean is not None and sd):
            ax.legend(fontsize=7, loc="upper right", frameon=False)
    if title:
        fig.suptitle(title, fontsize=12)
    return save_png(fig, path, dpi)
