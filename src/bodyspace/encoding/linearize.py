"""A linear stand-in for a non-linear decoder: ``v(z) ~ base + sum_k z_k C_k``, for measurement Jacobians.

With the relative rotation encoding a body ``v(z) = decode(mean + sum_k z_k P_k)`` is non-linear
in its coefficients, and its exact tangent (one rotation-system solve per direction) costs as
much as ``k`` decodes. Exact refinement (``refine.refine``) only needs a *direction* to step in:
its residuals are always measured on the truly decoded body, so any reasonable approximation of
``dv/dz`` gives the same fixed point, it only changes how many steps it takes. This module fits
that approximation once per model:

- ``DecoderLinearization.fit(z, vertices)`` (or ``partial_fit`` chunk by chunk): ordinary least
  squares of the decoded bodies on their coefficients, ``v = base + z C`` over the whole sampled
  box (a secant fit: good everywhere in the box, exact nowhere). The training set of the mapping
  decodes those bodies anyway (``training.make_training_set`` fits it on the way).
- ``DecoderLinearization.at_mean(space, k)``: forward differences at the mean body, ``k + 1``
  decodes (the tangent at z = 0), when no training set is at hand.
- ``DecoderLinearization.exact(base, basis)``: a decoder that is affine already (the vertex
  encoding), stored as it is.

Every encoder's ``linearize(space, k)`` returns one of these (exact for the vertex encoding,
forward differences for the relative rotation encoding), and its ``is_linear`` says whether
the least-squares fit is worth making; ``mapping.gradients.LinearBodyMeasures`` chains its
analytic measurement gradients (w.r.t. the vertices) with ``basis_``.

Shapes: N bodies, V vertices, k coefficients. Stored as flat float arrays (``to_arrays`` /
``from_arrays``, npz, never pickle).
"""

from __future__ import annotations

import weakref

import numpy as np

from bodyspace.errors import ParameterError

FORMAT_VERSION = 1
_CACHE: "weakref.WeakKeyDictionary" = weakref.WeakKeyDictionary()


class DecoderLinearization:
    """Affine approximation ``v = base_ + z @ basis_`` of a model's decoder on its first ``k`` coefficients.

    Learned state: ``base_`` (V, 3), ``basis_`` (k, V, 3) metres per unit coefficient,
    ``n_samples_`` (bodies it was fitted on; 0 for finite differences), ``residual_rms_`` (m,
    RMS vertex error of the fit on its own samples, from accumulated sums: rounding ~1e-5 m; NaN
    when unknown), ``method_`` ("least_squares"
    or "finite_differences").
    """

    def __init__(self, k: int):
        if int(k) < 1:
            raise ParameterError(f"k={k}: expected at least one coefficient")
        self.k = int(k)
        self._zz = None

    # ------------------------------------------------------------------ least squares
    def partial_fit(self, z: np.ndarray, vertices: np.ndarray) -> "DecoderLinearization":
        """Accumulate bodies ``vertices`` (N, V, 3) decoded from coefficients ``z`` (N, >= k)."""
        z = np.asarray(z, dtype=float)
        v = np.asarray(vertices, dtype=float)
        if z.ndim != 2 or z.shape[1] < self.k or v.ndim != 3 or v.shape[0] != len(z) or v.shape[2] != 3:
            raise ParameterError(f"z {z.shape} and vertices {v.shape}: expected (N, >= {self.k}) and (N, V, 3)")
        a = np.hstack([np.ones((len(z), 1)), z[:, :self.k]])           # (N, k + 1)
        flat = v.reshape(len(v), -1)
        if self._zz is None:
            self._zz = np.zeros((self.k + 1, self.k + 1))
            self._zv = np.zeros((self.k + 1, flat.shape[1]))
            self._vv = 0.0
            self._n = 0
            self._shape = v.shape[1:]
        elif v.shape[1:] != self._shape:
            raise ParameterError(f"vertices {v.shape}: expected (N, {self._shape[0]}, 3) like the earlier chunks")
        self._zz += a.T @ a
        self._zv += a.T @ flat
        self._vv += float(np.sum(flat * flat))
        self._n += len(z)
        return self._solve()

    def fit(self, z: np.ndarray, vertices: np.ndarray) -> "DecoderLinearization":
        """Least-squares fit on bodies ``vertices`` (N, V, 3) of coefficients ``z`` (N, >= k), N > k."""
        self._zz = None
        return self.partial_fit(z, vertices)

    def _solve(self) -> "DecoderLinearization":
        if self._n <= self.k:                      # not determined yet; keep accumulating
            return self
        # A tiny ridge keeps the solve defined for degenerate designs; uniform samples never need it.
        reg = 1e-12 * np.trace(self._zz) * np.eye(self.k + 1)
        coef = np.linalg.solve(self._zz + reg, self._zv)               # (k + 1, 3V)
        self.base_ = coef[0].reshape(self._shape)
        self.basis_ = coef[1:].reshape((self.k,) + tuple(self._shape))
        rss = self._vv - float(np.sum(coef * self._zv))                # |V|^2 - c^T A^T V at the optimum
        self.residual_rms_ = float(np.sqrt(max(rss, 0.0) / (self._n * self._shape[0])))
        self.n_samples_ = int(self._n)
        self.method_ = "least_squares"
        return self

    # ------------------------------------------------------------------ tangent at the mean
    @classmethod
    def exact(cls, base: np.ndarray, basis: np.ndarray) -> "DecoderLinearization":
        """An affine decoder ``v = base + z @ basis`` (base (V, 3), basis (k, V, 3)) kept as it is."""
        out = cls(len(basis))
        out.base_, out.basis_ = np.asarray(base, dtype=float), np.asarray(basis, dtype=float)
        out.n_samples_, out.residual_rms_, out.method_ = 0, 0.0, "exact"
        return out

    @classmethod
    def at_mean(cls, space, k: int = 25, step_sigma: float = 0.05) -> "DecoderLinearization":
        """Forward differences of ``space.reconstruct`` (a fitted ``ShapeSpace`` with its encoder)
        at z = 0, ``step_sigma`` standard deviations per coefficient: ``k + 1`` decodes in one
        batch. Cached per shape space (weakly) and (k, step)."""
        sp = space
        k = min(int(k), sp.n_components_)
        key = (k, float(step_sigma))
        try:
            per_model = _CACHE.setdefault(space, {})
        except TypeError:
            per_model = {}
        hit = per_model.get(key)
        if hit is not None and hit[0] is sp.components_:
            return hit[1]
        h = float(step_sigma) * np.sqrt(sp.explained_variance_[:k])
        z = np.zeros((k + 1, sp.n_components_))
        z[np.arange(1, k + 1), np.arange(k)] = h
        v = space.reconstruct(z)
        out = cls(k)
        out.base_ = v[0]
        out.basis_ = (v[1:] - v[0]) / h[:, None, None]
        out.n_samples_, out.residual_rms_, out.method_ = 0, float("nan"), "finite_differences"
        per_model[key] = (sp.components_, out)
        return out

    # ------------------------------------------------------------------ use
    def _require_fit(self):
        if not hasattr(self, "basis_"):
            raise ParameterError(f"DecoderLinearization: not fitted (needs more than k = {self.k} bodies; "
                                 f"has {getattr(self, '_n', 0)})")

    def predict(self, z: np.ndarray) -> np.ndarray:
        """Approximate bodies (N, V, 3) of coefficients z (N, >= k) (only the first k are used)."""
        self._require_fit()
        z = np.atleast_2d(np.asarray(z, dtype=float))[:, :self.k]
        return self.base_ + np.tensordot(z, self.basis_, axes=(1, 0))

    def to_arrays(self, prefix: str = "linearization_") -> dict[str, np.ndarray]:
        """Flat arrays for an npz file: ``base`` (V, 3), ``basis`` (k, V, 3) float64, ``info`` (3,)
        = (format version, n_samples, residual_rms); the method follows from n_samples (0: finite differences)."""
        self._require_fit()
        return {prefix + "base": np.asarray(self.base_, dtype=np.float64),
                prefix + "basis": np.asarray(self.basis_, dtype=np.float64),
                prefix + "info": np.array([FORMAT_VERSION, self.n_samples_, self.residual_rms_], dtype=np.float64)}

    @classmethod
    def from_arrays(cls, arrays, prefix: str = "linearization_") -> "DecoderLinearization":
        """Inverse of ``to_arrays`` (checks names, shapes and version)."""
        names = [prefix + s for s in ("base", "basis", "info")]
        missing = [n for n in names if n not in arrays]
        if missing:
            raise ParameterError(f"decoder linearization: arrays {missing} missing (has {sorted(arrays)})")
        base, basis, info = (np.asarray(arrays[n], dtype=float) for n in names)
        if base.ndim != 2 or base.shape[1] != 3 or basis.ndim != 3 or basis.shape[1:] != base.shape \
                or info.shape != (3,):
            raise ParameterError(f"decoder linearization: base {base.shape}, basis {basis.shape}, info {info.shape}; "
                                 "expected (V, 3), (k, V, 3), (3,)")
        if int(info[0]) != FORMAT_VERSION:
            raise ParameterError(f"decoder linearization: format version {int(info[0])}, expected {FORMAT_VERSION}")
        out = cls(len(basis))
        out.base_, out.basis_ = base, basis
        out.n_samples_, out.residual_rms_ = int(info[1]), float(info[2])
        out.method_ = "least_squares" if out.n_samples_ else "finite_differences"
        return out
