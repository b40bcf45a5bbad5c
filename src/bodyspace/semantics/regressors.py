"""Semantic regressors: a label value as a function of a body (Hasler §4, Hasler Table 1).

From encoded scans ``A`` (rows ``a_i``) and one label per scan ``l_i`` (stature, mass, body fat,
sex, ...), learn ``f(a) ~ l``. Three regressors, the three rows of Hasler Table 1:

- ``SimpleLinearRegressor``: Hasler Equation 10, ``argmin_[o, s] || [1 | A] [o; s] - l ||``, solved in
  the least-squares (minimum-norm when ``N <= D``) sense.
- ``FilteredLinearRegressor``: Hasler Equation 10 solved in the PCA space of ``A``, then PCA
  components *rejected in ascending order of their contribution* to the label (not in the
  classic smallest-eigenvalue order), the number kept chosen by k-fold cross-validation.
- ``KernelRegressor``: the non-linear row; RBF kernel ridge regression (numpy) or support vector
  regression (scikit-learn, optional) on standardized inputs.

Every regressor works on plain arrays: a body is a row ``x`` of length ``D``, either a full
encoding or its PCA coefficients, whatever it was fitted on. All expose ``predict(X) -> (N,)``
and ``gradient(X) -> (D,)`` or ``(N, D)``: the local morphing direction ``df/dx`` (constant for
the linear ones, the analytic gradient of the kernel expansion for the kernel one). Morphing
(``semantics.morph``) and the semantic basis (``semantics.basis``) only need these two methods.

Estimators in the scikit-learn style: hyper-parameters in ``__init__``, ``fit`` returns self,
learned state ends in ``_``, inputs validated at the door (``ParameterError`` naming the field,
what was found and what was expected). ``to_arrays`` / ``from_arrays`` give the learned state as
plain arrays for an ``npz`` file (never pickle).
"""

from __future__ import annotations

import inspect
import numbers

import numpy as np

from bodyspace.errors import ParameterError
from bodyspace.validation import as_generator, as_int, as_matrix, as_positive_grid, as_vector

__all__ = ["SimpleLinearRegressor", "FilteredLinearRegressor", "KernelRegressor", "kfold_indices"]


def kfold_indices(n: int, folds: int, rng=None, groups=None) -> list[np.ndarray]:
    """Test-index arrays of a shuffled k-fold split of ``n`` rows.

    With ``groups`` (n,) (e.g. subject ids), whole groups go to one fold, so no subject is in
    both the training and the test part. Folds are capped at the number of rows (groups).
    """
    folds = as_int(folds, "folds", 2)
    gen = as_generator(rng)
    if groups is None:
        if n < 2:
            raise ParameterError(f"X: {n} row(s), expected at least 2 for cross-validation")
        perm = gen.permutation(n)
        return [np.sort(p) for p in np.array_split(perm, min(folds, n))]
    g = np.asarray(groups)
    if g.shape != (n,):
        raise ParameterError(f"groups: shape {g.shape}, expected ({n},) (one group id per row)")
    uniq, inv = np.unique(g, return_inverse=True)
    if uniq.size < 2:
        raise ParameterError(f"groups: {uniq.size} distinct group(s), expected at least 2 for cross-validation")
    parts = np.array_split(gen.permutation(uniq.size), min(folds, uniq.size))
    return [np.flatnonzero(np.isin(inv, p)) for p in parts]


# ---------------------------------------------------------------------------- base
class _SemanticRegressor:
    """Shared plumbing: parameters (``get_params``/``set_params``, so ``sklearn.base.clone``
    works), fit checks, ``predict``/``gradient`` of a linear model, array state."""

    _state: tuple[str, ...] = ()

    # -- parameters
    @classmethod
    def _param_names(cls) -> list[str]:
        sig = inspect.signature(cls.__init__)
        return [p for p in sig.parameters if p != "self"]

    def get_params(self, deep: bool = True) -> dict:
        return {p: getattr(self, p) for p in self._param_names()}

    def set_params(self, **params):
        valid = self._param_names()
        for key, value in params.items():
            if key not in valid:
                raise ParameterError(f"{type(self).__name__}.set_params: unknown parameter {key!r}, expected one of {valid}")
            setattr(self, key, value)
        return self

    def __repr__(self) -> str:
        args = ", ".join(f"{k}={v!r}" for k, v in self.get_params().items())
        return f"{type(self).__name__}({args})"

    # -- fitted state
    def _require_fit(self):
        if not hasattr(self, "n_features_in_"):
            raise ParameterError(f"{type(self).__name__} is not fitted; call fit(X, y) first")

    def _input(self, X, name: str = "X") -> tuple[np.ndarray, bool]:
        self._require_fit()
        single = np.ndim(X) == 1
        return as_matrix(X, name, n_features=self.n_features_in_, allow_vector=True), single

    def to_arrays(self) -> dict[str, np.ndarray]:
        """Learned state as arrays (for ``np.savez``; scalars become 0-d arrays)."""
        self._require_fit()
        return {k: np.asarray(getattr(self, k)) for k in self._state}

    @classmethod
    def from_arrays(cls, arrays, **params):
        """A fitted regressor from ``to_arrays()`` output (hyper-parameters from ``params``)."""
        obj = cls(**params)
        missing = [k for k in cls._state if k not in arrays]
        if missing:
            raise ParameterError(f"{cls.__name__}.from_arrays: missing {missing}, expected keys {list(cls._state)}")
        for k in cls._state:
            a = np.asarray(arrays[k])
            setattr(obj, k, a.item() if a.ndim == 0 else a.copy())
        coef, d = getattr(obj, "coef_", None), getattr(obj, "n_features_in_", None)
        if coef is not None and d is not None and np.shape(coef) != (d,):
            raise ParameterError(f"{cls.__name__}.from_arrays: 'coef_' has shape {np.shape(coef)}, expected ({d},) "
                                 "(n_features_in_)")
        return obj


class LinearModel(_SemanticRegressor):
    """``f(x) = intercept_ + <coef_, x>``; the gradient is ``coef_`` everywhere."""

    def predict(self, X) -> np.ndarray:
        """Label values (N,) of bodies X (N, D); a float for a single body (D,)."""
        x, single = self._input(X)
        out = self.intercept_ + x @ self.coef_
        return float(out[0]) if single else out

    def gradient(self, X) -> np.ndarray:
        """Morphing direction ``df/dx``: ``coef_`` (D,) for a body (D,), tiled (N, D) for (N, D)."""
        x, single = self._input(X)
        return self.coef_.copy() if single else np.tile(self.coef_, (x.shape[0], 1))


# ---------------------------------------------------------------------------- Hasler Equation 10
class SimpleLinearRegressor(LinearModel):
    """Hasler Equation 10: ``argmin_[o, s] || [1 | A] [o; s] - l ||`` with intercept ``o``.

    Solved on centred data, ``s = pinv(A - mean) (l - mean(l))``, ``o = mean(l) - <s, mean>``:
    the least-squares solution, and of all of them the one of minimum norm when the system is
    under-determined (``N <= D``: then it interpolates the training labels, which is why its
    generalisation is limited, Hasler Table 1 row 1).

    Args:
        rcond: relative cut-off for small singular values (``numpy.linalg.lstsq``); None uses
            numpy's machine-precision default.

    Attributes (after ``fit``):
        coef_: (D,) gradient ``s``. intercept_: offset ``o``. rank_: rank of the centred ``A``.
        n_features_in_, n_samples_: ints.
    """

    _state = ("coef_", "intercept_", "n_features_in_")

    def __init__(self, rcond: float | None = None):
        self.rcond = rcond

    def fit(self, X, y) -> "SimpleLinearRegressor":
        x = as_matrix(X, "X", min_rows=2)
        l = as_vector(y, "y", x.shape[0])
        mean, lmean = x.mean(axis=0), l.mean()
        coef, _, rank, _ = np.linalg.lstsq(x - mean, l - lmean, rcond=self.rcond)
        self.coef_ = coef
        self.intercept_ = float(lmean - mean @ coef)
        self.rank_ = int(rank)
        self.n_samples_, self.n_features_in_ = x.shape
        return self


# ---------------------------------------------------------------------------- filtered Hasler Equation 10
def _pca_solve(x: np.ndarray, l: np.ndarray, tol: float):
    """PCA of ``x`` and Hasler Equation 10 in its coordinates.

    Returns ``mean (D,), components V (K, D), variances (K,), w (K,), lmean``. The PCA scores
    ``T = (x - mean) V^T`` have orthogonal columns, so least squares decouples:
    ``w_k = <t_k, l - lmean> / ||t_k||^2``.
    """
    n = x.shape[0]
    mean = x.mean(axis=0)
    u, s, vt = np.linalg.svd(x - mean, full_matrices=False)
    keep = s > tol * s[0] if s.size and s[0] > 0 else np.zeros(s.shape, bool)
    u, s, vt = u[:, keep], s[keep], vt[keep]
    lmean = l.mean()
    w = (u.T @ (l - lmean)) / s          # T = u * s  ->  w_k = <u_k s_k, l> / s_k^2
    return mean, vt, s ** 2 / (n - 1), w, lmean


def _rejection_order(w: np.ndarray, var: np.ndarray, order: str) -> np.ndarray:
    """Component indices from kept-first to rejected-first.

    ``contribution``: descending ``|w_k| sqrt(var_k)`` (the SD of component k's term in the
    prediction), so rejection runs in ascending order of contribution (Hasler §4).
    ``variance``: descending variance, the classic truncation (reject smallest eigenvalues).
    """
    if order == "contribution":
        return np.argsort(-np.abs(w) * np.sqrt(var), kind="stable")
    return np.argsort(-var, kind="stable")


class FilteredLinearRegressor(LinearModel):
    """Hasler Equation 10 in PCA space with noise components rejected by cross-validation (Hasler §4).

    Fit: (1) PCA of the training rows ``X`` (full encodings or PCA coefficients; for the
    latter the PCA is a rotation, the identity up to signs on the rows the shape space was
    fitted on); (2) solve Hasler Equation 10 in the PCA scores ``T``, ``l ~ o + T w`` (the scores are
    orthogonal, so every ``w_k`` is independent of the others and rejecting a component never
    changes the remaining weights); (3) rank the components by their **contribution**
    ``c_k = |w_k| sqrt(var_k)``, the standard deviation of component k's term ``w_k t_k`` over
    the database (equivalently ``|corr(t_k, l)| SD(l)``), and reject them in ascending order of
    ``c_k``: "components that contribute primarily noise are not correlated strongly with a
    given semantic gradient"; (4) keep the ``m`` best, ``m`` chosen by k-fold cross-validation
    (PCA, solve and ranking redone inside every fold; pooled held-out RMSE; the smallest ``m``
    on ties; ``m = 0`` predicts the mean label). The gradient is ``s = sum_{k kept} w_k v_k``.

    Args:
        n_components: the most components that may be kept (None: all with non-zero variance).
        cv: folds of the internal cross-validation (capped at the number of rows).
        order: ``"contribution"`` (Hasler's order, default) or ``"variance"`` (the classic
            order: reject the smallest-eigenvalue components first), for comparison.
        tol: singular values below ``tol * largest`` are treated as zero.
        rng: numpy Generator, seed or None for the fold shuffle.

    Attributes (after ``fit``):
        coef_: (D,) gradient ``s`` in the input space. intercept_: offset ``o``.
        mean_: (D,). components_: (K, D) PCA directions of the training rows.
        explained_variance_: (K,). component_coef_: (K,) unfiltered ``w``.
        contribution_: (K,) ``|w_k| sqrt(var_k)``. order_: (K,) component indices, kept first.
        n_kept_: number kept. kept_: (K,) bool. cv_rmse_: (M + 1,) held-out RMSE of keeping
        0..M components. n_features_in_, n_samples_: ints.
    """

    # components_ and mean_ (as large as X) are not part of the saved state: predict and
    # gradient need coef_ and intercept_ only.
    _state = ("coef_", "intercept_", "n_features_in_", "n_kept_", "kept_", "explained_variance_",
              "component_coef_", "contribution_", "order_", "cv_rmse_")

    def __init__(self, n_components: int | None = None, cv: int = 10, order: str = "contribution",
                 tol: float = 1e-10, rng=None):
        self.n_components = n_components
        self.cv = cv
        self.order = order
        self.tol = tol
        self.rng = rng

    def _check_params(self):
        if self.order not in ("contribution", "variance"):
            raise ParameterError(f"order={self.order!r}, expected 'contribution' or 'variance'")
        as_int(self.cv, "cv", 2)
        if self.n_components is not None:
            as_int(self.n_components, "n_components", 0)
        if not (isinstance(self.tol, numbers.Real) and 0 <= self.tol < 1):
            raise ParameterError(f"tol={self.tol!r}, expected a number in [0, 1)")

    def fit(self, X, y) -> "FilteredLinearRegressor":
        self._check_params()
        x = as_matrix(X, "X", min_rows=3)
        l = as_vector(y, "y", x.shape[0])
        n = x.shape[0]
        cap = np.inf if self.n_components is None else self.n_components

        # Internal cross-validation over the number of kept components.
        folds = kfold_indices(n, min(self.cv, n), self.rng)
        results = []
        for test in folds:
            train = np.setdiff1d(np.arange(n), test)
            mean, vt, var, w, lmean = _pca_solve(x[train], l[train], self.tol)
            rank = _rejection_order(w, var, self.order)
            terms = ((x[test] - mean) @ vt[rank].T) * w[rank]            # (n_test, K) per component
            preds = lmean + np.concatenate([np.zeros((len(test), 1)), np.cumsum(terms, axis=1)], axis=1)
            results.append((preds - l[test][:, None]) ** 2)               # (n_test, K + 1)
        m_max = int(min(min(r.shape[1] for r in results) - 1, cap))
        sse = sum(r[:, : m_max + 1].sum(axis=0) for r in results)
        self.cv_rmse_ = np.sqrt(sse / n)
        best = float(self.cv_rmse_.min())
        self.n_kept_ = int(np.flatnonzero(self.cv_rmse_ <= best * (1 + 1e-12))[0])

        # Final model on all rows.
        mean, vt, var, w, lmean = _pca_solve(x, l, self.tol)
        self.order_ = _rejection_order(w, var, self.order)
        self.n_kept_ = min(self.n_kept_, len(w))
        self.kept_ = np.zeros(len(w), bool)
        self.kept_[self.order_[: self.n_kept_]] = True
        self.mean_, self.components_, self.explained_variance_ = mean, vt, var
        self.component_coef_ = w
        self.contribution_ = np.abs(w) * np.sqrt(var)
        self.coef_ = (w * self.kept_) @ vt
        self.intercept_ = float(lmean - mean @ self.coef_)
        self.n_samples_, self.n_features_in_ = x.shape
        return self


# ---------------------------------------------------------------------------- non-linear
def _sq_dist(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    d = (a * a).sum(1)[:, None] + (b * b).sum(1)[None] - 2.0 * a @ b.T
    return np.maximum(d, 0.0)


class KernelRegressor(_SemanticRegressor):
    """Non-linear regressor (Hasler Table 1, row 3): RBF kernel expansion on scaled inputs.

    ``f(x) = intercept_ + sum_i dual_coef_i exp(-gamma_ ||u - u_i||^2)``, ``u = (x - mean_) / scale_``,
    over the support points ``u_i`` (``X_fit_``). Its analytic gradient, the local morphing
    direction, is ``df/dx = -2 gamma_ sum_i dual_coef_i k_i (u - u_i) / scale_``.

    Methods (the label is standardized to mean 0, SD 1 for fitting):
        ``"kernel_ridge"`` (numpy): ``(K + alpha I) a = (l - mean(l)) / SD(l)``; when ``gamma`` or
            ``alpha`` is a grid, the pair with the smallest closed-form leave-one-out error is
            used (one eigendecomposition of ``K`` per gamma). Every row is a support point.
        ``"svr"``: epsilon-SVR with RBF kernel (``sklearn.svm.SVR``), as in the paper; needs
            scikit-learn at fit time only (predict/gradient are numpy). When ``gamma`` or ``C``
            is a grid, the pair with the smallest ``cv``-fold error is used.

    Args:
        method: ``"kernel_ridge"`` or ``"svr"``.
        gamma: RBF width on scaled inputs: a float, a sequence (a grid), or None
            (``(0.01, 0.03, 0.1, 0.3, 1, 3) / D``).
        alpha: kernel ridge strength: float, sequence, or None (``logspace(-4, 1, 11)``).
        C: SVR penalty: float, sequence, or None (``(1, 10, 100)``).
        epsilon: SVR tube half-width in label SDs.
        standardize: input scaling before the kernel. ``"global"`` (default): centre, divide
            every column by one common scale (the RMS column SD), so relative scales are kept:
            right for PCA coefficients, where per-column scaling would whiten and blow up the
            noise components. ``"features"``: every column to unit SD, for columns in unrelated
            units (e.g. raw measurements). ``"none"``: as given.
        cv: folds for the SVR grid search. rng: seed/Generator for its shuffle.

    Attributes (after ``fit``):
        mean_, scale_: (D,) input scaling. X_fit_: (M, D) scaled support points.
        dual_coef_: (M,) in label units. intercept_: float. gamma_: float. alpha_ (kernel ridge)
        or C_ (SVR): float. cv_rmse_: (G, A) or (G, C) held-out RMSE over the grid (label
        units; leave-one-out for kernel ridge). n_features_in_, n_samples_: ints.
    """

    _state = ("mean_", "scale_", "X_fit_", "dual_coef_", "intercept_", "gamma_", "n_features_in_")

    def __init__(self, method: str = "kernel_ridge", gamma=None, alpha=None, C=None, epsilon: float = 0.05,
                 standardize: str = "global", cv: int = 5, rng=None):
        self.method = method
        self.gamma = gamma
        self.alpha = alpha
        self.C = C
        self.epsilon = epsilon
        self.standardize = standardize
        self.cv = cv
        self.rng = rng

    def fit(self, X, y) -> "KernelRegressor":
        if self.method not in ("kernel_ridge", "svr"):
            raise ParameterError(f"method={self.method!r}, expected 'kernel_ridge' or 'svr'")
        if self.standardize not in ("global", "features", "none"):
            raise ParameterError(f"standardize={self.standardize!r}, expected 'global', 'features' or 'none'")
        x = as_matrix(X, "X", min_rows=3)
        l = as_vector(y, "y", x.shape[0])
        n, d = x.shape
        if self.standardize == "none":
            self.mean_, sd = np.zeros(d), np.ones(d)
        else:
            self.mean_ = x.mean(axis=0)
            sd = x.std(axis=0)
            if self.standardize == "global":
                sd = np.full(d, np.sqrt(np.mean(sd ** 2)))
        self.scale_ = np.where(sd > 0, sd, 1.0)
        u = (x - self.mean_) / self.scale_
        lmean, lsd = l.mean(), l.std()
        lsd = lsd if lsd > 0 else 1.0
        ls = (l - lmean) / lsd
        gammas = as_positive_grid(np.array([0.01, 0.03, 0.1, 0.3, 1.0, 3.0]) / d if self.gamma is None
                                   else self.gamma, "gamma")
        if self.method == "kernel_ridge":
            alphas = as_positive_grid(np.logspace(-4, 1, 11) if self.alpha is None else self.alpha, "alpha")
            dual = self._fit_kernel_ridge(u, ls, gammas, alphas)
            self.X_fit_, self.dual_coef_, self.intercept_ = u, dual * lsd, float(lmean)
        else:
            cs = as_positive_grid((1.0, 10.0, 100.0) if self.C is None else self.C, "C")
            if not (isinstance(self.epsilon, numbers.Real) and self.epsilon >= 0):
                raise ParameterError(f"epsilon={self.epsilon!r}, expected a number >= 0")
            sv, dual, b = self._fit_svr(u, ls, gammas, cs)
            self.X_fit_, self.dual_coef_, self.intercept_ = sv, dual * lsd, float(lmean + lsd * b)
        self.cv_rmse_ = self.cv_rmse_ * lsd
        self.n_samples_, self.n_features_in_ = n, d
        return self

    def _fit_kernel_ridge(self, u, ls, gammas, alphas):
        d2 = _sq_dist(u, u)
        self.cv_rmse_ = np.empty((gammas.size, alphas.size))
        best = (np.inf, None, None)
        for gi, g in enumerate(gammas):
            e, vecs = np.linalg.eigh(np.exp(-g * d2))
            e = np.maximum(e, 0.0)
            proj = vecs.T @ ls
            v2 = vecs ** 2
            for ai, a in enumerate(alphas):
                shrink = e / (e + a)
                fitted = vecs @ (shrink * proj)
                hat = v2 @ shrink                       # diagonal of K (K + aI)^-1
                loo = (ls - fitted) / np.maximum(1.0 - hat, 1e-12)
                err = float(np.sqrt(np.mean(loo ** 2)))
                self.cv_rmse_[gi, ai] = err
                if err < best[0]:
                    best = (err, (gi, ai), vecs @ (proj / (e + a)))
        _, (gi, ai), dual = best
        self.gamma_, self.alpha_ = float(gammas[gi]), float(alphas[ai])
        return dual

    def _fit_svr(self, u, ls, gammas, cs):
        """The SVR grid search. scikit-learn is imported here, not at the top: it is an optional
        dependency, needed only for ``method="svr"``."""
        try:
            from sklearn.svm import SVR
        except ImportError:  # pragma: no cover - optional dependency
            raise ParameterError("method='svr' needs scikit-learn (pip install scikit-learn); "
                                 "method='kernel_ridge' needs numpy only") from None
        make = lambda g, c: SVR(kernel="rbf", gamma=float(g), C=float(c), epsilon=float(self.epsilon))  # noqa: E731
        self.cv_rmse_ = np.zeros((gammas.size, cs.size))
        if gammas.size * cs.size > 1:
            n = len(ls)
            for test in kfold_indices(n, min(as_int(self.cv, "cv", 2), n), self.rng):
                train = np.setdiff1d(np.arange(n), test)
                for gi, g in enumerate(gammas):
                    for ci, c in enumerate(cs):
                        pred = make(g, c).fit(u[train], ls[train]).predict(u[test])
                        self.cv_rmse_[gi, ci] += np.sum((pred - ls[test]) ** 2)
            self.cv_rmse_ = np.sqrt(self.cv_rmse_ / n)
        gi, ci = np.unravel_index(np.argmin(self.cv_rmse_), self.cv_rmse_.shape)
        self.gamma_, self.C_ = float(gammas[gi]), float(cs[ci])
        svr = make(self.gamma_, self.C_).fit(u, ls)
        return u[svr.support_], svr.dual_coef_[0], float(svr.intercept_[0])

    def _kernel(self, x):
        u = (x - self.mean_) / self.scale_
        return u, np.exp(-self.gamma_ * _sq_dist(u, self.X_fit_))

    def predict(self, X) -> np.ndarray:
        """Label values (N,) of bodies X (N, D); a float for a single body (D,)."""
        x, single = self._input(X)
        out = self.intercept_ + self._kernel(x)[1] @ self.dual_coef_
        return float(out[0]) if single else out

    def gradient(self, X) -> np.ndarray:
        """Analytic ``df/dx``: (D,) for a body (D,), (N, D) for (N, D)."""
        x, single = self._input(X)
        u, k = self._kernel(x)
        wk = k * self.dual_coef_                                    # (N, M)
        g = -2.0 * self.gamma_ * (u * wk.sum(axis=1, keepdims=True) - wk @ self.X_fit_) / self.scale_
        return g[0] if single else g
