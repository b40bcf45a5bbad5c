"""Per-mesh geometric quantities: normals, areas, boundary loops, capped volume.

All functions take ``vertices`` of shape (V, 3) or a batch (N, V, 3) and ``faces`` (F, 3) int.
"""

from __future__ import annotations

import numba
import numpy as np

from bodyspace.errors import MeshError
from bodyspace.validation import as_generator


def check_mesh(vertices: np.ndarray, faces: np.ndarray, name: str = "mesh") -> None:
    """Raise MeshError unless ``vertices`` is (..., V, 3) finite and ``faces`` (F, 3) indexes it."""
    vertices = np.asarray(vertices)
    faces = np.asarray(faces)
    if vertices.ndim < 2 or vertices.shape[-1] != 3:
        raise MeshError(f"{name}: vertices have shape {vertices.shape}, expected (V, 3) or (N, V, 3)")
    if faces.ndim != 2 or faces.shape[1] != 3:
        raise MeshError(f"{name}: faces have shape {faces.shape}, expected (F, 3)")
    if faces.size and (faces.min() < 0 or faces.max() >= vertices.shape[-2]):
        raise MeshError(f"{name}: faces index vertices 0..{faces.max()}, but there are only "
                        f"{vertices.shape[-2]} vertices")
    if not np.isfinite(vertices).all():
        raise MeshError(f"{name}: vertices contain NaN or infinity")


def face_normals(vertices: np.ndarray, faces: np.ndarray, normalize: bool = True) -> np.ndarray:
    """Face normals (..., F, 3); with ``normalize=False`` their length is twice the face area."""
    v = np.asarray(vertices)
    a, b, c = v[..., faces[:, 0], :], v[..., faces[:, 1], :], v[..., faces[:, 2], :]
    n = np.cross(b - a, c - a)
    if normalize:
        n = n / np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-300)
    return n


def vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Unit vertex normals (V, 3): area-weighted sums of the adjacent face normals; zero where a
    vertex is on no face (or its faces have no area)."""
    v = np.asarray(vertices, dtype=float)
    f = np.asarray(faces)
    fn = face_normals(v, f, normalize=False)                   # length 2 * area
    corners = f.ravel()
    per_corner = np.repeat(fn, 3, axis=0)
    n = np.stack([np.bincount(corners, per_corner[:, c], minlength=len(v)) for c in range(3)], axis=1)
    return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)


def face_areas(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Triangle areas (..., F)."""
    return 0.5 * np.linalg.norm(face_normals(vertices, faces, normalize=False), axis=-1)


def sample_surface(vertices: np.ndarray, faces: np.ndarray, n: int, rng=None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``n`` points spread uniformly by area over a mesh (V, 3), (F, 3).

    rng: a seed or ``numpy.random.Generator``. Returns points (n, 3), their faces (n,) and
    barycentric coordinates (n, 3).
    """
    rng = as_generator(rng)
    area = face_areas(vertices, faces)
    face = rng.choice(len(faces), size=int(n), p=area / area.sum())
    r1, r2 = np.sqrt(rng.random(int(n))), rng.random(int(n))
    bary = np.stack([1.0 - r1, r1 * (1.0 - r2), r1 * r2], axis=1)
    points = np.einsum("nk,nkd->nd", bary, vertices[faces[face]])
    return points, face, bary


def boundary_loops(faces: np.ndarray) -> list[np.ndarray]:
    """Ordered vertex loops of the mesh boundary (edges used by exactly one face).

    Each loop follows the faces' orientation, so capping it with a fan keeps the closed surface
    consistently oriented (the cap's triangles use the loop reversed).
    """
    faces = np.asarray(faces)
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    key = np.sort(e, axis=1)
    _, inverse, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    boundary = e[counts[inverse.ravel()] == 1]
    nxt = {int(a): int(b) for a, b in boundary}
    if len(nxt) != len(boundary):
        raise MeshError("mesh boundary is not manifold: a vertex starts two boundary edges")
    loops, seen = [], set()
    for start in nxt:
        if start in seen:
            continue
        loop, v = [], start
        while v not in seen:
            seen.add(v)
            loop.append(v)
            v = nxt[v]
        loops.append(np.array(loop))
    return loops


def cap_holes(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Close every boundary loop with a fan around an added centroid vertex.

    Returns ``(vertices', faces')`` for one mesh (V, 3); the new vertices are appended.
    For a batch use ``capped_volume``, which does not build the meshes.
    """
    loops = boundary_loops(faces)
    verts, new_faces = [np.asarray(vertices, dtype=float)], [np.asarray(faces)]
    nv = len(vertices)
    for k, loop in enumerate(loops):
        verts.append(np.asarray(vertices)[loop].mean(axis=0, keepdims=True))
        c = nv + k
        nxt = np.roll(loop, -1)
        new_faces.append(np.stack([nxt, loop, np.full_like(loop, c)], axis=1))
    return np.concatenate(verts), np.concatenate(new_faces)


@numba.njit(cache=True, nogil=True)
def _capped_volume_kernel(v, faces, loop_vertices, loop_starts, out):
    """Six times the capped volume of each body of ``v`` (N, V, 3) into ``out`` (N,): the
    faces' signed tetrahedra, then each loop's cap fan (q, p, centre) as in ``cap_holes``.
    Loop k is ``loop_vertices[loop_starts[k]:loop_starts[k + 1]]``."""
    for n in range(v.shape[0]):
        total = 0.0
        for f in range(faces.shape[0]):
            a, b, c = faces[f, 0], faces[f, 1], faces[f, 2]
            bx, by, bz = v[n, b, 0], v[n, b, 1], v[n, b, 2]
            cx, cy, cz = v[n, c, 0], v[n, c, 1], v[n, c, 2]
            total += (v[n, a, 0] * (by * cz - bz * cy) + v[n, a, 1] * (bz * cx - bx * cz)
                      + v[n, a, 2] * (bx * cy - by * cx))
        for k in range(loop_starts.shape[0] - 1):
            s, e = loop_starts[k], loop_starts[k + 1]
            mx = my = mz = 0.0
            for j in range(s, e):
                mx += v[n, loop_vertices[j], 0]
                my += v[n, loop_vertices[j], 1]
                mz += v[n, loop_vertices[j], 2]
            mx, my, mz = mx / (e - s), my / (e - s), mz / (e - s)
            for j in range(s, e):
                p, q = loop_vertices[j], loop_vertices[j + 1 if j + 1 < e else s]
                px, py, pz = v[n, p, 0], v[n, p, 1], v[n, p, 2]
                total += (v[n, q, 0] * (py * mz - pz * my) + v[n, q, 1] * (pz * mx - px * mz)
                          + v[n, q, 2] * (px * my - py * mx))
        out[n] = total


def capped_volume(vertices: np.ndarray, faces: np.ndarray, loops: list[np.ndarray] | None = None) -> np.ndarray:
    """Enclosed volume (...,) of a mesh (..., V, 3) whose holes are capped by centroid fans, in units^3.

    Divergence theorem: the sum of signed tetrahedra from the origin; the caps are added
    analytically so no capped mesh is built. Works on batches (N, V, 3). A compiled loop over
    the faces (``_capped_volume_kernel``): the population's height/weight solve measures tens
    of bodies per subject, and numpy's gathered (N, F, 3) copies and ``cross`` cost ~50x more.
    """
    v = np.asarray(vertices, dtype=float)
    if v.ndim < 2 or v.shape[-1] != 3:
        raise MeshError(f"vertices: shape {v.shape}, expected (V, 3) or (N, V, 3)")
    if loops is None:
        loops = boundary_loops(faces)
    flat = np.ascontiguousarray(v.reshape((-1,) + v.shape[-2:]))
    loop_vertices = np.concatenate([np.asarray(loop, dtype=np.int64) for loop in loops] or [np.zeros(0, np.int64)])
    loop_starts = np.concatenate([[0], np.cumsum([len(loop) for loop in loops])]).astype(np.int64)
    out = np.empty(len(flat))
    _capped_volume_kernel(flat, np.ascontiguousarray(faces, dtype=np.int64).reshape(-1, 3), loop_vertices,
                          loop_starts, out)
    return (out / 6.0).reshape(v.shape[:-2])


def surface_area(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Total area (...,) of the (uncapped) surface."""
    return face_areas(vertices, faces).sum(axis=-1)
