"""The fitted measurements-to-shape mapping a ``BodyModel`` carries in its file.

``fit_mapping(model)`` draws the training set from the model (Rupprecht §4.1), fits the
linear baseline and the linear-leaf forest on it and, for RRE models, keeps the decoder's
least-squares linearization that exact refinement steps with, and the mean and covariance of
the training measurements. ``MeasurementMapping.shape`` turns requested measurements (cm) into
coefficients: any non-empty subset of the measurement set; the forest's inputs that were not
asked are drawn from the population given the asked ones (the conditional Gaussian of the
training measurements), the forest predicts the start, and the exact refinement (``refine``)
meets the asked measurements, unless told not to. ``to_arrays``/``from_arrays`` store it as flat,
prefixed arrays inside the model's ``.npz`` (no pickle); ``BodyModel.save``/``load`` call them.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from bodyspace.encoding.linearize import DecoderLinearization
from bodyspace.errors import ParameterError
from bodyspace.mapping.forest import LinearLeafForest
from bodyspace.mapping.gradients import SAME_QUANTITY, LinearBodyMeasures
from bodyspace.mapping.linear import LinearMapping
from bodyspace.mapping.refine import RefineResult, refine
from bodyspace.mapping.training import default_sizes, make_training_set, sample_uniform

__all__ = ["MeasurementMapping", "fit_mapping", "forest_for", "conditional_draw", "PREFIX"]

# Key prefix of the mapping's arrays inside a BodyModel file.
PREFIX = "mapping_"
# Files written before the mapping kept its training measurements' statistics: they are
# estimated from this many bodies of the model (uniform in the training box, measured on the
# model's linearization; a few ms for a vertex model), once per mapping.
STATS_SAMPLES = 2000


def conditional_draw(mean, cov, given: dict, names, rng=None) -> np.ndarray:
    """Values of ``names`` (M,) drawn from the Gaussian ``N(mean, cov)`` (M,), (M, M) given the
    values ``given`` (name -> (N,) or scalar) of some of them (the standard conditional Gaussian:
    ``mu_u + S_ug S_gg^-1 (x_g - mu_g)``, covariance ``S_uu - S_ug S_gg^-1 S_gu``). Returns
    (N, M), the given columns as given. Deterministic given ``rng``."""
    names = list(names)
    gi = [names.index(n) for n in given if n in names]
    ui = [j for j in range(len(names)) if j not in gi]
    vals = [np.atleast_1d(np.asarray(given[names[j]], dtype=float)) for j in gi]
    n = max([len(v) for v in vals] + [1])
    out = np.empty((n, len(names)))
    for j, v in zip(gi, vals):
        out[:, j] = v
    if ui:
        mean, cov = np.asarray(mean, dtype=float), np.asarray(cov, dtype=float)
        mu, S_uu = mean[ui], cov[np.ix_(ui, ui)]
        if gi:
            S_gg, S_ug = cov[np.ix_(gi, gi)], cov[np.ix_(ui, gi)]
            gain = np.linalg.lstsq(S_gg, S_ug.T, rcond=None)[0].T            # S_ug S_gg^-1, (U, G)
            mu = mu + (out[:, gi] - mean[gi]) @ gain.T
            S_uu = S_uu - gain @ S_ug.T
        w, vec = np.linalg.eigh(0.5 * (S_uu + S_uu.T))
        root = vec * np.sqrt(np.clip(w, 0.0, None))
        out[:, ui] = mu + np.random.default_rng(rng).standard_normal((n, len(ui))) @ root.T
    return out


@dataclass
class MeasurementMapping:
    """Fitted mapping from measurements (cm, columns in the order of ``names``) to the first ``k``
    shape coefficients of the model it was fitted on.

    Attributes:
        names: its input measurements (of the model's set): Rupprecht's six on the template, their
            stand-ins on another topology (``gradients.mapping_inputs``).
        k: coefficients the mapping predicts (the rest stay 0).
        forest: ``LinearLeafForest`` (measurements -> k coefficients).
        linear: ``LinearMapping``, the related work's baseline, same interface.
        linearization: ``DecoderLinearization`` (RRE models; None for the vertex encoding).
        samples: size of the training set.
        measurement_mean, measurement_cov: (M,), (M, M) of the training measurements (cm), the
            population the inputs not asked are drawn from (None in files written before them:
            estimated from the model on first use).
    """

    names: tuple
    k: int
    forest: LinearLeafForest
    linear: LinearMapping
    linearization: DecoderLinearization | None = None
    samples: int = 0
    measurement_mean: np.ndarray | None = None
    measurement_cov: np.ndarray | None = None

    def _targets(self, targets) -> np.ndarray:
        if isinstance(targets, dict):
            missing = [n for n in self.names if n not in targets]
            extra = [n for n in targets if n not in self.names]
            if missing or extra:
                raise ParameterError(f"targets: missing {missing}, unknown {extra}; expected exactly "
                                     f"{', '.join(self.names)} (cm)")
            targets = [targets[n] for n in self.names]
        t = np.asarray(targets, dtype=float)
        if t.ndim == 1:
            t = t[None]
        if t.ndim != 2 or t.shape[1] != len(self.names) or not np.isfinite(t).all():
            raise ParameterError(f"targets: shape {np.shape(targets)}, expected (N, {len(self.names)}) finite "
                                 f"values in cm, columns {', '.join(self.names)}")
        return t

    def predict(self, targets, method: str = "forest") -> np.ndarray:
        """Coefficients (N, k) of requested measurements (N, M) cm (or a dict name -> cm), by the
        ``"forest"`` or the ``"linear"`` mapping alone."""
        t = self._targets(targets)
        if method == "forest":
            return self.forest.predict(t)
        if method == "linear":
            return self.linear.predict(t)
        raise ParameterError(f"method={method!r}, expected 'forest' or 'linear'")

    def statistics(self, model) -> tuple[np.ndarray, np.ndarray]:
        """Mean (M,) and covariance (M, M) (cm) of the training measurements: stored, or (older
        files) estimated once from ``STATS_SAMPLES`` bodies of ``model`` in the training box."""
        if self.measurement_mean is None or self.measurement_cov is None:
            k = min(self.k, model.n_components)
            z = sample_uniform(model, STATS_SAMPLES, k, rng=0)[:, :k]
            x = LinearBodyMeasures.from_model(model, None, self.names, k, linearization=self.linearization)(z) * 100.0
            self.measurement_mean, self.measurement_cov = x.mean(axis=0), np.cov(x, rowvar=False)
        return self.measurement_mean, self.measurement_cov

    def given_inputs(self, targets: dict) -> dict:
        """The mapping's inputs a request ``targets`` (name -> cm) fixes: {input name: value}, the
        asked ones and those asked under another name of the same quantity (``SAME_QUANTITY``:
        stature=175cm fixes the input height; drawn from the population instead, it started the
        forest at 176.6 cm)."""
        given = {n: v for n, v in targets.items() if n in self.names}
        for n in self.names:
            alias = next((a for a in SAME_QUANTITY.get(n, ()) if a in targets), None)
            if n not in given and alias is not None:
                given[n] = targets[alias]
        return given

    def inputs(self, model, targets: dict, rng=None) -> np.ndarray:
        """The forest's inputs (N, M) cm for a request ``targets`` (name -> cm, scalar or (N,)):
        the mapping's names that were asked as asked (``given_inputs``), the others drawn from
        the population given them (``conditional_draw`` of ``statistics``). Deterministic given
        ``rng``."""
        mean, cov = self.statistics(model)
        return conditional_draw(mean, cov, self.given_inputs(targets), self.names, rng)

    def shape(self, model, targets, refine_result: bool = True, rng=None, **refine_kw) -> RefineResult:
        """Coefficients of bodies that measure ``targets`` (cm): a ``RefineResult`` (coefficients
        (N, K'), measured, misses, in the order of ``RefineResult.names``).

        ``targets``: (N, M) in the order of ``names`` (all of the mapping's measurements), or a
        dict name -> cm (scalar or (N,)) of any non-empty subset of the measurement set (lengths
        in cm, e.g. ``{"waist_size": 80}``): the mapping's inputs not asked are drawn from the
        population given the asked ones (``inputs``, deterministic given ``rng``), the forest
        predicts the start, and ``refine`` meets the asked measurements (names outside the
        mapping's are refined too: analytic Jacobians, or forward differences for slices).
        ``refine_kw`` go to ``refine`` (tol_cm, max_iter, prior_weight, tolerances, linear ...)."""
        if isinstance(targets, dict):
            if not targets:
                raise ParameterError("targets: empty, expected at least one measurement name -> cm, e.g. "
                                     "{'waist_size': 80}")
            names = tuple(targets)
            cols = [np.atleast_1d(np.asarray(targets[n], dtype=float)) for n in names]
            n = max(len(c) for c in cols)
            if any(len(c) not in (1, n) for c in cols) or any(c.ndim != 1 for c in cols):
                raise ParameterError(f"targets: values of lengths {[len(c) for c in cols]}, expected scalars or "
                                     f"arrays of one length (N,)")
            t = np.column_stack([np.broadcast_to(c, (n,)) for c in cols])
            if not np.isfinite(t).all():
                raise ParameterError("targets: contain NaN or infinity, expected finite values in cm")
            x = self.inputs(model, dict(zip(names, t.T)), rng)
        else:
            t = x = self._targets(targets)
            names = self.names
        z = self.predict(x)
        if not refine_result:
            refine_kw = {**refine_kw, "max_iter": 0}
        return refine(model, z, t, names, k=self.k, linearization=self.linearization, **refine_kw)

    def to_arrays(self, prefix: str = PREFIX) -> dict[str, np.ndarray]:
        """Flat arrays (no object dtype) under ``prefix``: names, k, samples, the forest's and the
        linear mapping's arrays, and the linearization's (RRE)."""
        out = {prefix + "names": np.array(list(self.names)), prefix + "k": np.array(int(self.k)),
               prefix + "samples": np.array(int(self.samples))}
        out.update({prefix + "forest_" + key: v for key, v in self.forest.to_arrays().items()})
        out.update({prefix + "linear_" + key: v for key, v in self.linear.to_arrays().items()})
        if self.linearization is not None:
            out.update(self.linearization.to_arrays(prefix + "linearization_"))
        if self.measurement_mean is not None and self.measurement_cov is not None:
            out[prefix + "measurement_mean"] = np.asarray(self.measurement_mean, dtype=np.float64)
            out[prefix + "measurement_cov"] = np.asarray(self.measurement_cov, dtype=np.float64)
        return out

    @classmethod
    def from_arrays(cls, arrays, prefix: str = PREFIX) -> "MeasurementMapping":
        """Inverse of ``to_arrays``; checks that the parts agree on the number of measurements
        and coefficients."""
        for key in ("names", "k", "samples"):
            if prefix + key not in arrays:
                raise ParameterError(f"mapping: array '{prefix + key}' missing; expected the arrays written by "
                                     "MeasurementMapping.to_arrays")
        names = tuple(str(n) for n in np.asarray(arrays[prefix + "names"]).ravel())
        k = int(np.asarray(arrays[prefix + "k"]))

        def part(tag):
            return {key[len(prefix + tag):]: arrays[key] for key in arrays if key.startswith(prefix + tag)}

        forest = LinearLeafForest.from_arrays(part("forest_"))
        linear = LinearMapping.from_arrays(part("linear_"))
        linearization = None
        if any(key.startswith(prefix + "linearization_") for key in arrays):
            linearization = DecoderLinearization.from_arrays(arrays, prefix + "linearization_")
        for what, est in (("forest", forest), ("linear", linear)):
            if est.n_features_in_ != len(names) or est.n_outputs_ != k:
                raise ParameterError(f"mapping: the {what} maps {est.n_features_in_} measurements to "
                                     f"{est.n_outputs_} coefficients, expected {len(names)} to {k}")
        mean = cov = None
        if prefix + "measurement_mean" in arrays and prefix + "measurement_cov" in arrays:
            mean = np.asarray(arrays[prefix + "measurement_mean"], dtype=float)
            cov = np.asarray(arrays[prefix + "measurement_cov"], dtype=float)
            m = len(names)
            if mean.shape != (m,) or cov.shape != (m, m) or not (np.isfinite(mean).all() and np.isfinite(cov).all()):
                raise ParameterError(f"mapping: measurement_mean {mean.shape} / measurement_cov {cov.shape}, expected "
                                     f"({m},) / ({m}, {m}) finite values")
        return cls(names, k, forest, linear, linearization, int(np.asarray(arrays[prefix + "samples"])), mean, cov)


def forest_for(n_samples: int, rng=0, n_trees: int = 50, n_jobs: int | None = None) -> LinearLeafForest:
    """The unfitted forest for a training set of ``n_samples``: the paper's defaults, leaves of at
    least 30 samples, or of one for tiny (test) training sets."""
    return LinearLeafForest(n_trees=n_trees, rng=rng, n_jobs=n_jobs, min_samples_leaf=min(30, n_samples))


def fit_mapping(model, samples: int | None = None, k: int = 25, names=None, rng=0,
                n_trees: int = 50, n_jobs: int | None = None, progress=None) -> MeasurementMapping:
    """Fit the mapping of ``model`` (a ``BodyModel``) from a training set drawn from it.

    ``names``: its input measurements, default ``gradients.mapping_inputs`` of the model's
    measurement set (Rupprecht's six on the template; ISO girths standing in for the template's
    loops on another topology); the mapping stores them (``MeasurementMapping.names``).

    ``samples`` defaults to 10,000 for vertex models and 1,000 for RRE models (every RRE body is
    decoded; see docs/mapping.md). Deterministic given ``rng`` (a seed). ``progress(message, fraction)``.
    """
    samples = default_sizes(model)[0] if samples is None else int(samples)
    report = progress or (lambda msg, frac: None)
    train = make_training_set(model, samples, k, rng=rng, names=names,
                              progress=lambda msg, f: report(f"training set: {msg}", 0.8 * f))
    X, Y = train.measurements, train.coefficients[:, :train.k]
    report("linear mapping and forest", 0.8)
    linear = LinearMapping().fit(X, Y)
    forest = forest_for(len(X), rng, n_trees, n_jobs).fit(X, Y)
    report("done", 1.0)
    return MeasurementMapping(tuple(train.names), train.k, forest, linear, train.linearization, samples,
                              X.mean(axis=0), np.cov(X, rowvar=False) if len(X) > 1 else np.zeros((X.shape[1],) * 2))
