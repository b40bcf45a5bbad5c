"""Read and prepare a raw scan: points (and faces if any), normals, units and up axis.

Stage 1 of the registration (Hasler §2.2 starts from a point cloud). A scanner writes PLY, OBJ,
STL or XYZ files, points with or without faces, in millimetres more often than metres, with any
axis up. ``prepare_scan`` brings the points into metres with +Y up (the heading is left to the
initial alignment, ``align.py``), estimates unoriented normals, and says what it assumed. What a
real rig adds is taken away and said: the floor or turntable the body stands on (``find_floor``,
``remove_floors``, in ``mesh/floor.py``; its normal is the up axis), and a scan of millions of points is prepared on a
subsample (``PREPARE_POINTS``; every point kept in ``PreparedScan.dense`` for the detail transfer).
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import trimesh
from scipy.spatial import cKDTree

from bodyspace.errors import MeshError, ParameterError
from bodyspace.measure.conventions import AXIS_VECTORS, MESH_UNITS, UP_AXES, plausible_units, to_internal
from bodyspace.mesh.floor import FLOOR_UP_DEGREES, find_floor, remove_floors
from bodyspace.mesh.geometry import face_areas, sample_surface
from bodyspace.parallel import cores, halves, run_both

__all__ = ["PreparedScan", "read_scan", "estimate_normals", "prepare_scan", "find_floor", "MIN_POINTS", "SCAN_SUFFIXES"]

SCAN_SUFFIXES = (".ply", ".obj", ".stl", ".xyz", ".txt", ".csv", ".npy", ".glb")
# A scan with fewer points cannot hold a body's shape (100 points: ~10 cm apart on the skin).
MIN_POINTS = 2000
# Neighbours for the normal estimate (a local plane through each point and its neighbours): with
# 2 mm noise at 5 mm spacing, 12 neighbours leave normals 15-25° off, too many for the 30° gate.
NORMAL_NEIGHBOURS = 30
# A point whose k-th neighbour is this many times farther than the median point's is isolated:
# not on the body's surface (scanner outliers; the box's own floor or a wall stay, and are left
# to the fit's gates). Measured on the test scans: 97-99 % of the outliers, < 0.1 % of the body.
ISOLATION_NEIGHBOURS = 8
ISOLATION_FACTOR = 3.0
# Points are taken from a mesh's faces, area-uniform, when the mesh has fewer vertices than this
# (a coarse mesh's vertices alone are too sparse for the correspondences).
MESH_SAMPLES = 60_000
# Points a scan is prepared (and fitted) on at most: a photogrammetry scan's millions would cost
# seconds of KD-tree and plane fits per million and gigabytes for the normals' patches (1.5 M
# points: 156 s and 3.4 GB, against 15 s for 200 k, under load), and the fit uses 60,000
# (pipeline.MAX_POINTS) anyway. Above the 50-200 k points and their outliers, so those
# scans are prepared as before.
PREPARE_POINTS = 250_000


@dataclass(frozen=True)
class PreparedScan:
    """A scan in metres with +Y up (heading and position as scanned).

    points: (P, 3) metres, +Y up; normals: (P, 3) unit, unoriented (sign arbitrary).
    to_scan: (4, 4) homogeneous similarity mapping these coordinates back to the file's
        (``points_file = (to_scan @ [p, 1])[:3]``).
    units, up: what was used; up_known: False when the up axis was found (its sign is then left
        to the alignment); assumed: sentences saying what was found rather than given.
    faces: (F, 3) when the file was a mesh (indices into ``mesh_vertices``), else None.
    dense: (D, 3) every point of a scan denser than ``PREPARE_POINTS`` (same frame, isolated
        points and the floor removed) when ``points`` is a subsample of it, else None.
    """

    points: np.ndarray
    normals: np.ndarray
    to_scan: np.ndarray
    units: str
    up: str
    up_known: bool = True
    assumed: list[str] = field(default_factory=list)
    mesh_vertices: np.ndarray | None = None
    faces: np.ndarray | None = None
    dense: np.ndarray | None = None

    @property
    def all_points(self) -> np.ndarray:
        """(D, 3) every point of the scan (``dense``, else ``points``)."""
        return self.points if self.dense is None else self.dense


def read_scan(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray | None]:
    """Points (P, 3) and faces (F, 3) or None from a scan file.

    PLY/OBJ/STL/GLB through trimesh (point clouds and meshes); XYZ/TXT/CSV: one point a line,
    the first three numbers; NPY: a (P, 3) array.
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in SCAN_SUFFIXES:
        raise MeshError(f"{path}: unsupported scan format '{suffix}'; expected one of {', '.join(SCAN_SUFFIXES)}")
    if not path.is_file():
        raise MeshError(f"{path}: no such file; expected a scan ({', '.join(SCAN_SUFFIXES)})")
    faces = None
    if suffix == ".npy":
        points = np.load(path, allow_pickle=False)
    elif suffix in (".xyz", ".txt", ".csv"):
        try:
            points = np.loadtxt(path, delimiter="," if suffix == ".csv" else None, usecols=(0, 1, 2), ndmin=2)
        except ValueError as exc:
            raise MeshError(f"{path}: could not read points ({exc}); expected one point a line, x y z "
                            "first") from None
    else:
        try:
            loaded = trimesh.load(path, process=False)
        except Exception as exc:  # trimesh raises many kinds on a broken file
            raise MeshError(f"{path}: could not read the scan ({type(exc).__name__}: {exc}); expected a "
                            f"PLY/OBJ/STL/GLB point cloud or mesh") from None
        if isinstance(loaded, trimesh.Scene):
            geoms = list(loaded.dump()) if hasattr(loaded, "dump") else list(loaded.geometry.values())
            if not geoms:
                raise MeshError(f"{path}: the file holds no geometry; expected a point cloud or a mesh")
            loaded = trimesh.util.concatenate(geoms) if len(geoms) > 1 else geoms[0]
        points = np.asarray(loaded.vertices, dtype=float)
        if getattr(loaded, "faces", None) is not None and len(loaded.faces):
            faces = np.asarray(loaded.faces, dtype=np.int64)
    points = np.asarray(points, dtype=float)
    if points.ndim != 2 or points.shape[1] != 3:
        raise MeshError(f"{path}: points have shape {points.shape}; expected (P, 3)")
    return points, faces


def isolated_points(points: np.ndarray, k: int = ISOLATION_NEIGHBOURS) -> np.ndarray:
    """(P,) bool: points far from the surface the others sample (dust, reflections, hair): the
    distance to their ``k``-th neighbour is over ``ISOLATION_FACTOR`` times the median one."""
    return _isolation(points, k)[0]


def _isolation(points: np.ndarray, k: int = ISOLATION_NEIGHBOURS) -> tuple[np.ndarray, float]:
    """``isolated_points`` and ``ISOLATION_FACTOR`` times the points' median spacing (the distance
    to the nearest other point; the points' units): farther than that from every kept point, a
    point of the dense scan the points were drawn from is not on the surface they sample."""
    k = min(int(k), len(points) - 1)
    if k < 1:
        return np.zeros(len(points), dtype=bool), np.inf
    d = cKDTree(points).query(points, k=k + 1, workers=cores())[0]
    return d[:, -1] > ISOLATION_FACTOR * float(np.median(d[:, -1])), ISOLATION_FACTOR * float(np.median(d[:, 1]))


def estimate_normals(points: np.ndarray, k: int = NORMAL_NEIGHBOURS) -> np.ndarray:
    """Unoriented unit normals (P, 3) of points (P, 3): the least direction of each point's
    ``k`` nearest neighbours (a plane fitted to the local patch)."""
    points = np.asarray(points, dtype=float)
    k = min(int(k), len(points))
    # The KD-tree's queries on every core; the patches' planes in two halves (the second on
    # parallel's lane thread): 1.6 + 0.7 s of CPU on a 147 k-point scan.
    _, nb = cKDTree(points).query(points, k=k, workers=cores())

    def plane_normals(lo: int, hi: int) -> np.ndarray:
        patch = points[nb[lo:hi]]                                          # (n, k, 3)
        local = patch - patch.mean(axis=1, keepdims=True)
        return np.linalg.eigh(local.transpose(0, 2, 1) @ local)[1][:, :, 0]

    (a, b), (c, d) = halves(len(points))
    first, second = run_both(lambda: plane_normals(a, b), lambda: plane_normals(c, d))
    return np.concatenate([first, second])


def _sample_faces(vertices: np.ndarray, faces: np.ndarray, n: int) -> np.ndarray:
    """``n`` points area-uniform on a mesh, with a fixed seed (a scan reads the same each time)."""
    area = face_areas(vertices, faces)
    if not np.isfinite(area).all() or area.sum() <= 0:
        return vertices
    return sample_surface(vertices, faces, n, 0)[0]


def prepare_scan(points: np.ndarray, faces: np.ndarray | None = None, *, units: str | None = None,
                 up: str | None = None, name: str = "the scan", keep_dense: bool = True) -> PreparedScan:
    """Points (P, 3) in a file's frame → a ``PreparedScan`` in metres, +Y up.

    faces: (F, 3) if the scan is a mesh (points are then also sampled on its faces).
    units: "m", "cm", "mm" or "in", or None to find it from the size (the extent and the spread
        of the points; refused when no unit makes a human-sized body).
    up: one of ``UP_AXES``, or None: the axis along which the points spread most (a standing
        body's height); its sign is found by the initial alignment (``align.py``), which tries
        both, so the prepared scan may be upside down when ``up`` is not given.
    keep_dense: keep every point of a scan denser than ``PREPARE_POINTS`` as ``dense`` (its
        outliers and floor removed: a KD-tree query per point, seconds a million); False: only the
        subsample (``dense`` None).
    Raises MeshError for an empty scan, fewer than ``MIN_POINTS`` points, or NaN.
    """
    p = np.asarray(points, dtype=float)
    if p.ndim != 2 or p.shape[1] != 3 or len(p) == 0:
        raise MeshError(f"{name}: holds no points (shape {p.shape}); expected a point cloud or mesh of a body")
    p = p[np.isfinite(p).all(axis=1)]
    mesh_vertices = None
    welded = 0
    if faces is not None and len(faces):
        faces = np.asarray(faces, dtype=np.int64)
        if len(p) == len(points):
            # A triangle soup (an STL, an OBJ exported per face) repeats each corner once per
            # triangle: 54,000 points for 9,000 places, too many for the face sampling below and
            # stacked six deep, which flagged 1.5 % of a clean body as isolated points and left the
            # fit 2.4 mm from it instead of 1.5 mm. Exact repeats are one vertex.
            u, inverse = np.unique(p, axis=0, return_inverse=True)
            if len(u) < len(p):
                welded = len(p) - len(u)
                p, faces = u, inverse.reshape(-1)[faces]
            mesh_vertices = p
        if mesh_vertices is not None and len(p) < MESH_SAMPLES:
            p = np.concatenate([p, _sample_faces(p, faces, MESH_SAMPLES - len(p))])
    if len(p) < MIN_POINTS:
        raise MeshError(f"{name}: has {len(p)} finite points; expected at least {MIN_POINTS} on a body "
                        "(a full-body scan has 50,000 or more)")
    assumed, up_known = [], True
    if welded:
        assumed.append(f"merged {welded} repeated vertices (a triangle soup: each corner written once per "
                       f"triangle) into {len(mesh_vertices)}")
    dense = None
    if len(p) > PREPARE_POINTS:
        # A dense scan (photogrammetry: millions of points) is fitted on a random subsample; its
        # every point is kept for the detail transfer (``PreparedScan.dense``).
        dense, p = p, p[np.random.default_rng(0).choice(len(p), PREPARE_POINTS, replace=False)]
        assumed.append(f"{len(dense):,} points: the fit uses {PREPARE_POINTS:,} of them spread at random"
                       + (" (the detail transfer all)" if keep_dense else ""))
        if not keep_dense:
            dense = None
    isolated, limit = _isolation(p)
    if isolated.any():
        p = p[~isolated]
        assumed.append(f"removed {int(isolated.sum())} isolated points ({100 * isolated.mean():.1f} %: far from the "
                       "surface the others sample)")
    if dense is not None:
        # The dense points near the kept ones (an outlier of the subsample's is far from them all).
        dense = dense[cKDTree(p).query(dense, workers=cores())[0] <= limit]
    if units is None:
        centred = p - np.median(p, axis=0)
        extent = float(np.max(np.percentile(centred, 99.5, axis=0) - np.percentile(centred, 0.5, axis=0)))
        fits = plausible_units(extent)
        if not fits:
            raise MeshError(f"{name}: its points span {extent:.4g} units; no length unit makes that a human body "
                            f"(0.5-3.2 m); give the unit with --units ({', '.join(MESH_UNITS)})")
        units = fits[0]
        # Centimetres and inches overlap (a 51-unit scan: a 1.30 m child in inches or a 0.51 m
        # toddler in cm): the other reading is named, with the flag that settles it.
        other = "".join(f"; as {u} it would be {extent * MESH_UNITS[u]:.2f} m" for u in fits[1:])
        assumed.append(f"units: {units} (the points span {extent:.4g} {units}, {extent * MESH_UNITS[units]:.2f} m{other}; "
                       "--units sets it)")
    elif units not in MESH_UNITS:
        raise ParameterError(f"units={units!r}; expected one of {', '.join(MESH_UNITS)}")
    scale = MESH_UNITS[units]
    given_up = None
    if up is not None:
        if up not in UP_AXES:
            raise ParameterError(f"up={up!r}; expected one of {', '.join(UP_AXES)}")
        given_up = np.array(AXIS_VECTORS[up], dtype=float)                          # file axis up
    keep, floors, planes = remove_floors(p * scale, given_up)
    floor_normal = planes[-1][0] if planes else None
    if floors:
        p = p[keep]
        if dense is not None:
            for normal, offset, cut in planes:
                dense = dense[(dense * scale) @ normal - offset >= cut]
        assumed.extend(floors)
        if len(p) < MIN_POINTS:
            raise MeshError(f"{name}: has {len(p)} points besides the floor; expected at least {MIN_POINTS} on a body")
        axis = int(np.argmax(np.abs(floor_normal)))
        if up is None and abs(floor_normal[axis]) > np.cos(np.radians(FLOOR_UP_DEGREES)):
            # The floor says which way is up, sign included (the body stands on it).
            up = "xyz"[axis] if floor_normal[axis] > 0 else "-" + "xyz"[axis]
            assumed.append(f"up axis: {up} (the floor's normal; --up sets it)")
    if up is None:
        centred = p - p.mean(axis=0)
        _, _, vt = np.linalg.svd(centred[:: max(1, len(p) // 20000)], full_matrices=False)
        axis = int(np.argmax(np.abs(vt[0])))
        up = "xyz"[axis] if vt[0, axis] > 0 else "-" + "xyz"[axis]
        assumed.append(f"up axis: {up.lstrip('-')} (the points spread most along it; which end is the head "
                       "is found by the fit; --up sets it)")
        up_known = False
    elif up not in UP_AXES:
        raise ParameterError(f"up={up!r}; expected one of {', '.join(UP_AXES)}")
    rot = to_internal(np.eye(3), np.zeros((0, 3), dtype=np.int64), "m", up)[0].T     # the up axis onto +Y
    q = (p * scale) @ rot.T
    to_scan = np.eye(4)
    to_scan[:3, :3] = rot.T / scale
    normals = estimate_normals(q)
    mv = None if mesh_vertices is None else (mesh_vertices * scale) @ rot.T
    return PreparedScan(q, normals, to_scan, units, up, up_known, assumed, mv, faces if mv is not None else None,
                        None if dense is None else (dense * scale) @ rot.T)
