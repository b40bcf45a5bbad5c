"""Arms through the torso: a simple, honest measure of self-intersection in posed meshes.

Linear blend skinning knows nothing of collisions, and a clip retargeted onto a wider body can
swing a hand or forearm into the belly or hips. ``arm_torso_intersections`` reports how often
and how deep, without correcting anything:

* **Regions from the skin weights.** Arm vertices carry at least ``REGION_WEIGHT`` (90 %) of
  their weight on the bones from the shoulder landmark down (upper arm, forearm, hand,
  fingers); torso vertices as much on the trunk's bones (pelvis, spine, chest, clavicles:
  the pelvis's subtree without the legs, the arms and the head). Arm vertices within
  ``ATTACHED`` (3 cm) of the torso at rest are the skin joining the two and are left out
  (they always touch).
* **Depth.** For each remaining arm vertex, the nearest torso vertex of the posed mesh and its
  outward vertex normal ``n``: the arm vertex is inside the torso by ``-(x - t) . n`` when that
  is positive, the arm vertex lies within 45 degrees of the inward normal (behind the surface
  point, not beside it: at the edge of the torso region the nearest torso vertex can be far
  round the body) and the two are closer than ``REACH`` (5 cm; beyond it the nearest vertex
  says nothing about inside or out, so deeper points are reported as 5 cm at most). A frame
  intersects when its deepest arm vertex is more than
  ``MIN_DEPTH`` (5 mm) inside.

It is an approximation (one nearest vertex, not a point-in-solid test), tested to report
nothing at rest and a known depth for an arm pushed into the body.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.spatial import cKDTree

from bodyspace.errors import MotionError
from bodyspace.rig.skeleton import Skeleton

__all__ = ["ATTACHED", "MIN_DEPTH", "REACH", "REGION_WEIGHT", "Intersections", "arm_torso_intersections",
           "arm_torso_regions"]

REGION_WEIGHT = 0.9
ATTACHED = 0.03
REACH = 0.05
MIN_DEPTH = 0.005


def _subtree(parents: np.ndarray, root: int) -> np.ndarray:
    inside = np.zeros(len(parents), bool)
    inside[root] = True
    while True:
        new = inside | ((parents >= 0) & inside[np.maximum(parents, 0)])
        if (new == inside).all():
            return inside
        inside = new


def arm_torso_regions(skeleton: Skeleton, weights, landmarks: dict[str, str],
                      rest_vertices: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Indices of the arm vertices (away from the torso at rest) and of the torso vertices.

    weights: (V, B) skin weights; landmarks: role -> bone name (``SkeletonMatch.target_landmarks``:
    pelvis, hip.L/R, shoulder.L/R, head); rest_vertices: (V, 3).
    """
    need = ("pelvis", "shoulder.L", "shoulder.R")
    if any(r not in landmarks for r in need):
        raise MotionError(f"landmarks: {sorted(landmarks)}; the arm and torso regions need {', '.join(need)}")
    parents = skeleton.parents
    bone = {r: skeleton.bone_index(n) for r, n in landmarks.items()}
    arm = _subtree(parents, bone["shoulder.L"]) | _subtree(parents, bone["shoulder.R"])
    torso = _subtree(parents, bone["pelvis"]) & ~arm
    for r in ("hip.L", "hip.R", "head"):
        if r in bone:
            torso &= ~_subtree(parents, bone[r])
    W = sp.csr_matrix(weights, dtype=float)
    on_arm = np.asarray(W[:, arm].sum(axis=1)).ravel() >= REGION_WEIGHT
    on_torso = np.asarray(W[:, torso].sum(axis=1)).ravel() >= REGION_WEIGHT
    arm_v, torso_v = np.flatnonzero(on_arm), np.flatnonzero(on_torso)
    if len(arm_v) == 0 or len(torso_v) == 0:
        raise MotionError(f"skeleton {skeleton.name!r}: no vertex carries {REGION_WEIGHT:.0%} of its weight on the "
                          "arms or on the torso; the intersection measure needs both regions")
    rest = np.asarray(rest_vertices, dtype=float)
    d, _ = cKDTree(rest[torso_v]).query(rest[arm_v])
    return arm_v[d > ATTACHED], torso_v


@dataclass(frozen=True)
class Intersections:
    """Arms inside the torso per frame: ``depth`` (F,) of the deepest arm vertex (metres, 0 when
    none is inside), the number and share of ``frames`` deeper than ``MIN_DEPTH``, the
    ``max_depth`` and its frame."""

    depth: np.ndarray
    frames: int
    share: float
    max_depth: float
    worst_frame: int

    def to_dict(self) -> dict:
        return {"frames_intersecting": self.frames, "share_of_frames": self.share,
                "max_depth_m": self.max_depth, "worst_frame": self.worst_frame, "min_depth_counted_m": MIN_DEPTH}


def _vertex_normals(v: np.ndarray, faces: np.ndarray, incidence: sp.csr_matrix) -> np.ndarray:
    fn = np.cross(v[faces[:, 1]] - v[faces[:, 0]], v[faces[:, 2]] - v[faces[:, 0]])     # |fn| = 2 area
    n = incidence @ fn
    return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)


def arm_torso_intersections(posed: np.ndarray, faces: np.ndarray, arm: np.ndarray, torso: np.ndarray,
                            progress=None) -> Intersections:
    """How deep the arm vertices go into the torso in each frame (module docstring).

    posed: (F, V, 3) posed meshes; faces: (F', 3); arm, torso: vertex indices
    (``arm_torso_regions``); progress: optional ``callback(message, fraction)``.
    """
    P = np.asarray(posed)
    if P.ndim != 3 or P.shape[2] != 3:
        raise MotionError(f"posed: shape {P.shape}, expected (frames, V, 3)")
    f = np.asarray(faces, dtype=np.int64)
    # faces touching the torso, and the (torso vertex, face) incidence for the normals
    touching = np.flatnonzero(np.isin(f, torso).any(axis=1))
    ft = f[touching]
    where = np.full(P.shape[1], -1)
    where[torso] = np.arange(len(torso))
    rows = where[ft.ravel()]
    cols = np.repeat(np.arange(len(ft)), 3)
    keep = rows >= 0
    incidence = sp.csr_matrix((np.ones(keep.sum()), (rows[keep], cols[keep])), shape=(len(torso), len(ft)))
    depth = np.zeros(len(P))
    for i in range(len(P)):
        frame = P[i].astype(float)
        t = frame[torso]
        x = frame[arm]
        dist, j = cKDTree(t).query(x, distance_upper_bound=REACH)
        near = np.isfinite(dist)
        if near.any():
            n = _vertex_normals(frame, ft, incidence)[j[near]]
            offset = x[near] - t[j[near]]
            inside = -np.einsum("ki,ki->k", offset, n)
            # behind the surface point, not beside it: within 45 degrees of the inward normal
            lateral = np.linalg.norm(offset + inside[:, None] * n, axis=1)
            inside = np.where(lateral <= inside, inside, 0.0)
            depth[i] = max(0.0, float(inside.max()))
        if progress is not None and i % 50 == 0:
            progress(f"frame {i + 1} of {len(P)}", (i + 1) / len(P))
    hit = depth > MIN_DEPTH
    worst = int(np.argmax(depth)) if len(depth) else 0
    return Intersections(depth, int(hit.sum()), float(hit.mean()) if len(depth) else 0.0,
                         float(depth.max()) if len(depth) else 0.0, worst)
