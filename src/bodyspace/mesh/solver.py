"""Prefactored sparse solves: a symmetric positive definite factorization reused for many
right-hand sides, and the Poisson reconstruction of a mesh from per-triangle deformation
gradients (Yu et al. 2004; Hasler §3) with optional soft positional
constraints (Hasler §5.3 and Hasler §5.4).

The system matrices depend on the template only, so each is factored once and every body
afterwards costs triangular solves alone. SuperLU makes the factorization; for a symmetric
matrix its factors are ``P A P^T = L D L^T``, and the triangular solves run in a compiled loop
(numba) over all right-hand sides at once, interleaved so that each factor entry is read once
for all of them: measured 2-4x faster than SuperLU's own solve for the 3-9 right-hand sides of
a body (docs/encoding.md).
"""

from __future__ import annotations

import contextlib
from dataclasses import dataclass

import numba
import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as sla

from bodyspace.errors import MeshError
from bodyspace.mesh.operators import gradient_operator
from bodyspace.mesh.topology import vertex_components

try:  # threadpoolctl ships with scikit-learn; without it solves are just slower.
    from threadpoolctl import ThreadpoolController as _ThreadpoolController
except ImportError:  # pragma: no cover - depends on the environment
    _ThreadpoolController = None
_controller = None

# SuperLU's triangular solves call BLAS on small dense supernodes; a multi-threaded BLAS spends
# more time waking threads than computing there (measured: 9 right-hand sides on the 26,756-face
# dual Laplacian, 5 ms single-threaded, 40-70 ms with two OpenBLAS threads).
# Right-hand sides are solved in blocks of this many columns: SuperLU's cost per column grows
# with the block width past a few dozen (its work array is n x k), so wide blocks are slower.
SOLVE_BLOCK = 24


@numba.njit(cache=True, nogil=True)
def _solve9(lp, li, lx, dinv, x):
    """``L D L^T z = y`` in place for x (n, 9): each column's nine values held in scalars, so
    every factor entry is read once for all of them (measured 25% faster than a loop over a
    runtime column count)."""
    n = x.shape[0]
    for j in range(n):  # L y = P b, column by column
        a0, a1, a2, a3, a4 = x[j, 0], x[j, 1], x[j, 2], x[j, 3], x[j, 4]
        a5, a6, a7, a8 = x[j, 5], x[j, 6], x[j, 7], x[j, 8]
        for p in range(lp[j], lp[j + 1]):
            i = li[p]
            v = np.float64(lx[p])
            x[i, 0] -= v * a0
            x[i, 1] -= v * a1
            x[i, 2] -= v * a2
            x[i, 3] -= v * a3
            x[i, 4] -= v * a4
            x[i, 5] -= v * a5
            x[i, 6] -= v * a6
            x[i, 7] -= v * a7
            x[i, 8] -= v * a8
    for j in range(n - 1, -1, -1):  # L^T z = D^-1 y: rows of L^T are columns of L
        d = dinv[j]
        a0, a1, a2, a3, a4 = x[j, 0] * d, x[j, 1] * d, x[j, 2] * d, x[j, 3] * d, x[j, 4] * d
        a5, a6, a7, a8 = x[j, 5] * d, x[j, 6] * d, x[j, 7] * d, x[j, 8] * d
        for p in range(lp[j], lp[j + 1]):
            i = li[p]
            v = np.float64(lx[p])
            a0 -= v * x[i, 0]
            a1 -= v * x[i, 1]
            a2 -= v * x[i, 2]
            a3 -= v * x[i, 3]
            a4 -= v * x[i, 4]
            a5 -= v * x[i, 5]
            a6 -= v * x[i, 6]
            a7 -= v * x[i, 7]
            a8 -= v * x[i, 8]
        x[j, 0], x[j, 1], x[j, 2], x[j, 3], x[j, 4] = a0, a1, a2, a3, a4
        x[j, 5], x[j, 6], x[j, 7], x[j, 8] = a5, a6, a7, a8


@numba.njit(cache=True, nogil=True)
def _solve3(lp, li, lx, dinv, x):
    """``_solve9`` for x (n, 3): three columns (a vector field, e.g. the Poisson step's x, y,
    z) without padding them to nine (measured 1.8x faster than the padded call)."""
    n = x.shape[0]
    for j in range(n):
        a0, a1, a2 = x[j, 0], x[j, 1], x[j, 2]
        for p in range(lp[j], lp[j + 1]):
            i = li[p]
            v = np.float64(lx[p])
            x[i, 0] -= v * a0
            x[i, 1] -= v * a1
            x[i, 2] -= v * a2
    for j in range(n - 1, -1, -1):
        d = dinv[j]
        a0, a1, a2 = x[j, 0] * d, x[j, 1] * d, x[j, 2] * d
        for p in range(lp[j], lp[j + 1]):
            i = li[p]
            v = np.float64(lx[p])
            a0 -= v * x[i, 0]
            a1 -= v * x[i, 1]
            a2 -= v * x[i, 2]
        x[j, 0], x[j, 1], x[j, 2] = a0, a1, a2


@numba.njit(cache=True, nogil=True)
def ldl_solve(lp, li, lx, dinv, perm, b, out):
    """Solve ``A X = B`` with ``P A P^T = L D L^T`` for all columns of b (n, k).

    Columns go in groups of 9 (the 3x3 entries of a rotation field), or of 3 when at most three
    are left (``_solve9``, ``_solve3``).

    Args:
        lp, li, lx: strictly lower triangle of L in CSC (column pointers, row indices, values;
            values may be float32).
        dinv: (n,) ``1 / D``.
        perm: (n,) row i of A is row ``perm[i]`` of the factored matrix.
        b, out: (n, k) float64, C order; ``out`` may be ``b``.
    """
    n, k = b.shape
    for c0 in range(0, k, 9):
        w = min(9, k - c0)
        x = np.zeros((n, 3 if w <= 3 else 9))
        for i in range(n):
            for c in range(w):
                x[perm[i], c] = b[i, c0 + c]
        if w <= 3:
            _solve3(lp, li, lx, dinv, x)
        else:
            _solve9(lp, li, lx, dinv, x)
        for i in range(n):
            for c in range(w):
                out[i, c0 + c] = x[perm[i], c]


def single_threaded_blas():
    """Context in which BLAS runs on one thread (a no-op without threadpoolctl)."""
    global _controller
    if _ThreadpoolController is None:
        return contextlib.nullcontext()
    if _controller is None:  # inspecting the loaded libraries costs ~1 ms: do it once
        _controller = _ThreadpoolController()
    return _controller.limit(limits=1, user_api="blas")


class FactorizedSolver:
    """Sparse LU of a symmetric positive definite matrix, for repeated solves.

    A symmetric fill-reducing ordering with no pivoting (``diag_pivot_thresh=0``): for an SPD
    matrix that is stable and keeps the factor as sparse as a Cholesky factor. For a symmetric
    matrix the factors are used as ``L D L^T`` (``ldl_solve``); otherwise SuperLU solves.

    Args:
        matrix: (n, n) sparse, symmetric positive definite.
        dtype: factor precision; float32 halves memory traffic when the solver only serves as a
            preconditioner.
    """

    def __init__(self, matrix: sp.spmatrix, dtype=np.float64):
        matrix = sp.csc_matrix(matrix, dtype=dtype)
        if matrix.shape[0] != matrix.shape[1]:
            raise MeshError(f"solver matrix has shape {matrix.shape}, expected a square matrix")
        self.shape = matrix.shape
        self.dtype = np.dtype(dtype)
        with single_threaded_blas():
            self._lu = sla.splu(matrix, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0,
                                options={"SymmetricMode": True})
        self._ldl = None
        lu = self._lu
        d = lu.U.diagonal()
        scale = abs(matrix).max() if matrix.nnz else 1.0
        if (np.array_equal(lu.perm_r, lu.perm_c) and (d > 0).all()
                and abs(matrix - matrix.T).max() <= 1e-12 * scale):
            low = sp.tril(lu.L, k=-1).tocsc()
            low.sort_indices()
            self._ldl = (low.indptr.astype(np.int64), low.indices.astype(np.int64),
                         low.data.astype(self.dtype), 1.0 / d.astype(float), lu.perm_c.astype(np.int64))

    @property
    def factor_nnz(self) -> int:
        """Non-zeros in the L and U factors (a measure of solve cost)."""
        return int(self._lu.L.nnz + self._lu.U.nnz)

    def solve(self, rhs: np.ndarray) -> np.ndarray:
        """Solve ``A x = rhs`` for rhs (n,) or (n, k); returns float64 of the same shape."""
        rhs = np.asarray(rhs)
        if rhs.shape[0] != self.shape[0]:
            raise MeshError(f"right-hand side has {rhs.shape[0]} rows, expected {self.shape[0]}")
        if self._ldl is not None:
            b = np.ascontiguousarray(rhs.reshape(self.shape[0], -1), dtype=float)
            out = np.empty_like(b)
            ldl_solve(*self._ldl, b, out)
            return out.reshape(rhs.shape)
        if rhs.ndim == 1:
            with single_threaded_blas():
                return self._lu.solve(rhs.astype(self.dtype)).astype(float)
        out = np.empty(rhs.shape, dtype=float)
        with single_threaded_blas():
            for s in range(0, rhs.shape[1], SOLVE_BLOCK):
                block = np.asfortranarray(rhs[:, s:s + SOLVE_BLOCK], dtype=self.dtype)
                out[:, s:s + SOLVE_BLOCK] = self._lu.solve(block)
        return out


@dataclass(frozen=True)
class PositionConstraints:
    """Soft positional constraints for the Poisson step.

    Attributes:
        indices: (K,) vertex indices.
        positions: (K, 3) target positions, or (N, K, 3) one set per body of a batch.
        weight: strength relative to a vertex's own Poisson stencil (the mean diagonal of the
            cotangent Laplacian): 1 pulls a vertex about as hard as its neighbours hold it;
            large values (1e3 and up) make the constraints nearly hard.
    """

    indices: np.ndarray
    positions: np.ndarray
    weight: float = 100.0

    def checked(self, n_vertices: int, n_bodies: int) -> tuple[np.ndarray, np.ndarray, float]:
        """Return ``(indices (K,), positions (N, K, 3), weight)`` after validation."""
        idx = np.asarray(self.indices)
        pos = np.asarray(self.positions, dtype=float)
        if idx.ndim != 1 or len(idx) == 0 or not np.issubdtype(idx.dtype, np.integer):
            raise MeshError(f"constraints.indices: shape {idx.shape} dtype {idx.dtype}, expected (K,) integers, K >= 1")
        if idx.min() < 0 or idx.max() >= n_vertices:
            raise MeshError(f"constraints.indices: values {idx.min()}..{idx.max()}, expected 0..{n_vertices - 1}")
        if len(np.unique(idx)) != len(idx):
            raise MeshError("constraints.indices: repeated vertex index, expected each vertex at most once")
        if pos.shape == (len(idx), 3):
            pos = np.broadcast_to(pos, (n_bodies, len(idx), 3))
        if pos.shape != (n_bodies, len(idx), 3):
            raise MeshError(f"constraints.positions: shape {pos.shape}, expected ({len(idx)}, 3) or "
                            f"({n_bodies}, {len(idx)}, 3)")
        if not np.isfinite(pos).all():
            raise MeshError("constraints.positions: contain NaN or infinity")
        if not (np.isfinite(self.weight) and self.weight > 0):
            raise MeshError(f"constraints.weight: {self.weight}, expected a positive number")
        return idx.astype(np.int64), pos, float(self.weight)


class PoissonSolver:
    """Vertices from per-triangle deformation gradients, by a prefactored Poisson solve.

    Minimizes ``sum_f area_f |grad_f(x) - U_f|^2`` over vertex positions x (V, 3), where
    ``grad_f`` is the gradient on the rest triangle f (``gradient_operator``) and ``U_f`` the
    prescribed deformation gradient (only its action on the rest triangle's plane matters).
    The normal equations are ``L x = G^T A U`` with L the cotangent Laplacian of the rest
    mesh, fixed per template, so L is factored once. L is singular (translations): one
    vertex per connected component is pinned ("anchored"); callers place the result.

    With ``PositionConstraints`` the energy gains ``w sum_k |x_k - c_k|^2``; that matrix is
    factored once per distinct (indices, weight) and cached.

    Args:
        rest_vertices: (V, 3) the rest (template) mesh the gradients are relative to.
        faces: (F, 3) int.
    """

    def __init__(self, rest_vertices: np.ndarray, faces: np.ndarray):
        rest_vertices = np.asarray(rest_vertices, dtype=float)
        self.faces = np.asarray(faces)
        self.n_vertices = len(rest_vertices)
        g = gradient_operator(rest_vertices, self.faces)
        v = rest_vertices[self.faces]
        self.area = 0.5 * np.linalg.norm(np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0]), axis=1)
        # divergence (V, 3F): area-weighted per-face vectors to vertex right-hand sides
        self.divergence = (g.T @ sp.diags(np.repeat(self.area, 3))).tocsr()
        self.laplacian = (self.divergence @ g).tocsr()
        self.n_components, self.component = vertex_components(self.faces, self.n_vertices)
        # Pin the first vertex of each component.
        self.anchors = np.array([np.flatnonzero(self.component == c)[0] for c in range(self.n_components)])
        self._stencil = float(self.laplacian.diagonal().mean())
        self._factors: dict[tuple, tuple[FactorizedSolver, np.ndarray]] = {}
        self._factor(self.anchors, np.empty(0, dtype=np.int64), 0.0)

    def _factor(self, pinned: np.ndarray, soft: np.ndarray, weight: float):
        key = (tuple(pinned.tolist()), tuple(soft.tolist()), weight)
        if key not in self._factors:
            a = self.laplacian
            if len(soft):
                a = a + sp.csr_matrix((np.full(len(soft), weight * self._stencil), (soft, soft)), shape=a.shape)
            free = np.setdiff1d(np.arange(self.n_vertices), pinned)
            a = a.tocsr()[free][:, free]
            if len(self._factors) >= 16:  # keep the cache bounded (interactive handles)
                self._factors.pop(next(iter(self._factors)))
            self._factors[key] = (FactorizedSolver(a), free)
        return self._factors[key]

    def rhs(self, gradients: np.ndarray) -> np.ndarray:
        """Right-hand sides (V, 3N) for deformation gradients (N, F, 3, 3); column 3n+c is
        coordinate c of body n."""
        g = np.asarray(gradients)
        n, nf = g.shape[0], g.shape[1]
        # The gradient of coordinate c on face f is row c of U_f: lay out rows (f, d), columns (n, c).
        return self.divergence @ np.ascontiguousarray(g.transpose(1, 3, 0, 2)).reshape(nf * 3, n * 3)

    def solve(self, gradients: np.ndarray, constraints: PositionConstraints | None = None,
              pinned_positions: np.ndarray | None = None) -> np.ndarray:
        """Vertices (N, V, 3) from deformation gradients (N, F, 3, 3).

        Without constraints each component's anchor vertex is at the origin (or where
        ``pinned_positions`` (N, V, 3) has it, if given). With constraints, components holding
        no constrained vertex keep their anchor pinned at ``pinned_positions`` (required then);
        the others float, held by the soft constraints.
        """
        g = np.asarray(gradients, dtype=float)
        n = g.shape[0]
        b = self.rhs(g)  # (V, 3N)
        if constraints is None:
            pinned, soft, weight = self.anchors, np.empty(0, dtype=np.int64), 0.0
        else:
            soft, targets, weight = constraints.checked(self.n_vertices, n)
            held = np.unique(self.component[soft])
            pinned = self.anchors[np.setdiff1d(np.arange(self.n_components), held)]
            if len(pinned) and pinned_positions is None:
                raise MeshError("a component without constrained vertices needs pinned_positions to be placed")
            b[soft] += weight * self._stencil * targets.transpose(1, 0, 2).reshape(len(soft), 3 * n)
        solver, free = self._factor(pinned, soft, weight)
        x = np.zeros((self.n_vertices, 3 * n))
        if len(pinned) and pinned_positions is not None:
            x[pinned] = np.asarray(pinned_positions)[:, pinned, :].transpose(1, 0, 2).reshape(len(pinned), 3 * n)
            b = b - self.laplacian[:, pinned] @ x[pinned]
        x[free] = solver.solve(b[free])
        return x.reshape(self.n_vertices, n, 3).transpose(1, 0, 2)
