"""Where the study's errors come from (benchmarks/study_iso.py's saved scans; issue 15).

For every accepted scan of a study folder, the scan is made again (``study_iso.scan_spec``) and
each measurement's error against the true rest body is taken on:

- ``truth unposed``: the true posed body with the true pose undone (``unpose_known``): what the
  measurement and LBS unposing alone leave (not zero on scans posed with another skinning);
- ``fit, true pose``: the registered mesh (rigidly aligned to the true posed body, Kabsch over
  all vertices) with the true pose undone: the surface fit's error alone;
- ``model rest``: the refitted model's rest body (``Registration.standing_pose``);
- ``standing``: ``Registration.standing``, what ``bodyspace register`` measures.

Printed as the ISO 20685-1 protocol (``measure.agreement``) of each, side by side: mean (SD) in
mm and whether the 95 % interval is accepted.

    python benchmarks/diag_study_iso.py [--out /tmp/study_iso] [--scans 40]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from study_iso import scan_spec
from bodyspace.data.template import load_template
from bodyspace.measure import evaluate
from bodyspace.measure.agreement import agreement
from bodyspace.measure.definitions import load_measurement_set
from bodyspace.measure.tolerances import iso_categories
from bodyspace.rig.unpose import unpose_known
from bodyspace.synth.phenotype import PhenotypeModel
from bodyspace.synth.poses import load_pose_library
from bodyspace.synth.scans import raw_scan


def kabsch(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``a`` (V, 3) moved rigidly onto ``b`` (V, 3) (least squares, same vertex order)."""
    ca, cb = a.mean(axis=0), b.mean(axis=0)
    u, _, vt = np.linalg.svd((a - ca).T @ (b - cb))
    d = np.sign(np.linalg.det(u @ vt))
    r = u @ np.diag([1.0, 1.0, d]) @ vt
    return (a - ca) @ r + cb


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--out", default="/tmp/study_iso")
    ap.add_argument("--scans", type=int, default=40)
    ap.add_argument("--cache", default=None, help="JSON to keep the re-measured values in (default OUT/diag.json)")
    args = ap.parse_args()
    out = Path(args.out)
    cache_path = Path(args.cache) if args.cache else out / "diag.json"
    cache = json.loads(cache_path.read_text()) if cache_path.exists() else {}
    template = load_template()
    rig = template.rigs["default"]
    pm = PhenotypeModel(template)
    mset = load_measurement_set()
    library = load_pose_library()
    names = list(mset.names)
    cats = iso_categories(mset, template)
    kinds = ("truth unposed", "fit, true pose", "model rest", "standing")
    rows = {k: [] for k in kinds}
    truths = []
    for i in range(args.scans):
        path = out / f"scan_{i:04d}.json"
        if not path.exists():
            continue
        row = json.loads(path.read_text())
        if not row.get("accepted") or not (out / f"scan_{i:04d}.npz").exists():
            continue
        if str(i) not in cache:
            spec = scan_spec(i)
            scan = raw_scan(template, pm, spec["seed"], pose=spec["pose"], n_points=spec["n_points"],
                            weights=spec["weights"], preserve_volume=spec["preserve_volume"])
            true_pose = np.asarray(library.rotations(scan.pose, rig))[None]
            with np.load(out / f"scan_{i:04d}.npz") as z:
                fit = kabsch(z["internal"], scan.body)
                bodies = {"truth unposed": unpose_known(scan.body[None], rig, true_pose)[0][0],
                          "fit, true pose": unpose_known(fit[None], rig, true_pose)[0][0],
                          "model rest": z["model_rest"], "standing": z["standing"], "truth": z["truth_rest"]}
            cache[str(i)] = {k: {n: float(m.value) for n, m in evaluate(mset, v, template.faces,
                                                                        check_scale=False).items()}
                             for k, v in bodies.items()}
            cache_path.write_text(json.dumps(cache))
        c = cache[str(i)]
        truths.append([c["truth"][n] for n in names])
        for k in kinds:
            rows[k].append([c[k][n] - c["truth"][n] for n in names])
    ref = np.array(truths)
    res = {k: agreement(np.array(v), names, [cats[n] for n in names], reference=ref) for k, v in rows.items()}
    print(f"{len(ref)} scans; per measurement: mean (SD) of the error, mm (% for the relative ones), "
          "+ accepted / - rejected by ISO 20685-1's interval")
    print(f"{'measurement':<18}" + "".join(f"{k:>22}" for k in kinds))
    for j, n in enumerate(names):
        cells = []
        for k in kinds:
            a = res[k][j]
            s = 100.0 if a.relative else 1000.0
            cells.append(f"{a.mean * s:+6.1f} ({a.sd * s:4.1f}) {'+' if a.accepted else '-'}")
        print(f"{n:<18}" + "".join(f"{c:>22}" for c in cells))
    print("accepted:" + "".join(f"{sum(a.accepted for a in res[k]):>22}" for k in kinds))


if __name__ == "__main__":
    main()
