"""Pictures of a rigged body: the skeleton over the body (front and side) and weight maps.

``rig_figure`` draws, left to right: the body front and side with every bone as a line from
head to tail over it (drawn on top: an X-ray view, the bones are inside the body) and a dot at
each head; then one view per chosen bone with its skin weights as colour (white 0 to dark red
1) on the shaded body: from the front, or from the back for a bone whose weight lies mostly on
the back (a spine bone's: from the front its map was blank). The drawing (projection, shading, atomic PNG write) is
``report.render``'s.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Sequence

import numpy as np
import scipy.sparse as sp
from matplotlib import colormaps
from matplotlib.collections import LineCollection, PolyCollection

from bodyspace.errors import ParameterError
from bodyspace.mesh.geometry import vertex_normals
from bodyspace.report.render import draw_mesh, new_figure, project, save_png, shade
from bodyspace.rig.skeleton import Skeleton

__all__ = ["rig_figure", "default_weight_bones", "weight_view"]

BONE_COLOR = "#1f5fa8"
PALE_SKIN = (0.93, 0.86, 0.80)
# Bone families for the default weight maps, by the names the CC0 rigs use (default, game_engine,
# cmu_mb, mixamo): an upper arm, the spine, a thigh, the head.
_FAMILIES = (("upperarm", "leftarm", "arm"), ("spine",), ("upperleg", "thigh", "upleg"), ("head",))


def default_weight_bones(skeleton: Skeleton, weights: sp.spmatrix) -> list[str]:
    """Up to four bones worth a weight map: an upper arm, the spine, a thigh and the head,
    left side preferred, each the member of its family (by name) with the most skin."""
    total = np.asarray(sp.csr_matrix(weights).sum(axis=0)).ravel()
    names = [b.lower().replace("_", "").replace(":", "") for b in skeleton.bone_names]
    left = np.array([b.endswith((".l", "l")) or "left" in b for b in names])
    chosen = []
    for family in _FAMILIES:
        for key in family:
            hits = [i for i, b in enumerate(names) if key in b and total[i] > 0 and "fore" not in b
                    and skeleton.bone_names[i] not in chosen]
            if hits:
                hits.sort(key=lambda i: (not left[i] if family[0] in ("upperarm", "upperleg") else False, -total[i]))
                chosen.append(skeleton.bone_names[hits[0]])
                break
    return chosen


def _draw_weights(ax, vertices, faces, values, view="front"):
    """The shaded body with per-vertex ``values`` in [0, 1] as colour (mean over each face)."""
    xy, depth = project(vertices, view)
    intensity = shade(vertices, faces, view)
    keep = np.flatnonzero(~np.isnan(intensity))
    order = keep[np.argsort(-depth[faces[keep]].mean(axis=1), kind="stable")]
    rgb = colormaps["Reds"](np.clip(values[faces[order]].mean(axis=1), 0.0, 1.0) * 0.9)[:, :3]
    fc = np.clip(rgb * intensity[order, None] ** (1 / 2.2), 0.0, 1.0)
    fc = np.concatenate([fc, np.ones((len(fc), 1))], axis=1)
    polys = xy[faces[order]]
    ax.add_collection(PolyCollection(polys, facecolors=fc, edgecolors=fc, linewidths=0.25, antialiaseds=False))
    ax.update_datalim(polys.reshape(-1, 2))
    ax.autoscale_view()


def weight_view(weights: np.ndarray, facing: np.ndarray) -> str:
    """"front" or "back": the view that shows more of a bone's weight. weights (V,) of one bone;
    facing (V,) each vertex normal's component towards the front camera (+Z)."""
    front = float(weights @ np.maximum(facing, 0.0))
    back = float(weights @ np.maximum(-facing, 0.0))
    return "back" if back > front else "front"


def rig_figure(path: str | os.PathLike, vertices: np.ndarray, faces: np.ndarray, skeleton: Skeleton,
               weights: sp.spmatrix, bones: Sequence[str] | None = None, title: str | None = None,
               dpi: float = 110) -> Path:
    """Write the skeleton-and-weights picture of one rigged body to ``path`` (PNG).

    vertices (V, 3) metres, +Y up; faces (F, 3); skeleton: the body's ``Skeleton``; weights
    (V, B) skin weights; bones: names for the weight maps (default ``default_weight_bones``).
    """
    v = np.asarray(vertices, dtype=float)
    f = np.asarray(faces, dtype=np.int64)
    W = sp.csc_matrix(weights)
    if W.shape != (len(v), skeleton.n_bones):
        raise ParameterError(f"weights: shape {W.shape}, expected ({len(v)}, {skeleton.n_bones})")
    bones = list(default_weight_bones(skeleton, W) if bones is None else bones)
    index = [skeleton.bone_index(b) for b in bones]
    panels = 2 + len(bones)
    height = float(np.ptp(v[:, 1]))
    # one scale for every panel: each is as wide as the widest view of the body, centred on it
    width = 1.06 * max(float(np.ptp(project(v, view)[0][:, 0])) for view in ("front", "side"))
    fig = new_figure(5.0 * panels * width / (1.04 * height) + 0.2, 5.6, dpi)
    facing = vertex_normals(v, f)[:, 2]                  # +1 towards the front camera, -1 the back
    for k in range(panels):
        ax = fig.add_subplot(1, panels, k + 1)
        ax.set_axis_off()
        ax.set_aspect("equal")
        if k < 2:
            view = ("front", "side")[k]
            draw_mesh(ax, v, f, view, color=PALE_SKIN)
            h, _ = project(skeleton.heads, view)
            t, _ = project(skeleton.tails, view)
            ax.add_collection(LineCollection(np.stack([h, t], axis=1), colors=BONE_COLOR, linewidths=1.1, zorder=4))
            ax.scatter(h[:, 0], h[:, 1], s=5, color=BONE_COLOR, zorder=5, linewidths=0)
            ax.set_title(f"{skeleton.name}: {skeleton.n_bones} bones, {view}", fontsize=8)
        else:
            w = W[:, index[k - 2]].toarray().ravel()
            view = weight_view(w, facing)
            _draw_weights(ax, v, f, w, view)
            ax.set_title(f"weights of {bones[k - 2]}{'' if view == 'front' else f' ({view})'}", fontsize=8)
        xs = project(v, view)[0][:, 0]
        mid = 0.5 * (xs.min() + xs.max())
        ax.set_xlim(mid - width / 2, mid + width / 2)
        lo = v[:, 1].min() - 0.02 * height
        ax.set_ylim(lo, lo + 1.04 * height)
    if title:
        fig.suptitle(title, fontsize=9)
    fig.subplots_adjust(left=0.01, right=0.99, bottom=0.01, top=0.9 if title else 0.94, wspace=0.02)
    return save_png(fig, path, dpi)
