"""Study (issue 12 §4): the refined RRE basis (``ShapeSpace(basis="refined")``,
``shape.refine.refine_basis``) against the vertex order and vertex PCA, on held-out subjects.

Per fold (one held-out subject, leave-one-subject-out as ``studies.generalization``): an RRE
encoder fitted on all scans (as ``BodyModel.fit`` would), ``ShapeSpace(basis="vertex")`` on the
other subjects' scans (40 components), the same refined (``--levels``, default
``refine.DEFAULT_LEVELS``), vertex PCA on the same scans; every held-out scan fitted at each k
with both projections (code projection, vertex fit); mean vertex error (mm) after a rigid
alignment, the refined vertex fit's per scan, CPU seconds a mesh of the vertex fit, and the
refinement's cost and training error per level.

With ``--bases code,vertex,refined`` the code order (Hasler's) is measured too; ``all`` among
``--components`` measures every component the training scans give (N - 1): all orders span the
same space there and the code projection is the same, so it is measured once, on the vertex order.
Each fold's numbers go to ``--json`` (per fold, per scan and pose), so folds can run in separate
processes (``--folds 0,2,4`` and ``--folds 1,3,5``) and ``--merge A.json B.json`` prints the table of all.

Run: python benchmarks/study_basis_refinement.py DB [--folds 0,1|all] [--levels 4:8,8:16]
[--components 1,4,8,16,32,all] [--bases vertex,refined] [--json OUT.json]; DB e.g. ``bodyspace
population --subjects 8 --pose-set standard --seed 0 --out pop8s`` (every subject in the same
poses) or ``--subjects 24 --poses 5 --seed 0`` (poses drawn per subject).
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

N_COMPONENTS = 40  # at most (fewer on small databases), unless "all" is asked


def errors_mm(bodies, scans, parts):
    """Mean vertex distance (mm) of each body from its scan aligned rigidly onto it."""
    return np.array([np.linalg.norm(x - align_parts(y, x, parts), axis=1).mean()
                     for x, y in zip(bodies, scans)]) * 1000


def summary(folds: dict) -> None:
    """Mean over folds and held-out scans, per model and k, and the folds where RRE loses."""
    first = max(folds.values(), key=lambda f: len(f["errors_mm"]))
    ks = list(first["errors_mm"])
    names = list(dict.fromkeys(n for k in ks for n in first["errors_mm"][k] if not n.endswith("cpu s")))
    print(f"{len(folds)} folds ({', '.join(folds)}), {sum(len(f['poses']) for f in folds.values())} held-out scans")
    print("| model | " + " | ".join(f"k={k}" for k in ks) + " |")
    print("|---|" + "---|" * len(ks))
    for n in names:
        cells = []
        for k in ks:
            v = [np.mean(f["errors_mm"][k][n]) for f in folds.values() if n in f["errors_mm"].get(k, {})]
            cells.append(f"{np.mean(v):.1f}" if v else "")
        n_folds = sum(any(n in f["errors_mm"].get(k, {}) for k in ks) for f in folds.values())
        print(f"| {n} ({n_folds} folds) | " + " | ".join(cells) + " |")
    cpu = {}
    for k in ks:
        for n in first["errors_mm"][k]:
            if n.endswith("cpu s"):
                cpu.setdefault(n, {})[k] = np.mean([f["errors_mm"][k][n] for f in folds.values()
                                                    if n in f["errors_mm"].get(k, {})])
    for n, row in cpu.items():
        print(f"| {n} a mesh | " + " | ".join(f"{row[k]:.2f}" if k in row else "" for k in ks) + " |")
    for k in ks:
        for n in names:
            if n.startswith("refined vertex fit") or n.startswith("vertex order vertex fit"):
                lost = [fo for fo, f in folds.items() if n in f["errors_mm"].get(k, {})
                        and np.mean(f["errors_mm"][k][n]) > np.mean(f["errors_mm"][k]["vertex PCA"])]
                if lost:
                    print(f"k = {k}, {n}: above vertex PCA on folds {', '.join(lost)}")
    cost = [f["refine_s"] for f in folds.values() if f.get("refine_s")]
    if cost:
        print(f"refinement: {np.mean([c[0] for c in cost]):.0f} s wall, {np.mean([c[1] for c in cost]):.0f} s CPU a fold")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("db", nargs="?")
    ap.add_argument("--folds", default="0,1")
    ap.add_argument("--levels", default=",".join(f"{k}:{s}" for k, s in DEFAULT_LEVELS), help="k:span per level")
    ap.add_argument("--components", default="1,4,8,16,32")
    ap.add_argument("--bases", default="vertex,refined")
    ap.add_argument("--json", default=None)
    ap.add_argument("--merge", nargs="+", default=None, help="JSON files of earlier runs: print their table")
    args = ap.parse_args()
    if args.merge:
        folds = {}
        for f in args.merge:
            folds.update(json.loads(Path(f).read_text()))
        summary(dict(sorted(folds.items(), key=lambda kv: int(kv[0]))))
        return
    with_all = "all" in args.components.split(",")
    ks = [int(k) for k in args.components.split(",") if k != "all"]
    bases = args.bases.split(",")
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
    names = {"code": "code order", "vertex": "vertex order", "refined": "refined"}
    folds = range(len(held)) if args.folds == "all" else [int(f) for f in args.folds.split(",")]
    for fold in folds:
        test = subjects == held[fold]
        n_train = int((~test).sum())
        n_comp = n_train - 1 if with_all else min(N_COMPONENTS, n_train - 2)
        fold_ks = ks + ([n_comp] if with_all else [])
        spaces, cost = {}, None
        for b in bases:
            t, c = time.perf_counter(), time.process_time()
            spaces[b] = ShapeSpace(enc, n_comp, solver="full", basis=b,
                                   refine_levels=levels if b == "refined" else None).fit(codes[~test],
                                                                                         vertices=scans[~test])
            if b == "refined":
                cost = (time.perf_counter() - t, time.process_time() - c)
        vspace = ShapeSpace(venc, n_comp, solver="full").fit(vcodes[~test])
        rows = {}
        for k in fold_ks:
            row = {"vertex PCA": errors_mm(vspace.reconstruct(vspace.transform(vcodes[test])[:, :k]), scans[test], parts)}
            # At all components every order spans the same space: one of them measures it.
            for b in (bases if k < n_comp else ["vertex" if "vertex" in bases else bases[0]]):
                sp, name = spaces[b], (names[b] if k < n_comp else "RRE")
                z = sp.transform(codes[test])[:, :k]
                row[f"{name} code"] = errors_mm(sp.reconstruct(z), scans[test], parts)
                c0 = time.process_time()
                fz = fit_coefficients(sp, scans[test], k)
                row[f"{name} cpu s"] = np.array([(time.process_time() - c0) / int(test.sum())])
                row[f"{name} vertex fit"] = errors_mm(sp.reconstruct(fz.coefficients[:, :k]), scans[test], parts)
            key = str(k) if k < n_comp else "all"
            rows[key] = {n: v.tolist() for n, v in row.items()}
            print(f"fold {fold} k = {key}: " + ", ".join(f"{n} {np.mean(v):.1f}" for n, v in row.items()), flush=True)
            for n, v in row.items():
                if n.endswith("vertex fit") or n == "vertex PCA":
                    print(f"    {n}: " + " / ".join(f"{p} {e:.1f}" for p, e in zip(poses[test], v)), flush=True)
        out[fold] = {"errors_mm": rows, "poses": poses[test].tolist(), "n_components": n_comp}
        if cost is not None:
            rep = spaces["refined"].refine_report_
            train = "; ".join(f"k = {k} in {s}: " + " → ".join(f"{1000 * e:.1f}" for e in errs) + " mm"
                              for (k, s), errs in zip(rep.levels.tolist(), rep.train_error_m))
            print(f"fold {fold}: refinement {cost[0]:.0f} s wall, {cost[1]:.0f} s CPU; training scans' error per "
                  f"level ({train})", flush=True)
            out[fold].update(refine_s=cost, train_error_m=rep.train_error_m)
        if args.json:  # after every fold: a killed run keeps its finished folds
            Path(args.json).write_text(json.dumps(out, indent=1))
    summary({str(f): v for f, v in out.items()})


if __name__ == "__main__":
    main()
