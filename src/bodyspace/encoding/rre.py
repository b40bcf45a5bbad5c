"""Relative rotation encoding (RRE) of registered meshes (Hasler et al. 2009, Sec. 3).

Encoding, per triangle i of a mesh registered to the template:

1. deformation gradient ``U_i`` from the template triangle to the scan triangle (Sumner and
   Popovic's frame with a scaled normal, so ``U_i`` is a full 3x3 map);
2. polar decomposition ``U_i = R_i S_i``: rotation R_i, symmetric stretch S_i;
3. relative rotations to the edge neighbours (Eq. 8), one per edge slot. Eq. 8 is written for
   the rotations ``Q_i = R_i^T`` that take each scan triangle back to its rest frame:
   ``Q_ij = Q_i Q_j^-1 = R_i^T R_j``. That order is the one a global turn of the body
   (``R_i -> G R_i``) leaves unchanged; ``R_i R_j^-1`` would change with it;
4. everything relative to the *mean model*, the average of all components of all fitted scans:
   ``r_ij = log(Q_ij M_ij^-1)`` with ``M_ij = exp(mean of log Q_ij)`` and ``s_i = S_i - mean S_i``.

Code layout, 15 numbers per triangle, triangle-major (``code.reshape(F, 15)``):
``[r_i0 (3), r_i1 (3), r_i2 (3), s_00, s_01, s_02, s_11, s_12, s_22]``, where slot k is the
triangle's edge ``(faces[i, k], faces[i, (k+1) % 3])`` and ``r`` are rotation vectors (axis times
angle, radians). A boundary edge has no neighbour: its three numbers are zero in every code and
ignored by ``decode`` (``slot_mask_`` says which), so every code has the same length, 15 F.

Decoding, two sparse solves (Sec. 3):

1. rotations from the relative rotations by least squares on Eq. 9, ``Q_ij Q_j - Q_i = 0`` for
   every stored pair (both directions), with one *anchor* triangle per connected part fixed to
   the identity (the "global rotation fixed");
2. projection onto SO(3) (the polar factor, i.e. the SVD projection, computed by a Newton
   iteration), since a modified code gives matrices with scale or shear;
3. ``U_i = R_i S_i`` and Poisson reconstruction of the vertices (``mesh.solver.PoissonSolver``),
   with optional soft positional constraints;
4. placement: each connected part is moved rigidly (Kabsch: rotation and translation, no
   scale) onto the same vertices of the mean model. A decoded body is therefore never at an
   arbitrary offset: it overlaps the mean model as well as a rigid motion allows, and a round
   trip ``decode(encode(x))`` returns ``x`` rigidly aligned to the mean model. The mean
   model's own vertices ``mean_vertices_`` are placed the same way onto the template.

How step 1 avoids a factorization per body (its matrix changes with every code): the normal
matrix of Eq. 9 is a *connection Laplacian*, diagonal blocks ``2 deg_i I`` (relative rotations
are orthogonal) and off-diagonal blocks ``-(Q_ij + Q_ji^T)``. In the gauge of the rotations
``T_i`` chained from the anchor along a breadth-first spanning tree, it becomes ``2 L (x) I``
(L: the dual graph's uniform Laplacian, fixed per template) plus a perturbation that vanishes
wherever the code is consistent. So ``2 L`` is factored once per template, and each body is
solved by block conjugate gradients preconditioned with it. An unmodified code (a round trip)
is consistent: the tree rotations solve it exactly and no step runs. For a modified code the
tree gauge piles the code's holonomy onto the edges that close tree loops; a Gauss-Newton
step in the Lie algebra (a solve with the same ``2 L``) first spreads it, after which mild
codes (interpolations between nearby bodies) converge in 1-3 steps. Codes mismatched on many
edges or with a strong defect (PCA samples, LBS fold-overs combined), or that the first steps
predict to need more than ``max_iter`` steps, would cost more CG steps than a factorization
and are solved exactly by ``FixedPatternRotationSolver``: the system's pattern is analysed once
per template and each body costs a numeric LDL^T refactorization (qdldl).
``rotation_solver="exact"`` uses that for every body; ``"direct"`` assembles and factors the
full system with SuperLU for every body (the baseline the benchmark compares against).
See docs/encoding.md for the measurements behind these choices.
"""

from __future__ import annotations

import os
import threading
import warnings
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as sla

from bodyspace.encoding.vertex import check_codes, check_scans, rigid_procrustes
from bodyspace.errors import MeshError
from bodyspace.mesh.geometry import boundary_loops, capped_volume, check_mesh
from bodyspace.mesh.operators import dual_laplacian, triangle_frames
from bodyspace.mesh.solver import FactorizedSolver, PoissonSolver, PositionConstraints, single_threaded_blas
from bodyspace.mesh.topology import (check_topology, dual_graph, face_components, spanning_forest,
                                     vertex_components)
from scipy.sparse.csgraph import breadth_first_order

try:  # LDL^T with a reusable symbolic analysis (Apache-2.0); without it SuperLU per body.
    import qdldl as _qdldl
except ImportError:  # pragma: no cover - depends on the environment
    _qdldl = None

FEATURES_PER_FACE = 15
# A scan triangle whose area shrank below this fraction of its template area is degenerate:
# its deformation gradient is (nearly) singular and has no meaningful polar decomposition.
DEGENERATE_AREA_RATIO = 1e-8
# Bodies decoded per task. Arrays are ~6 MB per body on the 26,756-face template; several
# bodies at once fall out of cache and were slower per body (measured: 29 ms at 1, 47 at 8), so
# batches gain from threads (``n_jobs``), not from wider arrays.
DECODE_CHUNK = 1
# Block-CG steps before the convergence rate is judged, and the fraction of edge slots whose
# tree-gauge mismatch |E - I| exceeds 0.1 beyond which a code goes straight to the direct
# solve (see solve_rotations_pcg).
PROBE_STEPS = 3
DIRECT_FRACTION = 0.002
# A slot mismatched by more than this in the tree gauge (|E - I|_F = 1: a ~41 degree defect,
# typically where near-180-degree relative rotations of an LBS fold-over were combined) marks
# a vortex that CG resolves only in 15-70 steps (measured): such codes are factored at once.
DEFECT_MISMATCH = 1.0
# Gauss-Newton rounds smoothing the tree gauge before CG (see _smooth_gauge).
SMOOTH_ROUNDS = 1
# Encoding works on one body at a time: its arrays (~0.2 MB each) stay in cache, which made
# encoding 2x faster per body than 16 at once (measured).
ENCODE_CHUNK = 1
_STRETCH_ROWS = np.array([0, 0, 0, 1, 1, 2])
_STRETCH_COLS = np.array([0, 1, 2, 1, 2, 2])


# ---------------------------------------------------------------------------- rotations
# Quaternions are (..., 4) arrays (w, x, y, z). The arithmetic runs on *component-first*
# arrays (a leading axis of 4 quaternion or 9 matrix entries, each a contiguous array over all
# faces): elementwise passes over contiguous memory are 3-5x faster in numpy than np.cross,
# np.stack or matmul on stacks of tiny matrices.

def _planar(a: np.ndarray, n: int) -> np.ndarray:
    """(..., n) -> contiguous (n, ...)."""
    return np.ascontiguousarray(np.moveaxis(a, -1, 0))


def _qmul(p, q):
    """Hamilton product of component-first quaternions (4, ...): rotation q, then p."""
    pw, px, py, pz = p
    qw, qx, qy, qz = q
    return np.stack([pw * qw - px * qx - py * qy - pz * qz,
                     pw * qx + px * qw + py * qz - pz * qy,
                     pw * qy - px * qz + py * qw + pz * qx,
                     pw * qz + px * qy - py * qx + pz * qw])


def _qconj(q):
    return np.stack([q[0], -q[1], -q[2], -q[3]])


def _qlog(q):
    """Rotation vectors (3, ...) of component-first unit quaternions (4, ...), angle in [0, pi].

    ``atan2`` keeps full precision for tiny angles, where ``arccos`` of the trace would not.
    """
    sign = np.where(q[0] < 0, -1.0, 1.0)
    w = q[0] * sign
    s = np.sqrt(q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
    small = s < 1e-8
    # angle / sin(angle / 2) = 2 atan2(s, w) / s, whose limit for s -> 0 is 2 / w.
    factor = np.where(small, 2.0 / np.maximum(w, 1e-300), 2.0 * np.arctan2(s, w) / np.where(small, 1.0, s)) * sign
    return q[1:] * factor


def _qexp(r):
    """Component-first unit quaternions (4, ...) of rotation vectors (3, ...)."""
    theta = np.sqrt(r[0] * r[0] + r[1] * r[1] + r[2] * r[2])
    small = theta < 1e-6
    # sin(theta / 2) / theta, with its Taylor series near 0.
    sinc = np.where(small, 0.5 - theta * theta / 48.0, np.sin(0.5 * theta) / np.where(small, 1.0, theta))
    return np.concatenate([np.cos(0.5 * theta)[None], r * sinc])


def _qmatrix(q):
    """Row-major entries (9, ...) of the rotation matrices of unit quaternions (4, ...)."""
    w, x, y, z = q
    xx, yy, zz = x * x, y * y, z * z
    xy, xz, yz, wx, wy, wz = x * y, x * z, y * z, w * x, w * y, w * z
    return np.stack([1 - 2 * (yy + zz), 2 * (xy - wz), 2 * (xz + wy),
                     2 * (xy + wz), 1 - 2 * (xx + zz), 2 * (yz - wx),
                     2 * (xz - wy), 2 * (yz + wx), 1 - 2 * (xx + yy)])


def _qfrom_matrix(m):
    """Component-first unit quaternions (4, ...), w >= 0, of row-major rotations (9, ...).

    Shepperd (1978): the largest of 4w^2, 4x^2, 4y^2, 4z^2 is the pivot, so no branch divides
    by a small number. Most rotations here are far from 180 degrees, so the w pivot is taken
    for all and the full selection made only where ``1 + trace`` is small.
    """
    m00, m01, m02, m10, m11, m12, m20, m21, m22 = m
    tr = m00 + m11 + m22
    q = np.stack([1 + tr, m21 - m12, m02 - m20, m10 - m01])
    hard = 1 + tr < 0.5  # rotation angle above ~138 degrees
    if hard.any():
        h = [c[hard] for c in m]
        h00, h01, h02, h10, h11, h12, h20, h21, h22 = h
        htr = h00 + h11 + h22
        cand = np.stack([
            np.stack([1 + htr, h21 - h12, h02 - h20, h10 - h01]),
            np.stack([h21 - h12, 1 + h00 - h11 - h22, h01 + h10, h02 + h20]),
            np.stack([h02 - h20, h01 + h10, 1 - h00 + h11 - h22, h12 + h21]),
            np.stack([h10 - h01, h02 + h20, h12 + h21, 1 - h00 - h11 + h22]),
        ])  # (pivot, component, k): row p is 4 q_p q
        k = np.argmax(np.stack([htr, h00, h11, h22]), axis=0)
        q[:, hard] = np.take_along_axis(cand, k[None, None], axis=0)[0]
    q = q / np.sqrt((q * q).sum(axis=0))
    return q * np.where(q[0] < 0, -1.0, 1.0)


def _cofactor9(x):
    """Cofactor matrices (``det(X) X^-T``, row-major (9, ...)) and determinants of (9, ...)."""
    x00, x01, x02, x10, x11, x12, x20, x21, x22 = x
    c = np.stack([x11 * x22 - x12 * x21, x12 * x20 - x10 * x22, x10 * x21 - x11 * x20,
                  x21 * x02 - x22 * x01, x22 * x00 - x20 * x02, x20 * x01 - x21 * x00,
                  x01 * x12 - x02 * x11, x02 * x10 - x00 * x12, x00 * x11 - x01 * x10])
    return c, x00 * c[0] + x01 * c[1] + x02 * c[2]


def _polar9(x, tol: float = 1e-14, max_iter: int = 60):
    """Orthogonal polar factors (9, ...) of row-major matrices (9, ...) with det != 0.

    Scaled Newton iteration (Higham 1986): ``X <- (g X + X^-T / g) / 2``, ``g = |det X|^(-1/3)``.
    Quadratic convergence; a batched SVD of 26,756 3x3 matrices costs ~50 ms, this ~5 ms.
    """
    finishing = False
    for _ in range(max_iter):
        c, det = _cofactor9(x)
        g = np.abs(det) ** (-1.0 / 3.0)
        new = 0.5 * (g * x + c / (g * det))
        if finishing:
            return new
        change = np.abs(new - x).max() if x.size else 0.0
        x = new
        if change < tol:
            break
        # Quadratic convergence: one more step after a change of 1e-7 reaches round-off.
        finishing = change < 1e-7
    return x


def quaternion_from_matrix(r: np.ndarray) -> np.ndarray:
    """Unit quaternions (..., 4), w >= 0, of rotation matrices (..., 3, 3)."""
    r = np.asarray(r, dtype=float)
    return np.moveaxis(_qfrom_matrix(_planar(r.reshape(r.shape[:-2] + (9,)), 9)), 0, -1)


def matrix_from_quaternion(q: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) of unit quaternions (..., 4)."""
    q = np.asarray(q, dtype=float)
    return np.moveaxis(_qmatrix(_planar(q, 4)), 0, -1).reshape(q.shape[:-1] + (3, 3))


def quaternion_multiply(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Hamilton product p q (..., 4): the rotation q followed by p."""
    p, q = np.broadcast_arrays(np.asarray(p, dtype=float), np.asarray(q, dtype=float))
    return np.moveaxis(_qmul(_planar(p, 4), _planar(q, 4)), 0, -1)


def quaternion_conjugate(q: np.ndarray) -> np.ndarray:
    """Inverse rotation of unit quaternions (..., 4)."""
    return q * np.array([1.0, -1.0, -1.0, -1.0])


def quaternion_log(q: np.ndarray) -> np.ndarray:
    """Rotation vectors (..., 3), angle in [0, pi], of unit quaternions (..., 4)."""
    return np.moveaxis(_qlog(_planar(np.asarray(q, dtype=float), 4)), 0, -1)


def quaternion_exp(rotvec: np.ndarray) -> np.ndarray:
    """Unit quaternions (..., 4) of rotation vectors (..., 3)."""
    return np.moveaxis(_qexp(_planar(np.asarray(rotvec, dtype=float), 3)), 0, -1)


def rotation_exp(rotvec: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) of rotation vectors (..., 3) (Rodrigues)."""
    return matrix_from_quaternion(quaternion_exp(rotvec))


def rotation_log(r: np.ndarray) -> np.ndarray:
    """Rotation vectors (..., 3) of rotation matrices (..., 3, 3)."""
    return quaternion_log(quaternion_from_matrix(r))


def polar_decomposition(u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Polar decomposition ``U = R S`` of (..., 3, 3) matrices with det(U) != 0.

    R (..., 3, 3) orthogonal with the sign of det(U) as determinant; S = R^T U symmetric.
    """
    u = np.asarray(u, dtype=float)
    r = np.moveaxis(_polar9(_planar(u.reshape(u.shape[:-2] + (9,)), 9)), 0, -1).reshape(u.shape)
    s = np.swapaxes(r, -1, -2) @ u
    return r, 0.5 * (s + np.swapaxes(s, -1, -2))


def project_to_rotations(x: np.ndarray) -> np.ndarray:
    """Nearest rotation matrices (..., 3, 3) to ``x`` in the Frobenius norm.

    The polar factor where det(x) > 0; where a grossly inconsistent code gave det <= 0, the SVD
    with the smallest singular vector flipped.
    """
    x = np.asarray(x, dtype=float)
    x9 = _planar(x.reshape(x.shape[:-2] + (9,)), 9)
    _, det = _cofactor9(x9)
    good = det > 1e-12 * np.abs(x9).max(axis=0) ** 3
    if good.all():
        return np.moveaxis(_polar9(x9), 0, -1).reshape(x.shape)
    out = np.empty_like(x)
    out[good] = np.moveaxis(_polar9(x9[:, good]), 0, -1).reshape(-1, 3, 3)
    u, _, vt = np.linalg.svd(x[~good])
    d = np.sign(np.linalg.det(u @ vt))
    u[..., :, 2] *= np.where(d == 0, 1.0, d)[..., None]
    out[~good] = u @ vt
    return out


def pack_stretch(s: np.ndarray) -> np.ndarray:
    """Upper triangle (..., 6) of symmetric (..., 3, 3): S00, S01, S02, S11, S12, S22."""
    return s[..., _STRETCH_ROWS, _STRETCH_COLS]


def unpack_stretch(p: np.ndarray) -> np.ndarray:
    """Symmetric (..., 3, 3) from (..., 6) (``pack_stretch`` order)."""
    s = np.empty(p.shape[:-1] + (3, 3))
    s[..., _STRETCH_ROWS, _STRETCH_COLS] = p
    s[..., _STRETCH_COLS, _STRETCH_ROWS] = p
    return s


# ---------------------------------------------------------------------------- Eq. 9 solvers

def tree_rotations(relative: np.ndarray, parent: np.ndarray, parent_slot: np.ndarray,
                   levels: list[np.ndarray]) -> np.ndarray:
    """Rotations (N, F, 3, 3) chained from the roots (identity) along a spanning forest.

    ``Q_c = Q_cp Q_p`` from Eq. 8, one vectorized step per tree level. Exact for a consistent
    code; for a modified one, the inconsistencies accumulate along the tree paths.

    Args:
        relative: (N, F, 3, 3, 3) ``Q_ij`` per face i and edge slot.
        parent, parent_slot, levels: from ``topology.spanning_forest``.
    """
    n, nf = relative.shape[:2]
    t = np.empty((n, nf, 3, 3))
    t[:, levels[0]] = np.eye(3)
    for level in levels[1:]:
        t[:, level] = relative[:, level, parent_slot[level]] @ t[:, parent[level]]
    return t


def _gram(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Per-body Gram matrices (N, 3, 3) of block vectors (N, F, 3, 3): ``a_n^T b_n`` with each
    body's field flattened to (3F, 3)."""
    n = a.shape[0]
    return np.swapaxes(a.reshape(n, -1, 3), 1, 2) @ b.reshape(n, -1, 3)  # BLAS, not einsum


def _times(a: np.ndarray, m: np.ndarray) -> np.ndarray:
    """Block vectors (N, F, 3, 3) times per-body (N, 3, 3) matrices from the right."""
    return (a.reshape(a.shape[0], -1, 3) @ m).reshape(a.shape)


class _GaugedRotationSystem:
    """The normal equations of Eq. 9 in the gauge ``Q_i = T_i Y_i`` (T orthogonal per face).

    Multiplying each residual ``Q_ij Q_j - Q_i`` by the orthogonal ``T_i^T`` turns Eq. 9 into
    ``E_ij Y_j - Y_i = 0`` with ``E_ij = T_i^T Q_ij T_j``. The normal matrix has diagonal blocks
    ``2 deg_i I`` and off-diagonal blocks ``-(E_ij + E_ji^T)``: exactly twice the dual-graph
    Laplacian wherever T agrees with the code (E = I). Root faces are Dirichlet rows (Y = I).
    """

    def __init__(self, e, gauge, nbr, bk, valid, roots):
        """``e`` (N, F, slot, 3, 3) is ``E_ij = T_i^T Q_ij T_j`` per face i and slot."""
        self.gauge, self.roots = gauge, roots
        n, nf = gauge.shape[:2]
        self.blocks = e + np.swapaxes(e[:, nbr, bk], -1, -2)  # (N, F, slot, 3, 3)
        self.blocks[:, ~valid] = 0.0
        self.deg2 = 2.0 * valid.sum(axis=1)[None, :, None, None]
        # The off-diagonal part as one block-diagonal CSR matrix over all bodies: row (n, i, a)
        # holds -blocks[n, i, k, a, b] at column (n, nbr[i, k], b). A sparse product is ~5x
        # faster than an einsum over gathered neighbours.
        cols = (3 * nbr[:, None, :, None] + np.arange(3)[None, None, None, :]).repeat(3, axis=1)  # (F, a, k, b)
        cols = (cols.reshape(1, -1) + 3 * nf * np.arange(n)[:, None]).ravel()
        data = -np.ascontiguousarray(self.blocks.transpose(0, 1, 3, 2, 4)).ravel()
        self.offdiag = sp.csr_matrix((data, cols, np.arange(0, len(data) + 1, 9)), shape=(3 * nf * n,) * 2)

    def apply(self, y):
        out = self.deg2 * y + (self.offdiag @ y.reshape(-1, 3)).reshape(y.shape)
        out[:, self.roots] = 0.0
        return out

    def residual_at_identity(self):
        """``-A Y`` for Y = I everywhere (the gauge rotations themselves)."""
        r = self.blocks.sum(axis=2) - self.deg2 * np.eye(3)
        r[:, self.roots] = 0.0
        return r


def _block_pcg(system, precondition, y, r, tol, budget, state=None):
    """Up to ``budget`` steps of block preconditioned CG (O'Leary 1980) from (y, r).

    The three columns of the unknown rotation field are three right-hand sides of one matrix;
    block CG shares one Krylov space among them (step sizes are 3x3 matrices), so the slow
    directions, common to all three, are removed together: measured ~1.5x fewer steps than
    three scalar CGs. Returns (y, r, state, steps, converged).
    """
    if state is None:
        z = precondition(r)
        state = (z, z.copy(), _gram(z, r))
    z, p, zr = state
    for step in range(budget):
        if np.abs(z).max() < tol:
            return y, r, (z, p, zr), step, True
        q = system.apply(p)
        # pinv: once a body's columns have (nearly) converged its Gram matrices lose rank.
        alpha = np.linalg.pinv(_gram(p, q), rcond=1e-13) @ zr
        y += _times(p, alpha)
        r -= _times(q, alpha)
        z = precondition(r)
        zr_new = _gram(z, r)
        beta = np.linalg.pinv(zr, rcond=1e-13) @ zr_new
        zr = zr_new
        p = z + _times(p, beta)
    return y, r, (z, p, zr), budget, bool(np.abs(z).max() < tol)


def _smooth_gauge(q_rel, t, nbr, bk, valid, roots, laplacian):
    """One Gauss-Newton step on the gauge: ``T_i <- T_i exp([phi_i])`` where phi solves Eq. 9
    linearized in the Lie algebra, ``2 L phi_i = sum_j (eps_ij - eps_ji)`` with
    ``eps_ij = log(T_i^T Q_ij T_j)`` (zero at the roots). ``laplacian`` is the factored ``2 L``.

    Any gauge gives the same least-squares solution; a smooth one leaves CG a small, spread-out
    residual instead of the holonomy the tree gauge piles onto its loop-closing edges.
    Quaternions, component-first: ``q_rel`` (4, N, F, slot), ``t`` (4, N, F). Returns the new t.
    """
    n, nf = t.shape[1:]
    eps = _qlog(_qmul(_qmul(_qconj(t)[:, :, :, None], q_rel), t[:, :, nbr]))  # (3, N, F, slot)
    eps[:, :, ~valid] = 0.0
    b = (eps - eps[:, :, nbr, bk]).sum(axis=3)  # (3, N, F)
    b[:, :, roots] = 0.0
    phi = laplacian.solve(np.ascontiguousarray(b.transpose(2, 1, 0)).reshape(nf, n * 3))
    step = _qexp(np.ascontiguousarray(phi.reshape(nf, n, 3).transpose(2, 1, 0)))  # (4, N, F)
    return _qmul(t, step)


def solve_rotations_pcg(relative: np.ndarray, neighbors: np.ndarray, back: np.ndarray, forest,
                        preconditioner: FactorizedSolver, inverse_norm: float, tol: float = 3e-6,
                        max_iter: int = 5) -> tuple[np.ndarray, int, np.ndarray]:
    """Least-squares rotations of Eq. 9 by tree-gauged, Laplacian-preconditioned block CG.

    The gauge is the tree rotations (``tree_rotations``): they solve a consistent code exactly,
    so an unmodified code (a round trip) needs no CG step at all. A modified code (an
    interpolation, a PCA sample) leaves its inconsistency on the edges that close loops of the
    tree; ``SMOOTH_ROUNDS`` Gauss-Newton steps in the Lie algebra (``_smooth_gauge``) spread it
    over the mesh, and CG removes the rest in a few steps. Codes that would converge slowly
    are given up early: a code whose tree gauge is mismatched above 0.1 on more than
    ``DIRECT_FRACTION`` of its edge slots, or above ``DEFECT_MISMATCH`` anywhere, is returned
    at once, and otherwise after ``PROBE_STEPS`` steps the contraction rate predicts the total;
    if it exceeds ``max_iter`` the function returns early. Either way ``converged`` is False for those bodies, so that the
    caller solves them directly. Any gauge gives the same least-squares solution; it only
    changes the number of steps.

    Args:
        relative: (N, F, 3, 3, 3) relative rotations per face and edge slot (boundary slots
            are ignored).
        neighbors, back: (F, 3) from ``topology.face_adjacency``.
        forest: ``topology.spanning_forest``; its roots are the anchors (Y fixed to I).
        preconditioner: factorization of ``2 L`` (dual-graph Laplacian) with identity rows and
            columns at the roots.
        inverse_norm: ``|preconditioner^-1|_inf``, to skip the solves when the starting
            residual is round-off.
        tol: stop when the preconditioned residual, an estimate of the remaining correction of
            the rotation entries, is below this everywhere.
        max_iter: block-CG step budget.
    Returns:
        ``(R (N, F, 3, 3), steps, converged (N,) bool)``; R is not yet projected onto rotations.
    """
    n, nf = relative.shape[:2]
    valid = neighbors >= 0
    nbr = np.where(valid, neighbors, np.arange(nf)[:, None])
    bk = np.where(valid, back, 0)
    roots = forest.levels[0]

    def precondition(r):
        flat = np.ascontiguousarray(r.transpose(1, 0, 2, 3)).reshape(nf, n * 9)
        return preconditioner.solve(flat).reshape(nf, n, 3, 3).transpose(1, 0, 2, 3)

    gauge = tree_rotations(relative, forest.parent, forest.parent_slot, forest.levels)
    rt = relative @ gauge[:, nbr]  # Q_ij T_j
    # Eq. 9 residuals of the tree rotations, |Q_ij T_j - T_i| = |E_ij - I|. The starting CG
    # residual has entries <= 6 max|E - I| (two terms per slot, three slots): if even
    # |P^-1|_inf times that is below tol, the code is consistent up to round-off and the tree
    # rotations are the answer.
    mismatch = np.sqrt(((rt - gauge[:, :, None]) ** 2).sum(axis=(-1, -2)))
    mismatch[:, ~valid] = 0.0
    if 6.0 * mismatch.max() * inverse_norm < tol:
        return gauge, 0, np.ones(n, dtype=bool)
    # Codes mismatched on more than a few edges, or with one strong defect (measured: PCA samples,
    # 0.8-8% of the slots above 0.1; halfway codes across an LBS fold-over, up to 2.8) need
    # more CG steps than a factorization costs (measured: 4-70 steps at ~10 ms after ~50 ms of
    # set-up, against ~120 ms): do not even start.
    hard = ((mismatch > 0.1).sum(axis=(1, 2)) > DIRECT_FRACTION * valid.sum()) | \
        (mismatch.max(axis=(1, 2)) > DEFECT_MISMATCH)
    if hard.all():
        return gauge, 0, np.zeros(n, dtype=bool)
    # The tree gauge piles the code's holonomy onto the edges that close tree loops, which CG
    # then has to spread out again. Smooth the gauge first (Gauss-Newton steps in the Lie
    # algebra, quaternions): halfway codes 4 -> 1 step, PCA samples 23-200 -> 3-16 (measured).
    q_rel = _qfrom_matrix(_planar(relative.reshape(n, nf, 3, 9), 9))  # (4, N, F, slot)
    t = _qfrom_matrix(_planar(gauge.reshape(n, nf, 9), 9))  # (4, N, F)
    for _ in range(SMOOTH_ROUNDS):
        t = _smooth_gauge(q_rel, t, nbr, bk, valid, roots, preconditioner)
    eq = _qmul(_qmul(_qconj(t)[:, :, :, None], q_rel), t[:, :, nbr])  # E_ij = T_i^T Q_ij T_j
    gauge = np.moveaxis(_qmatrix(t), 0, -1).reshape(n, nf, 3, 3)
    e = np.moveaxis(_qmatrix(eq), 0, -1).reshape(n, nf, 3, 3, 3)
    system = _GaugedRotationSystem(e, gauge, nbr, bk, valid, roots)
    r = system.residual_at_identity()
    y = np.broadcast_to(np.eye(3), (n, nf, 3, 3)).copy()
    z = precondition(r)
    state = (z, z.copy(), _gram(z, r))
    history = [np.abs(z).max()]
    steps, done = 0, False
    while not done and steps < max_iter:
        y, r, state, more, done = _block_pcg(system, precondition, y, r, tol, 1, state)
        steps += more
        history.append(np.abs(state[0]).max())
        if not done and steps >= PROBE_STEPS:
            # The contraction over the last three steps predicts the steps still needed; when
            # they would exceed the budget, stop and let the caller solve directly.
            rate = (history[-1] / history[-4]) ** (1.0 / 3.0)
            needed = np.log(tol / history[-1]) / np.log(rate) if rate < 1.0 else np.inf
            if steps + needed > max_iter:
                break
    converged = np.abs(state[0]).max(axis=(1, 2, 3)) < tol
    return system.gauge @ y, steps, converged


def solve_rotations_direct(relative: np.ndarray, neighbors: np.ndarray, back: np.ndarray,
                           roots: np.ndarray) -> np.ndarray:
    """Least-squares rotations of Eq. 9 by assembling and factoring the system for each body.

    The obvious method, kept as the reference the benchmark and tests compare against: the
    (3F, 3F) normal matrix, root rows replaced by the identity, ``splu`` per body.
    """
    n, nf = relative.shape[:2]
    valid = neighbors >= 0
    nbr = np.where(valid, neighbors, 0)
    bk = np.where(valid, back, 0)
    is_root = np.zeros(nf, dtype=bool)
    is_root[roots] = True
    i_idx = np.broadcast_to(np.arange(nf)[:, None], (nf, 3))
    keep = valid & ~is_root[:, None]
    out = np.empty((n, nf, 3, 3))
    a3 = np.arange(3)
    for m in range(n):
        off = -(relative[m] + np.swapaxes(relative[m][nbr, bk], -1, -2))  # (F, 3, 3, 3)
        rows_off = 3 * i_idx[keep][:, None, None] + a3[None, :, None]
        cols_off = 3 * nbr[keep][:, None, None] + a3[None, None, :]
        diag = np.where(is_root, 1.0, 2.0 * valid.sum(axis=1))
        rows_d = 3 * np.arange(nf)[:, None] + a3
        rows = np.concatenate([np.broadcast_to(rows_off, off[keep].shape).ravel(), rows_d.ravel()])
        cols = np.concatenate([np.broadcast_to(cols_off, off[keep].shape).ravel(), rows_d.ravel()])
        vals = np.concatenate([off[keep].ravel(), np.repeat(diag, 3)])
        a = sp.csc_matrix((vals, (rows, cols)), shape=(3 * nf, 3 * nf))
        rhs = np.zeros((nf, 3, 3))
        rhs[roots] = np.eye(3)
        out[m] = sla.splu(a).solve(rhs.reshape(3 * nf, 3)).reshape(nf, 3, 3)
    return out


class FixedPatternRotationSolver:
    """Exact least-squares rotations of Eq. 9 with a sparsity pattern analysed once per template.

    The normal matrix of Eq. 9 changes its values with every code but never its pattern (3x3
    blocks on the dual graph). Anchor rows and columns are eliminated (their known identity
    moves to the right-hand side), which keeps the matrix symmetric, and only its upper
    triangle is stored: a precomputed map sends every (face, slot, 3x3 entry) of an upper
    off-diagonal block straight to its place in the CSC data array, so each body only writes
    values. With ``qdldl`` (LDL^T, Apache-2.0) the ordering and symbolic analysis are done at
    the first solve and every later body costs a numeric refactorization with the same pattern
    (``Solver.update``), which releases the GIL, so ``n_jobs`` threads factor bodies side by
    side. Without qdldl each body is factored by SuperLU (the same matrix, slower).
    One qdldl solver object per concurrent thread is kept in a small pool.
    """

    def __init__(self, neighbors: np.ndarray, back: np.ndarray, roots: np.ndarray):
        nf = len(neighbors)
        self.n_faces = nf
        valid = neighbors >= 0
        self.nbr = np.where(valid, neighbors, 0)
        self.bk = np.where(valid, back, 0)
        self.roots = np.asarray(roots)
        is_root = np.zeros(nf, dtype=bool)
        is_root[self.roots] = True
        self.valid = valid
        i_idx = np.broadcast_to(np.arange(nf)[:, None], (nf, 3))
        # Upper off-diagonal blocks: face i < neighbour j, neither an anchor.
        upper = valid & (i_idx < self.nbr) & ~is_root[:, None] & ~is_root[self.nbr]
        self.upper = upper
        # Anchor columns: rows i (not anchors) whose neighbour is an anchor; their block times
        # the anchor's identity goes to the right-hand side.
        self.to_root = valid & ~is_root[:, None] & is_root[self.nbr]
        a3 = np.arange(3)
        bi, bj = i_idx[upper], self.nbr[upper]
        rows = (3 * bi[:, None, None] + a3[None, :, None] + 0 * a3[None, None, :]).ravel()
        cols = (3 * bj[:, None, None] + 0 * a3[None, :, None] + a3[None, None, :]).ravel()
        diag = np.arange(3 * nf)
        rows = np.concatenate([rows, diag])
        cols = np.concatenate([cols, diag])
        n = 3 * nf
        # Place index k+1 at each entry; CSC conversion then tells where entry k lands.
        tag = sp.csc_matrix((np.arange(1, len(rows) + 1, dtype=np.float64), (rows, cols)), shape=(n, n))
        tag.sum_duplicates()
        if tag.nnz != len(rows):
            raise MeshError("rotation system: repeated face pair in the adjacency, expected a manifold mesh")
        self.indices, self.indptr = tag.indices.copy(), tag.indptr.copy()
        pos = np.empty(len(rows), dtype=np.int64)
        pos[tag.data.astype(np.int64) - 1] = np.arange(len(rows))
        n_off = len(rows) - n
        self.pos_off, self.pos_diag = pos[:n_off], pos[n_off:]
        self.diag_values = np.repeat(np.where(is_root, 1.0, 2.0 * valid.sum(axis=1)), 3)
        self.shape = (n, n)
        self._pool: list = []
        self._lock = threading.Lock()

    def matrix(self, relative: np.ndarray) -> sp.csc_matrix:
        """Upper triangle (CSC) of the anchored normal matrix for one body's relative rotations
        (F, 3, 3, 3); off-diagonal blocks ``-(Q_ij + Q_ji^T)``."""
        up = self.upper
        blocks = -(relative[up] + np.swapaxes(relative[self.nbr[up], self.bk[up]], -1, -2))
        data = np.empty(len(self.indices))
        data[self.pos_off] = blocks.ravel()
        data[self.pos_diag] = self.diag_values
        return sp.csc_matrix((data, self.indices, self.indptr), shape=self.shape)

    def rhs(self, relative: np.ndarray) -> np.ndarray:
        """Right-hand sides (3F, 3): identity at the anchors, ``(Q_ij + Q_ji^T) I`` moved from
        the eliminated anchor columns."""
        out = np.zeros((self.n_faces, 3, 3))
        out[self.roots] = np.eye(3)
        tr = self.to_root
        if tr.any():
            i = np.broadcast_to(np.arange(self.n_faces)[:, None], tr.shape)[tr]
            blocks = relative[tr] + np.swapaxes(relative[self.nbr[tr], self.bk[tr]], -1, -2)
            np.add.at(out, i, blocks)
        return out.reshape(3 * self.n_faces, 3)

    def solve(self, relative: np.ndarray) -> np.ndarray:
        """Least-squares ``Q_i`` (N, F, 3, 3), not projected, of relative rotations (N, F, 3, 3, 3)."""
        out = np.empty((len(relative),) + (self.n_faces, 3, 3))
        for m, rel in enumerate(relative):
            a, b = self.matrix(rel), self.rhs(rel)
            if _qdldl is None:
                full = a + sp.triu(a, k=1).T
                x = sla.splu(full.tocsc(), permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0,
                             options={"SymmetricMode": True}).solve(b)
            else:
                with self._lock:
                    solver = self._pool.pop() if self._pool else None
                if solver is None:
                    solver = _qdldl.Solver(a, upper=True)  # ordering + symbolic + numeric
                else:
                    solver.update(a, upper=True)  # numeric only, same pattern
                x = np.stack([solver.solve(b[:, k]) for k in range(3)], axis=1)
                with self._lock:
                    self._pool.append(solver)
            out[m] = x.reshape(self.n_faces, 3, 3)
        return out


# ---------------------------------------------------------------------------- the encoder

def _central_face(graph: sp.csr_matrix, start: int) -> int:
    """A face near the middle of its component's dual graph (double-sweep BFS): rooting the
    spanning tree there roughly halves its depth."""
    order, pred = breadth_first_order(graph, start, directed=False, return_predecessors=True)
    far = order[-1]
    order, pred = breadth_first_order(graph, far, directed=False, return_predecessors=True)
    path = [order[-1]]
    while pred[path[-1]] >= 0:
        path.append(pred[path[-1]])
    return int(path[len(path) // 2])


class RelativeRotationEncoder:
    """Relative rotation encoding of meshes registered to a template (Hasler et al. 2009).

    Works for any manifold, consistently oriented triangle topology; boundary edges and several
    connected parts are handled (see the module docstring for the code layout and placement).

    Args:
        template_vertices: (V, 3) the rest mesh whose triangles the deformations are relative to.
        faces: (F, 3) int, shared by every scan.
        rotation_solver: "pcg" (tree gauge, smoothed, Laplacian-preconditioned block CG with a
            factorization made once per template; the codes CG would not finish go to the exact
            path), "exact" (the Eq. 9 system refactorized for every body on a pattern analysed
            once: ``FixedPatternRotationSolver``) or "direct" (assemble and factor with SuperLU
            for every body; slow, the reference).
        tol: CG stops when the estimated remaining correction of every rotation entry is below
            this. The default leaves decoded vertices within ~3e-7 m of the exact least-squares
            decode on the 1.7 m template (measured, docs/encoding.md), well inside the
            1e-6 x height round-trip tolerance.
        max_iter: block-CG step budget, about the cost of one exact solve (~10 ms a step,
            ~120 ms a refactorization plus solve on the template). After a few steps the
            contraction rate predicts the steps needed; a code that would exceed the budget is
            solved exactly at once.
        on_flipped: what ``encode``/``fit`` do with a flipped triangle, one whose normal points
            against the vertex normals of its corners while the template's does not (a
            fold-over): "raise" (MeshError), "warn" or "ignore". Such triangles round-trip
            exactly, but their relative rotations sit near 180 degrees, where rotation vectors
            wrap, so interpolation and PCA misbehave there. Note: 89 of the 576 MakeHuman
            targets, applied at full weight, fold 2-20 small triangles this way.

    Attributes (after ``fit``):
        mean_rotvecs_: (F, 3, 3) mean rotation vector per face and edge slot.
        mean_stretch_: (F, 6) mean stretch per face.
        mean_vertices_: (V, 3) the mean model's mesh (decoded zero code), placed on the template.
        n_features_: D = 15 F (available before fit).
        slot_mask_: (F, 3) bool, True where the edge slot has a neighbour.
        last_iterations_: most block-CG steps any body of the last decode call took (0 for
            consistent codes, and for bodies sent straight to the factorization).
        last_factorized_: how many bodies of the last decode call were solved by a
            factorization instead of CG (all of them with "exact" or "direct").
    """

    def __init__(self, template_vertices: np.ndarray, faces: np.ndarray, *, rotation_solver: str = "pcg",
                 tol: float = 3e-6, max_iter: int = 5, on_flipped: str = "raise", n_jobs: int | None = None):
        check_mesh(template_vertices, faces, name="template")
        tv = np.asarray(template_vertices, dtype=float)
        if tv.ndim != 2:
            raise MeshError(f"template: vertices have shape {tv.shape}, expected (V, 3)")
        if rotation_solver not in ("pcg", "exact", "direct"):
            raise ValueError(f"rotation_solver={rotation_solver!r}, expected 'pcg', 'exact' or 'direct'")
        self.template_vertices = tv
        self.faces = np.asarray(faces, dtype=np.int64)
        if on_flipped not in ("raise", "warn", "ignore"):
            raise ValueError(f"on_flipped={on_flipped!r}, expected 'raise', 'warn' or 'ignore'")
        self.rotation_solver = rotation_solver
        self.on_flipped = on_flipped
        self.tol = tol
        self.max_iter = max_iter
        self.n_jobs = n_jobs
        self.n_vertices, self.n_faces = len(tv), len(self.faces)
        self.n_features_ = FEATURES_PER_FACE * self.n_faces

        adjacency = check_topology(self.faces, self.n_vertices)
        self.neighbors, self.back = adjacency.neighbors, adjacency.back
        self.slot_mask_ = self.neighbors >= 0
        frames = triangle_frames(tv, self.faces)
        dbl_area = np.linalg.norm(np.cross(frames[..., 0], frames[..., 1]), axis=-1)
        bad = np.flatnonzero(dbl_area <= 1e-12 * dbl_area.mean())
        if len(bad):
            raise MeshError(f"template: faces {bad[:5].tolist()} are degenerate (zero area); expected "
                            "non-degenerate triangles")
        self._rest_frames_inv = np.linalg.inv(frames)
        self._rest_double_area = dbl_area
        nf = len(self.faces)
        self._incidence = sp.csr_matrix((np.ones(3 * nf), (self.faces.ravel(), np.repeat(np.arange(nf), 3))),
                                        shape=(self.n_vertices, nf))
        self._rest_fold = _normal_agreement(frames[None, ..., 2], self.faces, self._incidence)[0]
        self._loops = boundary_loops(self.faces)
        self._rest_volume = float(capped_volume(tv, self.faces, self._loops))
        if abs(self._rest_volume) < 1e-12 * np.ptp(tv, axis=0).max() ** 3:
            raise MeshError("template: encloses no volume (flat); expected a surface with an inside")

        # One anchor (root) face per edge-connected part, near its middle.
        n_parts, labels = face_components(self.neighbors)
        graph = dual_graph(self.neighbors)
        self.anchor_faces = np.array([_central_face(graph, int(np.flatnonzero(labels == c)[0]))
                                      for c in range(n_parts)])
        self._forest = spanning_forest(self.neighbors, self.anchor_faces)
        lap = dual_laplacian(self.neighbors).tolil()
        lap[self.anchor_faces, :] = 0.0
        lap[:, self.anchor_faces] = 0.0
        lap[self.anchor_faces, self.anchor_faces] = 0.5
        # Single precision: it only preconditions (CG residuals stay in double), and its
        # triangular solves move half the memory (measured ~25% faster for 9 columns).
        self._preconditioner = FactorizedSolver(2.0 * lap.tocsr(), dtype=np.float32)
        # |P^-1|_inf = max row sum of P^-1 = max of P^-1 1, since P^-1 >= 0 (P is an M-matrix).
        self._inverse_norm = float(FactorizedSolver(2.0 * lap.tocsr()).solve(np.ones(self.n_faces)).max())

        self._poisson = PoissonSolver(tv, self.faces)
        # Placement: vertex components (one per edge-connected part, checked above).
        n_comp, self._vertex_part = vertex_components(self.faces, self.n_vertices)
        self._part_vertices = [np.flatnonzero(self._vertex_part == c) for c in range(n_comp)]
        self._face_part = self._vertex_part[self.faces[:, 0]]
        # Exact path: the Eq. 9 pattern analysed once, a numeric refactorization per body.
        self._exact = FixedPatternRotationSolver(self.neighbors, self.back, self.anchor_faces)
        self.last_iterations_ = 0
        self.last_factorized_ = 0

    # ------------------------------------------------------------------ validation
    def _require_fit(self):
        if not hasattr(self, "mean_vertices_"):
            raise MeshError(f"{type(self).__name__} is not fitted; call fit(scans) first "
                            "(fit(template[None]) makes the template the mean model)")

    def _check_codes(self, codes) -> np.ndarray:
        return check_codes(codes, self.n_features_, "relative rotation encoding",
                           f"15 numbers x {self.n_faces} triangles")

    def _deformation(self, x: np.ndarray, name: str, first: int = 0) -> np.ndarray:
        """Deformation gradients (N, F, 3, 3) of validated meshes (N, V, 3); rejects degenerate
        and flipped triangles."""
        frames = triangle_frames(x, self.faces)
        dbl = np.linalg.norm(np.cross(frames[..., 0], frames[..., 1]), axis=-1)
        ratio = dbl / self._rest_double_area
        if (ratio < DEGENERATE_AREA_RATIO).any():
            m, f = np.argwhere(ratio < DEGENERATE_AREA_RATIO)[0]
            count = int((ratio[m] < DEGENERATE_AREA_RATIO).sum())
            raise MeshError(f"{name}: mesh {first + m} has {count} degenerate triangle(s), first face {f} with area "
                            f"{0.5 * dbl[m, f]:.3g} m^2 (template {0.5 * self._rest_double_area[f]:.3g} m^2); "
                            "expected triangles of non-zero area")
        volume = capped_volume(x, self.faces, self._loops)
        inverted = np.sign(volume) != np.sign(self._rest_volume)
        if inverted.any():
            m = np.flatnonzero(inverted)[0]
            raise MeshError(f"{name}: mesh {first + m} is inside out (enclosed volume {volume[m]:.3g} m^3, "
                            f"the template's {self._rest_volume:.3g} m^3): mirrored, or every face flipped; "
                            "expected the template's orientation")
        if self.on_flipped != "ignore":
            fold = _normal_agreement(frames[..., 2], self.faces, self._incidence)
            flipped = (fold < 0) & (self._rest_fold >= 0)
            if flipped.any():
                m, f = np.argwhere(flipped)[0]
                msg = (f"{name}: mesh {first + m} has {int(flipped[m].sum())} flipped triangle(s), first face {f}: "
                       "its normal points against the surface around it (the vertex normals of its corners), "
                       "the template's does not; expected an orientation-preserving registration "
                       "(on_flipped='warn' or 'ignore' accepts it)")
                if self.on_flipped == "raise":
                    raise MeshError(msg)
                warnings.warn(msg, RuntimeWarning, stacklevel=4)
        return frames @ self._rest_frames_inv

    # ------------------------------------------------------------------ raw components
    def _raw(self, x: np.ndarray, name: str, first: int = 0):
        """Relative rotations as component-first quaternions (4, N, F, 3) and stretches (N, F, 6);
        ``first`` is the index of x[0] in the caller's batch (for error messages)."""
        u = self._deformation(x, name, first)
        n = len(x)
        u9 = _planar(u.reshape(n, self.n_faces, 9), 9)
        r9 = _polar9(u9)
        # S = R^T U, symmetrized: S_ab = sum_c R_ca U_cb.
        def s_entry(a, b):
            return r9[a] * u9[b] + r9[3 + a] * u9[3 + b] + r9[6 + a] * u9[6 + b]
        stretch = np.stack([s_entry(0, 0), 0.5 * (s_entry(0, 1) + s_entry(1, 0)), 0.5 * (s_entry(0, 2) + s_entry(2, 0)),
                            s_entry(1, 1), 0.5 * (s_entry(1, 2) + s_entry(2, 1)), s_entry(2, 2)], axis=-1)
        q = _qfrom_matrix(r9)  # (4, N, F)
        nbr = np.where(self.slot_mask_, self.neighbors, 0)
        # Q_ij = Q_i Q_j^-1 = R_i^T R_j: unchanged when the whole body turns (R -> G R); see the
        # module docstring.
        q_rel = _qmul(_qconj(q)[:, :, :, None], q[:, :, nbr])
        return q_rel, stretch

    # ------------------------------------------------------------------ API
    def fit(self, scans: np.ndarray, faces: np.ndarray | None = None) -> "RelativeRotationEncoder":
        """Compute the mean model: the average of every code component over ``scans`` (N, V, 3).

        ``fit(template_vertices[None])`` makes the template itself the mean model.
        """
        x = check_scans(scans, self.n_vertices, self.faces, faces, name="scans")
        sums = []

        def work(s):
            q_rel, stretch = self._raw(x[s:s + ENCODE_CHUNK], name="scans", first=s)
            sums.append((_qlog(q_rel).sum(axis=1), stretch.sum(axis=0)))

        self._run(work, range(0, len(x), ENCODE_CHUNK))
        sum_rot = sum(r for r, _ in sums)
        sum_str = sum(st for _, st in sums)
        self.mean_rotvecs_ = np.where(self.slot_mask_[..., None], np.moveaxis(sum_rot, 0, -1) / len(x), 0.0)
        self.mean_stretch_ = sum_str / len(x)
        self._mean_q = _qexp(_planar(self.mean_rotvecs_, 3))  # (4, F, 3)
        self.mean_vertices_ = self._decode(np.zeros((1, self.n_features_)), None, self.template_vertices)[0][0]
        return self

    def encode(self, vertices: np.ndarray, faces: np.ndarray | None = None) -> np.ndarray:
        """Codes (N, 15 F) of meshes (V, 3) or (N, V, 3) registered to the template.

        ``faces``, if given, must equal the template's (checked). Raises MeshError for wrong
        shapes, NaN, degenerate or flipped triangles.
        """
        self._require_fit()
        x = check_scans(vertices, self.n_vertices, self.faces, faces)
        out = np.empty((len(x), self.n_faces, FEATURES_PER_FACE))
        conj_mean = _qconj(self._mean_q)

        def work(s):
            q_rel, stretch = self._raw(x[s:s + ENCODE_CHUNK], name="vertices", first=s)
            rot = _qlog(_qmul(q_rel, conj_mean))  # (3, n, F, 3): component, body, face, slot
            rot[:, :, ~self.slot_mask_] = 0.0
            out[s:s + ENCODE_CHUNK, :, :9] = rot.transpose(1, 2, 3, 0).reshape(-1, self.n_faces, 9)
            out[s:s + ENCODE_CHUNK, :, 9:] = stretch - self.mean_stretch_

        self._run(work, range(0, len(x), ENCODE_CHUNK))
        return out.reshape(len(x), self.n_features_)

    def decode(self, codes: np.ndarray, constraints: PositionConstraints | None = None) -> np.ndarray:
        """Meshes (N, V, 3) from codes (N, 15 F) or (15 F,), placed on the mean model.

        With ``constraints`` (``mesh.solver.PositionConstraints``) the Poisson step also pulls
        the chosen vertices softly to the given positions; the body keeps the orientation the
        unconstrained placement gives it, and its position follows the constraints.
        """
        self._require_fit()
        c = self._check_codes(codes)
        out = np.empty((len(c), self.n_vertices, 3))
        steps = []

        def work(s):
            chunk_constraints = constraints
            if constraints is not None and np.ndim(constraints.positions) == 3:
                chunk_constraints = PositionConstraints(constraints.indices,
                                                        np.asarray(constraints.positions)[s:s + DECODE_CHUNK],
                                                        constraints.weight)
            out[s:s + DECODE_CHUNK], n_steps, n_fact = self._decode(c[s:s + DECODE_CHUNK], chunk_constraints,
                                                                     self.mean_vertices_)
            steps.append((n_steps, n_fact))

        self._run(work, range(0, len(c), DECODE_CHUNK))
        self.last_iterations_ = max(k for k, _ in steps)
        self.last_factorized_ = sum(f for _, f in steps)
        return out

    def _run(self, work, starts) -> None:
        """Call ``work(start)`` for every chunk start, on ``n_jobs`` threads when there are
        several chunks. numpy and the sparse products release the GIL, so two threads decode
        ~1.7x and encode ~1.5x as many bodies per second on two cores (measured)."""
        starts = list(starts)
        jobs = self.n_jobs or os.cpu_count() or 1
        if jobs <= 1 or len(starts) <= 1:
            for s in starts:
                work(s)
            return
        # One BLAS thread per worker, set once here rather than racing inside the threads.
        with single_threaded_blas(), ThreadPoolExecutor(min(jobs, len(starts))) as pool:
            for future in [pool.submit(work, s) for s in starts]:
                future.result()

    def relative_rotations(self, codes: np.ndarray) -> np.ndarray:
        """Relative rotation matrices Q_ij (N, F, 3, 3, 3) per face and edge slot of codes (N, D)."""
        c = np.asarray(codes).reshape(len(codes), self.n_faces, FEATURES_PER_FACE)
        r = _planar(c[..., :9].reshape(len(c), self.n_faces, 3, 3), 3)  # (3, N, F, slot)
        m9 = _qmatrix(_qmul(_qexp(r), self._mean_q))  # (9, N, F, slot)
        return np.moveaxis(m9, 0, -1).reshape(len(c), self.n_faces, 3, 3, 3)

    def solve_rotations(self, relative: np.ndarray, solver: str | None = None) -> np.ndarray:
        """Per-face rotations R_i (N, F, 3, 3) from relative rotations (N, F, 3, 3, 3) by Eq. 9,
        projected onto SO(3). ``solver``: "pcg", "exact" or "direct" (default:
        ``rotation_solver``)."""
        rot, self.last_iterations_, self.last_factorized_ = self._solve_rotations(
            relative, solver or self.rotation_solver)
        return rot

    def _solve_rotations(self, relative: np.ndarray, solver: str) -> tuple[np.ndarray, int, int]:
        """(R (N, F, 3, 3), most CG steps, number of bodies solved by a factorization)."""
        steps, factorized = 0, len(relative)
        if solver == "direct":
            rot = solve_rotations_direct(relative, self.neighbors, self.back, self.anchor_faces)
        elif solver == "exact":
            rot = self._exact.solve(relative)
        else:
            rot, steps, converged = solve_rotations_pcg(relative, self.neighbors, self.back, self._forest,
                                                        self._preconditioner, self._inverse_norm, self.tol,
                                                        self.max_iter)
            factorized = int((~converged).sum())
            if factorized:
                # Strongly inconsistent codes: CG would not pay off, factor their systems (fixed
                # pattern, numeric refactorization only).
                rot[~converged] = self._exact.solve(relative[~converged])
        # Eq. 9 solves for Q_i = R_i^T; return the rotations R_i of U_i = R_i S_i.
        return np.swapaxes(project_to_rotations(rot), -1, -2), steps, factorized

    def _decode(self, c: np.ndarray, constraints, reference: np.ndarray):
        n = len(c)
        c = c.reshape(n, self.n_faces, FEATURES_PER_FACE)
        rot, steps, factorized = self._solve_rotations(self.relative_rotations(c), self.rotation_solver)
        u = rot @ unpack_stretch(c[..., 9:] + self.mean_stretch_)
        x = self._poisson.solve(u)
        placed, part_rot = self._place(x, reference)
        if constraints is None:
            return placed, steps, factorized
        # Keep the placed orientation: rotate each part's gradients as the placement rotated it.
        u = part_rot[:, self._face_part] @ u
        return self._poisson.solve(u, constraints, pinned_positions=placed), steps, factorized

    def _place(self, x: np.ndarray, reference: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Rigidly align each connected part of ``x`` (N, V, 3) onto ``reference`` (V, 3)."""
        placed = np.empty_like(x)
        rots = np.empty((len(x), len(self._part_vertices), 3, 3))
        for k, idx in enumerate(self._part_vertices):
            placed[:, idx], rots[:, k], _ = rigid_procrustes(x[:, idx], reference[idx])
        return placed, rots


def _normal_agreement(normals: np.ndarray, faces: np.ndarray, incidence: sp.csr_matrix) -> np.ndarray:
    """``n_f . (m_a + m_b + m_c)`` (N, F): each face's unit normal against the vertex normals
    (sums of incident unit face normals) of its corners. Negative when a face is turned over
    against the surface around it; unlike a test against the edge neighbours alone, it also
    catches two flipped faces side by side."""
    n = normals / np.maximum(np.linalg.norm(normals, axis=-1, keepdims=True), 1e-300)
    nb, nf = n.shape[:2]
    vn = (incidence @ np.ascontiguousarray(n.transpose(1, 0, 2)).reshape(nf, nb * 3)).reshape(-1, nb, 3)
    corner_sum = vn[faces].sum(axis=1).transpose(1, 0, 2)  # (N, F, 3)
    return np.einsum("nfi,nfi->nf", n, corner_sum)
