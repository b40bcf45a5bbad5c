"""Study (issue 12 §4): the refined RRE basis (``ShapeSpace(basis="refined")``,
``shape.refine.refine_basis``) against the vertex order and vertex PCA, on held-out subjects.

Per fold (one held-out subject, leave-one-subject-out as ``studies.generalization``): an RRE
encoder fitted on all scans (as ``BodyModel.fit`` would), ``ShapeSpace(basis="vertex")`` on the
other subjects' scans (40 components), the same refined (``--levels``, default
``refine.DEFAULT_LEVELS``), vertex PCA on the same scans; every held-out scan fitted at each k
with both projections (code projection, vertex fit); mean vertex error (mm) after a rigid
alignment, the refined vertex fit's per scan, CPU seconds a mesh of the vertex fit, and the
refinement's cost and training error per level.

Run: python benchmarks/study_basis_refinement.py DB [--folds 0,1] [--levels 4:8,8:16]
[--components 1,4,8,16,32] [--json OUT.json]; DB e.g. ``bodyspace population --subjects 24
--poses 5 --seed 0 --out pop24``.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

try:
    import bodyspace  # noqa: F401
except ImportError:  # run from a source checkout without installing
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "src"))

import numpy as np

from bodyspace.data.database import ScanDatabase
from bodyspace.data.template import load_template
from bodyspace.encoding import RelativeRotationEncoder, VertexEncoder
from bodyspace.shape import ShapeSpace, fit_coefficients
from bodyspace.shape.refine import DEFAULT_LEVELS
from bodyspace.shape.vertex_fit import align_parts
from bodyspace.studies.scans import rows_by_subject

N_COMPONENTS = 40  # at most (fewer on small databases)


def errors_mm(bodies, scans, parts):
    """Mean vertex distance (mm) of each body from its scan aligned rigidly onto it."""
    return np.array([np.linalg.norm(x - align_parts(y, x, parts), axis=1).mean()
                     for x, y in zip(bodies, scans)]) * 1000


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("db")
    ap.add_argument("--folds", default="0,1")
    ap.add_argument("--levels", default=",".join(f"{k}:{s}" for k, s in DEFAULT_LEVELS), help="k:span per level")
    ap.add_argument("--components", default="1,4,8,16,32")
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    ks = [int(k) for k in args.components.split(",")]
    levels = [tuple(int(v) for v in lv.split(":")) for lv in args.levels.split(",")]
    db = ScanDatabase.load(args.db)
    template = load_template()
    scans = np.asarray(db.read(np.arange(db.n_scans)), dtype=float)
    enc = RelativeRotationEncoder(template.vertices, template.faces, on_flipped="ignore").fit(scans)
    codes = enc.encode(scans)
    venc = VertexEncoder(template.vertices, template.faces).fit(scans)
    vcodes = venc.encode(scans)
    subjects = np.asarray(db.scans["subject"])
    poses = np.asarray(db.scans["pose"])
    held = list(rows_by_subject(db, np.arange(db.n_scans)))
    parts = [np.arange(enc.n_vertices)]
    out = {}
    print("| fold (held-out poses) | k | vertex PCA | vertex order: code / vertex fit | refined: code / vertex fit "
          "| refined vertex fit per scan | CPU s a mesh (vertex order / refined) |")
    print("|---|---|---|---|---|---|---|")
    for fold in (int(f) for f in args.folds.split(",")):
        test = subjects == held[fold]
        n_comp = min(N_COMPONENTS, int((~test).sum()) - 2)
        space = ShapeSpace(enc, n_comp, solver="full", basis="vertex").fit(codes[~test], vertices=scans[~test])
        vspace = ShapeSpace(venc, n_comp, solver="full").fit(vcodes[~test])
        t, c = time.perf_counter(), time.process_time()
        refined = ShapeSpace(enc, n_comp, solver="full", basis="refined",
                             refine_levels=levels).fit(codes[~test], vertices=scans[~test])
        cost = (time.perf_counter() - t, time.process_time() - c)
        rep = refined.refine_report_
        rows = {}
        for k in ks:
            row = {"vertex PCA": errors_mm(vspace.reconstruct(vspace.transform(vcodes[test])[:, :k]), scans[test], parts)}
            for name, sp in (("vertex order", space), ("refined", refined)):
                z = sp.transform(codes[test])[:, :k]
                row[f"{name} code"] = errors_mm(sp.reconstruct(z), scans[test], parts)
                c0 = time.process_time()
                fz = fit_coefficients(sp, scans[test], k)
                row[f"{name} cpu s"] = np.array([(time.process_time() - c0) / int(test.sum())])
                row[f"{name} vertex fit"] = errors_mm(sp.reconstruct(fz.coefficients[:, :k]), scans[test], parts)
            rows[k] = {key: v.tolist() for key, v in row.items()}
            m = {key: float(np.mean(v)) for key, v in row.items()}
            print(f"| {fold} ({', '.join(poses[test])}) | {k} | {m['vertex PCA']:.1f} | {m['vertex order code']:.1f} / "
                  f"{m['vertex order vertex fit']:.1f} | {m['refined code']:.1f} / {m['refined vertex fit']:.1f} | "
                  f"{' / '.join(f'{e:.1f}' for e in row['refined vertex fit'])} | "
                  f"{m['vertex order cpu s']:.2f} / {m['refined cpu s']:.2f} |", flush=True)
        train = "; ".join(f"k = {k} in {s}: " + " → ".join(f"{1000 * e:.1f}" for e in errs) + " mm"
                          for (k, s), errs in zip(rep.levels.tolist(), rep.train_error_m))
        print(f"fold {fold}: refinement {cost[0]:.0f} s wall, {cost[1]:.0f} s CPU; training scans' error per level "
              f"({train})", flush=True)
        out[fold] = {"errors_mm": rows, "refine_s": cost, "train_error_m": rep.train_error_m}
    if args.json:
        Path(args.json).write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
