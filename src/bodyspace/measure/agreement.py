"""A measuring method against a reference, as ISO 20685-1 evaluates it.

ISO 20685-1:2018 (3-D scanning methodologies) accepts a method for a measurement over a sample
of subjects, not subject by subject: each subject's error (the method's value minus the
reference's, e.g. scan-derived minus tape), their mean and its 95 % confidence interval
mean ± 1.96 · SD / √N; the method is accepted for that measurement when the whole interval lies
within ± the maximum allowable error of its category (``tolerances``). A method may so be
unbiased but noisy (a wide interval around 0: too few subjects to tell) or precise but biased
(a narrow interval beside 0): both are refused, with the reason.

Used by benchmarks/study_iso.py on registered test scans; a lab validating its own scans against
tape measurements calls ``agreement`` with its errors.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from bodyspace.errors import ParameterError
from bodyspace.measure.tolerances import ALLOWABLE_ERROR

__all__ = ["Agreement", "agreement", "format_agreement", "Z95"]

Z95 = 1.96


@dataclass(frozen=True)
class Agreement:
    """One measurement's verdict.

    n: subjects measured (the errors that are not NaN); mean, sd: their mean and sample standard
    deviation (ddof 1), metres (a share of the reference when ``relative``); ci_low, ci_high:
    mean ∓ 1.96 sd / √n; allowable: the category's maximum allowable error (same unit);
    accepted: the whole interval within ± allowable (False with fewer than 2 subjects: no
    interval).
    """

    name: str
    category: str
    n: int
    mean: float
    sd: float
    ci_low: float
    ci_high: float
    allowable: float
    relative: bool
    accepted: bool

    @property
    def reason(self) -> str:
        """Why it is refused ("" if accepted): too few subjects, a bias, or a spread."""
        if self.accepted:
            return ""
        if self.n < 2:
            return f"{self.n} subject(s), an interval needs 2"
        if self.ci_low > self.allowable or self.ci_high < -self.allowable:
            return "biased: the whole interval lies beyond the allowable error"
        if self.ci_low > 0 or self.ci_high < 0:
            return "biased: the interval excludes 0 and reaches past the allowable error"
        return "spread: the interval holds 0 but reaches past the allowable error (scattered, or too few subjects)"


def agreement(errors, names, categories, *, reference=None) -> list[Agreement]:
    """Per measurement, the ISO 20685-1 verdict on ``errors`` (module docstring).

    errors: (N, M) of N subjects × M measurements, the method minus the reference, SI (metres;
    NaN where a subject lacks the measurement); names: (M,) names; categories: (M,) categories of
    ``tolerances.ALLOWABLE_ERROR`` (``tolerances.iso_categories``). reference: (N, M) reference
    values, needed for the categories held to a share of the value (volume, mass, ...): their
    errors are divided by it. Returns M ``Agreement``s in the given order.
    """
    e = np.asarray(errors, dtype=float)
    if e.ndim != 2:
        raise ParameterError(f"errors: shape {e.shape}; expected (subjects, measurements)")
    names, categories = list(names), list(categories)
    if len(names) != e.shape[1] or len(categories) != e.shape[1]:
        raise ParameterError(f"errors have {e.shape[1]} measurement columns, names {len(names)}, categories "
                             f"{len(categories)}; expected one name and one category per column")
    unknown = sorted({c for c in categories if c not in ALLOWABLE_ERROR})
    if unknown:
        raise ParameterError(f"categories: unknown {', '.join(map(repr, unknown))}; expected one of "
                             f"{', '.join(ALLOWABLE_ERROR)}")
    ref = None if reference is None else np.asarray(reference, dtype=float)
    if ref is not None and ref.shape != e.shape:
        raise ParameterError(f"reference: shape {ref.shape}; expected the errors' {e.shape}")
    out = []
    for j, (name, cat) in enumerate(zip(names, categories)):
        allowable, relative = ALLOWABLE_ERROR[cat]
        col = e[:, j]
        if relative:
            if ref is None:
                raise ParameterError(f"{name}: its category ({cat}) is held to {allowable:.0%} of the value; give "
                                     "the reference values (reference=) to divide its errors by")
            col = col / np.abs(ref[:, j])
        col = col[np.isfinite(col)]
        n = len(col)
        mean = float(col.mean()) if n else float("nan")
        sd = float(col.std(ddof=1)) if n >= 2 else float("nan")
        half = Z95 * sd / np.sqrt(n) if n >= 2 else float("nan")
        low, high = mean - half, mean + half
        accepted = bool(n >= 2 and -allowable <= low and high <= allowable)
        out.append(Agreement(name, cat, n, mean, sd, low, high, allowable, relative, accepted))
    return out


def format_agreement(rows: list[Agreement], length_unit: str = "mm") -> str:
    """The verdicts as a text table: lengths in ``length_unit`` ("mm" or "cm"), the relative ones in %."""
    scale = {"mm": 1000.0, "cm": 100.0}[length_unit]
    digits = 1 if length_unit == "mm" else 2
    lines = [f"{'measurement':<20} {'category':<20} {'N':>3} {'mean':>7} {'SD':>6} {'95% CI':>17} "
             f"{'allowed':>8}  verdict"]
    for r in rows:
        s, u, d = (100.0, "%", 1) if r.relative else (scale, length_unit, digits)
        ci = f"[{r.ci_low * s:+.{d}f}, {r.ci_high * s:+.{d}f}]"
        lines.append(f"{r.name:<20} {r.category:<20} {r.n:>3} {r.mean * s:>+7.{d}f} {r.sd * s:>6.{d}f} {ci:>17} "
                     f"{'±' + format(r.allowable * s, 'g') + ' ' + u:>8}  "
                     f"{'accepted' if r.accepted else 'REJECTED (' + r.reason + ')'}")
    acc = sum(r.accepted for r in rows)
    lines.append(f"accepted for {acc} of {len(rows)} measurements")
    return "\n".join(lines)
