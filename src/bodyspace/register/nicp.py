"""Non-rigid refinement (Hasler §2.3): one affine transform per template vertex.

The unknowns are ``X = [T_1 … T_n]^T`` (4n × 3), ``T_i`` the 3×4 affine transform of the posed
template's vertex ``p_i`` (Hasler Equation 1). The energy (Hasler Equation 2)

    E(X) = α E_d(X) + β E_s(X) + γ E_l(X)

- E_d (Hasler Equation 3): ``Σ_i |p̃_i − T_i p_i|²`` over the vertices that have a target
  (``correspondences.tangent_plane_targets``: the projection onto a plane fitted to the scan
  points matched to the vertex, raised by the vertex's sagitta so the fit does not shrink, else
  the closest scan point when it lies along the vertex's normal (not over a hole), gated at 30°
  and 50 mm);
- E_s (Hasler Equation 4): ``Σ_i |Σ_j w_ij (T_i − T_j)|_F²`` with the cotangent weights of the
  template's rest configuration: the transforms change as smoothly as possible (second
  differences), not as little as possible (Amberg's first differences);
- E_l (Hasler Equation 5): landmarks, ``Σ |l̃ − T l|²``.

Each step is linear least squares: the normal matrix ``α Dᵀ W D + β (LᵀL ⊗ I_4) + γ D_lᵀ D_l``
(D holds ``[p_iᵀ, h]`` in block i), solved for the three columns by conjugate gradients
warm-started from the previous step (``_System`` says why not a factorization; the loop is
compiled, ``_pcg``). The stiffness is annealed as ``β = k0 · e^(λt)`` from ``STIFFNESS_START`` =
3000 (Hasler's) down to ``stiffness_end`` (``STIFFNESS_END`` = 1 by default, Hasler: 0.01, see
there; the registration pipeline ends at 10) with γ = 2β, in ``steps`` levels (Hasler iterates
1500 times; here ``steps`` levels of ``inner`` iterations, the correspondences recomputed at
every iteration).

No folds. A step that folds a face it did not fold before is taken again with the data term of
the face's corners and their rings dropped for the rest of the fit (local stiffening: the
smoothness carries the neighbours' transforms there); after the last level ``unfold`` untangles
what is left (folds the input had: an LBS-posed armpit or groin), widening its patch until no
face is folded.

Units. Positions enter in metres, centred on the body, with the homogeneous coordinate 1: a body
of about unit size, so that smoothness weighs a change of translation like the same change of
the linear part times a typical lever arm (Amberg's γ weighting of the translation), and β = 1
balances moving one vertex by d against changing its transform by d relative to its
neighbours. (In millimetres every β of the schedule fits the noise: 2,000 folded triangles.)
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np
import scipy.sparse as sp
from scipy.spatial import cKDTree

from bodyspace.mesh.geometry import vertex_normals
from bodyspace.mesh.operators import cotangent_laplacian
from bodyspace.mesh.solver import single_threaded_blas
from bodyspace.register.correspondences import point_spacing, tangent_plane_targets
from bodyspace.rig.posing import folded_triangles

__all__ = ["NicpResult", "nonrigid_icp", "unfold", "stiffness_schedule", "STIFFNESS_START", "STIFFNESS_END"]

STIFFNESS_START = 3000.0
STIFFNESS_END = 1.0
# Hasler's end value, 0.01, folds ~1,200 triangles here (measured on a test scan: the targets'
# 2 mm noise is fitted vertex by vertex); 1.0 is where the folds stop falling (docs/registration.md).
HASLER_END = 0.01
HOMOGENEOUS = 1.0
MM = 1.0
# Rounds of ``unfold`` after the last level, and the rounds after which a fold still there is
# smoothed with one more ring of its neighbourhood.
UNFOLD_ROUNDS = 60
GROW_EVERY = 5
# The patch ``unfold`` smooths grows only within this distance (metres) of the faces it found
# folded. Grown ring by ring alone it went round a limb: on a short heavy man with his arms
# forward (the LBS armpit folded over 3-4 cm, 40 rounds to untangle) the patch took the whole
# upper arm and the side of the chest, and the uniform Laplacian shrank the arm's section by up
# to 42 mm: the fit, 1.6 mm from the truth before it, was refused at quality 0.84 for the scan
# it no longer explained beside both upper arms (docs/registration.md, "Arms forward").
UNFOLD_REACH = 0.05
# Conjugate-gradient iterations per solve (each level starts from the last level's transforms).
CG_ITERATIONS = 25


@dataclass(frozen=True)
class NicpResult:
    """vertices: (V, 3) metres (after ``unfold``); has_target: (V,) bool at the last iteration; transforms:
    (V, 4, 3) the affine transforms (millimetre frame, see the module docstring); stiffness:
    the β of each level; released: (V,) bool, the vertices whose data term was dropped where a
    step folded a face (local stiffening); folded: faces still folded after ``unfold`` (0 on
    every test scan measured)."""

    vertices: np.ndarray
    has_target: np.ndarray
    transforms: np.ndarray
    stiffness: np.ndarray
    released: np.ndarray | None = None
    folded: int = 0


def stiffness_schedule(steps: int, start: float = STIFFNESS_START, end: float = STIFFNESS_END) -> np.ndarray:
    """β_t = k0 · e^(λt), t = 0 … steps−1, from ``start`` to ``end`` (λ = ln(end/start)/(steps−1))."""
    steps = max(int(steps), 1)
    if steps == 1:
        return np.array([end])
    lam = np.log(end / start) / (steps - 1)
    return start * np.exp(lam * np.arange(steps))


def _data_matrix(p: np.ndarray) -> sp.csr_matrix:
    """D (V, 4V): row i holds [p_i, h] in columns 4i … 4i+3."""
    V = len(p)
    rows = np.repeat(np.arange(V), 4)
    cols = (4 * np.arange(V)[:, None] + np.arange(4)).ravel()
    vals = np.concatenate([p, np.full((V, 1), HOMOGENEOUS)], axis=1).ravel()
    return sp.csr_matrix((vals, (rows, cols)), shape=(V, 4 * V))


class _System:
    """The normal equations of one level without forming them: ``A X = β (LᵀL X) + α W (a aᵀ X)``
    per vertex (+ landmarks), applied on X (V, 4, 3), and its block-Jacobi preconditioner.

    Forming ``LᵀL ⊗ I_4`` (4V unknowns) and factoring it costs 5-7 s a level on the template
    (measured, SuperLU, 14 M factor entries): here the Kronecker product is applied as LᵀL on
    the (V, 12) matrix of the transforms (a few ms), and each level's solution is reached by
    preconditioned conjugate gradients started from the last level's (the stiffness changes by
    a constant factor per level, so the start is close; see ``CG_ITERATIONS``).
    """

    def __init__(self, LL: sp.csr_matrix, a: np.ndarray, weight: np.ndarray, beta: float, landmark=None):
        self.LL, self.a, self.w, self.beta = LL, a, weight, beta
        self.landmark = landmark            # (DL (L, 4V), factor) or None
        V = len(a)
        diag = LL.diagonal()
        blocks = beta * diag[:, None, None] * np.eye(4) + weight[:, None, None] * np.einsum("vi,vj->vij", a, a)
        if landmark is not None:
            DL, f = landmark
            dl = DL.tocoo()
            bd = np.zeros((V, 4, 4))
            # landmark rows' own diagonal blocks
            for r in range(DL.shape[0]):
                row = DL.getrow(r)
                idx = row.indices
                v = idx // 4
                for vv in np.unique(v):
                    m = v == vv
                    vals = np.zeros(4)
                    vals[idx[m] % 4] = row.data[m]
                    bd[vv] += f * np.outer(vals, vals)
            blocks += bd
            del dl
        self.pre = np.linalg.inv(blocks)

    def _extra(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The landmark term f·DLᵀDL as triplets (row, column, value) over the 4V unknowns."""
        if self.landmark is None:
            return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0)
        DL, f = self.landmark
        m = (DL.T @ DL).tocoo()
        return m.row.astype(np.int64), m.col.astype(np.int64), f * m.data

    def apply(self, X: np.ndarray) -> np.ndarray:
        """A X for X (V, 4, 3)."""
        out = np.empty_like(X)
        er, ec, ev = self._extra()
        _apply(self.LL.indptr, self.LL.indices, self.LL.data, self.beta, self.a, self.w, er, ec, ev,
               np.ascontiguousarray(X), out)
        return out

    def solve(self, b: np.ndarray, X: np.ndarray, iterations: int) -> np.ndarray:
        """Preconditioned conjugate gradients from X (V, 4, 3) for the three columns at once (one
        compiled loop: the numpy version spent 60 % of its time in temporaries and reductions)."""
        x = np.ascontiguousarray(X, dtype=float).copy()
        er, ec, ev = self._extra()
        _pcg(self.LL.indptr, self.LL.indices, self.LL.data, self.beta, self.a, self.w, er, ec, ev,
             np.ascontiguousarray(self.pre), np.ascontiguousarray(b, dtype=float), x, int(iterations))
        return x


@numba.njit(cache=True, nogil=True)
def _apply(indptr, indices, data, beta, a, w, er, ec, ev, X, out):  # pragma: no cover - compiled
    """out (V, 4, 3) = β (LᵀL X) + w_v a_v (a_vᵀ X_v) + Σ triplets (landmarks)."""
    V = X.shape[0]
    for v in range(V):
        for k in range(4):
            for c in range(3):
                out[v, k, c] = 0.0
        for e in range(indptr[v], indptr[v + 1]):
            u = indices[e]
            d = beta * data[e]
            for k in range(4):
                for c in range(3):
                    out[v, k, c] += d * X[u, k, c]
        if w[v] != 0.0:
            for c in range(3):
                ax = a[v, 0] * X[v, 0, c] + a[v, 1] * X[v, 1, c] + a[v, 2] * X[v, 2, c] + a[v, 3] * X[v, 3, c]
                for k in range(4):
                    out[v, k, c] += w[v] * a[v, k] * ax
    for t in range(len(ev)):
        i, j = er[t], ec[t]
        for c in range(3):
            out[i // 4, i % 4, c] += ev[t] * X[j // 4, j % 4, c]


@numba.njit(cache=True, nogil=True)
def _precondition(pre, r, z):  # pragma: no cover - compiled
    for v in range(r.shape[0]):
        for k in range(4):
            for c in range(3):
                z[v, k, c] = pre[v, k, 0] * r[v, 0, c] + pre[v, k, 1] * r[v, 1, c] + pre[v, k, 2] * r[v, 2, c] \
                    + pre[v, k, 3] * r[v, 3, c]


@numba.njit(cache=True, nogil=True)
def _pcg(indptr, indices, data, beta, a, w, er, ec, ev, pre, b, x, iterations):  # pragma: no cover - compiled
    """Block-Jacobi preconditioned CG on the three columns of x (V, 4, 3) at once, in place."""
    V = x.shape[0]
    r = np.empty_like(x)
    z = np.empty_like(x)
    Ap = np.empty_like(x)
    _apply(indptr, indices, data, beta, a, w, er, ec, ev, x, Ap)
    r[:] = b - Ap
    _precondition(pre, r, z)
    p = z.copy()
    rz = np.zeros(3)
    for v in range(V):
        for k in range(4):
            for c in range(3):
                rz[c] += r[v, k, c] * z[v, k, c]
    for _ in range(iterations):
        _apply(indptr, indices, data, beta, a, w, er, ec, ev, p, Ap)
        pAp = np.zeros(3)
        for v in range(V):
            for k in range(4):
                for c in range(3):
                    pAp[c] += p[v, k, c] * Ap[v, k, c]
        alpha = np.zeros(3)
        for c in range(3):
            alpha[c] = rz[c] / pAp[c] if pAp[c] > 0 else 0.0
        for v in range(V):
            for k in range(4):
                for c in range(3):
                    x[v, k, c] += alpha[c] * p[v, k, c]
                    r[v, k, c] -= alpha[c] * Ap[v, k, c]
        _precondition(pre, r, z)
        rz_new = np.zeros(3)
        for v in range(V):
            for k in range(4):
                for c in range(3):
                    rz_new[c] += r[v, k, c] * z[v, k, c]
        for c in range(3):
            g = rz_new[c] / rz[c] if rz[c] > 0 else 0.0
            for v in range(V):
                for k in range(4):
                    p[v, k, c] = z[v, k, c] + g * p[v, k, c]
            rz[c] = rz_new[c]


def _ring(faces: np.ndarray, V: int) -> sp.csr_matrix:
    """(V, V) 0/1 adjacency of the mesh's edges."""
    ring = sp.csr_matrix((np.ones(6 * len(faces)), (faces[:, [0, 1, 2, 1, 2, 0]].ravel(),
                                                    faces[:, [1, 2, 0, 0, 1, 2]].ravel())), shape=(V, V))
    ring.data[:] = 1.0
    return ring


def unfold(vertices: np.ndarray, faces: np.ndarray, rounds: int = UNFOLD_ROUNDS,
           reach: float | None = UNFOLD_REACH) -> tuple[np.ndarray, int]:
    """Move the corners of folded faces to the mean of their 1-ring until no face is folded.

    The last NICP levels follow the scan where it is folded itself (an LBS-posed armpit or
    groin) or where its normals are poor (fingers, toes, the face), and fold a few triangles; a
    uniform-Laplacian step on exactly those corners undoes most folds and moves nothing else.
    A fold that survives ``GROW_EVERY`` rounds is smoothed with one more ring of its
    neighbourhood each time (a wider patch relaxes towards the harmonic surface spanned by its
    rim, which does not fold unless the rim does), but only within ``reach`` metres of a face
    found folded in some round (``UNFOLD_REACH``): a patch grown round a limb shrinks its
    section (a uniform Laplacian pulls a tube's vertices towards its axis). Folds still there
    after ``rounds`` rounds are untangled again with the patch unbounded (``reach=None``, the
    old rule: no fold is left for want of room). Returns vertices (V, 3) and the number of
    faces still folded.
    """
    v = np.asarray(vertices, dtype=float).copy()
    V = len(v)
    ring = _ring(faces, V)
    degree = np.asarray(ring.sum(axis=1)).ravel()
    bad = folded_triangles(v, faces)
    near = np.zeros(V, dtype=bool)
    for r in range(int(rounds)):
        if not bad.any():
            break
        corners = np.unique(faces[bad])
        region = np.zeros(V, dtype=bool)
        region[corners] = True
        for _ in range(r // GROW_EVERY):
            region |= (ring @ region.astype(float)) > 0
        if reach is not None:
            near |= cKDTree(v[corners]).query(v, distance_upper_bound=reach)[0] <= reach
            region &= near
        move = np.flatnonzero(region)
        v[move] = (ring[move] @ v) / degree[move, None]
        bad = folded_triangles(v, faces)
    if bad.any() and reach is not None:
        return unfold(v, faces, rounds, None)
    return v, int(bad.sum())


def nonrigid_icp(vertices: np.ndarray, faces: np.ndarray, rest: np.ndarray, points: np.ndarray,
                 point_normals: np.ndarray, *, steps: int = 10, inner: int = 2,
                 cg_iterations: int = CG_ITERATIONS, stiffness_end: float = STIFFNESS_END,
                 landmarks: tuple[sp.csr_matrix, np.ndarray] | None = None,
                 scan_tree: cKDTree | None = None, progress=None) -> NicpResult:
    """Refine the posed, fitted template onto the scan (module docstring).

    vertices (V, 3): the template after the pose and model fits, metres; faces (F, 3);
    rest (V, 3): the configuration whose cotangent weights regularize (the template's rest body);
    points (P, 3), point_normals (P, 3) oriented (``correspondences.orient_normals``).
    landmarks: (template landmark matrix (L, V), scan positions (L, 3)), optional.
    steps, inner: stiffness levels and iterations per level; cg_iterations: conjugate-gradient
    iterations per solve. progress: callback(fraction).
    """
    centre = vertices.mean(axis=0)
    p = (vertices - centre) * MM
    tree = scan_tree if scan_tree is not None else cKDTree(points)
    V = len(p)
    L = cotangent_laplacian(rest, faces)
    LL = (L.T @ L).tocsr()
    a = np.concatenate([p, np.full((V, 1), HOMOGENEOUS)], axis=1)              # (V, 4): [p_i, h]
    X = np.tile(np.vstack([np.eye(3), np.zeros((1, 3))]), (V, 1, 1))        # identity transforms (V, 4, 3)
    X[:, 3, :] = 0.0
    DL = None
    if landmarks is not None:
        M, lm_points = landmarks
        DL = (M @ _data_matrix(p)).tocsr()     # a landmark row mixes its vertices' rows
        lq = (lm_points - centre) * MM
    betas = stiffness_schedule(steps, STIFFNESS_START, stiffness_end)
    x = p.copy()
    has = np.zeros(V, dtype=bool)
    total = len(betas) * inner
    done = 0
    ring = _ring(faces, V)
    released = np.zeros(V, dtype=bool)
    spacing = point_spacing(tree)
    with single_threaded_blas():
        for beta in betas:
            for _ in range(int(inner)):
                xm = x / MM + centre
                targets, has = tangent_plane_targets(xm, vertex_normals(xm, faces), points, point_normals, tree,
                                                     faces=faces, spacing=spacing)
                u = (targets - centre) * MM
                before = folded_triangles(x, faces)
                for attempt in range(2):
                    w = np.where(released, 0.0, has.astype(float))
                    system = _System(LL, a, w, beta, None if DL is None else (DL, 2 * beta))
                    b = w[:, None, None] * a[:, :, None] * u[:, None, :]
                    if DL is not None:
                        b = b + 2 * beta * (DL.T @ lq).reshape(V, 4, 3)
                    X_new = system.solve(b, X, cg_iterations)
                    x_new = (a[:, :, None] * X_new).sum(axis=1)
                    bad = folded_triangles(x_new, faces) & ~before
                    if attempt or not bad.any():
                        break
                    # Local stiffening: the corners of the faces this step folded, and their
                    # rings, lose their data term for the rest of the fit; the smoothness then
                    # carries their neighbours' transforms across instead of the scan's noise.
                    hit = np.zeros(V, dtype=bool)
                    hit[faces[bad].ravel()] = True
                    released |= (ring @ hit.astype(float)) > 0
                X, x = X_new, x_new
                done += 1
                if progress is not None:
                    progress(done / total)
    unfolded, left = unfold(x / MM + centre, faces)
    return NicpResult(unfolded, has, X, betas, released, left)
