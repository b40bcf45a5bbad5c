"""Benchmark of the vertex-space fit of RRE coefficients (``ShapeSpace.project(method="vertex")``).

Prints, in one run, on held-out posed scans of a synthetic population (13,380-vertex template,
an RRE pose+shape model fitted on the other subjects' scans, every scan):

0. two per-step pieces against their previous implementations, kept here as the baselines:
   the rigid-motion basis of the decoded body (closed form from the inertia tensor, against the
   QR of the (3V, 6) matrix it replaced; made twice a step) and the inverses of the tangent's
   26,756 3x3 polar-factor matrices (adjugate, against numpy's batched ``inv`` and ``det``);
1. the Jacobian of ``z -> decode(mean + z C)`` for k components: exact tangents
   (``encoder.tangent(code).jvp``: one factorization, k tangent directions) against forward
   finite differences (k + 1 decodes, each its own factorization), wall and CPU seconds, the
   ratio, and how far the finite-difference Jacobian is from the exact one;
2. per mesh and k: the code projection (encode + project + decode), the vertex fit (this
   package's Levenberg-Marquardt with exact Jacobians and Broyden updates) and the baseline
   ``scipy.optimize.least_squares`` (trust-region reflective, finite-difference Jacobian, the
   same residual, start and vertex alignment), each with its seconds per mesh and the mean
   vertex error it reaches (mm, after rigid alignment);
3. the Jacobian budget: 2 exact Jacobians a mesh against the default ``MAX_JACOBIANS`` (4), the
   same meshes and starts (the code projection), CPU seconds a mesh, the ratio and the mean error.

Usage: ``python benchmarks/bench_vertex_fit.py [--subjects 12] [--poses 3] [--meshes 2]
[--components 8,16,32] [--baseline-components 8,16] [--db DB] [--only 3]``; ``--db`` a scan
database to use instead of a new population (e.g. ``population --subjects 8 --pose-set standard``).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

try:
    import bodyspace  # noqa: F401
except ImportError:  # run from a source checkout without installing
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "src"))

import numpy as np
from scipy.optimize import least_squares

from bodyspace.data.template import load_template
from bodyspace.encoding import RelativeRotationEncoder
from bodyspace.shape import ShapeSpace, fit_coefficients
from bodyspace.data.database import ScanDatabase
from bodyspace.shape.vertex_fit import MAX_JACOBIANS, rigid_basis, align_parts
from bodyspace.synth.population import build_population


def clocks():
    return time.perf_counter(), time.process_time()


def since(start):
    wall, cpu = start
    return time.perf_counter() - wall, time.process_time() - cpu


def rigid_basis_qr(body, parts):
    """The previous ``rigid_basis`` (the baseline): the 6 P motion fields, then a QR."""
    cols = []
    for idx in parts:
        x = body[idx] - body[idx].mean(axis=0)
        for a in range(3):
            t = np.zeros_like(body)
            t[idx, a] = 1.0
            cols.append(t.ravel())
        for a in range(3):
            r = np.zeros_like(body)
            r[idx] = np.cross(np.eye(3)[a], x)
            cols.append(r.ravel())
    return np.linalg.qr(np.array(cols).T)[0]


def inverse_lapack(k):
    """The previous inverse of the tangent's (F, 3, 3) matrices (the baseline)."""
    det = np.linalg.det(k)
    ok = np.abs(det) > 1e-12 * np.maximum(np.abs(np.trace(k, axis1=-2, axis2=-1)), 1e-300) ** 3
    out = np.zeros_like(k)
    out[ok] = np.linalg.inv(k[ok])
    return out


def inverse_adjugate(k):
    """As ``RelativeRotationEncoder.tangent`` does it now."""
    adj = np.stack([np.cross(k[:, 1], k[:, 2]), np.cross(k[:, 2], k[:, 0]), np.cross(k[:, 0], k[:, 1])], axis=2)
    det = np.einsum("fi,fi->f", k[:, 0], adj[:, :, 0])
    ok = np.abs(det) > 1e-12 * np.maximum(np.abs(np.trace(k, axis1=-2, axis2=-1)), 1e-300) ** 3
    out = np.zeros_like(k)
    out[ok] = adj[ok] / det[ok, None, None]
    return out


def median_cpu(fn, repeats=7):
    """Median (wall, cpu) seconds of ``fn()``."""
    runs = []
    for _ in range(repeats):
        t = clocks()
        fn()
        runs.append(since(t))
    return tuple(np.median(np.array(runs), axis=0))


def mean_error(body, scan):
    return float(np.linalg.norm(body - align_parts(scan, body, [np.arange(len(body))]), axis=1).mean())


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--subjects", type=int, default=12)
    ap.add_argument("--poses", type=int, default=3)
    ap.add_argument("--meshes", type=int, default=2, help="held-out posed scans fitted")
    ap.add_argument("--components", default="8,16,32")
    ap.add_argument("--baseline-components", default="8,16")
    ap.add_argument("--db", default=None, help="scan database (default: a new population)")
    ap.add_argument("--only", default="0,1,2,3", help="3: section 3 alone (any of 0-2: all sections)")
    args = ap.parse_args()
    only = {int(x) for x in args.only.split(",")}
    ks = [int(k) for k in args.components.split(",")]
    base_ks = {int(k) for k in args.baseline_components.split(",") if k}

    template = load_template()
    if args.db:
        db = ScanDatabase.load(args.db)
        scans = np.asarray(db.read(np.arange(db.n_scans)), dtype=float)
    else:
        with tempfile.TemporaryDirectory() as tmp:
            db = build_population(template, Path(tmp) / "db", args.subjects, args.poses, rng=0)
            scans = np.asarray(db.read(np.arange(db.n_scans)), dtype=float)
    subjects = np.asarray(db.scans["subject"])
    test = subjects == subjects[0]
    held = np.flatnonzero(test & (np.asarray(db.scans["pose"]) != "rest"))[:args.meshes]
    enc = RelativeRotationEncoder(template.vertices, template.faces, on_flipped="ignore").fit(scans)
    codes = enc.encode(scans)
    space = ShapeSpace(enc, n_components=int((~test).sum()) - 1).fit(codes[~test])
    enc.decode(space.mean_)  # compile and warm up
    enc.tangent(space.mean_).jvp(space.components_[:2])
    print(f"{db.n_scans} scans, {len(held)} held-out posed scans ({', '.join(db.scans['pose'][held])}), "
          f"PCA of {int((~test).sum())} scans, up to {space.n_components_} components")

    if 3 in only:
        jacobian_budget(space, scans[held], ks)
    if not only & {0, 1, 2}:
        return
    print("\n0. Per-step pieces, median of 7: seconds wall (cpu)")
    print("| piece | this | previous (baseline) | ratio (cpu) | max difference |")
    print("|---|---|---|---|---|")
    tan = enc.tangent(space.transform(codes[held[:1]])[0] @ space.components_ + space.mean_)
    one = [np.arange(enc.n_vertices)]
    ours, theirs = median_cpu(lambda: rigid_basis(tan.vertices, one)), median_cpu(lambda: rigid_basis_qr(tan.vertices, one))
    a, b = rigid_basis(tan.vertices, one), rigid_basis_qr(tan.vertices, one)
    diff = np.abs(a @ a.T[:, :200] - b @ b.T[:, :200]).max()  # the same projector (bases differ by a rotation)
    print(f"| rigid-motion basis (3V = {3 * enc.n_vertices}, 6) | {ours[0]:.4f} ({ours[1]:.4f}) | {theirs[0]:.4f} "
          f"({theirs[1]:.4f}) | x{theirs[1] / max(ours[1], 1e-9):.1f} | projector {diff:.1e} |")
    p = tan._rot @ tan._q
    p = 0.5 * (p + np.swapaxes(p, -1, -2))
    kmat = np.trace(p, axis1=-2, axis2=-1)[:, None, None] * np.eye(3) - p
    ours, theirs = median_cpu(lambda: inverse_adjugate(kmat)), median_cpu(lambda: inverse_lapack(kmat))
    diff = np.abs(inverse_adjugate(kmat) - inverse_lapack(kmat)).max()
    print(f"| {len(kmat)} 3x3 inverses | {ours[0]:.4f} ({ours[1]:.4f}) | {theirs[0]:.4f} ({theirs[1]:.4f}) | "
          f"x{theirs[1] / max(ours[1], 1e-9):.1f} | {diff:.1e} |")

    print("\n1. Jacobian at the code projection of a held-out scan")
    print("| k | exact tangents s (cpu) | finite differences s (cpu) | ratio | max |J_fd - J| / max |J| |")
    print("|---|---|---|---|---|")
    z0 = space.transform(codes[held[:1]])[0]
    for k in ks:
        code = space.mean_ + z0[:k] @ space.components_[:k]
        t = clocks()
        tan = enc.tangent(code)
        jac = tan.jvp(space.components_[:k])
        ours = since(t)
        h = 1e-4 * np.sqrt(space.explained_variance_[:k])
        t = clocks()
        base = enc.decode(code)[0]
        fd = np.stack([(enc.decode(code + h[i] * space.components_[i])[0] - base) / h[i] for i in range(k)])
        theirs = since(t)
        # Both without the placement's rigid change: compare after removing each column's rigid part.
        x = base - base.mean(axis=0)
        rigid = np.concatenate([np.kron(np.ones((len(x), 1)), np.eye(3)),
                                np.stack([np.cross(e, x).ravel() for e in np.eye(3)], axis=1)], axis=1)
        q, _ = np.linalg.qr(rigid)
        diff = (fd - jac).reshape(k, -1).T
        diff -= q @ (q.T @ diff)
        rel = np.abs(diff).max() / np.abs(jac).max()
        print(f"| {k} | {ours[0]:.2f} ({ours[1]:.2f}) | {theirs[0]:.2f} ({theirs[1]:.2f}) | "
              f"x{theirs[0] / ours[0]:.1f} | {rel:.1e} |")

    print("\n2. Per mesh: seconds (cpu) and mean vertex error (mm)")
    print("| k | code projection | vertex fit (this) | scipy least_squares, FD Jacobian | fit vs baseline |")
    print("|---|---|---|---|---|")
    for k in ks:
        comps = space.components_[:k]
        rows = {"code": [], "fit": [], "base": []}
        for i in held:
            y = scans[i]
            t = clocks()
            z = space.project(y, method="code", n_components=k)
            body = space.reconstruct(z)[0]
            rows["code"].append(since(t) + (mean_error(body, y),))
            t = clocks()
            fit = fit_coefficients(space, y, k)
            body = space.reconstruct(fit.coefficients)[0]
            rows["fit"].append(since(t) + (mean_error(body, y),))
            if k in base_ks:
                t = clocks()
                start = space.project(y, method="code", n_components=k)[0, :k]

                def residual(zz):
                    x = enc.decode(space.mean_ + zz @ comps)[0]
                    return (x - align_parts(y, x, [np.arange(len(x))])).ravel()

                sol = least_squares(residual, start, method="trf", x_scale="jac", max_nfev=10 * (k + 1))
                body = enc.decode(space.mean_ + sol.x @ comps)[0]
                rows["base"].append(since(t) + (mean_error(body, y),))

        def cell(r):
            if not r:
                return "-"
            a = np.mean(r, axis=0)
            return f"{a[0]:.2f} s ({a[1]:.2f}), {1000 * a[2]:.2f} mm"
        ratio = (f"x{np.mean([r[0] for r in rows['base']]) / np.mean([r[0] for r in rows['fit']]):.1f} faster"
                 if rows["base"] else "-")
        print(f"| {k} | {cell(rows['code'])} | {cell(rows['fit'])} | {cell(rows['base'])} | {ratio} |", flush=True)


def jacobian_budget(space, meshes, ks, smaller=2):
    """Section 3: a smaller Jacobian budget against the default, one after the other, the same starts."""
    print(f"\n3. Jacobian budget: {smaller} against the default {MAX_JACOBIANS}, {len(meshes)} meshes, "
          "CPU s a mesh and mean error (mm)")
    print(f"| k | {smaller} | {MAX_JACOBIANS} (default) | ratio (cpu) |")
    print("|---|---|---|---|")
    start = space.transform(space.encoder.encode(meshes))
    for k in ks:
        cells = {}
        for name, budget in (("now", smaller), ("before", MAX_JACOBIANS)):
            c = time.process_time()
            fit = fit_coefficients(space, meshes, k, start=start, max_jacobians=budget)
            cells[name] = ((time.process_time() - c) / len(meshes), 1000 * float(fit.error_m.mean()))
        print(f"| {k} | {cells['now'][0]:.2f} s, {cells['now'][1]:.2f} mm | {cells['before'][0]:.2f} s, "
              f"{cells['before'][1]:.2f} mm | x{cells['before'][0] / max(cells['now'][0], 1e-9):.2f} |", flush=True)


if __name__ == "__main__":
    main()
