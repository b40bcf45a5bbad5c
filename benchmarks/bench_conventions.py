"""Cost of recognising input conventions (measure/conventions.py), against measuring.

1. The door for one user mesh (``conventions.prepare``: unit, winding, layout, up axis) against
   ``evaluate`` of the same single mesh (what ``bodyspace measure`` does next).
2. The batch door of ``evaluate`` (``check_body_scale`` on every body, ``check_winding`` on the
   first) against the batched measuring of the same 1,000 bodies (bench_measure.py's run):
   target < 5 %.
3. The bounding-box extent per coordinate against the (V, 3)-axis reduction it replaced.
4. ``conventions.body_faces`` (the floor, turntable or pole a scanner's mesh carries, left out
   before the door in ``bodyspace measure``) on bodies that carry none, against the door itself.
"""

from __future__ import annotations

import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import best_time, report  # noqa: E402

from bodyspace.data.template import load_template  # noqa: E402
from bodyspace.measure import conventions, evaluate, load_measurement_set  # noqa: E402
from bodyspace.synth.phenotype import PARAMETERS, PhenotypeModel  # noqa: E402

N = 1000
N_SINGLE = 40


def main() -> None:
    template = load_template()
    model = PhenotypeModel(template)
    rng = np.random.default_rng(0)
    phen = rng.uniform(0.1, 0.9, size=(N, len(PARAMETERS)))
    phen[:, 1] = rng.uniform(0.4, 0.8, N)  # adults
    bodies = model.vertices(phen)
    mset = load_measurement_set()
    faces = template.faces
    evaluate(mset, bodies[:2], faces)  # warm the caches

    # 1. one mesh at the door, against measuring it
    singles = bodies[:N_SINGLE]
    t_door = best_time(lambda: [conventions.prepare(v, faces, mset) for v in singles]) / N_SINGLE
    t_eval = best_time(lambda: [evaluate(mset, v, faces) for v in singles], repeat=2) / N_SINGLE
    parts = {
        "extent": lambda v: conventions.body_extent(v),
        "volume+area": lambda v: conventions.signed_volume(v, faces),
        "landmarks+layout+up": lambda v: (conventions.layout_checks(conventions.landmark_points(mset, v), 1.27),
                                          conventions.up_axis(conventions.landmark_points(mset, v))),
    }
    costs = {k: best_time(lambda f=f: [f(v) for v in singles]) / N_SINGLE for k, f in parts.items()}
    print(f"door per mesh (prepare): {t_door * 1e3:.2f} ms ("
          + ", ".join(f"{k} {c * 1e3:.2f} ms" for k, c in costs.items())
          + f"); evaluate of the same mesh {t_eval * 1e3:.1f} ms: the door adds {t_door / t_eval:.1%}")
    report("conventions door vs evaluate (one mesh)", t_door, t_eval, N_SINGLE, "meshes")

    # 2. the batch door against measuring the batch (CPU time, this process + reaped workers)
    def door():
        conventions.check_body_scale(bodies, "batch")
        conventions.check_winding(bodies, faces, "batch")
    t_batch_door = best_time(door)
    c = _cpu()
    t = time.perf_counter()
    evaluate(mset, bodies, faces, workers=2, check_scale=False, check_faces=False)
    t_measure, c_measure = time.perf_counter() - t, _cpu() - c
    print(f"batch door for {N} bodies: {t_batch_door * 1e3:.1f} ms, measuring them {t_measure:.2f} s wall / "
          f"{c_measure:.2f} s CPU on 2 workers: {t_batch_door / c_measure:.2%} of the CPU time, "
          f"{t_batch_door / t_measure:.2%} of the wall time; target < 5 %: "
          f"{'PASS' if t_batch_door < 0.05 * t_measure else 'FAIL'}")

    # 3. the extent, per coordinate against the (N, V, 3)-axis reduction
    def extent_axis():
        return (bodies.max(axis=-2) - bodies.min(axis=-2)).max(axis=-1)
    assert np.array_equal(extent_axis(), conventions.body_extent(bodies))
    report("bounding-box extent", best_time(lambda: conventions.body_extent(bodies)), best_time(extent_axis),
           N, "bodies")

    # 4. the look for other geometry on bodies that carry none (every mesh of `bodyspace measure`)
    assert all(conventions.body_faces(v, faces, mset).faces is faces for v in singles)
    t_body = best_time(lambda: [conventions.body_faces(v, faces, mset) for v in singles]) / N_SINGLE
    print(f"body_faces per mesh (all body): {t_body * 1e3:.2f} ms, {t_body / t_eval:.1%} of evaluating it")
    report("body_faces (all body) vs the door", t_body, t_door, N_SINGLE, "meshes")


def _cpu() -> float:
    """User + system CPU seconds of this process and its reaped children."""
    t = os.times()
    return t.user + t.system + t.children_user + t.children_system


if __name__ == "__main__":
    main()
