"""Measuring 1,000 bodies of the default template: batched vs a per-body loop (target < 10 s)."""

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

    for name in ("chest_girth", "waist_girth", "hip_girth", "stature"):
        a = batched[name].value[:N_LOOP]
        b = np.array([s[name].value for s in single])
        assert np.allclose(a, b, equal_nan=True), name
    print(f"measured {N} bodies x {len(mset.measurements)} measurements in {t_batch:.2f} s batched on 2 cores, "
          f"{c_batch:.2f} s CPU (per-body loop: {t_loop:.2f} s, {c_loop:.2f} s CPU, extrapolated from {N_LOOP}); "
          f"target < 10 s: {'PASS' if t_batch < 10 else 'FAIL'}")
    report("measure", t_batch, t_loop, N, "bodies")


def _cpu() -> float:
    """User + system CPU seconds of this process and its reaped children."""
    t = os.times()
    return t.user + t.system + t.children_user + t.children_system


if __name__ == "__main__":
    main()
