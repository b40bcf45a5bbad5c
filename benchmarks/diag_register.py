"""Where the registration error comes from: per stage, normal against tangential, per body region.

For each test scan (``synth.scans.raw_scan``, the benchmark's seeds and poses) ``register_scan``
runs with a ``trace`` callback and every stage's body (alignment, model fit, each pose round and
model refit, NICP, final) is scored against the truth: mean correspondence error, split into its
part along the true surface normal and its tangential part, the mean distance to the true
surface, and the correspondence error per region (the dominant bone's family: head, torso, arms,
hands, legs, feet).

    python benchmarks/diag_register.py [--scans 4] [--points 80000] [--landmarks]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from bodyspace.data.template import load_template
from bodyspace.mesh.geometry import vertex_normals
from bodyspace.register.model_fit import phenotype_basis
from bodyspace.register.pipeline import register_scan
from bodyspace.studies.registration import SURFACE_LANDMARKS, registration_errors
from bodyspace.synth.foreign import to_frame
from bodyspace.synth.phenotype import PhenotypeModel
from bodyspace.synth.scans import raw_scan

POSES = ("rest", "elbows_flexed", "step_forward_left", "hands_on_hips", "wide_stance", "t_pose")
# Region of a vertex: the first of these stems found in its dominant bone's name or an ancestor's.
REGIONS = (("hands", ("wrist", "finger", "metacarpal", "thumb")), ("feet", ("foot", "toe")),
           ("head", ("head", "jaw", "eye", "tongue", "neck", "ear", "levator", "oris", "orbicularis", "temporalis",
                     "risorius", "special")),
           ("arms", ("shoulder", "upperarm", "lowerarm")), ("legs", ("upperleg", "lowerleg")),
           ("torso", ("spine", "root", "pelvis", "clavicle", "breast")))


def vertex_regions(template) -> tuple[list[str], np.ndarray]:
    """Region names and each vertex's region index (V,), from the default rig's skin weights."""
    rig = template.rigs["default"]
    W = rig.weights.tocsr()
    dominant = np.asarray(W.argmax(axis=1)).ravel()
    names = [r for r, _ in REGIONS]

    def region(b):
        while b >= 0:
            n = rig.bone_names[b].lower()
            for k, (_, stems) in enumerate(REGIONS):
                if any(s in n for s in stems):
                    return k
            b = int(rig.parents[b])
        return names.index("torso")

    per_bone = np.array([region(b) for b in range(rig.n_bones)])
    return names, per_bone[dominant]


def score(vertices, template, scan, regions, region_names) -> dict:
    """Errors of a stage's body (V, 3) (the scan's frame) against the truth: registration_errors,
    the mean |normal| and tangential parts of the correspondence error (mm), and its mean per
    region."""
    scale = float(scan.frame["scale"])
    truth = to_frame(scan.body, **scan.frame)
    # Normals in the scan frame: the frame is a similarity, so the body's normals turn with it.
    tn = vertex_normals(truth, template.faces)
    e = (vertices - truth) / scale * 1000.0
    en = (e * tn).sum(1)
    et = np.linalg.norm(e - en[:, None] * tn, axis=1)
    out = registration_errors(vertices, template.faces, scan)
    out["normal_mm"] = float(np.abs(en).mean())
    out["tangential_mm"] = float(et.mean())
    c = np.linalg.norm(e, axis=1)
    out["regions"] = {n: float(c[regions == k].mean()) for k, n in enumerate(region_names)}
    return out


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--scans", type=int, default=4)
    ap.add_argument("--first", type=int, default=0)
    ap.add_argument("--points", type=int, default=80_000)
    ap.add_argument("--landmarks", action="store_true")
    args = ap.parse_args()
    template = load_template()
    pm = PhenotypeModel(template)
    phenotype_basis(template)
    names, regions = vertex_regions(template)
    print("regions:", {n: int((regions == k).sum()) for k, n in enumerate(names)})
    for i in range(args.first, args.first + args.scans):
        scan = raw_scan(template, pm, 100 + i, pose=POSES[i % len(POSES)], n_points=args.points)
        lms = {n: scan.landmarks[n] for n in SURFACE_LANDMARKS} if args.landmarks else None
        rows = []
        t = time.perf_counter()
        reg = register_scan(scan.points, template=template, landmarks=lms, check=False,
                            trace=lambda stage, v: rows.append((stage, score(v, template, scan, regions, names))))
        sec = time.perf_counter() - t
        rows.append(("final", score(reg.vertices, template, scan, regions, names)))
        print(f"\nscan {i} ({scan.pose}) {'13 landmarks' if lms else 'no landmarks'}: {sec:.1f} s, quality "
              f"{reg.quality.quality:.2f}, stages {({k: round(v, 1) for k, v in reg.seconds.items()})}")
        print(f"  {'stage':10s} {'corr':>6s} {'norm':>6s} {'tang':>6s} {'surf':>6s} {'fold':>5s}  "
              + " ".join(f"{n:>6s}" for n in names))
        for stage, e in rows:
            print(f"  {stage:10s} {e['correspondence_mm']:6.1f} {e['normal_mm']:6.1f} {e['tangential_mm']:6.1f} "
                  f"{e['surface_mm']:6.2f} {e['folded']:5d}  " + " ".join(f"{e['regions'][n]:6.1f}" for n in names),
                  flush=True)


if __name__ == "__main__":
    main()
