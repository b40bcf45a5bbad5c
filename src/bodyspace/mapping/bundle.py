"""The fitted measurements-to-shape mapping a ``BodyModel`` carries in its file.

``fit_mapping(model)`` draws the training set from the model (Rupprecht §4.1), fits the
linear baseline and the linear-leaf forest on it and, for RRE models, keeps the decoder's
least-squares linearization that exact refinement steps with. ``MeasurementMapping.shape``
turns requested measurements (cm) into coefficients: the forest's prediction, then the exact
refinement (``refine``) unless asked not to. ``to_arrays``/``from_arrays`` store it as flat,
prefixed arrays inside the model's ``.npz`` (no pickle); ``BodyModel.save``/``load`` call them.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from bodyspace.encoding.linearize import DecoderLinearization
from bodyspace.errors import ParameterError
from bodyspace.mapping.forest import LinearLeafForest
from bodyspace.mapping.gradients import RUPPRECHT_SIX
from bodyspace.mapping.linear import LinearMapping
from bodyspace.mapping.refine import RefineResult, refine
from bodyspace.mapping.training import default_sizes, make_training_set

__all__ = ["MeasurementMapping", "fit_mapping", "forest_for", "PREFIX"]

# Key prefix of the mapping's arrays inside a BodyModel file.
PREFIX = "mapping_"


@dataclass
class MeasurementMapping:
    """Fitted mapping from measurements (cm, columns in the order of ``names``) to the first ``k``
    shape coefficients of the model it was fitted on.

    Attributes:
        names: measurement names (hm08 set), e.g. Rupprecht's six.
        k: coefficients the mapping predicts (the rest stay 0).
        forest: ``LinearLeafForest`` (measurements -> k coefficients).
        linear: ``LinearMapping``, the related work's baseline, same interface.
        linearization: ``DecoderLinearization`` (RRE models; None for the vertex encoding).
        samples: size of the training set.
    """

    names: tuple
    k: int
    forest: LinearLeafForest
    linear: LinearMapping
    linearization: DecoderLinearization | None = None
    samples: int = 0

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

    def shape(self, model, targets, refine_result: bool = True, **refine_kw) -> RefineResult:
        """The forest's prediction refined until the decoded bodies measure ``targets`` (cm):
        a ``RefineResult`` (coefficients (N, K'), measured, misses). ``refine_kw`` go to
        ``refine`` (tol_cm, max_iter, prior_weight ...)."""
        t = self._targets(targets)
        z = self.predict(t)
        if not refine_result:
            refine_kw = {**refine_kw, "max_iter": 0}
        return refine(model, z, t, self.names, k=self.k, linearization=self.linearization, **refine_kw)

    def to_arrays(self, prefix: str = PREFIX) -> dict[str, np.ndarray]:
        """Flat arrays (no object dtype) under ``prefix``: names, k, samples, the forest's and the
        linear mapping's arrays, and the linearization's (RRE)."""
        out = {prefix + "names": np.array(list(self.names)), prefix + "k": np.array(int(self.k)),
               prefix + "samples": np.array(int(self.samples))}
        out.update({prefix + "forest_" + key: v for key, v in self.forest.to_arrays().items()})
        out.update({prefix + "linear_" + key: v for key, v in self.linear.to_arrays().items()})
        if self.linearization is not None:
            out.update(self.linearization.to_arrays(prefix + "linearization_"))
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
        return cls(names, k, forest, linear, linearization, int(np.asarray(arrays[prefix + "samples"])))


def forest_for(n_samples: int, seed: int = 0, n_trees: int = 50, n_jobs: int | None = None) -> LinearLeafForest:
    """The unfitted forest for a training set of ``n_samples``: the paper's defaults, leaves of at
    least 30 samples, or of one for tiny (test) training sets."""
    return LinearLeafForest(n_trees=n_trees, rng=seed, n_jobs=n_jobs, min_samples_leaf=min(30, n_samples))


def fit_mapping(model, samples: int | None = None, k: int = 25, names=RUPPRECHT_SIX, seed: int = 0,
                n_trees: int = 50, n_jobs: int | None = None, progress=None) -> MeasurementMapping:
    """Fit the mapping of ``model`` (a ``BodyModel``) from a training set drawn from it.

    ``samples`` defaults to 10,000 for vertex models and 1,000 for RRE models (every RRE body is
    decoded; see docs/mapping.md). Deterministic given ``seed``. ``progress(message, fraction)``.
    """
    samples = default_sizes(model)[0] if samples is None else int(samples)
    report = progress or (lambda msg, frac: None)
    train = make_training_set(model, samples, k, rng=seed, names=names,
                              progress=lambda msg, f: report(f"training set: {msg}", 0.8 * f))
    X, Y = train.measurements, train.coefficients[:, :train.k]
    report("linear mapping and forest", 0.8)
    linear = LinearMapping().fit(X, Y)
    forest = forest_for(len(X), seed, n_trees, n_jobs).fit(X, Y)
    report("done", 1.0)
    return MeasurementMapping(tuple(train.names), train.k, forest, linear, train.linearization, samples)
