"""The standing body (``pose_refit.standing_body``) with and without the skinning-uncertainty gate
(issue 15, Eighth round of docs/registration.md): its time and the neck girth it gives, on a body
posed with the smoothed weights (another skinning than the pipeline's) with its true pose and
shape and a 60 k-point scan of it, head turned and elbows flexed. Prints the ratio gated / plain.

    python benchmarks/bench_standing.py [--repeat 5]
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np

from bodyspace.data.template import load_template
from bodyspace.measure import evaluate, load_measurement_set
from bodyspace.mesh.geometry import sample_surface, vertex_normals
from bodyspace.register.pose_fit import PoseState
from bodyspace.register.pose_refit import standing_body
from bodyspace.rig.posing import pose_bodies
from bodyspace.synth.phenotype import PhenotypeModel
from bodyspace.synth.poses import load_pose_library


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--repeat", type=int, default=5)
    args = ap.parse_args()
    template = load_template()
    mset = load_measurement_set()
    rig = template.rigs["default"]
    rest = PhenotypeModel(template).vertices(np.full((1, 11), 0.5))[0]
    truth = evaluate(mset, rest, template.faces, check_scale=False)["neck_girth"].value
    print(f"load {os.getloadavg()[0]:.1f}; neck girth of the rest body {1000 * truth:.1f} mm")
    for pose in ("head_turn_left", "elbows_flexed"):
        R = np.asarray(load_pose_library().rotations(pose, rig))
        state = PoseState(rest, R, 1.0, np.zeros(3))
        x = pose_bodies(rest, rig, R, weights="smoothed", faces=template.faces)
        points, face, _ = sample_surface(x, template.faces, 60_000, 0)
        normals = vertex_normals(x, template.faces)[template.faces[face, 0]]
        times = {"plain": [], "gated": []}
        bodies = {}
        for _ in range(args.repeat):         # interleaved, so that both see the same load
            for name, su in (("plain", None), ("gated", "default")):
                kw = {} if su == "default" else {"skin_uncertainty": None}
                t = time.perf_counter()
                bodies[name] = standing_body(x, template.faces, template, state, points=points, normals=normals, **kw)
                times[name].append(time.perf_counter() - t)
        neck = {k: evaluate(mset, v, template.faces, check_scale=False)["neck_girth"].value for k, v in bodies.items()}
        tp, tg = np.median(times["plain"]), np.median(times["gated"])
        print(f"{pose} (smoothed weights): neck error plain {1000 * (neck['plain'] - truth):+.1f} mm, gated "
              f"{1000 * (neck['gated'] - truth):+.1f} mm; time plain {tp:.3f} s, gated {tg:.3f} s, "
              f"RATIO gated / plain {tg / tp:.2f}")
    print(f"load {os.getloadavg()[0]:.1f}")


if __name__ == "__main__":
    main()
