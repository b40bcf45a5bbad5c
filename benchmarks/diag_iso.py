"""Why a registered scan's measurements miss ISO 20685-1 (issue 15): per measurement, per stage.

For each test scan (``synth.scans.raw_scan``, bench_register's seeds, poses and point counts)
``register_scan`` runs once with a ``trace`` callback; the body after the pose and model fit
("pose 4") and after the NICP ("nicp") is measured against the true rest body's measurements:

- unposed as ``bodyspace register``'s measurements and bench_register are (``rig.unpose``: the
  pose estimated from the fit), and unposed with the *true* pose (``unpose_known`` with the
  pose library's rotations): what the first misses and the second does not is the pose
  estimate's (shape and pose traded), not the surface's;
- the registration's standing body (``Registration.standing``, what ``bodyspace register``
  measures: the model refitted to the scan, its rest body with the fit's normal offsets,
  ``register.pose_refit``), and the model's rest body alone;
- for the vertex-ring loops (Rupprecht's shoulder, breast, waist, hip size), the error of the
  true-pose rest body split into the part its error along the true normals makes and the part
  its tangential error makes (each added alone to the true rest body).

With ``--weights smoothed`` or ``--volume`` the scans are posed otherwise than the pipeline's
forward model (LBS with MakeHuman's weights), as a real body is.

    python benchmarks/diag_iso.py [--only 0,1,3] [--landmarks] [--points 50000,100000,150000,200000]
                                  [--weights smoothed] [--volume]
"""

from __future__ import annotations

import argparse
import os

import numpy as np

from bodyspace.data.template import load_template
from bodyspace.measure import evaluate
from bodyspace.measure.definitions import load_measurement_set
from bodyspace.measure.tolerances import iso_tolerance
from bodyspace.mesh.geometry import vertex_normals
from bodyspace.register.model_fit import phenotype_basis
from bodyspace.register.pipeline import register_scan
from bodyspace.rig.unpose import unpose, unpose_known
from bodyspace.studies.registration import SURFACE_LANDMARKS
from bodyspace.synth.foreign import from_frame
from bodyspace.synth.phenotype import PhenotypeModel
from bodyspace.synth.poses import load_pose_library
from bodyspace.synth.scans import raw_scan

POSES = ("rest", "elbows_flexed", "step_forward_left", "hands_on_hips", "wide_stance", "t_pose")
LOOPS = ("shoulder_size", "breast_size", "waist_size", "hip_size")


def ratios(rest, truth_rest, mset, faces) -> dict:
    """name → (error / ISO tolerance, error in the measurement's unit) of ``rest`` (V, 3)."""
    got, ref = evaluate(mset, rest, faces), evaluate(mset, truth_rest, faces)
    out = {}
    for name, m in got.items():
        r = ref[name].value
        if np.isnan(r) or np.isnan(m.value):
            continue
        tol, rel = iso_tolerance(name, m)
        d = (m.value - r) / r if rel else m.value - r
        out[name] = (d / tol, d)
    return out


def describe(r: dict) -> str:
    miss = sorted(((abs(v[0]), k) for k, v in r.items() if abs(v[0]) > 1.0), reverse=True)
    return (f"{sum(abs(v[0]) <= 1.0 for v in r.values())}/{len(r)} within; out: "
            + (", ".join(f"{k} {r[k][0]:+.1f}x" for _, k in miss) or "none"))


def loop_split(rest, truth_rest, mset, faces) -> str:
    """Each loop's error (mm) and the parts its normal and tangential vertex errors make."""
    defs = {m["name"]: m for m in mset.measurements}
    n = vertex_normals(truth_rest, faces)
    e = rest - rest.mean(axis=0) - (truth_rest - truth_rest.mean(axis=0))
    en = (e * n).sum(axis=1, keepdims=True) * n
    parts = []
    for name in LOOPS:
        ids = defs[name]["vertices"]

        def length(x):
            flat = x[ids] * np.array([1.0, 0.0, 1.0])
            return 1000.0 * np.linalg.norm(flat - np.roll(flat, -1, axis=0), axis=1).sum()

        base = length(truth_rest)
        parts.append(f"{name} {length(truth_rest + e) - base:+.1f} mm (normal {length(truth_rest + en) - base:+.1f}, "
                     f"tangential {length(truth_rest + e - en) - base:+.1f})")
    return "; ".join(parts)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--only", default="0,1,3", help="comma list of scan numbers (bench_register's)")
    ap.add_argument("--points", default="50000,100000,150000,200000")
    ap.add_argument("--landmarks", action="store_true", help="register with the 13 surface landmarks")
    ap.add_argument("--weights", default="original", help="the scans' skin weights: original or smoothed")
    ap.add_argument("--volume", action="store_true", help="pose the scans with the volume correction")
    args = ap.parse_args()
    template = load_template()
    rig = template.rigs["default"]
    pm = PhenotypeModel(template)
    mset = load_measurement_set()
    library = load_pose_library()
    phenotype_basis(template)
    points = [int(p) for p in args.points.split(",")]
    for i in (int(k) for k in args.only.split(",")):
        scan = raw_scan(template, pm, 100 + i, pose=POSES[i % len(POSES)], n_points=points[i % len(points)],
                        weights=args.weights, preserve_volume=args.volume)
        truth_rest = pm.vertices(scan.phenotype[None])[0]
        true_pose = np.asarray(library.rotations(scan.pose, rig))[None]
        stages = {}
        lms = {n: scan.landmarks[n] for n in SURFACE_LANDMARKS} if args.landmarks else None
        reg = register_scan(scan.points, template=template, landmarks=lms, check=False,
                            trace=lambda stage, v: stages.__setitem__(stage, v))
        print(f"scan {i} ({scan.pose}, {len(scan.points)} points, {'13' if lms else 'no'} landmarks, weights "
              f"{args.weights}{', volume corrected' if args.volume else ''}, load {os.getloadavg()[0]:.1f})")
        for stage in ("pose 4", "nicp"):
            fit = from_frame(stages[stage], **scan.frame)
            estimated = unpose(fit, rig, mesh_name="the fit")[0]
            known = unpose_known(fit[None], rig, true_pose)[0][0]
            print(f"  {stage}, unposed: {describe(ratios(estimated, truth_rest, mset, template.faces))}")
            print(f"  {stage}, true pose: {describe(ratios(known, truth_rest, mset, template.faces))}")
            print(f"  {stage}, loops (true pose): {loop_split(known, truth_rest, mset, template.faces)}")
        own = unpose_known(reg.internal[None], rig, reg.pose.rotations[None])[0][0]    # the fit's own frame
        refit = reg.standing_pose
        print(f"  nicp, unposed with the pose fit's rotations: "
              f"{describe(ratios(own, truth_rest, mset, template.faces))}")
        print(f"  model refitted, its rest body: "
              f"{describe(ratios(refit.scale * refit.rest, truth_rest, mset, template.faces))}")
        print(f"  standing (measured; {reg.seconds['standing']:.1f} s): "
              f"{describe(ratios(reg.standing, truth_rest, mset, template.faces))}")
        print(f"  standing, loops: {loop_split(reg.standing, truth_rest, mset, template.faces)}")


if __name__ == "__main__":
    main()
