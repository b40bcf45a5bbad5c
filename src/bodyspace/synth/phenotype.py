"""Phenotype to mesh: our implementation of MakeHuman's macro modifiers.

A phenotype is eleven numbers in [0, 1]: ``gender`` (0 female, 1 male), ``age``, ``muscle``,
``weight``, ``height``, ``proportions``, ``cupsize``, ``firmness`` and the ``african``,
``asian``, ``caucasian`` mix (normalized to sum one). Each macro target file is named by the
categories it stands for, e.g. ``universal-female-young-maxmuscle-averageweight``; its weight
for a body is the product of the weights of those categories, and the body is
``base + sum_t weight_t * target_t``. The rules, and where they come from, are in
docs/phenotype.md.

Batches go through one product: the (N, T) target-weight matrix is sparse (a body uses at most
2 categories per variable, so about 100 of the 576 targets) and multiplies the dense (T, V*3)
target matrix once for the whole batch.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping

import numpy as np
import scipy.sparse as sp

from bodyspace.data.template import Template
from bodyspace.errors import ParameterError

PARAMETERS = ("gender", "age", "muscle", "weight", "height", "proportions",
              "cupsize", "firmness", "african", "asian", "caucasian")
DEFAULTS = {"gender": 0.5, "age": 0.5, "muscle": 0.5, "weight": 0.5, "height": 0.5,
            "proportions": 0.5, "cupsize": 0.5, "firmness": 0.5,
            "african": 1 / 3, "asian": 1 / 3, "caucasian": 1 / 3}
RACES = ("african", "asian", "caucasian")

# Category names per variable, in the order of their breakpoints (docs/phenotype.md).
# ``None`` marks a neutral category that has no target file (weight simply unused).
CATEGORIES: dict[str, tuple[str | None, ...]] = {
    "race": RACES,
    "gender": ("female", "male"),
    "age": ("baby", "child", "young", "old"),
    "muscle": ("minmuscle", "averagemuscle", "maxmuscle"),
    "weight": ("minweight", "averageweight", "maxweight"),
    "height": ("minheight", None, "maxheight"),
    "proportions": ("uncommonproportions", None, "idealproportions"),
    "cupsize": ("mincup", "averagecup", "maxcup"),
    "firmness": ("minfirmness", "averagefirmness", "maxfirmness"),
}
# Breakpoints of the piecewise-linear category weights (MakeHuman's macro.json ranges).
BREAKPOINTS = {"age": (0.0, 0.1875, 0.5, 1.0)}
_TOKEN = {tok: (var, i) for var, cats in CATEGORIES.items() for i, tok in enumerate(cats) if tok}

# MakeHuman's age scale: 0 → 1 year, 0.1875 → 10 years, 0.5 → 25 years, 1 → 90 years.
AGE_YEARS = (1.0, 25.0, 90.0)


def age_to_years(age: np.ndarray) -> np.ndarray:
    """MakeHuman age parameter in [0, 1] → years (piecewise linear, 25 years at 0.5)."""
    return np.interp(age, (0.0, 0.5, 1.0), AGE_YEARS)


def years_to_age(years: np.ndarray) -> np.ndarray:
    """Years (1..90) → MakeHuman age parameter; inverse of ``age_to_years``."""
    return np.interp(years, AGE_YEARS, (0.0, 0.5, 1.0))


def category_weights(variable: str, value: np.ndarray) -> np.ndarray:
    """Weights (N, C) of a variable's categories at ``value`` (N,): hat functions on the breakpoints.

    For three categories with breakpoints (0, 0.5, 1): min = max(0, 1 - 2v),
    max = max(0, 2v - 1), average = 1 - min - max, exactly MakeHuman's rule.
    """
    cats = CATEGORIES[variable]
    knots = np.asarray(BREAKPOINTS.get(variable, np.linspace(0.0, 1.0, len(cats))))
    v = np.clip(np.asarray(value, dtype=float), 0.0, 1.0)
    eye = np.eye(len(cats))
    return np.stack([np.interp(v, knots, eye[c]) for c in range(len(cats))], axis=-1)


def phenotype_array(params: Mapping[str, np.ndarray | float] | np.ndarray, n: int | None = None) -> np.ndarray:
    """Validate and normalize phenotypes into an (N, 11) array in ``PARAMETERS`` order.

    ``params`` is an (N, 11) / (11,) array or a mapping from parameter names to scalars or (N,)
    arrays; missing names take ``DEFAULTS``. Race values are normalized to sum one.
    """
    if isinstance(params, Mapping):
        unknown = set(params) - set(PARAMETERS)
        if unknown:
            raise ParameterError(f"unknown phenotype parameter(s) {sorted(unknown)}; expected some of {list(PARAMETERS)}")
        sizes = {np.size(v) for v in params.values() if np.ndim(v) > 0}
        if len(sizes) > 1:
            raise ParameterError(f"phenotype parameters have different lengths {sorted(sizes)}; expected one batch size")
        count = n or (sizes.pop() if sizes else 1)
        arr = np.empty((count, len(PARAMETERS)))
        for j, name in enumerate(PARAMETERS):
            arr[:, j] = np.broadcast_to(np.asarray(params.get(name, DEFAULTS[name]), dtype=float), (count,))
    else:
        arr = np.array(params, dtype=float, ndmin=2)
        if arr.ndim != 2 or arr.shape[1] != len(PARAMETERS):
            raise ParameterError(f"phenotype array has shape {np.shape(params)}; expected (N, {len(PARAMETERS)}) "
                                 f"in the order {list(PARAMETERS)}")
    if not np.isfinite(arr).all():
        bad = PARAMETERS[int(np.argwhere(~np.isfinite(arr))[0, 1])]
        raise ParameterError(f"phenotype parameter {bad!r} is NaN or infinite; expected a value in [0, 1]")
    outside = (arr < 0) | (arr > 1)
    if outside.any():
        i, j = np.argwhere(outside)[0]
        raise ParameterError(f"phenotype parameter {PARAMETERS[j]!r} = {arr[i, j]:g} (body {i}); expected a value in [0, 1]")
    race = arr[:, 8:11]
    total = race.sum(axis=1, keepdims=True)
    if (total <= 0).any():
        raise ParameterError("african + asian + caucasian is 0; expected a positive mix (e.g. 1/3 each)")
    arr[:, 8:11] = race / total
    return arr


@dataclass(frozen=True)
class TargetFactors:
    """Which category of each variable every target stands for (-1: the variable is not used)."""

    variables: tuple[str, ...]
    index: np.ndarray  # (n_variables, T) int


def target_factors(target_names: tuple[str, ...]) -> tuple[TargetFactors, np.ndarray]:
    """Parse target file names into category indices; returns (factors, macro mask (T,) bool).

    A name like ``height/male-young-averagemuscle-minweight-maxheight`` is split on '-'. Names
    with any token that is not a category (``breast-dist-incr``: a detail slider, not a macro
    target) are masked out.
    """
    variables = tuple(CATEGORIES)
    index = np.full((len(variables), len(target_names)), -1)
    macro = np.ones(len(target_names), dtype=bool)
    for t, name in enumerate(target_names):
        for tok in name.rsplit("/", 1)[-1].split("-"):
            if tok == "universal":
                continue
            if tok not in _TOKEN:
                macro[t] = False
                break
            var, cat = _TOKEN[tok]
            index[variables.index(var), t] = cat
    return TargetFactors(variables, index), macro


class PhenotypeModel:
    """Bodies from phenotypes on the template: ``vertices = base + W(phenotype) @ targets``.

    Holds the template base mesh and the dense (T, V*3) macro target matrix; ``weights`` builds
    the sparse (N, T) matrix, ``vertices`` applies it in one product.
    """

    def __init__(self, template: Template):
        factors, macro = target_factors(template.target_names)
        self.template = template
        self.target_names = tuple(n for n, m in zip(template.target_names, macro) if m)
        self.factors = TargetFactors(factors.variables, factors.index[:, macro])
        self.targets = np.ascontiguousarray(template.target_deltas[macro].reshape(int(macro.sum()), -1))  # (T, V*3) float32
        self.base = np.asarray(template.vertices, dtype=float)

    def weights(self, phenotypes: Mapping | np.ndarray) -> sp.csr_matrix:
        """Sparse target weights (N, T) for phenotypes (see ``phenotype_array``)."""
        p = phenotype_array(phenotypes)
        value = {name: p[:, j] for j, name in enumerate(PARAMETERS)}
        W = np.ones((len(p), self.targets.shape[0]))
        for v, var in enumerate(self.factors.variables):
            cat = self.factors.index[v]
            if var == "race":
                cw = p[:, 8:11]
            else:
                cw = category_weights(var, value[var])
            # Append a column of ones for targets that do not depend on this variable.
            cw = np.concatenate([cw, np.ones((len(p), 1))], axis=1)
            W *= cw[:, np.where(cat >= 0, cat, cw.shape[1] - 1)]
        return sp.csr_matrix(W)

    def vertices(self, phenotypes: Mapping | np.ndarray) -> np.ndarray:
        """Bodies (N, V, 3) float64 in metres for a batch of phenotypes."""
        W = self.weights(phenotypes).astype(np.float32)
        offsets = W @ self.targets  # one sparse (N, T) × dense (T, V*3) product
        return self.base + offsets.reshape(W.shape[0], -1, 3)
