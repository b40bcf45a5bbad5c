"""Correspondences between the template being fitted and a scan's points.

Two kinds, both gated by distance and by the angle between normals:

- ``closest_pairs``: each query point's nearest neighbour (the ICP pairs of the pose and model
  fits, in both directions: template→scan and scan→template);
- ``tangent_plane_targets``: Hasler §2.3's targets for the non-rigid refinement: every scan
  point is matched to its closest template vertex; each vertex with at least ``MIN_SUPPORT``
  matched points is projected onto the plane fitted to them, any other vertex takes its closest
  scan point, and a vertex whose candidate fails the gates (normals within 30°, distance under
  50 mm) gets no target.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

__all__ = ["Pairs", "closest_pairs", "tangent_plane_targets", "orient_normals",
           "MAX_ANGLE_DEG", "MAX_DISTANCE_M", "MIN_SUPPORT"]

# Hasler §2.3: matches whose normals differ by more than 30° or that are more than 50 mm apart
# are discarded; a vertex needs at least four matched points for a fitted plane.
MAX_ANGLE_DEG = 30.0
MAX_DISTANCE_M = 0.050
MIN_SUPPORT = 4


@dataclass(frozen=True)
class Pairs:
    """Accepted pairs: query indices (K,), their matches (K,), distances (K,)."""

    query: np.ndarray
    match: np.ndarray
    distance: np.ndarray


def closest_pairs(query: np.ndarray, query_normals: np.ndarray, tree: cKDTree, normals: np.ndarray,
                  max_distance: float, min_cos: float, oriented: bool = True) -> Pairs:
    """Each query point (Q, 3) paired with its nearest point of ``tree`` when the pair is within
    ``max_distance`` and the normals' cosine is at least ``min_cos`` (``oriented=False``: the
    absolute cosine, for normals of unknown sign). normals: (N, 3) of the tree's points."""
    dist, idx = tree.query(query, distance_upper_bound=max_distance)
    ok = np.isfinite(dist)
    q = np.flatnonzero(ok)
    m = idx[ok]
    cos = (query_normals[q] * normals[m]).sum(axis=1)
    keep = (cos if oriented else np.abs(cos)) >= min_cos
    return Pairs(q[keep], m[keep], dist[ok][keep])


def orient_normals(points: np.ndarray, normals: np.ndarray, vertices: np.ndarray,
                   vertex_normal: np.ndarray) -> np.ndarray:
    """Scan normals (P, 3) flipped to agree with the nearest vertex's normal of a fitted mesh
    (the pose and model fits place the template close enough that its normals are a reliable
    outside)."""
    _, idx = cKDTree(vertices).query(points)
    sign = np.sign((normals * vertex_normal[idx]).sum(axis=1))
    sign[sign == 0] = 1.0
    return normals * sign[:, None]


def tangent_plane_targets(vertices: np.ndarray, vertex_normal: np.ndarray, points: np.ndarray,
                          point_normals: np.ndarray, scan_tree: cKDTree, *,
                          max_distance: float = MAX_DISTANCE_M, max_angle_deg: float = MAX_ANGLE_DEG,
                          min_support: int = MIN_SUPPORT) -> tuple[np.ndarray, np.ndarray]:
    """Hasler §2.3's target position of every template vertex.

    vertices (V, 3), vertex_normal (V, 3) unit: the template as deformed so far; points (P, 3),
    point_normals (P, 3) unit and oriented (``orient_normals``), scan_tree: ``cKDTree(points)``.
    Returns targets (V, 3) and has_target (V,) bool.
    """
    V = len(vertices)
    min_cos = np.cos(np.radians(max_angle_deg))
    # Every scan point to its closest vertex, gated.
    pairs = closest_pairs(points, point_normals, cKDTree(vertices), vertex_normal, max_distance, min_cos)
    v_of = pairs.match
    p = points[pairs.query]
    count = np.bincount(v_of, minlength=V).astype(float)
    sums = np.stack([np.bincount(v_of, p[:, d], minlength=V) for d in range(3)], axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        centroid = sums / count[:, None]
    # Covariance of each vertex's matched points (second moments minus the centroid's).
    outer = np.einsum("pi,pj->pij", p, p).reshape(len(p), 9)
    second = np.stack([np.bincount(v_of, outer[:, k], minlength=V) for k in range(9)], axis=1).reshape(V, 3, 3)
    targets = np.zeros((V, 3))
    has = np.zeros(V, dtype=bool)
    plane = count >= min_support
    if plane.any():
        c = centroid[plane]
        cov = second[plane] / count[plane, None, None] - np.einsum("vi,vj->vij", c, c)
        _, vecs = np.linalg.eigh(cov)
        n = vecs[:, :, 0]
        x = vertices[plane]
        targets[plane] = x - ((x - c) * n).sum(axis=1, keepdims=True) * n
        has[plane] = True
    # Otherwise: the closest scan point, if it passes the same gates.
    rest = np.flatnonzero(~plane)
    if len(rest):
        near = closest_pairs(vertices[rest], vertex_normal[rest], scan_tree, point_normals, max_distance, min_cos)
        targets[rest[near.query]] = points[near.match]
        has[rest[near.query]] = True
    return targets, has
