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
``write_request_report`` writes it as Markdown and JSON.
"""

from __future__ import annotations

import time
import warnings
from pathlib import Path

import numpy as np

from bodyspace.atomic import atomic_path, write_json
from bodyspace.errors import BodyspaceError
from bodyspace.semantics.model import tolerance
from bodyspace.units import kind_of

__all__ = ["REQUEST_LABELS", "request_study", "population_quantile", "format_request_report", "write_request_report"]

REQUEST_LABELS = ("stature", "mass", "waist_girth")
PERCENTILES = (2.0, 98.0)
ERROR_PERCENTILES = (50, 90, 99)
# Joint plausibility: a request drawn in the per-variable box is kept only when its Mahalanobis
# distance under the population's covariance of the labels is within this chi-square quantile
# (a box corner such as 155 cm, 92 kg, 67 cm waist is no one's body, and no model can make it).
JOINT_QUANTILE = 0.98


def _unit(name: str) -> tuple[str, float]:
    """Display unit of the *errors* of a label and the factor from SI."""
    kind = kind_of(name)
    if kind == "length":
        return "mm", 1000.0
    if kind == "mass":
        return "kg", 1.0
    return "1", 1.0


def _value_unit(name: str) -> tuple[str, float]:
    return ("cm", 100.0) if kind_of(name) == "length" else _unit(name)


def request_study(semantic_model, n: int = 200, rng=0, labels=REQUEST_LABELS, percentiles=PERCENTILES,
                  joint: float | None = JOINT_QUANTILE, progress=None) -> dict:
    """Generate ``n`` random joint requests inside the population's ``percentiles`` of every
    label in ``labels`` (measured labels of ``semantic_model``) and report how they landed.

    Returns a JSON-ready dict: ``n``, ``labels``, ``box`` (label -> [lo, hi] SI),
    ``tolerances`` (SI), ``successes``, ``success_rate``, ``errors`` (label -> unit and the
    50/90/99th percentile, max and mean of the absolute error, over the bodies generated),
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
    gen = np.random.default_rng(rng)
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
        unit, f = _unit(name)
        e = np.array([abs(r["error"][name]) for r in rows]) * f
        e = e[np.isfinite(e)]
        errors[name] = {"unit": unit, "tolerance": tol[name] * f, "bodies": int(e.size),
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
    from scipy.stats import chi2

    sm = semantic_model
    labels = list(labels)
    ys = sm.Y_[:, [sm.labels_.index(name) for name in labels]]
    ys = ys[np.isfinite(ys).all(axis=1)]
    mu, icov = ys.mean(axis=0), np.linalg.pinv(np.cov(ys, rowvar=False))

    def quantile(asked: dict) -> float:
        d = np.array([asked[name] for name in labels]) - mu
        return float(chi2.cdf(float(d @ icov @ d), len(labels)))
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


def _ordinal(p: float) -> str:
    k = int(p) if float(p).is_integer() else None
    if k is None:
        return f"{p:g}th"
    suffix = "th" if 10 <= k % 100 <= 20 else {1: "st", 2: "nd", 3: "rd"}.get(k % 10, "th")
    return f"{k}{suffix}"


def format_request_report(study: dict) -> str:
    """Markdown of a ``request_study`` result."""
    lines = [f"# Random requests: {study['n']} bodies asked for {', '.join(study['labels'])} together", ""]
    box = ", ".join(f"{n} {study['box'][n][0] * _value_unit(n)[1]:.1f} to {study['box'][n][1] * _value_unit(n)[1]:.1f} "
                    f"{_value_unit(n)[0]}" for n in study["labels"])
    lines += [f"Each variable drawn uniformly inside the population's {_ordinal(study['percentiles'][0])} to "
              f"{_ordinal(study['percentiles'][1])} percentile ({study['subjects']} subjects, measured on their rest "
              f"scans): {box}" + (f"; kept only when jointly plausible (Mahalanobis distance under the population's "
                                f"covariance within its {100 * study['joint_quantile']:g}% chi-square quantile)"
                                if study.get("joint_quantile") is not None else "; independently") +
              f". Model: {study['components']} components.", "",
              f"**{study['successes']}/{study['n']} ({100 * study['success_rate']:.1f}%) within every tolerance** "
              f"(4 mm stature, 9 mm girths, 0.5 kg mass).", "",
              "## |reached − asked| per variable", "",
              "| variable | unit | tolerance | p50 | p90 | p99 | max | mean |", "|---|---|---:|---:|---:|---:|---:|---:|"]
    for n in study["labels"]:
        e = study["errors"][n]
        cells = [f"{e.get(k, float('nan')):.2f}" for k in ("p50", "p90", "p99", "max", "mean")]
        lines.append(f"| {n} | {e['unit']} | {e['tolerance']:.1f} | " + " | ".join(cells) + " |")
    split = study.get("by_plausibility")
    if split and study.get("joint_quantile") is None:
        q = 100 * split["quantile"]
        lines += ["", "## Inside and outside the population", "",
                  "| requests | n | within tolerance |", "|---|---:|---:|",
                  f"| inside the population's {q:g}% joint region | {split['inside']['n']} | "
                  f"{split['inside']['successes']} |",
                  f"| outside it (combinations few or no subjects have) | {split['outside']['n']} | "
                  f"{split['outside']['successes']} |", "",
                  f"Misses returned without a message saying so: {study['silent_misses']}."]
    t, it = study["time_s"], study["iterations"]
    lines += ["", f"Time per request: mean {t['mean']:.2f} s, median {t['median']:.2f} s, p90 {t['p90']:.2f} s, "
              f"max {t['max']:.2f} s (total {t['total']:.1f} s). Closed-loop corrections: mean {it['mean']:.1f}, "
              f"max {it['max']}.", ""]
    if study["failures"]:
        lines += ["## Failures", ""]
        for f in study["failures"]:
            asked = ", ".join(f"{n} {f['asked'][n] * _value_unit(n)[1]:.1f} {_value_unit(n)[0]}" for n in study["labels"])
            lines.append(f"- #{f['index']}: {asked}: {f['message']}")
        lines.append("")
    return "\n".join(lines)


def _finite(obj):
    """JSON-safe copy: NaN/inf -> None."""
    if isinstance(obj, dict):
        return {k: _finite(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_finite(v) for v in obj]
    if isinstance(obj, float) and not np.isfinite(obj):
        return None
    return obj


def write_request_report(study: dict, out, stem: str = "requests") -> dict:
    """Write ``{stem}.md`` and ``{stem}.json`` into folder ``out``; returns their file names."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    with atomic_path(out / f"{stem}.md") as tmp:
        tmp.write_text(format_request_report(study))
    write_json(out / f"{stem}.json", _finite(study))
    return {"md": f"{stem}.md", "json": f"{stem}.json"}
