"""Relative rotation encoding (RRE) of registered meshes (Hasler §3).

Encoding, per triangle i of a mesh registered to the template:

1. deformation gradient ``U_i`` from the template triangle to the scan triangle (Sumner and
   Popovic's frame with a scaled normal, so ``U_i`` is a full 3x3 map);
2. polar decomposition ``U_i = R_i S_i``: rotation R_i, symmetric stretch S_i;
3. relative rotations to the edge neighbours (Hasler Equation 8), one per edge slot. Hasler Equation 8 is written for
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

Decoding, two sparse solves (Hasler §3):

1. rotations from the relative rotations by least squares on Hasler Equation 9, ``Q_ij Q_j - Q_i = 0`` for
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

How step 1 is made fast (its matrix changes with every code): the normal matrix of Hasler Equation 9 is a
*connection Laplacian*, diagonal blocks ``2 deg_i I`` (relative rotations are orthogonal) and
off-diagonal blocks ``-(Q_ij + Q_ji^T)``: its values change with the code, its pattern (one
3x3 block per pair of adjacent faces) never. So

* a consistent code (every round trip) is recognised and solved without any factorization:
  the rotations ``T_i`` chained from the anchor along a breadth-first spanning tree satisfy
  Hasler Equation 9 exactly, which one pass over the edges checks;
* every other code (interpolations, PCA samples, edited codes) is solved exactly by
  ``FixedPatternRotationSolver``: the ordering and the symbolic factorization of the pattern
  are made once per template (``mesh.block_cholesky``) and each body pays the compiled numeric
  factorization on whole 3x3 blocks and three triangular solves, the two halves of the
  elimination tree on two threads when one body is decoded.

An iterative method was used before (block CG preconditioned by the fixed dual Laplacian in the
tree gauge): it took 1-9 steps on mild codes but 15-110 on codes with rotation vortices
(pose+shape PCA samples), where partly converged rotations put limbs up to 1 m off, so those
codes needed a factorization anyway. The block factorization is faster than that CG was on
every kind of code and is exact. Every step of the chain (relative rotations, tree, system,
the projection and ``U = R S``) is a compiled kernel (numba) over the faces of one body.
``rotation_solver="direct"`` assembles and factors the full system with SuperLU for every body
(the baseline the benchmark compares against).
See docs/encoding.md for the measurements behind these choices.
"""

from __future__ import annotations

import os
import threading
import warnings
from concurrent.futures import ThreadPoolExecutor

import numba
import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as sla
from scipy.sparse.csgraph import breadth_first_order, reverse_cuthill_mckee

from bodyspace.encoding.deformation import polar_from_corners, rest_triangles
from bodyspace.encoding.linearize import DecoderLinearization
from bodyspace.encoding.tangent import DecodeTangent, PoissonAdjoint, left_jacobians
from bodyspace.encoding.rotations import (
    components_first,
    project_to_rotations,
    quaternion_conjugate_cf,
    quaternion_exp,
    quaternion_exp_cf,
    quaternion_from_matrix_cf,
)
from bodyspace.errors import MeshError, ParameterError
from bodyspace.mesh.alignment import rigid_procrustes
from bodyspace.mesh.block_cholesky import BlockCholesky, BlockPattern
from bodyspace.mesh.geometry import boundary_loops, capped_volume, check_mesh
from bodyspace.mesh.operators import dual_laplacian, triangle_frames
from bodyspace.mesh.solver import (
    FactorizedSolver,
    PoissonSolver,
    PositionConstraints,
    single_threaded_blas,
)
from bodyspace.mesh.topology import (
    check_registered_meshes,
    check_topology,
    dual_graph,
    face_components,
    spanning_forest,
    vertex_components,
)
from bodyspace.parallel import halves, run_both
from bodyspace.validation import as_codes

FEATURES_PER_FACE = 15
# linearize(space) without k: the leading coefficients the tangent covers (Rupprecht's k = 25).
LINEARIZED_COEFFICIENTS = 25
# What encode does with a flipped (folded) triangle; see RelativeRotationEncoder.
ON_FLIPPED = ("accept", "warn", "raise", "ignore")
# A scan triangle whose area shrank below this fraction of its template area is degenerate:
# its deformation gradient is (nearly) singular and has no meaningful polar decomposition.
DEGENERATE_AREA_RATIO = 1e-8
# Bodies decoded per task. Arrays are ~6 MB per body on the 26,756-face template; several
# bodies at once fall out of cache and were slower per body (measured: 29 ms at 1, 47 at 8), so
# batches gain from threads (``n_jobs``), not from wider arrays.
DECODE_CHUNK = 1
# Encoding works on one body per task and on its faces in blocks of this many, so that the
# temporaries of the closed-form polar decomposition and of the relative rotations (up to
# 3 x 8192 float64, 196 KB each) stay in the L2 cache. Measured on the 26,756-face template,
# single thread, under load: 10-12 ms of CPU a body for blocks of 4096 to 32768 faces, 14 ms
# for 2048 (per-call overhead), against 24 ms for the previous whole-body Newton iteration.
ENCODE_BLOCK = 8192
# A code whose tree rotations leave Hasler Equation 9 a residual this small (as a bound on the change of
# any rotation entry) is consistent: the tree rotations are its solution, no factorization.
CONSISTENT_TOL = 1e-7
# The mean model sums the scans' codes in this many fixed chunks (one thread task each).
FIT_CHUNKS = 4
_STRETCH_ROWS = np.array([0, 0, 0, 1, 1, 2])
_STRETCH_COLS = np.array([0, 1, 2, 1, 2, 2])


def pack_stretch(s: np.ndarray) -> np.ndarray:
    """Upper triangle (..., 6) of symmetric (..., 3, 3): S00, S01, S02, S11, S12, S22."""
    return s[..., _STRETCH_ROWS, _STRETCH_COLS]


def unpack_stretch(p: np.ndarray) -> np.ndarray:
    """Symmetric (..., 3, 3) from (..., 6) (``pack_stretch`` order)."""
    s = np.empty(p.shape[:-1] + (3, 3))
    s[..., _STRETCH_ROWS, _STRETCH_COLS] = p
    s[..., _STRETCH_COLS, _STRETCH_ROWS] = p
    return s


# ---------------------------------------------------------------------------- Hasler Equation 9 solvers

# Compiled kernels (numba, ``cache=True``: compiled on first use, ~10-25 s for all of them
# with ``mesh.solver.ldl_solve`` on a loaded 2-core machine, then loaded from the cache in
# ~1 s). Each is one pass over the faces of one body with the 3x3 products written out: the
# numpy version of the same steps cost 50-100 ms per body in temporaries and stacking
# (measured), the kernels ~15 ms. ``nogil``: ``n_jobs`` threads decode bodies side by side.
_kernel = numba.njit(cache=True, nogil=True)


@_kernel
def _relative_kernel(code, mean_q, out, lo, hi):
    """Relative rotation matrices ``exp(r_ik) M_ik`` (F, 3, 3, 3) of one code (F, 15) and the
    mean model's quaternions (F, 3, 4), all in one face order. Faces ``lo:hi`` only (as every
    kernel below: one lane's share, see ``_lanes``)."""
    for f in range(lo, hi):
        for k in range(3):
            r0, r1, r2 = code[f, 3 * k], code[f, 3 * k + 1], code[f, 3 * k + 2]
            th = np.sqrt(r0 * r0 + r1 * r1 + r2 * r2)
            s = 0.5 - th * th / 48.0 if th < 1e-6 else np.sin(0.5 * th) / th
            pw, px, py, pz = np.cos(0.5 * th), r0 * s, r1 * s, r2 * s
            qw, qx, qy, qz = mean_q[f, k, 0], mean_q[f, k, 1], mean_q[f, k, 2], mean_q[f, k, 3]
            w = pw * qw - px * qx - py * qy - pz * qz
            x = pw * qx + px * qw + py * qz - pz * qy
            y = pw * qy - px * qz + py * qw + pz * qx
            z = pw * qz + px * qy - py * qx + pz * qw
            m = out[f, k]
            m[0, 0] = 1 - 2 * (y * y + z * z)
            m[0, 1] = 2 * (x * y - w * z)
            m[0, 2] = 2 * (x * z + w * y)
            m[1, 0] = 2 * (x * y + w * z)
            m[1, 1] = 1 - 2 * (x * x + z * z)
            m[1, 2] = 2 * (y * z - w * x)
            m[2, 0] = 2 * (x * z - w * y)
            m[2, 1] = 2 * (y * z + w * x)
            m[2, 2] = 1 - 2 * (x * x + y * y)


@_kernel
def _tree_kernel(rel, order, parent, parent_slot, n_roots, t):
    """``T_c = Q_cp T_p`` along the forest, faces in breadth-first ``order``, roots first."""
    for a in range(n_roots):
        f = order[a]
        for r in range(3):
            for c in range(3):
                t[f, r, c] = 1.0 if r == c else 0.0
    for a in range(n_roots, len(order)):
        f, p, k = order[a], parent[order[a]], parent_slot[order[a]]
        for r in range(3):
            for c in range(3):
                t[f, r, c] = rel[f, k, r, 0] * t[p, 0, c] + rel[f, k, r, 1] * t[p, 1, c] + rel[f, k, r, 2] * t[p, 2, c]


@_kernel
def _mismatch_kernel(rel, t, nbr, valid, lo, hi):
    """Largest Hasler Equation 9 residual ``|Q_ij T_j - T_i|_F`` over the edge slots of faces lo:hi."""
    mx = 0.0
    for i in range(lo, hi):
        for k in range(3):
            if valid[i, k]:
                j, s = nbr[i, k], 0.0
                for r in range(3):
                    for c in range(3):
                        d = (rel[i, k, r, 0] * t[j, 0, c] + rel[i, k, r, 1] * t[j, 1, c]
                             + rel[i, k, r, 2] * t[j, 2, c] - t[i, r, c])
                        s += d * d
                mx = max(mx, s)
    return np.sqrt(mx)


@_kernel
def _system_kernel(rel, nbr, bk, pair_of_slot, off, lo, hi):
    """Off-diagonal blocks ``-(Q_ik + Q_jk'^T)`` (E, 3, 3) of the Hasler Equation 9 normal matrix, one per
    pair of free faces, from the slot of its lower face (``pair_of_slot[i, k] >= 0``)."""
    for i in range(lo, hi):
        for k in range(3):
            e = pair_of_slot[i, k]
            if e >= 0:
                j, kb = nbr[i, k], bk[i, k]
                for r in range(3):
                    for c in range(3):
                        off[e, r, c] = -(rel[i, k, r, c] + rel[j, kb, c, r])


@_kernel
def _gradients_kernel(q, stretch, mean_stretch, u, bad, lo, hi):
    """Deformation gradients ``U_i = R_i S_i`` (F, 3, 3): ``R_i`` the transposed polar factor
    of ``Q_i`` (q (F, 3, 3), scaled Newton iteration, as ``_polar9``), ``S_i`` from the code's
    stretch (F, 6) plus the mean's, all in one face order. ``bad[i]`` where det(Q_i) <= 0
    (U_i left unset)."""
    x = np.empty((3, 3))
    c = np.empty((3, 3))
    for i in range(lo, hi):
        scale = 0.0
        for r in range(3):
            for cc in range(3):
                x[r, cc] = q[i, r, cc]
                scale = max(scale, abs(x[r, cc]))
        bad[i] = False
        finishing = False
        for it in range(60):
            c[0, 0] = x[1, 1] * x[2, 2] - x[1, 2] * x[2, 1]
            c[0, 1] = x[1, 2] * x[2, 0] - x[1, 0] * x[2, 2]
            c[0, 2] = x[1, 0] * x[2, 1] - x[1, 1] * x[2, 0]
            c[1, 0] = x[2, 1] * x[0, 2] - x[2, 2] * x[0, 1]
            c[1, 1] = x[2, 2] * x[0, 0] - x[2, 0] * x[0, 2]
            c[1, 2] = x[2, 0] * x[0, 1] - x[2, 1] * x[0, 0]
            c[2, 0] = x[0, 1] * x[1, 2] - x[0, 2] * x[1, 1]
            c[2, 1] = x[0, 2] * x[1, 0] - x[0, 0] * x[1, 2]
            c[2, 2] = x[0, 0] * x[1, 1] - x[0, 1] * x[1, 0]
            det = x[0, 0] * c[0, 0] + x[0, 1] * c[0, 1] + x[0, 2] * c[0, 2]
            if it == 0 and not det > 1e-12 * scale ** 3:
                bad[i] = True
                break
            # The scaling only speeds up the first steps far from orthogonal; near it, skip the
            # cube root (the iteration converges to the same polar factor).
            g = 1.0 if abs(det - 1.0) < 1e-3 else 1.0 / np.cbrt(abs(det))
            h = 1.0 / (g * det)
            change = 0.0
            for r in range(3):
                for cc in range(3):
                    v = 0.5 * (g * x[r, cc] + c[r, cc] * h)
                    change = max(change, abs(v - x[r, cc]))
                    x[r, cc] = v
            if finishing or change < 1e-14:
                break
            finishing = change < 1e-7
        if bad[i]:
            continue
        s, m = stretch[i], mean_stretch[i]
        s00, s01, s02 = s[0] + m[0], s[1] + m[1], s[2] + m[2]
        s11, s12, s22 = s[3] + m[3], s[4] + m[4], s[5] + m[5]
        for r in range(3):  # row r of R = column r of the polar factor
            a0, a1, a2 = x[0, r], x[1, r], x[2, r]
            u[i, r, 0] = a0 * s00 + a1 * s01 + a2 * s02
            u[i, r, 1] = a0 * s01 + a1 * s11 + a2 * s12
            u[i, r, 2] = a0 * s02 + a1 * s12 + a2 * s22


class RotationGraph:
    """The arrays the Hasler Equation 9 kernels need, built once per template, in the graph's own face order.

    The faces are renumbered by reverse Cuthill-McKee on the dual graph, so that the neighbours
    a kernel reads for a face lie close to it in memory: the per-edge kernels ran 2x faster
    than in the template's own numbering (measured). Face i of the graph is face ``order[i]``
    of the mesh; ``rank`` is the inverse.

    Args:
        neighbors, back: (F, 3) from ``topology.face_adjacency``.
        roots: (C,) anchor faces (mesh numbering), one per edge-connected part; Q fixed to I.
    """

    def __init__(self, neighbors: np.ndarray, back: np.ndarray, roots: np.ndarray):
        nf = len(neighbors)
        self.order = reverse_cuthill_mckee(dual_graph(neighbors).tocsr(), symmetric_mode=True).astype(np.int64)
        self.rank = np.empty(nf, dtype=np.int64)
        self.rank[self.order] = np.arange(nf)
        neighbors = np.asarray(neighbors)[self.order]
        self.neighbors = np.where(neighbors >= 0, self.rank[np.maximum(neighbors, 0)], -1)
        self.back = np.ascontiguousarray(np.asarray(back)[self.order])
        self.valid = np.ascontiguousarray(self.neighbors >= 0)
        self.nbr = np.where(self.valid, self.neighbors, np.arange(nf)[:, None]).astype(np.int64)
        self.bk = np.where(self.valid, self.back, 0).astype(np.int64)
        self.roots = self.rank[np.asarray(roots, dtype=np.int64)]
        forest = spanning_forest(self.neighbors, self.roots)
        self.sweep = np.concatenate(forest.levels).astype(np.int64)  # roots first, parents before children
        self.parent = np.asarray(forest.parent, dtype=np.int64)
        self.parent_slot = np.asarray(forest.parent_slot, dtype=np.int64)
        self.is_root = np.zeros(nf, dtype=bool)
        self.is_root[self.roots] = True
        self.deg2 = 2.0 * self.valid.sum(axis=1)
        self.n_faces = nf


def _lanes(lanes: int, n: int, fn) -> tuple:
    """Results of ``fn(lo, hi)`` over rows ``0:n``: one call, or (``lanes == 2``) the two
    halves side by side (``bodyspace.parallel``)."""
    if lanes == 1:
        return (fn(0, n),)
    (a0, a1), (b0, b1) = halves(n)
    return run_both(lambda: fn(a0, a1), lambda: fn(b0, b1))


_workspaces = threading.local()


def _workspace(nf: int) -> dict:
    """This thread's arrays for one body's rotations (reused: fresh arrays of ~10 MB per body
    cost their page faults again every time)."""
    w = getattr(_workspaces, "arrays", None)
    if w is None or w["t"].shape[0] != nf:
        w = {"rel": np.empty((nf, 3, 3, 3)), "t": np.empty((nf, 3, 3))}
        _workspaces.arrays = w
    return w


def solve_rotations_direct(relative: np.ndarray, neighbors: np.ndarray, back: np.ndarray,
                           roots: np.ndarray) -> np.ndarray:
    """Least-squares rotations of Hasler Equation 9 by assembling and factoring the system for each body.

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
    """Exact least-squares rotations of Hasler Equation 9, the pattern analysed once per template.

    The normal matrix of Hasler Equation 9 changes its values with every code but never its pattern (one
    3x3 block per pair of adjacent faces). Anchor rows and columns are eliminated (their
    known identity moves to the right-hand side), which keeps it symmetric positive definite,
    and ``mesh.block_cholesky`` orders and analyses that pattern once; each body then costs
    the compiled numeric block Cholesky factorization and three triangular solves, on two
    threads for a single body. Everything is in the ``RotationGraph``'s face order.
    One numeric factorization per concurrent thread is kept in a small pool.
    """

    def __init__(self, graph: RotationGraph):
        self.graph = graph
        nf = graph.n_faces
        free = ~graph.is_root
        self.free = np.flatnonzero(free)
        index = np.full(nf, -1, dtype=np.int64)
        index[self.free] = np.arange(len(self.free))
        face = np.broadcast_to(np.arange(nf)[:, None], (nf, 3))
        pairs = graph.valid & (face < graph.nbr) & free[:, None] & free[graph.nbr]
        self.pair_of_slot = np.full((nf, 3), -1, dtype=np.int64)
        self.pair_of_slot[pairs] = np.arange(int(pairs.sum()))
        self.pattern = BlockPattern(len(self.free), index[face[pairs]], index[graph.nbr[pairs]])
        self.diag = graph.deg2[self.free][:, None, None] * np.eye(3)
        # Slots from a free face to an anchor: their block times the anchor's identity goes
        # to the right-hand side.
        self.to_root = np.nonzero(graph.valid & free[:, None] & graph.is_root[graph.nbr])
        self._pool: list = []
        self._lock = threading.Lock()

    def solve(self, rel: np.ndarray, lanes: int = 1, chol: BlockCholesky | None = None) -> np.ndarray:
        """Least-squares ``Q_i`` (F, 3, 3), not projected, of one body's relative rotations
        (F, 3, 3, 3), both in the graph's face order. ``lanes=2``: on two threads. ``chol``: a
        ``BlockCholesky`` of the caller's to factor into and keep (default: one of the pool)."""
        g = self.graph
        off = np.empty((self.pattern.n_pairs, 3, 3))
        _lanes(lanes, g.n_faces, lambda lo, hi: _system_kernel(rel, g.nbr, g.bk, self.pair_of_slot, off, lo, hi))
        b = np.zeros((g.n_faces, 3, 3))
        i, k = self.to_root
        np.add.at(b, i, rel[i, k] + np.swapaxes(rel[g.nbr[i, k], g.bk[i, k]], -1, -2))
        if chol is not None:
            x = chol.factor_solve(self.diag, off, b[self.free], lanes)
        else:
            with self._lock:
                chol = self._pool.pop() if self._pool else None
            if chol is None:
                chol = BlockCholesky(self.pattern)
            try:
                x = chol.factor_solve(self.diag, off, b[self.free], lanes)
            finally:
                with self._lock:
                    self._pool.append(chol)
        q = np.empty((g.n_faces, 3, 3))
        q[g.roots] = np.eye(3)
        q[self.free] = x
        return q


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


def _degenerate_faces_message(vertices: np.ndarray, faces: np.ndarray, bad: np.ndarray) -> str:
    """Why the reference body (V, 3) with faces (F, 3) cannot be encoded: ``bad`` (B,) zero-area
    faces, how many come from vertices at the same point (a remesher's leftover), and the fix."""
    corners = vertices[faces[bad]]                                         # (B, 3, 3)
    gaps = np.linalg.norm(corners - np.roll(corners, 1, axis=1), axis=-1)  # (B, 3): edge k joins corners k-1, k
    coincident = gaps <= 1e-9 * np.ptp(vertices, axis=0).max()
    pair = ""
    if coincident.any():
        row, k = np.argwhere(coincident)[0]
        a, b = sorted((int(faces[bad[row]][k]), int(faces[bad[row]][k - 1])))
        pair = (f"; {int(coincident.any(axis=1).sum())} of them join vertices at the same point "
                f"(e.g. vertices {a} and {b})")
    return (f"the meshes' topology has {len(bad)} zero-area face(s) of {len(faces)} on the reference body "
            f"(faces {bad[:5].tolist()}{' ...' if len(bad) > 5 else ''}){pair}; the relative rotation "
            "encoding needs a rotation per triangle, so every face must have an area. Fix the meshes (weld "
            "coincident vertices and drop the faces they flatten, e.g. with trimesh's merge_vertices and "
            "update_faces(nondegenerate_faces()), then import them again) or use the vertex encoding "
            "(encoding='vertex'; bodyspace build --encoding vertex)")


class RelativeRotationEncoder:
    """Relative rotation encoding of meshes registered to a template (Hasler et al. 2009).

    Works for any manifold, consistently oriented triangle topology; boundary edges and several
    connected parts are handled (see the module docstring for the code layout and placement).

    Args:
        template_vertices: (V, 3) the rest mesh whose triangles the deformations are relative to.
        faces: (F, 3) int, shared by every scan.
        rotation_solver: "exact" (the default: the Hasler Equation 9 system factored for every body that
            needs it, on a pattern analysed once per template: ``FixedPatternRotationSolver``)
            or "direct" (assemble and factor with SuperLU for every body; slow, the reference
            the benchmark compares against). "pcg", the name of an earlier iterative method
            that older model files carry in their header, is read as "exact".
        on_flipped: what ``encode``/``fit`` do with a flipped triangle, one whose normal points
            against the vertex normals of its corners while the template's does not (a
            fold-over): "accept" (the default: encode it and count it, ``last_flipped_``),
            "warn" (the same and a RuntimeWarning per mesh), "raise" (MeshError) or "ignore"
            (not even looked for; ``last_flipped_`` is then all 0). Such triangles round-trip
            exactly, but their relative rotations sit near 180 degrees, where rotation vectors
            wrap, so interpolation and PCA misbehave there. Note: 89 of the 576 MakeHuman
            targets, applied at full weight, fold 2-20 small triangles this way, and real
            registered meshes have 1-11 in almost every mesh, hence the default.

    Attributes (after ``fit``):
        mean_rotvecs_: (F, 3, 3) mean rotation vector per face and edge slot.
        mean_stretch_: (F, 6) mean stretch per face.
        mean_vertices_: (V, 3) the mean model's mesh (decoded zero code), placed on the template.
        n_features_: D = 15 F (available before fit).
        slot_mask_: (F, 3) bool, True where the edge slot has a neighbour.
        last_flipped_: (N,) int, the flipped triangles of each mesh of the last ``encode`` call.
        last_factorized_: how many bodies of the last decode call needed a factorization
            (the others were consistent codes, solved exactly by the tree rotations; with
            "direct", all of them).
    """

    kind = "rre"
    # Constructor keywords a model file keeps (header "encoder_params"), and the run-time ones.
    PARAMS = ("rotation_solver", "on_flipped")
    RUNTIME_PARAMS = ("n_jobs",)
    # Decoding is two sparse solves per body: mapping samples and measures bodies by decoding
    # them, with a fitted linearization (``linearize``, ``DecoderLinearization``) for Jacobians.
    is_linear = False

    def __init__(self, template_vertices: np.ndarray, faces: np.ndarray, *, rotation_solver: str = "exact",
                 on_flipped: str = "accept", n_jobs: int | None = None):
        check_mesh(template_vertices, faces, name="template")
        tv = np.asarray(template_vertices, dtype=float)
        if tv.ndim != 2:
            raise MeshError(f"template: vertices have shape {tv.shape}, expected (V, 3)")
        if rotation_solver == "pcg":
            rotation_solver = "exact"
        if rotation_solver not in ("exact", "direct"):
            raise ParameterError(f"rotation_solver={rotation_solver!r}, expected 'exact' or 'direct'")
        self.template_vertices = tv
        self.faces = np.asarray(faces, dtype=np.int64)
        if on_flipped not in ON_FLIPPED:
            raise ParameterError(f"on_flipped={on_flipped!r}, expected one of {', '.join(ON_FLIPPED)}")
        self.rotation_solver = rotation_solver
        self.on_flipped = on_flipped
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
            raise MeshError(_degenerate_faces_message(tv, self.faces, bad))
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
        # The graph's own face order (RotationGraph): the tree, the kernels and the exact solver.
        self._graph = RotationGraph(self.neighbors, self.back, self.anchor_faces)
        roots = self._graph.roots
        lap = dual_laplacian(self._graph.neighbors).tolil()
        lap[roots, :] = 0.0
        lap[:, roots] = 0.0
        lap[roots, roots] = 0.5
        # For the consistency test (``_solve_one``): |(2 L)^-1|_inf = max row sum = max of
        # (2 L)^-1 1, since (2 L)^-1 >= 0 (2 L is an M-matrix); for a consistent code the
        # Hasler Equation 9 matrix is 2 L (x) I up to the tree's orthogonal change of basis.
        self._inverse_norm = float(FactorizedSolver(2.0 * lap.tocsr()).solve(np.ones(self.n_faces)).max())

        self._poisson = PoissonSolver(tv, self.faces)
        # Placement: vertex components (one per edge-connected part, checked above).
        n_comp, self._vertex_part = vertex_components(self.faces, self.n_vertices)
        self._part_vertices = [np.flatnonzero(self._vertex_part == c) for c in range(n_comp)]
        self._face_part = self._vertex_part[self.faces[:, 0]]
        # The Hasler Equation 9 pattern analysed once, a numeric factorization per body.
        self._exact = FixedPatternRotationSolver(self._graph)
        self.last_factorized_ = 0

    # ------------------------------------------------------------------ validation
    def _require_fit(self):
        if not hasattr(self, "mean_vertices_"):
            raise MeshError(f"{type(self).__name__} is not fitted; call fit(scans) first "
                            "(fit(template[None]) makes the template the mean model)")

    def _check_codes(self, codes) -> np.ndarray:
        return as_codes(codes, self.n_features_,
                        f"relative rotation encoding of this template (15 numbers x {self.n_faces} triangles)",
                        error=MeshError)

    def _encoding_blocks(self) -> list:
        """Per-template constants of ``encode``/``fit``, made on first use: the faces in blocks
        of ``ENCODE_BLOCK``, each ``(faces slice, corner indices (3, B), rest constants,
        neighbour faces (slot, B) (0 at boundary slots), boundary slots (slot, B) or None)``.
        Slot-major, so that products of a face's rotation with its three neighbours' broadcast
        over a middle axis and numpy's inner loops run over B faces, not 3 slots."""
        blocks = getattr(self, "_blocks", None)
        if blocks is None:
            rest = rest_triangles(self.template_vertices, self.faces)
            nbr = np.where(self.slot_mask_, self.neighbors, 0)
            blocks = []
            for start in range(0, self.n_faces, ENCODE_BLOCK):
                sl = slice(start, min(start + ENCODE_BLOCK, self.n_faces))
                boundary = ~self.slot_mask_[sl].T
                blocks.append((sl, np.ascontiguousarray(self.faces[sl].T), rest.take(sl),
                               np.ascontiguousarray(nbr[sl].T), boundary if boundary.any() else None))
            self._blocks = blocks
        return blocks

    def _rotations(self, x: np.ndarray, name: str, index: int, look_for_folds: bool = True):
        """Rotations and stretches of the deformation gradients of one mesh x (V, 3), checked.

        Returns ``(q, stretch, n_flipped)``: the rotations R_i of ``U_i = R_i S_i`` as
        component-first quaternions (4, F), the stretches S_i packed (F, 6) and the number of
        flipped triangles (0 when not looked for). Raises MeshError for degenerate
        triangles and inside-out meshes, and applies ``on_flipped`` (``index``: the mesh's
        position in the caller's batch, for the messages).
        """
        nf = self.n_faces
        comps = [np.ascontiguousarray(x[:, k]) for k in range(3)]
        q = np.empty((4, nf))
        stretch = np.empty((nf, 6))
        dbl = np.empty(nf)
        check_flips = look_for_folds and self.on_flipped != "ignore"
        normals = np.empty((nf, 3)) if check_flips else None
        volume = 0.0
        for sl, corner, rest, _, _ in self._encoding_blocks():
            a, b, c = ([comp[corner[k]] for comp in comps] for k in range(3))
            rot, st, dbl[sl], n = polar_from_corners(a, b, c, rest)
            q[:, sl] = quaternion_from_matrix_cf(rot)
            stretch[sl] = st.T
            # Signed volume of the tetrahedra from the origin: a . (e1 x e2) / 6, e1 x e2 = dbl n.
            volume += float(((a[0] * n[0] + a[1] * n[1] + a[2] * n[2]) * dbl[sl]).sum())
            if check_flips:
                normals[sl] = np.transpose(n)
        ratio = dbl / self._rest_double_area
        if (ratio < DEGENERATE_AREA_RATIO).any():
            f = int(np.flatnonzero(ratio < DEGENERATE_AREA_RATIO)[0])
            count = int((ratio < DEGENERATE_AREA_RATIO).sum())
            raise MeshError(f"{name}: mesh {index} has {count} degenerate triangle(s), first face {f} with area "
                            f"{0.5 * dbl[f]:.3g} m^2 (template {0.5 * self._rest_double_area[f]:.3g} m^2); "
                            "expected triangles of non-zero area")
        # The holes' caps, as capped_volume adds them (no faces: the caps alone).
        volume = volume / 6.0 + float(capped_volume(x, self.faces[:0], self._loops))
        if np.sign(volume) != np.sign(self._rest_volume):
            raise MeshError(f"{name}: mesh {index} is inside out (enclosed volume {volume:.3g} m^3, "
                            f"the template's {self._rest_volume:.3g} m^3): mirrored, or every face flipped; "
                            "expected the template's orientation")
        n_flipped = 0
        if check_flips:
            fold = _normal_agreement(normals[None], self.faces, self._incidence)[0]
            flipped = (fold < 0) & (self._rest_fold >= 0)
            n_flipped = int(flipped.sum())
            if flipped.any() and self.on_flipped in ("raise", "warn"):
                f = int(np.flatnonzero(flipped)[0])
                msg = (f"{name}: mesh {index} has {int(flipped.sum())} flipped triangle(s), first face {f}: "
                       "its normal points against the surface around it (the vertex normals of its corners), "
                       "the template's does not; expected an orientation-preserving registration "
                       "(on_flipped='accept' encodes it)")
                if self.on_flipped == "raise":
                    raise MeshError(msg)
                warnings.warn(msg, RuntimeWarning, stacklevel=4)
        return q, stretch, n_flipped

    # ------------------------------------------------------------------ API
    def fit(self, scans: np.ndarray, faces: np.ndarray | None = None) -> "RelativeRotationEncoder":
        """Compute the mean model: the average of every code component over ``scans`` (N, V, 3).

        ``fit(template_vertices[None])`` makes the template itself the mean model.
        """
        x = check_registered_meshes(scans, self.n_vertices, self.faces, faces, name="scans")
        # Folds are refused here under "raise"; otherwise they are counted (and warned about)
        # by ``encode`` alone, so a scan both fitted on and encoded is counted once.
        look_for_folds = self.on_flipped == "raise"
        blocks = self._encoding_blocks()
        # Sums per fixed, contiguous chunk of scans, added in chunk order: the mean model is the
        # same to the last bit whatever the thread count or timing.
        chunks = np.array_split(np.arange(len(x)), min(FIT_CHUNKS, len(x)))
        sum_rot = np.zeros((len(chunks), 3, 3, self.n_faces))  # chunk, component, slot, face
        sum_str = np.zeros((len(chunks), self.n_faces, 6))

        def work(k):
            rot = np.empty(sum_rot.shape[1:])
            for m in chunks[k]:
                q, stretch, _ = self._rotations(x[m], "scans", m, look_for_folds)
                for sl, _, _, nbr, _ in blocks:
                    rot[:, :, sl] = _relative_rotvecs(q[:, sl], q[:, nbr])
                sum_rot[k] += rot
                sum_str[k] += stretch

        self._run(work, range(len(chunks)))
        total_rot, total_str = sum_rot[0].copy(), sum_str[0].copy()
        for k in range(1, len(chunks)):
            total_rot += sum_rot[k]
            total_str += sum_str[k]
        self.mean_rotvecs_ = np.where(self.slot_mask_[..., None], total_rot.transpose(2, 1, 0) / len(x), 0.0)
        self.mean_stretch_ = total_str / len(x)
        self._mean_q = quaternion_exp_cf(components_first(self.mean_rotvecs_, 3))  # (4, F, 3)
        self.mean_vertices_ = self._decode(np.zeros((1, self.n_features_)), None, self.template_vertices)[0][0]
        return self

    def encode(self, vertices: np.ndarray, faces: np.ndarray | None = None, *,
               out: np.ndarray | None = None) -> np.ndarray:
        """Codes (N, 15 F) of meshes (V, 3) or (N, V, 3) registered to the template.

        ``faces``, if given, must equal the template's (checked). ``out``: an optional
        C-contiguous (N, 15 F) float64 or float32 array the codes are written into (and
        returned), e.g. rows of a large float32 matrix (no float64 copy of the batch is made).
        Raises MeshError for wrong shapes, NaN, degenerate or flipped triangles.
        """
        self._require_fit()
        x = check_registered_meshes(vertices, self.n_vertices, self.faces, faces)
        shape = (len(x), self.n_features_)
        if out is None:
            out = np.empty(shape)
        elif (out.shape != shape or out.dtype not in (np.float64, np.float32)
              or not out.flags.c_contiguous):
            raise ParameterError(f"out: {out.dtype} array of shape {out.shape}, expected a C-contiguous float64 or "
                                 f"float32 array of shape {shape}")
        codes = out.reshape(len(x), self.n_faces, FEATURES_PER_FACE)
        blocks = self._encoding_blocks()
        conj_mean = np.ascontiguousarray(quaternion_conjugate_cf(self._mean_q).transpose(0, 2, 1))  # (4, slot, F)

        flipped = np.zeros(len(x), dtype=np.int64)

        def work(m):
            q, stretch, flipped[m] = self._rotations(x[m], "vertices", m)
            code = codes[m]
            for sl, _, _, nbr, boundary in blocks:
                # r_ij = log(Q_ij M_ij^-1), (3, slot, B)
                rot = _relative_rotvecs(q[:, sl], q[:, nbr], conj_mean[:, :, sl])
                if boundary is not None:
                    rot[:, boundary] = 0.0
                np.copyto(code[sl, :9].reshape(-1, 3, 3), rot.transpose(2, 1, 0))
            code[:, 9:] = stretch - self.mean_stretch_

        self._run(work, range(len(x)))
        self.last_flipped_ = flipped
        return out

    # ------------------------------------------------------------------ state
    def to_arrays(self, prefix: str = "encoder_") -> dict[str, np.ndarray]:
        """The fitted state as flat float64 arrays: ``mean_vertices`` (V, 3) metres,
        ``mean_rotvecs`` (F, 3, 3) radians, ``mean_stretch`` (F, 6). The template and the
        constructor keywords (``PARAMS``) are the caller's to store."""
        self._require_fit()
        return {prefix + "mean_vertices": np.asarray(self.mean_vertices_, dtype=np.float64),
                prefix + "mean_rotvecs": np.asarray(self.mean_rotvecs_, dtype=np.float64),
                prefix + "mean_stretch": np.asarray(self.mean_stretch_, dtype=np.float64)}

    @classmethod
    def from_arrays(cls, arrays, prefix: str, template_vertices: np.ndarray, faces: np.ndarray,
                    **params) -> "RelativeRotationEncoder":
        """A fitted encoder from ``to_arrays`` output, without refitting (shapes checked against the
        template; ``params``: constructor keywords). Files written while the default decoder was
        iterative also carry its step settings ("tol", "max_iter"): dropped."""
        params = {k: v for k, v in params.items() if k not in ("tol", "max_iter")}
        enc = cls(template_vertices, faces, **params)
        names = [prefix + s for s in ("mean_vertices", "mean_rotvecs", "mean_stretch")]
        missing = [n for n in names if n not in arrays]
        if missing:
            raise ParameterError(f"relative rotation encoder: arrays {', '.join(missing)} missing")
        mean_vertices, rot, stretch = (np.asarray(arrays[n], dtype=float) for n in names)
        if rot.shape != (enc.n_faces, 3, 3) or stretch.shape != (enc.n_faces, 6) \
                or mean_vertices.shape != (enc.n_vertices, 3):
            raise ParameterError(f"relative rotation encoder: '{names[0]}' {mean_vertices.shape}, '{names[1]}' "
                                 f"{rot.shape}, '{names[2]}' {stretch.shape}; expected ({enc.n_vertices}, 3), "
                                 f"({enc.n_faces}, 3, 3) and ({enc.n_faces}, 6) for this template")
        enc.mean_rotvecs_ = rot
        enc.mean_stretch_ = stretch
        # Component-first quaternions (4, F, 3), what fit derives from mean_rotvecs_.
        enc._mean_q = np.ascontiguousarray(np.moveaxis(quaternion_exp(rot), -1, 0))
        enc.mean_vertices_ = mean_vertices
        return enc

    def linearize(self, space, k: int | None = None) -> DecoderLinearization:
        """Affine stand-in ``v ~ base + z @ basis`` of ``space.reconstruct`` on the first ``k``
        coefficients (default ``LINEARIZED_COEFFICIENTS``, each costs a decode): the tangent at
        the mean by forward differences (``k + 1`` decodes, cached).
        A least-squares fit over sampled bodies (``DecoderLinearization.partial_fit``) is better
        over a whole box; mapping makes one on its training set since ``is_linear`` is False."""
        return DecoderLinearization.at_mean(space, LINEARIZED_COEFFICIENTS if k is None else k)

    def tangent(self, code: np.ndarray) -> DecodeTangent:
        """The decoder at one code (D,) with its exact derivatives (``encoding.tangent``):
        ``.vertices`` (V, 3) is ``decode(code)`` (to ~1e-9 m: the Hasler Equation 9 system is
        always factored here, the factor kept for the tangents), ``.jvp(dcodes)`` and
        ``.vjp(cotangents)`` its Jacobian and transpose. Costs one decode."""
        self._require_fit()
        c = self._check_codes(code)
        if len(c) != 1:
            raise ParameterError(f"code: {len(c)} codes, expected one (D,) code")
        c = np.ascontiguousarray(c[0], dtype=float)
        nf = self.n_faces
        lanes = 2 if (self.n_jobs or os.cpu_count() or 1) > 1 else 1
        g = self._graph
        mean_q, mean_stretch = self._graph_order_means()
        code_g = np.ascontiguousarray(c.reshape(nf, FEATURES_PER_FACE)[g.order])
        rel = np.empty((nf, 3, 3, 3))
        _lanes(lanes, nf, lambda lo, hi: _relative_kernel(code_g, mean_q, rel, lo, hi))
        chol = BlockCholesky(self._exact.pattern)
        q = self._exact.solve(rel, lanes, chol=chol)
        identity = np.tile([1.0, 0.0, 0.0, 1.0, 0.0, 1.0], (nf, 1))
        rot = self._gradients(q, np.zeros((nf, 6)), identity, lanes)[g.rank]        # R_i, mesh order
        q, rel = q[g.rank], rel[g.rank]
        stretch = unpack_stretch(c.reshape(nf, FEATURES_PER_FACE)[:, 9:] + self.mean_stretch_)
        x = self._poisson.solve((rot @ stretch)[None])
        placed, part_rot = self._place(x, self.mean_vertices_)
        # Polar factor's tangent: (tr(P) I - P) w = vee(W^T dQ - dQ^T W), P = W^T Q = R Q.
        p = rot @ q
        p = 0.5 * (p + np.swapaxes(p, -1, -2))
        k = np.trace(p, axis1=-2, axis2=-1)[:, None, None] * np.eye(3) - p
        # Inverse by the adjugate (rows' cross products), not LAPACK per 3x3 matrix (numpy's
        # batched inv and det: 45 ms a tangent under load; this: a few ms).
        adj = np.stack([np.cross(k[:, 1], k[:, 2]), np.cross(k[:, 2], k[:, 0]), np.cross(k[:, 0], k[:, 1])], axis=2)
        det = np.einsum("fi,fi->f", k[:, 0], adj[:, :, 0])
        ok = np.abs(det) > 1e-12 * np.maximum(np.abs(np.trace(k, axis1=-2, axis2=-1)), 1e-300) ** 3
        kinv = np.zeros_like(k)
        kinv[ok] = adj[ok] / det[ok, None, None]  # a face whose Q has det <= 0 (wild codes only): no rotation tangent
        jl = np.empty((nf, 3, 3, 3))
        left_jacobians(c.reshape(nf, FEATURES_PER_FACE), self.slot_mask_, jl)
        row = self._tangent_rows()
        if getattr(self, "_poisson_adjoint", None) is None:
            self._poisson_adjoint = PoissonAdjoint(self._poisson)
        valid = self.slot_mask_
        nbr = np.where(valid, self.neighbors, np.arange(nf)[:, None]).astype(np.int64)
        bk = np.where(valid, self.back, 0).astype(np.int64)
        return DecodeTangent(c, placed[0], jl=jl, rel=np.ascontiguousarray(rel), q=np.ascontiguousarray(q),
                             rot=np.ascontiguousarray(rot), stretch=stretch, kinv=kinv, row=row, nbr=nbr, bk=bk,
                             valid=np.ascontiguousarray(valid), chol=chol, poisson=self._poisson,
                             adjoint=self._poisson_adjoint, part_vertices=self._part_vertices,
                             part_rotations=part_rot[0], lanes=lanes)

    def _tangent_rows(self) -> np.ndarray:
        """Row of each face (mesh order) in the factor's permuted order (-1: an anchor)."""
        row = getattr(self, "_rows_cache", None)
        if row is None:
            ex, g = self._exact, self._graph
            position = np.empty(ex.pattern.n, dtype=np.int64)
            position[ex.pattern.order] = np.arange(ex.pattern.n)
            of_graph = np.full(self.n_faces, -1, dtype=np.int64)
            of_graph[ex.free] = position
            row = self._rows_cache = of_graph[g.rank]
        return row

    def decode(self, codes: np.ndarray, constraints: PositionConstraints | None = None) -> np.ndarray:
        """Meshes (N, V, 3) from codes (N, 15 F) or (15 F,), placed on the mean model.

        With ``constraints`` (``mesh.solver.PositionConstraints``) the Poisson step also pulls
        the chosen vertices softly to the given positions; the body keeps the orientation the
        unconstrained placement gives it, and its position follows the constraints.
        """
        self._require_fit()
        c = self._check_codes(codes)
        out = np.empty((len(c), self.n_vertices, 3))
        factorized = []
        # One body: split its kernels over two threads; a batch already has a body per thread.
        lanes = 2 if len(c) == 1 and (self.n_jobs or os.cpu_count() or 1) > 1 else 1

        def work(s):
            chunk_constraints = constraints
            if constraints is not None and np.ndim(constraints.positions) == 3:
                chunk_constraints = PositionConstraints(constraints.indices,
                                                        np.asarray(constraints.positions)[s:s + DECODE_CHUNK],
                                                        constraints.weight)
            out[s:s + DECODE_CHUNK], n_fact = self._decode(c[s:s + DECODE_CHUNK], chunk_constraints,
                                                            self.mean_vertices_, lanes)
            factorized.append(n_fact)

        self._run(work, range(0, len(c), DECODE_CHUNK))
        self.last_factorized_ = sum(factorized)
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
        c = np.ascontiguousarray(codes, dtype=float).reshape(len(codes), self.n_faces, FEATURES_PER_FACE)
        out = np.empty((len(c), self.n_faces, 3, 3, 3))
        mean_q = self._mean_quaternions()
        for m in range(len(c)):
            _relative_kernel(c[m], mean_q, out[m], 0, self.n_faces)
        return out

    def _mean_quaternions(self) -> np.ndarray:
        """Unit quaternions (F, 3, 4) of the mean relative rotations (cached per fit)."""
        cache = getattr(self, "_mean_q_cache", None)
        if cache is None or cache[0] is not self.mean_rotvecs_:
            cache = (self.mean_rotvecs_, np.ascontiguousarray(quaternion_exp(self.mean_rotvecs_)))
            self._mean_q_cache = cache
        return cache[1]

    def solve_rotations(self, relative: np.ndarray, solver: str | None = None) -> np.ndarray:
        """Per-face rotations R_i (N, F, 3, 3) from relative rotations (N, F, 3, 3, 3) by Hasler Equation 9,
        projected onto SO(3). ``solver``: "exact" or "direct" (default: ``rotation_solver``)."""
        solver = solver or self.rotation_solver
        if solver == "direct":
            q = solve_rotations_direct(relative, self.neighbors, self.back, self.anchor_faces)
            self.last_factorized_ = len(relative)
        else:
            g, q, self.last_factorized_ = self._graph, np.empty(relative.shape[:2] + (3, 3)), 0
            for m in range(len(relative)):
                rel = np.ascontiguousarray(relative[m][g.order], dtype=float)
                qm, factored = self._solve_one(rel, np.empty((self.n_faces, 3, 3)))
                q[m] = qm[g.rank]
                self.last_factorized_ += factored
        # Hasler Equation 9 solves for Q_i = R_i^T; return the rotations R_i of U_i = R_i S_i.
        return np.swapaxes(project_to_rotations(q), -1, -2)

    def _solve_one(self, rel: np.ndarray, t: np.ndarray, lanes: int = 1) -> tuple[np.ndarray, bool]:
        """Least-squares ``Q`` (F, 3, 3) of Hasler Equation 9 for one body's relative rotations (F, 3, 3, 3),
        graph order, and whether it needed a factorization. First the rotations ``T`` chained
        from the anchors along the spanning tree (into ``t``): they solve a consistent code
        exactly (every round trip), so such a body pays no factorization."""
        g = self._graph
        _tree_kernel(rel, g.sweep, g.parent, g.parent_slot, len(g.roots), t)
        # Hasler Equation 9's residual at T has entries <= 6 max|Q_ij T_j - T_i| (two terms per slot, three
        # slots), so T is within |A^-1|_inf times that of the least-squares solution.
        mismatch = max(_lanes(lanes, self.n_faces, lambda lo, hi: _mismatch_kernel(rel, t, g.nbr, g.valid, lo, hi)))
        if 6.0 * mismatch * self._inverse_norm < CONSISTENT_TOL:
            return t, False
        return self._exact.solve(rel, lanes), True

    def _decode(self, c: np.ndarray, constraints, reference: np.ndarray, lanes: int = 1):
        n = len(c)
        c = np.ascontiguousarray(c, dtype=float).reshape(n, self.n_faces, FEATURES_PER_FACE)
        u, factorized = np.empty((n, self.n_faces, 3, 3)), 0
        if self.rotation_solver == "exact":
            # Fused per body: relative rotations, the rotation solve and the gradients U = R S,
            # in the graph's face order (one gather of the code in, one of U out), where the
            # kernels walk their arrays in order: reading the mesh's order through an index
            # instead made the relative rotations 2.6x and the gradients 7x slower (measured).
            w = _workspace(self.n_faces)
            rel, order, rank = w["rel"], self._graph.order, self._graph.rank
            mean_q, mean_stretch = self._graph_order_means()
            for m in range(n):
                code = c[m][order]
                _lanes(lanes, self.n_faces, lambda lo, hi: _relative_kernel(code, mean_q, rel, lo, hi))
                q, factored = self._solve_one(rel, w["t"], lanes)
                factorized += factored
                u[m] = self._gradients(q, code[:, 9:], mean_stretch, lanes)[rank]
        else:
            rot = self.solve_rotations(self.relative_rotations(c), self.rotation_solver)
            u, factorized = rot @ unpack_stretch(c[..., 9:] + self.mean_stretch_), n
        x = self._poisson.solve(u)
        placed, part_rot = self._place(x, reference)
        if constraints is None:
            return placed, factorized
        # Keep the placed orientation: rotate each part's gradients as the placement rotated it.
        u = part_rot[:, self._face_part] @ u
        return self._poisson.solve(u, constraints, pinned_positions=placed), factorized

    def _graph_order_means(self) -> tuple[np.ndarray, np.ndarray]:
        """Mean relative rotations as quaternions (F, 3, 4) and mean stretches (F, 6), in the
        ``RotationGraph``'s face order (cached per fit)."""
        cache = getattr(self, "_graph_means_cache", None)
        if cache is None or cache[0] is not self.mean_rotvecs_ or cache[1] is not self.mean_stretch_:
            order = self._graph.order
            cache = (self.mean_rotvecs_, self.mean_stretch_, np.ascontiguousarray(self._mean_quaternions()[order]),
                     np.ascontiguousarray(self.mean_stretch_[order]))
            self._graph_means_cache = cache
        return cache[2], cache[3]

    def _gradients(self, q: np.ndarray, stretch: np.ndarray, mean_stretch: np.ndarray, lanes: int = 1) -> np.ndarray:
        """Deformation gradients (F, 3, 3) ``U_i = R_i S_i``: ``R_i^T`` the rotation nearest to
        ``Q_i`` (q (F, 3, 3), ``project_to_rotations``), S_i from the code's stretch (F, 6)
        plus the mean's (F, 6); all in one face order."""
        u = np.empty((self.n_faces, 3, 3))
        bad = np.empty(self.n_faces, dtype=bool)
        _lanes(lanes, self.n_faces, lambda lo, hi: _gradients_kernel(q, stretch, mean_stretch, u, bad, lo, hi))
        if bad.any():  # det(Q) <= 0: the SVD projection of project_to_rotations
            rot = np.swapaxes(project_to_rotations(q[bad]), -1, -2)
            u[bad] = rot @ unpack_stretch(stretch[bad] + mean_stretch[bad])
        return u

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


def _relative_rotvecs(qi, qj, right=None):
    """Rotation vectors (3, slot, B) of ``conj(q_i) q_j [right]``: the relative rotations
    ``Q_ij = R_i^T R_j`` of faces to their neighbours (Hasler Equation 8), optionally followed by ``right``
    (the conjugate mean ``M_ij^-1``).

    Encoding's inner loop, fused: ``qi`` (4, B), ``qj`` and ``right`` (4, slot, B) component-
    first quaternions; the same arithmetic as ``quaternion_log_cf(quaternion_multiply_cf(quaternion_multiply_cf(quaternion_conjugate_cf(qi), qj), right))``
    (so the same codes, to the last bit) without stacking or conjugating copies.
    """
    aw, ax, ay, az = (c[None] for c in qi)
    bw, bx, by, bz = qj
    w = aw * bw + ax * bx + ay * by + az * bz
    x = aw * bx - ax * bw - ay * bz + az * by
    y = aw * by + ax * bz - ay * bw - az * bx
    z = aw * bz - ax * by + ay * bx - az * bw
    if right is not None:
        qw, qx, qy, qz = right
        w, x, y, z = (w * qw - x * qx - y * qy - z * qz,
                      w * qx + x * qw + y * qz - z * qy,
                      w * qy - x * qz + y * qw + z * qx,
                      w * qz + x * qy - y * qx + z * qw)
    # quaternion_log_cf: angle in [0, pi], atan2 for full precision at small angles.
    sign = np.where(w < 0, -1.0, 1.0)
    w = w * sign
    s = np.sqrt(x * x + y * y + z * z)
    small = s < 1e-8
    factor = np.where(small, 2.0 / np.maximum(w, 1e-300), 2.0 * np.arctan2(s, w) / np.where(small, 1.0, s)) * sign
    return np.stack([x * factor, y * factor, z * factor])
