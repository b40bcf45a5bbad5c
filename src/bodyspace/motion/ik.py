"""Feet that stay put: analytic two-bone IK on the retargeted legs (Rupprecht §3.3.3).

A retargeted clip keeps the source's joint angles on other bone lengths, so a planted foot
slides and sinks. ``lock_feet`` moves each leg so that its foot joints go where they should:

* **Goals.** For each foot joint (ankle, toe) and each of the source's contact runs
  (``contacts.detect_contacts``) the anchor is the joint's mean horizontal position over the
  run; in the run the goal is the anchor, for ``blend`` seconds before and after it the goal
  slides linearly from the anchor back to the free position (no jump where a contact starts or
  ends). Every goal is kept at or above the joint's rest height over the floor (its clearance),
  so neither a planted nor a swinging foot goes through the floor.
* **Two-bone IK** (``two_bone_ik``), per frame, for hip (thigh head), knee (shin head) and
  ankle (foot head): the knee is bent to the angle that puts the ankle at the goal's distance
  from the hip (law of cosines, about the axis of the leg's current bend plane, so the knee
  keeps its direction), then the whole leg is swung about the hip onto the goal (the smallest
  rotation). Near full extension the reach is softened (``SOFT_REACH``: the last 2 % of the
  leg's length is approached exponentially, never reached) so the knee cannot snap straight
  between two frames: a knee pop. What this costs (the ankle's miss) is returned.
* **The foot** keeps its world orientation from the source, then turns about the ankle (the
  smallest rotation) to bring the toe to its own goal.
* **The sole** (optional, ``sole_points``): the foot's skin as points carried by the foot's
  bones. Where it would go below the floor (a toe-off, a tilted heel), that frame's goals are
  lifted by the depth and the leg is solved again (up to three passes), so the skin stays above
  the floor too, not only the joints.

The thigh's and shin's twist bones follow their bones (the deltas are applied to whole
sub-chains of world rotations), and the local rotations are recomputed from the world ones.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from bodyspace.errors import MotionError
from bodyspace.motion.contacts import contact_runs
from bodyspace.motion.retarget import Retargeted, minimal_rotation
from bodyspace.rig.kinematics import forward_kinematics, rotvec_to_matrix

__all__ = ["BLEND_SECONDS", "SOFT_REACH", "FootLock", "bend_angle", "foot_goals", "foot_vertices", "knee_angles",
           "lock_feet", "sole_points",
           "two_bone_ik"]

BLEND_SECONDS = 0.1      # goals ease between anchor and free position over this time
SOFT_REACH = 0.02        # share of the leg's length approached exponentially near full extension
_STRAIGHT = 1e-6         # |u x w| / (a b) below this: the leg is straight, its bend axis comes from the thigh


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-300)


def two_bone_ik(hip: np.ndarray, knee: np.ndarray, ankle: np.ndarray, goal: np.ndarray,
                straight_axis: np.ndarray, soft: float = SOFT_REACH) -> tuple[np.ndarray, np.ndarray]:
    """Rotations that bring the ankle to the goal: (swing (F, 3, 3), bend (F, 3, 3)).

    hip, knee, ankle, goal: (F, 3) world positions; straight_axis: (F, 3) the bend axis to use
    where the leg is straight (the thigh's lateral axis). The knee's sub-chain turns by ``bend``
    about the knee, then the whole leg by ``swing`` about the hip: new thigh world rotations are
    ``swing @ G``, the shin's ``swing @ bend @ G``. ``soft``: module docstring.
    """
    u, w = knee - hip, ankle - knee
    a, b = np.linalg.norm(u, axis=-1), np.linalg.norm(w, axis=-1)
    if (a <= 0).any() or (b <= 0).any():
        raise MotionError("two_bone_ik: a leg bone has zero length (hip, knee and ankle must be distinct)")
    cross = np.cross(u, w)
    s = np.linalg.norm(cross, axis=-1)
    axis = np.where((s > _STRAIGHT * a * b)[:, None], cross / np.maximum(s, 1e-300)[:, None], _unit(straight_axis))
    beta0 = np.arctan2(s, np.einsum("fi,fi->f", u, w))                 # current bend, 0 = straight
    d = np.linalg.norm(goal - hip, axis=-1)
    reach = a + b
    knee_limit = np.abs(a - b) + 1e-6 * reach
    start = reach * (1.0 - soft)
    over = np.maximum(d - start, 0.0)
    d_eff = np.where(d > start, start + soft * reach * (1.0 - np.exp(-over / np.maximum(soft * reach, 1e-300))), d)
    d_eff = np.clip(d_eff, knee_limit, reach * (1.0 - 1e-9))
    cos_beta = np.clip((d_eff ** 2 - a ** 2 - b ** 2) / (2.0 * a * b), -1.0, 1.0)
    beta1 = np.arccos(cos_beta)
    bend = rotvec_to_matrix(axis * (beta1 - beta0)[:, None])
    reached = knee + np.einsum("fij,fj->fi", bend, w) - hip
    toward = goal - hip
    swing = np.where((np.linalg.norm(toward, axis=-1) > 1e-9)[:, None, None], minimal_rotation(reached, np.where(
        np.linalg.norm(toward, axis=-1, keepdims=True) > 1e-9, toward, reached)), np.eye(3))
    return swing, bend


def foot_goals(track: np.ndarray, contact: np.ndarray, clearance: float, blend_frames: int) -> np.ndarray:
    """(F, 3) goals for one foot joint's track (F, 3) and its contacts (F,) (module docstring).

    The horizontal correction ``goal - track`` is ``anchor - track`` inside a contact run and
    eases linearly to zero over ``blend_frames`` outside it; between two runs closer than two
    blends it goes linearly from the one run's last correction to the next run's first, so the
    goal never jumps.
    """
    F = len(track)
    offset = np.zeros((F, 2))
    runs = contact_runs(contact)
    for a, b in runs:
        offset[a:b] = track[a:b][:, [0, 2]].mean(axis=0) - track[a:b][:, [0, 2]]
    ramp = blend_frames + 1
    bounds = [(-np.inf, None)] + [(a, b) for a, b in runs] + [(np.inf, None)]
    for (a0, b0), (a1, _) in zip(bounds[:-1], bounds[1:]):
        lo = 0 if a0 == -np.inf else int(b0)                      # first frame of the gap
        hi = F if a1 == np.inf else int(a1)                        # first frame after it
        if hi <= lo:
            continue
        f = np.arange(lo, hi)
        start = offset[lo - 1] if a0 != -np.inf else np.zeros(2)
        stop = offset[hi] if a1 != np.inf else np.zeros(2)
        if a0 != -np.inf and a1 != np.inf and hi - lo <= 2 * blend_frames:
            t = ((f - lo + 1) / (hi - lo + 1))[:, None]
            offset[lo:hi] = (1 - t) * start + t * stop
        else:
            w_prev = np.clip(1.0 - (f - lo + 1) / ramp, 0.0, 1.0)[:, None] if a0 != -np.inf else 0.0
            w_next = np.clip(1.0 - (hi - f) / ramp, 0.0, 1.0)[:, None] if a1 != np.inf else 0.0
            offset[lo:hi] = w_prev * start + w_next * stop
    goal = track.copy()
    goal[:, [0, 2]] += offset
    goal[:, 1] = np.maximum(track[:, 1], clearance)
    return goal


def _on_sphere(center: np.ndarray, goal: np.ndarray, radius: np.ndarray) -> np.ndarray:
    """(F, 3) the point at ``radius`` from ``center`` with the goal's height (as near as the
    radius allows) in the goal's horizontal direction: where a foot of that length can put its toe."""
    d = goal - center
    dy = np.clip(d[:, 1], -radius, radius)
    h = d[:, [0, 2]]
    hn = np.linalg.norm(h, axis=-1, keepdims=True)
    h = np.where(hn > 1e-9, h / np.maximum(hn, 1e-300), 0.0)
    hl = np.sqrt(np.maximum(radius ** 2 - dy ** 2, 0.0))[:, None]
    out = center.copy()
    out[:, 0] += h[:, 0] * hl[:, 0]
    out[:, 2] += h[:, 1] * hl[:, 0]
    out[:, 1] += dy
    return out


@dataclass(frozen=True)
class FootLock:
    """What ``lock_feet`` did: ``miss`` (F, K) distance of each foot joint from its goal after IK
    (metres; the soft reach and the foot's length keep a few from zero), ``goals`` (F, K, 3)."""

    miss: np.ndarray
    goals: np.ndarray


def _subtree(parents: np.ndarray, root: int) -> np.ndarray:
    inside = np.zeros(len(parents), bool)
    inside[root] = True
    changed = True
    while changed:                                       # parents need not precede children
        new = inside | ((parents >= 0) & inside[np.maximum(parents, 0)])
        changed = bool((new != inside).any())
        inside = new
    return inside


def _leg_bones(clip: Retargeted, side: str) -> tuple[int, int, int, int | None]:
    lm = clip.match.target_landmarks
    need = [f"hip.{side}", f"knee.{side}", f"ankle.{side}"]
    if not all(r in lm for r in need):
        raise MotionError(f"the target skeleton {clip.skeleton.name!r} has no {' / '.join(need)} found by the match; "
                          "the leg cannot be solved (give the joints with a map file)")
    toe = lm.get(f"toe.{side}")
    return (*(clip.skeleton.bone_index(lm[r]) for r in need), clip.skeleton.bone_index(toe) if toe else None)


def bend_angle(hip: np.ndarray, knee: np.ndarray, ankle: np.ndarray) -> np.ndarray:
    """(F,) the bend (radians, 0 = straight) at ``knee`` of tracks hip, knee, ankle (F, 3)."""
    u, w = knee - hip, ankle - knee
    return np.arctan2(np.linalg.norm(np.cross(u, w), axis=-1), np.einsum("fi,fi->f", u, w))


def knee_angles(clip: Retargeted, joint_positions: np.ndarray | None = None, source: bool = False) -> np.ndarray:
    """(F, 2) knee bend (radians, 0 = straight) of the left and right leg of the target (or,
    with ``source``, of the source clip)."""
    out = []
    for side in ("L", "R"):
        if source:
            lm = clip.match.source_landmarks
            J = clip.source_positions
            h, k, a = (clip.source_names.index(lm[f"{r}.{side}"]) for r in ("hip", "knee", "ankle"))
        else:
            J = clip.joint_positions() if joint_positions is None else joint_positions
            h, k, a, _ = _leg_bones(clip, side)
        out.append(bend_angle(J[:, h], J[:, k], J[:, a]))
    return np.stack(out, axis=1)


def foot_vertices(clip: Retargeted, weights, side: str | None = None) -> np.ndarray:
    """Indices of the vertices with at least half their weight (V, B) below an ankle landmark
    bone (one ``side``, "L" or "R", or both)."""
    W = sp.csr_matrix(weights, dtype=float)
    foot = np.zeros(clip.skeleton.n_bones, bool)
    for s in (side,) if side else ("L", "R"):
        foot |= _subtree(clip.skeleton.parents, _leg_bones(clip, s)[2])
    return np.flatnonzero(np.asarray(W[:, foot].sum(axis=1)).ravel() >= 0.5)


def sole_points(clip: Retargeted, weights, vertices: np.ndarray) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """The skin of each foot as points rigidly carried by its bones, for ``lock_feet(sole=...)``.

    weights: (V, B) skin weights; vertices: (V, 3) the rest body. Per side: the vertices with at
    least half their weight below the ankle landmark bone, each given to its heaviest bone there:
    (bone indices (P,), rest positions (P, 3)).
    """
    W = sp.csr_matrix(weights, dtype=float)
    v = np.asarray(vertices, dtype=float)
    out = {}
    for side in ("L", "R"):
        foot = _subtree(clip.skeleton.parents, _leg_bones(clip, side)[2])
        Wf = W[:, foot]
        mine = foot_vertices(clip, W, side)
        if len(mine) == 0:
            continue
        heaviest = np.flatnonzero(foot)[np.asarray(Wf[mine].argmax(axis=1)).ravel()]
        out[side] = (heaviest, v[mine])
    return out


def lock_feet(clip: Retargeted, blend: float = BLEND_SECONDS, soft: float = SOFT_REACH,
              sole: dict[str, tuple[np.ndarray, np.ndarray]] | None = None) -> tuple[Retargeted, FootLock]:
    """The clip with its feet kept where the source's feet are planted (module docstring).

    sole: per side (``"L"``, ``"R"``) the foot's skin as points on its bones (``sole_points``);
    given, a frame whose sole would go below the floor lifts that foot's goals by as much and
    solves the leg again (twice at most), so the skin, not only the joints, stays above the floor.
    Returns the new clip (same translation, new leg and foot rotations) and a ``FootLock``.
    """
    sk = clip.skeleton
    parents = sk.parents
    G = forward_kinematics(clip.rotations, sk.heads, parents, clip.translation)
    Rw = G[..., :3, :3].copy()                                           # (F, B, 3, 3) world rotations
    J = np.einsum("fbij,bj->fbi", Rw, sk.heads) + G[..., :3, 3]
    feet = clip.feet(J)
    blend_frames = max(int(round(blend / clip.frame_time)), 0)
    goals = feet.target.copy()
    role_index = {r: k for k, r in enumerate(feet.roles)}
    reached = np.full(goals.shape[:2], np.nan)
    changed = np.zeros(sk.n_bones, bool)
    F = clip.n_frames
    for side in ("L", "R"):
        h, k, a, toe = _leg_bones(clip, side)
        upper = _subtree(parents, h) & ~_subtree(parents, k)
        lower = _subtree(parents, k) & ~_subtree(parents, a)
        foot = _subtree(parents, a)
        ka = role_index.get(f"ankle.{side}")
        if ka is None:
            continue
        changed |= _subtree(parents, h)
        kt = role_index.get(f"toe.{side}") if toe is not None else None
        lateral = Rw[:, h] @ np.array([1.0, 0.0, 0.0])
        base_ankle = foot_goals(feet.target[:, ka], feet.contacts[:, ka], feet.clearance[ka], blend_frames)
        if sole is not None and side in sole:
            bones, rest = sole[side]
            # the sole as posed so far, relative to the ankle: one (F, 3, 3) @ (3, P_b) per bone
            sole_now = np.empty((F, len(bones), 3))
            for b in np.unique(bones):
                on = bones == b
                sole_now[:, on] = np.swapaxes(G[:, b, :3, :3] @ rest[on].T, 1, 2) + G[:, b, None, :3, 3]
            sole_now -= J[:, a][:, None]
        lift = np.zeros(F)
        for _ in range(3 if sole is not None and side in sole else 1):
            goal_a = base_ankle.copy()
            goal_a[:, 1] += lift
            swing, bend = two_bone_ik(J[:, h], J[:, k], J[:, a], goal_a, lateral, soft)
            ankle_new = J[:, h] + np.einsum("fij,fj->fi", swing,
                                            J[:, k] - J[:, h] + np.einsum("fij,fj->fi", bend, J[:, a] - J[:, k]))
            turn = np.broadcast_to(np.eye(3), (F, 3, 3))
            if kt is not None:
                toe_now = ankle_new + (J[:, toe] - J[:, a])               # the foot kept its world rotation
                goal_t = foot_goals(toe_now, feet.contacts[:, kt], feet.clearance[kt] + lift, blend_frames)
                reach = _on_sphere(ankle_new, goal_t, np.linalg.norm(toe_now - ankle_new, axis=-1))
                turn = minimal_rotation(toe_now - ankle_new, reach - ankle_new)
            if sole is None or side not in sole:
                break
            # the foot subtree moved rigidly: x -> ankle_new + turn (x - ankle_old)
            low = (sole_now @ turn[:, 1, :, None])[..., 0].min(axis=1) + ankle_new[:, 1]
            if (low >= -1e-4).all():
                break
            lift = lift + np.maximum(-low, 0.0)
        goals[:, ka] = goal_a
        reached[:, ka] = np.linalg.norm(ankle_new - goal_a, axis=-1)
        Rw[:, upper] = swing[:, None] @ Rw[:, upper]
        Rw[:, lower] = (swing @ bend)[:, None] @ Rw[:, lower]
        if kt is not None:
            Rw[:, foot] = turn[:, None] @ Rw[:, foot]
            goals[:, kt] = goal_t
            reached[:, kt] = np.linalg.norm(ankle_new + np.einsum("fij,fj->fi", turn, toe_now - ankle_new) - goal_t,
                                            axis=-1)
    # new local rotations of the legs' bones; every other bone keeps its own exactly
    R = clip.rotations.copy()
    legs = np.flatnonzero(changed & (parents >= 0))
    R[:, legs] = np.swapaxes(Rw[:, parents[legs]], -1, -2) @ Rw[:, legs]
    return clip.with_pose(R), FootLock(reached, goals)
