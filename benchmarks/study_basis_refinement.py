"""Study (issue 12 §4): one alternating refinement step of the vertex-ordered RRE basis, measured
on held-out subjects. An experiment, not a library feature yet (docs/encoding.md, "What limits
k = 4 and 8").

Per fold (one held-out subject, leave-one-subject-out as ``studies.generalization``):

1. ``ShapeSpace(basis="vertex")`` on the other subjects' scans (40 components).
2. Fit every *training* scan with the first ``--k`` components in vertex space
   (``fit_coefficients``, 6 steps, 2 Jacobians): coefficients z_i, residual r_i.
3. At each fitted body, the decoder's Jacobian on the first ``--span`` components S (exact
   tangents, rigid motions projected out), and the Levenberg-Marquardt step d_i inside span(S)
   that the linearization says would fit the scan: ``w_i = (z_i, 0) + d_i`` (``--span`` numbers)
   is where scan i wants to be in S's coordinates.
4. New first ``--span`` components: the principal directions of the w_i (uncentred: the mean
   code stays), mapped back through S, so they span the same space as before (components past
   ``--span`` and the nesting are kept).
5. Held-out scans fitted with the old and the new basis at each k, against vertex PCA.

Cost: step 2 is one vertex fit per training scan (~2 CPU s each at k = 8), step 3 one tangent
and ``--span`` tangent directions per training scan.

Run: python benchmarks/study_basis_refinement.py DB [--folds 0,1] [--k 8] [--span 24]
[--components 4,8,16]; DB e.g. ``bodyspace population --subjects 24 --poses 5 --seed 0 --out pop24``.
"""

from __future__ import annotations

import argparse
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
from bodyspace.shape.vertex_fit import _rigid_basis, align_parts
from bodyspace.studies.scans import rows_by_subject

N_COMPONENTS = 40  # at most (fewer on small databases)
DAMPING = 1e-2  # of the mean diagonal of J^T J, as the step in vertex_fit


def errors_mm(bodies, scans, parts):
    """Mean vertex distance (mm) of each body from its scan aligned rigidly onto it."""
    return np.array([np.linalg.norm(x - align_parts(y, x, parts), axis=1).mean()
                     for x, y in zip(bodies, scans)]) * 1000


def refine(space, scans, k, span, parts):
    """Components (K, D): the first ``span`` re-chosen by one alternating step (module docstring)."""
    enc = space.encoder
    s = space.components_[:span]
    fit = fit_coefficients(space, scans, k, max_iter=6, max_jacobians=2)
    wanted = np.zeros((len(scans), span))
    for i, y in enumerate(scans):
        z = fit.coefficients[i, :k]
        tan = enc.tangent(space.mean_ + z @ space.components_[:k])
        r = tan.vertices - align_parts(y, tan.vertices, parts)
        jac = tan.jvp(s).reshape(span, -1).T
        rigid = _rigid_basis(tan.vertices, parts)
        jac -= rigid @ (rigid.T @ jac)
        jtj = jac.T @ jac
        step = -np.linalg.solve(jtj + DAMPING * np.trace(jtj) / span * np.eye(span), jac.T @ r.ravel())
        wanted[i, :k] = z
        wanted[i] += step
    _, _, vt = np.linalg.svd(wanted, full_matrices=False)
    return np.vstack([vt @ s, space.components_[span:]]), float(fit.error_m.mean() * 1000)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("db")
    ap.add_argument("--folds", default="0,1")
    ap.add_argument("--k", type=int, default=8)
    ap.add_argument("--span", type=int, default=24)
    ap.add_argument("--components", default="4,8,16")
    args = ap.parse_args()
    ks = [int(k) for k in args.components.split(",")]
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
    print("| fold (held-out poses) | k | vertex PCA mm | RRE vertex order mm | refined mm | refined per scan |")
    print("|---|---|---|---|---|---|")
    for fold in (int(f) for f in args.folds.split(",")):
        test = subjects == held[fold]
        n_comp = min(N_COMPONENTS, int((~test).sum()) - 2)
        t = time.perf_counter()
        space = ShapeSpace(enc, n_comp, solver="full", basis="vertex").fit(codes[~test], vertices=scans[~test])
        vspace = ShapeSpace(venc, n_comp, solver="full").fit(vcodes[~test])
        comps, train_mm = refine(space, scans[~test], args.k, args.span, parts)
        refined = ShapeSpace(enc, n_comp, solver="full", basis="vertex").fit(codes[~test],
                                                                                   vertices=scans[~test])
        refined.components_ = comps
        cost = time.perf_counter() - t
        for k in ks:
            vz = vspace.transform(vcodes[test])[:, :k]
            row = [errors_mm(vspace.reconstruct(vz), scans[test], parts)]
            for sp in (space, refined):
                fz = fit_coefficients(sp, scans[test], k)
                row.append(errors_mm(sp.reconstruct(fz.coefficients[:, :k]), scans[test], parts))
            print(f"| {fold} ({', '.join(poses[test])}) | {k} | {row[0].mean():.1f} | {row[1].mean():.1f} | "
                  f"{row[2].mean():.1f} | {' / '.join(f'{e:.1f}' for e in row[2])} |", flush=True)
        print(f"fold {fold}: training fit at k = {args.k}: {train_mm:.1f} mm; refinement {cost:.0f} s", flush=True)


if __name__ == "__main__":
    main()
