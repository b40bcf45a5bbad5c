"""Registration of what real scanners deliver (issue 15, docs/registration.md "A real scanner's output").

One body (``raw_scan`` seed 3 by default, rest pose, the test scans' noise, outliers and holes),
registered without landmarks as:

- ``plain``: the test scan (80 k points): the baseline of the rows below;
- ``plane``: standing on a scanned ground disc 1.6 m across (as many points as the body);
- ``turntable``: on a platform 10 cm high (its top and side, the ground around it);
- ``front``: seen from the front only (one Kinect / phone LiDAR view);
- ``dense``: 1.5 M points (photogrammetry), against ``plain200k`` (200 k points) in the same
  process: RATIO = dense / 200 k, wall and CPU (this process and its forked short fits).

Per row: correspondence and surface error to the truth (mm), the quality, accepted or the refusal,
wall and CPU seconds, the process's peak memory so far, and what ``prepare`` assumed about the floor.

    python benchmarks/bench_register_scanners.py [--seed 3] [--only plain,plane,front] [--dense 1500000]
"""

from __future__ import annotations

import argparse
import resource
import time

import numpy as np

from bodyspace.data.template import load_template
from bodyspace.errors import RegistrationError
from bodyspace.register.pipeline import register_scan
from bodyspace.studies.registration import registration_errors
from bodyspace.synth.phenotype import PhenotypeModel
from bodyspace.synth.scans import raw_scan


def cpu_seconds() -> float:
    """CPU time of this process and of its finished child processes (the forked short fits)."""
    children = resource.getrusage(resource.RUSAGE_CHILDREN)
    return time.process_time() + children.ru_utime + children.ru_stime


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seed", type=int, default=3)
    ap.add_argument("--only", default="plain,plane,turntable,front,plain200k,dense")
    ap.add_argument("--dense", type=int, default=1_500_000)
    args = ap.parse_args()
    template = load_template()
    pm = PhenotypeModel(template)
    cases = {"plain": {}, "plane": {"floor": "plane"}, "turntable": {"floor": "turntable"},
             "front": {"view": "front"}, "plain200k": {"n_points": 200_000}, "dense": {"n_points": args.dense}}
    times = {}
    for name in args.only.split(","):
        kw = dict(n_points=80_000) | cases[name]
        scan = raw_scan(template, pm, args.seed, pose="rest", **kw)
        wall, cpu = time.perf_counter(), cpu_seconds()
        try:
            reg = register_scan(scan.points, rng=0)
        except RegistrationError as exc:
            print(f"{name}: {len(scan.points):,} points: REFUSED after {time.perf_counter() - wall:.1f} s: {exc}")
            continue
        wall, cpu = time.perf_counter() - wall, cpu_seconds() - cpu
        times[name] = (wall, cpu)
        e = registration_errors(reg.vertices, reg.faces, scan)
        floor = [n.split(":")[0] for n in reg.assumed if "floor" in n or "platform" in n]
        rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
        print(f"{name}: {len(scan.points):,} points: correspondence {e['correspondence_mm']:.2f} mm, surface "
              f"{e['surface_mm']:.2f} mm, {e['folded']} folds; quality {reg.quality.quality:.2f} (explained "
              f"{reg.quality.explained:.3f}, coverage {reg.quality.coverage:.3f}), accepted {reg.accepted}"
              f"{', ONE-SIDED' if reg.one_sided else ''}; {wall:.1f} s wall, {cpu:.1f} s CPU (prepare "
              f"{reg.seconds['prepare']:.1f} s); peak {rss:.0f} MB; {floor or 'no floor'}", flush=True)
    if "dense" in times and "plain200k" in times:
        (dw, dc), (bw, bc) = times["dense"], times["plain200k"]
        print(f"RATIO dense ({args.dense:,} points) / 200 k points: wall x{dw / bw:.2f}, CPU x{dc / bc:.2f}")


if __name__ == "__main__":
    main()
