"""Registration of raw test scans (issue 15): bodyspace's pipeline against trimesh's Amberg NICP.

Test scans (``synth.scans.raw_scan``): edge-of-population bodies in standing poses, ~80 k points,
σ = 2 mm, 2-5 % outliers, holes (head top, soles, armpits, crotch), millimetres, Z up, turned.
Per scan, in one process:
- bodyspace ``register_scan`` without landmarks, and with the 13 surface landmarks;
- the baseline: trimesh ``registration.nricp_amberg`` from the template's mean body after the
  landmark similarity alignment (13 landmarks), its default steps.
Errors against the truth (``studies.registration.registration_errors``): mean correspondence
error, mean distance to the true surface, folded triangles; wall time and this process's CPU
time, its child processes' included (the short fits run on two forked processes; on a machine
shared with other jobs the wall time says more about the load than the code). Also the mean distance
of the measurement set's 25 landmarks on the fit from the true body's, and the measurements of
the fit standing (``Registration.standing``), as ``bodyspace register`` measures it, against the true rest body's: how many are
within the ISO 20685-1 maximum allowable error of their category (``measure.tolerances``: heights,
small circumferences and breadths 4 mm, segment lengths and depths 5 mm, large circumferences (the
trunk's girths and Rupprecht's rings) 9 mm; volume, area, mass, BMI 1 %). A count per scan, not the
standard's protocol over a sample of subjects: that is benchmarks/study_iso.py.

Folds: the fit's folded triangles, and those it *adds*: folded in the fit but not in the true
body (the true LBS-posed bodies fold 4-35 triangles themselves, in armpits and groins).
Each bodyspace row also gives the fit's quality verdict (``quality.assess``: accepted or refused,
the body parts that failed) and the limbs the per-part check restarted.

    python benchmarks/bench_register.py [--scans 4] [--first 0] [--points 80000 | 50000,100000,150000,200000]
                                        [--only 0,2] [--no-baseline]
"""

from __future__ import annotations

import argparse
import os
import resource
import time

import numpy as np
import trimesh

from _common import report
from bodyspace.data.template import load_template
from bodyspace.errors import MeshError
from bodyspace.measure import evaluate
from bodyspace.measure.definitions import load_measurement_set
from bodyspace.measure.tolerances import iso_tolerance
from bodyspace.rig.unpose import unpose
from bodyspace.synth.foreign import from_frame
from bodyspace.register.align import similarity_from_landmarks
from bodyspace.register.model_fit import phenotype_basis
from bodyspace.register.pipeline import register_scan
from bodyspace.rig.posing import folded_triangles
from bodyspace.studies.registration import SURFACE_LANDMARKS, registration_errors
from bodyspace.synth.phenotype import PhenotypeModel
from bodyspace.synth.scans import raw_scan

def cpu_seconds() -> float:
    """CPU time of this process and of its finished child processes (the forked short fits)."""
    children = resource.getrusage(resource.RUSAGE_CHILDREN)
    return time.process_time() + children.ru_utime + children.ru_stime


POSES = ("rest", "elbows_flexed", "step_forward_left", "hands_on_hips", "wide_stance", "t_pose")


def landmarks_and_measurements(vertices, scan, template, mset, truth_rest, standing=None):
    """Mean landmark error (mm) of the fit (scan frame) and (within ISO, measured, worst) of
    ``standing`` (a ``Registration.standing``, as ``bodyspace register`` measures), else of the
    fit unposed by ``rig.unpose``."""
    M = mset.landmark_matrix(template.n_vertices)
    fit = from_frame(vertices, **scan.frame)
    lm = 1000.0 * np.linalg.norm(M @ fit - M @ scan.body, axis=1).mean()
    try:
        rest = standing if standing is not None else unpose(fit, template.rigs["default"], mesh_name="the fit")[0]
    except MeshError:
        return lm, (0, 0, "not unposed")
    got = evaluate(mset, rest, template.faces)
    ref = evaluate(mset, truth_rest, template.faces)
    ok, n, worst = 0, 0, (0.0, "")
    for name, m in got.items():
        r = ref[name].value
        if np.isnan(r) or np.isnan(m.value):
            continue
        tol, rel = iso_tolerance(name, m)
        ratio = abs((m.value - r) / r if rel else m.value - r) / tol
        n += 1
        ok += ratio <= 1.0
        worst = max(worst, (ratio, name))
    return lm, (ok, n, f"{worst[1]} {worst[0]:.1f}x")


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
    ap.add_argument("--scans", type=int, default=4)
    ap.add_argument("--points", default="80000", help="points per scan, or a comma list cycled over the scans")
    ap.add_argument("--only", default=None, help="comma list of scan numbers to run (default all)")
    ap.add_argument("--first", type=int, default=0, help="the first scan's index (to split the scans over processes)")
    ap.add_argument("--no-baseline", action="store_true", help="skip trimesh's nricp_amberg")
    args = ap.parse_args()
    template = load_template()
    pm = PhenotypeModel(template)
    mset = load_measurement_set()
    phenotype_basis(template)          # built once per process (cached), not timed
    rows = {"bodyspace, no landmarks": [], "bodyspace, 13 landmarks": [], "trimesh nricp_amberg, 13 landmarks": []}
    points = [int(p) for p in str(args.points).split(",")]
    only = None if args.only is None else {int(k) for k in args.only.split(",")}
    for i in range(args.first, args.first + args.scans):
        if only is not None and i not in only:
            continue
        scan = raw_scan(template, pm, 100 + i, pose=POSES[i % len(POSES)], n_points=points[i % len(points)])
        truth_folded = folded_triangles(scan.body, template.faces)
        truth_rest = pm.vertices(scan.phenotype[None])[0]
        lms = {n: scan.landmarks[n] for n in SURFACE_LANDMARKS}
        for name, run in (("bodyspace, no landmarks", lambda: register_scan(scan.points, template=template, check=False)),
                          ("bodyspace, 13 landmarks", lambda: register_scan(scan.points, template=template, landmarks=lms,
                                                                            check=False)),
                          ("trimesh nricp_amberg, 13 landmarks", lambda: amberg(scan, template, mset))):
            if args.no_baseline and name.startswith("trimesh"):
                continue
            t, c = time.perf_counter(), cpu_seconds()
            v = run()
            sec, cpu = time.perf_counter() - t, cpu_seconds() - c
            verdict, standing = "", None
            if not isinstance(v, np.ndarray):       # a Registration: its quality verdict, per body part
                q = v.quality
                verdict = (f", quality {q.quality:.2f} {'accepted' if q.accepted else 'REFUSED'}"
                           f"{' (' + ', '.join(p.name for p in q.failed_parts) + ')' if q.failed_parts else ''}"
                           f"{', restarted ' + ', '.join(v.restarted) if v.restarted else ''}")
                v, standing = v.vertices, v.standing
            e = registration_errors(v, template.faces, scan)
            e["seconds"], e["cpu_seconds"] = sec, cpu
            fit_folded = folded_triangles(from_frame(v, **scan.frame), template.faces)
            e["folds_added"] = int((fit_folded & ~truth_folded).sum())
            e["landmarks_mm"], iso = landmarks_and_measurements(v, scan, template, mset, truth_rest, standing)
            rows[name].append(e)
            print(f"scan {i} ({scan.pose}, {len(scan.points)} points) {name}: correspondence {e['correspondence_mm']:.1f} mm "
                  f"(p95 {e['correspondence_p95_mm']:.1f}), surface {e['surface_mm']:.2f} mm, folded {e['folded']} "
                  f"(truth {e['folded_truth']}, added {e['folds_added']}), {sec:.1f} s (CPU {cpu:.1f} s, load "
                  f"{os.getloadavg()[0]:.1f}), landmarks {e['landmarks_mm']:.1f} mm, "
                  f"ISO 20685-1 {iso[0]}/{iso[1]} (worst {iso[2]}){verdict}", flush=True)
    print("\nmean over scans:")
    for name, r in rows.items():
        print(f"  {name}: correspondence {np.mean([e['correspondence_mm'] for e in r]):.1f} mm, surface "
              f"{np.mean([e['surface_mm'] for e in r]):.2f} mm, folded {np.mean([e['folded'] for e in r]):.0f}, "
              f"{np.mean([e['seconds'] for e in r]):.1f} s (CPU {np.mean([e['cpu_seconds'] for e in r]):.1f} s), landmarks {np.mean([e['landmarks_mm'] for e in r]):.1f} mm"
              if r else f"  {name}: not run")
    if args.no_baseline:
        return
    ours = np.mean([e["seconds"] for e in rows["bodyspace, 13 landmarks"]])
    base = np.mean([e["seconds"] for e in rows["trimesh nricp_amberg, 13 landmarks"]])
    report("register (13 landmarks) vs nricp_amberg", ours, base, 1000, "milliscans")


if __name__ == "__main__":
    main()
