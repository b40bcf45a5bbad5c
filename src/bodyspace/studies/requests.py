"""Random-request study of a ``SemanticModel``: how often does a generated body measure what was asked?

``request_study`` draws ``n`` joint requests (stature, mass and waist girth together), each
variable uniformly inside the 2nd to 98th percentile of the database's *measured* labels
(``SemanticModel.Y_``, one rest scan per subject) and kept when jointly plausible (Mahalanobis
distance within the 98% chi-square quantile of the population's covariance; ``joint=None`` for
independent draws), generates a body for each, and reports the share
that lands within the closed loop's tolerances (4 mm stature, 9 mm girths, 0.5 kg mass) of the
request, the error distribution per variable (50/90/99th percentile and max of ``|reached - asked|``)
and the time per request. A request the model misses counts as a failure (with its message; its error still counts).
Every request also records where it sits in the population (``population_quantile``: the
chi-square quantile of its Mahalanobis distance), so a study of independent draws shows how its
successes split between requests inside and outside the population's joint region, and
``silent_misses`` counts misses that came back without a message saying so (the contract is zero).
``report.semantic_report.write_request_report`` writes it as Markdown and JSON.
"""

from __future__ import annotations

import time
import warnings

import numpy as np

from bodyspace.distributions import chi2_cdf
from bodyspace.errors import BodyspaceError
from bodyspace.semantics.model import tolerance
from bodyspace.units import kind_of
from bodyspace.validation import as_generator

__all__ = ["JOINT_QUANTILE", "REQUEST_LABELS", "population_quantile", "request_study", "si_unit"]

REQUEST_LABELS = ("stature", "mass", "waist_girth")
PERCENTILES = (2.0, 98.0)
ERROR_PERCENTILES = (50, 90, 99)
# Joint plausibility: a request drawn in the per-variable box is kept only when its Mahalanobis
# distance under the population's covariance of the labels is within this chi-square quantile
# (a box corner such as 155 cm, 92 kg, 67 cm waist is no one's body, and no model can make it).
JOINT_QUANTILE = 0.98


def si_unit(name: str) -> str:
    """SI unit of a label's values and errors: "m" (lengths), "kg" (mass) or "1"."""
    return {"length": "m", "mass": "kg"}.get(kind_of(name), "1")


def request_study(semantic_model, n: int = 200, rng=0, labels=REQUEST_LABELS, percentiles=PERCENTILES,
                  joint: float | None = JOINT_QUANTILE, progress=None) -> dict:
    """Generate ``n`` random joint requests inside the population's ``percentiles`` of every
    label in ``labels`` (measured labels of ``semantic_model``) and report how they landed.

    Returns a JSON-ready dict: ``n``, ``labels``, ``box`` (label -> [lo, hi] SI),
    ``tolerances`` (SI), ``successes``, ``success_rate``, ``errors`` (label -> SI unit, tolerance
    and the 50/90/99th percentile, max and mean of the absolute error over the bodies generated,
    SI; ``report.semantic_report.requests_in_display_units`` gives them in mm and kg),
    ``time_s`` (mean/median/p90/max per request, total), ``iterations`` (mean/max),
    ``failures`` (request, reached, message) and ``requests`` (one row per request, SI).

    ``joint``: keep only requests whose Mahalanobis distance to the population's mean (labels'
    covariance) is within the ``joint`` chi-square quantile (rejection sampling, the marginals
    stay inside the box); ``None`` draws every variable independently (box corners included).
    """
    sm = semantic_model
    labels = list(labels)
    bad = [n_ for n_ in labels if n_ not in sm.measured_]
    if bad:
        raise BodyspaceError(f"request_study: {bad} are not measured labels of this model; expected names from "
                             f"{', '.join(sm.measured_)}")
    n = int(n)
    if n < 1:
        raise BodyspaceError(f"request_study: n={n}, expected at least 1 request")
    gen = as_generator(rng)
    box = {}
    for name in labels:
        y = sm.Y_[:, sm.labels_.index(name)]
        y = y[np.isfinite(y)]
        box[name] = [float(np.percentile(y, percentiles[0])), float(np.percentile(y, percentiles[1]))]
    tol = {name: tolerance(name) for name in labels}
    quantile = population_quantile(sm, labels)
    accept = None
    if joint is not None:
        def accept(a):
            return quantile(a) <= joint
    # Misses are kept (clamp mode: a warning, not an exception) so their errors count too.
    mode, sm.on_infeasible = sm.on_infeasible, "clamp"
    try:
        t_all = time.perf_counter()
        rows, failures = _run_requests(sm, n, gen, labels, box, tol, accept, progress)
        total = time.perf_counter() - t_all
    finally:
        sm.on_infeasible = mode
    for row in rows:
        row["population_quantile"] = quantile(row["asked"])
    region = JOINT_QUANTILE if joint is None else joint
    inside = [r for r in rows if r["population_quantile"] <= region]
    outside = [r for r in rows if r["population_quantile"] > region]
    errors = {}
    for name in labels:
        e = np.array([abs(r["error"][name]) for r in rows])
        e = e[np.isfinite(e)]
        errors[name] = {"unit": si_unit(name), "tolerance": tol[name], "bodies": int(e.size),
                        **({f"p{p}": float(np.percentile(e, p)) for p in ERROR_PERCENTILES} if e.size else {}),
                        "max": float(e.max()) if e.size else float("nan"),
                        "mean": float(e.mean()) if e.size else float("nan")}
    times = np.array([r["time_s"] for r in rows])
    its = np.array([r["iterations"] for r in rows if r["iterations"] is not None])
    successes = sum(r["ok"] for r in rows)
    return {
        "n": n, "labels": labels, "percentiles": list(percentiles), "box": box, "joint_quantile": joint, "tolerances": tol,
        "subjects": int(len(sm.Y_)), "components": int(sm.X_.shape[1]),
        "successes": int(successes), "success_rate": successes / n,
        "errors": errors,
        "time_s": {"mean": float(times.mean()), "median": float(np.median(times)),
                   "p90": float(np.percentile(times, 90)), "max": float(times.max()), "total": total},
        "iterations": {"mean": float(its.mean()) if its.size else float("nan"),
                       "max": int(its.max()) if its.size else 0},
        "by_plausibility": {"quantile": region,
                            "inside": {"n": len(inside), "successes": int(sum(r["ok"] for r in inside))},
                            "outside": {"n": len(outside), "successes": int(sum(r["ok"] for r in outside))}},
        "silent_misses": int(sum(1 for f in failures if not f["explained"])),
        "failures": failures,
        "requests": rows,
    }


def population_quantile(semantic_model, labels=REQUEST_LABELS):
    """A function: request dict (label -> SI value) -> chi-square quantile in [0, 1] of its
    Mahalanobis distance under the covariance of ``labels`` over the model's subjects (measured
    labels ``Y_``). 0.98 means "on the edge of the population's 98% joint region"."""
    sm = semantic_model
    labels = list(labels)
    ys = sm.Y_[:, [sm.labels_.index(name) for name in labels]]
    ys = ys[np.isfinite(ys).all(axis=1)]
    mu, icov = ys.mean(axis=0), np.linalg.pinv(np.cov(ys, rowvar=False))

    def quantile(asked: dict) -> float:
        d = np.array([asked[name] for name in labels]) - mu
        return chi2_cdf(float(d @ icov @ d), len(labels))
    return quantile


def _run_requests(sm, n, gen, labels, box, tol, accept, progress):
    rows, failures = [], []
    for i in range(n):
        for _ in range(10000):
            asked = {name: float(gen.uniform(*box[name])) for name in labels}
            if accept is None or accept(asked):
                break
        else:
            raise BodyspaceError("request_study: no request inside the box passed the joint plausibility test")
        seed = int(gen.integers(2 ** 31))
        t = time.perf_counter()
        reached, iterations, message = None, None, ""
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always", RuntimeWarning)
            try:
                r = sm.generate(asked, rng=seed)
                reached = {name: float(r.values[name]) for name in labels}
                iterations = int(r.iterations)
                message = "; ".join(r.messages)
            except BodyspaceError as exc:
                message = str(exc)
        if caught and not message:
            message = "; ".join(str(w.message) for w in caught)
        dt = time.perf_counter() - t
        err = {name: (reached[name] - asked[name]) if reached else float("nan") for name in labels}
        ok = reached is not None and all(abs(err[name]) <= tol[name] for name in labels)
        row = {"asked": asked, "reached": reached, "error": err, "ok": bool(ok), "time_s": dt,
               "iterations": iterations, "seed": seed}
        rows.append(row)
        if not ok:
            # "explained": the caller was told (refusal, clamp warning or "not met" report).
            failures.append({"index": i, "asked": asked, "reached": reached, "explained": bool(message),
                             "message": message or "outside tolerance, with no message (a silent miss)"})
        if progress:
            progress(f"request {i + 1}/{n}", (i + 1) / n)
    return rows, failures
