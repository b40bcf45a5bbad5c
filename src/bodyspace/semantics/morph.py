"""Semantic morphing (Hasler §4, Hasler Equation 11, and Hasler §5.1 comparison directions).

One constraint: walk the regressor's gradient, ``d' = d + lambda s``; to change the label by
``delta``, ``lambda = delta / ||s||^2``.

Several constraints at once (Hasler Equation 11): each constraint ``i`` alone would move the body by
``v_i = delta_i s_i / ||s_i||^2``. Find one step ``z`` with ``<z, v_i> / ||v_i|| = ||v_i||`` for
every ``i``; multiplying row ``i`` by ``||s_i||^2 / delta_i`` shows it is the same row as
``<s_i, z> = delta_i``: the first-order change of label ``i`` is exactly ``delta_i``. The rows
``G z = delta`` (``G`` stacks the gradients) are usually under-determined; the minimum-norm
solution ``z = G^+ delta`` changes the subject as little as possible. The ``<s_i, z> = delta_i``
form also covers ``delta_i = 0`` ("keep this label"), where Hasler Equation 11 degenerates
(``v_i = 0``): "taller but the same weight" is the pair (stature +5 cm, weight +0 kg).

For non-linear regressors the gradients change along the way, so ``morph`` takes several such
minimum-norm steps (a Gauss-Newton walk) towards label values interpolated from the start to
the targets, then refines until the labels are met.

Hasler §5.1: when a quality is easier to compare than to measure (muscularity), a judge says which of
two scans is more so; the mean of the normalized differences "b - a" is the direction
(``comparison_direction``), and ``ComparisonRegressor`` makes it usable like any regressor.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from bodyspace.errors import ParameterError
from bodyspace.semantics.regressors import LinearModel
from bodyspace.validation import as_int, as_matrix, as_vector

__all__ = ["morph_directions", "morph", "comparison_direction", "ComparisonRegressor"]


def morph_directions(gradients, deltas, metric=None, rcond: float = 1e-10) -> np.ndarray:
    """Hasler Equation 11: the smallest step ``z`` (D,) with ``<gradients[i], z> = deltas[i]`` for all i.

    Args:
        gradients: (C, D) one label gradient (morphing direction) per constraint, or (D,).
        deltas: (C,) requested change of every label (0 holds a label fixed, to first order).
        metric: optional (D,) positive weights: minimise ``sum metric_j z_j^2`` instead of
            ``||z||^2`` (e.g. ``1 / explained_variance_`` on PCA coefficients for the most
            probable change). None: the plain minimum norm of Hasler Equation 11.
        rcond: relative singular-value cut-off of the pseudo-inverse; contradictory or
            parallel constraints are met in the least-squares sense.

    Returns:
        z (D,). With one constraint, ``z = delta s / ||s||^2``: walking the gradient.
    """
    g = as_matrix(gradients, "gradients", allow_vector=True)
    dl = as_vector(np.atleast_1d(np.asarray(deltas, dtype=float)), "deltas", g.shape[0])
    if metric is None:
        return np.linalg.pinv(g, rcond=rcond) @ dl
    w = as_vector(metric, "metric", g.shape[1])
    if (w <= 0).any():
        raise ParameterError("metric: contains values <= 0, expected positive weights")
    gw = g / w                                                   # G M^-1
    return gw.T @ (np.linalg.pinv(gw @ g.T, rcond=rcond, hermitian=True) @ dl)


def _check_regressors(regressors: Mapping) -> None:
    if not isinstance(regressors, Mapping) or not regressors:
        raise ParameterError(f"regressors: got {type(regressors).__name__}, expected a non-empty dict "
                             "name -> fitted regressor")
    for name, reg in regressors.items():
        if not (hasattr(reg, "predict") and hasattr(reg, "gradient")):
            raise ParameterError(f"regressors[{name!r}]: {type(reg).__name__} has no predict/gradient, "
                                 "expected a fitted semantic regressor")


def morph(x, regressors: Mapping, targets: Mapping, keep=(), steps: int = 10, refine: int = 10,
          tol: float = 1e-6, metric=None) -> np.ndarray:
    """Walk body ``x`` to the requested label values while holding others (Hasler Equation 11, iterated).

    At step ``t = 1..steps`` every targeted label aims at ``start + (target - start) t / steps``
    and every kept label at its start value; the minimum-norm step (``morph_directions``) at the
    current gradients moves there to first order. Up to ``refine`` further steps then aim at the
    final values until every residual is below ``tol`` (in label units). For linear regressors
    the first step is already exact.

    Args:
        x: (D,) body (encoding or PCA coefficients, as the regressors were fitted on).
        regressors: name -> fitted regressor (``predict``, ``gradient``).
        targets: name -> requested label value.
        keep: names to hold at their value at ``x``, or a dict name -> value to hold at.
        steps: intermediate targets (more steps follow a curved model more closely).
        refine: extra Gauss-Newton steps at the end (0: none).
        tol: label residual at which refinement stops.
        metric: optional (D,) weights, as in ``morph_directions``.

    Returns:
        path (S, D): ``path[0] = x``, ``path[-1]`` the morphed body (S = steps + 1 + refinements).
    """
    x0 = as_vector(x, "x")
    _check_regressors(regressors)
    if not isinstance(targets, Mapping):
        raise ParameterError(f"targets: got {type(targets).__name__}, expected a dict name -> value")
    keep_map = dict(keep) if isinstance(keep, Mapping) else {k: None for k in keep}
    names = list(targets) + list(keep_map)
    if not names:
        raise ParameterError("targets: empty and nothing to keep, expected at least one constraint")
    for n in names:
        if n not in regressors:
            raise ParameterError(f"targets/keep: unknown label {n!r}, expected one of {list(regressors)}")
    both = set(targets) & set(keep_map)
    if both:
        raise ParameterError(f"keep: {sorted(both)} also in targets, expected each label in one of them")
    steps = as_int(steps, "steps", 1)
    refine = as_int(refine, "refine", 0)
    regs = [regressors[n] for n in names]
    start = np.array([r.predict(x0) for r in regs], dtype=float)
    goal = np.array([float(targets[n]) for n in targets]
                    + [start[len(targets) + i] if v is None else float(v) for i, v in enumerate(keep_map.values())])
    if not np.isfinite(goal).all():
        raise ParameterError("targets/keep: contain NaN or infinity, expected finite label values")

    path = [x0]
    cur = x0
    for t in range(1, steps + 1):
        aim = start + (goal - start) * t / steps
        cur = _step(cur, regs, aim, metric)
        path.append(cur)
    for _ in range(refine):
        resid = goal - np.array([r.predict(cur) for r in regs])
        if np.max(np.abs(resid)) <= tol:
            break
        cur = _step(cur, regs, goal, metric)
        path.append(cur)
    return np.array(path)


def _step(x, regs, aim, metric):
    grads = np.array([r.gradient(x) for r in regs])
    deltas = aim - np.array([r.predict(x) for r in regs])
    return x + morph_directions(grads, deltas, metric=metric)


# ---------------------------------------------------------------------------- Hasler §5.1 comparisons
def comparison_direction(pairs_a, pairs_b) -> np.ndarray:
    """Hasler §5.1: the unit direction (D,) from judged pairs "b is more X than a".

    Every pair defines a direction ``b - a``; they are normalized, averaged, and the mean is
    normalized: ``u = mean_i (b_i - a_i)/||b_i - a_i||``, ``u / ||u||``.

    Args:
        pairs_a, pairs_b: (M, D) (or (D,) for one pair) bodies, row ``i`` of ``pairs_b`` judged
            more X than row ``i`` of ``pairs_a``.
    """
    a = as_matrix(pairs_a, "pairs_a", allow_vector=True)
    b = as_matrix(pairs_b, "pairs_b", n_features=a.shape[1], allow_vector=True)
    if a.shape != b.shape:
        raise ParameterError(f"pairs_b: shape {b.shape}, expected {a.shape} (one partner per row of pairs_a)")
    diff = b - a
    norm = np.linalg.norm(diff, axis=1)
    scale = max(np.abs(a).max(), np.abs(b).max(), 1e-300)
    same = np.flatnonzero(norm <= 1e-12 * scale)
    if same.size:
        raise ParameterError(f"pairs: rows {same[:10].tolist()} have identical bodies a and b, "
                             "expected two different bodies per comparison")
    mean = (diff / norm[:, None]).mean(axis=0)
    length = np.linalg.norm(mean)
    if length <= 1e-12:
        raise ParameterError("pairs: the normalized differences cancel out (mean ~ 0), "
                             "expected judgements that agree on a direction")
    return mean / length


class ComparisonRegressor(LinearModel):
    """A semantic label learned from pairwise comparisons (Hasler §5.1), usable like any regressor.

    ``fit(X, pairs)``: ``X`` (N, D) the database, ``pairs`` (M, 2) row indices ``(i, j)`` meaning
    "``X[j]`` is more X than ``X[i]``". The direction is ``comparison_direction(X[i], X[j])``; the
    label is the position along it in database standard deviations,
    ``f(x) = <x - mean_, direction_> / scale_``, so ``delta = 1`` in ``morph`` means "one SD more".

    Attributes (after ``fit``):
        direction_: (D,) unit direction. mean_: (D,). scale_: SD of the database along it.
        coef_ = direction_ / scale_ (the gradient), intercept_. n_features_in_: int.
    """

    _state = ("coef_", "intercept_", "direction_", "scale_", "n_features_in_")

    def __init__(self):
        pass

    def fit(self, X, pairs) -> "ComparisonRegressor":
        x = as_matrix(X, "X", min_rows=2)
        p = np.asarray(pairs)
        if p.ndim != 2 or p.shape[1] != 2 or p.shape[0] < 1 or not np.issubdtype(p.dtype, np.integer):
            raise ParameterError(f"pairs: shape {p.shape} dtype {p.dtype}, expected integer (M, 2) row indices "
                                 "(less, more)")
        if p.min() < 0 or p.max() >= x.shape[0]:
            raise ParameterError(f"pairs: indices {p.min()}..{p.max()}, expected 0..{x.shape[0] - 1} (rows of X)")
        self.direction_ = comparison_direction(x[p[:, 0]], x[p[:, 1]])
        self.mean_ = x.mean(axis=0)
        sd = float(np.std((x - self.mean_) @ self.direction_))
        self.scale_ = sd if sd > 0 else 1.0
        self.coef_ = self.direction_ / self.scale_
        self.intercept_ = float(-self.mean_ @ self.coef_)
        self.n_features_in_ = x.shape[1]
        return self
