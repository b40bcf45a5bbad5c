"""Registration of raw test scans (issue 15): bodyspace's pipeline against trimesh's Amberg NICP.

Test scans (``synth.scans.raw_scan``): edge-of-population bodies in standing poses, ~80 k points,
σ = 2 mm, 2-5 % outliers, holes (head top, soles, armpits, crotch), millimetres, Z up, turned.
Per scan, in one process:
- bodyspace ``register_scan`` without landmarks, and with the 13 surface landmarks;
- the baseline: trimesh ``registration.nricp_amberg`` from the template's mean body after the
  landmark similarity alignment (13 landmarks), its default steps.
Errors against the truth (``studies.registration.registration_errors``): mean correspondence
error, mean distance to the true surface, folded triangles; and wall time.

    python benchmarks/bench_register.py [--scans 3] [--points 80000]
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import trimesh

from _common import report
from bodyspace.data.template import load_template
from bodyspace.measure.definitions import load_measurement_set
from bodyspace.register.align import similarity_from_landmarks
from bodyspace.register.model_fit import phenotype_basis
from bodyspace.register.pipeline import register_scan
from bodyspace.studies.registration import SURFACE_LANDMARKS, registration_errors
from bodyspace.synth.phenotype import PhenotypeModel
from bodyspace.synth.scans import raw_scan

POSES = ("rest", "elbows_flexed", "step_forward_left", "hands_on_hips", "wide_stance", "t_pose")


def amberg(scan, template, mset):
    """trimesh's nricp_amberg after a 13-landmark similarity (scan frame)."""
    ids = np.array([int(mset.landmarks[n][0][0]) for n in SURFACE_LANDMARKS])
    target = np.array([scan.landmarks[n] for n in SURFACE_LANDMARKS])
    s, R, t = similarity_from_landmarks(template.vertices[ids], target)
    source = trimesh.Trimesh(s * template.vertices @ R.T + t, template.faces, process=False)
    out = trimesh.registration.nricp_amberg(source, np.asarray(scan.points), source_landmarks=ids,
                                            target_positions=target, distance_threshold=50.0, use_faces=False)
    return np.asarray(out)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--scans", type=int, default=3)
    ap.add_argument("--points", type=int, default=80_000)
    args = ap.parse_args()
    template = load_template()
    pm = PhenotypeModel(template)
    mset = load_measurement_set()
    phenotype_basis(template)          # built once per process (cached), not timed
    rows = {"bodyspace, no landmarks": [], "bodyspace, 13 landmarks": [], "trimesh nricp_amberg, 13 landmarks": []}
    for i in range(args.scans):
        scan = raw_scan(template, pm, 100 + i, pose=POSES[i % len(POSES)], n_points=args.points)
        lms = {n: scan.landmarks[n] for n in SURFACE_LANDMARKS}
        for name, run in (("bodyspace, no landmarks", lambda: register_scan(scan.points, template=template, check=False).vertices),
                          ("bodyspace, 13 landmarks", lambda: register_scan(scan.points, template=template, landmarks=lms,
                                                                            check=False).vertices),
                          ("trimesh nricp_amberg, 13 landmarks", lambda: amberg(scan, template, mset))):
            t = time.perf_counter()
            v = run()
            sec = time.perf_counter() - t
            e = registration_errors(v, template.faces, scan)
            e["seconds"] = sec
            rows[name].append(e)
            print(f"scan {i} ({scan.pose}, {len(scan.points)} points) {name}: correspondence {e['correspondence_mm']:.1f} mm "
                  f"(p95 {e['correspondence_p95_mm']:.1f}), surface {e['surface_mm']:.2f} mm, folded {e['folded']} "
                  f"(truth {e['folded_truth']}), {sec:.1f} s", flush=True)
    print("\nmean over scans:")
    for name, r in rows.items():
        print(f"  {name}: correspondence {np.mean([e['correspondence_mm'] for e in r]):.1f} mm, surface "
              f"{np.mean([e['surface_mm'] for e in r]):.2f} mm, folded {np.mean([e['folded'] for e in r]):.0f}, "
              f"{np.mean([e['seconds'] for e in r]):.1f} s")
    ours = np.mean([e["seconds"] for e in rows["bodyspace, 13 landmarks"]])
    base = np.mean([e["seconds"] for e in rows["trimesh nricp_amberg, 13 landmarks"]])
    report("register (13 landmarks) vs nricp_amberg", ours, base, 1000, "milliscans")


if __name__ == "__main__":
    main()
