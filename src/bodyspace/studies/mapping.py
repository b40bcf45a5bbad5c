"""Evaluation of the semantic mapping (Rupprecht §4.2, Rupprecht Tables 1-2, Rupprecht Figures 4 and 6).

Three methods side by side on held-out *feasible* requests (the measurements of bodies sampled
like the training set, so some body meets each exactly): the linear mapping of the related work
(Rupprecht Table 2), the linear-leaf forest (Rupprecht Table 1), and the forest followed by ``refine.refine``. For
each, the body of the predicted coefficients is measured again and ``measured - requested`` (cm)
is summarized per parameter by its mean and variance, as in the paper's tables; plus the share
of requests with all inputs within 1 mm. Rupprecht Figure 6: shoulder size swept from 100 to 140 cm, the
other five held at the training set's median. The inputs are the model's (``mapping_inputs`` of its
measurement set): Rupprecht's six on the template, ISO stand-ins on another topology (their
sweep: shoulder width over the training set's 5th-95th percentiles).

RRE models: every body is decoded (training set, held-out requests, both predictions, each
refinement iteration), so the default sizes are smaller (``default_sizes``) and
``estimate_seconds`` says how long it will take before starting; the measurements of all three
methods are those of the truly decoded bodies.

An input that is an affine function of the coefficients (a vertex model's shoulder_width between
mirrored landmarks) is returned exactly by the linear mapping and by every forest leaf, both
affine least-squares fits: its error of 0 says nothing about either, so it is flagged
(``settings["exact_by_construction"]``, ``exact_by_construction_note``), with every input's affine
residual (``settings["affine_residual_cm"]``).

This module returns data (``MappingEvaluation``); ``report.mapping_report`` writes its tables
and pictures.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from bodyspace.mapping.bundle import forest_for
from bodyspace.mapping.gradients import SUBSTITUTES, LinearBodyMeasures
from bodyspace.mapping.linear import LinearMapping
from bodyspace.mapping.refine import analytic_names, refine
from bodyspace.mapping.training import (
    AFFINE_CM,
    affine_residuals,
    default_sizes,
    make_training_set,
    measure_coefficients,
    sample_uniform,
)
from bodyspace.validation import as_seed

METHODS = ("linear", "forest", "forest + refinement")
SWEEP_CM = (100.0, 110.0, 120.0, 130.0, 140.0)


@dataclass
class MappingEvaluation:
    """names (M,); requests (N, M) cm; errors: method → (N, M) measured − requested (cm);
    timings (s); sweep: the shoulder-size sweep (see ``shoulder_sweep``); refine_misses: count of
    held-out requests refinement reported as missed."""

    names: tuple
    requests: np.ndarray
    errors: dict
    timings: dict
    sweep: dict = field(default_factory=dict)
    settings: dict = field(default_factory=dict)

    def table(self, method: str) -> dict:
        """name → {"mean": cm, "variance": cm², "sd": cm} for one method."""
        e = self.errors[method]
        return {n: {"mean": float(e[:, j].mean()), "variance": float(e[:, j].var()), "sd": float(e[:, j].std())}
                for j, n in enumerate(self.names)}

    def within(self, method: str, tol_cm: float = 0.1) -> float:
        """Share of requests whose measurements are all within ``tol_cm`` of the request."""
        return float(np.mean(np.abs(self.errors[method]).max(axis=1) <= tol_cm))

    def to_json(self) -> dict:
        return {"units": {"mean": "cm", "variance": "cm^2"}, "names": list(self.names),
                "held_out": int(len(self.requests)), "settings": self.settings,
                "tables": {m: self.table(m) for m in self.errors},
                "within_1mm": {m: self.within(m) for m in self.errors},
                "timings_s": {k: round(v, 4) for k, v in self.timings.items()},
                "shoulder_sweep": _jsonable(self.sweep)}


def _jsonable(x):
    if isinstance(x, dict):
        return {k: _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    if isinstance(x, np.ndarray):
        return x.tolist()
    if isinstance(x, np.generic):
        return x.item()
    return x


def _pad(z: np.ndarray, K: int) -> np.ndarray:
    out = np.zeros((len(z), K))
    out[:, :z.shape[1]] = z
    return out


def decode_seconds(model, n: int = 4, k: int = 25, rng=0) -> float:
    """Seconds per decoded body of ``model`` (wall clock, batched as in training), timed on ``n``
    uniform ±3 sigma samples drawn with ``rng`` (Generator, seed or None); 0 for a linear
    encoding such as the vertex one (nothing is decoded)."""
    if model.encoder.is_linear:
        return 0.0
    z = sample_uniform(model, n, k, 3.0, as_seed(rng) + 12345)
    t = time.perf_counter()
    model.reconstruct(z)
    return (time.perf_counter() - t) / n


def estimate_seconds(model, samples: int, held_out: int, per_body: float | None = None,
                     refine_iterations: float = 6.0, sweep: bool = True) -> float:
    """Rough wall-clock estimate of ``evaluate_mapping`` for an RRE model: every training body,
    every held-out body, the linear and forest predictions and ~``refine_iterations`` refinement
    iterations per request are one decode each. 0 for linear (vertex) models (seconds at most)."""
    if model.encoder.is_linear:
        return 0.0
    per_body = decode_seconds(model) if per_body is None else per_body
    n_sweep = len(SWEEP_CM) * (2 + refine_iterations) if sweep else 0
    return per_body * (samples + held_out * (3 + refine_iterations) + n_sweep)


def evaluate_mapping(model, samples: int | None = None, held_out: int | None = None, rng=0, k: int = 25,
                     n_trees: int = 50, n_jobs: int | None = None, sweep: bool = True,
                     progress=None) -> tuple[MappingEvaluation, dict]:
    """Train the three methods on ``samples`` bodies and evaluate them on ``held_out`` requests.

    ``rng``: Generator, seed or None. With an integer seed ``s`` (recorded as ``seed``) the
    training set is drawn with ``s``, the held-out set with ``s + 1``, the forest seeded with ``s``.
    ``samples`` / ``held_out`` default to ``default_sizes(model)``. With the RRE encoding every
    body is decoded (training, held-out, the predictions, each refinement iteration): see
    ``estimate_seconds``; the refinement's Jacobians use the training set's least-squares
    linearization of the decoder.
    Returns the evaluation and the fitted ``{"linear": ..., "forest": ..., "linearization": ...}``
    (linearization None for vertex models).
    """
    report = progress or (lambda msg, frac: None)
    seed = as_seed(rng)
    d_samples, d_held = default_sizes(model)
    samples = d_samples if samples is None else int(samples)
    held_out = d_held if held_out is None else int(held_out)
    decoded = not model.encoder.is_linear
    # progress fractions of the stages (decoding dominates for RRE models)
    f_train, f_held, f_fit, f_pred, f_ref = (0.2, 0.22, 0.25, 0.6, 0.95) if not decoded else \
        _stage_fractions(samples, held_out)
    timings = {}
    t = time.perf_counter()
    report("training set", 0.0)
    train = make_training_set(model, samples, k, rng=seed,
                              progress=lambda msg, f: report(f"training set: {msg}", f * f_train))
    held = make_training_set(model, held_out, k, rng=seed + 1,
                             progress=lambda msg, f: report(f"held-out: {msg}", f_train + f * (f_held - f_train)))
    timings["training_set_s"] = time.perf_counter() - t
    kk = train.k
    X, Y = train.measurements, train.coefficients[:, :kk]
    report("linear mapping", f_held)
    t = time.perf_counter()
    lin = LinearMapping().fit(X, Y)
    timings["linear_fit_s"] = time.perf_counter() - t
    report("forest", f_held)
    t = time.perf_counter()
    forest = forest_for(len(X), seed, n_trees, n_jobs).fit(X, Y)
    timings["forest_fit_s"] = time.perf_counter() - t
    names, mset = train.names, model.measurement_set
    # An input that is affine in the coefficients is met exactly by every affine least-squares
    # mapping (linear, each forest leaf): flagged, so an error of 0 is not read as a perfect method.
    residual = affine_residuals(train.coefficients[:, :kk], X)
    # Rupprecht's six (loops, distances) have analytic Jacobians and are measured on the touched
    # vertices; stand-ins of another topology (slices) are measured on reconstructed bodies.
    measurer = None
    if analytic_names(mset, names) == tuple(names):
        measurer = LinearBodyMeasures.from_model(model, mset, names, k=kk, linearization=train.linearization)

    def measure_z(z, progress=lambda msg, f: None):
        """Measurements (N, M) cm of the bodies of coefficients z (N, K)."""
        if measurer is None:
            return measure_coefficients(model, z, names, mset, progress=progress)[0]
        if decoded:
            return _measure_decoded(model, measurer, z, kk, progress)
        return measurer(z[:, :kk]) * 100.0

    req = held.measurements
    K = model.n_components
    preds = {"linear": _pad(lin.predict(req), K)}
    t = time.perf_counter()
    preds["forest"] = _pad(forest.predict(req), K)
    timings["forest_predict_s"] = time.perf_counter() - t
    errors = {}
    for i, m in enumerate(("linear", "forest")):
        errors[m] = measure_z(preds[m], lambda msg, f, i=i, m=m: report(
            f"{m}: {msg}", f_fit + (i + f) / 2 * (f_pred - f_fit))) - req
    report("refinement", f_pred)
    t = time.perf_counter()
    ref = refine(model, preds["forest"], req, names, mset=mset, measurer=measurer, k=kk,
                 linearization=train.linearization,
                 progress=lambda msg, f: report(f"refinement: {msg}", f_pred + f * (f_ref - f_pred)))
    timings["refine_s"] = time.perf_counter() - t
    timings["refine_ms_per_request"] = 1000 * timings["refine_s"] / len(req)
    preds["forest + refinement"] = ref.coefficients
    # measured on the reconstructed (RRE: truly decoded) bodies, as refine measured them
    errors["forest + refinement"] = ref.measured - req if decoded or measurer is None else \
        measure_z(ref.coefficients) - req
    report("shoulder sweep", f_ref)
    sw = shoulder_sweep(model, forest, train, measure_z, mset=mset, measurer=measurer) if sweep else {}
    report("done", 1.0)
    ev = MappingEvaluation(train.names, req, errors, timings, sw,
                           {"samples": samples, "held_out": held_out, "seed": seed, "k": kk, "n_trees": n_trees,
                            "inputs": list(names), "measurement_set": mset.source,
                            "dropped_bodies": int(train.dropped + held.dropped),
                            "encoding": model.encoding, "refine_misses": int(sum(bool(m) for m in ref.misses)),
                            "refine_iterations_mean": float(ref.iterations.mean()),
                            "refine_iterations_max": int(ref.iterations.max()), "refine_decodes": int(ref.decodes),
                            "affine_residual_cm": {n: (None if not np.isfinite(r) else float(r))
                                                   for n, r in zip(names, residual)},
                            "exact_by_construction": [n for n, r in zip(names, residual) if r < AFFINE_CM]})
    return ev, {"linear": lin, "forest": forest, "linearization": train.linearization}


def exact_by_construction_note(ev: MappingEvaluation) -> str:
    """One sentence on the inputs every affine least-squares mapping returns exactly ("" if none).

    Such an input is an affine function of the model's coefficients over the training set
    (``training.affine_residuals`` below ``training.AFFINE_CM``): its error in the tables is 0 up
    to rounding for the linear mapping and the forest alike, which tests neither method.
    """
    exact = ev.settings.get("exact_by_construction") or []
    if not exact:
        return ""
    res = ev.settings.get("affine_residual_cm", {})
    said = ", ".join(f"{n} (affine residual {res.get(n, 0.0):.1e} cm)" for n in exact)
    verb = "is an affine function" if len(exact) == 1 else "are affine functions"
    return (f"exact by construction (*): {said} {verb} of this model's coefficients over the training set, "
            "so the linear mapping and every forest leaf (affine least-squares fits on the inputs) return "
            f"{'it' if len(exact) == 1 else 'them'} exactly; the error of 0 there tests neither method "
            "(with the vertex encoding a straight distance whose direction does not change between bodies, "
            "such as a shoulder width between mirrored landmarks, is one)")


def _stage_fractions(samples, held_out, iterations=6.0):
    """Progress fractions at the end of each stage, in proportion to the decodes it does."""
    w = np.cumsum([samples, held_out, 1e-9, 2 * held_out, iterations * held_out, len(SWEEP_CM) * (2 + iterations)])
    return tuple(w[:5] / w[-1])


def _measure_decoded(model, measurer, z, k, progress, chunk: int = 32) -> np.ndarray:
    """Measurements (N, M) cm of the decoded bodies of coefficients z (N, K), in chunks."""
    out = np.empty((len(z), len(measurer.names)))
    for s in range(0, len(z), chunk):
        out[s:s + chunk] = measurer.measure_bodies(model.reconstruct(z[s:s + chunk])) * 100.0
        progress(f"decoded {min(len(z), s + chunk)}/{len(z)}", min(1.0, (s + chunk) / len(z)))
    return out


def shoulder_sweep(model, forest, train, measure_z, sizes=None, name: str | None = None, mset=None,
                   measurer=None) -> dict:
    """Rupprecht Figure 6: ``name`` set to each of ``sizes`` (cm), the other parameters at the training median.

    ``measure_z(z (N, K)) -> (N, M) cm`` measures bodies; ``name`` defaults to shoulder_size (or its
    stand-in, ``SUBSTITUTES``), ``sizes`` to ``SWEEP_CM`` for shoulder_size, else five steps over
    the training set's 5th-95th percentiles. ``mset``, ``measurer`` go to ``refine``.
    Returns requests (S, M), coefficients (S, K) (forest + refinement), measured (S, M) cm,
    forest_measured (S, M) cm (forest alone), misses (per size: what refinement could not meet).
    """
    names = train.names
    if name is None:
        name = next((n for n in ("shoulder_size",) + SUBSTITUTES["shoulder_size"] if n in names), names[-1])
    j = names.index(name)
    if sizes is None:
        sizes = SWEEP_CM if name == "shoulder_size" else tuple(
            float(x) for x in np.round(np.linspace(*np.percentile(train.measurements[:, j], [5, 95]), 5), 1))
    base = np.median(train.measurements, axis=0)
    req = np.tile(base, (len(sizes), 1))
    req[:, j] = sizes
    K = model.n_components
    z0 = _pad(forest.predict(req), K)
    res = refine(model, z0, req, names, mset=mset, measurer=measurer, k=train.k, linearization=train.linearization)
    start = measure_z(z0)
    return {"names": list(names), "swept": name, "sizes_cm": list(sizes), "requests": req,
            "coefficients": res.coefficients, "measured": res.measured,
            "forest_measured": start, "misses": res.misses}
