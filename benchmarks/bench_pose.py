"""Posing bodies (joints, forward kinematics, linear blend skinning): one batch against a per-body loop.

Run: python benchmarks/bench_pose.py
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import best_time, report  # noqa: E402

from bodyspace.data.template import load_template  # noqa: E402
from bodyspace.rig.posing import pose_bodies
from bodyspace.synth.phenotype import PARAMETERS, PhenotypeModel
from bodyspace.synth.poses import load_pose_library


def main(n: int = 100) -> None:
    template = load_template()
    rig = template.rigs["default"]
    bodies = PhenotypeModel(template).vertices(np.random.default_rng(0).random((n, len(PARAMETERS))))
    library = load_pose_library()
    names = [library.names[i % len(library.names)] for i in range(n)]
    R = library.stack(names, rig)
    batch = pose_bodies(bodies, rig, R, on_ground=True)
    one = pose_bodies(bodies[3], rig, R[3], on_ground=True)
    np.testing.assert_allclose(batch[3], one, atol=1e-9)
    fast = best_time(lambda: pose_bodies(bodies, rig, R, on_ground=True))
    slow = best_time(lambda: [pose_bodies(bodies[i], rig, R[i], on_ground=True) for i in range(n)], repeat=1)
    report(f"pose {n} bodies (FK + LBS)", fast, slow, n, "bodies")


if __name__ == "__main__":
    main()
