"""Refinement of a shape space's leading components for the vertex fit (issue 12 §4).

The vertex-ordered basis (``solvers.vertex_ordered_basis``) takes, for each k, the codes of
vertex PCA's first k components. Through a non-linear decoder (RRE) the best k-dimensional code
subspace for the *vertex fit* (``shape.vertex_fit``) is another one: on posed bodies the first 8
vertex-ordered directions could not fold the arms (``hands_behind_head``, ``arms_crossed``:
105 mm where vertex PCA has 39-48 mm, docs/encoding.md). ``refine_basis`` re-chooses the leading
components by alternating, on the training bodies, between their coefficients and the basis:

For each level (k, span), smallest k first, with the k' components of the level before fixed
(k' = ``keep`` at the first level, default the first component) and ``S = C[:span]``:

1. every training body y_i has coefficients z_i on the first k components: at the start the
   vertex fit's (``fit_coefficients`` from the code projection, as a held-out mesh's fit starts;
   a short budget), later the ones carried over from the
   previous alternation;
2. at each body ``decode(mean + z_i C[:k])`` the decoder's Jacobian on S (exact tangents,
   rigid motions projected out: the error is taken after a rigid alignment), J_i (3V, span),
   and the residual r_i; the damped Gauss-Newton step inside span(S) says where the body wants
   to be, ``w_i = (z_i, 0) - (J_i^T J_i + lambda D)^-1 J_i^T r_i``;
3. the new free components (k'..span) are the principal directions of the w_i's free
   coordinates in the metric ``M = mean_i J_i^T J_i`` (the vertex error the linearization
   predicts), after the fixed components have taken what they can (the Schur complement of
   M on the free coordinates): the k - k' leading ones minimize the predicted vertex error of
   the training bodies in the new first k, given the fixed ones;
4. z_i <- the same linearization's solution on the new first k components, then a short vertex
   fit from there (``ALTERNATION_STEPS`` steps, one Jacobian); the rotation is kept if the
   training bodies' mean vertex error at k fell (else undone, and the level ends), and the level
   alternates from 2 while it falls by more than ``TOL``.

The span of S never changes, so the components past ``span`` and every k >= span keep their
spaces; the fixed components keep the smaller k of earlier levels. Cost per level: one short
vertex fit per training body, then per alternation one decode that keeps its factorization,
``span`` tangent directions and a 3-step fit per body (measured: ~4 CPU s a training body for
the default levels, docs/encoding.md).

Why nested from the smallest k (measured, docs/encoding.md): a level at k = 8 that rotates all
of its span reorders the first 4 components too, and lost k = 4 (80 -> 122 mm on a fold).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from bodyspace.errors import ParameterError
from bodyspace.mesh.solver import single_threaded_blas
from bodyspace.shape.vertex_fit import align_parts, fit_coefficients, mesh_parts, residual_error, rigid_basis

__all__ = ["DEFAULT_LEVELS", "RefineReport", "refine_basis", "check_levels"]

# (k, span) levels: the k = 4 and k = 8 components re-chosen inside the first 8 and 16 (where
# the vertex order left RRE behind vertex PCA on the posed study; k = 1, 16, 32 were ahead).
DEFAULT_LEVELS = ((4, 8), (8, 16))
# Alternations per level at most (each: one decode and span tangent directions per body, and a
# short vertex fit from the new coefficients: ALTERNATION_STEPS decodes and one Jacobian).
MAX_ALTERNATIONS = 3
ALTERNATION_STEPS = 3
# Leading components never rotated: the vertex order's first one (RRE's vertex fit with it
# already beat vertex PCA at k = 1 on the posed study, docs/encoding.md).
KEEP = 1
# The training bodies' first fit at each level: a short budget (most of the gain is in the first
# steps, shape/vertex_fit.py); the alternations refine the coefficients afterwards.
FIT_STEPS = 6
FIT_JACOBIANS = 2
# Damping of the step inside the span, relative to the mean diagonal of J^T J.
DAMPING = 1e-2
# Stop a level when an alternation lowers the mean training error by less than this fraction.
TOL = 2e-3


@dataclass
class RefineReport:
    """What ``refine_basis`` did, level by level.

    Attributes:
        levels: (L, 2) int (k, span) of each level.
        train_error_m: list of L lists: the training bodies' mean vertex error (m) at k after the
            short fit, then after each kept alternation (empty for a skipped level).
        alternations: (L,) alternations kept per level.
    """

    levels: np.ndarray
    train_error_m: list = field(default_factory=list)
    alternations: np.ndarray = None


def check_levels(levels, n_components: int) -> np.ndarray:
    """Levels as an (L, 2) int array of (k, span): 1 <= k < span <= n_components, k and span
    increasing from level to level; raises ParameterError otherwise."""
    lv = np.asarray(levels)
    bad = (lv.ndim != 2 or lv.shape[1] != 2 or lv.dtype.kind not in "iu" or len(lv) == 0)
    if not bad:
        ks, spans = lv[:, 0], lv[:, 1]
        bad = bool((ks < 1).any() or (spans <= ks).any() or (np.diff(ks) <= 0).any()
                   or (np.diff(spans) < 0).any() or (spans > n_components).any())
    if bad:
        raise ParameterError(f"refine levels: {np.asarray(levels).tolist()!r}, expected pairs (k, span) with "
                             f"1 <= k < span <= {n_components} (the components kept), k and span increasing")
    return lv.astype(np.int64)


def _linearize(enc, mean, comps, span, y, z, parts, need_jac=True):
    """At the body of coefficients z (k,) on ``comps[:k]``: the residual's mean distance (m) and,
    with ``need_jac``, ``J^T J`` (span, span) and ``J^T r`` (span,) of the decoder on the first
    ``span`` components (rigid motions projected out), else None, None."""
    k = len(z)
    tan = enc.tangent(mean + z @ comps[:k]) if need_jac else None
    body = tan.vertices if need_jac else enc.decode(mean + z @ comps[:k])[0]
    r = body - align_parts(y, body, parts)
    dist = residual_error(r)[1]
    if not need_jac:
        return dist, None, None
    jac = tan.jvp(comps[:span]).reshape(span, -1).T                     # (3V, span)
    rigid = rigid_basis(body, parts)
    jac -= rigid @ (rigid.T @ jac)                                      # the alignment takes rigid motions
    return dist, jac.T @ jac, jac.T @ r.ravel()


def _damped_solve(h: np.ndarray, rhs: np.ndarray) -> np.ndarray:
    """``(h + lambda mean(diag h) I)^-1 rhs``: the damped Gauss-Newton step's system."""
    n = len(h)
    return np.linalg.solve(h + DAMPING * max(np.trace(h), 1e-300) / n * np.eye(n), rhs)


def _free_directions(w_free: np.ndarray, m: np.ndarray, fixed: int) -> np.ndarray:
    """Orthonormal (f, f) rotation of the free coordinates (rows: the new free directions, best
    first) from the targets' free coordinates w_free (N, f) and the metric m (span, span)."""
    mff = m[fixed:, fixed:]
    if fixed:
        mfx = m[fixed:, :fixed]
        mff = mff - mfx @ np.linalg.solve(m[:fixed, :fixed], mfx.T)     # the fixed ones compensate
    mff = 0.5 * (mff + mff.T)
    lam, vec = np.linalg.eigh(mff)
    lam = np.maximum(lam, 1e-12 * max(lam[-1], 1e-300))
    half, inv_half = (vec * np.sqrt(lam)) @ vec.T, (vec / np.sqrt(lam)) @ vec.T
    _, _, vt = np.linalg.svd(w_free @ half, full_matrices=False)        # principal directions, M-weighted
    d = inv_half @ vt.T                                                 # (f, r) best first
    if d.shape[1] < len(mff):                                           # fewer targets than free coordinates
        d = np.hstack([d, np.eye(len(mff))])
    q, r = np.linalg.qr(d)                                              # orthonormal, the order kept
    q = q[:, :len(mff)] * np.where(np.diag(r)[:len(mff)] < 0, -1.0, 1.0)
    return q.T


def refine_basis(space, bodies: np.ndarray, levels=DEFAULT_LEVELS, *, max_alternations: int = MAX_ALTERNATIONS,
                 keep: int = KEEP, progress=None) -> tuple[np.ndarray, RefineReport]:
    """Leading components of a fitted ``space`` re-chosen for the vertex fit (module docstring).

    Args:
        space: a fitted ``ShapeSpace`` with a non-linear encoder (RRE); not changed.
        bodies: (N, V, 3) the training bodies (any rigid placement).
        levels: (k, span) pairs, k and span increasing (``check_levels``).
        max_alternations: alternations per level at most.
        keep: the leading components never rotated (a level with k <= keep is skipped).
        progress: ``progress(message)`` or None.
    Returns:
        ``(components (K, D), RefineReport)``: orthonormal, the first ``span`` of each level
        rotated inside their own span, the rest unchanged.
    """
    enc = space.encoder
    lv = check_levels(levels, space.n_components_)
    comps = np.array(space.components_, dtype=np.float64)
    y = np.asarray(bodies, dtype=np.float64)
    if y.ndim != 3 or y.shape[1:] != (enc.n_vertices, 3):
        raise ParameterError(f"bodies: shape {y.shape}, expected (N, {enc.n_vertices}, 3)")
    say = progress or (lambda msg: None)
    parts = mesh_parts(enc)
    report = RefineReport(lv, [], np.zeros(len(lv), dtype=np.int64))
    fixed = int(keep)
    for li, (k, span) in enumerate(lv):
        if k <= fixed:                                                  # nothing of the first k may turn
            report.train_error_m.append([])
            continue
        fit = fit_coefficients(_with_components(space, comps), y, int(k), max_iter=FIT_STEPS,
                               max_jacobians=FIT_JACOBIANS)
        z = fit.coefficients[:, :k]
        errors = [float(fit.error_m.mean())]
        say(f"level k = {k} in {span}: training bodies fitted, {1000 * errors[0]:.1f} mm")
        for it in range(max_alternations):
            hs, gs = np.empty((len(y), span, span)), np.empty((len(y), span))
            with single_threaded_blas():
                for i in range(len(y)):
                    _, hs[i], gs[i] = _linearize(enc, space.mean_, comps, span, y[i], z[i], parts)
            kept_comps, kept_z = comps.copy(), z.copy()
            # Where each body wants to be inside the span: w_i = (z_i, 0) - step.
            u0 = np.zeros((len(y), span))
            u0[:, :k] = z
            w = u0 - np.stack([_damped_solve(h, g) for h, g in zip(hs, gs)])
            rot = np.eye(span)
            rot[fixed:, fixed:] = _free_directions(w[:, fixed:], hs.mean(axis=0), fixed)
            comps[:span] = rot @ comps[:span]
            # The coefficients on the new first k: the same linearization's damped Gauss-Newton
            # solution restricted to them (u = P z', P the new first k directions in the old
            # coordinates), then a short vertex fit from there: the new basis is judged by a fit,
            # as the old one was (a linearized point alone was up to ~10 % worse than a fit and
            # made every rotation look like a loss).
            p = rot[:k].T                                                   # (span, k)
            z = np.stack([_damped_solve(p.T @ h @ p, p.T @ (h @ u - g)) for h, g, u in zip(hs, gs, u0)])
            fit = fit_coefficients(_with_components(space, comps), y, int(k), start=z, max_iter=ALTERNATION_STEPS,
                                   max_jacobians=1)
            err = float(fit.error_m.mean())
            if err >= errors[-1]:
                comps, z = kept_comps, kept_z                               # the rotation did not help: undo it
                say(f"level k = {k} in {span}: alternation {it + 1} undone ({1000 * err:.1f} mm)")
                break
            z = fit.coefficients[:, :k]
            errors.append(err)
            report.alternations[li] = it + 1
            say(f"level k = {k} in {span}: alternation {it + 1}, {1000 * err:.1f} mm")
            if err > errors[-2] * (1.0 - TOL):
                break
        report.train_error_m.append(errors)
        fixed = int(k)
    return comps, report


def _with_components(space, comps: np.ndarray):
    """A shallow copy of ``space`` with other components (the fit reads only these)."""
    other = object.__new__(type(space))
    other.__dict__.update(space.__dict__)
    other.components_ = comps
    return other
