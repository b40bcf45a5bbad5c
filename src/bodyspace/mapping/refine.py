"""Exact refinement of a semantic mapping's prediction (beyond Rupprecht et al.).

The forest (Rupprecht §3.2) returns the *mean* body with the requested measurements; measured again,
that body is off by a few millimetres. Starting from it, ``refine`` solves, per request,

    min_s  || m(sigma * s) - t ||^2  +  w ||s||^2     subject to  |s_k| <= max_sigma

with ``s = z / sigma`` the coefficients in standard deviations, ``m`` the measurements (cm) of
the reconstructed body, ``t`` the request, and ``w`` (small) the plausibility prior: among the
many bodies that meet the six numbers it picks the one closest to the mean, and the box keeps
the body inside the sampled shape space. Projected Levenberg-Marquardt, batched over requests,
with the exact Jacobians of ``gradients.LinearBodyMeasures`` (vertex encoding: one pass over
the touched vertices per iteration instead of 2K finite-difference reconstructions).
Coefficients at the box whose gradient pushes outward are held (active set).

RRE encoding (bodies non-linear in z): the same iteration, with residuals always measured on
the truly decoded bodies (one batched decode of the active requests per iteration, so a request
reported as met is met exactly) and Jacobians that are approximate: the analytic vertex gradients
at the decoded body chained with a linearization of the decoder
(``encoding.linearize.DecoderLinearization``), corrected per request by Broyden rank-1 updates from the
steps taken, a damping floor, and, once for a stalled request, finite differences at its body.
See ``_refine_decoded`` and docs/mapping.md.

Measurements that are not differentiated analytically (slices, mass, volume, ...: any method of
the measurement set outside ``gradients.DIFFERENTIABLE``) and linear functions of the
coefficients (``linear``: e.g. a semantic label's linear regressor, held while the rest moves)
take the general path (``_general_evaluator`` in ``_refine_linear``): every evaluation reconstructs the bodies (exact for
either encoding) and measures them, the analytic Jacobians where there are some, forward
differences (``k`` more bodies per request) for the rest. Each measurement has its own
tolerance (``tolerances``, in its display units: cm for lengths, kg for mass); residuals are
weighted by ``tol_cm / tolerance`` so that every measurement is met to the same fraction of it.

A request no body in the box can meet gets the closest plausible body and a report of the
measurements it misses by more than its tolerance, and by how much.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from bodyspace.errors import ParameterError
from bodyspace.mapping.gradients import (
    DIFFERENTIABLE,
    LinearBodyMeasures,
    mapping_inputs,
    subset,
)
from bodyspace.measure import measure

# RRE: after a rejected step the damping (relative to diag(H)) is at least this, so the next
# step is shorter at once instead of after ~6 rejections (each costs a decode).
REJECT_MU = 1e-2
# RRE: coefficients the step pushes past the box are fixed on it and the rest solved again, this often.
BOUND_PASSES = 3
# RRE: finite-difference step (sigma) of the one-time Jacobian refresh of a stalled request.
REFRESH_STEP = 0.01
# RRE: a request whose accepted step lowers the cost by less than this (relative) has stalled
# (each further step costs a decode; the vertex path uses ``ftol``).
RRE_FTOL = 1e-3
# General path: forward-difference step (sigma) of the measurements not differentiated analytically.
FD_STEP = 1e-3
# General path: a request's differenced Jacobian is reused for this many iterations (chord
# steps; residuals are always measured on the true bodies), then differenced again. Slices and
# mass are smooth in the coefficients; differencing every iteration tripled generate's time.
FD_REUSE = 8


def analytic_names(mset, names) -> tuple:
    """The ``names`` whose Jacobians ``LinearBodyMeasures`` writes out (loops about the up axis,
    distances, paths); the rest are differenced (``refine``'s general path)."""
    by_name = {m["name"]: m for m in subset(mset, names).measurements}
    return tuple(n for n in names if by_name[n]["method"] in DIFFERENTIABLE
                 and (by_name[n]["method"] != "loop" or by_name[n].get("axis", "up") == "up"))


def display_scale(mset, names) -> np.ndarray:
    """(M,) factor from SI to the units refinement works in: cm for lengths (unit "m"), else 1."""
    by_name = {m["name"]: m for m in subset(mset, names).measurements}
    return np.array([100.0 if by_name[n]["unit"] == "m" else 1.0 for n in names])


@dataclass
class RefineResult:
    """coefficients (N, K); measured (N, M) cm; targets (N, M) cm; names; iterations (N,);
    sigma_distance (N,) ``||z / sigma||``; misses: per request a dict name → {requested,
    measured, difference} (cm) of the measurements off by more than ``tol_cm`` (empty: met);
    decodes: bodies decoded (RRE; 0 for the vertex encoding)."""

    coefficients: np.ndarray
    measured: np.ndarray
    targets: np.ndarray
    names: tuple
    iterations: np.ndarray
    sigma_distance: np.ndarray
    misses: list = field(default_factory=list)
    decodes: int = 0

    @property
    def met(self) -> np.ndarray:
        """(N,) bool: every measurement within tolerance."""
        return np.array([not m for m in self.misses])


def refine(model, coefficients0, targets, names=None, *, mset=None, measurer=None, k: int = 25,
           prior_weight: float = 1e-4, max_sigma: float = 3.0, tol_cm: float = 0.1, max_iter: int = 40,
           xtol: float = 1e-9, ftol: float = 1e-6, linearization=None, stop_cm: float | None = None,
           update: str = "broyden", damping: float = 0.1, tolerances=None, linear=None, offset=None,
           bodies=None, progress=None) -> RefineResult:
    """Refine coefficients so the bodies measure ``targets`` exactly (see the module docstring).

    Args:
        model: a ``BodyModel``, vertex or RRE encoding (selected by ``model.encoder.is_linear``).
        coefficients0: (N, K') or (K',) start, e.g. the forest's prediction (only the first ``k`` are refined).
        targets: (N, M) or (M,) requested measurements in cm, columns in the order of ``names``.
        names: the measurements (default ``mapping_inputs(mset)``: Rupprecht's six on the
            template); mset: their set (default the model's own, ``model.measurement_set``).
        measurer: a prebuilt ``LinearBodyMeasures`` for these names (saves its setup per call).
        k: coefficients refined (the first 25, as sampled for training).
        prior_weight: ``w`` above, per cm² of measurement error per sigma².
        max_sigma: the plausibility box, in standard deviations.
        tol_cm: a measurement further than this from its request is reported as missed.
        max_iter: Levenberg-Marquardt iterations at most; a request stops earlier when an
            accepted step moves less than ``xtol`` sigma or lowers the cost by less than ``ftol`` (relative).
        linearization: RRE only: the ``encoding.linearize.DecoderLinearization`` whose basis stands for
            dv/dz (default: forward differences at the mean, ``k + 1`` decodes, cached per model;
            better: the least-squares one of a training set, ``TrainingSet.linearization``).
        stop_cm: RRE only: a request also stops once every measurement is within this of its
            request (default ``tol_cm / 10``): each iteration costs a decode.
        update: RRE only: how the measurement Jacobian follows the decoder between steps,
            "broyden" (rank-1 secant updates from the steps taken, on top of the analytic
            chain at the current body) or "chain" (the analytic chain alone).
        damping: RRE only: Levenberg damping floor, cm² per sigma², added to the Gauss-Newton
            matrix. The Jacobians are approximate, so a full step along their null space (where
            only the prior acts) changes the true measurements a lot: with this floor the body
            moves only slowly toward the mean there, and each iteration mostly fixes the
            measurements (3-6 iterations instead of 5-11, measured).
        tolerances: (M,) per-measurement tolerance in the targets' units (default ``tol_cm`` for each);
            residuals are weighted by ``tol_cm / tolerances``.
        linear: dict name -> (g (K,), b): values ``b + g . z`` that are linear in the coefficients
            (a semantic label's linear regressor), targets in the columns of ``names`` as well.
        offset: (V, 3) added to every reconstructed body (a morphed mesh: its difference from its
            projection); takes the general path, Jacobians unchanged.
        bodies: ``bodies(z (n, K)) -> (n, V, 3)`` instead of ``model.reconstruct`` (a masked
            morph); takes the general path with every Jacobian by forward differences.
        progress: ``progress(message, fraction)`` after each iteration (fraction of requests done).

    ``names`` may hold any measurement of ``mset`` (cm for lengths, the set's unit otherwise, e.g.
    kg); those outside ``analytic_names`` and ``linear`` send the request down the general path.
    """
    z0 = np.asarray(coefficients0, dtype=float)
    t = np.asarray(targets, dtype=float)
    single = t.ndim == 1
    z0, t = np.atleast_2d(z0), np.atleast_2d(t)
    mset = model.measurement_set if mset is None else mset
    names = mapping_inputs(mset) if names is None else tuple(names)
    if t.shape[1] != len(names) or len(z0) != len(t):
        raise ParameterError(f"targets: shape {t.shape} for {len(z0)} start(s), expected ({len(z0)}, {len(names)}) "
                             f"(one column per name: {', '.join(names)})")
    if not (np.isfinite(t).all() and np.isfinite(z0).all()):
        raise ParameterError("targets / coefficients0: contain NaN or infinity, expected finite numbers")
    if update not in ("broyden", "chain"):
        raise ParameterError(f"update={update!r}, expected 'broyden' or 'chain'")
    linear = dict(linear or {})
    tol = np.full(len(names), float(tol_cm)) if tolerances is None else np.asarray(tolerances, dtype=float)
    if tol.shape != (len(names),) or not np.all(tol > 0):
        raise ParameterError(f"tolerances: {tolerances!r}, expected {len(names)} positive values (one per name)")
    measured_names = tuple(n for n in names if n not in linear)
    fast = analytic_names(mset, measured_names) if measured_names else ()
    if bodies is not None:                     # dv/dz is not the model's basis: difference everything
        fast = ()
    general = (bool(linear) or len(fast) < len(measured_names) or tolerances is not None or offset is not None
               or bodies is not None)
    if measurer is None and (fast or not general):
        measurer = LinearBodyMeasures.from_model(model, mset, fast if general else names, k,
                                                 linearization=linearization)
    k = min(measurer.n_coefficients if measurer is not None else int(k), model.n_components)
    sd = np.sqrt(model.space.explained_variance_[:k])
    s = np.clip(z0[:, :k] / sd, -max_sigma, max_sigma)
    if general:
        decodes = 0
        weight = float(tol_cm) / tol
        full = np.zeros((len(t), model.n_components))
        full[:, :min(z0.shape[1], model.n_components)] = z0[:, :model.n_components]
        evaluate = _general_evaluator(model, mset, names, fast, linear, measurer if fast else None, sd, full,
                                      weight, max_sigma, offset, bodies)
        # every evaluation reconstructs bodies: stop a request once it is within a tenth of each tolerance
        stop = tol_cm / 10.0 if stop_cm is None else float(stop_cm)
        s, m, iters = _refine_linear(evaluate, s, t * weight, float(prior_weight), max_sigma, max_iter, xtol, ftol,
                                     progress, stop)
        m = m / weight
        decodes = 0 if model.encoder.is_linear else int(evaluate.bodies)
    elif model.encoder.is_linear:
        decodes = 0
        s, m, iters = _refine_linear(_linear_evaluator(measurer, sd), s, t, float(prior_weight), max_sigma,
                                     max_iter, xtol, ftol, progress)
    else:
        stop = tol_cm / 10.0 if stop_cm is None else float(stop_cm)
        full = np.zeros((len(t), model.n_components))          # coefficients beyond k stay as given
        full[:, :min(z0.shape[1], model.n_components)] = z0[:, :model.n_components]
        s, m, iters, decodes = _refine_decoded(model, measurer, s, t, sd, float(prior_weight), max_sigma, max_iter,
                                               xtol, ftol, stop, update, float(damping), progress, full)
    n = len(t)
    z = np.zeros((n, max(z0.shape[1], k)))
    z[:, :z0.shape[1]] = z0
    z[:, :k] = s * sd
    misses = []
    for i in range(n):
        d = m[i] - t[i]
        misses.append({names[j]: {"requested": float(t[i, j]), "measured": float(m[i, j]), "difference": float(d[j]),
                                  "tolerance": float(tol[j])}
                       for j in np.flatnonzero(np.abs(d) > tol)})
    res = RefineResult(z, m, t, names, iters, np.linalg.norm(s, axis=1), misses, decodes)
    if single:
        res = RefineResult(z[0], m[0], t[0], names, iters[:1], res.sigma_distance[:1], misses, decodes)
    return res


def _lm_step(J, r, sa, w, mu, max_sigma, floor: float = 0.0, bound_passes: int = 0):
    """One projected Levenberg-Marquardt step for a batch: J (n, M, k) cm/sigma, residuals r (n, M)
    cm, coefficients sa (n, k) sigma, damping mu (n,) (relative to diag(H)) plus ``floor``
    (absolute). Returns the clipped new coefficients (n, k).

    ``bound_passes`` > 0: coefficients the step would push past the box are set on it and the
    others solved again with them fixed (up to that many times), instead of clipping the step
    (a clipped Gauss-Newton step is no longer a Gauss-Newton step; with exact Jacobians the
    vertex path does not need it)."""
    k = sa.shape[1]
    eye = np.eye(k)
    g = np.einsum("nmk,nm->nk", J, r) + w * sa
    H = np.einsum("nmk,nml->nkl", J, J) + w * eye
    held = ((sa >= max_sigma) & (g < 0)) | ((sa <= -max_sigma) & (g > 0))
    diag = np.einsum("nkk->nk", H)
    A = H + (floor + mu[:, None] * np.maximum(diag, 1e-12))[:, :, None] * eye
    d_fixed = np.zeros_like(sa)
    for p in range(bound_passes + 1):
        free = ~held
        gp = g + np.einsum("nkl,nl->nk", H, d_fixed) if p else g      # gradient at d_fixed (prior included)
        gp = np.where(held, 0.0, gp)
        Ap = A * (free[:, :, None] & free[:, None, :]) + eye * held[:, :, None]
        step = d_fixed - np.linalg.solve(Ap, gp[..., None])[..., 0]
        s_new = sa + step
        out = (np.abs(s_new) > max_sigma) & ~held
        if p == bound_passes or not out.any():
            break
        held = held | out
        d_fixed = np.where(held, np.clip(s_new, -max_sigma, max_sigma) - sa, 0.0) if p == 0 else \
            np.where(out, np.clip(s_new, -max_sigma, max_sigma) - sa, d_fixed)
    return np.clip(s_new, -max_sigma, max_sigma)


def _linear_evaluator(measurer, sd):
    """Vertex encoding: ``evaluate(s (n, k) sigma, jacobian)`` -> cm (n, M) [, cm per sigma (n, M, k)]
    from the exact Jacobians of ``v = base + z C``; one pass over the touched vertices."""
    scale = 100.0                                                    # metres -> cm

    def evaluate(si, jac, rows=None):
        out = measurer(si * sd, jacobian=jac)
        if jac:
            return out[0] * scale, out[1] * scale * sd
        return out * scale
    return evaluate


class _general_evaluator:
    """``evaluate(s, jacobian, rows)`` of the general path: bodies reconstructed (coefficients
    beyond ``k`` from ``full`` (n, K)), the ``fast`` names measured with their analytic Jacobians
    (``measurer.measure_bodies``), the other measured names with ``measure.measure`` and forward
    differences, ``linear`` ones as ``b + g . z``; everything in display units times ``weight`` (M,).
    ``bodies`` counts the bodies reconstructed."""

    def __init__(self, model, mset, names, fast, linear, measurer, sd, full, weight, max_sigma, offset=None,
                 bodies=None):
        self.model, self.names, self.fast, self.linear, self.measurer = model, names, fast, linear, measurer
        self.offset = None if offset is None else np.asarray(offset, dtype=float)
        self.reconstruct = model.reconstruct if bodies is None else bodies
        self.sd, self.full, self.max_sigma, self.bodies = sd, full, max_sigma, 0
        slow = [n for n in names if n not in fast and n not in linear]
        self.slow = tuple(slow)
        self.sub = subset(mset, slow) if slow else None
        self.scale = display_scale(mset, [n for n in names if n not in linear]) if len(linear) < len(names) else None
        self.col = {n: j for j, n in enumerate(names)}
        self.weight = weight
        self.faces = model.faces
        self.slow_jac = {}                     # row -> (uses left, (Ms, k) differenced Jacobian, display units)

    def _bodies(self, z):
        v = np.asarray(self.reconstruct(z), dtype=float)
        return v if self.offset is None else v + self.offset

    def _slow_values(self, v):
        vals = measure(self.sub, v, self.faces)
        return np.column_stack([np.asarray(vals[n], dtype=float) for n in self.slow])

    def __call__(self, si, jac, rows=None):
        rows = np.arange(len(si)) if rows is None else rows
        n, k = si.shape
        M = len(self.names)
        z = self.full[rows].copy()
        z[:, :k] = si * self.sd
        out = np.empty((n, M))
        J = np.zeros((n, M, k)) if jac else None
        measured = [nm for nm in self.names if nm not in self.linear]
        unit = dict(zip(measured, self.scale)) if self.scale is not None else {}
        # a linear encoding, nothing differenced and no offset: the touched vertices suffice
        direct = self.model.encoder.is_linear and not self.slow and self.offset is None and self.reconstruct is \
            self.model.reconstruct and self.measurer is not None and k == self.measurer.n_coefficients
        if measured and not direct:
            v = self._bodies(z)
            self.bodies += n
        if self.fast:
            res = self.measurer(z[:, :k], jacobian=jac) if direct else self.measurer.measure_bodies(v, jacobian=jac)
            vals, Jf = (res if jac else (res, None))
            for i, nm in enumerate(self.fast):
                out[:, self.col[nm]] = vals[:, i] * unit[nm]
                if jac:
                    J[:, self.col[nm]] = Jf[:, i, :k] * unit[nm] * self.sd
        if self.slow:
            base = self._slow_values(v)
            cols = [self.col[nm] for nm in self.slow]
            sc = np.array([unit[nm] for nm in self.slow])
            out[:, cols] = base * sc
            if jac:
                stale = np.array([self.slow_jac.get(int(r), (0, None))[0] <= 0 for r in rows])
                if stale.any():
                    # forward differences, stepping inward at the box
                    ns = int(stale.sum())
                    h = np.where(si[stale] + FD_STEP > self.max_sigma, -FD_STEP, FD_STEP)     # (ns, k)
                    zz = np.repeat(z[stale], k, axis=0)
                    zz[:, :k] += (h[:, :, None] * np.eye(k)).reshape(-1, k) * self.sd
                    moved = self._slow_values(self._bodies(zz)).reshape(ns, k, -1)
                    self.bodies += ns * k
                    fresh = np.swapaxes((moved - base[stale][:, None]) / h[:, :, None], 1, 2) * sc[None, :, None]
                    for r, Jr in zip(rows[stale], fresh):
                        self.slow_jac[int(r)] = (FD_REUSE, Jr)
                for i, r in enumerate(rows):
                    left, Jr = self.slow_jac[int(r)]
                    J[i, cols] = Jr
                    self.slow_jac[int(r)] = (left - 1, Jr)
        for nm, (g, b) in self.linear.items():
            g = np.asarray(g, dtype=float)
            out[:, self.col[nm]] = b + z @ g[:z.shape[1]]
            if jac:
                J[:, self.col[nm]] = g[:k] * self.sd
        out *= self.weight
        if jac:
            return out, J * self.weight[None, :, None]
        return out


def _refine_linear(evaluate, s, t, w, max_sigma, max_iter, xtol, ftol, progress=None, stop_cm=None):
    """Projected Levenberg-Marquardt with the Jacobians of ``evaluate(s, jacobian)`` (exact for the
    vertex encoding; the general path's analytic-plus-differenced ones), batched over requests.
    ``stop_cm``: a request also stops once every residual is within it (general path)."""
    n = len(t)
    m = evaluate(s, False)
    cost = np.sum((m - t) ** 2, axis=1) + w * np.sum(s ** 2, axis=1)
    mu = np.full(n, 1e-7)          # relative to diag(H); w ~ 1e-4 << J^2, so start small
    iters = np.zeros(n, dtype=np.int64)
    active = np.arange(n) if stop_cm is None else np.flatnonzero(np.abs(m - t).max(axis=1) > stop_cm)
    for _ in range(max_iter):
        if not len(active):
            break
        sa, ta = s[active], t[active]
        ma, J = evaluate(sa, True, active)
        s_new = _lm_step(J, ma - ta, sa, w, mu[active], max_sigma)
        m_new = evaluate(s_new, False, active)
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
        if stop_cm is not None:
            done |= np.abs(m[active] - ta).max(axis=1) <= stop_cm
        active = active[~done]
        if progress is not None:
            progress(f"iteration {iters.max()}: {n - len(active)}/{n} requests done", 1.0 - len(active) / n)
    return s, m, iters


def _refine_decoded(model, measurer, s, t, sd, w, max_sigma, max_iter, xtol, ftol, stop_cm, update, damping,
                    progress=None, full=None):
    """RRE encoding: residuals measured on the truly decoded bodies (one batched decode of the
    active requests per iteration), Jacobians from the analytic vertex gradients of the current
    body chained with the decoder's linearization, plus Broyden rank-1 corrections."""
    K = model.n_components
    k = s.shape[1]
    full = np.zeros((len(s), K)) if full is None else full      # (n, K): the coefficients beyond k

    def evaluate(si, rows):
        z = full[rows].copy()
        z[:, :k] = si * sd
        vals, J = measurer.measure_bodies(model.reconstruct(z), jacobian=True)
        return vals * 100.0, J * 100.0 * sd

    def finite_differences(si, rows, base):
        """(n, M, k) cm per sigma by forward differences at si (n, k) (measured ``base`` (n, M)
        cm): n k decodes in one batch."""
        h = np.where(si + REFRESH_STEP > max_sigma, -REFRESH_STEP, REFRESH_STEP)        # (n, k)
        pts = np.repeat(si[:, None, :], k, axis=1) + h[:, :, None] * np.eye(k)         # (n, k, k)
        z = np.repeat(full[rows], k, axis=0)
        z[:, :k] = pts.reshape(-1, k) * sd
        vals = measurer.measure_bodies(model.reconstruct(z)).reshape(len(si), k, -1) * 100.0
        return np.swapaxes((vals - base[:, None]) / h[:, :, None], 1, 2)

    n = len(t)
    m, chain = evaluate(s, np.arange(n))
    decodes = n
    corr = np.zeros_like(chain)                 # Broyden's correction to the chain, per request
    cost = np.sum((m - t) ** 2, axis=1) + w * np.sum(s ** 2, axis=1)
    mu = np.full(n, 1e-7)
    iters = np.zeros(n, dtype=np.int64)
    streak = np.zeros(n, dtype=np.int64)        # consecutive rejected steps
    refreshed = np.zeros(n, dtype=bool)
    active = np.flatnonzero(np.abs(m - t).max(axis=1) > stop_cm)
    for _ in range(max_iter):
        if not len(active):
            break
        sa, ta, ma = s[active], t[active], m[active]
        B = chain[active] + corr[active]
        s_new = _lm_step(B, ma - ta, sa, w, mu[active], max_sigma, damping, BOUND_PASSES)
        m_new, chain_new = evaluate(s_new, active)
        decodes += len(active)
        c_new = np.sum((m_new - ta) ** 2, axis=1) + w * np.sum(s_new ** 2, axis=1)
        d = s_new - sa
        dd = np.sum(d * d, axis=1)
        if update == "broyden":                 # secant condition B d = m_new - m on the step taken
            ok = dd > 1e-24
            y = m_new - ma - np.einsum("nmk,nk->nm", B, d)
            upd = np.where(ok[:, None, None], y[:, :, None] * d[:, None, :] / np.maximum(dd, 1e-300)[:, None, None],
                           0.0)
            corr[active] = corr[active] + upd
        better = c_new <= cost[active]
        gain = np.where(better, cost[active] - c_new, 0.0)
        old = cost[active]
        acc = active[better]
        s[acc], m[acc], cost[acc], chain[acc] = s_new[better], m_new[better], c_new[better], chain_new[better]
        mu[active] = np.where(better, np.maximum(mu[active] / 10.0, 1e-14), np.maximum(mu[active] * 8.0, REJECT_MU))
        streak[active] = np.where(better, 0, streak[active] + 1)
        iters[active] += 1
        moved = np.sqrt(dd)
        met = np.abs(m[active] - ta).max(axis=1) <= stop_cm
        stalled = (better & ((moved < xtol) | (gain <= max(ftol, RRE_FTOL) * old))) | (mu[active] > 1e8)
        # A stalled request (or one rejected 3 times running) gets, once, its Jacobian by finite
        # differences at its current body: the approximate one may have a false fixed point.
        fresh = ~met & ~refreshed[active] & (stalled | (streak[active] >= 3))
        if fresh.any():
            R = active[fresh]
            corr[R] = finite_differences(s[R], R, m[R]) - chain[R]
            decodes += len(R) * k
            mu[R], streak[R], refreshed[R] = 1e-7, 0, True
        done = met | (stalled & ~fresh)
        active = active[~done]
        if progress is not None:
            progress(f"iteration {iters.max()}: {n - len(active)}/{n} requests done", 1.0 - len(active) / n)
    return s, m, iters, decodes

