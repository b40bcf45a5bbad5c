"""The semantic closed loop: coefficients whose decoded body measures what was asked.

``closed_loop`` is a pure function of arrays and two callables (decode a body, read its values);
``SemanticModel`` holds the regressors and calls it. Hasler Equation 11 gives the first step, a
Gauss-Newton loop on the values measured on decoded bodies corrects what the linear regressors
got wrong.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Callable

import numpy as np

from bodyspace.errors import ParameterError
from bodyspace.semantics.morph import morph_directions

__all__ = ["closed_loop", "LoopResult", "FD_STEP", "MAX_STEP", "EXTRA_DIRECTIONS", "BACKTRACKS"]

# finite-difference step and largest step, in standard deviations (Mahalanobis)
FD_STEP = 0.25
MAX_STEP = 1.0
# the loop also searches along this many leading PCA components (conditioning)
EXTRA_DIRECTIONS = 4
# a step that does not reduce the residual is halved at most this many times
BACKTRACKS = 4


@dataclass
class LoopResult:
    """What ``closed_loop`` reached.

    coefficients: (K,). vertices: (V, 3) the body of ``coefficients``. values: (C,) its values.
    measurements: what ``values_of`` measured on it (name -> value). converged: every value
    within its tolerance. missed: (C,) bool, the values outside their tolerance. iterations:
    bodies decoded for corrections (Hasler Equation 11 step included; finite-difference bodies not).
    solve_s: seconds in the loop's own linear algebra.
    """

    coefficients: np.ndarray
    vertices: np.ndarray
    values: np.ndarray
    measurements: dict
    converged: bool
    missed: np.ndarray
    iterations: int
    solve_s: float


def _metric_orthonormal(u, metric):
    """Columns of ``u`` (K, m) orthonormalized in the inner product ``a^T diag(metric) b``
    (dependent columns dropped): (K, m') with m' <= m."""
    w = np.sqrt(metric)[:, None]
    q, r = np.linalg.qr(u * w)
    keep = np.abs(np.diag(r)) > 1e-10 * np.abs(np.diag(r)).max()
    return q[:, keep] / w


def closed_loop(c0, goal, tolerance, variances, gradients,
                body: Callable[[np.ndarray], np.ndarray],
                values_of: Callable[[np.ndarray, np.ndarray], tuple],
                current=None, max_iter: int = 20, fd_step: float = FD_STEP, max_step: float = MAX_STEP,
                extra_directions: int = EXTRA_DIRECTIONS) -> LoopResult:
    """Coefficients near ``c0`` whose body has values ``goal``, each within its ``tolerance``.

    Args:
        c0: (K,) start coefficients.
        goal: (C,) the values asked, one per constraint (SI).
        tolerance: (C,) how close each value must come (SI, > 0).
        variances: (K,) the PCA variances: steps are measured in ``sum_k z_k^2 / var_k``
            (the most probable change, the least in units of the population's spread).
        gradients: (C, K) the regressors' gradients at ``c0``: the first model of how the
            values change with the coefficients.
        body: ``body(c (K,)) -> (V, 3)`` the body of coefficients c (decoded; for a morph the
            start mesh plus the, possibly masked, change).
        values_of: ``values_of(x (V, 3), c (K,)) -> (values (C,), measurements dict)``: the
            constraints' values on body x (measured, or predicted from c).
        current: optional ``(values (C,), measurements)`` of ``body(c0)``, when already known.
        max_iter: most correction bodies (the Hasler Equation 11 step included), checked before
            each step: a step's backtracking may add up to ``BACKTRACKS - 1`` more.
        fd_step, max_step: finite-difference step and largest step, in SD.
        extra_directions: leading PCA components added to the search span.

    Returns:
        ``LoopResult``; a miss is reported (``converged`` False, ``missed``), never raised. A
        start body whose values are not all finite is refused (ParameterError); a step to a
        body with an undefined value counts as no progress.

    Steps:
        1. Hasler Equation 11: the minimum-norm step ``z`` (metric ``1 / var``) with
           ``<s_i, z> = goal_i - value_i``, kept if it lowers the residual.
        2. The search span: the minimum-norm directions ``u_i = var * s_i`` (where every
           minimum-norm solution lies) and the leading ``extra_directions`` components,
           orthonormalized in the metric.
        3. Gauss-Newton in that span, at most ``max_step`` SD a step, halved up to
           ``BACKTRACKS`` times until the residual drops. Its Jacobian starts as the
           regressors' gradients (one decode a step instead of a finite-difference column a
           direction), is refreshed by Broyden's rank-one update after a step, and measured
           by finite differences when progress stalls.
        4. Stop when every value is within tolerance, after ``max_iter`` corrections, or when
           even a fresh Jacobian makes no progress.
    """
    c = np.asarray(c0, dtype=float).copy()
    g = np.asarray(goal, dtype=float)
    tol = np.asarray(tolerance, dtype=float)
    var = np.asarray(variances, dtype=float)
    grads = np.asarray(gradients, dtype=float).reshape(len(g), len(c))
    metric = 1.0 / np.maximum(var, 1e-300)
    solve_s = 0.0
    x = body(c)
    vals, meas = current if current is not None else values_of(x, c)
    vals = np.asarray(vals, dtype=float)
    if not np.isfinite(vals).all():
        # a NaN residual would become a NaN step and NaN coefficients: the caller picks a start
        # body whose values are defined (SemanticModel._defined_start) or refuses
        raise ParameterError(f"closed_loop: the start body's values {vals.tolist()} are not all finite; expected a "
                             "start body on which every asked value is defined")

    def score(v):
        e = np.abs(g - v) / tol
        return float(np.linalg.norm(e)) if np.isfinite(e).all() else np.inf

    def try_step(step):
        cn = c + step
        xn = body(cn)
        vn, mn = values_of(xn, cn)
        return cn, xn, np.asarray(vn, dtype=float), mn

    it = 0
    # 1. Hasler Equation 11
    if score(vals) > np.sqrt(len(g)) or np.any(np.abs(g - vals) > tol):
        t = time.perf_counter()
        z = morph_directions(grads, g - vals, metric=metric)
        solve_s += time.perf_counter() - t
        cn, xn, vn, mn = try_step(z)
        it += 1
        if score(vn) < score(vals):
            c, x, vals, meas = cn, xn, vn, mn
    # 2. the search span
    u = var[:, None] * grads.T
    extra = np.eye(len(metric))[:, :min(extra_directions, len(metric))] * np.sqrt(var)[:, None]
    u = _metric_orthonormal(np.hstack([u, extra]), metric)
    # 3. Gauss-Newton with a Broyden-updated Jacobian
    jac, fresh = grads @ u, False
    while np.any(np.abs(g - vals) > tol) and it < max_iter:
        if jac is None:
            jac = np.empty((len(g), u.shape[1]))
            for i in range(u.shape[1]):
                _, _, vi, _ = try_step(fd_step * u[:, i])
                jac[:, i] = (vi - vals) / fd_step
            fresh = True
            if not np.isfinite(jac).all():
                break
        t = time.perf_counter()
        a = np.linalg.lstsq(jac, g - vals, rcond=1e-8)[0]
        a *= min(1.0, max_step / max(np.linalg.norm(a), 1e-300))
        solve_s += time.perf_counter() - t
        before = score(vals)
        for _ in range(BACKTRACKS):
            cn, xn, vn, mn = try_step(u @ a)
            it += 1
            if score(vn) < before:
                break
            a = a * 0.5
        if score(vn) < before:
            if score(vn) > 0.5 * before and not fresh:
                jac = None  # slow progress: the secant model is off, measure it again
            elif np.isfinite(vn).all():
                jac = jac + np.outer((vn - vals) - jac @ a, a) / max(float(a @ a), 1e-300)
            c, x, vals, meas = cn, xn, vn, mn
            fresh = False
        elif fresh:
            break  # 4. no progress even with a fresh Jacobian
        else:
            jac = None  # refresh the Jacobian where we are
    missed = ~(np.abs(g - vals) <= tol)
    return LoopResult(c, x, vals, meas, bool(not missed.any()), missed, it, solve_s)
