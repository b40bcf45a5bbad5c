"""PCA shape space over encoded bodies (Hasler et al. 2009, Sec. 4; Rupprecht et al., Eq. 1).

A body's code is ``mean_ + coefficients @ components_``. With the relative rotation encoding
the space holds pose and shape together when fitted on the whole database, or shape alone
when fitted on a selection (the rest-pose scans). With the vertex encoding it is Rupprecht's
model ``M = M_mean + sum_i alpha_i a_i``.

Estimator in the scikit-learn style: hyper-parameters in ``__init__``, ``fit`` returns self,
learned state ends in ``_``. The PCA is a thin SVD of the centred codes (numpy only; the
project does not depend on scikit-learn), with scikit-learn's sign convention so results
match ``sklearn.decomposition.PCA``.
"""

from __future__ import annotations

import numbers

import numpy as np
from scipy.stats import truncnorm

from bodyspace.errors import ParameterError


def _rng(rng) -> np.random.Generator:
    return np.random.default_rng(rng)


class ShapeSpace:
    """Principal component analysis of encoded bodies, with sampling and reconstruction.

    Args:
        encoder: a fitted ``RelativeRotationEncoder`` or ``VertexEncoder`` (anything with
            ``encode``/``decode``/``n_features_``), needed for the mesh-level methods
            (``fit`` on meshes, ``project``, ``reconstruct``, ``sample``); None for codes only.
        n_components: None keeps every component with variance (``min(N - 1, D)``); an int
            keeps that many; a float in (0, 1) keeps the fewest that explain that fraction of
            the variance.

    Attributes (after ``fit``):
        mean_: (D,) mean code.
        components_: (K, D) orthonormal principal directions, by decreasing variance.
        explained_variance_: (K,) variance along each component (``s^2 / (N - 1)``).
        explained_variance_ratio_: (K,) fraction of the total variance.
        singular_values_: (K,).
        n_components_, n_samples_, n_features_in_: ints.
    """

    def __init__(self, encoder=None, n_components: int | float | None = None):
        self.encoder = encoder
        self.n_components = n_components

    # ------------------------------------------------------------------ validation
    def _codes(self, x, name: str = "X") -> np.ndarray:
        x = np.asarray(x)
        if x.ndim == 3:  # meshes (N, V, 3)
            if self.encoder is None:
                raise ParameterError(f"{name}: got meshes of shape {x.shape} but the shape space has no encoder; "
                                     "pass codes (N, D) or give ShapeSpace an encoder")
            return self.encoder.encode(x)
        if x.ndim == 1:
            x = x[None]
        if x.ndim != 2:
            raise ParameterError(f"{name}: shape {x.shape}, expected codes (N, D) or meshes (N, V, 3)")
        if hasattr(self, "n_features_in_") and x.shape[1] != self.n_features_in_:
            raise ParameterError(f"{name}: codes have length {x.shape[1]}, expected {self.n_features_in_} "
                                 "(the length the shape space was fitted on)")
        x = x.astype(float, copy=False)
        if not np.isfinite(x).all():
            raise ParameterError(f"{name}: contains NaN or infinity")
        return x

    def _require_fit(self):
        if not hasattr(self, "components_"):
            raise ParameterError("ShapeSpace is not fitted; call fit(codes) first")

    def _require_encoder(self, what: str):
        if self.encoder is None:
            raise ParameterError(f"ShapeSpace.{what} needs an encoder; construct ShapeSpace(encoder, ...)")

    # ------------------------------------------------------------------ estimator API
    def fit(self, X, y=None, *, select=None) -> "ShapeSpace":
        """Fit on codes (N, D) or meshes (N, V, 3); ``select`` (boolean mask or indices) restricts
        the fit to some rows, e.g. the rest-pose scans for a shape-only space."""
        x = self._codes(X)
        if select is not None:
            x = x[np.asarray(select)]
        n, d = x.shape
        if n < 2:
            raise ParameterError(f"X: {n} sample(s) selected, expected at least 2 to fit a PCA")
        self.mean_ = x.mean(axis=0)
        u, s, vt = np.linalg.svd(x - self.mean_, full_matrices=False)
        # scikit-learn's sign convention (svd_flip on the components): each component's largest
        # |entry| is positive, so the basis does not depend on the order of the samples.
        signs = np.sign(vt[np.arange(vt.shape[0]), np.argmax(np.abs(vt), axis=1)])
        signs[signs == 0] = 1.0
        vt *= signs[:, None]
        var = s ** 2 / (n - 1)
        total = var.sum()
        k = self._n_keep(var, total, n, d)
        self.components_ = vt[:k]
        self.singular_values_ = s[:k]
        self.explained_variance_ = var[:k]
        self.explained_variance_ratio_ = var[:k] / total if total > 0 else np.zeros(k)
        self.n_components_, self.n_samples_, self.n_features_in_ = k, n, d
        return self

    def _n_keep(self, var, total, n, d) -> int:
        nc = self.n_components
        limit = min(n - 1, d)
        if nc is None:
            return max(limit, 1)
        if isinstance(nc, numbers.Integral):
            if not 1 <= nc <= min(n, d):
                raise ParameterError(f"n_components={nc}, expected 1..{min(n, d)} for {n} samples of length {d}")
            return int(nc)
        if isinstance(nc, numbers.Real) and 0 < nc < 1:
            cum = np.cumsum(var) / total if total > 0 else np.ones_like(var)
            return int(min(np.searchsorted(cum, nc) + 1, len(var)))
        raise ParameterError(f"n_components={nc!r}, expected None, an int or a float in (0, 1)")

    def transform(self, X) -> np.ndarray:
        """Coefficients (N, K) of codes (N, D) or meshes (N, V, 3)."""
        self._require_fit()
        return (self._codes(X) - self.mean_) @ self.components_.T

    def fit_transform(self, X, y=None, *, select=None) -> np.ndarray:
        return self.fit(X, select=select).transform(X)

    def inverse_transform(self, Z) -> np.ndarray:
        """Codes (N, D) of coefficients (N, k) or (k,), k <= K (missing ones are zero)."""
        self._require_fit()
        z = np.asarray(Z, dtype=float)
        if z.ndim == 1:
            z = z[None]
        if z.ndim != 2 or z.shape[1] > self.n_components_:
            raise ParameterError(f"coefficients: shape {np.shape(Z)}, expected (N, k) with k <= {self.n_components_}")
        if not np.isfinite(z).all():
            raise ParameterError("coefficients: contain NaN or infinity")
        return self.mean_ + z @ self.components_[: z.shape[1]]

    # ------------------------------------------------------------------ bodies
    def sample_coefficients(self, n: int, n_components: int | None = None, sigma_range=3.0,
                            rng=None) -> np.ndarray:
        """Random coefficients (n, K): Gaussian with each component's variance, truncated.

        Args:
            n: number of bodies.
            n_components: how many leading components vary (default all); the rest are 0.
            sigma_range: truncation in standard deviations: a number s for [-s, s], a pair
                (lo, hi), or None for an untruncated Gaussian.
            rng: numpy Generator, seed, or None.
        """
        self._require_fit()
        k = self.n_components_ if n_components is None else int(n_components)
        if not 1 <= k <= self.n_components_:
            raise ParameterError(f"n_components={n_components}, expected 1..{self.n_components_}")
        if sigma_range is None:
            lo, hi = -np.inf, np.inf
        elif np.ndim(sigma_range) == 0:
            lo, hi = -abs(float(sigma_range)), abs(float(sigma_range))
        else:
            lo, hi = (float(v) for v in sigma_range)
        if not lo < hi:
            raise ParameterError(f"sigma_range={sigma_range!r}, expected lo < hi")
        t = truncnorm.rvs(lo, hi, size=(int(n), k), random_state=_rng(rng))
        z = np.zeros((int(n), self.n_components_))
        z[:, :k] = t * np.sqrt(self.explained_variance_[:k])
        return z

    def sample(self, n: int, n_components: int | None = None, sigma_range=3.0, rng=None) -> np.ndarray:
        """Random bodies (n, V, 3): ``reconstruct(sample_coefficients(...))``."""
        self._require_encoder("sample")
        return self.reconstruct(self.sample_coefficients(n, n_components, sigma_range, rng))

    def project(self, vertices, faces=None) -> np.ndarray:
        """Coefficients (N, K) of registered meshes (V, 3) or (N, V, 3)."""
        self._require_encoder("project")
        self._require_fit()
        return self.transform(self.encoder.encode(vertices, faces))

    def reconstruct(self, coefficients, constraints=None) -> np.ndarray:
        """Bodies (N, V, 3) from coefficients (N, k) or (k,), k <= K, decoded by the encoder
        (``constraints`` as in ``encoder.decode``)."""
        self._require_encoder("reconstruct")
        return self.encoder.decode(self.inverse_transform(coefficients), constraints=constraints)
