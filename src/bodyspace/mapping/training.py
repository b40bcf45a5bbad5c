"""Training data for the semantic mapping, drawn from the shape space (Rupprecht §3.1.2, Rupprecht §4.1).

The first ``k`` shape coefficients (25 in the paper) are drawn uniformly within ``±sigma_range``
standard deviations (the rest are 0), the bodies are reconstructed and measured with the loop
definitions of Rupprecht §3.1.2 (``height``, ``breast_size``, ``waist_size``, ``hip_size``,
``leg_length``, ``shoulder_size``) and, optionally, any other measurements of a set. The set is
the model's own (``model.measurement_set``); on another topology the template's loops are stood
in for by ISO girths (``gradients.mapping_inputs``), measured as slices.

With the vertex encoding, loops, distances and paths are computed straight from the
coefficients on the few vertices they touch (``gradients.LinearBodyMeasures``, the same numbers
as ``measure.evaluate`` to rounding; conditions such as "upright" are not applied, as in the
paper); any other measurement (slices, volume, mass) goes through ``model.reconstruct`` and
``measure.evaluate`` in chunks. With the RRE encoding every body is decoded (in chunks, on the
decoder's threads); loops, distances and paths are measured on the decoded vertices
(``LinearBodyMeasures.measure_bodies``, same numbers as ``measure.evaluate``), and the decoded
bodies are fitted, on the way, by the least-squares linearization refinement uses.

Measurements are returned in **cm** (lengths; other units unchanged), the units of the mapping.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from bodyspace.encoding.linearize import DecoderLinearization
from bodyspace.errors import ParameterError
from bodyspace.mapping.gradients import (
    DIFFERENTIABLE,
    LinearBodyMeasures,
    mapping_inputs,
    subset,
)
from bodyspace.measure import measure

CHUNK = 256
# An input whose spread over the training bodies is below this (cm) does not vary with the body.
CONSTANT_CM = 1e-6
# An input that is an affine function of the coefficients to within this (rms, cm) over the
# training set is returned exactly by every affine least-squares mapping (see ``affine_residuals``).
AFFINE_CM = 1e-3
# RRE bodies are decoded (~30-400 ms each): smaller chunks, so progress is reported every few seconds.
DECODED_CHUNK = 32


@dataclass
class TrainingSet:
    """coefficients (N, K) (the first ``k`` vary), measurements (N, M) in cm for lengths,
    names (M,), units (M,) as shown ("cm", "kg", ...), k, sigma_range, seed; linearization: RRE
    models only, the least-squares ``encoding.linearize.DecoderLinearization`` of the decoded bodies (None
    for the vertex encoding, which is linear); dropped: bodies left out because a measurement was
    undefined on them (a failed condition)."""

    coefficients: np.ndarray
    measurements: np.ndarray
    names: tuple
    units: tuple
    k: int
    sigma_range: float
    seed: object = None
    linearization: object = None
    dropped: int = 0


    def column(self, name: str) -> np.ndarray:
        return self.measurements[:, self.names.index(name)]


def default_sizes(model) -> tuple[int, int]:
    """(training samples, held-out requests): the paper's 10,000 / 1,000 for vertex models whose
    inputs are loops and lengths (Rupprecht's six: measured on the few vertices they touch);
    1,000 / 100 for RRE models, whose every body is decoded (~0.03-0.4 s each), and for models
    of another topology, whose girth inputs are slices of every reconstructed body (~3-10 ms each)."""
    mset = model.measurement_set
    by_name = {m["name"]: m for m in mset.measurements}
    sliced = any(by_name[n]["method"] not in DIFFERENTIABLE for n in mapping_inputs(mset))
    return (10000, 1000) if model.encoder.is_linear and not sliced else (1000, 100)


def sample_uniform(model, n: int, k: int = 25, sigma_range: float = 3.0, rng=None) -> np.ndarray:
    """Coefficients (n, K): the first ``min(k, K)`` uniform in ±sigma_range standard deviations, rest 0."""
    K = model.n_components
    k = min(int(k), K)
    if n < 1 or k < 1:
        raise ParameterError(f"n={n}, k={k}: expected at least one sample and one coefficient")
    sd = np.sqrt(model.space.explained_variance_[:k])
    z = np.zeros((int(n), K))
    z[:, :k] = np.random.default_rng(rng).uniform(-sigma_range, sigma_range, (int(n), k)) * sd
    return z


def _display(unit: str) -> tuple[str, float]:
    return ("cm", 100.0) if unit == "m" else (unit, 1.0)


def measure_coefficients(model, z: np.ndarray, names=None, mset=None, measurer=None,
                         progress=None, linearization=None) -> tuple[np.ndarray, tuple]:
    """Measurements (N, M) (cm for lengths) and their display units of bodies with coefficients z (N, K).

    ``mset``: default the model's own (``model.measurement_set``); ``names``: default the
    mapping's inputs for it (``gradients.mapping_inputs``: Rupprecht's six on the template).
    RRE models decode every body; pass ``linearization`` (a ``DecoderLinearization``) to have
    it accumulate the decoded bodies on the way (``partial_fit``).
    """
    mset = model.measurement_set if mset is None else mset
    names = mapping_inputs(mset) if names is None else tuple(names)
    by_name = {m["name"]: m for m in subset(mset, names).measurements}
    units = tuple(_display(by_name[n]["unit"])[0] for n in names)
    scale = np.array([_display(by_name[n]["unit"])[1] for n in names])
    out = np.empty((len(z), len(names)))
    fast = [i for i, n in enumerate(names) if by_name[n]["method"] in DIFFERENTIABLE
            and (by_name[n]["method"] != "loop" or by_name[n].get("axis", "up") == "up")]
    slow = [i for i in range(len(names)) if i not in fast]
    report = progress or (lambda msg, frac: None)
    if model.encoder.is_linear:
        if fast:
            if measurer is None:
                measurer = LinearBodyMeasures.from_model(model, mset, [names[i] for i in fast])
            for s in range(0, len(z), 4 * CHUNK):
                out[s:s + 4 * CHUNK, fast] = measurer(z[s:s + 4 * CHUNK, :measurer.n_coefficients])
                report(f"measured {min(len(z), s + 4 * CHUNK)}/{len(z)} bodies", min(1.0, (s + 4 * CHUNK) / len(z)))
        fast_bodies = None
    else:
        # Every body is decoded: measure the loops/distances/paths on the decoded vertices (same
        # numbers as measure.evaluate, without its conditions), the rest with evaluate.
        fast_bodies = LinearBodyMeasures(model.mean_vertices, np.zeros((1,) + model.mean_vertices.shape), mset,
                                         [names[i] for i in fast]) if fast else None
    if slow or fast_bodies is not None:
        sub = subset(mset, [names[i] for i in slow]) if slow else None
        chunk = CHUNK if model.encoder.is_linear else DECODED_CHUNK
        for s in range(0, len(z), chunk):
            v = model.reconstruct(z[s:s + chunk])
            if linearization is not None:
                linearization.partial_fit(z[s:s + chunk], v)
            if fast_bodies is not None:
                out[s:s + chunk, fast] = fast_bodies.measure_bodies(v)
            if slow:
                vals = measure(sub, v, model.faces)
                for i in slow:
                    out[s:s + chunk, i] = vals[names[i]]
            report(f"decoded and measured {min(len(z), s + chunk)}/{len(z)} bodies",
                   min(1.0, (s + chunk) / len(z)))
    return out * scale, units


def make_training_set(model, n: int = 10000, k: int = 25, rng=0, names=None, mset=None,
                      sigma_range: float = 3.0, progress=None) -> TrainingSet:
    """Sample ``n`` bodies from ``model`` and measure them (Rupprecht §4.1).

    Args:
        model: a ``BodyModel`` (vertex encoding: fast path; RRE: decoded in chunks, and the
            least-squares ``DecoderLinearization`` of those bodies is fitted on the way,
            ``TrainingSet.linearization``, for refinement).
        n: number of bodies (10,000 in the paper); k: coefficients that vary (25).
        rng: seed or Generator; the same seed gives the same set, bit for bit.
        names: measurements to take (default ``mapping_inputs(mset)``: Rupprecht's six on the
            template); mset: their set (default the model's, ``model.measurement_set``).
        sigma_range: half-width of the uniform box in standard deviations (3).
        progress: ``progress(message, fraction)``.
    """
    mset = model.measurement_set if mset is None else mset
    names = mapping_inputs(mset) if names is None else tuple(names)
    z = sample_uniform(model, n, k, sigma_range, rng)
    kk = min(int(k), model.n_components)
    lin = None
    if not model.encoder.is_linear:                      # an exact linearization needs no fit
        lin = DecoderLinearization(kk)
    x, units = measure_coefficients(model, z, names, mset, progress=progress, linearization=lin)
    if lin is not None and not hasattr(lin, "basis_"):
        lin = None                                       # n <= k bodies: not determined
    # A measurement with a condition (stature: upright) is NaN on a body that fails it (a pose
    # of a pose-and-shape model): such bodies are left out, and too many of them refused.
    ok = np.isfinite(x).all(axis=1)
    if not ok.all():
        bad = [n for n, col in zip(names, np.isfinite(x).all(axis=0)) if not col]
        if ok.sum() < max(2, len(x) // 2):
            raise ParameterError(f"training set: {int((~ok).sum())} of {len(x)} bodies drawn from the model have "
                                 f"undefined {', '.join(bad)} (conditions such as 'upright' fail on them); expected "
                                 "a shape model whose bodies stand (build --selection rest)")
        z, x = z[ok], x[ok]
    _refuse_degenerate(names, x, mset, kk, units)
    return TrainingSet(z, x, tuple(names), units, kk, float(sigma_range),
                       rng if isinstance(rng, (int, np.integer)) else None, lin, int((~ok).sum()))


def _landmarks_of(definition: dict) -> list[str]:
    """Landmark names a measurement definition reads (from/to/through), for messages."""
    out = []
    for key in ("from", "to", "through"):
        v = definition.get(key)
        for item in (v if isinstance(v, (list, tuple)) else [v]):
            for name in (item if isinstance(item, (list, tuple)) else [item]):
                if isinstance(name, str) and name not in ("floor",) and name not in out:
                    out.append(name)
    return out


def _refuse_degenerate(names, x: np.ndarray, mset, k: int, units=None) -> None:
    """Refuse an input that has one value on every training body (x: (N, M) cm), or, when the
    ``k`` varying coefficients are at least as many as the inputs, one that is an affine function
    of the others.

    Such an input (two landmarks on one vertex, a slice that always cuts the same ring) cannot be
    asked for, and every mapping would "meet" it with an error of exactly 0, which reads as a
    perfect prediction. ``measure`` checks landmark files on a database's rest scans; this also
    covers sets given in Python and measurements that vary on the scans but not in the model.
    """
    if len(x) < 2:
        return
    by_name = {m["name"]: m for m in mset.measurements}
    for j, n in enumerate(names):
        spread = float(np.ptp(x[:, j]))
        if spread < CONSTANT_CM:
            marks = _landmarks_of(by_name.get(n, {}))
            uses = f" (it uses the landmarks {', '.join(marks)})" if marks else ""
            unit = f" {units[j]}" if units else ""
            raise ParameterError(
                f"mapping input '{n}' of the measurement set {mset.source}: {x[0, j]:.4f}{unit} on every one of the "
                f"{len(x)} bodies drawn from the model (spread {spread:.1e}){uses}; expected a measurement "
                "that changes with the body: a constant one cannot be asked for and its error would read 0. "
                "Check its landmark ids (CLI: bodyspace build --landmarks FILE) or leave it out of the inputs")
    # An input that is an affine function of the others (crotch_height and leg_length, one
    # definition under two names) is one input asked twice: two values for it contradict each
    # other, and an affine mapping's least squares are not determined. With fewer coefficients
    # than inputs the inputs are functions of fewer numbers than they are, and near-affine ones
    # (distances) may depend on each other by construction: only checked when k >= M.
    if len(x) > x.shape[1] + 1 and k >= x.shape[1]:
        for j, n in enumerate(names):
            others = [i for i in range(len(names)) if i != j]
            a = np.c_[x[:, others], np.ones(len(x))]
            r = x[:, j] - a @ np.linalg.lstsq(a, x[:, j], rcond=None)[0]
            if float(np.sqrt(np.mean(r ** 2))) < CONSTANT_CM * max(1.0, float(np.std(x[:, j]))):
                raise ParameterError(
                    f"mapping input '{n}' of the measurement set {mset.source} is an affine function of the other "
                    f"inputs ({', '.join(names[i] for i in others)}) on all {len(x)} bodies drawn from the model: "
                    "it is one input asked twice; expected inputs that each say something of their own: "
                    f"leave '{n}' (or the input it repeats) out of the inputs")


def affine_residuals(coefficients: np.ndarray, measurements: np.ndarray) -> np.ndarray:
    """Rms residual (M,), in the measurements' units, of the least-squares affine fit of each
    measurement (N, M) on the coefficients (N, k); NaN when N <= k + 1 (not determined).

    A measurement with a residual near 0 (below ``AFFINE_CM``) is an affine function of the
    coefficients: with the vertex encoding every body is affine in them, so a straight distance
    whose direction does not change from body to body is one (shoulder_width between mirrored
    landmarks: |v_l - v_r| is the length of a vector that always points sideways). Every mapping
    that predicts the coefficients by an affine least-squares fit on the inputs, the linear one
    and each leaf of the forest (Rupprecht Equations 2 and 3), then returns such an input exactly:
    its fit is the fit of an affine function of the inputs that includes the input itself. Its
    error in ``mapping evaluate`` is 0 by construction and says nothing about the method.
    """
    z = np.asarray(coefficients, float)
    m = np.asarray(measurements, float)
    if len(z) <= z.shape[1] + 1:
        return np.full(m.shape[1], np.nan)
    a = np.c_[z, np.ones(len(z))]
    sol = np.linalg.lstsq(a, m, rcond=None)[0]
    return np.sqrt(np.mean((m - a @ sol) ** 2, axis=0))
