"""The three distribution functions the library needs, from ``scipy.special``.

``scipy.stats`` builds every one of its ~120 distributions when imported (0.5 s on a quiet
machine, paid by every command that loads a shape space); these are the same computations
``scipy.stats`` runs for ``norm.ppf``, ``chi2.cdf`` and ``truncnorm.rvs``, on the same special
functions, so the numbers are the same to the bit (tests/test_distributions.py compares them).
"""

from __future__ import annotations

import numpy as np
from scipy.special import chdtr, log1p, log_ndtr, logsumexp, ndtr, ndtri, ndtri_exp

from bodyspace.validation import as_generator


def norm_ppf(q) -> np.ndarray:
    """Standard normal quantiles of probabilities ``q`` (any shape, same shape back):
    ``scipy.stats.norm.ppf``. 0 -> -inf, 1 -> +inf."""
    return ndtri(np.asarray(q, dtype=float))


def chi2_cdf(x: float, df: float) -> float:
    """The chi-square distribution function with ``df`` degrees of freedom at ``x``:
    ``scipy.stats.chi2.cdf`` (0 for ``x <= 0``, NaN for NaN)."""
    x = float(x)
    if np.isnan(x):
        return float("nan")
    return float(chdtr(float(df), x)) if x > 0 else 0.0


def _log_gauss_mass(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """log P(a < Z < b) of a standard normal Z, elementwise over (M,) arrays; computed as
    ``scipy.stats`` does (left tail, right tail by symmetry, or the central case without the
    cancellation of 1 - tails)."""
    left, right = b <= 0, a > 0
    central = ~(left | right)
    out = np.full_like(a, fill_value=np.nan, dtype=np.complex128)

    def mass_left(a, b):  # log(Phi(b) - Phi(a)) = logsumexp(log Phi(b), log Phi(a) + i*pi)
        return logsumexp([log_ndtr(b), log_ndtr(a) + np.pi * 1j], axis=0)

    if a[left].size:
        out[left] = mass_left(a[left], b[left])
    if a[right].size:
        out[right] = mass_left(-b[right], -a[right])
    if a[central].size:
        out[central] = log1p(-ndtr(a[central]) - ndtr(-b[central]))
    return np.real(out)


def truncnorm_rvs(lo: float, hi: float, size: tuple[int, ...], rng=None) -> np.ndarray:
    """Standard normal draws truncated to [lo, hi] (``size`` shape; lo < hi, either may be
    infinite): ``scipy.stats.truncnorm.rvs(lo, hi, size=size, random_state=rng)``, the same
    numbers for the same generator state. One uniform per draw, through the truncated
    distribution's quantile function computed in log space (accurate far in a tail)."""
    rng = as_generator(rng)
    q = rng.uniform(size=size)
    q, a, b = np.broadcast_arrays(q, float(lo), float(hi))
    out = np.empty_like(q)
    left = a < 0
    right = ~left
    if left.any():  # from the left end: Phi(x) = Phi(a) + q * mass
        ql, al, bl = q[left], a[left], b[left]
        out[left] = ndtri_exp(logsumexp([log_ndtr(al), np.log(ql) + _log_gauss_mass(al, bl)], axis=0))
    if right.any():  # from the right end, by symmetry: Phi(-x) = Phi(-b) + (1 - q) * mass
        qr, ar, br = q[right], a[right], b[right]
        out[right] = -ndtri_exp(logsumexp([log_ndtr(-br), np.log1p(-qr) + _log_gauss_mass(ar, br)], axis=0))
    return out
