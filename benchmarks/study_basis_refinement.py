"""Study (issue 12 §4): alternating refinement of the vertex-ordered RRE basis, measured on
held-out subjects. An experiment, not a library feature yet (docs/encoding.md, "What limits
k = 4 and 8").

Per fold (one held-out subject, leave-one-subject-out as ``studies.generalization``):

1. ``ShapeSpace(basis="vertex")`` on the other subjects' scans (40 components).
2. For each level (k, span), from the largest: fit every *training* scan with the first k
   components in vertex space (``fit_coefficients``, 6 steps, 2 Jacobians): coefficients z_i,
   residual r_i. At each fitted body, the decoder's Jacobian on the first ``span`` components S
   (exact tangents, rigid motions projected out), and the Levenberg-Marquardt step d_i inside
   span(S) that the linearization says would fit the scan: ``w_i = (z_i, 0) + d_i`` is where
   scan i wants to be in S's coordinates. The new first ``span`` components are the principal
   directions of the w_i (uncentred: the mean code stays), mapped back through S: they span
   the same space as before, so components past ``span`` and the nesting are kept, and a
   later level with a smaller span leaves the larger k of the levels before it unchanged.
3. Held-out scans fitted with the vertex-ordered and the refined basis at each k, against
   vertex PCA.

Cost: one vertex fit per training scan and level (~2 CPU s each at k = 8), and one tangent and
``span`` tangent directions per training scan and level.

Run: python benchmarks/study_basis_refinement.py DB [--folds 0,1] [--levels 8:24,4:8]
[--components 4,8,16] (levels k:span); DB e.g. ``bodyspace population --subjects 24 --poses 5 --seed 0 --out pop24``.
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
    """Components (K, D): the first ``span`` re-chosen by one alternating step (module docstring);
    and the training scans' mean error (mm) at k before it."""
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
    ap.add_argument("--levels", default="8:24,4:8", help="k:span per level, largest first")
    ap.add_argument("--components", default="4,8,16")
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
    print("| fold (held-out poses) | k | vertex PCA mm | RRE vertex order mm | refined mm | refined per scan |")
    print("|---|---|---|---|---|---|")
    for fold in (int(f) for f in args.folds.split(",")):
        test = subjects == held[fold]
        n_comp = min(N_COMPONENTS, int((~test).sum()) - 2)
        t = time.perf_counter()
        space = ShapeSpace(enc, n_comp, solver="full", basis="vertex").fit(codes[~test], vertices=scans[~test])
        vspace = ShapeSpace(venc, n_comp, solver="full").fit(vcodes[~test])
        refined = ShapeSpace(enc, n_comp, solver="full", basis="vertex").fit(codes[~test], vertices=scans[~test])
        train = []
        for k_level, span in levels:
            comps, train_mm = refine(refined, scans[~test], k_level, min(span, n_comp), parts)
            refined.components_ = comps
            train.append(f"k = {k_level} in {span}: {train_mm:.1f} mm before")
        cost = time.perf_counter() - t
        for k in ks:
            vz = vspace.transform(vcodes[test])[:, :k]
            row = [errors_mm(vspace.reconstruct(vz), scans[test], parts)]
            for sp in (space, refined):
                fz = fit_coefficients(sp, scans[test], k)
                row.append(errors_mm(sp.reconstruct(fz.coefficients[:, :k]), scans[test], parts))
            print(f"| {fold} ({', '.join(poses[test])}) | {k} | {row[0].mean():.1f} | {row[1].mean():.1f} | "
                  f"{row[2].mean():.1f} | {' / '.join(f'{e:.1f}' for e in row[2])} |", flush=True)
        print(f"fold {fold}: training scans' fit per level ({'; '.join(train)}); refinement {cost:.0f} s", flush=True)


if __name__ == "__main__":
    main()
