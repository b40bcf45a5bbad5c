"""``bodyspace rig`` on a scanner's mesh (rig/scan_body.py): the cost of looking for a floor,
turntable or pole, against the rig of the body itself in the same run.

For the template body in millimetres, Z up, clean and with (a) a separate floor disc, (b) a sheet
welded to its soles, (c) a turntable, (d) a pole: ``scan_body`` with the frame given and found;
baseline: ``skeleton_and_weights`` (embedding + bone heat) of the clean body, the work every
``bodyspace rig`` of a foreign mesh does. Prints the ratio (the search's share of a rig).

Run: python benchmarks/bench_rig_floor.py
"""

from __future__ import annotations

import os
import sys
import time

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", "tests"))

from floor_meshes import scanner_meshes  # noqa: E402

from bodyspace.cli.export import skeleton_and_weights  # noqa: E402
from bodyspace.data.template import load_template  # noqa: E402
from bodyspace.measure.conventions import UP_ROTATIONS  # noqa: E402
from bodyspace.rig.scan_body import scan_body  # noqa: E402


def best_of(fn, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return min(times)


def main() -> None:
    t = load_template()
    v, f = np.asarray(t.vertices, float), np.asarray(t.faces)
    z = UP_ROTATIONS["z"]
    clean = v @ z * 1000.0
    skeleton_and_weights(clean, f, "default", "warm-up", up="z", units="mm")        # numba compiled
    base = best_of(lambda: skeleton_and_weights(clean, f, "default", "bench", up="z", units="mm"), 2)
    print(f"baseline: embedding + bone heat of the clean template body: {base:.2f} s")
    cases = {"clean": (v, f), **scanner_meshes(v, f)}
    for name, (mv, mf) in cases.items():
        mm = mv @ z * 1000.0
        for label, kw in (("given", dict(up="z", units="mm")), ("found", {})):
            s = best_of(lambda: scan_body(mm, mf, **kw), 3)
            print(f"{name:10s} frame {label}: scan_body {1000 * s:6.0f} ms, ratio to the rig {s / base:.3f}")


if __name__ == "__main__":
    main()
