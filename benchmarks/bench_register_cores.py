"""One registration on one core and on two, in one process (issue 15: "under 30 s a scan on 2 cores").

The step-forward test scan of ``bench_register.py`` (scan 2, seed 102, 147 k points: the one whose
limbs are restarted) registered by ``register_scan`` with the independent short fits (heading
candidates, start poses, limb restarts) in one process (``align.WORKERS = 1``, the baseline) and
in two forked ones (``WORKERS = 2``, the default); the KD-tree queries use every core in both
runs (``parallel.cores()``). The fits are the same either way (each short fit is a pure function
of its start and seed): the benchmark checks that the vertices are identical. Prints the wall time
per stage, the CPU time (this process's and its finished workers') and the load average, then the
ratio. Run it on a quiet machine: on a loaded one the second process competes with the others.

    python benchmarks/bench_register_cores.py [--landmarks] [--points 150000]
"""

from __future__ import annotations

import argparse
import os
import resource
import time

import numpy as np

from _common import report
from bodyspace.data.template import load_template
from bodyspace.register import align
from bodyspace.register.model_fit import phenotype_basis
from bodyspace.register.pipeline import register_scan
from bodyspace.studies.registration import SURFACE_LANDMARKS
from bodyspace.synth.phenotype import PhenotypeModel
from bodyspace.synth.scans import raw_scan


def cpu_seconds() -> float:
    """CPU time of this process and of its finished child processes (the forked short fits)."""
    children = resource.getrusage(resource.RUSAGE_CHILDREN)
    return time.process_time() + children.ru_utime + children.ru_stime


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--points", type=int, default=150_000)
    ap.add_argument("--landmarks", action="store_true", help="register with the 13 surface landmarks")
    args = ap.parse_args()
    template = load_template()
    phenotype_basis(template)          # built once per process (cached), not timed
    scan = raw_scan(template, PhenotypeModel(template), 102, pose="step_forward_left", n_points=args.points)
    lms = {n: scan.landmarks[n] for n in SURFACE_LANDMARKS} if args.landmarks else None
    seconds, fits = {}, {}
    for workers in (1, 2):
        align.WORKERS = workers
        t, c = time.perf_counter(), cpu_seconds()
        reg = register_scan(scan.points, template=template, landmarks=lms, check=False)
        seconds[workers] = time.perf_counter() - t
        fits[workers] = reg.vertices
        stages = ", ".join(f"{k} {v:.1f}" for k, v in reg.seconds.items() if k != "total")
        print(f"{workers} process(es): {seconds[workers]:.1f} s wall (CPU {cpu_seconds() - c:.1f} s, "
              f"load {os.getloadavg()[0]:.1f}); {stages}; quality {reg.quality.quality:.2f}"
              f"{', restarted ' + ', '.join(reg.restarted) if reg.restarted else ''}", flush=True)
    print(f"same fit: {np.array_equal(fits[1], fits[2])}")
    report("register_scan, short fits on 2 processes vs 1", seconds[2], seconds[1], 1000, "milliscans")


if __name__ == "__main__":
    main()
