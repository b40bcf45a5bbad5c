"""SemanticModel: bodies that *measure* what was asked (Hasler §4, Hasler §5.1, and beyond).

A scikit-learn-style estimator: hyper-parameters in ``__init__``, ``fit(db)`` returns self, the
learned state ends in ``_``. It holds one ``FilteredLinearRegressor`` (Hasler Table 1
winner) per label on a shape-only ``BodyModel``'s PCA coefficients ``c`` (K,), whose gradient is
the label's morphing direction, and calls the pure parts of the package:

- ``labels``: which labels, from one rest scan per subject: the user's own values where the
  database's subject table has them (stature_cm, mass_kg, waist_girth_cm, any ``<length>_cm``),
  measured on the rest scans where it has not, the subject columns (sex, age, ...), and every
  other length of the measurement set as a target; where each label's values came from is kept
  (``provenance_``) and stored with the model;
- ``closed_loop``: Hasler Equation 11, then decode, measure and correct until every value is
  within tolerance (``TOLERANCES``: 4 mm stature, 9 mm lengths, 0.5 kg mass); a miss is never
  silent (``on_infeasible``);
- ``masks``: morphs confined to body regions by the masked Poisson solve (Hasler §5.1).

Requests the model cannot reach: the reachable range of a label is its linear regressor over
the coefficients within ``sigma_limit`` standard deviations (``f(0) +- sigma sqrt(sum s_k^2
var_k)``), widened to every training subject's value (``spans_``: a subject's own body is in the
model, so its values are reachable even where a regressor fitted on few subjects predicts a
narrower range); outside it a request is refused (``TargetError`` with the range) or, with
``on_infeasible="clamp"``, clamped with a warning. The exact refinement's box admits every
training subject too (``coefficient_bound``).

Generation starts from a random body whose asked measurements are defined (another draw, then
bodies toward the mean; ``START_DRAWS``, ``START_SHRINK``), or is refused with the measurement's
reason: a NaN never enters the closed loop.

Storage: the fitted state lives inside the BodyModel file, as flat arrays under a prefix
(``to_arrays`` / ``from_arrays``, no pickle), like the measurement mapping. ``load`` still reads
the sidecar ``MODEL.semantics.npz`` earlier versions wrote beside the model.
"""

from __future__ import annotations

import copy
import json
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from bodyspace.data.template import load_template
from bodyspace.errors import BodyspaceError, MeasurementError, ParameterError, SemanticsFileError, TargetError
from bodyspace.measure import evaluate as evaluate_measurements
from bodyspace.measure import measure
from bodyspace.mesh.alignment import rigid_procrustes
from bodyspace.semantics.closed_loop import closed_loop
from bodyspace.semantics.evaluation import cross_validated_rmse, direction_angles
from bodyspace.semantics.labels import (
    MEASURED_LABELS,
    SUBJECT_LABELS,
    first_scan_per_subject,
    label_set,
    measurement_subset,
    measurement_targets,
    read_scans,
)
from bodyspace.semantics.masks import (
    REGIONS,
    SKELETON_LANDMARKS,
    MaskedPoissonBlend,
    region_weights_from_landmarks,
    region_weights_from_template,
)
from bodyspace.semantics.regressors import (
    FilteredLinearRegressor,
    KernelRegressor,
    SimpleLinearRegressor,
)
from bodyspace.units import Target, format_value, kind_of

__all__ = ["SemanticModel", "GenerationResult", "TargetError", "REGIONS", "TOLERANCES", "MEASURED_LABELS",
           "SUBJECT_LABELS", "PREFIX", "semantics_path", "tolerance"]

FORMAT = "bodyspace.SemanticModel"
FORMAT_VERSION = 1  # of the legacy sidecar file and of the arrays inside a model file
# Key prefix of the semantic model's arrays inside a BodyModel file.
PREFIX = "semantics_"
# closed-loop tolerance per label (SI); girths and other lengths 9 mm
TOLERANCES = {"stature": 0.004, "mass": 0.5}
LENGTH_TOLERANCE = 0.009
# a mask's factored Poisson solve is cached; user-supplied weight arrays are keys too
MAX_CACHED_MASKS = 8
# Start bodies of generate: random draws tried until the asked measurements are all defined, then
# the first draw moved toward the mean body by these factors (0: the mean body itself).
START_DRAWS = 8
START_SHRINK = (0.5, 0.25, 0.0)
_REGRESSOR_KINDS = {"FilteredLinearRegressor": FilteredLinearRegressor,
                    "SimpleLinearRegressor": SimpleLinearRegressor, "KernelRegressor": KernelRegressor}


def semantics_path(model_path) -> Path:
    """Where earlier versions kept the SemanticModel of model file ``x.npz``: ``x.semantics.npz``
    beside it (read once by the CLI and folded into the model file)."""
    p = Path(model_path)
    return p.with_name(p.name[:-4] + ".semantics.npz" if p.name.endswith(".npz") else p.name + ".semantics.npz")


def tolerance(name: str) -> float:
    """Closed-loop tolerance of a label, SI units."""
    if name in TOLERANCES:
        return TOLERANCES[name]
    if kind_of(name) == "length":
        return LENGTH_TOLERANCE
    return 1e-3


# ----------------------------------------------------------------------------------- results
@dataclass
class GenerationResult:
    """One generated or morphed body.

    coefficients: (K,) PCA coefficients. vertices: (V, 3) metres. values: label -> value reached
    (measured labels measured on ``vertices``, the others from their regressor). measurements: what
    the loop measured on the final body (the asked names, their dependencies, and, when anything
    was measured, every core measured label). targets: label ->
    value asked (after ranges were resolved and clamping). converged: every label within its
    tolerance. iterations: closed-loop corrections taken. mahalanobis: ``sqrt(sum c_k^2/var_k)``
    of the step from the start. timings: seconds in decode, measure, solve (and refine, when the
    exact refinement ran). messages: warnings. start: (K,) the coefficients the loop started from.
    """

    coefficients: np.ndarray
    vertices: np.ndarray
    values: dict
    targets: dict
    converged: bool
    iterations: int
    mahalanobis: float
    timings: dict = field(default_factory=dict)
    messages: list = field(default_factory=list)
    measurements: dict = field(default_factory=dict)
    start: np.ndarray | None = None

    def residuals(self) -> dict:
        return {k: self.values[k] - v for k, v in self.targets.items()}


# ----------------------------------------------------------------------------------- the model
class SemanticModel:
    """Semantic regressors on a BodyModel's coefficients, closed-loop generation, morphing, masks.

    Args:
        body_model: a fitted ``BodyModel`` (shape-only: rest scans).
        sigma_limit: reachable region, in standard deviations (Mahalanobis radius).
        max_iter: most corrections (decode + measure) of the closed loop, the Hasler Equation 11 step
            included; finite-difference Jacobians (C + 4 bodies) come on top.
        on_infeasible: "raise" (refuse with the reachable range / the residuals) or "clamp"
            (clamp to the range and warn; a miss after ``max_iter`` warns).

    Attributes (after ``fit``/``from_arrays``): labels_ (names), measured_ (names measured on
    bodies), lengths_ (measurement targets), X_ (N, K) coefficients of one rest scan per subject,
    Y_ (N, L) labels (NaN unknown), regressors_ name -> fitted regressor, regions_ name -> (V,)
    weights, subjects_ (N,) ids.
    """

    def __init__(self, body_model, sigma_limit: float = 3.0, max_iter: int = 20, on_infeasible: str = "raise"):
        self.body_model = body_model
        self.sigma_limit = float(sigma_limit)
        self.max_iter = int(max_iter)
        self.on_infeasible = on_infeasible
        self._check_params()
        self._sub_msets = {}
        self._landmark_regions = None
        self._blends = {}
        self._projector = None
        self.lengths_ = []

    def _check_params(self) -> None:
        if self.on_infeasible not in ("raise", "clamp"):
            raise ParameterError(f"on_infeasible={self.on_infeasible!r}, expected 'raise' or 'clamp'")

    def set_params(self, **params) -> "SemanticModel":
        """Change hyper-parameters (sigma_limit, max_iter, on_infeasible) of a fitted model."""
        valid = ("sigma_limit", "max_iter", "on_infeasible")
        for key, value in params.items():
            if key not in valid:
                raise ParameterError(f"SemanticModel.set_params: unknown parameter {key!r}, expected one of {valid}")
            setattr(self, key, value if key == "on_infeasible" else type(getattr(self, key))(value))
        self._check_params()
        return self

    # ------------------------------------------------------------------ fitting
    @property
    def mset(self):
        """The body model's measurement set (``BodyModel.measurement_set``: its topology's)."""
        return self.body_model.measurement_set

    def _is_measured(self, name: str) -> bool:
        return name in self.measured_ or name in self.lengths_

    def measure_body(self, vertices, names=None) -> dict:
        """Measurements of bodies: the whole set, or just ``names`` and what they depend on
        (``labels.measurement_subset``, cached per set of names)."""
        mset = self.mset
        if names is not None:
            key = frozenset(names)
            if key not in self._sub_msets:
                self._sub_msets[key] = measurement_subset(mset, key)
            mset = self._sub_msets[key]
        return measure(mset, vertices, self.body_model.faces)

    def project_mesh(self, vertices) -> np.ndarray:
        """Coefficients (N, K) of registered meshes (V, 3) or (N, V, 3), with the encoder's
        check for flipped triangles off. The model's own bodies fold where its training scans
        fold (the LBS-posed population folds a few triangles, a model fitted on it decodes
        them), so a mesh ``generate`` wrote would be reported, or refused under
        ``on_flipped="raise"``; the projection is exact for folded triangles all the same, and
        a morph adds a change to the mesh, keeping whatever folds it had."""
        if self._projector is None:
            encoder = copy.copy(self.body_model.encoder)
            if hasattr(encoder, "on_flipped"):  # a flip policy, where the encoder has one
                encoder.on_flipped = "ignore"
            self._projector = encoder
        codes = self._projector.encode(vertices)
        return np.asarray(self.body_model.space.transform(codes), dtype=float)

    def fit(self, db, measured=MEASURED_LABELS, subject_labels=None, rng=0, template=None) -> "SemanticModel":
        """Labels and regressors from ``db`` (the database the body model was fitted on): one
        rest scan per subject (the first of the model's fitted scans for that subject).

        A measured label's value of a subject is the database's own (its subject column
        ``stature_cm``, ``mass_kg``, ``<length>_cm``), else what the measurement set reads on the
        rest scan (``labels.label_set``); a label known on fewer than ``MIN_LABELLED`` subjects
        is left out with the reason (``skipped_``)."""
        bm = self.body_model
        rows, self.subjects_ = first_scan_per_subject(db.scans["subject"], bm.fitted_scans)
        verts = read_scans(db, rows)
        self.X_ = self.project_mesh(verts).reshape(len(rows), -1)
        found = evaluate_measurements(self.mset, verts, bm.faces, mesh_name="the rest scans")
        values = {name: np.atleast_1d(m.value) for name, m in found.items()}
        notes = {name: (m.note if isinstance(m.note, list) else [m.note]) for name, m in found.items()}
        source = Path(str((db.meta.get("provenance") or {}).get("labels") or "subjects.csv")).name
        given = label_set(self.mset, db.subjects, self.subjects_, values, notes, measured, subject_labels, source)
        if not given.values:
            raise ParameterError("database: no label can be learned: " + "; ".join(
                f"{name}: {why}" for name, why in given.skipped.items()))
        labels = given.values
        self.labels_ = list(labels)
        self.measured_ = list(given.measured)
        self.provenance_, self.skipped_, self.unused_columns_ = given.provenance, given.skipped, given.unused
        self.Y_ = np.column_stack([labels[n] for n in self.labels_])
        # every other length of the measurement set is a target too: a regressor each (cheap),
        # measured on a body only when asked
        targets = measurement_targets(self.mset, values, exclude=set(labels) | set(given.skipped))
        self.lengths_ = list(targets)
        self.regressors_, self.spans_ = {}, {}
        for name, y in {**labels, **targets}.items():
            ok = np.isfinite(y)
            self.regressors_[name] = self._fit_one(self.X_[ok], y[ok], rng)
            # every training subject's value, and for a measured label what its rest scan measures
            seen = np.concatenate([y[ok], values[name][np.isfinite(values[name])] if name in values else []])
            self.spans_[name] = (float(seen.min()), float(seen.max()))
        if template is None:
            try:
                template = load_template()
            except BodyspaceError:
                template = None
        self.regions_ = {}
        if template is not None and template.n_vertices == len(bm.template_vertices) and \
                np.array_equal(np.asarray(template.faces), bm.faces):
            self.regions_ = region_weights_from_template(template)
        return self

    @staticmethod
    def _fit_one(x, y, rng):
        reg = FilteredLinearRegressor(rng=rng).fit(x, y)
        if not np.any(reg.coef_):  # nothing kept: fall back to the plain least squares (Hasler Equation 10)
            reg = SimpleLinearRegressor().fit(x, y)
        return reg

    # ------------------------------------------------------------------ ranges
    @property
    def variances(self) -> np.ndarray:
        return np.asarray(self.body_model.space.explained_variance_, dtype=float)

    def reachable_range(self, name: str) -> tuple[float, float]:
        """(lo, hi) of label ``name``: its linear regressor over coefficients within
        ``sigma_limit`` SD, widened to the values of the training subjects (``spans_``)."""
        reg = self.regressor(name)
        center = float(reg.predict(np.zeros(self.X_.shape[1])))
        half = self.sigma_limit * float(np.sqrt(np.sum(reg.coef_ ** 2 * self.variances)))
        lo, hi = center - half, center + half
        span = getattr(self, "spans_", {}).get(name)
        if span is not None:
            lo, hi = min(lo, span[0]), max(hi, span[1])
        return lo, hi

    @property
    def coefficient_bound(self) -> float:
        """The largest coefficient, in SD, a request may need (the exact refinement's box):
        ``sigma_limit``, or more when a training subject lies further out on a component, so
        that every training subject's body, and its values, can be reached."""
        z = np.abs(np.asarray(self.X_, dtype=float)) / np.sqrt(np.maximum(self.variances, 1e-300))
        return max(self.sigma_limit, float(z.max()) if z.size else 0.0)

    def regressor(self, name):
        """The fitted regressor of label or measurement ``name`` (ParameterError naming the accepted
        names, or why the label was not learned)."""
        if name not in getattr(self, "regressors_", {}):
            skipped = getattr(self, "skipped_", {})
            if name in skipped:
                raise ParameterError(f"{name}: not learned from the database: {skipped[name]}")
            labels = list(getattr(self, "labels_", []))
            lengths = list(getattr(self, "lengths_", []))
            meas = ", ".join(lengths) or "(none: these regressors predate measurement targets; refit them)"
            raise ParameterError(f"unknown semantic variable {name!r}; accepted names: labels "
                                 f"{', '.join(labels) or '(none)'}; measurements {meas}")
        return self.regressors_[name]

    def _check_reachable(self, name: str, value: float, messages: list) -> float:
        lo, hi = self.reachable_range(name)
        if lo <= value <= hi:
            return value
        rng_txt = f"{format_value(name, lo)} to {format_value(name, hi)}"
        if self.on_infeasible == "raise":
            raise TargetError(f"{name}: {format_value(name, value)} is outside what the model can reach "
                              f"({rng_txt}: within {self.sigma_limit:g} SD, and every training subject's value); "
                              "ask within that range, or have it clamped to the range (--clamp on the command line, "
                              "on_infeasible='clamp' in Python)")
        clamped = min(max(value, lo), hi)
        msg = (f"{name}: {format_value(name, value)} is outside the reachable range {rng_txt}; "
               f"clamped to {format_value(name, clamped)}")
        warnings.warn(msg, RuntimeWarning, stacklevel=3)
        messages.append(msg)
        return clamped

    # ------------------------------------------------------------------ values of a body
    def _values(self, names, x, c, timings) -> tuple[np.ndarray, dict]:
        meas = {}
        measured = [n for n in names if self._is_measured(n)]
        if measured:
            t = time.perf_counter()
            meas = self.measure_body(x, measured)
            timings["measure"] += time.perf_counter() - t
        return np.array([float(meas[n]) if self._is_measured(n) else float(self.regressors_[n].predict(c))
                         for n in names]), meas

    def _decode(self, c, timings) -> np.ndarray:
        t = time.perf_counter()
        x = np.asarray(self.body_model.reconstruct(c))[0]
        timings["decode"] += time.perf_counter() - t
        return x

    # ------------------------------------------------------------------ the closed loop
    def _solve(self, c0, goal: dict, body, timings, messages, current=None, defer_misses=False) -> GenerationResult:
        """``closed_loop`` from ``c0`` to ``goal`` (name -> SI value), with this model's
        regressors, tolerances and ``on_infeasible`` policy for a miss (``defer_misses``: neither
        raised nor warned, ``converged`` False: the caller refines further and judges)."""
        names = list(goal)
        g = np.array([goal[n] for n in names], dtype=float)
        grads = np.array([self.regressor(n).gradient(c0) for n in names], dtype=float)
        loop = closed_loop(c0, g, [tolerance(n) for n in names], self.variances, grads, body,
                           lambda x, c: self._values(names, x, c, timings), current=current,
                           max_iter=self.max_iter)
        timings["solve"] += loop.solve_s
        vals, meas = loop.values, loop.measurements
        if not loop.converged:
            miss = ", ".join(f"{n} {format_value(n, v)} (asked {format_value(n, gv)})"
                             for n, v, gv, m in zip(names, vals, g, loop.missed) if m)
            msg = (f"not met after {loop.iterations} corrections: {miss}; the request is probably not jointly "
                   "reachable (ask for less, or fewer constraints)")
            if defer_misses:
                pass
            elif self.on_infeasible == "raise":
                raise TargetError(msg)
            else:
                warnings.warn(msg, RuntimeWarning, stacklevel=3)
                messages.append(msg)
        missing = [n for n in self.measured_ if n not in meas]
        if meas and missing:  # the result reports every measured label: the rest once, on the final body
            t = time.perf_counter()
            meas = {**meas, **self.measure_body(loop.vertices, missing)}
            timings["measure"] += time.perf_counter() - t
        metric = 1.0 / np.maximum(self.variances, 1e-300)
        maha = float(np.sqrt(np.sum((loop.coefficients - np.asarray(c0, dtype=float)) ** 2 * metric)))
        return GenerationResult(loop.coefficients, loop.vertices, dict(zip(names, vals.tolist())),
                                dict(zip(names, g.tolist())), loop.converged, loop.iterations, maha,
                                dict(timings), messages, {k: float(v) for k, v in meas.items()},
                                np.asarray(c0, dtype=float))

    # ------------------------------------------------------------------ generate
    def generate(self, targets: dict, rng=None, sigma_range: float = 2.0, defer_misses: bool = False) -> GenerationResult:
        """A random body that measures ``targets``: name -> value (SI), ``(lo, hi)`` or ``Target``.

        The other degrees of freedom are drawn at random (Gaussian coefficients truncated to
        ``sigma_range`` SD); a range is met by moving the random body's value to the nearest
        point of the range (kept where it already is when inside). Lengths of the measurement
        set are met to the closed loop's 9 mm here; ``BodyModel.generate`` meets them to 1 mm
        (exact refinement, with ``defer_misses``: a miss of the loop is judged after it).
        """
        timings = {"decode": 0.0, "measure": 0.0, "solve": 0.0}
        messages: list = []
        gen = np.random.default_rng(rng)
        reqs = self._requests(targets)
        names = list(reqs)
        c0, vals0, meas0 = self._defined_start(names, gen, sigma_range, timings)
        goal = {}
        for name, v0 in zip(names, vals0):
            goal[name] = self._resolve(reqs[name], v0, messages)
        return self._solve(c0, goal, lambda c: self._decode(c, timings), timings, messages,
                           current=(vals0, meas0), defer_misses=defer_misses)

    def _defined_start(self, names, gen, sigma_range: float, timings) -> tuple:
        """A start body for ``generate`` whose values of ``names`` are all defined: a random draw
        (truncated to ``sigma_range`` SD); if one is undefined (a measurement's condition fails,
        e.g. a body that is not upright has no stature), up to ``START_DRAWS`` draws, then the
        first draw moved toward the mean (``START_SHRINK``). Returns (c (K,), values (C,),
        measurements); MeasurementError with the measurement's reason when none is defined."""
        first = np.asarray(self.body_model.sample_coefficients(1, sigma_range=sigma_range, rng=gen), dtype=float)[0]

        def candidates():
            yield first
            for _ in range(START_DRAWS - 1):
                yield np.asarray(self.body_model.sample_coefficients(1, sigma_range=sigma_range, rng=gen),
                                 dtype=float)[0]
            for factor in START_SHRINK:
                yield first * factor
        for c in candidates():
            x = self._decode(c, timings)
            values, meas = self._values(names, x, c, timings)
            if np.isfinite(values).all():
                return c, values, meas
        undefined = [n for n, v in zip(names, values) if not np.isfinite(v)]
        raise MeasurementError(f"generate: {', '.join(undefined)} not defined on this model's bodies: "
                               f"{START_DRAWS} random bodies and the mean body measure no value "
                               f"({self._why_undefined(x, undefined)}); the measurement set's definition does not "
                               "hold on the bodies the model makes (its landmarks, or the scans it was built from)")

    def _why_undefined(self, vertices, names) -> str:
        """The measurement's own note on why ``names`` have no value on ``vertices`` (V, 3)."""
        found = evaluate_measurements(measurement_subset(self.mset, names), vertices, self.body_model.faces)
        return "; ".join(f"{n}: {found[n].note or 'no value'}" for n in names if n in found) or "no value"

    def _requests(self, targets) -> dict:
        if not isinstance(targets, dict):
            raise ParameterError(f"targets: got {type(targets).__name__}, expected a dict name -> value or (lo, hi)")
        out = {}
        for name, t in targets.items():
            if isinstance(t, Target):
                req = t
            elif isinstance(t, (tuple, list)) and len(t) == 2:
                req = Target(name, "range", lo=float(t[0]), hi=float(t[1]))
            else:
                req = Target(name, "value", value=float(t))
            self.regressor(req.name)
            out[req.name] = req
        return out

    def _resolve(self, req: Target, current: float, messages) -> float:
        name = req.name
        if req.kind == "value":
            return self._check_reachable(name, req.value, messages)
        if req.kind == "delta":
            return self._check_reachable(name, current + req.value, messages)
        lo, hi = self.reachable_range(name)
        a, b = max(req.lo, lo), min(req.hi, hi)
        if a > b:
            if self.on_infeasible == "raise":
                raise TargetError(f"{name}: range {format_value(name, req.lo)} to {format_value(name, req.hi)} lies "
                                  f"outside what the model can reach ({format_value(name, lo)} to "
                                  f"{format_value(name, hi)}, within {self.sigma_limit:g} SD)")
            return self._check_reachable(name, req.lo if req.lo > hi else req.hi, messages)
        margin = min(tolerance(name), (b - a) / 2)
        return float(np.clip(current, a + margin, b - margin))

    # ------------------------------------------------------------------ morph
    def mask_weights(self, mask) -> np.ndarray:
        """(V,) weights of a region name, a list of names (their union), or an array."""
        if mask is None:
            return None
        if isinstance(mask, str):
            mask = [mask]
        if isinstance(mask, (list, tuple)) and all(isinstance(m, str) for m in mask):
            regions = self.regions()
            bad = [m for m in mask if m not in regions]
            if bad:
                raise ParameterError(f"mask: unknown region(s) {bad}; expected one of "
                                     f"{', '.join(regions) or self._no_regions()}")
            return np.max([regions[m] for m in mask], axis=0)
        return np.asarray(mask, dtype=float)

    def regions(self) -> dict:
        """Region name -> (V,) weights: the template's (``regions_``, from its rig), or on another
        topology those of the skeleton the model's landmarks define
        (``masks.region_weights_from_landmarks`` on the mean body; derived once, not stored)."""
        if getattr(self, "regions_", None):
            return self.regions_
        if self._landmark_regions is None:
            bm = self.body_model
            self._landmark_regions = (region_weights_from_landmarks(bm.mean_vertices, bm.measurement_set)
                                      if bm.has_measurement_set else {})
        return self._landmark_regions

    def _no_regions(self) -> str:
        bm = self.body_model
        if not bm.has_measurement_set:
            return "(none: this model carries no measurement set, whose landmarks define the regions; pass per-vertex weights)"
        missing = [n for n in SKELETON_LANDMARKS if n not in bm.measurement_set.landmarks]
        return (f"(none: the model's landmarks lack {', '.join(missing)}, which the regions are made from; give "
                "them in the landmark file, or pass per-vertex weights)")

    def masked_blend(self, weights) -> MaskedPoissonBlend:
        """The ``MaskedPoissonBlend`` of a mask, built on the model's mean body and cached: its
        matrix depends on the mask and the rest geometry only, so a morph pays triangular
        solves, not a factorization. Using the mean body's gradients instead of the morphed
        body's changes only the metric the change is blended in; outside the mask nothing moves
        either way."""
        key = np.asarray(weights, dtype=float).tobytes()
        if key not in self._blends:
            if len(self._blends) >= MAX_CACHED_MASKS:
                self._blends.pop(next(iter(self._blends)))
            mean = np.asarray(self.body_model.encoder.mean_vertices_, dtype=float)
            self._blends[key] = MaskedPoissonBlend(mean, self.body_model.faces, weights)
        return self._blends[key]

    def morph(self, vertices, changes: dict, keep=(), mask=None, defer_misses: bool = False) -> GenerationResult:
        """Morph a registered mesh (V, 3): ``changes`` name -> ``Target`` (value/delta/range) or a
        float *change* (SI), ``keep`` names held at their measured value, ``mask`` a region
        name(s) or (V,) weights: the change is confined to it (``MaskedPoissonBlend``), and the loop
        corrects for what the mask took away. ``defer_misses`` as in ``generate``
        (``BodyModel.morph`` refines asked lengths to 1 mm)."""
        timings = {"decode": 0.0, "measure": 0.0, "solve": 0.0}
        messages: list = []
        x0 = np.asarray(vertices, dtype=float)
        reqs = {}
        for name, t in dict(changes).items():
            reqs[name] = t if isinstance(t, Target) else Target(name, "delta", value=float(t))
        reqs = self._requests(reqs)
        for name in keep:
            if name in reqs:
                raise ParameterError(f"keep: {name!r} is also asked to change, expected each label in one of them")
            self.regressor(name)
            reqs[name] = Target(name, "delta", value=0.0)
        if not reqs:
            raise ParameterError("morph: nothing to change, expected at least one --set")
        t = time.perf_counter()
        c0 = self.project_mesh(x0).reshape(-1)
        d0 = np.asarray(self.body_model.reconstruct(c0))[0]
        timings["decode"] += time.perf_counter() - t
        # The model decodes in its own frame (the encoder's Procrustes frame), the mesh stands in
        # its own: a registration keeps the scan's turn about the vertical (24° on a T-posed scan),
        # and the change added unturned put a "heavier" belly and longer legs 24° off the body.
        # The change is turned by the rigid motion of the model's reconstruction onto the mesh.
        _, turn, _ = rigid_procrustes(d0, x0)
        w = self.mask_weights(mask)
        blend = self.masked_blend(w) if w is not None else None

        def body(c):
            d = self._decode(c, timings) - d0
            if blend is not None:
                t = time.perf_counter()
                d = blend(d)
                timings["solve"] += time.perf_counter() - t
            return x0 + d @ turn.T

        names = list(reqs)
        vals0, meas0 = self._values(names, x0, c0, timings)
        undefined = [n for n, v in zip(names, vals0) if not np.isfinite(v)]
        if undefined:
            raise MeasurementError(f"the body to morph: {', '.join(undefined)} not defined "
                                   f"({self._why_undefined(x0, undefined)}); changing or keeping a measurement needs "
                                   "its value on the body")
        goal = {n: (v0 if n in keep else self._resolve(reqs[n], v0, messages)) for n, v0 in zip(names, vals0)}
        return self._solve(c0, goal, body, timings, messages, current=(vals0, meas0), defer_misses=defer_misses)

    # ------------------------------------------------------------------ crowd
    def crowd(self, n: int, targets: dict, rng=None, progress=None) -> list[GenerationResult]:
        """``n`` bodies meeting ``targets`` (values or ranges), the rest random."""
        gen = np.random.default_rng(rng)
        out = []
        for i in range(int(n)):
            out.append(self.generate(targets, rng=gen))
            if progress:
                progress(f"body {i + 1}/{n}", (i + 1) / n)
        return out

    # ------------------------------------------------------------------ Hasler Table 1 / Hasler Table 2
    def evaluate(self, folds: int = 10, rng=0) -> tuple:
        """(Hasler Table 1 ``RegressionTable``, Hasler Table 2 dict label -> (mean, sd) degrees) on the model's
        subjects (one row per subject)."""
        labels = {n: self.Y_[:, j] for j, n in enumerate(self.labels_)}
        table1 = cross_validated_rmse(self.X_, labels, folds=folds, rng=rng)
        table2 = {}
        for n, y in labels.items():
            ok = np.isfinite(y)
            reg = KernelRegressor().fit(self.X_[ok], y[ok])
            table2[n] = direction_angles(reg, self.X_[ok])
        return table1, table2

    # ------------------------------------------------------------------ storage
    def to_arrays(self, prefix: str = PREFIX) -> dict[str, np.ndarray]:
        """The fitted state as flat arrays under ``prefix`` (no object dtype, no pickle), for the
        BodyModel file: ``meta`` (uint8 JSON: names, regressor kinds, sigma_limit, ...), ``X``
        (N, K), ``Y`` (N, L) with ``Y_known`` (N, L) bool (unknown labels stored as 0: a model
        file holds finite numbers only), ``subjects`` (N,), ``reg<j>_<key>`` the j-th
        regressor's arrays, ``region_<name>`` (V,) float64."""
        if not hasattr(self, "regressors_"):
            raise ParameterError("SemanticModel is not fitted; call fit(db) first")
        names = list(self.regressors_)
        meta = {"format": FORMAT, "format_version": FORMAT_VERSION, "labels": list(self.labels_),
                "measured": list(self.measured_), "lengths": list(self.lengths_),
                "regressors": [[n, type(self.regressors_[n]).__name__] for n in names],
                "regions": list(self.regions_), "sigma_limit": self.sigma_limit,
                "n_components": int(self.X_.shape[1]), "template_id": self.body_model.template_id,
                "units": {n: kind_of(n) for n in list(self.labels_) + list(self.lengths_)},
                "provenance": getattr(self, "provenance_", {}), "skipped": getattr(self, "skipped_", {}),
                "unused_columns": getattr(self, "unused_columns_", []),
                "spans": {n: list(v) for n, v in getattr(self, "spans_", {}).items()}}
        y = np.asarray(self.Y_, dtype=float)
        out = {prefix + "meta": np.frombuffer(json.dumps(meta).encode("utf-8"), dtype=np.uint8),
               prefix + "X": np.asarray(self.X_, dtype=np.float64),
               prefix + "Y": np.where(np.isfinite(y), y, 0.0), prefix + "Y_known": np.isfinite(y),
               prefix + "subjects": np.array(self.subjects_, dtype="U")}
        for j, name in enumerate(names):
            for key, a in self.regressors_[name].to_arrays().items():
                out[f"{prefix}reg{j}_{key}"] = a
        for name, w in self.regions_.items():
            out[f"{prefix}region_{name}"] = np.asarray(w, dtype=np.float64)
        return out

    @classmethod
    def from_arrays(cls, arrays, body_model, prefix: str = PREFIX, **params) -> "SemanticModel":
        """Inverse of ``to_arrays`` for ``body_model`` (the model whose file holds them);
        ``params`` override the stored hyper-parameters. Raises ``SemanticsFileError`` naming the
        array that is missing or does not fit."""
        def get(key):
            if prefix + key not in arrays:
                raise SemanticsFileError(f"semantic regressors: array '{prefix + key}' is missing; expected the "
                                         "arrays written by SemanticModel.to_arrays")
            return np.asarray(arrays[prefix + key])

        raw = get("meta")
        try:
            meta = json.loads(raw.astype(np.uint8).tobytes().decode("utf-8"))
            assert isinstance(meta, dict)
        except (ValueError, TypeError, AssertionError) as exc:
            raise SemanticsFileError(f"semantic regressors: array '{prefix}meta' is not UTF-8 JSON ({exc})") from None
        regs = {}
        for j, entry in enumerate(meta.get("regressors") or []):
            if not (isinstance(entry, list) and len(entry) == 2):
                raise SemanticsFileError(f"semantic regressors: entry {j} of '{prefix}meta' regressors is {entry!r}, "
                                         "expected [name, kind]")
            key = f"{prefix}reg{j}_"
            regs[str(entry[0])] = (entry[1], {k[len(key):]: arrays[k] for k in arrays if k.startswith(key)})
        y, known = get("Y").astype(float), get("Y_known")
        if known.shape != y.shape or known.dtype != bool:
            raise SemanticsFileError(f"semantic regressors: '{prefix}Y_known' has shape {known.shape} and dtype "
                                     f"{known.dtype}, expected {y.shape} bool")
        regions = {name: get(f"region_{name}") for name in meta.get("regions") or []}
        return cls._from_state(body_model, meta, get("X"), np.where(known, y, np.nan), get("subjects"), regs,
                               regions, params, "semantic regressors")

    @classmethod
    def load(cls, path, body_model, **params) -> "SemanticModel":
        """Read a sidecar ``MODEL.semantics.npz`` that earlier versions wrote beside the model
        (``allow_pickle=False``). New fits live inside the model file (``to_arrays``); the CLI
        folds a sidecar in on first use. Raises ``SemanticsFileError`` for a missing, damaged
        or mismatched file, saying how to refit."""
        path = Path(path)
        refit = ("refit the regressors from the scan database the model was built from (CLI: --database DB; "
                 "API: SemanticModel(model).fit(db))")
        if not path.is_file():
            raise SemanticsFileError(f"{path}: no semantic model; {refit}")
        with open(path, "rb") as fh:
            magic = fh.read(4)
        if magic != b"PK\x03\x04":  # numpy would call any other file pickled data
            raise SemanticsFileError(f"{path}: damaged, not an .npz archive (starts with {magic!r}); {refit}")
        try:
            with np.load(path, allow_pickle=False) as z:
                header = json.loads(z["header"].tobytes().decode("utf-8"))
                if not isinstance(header, dict) or header.get("format") != FORMAT:
                    found = header.get("format") if isinstance(header, dict) else type(header).__name__
                    raise SemanticsFileError(f"{path}: format {found!r}, expected {FORMAT!r}; {refit}")
                regs = {}
                for name, kind in dict(header["regressors"]).items():
                    key = f"reg/{name}/"
                    regs[name] = (kind, {k[len(key):]: z[k] for k in z.files if k.startswith(key)})
                state = (z["X"], z["Y"], z["subjects"], regs,
                         {name: z[f"region/{name}"] for name in header["regions"]})
        except SemanticsFileError:
            raise
        except Exception as exc:  # noqa: BLE001 - any damage (zip, npy, JSON, missing key) is reported one way
            raise SemanticsFileError(f"{path}: damaged, not a semantics file ({type(exc).__name__}: {exc}); "
                                     f"{refit}") from None
        if header.get("format_version") != FORMAT_VERSION:
            raise SemanticsFileError(f"{path}: format_version {header.get('format_version')!r}, expected "
                                     f"{FORMAT_VERSION}; {refit}")
        return cls._from_state(body_model, header, *state, params, str(path), refit=refit)

    @classmethod
    def _from_state(cls, body_model, meta, X, Y, subjects, regressors, regions, params, where: str,
                    refit: str = "refit them (CLI: --database DB --refit)") -> "SemanticModel":
        """A fitted model from its stored parts, every part checked against ``body_model``.

        meta: dict (labels, measured, lengths, sigma_limit, n_components). X (N, K), Y (N, L),
        subjects (N,); regressors: name -> (kind, arrays); regions: name -> (V,). ``where``
        names the source in messages."""
        k = body_model.n_components
        if meta.get("n_components") != k:
            raise SemanticsFileError(f"{where}: fitted on {meta.get('n_components')!r} components, the model has "
                                     f"{k}; {refit}")
        try:
            labels, measured = [str(n) for n in meta["labels"]], [str(n) for n in meta["measured"]]
            lengths = [str(n) for n in meta.get("lengths", [])]
            params = {"sigma_limit": float(meta.get("sigma_limit", 3.0)), **params}
        except (KeyError, TypeError, ValueError) as exc:
            raise SemanticsFileError(f"{where}: header field {exc} is missing or malformed; {refit}") from None
        X, Y, subjects = np.asarray(X), np.asarray(Y), np.asarray(subjects)
        n = len(X)
        for name, a, shape in (("X", X, (n, k)), ("Y", Y, (n, len(labels))), ("subjects", subjects, (n,))):
            if a.shape != shape or (name != "subjects" and a.dtype.kind != "f"):
                raise SemanticsFileError(f"{where}: '{name}' has shape {a.shape} and dtype {a.dtype}, expected "
                                         f"{shape}{'' if name == 'subjects' else ' float'}; {refit}")
        self = cls(body_model, **params)
        self.X_, self.Y_, self.subjects_ = X.astype(float), Y.astype(float), subjects.astype(str)
        self.labels_, self.measured_, self.lengths_ = labels, measured, lengths
        self.regressors_ = {}
        for name, (kind, arrays) in regressors.items():
            if kind not in _REGRESSOR_KINDS:
                raise SemanticsFileError(f"{where}: regressor {name!r} of kind {kind!r}, expected one of "
                                         f"{', '.join(_REGRESSOR_KINDS)}; {refit}")
            try:
                reg = _REGRESSOR_KINDS[kind].from_arrays(arrays)
            except ParameterError as exc:
                raise SemanticsFileError(f"{where}: regressor {name!r}: {exc}; {refit}") from None
            if reg.n_features_in_ != k:
                raise SemanticsFileError(f"{where}: regressor {name!r} takes {reg.n_features_in_} coefficients, "
                                         f"expected {k}; {refit}")
            self.regressors_[name] = reg
        try:  # where the labels came from (absent in files of earlier versions: unknown, not an error)
            self.provenance_ = {str(k): dict(v) for k, v in dict(meta.get("provenance") or {}).items()}
            self.skipped_ = {str(k): str(v) for k, v in dict(meta.get("skipped") or {}).items()}
            self.unused_columns_ = [str(c) for c in meta.get("unused_columns") or []]
            self.spans_ = {str(k): (float(v[0]), float(v[1])) for k, v in dict(meta.get("spans") or {}).items()}
        except (TypeError, ValueError, IndexError) as exc:
            raise SemanticsFileError(f"{where}: header field provenance/skipped/spans is malformed ({exc}); "
                                     f"{refit}") from None
        if not self.spans_:  # earlier files: the training subjects' labels at least
            self.spans_ = {n: (float(np.nanmin(y)), float(np.nanmax(y))) for n, y in zip(labels, self.Y_.T)
                           if np.isfinite(y).any()}
        absent = [n for n in labels + lengths if n not in self.regressors_]
        if absent:
            raise SemanticsFileError(f"{where}: no regressor for {absent}; {refit}")
        nv = len(body_model.template_vertices)
        self.regions_ = {}
        for name, w in regions.items():
            w = np.asarray(w, dtype=float)
            if w.shape != (nv,):
                raise SemanticsFileError(f"{where}: region {name!r} has shape {w.shape}, expected ({nv},); {refit}")
            self.regions_[name] = w
        return self
