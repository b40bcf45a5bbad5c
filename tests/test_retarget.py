"""Retargeting (bodyspace.motion.retarget, Rupprecht §3.3.3), foot contacts and skating
(motion.contacts) and foot locking by two-bone IK (motion.ik): the shared CMU clips onto bodies
of 150 and 195 cm, the same clip restructured / turned Z-up in millimetres, round trips through
BVH files, and the pieces on synthetic data."""

from __future__ import annotations

import numpy as np
import pytest
from test_bvh import CLIPS, needs_clips
from test_matching import RESTRUCTURED, edit, through_file

from bodyspace.errors import MotionError
from bodyspace.motion.bvh import Motion, MotionSkeleton, read_bvh, skeleton_from_rig, write_bvh
from bodyspace.motion.contacts import detect_contacts, penetration, skating
from bodyspace.motion.ik import foot_goals, knee_angles, lock_feet, two_bone_ik
from bodyspace.motion.matching import graph_from_motion, graph_from_skeleton, match_skeletons
from bodyspace.motion.retarget import minimal_rotation, retarget, to_bvh
from bodyspace.rig.kinematics import forward_kinematics, rotvec_to_matrix
from bodyspace.rig.skeleton import Skeleton, body_skeleton
from bodyspace.studies.retargeting import clip_on_body
from bodyspace.synth.poses import load_pose_library


def body_of_stature(phenotype_model, stature_m: float, gender: float) -> np.ndarray:
    """A phenotype body (V, 3) whose vertical extent is ``stature_m`` (bisection on height)."""
    lo, hi = 0.0, 1.0
    for _ in range(30):
        mid = 0.5 * (lo + hi)
        v = phenotype_model.vertices({"gender": np.array([gender]), "height": np.array([mid]),
                                      "weight": np.array([0.5])})[0]
        lo, hi = (mid, hi) if np.ptp(v[:, 1]) < stature_m else (lo, mid)
    return v


@pytest.fixture(scope="module")
def bodies(phenotype_model, template):
    """Skeletons (default rig) and floors of a 150 cm woman and a 195 cm man."""
    out = {}
    for label, stature, gender in (("150", 1.50, 0.0), ("195", 1.95, 1.0)):
        v = body_of_stature(phenotype_model, stature, gender)
        out[label] = (body_skeleton(template.rigs["default"], v), float(v[:, 1].min()), v)
    return out


@pytest.fixture(scope="module")
def walk():
    return read_bvh(CLIPS[0])


def limb_directions(positions: np.ndarray, index: dict, pairs) -> np.ndarray:
    d = np.stack([positions[:, index[b]] - positions[:, index[a]] for a, b in pairs], axis=1)
    return d / np.linalg.norm(d, axis=-1, keepdims=True)


LIMBS = [("hip", "knee"), ("knee", "ankle"), ("shoulder", "elbow"), ("elbow", "wrist"), ("ankle", "toe")]


def angle_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.degrees(np.arccos(np.clip(np.einsum("...i,...i->...", a, b), -1.0, 1.0)))


# ----------------------------------------------------------------------------- pieces

def test_minimal_rotation_takes_a_onto_b(rng):
    a, b = rng.normal(size=(200, 3)), rng.normal(size=(200, 3))
    b[0] = -a[0]                                         # antiparallel
    b[1] = 2 * a[1]                                      # parallel
    R = minimal_rotation(a, b)
    au, bu = a / np.linalg.norm(a, axis=1)[:, None], b / np.linalg.norm(b, axis=1)[:, None]
    assert np.allclose(np.einsum("nij,nj->ni", R, au), bu, atol=1e-12)
    assert np.allclose(R @ np.swapaxes(R, 1, 2), np.eye(3), atol=1e-12)
    # smallest: the axis is perpendicular to both
    assert np.allclose(np.einsum("nij,nj->ni", R, np.cross(au, bu))[2:], np.cross(au, bu)[2:], atol=1e-12)
    assert np.allclose(R[1], np.eye(3))


def test_two_bone_ik_reaches_what_a_leg_can_reach(rng):
    F = 500
    hip = rng.normal(size=(F, 3))
    u = rng.normal(size=(F, 3))
    w = rng.normal(size=(F, 3))
    u *= (0.45 / np.linalg.norm(u, axis=1))[:, None]
    w *= (0.42 / np.linalg.norm(w, axis=1))[:, None]
    knee, ankle = hip + u, hip + u + w
    d = rng.uniform(0.1, 0.8, F)                          # all within |a - b| .. 0.98 (a + b)
    goal = hip + rng.normal(size=(F, 3)) / 1.0
    goal = hip + (goal - hip) * (d / np.linalg.norm(goal - hip, axis=1))[:, None]
    swing, bend = two_bone_ik(hip, knee, ankle, goal, np.tile([1.0, 0, 0], (F, 1)))
    knee2 = hip + np.einsum("fij,fj->fi", swing, u)
    ankle2 = knee2 + np.einsum("fij,fj->fi", swing @ bend, w)
    assert np.abs(np.linalg.norm(ankle2 - goal, axis=1)).max() < 1e-9
    assert np.allclose(np.linalg.norm(knee2 - hip, axis=1), 0.45)
    assert np.allclose(np.linalg.norm(ankle2 - knee2, axis=1), 0.42)
    # the bend stays in the leg's plane: the bend axis is unchanged by the bend itself
    axis = np.cross(u, w)
    axis /= np.linalg.norm(axis, axis=1)[:, None]
    assert np.allclose(np.einsum("fij,fj->fi", bend, axis), axis, atol=1e-9)
    # out of reach: straight toward the goal, short of it by the soft reach only
    far = hip + 2.0 * (goal - hip) / np.linalg.norm(goal - hip, axis=1)[:, None]
    swing, bend = two_bone_ik(hip, knee, ankle, far, np.tile([1.0, 0, 0], (F, 1)))
    ankle3 = hip + np.einsum("fij,fj->fi", swing, u) + np.einsum("fij,fj->fi", swing @ bend, w)
    toward = (far - hip) / 2.0
    assert np.allclose(np.einsum("fi,fi->f", ankle3 - hip, toward), np.linalg.norm(ankle3 - hip, axis=1))
    assert (np.linalg.norm(ankle3 - hip, axis=1) > 0.87 * 0.99).all()
    assert (np.linalg.norm(ankle3 - hip, axis=1) < 0.87).all()


def test_contacts_and_skating_on_a_synthetic_foot():
    dt = 1 / 100
    F = 300
    x = np.zeros((F, 1, 3))
    # planted 0-99 (drifting 5 cm over the run), swinging 100-199 (1.5 m/s, 10 cm up), planted 200-299
    x[:100, 0, 0] = np.linspace(0, 0.05, 100)
    x[100:200, 0, 0] = 0.05 + np.linspace(0, 1.5, 100)
    x[100:200, 0, 1] = 0.1 * np.sin(np.linspace(0, np.pi, 100))
    x[200:, 0, 0] = x[199, 0, 0]
    x[..., 1] += 0.08                                      # an ankle 8 cm over the floor
    contacts, clearance = detect_contacts(x, dt)
    assert clearance[0] == pytest.approx(0.08)
    assert contacts[:99, 0].all() and contacts[201:, 0].all() and not contacts[110:190, 0].any()
    s = skating(x, contacts, dt)
    # the first run slides 0.5 mm a frame: more than 2.5 cm from frame 50 on
    first = np.flatnonzero(contacts[:100, 0])
    expected = int((x[first, 0, 0] - x[first[0], 0, 0] > 0.025).sum()) / contacts.sum()
    assert s.share == pytest.approx(expected)
    assert s.max_slide == pytest.approx(x[first[-1], 0, 0] - x[0, 0, 0])
    assert penetration(x[..., 1] - 0.1) == pytest.approx(0.02)
    assert penetration(x[..., 1]) == 0.0
    with pytest.raises(MotionError, match="expected \\(frames, joints, 3\\)"):
        detect_contacts(x[:, 0], dt)


def test_foot_goals_never_jump():
    F = 200
    track = np.zeros((F, 3))
    track[:, 0] = np.linspace(0, 1, F)                    # a foot sliding at constant speed
    track[:, 1] = 0.08
    contact = np.zeros(F, bool)
    contact[20:60] = contact[70:120] = contact[180:] = True
    goal = foot_goals(track, contact, 0.08, blend_frames=12)
    assert np.ptp(goal[20:60, 0]) == 0 and np.ptp(goal[70:120, 0]) == 0
    assert np.abs(np.diff(goal[:, 0])).max() < 0.05                 # no jump anywhere
    assert np.allclose(goal[140:167], track[140:167])             # far from contacts: free
    assert (goal[:, 1] >= 0.08).all()


# ----------------------------------------------------------------------------- retargeting

@needs_clips
def test_limbs_point_where_the_source_limbs_point(walk, bodies):
    clip = walk.frames(slice(0, None, 5))
    for sk, floor, _ in bodies.values():
        out = retarget(clip, sk, target_floor=floor)
        J = out.joint_positions()
        src = {r: out.source_names.index(n) for r, n in out.match.source_landmarks.items()}
        tgt = {r: sk.bone_index(n) for r, n in out.match.target_landmarks.items()}
        for side in "LR":
            pairs = [(f"{a}.{side}", f"{b}.{side}") for a, b in LIMBS]
            ds = limb_directions(out.source_positions, src, pairs)
            dt = limb_directions(J, tgt, pairs)
            assert angle_deg(ds, dt).max() < 1e-4        # degrees (arccos near 1 rounds to ~1e-6)
        assert np.isfinite(J).all()
        assert (J[:, tgt["head"], 1] > J[:, tgt["pelvis"], 1] + 0.4).all()      # upright


@needs_clips
def test_root_path_scales_with_the_legs(walk, bodies):
    clip = walk.frames(slice(0, None, 5))
    short, tall = (retarget(clip, bodies[k][0], target_floor=bodies[k][1]) for k in ("150", "195"))
    assert 0.7 < short.leg_ratio < tall.leg_ratio < 1.3
    for out in (short, tall):
        p = out.joint_positions()[:, out.skeleton.bone_index(out.match.target_landmarks["pelvis"])]
        src = out.source_positions[:, out.source_names.index(out.match.source_landmarks["pelvis"])]
        assert np.allclose(p[:, [0, 2]], out.leg_ratio * src[:, [0, 2]], atol=1e-9)
        assert np.allclose(p[:, 1] - out.floor_shift, out.leg_ratio * src[:, 1], atol=1e-9)
        # the constant that puts the planted feet on the floor: how far the pelvis heights of the
        # two skeletons differ over their legs (CMU's root sits ~9 cm above its hip joints)
        assert abs(out.floor_shift) < 0.2 * out.leg_ratio


def turned(motion: Motion, T: np.ndarray, scale: float) -> Motion:
    """The same motion in other axes (T: 3x3 rotation, file axes to new ones) and another unit:
    offsets, End Sites and root positions turned and scaled, every local rotation conjugated."""
    sk = motion.skeleton
    skeleton = MotionSkeleton(sk.names, sk.parents, sk.offsets @ T.T * scale, sk.channels, sk.end_sites @ T.T * scale,
                              sk.end_site_parents)
    R = T @ motion.local_rotations() @ T.T
    t = motion.local_translations() / motion.unit @ T.T * scale
    return Motion.from_rotations(skeleton, R, t, motion.frame_time, motion.unit / scale, motion.name)


@needs_clips
@pytest.mark.parametrize("variant", ["zup_mm", "merged", "split"])
def test_restructured_and_turned_clips_give_the_same_motion(walk, bodies, variant, tmp_path):
    clip = walk.frames(slice(0, 400, 8))
    sk, floor, _ = bodies["195"]
    ref = retarget(clip, sk, target_floor=floor)
    if variant == "zup_mm":
        changed = turned(clip, np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]]), 56.444)
    else:
        changed = edit(clip, **RESTRUCTURED[variant])
    changed = through_file(changed, tmp_path, variant)
    got = retarget(changed, sk, target_floor=floor)
    J, Jref = got.joint_positions(), ref.joint_positions()
    tgt = {r: sk.bone_index(n) for r, n in ref.match.target_landmarks.items()}
    for side in "LR":
        pairs = [(f"{a}.{side}", f"{b}.{side}") for a, b in LIMBS]
        assert angle_deg(limb_directions(J, tgt, pairs), limb_directions(Jref, tgt, pairs)).max() < 1e-3
    # Z-up mm: written to 6 decimals of a millimetre; merged joints carried no rotation in the
    # CMU clips (LHipJoint, lhand are zero; without lhand the fingers pair differently, so only
    # landmarks are compared). An inserted spine joint takes a spine bone of its own, so the
    # bend between spine bones is spread differently: the chest moves by a few cm.
    tolerance = {"zup_mm": 1e-5, "merged": 1e-6, "split": 0.03}[variant]
    keys = sorted(tgt.values())
    assert np.abs(J[:, keys] - Jref[:, keys]).max() < tolerance, np.abs(J[:, keys] - Jref[:, keys]).max()


def _posed_skeleton_clip(sk: Skeleton, rng, frames=20):
    R = rotvec_to_matrix(rng.normal(scale=0.3, size=(frames, sk.n_bones, 3)))
    t = rng.normal(scale=0.2, size=(frames, 3))
    return R, t


@needs_clips
def test_a_clip_of_the_target_itself_comes_back_exactly(template, rng, tmp_path):
    """Rest pose = the target's own (A-pose): alignment is the identity and every bone is matched."""
    sk = body_skeleton(template.rigs["cmu_mb"], template.vertices)
    R, t = _posed_skeleton_clip(sk, rng)
    rest = skeleton_from_rig(sk, frames=len(R))
    order = [sk.bone_index(n) for n in rest.skeleton.names]
    tr = np.broadcast_to(rest.skeleton.offsets, (len(R), sk.n_bones, 3)).copy()
    tr[:, 0] += t
    motion = Motion.from_rotations(rest.skeleton, R[:, order], tr, frame_time=1 / 30)
    motion = read_bvh(write_bvh(tmp_path / "self.bvh", motion, precision=9), unit="m", translation="replace")
    out = retarget(motion, sk, target_floor=float(template.vertices[:, 1].min()))
    assert len(out.match.pairs) == sk.n_bones
    want = forward_kinematics(R, sk.heads, sk.parents)
    got = forward_kinematics(out.rotations, sk.heads, sk.parents)
    assert np.abs(got[..., :3, :3] - want[..., :3, :3]).max() < 1e-6
    # the root path is the clip's, moved to the origin and the floor, scale 1
    assert out.leg_ratio == pytest.approx(1.0, abs=1e-9)


@needs_clips
def test_onto_the_a_pose_body_and_back(walk, bodies, template, tmp_path):
    """T-pose CMU -> A-pose body -> BVH file -> the CMU skeleton's MotionBuilder rig: limbs point the same way."""
    clip = walk.frames(slice(0, None, 10))
    sk, floor, _ = bodies["150"]
    there = retarget(clip, sk, target_floor=floor)
    back_file = read_bvh(write_bvh(tmp_path / "on_body.bvh", to_bvh(there)), unit="m", translation="replace")
    assert back_file.skeleton.names[0] == "root" and back_file.n_frames == clip.n_frames
    # the BVH holds the same motion as the retargeted clip
    gp = back_file.global_positions()
    J = there.joint_positions()
    assert np.abs(gp - J[:, [sk.bone_index(n) for n in back_file.skeleton.names]]).max() < 1e-5
    cmu = body_skeleton(template.rigs["cmu_mb"], template.vertices)
    back = retarget(back_file, cmu, target_floor=float(template.vertices[:, 1].min()))
    Jb = back.joint_positions()
    src = {r: there.source_names.index(n) for r, n in there.match.source_landmarks.items()}
    tgt = {r: cmu.bone_index(n) for r, n in back.match.target_landmarks.items()}
    for side in "LR":
        pairs = [(f"{a}.{side}", f"{b}.{side}") for a, b in LIMBS]
        a = angle_deg(limb_directions(there.source_positions, src, pairs), limb_directions(Jb, tgt, pairs))
        assert a.max() < 1e-3


@needs_clips
def test_bvh_of_the_retargeted_clip_round_trips(walk, bodies, tmp_path):
    clip = walk.frames(slice(0, 60, 3))
    sk, floor, _ = bodies["195"]
    out = retarget(clip, sk, target_floor=floor)
    m = to_bvh(out)
    again = read_bvh(write_bvh(tmp_path / "t.bvh", m, precision=9), unit="m", translation="replace")
    assert again.skeleton.names == m.skeleton.names
    assert np.abs(again.values - m.values).max() < 1e-8


def test_refusals(template):
    sk = body_skeleton(template.rigs["cmu_mb"], template.vertices)
    rest = skeleton_from_rig(sk, frames=1)
    with pytest.raises(MotionError, match="expected a bodyspace.rig.skeleton.Skeleton"):
        retarget(rest, "not a skeleton")
    with pytest.raises(MotionError, match="no frames"):
        retarget(rest.frames(slice(0, 0)), sk)
    other = body_skeleton(template.rigs["game_engine"], template.vertices)
    wrong = match_skeletons(graph_from_motion(rest), graph_from_skeleton(other))
    with pytest.raises(MotionError, match="expected a match made for these two skeletons"):
        retarget(rest, sk, wrong)


# ----------------------------------------------------------------------------- feet

@pytest.fixture(scope="module")
def locked(walk, bodies):
    out = {}
    for label, (sk, floor, _) in bodies.items():
        before = retarget(walk, sk, target_floor=floor)
        after, lock = lock_feet(before)
        out[label] = (before, after, lock)
    return out


@needs_clips
def test_feet_stay_put_on_short_and_tall_bodies(walk, locked):
    for label, (before, after, lock) in locked.items():
        fb, fa = before.feet(), after.feet()
        assert (fb.contacts == fa.contacts).all()
        src = skating(fb.source, fb.contacts, walk.frame_time)
        b = skating(fb.target, fb.contacts, walk.frame_time)
        a = skating(fa.target, fa.contacts, walk.frame_time)
        assert a.share <= src.share and a.mean_speed <= src.mean_speed, (label, src, a)
        assert a.share < b.share and a.mean_speed < b.mean_speed
        assert penetration(fa.target[..., 1] - fa.clearance) < 0.01
        # only the legs and feet changed
        legs = np.zeros(before.skeleton.n_bones, bool)
        for n in before.skeleton.bone_names:
            if any(k in n for k in ("upperleg", "lowerleg", "foot", "toe")):
                legs[before.skeleton.bone_index(n)] = True
        assert np.array_equal(before.rotations[:, ~legs], after.rotations[:, ~legs])


@needs_clips
def test_no_knee_pops(locked):
    for label, (before, after, _) in locked.items():
        speed_before = np.abs(np.diff(knee_angles(before), axis=0)).max()
        speed_after = np.abs(np.diff(knee_angles(after), axis=0)).max()
        # the fastest knee of the locked clip is not much faster than the clip's own fastest
        assert speed_after < 1.5 * speed_before, (label, np.degrees([speed_before, speed_after]))


@needs_clips
def test_study_row_has_every_measure(walk, template):
    row = clip_on_body(walk.frames(slice(0, 300)), template.vertices)
    assert row["frames"] == 300 and 0.9 < row["leg_ratio"] < 1.1
    for stage in ("source", "retargeted", "foot_ik"):
        assert 0.0 <= row[stage]["share_sliding"] <= 1.0 and row[stage]["fastest_knee_deg_per_s"] > 0
    assert row["foot_ik"]["share_sliding"] <= row["retargeted"]["share_sliding"]
    assert row["foot_ik"]["feet_skin_below_floor_m"] < 0.01
    assert 0 <= row["arms_in_torso"]["frames_intersecting"] <= 300


def test_a_t_pose_clip_onto_the_a_pose_body(template, bodies, rng, tmp_path):
    """A source whose rest pose is a T-pose (the default rig posed in the library's t_pose and taken
    as a new rest skeleton), moving at random: on the A-pose body every limb points where the
    source's does, and at the source's rest the body's arms are horizontal."""
    rig = template.rigs["default"]
    sk = body_skeleton(rig, template.vertices)
    G = forward_kinematics(load_pose_library().rotations("t_pose", rig)[None], sk.heads, sk.parents)[0]
    heads = np.einsum("bij,bj->bi", G[:, :3, :3], sk.heads) + G[:, :3, 3]
    tails = np.einsum("bij,bj->bi", G[:, :3, :3], sk.tails) + G[:, :3, 3]
    t_skeleton = Skeleton("t_pose", sk.bone_names, sk.parents, heads, tails, np.zeros(sk.n_bones))
    rest = skeleton_from_rig(t_skeleton, frames=8)
    R = rotvec_to_matrix(rng.normal(scale=0.25, size=(8, sk.n_bones, 3)))
    R[0] = np.eye(3)                                                     # frame 0: the T-pose rest
    tr = np.broadcast_to(rest.skeleton.offsets, (8, sk.n_bones, 3)).copy()
    clip = Motion.from_rotations(rest.skeleton, R, tr, frame_time=1 / 30, name="tpose")
    clip = read_bvh(write_bvh(tmp_path / "tpose.bvh", clip, precision=9), unit="m", translation="replace")
    target, floor, _ = bodies["150"]
    out = retarget(clip, target, target_floor=floor)
    J = out.joint_positions()
    tgt = {r: target.bone_index(n) for r, n in out.match.target_landmarks.items()}
    # every bone below the hips and shoulders points where its source bone points (bone by bone:
    # the random twist-bone rotations bend the limbs, so landmark-to-landmark lines differ with
    # the proportions; a bone with several matched children, a foot with five toes, points to
    # their mean)
    limbs = [out.match.source_landmarks[f"{r}.{s}"] for r in ("hip", "shoulder") for s in "LR"]
    n_children = {}
    for seg in out.match.segments:
        n_children[seg.parent] = n_children.get(seg.parent, 0) + 1
    checked = 0
    for seg in out.match.segments:
        if seg.parent is None or n_children[seg.parent] > 1 or seg.parent[0] not in limbs and not any(
                seg.parent[0] in _below(clip.skeleton, j) for j in limbs):
            continue
        ds = out.source_positions[:, out.source_names.index(seg.child[0])] - \
            out.source_positions[:, out.source_names.index(seg.parent[0])]
        dt = J[:, target.bone_index(seg.child[1])] - J[:, target.bone_index(seg.parent[1])]
        ok = (np.linalg.norm(ds, axis=1) > 0.01) & (np.linalg.norm(dt, axis=1) > 0.01)
        if not ok.any():                                  # heads that coincide (metacarpals at the wrist)
            continue
        ds, dt = (d[ok] / np.linalg.norm(d[ok], axis=1)[:, None] for d in (ds, dt))
        assert angle_deg(ds, dt).max() < 1e-4, seg
        checked += 1
    assert checked > 20
    for side in "LR":
        arm = J[0, tgt[f"wrist.{side}"]] - J[0, tgt[f"shoulder.{side}"]]
        assert abs(arm[1]) / np.linalg.norm(arm) < 0.05                 # horizontal: the A-pose body in a T
    rest_arm = target.heads[tgt["wrist.L"]] - target.heads[tgt["shoulder.L"]]
    assert -rest_arm[1] / np.linalg.norm(rest_arm) > 0.3                  # the body's own rest is an A-pose


def _below(skeleton, name: str) -> set[str]:
    """Joint names in the subtree of ``name`` (inclusive) of a BVH skeleton."""
    j = skeleton.index(name)
    inside = {j}
    for k in range(skeleton.n_joints):                   # parents precede children
        if skeleton.parents[k] in inside:
            inside.add(k)
    return {skeleton.names[k] for k in inside}
