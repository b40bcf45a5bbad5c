"""Semantic model basis (Hasler §4.1).

Rotate the shape space so that its first vectors are semantic morphing directions (e.g. the
gradients of the stature and weight regressors) and the rest is a PCA basis of what those
directions do not explain:

1. Gram-Schmidt orthonormalizes the C semantic directions: ``q_1 .. q_C`` (``q_1`` parallel to
   the first direction, ``q_2`` to the part of the second orthogonal to it, ...).
2. Every centred body ``x - mean`` loses its components along ``q_1 .. q_C``; these residuals
   are invariant to the semantic variables.
3. The PCA of the residuals gives ``p_1 .. p_K'``, orthogonal to every ``q``.

The final basis is ``[q_1 .. q_C, p_1 .. p_K']`` (orthonormal). A body's coordinates are
``c = (x - mean) [q | p]``; the first C are its projections on the orthonormalized semantic
directions, and ``x = mean + c [q | p]^T``. Fixing the first C coordinates and varying the rest
changes the body without changing the semantic variables (to first order for non-linear
labels, exactly for linear ones when the semantic directions are their gradients): e.g. more
height at constant weight gives slimmer bodies.

If the bodies are PCA coefficients (N, K) of a shape space with ``K <= N - 1`` the new basis
spans the whole space and the round trip is exact for any body; for full encodings (D > N) it
spans the mean plus the directions plus the data's residual span, and the round trip is exact
for the training bodies and anything in that span.
"""

from __future__ import annotations

import numbers

import numpy as np

from bodyspace.errors import ParameterError
from bodyspace.validation import as_int, as_matrix

__all__ = ["gram_schmidt", "SemanticBasis"]


def gram_schmidt(vectors, tol: float = 1e-8) -> np.ndarray:
    """Orthonormalize the rows of ``vectors`` (C, D) in order (modified Gram-Schmidt, applied
    twice for stability). Row i of the result is parallel (same sign) to the part of row i
    orthogonal to the rows before it.

    Raises ParameterError if a row is (nearly, relative ``tol``) a combination of the earlier ones.
    """
    v = as_matrix(vectors, "directions", allow_vector=True)
    q = np.zeros_like(v)
    for i, row in enumerate(v):
        norm0 = np.linalg.norm(row)
        r = row.copy()
        for _ in range(2):
            for j in range(i):
                r -= (q[j] @ r) * q[j]
        norm = np.linalg.norm(r)
        if norm0 == 0 or norm <= tol * norm0:
            raise ParameterError(f"directions: row {i} is zero or a linear combination of the rows before it, "
                                 "expected linearly independent semantic directions")
        q[i] = r / norm
    return q


class SemanticBasis:
    """Hasler §4.1: orthonormal basis whose first vectors are semantic directions, the rest a PCA.

    Args:
        n_components: residual PCA components to keep (None: every one with variance above
            ``tol`` times the largest; at most ``min(N - 1, D - C)``).
        tol: relative variance below which a residual component is dropped. (A semantic
            direction counts as dependent when less than 1e-8 of its norm is left after
            Gram-Schmidt.)

    Attributes (after ``fit``):
        mean_: (D,). semantic_components_: (C, D) orthonormalized directions ``q``.
        residual_components_: (K', D) residual PCA directions ``p``.
        components_: (C + K', D) the whole basis, semantic first.
        explained_variance_: (K',) residual PCA variances. semantic_variance_: (C,) variance of
        the bodies along every ``q``. n_semantic_ = C, n_components_ = C + K', n_features_in_.
    """

    def __init__(self, n_components: int | None = None, tol: float = 1e-10):
        self.n_components = n_components
        self.tol = tol

    def fit(self, directions, X) -> "SemanticBasis":
        """``directions`` (C, D) semantic morphing vectors (e.g. regressor gradients), ``X`` (N, D)
        bodies (encodings or PCA coefficients)."""
        if not (isinstance(self.tol, numbers.Real) and 0 <= self.tol < 1):
            raise ParameterError(f"tol={self.tol!r}, expected a number in [0, 1)")
        q = gram_schmidt(directions)
        x = as_matrix(X, "X", n_features=q.shape[1], min_rows=2)
        n, d = x.shape
        c = q.shape[0]
        if c > d:
            raise ParameterError(f"directions: {c} rows, expected at most D = {d}")
        mean = x.mean(axis=0)
        xc = x - mean
        resid = xc - (xc @ q.T) @ q
        _, s, vt = np.linalg.svd(resid, full_matrices=False)
        var = s ** 2 / (n - 1)
        limit = min(n - 1, d - c)
        k = int(np.sum(var[:limit] > self.tol * var[0])) if var.size and var[0] > 0 else 0
        if self.n_components is not None:
            k = min(as_int(self.n_components, "n_components", 0, limit), k)
        p = vt[:k]
        p = p - (p @ q.T) @ q                     # remove round-off leakage into the semantic span
        p /= np.linalg.norm(p, axis=1, keepdims=True) if k else 1.0
        self.mean_ = mean
        self.semantic_components_ = q
        self.residual_components_ = p
        self.components_ = np.vstack([q, p])
        self.explained_variance_ = var[:k]
        self.semantic_variance_ = np.var(xc @ q.T, axis=0, ddof=1)
        self.n_semantic_, self.n_components_, self.n_features_in_ = c, c + k, d
        return self

    def _require_fit(self):
        if not hasattr(self, "components_"):
            raise ParameterError("SemanticBasis is not fitted; call fit(directions, X) first")

    def transform(self, X) -> np.ndarray:
        """Coordinates (N, C + K') of bodies (N, D): semantic first, then residual PCA."""
        self._require_fit()
        single = np.ndim(X) == 1
        x = as_matrix(X, "X", n_features=self.n_features_in_, allow_vector=True)
        out = (x - self.mean_) @ self.components_.T
        return out[0] if single else out

    def inverse_transform(self, coordinates) -> np.ndarray:
        """Bodies (N, D) from coordinates (N, m) or (m,), m <= C + K' (missing ones are 0)."""
        self._require_fit()
        single = np.ndim(coordinates) == 1
        c = as_matrix(coordinates, "coordinates", allow_vector=True)
        if c.shape[1] > self.n_components_:
            raise ParameterError(f"coordinates: {c.shape[1]} per body, expected at most {self.n_components_}")
        out = self.mean_ + c @ self.components_[: c.shape[1]]
        return out[0] if single else out

    def split(self, coordinates) -> tuple[np.ndarray, np.ndarray]:
        """``(semantic (..., C), residual (..., K'))`` parts of coordinates from ``transform``."""
        self._require_fit()
        c = np.asarray(coordinates, dtype=float)
        return c[..., : self.n_semantic_], c[..., self.n_semantic_:]
