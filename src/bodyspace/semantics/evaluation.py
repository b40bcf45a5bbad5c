"""Accuracy of the semantic regressors: Hasler Table 1 and Hasler Table 2.

Hasler Table 1: RMSE from 10-fold cross-validation, for each label and each regressor, on a model
that contains every subject exactly once (``cross_validated_rmse``; pass one row per subject,
or ``groups`` = subject ids so that no subject is split between training and test folds). A
label is split over the rows that know it; with few of them (a small database, a label given
for some subjects only) the split becomes leave-one-out, so that every training set keeps the
rows a regressor needs (``label_folds``).

Hasler Table 2: mean and SD of the angles between the morphing directions (gradients) of the
non-linear model taken at every subject (``direction_angles``). Small angles mean the gradient
hardly depends on where in shape space it is taken, i.e. a linear function is admissible.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass

import numpy as np

from bodyspace.errors import ParameterError
from bodyspace.semantics.regressors import (
    FilteredLinearRegressor,
    KernelRegressor,
    SimpleLinearRegressor,
    kfold_indices,
)
from bodyspace.validation import as_generator, as_matrix

__all__ = ["RegressionTable", "MIN_TRAINING_ROWS", "label_folds", "default_regressors", "cross_validated_rmse",
           "direction_angles", "format_rmse_table", "format_angle_table"]


def default_regressors(rng=None) -> dict[str, Callable]:
    """The three rows of Hasler Table 1: name -> factory of an unfitted regressor."""
    return {
        "simple linear": SimpleLinearRegressor,
        "filtered linear": lambda: FilteredLinearRegressor(rng=rng),
        "non-linear": KernelRegressor,
    }


# The filtered linear and the kernel regressor fit on at least this many rows; a label's folds
# leave every training set at least this many known values (leave-one-out when few are known).
MIN_TRAINING_ROWS = 3


@dataclass
class RegressionTable:
    """Hasler Table 1: ``rmse[r, l]`` of regressor ``regressors[r]`` on label ``labels[l]``;
    ``n_samples[l]`` rows with that label were used (rows with NaN labels are left out).
    ``folds``: the folds asked for; ``label_folds[l]``: the folds label l was split into (fewer
    when it has fewer known values, leave-one-out when a fold would leave fewer than
    ``MIN_TRAINING_ROWS`` to train on)."""

    regressors: list[str]
    labels: list[str]
    rmse: np.ndarray
    n_samples: np.ndarray
    folds: int
    label_folds: np.ndarray | None = None

    def __str__(self) -> str:
        return format_rmse_table(self)

    def to_markdown(self) -> str:
        return format_rmse_table(self, markdown=True)


def label_folds(units: int, folds: int) -> int:
    """The folds for a label known on ``units`` rows (or subjects): ``folds``, at most ``units``,
    and ``units`` (leave-one-out) when a fold of ``folds`` would leave fewer than
    ``MIN_TRAINING_ROWS`` to train on."""
    k = min(int(folds), units)
    if units - -(-units // k) < MIN_TRAINING_ROWS:
        k = units
    return k


def cross_validated_rmse(X, labels: Mapping, regressors: Mapping | None = None, folds: int = 10,
                         rng=None, groups=None) -> RegressionTable:
    """Hasler Table 1: pooled held-out RMSE of k-fold cross-validation, per regressor and label.

    Args:
        X: (N, D) bodies (encodings or PCA coefficients), one per subject.
        labels: name -> (N,) label values; NaN marks a missing label (that row is left out for
            that label). Each label needs ``MIN_TRAINING_ROWS + 1`` known values.
        regressors: name -> factory (a class or a zero-argument callable) of an unfitted
            regressor; None: ``default_regressors(rng)``.
        folds: k, 2 up to the number of rows (groups); k = rows is leave-one-out. More folds
            than rows are refused (which k was meant?). A label is split over its known rows
            only, into ``label_folds(known, folds)`` folds (leave-one-out for a label known on
            few rows: every training set keeps ``MIN_TRAINING_ROWS``).
        rng: numpy Generator, seed or None: the shuffle (one split per label, the same for
            every regressor, so the rows of the table are paired comparisons).
        groups: optional (N,) subject ids; a subject's rows stay in one fold.

    Returns:
        RegressionTable; RMSE is ``sqrt(mean over all held-out rows of (prediction - label)^2)``.
    """
    x = as_matrix(X, "X", min_rows=2)
    n = x.shape[0]
    if not isinstance(labels, Mapping) or not labels:
        raise ParameterError(f"labels: got {type(labels).__name__}, expected a non-empty dict name -> (N,) values")
    gen = as_generator(rng)
    if regressors is None:
        regressors = default_regressors(gen)
    if not isinstance(regressors, Mapping) or not regressors:
        raise ParameterError(f"regressors: got {type(regressors).__name__}, expected a non-empty dict name -> factory")
    for name, factory in regressors.items():
        if not callable(factory):
            raise ParameterError(f"regressors[{name!r}]: {factory!r} is not callable, expected a class or factory")
    group_ids = None if groups is None else np.asarray(groups)
    if group_ids is not None and group_ids.shape != (n,):
        raise ParameterError(f"groups: shape {group_ids.shape}, expected ({n},) (one group id per row)")
    values, units = {}, {}
    for name, y in labels.items():
        v = np.asarray(y, dtype=float)
        if v.shape != (n,):
            raise ParameterError(f"labels[{name!r}]: shape {v.shape}, expected ({n},) (one value per row of X)")
        if np.isinf(v).any():
            raise ParameterError(f"labels[{name!r}]: contains infinity, expected finite values or NaN for missing")
        known = np.isfinite(v)
        units[name] = int(known.sum()) if group_ids is None else len(np.unique(group_ids[known]))
        if units[name] < MIN_TRAINING_ROWS + 1:
            what = "known value(s)" if group_ids is None else "subject(s) with a known value"
            raise ParameterError(f"labels[{name!r}]: {units[name]} {what}, expected at least {MIN_TRAINING_ROWS + 1} "
                                 f"(one to hold out, {MIN_TRAINING_ROWS} to train on)")
        values[name] = v
    total = n if group_ids is None else len(np.unique(group_ids))
    if isinstance(folds, (bool, np.bool_)) or not isinstance(folds, (int, np.integer)) or not 2 <= folds <= total:
        what = "rows (subjects)" if groups is None else "subjects (groups)"
        raise ParameterError(f"folds {folds!r}: there are {total} {what} to split, expected 2..{total} folds "
                             f"({total} is leave-one-out)")
    rmse = np.empty((len(regressors), len(values)))
    counts = np.empty(len(values), dtype=int)
    used_folds = np.empty(len(values), dtype=int)
    for li, (lname, v) in enumerate(values.items()):
        known = np.flatnonzero(np.isfinite(v))
        counts[li] = len(known)
        k = label_folds(units[lname], folds)
        tests = [known[t] for t in kfold_indices(len(known), k, gen,
                                                 None if group_ids is None else group_ids[known])]
        used_folds[li] = len(tests)
        for ri, (rname, factory) in enumerate(regressors.items()):
            sq = []
            for test in tests:
                train = np.setdiff1d(known, test)
                model = factory().fit(x[train], v[train])
                sq.append((model.predict(x[test]) - v[test]) ** 2)
            rmse[ri, li] = np.sqrt(np.mean(np.concatenate(sq)))
    return RegressionTable(list(regressors), list(values), rmse, counts, int(folds), used_folds)


def direction_angles(regressor, X, reference="mean") -> tuple[float, float]:
    """Hasler Table 2: mean and SD (degrees) of the angles between the morphing directions
    ``regressor.gradient(x_i)`` taken at every body ``x_i`` of ``X`` (N, D).

    The paper does not say which pairs of directions it compares; ``reference`` chooses:
    ``"mean"`` (default) the angle of every direction to the mean of the normalized
    directions; ``"pairwise"`` every pair ``i < j``; or a (D,) vector (e.g. the filtered linear
    gradient). SD is the population SD (``ddof=0``).
    """
    x = as_matrix(X, "X", min_rows=2)
    g = np.asarray(regressor.gradient(x), dtype=float)
    if g.shape != x.shape:
        raise ParameterError(f"regressor.gradient: shape {g.shape}, expected {x.shape}")
    norms = np.linalg.norm(g, axis=1)
    if (norms == 0).any():
        raise ParameterError(f"regressor.gradient: zero at rows {np.flatnonzero(norms == 0)[:10].tolist()}, "
                             "expected a defined direction at every body")
    u = g / norms[:, None]
    if isinstance(reference, str) and reference == "pairwise":
        cos = (u @ u.T)[np.triu_indices(len(u), 1)]
    else:
        if isinstance(reference, str):
            if reference != "mean":
                raise ParameterError(f"reference={reference!r}, expected 'mean', 'pairwise' or a (D,) vector")
            ref = u.mean(axis=0)
        else:
            ref = np.asarray(reference, dtype=float)
            if ref.shape != (x.shape[1],) or not np.isfinite(ref).all():
                raise ParameterError(f"reference: shape {ref.shape}, expected ({x.shape[1]},) finite")
        rn = np.linalg.norm(ref)
        if rn == 0:
            raise ParameterError("reference: zero vector, expected a direction")
        cos = u @ (ref / rn)
    ang = np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))
    return float(ang.mean()), float(ang.std())


# ---------------------------------------------------------------------------- formatting
def _render(header: list[str], rows: list[list[str]], markdown: bool) -> str:
    if markdown:
        lines = ["| " + " | ".join(header) + " |", "|" + "|".join(["---"] + ["---:"] * (len(header) - 1)) + "|"]
        lines += ["| " + " | ".join(r) + " |" for r in rows]
        return "\n".join(lines)
    widths = [max(len(r[i]) for r in [header] + rows) for i in range(len(header))]
    fmt = lambda r: "  ".join(c.ljust(widths[0]) if i == 0 else c.rjust(widths[i]) for i, c in enumerate(r))  # noqa: E731
    return "\n".join(fmt(r).rstrip() for r in [header] + rows)


def format_rmse_table(table: RegressionTable, markdown: bool = False, digits: int = 3) -> str:
    """Hasler Table 1 layout: one row per regressor, one column per label (``digits`` significant)."""
    header = ["Regressor"] + list(table.labels)
    rows = [[name] + [f"{v:.{digits}g}" for v in table.rmse[i]] for i, name in enumerate(table.regressors)]
    return _render(header, rows, markdown)


def format_angle_table(angles: Mapping, markdown: bool = False, digits: int = 3) -> str:
    """Hasler Table 2 layout: one column per label, rows μ (mean) and σ (SD) in degrees, from a dict
    label -> ``(mean_deg, sd_deg)`` (``direction_angles`` per label)."""
    if not isinstance(angles, Mapping) or not angles:
        raise ParameterError(f"angles: got {type(angles).__name__}, expected a non-empty dict label -> (mean, sd)")
    header = [""] + list(angles)
    rows = [["μ"] + [f"{m:.{digits}g}" for m, _ in angles.values()],
            ["σ"] + [f"{s:.{digits}g}" for _, s in angles.values()]]
    return _render(header, rows, markdown)
