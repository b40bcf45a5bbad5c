"""Plane–mesh cross-sections and the tape-measure girth of one contour.

A girth is read the way a tape measure reads it: the tape bridges every concavity, so its
length is the perimeter of the convex hull of the cross-section contour (Rupprecht et al. and
ISO 8559-1 both measure girths with a tape). This module does it for a whole batch of bodies
and one plane per body at once:

1. ``edge_crossings``: every mesh edge whose endpoints lie on different sides of the plane,
   with its intersection point. A vertex exactly on the plane counts as the positive side, so
   every triangle is crossed by exactly 0 or 2 of its edges and the segments always chain.
2. ``slice_contours``: each crossed triangle links its two crossed edges; the connected
   components of that graph (``scipy.sparse.csgraph``, one call for the whole batch) are the
   contours: one ring per limb or torso that the plane cuts.
3. ``pick_contours``: per body, the contour that *contains* the landmark's projection on the
   plane (even–odd ray test, vectorized over all segments), else the nearest one. So a thigh
   plane that also cuts the other leg and a hand keeps only the thigh.
4. ``hull_perimeter``: perimeter of the 2-D convex hull (Qhull; Andrew's monotone chain for
   degenerate input); ``hull_perimeters`` does all chosen contours of a batch at once.

``band_contours`` is the fast path ``evaluate`` uses: every plane of a band (or the one plane
of a slice) for every body in one ``Contours`` (group = plane * N + body). It drops the edges
that cannot cross any plane in any body from approximate heights, finds which planes an edge
crosses from its ends' ranks among the sorted plane offsets, and links the two crossings of a
triangle through the face's third vertex instead of a sort. The points, their order within a
group, the segments and the contours are the same as ``slice_band``'s, so every value is too.

``part_girths`` is the compiled path of a girth round one body part (``part_sections``, then
the band's choice by ``support_perimeters`` and the hull of ``contour_girths``): one pass a body,
the same arithmetic, no Python per plane.

Arrays: vertices (N, V, 3), faces (F, 3), plane origins and normals (N, 3).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numba
import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components
from scipy.spatial import ConvexHull, QhullError


def mesh_edges(faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unique undirected edges (E, 2) and the two faces beside each (E, 2) (-1 on a border).

    A non-manifold edge (three or more faces) keeps two of them; body meshes have none.
    """
    faces = np.asarray(faces)
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    edges, inverse = np.unique(np.sort(e, axis=1), axis=0, return_inverse=True)
    inverse = inverse.ravel()
    face_of = np.tile(np.arange(len(faces)), 3)
    order = np.argsort(inverse, kind="stable")
    inv_sorted = inverse[order]
    first = np.searchsorted(inv_sorted, np.arange(len(edges)), side="left")
    count = np.bincount(inverse, minlength=len(edges))
    edge_faces = np.full((len(edges), 2), -1, dtype=np.int64)
    edge_faces[:, 0] = face_of[order[first]]
    two = count >= 2
    edge_faces[two, 1] = face_of[order[first[two] + 1]]
    return edges, edge_faces


def plane_basis(normals: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors (N, 3), (N, 3) spanning the planes of unit ``normals`` (N, 3).

    The first in-plane axis is the world axis least aligned with the normal, orthogonalized,
    so a horizontal plane gets (x, z) axes and the choice is stable across poses.
    """
    n = np.asarray(normals, dtype=float)
    eye = np.eye(3)
    helper = eye[np.argmin(np.abs(n), axis=-1)]
    u = helper - np.sum(helper * n, axis=-1, keepdims=True) * n
    u /= np.linalg.norm(u, axis=-1, keepdims=True)
    w = np.cross(n, u)
    return u, w


@dataclass
class Contours:
    """Cross-sections of a batch of bodies, one plane per body.

    points: (K, 3) intersection points (one per crossed edge, all bodies).
    body: (K,) body index of each point.
    label: (K,) contour id (global over the batch; contours never span two bodies).
    seg: (S, 2) point indices of the segments (one per crossed triangle).
    n_labels: number of contours.
    """

    points: np.ndarray
    body: np.ndarray
    label: np.ndarray
    seg: np.ndarray
    n_labels: int


def slice_contours(vertices: np.ndarray, edges: np.ndarray, edge_faces: np.ndarray,
                   origins: np.ndarray, normals: np.ndarray) -> Contours:
    """Cut bodies (N, V, 3) by planes through ``origins`` (N, 3) with unit ``normals`` (N, 3).

    ``edges`` (E, 2), ``edge_faces`` (E, 2) from ``mesh_edges`` (the faces on either side of
    each edge, -1 on a border). Returns every contour of every body as a ``Contours`` (empty
    arrays where a plane misses a body).
    """
    return slice_band(vertices, edges, edge_faces, np.asarray(origins)[None], normals)[0]


def slice_band(vertices: np.ndarray, edges: np.ndarray, edge_faces: np.ndarray,
               origins: np.ndarray, normals: np.ndarray, heights: np.ndarray | None = None) -> list[Contours]:
    """Cut bodies (N, V, 3) by P parallel planes each: ``origins`` (P, N, 3), ``normals`` (N, 3).

    Returns one ``Contours`` per plane (``band_contours`` gives one for the whole band, faster).
    """
    x = _band_crossings(vertices, edges, origins, normals, heights)
    n_faces = int(edge_faces.max()) + 1
    order = np.argsort(x.plane, kind="stable")
    starts = np.searchsorted(x.plane[order], np.arange(len(origins) + 1))
    return [_assemble(x.points[i], x.body[i], x.edge[i], edge_faces, n_faces)
            for i in (order[s:t] for s, t in zip(starts[:-1], starts[1:]))]


def band_contours(vertices: np.ndarray, edges: np.ndarray, edge_faces: np.ndarray,
                  origins: np.ndarray, normals: np.ndarray, heights: np.ndarray | None = None,
                  neighbours: tuple | None = None) -> Contours:
    """All contours of P parallel planes per body in one ``Contours``: ``origins`` (P, N, 3).

    Its ``body`` is the group p * N + i (plane p, body i), so the per-body functions
    (``pick_contours``, ``support_perimeters``, ``contour_girths``) run on every plane of the
    band at once with (P * N, ...) arguments. Within a group the points are in edge order, as
    in ``slice_band``, so every per-group result is the same. ``heights`` (N, V) float32 may
    pass ``vertex_heights(vertices, normals)`` when several bands share a normal;
    ``neighbours`` = ``edge_neighbours(faces, edges, edge_faces)`` links the crossings without
    a sort.
    """
    x = _band_crossings(vertices, edges, origins, normals, heights)
    group = x.plane * len(vertices) + x.body
    if neighbours is None:
        return _assemble(x.points, group, x.edge, edge_faces, int(edge_faces.max()) + 1)
    # Each crossed triangle holds exactly two crossings: the second is on the edge from the
    # crossed edge's end that is on the other side than the triangle's third vertex.
    opp, other_a, other_b = neighbours
    k = len(x.points)
    side_a = x.h_a >= x.off                                                    # on or above: "above"
    n_local = x.hv.shape[1]
    partner = np.full((k, 2), -1, dtype=np.int64)
    for s in range(2):
        o = opp[x.edge, s]
        ok = o >= 0
        # c is on a crossed edge of the crossed face, so it is a candidate vertex.
        side_c = x.hv.ravel()[x.body[ok] * n_local + x.local[o[ok]]] >= x.off[ok]
        # Third vertex on a's side: the b-c edge is crossed, else the a-c edge.
        pe = np.where(side_c == side_a[ok], other_b[x.edge[ok], s], other_a[x.edge[ok], s])
        ok[ok] = pe >= 0
        pe = pe[pe >= 0]
        cell = x.body[ok] * x.n_cand + x.cand_of[pe]
        partner[ok, s] = x.first[cell] + x.rank[x.plane[ok], x.body[ok]] - x.start[cell]
    me = np.arange(k)
    seg = np.concatenate([np.stack([me[partner[:, s] > me], partner[partner[:, s] > me, s]], axis=1)
                          for s in range(2)])
    if k == 0:
        return Contours(x.points, group, np.zeros(0, dtype=np.int64), seg, 0)
    graph = sp.coo_matrix((np.ones(len(seg)), (seg[:, 0], seg[:, 1])), shape=(k, k))
    n_labels, label = connected_components(graph, directed=False)
    return Contours(x.points, group, label.astype(np.int64), seg, int(n_labels))


def part_sections(vertices: np.ndarray, edges: np.ndarray, origins: np.ndarray, normals: np.ndarray,
                  heights: HeightBounds | None = None) -> tuple[Contours, np.ndarray]:
    """The cross-section of one body part by P parallel planes per body: ``origins`` (P, N, 3),
    unit ``normals`` (N, 3), ``edges`` (E', 2) the part's edges (both ends on the part).

    Every crossing of a plane with the part is one contour (label = group = p * N + i), so the
    tape goes round the whole part however its border cuts the ring (the armpit of a chest
    plane opens the torso's ring: the tape bridges it, as ``contour_girths``' hull does), and
    nothing of another part (an arm against the chest, the other thigh) ever enters it. No
    linking of crossings is needed: the same ``_band_crossings`` pass, on fewer edges. Returns
    the Contours and the edge (into ``edges``) of each crossing (K,).
    """
    x = _band_crossings(vertices, edges, origins, normals, heights)
    group = x.plane * len(vertices) + x.body
    return (Contours(x.points, group, group, np.zeros((0, 2), dtype=np.int64), len(origins) * len(vertices)),
            x.edge)


def edge_neighbours(faces: np.ndarray, edges: np.ndarray, edge_faces: np.ndarray):
    """Per edge (a, b) and each of its two faces (E, 2): the face's third vertex c and the edge
    ids of a-c and b-c, for ``band_contours``. -1 on a border, on a degenerate face and where
    that edge does not list the face among its two (non-manifold), as ``mesh_edges`` pairs them.
    """
    faces = np.asarray(faces)
    nv = int(faces.max()) + 1
    keys = edges[:, 0].astype(np.int64) * nv + edges[:, 1]                   # sorted (np.unique)

    def edge_id(p, q, f):
        lo, hi = np.minimum(p, q), np.maximum(p, q)
        i = np.minimum(np.searchsorted(keys, lo.astype(np.int64) * nv + hi), len(keys) - 1)
        ok = (keys[i] == lo.astype(np.int64) * nv + hi) & ((edge_faces[i] == f[:, None]).any(axis=1))
        return np.where(ok, i, -1)

    opp = np.full(edge_faces.shape, -1, dtype=np.int64)
    other_a, other_b = opp.copy(), opp.copy()
    for s in range(2):
        ok = edge_faces[:, s] >= 0
        f_id = edge_faces[ok, s]
        f = faces[f_id]                                                        # (M, 3)
        a, b = edges[ok, 0], edges[ok, 1]
        c = f.sum(axis=1) - a - b                                              # the third vertex
        good = (c != a) & (c != b) & (a != b)
        opp[ok, s] = np.where(good, c, -1)
        other_a[ok, s] = np.where(good, edge_id(a, c, f_id), -1)
        other_b[ok, s] = np.where(good, edge_id(b, c, f_id), -1)
    return opp, other_a, other_b


@dataclass
class _Crossings:
    points: np.ndarray     # (K, 3) float64
    plane: np.ndarray      # (K,)
    body: np.ndarray       # (K,)
    edge: np.ndarray       # (K,)
    h_a: np.ndarray        # (K,) float32 height of the edge's first vertex
    off: np.ndarray        # (K,) float32 plane offset
    hv: np.ndarray         # (N, Vc) float32 heights of the candidate edges' vertices
    local: np.ndarray      # (V,) column of a vertex in ``hv``
    n_cand: int            # candidate edges C
    cand_of: np.ndarray    # (E,) candidate index of an edge (-1: none)
    first: np.ndarray      # (N * C,) index of the first crossing of (body, candidate)
    start: np.ndarray      # (N * C,) its rank among the body's sorted plane offsets
    rank: np.ndarray       # (P, N) rank of each plane among the body's offsets


def _band_crossings(vertices, edges, origins, normals, heights) -> _Crossings:
    """Every crossing of P parallel planes per body, sorted by body, then edge (then plane).

    Parallel planes differ only by their offset along the normal, so the signed heights and
    the edges' height intervals are computed once for the whole band.
    """
    v = np.asarray(vertices, dtype=float)
    n = np.asarray(normals, dtype=float)
    if heights is None:
        heights = HeightBounds(vertex_heights(v, n), 0.0)
    offs = plane_offsets(origins, n)  # (P, N)
    n_planes = len(offs)
    o_lo, o_hi = offs.min(axis=0)[:, None], offs.max(axis=0)[:, None]
    # A vertex exactly on the plane counts as above it: edge crosses iff lo < off <= hi. An edge
    # whose two ends are below every plane (or at/above every plane) in every body of the batch
    # crosses nothing: two cheap (N, V) passes drop them, and the interval passes below run on
    # the edges left (a superset of the crossings, in edge order, so nothing else changes).
    t_lo, t_hi = o_lo, o_hi
    if heights.tol > 0:             # thresholds rounded outwards, so the margin stays >= tol
        t_lo = np.nextafter((o_lo.astype(float) - heights.tol).astype(np.float32), np.float32(-np.inf))
        t_hi = np.nextafter((o_hi.astype(float) + heights.tol).astype(np.float32), np.float32(np.inf))
    below, above = (heights.h < t_lo).all(axis=0), (heights.h >= t_hi).all(axis=0)
    ea, eb = edges[:, 0], edges[:, 1]
    cand = np.flatnonzero(~((below[ea] & below[eb]) | (above[ea] & above[eb])))
    n_cand = len(cand)
    nv = v.shape[1]
    # Each vertex's slot: how many of its body's planes are at or below it. An edge crosses
    # exactly the planes between its two ends' slots (those with lo < off <= hi), so the P
    # comparisons run once per vertex of the candidate edges, not per edge.
    used = np.zeros(nv, dtype=bool)
    used[ea[cand]] = used[eb[cand]] = True
    cv = np.flatnonzero(used)
    local = np.zeros(nv, dtype=np.int64)
    local[cv] = np.arange(len(cv))
    # Exact heights (``vertex_heights``' values: einsum row by row) on those vertices only.
    hv = heights.h[:, cv] if heights.tol == 0 else vertex_heights(v[:, cv], n)  # (N, Vc)
    order = np.argsort(offs, axis=0, kind="stable")                            # (P, N)
    srt = np.take_along_axis(offs, order, axis=0)
    rank = np.empty_like(order)
    np.put_along_axis(rank, order, np.arange(n_planes)[:, None], axis=0)
    slot = np.zeros(hv.shape, np.int8 if n_planes < 127 else np.int64)
    for q in range(n_planes):
        slot += srt[q][:, None] <= hv
    sa, sb = slot[:, local[ea[cand]]], slot[:, local[eb[cand]]]                # (N, C)
    start = np.minimum(sa, sb).ravel()
    cnt = np.abs(sa.astype(np.int64) - sb).ravel() if n_planes >= 127 else np.abs(sa - sb).ravel()
    cell = np.flatnonzero(cnt)                                                 # (body, candidate)
    c = cnt[cell].astype(np.int64)
    first_of_cell = np.cumsum(c) - c
    if len(c) and c.max() > 1:
        rep = np.repeat(np.arange(len(cell)), c)
        pos = np.arange(len(rep)) - first_of_cell[rep] + start[cell][rep]
        fl = cell[rep]
    else:
        pos, fl = start[cell].astype(np.int64), cell
    b, j = fl // n_cand, fl % n_cand
    p = order[pos, b]
    e = cand[j]
    off = offs[p, b]
    hflat = hv.ravel()
    h_a, h_b = hflat[b * len(cv) + local[ea[e]]], hflat[b * len(cv) + local[eb[e]]]
    va_, vb_ = b * nv + ea[e], b * nv + eb[e]
    da = h_a.astype(float) - off
    db = h_b.astype(float) - off
    t = (da / (da - db))[:, None]                                              # signs differ: no 0/0
    flat_v = v.reshape(-1, 3)
    pa, pb = np.take(flat_v, va_, axis=0), np.take(flat_v, vb_, axis=0)
    first = np.zeros(len(cnt), dtype=np.int64)
    first[cell] = first_of_cell
    cand_of = np.full(len(edges), -1, dtype=np.int64)
    cand_of[cand] = np.arange(n_cand)
    return _Crossings(pa + t * (pb - pa), p, b, e, h_a, off, hv, local, n_cand, cand_of, first,
                      start.astype(np.int64), rank)


@dataclass
class HeightBounds:
    """Vertex heights ``h`` (N, V) float32 within ``tol`` of ``vertex_heights`` (exact if 0).

    Only used to rule out edges that cannot cross (with ``tol`` to spare); the crossings
    themselves always use the exact heights.
    """

    h: np.ndarray
    tol: float


def approx_heights(planes: tuple, normals: np.ndarray, scale: float) -> HeightBounds:
    """Float32 heights from the coordinate planes ``planes`` = (x, y, z), each (N, V) float32,
    of bodies whose coordinates satisfy |x| + |y| + |z| <= ``scale``: 3x cheaper than the exact
    einsum, within 2^-18 * scale of it (float32 rounding is below 2^-21 * scale here)."""
    n = np.asarray(normals, dtype=np.float32)
    x, y, z = planes
    h = x * n[:, :1]
    h += y * n[:, 1:2]
    h += z * n[:, 2:]
    return HeightBounds(h, float(2.0 ** -18 * scale))


def plane_offsets(origins: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """The offsets (P, N) of planes through ``origins`` (P, N, 3) along unit ``normals`` (N, 3), in
    float32 as every slicer compares them with the float32 vertex heights."""
    n = np.asarray(normals, dtype=float)
    return np.einsum("pni,ni->pn", np.asarray(origins, dtype=float), n).astype(np.float32)


def vertex_heights(vertices: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """Signed heights (N, V) of the vertices along unit ``normals`` (N, 3), in float32.

    Float32 (0.1 um at 1 m): the passes over the heights are memory-bound and this halves them;
    the crossing points themselves are interpolated in float64.
    """
    return np.einsum("nvi,ni->nv", np.asarray(vertices, dtype=float),
                     np.asarray(normals, dtype=float)).astype(np.float32)


def _assemble(points: np.ndarray, b: np.ndarray, e: np.ndarray, edge_faces: np.ndarray,
              n_faces: int) -> Contours:
    """Link crossings (K,) into segments and contours (see ``Contours``)."""
    # Each crossed triangle holds exactly two crossings: sort the (body, face) keys of both
    # faces of every crossed edge and neighbours with equal keys form the segments. O(K log K)
    # in the crossings, never touching the uncrossed (N, F) bulk.
    f2 = edge_faces[e]                                                         # (K, 2), -1 on a border
    key = np.where(f2 >= 0, b[:, None].astype(np.int64) * n_faces + f2, -1).ravel()
    pt = np.repeat(np.arange(len(b)), 2)
    ok = key >= 0
    key, pt = key[ok], pt[ok]
    order = np.argsort(key, kind="stable")
    key, pt = key[order], pt[order]
    pairs = np.flatnonzero(key[1:] == key[:-1])
    seg = np.stack([pt[pairs], pt[pairs + 1]], axis=1)
    k = len(points)
    if k == 0:
        return Contours(points, b, np.zeros(0, dtype=np.int64), seg, 0)
    graph = sp.coo_matrix((np.ones(len(seg)), (seg[:, 0], seg[:, 1])), shape=(k, k))
    n_labels, label = connected_components(graph, directed=False)
    return Contours(points, b, label.astype(np.int64), seg, int(n_labels))


def pick_contours(c: Contours, points: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """Per body, the contour id that contains ``points`` (N, 3) projected on its plane, else the nearest.

    Containment is the even–odd rule along a ray in the plane (its first basis axis), counted
    over all segments at once; nested contours (the rare inner shell) resolve to the one with
    the nearest point. Returns (N,) contour ids, -1 where the plane cut nothing.
    """
    n_bodies = len(points)
    out = np.full(n_bodies, -1, dtype=np.int64)
    if c.n_labels == 0:
        return out
    u, w = plane_basis(normals)
    rel = c.points - points[c.body]
    pu = np.einsum("ki,ki->k", rel, u[c.body])
    pw = np.einsum("ki,ki->k", rel, w[c.body])
    s0, s1 = c.seg[:, 0], c.seg[:, 1]
    straddle = (pw[s0] > 0) != (pw[s1] > 0)
    with np.errstate(divide="ignore", invalid="ignore"):
        x_cross = pu[s0] + (0.0 - pw[s0]) * (pu[s1] - pu[s0]) / (pw[s1] - pw[s0])
    hits = straddle & (x_cross > 0)
    parity = np.bincount(c.label[s0[hits]], minlength=c.n_labels) % 2
    # Nearest distance from the landmark to each contour (in the plane).
    dist = np.hypot(pu, pw)
    near = np.full(c.n_labels, np.inf)
    np.minimum.at(near, c.label, dist)
    comp_body = np.empty(c.n_labels, dtype=np.int64)
    comp_body[c.label] = c.body
    # Rank: containing contours first, then by distance; the first per body wins.
    order = np.lexsort((near, 1 - parity, comp_body))
    first = np.ones(len(order), dtype=bool)
    first[1:] = comp_body[order][1:] != comp_body[order][:-1]
    out[comp_body[order[first]]] = order[first]
    return out


def convex_hull_2d(xy: np.ndarray) -> np.ndarray:
    """Indices of the convex hull of points (K, 2), counter-clockwise (Andrew's monotone chain)."""
    xy = np.asarray(xy, dtype=float)
    if len(xy) < 3:
        return np.arange(len(xy))
    order = np.lexsort((xy[:, 1], xy[:, 0]))
    p = xy[order].tolist()

    def half(seq):
        h: list[int] = []
        for i in seq:
            while len(h) >= 2:
                (ax, ay), (bx, by), (cx, cy) = p[h[-2]], p[h[-1]], p[i]
                if (bx - ax) * (cy - ay) - (by - ay) * (cx - ax) > 0:
                    break
                h.pop()
            h.append(i)
        return h

    lower = half(range(len(p)))
    upper = half(range(len(p) - 1, -1, -1))
    return order[np.array(lower[:-1] + upper[:-1])]


def hull_perimeter(xy: np.ndarray) -> tuple[float, np.ndarray]:
    """Tape length of points (K, 2): perimeter of their convex hull, and the hull indices (H,).

    Qhull (C) is ~10x faster than the Python monotone chain on contours of a few hundred
    points; the chain remains for the degenerate inputs Qhull rejects (collinear, < 3 points).
    """
    try:
        idx = ConvexHull(xy).vertices          # counter-clockwise in 2-D
    except (QhullError, ValueError):
        idx = convex_hull_2d(xy)
    if len(idx) < 2:
        return 0.0, idx
    h = xy[idx]
    return float(np.linalg.norm(h - np.roll(h, -1, axis=0), axis=1).sum()), idx


def hull_perimeters(xy: np.ndarray, starts: np.ndarray, max_rounds: int = 64) -> np.ndarray:
    """Convex-hull perimeters (G,) of G point groups at once: ``xy`` (K, 2), group g is
    ``xy[starts[g]:starts[g + 1]]``. NaN where a group needs ``hull_perimeter`` (fewer than
    four points, degenerate, or not settled in ``max_rounds``).

    Vectorized over all groups (no per-contour call): sort each group by angle around its
    centroid (strictly inside the hull), then repeatedly drop every point that does not turn
    left between its neighbours (it lies in the triangle centroid-prev-next, so it is not a
    hull vertex); what remains is the hull in counter-clockwise order. Same hull as Qhull, so
    the same perimeter up to rounding (1e-16 relative).
    """
    k = len(xy)
    n_groups = len(starts)
    out = np.full(n_groups, np.nan)
    if k == 0:
        return out
    size = np.diff(np.r_[starts, k])
    g = np.repeat(np.arange(n_groups), size)
    c = np.add.reduceat(xy, starts, axis=0) / size[:, None]
    r = xy - c[g]
    ang = np.arctan2(r[:, 1], r[:, 0])
    rad = np.einsum("ki,ki->k", r, r)
    order = np.lexsort((-rad, ang, g))
    g, r, ang = g[order], r[order], ang[order]
    # Points on one ray from the centroid: only the farthest can be a hull vertex (this also
    # drops duplicates).
    keep = np.r_[True, (g[1:] != g[:-1]) | (ang[1:] != ang[:-1])]
    g, r = g[keep], r[keep]
    settled = False
    for _ in range(max_rounds):
        first = np.r_[True, g[1:] != g[:-1]]
        last = np.r_[first[1:], True]
        idx = np.arange(len(g))
        grp_start = np.maximum.accumulate(np.where(first, idx, 0))
        nxt = np.where(last, 0, idx + 1)
        nxt[last] = grp_start[last]
        prv = np.where(first, 0, idx - 1)
        grp_end = np.flatnonzero(last)
        prv[first] = grp_end
        a, b = r[prv], r[nxt]
        turn = (r[:, 0] - a[:, 0]) * (b[:, 1] - r[:, 1]) - (r[:, 1] - a[:, 1]) * (b[:, 0] - r[:, 0])
        wedge = a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]
        drop = (turn <= 0) & (wedge > 0)
        if not drop.any():
            settled = True
            break
        g, r = g[~drop], r[~drop]
    if not settled:
        return out
    ok = np.ones(n_groups, dtype=bool)
    ok[size < 4] = False
    cnt = np.bincount(g, minlength=n_groups)
    ok[cnt < 3] = False
    ok[g[(turn <= 0) | (wedge <= 0)]] = False                                 # not a convex fan
    d = b - r
    length = np.sqrt(d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1])
    per = np.bincount(g, weights=length, minlength=n_groups)
    out[ok] = per[ok]
    return out


def _chosen_in_plane(c: Contours, chosen: np.ndarray, normals: np.ndarray):
    """Points of each body's chosen contour, grouped by body, in their plane's (u, w) basis.

    Returns (sel (K,) point indices into ``c.points``, bodies (K,) sorted, x (K,), y (K,)).
    """
    u, w = plane_basis(normals)
    comp_is_chosen = np.zeros(c.n_labels, dtype=bool)
    comp_is_chosen[chosen[chosen >= 0]] = True
    sel = np.flatnonzero(comp_is_chosen[c.label])
    sel = sel[np.argsort(c.body[sel], kind="stable")]
    bodies = c.body[sel]
    return (sel, bodies, np.einsum("ki,ki->k", c.points[sel], u[bodies]),
            np.einsum("ki,ki->k", c.points[sel], w[bodies]))


def support_perimeters(c: Contours, chosen: np.ndarray, normals: np.ndarray, n_dirs: int = 48) -> np.ndarray:
    """Fast estimate (N,) of the chosen contours' hull perimeters (NaN where none).

    Cauchy's formula: a convex curve's perimeter is the integral of its support function
    h(theta) = max_p p.u(theta) over the circle; sampled at ``n_dirs`` directions it is within
    ~0.1 % for body sections, all bodies in one reduction. Used to pick the extreme plane of a
    band; the reported girth is the exact hull of that plane.
    """
    out = np.full(len(chosen), np.nan)
    if c.n_labels == 0:
        return out
    sel, bodies, x, y = _chosen_in_plane(c, chosen, normals)
    if not len(sel):
        return out
    th = np.linspace(0.0, 2 * np.pi, n_dirs, endpoint=False)
    cos, sin = np.cos(th), np.sin(th)
    starts = np.flatnonzero(np.r_[True, bodies[1:] != bodies[:-1]])
    # One direction at a time: (K,) temporaries stay in cache where a (K, n_dirs) one does not.
    h = np.empty((len(starts), n_dirs))
    for d in range(n_dirs):
        h[:, d] = np.maximum.reduceat(x * cos[d] + y * sin[d], starts)
    out[bodies[starts]] = h.sum(axis=1) * (2 * np.pi / n_dirs)
    return out


def contour_girths(c: Contours, chosen: np.ndarray, normals: np.ndarray,
                   keep_polylines: bool = False) -> tuple[np.ndarray, list]:
    """Convex-hull perimeters (N,) of the chosen contour of each body (NaN where none).

    With ``keep_polylines`` also the hull as a closed 3-D polyline (H+1, 3) per body (else None).
    """
    n_bodies = len(chosen)
    girth = np.full(n_bodies, np.nan)
    lines: list = [None] * n_bodies
    if c.n_labels == 0:
        return girth, lines
    sel, bodies, x, y = _chosen_in_plane(c, chosen, normals)
    if not len(sel):
        return girth, lines
    xy = np.stack([x, y], axis=1)
    starts = np.flatnonzero(np.r_[True, bodies[1:] != bodies[:-1]])
    ends = np.r_[starts[1:], len(sel)]
    if not keep_polylines:
        # All hulls at once; the rare group the batched hull leaves (NaN) goes to Qhull below.
        fast = hull_perimeters(xy, starts)
        girth[bodies[starts]] = fast
        todo = np.flatnonzero(np.isnan(fast))
        starts, ends = starts[todo], ends[todo]
    for s, e in zip(starts, ends):
        i = bodies[s]
        girth[i], idx = hull_perimeter(xy[s:e])
        if keep_polylines:
            pts = c.points[sel[s:e]][idx]
            lines[i] = np.concatenate([pts, pts[:1]])
    return girth, lines


# --- the compiled part-girth slicer ---------------------------------------------------------
# ``part_girths`` gives, per body, what ``methods.slice_girth`` computes from ``part_sections``,
# ``support_perimeters`` and ``contour_girths`` for a girth round one body part (the default set's
# every girth), in one compiled pass a body: no Python and no (K,) temporaries per plane. The
# arithmetic is the numpy path's, operation for operation (float32 heights and offsets, the
# crossing interpolated in float64, the in-plane coordinates as ``einsum`` sums them, the support
# function's pairwise sum), so the band picks the same plane and the girth is the same hull's
# perimeter (to rounding, ~1e-16 relative).

_N_DIRS = 48     # ``support_perimeters``' directions
# Crossings a body's planes may add off the part (``_ring_runs``): a neck band's runs over the
# jaw and shoulders are a few hundred; a plane beyond this stays "opened" (left out of a min).
_RUN_POINTS = 8192


@dataclass
class PartMesh:
    """A body part's edges for ``part_girths``: its vertices (Vp,) (ids into the mesh), the edges
    as local indices into them ``ea``, ``eb`` (E',) (in ``part_edges`` order, the first end
    first), and ``border`` (E',) bool (the edge lies on the part's border).

    With the mesh (``part_mesh``'s ``faces``), how far a plane leaves the part is measured along
    the other parts' faces: ``gid`` (E',) the part edges' ids in the mesh's edges ``edges``
    (E, 2), ``edge_faces`` (E, 2) (-1: none), ``face_edges`` (F, 3), ``face_on`` (F,) bool (all
    three corners on the part), ``edge_on`` (E,) bool (both ends on the part). Without it (empty
    arrays) any crossing of the border opens a plane."""

    vertices: np.ndarray
    ea: np.ndarray
    eb: np.ndarray
    border: np.ndarray
    gid: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    edges: np.ndarray = field(default_factory=lambda: np.zeros((0, 2), dtype=np.int64))
    edge_faces: np.ndarray = field(default_factory=lambda: np.zeros((0, 2), dtype=np.int64))
    face_edges: np.ndarray = field(default_factory=lambda: np.zeros((0, 3), dtype=np.int64))
    face_on: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.bool_))
    edge_on: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.bool_))


def face_edge_ids(faces: np.ndarray, edges: np.ndarray) -> np.ndarray:
    """Each face's three edges (F, 3) as ids into ``mesh_edges``' sorted unique ``edges`` (E, 2):
    the edges (0, 1), (1, 2), (2, 0) of the face."""
    faces = np.asarray(faces, dtype=np.int64)
    nv = int(max(faces.max(), edges.max())) + 1
    keys = edges[:, 0].astype(np.int64) * nv + edges[:, 1]
    out = np.empty(faces.shape, dtype=np.int64)
    for k, (a, b) in enumerate(((0, 1), (1, 2), (2, 0))):
        lo, hi = np.minimum(faces[:, a], faces[:, b]), np.maximum(faces[:, a], faces[:, b])
        out[:, k] = np.searchsorted(keys, lo * nv + hi)
    return out


def part_mesh(edges: np.ndarray, border: np.ndarray, mesh: dict | None = None) -> PartMesh:
    """``PartMesh`` of a part's edges (E', 2) and their border flags (E',) (``Topology.part_edges``);
    ``mesh``: the whole mesh's ``faces`` (F, 3), ``edges`` (E, 2), ``edge_faces`` (E, 2),
    ``face_edges`` (F, 3) (``face_edge_ids``), ``gid`` (E',) and the part's vertex flags ``on``
    (V,) bool, so that a min band follows a plane's ring off the part (``ring_runs``)."""
    verts, local = np.unique(edges, return_inverse=True)
    local = local.reshape(edges.shape).astype(np.int64)
    pm = PartMesh(verts.astype(np.int64), np.ascontiguousarray(local[:, 0]), np.ascontiguousarray(local[:, 1]),
                  np.ascontiguousarray(border, dtype=np.bool_))
    if mesh is not None:
        on = np.asarray(mesh["on"], dtype=bool)
        pm.gid = np.ascontiguousarray(mesh["gid"], dtype=np.int64)
        pm.edges = np.ascontiguousarray(mesh["edges"], dtype=np.int64)
        pm.edge_faces = np.ascontiguousarray(mesh["edge_faces"], dtype=np.int64)
        pm.face_edges = np.ascontiguousarray(mesh["face_edges"], dtype=np.int64)
        pm.face_on = np.ascontiguousarray(on[np.asarray(mesh["faces"])].all(axis=1))
        pm.edge_on = np.ascontiguousarray(on[pm.edges].all(axis=1))
    return pm


@numba.njit(cache=True, nogil=True)
def _off_run(v, i, n0, n1, n2, off, e, f, edges, edge_faces, face_edges, edge_on, seen, stamp, pts, k):
    """Follow a plane's contour off the part: from the part's border edge ``e`` (a crossed mesh
    edge) into the face ``f`` that has a vertex off the part, face by face along the other parts'
    skin until the contour is back on an edge of the part. Heights and crossings as
    ``_part_girths_kernel``'s (float32 heights, lo < off <= hi, so a crossed face has exactly
    two crossed edges). Appends the crossings off the part to ``pts`` (cap, 3) from row ``k``;
    stamps the faces walked with ``stamp`` in ``seen`` (F,): a face already stamped ends the
    walk (the run was followed from its other end). Returns (True when the contour comes back
    to the part, False where it ends at a hole of the mesh, a degenerate face or the end of
    ``pts``; the new row count)."""
    while True:
        if seen[f] == stamp:
            return True, k
        seen[f] = stamp
        nxt = -1
        ha = hb = np.float32(0.0)
        for j in range(3):
            g = face_edges[f, j]
            if g == e:
                continue
            a, b = edges[g, 0], edges[g, 1]
            ha = np.float32(v[i, a, 0] * n0 + v[i, a, 1] * n1 + v[i, a, 2] * n2)
            hb = np.float32(v[i, b, 0] * n0 + v[i, b, 1] * n1 + v[i, b, 2] * n2)
            if min(ha, hb) < off and off <= max(ha, hb):
                nxt = g
                break
        if nxt < 0:
            return False, k
        if edge_on[nxt]:                                 # back on the part: its own crossing
            return True, k
        if k >= len(pts):
            return False, k
        a, b = edges[nxt, 0], edges[nxt, 1]
        da = np.float64(ha) - np.float64(off)
        t = da / (da - (np.float64(hb) - np.float64(off)))
        for c in range(3):
            pts[k, c] = v[i, a, c] + t * (v[i, b, c] - v[i, a, c])
        k += 1
        e = nxt
        f = edge_faces[e, 1] if edge_faces[e, 0] == f else edge_faces[e, 0]
        if f < 0:                                        # a hole: the ring never closes
            return False, k


@numba.njit(cache=True, nogil=True)
def _ring_runs(v, i, n0, n1, n2, offs_i, bx_p, bx_e, n_bx, gid, edges, edge_faces, face_edges, face_on,
               edge_on, seen, stamp0, pts, run_plane, closed):
    """Every run off the part of body ``i``'s planes (offsets ``offs_i`` (P,)) from its border
    crossings ``bx_p``, ``bx_e`` [:n_bx] (plane, part edge): the points into ``pts`` (cap, 3),
    their plane into ``run_plane`` (cap,); ``closed`` (P,) set False for a plane whose contour
    leaves the part and does not come back. Returns the number of points."""
    k = 0
    for j in range(n_bx):
        p = bx_p[j]
        g = gid[bx_e[j]]
        for s in range(2):
            f = edge_faces[g, s]
            if f < 0:                                    # a hole beside the part's border edge
                closed[p] = False
                continue
            if face_on[f]:
                continue
            k0 = k
            ok, k = _off_run(v, i, n0, n1, n2, offs_i[p], g, f, edges, edge_faces, face_edges, edge_on, seen,
                             stamp0 + p, pts, k)
            for r in range(k0, k):
                run_plane[r] = p
            if not ok:
                closed[p] = False
    return k


def ring_runs(vertices: np.ndarray, part: PartMesh, origins: np.ndarray, normals: np.ndarray):
    """The runs off the part of P parallel planes per body (``origins`` (P, N, 3), unit
    ``normals`` (N, 3)), as ``part_girths`` adds them to a min band's rings: their crossings
    (K, 3), the group p * N + i of each (K,), and ``closed`` (P * N,) bool (every run of the
    plane comes back to the part; a plane without a run is closed)."""
    v = np.ascontiguousarray(vertices, dtype=float)
    n = np.ascontiguousarray(normals, dtype=float)
    offs = plane_offsets(origins, n)  # (P, N)
    n_planes, nb = offs.shape
    closed = np.ones((n_planes, nb), dtype=bool)
    points, groups = [np.zeros((0, 3))], [np.zeros(0, dtype=np.int64)]
    if not len(part.gid):
        return points[0], groups[0], closed.ravel()
    border = np.flatnonzero(part.border)
    seen = np.zeros(len(part.face_on), dtype=np.int64)
    pts = np.empty((_RUN_POINTS, 3))
    run_plane = np.empty(_RUN_POINTS, dtype=np.int64)
    for i in range(nb):
        h = v[i, :, 0] * n[i, 0] + v[i, :, 1] * n[i, 1] + v[i, :, 2] * n[i, 2]   # the kernel's sum, in its order
        ha = h[part.vertices[part.ea[border]]].astype(np.float32)
        hb = h[part.vertices[part.eb[border]]].astype(np.float32)
        lo, hi = np.minimum(ha, hb), np.maximum(ha, hb)
        cross = (lo[None] < offs[:, i, None]) & (offs[:, i, None] <= hi[None])          # (P, B)
        bx_p, bx_j = np.nonzero(cross)
        c = np.ones(n_planes, dtype=np.bool_)
        k = _ring_runs(v, i, n[i, 0], n[i, 1], n[i, 2], np.ascontiguousarray(offs[:, i]), bx_p.astype(np.int64),
                       border[bx_j].astype(np.int64), len(bx_p), part.gid, part.edges, part.edge_faces,
                       part.face_edges, part.face_on, part.edge_on, seen, i * n_planes + 1, pts, run_plane, c)
        closed[:, i] = c
        points.append(pts[:k].copy())
        groups.append(run_plane[:k] * nb + i)
    return np.concatenate(points), np.concatenate(groups), closed.ravel()


MODE_ONE, MODE_MAX, MODE_MIN, MODE_FRONT = 0, 1, 2, 3


def part_girths(vertices: np.ndarray, part: PartMesh, origins: np.ndarray, normals: np.ndarray,
                mode: int, active: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The tape round one body part of each body: ``vertices`` (N, V, 3), P parallel planes a body
    through ``origins`` (P, N, 3) with unit ``normals`` (N, 3); ``mode`` MODE_ONE (P = 1),
    MODE_MAX or MODE_MIN (a band: the plane of largest / smallest support-function estimate).
    For MODE_MIN with the mesh in ``part`` (``part_mesh(..., mesh=)``), a plane that crosses the
    part's border has its ring followed along the other parts' faces back onto the part and
    those crossings join its hull (``ring_runs``); a plane whose ring does not come back (a hole),
    or any plane that crosses the border without the mesh, is chosen only when every plane is.
    ``active`` (N,) bool: the bodies measured (the others get NaN and plane 0).

    Returns girth (N,) (the convex-hull perimeter of the chosen plane's crossings, NaN where it
    has fewer than three), the chosen plane (N,) and ``missed`` (N,) bool (no plane crosses the
    part three times). Same values as ``part_sections`` + ``support_perimeters`` +
    ``contour_girths`` (``methods.slice_girth`` keeps that path for drawn polylines).
    """
    girth, plane, missed, _ = _run_kernel(vertices, part, origins, normals, mode, None, -1, active)
    return girth, plane, missed


def part_fronts(vertices: np.ndarray, part: PartMesh, origins: np.ndarray, normals: np.ndarray,
                forward: np.ndarray, hull_plane: int = -1,
                active: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The front of each of P parallel planes round one body part (``part_girths``' planes and
    crossings): the largest coordinate along unit ``forward`` (N, 3) (in the planes) of the
    plane's crossings with the part, NaN where it has none; no hull but plane ``hull_plane``'s
    (-1: none). ``active`` (N,) bool: the bodies measured.

    Returns fronts (P, N), the girth (N,) of plane ``hull_plane`` (NaN without one) and ``missed``
    (N,) bool (no plane crosses the part three times)."""
    girth, _, missed, fronts = _run_kernel(vertices, part, origins, normals, MODE_FRONT, forward, hull_plane, active)
    return fronts, girth, missed


def _run_kernel(vertices, part, origins, normals, mode, forward, hull_plane, active):
    v = np.ascontiguousarray(vertices, dtype=float)
    n = np.ascontiguousarray(normals, dtype=float)
    offs = plane_offsets(origins, n)  # (P, N)
    u, w = plane_basis(n)
    th = np.linspace(0.0, 2 * np.pi, _N_DIRS, endpoint=False)
    nb = len(v)
    girth, plane, missed = np.full(nb, np.nan), np.zeros(nb, dtype=np.int64), np.zeros(nb, dtype=np.bool_)
    fronts = np.full(offs.shape, np.nan)
    fwd = np.zeros((nb, 3)) if forward is None else np.ascontiguousarray(forward, dtype=float)
    act = np.ones(nb, dtype=np.bool_) if active is None else np.ascontiguousarray(active, dtype=np.bool_)
    _part_girths_kernel(v, part.vertices, part.ea, part.eb, part.border, np.ascontiguousarray(offs), n,
                        np.ascontiguousarray(u), np.ascontiguousarray(w), int(mode), np.cos(th), np.sin(th),
                        2 * np.pi / _N_DIRS, part.gid, part.edges, part.edge_faces, part.face_edges, part.face_on,
                        part.edge_on, fwd, int(hull_plane), act, girth, plane, missed, fronts)
    return girth, plane, missed, fronts


# A fold band (the underbust, docs/measurements.md "Underbust girth"): each gap of the band's
# planes is cut into FOLD_FINE to find where the front stops receding, and the girth is the
# smallest of FOLD_BELOW planes from there down the band's ``below``.
FOLD_FINE = 8
FOLD_BELOW = 4


def fold_coarse(a: np.ndarray, b: np.ndarray, start: float, stop: float, steps: int) -> tuple[np.ndarray, np.ndarray]:
    """A fold band's planes: ``steps`` evenly from ``start`` to ``stop`` of the way from ``a`` to
    ``b`` (N, 3), and one more a step above ``start`` first (a fold just above the band's first
    plane still shows as a steep gap). Returns origins (steps + 1, N, 3) and their fractions
    (steps + 1,); plane 1 is ``a + start (b - a)``."""
    ts = np.linspace(float(start), float(stop), int(steps))
    ts = np.concatenate([[2 * ts[0] - ts[1]], ts])
    return np.stack([a + t * (b - a) for t in ts]), ts


def _steep_run_end(fronts: np.ndarray, offs: np.ndarray, steep: float, last_top: int | None = None,
                   last: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Per body (fronts, offs (P, N)): the first (``last``: the last) gap g (planes g, g + 1) up to
    ``last_top`` (its upper plane's index) whose front falls by more than ``steep`` times the
    planes' distance, and the last gap of the run of such gaps from it (it may go on below
    ``last_top``). Returns found (N,) bool and that last gap (N,) (0 where none)."""
    s = fronts[:-1] - fronts[1:] > steep * np.abs(offs[:-1] - offs[1:])     # NaN fronts: not steep
    g = np.arange(len(s))[:, None]
    top = s & (g <= (len(s) - 1 if last_top is None else last_top))
    found = top.any(axis=0)
    first = len(s) - 1 - np.argmax(top[::-1], axis=0) if last else np.argmax(top, axis=0)
    # The run goes on to the gap before the first gap after it that is not steep (or the last).
    flat = ~s & (g > first)
    end = np.where(flat.any(axis=0), np.argmax(flat, axis=0), len(s)) - 1
    return found, np.where(found, end, 0)


def fold_planes(a: np.ndarray, b: np.ndarray, normals: np.ndarray, origins: np.ndarray, ts: np.ndarray,
                fronts: np.ndarray, steep: float, below: float, fine_fronts) -> tuple[np.ndarray | None, np.ndarray]:
    """Where a fold band measures: ``a``, ``b`` (N, 3) its ends, unit ``normals`` (N, 3), its
    planes' ``origins`` (P, N, 3) and fractions ``ts`` (P,) (``fold_coarse``) and ``fronts`` (P,
    N) their fronts (``part_fronts``). A breast's underside faces down: the front recedes by more than ``steep``
    (metres per metre) from one plane to the next, and where it stops receding (on the chest
    wall) is the inframammary fold. The first such run of gaps is found on the band's planes,
    its last gap and the next are cut ``FOLD_FINE`` times (``fine_fronts(origins (Q, N, 3),
    active (N,) bool) -> (Q, N)``), and the fold is the plane below the last steep fine gap of
    the run. Returns ``FOLD_BELOW`` origins (FOLD_BELOW, N, 3) from the fold down ``below``
    metres along the normal, none above plane 1 (``a + ts[1] (b - a)``), and ``folded`` (N,) bool
    (some of them below plane 1); a body without has every origin on plane 1 (None when no body
    has one)."""
    folded, k1 = _steep_run_end(fronts, plane_offsets(origins, normals).astype(float), steep)
    if not folded.any():
        return None, folded
    # The run's last gap and the one below it, FOLD_FINE planes each (the fold may end just below
    # the last steep gap: the next gap falls less than ``steep`` on the whole).
    j = np.arange(2 * FOLD_FINE + 1)[:, None]
    t_fine = np.minimum(ts[k1][None] + j * ((ts[1] - ts[0]) / FOLD_FINE), ts[-1])            # (Q, N)
    fine = a[None] + t_fine[..., None] * (b - a)[None]
    # The last steep fine gap that starts in the coarse gap (a breast's lower curve may recede
    # steeply too, then less, before its underside), and the run from it.
    ok, end = _steep_run_end(fine_fronts(fine, folded), plane_offsets(fine, normals).astype(float), steep,
                             FOLD_FINE - 1, last=True)
    t_fold = np.take_along_axis(t_fine, np.where(ok, end + 1, FOLD_FINE)[None], axis=0)[0]
    # ``below`` metres as a fraction of the way a -> b along the normal (the band's own scale); no
    # plane above plane 1, and a body whose planes all reach it keeps plane 1 (a fold far above).
    length = np.abs(np.einsum("ni,ni->n", a - b, normals))
    t_win = t_fold[None] + np.linspace(0.0, 1.0, FOLD_BELOW)[:, None] * (below / np.maximum(length, 1e-9))[None]
    folded &= t_win[-1] > ts[1]
    if not folded.any():
        return None, folded
    t_win = np.where(folded[None], np.maximum(t_win, ts[1]), ts[1])
    return a[None] + t_win[..., None] * (b - a)[None], folded




@numba.njit(cache=True, nogil=True, inline="always")
def _hull_push(x, y, hull, m, floor, c):
    """One step of a monotone chain: drop the chain's last points (down to ``floor`` of them) that
    do not turn left before point ``c``, append ``c``; returns the chain's new length."""
    while m > floor:
        a, b = hull[m - 2], hull[m - 1]
        if (x[b] - x[a]) * (y[c] - y[a]) - (y[b] - y[a]) * (x[c] - x[a]) > 0:
            break
        m -= 1
    hull[m] = c
    return m + 1


@numba.njit(cache=True, nogil=True)
def _hull_chain(x, y, k, order, hull):
    """Andrew's monotone chain on points (x[:k], y[:k]): the hull's point indices, counter-
    clockwise, into ``hull``; returns their count (collinear points dropped, as Qhull does)."""
    o = np.argsort(x[:k])
    for i in range(k):
        order[i] = o[i]
    # argsort orders by x only: equal x by y (insertion: the runs of equal x are short).
    for i in range(1, k):
        j = i
        while j > 0:
            a, b = order[j - 1], order[j]
            if x[a] > x[b] or (x[a] == x[b] and y[a] > y[b]):
                order[j - 1], order[j] = b, a
                j -= 1
            else:
                break
    m = 0
    for i in range(k):                                   # lower chain
        m = _hull_push(x, y, hull, m, 1, order[i])
    lower = m
    for i in range(k - 2, -1, -1):                       # upper chain
        m = _hull_push(x, y, hull, m, lower, order[i])
    return m - 1 if k > 1 else m                         # the last point repeats the first


@numba.njit(cache=True, nogil=True)
def _part_girths_kernel(v, verts, ea, eb, border, offs, normal, u, w, mode, cos, sin, step,
                        gid, edges, edge_faces, face_edges, face_on, edge_on, fwd, hull_p, active,
                        girth, plane, missed, fronts):
    """Per active body: float32 heights of the part's vertices, every crossing of every plane (lo <
    off <= hi, as ``_band_crossings``), its in-plane point (MODE_FRONT: and its coordinate along
    ``fwd``, the plane's front the largest), for a min band with the mesh the runs off the part
    (``_ring_runs``), each plane's hull (MODE_FRONT: plane ``hull_p``'s only), the band's choice."""
    n_bodies, n_planes, n_edges, n_dirs = v.shape[0], offs.shape[0], len(ea), len(cos)
    h = np.empty(len(verts), dtype=np.float32)
    walk = len(gid) > 0 and mode == 2
    cap = n_edges + (_RUN_POINTS if walk else 0)      # the part's crossings, then the runs off it
    xs = np.empty((n_planes, cap))
    ys = np.empty((n_planes, cap))
    seen = np.zeros(len(face_on) if walk else 0, dtype=np.int64)
    cnt = np.zeros(n_planes, dtype=np.int64)
    opened = np.zeros(n_planes, dtype=np.bool_)
    per = np.empty(n_planes)
    est = np.empty(n_planes)
    order = np.empty(cap, dtype=np.int64)
    hull = np.empty(cap + 1, dtype=np.int64)
    sup = np.empty(n_dirs)
    n_border = 0
    for e in range(n_edges):
        if border[e]:
            n_border += 1
    bx_p = np.empty(n_border * n_planes + 1, dtype=np.int64)
    bx_e = np.empty(n_border * n_planes + 1, dtype=np.int64)
    closed = np.ones(n_planes, dtype=np.bool_)
    pts = np.empty((_RUN_POINTS if walk else 0, 3))
    run_plane = np.empty(len(pts), dtype=np.int64)
    front = mode == 3
    for i in range(n_bodies):
        if not active[i]:
            continue
        n_bx = 0
        n0, n1, n2 = normal[i, 0], normal[i, 1], normal[i, 2]
        f0, f1, f2 = fwd[i, 0], fwd[i, 1], fwd[i, 2]
        u0, u1, u2 = u[i, 0], u[i, 1], u[i, 2]
        w0, w1, w2 = w[i, 0], w[i, 1], w[i, 2]
        for k in range(len(verts)):
            q = verts[k]
            h[k] = np.float32(v[i, q, 0] * n0 + v[i, q, 1] * n1 + v[i, q, 2] * n2)
        o_lo = offs[0, i]
        o_hi = offs[0, i]
        for p in range(n_planes):
            cnt[p] = 0
            opened[p] = False
            o_lo = min(o_lo, offs[p, i])
            o_hi = max(o_hi, offs[p, i])
        # A band's offsets run one way (its planes are evenly spaced along a segment): an edge
        # then crosses a run of planes found by bisection, not by testing all P (a long band of
        # many planes costs little more than a short one). Any other order tests every plane.
        step_sign = 0
        if n_planes > 2:
            step_sign = 1 if offs[1, i] > offs[0, i] else -1
            for p in range(1, n_planes):
                if (offs[p, i] - offs[p - 1, i]) * step_sign <= 0:
                    step_sign = 0
                    break
        for e in range(n_edges):
            ha, hb = h[ea[e]], h[eb[e]]
            lo, hi = min(ha, hb), max(ha, hb)
            if hi < o_lo or lo >= o_hi:                  # crosses no plane of the band
                continue
            a, b = verts[ea[e]], verts[eb[e]]
            p_from, p_to = 0, n_planes
            if step_sign != 0:
                p_from, p_to = _plane_run(offs, i, n_planes, step_sign, lo, hi)
            for p in range(p_from, p_to):
                off = offs[p, i]
                if lo < off and off <= hi:
                    da = np.float64(ha) - np.float64(off)
                    db = np.float64(hb) - np.float64(off)
                    t = da / (da - db)
                    px = v[i, a, 0] + t * (v[i, b, 0] - v[i, a, 0])
                    py = v[i, a, 1] + t * (v[i, b, 1] - v[i, a, 1])
                    pz = v[i, a, 2] + t * (v[i, b, 2] - v[i, a, 2])
                    c = cnt[p]
                    cnt[p] = c + 1
                    if front:
                        fz = px * f0 + py * f1 + pz * f2
                        if c == 0 or fz > fronts[p, i]:
                            fronts[p, i] = fz
                        if p != hull_p:                  # a front alone: no hull, no ring
                            continue
                    xs[p, c] = px * u0 + py * u1 + pz * u2
                    ys[p, c] = px * w0 + py * w1 + pz * w2
                    if border[e]:
                        opened[p] = True
                        bx_p[n_bx] = p
                        bx_e[n_bx] = e
                        n_bx += 1
        if walk:
            # A min band: a plane that leaves the part goes on round the other parts' skin it
            # meets, joined to the part's ring (the jaw under a short neck, a triangle of the
            # head grazed by the plane): the tape's ring there, so the choice does not hang on
            # whether a plane touches one edge of a triangle with another part's vertex.
            for p in range(n_planes):
                closed[p] = True
            k = _ring_runs(v, i, n0, n1, n2, offs[:, i], bx_p, bx_e, n_bx, gid, edges, edge_faces, face_edges,
                           face_on, edge_on, seen, i * n_planes + 1, pts, run_plane, closed)
            for r in range(k):
                p = run_plane[r]
                c = cnt[p]
                if c >= cap:
                    closed[p] = False
                    continue
                xs[p, c] = pts[r, 0] * u0 + pts[r, 1] * u1 + pts[r, 2] * u2
                ys[p, c] = pts[r, 0] * w0 + pts[r, 1] * w1 + pts[r, 2] * w2
                cnt[p] = c + 1
            for p in range(n_planes):
                if closed[p]:
                    opened[p] = False
        any_whole = False
        for p in range(n_planes):
            if not opened[p]:
                any_whole = True
        run_best = np.inf          # a min band: the smallest estimate so far
        for p in range(n_planes):
            per[p] = np.nan
            est[p] = np.nan
            k = cnt[p]
            if k < 3 or (front and p != hull_p):
                continue
            eligible = mode == 2 and not (any_whole and opened[p])
            if eligible and run_best < np.inf:
                # A plane that cannot be the band's min is not measured: the estimate is at least
                # 0.99857 x the hull's perimeter (48 directions; the worst case is a segment), which
                # is at least the perimeter of the octagon of its extreme points in 8 directions.
                if 0.998 * _octagon_inner(xs[p], ys[p], k) > run_best:
                    continue
            m = _hull_chain(xs[p], ys[p], k, order, hull)
            if m < 2:
                per[p] = 0.0
            else:
                s = 0.0
                for j in range(m):
                    a = hull[j]
                    b = hull[j + 1] if j + 1 < m else hull[0]
                    dx = xs[p, b] - xs[p, a]
                    dy = ys[p, b] - ys[p, a]
                    s += np.sqrt(dx * dx + dy * dy)
                per[p] = s
            if mode == 0 or front:
                continue
            # The support function over the hull's vertices (its maximum over all the points).
            for d in range(n_dirs):
                best = -np.inf
                for j in range(m):
                    a = hull[j]
                    val = xs[p, a] * cos[d] + ys[p, a] * sin[d]
                    if val > best:
                        best = val
                sup[d] = best
            est[p] = _pairwise_sum(sup) * step
            if eligible and est[p] < run_best:
                run_best = est[p]
        missed[i] = True
        for p in range(n_planes):
            if cnt[p] >= 3:
                missed[i] = False
        if mode == 0:
            plane[i] = 0
            girth[i] = per[0]
            continue
        if front:
            plane[i] = hull_p
            if hull_p >= 0:
                girth[i] = per[hull_p]
            continue
        best_p = 0
        best = np.inf if mode == 2 else -np.inf
        for p in range(n_planes):
            e_p = est[p]
            if mode == 2 and any_whole and opened[p]:
                e_p = np.nan
            if np.isnan(e_p):
                e_p = -np.inf if mode == 1 else np.inf
            if (mode == 1 and e_p > best) or (mode == 2 and e_p < best) or p == 0:
                best, best_p = e_p, p
        plane[i] = best_p
        girth[i] = per[best_p]


@numba.njit(cache=True, nogil=True)
def _octagon_inner(x, y, k):
    """The perimeter of the polygon through the extreme points of (x[:k], y[:k]) in the directions
    0, 45, ..., 315 degrees, in that order: inside the hull, so at most the hull's."""
    ix = np.zeros(8, dtype=np.int64)
    val = np.empty(8)
    for j in range(8):
        val[j] = -np.inf
    for q in range(k):
        a, b = x[q], y[q]
        c = (a, a + b, b, b - a, -a, -a - b, -b, a - b)
        for j in range(8):
            if c[j] > val[j]:
                val[j] = c[j]
                ix[j] = q
    inner = 0.0
    for j in range(8):
        a, b = ix[j], ix[(j + 1) % 8]
        inner += np.sqrt((x[b] - x[a]) ** 2 + (y[b] - y[a]) ** 2)
    return inner


@numba.njit(cache=True, nogil=True, inline="always")
def _count_past(offs, i, n_planes, step_sign, x):
    """By bisection, for offsets ``offs[:, i]`` strictly increasing (``step_sign`` 1) or decreasing
    (-1): how many are <= x (increasing) or > x (decreasing), the first that are."""
    a, b = 0, n_planes
    while a < b:
        m = (a + b) // 2
        if (offs[m, i] <= x) == (step_sign > 0):
            a = m + 1
        else:
            b = m
    return a


@numba.njit(cache=True, nogil=True, inline="always")
def _plane_run(offs, i, n_planes, step_sign, lo, hi):
    """The planes p in [from, to) of body ``i`` whose offset is in (lo, hi] (``_count_past``)."""
    k_lo = _count_past(offs, i, n_planes, step_sign, lo)
    k_hi = _count_past(offs, i, n_planes, step_sign, hi)
    if step_sign > 0:        # above lo: from k_lo on; at or below hi: before k_hi
        return k_lo, k_hi
    return k_hi, k_lo        # decreasing: above lo before k_lo, at or below hi from k_hi on


@numba.njit(cache=True, nogil=True)
def _pairwise_sum(a):
    """numpy's sum of a short contiguous (n <= 128) float64 array, in its order (eight partial
    sums, then pairs), so the band's estimate has the bits of ``support_perimeters``'."""
    n = len(a)
    if n < 8:
        s = 0.0
        for i in range(n):
            s += a[i]
        return s
    r0, r1, r2, r3, r4, r5, r6, r7 = a[0], a[1], a[2], a[3], a[4], a[5], a[6], a[7]
    i = 8
    while i < n - n % 8:
        r0 += a[i]
        r1 += a[i + 1]
        r2 += a[i + 2]
        r3 += a[i + 3]
        r4 += a[i + 4]
        r5 += a[i + 5]
        r6 += a[i + 6]
        r7 += a[i + 7]
        i += 8
    s = ((r0 + r1) + (r2 + r3)) + ((r4 + r5) + (r6 + r7))
    while i < n:
        s += a[i]
        i += 1
    return s
