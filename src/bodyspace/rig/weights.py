"""Bone-heat skin weights (Baran & Popović 2007, "Automatic rigging and animation of 3D
characters", §4 "Skin attachment"), for any triangle mesh and any skeleton of bone segments.

The weight of bone b is the equilibrium temperature of the surface when bone b is held at
temperature 1 and every other bone at 0, each vertex exchanging heat only with its nearest
*visible* bone (the segment from the vertex to its closest point on the bone crosses no other
part of the surface):

    (−Δ + H) w_b = H p_b

with Δ the cotangent Laplacian, ``H_jj = c / d(j)²`` for d(j) the distance from vertex j to its
nearest visible bone (0 if it sees none), and ``p_b[j] = 1`` when bone b is that nearest
visible bone (``1/k`` when k bones tie). In the symmetric form solved here the Laplacian is the
positive semi-definite stiffness matrix ``L`` (``mesh.operators.cotangent_laplacian``) and Δ =
−M⁻¹L with the lumped vertex areas M, so every bone solves

    (L + M H) w_b = M H p_b

with **one** matrix: H is one diagonal for all bones, only the right-hand side changes. The
matrix is factored once (``mesh.solver.FactorizedSolver``, sparse LDLᵀ) and all bones' columns
are solved against that factor, on two threads. Because ``L 1 = 0`` and ``Σ_b p_b = 1`` on every
heated vertex, the bones' weights sum to one at every vertex before truncation (tested).

Visibility is our own ray test: a bounding-volume hierarchy of the triangles (median splits,
compiled) and a segment query per (vertex, candidate bone), candidates taken in increasing
distance until one is visible, so most vertices cost two queries (2.2 on the template).
Afterwards each vertex keeps at most ``max_influences`` bones by a *continuous* cut: negative
values (obtuse triangles have negative cotangent weights) become zero, the row's
``(max_influences + 1)``-th largest weight (or ``MIN_WEIGHT`` if larger) is subtracted from the
kept ones and the row is renormalized, so a bone's weight reaches zero exactly where it drops
out of a vertex's four (a plain top-4 cut jumps there, and the jumps fold skin when posed).
Finally each bone's cut column is smoothed by one implicit heat step confined to its support
(``smooth_within_support``): the cut leaves kinks where the (k+1)-th bone changes, and those
fold skin too; the smoothed cut folds about as little as the uncut heat.

Two options serve a skeleton whose bone names say more (``rig.posing.template_heat_rules`` for
the template): ``allowed``, a (V, B) mask of the bones each vertex may be weighted by (a bone
neither heats nor keeps weight where it is not allowed), and ``twist_of``, which heats a twist
bone together with the bone it twists and splits the pair's weight along it afterwards.

Any topology: degenerate (zero-area) faces are left out of the operator and the ray test;
vertices no face uses take their nearest bone with weight 1; a connected component on which no
vertex sees a bone (a loose part outside the skeleton) is heated by each vertex's nearest bone
regardless of visibility, so the system stays positive definite. Units and axes do not matter:
``M H`` is dimensionless, so a body in millimetres or turned gets the same weights.
"""

from __future__ import annotations

import numba
import numpy as np
import scipy.sparse as sp

from bodyspace.errors import MeshError, ParameterError
from bodyspace.mesh.operators import cotangent_laplacian
from bodyspace.mesh.solver import FactorizedSolver
from bodyspace.mesh.topology import vertex_components
from bodyspace.parallel import halves, run_both

__all__ = ["DEFAULT_HEAT", "DEFAULT_SMOOTHING", "GROUP_RAMP", "MIN_WEIGHT", "bone_heat_weights", "keep_group_totals",
           "nearest_visible_bones", "segments_blocked", "smooth_within_support", "twist_share"]

_kernel = numba.njit(cache=True, nogil=True)

# The paper's c in H_jj = c / d(j)^2 ("c = 1 works well"; larger values follow the nearest bone
# more closely, smaller ones blur the weights more).
DEFAULT_HEAT = 1.0
# Diffusion length of the smoothing after the cut, as a fraction of the square root of the
# mesh's surface area (a length that turning the mesh does not change): 0.05 is 6.4 cm on the
# template (1.61 m^2). Measured on 3 bodies x 39 poses (docs/skinning.md): the folds added by
# the 4-influence cut fall from 526 to about 240 for 3.5-8 cm (the uncut heat adds 233), to 287
# at 3.2 cm and 411 at 1 cm; at 32 cm 288 again.
DEFAULT_SMOOTHING = 0.05
# Bone groups (``bone_heat_weights(groups=...)``): a group whose kept bones' share after the cut
# falls below this fraction of its uncut share fades back to the plain cut (smoothstep), so a
# group leaving a vertex's four does so continuously. Chosen on the six training bodies with the
# template's chest group (docs/skinning.md): 1 / 0.5 / 0.25 / 0.1 gave 223 / 213 / 197 / 209
# folds added (LBS, 39 poses).
GROUP_RAMP = 0.25
# The least threshold of the cut (the skinning kernels cost per influence; a 1e-3 weight moves a
# vertex by at most 1e-3 of the bones' relative displacement).
MIN_WEIGHT = 1e-3
# Bones within this relative distance of the nearest visible one share its heat (ties at a
# joint, where a bone's tail is its child's head, are exact).
TIE_TOLERANCE = 1e-6
# A ray hit this close to the vertex's end of the segment (as a fraction of its length) is the
# vertex's own neighbourhood, not an occluder.
_SEGMENT_END = 1.0 - 1e-7
# Faces with double area below this times the squared bounding-box diagonal are degenerate.
_DEGENERATE_AREA = 1e-14
# Distances below this times the bounding-box diagonal count as this (H stays finite on a bone).
_MIN_DISTANCE = 1e-6
_LEAF_SIZE = 4


# -------------------------------------------------------------------------------- ray test

@_kernel
def _build_bvh(lo, hi, centroid, leaf_size):
    """Median-split bounding-volume hierarchy of boxes (F, 3) ``lo``/``hi``.

    Returns ``order`` (F,) (the boxes in leaf order), per node its box ``nlo``/``nhi``
    (n_nodes, 3), ``child`` (the left child; the right is ``child + 1``; -1 for a leaf) and
    ``start``/``stop`` (the leaf's range of ``order``).
    """
    F = lo.shape[0]
    order = np.arange(F)
    cap = max(1, 2 * F)
    nlo = np.empty((cap, 3))
    nhi = np.empty((cap, 3))
    child = np.full(cap, -1, dtype=np.int64)
    start = np.zeros(cap, dtype=np.int64)
    stop = np.zeros(cap, dtype=np.int64)
    stack = np.empty(128, dtype=np.int64)
    start[0], stop[0] = 0, F
    n_nodes, top = 1, 0
    stack[0] = 0
    while top >= 0:
        node = stack[top]
        top -= 1
        s, e = start[node], stop[node]
        for c in range(3):
            a, b = np.inf, -np.inf
            for k in range(s, e):
                f = order[k]
                a = min(a, lo[f, c])
                b = max(b, hi[f, c])
            nlo[node, c], nhi[node, c] = a, b
        if e - s <= leaf_size:
            continue
        axis, extent = 0, -1.0
        for c in range(3):
            a, b = np.inf, -np.inf
            for k in range(s, e):
                a = min(a, centroid[order[k], c])
                b = max(b, centroid[order[k], c])
            if b - a > extent:
                axis, extent = c, b - a
        if extent <= 0.0:
            continue                        # all centroids equal: one (large) leaf
        sub = order[s:e].copy()
        keys = np.empty(e - s)
        for k in range(e - s):
            keys[k] = centroid[sub[k], axis]
        order[s:e] = sub[np.argsort(keys, kind="mergesort")]
        mid = (s + e) // 2
        child[node] = n_nodes
        start[n_nodes], stop[n_nodes] = s, mid
        start[n_nodes + 1], stop[n_nodes + 1] = mid, e
        top += 1
        stack[top] = n_nodes
        top += 1
        stack[top] = n_nodes + 1
        n_nodes += 2
    return order, nlo[:n_nodes].copy(), nhi[:n_nodes].copy(), child[:n_nodes].copy(), start[:n_nodes].copy(), \
        stop[:n_nodes].copy()


@_kernel
def _segment_hits(p, q, skip, tri, corners, order, nlo, nhi, child, start, stop, stack):
    """True when the segment p → q (end ``_SEGMENT_END``) crosses a triangle that does not have
    vertex ``skip`` as a corner. tri (F, 3, 3) corner positions, corners (F, 3) vertex ids."""
    d0, d1, d2 = q[0] - p[0], q[1] - p[1], q[2] - p[2]
    inv0 = 1.0 / d0 if d0 != 0.0 else np.inf
    inv1 = 1.0 / d1 if d1 != 0.0 else np.inf
    inv2 = 1.0 / d2 if d2 != 0.0 else np.inf
    top = 0
    stack[0] = 0
    while top >= 0:
        node = stack[top]
        top -= 1
        # slab test of the segment t in [0, 1] against the node's box
        t0, t1 = 0.0, 1.0
        ok = True
        for c in range(3):
            pc = p[c]
            inv = inv0 if c == 0 else (inv1 if c == 1 else inv2)
            if inv == np.inf:
                if pc < nlo[node, c] or pc > nhi[node, c]:
                    ok = False
                    break
                continue
            ta = (nlo[node, c] - pc) * inv
            tb = (nhi[node, c] - pc) * inv
            if ta > tb:
                ta, tb = tb, ta
            t0 = max(t0, ta)
            t1 = min(t1, tb)
            if t0 > t1:
                ok = False
                break
        if not ok:
            continue
        if child[node] >= 0:
            top += 1
            stack[top] = child[node]
            top += 1
            stack[top] = child[node] + 1
            continue
        for k in range(start[node], stop[node]):
            f = order[k]
            if corners[f, 0] == skip or corners[f, 1] == skip or corners[f, 2] == skip:
                continue
            # Möller–Trumbore; edges and corners count as hits (conservative)
            ax, ay, az = tri[f, 0, 0], tri[f, 0, 1], tri[f, 0, 2]
            e1x, e1y, e1z = tri[f, 1, 0] - ax, tri[f, 1, 1] - ay, tri[f, 1, 2] - az
            e2x, e2y, e2z = tri[f, 2, 0] - ax, tri[f, 2, 1] - ay, tri[f, 2, 2] - az
            hx, hy, hz = d1 * e2z - d2 * e2y, d2 * e2x - d0 * e2z, d0 * e2y - d1 * e2x
            det = e1x * hx + e1y * hy + e1z * hz
            if det == 0.0:
                continue
            inv_det = 1.0 / det
            sx, sy, sz = p[0] - ax, p[1] - ay, p[2] - az
            u = (sx * hx + sy * hy + sz * hz) * inv_det
            if u < 0.0 or u > 1.0:
                continue
            qx, qy, qz = sy * e1z - sz * e1y, sz * e1x - sx * e1z, sx * e1y - sy * e1x
            v = (d0 * qx + d1 * qy + d2 * qz) * inv_det
            if v < 0.0 or u + v > 1.0:
                continue
            t = (e2x * qx + e2y * qy + e2z * qz) * inv_det
            if 0.0 <= t < _SEGMENT_END:
                return True
    return False


@_kernel
def _closest_on_segment(x, h, t, out):
    """Closest point of segment h → t to x into ``out``; returns the squared distance."""
    d0, d1, d2 = t[0] - h[0], t[1] - h[1], t[2] - h[2]
    dd = d0 * d0 + d1 * d1 + d2 * d2
    s = 0.0
    if dd > 0.0:
        s = ((x[0] - h[0]) * d0 + (x[1] - h[1]) * d1 + (x[2] - h[2]) * d2) / dd
        s = min(1.0, max(0.0, s))
    out[0], out[1], out[2] = h[0] + s * d0, h[1] + s * d1, h[2] + s * d2
    return (x[0] - out[0]) ** 2 + (x[1] - out[1]) ** 2 + (x[2] - out[2]) ** 2


@_kernel
def _nearest_visible_kernel(vertices, heads, tails, bones, tri, corners, order, nlo, nhi, child, start, stop,
                            allow, i0, i1, tie, source, source_count, nearest, dist, tests):
    """For vertices i0:i1: the nearest visible bones (``source`` (V, 4) ids into ``bones``,
    ``source_count``: how many tie, 0 if none is visible), the nearest bone regardless of
    visibility (``nearest``), the distance to the nearest visible one (``dist``, inf if none)
    and the number of segment queries (``tests``). ``allow`` (V, K) bool: the bones each vertex
    may take as its source (a (1, 1) array: all)."""
    B = len(bones)
    d2 = np.empty(B)
    point = np.empty(3)
    stack = np.empty(256, dtype=np.int64)
    masked = allow.shape[0] == vertices.shape[0] and allow.shape[1] == B
    for i in range(i0, i1):
        x = vertices[i]
        for k in range(B):
            d2[k] = _closest_on_segment(x, heads[bones[k]], tails[bones[k]], point)
        if masked:                              # a row that allows no bone allows all
            some = False
            for k in range(B):
                some = some or allow[i, k]
            if some:
                for k in range(B):
                    if not allow[i, k]:
                        d2[k] = np.inf
        best = np.inf
        count = 0
        first = True
        while True:
            k_min, m = -1, np.inf
            for k in range(B):
                if d2[k] < m:
                    k_min, m = k, d2[k]
            if k_min < 0 or m > best * (1.0 + tie) ** 2:
                break
            if first:
                nearest[i] = k_min
                first = False
            b = bones[k_min]
            _closest_on_segment(x, heads[b], tails[b], point)
            tests[i] += 1
            if not _segment_hits(point, x, i, tri, corners, order, nlo, nhi, child, start, stop, stack):
                if count == 0:
                    best = m
                if count < 4:
                    source[i, count] = k_min
                    count += 1
            d2[k_min] = np.inf
        source_count[i] = count
        dist[i] = np.sqrt(best)


class _Bvh:
    """The ray-test structure of a mesh: triangles (without degenerate ones) in a BVH."""

    def __init__(self, vertices: np.ndarray, faces: np.ndarray):
        tri = vertices[faces]                                   # (F, 3, 3)
        self.tri = np.ascontiguousarray(tri)
        self.corners = np.ascontiguousarray(faces, dtype=np.int64)
        self.order, self.nlo, self.nhi, self.child, self.start, self.stop = _build_bvh(
            tri.min(axis=1), tri.max(axis=1), tri.mean(axis=1), _LEAF_SIZE)

    @property
    def arrays(self):
        return self.tri, self.corners, self.order, self.nlo, self.nhi, self.child, self.start, self.stop


def nearest_visible_bones(vertices: np.ndarray, faces: np.ndarray, heads: np.ndarray, tails: np.ndarray,
                          bones: np.ndarray | None = None, *, tie: float = TIE_TOLERANCE, lanes: int | None = None,
                          allowed: np.ndarray | None = None):
    """Each vertex's nearest visible bone (Baran & Popović §4): the closest bone segment whose
    closest point the vertex sees, i.e. the segment between them crosses no triangle that does
    not have the vertex as a corner.

    vertices (V, 3), faces (F, 3); heads, tails (B, 3); bones: (K,) indices of the bones that
    may be chosen (default all); allowed: (V, B) bool, the bones each vertex may take (a
    vertex's row with no True allows all; default: all). Returns ``source`` (V, 4) int (bone
    indices, -1 padded; up to four bones tie within ``tie`` relative distance), ``count`` (V,) (0: no bone visible),
    ``nearest`` (V,) the nearest bone regardless of visibility, ``distance`` (V,) to the
    nearest visible bone (inf if none) and ``tests`` (V,) segment queries made.
    """
    v = np.ascontiguousarray(vertices, dtype=float)
    f = np.ascontiguousarray(faces, dtype=np.int64)
    h = np.ascontiguousarray(heads, dtype=float)
    t = np.ascontiguousarray(tails, dtype=float)
    bones = np.arange(len(h)) if bones is None else np.ascontiguousarray(bones, dtype=np.int64)
    bvh = _Bvh(v, f)
    V = len(v)
    source = np.full((V, 4), -1, dtype=np.int64)
    count = np.zeros(V, dtype=np.int64)
    nearest = np.zeros(V, dtype=np.int64)
    dist = np.full(V, np.inf)
    tests = np.zeros(V, dtype=np.int64)
    allow = np.ones((1, 1), dtype=np.bool_) if allowed is None else \
        np.ascontiguousarray(_check_allowed(allowed, V, len(h))[:, bones])
    args = (v, h, t, bones, *bvh.arrays, allow)
    outs = (tie, source, count, nearest, dist, tests)
    if lanes is None:
        lanes = 2 if V * len(bones) >= 50_000 else 1
    if lanes == 2:
        (a0, a1), (b0, b1) = halves(V)
        run_both(lambda: _nearest_visible_kernel(*args, a0, a1, *outs),
                 lambda: _nearest_visible_kernel(*args, b0, b1, *outs))
    else:
        _nearest_visible_kernel(*args, 0, V, *outs)
    source = np.where(source >= 0, bones[np.maximum(source, 0)], -1)
    return source, count, bones[nearest], dist, tests


def segments_blocked(vertices: np.ndarray, faces: np.ndarray, starts: np.ndarray, vertex_ids: np.ndarray) -> np.ndarray:
    """(K,) bool: does the segment from ``starts[k]`` (K, 3) to vertex ``vertex_ids[k]`` cross
    the mesh (a triangle without that vertex as a corner)? The visibility test of the bone heat,
    exposed for tests and for other callers (e.g. skeleton embedding)."""
    v = np.ascontiguousarray(vertices, dtype=float)
    bvh = _Bvh(v, np.ascontiguousarray(faces, dtype=np.int64))
    stack = np.empty(256, dtype=np.int64)
    starts = np.asarray(starts, dtype=float)
    return np.array([_segment_hits(starts[k], v[i], int(i), *bvh.arrays, stack)
                     for k, i in enumerate(np.asarray(vertex_ids, dtype=np.int64))], dtype=bool)


# ------------------------------------------------------------------------------ bone heat

def _check_inputs(vertices, faces, heads, tails, max_influences, deform, heat):
    v = np.asarray(vertices, dtype=float)
    if v.ndim != 2 or v.shape[1] != 3 or len(v) == 0:
        raise MeshError(f"vertices: shape {np.shape(vertices)}, expected (V, 3) with V >= 1")
    if not np.isfinite(v).all():
        raise MeshError(f"vertices: vertex {int(np.flatnonzero(~np.isfinite(v).all(1))[0])} holds NaN or infinity; "
                        f"expected finite coordinates")
    f = np.asarray(faces)
    if f.ndim != 2 or f.shape[1] != 3 or len(f) == 0 or not np.issubdtype(f.dtype, np.integer):
        raise MeshError(f"faces: shape {f.shape} dtype {f.dtype}, expected (F, 3) vertex indices with F >= 1")
    if f.min() < 0 or f.max() >= len(v):
        raise MeshError(f"faces: indices {int(f.min())}..{int(f.max())}, expected 0..{len(v) - 1} "
                        f"(the mesh has {len(v)} vertices)")
    h = np.asarray(heads, dtype=float)
    t = np.asarray(tails, dtype=float)
    if h.ndim != 2 or h.shape[1] != 3 or len(h) == 0 or t.shape != h.shape:
        raise ParameterError(f"heads, tails: shapes {np.shape(heads)} and {np.shape(tails)}, expected (B, 3) "
                             f"each with B >= 1 bones")
    if not (np.isfinite(h).all() and np.isfinite(t).all()):
        raise ParameterError("heads, tails: NaN or infinity found; expected finite bone ends in the mesh's units")
    if isinstance(max_influences, bool) or not isinstance(max_influences, (int, np.integer)) or max_influences < 1:
        raise ParameterError(f"max_influences={max_influences!r}; expected an integer >= 1 (4 for glTF)")
    if deform is None:
        deform = np.ones(len(h), dtype=bool)
    deform = np.asarray(deform)
    if deform.shape != (len(h),) or deform.dtype != bool or not deform.any():
        raise ParameterError(f"deform: shape {deform.shape} dtype {deform.dtype}, expected ({len(h)},) bool "
                             f"with at least one True (the bones that receive weights)")
    if not (np.isfinite(heat) and heat > 0):
        raise ParameterError(f"heat={heat!r}; expected a positive number (the paper's c, default {DEFAULT_HEAT})")
    return v, f.astype(np.int64), h, t, deform


def _check_allowed(allowed, V: int, B: int) -> np.ndarray:
    """``allowed`` as a dense (V, B) bool array, or a clear error."""
    a = allowed.toarray() if sp.issparse(allowed) else np.asarray(allowed)
    if a.shape != (V, B) or a.dtype != bool:
        raise ParameterError(f"allowed: shape {a.shape} dtype {a.dtype}, expected ({V}, {B}) bool (the bones each "
                             f"of the {V} vertices may be weighted by; None: all)")
    return np.ascontiguousarray(a)


@_kernel
def _cut_rows(W, k, min_weight, idx, val):
    """Per row of W (n, K): the k largest entries' columns into ``idx`` (n, k) (-1 padded)
    and their weights minus the row's threshold, renormalized, into ``val`` (``_top_weights``)."""
    n, K = W.shape
    top = np.empty(k + 1, dtype=np.int64)
    for i in range(n):
        row = W[i]
        m = 0                                        # top[:m]: the largest so far, descending
        for j in range(K):
            w = row[j]
            if w <= 0.0 or (m == k + 1 and w <= row[top[k]]):
                continue
            p = min(m, k)
            while p > 0 and row[top[p - 1]] < w:
                top[p] = top[p - 1]
                p -= 1
            top[p] = j
            m = min(m + 1, k + 1)
        kept = min(m, k)
        tau = min_weight
        if m == k + 1:
            tau = max(tau, row[top[k]])
        total = 0.0
        for q in range(kept):
            val[i, q] = max(row[top[q]] - tau, 0.0)
            idx[i, q] = top[q]
            total += val[i, q]
        if total <= 0.0:                             # k+1 equal weights, or all below min_weight
            for q in range(kept):
                val[i, q] = 1.0 if row[top[q]] >= row[top[0]] else 0.0
                total += val[i, q]
        for q in range(kept):
            val[i, q] /= total
        for q in range(kept, k):
            idx[i, q] = -1
            val[i, q] = 0.0


def _top_weights(W: np.ndarray, k: int, min_weight: float) -> sp.csr_matrix:
    """Rows of the dense (V, K) W cut to at most k bones *continuously*: each row's weights
    minus its threshold ``tau = max(w_(k+1), min_weight)`` (w_(k+1) its (k+1)-th largest
    weight), negatives to zero, renormalized to sum to one.

    A plain top-k cut jumps where the k-th and (k+1)-th bones swap places between neighbouring
    vertices, and those jumps fold triangles when posed (measured on 3 bodies x 39 poses: 677
    folds added with the plain cut, 526 with this one, 239 with no cut at all, c = 1);
    subtracting the (k+1)-th weight makes a dropped bone's weight reach zero where it leaves.
    """
    V, K = W.shape
    k = min(k, K)
    idx = np.empty((V, k), dtype=np.int64)
    val = np.empty((V, k))
    _cut_rows(np.ascontiguousarray(W), k, min_weight, idx, val)
    keep = idx >= 0
    indptr = np.concatenate([[0], np.cumsum(keep.sum(axis=1))])
    M = sp.csr_matrix((val[keep], idx[keep], indptr), shape=(V, K))
    M.eliminate_zeros()
    M.sort_indices()
    return M


def keep_group_totals(uncut: np.ndarray, cut: sp.spmatrix, groups: np.ndarray,
                      ramp: float = GROUP_RAMP) -> sp.csr_matrix:
    """Cut weights with each bone group's share of a row moved back toward its share before the cut.

    uncut: (n, K) dense, the weights before the cut (negatives count as zero; rows are
        normalized here); cut: (n, K) sparse, the continuous cut of them (``_top_weights``),
        rows summing to one; groups: (K,) int, each column's group (-1: in no group);
        ramp: in (0, 1].
    Returns (n, K) CSR with the cut's sparsity (no vertex gains a bone), rows summing to one.

    The continuous cut subtracts the (k+1)-th weight from every kept bone and renormalizes, which
    hands the dropped bones' weight to the *largest* kept bone: beside the armpit five bones of
    the rib cage (spine01-03, breast, clavicle) share the four places with the upper arm, and an
    uncut upper-arm weight of 0.51 becomes 0.70, which folds the skin there when the arm swings
    forward. Here the kept bones of each group g are scaled to the group's uncut share ``G_g``
    instead of their cut share ``C_g``, with a ramp ``s = smoothstep(C_g / (ramp G_g))`` so that
    a group whose last kept bone leaves the vertex's four fades out continuously:
    ``w_b <- c_b (1 - s) + c_b G_g / C_g s``; bones in no group keep their cut weight c_b; then
    the row is renormalized (a group's share becomes ``G_g / (sum of groups' G + sum of the
    lone bones' c)``, not exactly G_g).
    """
    n, K = uncut.shape
    g = np.asarray(groups, dtype=np.int64)
    if g.shape != (K,) or not (0.0 < ramp <= 1.0):
        raise ParameterError(f"groups: shape {g.shape}, ramp {ramp!r}; expected ({K},) ints (one a column of the "
                             f"weights) and a ramp in (0, 1]")
    lone = g < 0
    _, gid = np.unique(np.where(lone, -1, g), return_inverse=True)      # lone bones share one id, unused
    onehot = sp.csr_matrix((np.ones(K), (np.arange(K), gid)), shape=(K, int(gid.max()) + 1))
    u = np.maximum(uncut, 0.0)
    u = u / np.maximum(u.sum(axis=1, keepdims=True), 1e-300)
    G = np.asarray(u @ onehot)                                          # (n, groups) uncut shares
    c = sp.csr_matrix(cut, dtype=float)
    C = (c @ onehot).toarray()                                          # (n, groups) cut shares
    row = np.repeat(np.arange(n), np.diff(c.indptr))
    Gv, Cv = G[row, gid[c.indices]], C[row, gid[c.indices]]
    x = np.clip(Cv / np.maximum(ramp * Gv, 1e-300), 0.0, 1.0)
    s = np.where(lone[c.indices], 0.0, x * x * (3.0 - 2.0 * x))
    data = c.data * ((1.0 - s) + s * Gv / np.maximum(Cv, 1e-300))
    out = sp.csr_matrix((data, c.indices.copy(), c.indptr.copy()), shape=c.shape)
    total = np.asarray(out.sum(axis=1)).ravel()
    out = (sp.diags(1.0 / np.where(total > 0.0, total, 1.0)) @ out).tocsr()
    out.sort_indices()
    return out


def smooth_within_support(weights: sp.spmatrix, stiffness: sp.spmatrix, mass: np.ndarray,
                          length: float) -> sp.csr_matrix:
    """Weights cut to a few bones a vertex, smoothed over the surface *within each bone's support*.

    weights: (V, B) sparse, rows summing to one (the cut weights: at most k entries a row).
    stiffness: (V, V) the cotangent stiffness L (positive semi-definite, ``cotangent_laplacian``).
    mass: (V,) lumped vertex areas.
    length: the diffusion length, in the mesh's units (``t = length^2``).
    Returns (V, B) CSR with the same sparsity (no vertex gains a bone), rows summing to one.

    Bone b's column is replaced by the solution of ``(M + t L)_DD x = M_DD w_b[D]`` on its
    support D (the vertices where it has weight), zero outside it: one implicit heat step with
    the column held at zero beyond its support (a Dirichlet boundary), so every bone still
    leaves a vertex's four exactly where the cut made it leave, but its weight now falls there
    as smoothly as the support's width allows instead of along the cut's kinks (where the
    (k+1)-th bone changes, the cut's gradient jumps and is magnified by the renormalization:
    those steep, kinked weights fold the skin when posed). Negative values (obtuse triangles)
    become zero; each row is renormalized (a row the solve empties keeps its cut weights).
    """
    W = sp.csr_matrix(weights, dtype=float)
    W.sort_indices()
    V = W.shape[0]
    mass = np.asarray(mass, dtype=float)
    if sp.csr_matrix(stiffness).shape != (V, V) or mass.shape != (V,) or not (mass > 0).all():
        raise MeshError(f"stiffness {np.shape(stiffness)}, mass {mass.shape}: expected ({V}, {V}) and ({V},) "
                        f"positive vertex areas for the {V} rows of the weights")
    if not (np.isfinite(length) and length >= 0):
        raise ParameterError(f"length={length!r}; expected a diffusion length >= 0 in the mesh's units")
    A = (float(length) ** 2 * sp.csr_matrix(stiffness) + sp.diags(mass)).tocoo()     # SPD, (V, V)
    # All bones' systems as one block-diagonal system over the entries of W: entry (i, b) couples
    # with entry (j, b) through A_ij when bone b has weight at both i and j. One factorization
    # (the blocks' fill stays within each block) instead of one per bone.
    k = int(np.diff(W.indptr).max(initial=0))
    slot_bone = np.full((V, max(k, 1)), -1, dtype=np.int64)            # (V, k) bone of each slot
    slot_entry = np.zeros((V, max(k, 1)), dtype=np.int64)              # (V, k) entry id in W.data
    row = np.repeat(np.arange(V), np.diff(W.indptr))
    pos = np.arange(W.nnz) - W.indptr[row]
    slot_bone[row, pos] = W.indices
    slot_entry[row, pos] = np.arange(W.nnz)
    rows, cols, vals = [], [], []
    for a in range(k):
        for c in range(k):
            same = (slot_bone[A.row, a] == slot_bone[A.col, c]) & (slot_bone[A.row, a] >= 0)
            rows.append(slot_entry[A.row[same], a])
            cols.append(slot_entry[A.col[same], c])
            vals.append(A.data[same])
    blocks = sp.csc_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(W.nnz, W.nnz))
    data = FactorizedSolver(blocks).solve(mass[row] * W.data)
    S = sp.csr_matrix((np.maximum(data, 0.0), W.indices, W.indptr), shape=W.shape)
    total = np.asarray(S.sum(axis=1)).ravel()
    empty = total <= 0.0
    if empty.any():                          # keep the cut weights on such (isolated) rows
        S = (sp.diags((~empty).astype(float)) @ S + sp.diags(empty.astype(float)) @ sp.csr_matrix(weights)).tocsr()
        total = np.where(empty, 1.0, total)
    S = (sp.diags(1.0 / total) @ S).tocsr()
    S.eliminate_zeros()
    S.sort_indices()
    return S


def bone_heat_weights(vertices: np.ndarray, faces: np.ndarray, heads: np.ndarray, tails: np.ndarray,
                      max_influences: int = 4, *, deform: np.ndarray | None = None, heat: float = DEFAULT_HEAT,
                      min_weight: float = MIN_WEIGHT, smoothing: float = DEFAULT_SMOOTHING,
                      allowed: np.ndarray | None = None, twist_of: np.ndarray | None = None,
                      groups: np.ndarray | None = None, lanes: int | None = None) -> sp.csr_matrix:
    """Bone-heat skin weights (Baran & Popović 2007 §4): (V, B) sparse, rows summing to one.

    vertices: (V, 3) any triangle mesh (any units and axes, holes and loose parts allowed).
    faces: (F, 3) int.
    heads, tails: (B, 3) the bones as segments, in the mesh's units and frame (the skeleton
        inside the body, e.g. ``Rig.heads(body)``, ``Rig.tails(body)``).
    max_influences: bones kept per vertex (the largest weights; 4 for glTF).
    deform: (B,) bool, the bones that receive weights (default all; e.g. leave out a root or
        control bones); the others get zero columns.
    heat: the paper's c in ``H_jj = c / d(j)^2``.
    min_weight: the least threshold of the continuous cut (rows sum to one): smaller weights
        are dropped.
    smoothing: diffusion length of the smoothing after the cut, as a fraction of the square
        root of the surface area (``smooth_within_support``); 0 keeps the cut weights. Skipped
        when nothing is cut (``max_influences`` at least the number of bones with heat).
    allowed: (V, B) bool (dense or sparse), the bones each vertex may be weighted by (default
        all): a vertex takes only allowed bones as its heat source, and a bone's heat is cut
        where it is not allowed (before the cut to ``max_influences``). A part-aware mask, e.g.
        the jaw only on the chin, the upper arm not on the torso away from the armpit
        (``posing.bone_heat_rig_weights``).
        A row with no True allows all.
    twist_of: (B,) int, for a twist bone the bone it twists (its parent, whose tail is its
        head; e.g. MakeHuman's upperarm02 of upperarm01), -1 for the others (default none).
        The pair is heated as one bone (the segment from the parent's head to the twist bone's
        tail), then the pair's weight is split along that segment: the twist bone's share
        rises linearly from 0 at their joint to 1 at its tail (``twist_share``). So a twist
        bone takes no place among a vertex's four where the pair meets the body (at the
        shoulder: one arm bone and three of the torso instead of two arm bones and two).
    groups: (B,) int, bones that move together (e.g. the rib cage's), the same id >= 0 for the
        bones of a group, -1 for the others (default none): through the cut to
        ``max_influences`` each group keeps the share of the vertex it had before it, instead of
        the largest bone taking the dropped bones' weight (``keep_group_totals``).
    lanes: 1 or 2 threads; None: two for large meshes.
    Returns a CSR (V, B) float64 matrix, at most ``max_influences`` entries a row, each row
    summing to one.

    1. Each vertex's nearest visible deforming bone (``nearest_visible_bones``) and its
       distance d give ``H = c / d^2`` and the heat source ``p`` (ties share it).
    2. The cotangent stiffness L and lumped areas M of the non-degenerate faces;
       ``A = L + M H``, factored once.
    3. One solve of ``A w_b = M H p_b`` for each bone that is some vertex's source (the others'
       weights are zero), all columns against the one factor; with ``allowed``, each bone's
       weight set to zero where it is not allowed and the rows renormalized.
    4. Per vertex: negatives dropped, the largest ``max_influences`` kept minus the next
       one's weight (continuous cut, ``_top_weights``), renormalized; with ``groups`` each
       group's kept bones scaled back to the group's uncut share (``keep_group_totals``).
    5. Each bone's cut column smoothed within its own support (``smooth_within_support``), so
       the cut's kinks do not fold the skin; rows renormalized.
    6. With ``twist_of``: each pair's weight split between the bone and its twist bone
       (``twist_share``); rows that this takes past ``max_influences`` cut again (step 4).
    """
    v, f, h, t, deform = _check_inputs(vertices, faces, heads, tails, max_influences, deform, heat)
    if not (0.0 <= min_weight < 1.0):
        raise ParameterError(f"min_weight={min_weight!r}; expected a number in [0, 1) (default {MIN_WEIGHT})")
    if lanes not in (None, 1, 2):
        raise ParameterError(f"lanes={lanes!r}; expected 1, 2 or None (automatic)")
    if not (np.isfinite(smoothing) and smoothing >= 0):
        raise ParameterError(f"smoothing={smoothing!r}; expected a fraction of sqrt(surface area) >= 0 "
                             f"(default {DEFAULT_SMOOTHING}; 0: no smoothing after the cut)")
    V, B = len(v), len(h)
    scale = float(np.linalg.norm(v.max(0) - v.min(0))) or 1.0
    twist = _check_twist(twist_of, h, t, deform, scale)
    if groups is not None:
        groups = np.asarray(groups)
        if groups.shape != (B,) or not np.issubdtype(groups.dtype, np.integer) or groups.min(initial=-1) < -1:
            raise ParameterError(f"groups: shape {groups.shape} dtype {groups.dtype}, expected ({B},) ints >= -1 "
                                 f"(the same id for bones that move together, -1 for bones in no group)")
    bone_tails = t
    if twist is not None:              # each pair heated as one bone: parent's head to child's tail
        t = t.copy()
        t[twist[twist >= 0]] = bone_tails[twist >= 0]
        deform = deform & (twist < 0)
    # 1. faces with area; vertices that some such face uses
    dbl = np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), axis=1)
    f = f[dbl > _DEGENERATE_AREA * scale * scale]
    used = np.zeros(V, dtype=bool)
    used[f.ravel()] = True
    bones = np.flatnonzero(deform)
    if not len(f):
        raise MeshError(f"faces: all {len(faces)} faces have zero area; expected a surface mesh")
    allow = None if allowed is None else _check_allowed(allowed, V, B)
    source, count, nearest, dist, _ = nearest_visible_bones(v, f, h, t, bones, lanes=lanes, allowed=allow)
    # a component where no vertex sees a bone is heated by every vertex's nearest bone
    _, comp = vertex_components(f, V)
    seen = np.bincount(comp, weights=(count > 0) & used, minlength=comp.max() + 1) > 0
    blind = used & ~seen[comp]
    if blind.any():
        source[blind] = -1
        source[blind, 0] = nearest[blind]
        count[blind] = 1
        d = np.empty(int(blind.sum()))
        point = np.empty(3)
        for k, i in enumerate(np.flatnonzero(blind)):
            d[k] = np.sqrt(_closest_on_segment(v[i], h[nearest[i]], t[nearest[i]], point))
        dist[blind] = d
    # 2. the system
    L = cotangent_laplacian(v, f)
    mass = np.bincount(f.ravel(), weights=np.repeat(dbl[dbl > _DEGENERATE_AREA * scale * scale] / 6.0, 3),
                       minlength=V)
    heated = used & (count > 0)
    H = np.zeros(V)
    H[heated] = heat / np.maximum(dist[heated], _MIN_DISTANCE * scale) ** 2
    active = np.flatnonzero(used)                       # unused vertices: no row in the system
    A = (L + sp.diags(mass * H))[active][:, active]
    rows = np.repeat(np.flatnonzero(heated), count[heated])
    cols = source[heated][source[heated] >= 0]
    share = np.repeat(1.0 / count[heated], count[heated])
    P = sp.csr_matrix((share, (rows, cols)), shape=(V, B))
    columns = np.flatnonzero(np.asarray(P.sum(axis=0)).ravel() > 0)
    rhs = np.ascontiguousarray((sp.diags(mass * H) @ P[:, columns])[active].toarray())
    # 3. one factorization, every bone's column against it
    solver = FactorizedSolver(A)
    W = _solve_columns(solver, rhs, lanes)
    if allow is not None:
        # a bone keeps no heat where it is not allowed (the heat diffuses past the vertices it
        # sources); rows renormalized, a row left with nothing keeps its heat
        kept = np.where(allow[active][:, columns], W, 0.0)
        total = kept.sum(axis=1, keepdims=True)
        W = np.where(total > 0.0, kept / np.where(total > 0.0, total, 1.0), W)
    # 4. truncate and normalize; unused vertices take their nearest bone
    top = _top_weights(W, max_influences, min_weight)              # (len(active), K)
    if groups is not None and (groups >= 0).any():
        top = keep_group_totals(W, top, groups[columns])
    if smoothing > 0 and max_influences < len(columns):
        # 5. the cut smoothed within each bone's support
        length = smoothing * np.sqrt(mass.sum())          # mass sums to the surface area
        top = smooth_within_support(top, L[active][:, active], mass[active], length)
    if twist is not None:
        # 6. each pair's weight split between the bone and its twist bone along their segment;
        # where that makes a fifth bone (the pair meets three others, at the elbow and wrist),
        # the continuous cut again
        dense = top.toarray()
        extra = []
        for c in np.flatnonzero(twist >= 0):
            k = np.flatnonzero(columns == twist[c])
            if len(k):
                share = twist_share(v[active], h[twist[c]], bone_tails[twist[c]], bone_tails[c])
                extra.append((c, dense[:, k[0]] * share))
                dense[:, k[0]] *= 1.0 - share
        if extra:
            columns = np.concatenate([columns, [c for c, _ in extra]])
            dense = np.hstack([dense, np.stack([w for _, w in extra], axis=1)])
            over = (dense > 0.0).sum(axis=1) > max_influences
            if over.any():
                dense[over] = _top_weights(dense[over], max_influences, min_weight).toarray()
            top = sp.csr_matrix(dense)
    top = sp.csr_matrix((top.data, columns[top.indices], top.indptr), shape=(len(active), B))
    if used.all():
        out = top
    else:
        lone = np.flatnonzero(~used)
        expand = sp.csr_matrix((np.ones(len(active)), (active, np.arange(len(active)))), shape=(V, len(active)))
        out = (expand @ top + sp.csr_matrix((np.ones(len(lone)), (lone, _nearest_bones(v[lone], h, t, bones))),
                                            shape=(V, B))).tocsr()
    out.sort_indices()
    return out


def _check_twist(twist_of, heads, tails, deform, scale) -> np.ndarray | None:
    """``twist_of`` as a (B,) int array (or None), or a clear error."""
    if twist_of is None:
        return None
    B = len(heads)
    tw = np.asarray(twist_of)
    if tw.shape != (B,) or not np.issubdtype(tw.dtype, np.integer) or tw.min(initial=-1) < -1 or \
            tw.max(initial=-1) >= B:
        raise ParameterError(f"twist_of: shape {tw.shape} dtype {tw.dtype}, expected ({B},) ints in -1..{B - 1} "
                             f"(for a twist bone the bone it twists, else -1)")
    for c in np.flatnonzero(tw >= 0):
        p = int(tw[c])
        if p == c or tw[p] >= 0 or not (deform[p] and deform[c]):
            raise ParameterError(f"twist_of[{c}] = {p}: expected another, deforming bone that is not itself a twist "
                                 f"bone (bone {c} must deform too)")
        if np.linalg.norm(np.asarray(tails[p]) - np.asarray(heads[c])) > 1e-3 * scale:
            raise ParameterError(f"twist_of[{c}] = {p}: bone {p}'s tail is {np.asarray(tails[p]).tolist()}, bone {c}'s "
                                 f"head {np.asarray(heads[c]).tolist()}; a twist bone must start where the bone it "
                                 f"twists ends")
    return tw.astype(np.int64)


def twist_share(points: np.ndarray, head: np.ndarray, joint: np.ndarray, tail: np.ndarray) -> np.ndarray:
    """(P,) the twist bone's share of a (bone, twist bone) pair's weight at points (P, 3).

    head: the bone's head, joint: its tail = the twist bone's head, tail: the twist bone's
    tail (3,). With u a point's position along head → tail (0 at head, 1 at tail) and u_j the
    joint's, the share is ``clip((u - u_j) / (1 - u_j), 0, 1)``: nothing along the bone, all
    at the twist bone's tail, so the twist grows along the limb.
    """
    seg = np.asarray(tail, dtype=float) - head
    dd = float(seg @ seg) or 1.0
    u = (np.asarray(points, dtype=float) - head) @ seg / dd
    u_joint = float((np.asarray(joint, dtype=float) - head) @ seg / dd)
    return np.clip((u - u_joint) / max(1.0 - u_joint, 1e-12), 0.0, 1.0)


def _solve_columns(solver: FactorizedSolver, rhs: np.ndarray, lanes: int | None) -> np.ndarray:
    """``A X = rhs`` (n, K) with the one factor; two lanes take whole groups of nine columns
    each (the factor's compiled solve works in groups of nine and releases the GIL)."""
    n, K = rhs.shape
    if lanes is None:
        lanes = 2 if n * K >= 100_000 else 1
    if lanes == 1 or K <= 9:
        return solver.solve(rhs)
    m = -(-(K // 2) // 9) * 9
    a, b = run_both(lambda: solver.solve(rhs[:, :m]), lambda: solver.solve(rhs[:, m:]))
    return np.hstack([a, b])


def _nearest_bones(points: np.ndarray, heads: np.ndarray, tails: np.ndarray, bones: np.ndarray) -> np.ndarray:
    """(P,) the nearest of ``bones`` to each point (no visibility)."""
    d = heads[bones][None] - points[:, None]                     # (P, K, 3)
    seg = (tails - heads)[bones]
    dd = np.maximum((seg * seg).sum(-1), 1e-300)
    s = np.clip(-(d * seg[None]).sum(-1) / dd, 0.0, 1.0)
    dist = np.linalg.norm(d + s[..., None] * seg[None], axis=-1)
    return bones[np.argmin(dist, axis=1)]
