"""``bodyspace measure DB --csv`` (issue 16): where a scan's time goes, and the database path
against the per-body path in the same process.

Stages, CPU milliseconds a scan (best of three a chunk) on chunks of 128 scans of a population database: reading the rows,
unposing with the recorded rotations (``rig.unpose.unpose_known``, exact inverse skinning), unposing
by fitting the pose (``rig.unpose.unpose``, the per-body path's and the fallback; on a subset), and
measuring the whole set (``measure.evaluate``). Then the whole command's rate on 2 worker processes
(wall, this machine's load as printed), against the per-body path (fit + evaluate of each scan alone,
extrapolated from a subset).

    PYTHONPATH=src python benchmarks/bench_measure_db.py [--db DB] [--subjects 200]
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import best_time, report  # noqa: E402

from bodyspace.cli.measure import _cells, measure_database  # noqa: E402
from bodyspace.data.database import ScanDatabase  # noqa: E402
from bodyspace.data.template import load_template  # noqa: E402
from bodyspace.measure import evaluate, load_measurement_set  # noqa: E402
from bodyspace.rig.unpose import unpose, unpose_known  # noqa: E402
from bodyspace.synth.population import build_population  # noqa: E402

CHUNK = 128
N_FIT = 32       # bodies the fit and the per-body path are timed on


def _cpu() -> float:
    t = os.times()
    return t.user + t.system + t.children_user + t.children_system


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--db", type=Path, default=None, help="a population database (default: build one)")
    parser.add_argument("--subjects", type=int, default=200, help="subjects of the database built (x5 scans)")
    parser.add_argument("--runs", type=int, default=2, help="runs of the whole command (the best is reported)")
    args = parser.parse_args()
    work = Path(tempfile.mkdtemp(prefix="bench-measure-db-"))
    template = load_template()
    if args.db is None:
        args.db = work / "db"
        build_population(template, args.db, args.subjects, 4, rng=0)
    db = ScanDatabase.load(args.db, check_values=False)
    rig, mset = template.rigs["default"], load_measurement_set()
    n = min(db.n_scans, 4 * CHUNK)
    print(f"bench_measure_db: {os.cpu_count()} cores, load average {os.getloadavg()[0]:.1f}; "
          f"{db.n_scans} scans, stages timed on {n}")
    evaluate(mset, db.read(np.arange(2)), db.faces)                      # warm the caches and kernels
    unpose_known(db.read(np.arange(2)), rig, np.asarray(db.rotations[:2]))
    # Each stage of each chunk: the best of three (CPU seconds of this thread; the machine is shared
    # and a loaded one inflates CPU time too, by cache and memory contention).
    cpu = dict.fromkeys(("read", "unpose_known", "evaluate", "CSV cells (parent)"), 0.0)
    for s in range(0, n, CHUNK):
        rows = np.arange(s, s + CHUNK)
        cpu["read"] += best_time(lambda: db.read(rows), clock=time.thread_time)
        v = db.read(rows)
        R = np.asarray(db.rotations[s:s + CHUNK])
        cpu["unpose_known"] += best_time(lambda: unpose_known(v, rig, R), clock=time.thread_time)
        rest = unpose_known(v, rig, R)[0]
        cpu["evaluate"] += best_time(lambda: evaluate(mset, rest, db.faces, chunk=CHUNK), clock=time.thread_time)
        values = np.stack([m.value for m in evaluate(mset, rest, db.faces, chunk=CHUNK).values()], axis=1)
        cpu["CSV cells (parent)"] += best_time(lambda: _cells(values, np.zeros(len(values))), clock=time.thread_time)
    posed = np.flatnonzero(db.scans["pose"][:n] != "rest")[:N_FIT]
    v = db.read(posed)
    c = _cpu()
    unpose(v, rig)
    fit = (_cpu() - c) / len(posed)
    c, t = _cpu(), time.perf_counter()
    for i in posed:
        evaluate(mset, unpose(db.mesh(i), rig)[0], db.faces)
    per_body_wall, per_body_cpu = (time.perf_counter() - t) / len(posed), (_cpu() - c) / len(posed)
    print("| stage | CPU ms a scan |\n|---|---|")
    for k, x in cpu.items():
        print(f"| {k} | {1000 * x / n:.2f} |")
    print(f"| unpose (fit, batch of {len(posed)}) | {1000 * fit:.2f} |")
    print(f"| per-body path (fit + evaluate, one scan at a time) | {1000 * per_body_cpu:.2f} |")
    total = sum(cpu.values()) / n
    print(f"stages of the database path: {1000 * total:.2f} ms CPU a scan, so at most {2 / total:,.0f} scans/s "
          f"on 2 idle cores (1,000 scans/s needs 2.0 ms)")
    wall = whole_cpu = float("inf")
    for k in range(args.runs):                         # the whole command, best of --runs
        out = work / f"m{k}.csv"
        c, t = _cpu(), time.perf_counter()
        measure_database(args.db, out, landmarks=None, model=None, json_out=False, png=None, units=None, up=None,
                         flip_winding=False, as_posed=False, force=False)
        wall, whole_cpu = min(wall, time.perf_counter() - t), min(whole_cpu, _cpu() - c)
    print(f"measure DB --csv: {db.n_scans} scans in {wall:.2f} s wall (best of {args.runs}), "
          f"{1000 * whole_cpu / db.n_scans:.2f} ms CPU a scan (parent + 2 workers), load average now "
          f"{os.getloadavg()[0]:.1f}")
    report("measure DB", wall, per_body_wall * db.n_scans, db.n_scans, "scans")


if __name__ == "__main__":
    main()
