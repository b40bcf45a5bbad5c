"""Bone-heat skin weights (``rig.weights.bone_heat_weights``) for the template (13,380 vertices)
and the 163-bone default rig, against a plain baseline in the same run: the same heat system
solved with one ``scipy.sparse.linalg.spsolve`` per bone (a factorization each).

The cut alone (``smoothing=0``) is timed beside it, to show what the smoothing after the cut
costs, and the template's rules (``posing.template_heat_rules``: MakeHuman's deforming bones, the
part-aware mask and the arm twist pairs), what ``pose_bodies(weights="bone_heat")`` computes.
Also a foreign body (remeshed to 6,000 vertices, millimetres, Z up) to show the time
follows the vertex count. Run: python benchmarks/bench_boneheat.py
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as sla

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import best_time, report  # noqa: E402

from bodyspace.data.template import load_template  # noqa: E402
from bodyspace.mesh.operators import cotangent_laplacian  # noqa: E402
from bodyspace.rig.posing import template_heat_rules  # noqa: E402
from bodyspace.rig.weights import DEFAULT_HEAT, bone_heat_weights, nearest_visible_bones  # noqa: E402
from bodyspace.synth.foreign import remesh, to_frame  # noqa: E402


def per_bone_spsolve(vertices, faces, heads, tails) -> np.ndarray:
    """The baseline: the same system ``(L + M H) w_b = M H p_b``, one spsolve per bone."""
    source, count, _, dist, _ = nearest_visible_bones(vertices, faces, heads, tails)
    V, B = len(vertices), len(heads)
    L = cotangent_laplacian(vertices, faces)
    dbl = np.linalg.norm(np.cross(vertices[faces[:, 1]] - vertices[faces[:, 0]],
                                  vertices[faces[:, 2]] - vertices[faces[:, 0]]), axis=1)
    mass = np.bincount(faces.ravel(), weights=np.repeat(dbl / 6.0, 3), minlength=V)
    H = np.where(count > 0, DEFAULT_HEAT / np.maximum(dist, 1e-9) ** 2, 0.0)
    A = sp.csc_matrix(L + sp.diags(mass * H))
    W = np.zeros((V, B))
    for b in range(B):
        p = ((source == b).sum(axis=1) / np.maximum(count, 1))
        if p.any():
            W[:, b] = sla.spsolve(A, mass * H * p)
    return W


def main() -> None:
    template = load_template()
    rig = template.rigs["default"]
    v, f = template.vertices, template.faces
    heads, tails = rig.heads(v), rig.tails(v)
    print(f"template: {len(v):,} vertices, {len(f):,} faces, rig {rig.name!r} with {rig.n_bones} bones")
    bone_heat_weights(v, f, heads, tails)                        # compile
    t_vis = best_time(lambda: nearest_visible_bones(v, f, heads, tails), 3)
    t = best_time(lambda: bone_heat_weights(v, f, heads, tails), 3)
    t1 = best_time(lambda: bone_heat_weights(v, f, heads, tails, lanes=1), 3)
    t0_cut = best_time(lambda: bone_heat_weights(v, f, heads, tails, smoothing=0.0), 3)
    _, _, _, _, tests = nearest_visible_bones(v, f, heads, tails)
    print(f"  nearest visible bone: {t_vis:.3f} s ({tests.sum():,} segment queries, {tests.mean():.2f} a vertex)")
    print(f"  bone_heat_weights: {t:.3f} s on two lanes, {t1:.3f} s on one (target < 3 s); "
          f"{t0_cut:.3f} s without the smoothing after the cut (smoothing=0)")
    t0 = time.perf_counter()
    W = per_bone_spsolve(v, f, heads, tails)
    t_base = time.perf_counter() - t0
    report("bone heat, template and default rig", t, t_base, rig.n_bones, "bones")
    # what pose_bodies(weights="bone_heat") computes: the template's rules (deforming bones,
    # part-aware mask, arm twist pairs), the rules' construction included
    t_rules = best_time(lambda: bone_heat_weights(v, f, heads, tails, **template_heat_rules(rig, v, f)), 3)
    report("bone heat with the template's rules (bone_heat_rig_weights)", t_rules, t_base, rig.n_bones, "bones")
    ours = bone_heat_weights(v, f, heads, tails, max_influences=rig.n_bones, min_weight=0.0, smoothing=0.0)
    print(f"  same weights as the baseline before the cut: max |difference| "
          f"{np.abs(ours.toarray() - np.maximum(W, 0) / np.maximum(W, 0).sum(1, keepdims=True)).max():.1e}")

    rng = np.random.default_rng(0)
    v2, f2, _ = remesh(v, f, 6000, rng)
    h2, t2 = to_frame(heads), to_frame(tails)
    v2 = to_frame(v2)
    tf = best_time(lambda: bone_heat_weights(v2, f2, h2, t2), 3)
    print(f"foreign body (remeshed to {len(v2):,} vertices, mm, Z up): {tf:.3f} s")
    print(f"measured {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}")


if __name__ == "__main__":
    main()
