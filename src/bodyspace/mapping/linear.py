"""The linear semantic mapping of the related work: one affine map ``y = A x + b`` over all data.

Allen et al. (2003), Hasler et al. (2009) and MovieReshape (Jain et al. 2010) map semantic
measurements to PCA coefficients with a single linear regression over the whole shape space;
(Rupprecht §2, Rupprecht Table 2) use it as the baseline their regression forest beats. It is
also the leaf model of that forest (Rupprecht Equations 2 and 3), so the least-squares solve lives here, once,
as the pure function ``fit_affine`` that both estimators call.

Shapes: ``X`` (N, n) measurements, ``Y`` (N, m) coefficients, ``A`` (m, n), ``b`` (m,).
"""

from __future__ import annotations


import numpy as np

from bodyspace.errors import ParameterError
from bodyspace.validation import as_nonnegative_float, as_samples, as_targets, check_state_arrays

FORMAT_VERSION = 1


# ---------------------------------------------------------------------- Rupprecht Equation 3
def fit_affine(X: np.ndarray, Y: np.ndarray, ridge: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares affine map (Rupprecht Equation 3): ``argmin sum ||A x + b - y||^2``.

    Args:
        X: (N, n) inputs, Y: (N, m) outputs.
        ridge: Tikhonov weight on ``A`` (never on ``b``), relative to the mean variance of the
            inputs after each is scaled to unit variance: the penalty is
            ``ridge * N * ||A D||_F^2`` with ``D`` the input standard deviations. Being relative,
            it means the same in cm or m and in a 30-sample leaf or the whole data set; it keeps
            the normal equations invertible when an input is constant or two are collinear.

    Returns:
        A (m, n), b (m,), in the units of X and Y.

    The solve is on centred, standardized inputs (so ``b`` is free and cm-scale offsets do not
    cost digits) through the normal equations: n is small (6 measurements), and the Gram matrix
    is what the forest's split search accumulates anyway.
    """
    x_mean = X.mean(axis=0)
    y_mean = Y.mean(axis=0)
    scale = X.std(axis=0)
    scale[scale == 0] = 1.0               # a constant input gets slope 0 from the ridge, not a NaN
    xs = (X - x_mean) / scale
    gram = xs.T @ xs
    cross = xs.T @ (Y - y_mean)
    a_std = solve_ridge(gram[None], cross[None], ridge)[0]       # (n, m) in standardized inputs
    A = (a_std / scale[:, None]).T
    b = y_mean - A @ x_mean
    return A, b


def solve_ridge(gram: np.ndarray, cross: np.ndarray, ridge: float, return_lambda: bool = False):
    """Batched ridge normal equations ``(G + lambda I) W = C`` for centred statistics.

    ``gram`` (B, n, n) and ``cross`` (B, n, m) are sums over the samples of centred ``x x^T``
    and ``x y^T``. ``lambda = (ridge + 1e-12) * trace(G) / n`` (``ridge`` times N times the mean
    input variance; the 1e-12 floor keeps ``ridge=0`` solvable for collinear inputs, and an
    all-constant node gets ``lambda = 1``, i.e. slopes 0). Returns W (B, n, m), and lambda (B,)
    if asked.
    """
    n = gram.shape[-1]
    scale = np.trace(gram, axis1=-2, axis2=-1) / n                       # N * mean variance
    lam = np.where(scale > 0, (ridge + 1e-12) * scale, 1.0)
    g = gram + lam[:, None, None] * np.eye(n)
    try:
        # inv-then-multiply: 2x faster than batched solve for these 6x6 systems with 25 right-hand
        # sides (measured), and accurate here since g is symmetric positive definite and regularized.
        w = np.linalg.inv(g) @ cross
    except np.linalg.LinAlgError:
        # Only reachable for degenerate statistics (e.g. overflow): the minimum-norm solution.
        w = np.stack([np.linalg.lstsq(gi, ci, rcond=None)[0] for gi, ci in zip(g, cross)])
    return (w, lam) if return_lambda else w


# ---------------------------------------------------------------------- estimator
class LinearMapping:
    """One affine map ``y = A x + b`` from measurements to shape coefficients, over all data.

    The baseline of Rupprecht Table 2, after Allen et al. (2003) and Hasler et al.
    (2009); same interface as ``LinearLeafForest``.

    Args:
        ridge: Tikhonov weight on ``A`` relative to the inputs' variance (see ``fit_affine``);
            the small default only guards against collinear measurements.

    Attributes (after ``fit``):
        coef_: (m, n) the matrix A.
        intercept_: (m,) the vector b.
        n_features_in_, n_outputs_: ints.
    """

    def __init__(self, ridge: float = 1e-6):
        self.ridge = ridge

    def fit(self, X, Y) -> "LinearMapping":
        """Fit on measurements X (N, n) and coefficients Y (N, m) or (N,)."""
        ridge = as_nonnegative_float(self.ridge, "ridge")
        x, _ = as_samples(X)
        y, one_d = as_targets(Y, x.shape[0])
        if x.shape[0] < 2:
            raise ParameterError(f"X: {x.shape[0]} sample(s), expected at least 2 to fit A x + b")
        self.coef_, self.intercept_ = fit_affine(x, y, ridge)
        self.n_features_in_, self.n_outputs_ = x.shape[1], y.shape[1]
        self._y_1d = one_d
        return self

    def predict(self, X) -> np.ndarray:
        """Coefficients (N, m) of measurements (N, n); a single sample (n,) gives (m,)."""
        self._require_fit()
        x, single = as_samples(X, self.n_features_in_)
        y = x @ self.coef_.T + self.intercept_
        if self._y_1d:
            y = y[:, 0]
        return y[0] if single else y

    def _require_fit(self):
        if not hasattr(self, "coef_"):
            raise ParameterError("LinearMapping is not fitted; call fit(X, Y) first")

    # ------------------------------------------------------------------ serialization
    def to_arrays(self) -> dict[str, np.ndarray]:
        """Flat arrays for an ``np.savez`` loadable with ``allow_pickle=False`` (no object arrays)."""
        self._require_fit()
        return {
            "kind": np.array("LinearMapping"),
            "format_version": np.array(FORMAT_VERSION),
            "ridge": np.array(float(self.ridge)),
            "y_1d": np.array(self._y_1d),
            "coef": self.coef_.copy(),
            "intercept": self.intercept_.copy(),
        }

    @classmethod
    def from_arrays(cls, arrays) -> "LinearMapping":
        """Inverse of ``to_arrays`` (accepts the dict or an opened ``NpzFile``)."""
        check_state_arrays(arrays, "LinearMapping", ("ridge", "y_1d", "coef", "intercept"), FORMAT_VERSION)
        coef = np.asarray(arrays["coef"], dtype=np.float64)
        intercept = np.asarray(arrays["intercept"], dtype=np.float64)
        if coef.ndim != 2 or intercept.shape != (coef.shape[0],):
            raise ParameterError(f"arrays['coef'], ['intercept']: shapes {coef.shape}, {intercept.shape}, "
                                 "expected (m, n) and (m,)")
        self = cls(ridge=float(np.asarray(arrays["ridge"])))
        self.coef_, self.intercept_ = coef, intercept
        self.n_outputs_, self.n_features_in_ = coef.shape
        self._y_1d = bool(np.asarray(arrays["y_1d"]))
        return self
