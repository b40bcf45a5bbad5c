"""Coefficients of a shape space fitted to a mesh in vertex space, through the decoder.

``ShapeSpace.project`` has two ways to find a mesh's coefficients z:

- **code projection** (``method="code"``): encode the mesh, project its code orthogonally on
  the components, ``z = (encode(y) - mean) C^T``. It minimizes the error of the *code*. For the
  vertex encoding the code is the aligned vertices, so this is the vertex error too. For the
  relative rotation encoding it weighs every triangle's relative rotation and stretch alike,
  and the decode integrates what the projection leaves over the whole body: limbs in the wrong
  place, the wrong stature (docs/encoding.md, "Generalization").
- **vertex fit** (``method="vertex"``, this module): minimize the vertex error itself,
  ``min_z min_g |decode(mean + z C) - g(y)|^2`` with g a rigid motion of each connected part
  (the placement a decode makes anyway), by Levenberg-Marquardt on the exact Jacobian of the
  decoder (``encoding.tangent``: the decode's own factorization reused for every direction),
  warm-started from the code projection. Rigid motions are projected out of the Jacobian
  (the alignment takes them), so a step moves the shape only.

For an encoder whose decoder is affine (``is_linear``, the vertex encoding) the two are one and
the same: the code projection is returned as it is.

Cost per mesh (measured in docs/encoding.md and ``benchmarks/bench_vertex_fit.py``): the warm
start (an encode), then each step one tangent decode (a decode that keeps its factorization),
and each exact Jacobian k tangent directions (triangular solves with that factor, three
right-hand sides a direction, several directions in one pass over it, and a Poisson solve). A
Jacobian is therefore kept between steps and corrected along every accepted step by Broyden's
update; it is made anew where a kept one fails (a rejected step) and when the fit stalls on a
kept one, so the last step is taken on an exact Jacobian (at most ``MAX_JACOBIANS``).
The rigid motions projected out of each Jacobian come in closed form (``rigid_basis``) and the
fit's small dense products run on one BLAS thread (both measured in docs/encoding.md).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from bodyspace.errors import ParameterError
from bodyspace.mesh.alignment import rigid_procrustes
from bodyspace.mesh.solver import single_threaded_blas
from bodyspace.mesh.topology import check_registered_meshes, vertex_components

__all__ = ["VertexFit", "align_parts", "fit_coefficients", "mesh_parts", "residual_error", "rigid_basis", "MAX_ITER",
           "MAX_JACOBIANS", "TOL"]

# Steps (decodes) per mesh at most, and the relative decrease of the squared error below which
# the fit stops (measured on posed bodies: most of the gain in the first 3-5 steps,
# docs/encoding.md; 1e-2 instead of 1e-3 gave the same mean errors to 0.1 mm on 6 held-out
# posed scans at k = 4 and 8 with 10-15 % less CPU time, benchmarks/RESULTS.md).
MAX_ITER = 10
TOL = 1e-2
# Exact Jacobians per mesh at most (each costs k tangent directions; Broyden updates in between).
# 2 instead of 4 was measured and not kept: on 4 held-out posed scans (every subject in the same
# poses, vertex-ordered basis, one process) 0.85 / 1.43 / 1.90 CPU s a mesh at k = 8 / 16 / 32
# against 1.08 / 1.70 / 2.82 for 0-3 % more mean error, but the fits this budget leaves short
# are the ones far from their minimum (a bent-forward scan at k = 4: 199 mm with 4 Jacobians,
# 68 mm with 30 steps and 8), and a smaller budget leaves more of them (docs/encoding.md).
MAX_JACOBIANS = 4
# Levenberg-Marquardt damping at the start, relative to the diagonal of J^T J (Marquardt's
# scaling): a pure Gauss-Newton step from the code projection overshoots where limbs turn.
DAMPING = 1e-2


@dataclass
class VertexFit:
    """Result of ``fit_coefficients`` for N meshes.

    Attributes:
        coefficients: (N, K) fitted coefficients (zero past the fitted ``n_components``).
        error_m: (N,) mean vertex distance (m) of the fitted body from the mesh after a rigid
            alignment of each part; ``start_error_m`` the same for the code projection.
        iterations: (N,) Gauss-Newton steps taken (accepted or not); ``jacobians`` how many
            Jacobians were made.
    """

    coefficients: np.ndarray
    error_m: np.ndarray
    start_error_m: np.ndarray
    iterations: np.ndarray
    jacobians: np.ndarray


def mesh_parts(encoder) -> list[np.ndarray]:
    """Vertex index arrays of the connected parts of the encoder's topology."""
    n, label = vertex_components(encoder.faces, encoder.n_vertices)
    return [np.flatnonzero(label == c) for c in range(n)]


def align_parts(target: np.ndarray, body: np.ndarray, parts) -> np.ndarray:
    """``target`` (V, 3) moved rigidly, part by part, onto ``body`` (V, 3)."""
    if len(parts) == 1:
        return rigid_procrustes(target, body)[0]
    out = np.empty_like(target)
    for idx in parts:
        out[idx] = rigid_procrustes(target[idx], body[idx])[0]
    return out


def rigid_basis(body: np.ndarray, parts) -> np.ndarray:
    """Orthonormal basis (3V, 6 P) of the infinitesimal rigid motions of each part of ``body``.

    In closed form, no QR of a (3V, 6 P) matrix (measured: 45 ms a call under load, two calls a
    step): about each part's centroid, translations are orthogonal to rotations, the three
    translations of a part are orthogonal with norm sqrt(n), and the rotation fields
    ``e_a x x`` have the part's inertia tensor ``I = sum |x|^2 Id - x x^T`` as their Gram
    matrix, so ``[e_a x x] I^-1/2`` is orthonormal. Parts are disjoint: their columns too."""
    out = np.zeros((len(parts) * 6,) + body.shape)
    for p, idx in enumerate(parts):
        x = body[idx] - body[idx].mean(axis=0)
        cols = out[6 * p:6 * p + 6]
        for a in range(3):
            cols[a, idx, a] = 1.0 / np.sqrt(len(idx))
        rot = np.stack([np.cross(e, x) for e in np.eye(3)])              # (3, n, 3)
        inertia = np.einsum("anc,bnc->ab", rot, rot)
        lam, vec = np.linalg.eigh(inertia)
        # A part whose vertices lie on a line has a rotation with no effect: drop it (no NaN).
        inv_sqrt = np.where(lam > 1e-12 * max(lam[-1], 1e-300), 1.0 / np.sqrt(np.maximum(lam, 1e-300)), 0.0)
        cols[3:, idx] = np.einsum("ab,bnc->anc", (vec * inv_sqrt) @ vec.T, rot)
    return out.reshape(len(out), -1).T


def residual_error(residual: np.ndarray) -> tuple[float, float]:
    """(sum of squared distances, mean distance) of a residual (V, 3)."""
    d2 = np.einsum("ij,ij->i", residual, residual)
    return float(d2.sum()), float(np.sqrt(d2).mean())


def fit_coefficients(space, vertices, n_components: int | None = None, *, start=None,
                     max_iter: int = MAX_ITER, tol: float = TOL, max_jacobians: int = MAX_JACOBIANS) -> VertexFit:
    """Fit the first ``n_components`` coefficients of ``space`` to meshes in vertex space.

    Args:
        space: a fitted ``ShapeSpace`` with an encoder.
        vertices: (V, 3) or (N, V, 3) registered meshes (any rigid placement).
        n_components: how many leading coefficients to fit (default all; the rest are 0).
        start: (N, >= n_components) coefficients to start from (default: the code projection).
        max_iter: steps (decodes) at most per mesh; tol: stop when a step on an exact Jacobian
            lowers the squared error by less than this fraction; max_jacobians: exact Jacobians
            at most per mesh.
    Returns:
        ``VertexFit``.
    """
    enc = space.encoder
    k = space.n_components_ if n_components is None else int(n_components)
    if not 1 <= k <= space.n_components_:
        raise ParameterError(f"n_components={n_components}, expected 1..{space.n_components_}")
    y = check_registered_meshes(vertices, enc.n_vertices, enc.faces, name="vertices")
    if start is None:
        z0 = space.transform(enc.encode(y))
    else:
        z0 = np.atleast_2d(np.asarray(start, dtype=float))
        if z0.shape[0] != len(y) or z0.shape[1] < k or not np.isfinite(z0).all():
            raise ParameterError(f"start: shape {z0.shape}, expected finite coefficients ({len(y)}, >= {k})")
    z = np.zeros((len(y), space.n_components_))
    z[:, :k] = z0[:, :k]
    n = len(y)
    err, err0 = np.zeros(n), np.zeros(n)
    iters, jacs = np.zeros(n, dtype=np.int64), np.zeros(n, dtype=np.int64)
    parts = mesh_parts(enc)
    if getattr(enc, "is_linear", False):
        # The code metric is the vertex metric: the code projection is the fit.
        bodies = space.reconstruct(z)
        for m in range(n):
            err[m] = err0[m] = residual_error(bodies[m] - align_parts(y[m], bodies[m], parts))[1]
        return VertexFit(z, err, err0, iters, jacs)
    comps = space.components_[:k]
    # The fit's dense products are small ((3V, k) by (k, k) or (3V, 6)): one BLAS thread. Two
    # threads spinning against a loaded machine made them several times slower (measured in
    # benchmarks/bench_vertex_fit.py); the decoder's own kernels keep their two lanes.
    with single_threaded_blas():
        for m in range(n):
            z[m, :k], err[m], err0[m], iters[m], jacs[m] = _fit_one(enc, space.mean_, comps, y[m], z[m, :k],
                                                                    parts, max_iter, tol, max_jacobians)
    return VertexFit(z, err, err0, iters, jacs)


def _fit_one(enc, mean: np.ndarray, comps: np.ndarray, y: np.ndarray, z: np.ndarray, parts, max_iter: int,
             tol: float, max_jacobians: int):
    """Levenberg-Marquardt for one mesh y (V, 3) from coefficients z (k,); returns
    ``(z, mean distance, mean distance at the start, decodes, Jacobians)``.

    The exact Jacobian costs k tangent directions, a step's decode one factorization, so the
    Jacobian is kept between steps and corrected along each accepted step by Broyden's update
    (the observed change of the residual); it is made anew where a kept one fails (a rejected
    step) and once more when the fit stalls on a kept one, so the fit ends on an exact
    Jacobian's step."""
    k = len(z)
    z = np.array(z, dtype=float)
    tan = enc.tangent(mean + z @ comps)
    r = tan.vertices - align_parts(y, tan.vertices, parts)
    sq, dist = residual_error(r)
    dist0 = dist
    lam, nu = DAMPING, 2.0
    jac = None
    fresh = False
    steps = made = 0
    while steps < max_iter:
        if jac is None:
            if made >= max_jacobians:
                break
            jac = tan.jvp(comps).reshape(k, -1).T                       # (3V, k)
            basis = rigid_basis(tan.vertices, parts)
            jac -= basis @ (basis.T @ jac)                              # the alignment takes rigid motions
            jtj = jac.T @ jac
            made += 1
            fresh = True
        grad = jac.T @ r.ravel()
        diag = np.maximum(np.diag(jtj), 1e-12 * max(np.trace(jtj), 1e-300) / k)
        delta = -np.linalg.solve(jtj + lam * np.diag(diag), grad)
        predicted = -(2.0 * grad @ delta + delta @ (jtj @ delta))       # the model's decrease of sq
        z_new = z + delta
        tan_new = enc.tangent(mean + z_new @ comps)
        r_new = tan_new.vertices - align_parts(y, tan_new.vertices, parts)
        sq_new, dist_new = residual_error(r_new)
        steps += 1
        if sq_new < sq:
            rho = (sq - sq_new) / max(predicted, 1e-300)
            stalled = sq - sq_new < tol * sq
            # Broyden: make the kept Jacobian reproduce the observed change along delta.
            basis = rigid_basis(tan_new.vertices, parts)
            dr = (r_new - r).ravel()
            dr -= basis @ (basis.T @ dr)
            u = (dr - jac @ delta) / (delta @ delta)
            jtu = jac.T @ u
            jac += np.outer(u, delta)
            jtj += np.outer(jtu, delta) + np.outer(delta, jtu) + (u @ u) * np.outer(delta, delta)
            was_fresh, fresh = fresh, False
            z, tan, r, sq, dist = z_new, tan_new, r_new, sq_new, dist_new
            lam *= max(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3)         # Nielsen's update
            nu = 2.0
            if stalled:
                if was_fresh:
                    break
                jac = None                                              # one more look with an exact Jacobian
        else:
            lam *= nu
            nu *= 2.0
            if not fresh:
                jac = None
            elif lam > 1e10:
                break
    return z, dist, dist0, steps, made
