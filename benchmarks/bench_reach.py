"""The last model fit (``model_fit.reach_shape``) against the pipeline without it, in one process.

Per test scan, ``register_scan`` without landmarks twice: as it is, and with ``reach_shape``
replaced by the state unchanged (the pipeline before the tenth round). Errors against the truth
(``studies.registration.registration_errors``): mean correspondence error, mean distance to the
true surface, folded triangles; the breast vertices' error (8549 and 1877, the registered mesh
against the true posed body, and the standing body against the true rest body after both are
centred); wall and CPU seconds; the RATIO of the CPU time with the last fit to without.

Scans: bench_register's (seed 100 + i, its poses and point counts) and study_iso's (seed 1000 + i,
its poses, skinnings and point counts; 44 and 54 are the women with large, low breasts).

    python benchmarks/bench_reach.py [--bench 0,1,2,3] [--study 44,54]
"""

from __future__ import annotations

import argparse
import os
import resource
import sys
import time
from pathlib import Path

import numpy as np

from bodyspace.data.template import load_template
from bodyspace.register import pipeline
from bodyspace.register.model_fit import phenotype_basis
from bodyspace.studies.registration import registration_errors
from bodyspace.synth.foreign import from_frame
from bodyspace.synth.phenotype import PhenotypeModel
from bodyspace.synth.scans import raw_scan

sys.path.insert(0, str(Path(__file__).parent))
from bench_register import POSES  # noqa: E402
from study_iso import scan_spec  # noqa: E402

BREAST = (8549, 1877)
POINTS = (50_000, 100_000, 150_000, 200_000)


def cpu_seconds() -> float:
    children = resource.getrusage(resource.RUSAGE_CHILDREN)
    return time.process_time() + children.ru_utime + children.ru_stime


def run(scan, template, truth_rest, reach: bool) -> dict:
    real = pipeline.reach_shape
    if not reach:
        pipeline.reach_shape = lambda q, qn, template, state, basis, **kw: (state, state.coefficients)
    try:
        t, c = time.perf_counter(), cpu_seconds()
        reg = pipeline.register_scan(scan.points, template=template, check=False, rng=0)
        wall, cpu = time.perf_counter() - t, cpu_seconds() - c
    finally:
        pipeline.reach_shape = real
    err = registration_errors(reg.vertices, template.faces, scan)
    fit = from_frame(reg.vertices, **scan.frame)
    posed = [1000 * np.linalg.norm(fit[v] - scan.body[v]) for v in BREAST]
    st = reg.standing - reg.standing.mean(axis=0)
    tr = truth_rest - truth_rest.mean(axis=0)
    rest = [1000 * np.linalg.norm(st[v] - tr[v]) for v in BREAST]
    return dict(err, posed=posed, rest=rest, wall=wall, cpu=cpu, accepted=reg.quality.accepted,
                quality=reg.quality.quality)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--bench", default="0,1,2,3", help="bench_register scans (seed 100 + i)")
    ap.add_argument("--study", default="44,54", help="study_iso scans (seed 1000 + i)")
    args = ap.parse_args()
    template = load_template()
    pm = PhenotypeModel(template)
    phenotype_basis(template)
    scans = []
    for i in [int(s) for s in args.bench.split(",") if s]:
        scans.append((f"bench {i}", raw_scan(template, pm, 100 + i, pose=POSES[i % len(POSES)],
                                             n_points=POINTS[i % len(POINTS)])))
    for i in [int(s) for s in args.study.split(",") if s]:
        spec = scan_spec(i)
        scans.append((f"study {i}", raw_scan(template, pm, spec["seed"], pose=spec["pose"], n_points=spec["n_points"],
                                             weights=spec["weights"], preserve_volume=spec["preserve_volume"])))
    cpu = {True: 0.0, False: 0.0}
    for name, scan in scans:
        truth_rest = pm.vertices(scan.phenotype[None])[0]
        for reach in (False, True):
            r = run(scan, template, truth_rest, reach)
            cpu[reach] += r["cpu"]
            print(f"{name} ({scan.pose}, {len(scan.points)} points) {'with' if reach else 'without'} the last fit: "
                  f"correspondence {r['correspondence_mm']:.2f} mm, surface {r['surface_mm']:.2f} mm, "
                  f"folds {r['folded']}, breast vertices posed {r['posed'][0]:.1f} / {r['posed'][1]:.1f} mm, "
                  f"standing {r['rest'][0]:.1f} / {r['rest'][1]:.1f} mm, "
                  f"{'accepted' if r['accepted'] else 'REFUSED'} {r['quality']:.2f}, "
                  f"{r['wall']:.1f} s wall ({r['cpu']:.1f} CPU), load {os.getloadavg()[0]:.1f}", flush=True)
    print(f"RATIO CPU with / without the last model fit: x{cpu[True] / max(cpu[False], 1e-9):.3f} "
          f"({cpu[True]:.1f} s / {cpu[False]:.1f} s over {len(scans)} scans)")


if __name__ == "__main__":
    main()
