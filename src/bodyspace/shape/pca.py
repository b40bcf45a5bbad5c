"""PCA shape space over encoded bodies (Hasler §4; Rupprecht Equation 1).

A body's code is ``mean_ + coefficients @ components_``. With the relative rotation encoding
the space holds pose and shape together when fitted on the whole database, or shape alone
when fitted on a selection (the rest-pose scans). With the vertex encoding it is Rupprecht's
model ``M = M_mean + sum_i alpha_i a_i``.

Estimator in the scikit-learn style (``sklearn.decomposition.PCA``): hyper-parameters in
``__init__``, ``fit`` returns self, learned state ends in ``_``. ``fit`` validates once,
resolves ``solver="auto"`` from the data size, then ``_fit_full`` (exact, float64) or
``_fit_truncated`` (randomized block Krylov, float32 codes welcome) set the same attributes.
The solvers are in ``shape.solvers`` (numpy only; the project does not depend on
scikit-learn); the sign convention is scikit-learn's, so results match its ``PCA``.

This is the one PCA fit path: ``BodyModel.fit`` hands it the (N, D) code matrix it encoded
(float64, or float32 beyond ``FULL_PCA_MAX_BYTES``), with ``copy=False``.
"""

from __future__ import annotations

import numbers

import numpy as np

from bodyspace.distributions import truncnorm_rvs
from bodyspace.errors import ParameterError
from bodyspace.encoding.vertex import VertexEncoder
from bodyspace.mesh.solver import single_threaded_blas
from bodyspace.rowfile import RowFile
from bodyspace.shape.refine import DEFAULT_LEVELS, check_levels, refine_basis
from bodyspace.shape.solvers import mean_and_scatter, pca_block_krylov, pca_full, vertex_ordered_basis
from bodyspace.shape.vertex_fit import fit_coefficients
from bodyspace.validation import as_generator

SOLVERS = ("auto", "full", "krylov")
# How the components are chosen (see ``ShapeSpace``): by code variance, by the vertex-space
# variance they carry, or that order refined for the vertex fit (``shape.refine``).
BASES = ("code", "vertex", "refined")
# basis="vertex" decodes the training codes in batches of this many bodies.
DECODE_BATCH = 16
# How ``project`` finds a mesh's coefficients (see ``ShapeSpace.project``).
PROJECTIONS = ("vertex", "code")
# solver="auto": up to this many bytes of float64 codes the PCA is exact (Gram matrix, float64);
# beyond, the leading components are found by the randomized block Krylov method on codes that
# may be held in float32 (half the memory).
FULL_PCA_MAX_BYTES = 2_000_000_000
# transform: up to this many codes the product runs on one BLAS thread (see there).
SMALL_TRANSFORM_ROWS = 64
# n_components=None keeps every component with variance, at most this many.
MAX_DEFAULT_COMPONENTS = 100


def resolve_solver(solver: str, n_samples: int, n_features: int, n_components=None) -> str:
    """"full" or "krylov" for ``solver`` ("auto", "full", "krylov") on an (n_samples, n_features)
    code matrix: "auto" is exact up to ``FULL_PCA_MAX_BYTES`` of float64 codes or when
    ``n_components`` is a variance fraction (only the exact PCA knows the whole spectrum)."""
    if solver not in SOLVERS:
        raise ParameterError(f"solver={solver!r}, expected one of {', '.join(SOLVERS)}")
    if solver != "auto":
        return solver
    fraction = isinstance(n_components, numbers.Real) and not isinstance(n_components, numbers.Integral)
    return "full" if fraction or n_samples * n_features * 8 <= FULL_PCA_MAX_BYTES else "krylov"


class ShapeSpace:
    """Principal component analysis of encoded bodies, with sampling and reconstruction.

    Args:
        encoder: a fitted encoder (``encoding.ENCODERS``; anything with ``encode``/``decode``/
            ``n_features_``), needed for the mesh-level methods (``fit`` on meshes, ``project``,
            ``reconstruct``, ``sample``); None for codes only.
        n_components: None keeps every component with variance (numerical rank, at most
            ``MAX_DEFAULT_COMPONENTS``); an int keeps that many; a float in (0, 1) keeps the
            fewest that explain that fraction of the total variance (exact solver only).
        solver: "full" (exact: eigen-decomposition of the (N, N) Gram matrix of the centred
            float64 codes), "krylov" (randomized block Krylov, Musco and Musco 2015: the leading
            components only, float32 codes kept as they are), or "auto" (``resolve_solver``).
        copy: False lets the exact solver centre a float64 code matrix in place (what
            ``BodyModel.fit`` does with the matrix it made); True (default) leaves X untouched.
        rng: the Krylov start block's seed (Generator, seed or None).
        n_jobs: threads of the Krylov products (default: all cores).
        basis: "code" (default: the principal directions of the codes, Hasler §4) or "vertex":
            code-space directions ordered by the vertex-space variance of the training bodies
            (``solvers.vertex_ordered_basis``: the first k span the codes of vertex PCA's first
            k components; exact solver only). For a non-linear decoder (RRE) the first few
            "vertex" components move whole limbs, which the code PCA puts late; the fitted
            coefficients are then correlated (``sample`` draws them independently, with each
            one's variance). For the vertex encoding both are vertex PCA. "refined": the vertex
            order, then its leading components re-chosen for the vertex fit of the training
            bodies (``shape.refine.refine_basis``, levels ``refine_levels``; costs a few vertex
            fits of every training body, docs/encoding.md); an affine decoder needs none.
        refine_levels: (k, span) pairs of ``basis="refined"`` (default
            ``refine.DEFAULT_LEVELS``, levels cut to the components kept: a span past them is
            cut to their count, a level with nothing to rotate is dropped).

    Attributes (after ``fit``):
        mean_: (D,) mean code.
        components_: (K, D) orthonormal principal directions, by decreasing variance.
        explained_variance_: (K,) variance along each component (``s^2 / (N - 1)``).
        explained_variance_ratio_: (K,) fraction of the total variance.
        singular_values_: (K,).
        total_variance_: float, the variance of the codes summed over all D features.
        solver_: "full" or "krylov", the solver used.
        basis_: "code", "vertex" or "refined"; vertex_variance_ (K,): with basis "vertex" or
            "refined", the vertex-space variance (m^2) of vertex PCA's component k (None with
            "code"); refine_levels_ (L, 2): the levels refined (None unless "refined");
            refine_report_: ``refine.RefineReport`` of the fit (not stored in a file).
        n_components_, n_samples_, n_features_in_: ints.
    """

    def __init__(self, encoder=None, n_components: int | float | None = None, *, solver: str = "auto",
                 copy: bool = True, rng=0, n_jobs: int | None = None, basis: str = "code", refine_levels=None):
        self.encoder = encoder
        self.basis = basis
        self.refine_levels = refine_levels
        self.n_components = n_components
        self.solver = solver
        self.copy = copy
        self.rng = rng
        self.n_jobs = n_jobs

    # ------------------------------------------------------------------ validation
    def _codes(self, x, name: str = "X") -> np.ndarray:
        x = self._code_matrix(x, name)
        x = x.astype(float, copy=False)
        if not np.isfinite(x).all():
            raise ParameterError(f"{name}: contains NaN or infinity")
        return x

    def _code_matrix(self, x, name: str) -> np.ndarray:
        """Codes (N, D) of codes or meshes (N, V, 3), any float dtype kept (a float32 memmap is
        not copied); checked against the fitted length."""
        if isinstance(x, RowFile):  # codes on disk: checked by their header, read in blocks
            if x.ndim != 2 or x.dtype.kind != "f":
                raise ParameterError(f"{name}: {x!r}, expected float codes (N, D) on disk")
            if hasattr(self, "n_features_in_") and x.shape[1] != self.n_features_in_:
                raise ParameterError(f"{name}: codes have length {x.shape[1]}, expected {self.n_features_in_}")
            return x
        if not isinstance(x, np.ndarray):
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
        if not np.issubdtype(x.dtype, np.number):
            raise ParameterError(f"{name}: dtype {x.dtype}, expected floating-point codes")
        if hasattr(self, "n_features_in_") and x.shape[1] != self.n_features_in_:
            raise ParameterError(f"{name}: codes have length {x.shape[1]}, expected {self.n_features_in_} "
                                 "(the length the shape space was fitted on)")
        return x

    def _require_fit(self):
        if not hasattr(self, "components_"):
            raise ParameterError("ShapeSpace is not fitted; call fit(codes) first")

    def _require_encoder(self, what: str):
        if self.encoder is None:
            raise ParameterError(f"ShapeSpace.{what} needs an encoder; construct ShapeSpace(encoder, ...)")

    # ------------------------------------------------------------------ estimator API
    def fit(self, X, y=None, *, select=None, vertices=None) -> "ShapeSpace":
        """Fit on codes (N, D) (float64 or float32, e.g. a memmap) or meshes (N, V, 3).

        ``select`` (boolean mask or indices) restricts the fit to some rows, e.g. the rest-pose
        scans for a shape-only space. Steps (as ``sklearn.decomposition.PCA._fit``): validate X
        and ``n_components`` once, resolve the solver, then ``_fit_full``, ``_fit_truncated``
        or, with ``basis="vertex"``, ``_fit_vertex_basis``: ``vertices`` (N, V, 3), the bodies of
        the rows of X (before ``select``) when at hand, saves decoding them (meshes as X are used
        as they are).
        """
        for name in [n for n in ("components_", "n_features_in_") if hasattr(self, n)]:
            delattr(self, name)  # a refit may change the code length
        if vertices is None and np.ndim(X) == 3:
            vertices = X
        x = self._code_matrix(X, "X")
        if vertices is not None:
            vertices = np.asarray(vertices)
            if vertices.ndim != 3 or len(vertices) != len(x) or vertices.shape[2] != 3:
                raise ParameterError(f"vertices: shape {vertices.shape}, expected ({len(x)}, V, 3): the bodies of "
                                     "the rows of X")
        if select is not None:
            if isinstance(x, RowFile):
                raise ParameterError("select: not with codes on disk (a RowFile); write only the selected codes")
            x = x[np.asarray(select)]
            vertices = None if vertices is None else vertices[np.asarray(select)]
        n, d = x.shape
        if n < 2:
            raise ParameterError(f"X: {n} sample(s) selected, expected at least 2 to fit a PCA")
        nc = self.n_components
        if not (nc is None or (isinstance(nc, numbers.Integral) and not isinstance(nc, bool) and nc >= 1)
                or (isinstance(nc, numbers.Real) and not isinstance(nc, numbers.Integral) and 0 < nc < 1)):
            raise ParameterError(f"n_components={nc!r}, expected None, an int >= 1 or a float in (0, 1)")
        if self.basis not in BASES:
            raise ParameterError(f"basis={self.basis!r}, expected one of {', '.join(BASES)}")
        vertex_basis = self.basis != "code" and not getattr(self.encoder, "is_linear", True)
        solver = resolve_solver(self.solver, n, d, nc)
        if vertex_basis and solver != "full":
            raise ParameterError(f"basis={self.basis!r} needs the exact PCA (solver='full'); got solver={self.solver!r} "
                                 f"for {n} x {d} codes")
        if solver == "krylov" and not (nc is None or isinstance(nc, numbers.Integral)):
            raise ParameterError(f"n_components={nc!r}: a variance fraction needs the exact PCA (solver='full'); "
                                 f"the Krylov solver (chosen for {n} x {d} codes, > {FULL_PCA_MAX_BYTES / 1e9:.0f} GB "
                                 "in float64) needs an int")
        if vertex_basis:
            self._fit_vertex_basis(x, n, d, vertices)
        elif solver == "full":
            self._fit_full(x, n, d)
        else:
            self._fit_truncated(x, n, d)
        self.solver_ = solver
        self.basis_ = self.basis
        if not vertex_basis:
            # An affine decoder's codes are vertex offsets: its PCA is already the vertex order
            # (and the vertex fit is the code projection: nothing to refine).
            self.vertex_variance_ = self.explained_variance_.copy() if self.basis != "code" else None
            self.refine_levels_ = np.zeros((0, 2), dtype=np.int64) if self.basis == "refined" else None
            self.refine_report_ = None
        return self

    def _fit_full(self, x: np.ndarray, n: int, d: int) -> None:
        """Exact PCA in float64 (Gram matrix eigen-decomposition, ``solvers.pca_full``)."""
        if isinstance(x, RowFile):  # the exact solver needs the codes in memory (at most FULL_PCA_MAX_BYTES)
            x = x.read(0, n).astype(np.float64, copy=False)
        own = x.dtype == np.float64 and not self.copy
        x = x if own else np.array(x, dtype=np.float64)
        mean = x.mean(axis=0)
        if not np.isfinite(mean).all():  # a NaN or infinity anywhere reaches its column's mean
            raise ParameterError("X: contains NaN or infinity")
        kept = {}

        def n_keep(s):  # called by pca_full once x is centred: only the kept components are formed
            kept["total"] = float(np.einsum("ij,ij->", x, x)) / (n - 1)
            kept["k"] = self._n_keep(s ** 2 / (n - 1), kept["total"], n, d)
            return kept["k"]

        s, vt = pca_full(x, mean, n_keep)               # centres x in place
        self._set(mean, s, vt, s ** 2 / (n - 1), kept["total"], n, d, kept["k"])

    def _fit_truncated(self, x: np.ndarray, n: int, d: int) -> None:
        """Leading components by the randomized block Krylov method (``solvers.pca_block_krylov``),
        on x as it is (float32 ok, never copied); mean and total variance accumulated in float64."""
        if x.dtype not in (np.float32, np.float64) and not isinstance(x, RowFile):
            x = x.astype(np.float64)
        mean, scatter = mean_and_scatter(x)
        if not (np.isfinite(mean).all() and np.isfinite(scatter)):
            raise ParameterError("X: contains NaN or infinity")
        limit = min(n - 1, d)
        k = min(limit, MAX_DEFAULT_COMPONENTS) if self.n_components is None else int(self.n_components)
        if not 1 <= k <= limit:
            raise ParameterError(f"n_components={self.n_components}, expected 1..{limit} for {n} samples "
                                 f"of length {d}")
        s, vt = pca_block_krylov(x, mean, k, rng=self.rng, n_jobs=self.n_jobs)
        self._set(mean, s, vt, s ** 2 / (n - 1), scatter / (n - 1), n, d, k)

    def _fit_vertex_basis(self, x: np.ndarray, n: int, d: int, vertices=None) -> None:
        """Components ordered by vertex variance (``solvers.vertex_ordered_basis``): the bodies
        (``vertices``, or the codes decoded: N decodes) aligned rigidly by generalized
        Procrustes (``VertexEncoder``), as vertex PCA sees them. Holds (N, 3V) float64
        vertices in memory beside the codes."""
        x = x.read(0, n) if isinstance(x, RowFile) else x
        x = np.array(x, dtype=np.float64)                  # centred in place below
        if not np.isfinite(x).all():
            raise ParameterError("X: contains NaN or infinity")
        mean = x.mean(axis=0)
        enc = self.encoder
        if vertices is not None:
            bodies = np.asarray(vertices, dtype=np.float64)
            if bodies.shape[1] != enc.n_vertices:
                raise ParameterError(f"vertices: {bodies.shape[1]} vertices a body, the encoder's meshes have "
                                     f"{enc.n_vertices}")
        else:
            bodies = np.empty((n, enc.n_vertices, 3))
            for s in range(0, n, DECODE_BATCH):
                bodies[s:s + DECODE_BATCH] = enc.decode(x[s:s + DECODE_BATCH])
        aligned = VertexEncoder(bodies.mean(axis=0), enc.faces).fit(bodies).encode(bodies)
        if self.basis != "refined":
            del bodies
        comps, vertex_var = vertex_ordered_basis(x, mean, aligned)    # centres x
        del aligned
        total = float(np.einsum("ij,ij->", x, x)) / (n - 1)
        # n_components as a count, or a fraction of the vertex variance (the order's measure; the
        # vertex components hold all of it).
        k = self._n_keep(vertex_var, float(vertex_var.sum()), n, d)
        comps = comps[:k]
        self.refine_levels_, self.refine_report_ = None, None
        if self.basis == "refined":
            levels = self._refine_levels(k)
            if len(levels):
                self._set(mean, np.ones(k), comps, np.ones(k), total, n, d, k)
                comps, self.refine_report_ = refine_basis(self, bodies, levels)
            self.refine_levels_ = levels
            del bodies
        coefficients = x @ comps.T
        var = np.einsum("ij,ij->j", coefficients, coefficients) / (n - 1)    # code variance along each
        self._set(mean, np.sqrt(var * (n - 1)), comps, var, total, n, d, k)
        self.vertex_variance_ = vertex_var[:k]

    def _refine_levels(self, k: int) -> np.ndarray:
        """The (L, 2) levels of ``basis="refined"`` for k kept components: ``refine_levels``
        checked, or the default ones cut to k (a span past k cut to k, a level with k >= its
        cut span dropped)."""
        if self.refine_levels is not None:
            return check_levels(self.refine_levels, k)
        levels = [(lk, min(span, k)) for lk, span in DEFAULT_LEVELS if lk < min(span, k)]
        return check_levels(levels, k) if levels else np.zeros((0, 2), dtype=np.int64)

    def _set(self, mean, s, vt, var, total, n, d, k) -> None:
        self.mean_ = np.asarray(mean, dtype=np.float64)
        self.components_ = vt[:k]
        self.singular_values_ = s[:k]
        self.explained_variance_ = var[:k]
        self.explained_variance_ratio_ = var[:k] / total if total > 0 else np.zeros(k)
        self.total_variance_ = float(total)
        self.n_components_, self.n_samples_, self.n_features_in_ = int(k), int(n), int(d)

    def _n_keep(self, var, total, n, d) -> int:
        """Components kept by the exact solver: ``n_components`` against the ``len(var)``
        components with variance (the numerical rank)."""
        nc = self.n_components
        if nc is None:
            return int(max(min(len(var), MAX_DEFAULT_COMPONENTS), 1))
        if isinstance(nc, numbers.Integral):
            if not 1 <= nc <= len(var):
                raise ParameterError(f"n_components={nc}, expected 1..{len(var)} (the components with variance "
                                     f"among {n} samples of length {d})")
            return int(nc)
        cum = np.cumsum(var) / total if total > 0 else np.ones_like(var)
        return int(min(np.searchsorted(cum, nc) + 1, len(var)))

    # ------------------------------------------------------------------ state
    def to_arrays(self, prefix: str = "pca_") -> dict[str, np.ndarray]:
        """The learned state as flat arrays for an npz file: ``mean`` (D,) float64, ``components``
        (K, D) float32 (half the file; a model keeps its components float32-exact, so it loads
        bit-exactly), ``explained_variance``, ``explained_variance_ratio``, ``singular_values``
        (K,) float64, ``n_samples`` () int64, with ``basis_ == "vertex"`` or ``"refined"`` its
        ``vertex_variance`` (K,) float64, and with ``"refined"`` its ``refine_levels`` (L, 2)
        (whole numbers, stored float64) (their presence says the basis; a reader that knows
        neither takes the components as they are, which is all the refinement changed)."""
        self._require_fit()
        basis = getattr(self, "basis_", "code")
        extra = ({} if basis == "code" else
                 {prefix + "vertex_variance": np.asarray(self.vertex_variance_, dtype=np.float64)})
        if basis == "refined":
            # float64 (small integers, exact) like every other shape-space array: a reader that
            # does not know the field (format_version 3 files before it) checks it as one of its
            # floats and loads the components, which are all the refinement changed.
            extra[prefix + "refine_levels"] = np.asarray(self.refine_levels_, dtype=np.float64).reshape(-1, 2)
        return {**extra, prefix + "mean": np.asarray(self.mean_, dtype=np.float64),
                prefix + "components": np.asarray(self.components_, dtype=np.float32),
                prefix + "explained_variance": np.asarray(self.explained_variance_, dtype=np.float64),
                prefix + "explained_variance_ratio": np.asarray(self.explained_variance_ratio_, dtype=np.float64),
                prefix + "singular_values": np.asarray(self.singular_values_, dtype=np.float64),
                prefix + "n_samples": np.asarray(self.n_samples_, dtype=np.int64)}

    @classmethod
    def from_arrays(cls, arrays, prefix: str = "pca_", encoder=None) -> "ShapeSpace":
        """A fitted ShapeSpace from ``to_arrays`` output (names, shapes and finiteness checked;
        raises ParameterError naming the array)."""
        names = ("mean", "components", "explained_variance", "explained_variance_ratio", "singular_values",
                 "n_samples")
        missing = [prefix + s for s in names if prefix + s not in arrays]
        if missing:
            raise ParameterError(f"shape space: arrays {', '.join(missing)} missing")
        mean, comps, var, ratio, sv = (np.asarray(arrays[prefix + s], dtype=np.float64) for s in names[:5])
        n_samples = np.asarray(arrays[prefix + "n_samples"])
        if comps.ndim != 2 or mean.shape != (comps.shape[1],):
            raise ParameterError(f"shape space: '{prefix}components' {comps.shape} and '{prefix}mean' {mean.shape}, "
                                 "expected (K, D) and (D,)")
        for s, a in zip(names[2:5], (var, ratio, sv)):
            if a.shape != (len(comps),):
                raise ParameterError(f"shape space: '{prefix}{s}' has shape {a.shape}, expected ({len(comps)},)")
        for s, a in zip(names[:5], (mean, comps, var, ratio, sv)):
            if not np.isfinite(a).all():
                raise ParameterError(f"shape space: '{prefix}{s}' contains NaN or infinity")
        if n_samples.shape != () or n_samples.dtype.kind not in "iu" or int(n_samples) < 0:
            raise ParameterError(f"shape space: '{prefix}n_samples' is {n_samples!r}, expected a count >= 0")
        if encoder is not None and mean.shape[0] != encoder.n_features_:
            raise ParameterError(f"shape space: codes of length {mean.shape[0]}, the encoder makes "
                                 f"{encoder.n_features_}")
        basis, vertex_var = "code", None
        if prefix + "vertex_variance" in arrays:
            basis = "vertex"
            vertex_var = np.asarray(arrays[prefix + "vertex_variance"], dtype=np.float64)
            if vertex_var.shape != (len(comps),) or not np.isfinite(vertex_var).all():
                raise ParameterError(f"shape space: '{prefix}vertex_variance' has shape {vertex_var.shape}, "
                                     f"expected ({len(comps)},) finite values")
        levels = None
        if prefix + "refine_levels" in arrays:
            raw = np.asarray(arrays[prefix + "refine_levels"])
            whole = (raw.dtype.kind in "iu" or (raw.dtype.kind == "f" and np.isfinite(raw).all()
                                                 and (raw == np.round(raw)).all()))
            if vertex_var is None or raw.ndim != 2 or raw.shape[1] != 2 or not whole:
                raise ParameterError(f"shape space: '{prefix}refine_levels' has shape {raw.shape} and dtype "
                                     f"{raw.dtype}, expected (L, 2) whole numbers beside '{prefix}vertex_variance'")
            raw = raw.astype(np.int64)
            basis, levels = "refined", (check_levels(raw, len(comps)) if len(raw) else raw)
        space = cls(encoder, n_components=len(comps), basis=basis,
                    refine_levels=None if levels is None else levels.tolist())
        total = float(var[0] / ratio[0]) if len(var) and ratio[0] > 0 else float(var.sum())
        space._set(mean, sv, comps, var, total, int(n_samples), mean.shape[0], len(comps))
        space.explained_variance_ratio_ = ratio
        space.basis_, space.vertex_variance_ = basis, vertex_var
        space.refine_levels_, space.refine_report_ = levels, None
        return space

    def transform(self, X) -> np.ndarray:
        """Coefficients (N, K) of codes (N, D) or meshes (N, V, 3)."""
        self._require_fit()
        x = self._codes(X)
        if len(x) > SMALL_TRANSFORM_ROWS:
            return (x - self.mean_) @ self.components_.T
        # A few codes: the product reads all K x D components once (memory-bound), and two BLAS
        # threads spinning on a loaded machine made it 5x slower in wall time, 9x in CPU time
        # (3 codes x 40 components of an RRE model: 0.24 s against 0.045 s at load 9).
        with single_threaded_blas():
            return (x - self.mean_) @ self.components_.T

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
        t = truncnorm_rvs(lo, hi, (int(n), k), rng=as_generator(rng))
        z = np.zeros((int(n), self.n_components_))
        z[:, :k] = t * np.sqrt(self.explained_variance_[:k])
        return z

    def sample(self, n: int, n_components: int | None = None, sigma_range=3.0, rng=None) -> np.ndarray:
        """Random bodies (n, V, 3): ``reconstruct(sample_coefficients(...))``."""
        self._require_encoder("sample")
        return self.reconstruct(self.sample_coefficients(n, n_components, sigma_range, rng))

    def project(self, vertices, faces=None, *, method: str = "vertex", n_components: int | None = None) -> np.ndarray:
        """Coefficients (N, K) of registered meshes (V, 3) or (N, V, 3), in any rigid placement.

        ``method``: "vertex" (default) fits the coefficients to the mesh in vertex space through
        the decoder (``shape.vertex_fit``: the body ``reconstruct`` gives is as close to the mesh
        as the model allows, after a rigid alignment); "code" projects the mesh's code
        orthogonally on the components (``transform(encode(vertices))``: ~one encode, but with
        the relative rotation encoding it minimizes the code's error, and the decoded body can
        stand in another pose than the mesh, docs/encoding.md). For the vertex encoding the two
        are the same. ``n_components``: fit only the first k (the rest 0; default all).
        """
        self._require_encoder("project")
        self._require_fit()
        if method not in PROJECTIONS:
            raise ParameterError(f"method={method!r}, expected one of {', '.join(PROJECTIONS)}")
        k = self.n_components_ if n_components is None else n_components
        if isinstance(k, bool) or not isinstance(k, numbers.Integral) or not 1 <= k <= self.n_components_:
            raise ParameterError(f"n_components={n_components!r}, expected an int in 1..{self.n_components_}")
        z = self.transform(self.encoder.encode(vertices, faces))
        z[:, int(k):] = 0.0
        if method == "code":
            return z
        return fit_coefficients(self, vertices, int(k), start=z).coefficients

    def reconstruct(self, coefficients, constraints=None) -> np.ndarray:
        """Bodies (N, V, 3) from coefficients (N, k) or (k,), k <= K, decoded by the encoder
        (``constraints`` as in ``encoder.decode``)."""
        self._require_encoder("reconstruct")
        return self.encoder.decode(self.inverse_transform(coefficients), constraints=constraints)
