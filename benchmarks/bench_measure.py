"""Measuring 1,000 bodies of the default template with the whole set (part-aware girths): batched
on 2 cores vs a per-body loop of ``evaluate`` and vs a naive per-body trimesh section of every
girth plane (issue 12 §3: target < 2.5 s on 2 cores)."""

from __future__ import annotations

import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import report  # noqa: E402

from bodyspace.data.template import load_template  # noqa: E402
from bodyspace.measure import evaluate, load_measurement_set  # noqa: E402
from bodyspace.synth.phenotype import PARAMETERS, PhenotypeModel

N = 1000
N_LOOP = 100   # the per-body baseline is timed on a subset and scaled
N_TRIMESH = 20  # the trimesh baseline too


def main() -> None:
    template = load_template()
    model = PhenotypeModel(template)
    rng = np.random.default_rng(0)
    phen = rng.uniform(0.1, 0.9, size=(N, len(PARAMETERS)))
    phen[:, 1] = rng.uniform(0.4, 0.8, N)  # adults
    bodies = model.vertices(phen)
    mset = load_measurement_set()
    evaluate(mset, bodies[:2], template.faces)  # warm the caches

    # CPU seconds next to wall time: the machines are shared, and CPU time (this process plus
    # the pool's workers, reaped when the pool closes) shows the work whatever the load.
    c, t = _cpu(), time.perf_counter()
    batched = evaluate(mset, bodies, template.faces, workers=2)   # 2 cores
    t_batch, c_batch = time.perf_counter() - t, _cpu() - c

    c, t = _cpu(), time.perf_counter()
    single = [evaluate(mset, b, template.faces) for b in bodies[:N_LOOP]]
    t_loop, c_loop = (time.perf_counter() - t) * N / N_LOOP, (_cpu() - c) * N / N_LOOP

    c, t = _cpu(), time.perf_counter()
    _trimesh_sections(mset, bodies[:N_TRIMESH], template.faces)
    t_tri, c_tri = (time.perf_counter() - t) * N / N_TRIMESH, (_cpu() - c) * N / N_TRIMESH

    for name in ("chest_girth", "waist_girth", "hip_girth", "stature"):
        a = batched[name].value[:N_LOOP]
        b = np.array([s[name].value for s in single])
        assert np.allclose(a, b, equal_nan=True), name
    print(f"measured {N} bodies x {len(mset.measurements)} measurements in {t_batch:.2f} s batched on 2 cores, "
          f"{c_batch:.2f} s CPU (per-body loop: {t_loop:.2f} s, {c_loop:.2f} s CPU, extrapolated from {N_LOOP}); "
          f"naive trimesh section per body and plane (girths only): {t_tri:.2f} s, {c_tri:.2f} s CPU, "
          f"extrapolated from {N_TRIMESH}; target < 2.5 s: {'PASS' if t_batch < 2.5 else 'FAIL'}")
    report("measure", t_batch, t_loop, N, "bodies")
    report("measure vs trimesh sections", t_batch, t_tri, N, "bodies")


def _trimesh_sections(mset, bodies, faces) -> None:
    """The naive baseline: each slice girth of each body through ``trimesh.intersections.mesh_plane``
    (one call per plane of a band), the convex hull of the whole section, no parts."""
    import trimesh
    from scipy.spatial import ConvexHull

    from bodyspace.measure.points import axis, point
    from bodyspace.measure.slicing import plane_basis
    L = mset.landmark_matrix(bodies.shape[1])
    for v in bodies:
        P = L @ v
        lm = {n: P[i][None] for i, n in enumerate(mset.landmarks)}
        mesh = trimesh.Trimesh(v, faces, process=False)
        for m in mset.measurements:
            if m["method"] != "slice":
                continue
            normal = axis(m["normal"], lm, 1)[0]
            band = m.get("band")
            if band is None:
                origins = [point(m["at"], lm)[0]]
            else:
                a, b = point(band["from"], lm)[0], point(band["to"], lm)[0]
                origins = [a + s * (b - a) for s in np.linspace(band.get("start", 0.0), band.get("stop", 1.0),
                                                                band.get("steps", 12))]
            u, w = plane_basis(normal[None])
            for o in origins:
                seg = trimesh.intersections.mesh_plane(mesh, normal, o).reshape(-1, 3)
                if len(seg) >= 3:
                    xy = np.stack([seg @ u[0], seg @ w[0]], axis=1)
                    ConvexHull(xy).area


def _cpu() -> float:
    """User + system CPU seconds of this process and its reaped children."""
    t = os.times()
    return t.user + t.system + t.children_user + t.children_system


if __name__ == "__main__":
    main()
