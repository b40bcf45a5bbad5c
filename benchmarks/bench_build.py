"""Benchmark: build a BodyModel (RRE, pose and shape, all scans) from 2,000 scans.

Target: under 60 s and under 6 GB peak memory on the 2-core machine.

Prints, in one run:
- the population build (100 subjects x 20 scans by default, into a temporary folder; not timed
  against the target);
- ``BodyModel.fit(db, "rre", "all", n_components=100)``: wall time per stage (encoder mean
  model, encoding pass, PCA) and the peak resident memory of the process (``ru_maxrss``);
- the baseline in the same run: encoding one scan at a time (``encode`` per scan) over a sample
  of the scans, extrapolated to all of them, against the batched encoding pass of ``fit``.

Usage: ``python benchmarks/bench_build.py [--subjects 100] [--poses 19] [--components 100]``.
"""

from __future__ import annotations

import argparse
import resource
import sys
import tempfile
import time
from pathlib import Path

try:
    import bodyspace  # noqa: F401
except ImportError:  # run from a source checkout without installing
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "src"))

import numpy as np

from bodyspace.data.population import build_population
from bodyspace.data.template import load_template
from bodyspace.model import BodyModel


def peak_rss_gb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024 ** 2  # Linux: kB


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--subjects", type=int, default=100)
    ap.add_argument("--poses", type=int, default=19, help="poses per subject besides the rest pose")
    ap.add_argument("--components", type=int, default=100)
    ap.add_argument("--baseline-scans", type=int, default=40)
    args = ap.parse_args()

    template = load_template()
    with tempfile.TemporaryDirectory() as tmp:
        t = time.perf_counter()
        db = build_population(template, Path(tmp) / "population", args.subjects, args.poses, rng=0)
        print(f"population: {db!r} in {time.perf_counter() - t:.1f} s (not part of the target); "
              f"peak RSS so far {peak_rss_gb():.2f} GB")
        del db
        from bodyspace.data.database import ScanDatabase
        db = ScanDatabase.load(Path(tmp) / "population", check_values=False)

        t = time.perf_counter()
        model = BodyModel.fit(db, "rre", "all", n_components=args.components, template=template,
                              on_flipped="ignore")
        wall = time.perf_counter() - t
        print(f"BodyModel.fit: {model!r}")
        print(f"  stages (s): {model.provenance['timings_s']}  (PCA solver: {model.provenance['pca_solver']})")
        print(f"  wall {wall:.1f} s (target < 60 s), {db.n_scans / wall:.0f} scans/s; peak RSS "
              f"{peak_rss_gb():.2f} GB (target < 6 GB); explained variance "
              f"{model.space.explained_variance_ratio_.sum():.3f}")

        # Baseline, same process: one scan per encode call.
        rows = np.linspace(0, db.n_scans - 1, args.baseline_scans).round().astype(int)
        t = time.perf_counter()
        for r in rows:
            model.encode(db.mesh(r))
        one = (time.perf_counter() - t) / len(rows)
        batched = model.provenance["timings_s"]["encode_s"] / db.n_scans
        print(f"encoding: batched {1 / batched:.0f} scans/s (baseline one at a time {1 / one:.0f} scans/s), "
              f"speed-up x{one / batched:.1f}; one at a time all {db.n_scans} scans would take {one * db.n_scans:.0f} s")
        with tempfile.TemporaryDirectory() as tmp2:
            t = time.perf_counter()
            path = model.save(Path(tmp2) / "model.npz")
            size = path.stat().st_size / 1e6
            save_s = time.perf_counter() - t
            t = time.perf_counter()
            BodyModel.load(path)
            print(f"save {save_s:.1f} s ({size:.0f} MB), load {time.perf_counter() - t:.1f} s")


if __name__ == "__main__":
    main()
