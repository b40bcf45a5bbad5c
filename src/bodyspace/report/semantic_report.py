"""Markdown and JSON of a random-request study (``studies.requests.request_study``).

``format_request_report`` lays the study out (share within tolerance, errors per variable,
inside and outside the population, time per request, failures); ``write_request_report``
writes it as ``requests.md`` and ``requests.json``. The study's errors are SI; both show them
as ``requests_in_display_units`` does (mm for lengths, kg).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from bodyspace.atomic import atomic_path, write_json
from bodyspace.units import kind_of

__all__ = ["format_request_report", "requests_in_display_units", "write_request_report"]


def error_unit(name: str) -> tuple[str, float]:
    """Display unit of the *errors* of a label and the factor from SI."""
    kind = kind_of(name)
    if kind == "length":
        return "mm", 1000.0
    if kind == "mass":
        return "kg", 1.0
    return "1", 1.0


def _value_unit(name: str) -> tuple[str, float]:
    return ("cm", 100.0) if kind_of(name) == "length" else error_unit(name)


def _ordinal(p: float) -> str:
    k = int(p) if float(p).is_integer() else None
    if k is None:
        return f"{p:g}th"
    suffix = "th" if 10 <= k % 100 <= 20 else {1: "st", 2: "nd", 3: "rd"}.get(k % 10, "th")
    return f"{k}{suffix}"


def requests_in_display_units(study: dict) -> dict:
    """A copy of ``request_study``'s result whose ``errors`` are in display units (mm for
    lengths, kg for mass: ``unit`` says which); every other field as it is (SI)."""
    errors = {}
    for name, e in study["errors"].items():
        unit, f = error_unit(name)
        errors[name] = {k: (unit if k == "unit" else v if k == "bodies" else v * f) for k, v in e.items()}
    return {**study, "errors": errors}


def format_request_report(study: dict) -> str:
    """Markdown of a ``request_study`` result (errors in SI, as the study returns them)."""
    study = requests_in_display_units(study)
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
    write_json(out / f"{stem}.json", _finite(requests_in_display_units(study)))
    return {"md": f"{stem}.md", "json": f"{stem}.json"}
