"""Foreign test bodies: the template's bodies as a user's data would come, never as ours.

Our own data is one topology (hm08, 13,380 vertices), metres, +Y up, the floor at y = 0 and
mostly population phenotypes. A user's meshes differ in all of that. This module makes bodies
that differ in every way we can control, each with its exact ground truth, so every feature can
be tested on data it has never seen (issue 12 §5; docs/foreign.md):

- ``remesh``: another triangulation and vertex count, with a ``Correspondence`` (source face and
  barycentric coordinates of every new vertex) that carries any per-vertex quantity of the
  template (landmarks, joints, skin weights, groups) over exactly;
- ``shuffle_vertices``: the same surface, the vertices in another order;
- ``to_frame`` / ``from_frame``: another up axis, unit, heading and origin (floor not at zero);
- ``add_noise``, ``punch_holes``, ``reverse_winding``: scanner damage;
- ``foreign_topology`` + ``foreign_body``: one call for a body the model never saw, with the true
  landmark and joint positions and a landmark file for its topology that
  ``bodyspace.measure.load_landmarks`` reads.

Remeshing method: quadric-error decimation (Garland & Heckbert 1997, through
``fast-simplification``, MIT, numpy-only wheels, ~20 ms for the template) down to the requested
count (for a finer mesh: to a quarter of it, then every triangle split in four at random points
of its edges), then every vertex is moved onto its closest point of the source surface.
The last step makes the correspondence exact: a new vertex *is* a barycentric point of a source
face, so ``transfer`` reproduces the remeshed body from any template body (another phenotype, a
pose) without a second projection, and bodies of one foreign topology form a database.
Quadric decimation was chosen over isotropic remeshing because it is ~100x faster, keeps the
surface within ~1 mm at 5,000 vertices, and is available under a permissive licence without
VTK or MeshLab (pymeshlab is GPL).
"""

from __future__ import annotations

import csv
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import fast_simplification
import numpy as np
import scipy.sparse as sp
from scipy.spatial import cKDTree

from bodyspace.atomic import atomic_dir
from bodyspace.data.template import Template
from bodyspace.errors import MeshError, ParameterError
from bodyspace.measure.definitions import MeasurementSet, load_measurement_set
from bodyspace.mesh.geometry import face_normals, vertex_normals
from bodyspace.mesh.io import save_mesh
from bodyspace.rig.posing import pose_bodies
from bodyspace.synth.phenotype import PARAMETERS, years_to_age
from bodyspace.synth.population import REST_POSE, Subjects, sample_subjects
from bodyspace.synth.poses import load_pose_library
from bodyspace.validation import as_generator

CANDIDATE_FACES = 24          # source faces searched per point (by centroid) in closest_points
SPLIT_RANGE = (0.3, 0.7)      # where split_edges cuts each edge (fraction from its first vertex)
UP_AXES = ("y", "z", "-y")

# Frame matrices: internal (+Y up, +Z front) to the user's frame. "z": Z up, the person facing
# -Y (Blender's convention); "-y": upside down (a mesh exported with the wrong up axis).
_UP_MATRIX = {
    "y": np.eye(3),
    "z": np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]]),
    "-y": np.array([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]]),
}


# ------------------------------------------------------------------------------ correspondence

@dataclass(frozen=True)
class Correspondence:
    """Where each vertex of a new mesh lies on a source mesh.

    face: (V2,) source face index of each new vertex.
    barycentric: (V2, 3) its barycentric coordinates in that face (non-negative, rows sum to 1).
    """

    face: np.ndarray
    barycentric: np.ndarray

    def __len__(self) -> int:
        return len(self.face)

    def matrix(self, source_faces: np.ndarray, n_source: int) -> sp.csr_matrix:
        """Sparse (V2, V) matrix ``M``: ``M @ source_values`` are the values on the new vertices."""
        rows = np.repeat(np.arange(len(self.face)), 3)
        cols = np.asarray(source_faces)[self.face].ravel()
        return sp.csr_matrix((self.barycentric.ravel(), (rows, cols)), shape=(len(self.face), n_source))

    def permuted(self, permutation: np.ndarray) -> "Correspondence":
        """The correspondence of the mesh whose vertex i is this mesh's vertex ``permutation[i]``."""
        return Correspondence(self.face[permutation], self.barycentric[permutation])


def transfer(correspondence: Correspondence, source_faces: np.ndarray, values: np.ndarray) -> np.ndarray:
    """Carry per-vertex values of the source to the new vertices, exactly.

    values: (V, ...) or (N, V, 3) (a batch of bodies: vertex axis second to last).
    Returns (V2, ...) or (N, V2, 3): each new vertex's barycentric mix of its source face.
    """
    values = np.asarray(values, dtype=float)
    corners = np.asarray(source_faces)[correspondence.face]          # (V2, 3)
    w = correspondence.barycentric
    if values.ndim == 3 and values.shape[-1] == 3 and values.shape[1] != len(corners):
        # (N, V, 3) batch of bodies
        return np.einsum("vk,nvkd->nvd", w, values[:, corners, :])
    return np.einsum("vk,vk...->v...", w, values[corners])


def _closest_on_triangles(p: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Barycentric coordinates (..., 3) of the closest point of triangles (a, b, c) to points p.

    All inputs (..., 3). Ericson, *Real-Time Collision Detection* §5.1.5 (ClosestPtPointTriangle),
    vectorized: the Voronoi regions are tested in reverse order so that the first match wins.
    """
    ab, ac, ap = b - a, c - a, p - a
    bp, cp = p - b, p - c
    d1, d2 = (ab * ap).sum(-1), (ac * ap).sum(-1)
    d3, d4 = (ab * bp).sum(-1), (ac * bp).sum(-1)
    d5, d6 = (ab * cp).sum(-1), (ac * cp).sum(-1)
    va, vb, vc = d3 * d6 - d5 * d4, d5 * d2 - d1 * d6, d1 * d4 - d3 * d2
    with np.errstate(divide="ignore", invalid="ignore"):
        denom = va + vb + vc
        v_in, w_in = vb / denom, vc / denom
        bary = np.stack([1 - v_in - w_in, v_in, w_in], axis=-1)
        w_bc = (d4 - d3) / ((d4 - d3) + (d5 - d6))
        w_ac = d2 / (d2 - d6)
        v_ab = d1 / (d1 - d3)
    regions = [  # (mask, barycentric), lowest priority first
        ((va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0), np.stack([0 * w_bc, 1 - w_bc, w_bc], -1)),
        ((vb <= 0) & (d2 >= 0) & (d6 <= 0), np.stack([1 - w_ac, 0 * w_ac, w_ac], -1)),
        ((d6 >= 0) & (d5 <= d6), np.broadcast_to([0.0, 0.0, 1.0], bary.shape)),
        ((vc <= 0) & (d1 >= 0) & (d3 <= 0), np.stack([1 - v_ab, v_ab, 0 * v_ab], -1)),
        ((d3 >= 0) & (d4 <= d3), np.broadcast_to([0.0, 1.0, 0.0], bary.shape)),
        ((d1 <= 0) & (d2 <= 0), np.broadcast_to([1.0, 0.0, 0.0], bary.shape)),
    ]
    for mask, value in regions:
        bary = np.where(mask[..., None], value, bary)
    bary = np.nan_to_num(bary, nan=1.0 / 3.0)   # degenerate triangle: its centroid
    return np.clip(bary, 0.0, 1.0) / np.clip(bary, 0.0, 1.0).sum(-1, keepdims=True)


def closest_points(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray,
                   point_normals: np.ndarray | None = None) -> tuple[Correspondence, np.ndarray]:
    """Closest point of a surface to each point.

    points: (P, 3); vertices (V, 3), faces (F, 3): the surface.
    point_normals: (P, 3) optional unit normals of the points' own surface: a face facing the
        other way (the far side of a thin part, the neighbouring finger) is only taken when no
        candidate faces the same way.
    Returns the correspondence (face (P,), barycentric (P, 3)) and the distances (P,).
    Candidates are the ``CANDIDATE_FACES`` faces with the nearest centroids: exact for points
    within about one edge length of the surface, which is what it is used for.
    """
    points = np.asarray(points, dtype=float)
    tri = vertices[faces]                                              # (F, 3, 3)
    k = min(CANDIDATE_FACES, len(faces))
    _, cand = cKDTree(tri.mean(axis=1)).query(points, k=k)
    cand = cand.reshape(len(points), k)
    t = tri[cand]                                                      # (P, k, 3, 3)
    p = np.broadcast_to(points[:, None, :], t.shape[:2] + (3,))
    bary = _closest_on_triangles(p, t[..., 0, :], t[..., 1, :], t[..., 2, :])
    q = np.einsum("pkc,pkcd->pkd", bary, t)
    dist = np.linalg.norm(q - p, axis=-1)
    score = dist
    if point_normals is not None:
        fn = face_normals(vertices, faces)[cand]                       # (P, k, 3)
        facing = (fn * point_normals[:, None, :]).sum(-1) > 0
        score = np.where(facing, dist, dist + 1e3)
    best = np.argmin(score, axis=1)
    rows = np.arange(len(points))
    return Correspondence(cand[rows, best], bary[rows, best]), dist[rows, best]


# ------------------------------------------------------------------------------ remeshing

def _edge_keys(faces: np.ndarray) -> np.ndarray:
    """(3F,) one integer per half-edge, equal for both halves of an edge (lo * n + hi); rows in
    the order of faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]."""
    half = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]).astype(np.int64)
    n = int(faces.max()) + 1
    return half.min(axis=1) * n + half.max(axis=1)


def edge_face_counts(faces: np.ndarray) -> np.ndarray:
    """Number of faces on each undirected edge (E,): 2 everywhere on a closed manifold."""
    return np.unique(_edge_keys(faces), return_counts=True)[1]


def euler_characteristic(faces: np.ndarray) -> int:
    """V - E + F of the vertices the faces use (2 for a closed genus-0 surface)."""
    return int(np.unique(faces).size - np.unique(_edge_keys(faces)).size + len(faces))


def split_edges(vertices: np.ndarray, faces: np.ndarray, rng=None) -> tuple[np.ndarray, np.ndarray]:
    """Every triangle split in four, every edge cut at a random point of it.

    vertices (V, 3), faces (F, 3) → vertices (V + E, 3), faces (4F, 3). The new vertices lie on
    the source edges (so on the surface) at ``SPLIT_RANGE`` fractions drawn from ``rng``.
    """
    rng = as_generator(rng)
    keys, inverse = np.unique(_edge_keys(faces), return_inverse=True)
    n = int(faces.max()) + 1
    lo, hi = keys // n, keys % n
    t = rng.uniform(*SPLIT_RANGE, len(keys))[:, None]
    new = (1 - t) * vertices[lo] + t * vertices[hi]
    mid = len(vertices) + inverse.reshape(3, len(faces)).T                        # (F, 3): ab, bc, ca
    a, b, c = faces.T
    mab, mbc, mca = mid.T
    out = np.concatenate([np.c_[a, mab, mca], np.c_[mab, b, mbc], np.c_[mca, mbc, c], np.c_[mab, mbc, mca]])
    return np.concatenate([vertices, new]), out


def _decimate(vertices: np.ndarray, faces: np.ndarray, target_vertices: int, closed: bool, chi: int,
              rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Quadric decimation (fast-simplification) of a copy whose vertices are moved along their
    normals by 0.3 mm of noise from ``rng`` (it breaks the ties of flat regions, so each seed
    collapses other edges); the positions are put back on the true surface by the caller.
    Tries gentler settings while the result is not a closed manifold like the source."""
    noisy = vertices + vertex_normals(vertices, faces) * rng.normal(0.0, 3e-4, (len(vertices), 1))
    target_faces = 2 * target_vertices - 2 * chi if closed else int(len(faces) * target_vertices / len(vertices))
    reason = ""
    for agg in (3.0, 2.0, 1.5):
        v2, f2 = fast_simplification.simplify(noisy, faces, target_count=target_faces, agg=agg)
        f2 = np.asarray(f2, dtype=np.int64)
        used = np.unique(f2)
        if len(used) < len(v2):                       # drop vertices the decimation orphaned
            remap = np.full(len(v2), -1)
            remap[used] = np.arange(len(used))
            v2, f2 = v2[used], remap[f2]
        if not closed:
            return v2, f2
        counts = edge_face_counts(f2)
        if not (counts == 2).all():
            reason = f"{int((counts != 2).sum())} edge(s) not shared by exactly two faces"
        elif euler_characteristic(f2) != chi:
            reason = f"Euler characteristic {euler_characteristic(f2)}, expected {chi}"
        else:
            return v2, f2
    raise MeshError(f"remesh to {target_vertices} vertices: {reason}; expected a closed manifold like "
                    "the source. Ask for more vertices")


def _onto_surface(points: np.ndarray, faces2: np.ndarray, vertices: np.ndarray, faces: np.ndarray,
                  keep: np.ndarray | None = None) -> tuple[np.ndarray, Correspondence, int]:
    """Move the new mesh's vertices onto the source surface without folding a face.

    points (V2, 3), faces2 (F2, 3): the new mesh near the surface. A face whose normal turns
    over (or whose area vanishes) when its corners are projected gets its corners moved to
    their 1-ring centroid first (uniform Laplacian smoothing, up to 8 rounds).
    keep: (K,) source vertex ids: the new vertex nearest to each (one new vertex per id) is put
    exactly on it and never smoothed.
    Returns vertices (V2, 3) on the surface, their correspondence, and the faces still folded.
    """
    source_normals = face_normals(vertices, faces)
    ring = sp.csr_matrix((np.ones(6 * len(faces2)),
                          (faces2[:, [0, 1, 2, 1, 2, 0]].ravel(), faces2[:, [1, 2, 0, 0, 1, 2]].ravel())),
                         shape=(len(points),) * 2)
    ring.data[:] = 1.0
    degree = np.asarray(ring.sum(axis=1)).ravel()
    p = points.copy()
    corr, _ = closest_points(p, vertices, faces, vertex_normals(p, faces2))
    pinned = np.zeros(len(p), dtype=bool)
    if keep is not None and len(keep):
        tree = cKDTree(p)
        corner_of = {}
        for f_id, tri in enumerate(faces):          # a face of each kept vertex, and its corner
            for c, j in enumerate(tri):
                corner_of.setdefault(int(j), (f_id, c))
        for j in np.asarray(keep, dtype=np.int64):
            near = tree.query(vertices[j], k=min(16, len(p)))[1]
            k = int(near[~pinned[near]][0])
            pinned[k] = True
            f_id, c = corner_of[int(j)]
            corr.face[k], corr.barycentric[k] = f_id, np.eye(3)[c]
    for _ in range(8):
        on = transfer(corr, faces, vertices)
        n = face_normals(on, faces2, normalize=False)
        ref = source_normals[corr.face][faces2].sum(axis=1)        # the surface's normal under the face
        bad = ((n * ref).sum(1) <= 0) | (np.linalg.norm(n, axis=1) < 1e-12)
        if not bad.any():
            return on, corr, 0
        move = np.unique(faces2[bad])
        move = move[~pinned[move]]
        p[move] = (ring[move] @ p) / degree[move, None]
        c2, _ = closest_points(p[move], vertices, faces, vertex_normals(p, faces2)[move])
        corr = Correspondence(corr.face.copy(), corr.barycentric.copy())
        corr.face[move], corr.barycentric[move] = c2.face, c2.barycentric
    return on, corr, int(bad.sum())


def remesh(vertices: np.ndarray, faces: np.ndarray, target_vertices: int, rng=None,
           keep: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, Correspondence]:
    """Another triangulation of the same surface with ``target_vertices`` vertices.

    vertices (V, 3), faces (F, 3): the source. Coarser than the source: quadric decimation
    (``_decimate``). Finer: decimation to a quarter of the target, then every triangle split in
    four at random points of its edges (``split_edges``), which gives exactly 4 V' - 6 vertices
    on a closed genus-0 surface (the target rounded to that). Then every vertex is put on its
    closest point of the source surface (``_onto_surface``); ``keep`` (K,) source vertex ids
    (surface landmarks) are each reproduced exactly by one new vertex.
    Returns vertices (V2, 3) on the source surface, faces (F2, 3) and the ``Correspondence`` of
    every new vertex (exact: ``transfer(corr, faces, vertices)`` equals the returned vertices).
    A closed manifold source gives a closed manifold result with the same Euler characteristic
    and orientation, with no folded face; else ``MeshError``.
    """
    rng = as_generator(rng)
    vertices = np.asarray(vertices, dtype=float)
    faces = np.asarray(faces, dtype=np.int64)
    target_vertices = int(target_vertices)
    if not 100 <= target_vertices <= 4 * len(vertices):
        raise ParameterError(f"target_vertices={target_vertices}; expected 100 to {4 * len(vertices)} "
                             f"for a source of {len(vertices)} vertices")
    closed = bool((edge_face_counts(faces) == 2).all())
    chi = euler_characteristic(faces)
    for _attempt in range(4):                         # a fold left after smoothing: decimate anew
        if target_vertices < 0.9 * len(vertices):
            v2, f2 = _decimate(vertices, faces, target_vertices, closed, chi, rng)
        else:
            coarse_v, coarse_f = _decimate(vertices, faces, (target_vertices + 2 * chi) // 4, closed, chi, rng)
            v2, f2 = split_edges(coarse_v, coarse_f, rng)
        on_surface, corr, folded = _onto_surface(v2, f2, vertices, faces, keep)
        if not folded:
            break
    else:
        raise MeshError(f"remesh to {target_vertices} vertices: {folded} face(s) fold over on the source "
                        "surface; expected none. Try another rng or more vertices")
    return on_surface, f2, corr


def shuffle_vertices(vertices: np.ndarray, faces: np.ndarray, rng=None
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The same surface with its vertices (and faces, and each face's first corner) reordered.

    vertices (V, 3) or (N, V, 3), faces (F, 3) → vertices2, faces2 (F, 3), permutation (V,):
    ``vertices2[..., i, :] == vertices[..., permutation[i], :]``. Orientation is kept (corners are
    rotated cyclically, never swapped).
    """
    rng = as_generator(rng)
    faces = np.asarray(faces)
    n = np.shape(vertices)[-2]
    perm = rng.permutation(n)
    inverse = np.empty(n, dtype=np.int64)
    inverse[perm] = np.arange(n)
    f = inverse[faces][rng.permutation(len(faces))]
    shift = rng.integers(0, 3, len(f))
    f = np.take_along_axis(f, (np.arange(3)[None, :] + shift[:, None]) % 3, axis=1)
    return np.asarray(vertices)[..., perm, :], f, perm


# ------------------------------------------------------------------------------ frames and units

def _frame_matrix(up: str, yaw_degrees: float) -> np.ndarray:
    if up not in _UP_MATRIX:
        raise ParameterError(f"up={up!r}; expected one of {', '.join(UP_AXES)}")
    c, s = np.cos(np.radians(yaw_degrees)), np.sin(np.radians(yaw_degrees))
    yaw = np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])      # about +Y (internal up)
    return _UP_MATRIX[up] @ yaw


def to_frame(vertices: np.ndarray, up: str = "z", scale: float = 1000.0,
             translation=(0.42, -0.17, 0.93), yaw_degrees: float = 25.0) -> np.ndarray:
    """Internal bodies (metres, +Y up, +Z front) in a user's frame.

    vertices: (..., 3). ``x' = scale * (U @ R_yaw @ x + translation)``: turned by ``yaw_degrees``
    about the vertical, the up axis mapped to ``up`` ("y", "z": Z up and facing -Y, "-y": upside
    down), moved by ``translation`` (metres, in the new axes: the floor is then not at zero and
    the body off the origin) and scaled (1000: millimetres). Returns (..., 3).
    """
    if not np.isfinite(scale) or scale <= 0:
        raise ParameterError(f"scale={scale}; expected a positive number (1000 for millimetres)")
    M = _frame_matrix(up, yaw_degrees)
    return scale * (np.asarray(vertices, dtype=float) @ M.T + np.asarray(translation, dtype=float))


def from_frame(vertices: np.ndarray, up: str = "z", scale: float = 1000.0,
               translation=(0.42, -0.17, 0.93), yaw_degrees: float = 25.0) -> np.ndarray:
    """The inverse of ``to_frame`` with the same arguments: (..., 3) back to metres, +Y up."""
    if not np.isfinite(scale) or scale <= 0:
        raise ParameterError(f"scale={scale}; expected a positive number (1000 for millimetres)")
    M = _frame_matrix(up, yaw_degrees)
    return (np.asarray(vertices, dtype=float) / scale - np.asarray(translation, dtype=float)) @ M


# ------------------------------------------------------------------------------ damage

def add_noise(vertices: np.ndarray, sigma: float, rng=None, faces: np.ndarray | None = None) -> np.ndarray:
    """Scanner noise: Gaussian offsets of standard deviation ``sigma`` (the vertices' unit).

    vertices (V, 3). With ``faces`` (F, 3) each vertex moves along its normal (depth noise of a
    range scanner: the surface gets rough, its vertices stay evenly spread); without, each
    coordinate gets independent noise (isotropic, per-axis SD ``sigma``). Returns (V, 3).
    """
    rng = as_generator(rng)
    v = np.asarray(vertices, dtype=float)
    if faces is None:
        return v + rng.normal(0.0, sigma, v.shape)
    return v + rng.normal(0.0, sigma, (len(v), 1)) * vertex_normals(v, np.asarray(faces))


def punch_holes(vertices: np.ndarray, faces: np.ndarray, centres: np.ndarray, radius: float) -> np.ndarray:
    """Faces (F2, 3) left after removing every face with a corner within ``radius`` of a centre.

    vertices (V, 3), faces (F, 3), centres (K, 3) (e.g. ``hole_sites``: head top, soles,
    armpits, crotch: where a scanner sees nothing). The vertices stay as they are (the mesh
    then has unused vertices, as many scans do).
    """
    centres = np.atleast_2d(np.asarray(centres, dtype=float))
    near = cKDTree(centres).query(vertices, distance_upper_bound=radius)[0] <= radius   # (V,)
    return np.asarray(faces)[~near[faces].any(axis=1)]


def reverse_winding(faces: np.ndarray) -> np.ndarray:
    """Faces (F, 3) with every triangle's orientation flipped (normals pointing inwards)."""
    return np.asarray(faces)[:, ::-1].copy()


def hole_sites(vertices: np.ndarray, landmarks: dict[str, np.ndarray]) -> np.ndarray:
    """Where scanners leave holes (K=6, 3) on an upright body (V, 3), internal frame.

    landmarks: name → (3,) positions of the hm08 set (``ForeignBody.true_landmarks``). Head top,
    both soles (the lowest vertex near each ankle), both armpits (6 cm below the shoulder joint,
    at the torso's side) and the crotch.
    """
    v = np.asarray(vertices)
    sites = [landmarks["head_top"], landmarks["crotch"]]
    for side in ("l", "r"):
        ankle = landmarks[f"ankle_joint_{side}"]
        near = np.linalg.norm((v - ankle)[:, [0, 2]], axis=1) < 0.12
        sites.append(v[near][np.argmin(v[near, 1])])
        joint = landmarks[f"shoulder_joint_{side}"]
        sites.append(joint + np.array([-0.03 * np.sign(joint[0]), -0.06, 0.0]))
    return np.array(sites)


# ------------------------------------------------------------------------------ foreign bodies

def foreign_phenotype(rng=None) -> np.ndarray:
    """A phenotype (11,) at or beyond the edges of the synthetic population (population.py).

    The population draws muscle in [0.1, 0.6], proportions [0.3, 0.8], cup size and firmness
    [0.2, 0.8], ages 18-50 and solves height/weight for survey targets. Here each of those is
    drawn from the ends of MakeHuman's [0, 1] range instead (muscle, proportions, cup, firmness
    in [0, 0.1] or [0.8, 1]; height and weight in [0.05, 0.2] or [0.8, 0.95]; age 55-85 years or
    18-20), the sex is 0 or 1 and the race mix one-sided. Returns (11,) in ``PARAMETERS`` order.
    """
    rng = as_generator(rng)

    def edge(lo_band, hi_band):
        band = lo_band if rng.random() < 0.5 else hi_band
        return rng.uniform(*band)

    p = {"gender": float(rng.integers(0, 2)),
         "age": float(years_to_age(np.array(rng.uniform(55, 85) if rng.random() < 0.7 else rng.uniform(18, 20)))),
         "muscle": edge((0.0, 0.1), (0.8, 1.0)), "proportions": edge((0.0, 0.1), (0.8, 1.0)),
         "cupsize": edge((0.0, 0.1), (0.8, 1.0)), "firmness": edge((0.0, 0.1), (0.8, 1.0)),
         "height": edge((0.05, 0.2), (0.8, 0.95)), "weight": edge((0.05, 0.2), (0.8, 0.95))}
    race = rng.dirichlet([0.3, 0.3, 0.3])
    p["african"], p["asian"], p["caucasian"] = race
    return np.array([p[name] for name in PARAMETERS])


@dataclass(frozen=True)
class ForeignTopology:
    """A remeshed, reordered topology of the template that many bodies can share.

    faces: (F2, 3) faces of the new mesh.
    correspondence: new vertex → template face + barycentric (V2 entries, in the new order).
    landmarks: the measurement set's landmarks as weighted sets of new vertices:
        name → (vertex ids (k,), convex weights (k,)), built on the template's mean body.
    """

    faces: np.ndarray
    correspondence: Correspondence
    landmarks: dict[str, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)

    @property
    def n_vertices(self) -> int:
        return len(self.correspondence)

    def landmark_file(self) -> dict:
        """The landmarks as a document ``bodyspace.measure.load_landmarks`` reads (json.dump it)."""
        out = {}
        for name, (ids, w) in self.landmarks.items():
            out[name] = int(ids[0]) if len(ids) == 1 else {"vertices": [int(i) for i in ids],
                                                           "weights": [float(x) for x in w]}
        return {"landmarks": out, "n_vertices": self.n_vertices}


def carry_points(points: dict[str, tuple[np.ndarray, np.ndarray]], source_vertices: np.ndarray,
                 source_faces: np.ndarray, vertices: np.ndarray, faces: np.ndarray
                 ) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Points given as weighted sets of a source mesh's vertices, as weighted sets of another mesh.

    points: name → (vertex ids (k,), convex weights (k,)) of the source; source_vertices (V, 3),
    source_faces (F, 3): the source body; vertices (V2, 3), faces (F2, 3): the same body in another
    meshing. Each source vertex a point uses is replaced by its closest point of the new surface
    (three vertices with barycentric weights), and the point's weights are mixed accordingly, so
    it stays convex and is reproduced up to the distance between the two surfaces (< 1 mm at
    5,000 vertices). Returns name → (ids (k2,), weights (k2,)).
    """
    normals = vertex_normals(source_vertices, source_faces)
    out = {}
    for name, (ids, w) in points.items():
        ids, w = np.asarray(ids), np.asarray(w, dtype=float)
        corr, _ = closest_points(source_vertices[ids], vertices, faces, normals[ids])
        new_ids = faces[corr.face].ravel()
        new_w = (w[:, None] * corr.barycentric).ravel()
        keep = new_w > 1e-12
        uniq, inv = np.unique(new_ids[keep], return_inverse=True)
        merged = np.bincount(inv, new_w[keep])
        out[name] = (uniq, merged / merged.sum())
    return out


def carry_landmarks(mset: MeasurementSet, source_vertices: np.ndarray, source_faces: np.ndarray,
                    vertices: np.ndarray, faces: np.ndarray) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """A measurement set's landmarks (on the source topology) as weighted sets of another mesh
    (``carry_points``). Returns name → (ids (k,), weights (k,))."""
    return carry_points(mset.landmarks, source_vertices, source_faces, vertices, faces)


def carry_joints(mset: MeasurementSet, source_vertices: np.ndarray, source_faces: np.ndarray,
                 vertices: np.ndarray, faces: np.ndarray) -> dict[str, dict[str, dict]]:
    """The joints of the set's joint axes (the neck girth's neck and head joints, weighted sets of
    the source's vertices) on another mesh of the same body (``carry_points``), as
    ``definitions.with_axis_joints`` takes them: measurement name → axis field → {"from", "to"}
    inline points ``{"vertices": [...], "weights": [...]}``. Carried joints follow the template's
    joint placement into every pose; joints placed on the mesh itself (``parts.axis_joints``)
    depend on its body-part labels and put the neck girth's plane 8-12 cm wrong in a side bend or
    with the head down (a 6,000-vertex body labelled with the template's parts)."""
    found = {}
    for m in mset.measurements:
        for field_name in ("normal", "axis"):
            a = m.get(field_name)
            if isinstance(a, dict) and a.get("from") is not None and a.get("to") is not None:
                for end in ("from", "to"):
                    found[(m["name"], field_name, end)] = (np.asarray(a[end]["vertices"]),
                                                           np.asarray(a[end]["weights"], dtype=float))
    carried = carry_points(found, source_vertices, source_faces, vertices, faces)
    out: dict[str, dict[str, dict]] = {}
    for (name, field_name, end), (ids, w) in carried.items():
        out.setdefault(name, {}).setdefault(field_name, {})[end] = {"vertices": [int(i) for i in ids],
                                                                     "weights": [float(x) for x in w]}
    return out


def foreign_topology(template: Template, target_vertices: int = 6000, rng=None,
                     mset: MeasurementSet | None = None) -> ForeignTopology:
    """Remesh the template's mean body to ``target_vertices``, shuffle the order, carry landmarks.

    The set's surface landmarks (one vertex each) are kept as vertices of the new mesh, so they
    are exact on every body of the topology; the weighted ones (joint centres) are carried by
    ``carry_landmarks`` (within ~1.5 mm on posed bodies).

    mset: the measurement set whose landmarks are carried (default: the shipped hm08 set).
    Any template body goes onto the topology with ``transfer(topology.correspondence,
    template.faces, body)``.
    """
    rng = as_generator(rng)
    mset = mset if mset is not None else load_measurement_set()
    surface_landmarks = [int(ids[0]) for ids, _ in mset.landmarks.values() if len(ids) == 1]
    v2, f2, corr = remesh(template.vertices, template.faces, target_vertices, rng, keep=surface_landmarks)
    v2, f2, perm = shuffle_vertices(v2, f2, rng)
    corr = corr.permuted(perm)
    landmarks = carry_landmarks(mset, template.vertices, template.faces, v2, f2)
    return ForeignTopology(f2, corr, landmarks)


@dataclass(frozen=True)
class ForeignBody:
    """A body the model never saw, with its ground truth.

    vertices: (V2, 3) in the foreign frame (``frame``: the ``to_frame`` arguments; units
        ``frame["scale"]`` per metre). faces: (F2, 3).
    landmark_file: a ``load_landmarks`` document for this topology (vertex ids of ``vertices``).
    true_landmarks: name → (3,) exact landmark positions (the hm08 set on the template body),
        in the foreign frame.
    true_joints: (B, 3) the rig's bone heads of the posed body (``pose_bodies``), foreign frame.
    template_vertices: (V, 3) the same body on the template topology, metres, +Y up, on the
        ground (y = 0 at its lowest point).
    phenotype: (11,); pose: its library name; topology: the shared ``ForeignTopology``.
    """

    vertices: np.ndarray
    faces: np.ndarray
    landmark_file: dict
    true_landmarks: dict[str, np.ndarray]
    true_joints: np.ndarray
    template_vertices: np.ndarray
    phenotype: np.ndarray
    pose: str
    frame: dict
    topology: ForeignTopology

    def internal_vertices(self) -> np.ndarray:
        """(V2, 3) the mesh back in metres, +Y up (``from_frame``)."""
        return from_frame(self.vertices, **self.frame)


def foreign_body(template, phenotype_model, topology: ForeignTopology | None = None, rng=None, *,
                 phenotype: np.ndarray | None = None, pose: str | None = None,
                 target_vertices: int = 6000, frame: dict | None = None,
                 mset: MeasurementSet | None = None) -> ForeignBody:
    """One body the model never saw: edge-of-population phenotype, posed, remeshed, moved.

    template: the ``Template``; phenotype_model: its ``PhenotypeModel``.
    topology: a shared ``ForeignTopology`` (default: a new one of ``target_vertices``).
    phenotype: (11,) (default ``foreign_phenotype(rng)``); pose: a library name ("rest" is
    MakeHuman's A-pose, "t_pose" the T-pose; default: drawn from the library).
    frame: ``to_frame`` arguments (default: millimetres, Z up, turned 25°, floor at -170 mm).
    """
    rng = as_generator(rng)
    mset = mset if mset is not None else load_measurement_set()
    topology = topology if topology is not None else foreign_topology(template, target_vertices, rng, mset)
    phenotype = foreign_phenotype(rng) if phenotype is None else np.asarray(phenotype, dtype=float)
    library = load_pose_library()
    pose = pose if pose is not None else str(rng.choice(library.names))
    rig = template.rigs["default"]
    rest = phenotype_model.vertices(phenotype[None])[0]
    body, joints = pose_bodies(rest, rig, library.rotations(pose, rig), on_ground=True, return_joints=True)
    frame = dict(up="z", scale=1000.0, translation=(0.42, -0.17, 0.93), yaw_degrees=25.0) | (frame or {})
    lm_matrix = mset.landmark_matrix(template.n_vertices)
    true_lm = to_frame(lm_matrix @ body, **frame)
    vertices = to_frame(transfer(topology.correspondence, template.faces, body), **frame)
    return ForeignBody(vertices, topology.faces, topology.landmark_file(),
                       dict(zip(mset.landmark_names, true_lm)), to_frame(joints, **frame), body,
                       phenotype, pose, frame, topology)


# ------------------------------------------------------------------------------ a user's scan folder

SCAN_FOLDER_KIND = "scans"
LABELS_FILE = "labels.csv"
LANDMARKS_FILE = "landmarks.json"
# Length units a scan folder can be written in: scale per metre.
FOLDER_UNITS = {"m": 1.0, "cm": 100.0, "mm": 1000.0}
# Poses of a scan folder besides the rest pose: standing poses a scanning session would ask
# for, in this order (a folder of P poses uses the first P).
SESSION_POSES = ("t_pose", "arms_overhead", "elbows_flexed", "step_forward_left", "arms_at_sides",
                 "head_turn_left", "torso_twist_left", "knee_lift_left", "squat")


@dataclass(frozen=True)
class ScanFolder:
    """A folder of registered scans as a user would bring them (``write_scan_folder``).

    folder: the folder; meshes: (N,) file names in it, in the CSV's order; labels_csv,
    landmarks_json: the paths of the labels CSV and the landmark file.
    subjects: the ground truth of the subjects (``synth.population.Subjects``: phenotypes,
    stature_m, mass_kg, ... measured on the template-topology rest bodies, metres).
    subject_ids: (S,) ids as in the CSV; poses: the pose names of each subject, the rest first.
    topology: the shared ``ForeignTopology``; frame: the ``to_frame`` arguments of the meshes.
    """

    folder: Path
    meshes: list
    labels_csv: Path
    landmarks_json: Path
    subjects: Subjects
    subject_ids: list
    poses: list
    topology: ForeignTopology
    frame: dict


def write_scan_folder(template: Template, phenotype_model, out, subjects: int = 10, poses: int = 2, *,
                      target_vertices: int = 5000, units: str = "mm", rest_name: str = "a_pose", rng=None,
                      frame: dict | None = None, overwrite: bool = False,
                      progress: Callable[[str, float], None] | None = None) -> ScanFolder:
    """Write a folder of registered scans of one foreign topology, as a user would bring them.

    ``subjects`` adults drawn like the synthetic population (``sample_subjects``: survey stature
    and BMI), each in MakeHuman's A-pose (named ``rest_name``, not "rest") and the first
    ``poses`` of ``SESSION_POSES``, posed on the ground by the rig, put on one remeshed and
    reordered topology of ``target_vertices`` (``foreign_topology``), then moved into the
    user's frame (``to_frame``: default +Y up, turned 25° about the vertical, 0.42 m right,
    0.93 m forward, the floor at -0.17 m) and written in ``units`` ("m", "cm" or "mm").

    Files: ``s01_a_pose.obj``, ... (one per scan), ``labels.csv`` (columns mesh, subject, pose,
    sex, age_years, stature_cm, mass_kg: stature and mass of the rest body on the template
    topology, rounded to 0.1 cm / 0.1 kg as a clinic would write them) and ``landmarks.json``
    (the hm08 landmarks carried to the topology, a ``load_landmarks`` document). The folder is
    written atomically with the ``.bodyspace`` marker of kind ``SCAN_FOLDER_KIND``; an existing
    ``out`` is refused unless ``overwrite`` (and then replaced only if it is such a folder).
    ``bodyspace import OUT --labels OUT/labels.csv --units mm --rest-pose a_pose --landmarks
    OUT/landmarks.json --out DB`` reads it. Returns a ``ScanFolder`` with the ground truth.
    """
    if units not in FOLDER_UNITS:
        raise ParameterError(f"units={units!r}; expected one of {', '.join(FOLDER_UNITS)}")
    if not 1 <= int(subjects):
        raise ParameterError(f"subjects={subjects}; expected at least 1")
    if not 0 <= int(poses) <= len(SESSION_POSES):
        raise ParameterError(f"poses={poses}; expected 0 to {len(SESSION_POSES)} (the session poses "
                             f"{', '.join(SESSION_POSES)})")
    if not isinstance(rest_name, str) or not rest_name or rest_name in SESSION_POSES[:int(poses)]:
        raise ParameterError(f"rest_name={rest_name!r}; expected a pose name other than "
                             f"{', '.join(SESSION_POSES[:int(poses)])}")
    rng = as_generator(rng)
    report = progress or (lambda msg, frac: None)
    frame = dict(up="y", translation=(0.42, -0.17, 0.93), yaw_degrees=25.0) | (frame or {})
    frame["scale"] = FOLDER_UNITS[units]
    report(f"drawing {subjects} subjects", 0.0)
    truth = sample_subjects(phenotype_model, int(subjects), rng)
    report(f"remeshing the template to {target_vertices} vertices", 0.2)
    topology = foreign_topology(template, target_vertices, rng)
    library = load_pose_library()
    rig = template.rigs["default"]
    session = [REST_POSE] + list(SESSION_POSES[:int(poses)])
    names = [rest_name] + session[1:]
    R = np.stack([library.rotations(p, rig) for p in session])
    ids = [f"s{i + 1:02d}" for i in range(int(subjects))]
    rows, meshes = [], []
    with atomic_dir(out, overwrite=overwrite, kind=SCAN_FOLDER_KIND) as tmp:
        for i, sid in enumerate(ids):
            rest = phenotype_model.vertices(truth.phenotypes[i][None])[0]
            posed = pose_bodies(np.repeat(rest[None], len(R), axis=0), rig, R, on_ground=True)   # (P, V, 3)
            bodies = to_frame(transfer(topology.correspondence, template.faces, posed), **frame)
            for pose, body in zip(names, bodies):
                mesh = f"{sid}_{pose}.obj"
                save_mesh(tmp / mesh, body, topology.faces)
                meshes.append(mesh)
                rows.append({"mesh": mesh, "subject": sid, "pose": pose,
                             "sex": "male" if truth.male[i] else "female",
                             "age_years": f"{truth.age_years[i]:.0f}",
                             "stature_cm": f"{100 * truth.stature_m[i]:.1f}",
                             "mass_kg": f"{truth.mass_kg[i]:.1f}"})
            report(f"wrote the scans of {sid}", 0.3 + 0.65 * (i + 1) / len(ids))
        with open(tmp / LABELS_FILE, "w", newline="", encoding="utf-8") as fh:
            writer = csv.DictWriter(fh, fieldnames=list(rows[0]))
            writer.writeheader()
            writer.writerows(rows)
        (tmp / LANDMARKS_FILE).write_text(json.dumps(topology.landmark_file(), indent=1) + "\n",
                                          encoding="utf-8")
    report("done", 1.0)
    out = Path(out)
    return ScanFolder(out, meshes, out / LABELS_FILE, out / LANDMARKS_FILE, truth, ids, names, topology, frame)
