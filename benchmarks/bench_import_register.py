"""A folder of raw scans registered one at a time and two at once (``import --register``), in one
process.

Four test scans (``synth.scans.raw_scan``: seeds 1100-1103, rest / elbows flexed / step forward /
hands on hips, 80 k points, σ = 2 mm, outliers, holes, mm, Z up, turned) written as PLY files and
registered by ``register.batch.register_files`` with ``workers=1`` (the baseline: each scan on its
own uses part of the second core for its short fits and the NICP's halves) and ``workers=2`` (two
scans at once, each in a forked one-lane process). The fits must be identical (each scan runs with
one BLAS thread either way): the benchmark checks it. Prints the wall time of each run, the load
average, and the ratio. Run it on a quiet machine: on a loaded one the second worker competes with
the other jobs.

    python benchmarks/bench_import_register.py [--scans 4] [--points 80000]
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path

import numpy as np
import trimesh

from bodyspace.data.template import load_template
from bodyspace.register.batch import register_files
from bodyspace.register.model_fit import phenotype_basis
from bodyspace.synth.phenotype import PhenotypeModel
from bodyspace.synth.scans import raw_scan

POSES = ("rest", "elbows_flexed", "step_forward_left", "hands_on_hips")


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--scans", type=int, default=4)
    ap.add_argument("--points", type=int, default=80_000)
    args = ap.parse_args()
    template = load_template()
    phenotype_basis(template)          # built once per process (cached) and inherited by the workers
    pm = PhenotypeModel(template)
    folder = Path(tempfile.mkdtemp(prefix="bench_import_register_"))
    paths = []
    for i in range(args.scans):
        scan = raw_scan(template, pm, 1100 + i, pose=POSES[i % len(POSES)], n_points=args.points)
        paths.append(folder / f"scan{i}.ply")
        trimesh.PointCloud(scan.points).export(paths[-1])
    seconds, fits = {}, {}
    for workers in (1, 2):
        t = time.perf_counter()
        out = register_files(paths, template=template, workers=workers)
        seconds[workers] = time.perf_counter() - t
        fits[workers] = [o.vertices for o in out]
        print(f"workers={workers}: {seconds[workers]:.1f} s wall for {len(paths)} scans (load "
              f"{os.getloadavg()[0]:.1f}); " + ", ".join(f"{o.path.name} {o.seconds:.0f} s "
                                                         f"{'accepted' if o.accepted else 'REFUSED'}" for o in out),
              flush=True)
    same = all(a is None and b is None or a is not None and b is not None and np.array_equal(a, b)
               for a, b in zip(fits[1], fits[2]))
    print(f"same fits: {same}")
    # report()'s rates are per second; a folder's are per minute.
    print(f"import --register: {60 * len(paths) / seconds[2]:.1f} scans/min (baseline "
          f"{60 * len(paths) / seconds[1]:.1f} scans/min), speed-up x{seconds[1] / seconds[2]:.1f}")


if __name__ == "__main__":
    main()
