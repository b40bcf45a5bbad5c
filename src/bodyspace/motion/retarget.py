"""Retargeting a motion capture clip onto a body's skeleton (Rupprecht §3.3.3).

Input: a source ``Motion`` (any BVH skeleton, any axes and unit) and a target ``Skeleton`` (a
rig regressed on one body, metres, our axes), joined by a ``SkeletonMatch`` (``matching``).
Output: a ``Retargeted`` clip: per-frame local rotations of every target bone (rest-pose world
axes, about the bone heads: the convention of ``rig.kinematics``) and a root translation, with
the floor at y = 0.

The steps, in the right frames:

1. **Axes.** The match knows the source's up, left and front (``SkeletonMatch.source_axes``);
   ``M`` (rows left, up, front) takes the file's axes to ours (+X left, +Y up, +Z front):
   ``p_ours = M p_file``, ``R_ours = M R_file Mᵀ``. The source's global rotations
   ``Rg_j`` (rest-pose world axes, BVH rest frames are the file's axes) are taken to ours.
2. **Rest-pose alignment.** Source and target rest poses differ (CMU: arms down, legs apart;
   MakeHuman: an A-pose). For each matched limb pair (the hips, the shoulders and every joint
   below them) the rest direction of the bone in both skeletons (from the pair's pivot to its
   matched child pairs' pivots, else to all matched pairs below it, else to the joint's End
   Site / bone tail) gives ``A``, the minimal rotation taking the target's rest direction onto
   the source's. The target bone's global rotation is then ``G_t = Rg_s · A``: at the source's
   rest (``Rg_s = I``) the target takes the source's rest pose, and in every frame the target
   bone points where the source bone points; a minimal rotation leaves the twist about the
   bone as the source has it. Pairs above the limbs (pelvis bones, spine, clavicles, neck,
   head) take their parent pair's ``A`` (the identity at the pelvis: both skeletons stand
   upright facing +Z): their rest directions differ by how the skeletons were built (where a
   CMU hip joint sits in the pelvis), not by pose, so the target keeps its own trunk and the
   source's rotations apply to it as local rotations.
3. **Bones without a source joint** keep their rest pose relative to the parent (local
   identity): twist bones, fingers and face bones the clip does not have. Target bones strictly
   between two matched spine or neck bones share the bend between them evenly (spherical
   interpolation of the two globals), so one CMU chest joint bends three MakeHuman spine bones.
4. **Local rotations** ``R_b = Gᵀ_parent(b) G_b``.
5. **Root translation**, scaled by the ratio of leg lengths ``k = L_target / L_source``
   (hip → knee → ankle, averaged over both legs): the target's pelvis goes to
   ``k (p_s − p_s(0))`` horizontally (the clip starts at the origin) and to ``k`` times the
   source pelvis's height above the source floor. The source floor is the 5th percentile of
   the lowest foot point per frame (ankles, toes, their End Sites). A constant vertical shift
   then puts the target's feet on the floor: the median over the source's contact frames of
   the target sole's height (``contacts``) goes to 0.

Foot contacts, foot locking by two-bone IK and the skating measures are in
``motion.contacts``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from bodyspace.errors import MotionError
from bodyspace.motion.bvh import Motion, MotionSkeleton, skeleton_from_rig
from bodyspace.motion.contacts import detect_contacts
from bodyspace.motion.matching import SkeletonMatch, graph_from_motion, graph_from_skeleton, match_skeletons
from bodyspace.rig.kinematics import forward_kinematics, matrix_to_rotvec, rotvec_to_matrix, topological_order
from bodyspace.rig.skeleton import Skeleton

__all__ = ["FOOT_ROLES", "FootTracks", "Retargeted", "axes_to_ours", "leg_length", "minimal_rotation",
           "rest_alignment", "retarget", "source_floor", "to_bvh"]

# A rest direction shorter than this (metres) is undefined: the next candidate is tried.
_MIN_DIRECTION = 0.005
# Parts whose target bones between two matched bones share the bend (a spine, a neck).
_SPREAD_PARTS = ("spine", "neck", "trunk")
_FLOOR_PERCENTILE = 5.0
# Landmarks from which on (inclusive) bones are aligned by direction; above them (pelvis bones,
# spine, clavicles, neck, head) the target keeps its own rest structure.
_LIMB_ROOTS = ("hip.L", "hip.R", "shoulder.L", "shoulder.R")


@dataclass(frozen=True)
class Retargeted:
    """A clip on a target skeleton (F frames, B bones; metres, our axes, floor at y = 0).

    rotations: (F, B, 3, 3) local rotations in rest-pose world axes about the bone heads
    (``rig.kinematics``); translation: (F, 3) added to every bone after posing.
    leg_ratio: target / source leg length (the root path's scale); frame_time: seconds.
    source_positions: (F, J, 3) the source's joints (metres, our axes, its floor at y = 0,
    horizontally at the origin in frame 0; unscaled); target_floor: the y of the target's soles
    in its rest coordinates; floor_shift: the constant vertical shift that put the target's feet
    on the floor (metres).
    """

    skeleton: Skeleton
    rotations: np.ndarray
    translation: np.ndarray
    frame_time: float
    leg_ratio: float
    match: SkeletonMatch
    source_positions: np.ndarray
    source_names: tuple[str, ...]
    target_floor: float = 0.0
    floor_shift: float = 0.0

    @property
    def n_frames(self) -> int:
        return self.rotations.shape[0]

    def transforms(self) -> np.ndarray:
        """(F, B, 4, 4) posed bone transforms (``forward_kinematics``, translation included)."""
        return forward_kinematics(self.rotations, self.skeleton.heads, self.skeleton.parents, self.translation)

    def joint_positions(self) -> np.ndarray:
        """(F, B, 3) posed bone heads (metres, floor at y = 0)."""
        G = self.transforms()
        return np.einsum("fbij,bj->fbi", G[..., :3, :3], self.skeleton.heads) + G[..., :3, 3]

    def with_pose(self, rotations: np.ndarray, translation: np.ndarray | None = None) -> "Retargeted":
        """The same clip with other rotations (and translation)."""
        return Retargeted(self.skeleton, np.asarray(rotations, dtype=float),
                          self.translation if translation is None else np.asarray(translation, dtype=float),
                          self.frame_time, self.leg_ratio, self.match, self.source_positions, self.source_names,
                          self.target_floor, self.floor_shift)

    def feet(self, joint_positions: np.ndarray | None = None) -> "FootTracks":
        """The foot joints (ankles, toes) both skeletons have, their tracks and the source's contacts."""
        s_idx = {n: i for i, n in enumerate(self.source_names)}
        roles = [r for r in FOOT_ROLES if r in self.match.source_landmarks and r in self.match.target_landmarks]
        if not roles:
            raise MotionError("the match found no ankle or toe in both skeletons; feet cannot be tracked")
        s = [s_idx[self.match.source_landmarks[r]] for r in roles]
        t = [self.skeleton.bone_index(self.match.target_landmarks[r]) for r in roles]
        source = self.source_positions[:, s]
        contacts, _ = detect_contacts(source, self.frame_time)
        pos = self.joint_positions() if joint_positions is None else joint_positions
        return FootTracks(tuple(roles), np.array(t), source, pos[:, t],
                          self.skeleton.heads[t, 1] - self.target_floor, contacts)


# Foot landmarks whose tracks are kept on the floor, in this order.
FOOT_ROLES = ("ankle.L", "toe.L", "ankle.R", "toe.R")


@dataclass(frozen=True)
class FootTracks:
    """Foot joints of a retargeted clip: ``roles`` (K,) landmark names, ``bones`` (K,) target
    bone indices, ``source`` / ``target`` (F, K, 3) tracks (metres, floor at 0; the source
    unscaled), ``clearance`` (K,) each target joint's rest height above its soles, ``contacts``
    (F, K) the source's contact frames (``contacts.detect_contacts``)."""

    roles: tuple[str, ...]
    bones: np.ndarray
    source: np.ndarray
    target: np.ndarray
    clearance: np.ndarray
    contacts: np.ndarray


# ----------------------------------------------------------------------------- pieces

def axes_to_ours(axes: np.ndarray) -> np.ndarray:
    """(3, 3) rotation taking a skeleton's coordinates to ours from its body axes (rows up,
    left, front in its coordinates, as ``SkeletonMatch.source_axes``): rows left, up, front."""
    a = np.asarray(axes, dtype=float)
    M = a[[1, 0, 2]]
    # Snapped or measured axes are orthonormal up to rounding; make M a proper rotation.
    U, _, Vt = np.linalg.svd(M)
    M = U @ Vt
    if np.linalg.det(M) < 0:
        raise MotionError("the source's body axes (up, left, front) are left-handed; expected left = up x front")
    return M


def minimal_rotation(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(..., 3, 3) the smallest rotation taking directions a (..., 3) onto b (..., 3).

    Opposite directions turn by pi about an axis perpendicular to a.
    """
    a = np.asarray(a, dtype=float)
    b = np.asarray(b, dtype=float)
    a = a / np.linalg.norm(a, axis=-1, keepdims=True)
    b = b / np.linalg.norm(b, axis=-1, keepdims=True)
    axis = np.cross(a, b)
    s = np.linalg.norm(axis, axis=-1)
    c = np.einsum("...i,...i->...", a, b)
    angle = np.arctan2(s, c)
    # perpendicular fallback for antiparallel vectors: a x e for the coordinate axis least along a
    e = np.eye(3)[np.argmin(np.abs(a), axis=-1)]
    perp = np.cross(a, e)
    perp /= np.linalg.norm(perp, axis=-1, keepdims=True)
    unit = np.where((s > 1e-12)[..., None], axis / np.maximum(s, 1e-300)[..., None], perp)
    return rotvec_to_matrix(unit * angle[..., None])


def leg_length(positions: dict[str, np.ndarray]) -> float:
    """Mean over the legs present of |hip - knee| + |knee - ankle| (metres); ``positions`` maps
    landmark roles (``hip.L`` ...) to rest positions."""
    lengths = []
    for side in ("L", "R"):
        p = [positions.get(f"{r}.{side}") for r in ("hip", "knee", "ankle")]
        if all(x is not None for x in p):
            lengths.append(np.linalg.norm(p[0] - p[1]) + np.linalg.norm(p[1] - p[2]))
    if not lengths:
        raise MotionError("no leg with hip, knee and ankle found in the match; the root path cannot be scaled "
                          "(give the joints with a map file)")
    return float(np.mean(lengths))


def _foot_points(motion: Motion, match: SkeletonMatch, M: np.ndarray) -> np.ndarray:
    """(F, K, 3) the source's ankles, toes and the End Sites below them, metres, our axes."""
    sk = motion.skeleton
    Rg, pos = motion.global_transforms()
    feet = [sk.index(match.source_landmarks[r]) for r in ("ankle.L", "ankle.R", "toe.L", "toe.R")
            if r in match.source_landmarks]
    if not feet:
        raise MotionError(f"{motion.name}: no ankle or toe joint found by the match; the floor cannot be found")
    below = set(feet)
    for j in range(sk.n_joints):                       # parents precede children
        if sk.parents[j] in below:
            below.add(j)
    pts = [pos[:, sorted(below)]]
    ends = [e for e, j in enumerate(sk.end_site_parents) if j in below]
    if ends:
        p = sk.end_site_parents[ends]
        pts.append(pos[:, p] + np.einsum("feij,ej->fei", Rg[:, p], sk.end_sites[ends] * motion.unit))
    return np.concatenate(pts, axis=1) @ M.T


def source_floor(foot_points: np.ndarray) -> float:
    """Height (y, metres) of the floor under a clip: the 5th percentile over frames of the lowest
    foot point. foot_points: (F, K, 3) in our axes."""
    return float(np.percentile(np.asarray(foot_points)[..., 1].min(axis=1), _FLOOR_PERCENTILE))


def rest_alignment(match: SkeletonMatch, source_pivots: np.ndarray, source_tips: np.ndarray,
                   source_names: tuple[str, ...], target: Skeleton) -> dict[str, np.ndarray]:
    """Per matched target bone, the rest alignment ``A`` (3, 3): for limbs the minimal rotation
    taking the target bone's rest direction onto the source joint's, above them the parent
    pair's (module docstring, step 2).

    source_pivots, source_tips: (J, 3) the source's rest joints and segment ends in our axes
    (tips NaN where unknown).
    """
    s_idx = {n: i for i, n in enumerate(source_names)}
    t_idx = {n: i for i, n in enumerate(target.bone_names)}
    children: dict[tuple[str, str], list[tuple[str, str]]] = {}
    below: dict[tuple[str, str], list[tuple[str, str]]] = {}
    parent_of = {seg.child: seg.parent for seg in match.segments}
    for seg in match.segments:
        if seg.parent is not None:
            children.setdefault(seg.parent, []).append(seg.child)
            up = seg.parent
            while up is not None:
                below.setdefault(up, []).append(seg.child)
                up = parent_of.get(up)
    # limb joints: the hips, shoulders and everything below them in the source
    limb = {match.source_landmarks[r] for r in _LIMB_ROOTS if r in match.source_landmarks}
    src_parent = {seg.child[0]: seg.parent[0] if seg.parent else None for seg in match.segments}
    out: dict[str, np.ndarray] = {}
    for seg in sorted(match.segments, key=lambda s: _depth(parent_of, s.child)):
        s, t = seg.child
        i, b = s_idx[s], t_idx[t]
        inherited = out.get(seg.parent[1], np.eye(3)) if seg.parent is not None else np.eye(3)
        if not _ancestor_in(s, limb, src_parent):
            out[t] = inherited
            continue
        candidates = []
        for group in (children.get(seg.child, []), below.get(seg.child, [])):
            if group:
                ps = np.mean([source_pivots[s_idx[c[0]]] for c in group], axis=0)
                pt = np.mean([target.heads[t_idx[c[1]]] for c in group], axis=0)
                candidates.append((ps - source_pivots[i], pt - target.heads[b]))
        if np.isfinite(source_tips[i]).all():
            candidates.append((source_tips[i] - source_pivots[i], target.tails[b] - target.heads[b]))
        A = inherited
        for ds, dt in candidates:
            if np.linalg.norm(ds) > _MIN_DIRECTION and np.linalg.norm(dt) > _MIN_DIRECTION:
                A = minimal_rotation(dt, ds)
                break
        out[t] = A
    return out


def _ancestor_in(joint: str, group: set, parent: dict) -> bool:
    up = joint
    while up is not None:
        if up in group:
            return True
        up = parent.get(up)
    return False


def _depth(parent_of: dict, child) -> int:
    d, up = 0, parent_of.get(child)
    while up is not None:
        d, up = d + 1, parent_of.get(up)
    return d


def _slerp_from_identity(R: np.ndarray, t: float) -> np.ndarray:
    """(..., 3, 3) the rotation ``R^t`` (same axis, t times the angle)."""
    return rotvec_to_matrix(matrix_to_rotvec(R) * t)


# ----------------------------------------------------------------------------- retarget

def retarget(motion: Motion, skeleton: Skeleton, match: SkeletonMatch | None = None, *,
             target_floor: float | None = None) -> Retargeted:
    """The clip ``motion`` on the target ``skeleton`` (module docstring).

    motion: the source clip (any axes and unit; ``Motion.unit`` already resolved).
    skeleton: the target (B bones, metres, our axes), e.g. ``body_skeleton(rig, vertices)``.
    match: ``match_skeletons(graph_from_motion(motion), graph_from_skeleton(skeleton))`` by
        default; pass one to reuse it or to apply a map file.
    target_floor: the y of the target body's soles at rest (e.g. its lowest vertex); by default
        the lowest bone end of the skeleton. The result stands on y = 0.
    Returns a ``Retargeted`` (F frames).
    """
    if not isinstance(skeleton, Skeleton):
        raise MotionError(f"skeleton: got {type(skeleton).__name__}, expected a bodyspace.rig.skeleton.Skeleton")
    if motion.n_frames == 0:
        raise MotionError(f"{motion.name}: has no frames; expected a clip with at least one frame")
    source_graph = graph_from_motion(motion)
    if match is None:
        match = match_skeletons(source_graph, graph_from_skeleton(skeleton))
    M = axes_to_ours(match.source_axes)
    sk = motion.skeleton
    F, B = motion.n_frames, skeleton.n_bones
    s_idx = {n: i for i, n in enumerate(sk.names)}
    t_idx = {n: i for i, n in enumerate(skeleton.bone_names)}
    for p in match.pairs:
        if p.source not in s_idx or p.target not in t_idx:
            raise MotionError(f"match pair {p.source} -> {p.target}: not a joint of clip {motion.name!r} and a bone of "
                              f"skeleton {skeleton.name!r}; expected a match made for these two skeletons")
    # 1. the source's global rotations and positions in our axes
    Rg, pos = motion.global_transforms()                              # (F, J, 3, 3), (F, J, 3)
    Rg = M @ Rg @ M.T
    pos = pos @ M.T
    pivots = source_graph.pivots @ M.T
    tips = source_graph.tips @ M.T
    # 2. rest alignment per matched target bone
    A = rest_alignment(match, pivots, tips, sk.names, skeleton)
    # 3. target globals: matched bones from the source, the others follow their parent
    G = np.empty((F, B, 3, 3))
    matched = np.zeros(B, bool)
    src_of = {p.target: p.source for p in match.pairs}
    part_of = {p.target: p.part for p in match.pairs}
    order = _parent_first(skeleton.parents)
    for b in order:
        name = skeleton.bone_names[b]
        p = skeleton.parents[b]
        if name in src_of:
            G[:, b] = Rg[:, s_idx[src_of[name]]] @ A[name]
            matched[b] = True
        elif p >= 0:
            G[:, b] = G[:, p]
        else:
            G[:, b] = np.eye(3)
    for seg in match.segments:
        if seg.parent is None or not seg.target or part_of.get(seg.child[1]) not in _SPREAD_PARTS:
            continue
        ga, gc = G[:, t_idx[seg.parent[1]]], G[:, t_idx[seg.child[1]]]
        rel = np.swapaxes(ga, -1, -2) @ gc
        k = len(seg.target)
        for i, name in enumerate(seg.target, start=1):
            G[:, t_idx[name]] = ga @ _slerp_from_identity(rel, i / (k + 1))
        # bones below a spread bone that are not matched follow it
        spread = {t_idx[n] for n in seg.target}
        for b in order:
            if not matched[b] and b not in spread and skeleton.parents[b] in spread:
                spread.add(b)
                G[:, b] = G[:, skeleton.parents[b]]
    # 4. locals
    parents = skeleton.parents
    R = G.copy()
    has = parents >= 0
    R[:, has] = np.swapaxes(G[:, parents[has]], -1, -2) @ G[:, has]
    # 5. root path scaled by the leg ratio
    feet = _foot_points(motion, match, M)
    floor_s = source_floor(feet)
    src_rest = {r: pivots[s_idx[n]] for r, n in match.source_landmarks.items()}
    tgt_rest = {r: skeleton.heads[t_idx[n]] for r, n in match.target_landmarks.items()}
    k = leg_length(tgt_rest) / leg_length(src_rest)
    pelvis_s = s_idx[match.source_landmarks["pelvis"]]
    pelvis_t = t_idx[match.target_landmarks["pelvis"]]
    origin = pos[0, pelvis_s].copy()
    origin[1] = floor_s
    src_positions = pos - origin
    goal = k * src_positions[:, pelvis_s]                              # (F, 3) target pelvis, floor at 0
    Gfk = forward_kinematics(R, skeleton.heads, parents)
    pelvis_fk = Gfk[:, pelvis_t, :3, :3] @ skeleton.heads[pelvis_t] + Gfk[:, pelvis_t, :3, 3]
    translation = goal - pelvis_fk
    floor_t = float(np.min(np.r_[skeleton.heads[:, 1], skeleton.tails[:, 1]])) if target_floor is None \
        else float(target_floor)
    out = Retargeted(skeleton, R, translation, motion.frame_time, k, match, src_positions, sk.names,
                     target_floor=floor_t)
    # the target's feet on the floor: the median height of its planted foot joints over their
    # rest height above the floor, over the source's contact frames, goes to 0
    feet = out.feet()
    residual = feet.target[..., 1] - feet.clearance
    shift = -float(np.median(residual[feet.contacts]) if feet.contacts.any() else residual.min())
    return Retargeted(skeleton, R, translation + np.array([0.0, shift, 0.0]), motion.frame_time, k, match,
                      src_positions, sk.names, floor_t, shift)


def _parent_first(parents: np.ndarray) -> list[int]:
    return [int(b) for b in topological_order(parents)]


# ----------------------------------------------------------------------------- output

def to_bvh(clip: Retargeted, order: str = "ZXY") -> Motion:
    """The retargeted clip as a BVH ``Motion`` on the target skeleton (metres, our axes): joints
    at the bone heads in depth-first order, End Sites at the tails of end bones, the root with
    position channels (its head plus the translation)."""
    rest = skeleton_from_rig(clip.skeleton, 1, clip.frame_time, order)
    sk: MotionSkeleton = rest.skeleton
    where = [clip.skeleton.bone_index(n) for n in sk.names]
    R = clip.rotations[:, where]
    t = np.broadcast_to(sk.offsets, (clip.n_frames,) + sk.offsets.shape).copy()
    roots = np.flatnonzero(sk.parents < 0)
    t[:, roots] = sk.offsets[roots] + clip.translation[:, None, :]
    return Motion.from_rotations(sk, R, t, frame_time=clip.frame_time, unit=1.0, name=clip.skeleton.name)
