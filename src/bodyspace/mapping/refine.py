"""Exact refinement of a semantic mapping's prediction (beyond Rupprecht et al.).

The forest (Sec. 3.2) returns the *mean* body with the requested measurements; measured again,
that body is off by a few millimetres. Starting from it, ``refine`` solves, per request,

    min_s  || m(sigma * s) - t ||^2  +  w ||s||^2     subject to  |s_k| <= max_sigma

with ``s = z / sigma`` the coefficients in standard deviations, ``m`` the measurements (cm) of
the reconstructed body, ``t`` the request, and ``w`` (small) the plausibility prior: among the
many bodies that meet the six numbers it picks the one closest to the mean, and the box keeps
the body inside the sampled shape space. Projected Levenberg-Marquardt, batched over requests,
with the exact Jacobians of ``gradients.LinearBodyMeasures`` (vertex encoding: one pass over
the touched vertices per iteration instead of 2K finite-difference reconstructions).
Coefficients at the box whose gradient pushes outward are held (active set).

A request no body in the box can meet gets the closest plausible body and a report of the
measurements it misses by more than ``tol_cm``, and by how much.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from bodyspace.errors import ParameterError
from bodyspace.mapping.gradients import RUPPRECHT_SIX, LinearBodyMeasures


@dataclass
class RefineResult:
    """coefficients (N, K); measured (N, M) cm; targets (N, M) cm; names; iterations (N,);
    sigma_distance (N,) ``||z / sigma||``; misses: per request a dict name → {requested,
    measured, difference} (cm) of the measurements off by more than ``tol_cm`` (empty: met)."""

    coefficients: np.ndarray
    measured: np.ndarray
    targets: np.ndarray
    names: tuple
    iterations: np.ndarray
    sigma_distance: np.ndarray
    misses: list = field(default_factory=list)

    @property
    def met(self) -> np.ndarray:
        """(N,) bool: every measurement within tolerance."""
        return np.array([not m for m in self.misses])


def refine(model, coefficients0, targets, names=RUPPRECHT_SIX, *, mset=None, measurer=None, k: int = 25,
           prior_weight: float = 1e-4, max_sigma: float = 3.0, tol_cm: float = 0.1, max_iter: int = 40,
           xtol: float = 1e-9, ftol: float = 1e-6) -> RefineResult:
    """Refine coefficients so the bodies measure ``targets`` exactly (see the module docstring).

    Args:
        model: a vertex-encoding ``BodyModel`` (the RRE encoding is not linearized yet).
        coefficients0: (N, K') or (K',) start, e.g. the forest's prediction (only the first ``k`` are refined).
        targets: (N, M) or (M,) requested measurements in cm, columns in the order of ``names``.
        names: the measurements (loop, distance or path methods); mset: their set (default hm08).
        measurer: a prebuilt ``LinearBodyMeasures`` for these names (saves its setup per call).
        k: coefficients refined (the first 25, as sampled for training).
        prior_weight: ``w`` above, per cm² of measurement error per sigma².
        max_sigma: the plausibility box, in standard deviations.
        tol_cm: a measurement further than this from its request is reported as missed.
        max_iter: Levenberg-Marquardt iterations at most; a request stops earlier when an
            accepted step moves less than ``xtol`` sigma or lowers the cost by less than ``ftol`` (relative).
    """
    z0 = np.asarray(coefficients0, dtype=float)
    t = np.asarray(targets, dtype=float)
    single = t.ndim == 1
    z0, t = np.atleast_2d(z0), np.atleast_2d(t)
    names = tuple(names)
    if t.shape[1] != len(names) or len(z0) != len(t):
        raise ParameterError(f"targets: shape {t.shape} for {len(z0)} start(s), expected ({len(z0)}, {len(names)}) "
                             f"(one column per name: {', '.join(names)})")
    if not (np.isfinite(t).all() and np.isfinite(z0).all()):
        raise ParameterError("targets / coefficients0: contain NaN or infinity, expected finite numbers")
    if measurer is None:
        measurer = LinearBodyMeasures.from_model(model, mset, names, k)
    k = measurer.n_coefficients
    sd = np.sqrt(model.space.explained_variance_[:k])
    scale = np.array([100.0] * len(names))                          # metres -> cm
    n = len(t)
    s = np.clip(z0[:, :k] / sd, -max_sigma, max_sigma)
    w = float(prior_weight)

    def evaluate(si, jac):
        out = measurer(si * sd, jacobian=jac)
        if jac:
            return out[0] * scale, out[1] * scale[:, None] * sd
        return out * scale

    m = evaluate(s, False)
    cost = np.sum((m - t) ** 2, axis=1) + w * np.sum(s ** 2, axis=1)
    mu = np.full(n, 1e-7)          # relative to diag(H); w ~ 1e-4 << J^2, so start small
    iters = np.zeros(n, dtype=np.int64)
    active = np.arange(n)
    eye = np.eye(k)
    for _ in range(max_iter):
        if not len(active):
            break
        sa, ta = s[active], t[active]
        ma, J = evaluate(sa, True)
        r = ma - ta
        g = np.einsum("nmk,nm->nk", J, r) + w * sa
        H = np.einsum("nmk,nml->nkl", J, J) + w * eye
        held = ((sa >= max_sigma) & (g < 0)) | ((sa <= -max_sigma) & (g > 0))
        g = np.where(held, 0.0, g)
        free = ~held
        H = H * (free[:, :, None] & free[:, None, :]) + eye * held[:, :, None]
        diag = np.einsum("nkk->nk", H)
        A = H + (mu[active, None] * np.maximum(diag, 1e-12))[:, :, None] * eye
        step = -np.linalg.solve(A, g[..., None])[..., 0]
        s_new = np.clip(sa + step, -max_sigma, max_sigma)
        m_new = evaluate(s_new, False)
        c_new = np.sum((m_new - ta) ** 2, axis=1) + w * np.sum(s_new ** 2, axis=1)
        better = c_new <= cost[active]
        gain = np.where(better, cost[active] - c_new, 0.0)
        old = cost[active]
        acc = active[better]
        s[acc], m[acc], cost[acc] = s_new[better], m_new[better], c_new[better]
        mu[active] = np.where(better, np.maximum(mu[active] / 10.0, 1e-14), mu[active] * 8.0)
        iters[active] += 1
        moved = np.max(np.abs(s_new - sa), axis=1)
        done = (better & ((moved < xtol) | (gain <= ftol * old))) | (mu[active] > 1e8)
        active = active[~done]
    z = np.zeros((n, max(z0.shape[1], k)))
    z[:, :z0.shape[1]] = z0
    z[:, :k] = s * sd
    misses = []
    for i in range(n):
        d = m[i] - t[i]
        misses.append({names[j]: {"requested": float(t[i, j]), "measured": float(m[i, j]), "difference": float(d[j])}
                       for j in np.flatnonzero(np.abs(d) > tol_cm)})
    res = RefineResult(z, m, t, names, iters, np.linalg.norm(s, axis=1), misses)
    if single:
        res = RefineResult(z[0], m[0], t[0], names, iters[:1], res.sigma_distance[:1], misses)
    return res
