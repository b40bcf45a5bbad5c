"""Masked morphing (Hasler §5.1): a change confined to body regions by a masked Poisson solve.

Hasler §5.1: "A multiplicative mask allows deformation to occur in selected areas. The
reconstruction process spreads out" the change at the mask's border. Here the mask multiplies
the change of every triangle's gradient, and a Poisson solve (Yu et al. 2004, the same
reconstruction as Hasler's encoding) rebuilds the surface with the vertices outside the mask
held fixed:

    minimise  sum_f area_f || grad_f(d') - w_f grad_f(d) ||^2   over d' (V, 3),  d' = 0 where w = 0,

``grad_f`` the gradient operator on the rest mesh (``mesh.operators.gradient_operator``), ``w_f``
the mean weight of face f's corners. The normal matrix is the cotangent Laplacian
(``mesh.operators.cotangent_laplacian``) restricted to the free vertices, factored once per mask
(``mesh.solver.FactorizedSolver``); a morph then pays three triangular solves. Inside the mask
the change is kept, at the seam it fades over the blended triangles, outside nothing moves
(exactly 0.000 mm: those rows are never written).

Regions (``REGIONS``) are per-vertex weights from the template's default rig (sums of skinning
weights over a region's bones, smooth across joints) and its left/right vertex groups; on any
other topology, from the skeleton its measurement set's landmarks define
(``region_weights_from_landmarks``).
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from bodyspace.errors import ParameterError
from bodyspace.mesh.operators import cotangent_laplacian, gradient_operator
from bodyspace.mesh.solver import FactorizedSolver

__all__ = ["REGIONS", "region_weights_from_template", "region_weights_from_landmarks", "MaskedPoissonBlend",
           "masked_poisson_blend"]

REGIONS = ("upper_body", "lower_body", "arms", "legs", "torso", "head", "left", "right")
_ARM = ("shoulder01", "upperarm", "lowerarm", "wrist", "finger", "metacarpal")
_LEG = ("upperleg", "lowerleg", "foot", "toe")
_LOWER = _LEG + ("pelvis", "spine05", "root")
_TORSO = ("spine", "pelvis", "breast", "clavicle", "root")


def region_weights_from_template(template) -> dict[str, np.ndarray]:
    """Per-vertex weights (V,) in [0, 1] of every region in ``REGIONS``: sums of the default
    rig's skinning weights over the region's bones (smooth across joints); left/right from the
    template's vertex groups (1 on the side, 0.5 on the symmetry plane)."""
    rig = template.rigs["default"]
    w = sp.csc_matrix(rig.weights)

    def bones(prefixes):
        cols = [i for i, b in enumerate(rig.bone_names) if b.startswith(prefixes)]
        return np.clip(np.asarray(w[:, cols].sum(axis=1)).ravel(), 0.0, 1.0)

    nv = template.n_vertices
    lower = bones(_LOWER)
    arms, legs, torso = bones(_ARM), bones(_LEG), bones(_TORSO)
    left, right = np.zeros(nv), np.zeros(nv)
    left[template.left] = 1.0
    right[template.right] = 1.0
    left[template.mid] = right[template.mid] = 0.5
    head = np.clip(1.0 - arms - legs - torso, 0.0, 1.0)
    out = {"upper_body": 1.0 - lower, "lower_body": lower, "arms": arms, "legs": legs, "torso": torso,
           "head": head, "left": left, "right": right}
    return {k: np.where(v < 1e-4, 0.0, np.where(v > 1 - 1e-4, 1.0, v)) for k, v in out.items()}


# The body parts of a landmark skeleton (``region_weights_from_landmarks``): chains of points
# (landmark names, or a list of names: their mean) whose segments a part's vertices are nearest to.
NECK = ["neck_front", "neck_back"]
PART_CHAINS = {
    "head": [[NECK, "head_top"]],
    "torso": [["crotch", NECK], ["hip_joint_l", "hip_joint_r"], ["shoulder_joint_l", "shoulder_joint_r"],
              ["hip_joint_l", "shoulder_joint_l"], ["hip_joint_r", "shoulder_joint_r"]],
    "arm_l": [["shoulder_joint_l", "elbow_joint_l", "wrist_joint_l", "hand_l"]],
    "arm_r": [["shoulder_joint_r", "elbow_joint_r", "wrist_joint_r", "hand_r"]],
    "leg_l": [["hip_joint_l", "knee_joint_l", "ankle_joint_l"]],
    "leg_r": [["hip_joint_r", "knee_joint_r", "ankle_joint_r"]],
}
# Landmarks the skeleton needs (hand_l/r are made: the wrist joint plus HAND_LENGTH forearms).
SKELETON_LANDMARKS = ("crotch", "neck_front", "neck_back", "head_top") + tuple(
    f"{j}_joint_{s}" for s in "lr" for j in ("shoulder", "elbow", "wrist", "hip", "knee", "ankle"))
HAND_LENGTH = 0.75           # hand (wrist to fingertip) in forearms (elbow to wrist)
# Soft assignment: weight of a part ~ exp(-(its distance - the nearest part's) / PART_SOFTNESS);
# the waist boundary of lower_body is as soft, along the torso axis.
PART_SOFTNESS = 0.01         # metres
# lower_body's border on the torso, as a fraction of the crotch -> neck distance above the crotch:
# where the template's lower_body (legs, pelvis, lowest spine bone) meets its upper_body.
LOWER_BODY_TOP = 0.31
# left/right: the sagittal plane's soft band, half-width in metres (the template's mid vertices are 0.5)
SAGITTAL_BAND = 0.005


def _skeleton_points(vertices, mset) -> dict[str, np.ndarray]:
    """Landmark positions (3,) of ``vertices`` (V, 3) by name, plus the hand tips."""
    pts = dict(zip(mset.landmark_names, np.asarray(mset.landmark_matrix(len(vertices)) @ vertices)))
    for s in "lr":
        e, w = pts[f"elbow_joint_{s}"], pts[f"wrist_joint_{s}"]
        pts[f"hand_{s}"] = w + HAND_LENGTH * (w - e)
    return pts


def _segment_distance(x, a, b) -> np.ndarray:
    """Distances (V,) of points x (V, 3) to the segment a-b (3,)."""
    d = b - a
    t = np.clip((x - a) @ d / max(float(d @ d), 1e-300), 0.0, 1.0)
    return np.linalg.norm(x - (a + t[:, None] * d), axis=1)


def region_weights_from_landmarks(vertices, mset) -> dict[str, np.ndarray]:
    """Per-vertex weights (V,) in [0, 1] of every region in ``REGIONS`` for a body of any
    topology, from its measurement set's landmarks (``SKELETON_LANDMARKS``: crotch, neck, head
    top and the joint centres) on ``vertices`` (V, 3), a standing body (the model's mean).

    Every vertex is assigned, softly, to the nearest part of the skeleton the landmarks define
    (``PART_CHAINS``: head, torso, each arm with its hand, each leg; weights ~ exp(-(distance -
    nearest distance) / ``PART_SOFTNESS``), summing to 1); lower_body is the legs plus the torso
    below ``LOWER_BODY_TOP`` of the crotch-to-neck height, upper_body the rest; left/right by the
    side of the sagittal plane (through the crotch-neck axis, normal to it and the hip joints'
    left-right direction; 0.5 on the plane). Returns {} when a needed landmark is missing."""
    v = np.asarray(vertices, dtype=float)
    if any(n not in mset.landmarks for n in SKELETON_LANDMARKS):
        return {}
    pts = _skeleton_points(v, mset)

    def point(p):
        return np.mean([pts[q] for q in p], axis=0) if isinstance(p, list) else pts[p]

    dist = {}
    for part, chains in PART_CHAINS.items():
        dist[part] = np.min([_segment_distance(v, point(a), point(b))
                             for chain in chains for a, b in zip(chain[:-1], chain[1:])], axis=0)
    parts = list(dist)
    d = np.stack([dist[p] for p in parts])                                  # (P, V)
    w = np.exp(-(d - d.min(axis=0)) / PART_SOFTNESS)
    w /= w.sum(axis=0)
    part = dict(zip(parts, w))
    crotch, neck = pts["crotch"], point(NECK)
    axis = neck - crotch
    length = float(np.linalg.norm(axis))
    axis /= length
    height = (v - crotch) @ axis                                            # metres above the crotch
    below = 1.0 / (1.0 + np.exp(np.clip((height - LOWER_BODY_TOP * length) / PART_SOFTNESS, -50, 50)))
    legs, arms = part["leg_l"] + part["leg_r"], part["arm_l"] + part["arm_r"]
    lower = np.clip(legs + part["torso"] * below, 0.0, 1.0)
    lateral = pts["hip_joint_l"] - pts["hip_joint_r"]
    lateral -= (lateral @ axis) * axis
    lateral /= np.linalg.norm(lateral)
    side = (v - 0.5 * (crotch + neck)) @ lateral                            # + on the body's left
    left = np.clip(0.5 + side / (2 * SAGITTAL_BAND), 0.0, 1.0)
    out = {"upper_body": 1.0 - lower, "lower_body": lower, "arms": arms, "legs": legs, "torso": part["torso"],
           "head": part["head"], "left": left, "right": 1.0 - left}
    return {k: np.where(x < 1e-4, 0.0, np.where(x > 1 - 1e-4, 1.0, x)) for k, x in out.items()}


class MaskedPoissonBlend:
    """The masked Poisson solve of one mask on one rest mesh, factored once, for many changes.

    Args:
        rest_vertices: (V, 3) the mesh the gradients are taken on (the model's mean body).
        faces: (F, 3) int.
        weights: (V,) mask in [0, 1]; 0 = held fixed, 1 = changed in full.

    ``blend(d)`` maps a change d (V, 3) to the masked change (V, 3), 0.0 exactly where the
    weight is 0. Raises ``ParameterError`` for weights of another shape, outside [0, 1], or all 0.
    """

    def __init__(self, rest_vertices, faces, weights):
        x0 = np.asarray(rest_vertices, dtype=float)
        faces = np.asarray(faces, dtype=np.int64)
        w = np.asarray(weights, dtype=float)
        if w.shape != (len(x0),) or not np.isfinite(w).all() or w.min() < 0 or w.max() > 1:
            raise ParameterError(f"mask: weights of shape {w.shape}, expected ({len(x0)},) values in [0, 1]")
        self.weights = w
        self.free = np.flatnonzero(w > 0)
        if self.free.size == 0:
            raise ParameterError("mask: every weight is 0, expected a region to change")
        # 1. gradient operator G (3F, V) and the area-weighted, masked gradient target
        self.gradient = gradient_operator(x0, faces)
        a, b, c = (x0[faces[:, i]] for i in range(3))
        self.area3 = np.repeat(0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1), 3)
        self.face_weight3 = np.repeat(w[faces].mean(axis=1), 3)
        # 2. normal matrix G^T diag(area) G = the cotangent Laplacian, restricted to the free vertices
        laplacian = cotangent_laplacian(x0, faces)
        self.holds_nothing = self.free.size == len(w)
        sub = laplacian[self.free][:, self.free]
        if self.holds_nothing:  # nothing held: pin one vertex of weight 1 (translation)
            sub = sub + sp.diags(np.r_[1e-8 * laplacian.diagonal().mean(), np.zeros(self.free.size - 1)])
        self.solver = FactorizedSolver(sub)

    def __call__(self, change) -> np.ndarray:
        """The masked change (V, 3) of ``change`` (V, 3)."""
        d = np.asarray(change, dtype=float)
        if self.holds_nothing and np.all(self.weights == 1):
            return d.copy()
        # 3. right-hand side G^T diag(area) (w_f grad d), solved on the free vertices only
        target = (self.gradient @ d) * self.face_weight3[:, None]
        rhs = self.gradient.T @ (self.area3[:, None] * target)
        out = np.zeros_like(d)
        out[self.free] = self.solver.solve(rhs[self.free])
        return out


def masked_poisson_blend(rest_vertices, faces, weights, change) -> np.ndarray:
    """One masked Poisson solve (see the module docstring): the change (V, 3) of ``change``
    (V, 3) confined to ``weights`` (V,) on the rest mesh ``rest_vertices`` (V, 3), ``faces``
    (F, 3). For many changes of one mask, build ``MaskedPoissonBlend`` once."""
    return MaskedPoissonBlend(rest_vertices, faces, weights)(change)
