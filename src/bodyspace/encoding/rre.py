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
step in the Lie algebra (a solve with the same ``2 L``) first spreads it, after which
shape-only PCA samples and mild interpolations converge in 1-9 steps to ``tol``. Every step of
the chain (relative rotations, tree, smoothing, the gauged system and its products, the
projection and ``U = R S``) is a compiled kernel (numba) over the faces of one body, and the
``2 L`` solves are triangular solves of its LDL^T factor over all 9 columns at once
(``mesh.solver.ldl_solve``). Codes with vortices (more than ``DEFECT_SLOTS`` of the slots
still turned by more than ``DEFECT_ANGLE`` after smoothing: pose+shape PCA samples and
interpolations across LBS fold-overs), where the least-squares Q_i collapse towards 0 and CG
needs 15-110 steps, and codes not converged in ``max_iter`` steps, are solved exactly by
``FixedPatternRotationSolver``: the system's pattern is analysed once per template and each
body costs a numeric LDL^T refactorization (qdldl).
``rotation_solver="exact"`` uses that for every body; ``"direct"`` assembles and factors the
full system with SuperLU for every body (the baseline the benchmark compares against).
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

from bodyspace.encoding.deformation import polar_from_corners, rest_triangles
from bodyspace.encoding.rotations import _planar, _qconj, _qexp, _qfrom_matrix, project_to_rotations, quaternion_exp
from bodyspace.encoding.vertex import check_codes, check_scans, rigid_procrustes
from bodyspace.errors import MeshError, ParameterError
from bodyspace.mesh.geometry import boundary_loops, capped_volume, check_mesh
from bodyspace.mesh.operators import dual_laplacian, triangle_frames
from bodyspace.mesh.solver import FactorizedSolver, PoissonSolver, PositionConstraints, single_threaded_blas
from bodyspace.mesh.topology import (check_topology, dual_graph, face_components, spanning_forest,
                                     vertex_components)
from scipy.sparse.csgraph import breadth_first_order, reverse_cuthill_mckee

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
# A slot of the smoothed gauge turned by more than DEFECT_ANGLE (radians) marks a defect of
# the code (a vortex of the rotation field: typically where near-180-degree relative rotations
# of an LBS fold-over were combined). Codes with more than DEFECT_SLOTS of their slots so
# turned need 15-70 CG steps (measured): they are factored at once.
DEFECT_ANGLE = 0.3
DEFECT_SLOTS = 0.001
# Gauss-Newton rounds smoothing the tree gauge before CG (see solve_rotations_pcg).
SMOOTH_ROUNDS = 1
# Encoding works on one body per task and on its faces in blocks of this many, so that the
# temporaries of the closed-form polar decomposition and of the relative rotations (up to
# 3 x 8192 float64, 196 KB each) stay in the L2 cache. Measured on the 26,756-face template,
# single thread, under load: 10-12 ms of CPU a body for blocks of 4096 to 32768 faces, 14 ms
# for 2048 (per-call overhead), against 24 ms for the previous whole-body Newton iteration.
ENCODE_BLOCK = 8192
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


# ---------------------------------------------------------------------------- Eq. 9 solvers

# Compiled kernels (numba, ``cache=True``: compiled on first use, ~10-25 s for all of them
# with ``mesh.solver.ldl_solve`` on a loaded 2-core machine, then loaded from the cache in
# ~1 s). Each is one pass over the faces of one body with the 3x3 products written out: the
# numpy version of the same steps cost 50-100 ms per body in temporaries and stacking
# (measured), the kernels ~15 ms. ``nogil``: ``n_jobs`` threads decode bodies side by side.
_kernel = numba.njit(cache=True, nogil=True)


@_kernel
def _relative_kernel(code, mean_q, faces, out):
    """Relative rotation matrices ``exp(r_ik) M_ik`` (F, 3, 3, 3) of one code (F, 15) and the
    mean model's quaternions (F, 3, 4); out[i] is for face ``faces[i]`` of the code."""
    for i in range(len(faces)):
        f = faces[i]
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
            m = out[i, k]
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
def _mismatch_kernel(rel, t, nbr, valid):
    """Largest Eq. 9 residual ``|Q_ij T_j - T_i|_F`` over the edge slots."""
    mx = 0.0
    for i in range(rel.shape[0]):
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
def _gauged(rel, t, i, k, j, e):
    """``e = T_i^T Q_ik T_j`` (3, 3)."""
    for c in range(3):
        m0 = rel[i, k, 0, 0] * t[j, 0, c] + rel[i, k, 0, 1] * t[j, 1, c] + rel[i, k, 0, 2] * t[j, 2, c]
        m1 = rel[i, k, 1, 0] * t[j, 0, c] + rel[i, k, 1, 1] * t[j, 1, c] + rel[i, k, 1, 2] * t[j, 2, c]
        m2 = rel[i, k, 2, 0] * t[j, 0, c] + rel[i, k, 2, 1] * t[j, 1, c] + rel[i, k, 2, 2] * t[j, 2, c]
        for r in range(3):
            e[r, c] = t[i, 0, r] * m0 + t[i, 1, r] * m1 + t[i, 2, r] * m2


@_kernel
def _rotvec(e, out):
    """Rotation vector (angle in [0, pi]) of a rotation matrix (3, 3): Shepperd's quaternion
    (largest pivot), then ``2 atan2(|v|, w)``."""
    tr = e[0, 0] + e[1, 1] + e[2, 2]
    if tr >= e[0, 0] and tr >= e[1, 1] and tr >= e[2, 2]:
        w, x, y, z = 1 + tr, e[2, 1] - e[1, 2], e[0, 2] - e[2, 0], e[1, 0] - e[0, 1]
    elif e[0, 0] >= e[1, 1] and e[0, 0] >= e[2, 2]:
        w, x, y, z = e[2, 1] - e[1, 2], 1 + e[0, 0] - e[1, 1] - e[2, 2], e[0, 1] + e[1, 0], e[0, 2] + e[2, 0]
    elif e[1, 1] >= e[2, 2]:
        w, x, y, z = e[0, 2] - e[2, 0], e[0, 1] + e[1, 0], 1 - e[0, 0] + e[1, 1] - e[2, 2], e[1, 2] + e[2, 1]
    else:
        w, x, y, z = e[1, 0] - e[0, 1], e[0, 2] + e[2, 0], e[1, 2] + e[2, 1], 1 - e[0, 0] - e[1, 1] + e[2, 2]
    if w < 0:
        w, x, y, z = -w, -x, -y, -z
    s = np.sqrt(x * x + y * y + z * z)
    f = 2.0 * np.arctan2(s, w) / s if s > 1e-300 else 0.0
    out[0], out[1], out[2] = x * f, y * f, z * f


@_kernel
def _smooth_rhs_kernel(rel, t, nbr, bk, valid, is_root, b):
    """Right-hand side (F, 3) of the Gauss-Newton gauge step: ``sum_k eps_ik - eps_jk'`` with
    ``eps_ik = log(T_i^T Q_ik T_j)``; zero at the roots. Each edge is visited once (from its
    lower face), both directions together."""
    e = np.empty((3, 3))
    v = np.empty(3)
    w = np.empty(3)
    b[:] = 0.0
    for i in range(rel.shape[0]):
        for k in range(3):
            j = nbr[i, k]
            if valid[i, k] and i < j:
                _gauged(rel, t, i, k, j, e)
                _rotvec(e, v)
                _gauged(rel, t, j, bk[i, k], i, e)
                _rotvec(e, w)
                for c in range(3):
                    b[i, c] += v[c] - w[c]
                    b[j, c] += w[c] - v[c]
    for i in range(rel.shape[0]):
        if is_root[i]:
            b[i] = 0.0


@_kernel
def _turn_gauge_kernel(t, phi):
    """``T_i <- T_i exp([phi_i])`` (Rodrigues)."""
    for i in range(t.shape[0]):
        x, y, z = phi[i, 0], phi[i, 1], phi[i, 2]
        th2 = x * x + y * y + z * z
        th = np.sqrt(th2)
        if th < 1e-4:
            a, b = 1.0 - th2 / 6.0, 0.5 - th2 / 24.0
        else:
            a, b = np.sin(th) / th, (1.0 - np.cos(th)) / th2
        g00, g01, g02 = 1 - b * (y * y + z * z), -a * z + b * x * y, a * y + b * x * z
        g10, g11, g12 = a * z + b * x * y, 1 - b * (x * x + z * z), -a * x + b * y * z
        g20, g21, g22 = -a * y + b * x * z, a * x + b * y * z, 1 - b * (x * x + y * y)
        for r in range(3):
            t0, t1, t2 = t[i, r, 0], t[i, r, 1], t[i, r, 2]
            t[i, r, 0] = t0 * g00 + t1 * g10 + t2 * g20
            t[i, r, 1] = t0 * g01 + t1 * g11 + t2 * g21
            t[i, r, 2] = t0 * g02 + t1 * g12 + t2 * g22


@_kernel
def _gauged_system_kernel(rel, t, nbr, bk, valid, is_root, deg2, defect_trace, blocks, r0):
    """Off-diagonal blocks ``E_ik + E_jk'^T`` (F, 3, 3, 3) of the gauged normal matrix
    (``E_ik = T_i^T Q_ik T_j``; zero on boundary slots) and the residual ``-A I`` (F, 3, 3) of
    Y = I. Returns how many slots have ``trace E < defect_trace`` (turned by more than the
    defect angle). Each edge is visited once, from its lower face."""
    nf = rel.shape[0]
    e = np.empty((3, 3))
    f = np.empty((3, 3))
    defects = 0
    for i in range(nf):
        for r in range(3):
            for c in range(3):
                r0[i, r, c] = -deg2[i] if r == c else 0.0
    for i in range(nf):
        for k in range(3):
            j = nbr[i, k]
            if not valid[i, k]:
                blocks[i, k] = 0.0
            elif i < j:
                kb = bk[i, k]
                _gauged(rel, t, i, k, j, e)
                _gauged(rel, t, j, kb, i, f)
                if e[0, 0] + e[1, 1] + e[2, 2] < defect_trace:
                    defects += 1
                if f[0, 0] + f[1, 1] + f[2, 2] < defect_trace:
                    defects += 1
                for r in range(3):
                    for c in range(3):
                        v = e[r, c] + f[c, r]
                        blocks[i, k, r, c] = v
                        blocks[j, kb, c, r] = v
                        r0[i, r, c] += v
                        r0[j, c, r] += v
    for i in range(nf):
        if is_root[i]:
            r0[i] = 0.0
    return defects


@_kernel
def _apply_kernel(blocks, nbr, deg2, is_root, y, out):
    """``out = A y`` for the gauged normal matrix (diagonal ``deg2 I``, off-diagonal
    ``-blocks``), root rows zero; y, out (F, 3, 3)."""
    for i in range(y.shape[0]):
        if is_root[i]:
            out[i] = 0.0
            continue
        for r in range(3):
            for c in range(3):
                out[i, r, c] = deg2[i] * y[i, r, c]
        for k in range(3):
            j = nbr[i, k]
            for r in range(3):
                b0, b1, b2 = blocks[i, k, r, 0], blocks[i, k, r, 1], blocks[i, k, r, 2]
                for c in range(3):
                    out[i, r, c] -= b0 * y[j, 0, c] + b1 * y[j, 1, c] + b2 * y[j, 2, c]


@_kernel
def _gram_kernel(a, b):
    """``a^T b`` (3, 3) of block vectors (F, 3, 3) flattened to (3F, 3)."""
    g = np.zeros((3, 3))
    for i in range(a.shape[0]):
        for r in range(3):
            for c in range(3):
                g[r, c] += a[i, 0, r] * b[i, 0, c] + a[i, 1, r] * b[i, 1, c] + a[i, 2, r] * b[i, 2, c]
    return g


@_kernel
def _cg_update_kernel(y, r, p, q, alpha):
    """``y += p alpha``, ``r -= q alpha`` (block vectors (F, 3, 3), alpha (3, 3))."""
    for i in range(y.shape[0]):
        for a in range(3):
            p0, p1, p2 = p[i, a, 0], p[i, a, 1], p[i, a, 2]
            q0, q1, q2 = q[i, a, 0], q[i, a, 1], q[i, a, 2]
            for c in range(3):
                y[i, a, c] += p0 * alpha[0, c] + p1 * alpha[1, c] + p2 * alpha[2, c]
                r[i, a, c] -= q0 * alpha[0, c] + q1 * alpha[1, c] + q2 * alpha[2, c]


@_kernel
def _cg_direction_kernel(z, p, beta):
    """``p <- z + p beta``."""
    for i in range(z.shape[0]):
        for a in range(3):
            p0, p1, p2 = p[i, a, 0], p[i, a, 1], p[i, a, 2]
            for c in range(3):
                p[i, a, c] = z[i, a, c] + p0 * beta[0, c] + p1 * beta[1, c] + p2 * beta[2, c]


@_kernel
def _gradients_kernel(t, y, stretch, mean_stretch, faces, u, bad):
    """Deformation gradients ``U_f = R_f S_f`` (F, 3, 3) of the mesh faces ``f = faces[i]``:
    ``R_f`` the transposed polar factor of ``Q_i = T_i Y_i`` (scaled Newton iteration, as
    ``_polar9``), ``S_f`` from the code's stretch (F, 6) plus the mean's. ``bad[i]`` where
    det(Q_i) <= 0 (U_f left unset)."""
    x = np.empty((3, 3))
    c = np.empty((3, 3))
    for i in range(t.shape[0]):
        scale = 0.0
        for r in range(3):
            for cc in range(3):
                x[r, cc] = t[i, r, 0] * y[i, 0, cc] + t[i, r, 1] * y[i, 1, cc] + t[i, r, 2] * y[i, 2, cc]
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
        f = faces[i]
        s, m = stretch[f], mean_stretch[f]
        s00, s01, s02 = s[0] + m[0], s[1] + m[1], s[2] + m[2]
        s11, s12, s22 = s[3] + m[3], s[4] + m[4], s[5] + m[5]
        for r in range(3):  # row r of R = column r of the polar factor
            a0, a1, a2 = x[0, r], x[1, r], x[2, r]
            u[f, r, 0] = a0 * s00 + a1 * s01 + a2 * s02
            u[f, r, 1] = a0 * s01 + a1 * s11 + a2 * s12
            u[f, r, 2] = a0 * s02 + a1 * s12 + a2 * s22


class RotationGraph:
    """The arrays the Eq. 9 kernels need, built once per template, in the graph's own face order.

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


def _pcg_one(rel: np.ndarray, graph: RotationGraph, preconditioner: FactorizedSolver, inverse_norm: float,
             tol: float, max_iter: int) -> tuple[np.ndarray, np.ndarray, int, bool]:
    """One body of ``solve_rotations_pcg``: ``(T (F, 3, 3), Y (F, 3, 3), steps, converged)``
    with the least-squares ``Q = T Y``."""
    nf = graph.n_faces
    t = np.empty((nf, 3, 3))
    _tree_kernel(rel, graph.sweep, graph.parent, graph.parent_slot, len(graph.roots), t)
    y = np.zeros((nf, 3, 3))
    y[:, 0, 0] = y[:, 1, 1] = y[:, 2, 2] = 1.0
    # The starting CG residual has entries <= 6 max|Q_ij T_j - T_i| (two terms per slot, three
    # slots): if even |P^-1|_inf times that is below tol, the code is consistent up to
    # round-off and the tree rotations are the answer (every round trip).
    if 6.0 * _mismatch_kernel(rel, t, graph.nbr, graph.valid) * inverse_norm < tol:
        return t, y, 0, True
    b = np.empty((nf, 3))
    for _ in range(SMOOTH_ROUNDS):
        _smooth_rhs_kernel(rel, t, graph.nbr, graph.bk, graph.valid, graph.is_root, b)
        _turn_gauge_kernel(t, preconditioner.solve(b))
    blocks = np.empty((nf, 3, 3, 3))
    r = np.empty((nf, 3, 3))
    defects = _gauged_system_kernel(rel, t, graph.nbr, graph.bk, graph.valid, graph.is_root, graph.deg2,
                                    1.0 + 2.0 * np.cos(DEFECT_ANGLE), blocks, r)
    if defects > DEFECT_SLOTS * graph.valid.sum():
        return t, y, 0, False

    def precondition(v):
        return preconditioner.solve(v.reshape(nf, 9)).reshape(nf, 3, 3)

    # Block preconditioned CG (O'Leary 1980): the three columns of Y are three right-hand
    # sides of one matrix sharing one Krylov space (3x3 step sizes), so the slow directions,
    # common to all three, are removed together. pinv: once the columns have (nearly)
    # converged the Gram matrices lose rank.
    z = precondition(r)
    p, zr, q = z.copy(), _gram_kernel(z, r), np.empty_like(z)
    steps = 0
    while np.abs(z).max() >= tol:
        if steps == max_iter:
            return t, y, steps, False
        _apply_kernel(blocks, graph.nbr, graph.deg2, graph.is_root, p, q)
        alpha = np.linalg.pinv(_gram_kernel(p, q), rcond=1e-13) @ zr
        _cg_update_kernel(y, r, p, q, alpha)
        z = precondition(r)
        zr_new = _gram_kernel(z, r)
        beta = np.linalg.pinv(zr, rcond=1e-13) @ zr_new
        zr = zr_new
        _cg_direction_kernel(z, p, beta)
        steps += 1
    return t, y, steps, True


def solve_rotations_pcg(relative: np.ndarray, graph: RotationGraph, preconditioner: FactorizedSolver,
                        inverse_norm: float, tol: float = 1e-5,
                        max_iter: int = 20) -> tuple[np.ndarray, int, np.ndarray]:
    """Least-squares rotations of Eq. 9 by tree-gauged, Laplacian-preconditioned block CG.

    The gauge is the tree rotations (``_tree_kernel``): they solve a consistent code exactly,
    so an unmodified code (a round trip) needs no CG step at all. A modified code (an
    interpolation, a PCA sample) leaves its inconsistency on the edges that close loops of the
    tree; ``SMOOTH_ROUNDS`` Gauss-Newton steps in the Lie algebra spread it over the mesh
    (``T_i <- T_i exp([phi_i])``, ``2 L phi_i = sum_j (eps_ij - eps_ji)``,
    ``eps_ij = log(T_i^T Q_ij T_j)``), and block CG on ``E_ij Y_j - Y_i = 0``
    (``E_ij = T_i^T Q_ij T_j``, normal matrix ``2 L (x) I`` plus a perturbation that vanishes
    where the code is consistent) removes the rest. Any gauge gives the same least-squares
    solution; it only changes the number of steps.

    Codes CG would not finish quickly are given up, with ``converged`` False so that the caller
    solves them exactly: more than ``DEFECT_SLOTS`` of the slots still turned by more than
    ``DEFECT_ANGLE`` after smoothing (vortices of the rotation field, where the least-squares
    Q_i collapse towards 0 and 2 L is a poor model of the matrix), or not converged in
    ``max_iter`` steps.

    Args:
        relative: (N, F, 3, 3, 3) relative rotations per face and edge slot (boundary slots
            are ignored), mesh face order.
        graph: ``RotationGraph`` of the template.
        preconditioner: factorization of ``2 L`` (dual-graph Laplacian, the graph's face
            order) with identity rows and columns at the roots.
        inverse_norm: ``|preconditioner^-1|_inf``, to skip the solves when the starting
            residual is round-off.
        tol: stop when the preconditioned residual, an estimate of the remaining correction of
            the rotation entries, is below this everywhere.
        max_iter: block-CG step budget.
    Returns:
        ``(Q (N, F, 3, 3), steps, converged (N,) bool)``; Q is not yet projected onto rotations.
    """
    out = np.empty(relative.shape[:2] + (3, 3))
    converged = np.zeros(len(relative), dtype=bool)
    steps = 0
    for m in range(len(relative)):
        rel = np.ascontiguousarray(relative[m][graph.order], dtype=float)
        t, y, k, converged[m] = _pcg_one(rel, graph, preconditioner, inverse_norm, tol, max_iter)
        out[m] = (t @ y)[graph.rank]
        steps = max(steps, k)
    return out, steps, converged


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
            this. The default keeps decoded vertices within 0.05 mm of the exact least-squares
            decode on the 1.7 m template even for codes with vortices (measured,
            docs/encoding.md; the stated accuracy is 0.1 mm); consistent codes (round trips)
            are exact.
        max_iter: block-CG step budget (~3-5 ms a step on the template, against ~130 ms for
            the exact refactorization); a code not converged within it is solved exactly.
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
                 tol: float = 1e-5, max_iter: int = 20, on_flipped: str = "raise", n_jobs: int | None = None):
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
        # CG path: the graph's own face order (RotationGraph), its 2 L factored once.
        self._graph = RotationGraph(self.neighbors, self.back, self.anchor_faces)
        self._all_faces = np.arange(self.n_faces)
        roots = self._graph.roots
        lap = dual_laplacian(self._graph.neighbors).tolil()
        lap[roots, :] = 0.0
        lap[:, roots] = 0.0
        lap[roots, roots] = 0.5
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

    def _rotations(self, x: np.ndarray, name: str, index: int):
        """Rotations and stretches of the deformation gradients of one mesh x (V, 3), checked.

        Returns ``(q, stretch)``: the rotations R_i of ``U_i = R_i S_i`` as component-first
        quaternions (4, F) and the stretches S_i packed (F, 6). Raises MeshError for degenerate
        triangles and inside-out meshes, and applies ``on_flipped`` (``index``: the mesh's
        position in the caller's batch, for the messages).
        """
        nf = self.n_faces
        comps = [np.ascontiguousarray(x[:, k]) for k in range(3)]
        q = np.empty((4, nf))
        stretch = np.empty((nf, 6))
        dbl = np.empty(nf)
        check_flips = self.on_flipped != "ignore"
        normals = np.empty((nf, 3)) if check_flips else None
        volume = 0.0
        for sl, corner, rest, _, _ in self._encoding_blocks():
            a, b, c = ([comp[corner[k]] for comp in comps] for k in range(3))
            rot, st, dbl[sl], n = polar_from_corners(a, b, c, rest)
            q[:, sl] = _qfrom_matrix(rot)
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
        if check_flips:
            fold = _normal_agreement(normals[None], self.faces, self._incidence)[0]
            flipped = (fold < 0) & (self._rest_fold >= 0)
            if flipped.any():
                f = int(np.flatnonzero(flipped)[0])
                msg = (f"{name}: mesh {index} has {int(flipped.sum())} flipped triangle(s), first face {f}: "
                       "its normal points against the surface around it (the vertex normals of its corners), "
                       "the template's does not; expected an orientation-preserving registration "
                       "(on_flipped='warn' or 'ignore' accepts it)")
                if self.on_flipped == "raise":
                    raise MeshError(msg)
                warnings.warn(msg, RuntimeWarning, stacklevel=4)
        return q, stretch

    # ------------------------------------------------------------------ API
    def fit(self, scans: np.ndarray, faces: np.ndarray | None = None) -> "RelativeRotationEncoder":
        """Compute the mean model: the average of every code component over ``scans`` (N, V, 3).

        ``fit(template_vertices[None])`` makes the template itself the mean model.
        """
        x = check_scans(scans, self.n_vertices, self.faces, faces, name="scans")
        blocks = self._encoding_blocks()
        # Sums per fixed, contiguous chunk of scans, added in chunk order: the mean model is the
        # same to the last bit whatever the thread count or timing.
        chunks = np.array_split(np.arange(len(x)), min(FIT_CHUNKS, len(x)))
        sum_rot = np.zeros((len(chunks), 3, 3, self.n_faces))  # chunk, component, slot, face
        sum_str = np.zeros((len(chunks), self.n_faces, 6))

        def work(k):
            rot = np.empty(sum_rot.shape[1:])
            for m in chunks[k]:
                q, stretch = self._rotations(x[m], "scans", m)
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
        self._mean_q = _qexp(_planar(self.mean_rotvecs_, 3))  # (4, F, 3)
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
        x = check_scans(vertices, self.n_vertices, self.faces, faces)
        shape = (len(x), self.n_features_)
        if out is None:
            out = np.empty(shape)
        elif (out.shape != shape or out.dtype not in (np.float64, np.float32)
              or not out.flags.c_contiguous):
            raise ParameterError(f"out: {out.dtype} array of shape {out.shape}, expected a C-contiguous float64 or "
                                 f"float32 array of shape {shape}")
        codes = out.reshape(len(x), self.n_faces, FEATURES_PER_FACE)
        blocks = self._encoding_blocks()
        conj_mean = np.ascontiguousarray(_qconj(self._mean_q).transpose(0, 2, 1))  # (4, slot, F)

        def work(m):
            q, stretch = self._rotations(x[m], "vertices", m)
            code = codes[m]
            for sl, _, _, nbr, boundary in blocks:
                # r_ij = log(Q_ij M_ij^-1), (3, slot, B)
                rot = _relative_rotvecs(q[:, sl], q[:, nbr], conj_mean[:, :, sl])
                if boundary is not None:
                    rot[:, boundary] = 0.0
                np.copyto(code[sl, :9].reshape(-1, 3, 3), rot.transpose(2, 1, 0))
            code[:, 9:] = stretch - self.mean_stretch_

        self._run(work, range(len(x)))
        return out

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
        c = np.ascontiguousarray(codes, dtype=float).reshape(len(codes), self.n_faces, FEATURES_PER_FACE)
        out = np.empty((len(c), self.n_faces, 3, 3, 3))
        mean_q = self._mean_quaternions()
        for m in range(len(c)):
            _relative_kernel(c[m], mean_q, self._all_faces, out[m])
        return out

    def _mean_quaternions(self) -> np.ndarray:
        """Unit quaternions (F, 3, 4) of the mean relative rotations (cached per fit)."""
        cache = getattr(self, "_mean_q_cache", None)
        if cache is None or cache[0] is not self.mean_rotvecs_:
            cache = (self.mean_rotvecs_, np.ascontiguousarray(quaternion_exp(self.mean_rotvecs_)))
            self._mean_q_cache = cache
        return cache[1]

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
            rot, steps, converged = solve_rotations_pcg(relative, self._graph, self._preconditioner,
                                                        self._inverse_norm, self.tol, self.max_iter)
            factorized = int((~converged).sum())
            if factorized:
                # Strongly inconsistent codes: CG would not pay off, factor their systems (fixed
                # pattern, numeric refactorization only).
                rot[~converged] = self._exact.solve(relative[~converged])
        # Eq. 9 solves for Q_i = R_i^T; return the rotations R_i of U_i = R_i S_i.
        return np.swapaxes(project_to_rotations(rot), -1, -2), steps, factorized

    def _decode(self, c: np.ndarray, constraints, reference: np.ndarray):
        n = len(c)
        c = np.ascontiguousarray(c, dtype=float).reshape(n, self.n_faces, FEATURES_PER_FACE)
        if self.rotation_solver == "pcg":
            # Fused per body: relative rotations, tree gauge, CG or the exact fallback, and the
            # gradients U = R S straight from Q = T Y (no intermediate batches).
            u, steps, factorized = np.empty((n, self.n_faces, 3, 3)), 0, 0
            rel = np.empty((self.n_faces, 3, 3, 3))
            order, rank = self._graph.order, self._graph.rank
            mean_q, mean_stretch = self._graph_order_means()
            for m in range(n):
                # Into the graph's face order once (a plain gather), so every kernel below
                # walks its arrays in order.
                code = c[m][order]
                _relative_kernel(code, mean_q, self._all_faces, rel)
                t, y, k, ok = _pcg_one(rel, self._graph, self._preconditioner, self._inverse_norm, self.tol,
                                       self.max_iter)
                steps = max(steps, k)
                if not ok:  # see solve_rotations_pcg: factor this body's system instead
                    t = self._exact.solve(rel[rank][None])[0][order]
                    y = np.broadcast_to(np.eye(3), t.shape).copy()
                    factorized += 1
                u[m] = self._gradients(t, y, code[:, 9:], mean_stretch)[rank]
        else:
            rot, steps, factorized = self._solve_rotations(self.relative_rotations(c), self.rotation_solver)
            u = rot @ unpack_stretch(c[..., 9:] + self.mean_stretch_)
        x = self._poisson.solve(u)
        placed, part_rot = self._place(x, reference)
        if constraints is None:
            return placed, steps, factorized
        # Keep the placed orientation: rotate each part's gradients as the placement rotated it.
        u = part_rot[:, self._face_part] @ u
        return self._poisson.solve(u, constraints, pinned_positions=placed), steps, factorized

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

    def _gradients(self, t: np.ndarray, y: np.ndarray, stretch: np.ndarray, mean_stretch: np.ndarray) -> np.ndarray:
        """Deformation gradients (F, 3, 3) ``U_i = R_i S_i``: ``R_i^T`` the rotation nearest to
        ``Q_i = T_i Y_i`` (``project_to_rotations``), S_i from the code's stretch (F, 6) plus the
        mean's (F, 6); all in one face order."""
        u = np.empty((self.n_faces, 3, 3))
        bad = np.empty(self.n_faces, dtype=bool)
        _gradients_kernel(t, y, stretch, mean_stretch, self._all_faces, u, bad)
        if bad.any():  # det(Q) <= 0: the SVD projection of project_to_rotations
            rot = np.swapaxes(project_to_rotations(t[bad] @ y[bad]), -1, -2)
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
    ``Q_ij = R_i^T R_j`` of faces to their neighbours (Eq. 8), optionally followed by ``right``
    (the conjugate mean ``M_ij^-1``).

    Encoding's inner loop, fused: ``qi`` (4, B), ``qj`` and ``right`` (4, slot, B) component-
    first quaternions; the same arithmetic as ``_qlog(_qmul(_qmul(_qconj(qi), qj), right))``
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
    # _qlog: angle in [0, pi], atan2 for full precision at small angles.
    sign = np.where(w < 0, -1.0, 1.0)
    w = w * sign
    s = np.sqrt(x * x + y * y + z * z)
    small = s < 1e-8
    factor = np.where(small, 2.0 / np.maximum(w, 1e-300), 2.0 * np.arctan2(s, w) / np.where(small, 1.0, s)) * sign
    return np.stack([x * factor, y * factor, z * factor])
