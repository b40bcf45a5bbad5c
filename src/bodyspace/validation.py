"""Array and argument checks every layer uses: validate once at the door, then trust the data.

Each function takes the user's value and the name the user knows it by (``name``), and either
returns it in the one form the code below works with (finite float64 arrays of a stated shape,
plain ints and floats) or raises a ``bodyspace.errors`` class whose message names the field,
what was found and what was expected.

Domain checks stay with their domain: a mesh's faces and topology in ``mesh/``, a measurement
set in ``measure/``, a scan database in ``data/``. This module knows only numbers and shapes.

Base layer: imports nothing of bodyspace but ``errors``.
"""

from __future__ import annotations

import numbers

import numpy as np

from bodyspace.errors import BodyspaceError, ParameterError

__all__ = ["as_matrix", "as_vector", "as_int", "as_positive_grid", "as_samples", "as_targets",
           "as_nonnegative_float", "as_codes", "check_state_arrays", "check_rng", "as_generator", "as_seed"]


def as_matrix(X, name: str = "X", n_features: int | None = None, min_rows: int = 1,
              allow_vector: bool = False) -> np.ndarray:
    """``X`` as a finite float (N, D) array; a (D,) vector becomes (1, D) if ``allow_vector``.

    Raises ``ParameterError`` on anything not numeric, not 2-D, with fewer than ``min_rows``
    rows, no column, a row length other than ``n_features`` (when given), or NaN/infinity.
    """
    try:
        x = np.asarray(X, dtype=float)
    except (TypeError, ValueError) as exc:
        raise ParameterError(f"{name}: could not be read as numbers ({exc}); expected a float array (N, D)") from None
    if x.ndim == 1 and allow_vector:
        x = x[None]
    if x.ndim != 2:
        raise ParameterError(f"{name}: shape {x.shape}, expected a 2-D array (N, D)")
    if x.shape[0] < min_rows:
        raise ParameterError(f"{name}: {x.shape[0]} row(s), expected at least {min_rows}")
    if x.shape[1] < 1:
        raise ParameterError(f"{name}: shape {x.shape}, expected at least one column")
    if n_features is not None and x.shape[1] != n_features:
        raise ParameterError(f"{name}: rows have length {x.shape[1]}, expected {n_features} "
                             "(the length the model was fitted on)")
    if not np.isfinite(x).all():
        raise ParameterError(f"{name}: contains NaN or infinity, expected finite values")
    return x


def as_vector(y, name: str, n: int | None = None) -> np.ndarray:
    """``y`` as a finite float (n,) array (``ParameterError`` otherwise)."""
    try:
        v = np.asarray(y, dtype=float)
    except (TypeError, ValueError) as exc:
        raise ParameterError(f"{name}: could not be read as numbers ({exc}); expected a float array") from None
    if v.ndim != 1:
        raise ParameterError(f"{name}: shape {v.shape}, expected a 1-D array" + (f" ({n},)" if n else ""))
    if n is not None and v.shape[0] != n:
        raise ParameterError(f"{name}: length {v.shape[0]}, expected {n} (one value per row of X)")
    if not np.isfinite(v).all():
        raise ParameterError(f"{name}: contains NaN or infinity, expected finite values")
    return v


def as_int(value, name: str, lo: int, hi: int | None = None) -> int:
    """``value`` as an int in ``[lo, hi]`` (``hi`` None: no upper bound); a bool is refused."""
    if isinstance(value, bool) or not isinstance(value, numbers.Integral) or value < lo \
            or (hi is not None and value > hi):
        bounds = f"{lo}..{hi}" if hi is not None else f">= {lo}"
        raise ParameterError(f"{name}={value!r}, expected an integer {bounds}")
    return int(value)


def as_positive_grid(value, name: str) -> np.ndarray:
    """A positive number or a non-empty sequence of them as a float (K,) array."""
    try:
        grid = np.atleast_1d(np.asarray(value, dtype=float))
    except (TypeError, ValueError):
        grid = np.empty(0)
    if grid.ndim != 1 or grid.size == 0 or not np.isfinite(grid).all() or (grid <= 0).any():
        raise ParameterError(f"{name}={value!r}, expected a positive number or a non-empty sequence of them")
    return grid


def as_nonnegative_float(value, name: str) -> float:
    """A finite real number >= 0 as a float (a bool is refused)."""
    if isinstance(value, bool) or not isinstance(value, numbers.Real) or not np.isfinite(value) or value < 0:
        raise ParameterError(f"{name}={value!r}, expected a finite number >= 0")
    return float(value)


def as_samples(X, n_features: int | None = None, name: str = "X") -> tuple[np.ndarray, bool]:
    """Estimator inputs ``X`` as float64 (N, n), and whether it was a single 1-D sample.

    A 1-D ``X`` is one sample only when the estimator is fitted (``n_features`` known); in
    ``fit`` a 2-D array is required so a column vector is never mistaken for a row.
    """
    x = np.asarray(X)
    single = False
    if x.ndim == 1 and n_features is not None:
        x, single = x[None, :], True
    if x.ndim != 2:
        expected = f"(N, {n_features})" if n_features is not None else "(N, n_features)"
        raise ParameterError(f"{name}: shape {x.shape}, expected a 2-D array {expected}")
    if not (np.issubdtype(x.dtype, np.number) or x.dtype == bool):
        raise ParameterError(f"{name}: dtype {x.dtype}, expected numbers")
    if x.shape[1] == 0:
        raise ParameterError(f"{name}: shape {x.shape}, expected at least one feature column")
    if n_features is not None and x.shape[1] != n_features:
        raise ParameterError(f"{name}: {x.shape[1]} features per sample, expected {n_features} "
                             "(the number the estimator was fitted on)")
    return _finite_float64(x, name), single


def as_targets(Y, n_samples: int, name: str = "Y") -> tuple[np.ndarray, bool]:
    """Estimator outputs ``Y`` as float64 (N, m), and whether it was given 1-D (one output)."""
    y = np.asarray(Y)
    one_d = y.ndim == 1
    if one_d:
        y = y[:, None]
    if y.ndim != 2:
        raise ParameterError(f"{name}: shape {y.shape}, expected (N, n_outputs) or (N,)")
    if not (np.issubdtype(y.dtype, np.number) or y.dtype == bool):
        raise ParameterError(f"{name}: dtype {y.dtype}, expected numbers")
    if y.shape[0] != n_samples:
        raise ParameterError(f"{name}: {y.shape[0]} rows, expected {n_samples} (one per row of X)")
    if y.shape[1] < 1:
        raise ParameterError(f"{name}: shape {y.shape}, expected at least one output column")
    return _finite_float64(y, name), one_d


def _finite_float64(a: np.ndarray, name: str) -> np.ndarray:
    """A 2-D numeric array as float64; refuses NaN or infinity, naming the first place."""
    a = a.astype(np.float64, copy=False)
    if not np.isfinite(a).all():
        bad = np.argwhere(~np.isfinite(a))[0]
        raise ParameterError(f"{name}: contains NaN or infinity (first at row {bad[0]}, column {bad[1]}), "
                             "expected finite numbers")
    return a


def as_codes(codes, n_features: int, description: str, error: type[BodyspaceError] = ParameterError,
             name: str = "codes") -> np.ndarray:
    """Codes (D,) or (N, D) as finite float (N, D), ``D = n_features``.

    ``description`` says what a code is, for the message ("relative rotation encoding of this
    template (...)"); ``error`` is the class raised, so each layer keeps its own.
    """
    c = np.asarray(codes)
    if c.ndim == 1:
        c = c[None]
    if c.ndim != 2 or c.shape[1] != n_features:
        raise error(f"{name}: shape {np.shape(codes)}, expected ({n_features},) or (N, {n_features}) for the "
                    f"{description}")
    if not np.issubdtype(c.dtype, np.number):
        raise error(f"{name}: dtype {c.dtype}, expected floating-point numbers")
    c = c.astype(float, copy=False)
    if not np.isfinite(c).all():
        n, j = np.argwhere(~np.isfinite(c))[0]
        raise error(f"{name}: code {n} has NaN or infinity at entry {j}; expected finite values")
    return c


def check_state_arrays(arrays, kind: str, keys: tuple[str, ...], format_version: int) -> None:
    """``from_arrays`` input: a mapping holding ``keys``, written by ``kind.to_arrays``, with a
    ``format_version`` no newer than ``format_version``."""
    if "kind" not in arrays or str(np.asarray(arrays["kind"])) != kind:
        found = str(np.asarray(arrays["kind"])) if "kind" in arrays else "no 'kind' key"
        raise ParameterError(f"arrays['kind']: {found!r}, expected {kind!r} (the dict written by {kind}.to_arrays())")
    missing = [k for k in ("format_version", *keys) if k not in arrays]
    if missing:
        raise ParameterError(f"arrays: missing {missing}, expected the dict written by {kind}.to_arrays()")
    try:
        version = int(np.asarray(arrays["format_version"]))
    except (TypeError, ValueError):
        raise ParameterError(f"arrays['format_version']: {arrays['format_version']!r}, expected an integer") from None
    if version > format_version:
        raise ParameterError(f"arrays['format_version']: {version}, expected <= {format_version} "
                             "(written by a newer bodyspace)")


# ---------------------------------------------------------------------- randomness
def check_rng(rng, name: str = "rng"):
    """``rng`` unchanged if it is what every random function of bodyspace takes: a
    ``numpy.random.Generator``, a ``SeedSequence``, an integer seed >= 0, or None (fresh entropy)."""
    if rng is None or isinstance(rng, (np.random.Generator, np.random.SeedSequence, np.random.BitGenerator)):
        return rng
    if isinstance(rng, numbers.Integral) and not isinstance(rng, bool) and rng >= 0:
        return rng
    raise ParameterError(f"{name}={rng!r}, expected an integer seed >= 0, a numpy Generator or None")


def as_generator(rng, name: str = "rng") -> np.random.Generator:
    """``np.random.default_rng(rng)`` after ``check_rng``: a Generator passes through unchanged
    (the caller's stream advances), a seed gives the same numbers every time."""
    return np.random.default_rng(check_rng(rng, name))


def as_seed(rng, name: str = "rng") -> int:
    """An integer seed from ``rng``: an int passes unchanged (so ``seed + 1`` derivations and the
    recorded seed stay as they were), a Generator gives one draw (advancing it), None a fresh one."""
    rng = check_rng(rng, name)
    if isinstance(rng, numbers.Integral):
        return int(rng)
    return int(np.random.default_rng(rng).integers(2 ** 31))
