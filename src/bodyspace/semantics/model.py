"""SemanticModel: bodies that *measure* what was asked (Hasler et al. 2009 §4, §5.1, and beyond).

Fitted from a shape-only ``BodyModel`` and the scan database it came from: one row per subject
(its rest scan), PCA coefficients ``c`` (K,) as the body, and two kinds of labels:

- *measured* labels (stature, mass, waist/chest/hip girth): ``bodyspace.measure`` on the rest
  scans, i.e. the quantity a tape measure (and a scale, at the default density) reads on the
  mesh; during generation they are measured again on every decoded body;
- *subject* labels (sex 1 = male / 0 = female, age, body fat %, muscle): the database's columns,
  only known through their regressors.
- *measurement targets* (``lengths_``): every other length of the measurement set (Rupprecht's
  waist_size, ..., ISO thigh_girth_l, shoulder_width, ...): a regressor each, measured on the
  decoded body only when asked (the loop measures just the requested names and their dependencies).

Every label gets a ``FilteredLinearRegressor`` on the coefficients (the paper's Table 1 winner),
whose gradient is its morphing direction.

Generation and morphing (``_solve``):

1. Equation (11) gives the first step: the minimum-norm ``z`` with ``<s_i, z> = delta_i`` for all
   constraints, in the metric ``sum_k z_k^2 / var_k`` (the PCA variances), i.e. the most
   probable change, the one that moves the body least in units of the population's spread.
2. Closed loop: decode, measure, and correct the measured residuals with a Gauss-Newton step,
   the minimum-norm (same metric) solution within the span of the minimum-norm directions
   ``var * s_i`` plus the leading PCA components. Its Jacobian is measured there by finite
   differences and refreshed by Broyden's rank-one update (remeasured when progress stalls);
   steps are limited to 1 SD and backtracked when they do not reduce the residual. It stops when
   every label is within tolerance (``TOLERANCES``: 4 mm stature, 9 mm girths, 0.5 kg mass) or
   after ``max_iter`` corrections; a miss is never silent (``on_infeasible``).

Requests the model cannot reach: the reachable range of a label is its linear regressor over
the coefficients within ``sigma_limit`` standard deviations (``f(0) +- sigma sqrt(sum s_k^2
var_k)``); outside it a request is refused (``TargetError`` with the range) or, with
``on_infeasible="clamp"``, clamped with a warning.

Masks (§5.1): named regions (``REGIONS``) as per-vertex weights from the template's skinning
weights (smooth across joints) and left/right vertex groups. The change of a masked morph is
blended in the gradient domain: per-triangle weights ``w_f`` scale the change of every
triangle's deformation gradient, and a Poisson solve with the unmasked vertices held fixed
rebuilds the surface, spreading the seam with no step (``MaskedBlend``).
"""

from __future__ import annotations

import dataclasses
import json
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import scipy.sparse as sp

from bodyspace.atomic import atomic_path
from bodyspace.errors import BodyspaceError, ParameterError
from bodyspace.semantics.morph import morph_directions
from bodyspace.semantics.regressors import (
    FilteredLinearRegressor,
    SimpleLinearRegressor,
)
from bodyspace.units import Target, format_value, kind_of

__all__ = ["SemanticModel", "GenerationResult", "TargetError", "MaskedBlend", "REGIONS", "TOLERANCES",
           "MEASURED_LABELS", "SUBJECT_LABELS", "semantics_path", "region_weights_from_template"]

FORMAT = "bodyspace.SemanticModel"
FORMAT_VERSION = 1
MEASURED_LABELS = ("stature", "mass", "waist_girth", "chest_girth", "hip_girth")
# label -> database subject column
SUBJECT_LABELS = {"sex": "sex", "age": "age_years", "body_fat": "body_fat_percent", "muscle": "muscle_1"}
# closed-loop tolerance per label (SI); girths and other lengths 9 mm
TOLERANCES = {"stature": 0.004, "mass": 0.5}
LENGTH_TOLERANCE = 0.009
# closed loop: finite-difference step and largest step, in standard deviations (Mahalanobis)
FD_STEP = 0.25
MAX_STEP = 1.0
# the closed loop also searches along this many leading PCA components (conditioning)
EXTRA_DIRECTIONS = 4
REGIONS = ("upper_body", "lower_body", "arms", "legs", "torso", "head", "left", "right")
_ARM = ("shoulder01", "upperarm", "lowerarm", "wrist", "finger", "metacarpal")
_LEG = ("upperleg", "lowerleg", "foot", "toe")
_LOWER = _LEG + ("pelvis", "spine05", "root")
_TORSO = ("spine", "pelvis", "breast", "clavicle", "root")


class TargetError(ParameterError):
    """A requested label value is outside what the model can reach, or was not met."""


def semantics_path(model_path) -> Path:
    """Where the SemanticModel of model file ``x.npz`` lives: ``x.semantics.npz`` beside it."""
    p = Path(model_path)
    return p.with_name(p.name[:-4] + ".semantics.npz" if p.name.endswith(".npz") else p.name + ".semantics.npz")


def tolerance(name: str) -> float:
    """Closed-loop tolerance of a label, SI units."""
    if name in TOLERANCES:
        return TOLERANCES[name]
    if kind_of(name) == "length":
        return LENGTH_TOLERANCE
    return 1e-3


# ----------------------------------------------------------------------------------- masks
def region_weights_from_template(template) -> dict[str, np.ndarray]:
    """Per-vertex weights (V,) in [0, 1] of every region in ``REGIONS``: sums of the default
    rig's skinning weights over the region's bones (smooth across joints); left/right from the
    template's vertex groups (1 on the side, 0.5 on the symmetry plane)."""
    rig = template.rigs["default"]
    w = sp.csc_matrix(rig.weights)

    def bones(prefixes):
        cols = [i for i, b in enumerate(rig.bone_names) if b.startswith(prefixes)]
        return np.clip(np.asarray(w[:, cols].sum(axis=1)).ravel(), 0.0, 1.0)

    nv = template.n_vertices
    lower = bones(_LOWER)
    arms, legs, torso = bones(_ARM), bones(_LEG), bones(_TORSO)
    left, right = np.zeros(nv), np.zeros(nv)
    left[template.left] = 1.0
    right[template.right] = 1.0
    left[template.mid] = right[template.mid] = 0.5
    head = np.clip(1.0 - arms - legs - torso, 0.0, 1.0)
    out = {"upper_body": 1.0 - lower, "lower_body": lower, "arms": arms, "legs": legs, "torso": torso,
           "head": head, "left": left, "right": right}
    return {k: np.where(v < 1e-4, 0.0, np.where(v > 1 - 1e-4, 1.0, v)) for k, v in out.items()}


class MaskedBlend:
    """Apply a change ``d`` (V, 3) to mesh ``x0`` only where ``weights`` (V,) say, in the gradient
    domain: minimise ``sum_f area_f || grad(d') - w_f grad(d) ||^2`` with ``d' = 0`` at every vertex
    of weight 0, ``w_f`` the mean weight of face f's corners. Inside the mask the shape change is
    kept, at the seam it fades over the blended triangles, outside nothing moves (exactly)."""

    def __init__(self, x0, faces, weights):
        from bodyspace.mesh.operators import gradient_operator
        from bodyspace.mesh.solver import FactorizedSolver
        faces = np.asarray(faces, dtype=np.int64)
        w = np.asarray(weights, dtype=float)
        if w.shape != (len(x0),) or not np.isfinite(w).all() or w.min() < 0 or w.max() > 1:
            raise ParameterError(f"mask: weights of shape {w.shape}, expected ({len(x0)},) values in [0, 1]")
        self.weights = w
        self.free = np.flatnonzero(w > 0)
        if self.free.size == 0:
            raise ParameterError("mask: every weight is 0, expected a region to change")
        self.g = gradient_operator(x0, faces)
        a, b, c = (np.asarray(x0)[faces[:, i]] for i in range(3))
        area = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)
        wf = w[faces].mean(axis=1)
        self.area3 = np.repeat(area, 3)
        self.wf3 = np.repeat(wf, 3)
        lap = (self.g.T @ sp.diags(self.area3) @ self.g).tocsr()
        self.fixed_all = self.free.size == len(w)
        sub = lap[self.free][:, self.free]
        if self.fixed_all:  # nothing held: pin one vertex of weight 1 (translation)
            sub = sub + sp.diags(np.r_[1e-8 * lap.diagonal().mean(), np.zeros(self.free.size - 1)])
        self.solver = FactorizedSolver(sub)

    def __call__(self, d) -> np.ndarray:
        d = np.asarray(d, dtype=float)
        if self.fixed_all and np.all(self.weights == 1):
            return d.copy()
        target = (self.g @ d) * self.wf3[:, None]
        rhs = self.g.T @ (self.area3[:, None] * target)
        out = np.zeros_like(d)
        out[self.free] = self.solver.solve(rhs[self.free])
        return out


def _metric_orthonormal(u, metric):
    """Columns of ``u`` (K, m) orthonormalized in the inner product ``a^T diag(metric) b``
    (dependent columns dropped)."""
    w = np.sqrt(metric)[:, None]
    q, r = np.linalg.qr(u * w)
    keep = np.abs(np.diag(r)) > 1e-10 * np.abs(np.diag(r)).max()
    return q[:, keep] / w


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
    of the step from the start. timings: seconds in decode, measure, solve. messages: warnings.
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

    def residuals(self) -> dict:
        return {k: self.values[k] - v for k, v in self.targets.items()}


# ----------------------------------------------------------------------------------- the model
class SemanticModel:
    """Semantic regressors on a BodyModel's coefficients, closed-loop generation, morphing, masks.

    Args:
        body_model: a fitted ``BodyModel`` (shape-only: rest scans).
        sigma_limit: reachable region, in standard deviations (Mahalanobis radius).
        max_iter: most corrections (decode + measure) of the closed loop, the Eq. 11 step
            included; finite-difference Jacobians (C + 4 bodies) come on top.
        on_infeasible: "raise" (refuse with the reachable range / the residuals) or "clamp"
            (clamp to the range and warn; a miss after ``max_iter`` warns).

    Attributes (after ``fit``/``load``): labels_ (names), measured_ (names measured on bodies),
    X_ (N, K) coefficients of one rest scan per subject, Y_ (N, L) labels (NaN unknown),
    regressors_ name -> fitted regressor, regions_ name -> (V,) weights, subjects_ (N,) ids.
    """

    def __init__(self, body_model, sigma_limit: float = 3.0, max_iter: int = 20, on_infeasible: str = "raise"):
        if on_infeasible not in ("raise", "clamp"):
            raise ParameterError(f"on_infeasible={on_infeasible!r}, expected 'raise' or 'clamp'")
        self.body_model = body_model
        self.sigma_limit = float(sigma_limit)
        self.max_iter = int(max_iter)
        self.on_infeasible = on_infeasible
        self._mset = None
        self._sub_msets = {}
        self._blends = {}
        self.lengths_ = []

    # ------------------------------------------------------------------ fitting
    @property
    def mset(self):
        if self._mset is None:
            from bodyspace.measure import load_measurement_set
            self._mset = load_measurement_set()
        return self._mset

    def _is_measured(self, name: str) -> bool:
        return name in self.measured_ or name in self.lengths_

    def _measure(self, vertices, names=None) -> dict:
        """Measurements of bodies: the whole set, or just ``names`` (plus what they depend on:
        mass needs stature, bmi mass and stature), in the set's order. The generation loop
        measures only what the request needs (the full set costs several times as much)."""
        from bodyspace.measure import measure
        mset = self.mset
        if names is not None:
            key = frozenset(names)
            if key not in self._sub_msets:
                by_name = {m["name"]: m for m in mset.measurements}
                need, todo = set(), list(key)
                while todo:
                    n = todo.pop()
                    if n in need or n not in by_name:
                        continue
                    need.add(n)
                    m = by_name[n]
                    if m["method"] in ("mass", "bmi"):
                        todo += [m[k] for k in ("stature", "mass") if isinstance(m.get(k), str)]
                self._sub_msets[key] = dataclasses.replace(
                    mset, measurements=tuple(m for m in mset.measurements if m["name"] in need))
            mset = self._sub_msets[key]
        return measure(mset, vertices, self.body_model.faces)

    def fit(self, db, measured=MEASURED_LABELS, subject_labels=None, rng=0, template=None) -> "SemanticModel":
        """Labels and regressors from ``db`` (the database the body model was fitted on): one
        rest scan per subject (the first of the model's fitted scans for that subject)."""
        from bodyspace.model import _read
        bm = self.body_model
        rows = np.asarray(bm.fitted_scans)
        if rows.size == 0:
            raise ParameterError("body_model: no fitted_scans recorded, expected a BodyModel from BodyModel.fit")
        scan_subj = np.asarray(db.scans["subject"])[rows]
        _, first = np.unique(scan_subj, return_index=True)
        first = np.sort(first)
        rows, subj = rows[first], scan_subj[first]
        if len(rows) < 4:
            raise ParameterError(f"database: {len(rows)} subjects, expected at least 4 to fit semantic regressors")
        verts = _read(db, rows)
        self.subjects_ = subj.astype(str)
        self.X_ = np.asarray(bm.project(verts), dtype=float).reshape(len(rows), -1)
        values = self._measure(verts)
        unknown = [m for m in measured if m not in values]
        if unknown:
            raise ParameterError(f"measured labels {unknown} are not in the measurement set; expected names from "
                                 f"{', '.join(values)}")
        labels = {m: np.asarray(values[m], dtype=float) for m in measured}
        cols = db.subjects
        ids = np.asarray(cols["subject"]).astype(str)
        index = {s: i for i, s in enumerate(ids)}
        where = np.array([index[s] for s in self.subjects_])
        for name, col in (SUBJECT_LABELS if subject_labels is None else subject_labels).items():
            if col not in cols:
                continue
            raw = np.asarray(cols[col])[where]
            if name == "sex" or raw.dtype.kind in "OUS":
                low = np.char.lower(raw.astype(str))
                v = np.where(low == "male", 1.0, np.where(low == "female", 0.0, np.nan))
            else:
                v = raw.astype(float)
            if np.isfinite(v).sum() >= 4 and np.nanstd(v) > 0:
                labels[name] = v
        self.labels_ = list(labels)
        self.measured_ = [m for m in measured]
        self.Y_ = np.column_stack([labels[n] for n in self.labels_])
        self._fit_regressors(rng)
        # every other length of the measurement set (girths, Rupprecht loops, widths, limb
        # lengths) is a target too: a regressor each (cheap), measured only when asked
        self.lengths_ = []
        for m in self.mset.measurements:
            name = m["name"]
            if name in labels or m["unit"] != "m" or name not in values:
                continue
            y = np.asarray(values[name], dtype=float)
            ok = np.isfinite(y)
            if ok.sum() >= 4 and np.std(y[ok]) > 0:
                self.regressors_[name] = self._fit_one(self.X_[ok], y[ok], rng)
                self.lengths_.append(name)
        if template is None:
            try:
                from bodyspace.data.template import load_template
                template = load_template()
            except BodyspaceError:
                template = None
        self.regions_ = {}
        if template is not None and template.n_vertices == len(bm.template_vertices) and \
                np.array_equal(np.asarray(template.faces), bm.faces):
            self.regions_ = region_weights_from_template(template)
        return self

    def _fit_regressors(self, rng):
        self.regressors_ = {}
        for j, name in enumerate(self.labels_):
            y = self.Y_[:, j]
            ok = np.isfinite(y)
            self.regressors_[name] = self._fit_one(self.X_[ok], y[ok], rng)

    @staticmethod
    def _fit_one(x, y, rng):
        reg = FilteredLinearRegressor(rng=rng).fit(x, y)
        if not np.any(reg.coef_):  # nothing kept: fall back to the plain least squares (Eq. 10)
            reg = SimpleLinearRegressor().fit(x, y)
        return reg

    # ------------------------------------------------------------------ ranges
    @property
    def variances(self) -> np.ndarray:
        return np.asarray(self.body_model.space.explained_variance_, dtype=float)

    def reachable_range(self, name: str) -> tuple[float, float]:
        """(lo, hi) of label ``name`` over coefficients within ``sigma_limit`` SD (linear regressor)."""
        reg = self._regressor(name)
        center = float(reg.predict(np.zeros(self.X_.shape[1])))
        half = self.sigma_limit * float(np.sqrt(np.sum(reg.coef_ ** 2 * self.variances)))
        return center - half, center + half

    def _regressor(self, name):
        if name not in getattr(self, "regressors_", {}):
            labels = list(getattr(self, "labels_", []))
            lengths = list(getattr(self, "lengths_", []))
            meas = ", ".join(lengths) or "(none: this semantics file predates measurement targets; refit it)"
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
                              f"({rng_txt}, within {self.sigma_limit:g} SD); ask within that range or clamp")
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
            meas = self._measure(x, measured)
            timings["measure"] += time.perf_counter() - t
        return np.array([float(meas[n]) if self._is_measured(n) else float(self.regressors_[n].predict(c))
                         for n in names]), meas

    def _decode(self, c, timings) -> np.ndarray:
        t = time.perf_counter()
        x = np.asarray(self.body_model.reconstruct(c))[0]
        timings["decode"] += time.perf_counter() - t
        return x

    # ------------------------------------------------------------------ the closed loop
    def _solve(self, c0, goal: dict, body, timings, messages, current=None) -> GenerationResult:
        names = list(goal)
        g = np.array([goal[n] for n in names], dtype=float)
        tol = np.array([tolerance(n) for n in names])
        metric = 1.0 / np.maximum(self.variances, 1e-300)
        grads = np.array([self._regressor(n).gradient(c0) for n in names], dtype=float)
        c = np.asarray(c0, dtype=float).copy()
        x = body(c)
        vals, meas = current if current is not None else self._values(names, x, c, timings)

        def score(v):
            e = np.abs(g - v) / tol
            return float(np.linalg.norm(e)) if np.isfinite(e).all() else np.inf

        def try_step(step):
            cn = c + step
            xn = body(cn)
            vn, mn = self._values(names, xn, cn, timings)
            return cn, xn, vn, mn

        it = 0
        # 1. Equation (11): the minimum-norm step (PCA-variance metric) along the regressor gradients.
        if score(vals) > np.sqrt(len(names)) or np.any(np.abs(g - vals) > tol):
            t = time.perf_counter()
            z = morph_directions(grads, g - vals, metric=metric)
            timings["solve"] += time.perf_counter() - t
            cn, xn, vn, mn = try_step(z)
            it += 1
            if score(vn) < score(vals):
                c, x, vals, meas = cn, xn, vn, mn
        # 2. Closed loop: Gauss-Newton on the measured residuals in the span of the minimum-norm
        #    directions u_i = var * s_i (where every minimum-norm solution lies), Jacobian by
        #    finite differences there, refreshed by Broyden updates, steps at most MAX_STEP SD.
        u = self.variances[:, None] * grads.T
        extra = np.eye(len(metric))[:, :min(EXTRA_DIRECTIONS, len(metric))] * np.sqrt(self.variances)[:, None]
        u = _metric_orthonormal(np.hstack([u, extra]), metric)
        # The regressors' gradients are a first model of the measured Jacobian in that span: a
        # correction costs one decode instead of a finite-difference column per direction, and
        # the finite differences run only once a step shows the model is off.
        jac, fresh = grads @ u, False
        while np.any(np.abs(g - vals) > tol) and it < self.max_iter:
            if jac is None:
                jac = np.empty((len(names), u.shape[1]))
                for i in range(u.shape[1]):
                    _, _, vi, _ = try_step(FD_STEP * u[:, i])
                    jac[:, i] = (vi - vals) / FD_STEP
                fresh = True
                if not np.isfinite(jac).all():
                    break
            t = time.perf_counter()
            a = np.linalg.lstsq(jac, g - vals, rcond=1e-8)[0]
            a *= min(1.0, MAX_STEP / max(np.linalg.norm(a), 1e-300))
            timings["solve"] += time.perf_counter() - t
            before = score(vals)
            for _ in range(4):  # backtrack if a step makes things worse
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
                break  # no progress even with a fresh Jacobian
            else:
                jac = None  # refresh the Jacobian where we are
        converged = bool(np.all(np.abs(g - vals) <= tol))
        if not converged:
            miss = ", ".join(f"{n} {format_value(n, v)} (asked {format_value(n, gv)})"
                             for n, v, gv, tl in zip(names, vals, g, tol) if abs(gv - v) > tl)
            msg = (f"not met after {it} corrections: {miss}; the request is probably not jointly reachable "
                   f"(ask for less, or fewer constraints)")
            if self.on_infeasible == "raise":
                raise TargetError(msg)
            warnings.warn(msg, RuntimeWarning, stacklevel=3)
            messages.append(msg)
        missing = [n for n in self.measured_ if n not in meas]
        if meas and missing:  # the result reports every measured label: the rest once, on the final body
            t = time.perf_counter()
            meas = {**meas, **self._measure(x, missing)}
            timings["measure"] += time.perf_counter() - t
        maha = float(np.sqrt(np.sum((c - c0) ** 2 * metric)))
        return GenerationResult(c, x, dict(zip(names, vals.tolist())), dict(zip(names, g.tolist())), converged,
                                it, maha, dict(timings), messages, {k: float(v) for k, v in meas.items()})

    # ------------------------------------------------------------------ generate
    def generate(self, targets: dict, rng=None, sigma_range: float = 2.0) -> GenerationResult:
        """A random body that measures ``targets``: name -> value (SI), ``(lo, hi)`` or ``Target``.

        The other degrees of freedom are drawn at random (Gaussian coefficients truncated to
        ``sigma_range`` SD); a range is met by moving the random body's value to the nearest
        point of the range (kept where it already is when inside).
        """
        timings = {"decode": 0.0, "measure": 0.0, "solve": 0.0}
        messages: list = []
        gen = np.random.default_rng(rng)
        reqs = self._requests(targets)
        c0 = np.asarray(self.body_model.sample_coefficients(1, sigma_range=sigma_range, rng=gen), dtype=float)[0]
        names = list(reqs)
        x0 = self._decode(c0, timings)
        vals0, meas0 = self._values(names, x0, c0, timings)
        goal = {}
        for name, v0 in zip(names, vals0):
            goal[name] = self._resolve(reqs[name], v0, messages)
        return self._solve(c0, goal, lambda c: self._decode(c, timings), timings, messages,
                           current=(vals0, meas0))

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
            self._regressor(req.name)
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
            bad = [m for m in mask if m not in self.regions_]
            if bad:
                raise ParameterError(f"mask: unknown region(s) {bad}; expected one of {', '.join(self.regions_) or '(none: this model has no template regions; pass per-vertex weights)'}")
            return np.max([self.regions_[m] for m in mask], axis=0)
        return np.asarray(mask, dtype=float)

    def _masked_blend(self, weights) -> MaskedBlend:
        """The ``MaskedBlend`` of a mask, built on the model's mean body and cached: its matrix
        depends on the mask and the rest geometry only, so a morph pays triangular solves, not a
        factorization. Using the mean body's gradients instead of the morphed body's changes only
        the metric the change is blended in; outside the mask nothing moves either way."""
        key = np.asarray(weights, dtype=float).tobytes()
        if key not in self._blends:
            if len(self._blends) >= 8:  # bounded: user-supplied weight arrays are keys too
                self._blends.pop(next(iter(self._blends)))
            mean = np.asarray(self.body_model.encoder.mean_vertices_, dtype=float)
            self._blends[key] = MaskedBlend(mean, self.body_model.faces, weights)
        return self._blends[key]

    def morph(self, vertices, changes: dict, keep=(), mask=None) -> GenerationResult:
        """Morph a registered mesh (V, 3): ``changes`` name -> ``Target`` (value/delta/range) or a
        float *change* (SI), ``keep`` names held at their measured value, ``mask`` a region
        name(s) or (V,) weights: the change is confined to it (``MaskedBlend``), and the loop
        corrects for what the mask took away."""
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
            self._regressor(name)
            reqs[name] = Target(name, "delta", value=0.0)
        if not reqs:
            raise ParameterError("morph: nothing to change, expected at least one --set")
        t = time.perf_counter()
        c0 = np.asarray(self.body_model.project(x0), dtype=float).reshape(-1)
        d0 = np.asarray(self.body_model.reconstruct(c0))[0]
        timings["decode"] += time.perf_counter() - t
        w = self.mask_weights(mask)
        blend = self._masked_blend(w) if w is not None else None

        def body(c):
            d = self._decode(c, timings) - d0
            if blend is not None:
                t = time.perf_counter()
                d = blend(d)
                timings["solve"] += time.perf_counter() - t
            return x0 + d

        names = list(reqs)
        vals0, meas0 = self._values(names, x0, c0, timings)
        goal = {n: (v0 if n in keep else self._resolve(reqs[n], v0, messages)) for n, v0 in zip(names, vals0)}
        return self._solve(c0, goal, body, timings, messages, current=(vals0, meas0))

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

    # ------------------------------------------------------------------ Table 1 / Table 2
    def evaluate(self, folds: int = 10, rng=0) -> tuple:
        """(Table 1 ``RegressionTable``, Table 2 dict label -> (mean, sd) degrees) on the model's
        subjects (one row per subject)."""
        from bodyspace.semantics.evaluation import (
            cross_validated_rmse,
            direction_angles,
        )
        from bodyspace.semantics.regressors import KernelRegressor
        labels = {n: self.Y_[:, j] for j, n in enumerate(self.labels_)}
        table1 = cross_validated_rmse(self.X_, labels, folds=folds, rng=rng)
        table2 = {}
        for n, y in labels.items():
            ok = np.isfinite(y)
            reg = KernelRegressor().fit(self.X_[ok], y[ok])
            table2[n] = direction_angles(reg, self.X_[ok])
        return table1, table2

    # ------------------------------------------------------------------ files
    def save(self, path) -> Path:
        """One ``.npz`` (no pickle) with a JSON header; by default beside the model file."""
        path = Path(path)
        arrays = {"X": self.X_, "Y": self.Y_, "subjects": np.array(self.subjects_, dtype="U")}
        regs = {}
        for name, reg in self.regressors_.items():
            regs[name] = type(reg).__name__
            for k, a in reg.to_arrays().items():
                arrays[f"reg/{name}/{k}"] = a
        for name, w in self.regions_.items():
            arrays[f"region/{name}"] = w.astype(np.float32)
        header = {"format": FORMAT, "format_version": FORMAT_VERSION, "labels": self.labels_,
                  "measured": self.measured_, "lengths": self.lengths_, "regressors": regs, "regions": list(self.regions_),
                  "sigma_limit": self.sigma_limit, "n_components": int(self.X_.shape[1]),
                  "template_id": self.body_model.template_id,
                  "units": {n: kind_of(n) for n in self.labels_ + self.lengths_}}
        arrays["header"] = np.frombuffer(json.dumps(header).encode("utf-8"), dtype=np.uint8)
        with atomic_path(path) as tmp, open(tmp, "wb") as fh:
            np.savez(fh, **arrays)
        return path

    @classmethod
    def load(cls, path, body_model, **params) -> "SemanticModel":
        from bodyspace.semantics.regressors import KernelRegressor
        path = Path(path)
        if not path.is_file():
            raise ParameterError(f"{path}: no semantic model; fit one from the database (CLI: --database DB)")
        try:
            z = np.load(path, allow_pickle=False)
            header = json.loads(z["header"].tobytes().decode("utf-8"))
        except Exception as exc:  # noqa: BLE001 - any damage is reported the same way
            raise ParameterError(f"{path}: not a SemanticModel file ({exc})") from None
        if header.get("format") != FORMAT or header.get("format_version") != FORMAT_VERSION:
            raise ParameterError(f"{path}: format {header.get('format')!r} v{header.get('format_version')!r}, "
                                 f"expected {FORMAT!r} v{FORMAT_VERSION}")
        if header.get("n_components") != body_model.n_components:
            raise ParameterError(f"{path}: fitted on {header.get('n_components')} components, the model has "
                                 f"{body_model.n_components}; refit it (--database DB --refit)")
        self = cls(body_model, sigma_limit=params.pop("sigma_limit", header.get("sigma_limit", 3.0)), **params)
        kinds = {"FilteredLinearRegressor": FilteredLinearRegressor, "SimpleLinearRegressor": SimpleLinearRegressor,
                 "KernelRegressor": KernelRegressor}
        with z:
            self.X_, self.Y_ = z["X"], z["Y"]
            self.subjects_ = z["subjects"].astype(str)
            self.labels_, self.measured_ = list(header["labels"]), list(header["measured"])
            self.lengths_ = list(header.get("lengths", []))
            self.regressors_ = {}
            for name, kind in header["regressors"].items():
                prefix = f"reg/{name}/"
                arrs = {k[len(prefix):]: z[k] for k in z.files if k.startswith(prefix)}
                self.regressors_[name] = kinds[kind].from_arrays(arrs)
            self.regions_ = {name: z[f"region/{name}"].astype(float) for name in header["regions"]}
        return self
