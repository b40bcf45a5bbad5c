"""Volume-preserving skinning: a displacement on top of linear blend (or dual-quaternion)
skinning that gives every posed body exactly its rest volume.

LBS loses volume where bones blend (the blended rotation ``sum_b w_b R_b`` shrinks: knee, hip
and spine in a squat lose 17 % of the body with bone heat, docs/skinning.md), and no skin
weights fix that: even rigid weights lose 5.8 % in the squat. Following the idea of Rohmer,
Hahmann & Cani 2009 ("Exact volume preserving skinning with shape control": a displacement
along the posed normals with a shape profile around each joint, its amplitude solved so the
volume is the rest volume), each posed frame ``x`` (V, 3) is corrected to ``x + s d``:

1. **Joint bumps.** For joint c (the head of bone c, shared with its parent), ``A_c(v)`` is the
   weight of c's subtree at vertex v and ``h_c(v) = 4 A_c (1 - A_c)``: 1 where the skin is half
   on each side of the joint, 0 where it follows one side rigidly. Precomputed from the weights.
2. **Region volume change.** Each face's signed tetrahedron is measured from the *posed joint*
   (which both bones of the joint carry), shared among the joints by ``pi_c = h_c / sum h``; a
   piece of skin that moves rigidly with either bone keeps its tetrahedra, so ``dV_c`` is the
   volume the blend lost or gained around joint c.
3. **Amplitudes.** ``alpha_c = -dV_c / g_c`` with ``g_c`` the volume a unit bump adds; only
   joints whose change has the body's sign (as the arms rise the armpits lose while the chest
   region "gains": pushing the chest in would shrink its girth by centimetres). The bump is
   *contact-aware*: faded out on the inner side of the bend (normals toward the sum of the two
   posed bones' directions: the back of the knee in a squat, the groin), so it does not push
   skin into the neighbouring limb and bulges on the outer side instead.
4. **Smooth field.** ``d = sum_c alpha_c h_c C_c n`` (n: the rest normal carried by the blended
   rotation, which does not flip where LBS folds the skin) is smoothed as a *vector* field
   (``steps`` neighbour-mean steps over the field's support): opposite pushes across a crease
   cancel.
5. **Exact volume.** The enclosed volume of ``x + s d`` is a cubic in s (each tetrahedron is a
   3x3 determinant); s is its root near 1 (Newton on the exact cubic), so the posed volume equals
   the rest volume to rounding. Where the regions' estimate has the wrong sign or scale
   (``s`` outside [0, 10]: small, mixed changes), the field of every changed joint's
   ``|alpha_c| h_c C_c n`` (every bump pushing one way) is scaled instead, at either sign.
6. **Fold guard.** Faces the correction folds that LBS did not (the test of
   ``posing.count_folded_triangles``): the displacement is faded to 0 at their corners, ramping
   back over ``GUARD_RINGS`` edge rings, and s is solved again (up to ``GUARD_ROUNDS`` rounds).
   Measured over 3 bodies x 39 poses: no pose gains a fold, the folds fall 13-22 %.

Holes are capped as ``mesh.geometry.capped_volume`` caps them (a centroid fan a loop), so the
volume kept is the one that function measures. A compiled kernel (numba), frames on two lanes.
The identity pose is returned unchanged (every ``dV_c`` is 0, so is d).
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np
import scipy.sparse as sp

from bodyspace.errors import MeshError, ParameterError
from bodyspace.mesh.geometry import boundary_loops
from bodyspace.mesh.topology import face_adjacency_matrix
from bodyspace.parallel import halves, run_both

__all__ = ["VolumeRig", "preserve_volume", "volume_rig", "SMOOTHING_STEPS"]

# Steps of the displacement's vector smoothing, each d <- (1 - rate) d + rate (mean of the
# neighbours' d): 20 full steps spread the field over ~6 edge rings on the template, as 40 half
# steps did at 2.5x the time, with the same folds. Without it the bulge folds every crease
# (the mean body, bone heat: squat 12 -> 49 folds; docs/skinning.md).
SMOOTHING_STEPS = 20
_RATE = 1.0
# Joints whose bump nowhere exceeds this are left out (nothing blends across them).
MIN_BUMP = 0.05
# Bump values below this are dropped (sparsity).
_BUMP_FLOOR = 1e-3
# Fold guard: rounds of "fade the displacement out around the faces it folded, re-solve s", and
# the edge rings of the fade (zero on the folded faces' corners, then a smooth ramp).
GUARD_ROUNDS = 4
GUARD_RINGS = 3
# Frames of float32 input corrected a float64 copy at a time.
_FLOAT32_CHUNK = 64
# Correct only the joints whose change has the body's sign (step 3).
ONE_SIGNED = True
# A joint whose region changed by less than this fraction of the body's volume is left alone
# (its change is rounding: a bone that did not move).
_NEGLIGIBLE = 1e-7
# Accepted range of the global scale s of the region field; outside it the one-signed field is used.
_SCALE_RANGE = (0.0, 10.0)


@dataclass(frozen=True)
class VolumeRig:
    """What the correction needs of a rig, its weights and the mesh (independent of the body).

    joints: (K,) bone index c of each joint (its head, shared with parent ``parents[c]``).
    parents: (K,) the parent bone of each joint's bone.
    bump_indptr, bump_joint, bump_value, bump_share: CSR over vertices (V rows) of h_c(v) and
        pi_c(v) = h_c / sum_c h_c.
    weight_indptr, weight_bone, weight_value: the skin weights (V, B) as CSR arrays.
    adjacency_indptr, adjacency_index: the mesh's vertex adjacency (CSR, no diagonal).
    faces: (F, 3) int64; loop_vertices, loop_starts: the boundary loops (capped as capped_volume).
    face_adjacency_indptr, face_adjacency_index: faces sharing an edge (CSR, F rows), for the fold test.
    """
    joints: np.ndarray
    parents: np.ndarray
    bump_indptr: np.ndarray
    bump_joint: np.ndarray
    bump_value: np.ndarray
    bump_share: np.ndarray
    weight_indptr: np.ndarray
    weight_bone: np.ndarray
    weight_value: np.ndarray
    adjacency_indptr: np.ndarray
    adjacency_index: np.ndarray
    faces: np.ndarray
    loop_vertices: np.ndarray
    loop_starts: np.ndarray
    face_adjacency_indptr: np.ndarray
    face_adjacency_index: np.ndarray

    @property
    def n_vertices(self) -> int:
        return len(self.bump_indptr) - 1


def volume_rig(weights, parents, faces) -> VolumeRig:
    """The joint bumps and mesh arrays of the correction for skin ``weights`` (V, B) (rows sum
    to 1), bone ``parents`` (B,) (-1 for a root) and ``faces`` (F, 3) of the V-vertex mesh."""
    W = sp.csr_matrix(weights, dtype=float)
    W.sum_duplicates()
    V, B = W.shape
    par = np.asarray(parents, dtype=np.int64)
    if par.shape != (B,):
        raise ParameterError(f"parents: shape {par.shape}, expected ({B},) one parent a bone of the weights")
    f = np.ascontiguousarray(faces, dtype=np.int64)
    if f.ndim != 2 or f.shape[1] != 3 or (f.size and (f.min() < 0 or f.max() >= V)):
        raise MeshError(f"faces: shape {f.shape}, expected (F, 3) indices of the weights' {V} vertices")
    # subtree[c, b]: bone b is c or below it; A[:, c] = the weight of c's subtree.
    rows, cols = [], []
    for b in range(B):
        a = b
        for _ in range(B + 1):
            if a < 0:
                break
            rows.append(a)
            cols.append(b)
            a = par[a]
        else:
            raise ParameterError("parents: the bones form a cycle; expected a tree (-1 for a root)")
    subtree = sp.csr_matrix((np.ones(len(rows)), (rows, cols)), shape=(B, B))
    A = (W @ subtree.T).tocsc()                                         # (V, B)
    A.data = np.clip(A.data, 0.0, 1.0)
    H = A.copy()
    H.data = 4.0 * A.data * (1.0 - A.data)
    H.data[H.data < _BUMP_FLOOR] = 0.0
    H.eliminate_zeros()
    peak = np.zeros(B)
    if H.nnz:
        peak = np.asarray(H.max(axis=0).todense()).ravel()
    joints = np.flatnonzero((par >= 0) & (peak > MIN_BUMP)).astype(np.int64)
    Hk = H[:, joints].tocsr()
    Hk.sort_indices()
    total = np.asarray(Hk.sum(axis=1)).ravel()
    share = Hk.data / np.repeat(np.maximum(total, 1e-300), np.diff(Hk.indptr))
    e = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    adj = sp.coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(V, V))
    adj = ((adj + adj.T) > 0).tocsr()
    adj.setdiag(False)
    adj.eliminate_zeros()
    adj.sort_indices()
    loops = boundary_loops(f) if len(f) else []
    loop_vertices = np.concatenate([np.asarray(lp, dtype=np.int64) for lp in loops] or [np.zeros(0, np.int64)])
    loop_starts = np.concatenate([[0], np.cumsum([len(lp) for lp in loops])]).astype(np.int64)
    W.sort_indices()
    fa = face_adjacency_matrix(f)         # the neighbours of count_folded_triangles' test
    return VolumeRig(joints, par[joints], Hk.indptr.astype(np.int64), Hk.indices.astype(np.int64),
                     Hk.data.copy(), share, W.indptr.astype(np.int64), W.indices.astype(np.int64), W.data.copy(),
                     adj.indptr.astype(np.int64), adj.indices.astype(np.int64), f, loop_vertices, loop_starts,
                     fa.indptr.astype(np.int64), fa.indices.astype(np.int64))


def preserve_volume(posed: np.ndarray, rest: np.ndarray, transforms: np.ndarray, heads: np.ndarray,
                    tails: np.ndarray, vrig: VolumeRig, *, steps: int = SMOOTHING_STEPS,
                    lanes: int | None = None) -> np.ndarray:
    """Correct skinned frames in place so each has its rest body's enclosed volume.

    posed: (N, V, 3) float64 or float32, the skinned frames (LBS or DQS); changed in place.
    rest: (N, V, 3) rest bodies, or (1, V, 3) one body for every frame.
    transforms: (N, B, 4, 4) the bones' world transforms (``forward_kinematics``).
    heads, tails: (N, B, 3) or (1, B, 3) rest bone heads and tails of each body.
    vrig: ``volume_rig(weights, parents, faces)`` of the weights the frames were skinned with.
    steps: Jacobi steps of the displacement's smoothing; lanes: 1, 2 or None (two for many frames).
    Returns (N,) the scale s applied to each frame's displacement field (0 where nothing changed).
    """
    x = posed
    if x.ndim != 3 or x.shape[1:] != (vrig.n_vertices, 3) or x.dtype not in (np.float32, np.float64):
        raise MeshError(f"posed: shape {x.shape} {x.dtype}, expected (N, {vrig.n_vertices}, 3) float32 or float64")
    if not x.flags.c_contiguous or not x.flags.writeable:
        raise ParameterError("posed: expected a writeable C-contiguous array (it is corrected in place)")
    N = x.shape[0]
    rest = np.ascontiguousarray(rest, dtype=float)
    G = np.ascontiguousarray(transforms, dtype=float)
    heads = np.asarray(heads, dtype=float)
    tails = np.asarray(tails, dtype=float)
    if rest.ndim != 3 or rest.shape[0] not in (1, N) or rest.shape[1:] != x.shape[1:]:
        raise MeshError(f"rest: shape {rest.shape}, expected ({N} or 1, {vrig.n_vertices}, 3)")
    if G.ndim != 4 or G.shape[0] != N or G.shape[2:] != (4, 4):
        raise ParameterError(f"transforms: shape {G.shape}, expected ({N}, B, 4, 4)")
    B = G.shape[1]
    for name, arr in (("heads", heads), ("tails", tails)):
        if arr.ndim != 3 or arr.shape[0] not in (1, N) or arr.shape[1:] != (B, 3):
            raise ParameterError(f"{name}: shape {arr.shape}, expected ({N} or 1, {B}, 3)")
    if int(steps) < 0:
        raise ParameterError(f"steps={steps!r}; expected an integer >= 0")
    k, p = vrig.joints, vrig.parents
    # Posed joints and the bend's inner direction per frame: (N, K, 3).
    Gk, Gp = G[:, k], G[:, p]                                    # (N, K, 4, 4)
    Rk, tk = Gk[..., :3, :3], Gk[..., :3, 3]
    hk = np.broadcast_to(heads[:, k], (N, len(k), 3))
    joint_posed = np.einsum("nkij,nkj->nki", Rk, hk) + tk
    parent_head = np.einsum("nkij,nkj->nki", Gp[..., :3, :3], np.broadcast_to(heads[:, p], (N, len(k), 3))) \
        + Gp[..., :3, 3]
    tail_posed = np.einsum("nkij,nkj->nki", Rk, np.broadcast_to(tails[:, k], (N, len(k), 3))) + tk
    up = parent_head - joint_posed
    uc = tail_posed - joint_posed
    inner = up / np.maximum(np.linalg.norm(up, axis=2, keepdims=True), 1e-12) \
        + uc / np.maximum(np.linalg.norm(uc, axis=2, keepdims=True), 1e-12)
    joint_rest = np.ascontiguousarray(heads[:, k])
    joint_posed = np.ascontiguousarray(joint_posed)
    inner = np.ascontiguousarray(inner)
    scale = np.zeros(N)
    if lanes is None:
        lanes = 2 if N >= 4 else 1
    if lanes not in (1, 2):
        raise ParameterError(f"lanes={lanes!r}; expected 1, 2 or None (automatic)")
    mesh = (vrig.bump_indptr, vrig.bump_joint, vrig.bump_value, vrig.bump_share, vrig.weight_indptr,
            vrig.weight_bone, vrig.weight_value, vrig.adjacency_indptr, vrig.adjacency_index, vrig.faces,
            vrig.loop_vertices, vrig.loop_starts, vrig.face_adjacency_indptr, vrig.face_adjacency_index, int(steps))
    # One compiled kernel (float64 frames): float32 frames are corrected in float64 copies of
    # _FLOAT32_CHUNK frames at a time (a long clip is not doubled in memory).
    chunk = N if x.dtype == np.float64 else _FLOAT32_CHUNK
    for i in range(0, N, chunk):
        j = min(N, i + chunk)
        work = x[i:j] if x.dtype == np.float64 else x[i:j].astype(np.float64)
        per = (lambda arr: arr if arr.shape[0] == 1 else arr[i:j])
        args = (work, per(rest), G[i:j], per(joint_rest), joint_posed[i:j], inner[i:j]) + mesh
        out = scale[i:j]
        if lanes == 1 or j - i < 2:
            _volume_kernel(0, j - i, *args, out)
        else:
            (a0, a1), (b0, b1) = halves(j - i)
            run_both(lambda: _volume_kernel(a0, a1, *args, out), lambda: _volume_kernel(b0, b1, *args, out))
        if work.dtype != x.dtype:
            x[i:j] = work
    return scale


_kernel = numba.njit(cache=True, nogil=True, fastmath={"contract"}, error_model="numpy")


@_kernel
def _area_vectors(x, faces, a, e):
    """a[v] = dV/dx_v = (1/6) sum over v's faces of the face's cross product (V, 3); e[v] =
    a third of the 6-fold signed tetrahedra (origin) of v's faces over 6 (so sum e = volume)."""
    a[:] = 0.0
    e[:] = 0.0
    for f in range(faces.shape[0]):
        i, j, k = faces[f, 0], faces[f, 1], faces[f, 2]
        ux, uy, uz = x[j, 0] - x[i, 0], x[j, 1] - x[i, 1], x[j, 2] - x[i, 2]
        wx, wy, wz = x[k, 0] - x[i, 0], x[k, 1] - x[i, 1], x[k, 2] - x[i, 2]
        cx, cy, cz = (uy * wz - uz * wy) / 6.0, (uz * wx - ux * wz) / 6.0, (ux * wy - uy * wx) / 6.0
        t = (x[i, 0] * cx + x[i, 1] * cy + x[i, 2] * cz) / 3.0
        for v in (i, j, k):
            a[v, 0] += cx
            a[v, 1] += cy
            a[v, 2] += cz
            e[v] += t


@_kernel
def _region_volumes(a, e, joints_xyz, bump_indptr, bump_joint, bump_share, out):
    """out[c] = sum_v pi_c(v) (e_v - p_c . a_v / 3): joint c's share of the tetrahedra measured
    from p_c (each face's tetrahedron (x_i - p) . cross / 6 split in thirds among its corners)."""
    out[:] = 0.0
    for v in range(a.shape[0]):
        for q in range(bump_indptr[v], bump_indptr[v + 1]):
            c = bump_joint[q]
            out[c] += bump_share[q] * (e[v] - (joints_xyz[c, 0] * a[v, 0] + joints_xyz[c, 1] * a[v, 1]
                                               + joints_xyz[c, 2] * a[v, 2]) / 3.0)


@_kernel
def _cubic(x, d, faces, loop_vertices, loop_starts, coef):
    """coef[0..3]: six times the capped volume of x + s d as c0 + c1 s + c2 s^2 + c3 s^3."""
    coef[:] = 0.0
    for f in range(faces.shape[0]):
        _det_terms(x[faces[f, 0]], x[faces[f, 1]], x[faces[f, 2]], d[faces[f, 0]], d[faces[f, 1]],
                   d[faces[f, 2]], coef)
    p = np.empty(3)
    dp = np.empty(3)
    for k in range(loop_starts.shape[0] - 1):
        s, t = loop_starts[k], loop_starts[k + 1]
        m = np.zeros(3)
        dm = np.zeros(3)
        for j in range(s, t):
            for c in range(3):
                m[c] += x[loop_vertices[j], c]
                dm[c] += d[loop_vertices[j], c]
        m /= t - s
        dm /= t - s
        for j in range(s, t):
            pi, qi = loop_vertices[j], loop_vertices[j + 1 if j + 1 < t else s]
            for c in range(3):
                p[c] = x[pi, c]
                dp[c] = d[pi, c]
            # the cap fan's triangle (q, p, centre), as capped_volume orients it
            _det_terms(x[qi], p, m, d[qi], dp, dm, coef)


@_kernel
def _volume6(x, faces, loop_vertices, loop_starts):
    """Six times the capped volume of x (V, 3): c0 of ``_cubic`` alone."""
    total = 0.0
    for f in range(faces.shape[0]):
        total += _det3(x[faces[f, 0]], x[faces[f, 1]], x[faces[f, 2]])
    m = np.empty(3)
    for k in range(loop_starts.shape[0] - 1):
        s, t = loop_starts[k], loop_starts[k + 1]
        m[:] = 0.0
        for j in range(s, t):
            for c in range(3):
                m[c] += x[loop_vertices[j], c]
        m /= t - s
        for j in range(s, t):
            total += _det3(x[loop_vertices[j + 1 if j + 1 < t else s]], x[loop_vertices[j]], m)
    return total


@numba.njit(inline="always", nogil=True, fastmath={"contract"}, error_model="numpy")
def _det3(a, b, c):
    return (a[0] * (b[1] * c[2] - b[2] * c[1]) + a[1] * (b[2] * c[0] - b[0] * c[2])
            + a[2] * (b[0] * c[1] - b[1] * c[0]))


@numba.njit(inline="always", nogil=True, fastmath={"contract"}, error_model="numpy")
def _det_terms(a, b, c, da, db, dc, coef):
    """Add the s-polynomial of det(a + s da, b + s db, c + s dc) to coef (4,)."""
    coef[0] += _det3(a, b, c)
    coef[1] += _det3(da, b, c) + _det3(a, db, c) + _det3(a, b, dc)
    coef[2] += _det3(da, db, c) + _det3(da, b, dc) + _det3(a, db, dc)
    coef[3] += _det3(da, db, dc)


@_kernel
def _cubic_root(coef, target):
    """The root near 1 of c0 + c1 s + c2 s^2 + c3 s^3 = target (Newton from 1); NaN if none."""
    s = 1.0
    tol = 1e-13 * max(abs(target), 1e-300)
    for _ in range(60):
        f = coef[0] + s * (coef[1] + s * (coef[2] + s * coef[3])) - target
        if abs(f) <= tol:
            return s
        df = coef[1] + s * (2.0 * coef[2] + s * 3.0 * coef[3])
        if df == 0.0 or not np.isfinite(df):
            return np.nan
        s -= f / df
    f = coef[0] + s * (coef[1] + s * (coef[2] + s * coef[3])) - target
    return s if abs(f) <= 1e-9 * max(abs(target), 1e-300) else np.nan


@_kernel
def _support(m, adj_indptr, adj_index, steps, dist, order):
    """The vertices within ``steps`` edge rings of a nonzero ``m`` (V,): their count n, the
    vertices in ``order[:n]`` (breadth first); ``dist`` (V,) their ring (-1 outside)."""
    dist[:] = -1
    n = 0
    for v in range(m.shape[0]):
        if m[v] != 0.0:
            dist[v] = 0
            order[n] = v
            n += 1
    head = 0
    while head < n:
        v = order[head]
        head += 1
        if dist[v] >= steps:
            continue
        for q in range(adj_indptr[v], adj_indptr[v + 1]):
            u = adj_index[q]
            if dist[u] < 0:
                dist[u] = dist[v] + 1
                order[n] = u
                n += 1
    return n


@_kernel
def _smooth_field(m, n, adj_indptr, adj_index, steps, d, tmp, dist, order):
    """d = (m n) after ``steps`` Jacobi steps d <- (d + mean of the neighbours' d) / 2; only the
    vertices within ``steps`` rings of a nonzero m are visited (d is 0 beyond them anyway)."""
    count = _support(m, adj_indptr, adj_index, steps, dist, order)
    d[:, :] = 0.0
    for i in range(count):
        v = order[i]
        for c in range(3):
            d[v, c] = m[v] * n[v, c]
    for _ in range(steps):
        for i in range(count):
            v = order[i]
            s0 = s1 = s2 = 0.0
            k = adj_indptr[v + 1] - adj_indptr[v]
            for q in range(adj_indptr[v], adj_indptr[v + 1]):
                u = adj_index[q]
                s0 += d[u, 0]
                s1 += d[u, 1]
                s2 += d[u, 2]
            if k > 0:
                r = _RATE / k
                tmp[v, 0] = (1.0 - _RATE) * d[v, 0] + r * s0
                tmp[v, 1] = (1.0 - _RATE) * d[v, 1] + r * s1
                tmp[v, 2] = (1.0 - _RATE) * d[v, 2] + r * s2
            else:
                tmp[v, 0], tmp[v, 1], tmp[v, 2] = d[v, 0], d[v, 1], d[v, 2]
        for i in range(count):
            v = order[i]
            d[v, 0], d[v, 1], d[v, 2] = tmp[v, 0], tmp[v, 1], tmp[v, 2]


@_kernel
def _volume_kernel(n0, n1, posed, rest, G, joint_rest, joint_posed, inner, bump_indptr, bump_joint, bump_value,
                   bump_share, w_indptr, w_bone, w_value, adj_indptr, adj_index, faces, loop_vertices, loop_starts,
                   fadj_indptr, fadj_index, steps, scale):
    """Frames n0..n1-1 of ``preserve_volume`` (see there; every buffer is this lane's own)."""
    V = posed.shape[1]
    K = joint_posed.shape[1]
    x = np.empty((V, 3))
    a = np.empty((V, 3))
    e = np.empty(V)
    n = np.empty((V, 3))
    m = np.empty(V)
    m_abs = np.empty(V)
    d = np.empty((V, 3))
    tmp = np.empty((V, 3))
    base = np.empty(K)
    dV = np.empty(K)
    g = np.empty(K)
    alpha = np.empty(K)
    alpha_abs = np.empty(K)
    coef = np.empty(4)
    rest_a = np.empty((V, 3))
    y = np.empty((V, 3))
    dist = np.empty(V, np.int64)
    order = np.empty(V, np.int64)
    fade = np.empty(V)
    fade_tmp = np.empty(V)
    cross = np.empty((faces.shape[0], 3))
    folded_before = np.empty(faces.shape[0], np.bool_)
    folded_after = np.empty(faces.shape[0], np.bool_)
    last_rest = -1
    rest_volume6 = 0.0
    for fr in range(n0, n1):
        r = fr if rest.shape[0] > 1 else 0
        hr = fr if joint_rest.shape[0] > 1 else 0
        if r != last_rest or joint_rest.shape[0] > 1:
            # the rest body: its region volumes (from the rest joints), volume and normals
            _area_vectors(rest[r], faces, a, e)
            _region_volumes(a, e, joint_rest[hr], bump_indptr, bump_joint, bump_share, base)
            for c in range(3):
                d[:, c] = 0.0
            _cubic(rest[r], d, faces, loop_vertices, loop_starts, coef)
            rest_volume6 = coef[0]
            rest_a[:, :] = a
            last_rest = r
        for v in range(V):
            for c in range(3):
                x[v, c] = posed[fr, v, c]
        _area_vectors(x, faces, a, e)
        _region_volumes(a, e, joint_posed[fr], bump_indptr, bump_joint, bump_share, dV)
        changed = False
        for c in range(K):
            dV[c] -= base[c]
            if dV[c] != 0.0:
                changed = True
        if not changed:
            scale[fr] = 0.0
            continue
        # normals: the rest area vector carried by the blended rotation (does not flip in folds)
        for v in range(V):
            n0x, n0y, n0z = rest_a[v, 0], rest_a[v, 1], rest_a[v, 2]
            s0 = s1 = s2 = 0.0
            for q in range(w_indptr[v], w_indptr[v + 1]):
                b, w = w_bone[q], w_value[q]
                s0 += w * (G[fr, b, 0, 0] * n0x + G[fr, b, 0, 1] * n0y + G[fr, b, 0, 2] * n0z)
                s1 += w * (G[fr, b, 1, 0] * n0x + G[fr, b, 1, 1] * n0y + G[fr, b, 1, 2] * n0z)
                s2 += w * (G[fr, b, 2, 0] * n0x + G[fr, b, 2, 1] * n0y + G[fr, b, 2, 2] * n0z)
            ln = np.sqrt(s0 * s0 + s1 * s1 + s2 * s2)
            if ln > 0.0:
                n[v, 0], n[v, 1], n[v, 2] = s0 / ln, s1 / ln, s2 / ln
            else:
                n[v, 0] = n[v, 1] = n[v, 2] = 0.0
        # g_c: the volume a unit bump (faded on the bend's inner side) adds
        g[:] = 0.0
        for v in range(V):
            an = a[v, 0] * n[v, 0] + a[v, 1] * n[v, 1] + a[v, 2] * n[v, 2]
            for q in range(bump_indptr[v], bump_indptr[v + 1]):
                c = bump_joint[q]
                g[c] += bump_value[q] * _contact(n, v, inner[fr, c]) * an
        # only the joints whose change has the body's sign are corrected (ONE_SIGNED): a joint
        # that gained while the body lost (the chest as the arms rise) is not pushed inward
        lost = _volume6(x, faces, loop_vertices, loop_starts) - rest_volume6
        small = _NEGLIGIBLE * abs(rest_volume6) / 6.0     # below: rounding, not a bend
        n_signed = n_any = 0
        for c in range(K):
            alpha[c] = -dV[c] / g[c] if abs(g[c]) > 1e-12 and abs(dV[c]) >= small else 0.0
            alpha_abs[c] = abs(alpha[c])
            if alpha[c] != 0.0:
                n_any += 1
                if ONE_SIGNED and dV[c] * lost <= 0.0:
                    alpha[c] = 0.0
                else:
                    n_signed += 1
        if n_any == 0:
            scale[fr] = 0.0
            continue
        for v in range(V):
            s0 = s1 = 0.0
            for q in range(bump_indptr[v], bump_indptr[v + 1]):
                c = bump_joint[q]
                if alpha_abs[c] != 0.0:
                    hc = bump_value[q] * _contact(n, v, inner[fr, c])
                    s0 += alpha[c] * hc
                    s1 += alpha_abs[c] * hc
            m[v] = s0
            m_abs[v] = s1
        s = np.nan
        if n_signed > 0:
            _smooth_field(m, n, adj_indptr, adj_index, steps, d, tmp, dist, order)
            _cubic(x, d, faces, loop_vertices, loop_starts, coef)
            s = _cubic_root(coef, rest_volume6)
        if not (_SCALE_RANGE[0] <= s <= _SCALE_RANGE[1]):
            # the regions' estimate disagrees with the whole body: every changed joint's bump
            # pushing one way, at whatever scale (of either sign) gives the rest volume
            _smooth_field(m_abs, n, adj_indptr, adj_index, steps, d, tmp, dist, order)
            _cubic(x, d, faces, loop_vertices, loop_starts, coef)
            s = _cubic_root(coef, rest_volume6)
            if not np.isfinite(s):
                s = 0.0
        if s != 0.0 and GUARD_ROUNDS > 0:
            # fold guard: where the displaced skin folds a face that LBS did not fold, fade the
            # displacement out (a smooth ramp over GUARD_RINGS rings) and solve s again
            _folded(x, faces, fadj_indptr, fadj_index, cross, folded_before)
            fade[:] = 1.0
            for _ in range(GUARD_ROUNDS):
                for v in range(V):
                    for c in range(3):
                        y[v, c] = x[v, c] + s * d[v, c]
                _folded(y, faces, fadj_indptr, fadj_index, cross, folded_after)
                new_folds = False
                for f in range(faces.shape[0]):
                    if folded_after[f] and not folded_before[f]:
                        new_folds = True
                        fade[faces[f, 0]] = fade[faces[f, 1]] = fade[faces[f, 2]] = 0.0
                if not new_folds:
                    break
                _ramp(fade, adj_indptr, adj_index, GUARD_RINGS, fade_tmp)
                for v in range(V):
                    for c in range(3):
                        d[v, c] *= fade[v]
                _cubic(x, d, faces, loop_vertices, loop_starts, coef)
                s_new = _cubic_root(coef, rest_volume6)
                if not (np.isfinite(s_new) and s_new * s > 0.0):
                    break
                s = s_new
        scale[fr] = s
        for v in range(V):
            for c in range(3):
                posed[fr, v, c] = x[v, c] + s * d[v, c]


@_kernel
def _folded(x, faces, fadj_indptr, fadj_index, cross, out):
    """out[f]: face f's normal opposes the summed normals of its edge neighbours (as in
    ``posing.count_folded_triangles``)."""
    for f in range(faces.shape[0]):
        i, j, k = faces[f, 0], faces[f, 1], faces[f, 2]
        ux, uy, uz = x[j, 0] - x[i, 0], x[j, 1] - x[i, 1], x[j, 2] - x[i, 2]
        wx, wy, wz = x[k, 0] - x[i, 0], x[k, 1] - x[i, 1], x[k, 2] - x[i, 2]
        cross[f, 0], cross[f, 1], cross[f, 2] = uy * wz - uz * wy, uz * wx - ux * wz, ux * wy - uy * wx
    for f in range(faces.shape[0]):
        s0 = s1 = s2 = 0.0
        for q in range(fadj_indptr[f], fadj_indptr[f + 1]):
            g = fadj_index[q]
            s0 += cross[g, 0]
            s1 += cross[g, 1]
            s2 += cross[g, 2]
        out[f] = cross[f, 0] * s0 + cross[f, 1] * s1 + cross[f, 2] * s2 < 0.0


@_kernel
def _ramp(fade, adj_indptr, adj_index, rings, tmp):
    """Zeros of ``fade`` (V,) grown by ``rings`` edge rings into a linear ramp: a vertex k rings
    from a zero gets at most k / (rings + 1) (min over its neighbours plus a step), values in [0, 1]."""
    step = 1.0 / (rings + 1)
    for _ in range(rings):
        for v in range(fade.shape[0]):
            lo = fade[v]
            for q in range(adj_indptr[v], adj_indptr[v + 1]):
                t = fade[adj_index[q]] + step
                if t < lo:
                    lo = t
            tmp[v] = lo
        fade[:] = tmp


@numba.njit(inline="always", nogil=True, fastmath={"contract"}, error_model="numpy")
def _contact(n, v, k):
    """1 - smoothstep(n_v . k): 0 where the normal faces the other limb of a bent joint (k = the
    sum of the unit directions from the joint to the two bones' far ends; |k| = 0 straight)."""
    t = n[v, 0] * k[0] + n[v, 1] * k[1] + n[v, 2] * k[2]
    if t <= 0.0:
        return 1.0
    if t >= 1.0:
        return 0.0
    return 1.0 - t * t * (3.0 - 2.0 * t)
