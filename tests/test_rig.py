"""Tests for bodyspace.rig: rotations, forward kinematics, skinning, Blender frames, pose library."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest
import scipy.sparse as sp
from scipy.spatial.transform import Rotation

try:
    import bodyspace  # noqa: F401
except ModuleNotFoundError:  # not installed: run from the source tree
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "src"))

from bodyspace.errors import AssetError, ParameterError
from bodyspace.rig.kinematics import (
    bone_rest_frames,
    dual_quaternion_skinning,
    forward_kinematics,
    linear_blend_skinning,
    matrix_to_rotvec,
    rotvec_to_matrix,
    topological_order,
)
from bodyspace.rig.posing import count_folded_triangles, folded_triangles, place_on_ground, pose_bodies
from bodyspace.synth.poses import LIBRARY_PATH, load_pose_library

FLIP_X = np.array([-1.0, 1.0, 1.0])


# ------------------------------------------------------------------------------- fixtures

@pytest.fixture(scope="module")
def template():
    from bodyspace.data.template import load_template
    try:
        return load_template()
    except AssetError as e:  # the CC0 assets are not available offline
        pytest.skip(f"template assets unavailable: {e}")


@pytest.fixture(scope="module")
def rig(template):
    return template.rigs["default"]


@pytest.fixture(scope="module")
def body(template):
    """A symmetric male body (the phenotype model is exactly left/right symmetric)."""
    from bodyspace.synth.phenotype import PhenotypeModel
    return PhenotypeModel(template).vertices({"gender": 1.0, "height": 0.6})[0]


@pytest.fixture(scope="module")
def library():
    return load_pose_library()


@pytest.fixture(scope="module")
def posed_library(body, rig, library):
    """Every library pose on ``body``, on the ground: (P, V, 3) vertices and (P, B, 3) joints."""
    R = library.stack(library.names, rig)
    v, j = pose_bodies(np.broadcast_to(body, (len(R),) + body.shape), rig, R, on_ground=True, return_joints=True)
    return dict(zip(library.names, v)), dict(zip(library.names, j))


@pytest.fixture(scope="module")
def rest_on_ground(body, rig):
    return pose_bodies(body, rig, np.broadcast_to(np.eye(3), (rig.n_bones, 3, 3)), on_ground=True, return_joints=True)


def bone_vertices(template, rig, prefixes, side=""):
    """Vertices skinned mostly (> 0.5) to the bones whose names start with one of ``prefixes``."""
    cols = [i for i, b in enumerate(rig.bone_names) if b.endswith(side) and b.startswith(tuple(prefixes))]
    w = np.asarray(rig.weights[:, cols].sum(axis=1)).ravel()
    return np.flatnonzero(w > 0.5)


def mirrored_bone_index(rig):
    idx = {b: i for i, b in enumerate(rig.bone_names)}
    swap = {".L": ".R", ".R": ".L"}
    return np.array([idx[b[:-2] + swap[b[-2:]]] if b[-2:] in swap else idx[b] for b in rig.bone_names])


# ------------------------------------------------------------------------------ rotations

def test_rodrigues_matches_scipy_and_round_trips():
    rng = np.random.default_rng(0)
    axes = rng.normal(size=(500, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    angles = np.concatenate([rng.uniform(0, np.pi - 1e-3, 480), [0, 1e-12, 1e-8, 1e-6, 1e-4],
                             np.pi - np.array([1e-3, 1e-5, 1e-7, 1e-9, 1e-11, 1e-13]), np.full(9, np.pi - 1e-14)])
    rv = axes * angles[:, None]
    R = rotvec_to_matrix(rv)
    np.testing.assert_allclose(R, Rotation.from_rotvec(rv).as_matrix(), atol=1e-13)
    back = matrix_to_rotvec(R)
    # near pi the matrix fixes the rotation vector only up to O(eps) of the angle gap
    np.testing.assert_allclose(back, rv, atol=1e-7)
    np.testing.assert_allclose(back[angles < np.pi - 1e-3], rv[angles < np.pi - 1e-3], atol=1e-12)
    np.testing.assert_allclose(rotvec_to_matrix(back), R, atol=1e-13)


def test_matrix_to_rotvec_at_exactly_pi_and_batched_shapes():
    for axis in (np.eye(3)[0], np.eye(3)[1], np.eye(3)[2], np.array([1.0, -2.0, 0.5]) / np.sqrt(5.25)):
        R = rotvec_to_matrix(axis * np.pi)
        back = matrix_to_rotvec(R)
        assert abs(np.linalg.norm(back) - np.pi) < 1e-12
        assert min(np.abs(back - axis * np.pi).max(), np.abs(back + axis * np.pi).max()) < 1e-7
        np.testing.assert_allclose(rotvec_to_matrix(back), R, atol=1e-12)
    assert rotvec_to_matrix(np.zeros((2, 4, 3))).shape == (2, 4, 3, 3)
    assert matrix_to_rotvec(np.broadcast_to(np.eye(3), (2, 4, 3, 3))).shape == (2, 4, 3)
    np.testing.assert_array_equal(matrix_to_rotvec(np.eye(3)), np.zeros(3))
    with pytest.raises(ParameterError):
        rotvec_to_matrix(np.zeros(4))


# ---------------------------------------------------------------------- forward kinematics

def test_forward_kinematics_two_bone_chain_by_hand():
    # bone 0 at the origin, bone 1 (its child) with head at (1, 0, 0); both turn 90 degrees about +Z.
    # Listed child first, so FK must not rely on index order.
    parents = np.array([1, -1])
    heads = np.array([[1.0, 0, 0], [0.0, 0, 0]])
    R = rotvec_to_matrix(np.array([[[0, 0, np.pi / 2], [0, 0, np.pi / 2]]]))
    G = forward_kinematics(R, heads, parents)
    assert G.shape == (1, 2, 4, 4)

    def apply(g, p):
        return g[:3, :3] @ p + g[:3, 3]
    # parent: plain rotation about the origin
    np.testing.assert_allclose(apply(G[0, 1], [1, 0, 0]), [0, 1, 0], atol=1e-15)
    # child's head rides on the parent; its tip (2, 0, 0) turns 90 about (1, 0, 0) → (1, 1, 0),
    # then 90 about the origin → (-1, 1, 0)
    np.testing.assert_allclose(apply(G[0, 0], [1, 0, 0]), [0, 1, 0], atol=1e-15)
    np.testing.assert_allclose(apply(G[0, 0], [2, 0, 0]), [-1, 1, 0], atol=1e-15)
    np.testing.assert_allclose(G[0, :, 3], [[0, 0, 0, 1]] * 2)
    # only the child turns: the parent stays, the tip goes to (1, 1, 0)
    G2 = forward_kinematics(np.stack([R[0], np.stack([R[0, 0], np.eye(3)])]), heads, parents,
                            translation=np.array([[0, 0, 0], [0, 0, 5.0]]))
    np.testing.assert_allclose(apply(G2[1, 0], [2, 0, 0]), [1, 1, 5], atol=1e-15)
    np.testing.assert_allclose(apply(G2[1, 1], [3, 4, 0]), [3, 4, 5], atol=1e-15)


def test_topological_order_and_cycles():
    parents = np.array([2, -1, 1, 0])
    order = list(topological_order(parents))
    assert all(order.index(p) < order.index(b) for b, p in enumerate(parents) if p >= 0)
    with pytest.raises(ParameterError):
        topological_order(np.array([1, 0]))


# -------------------------------------------------------------------------------- skinning

def test_lbs_identity_returns_input_exactly(template, rig, body):
    G = np.broadcast_to(np.eye(4), (2, rig.n_bones, 4, 4))
    v = np.stack([body, template.vertices])
    np.testing.assert_array_equal(linear_blend_skinning(v, rig.weights, G), v)


def test_lbs_matches_dense_reference():
    rng = np.random.default_rng(1)
    V, B, N = 50, 4, 3
    W = rng.uniform(size=(V, B)) * (rng.uniform(size=(V, B)) < 0.6)
    W[:, 0] += 0.1
    W /= W.sum(1, keepdims=True)
    G = np.tile(np.eye(4), (N, B, 1, 1))
    G[..., :3, :3] = rotvec_to_matrix(rng.normal(size=(N, B, 3)))
    G[..., :3, 3] = rng.normal(size=(N, B, 3))
    v = rng.normal(size=(N, V, 3))
    A = np.einsum("vb,nbij->nvij", W, G)
    ref = np.einsum("nvij,nvj->nvi", A[..., :3, :3], v) + A[..., :3, 3]
    np.testing.assert_allclose(linear_blend_skinning(v, sp.csr_matrix(W), G), ref, atol=1e-12)
    np.testing.assert_allclose(linear_blend_skinning(v[0], W, G), np.einsum(
        "nvij,vj->nvi", A[..., :3, :3], v[0]) + A[..., :3, 3], atol=1e-12)


def test_root_rotation_rotates_the_whole_mesh_rigidly(rig, body):
    root = int(np.flatnonzero(rig.parents < 0)[0])
    R = np.broadcast_to(np.eye(3), (rig.n_bones, 3, 3)).copy()
    Rroot = rotvec_to_matrix(np.array([0.3, -1.1, 0.7]))
    R[root] = Rroot
    posed, joints = pose_bodies(body, rig, R, return_joints=True)
    h = rig.heads(body)[root]
    np.testing.assert_allclose(posed, (body - h) @ Rroot.T + h, atol=1e-9)
    np.testing.assert_allclose(joints, (rig.heads(body) - h) @ Rroot.T + h, atol=1e-9)


# -------------------------------------------------------------------------- Blender frames

def test_bone_rest_frames_follow_blender_convention():
    heads = np.zeros((5, 3))
    tails = np.array([[0, 1.0, 0], [0, 2.0, 0], [1.0, 0, 0], [0, 0, 1.0], [0, -1.0, 0]])
    roll = np.array([0.0, 0.7, 0.0, 0.0, 0.0])
    F = bone_rest_frames(heads, tails, roll)
    # an upright bone with roll 0: Blender's local z faces the front (-Y Blender = +Z ours)
    np.testing.assert_allclose(F[0], np.eye(3), atol=1e-15)
    # roll turns the frame about the bone axis (right-handed)
    np.testing.assert_allclose(F[1], rotvec_to_matrix(np.array([0, 0.7, 0])), atol=1e-15)
    # a bone along +X: local y = +X, local z = up (Blender +Z), local x = front
    np.testing.assert_allclose(F[2], np.array([[0, 1, 0], [0, 0, 1], [1, 0, 0.0]]), atol=1e-15)
    # a bone pointing to the front is Blender's -Y singularity: a fixed, valid frame
    np.testing.assert_allclose(F[3][:, 1], [0, 0, 1], atol=1e-15)
    for f in F:
        np.testing.assert_allclose(f.T @ f, np.eye(3), atol=1e-12)
        assert np.linalg.det(f) > 0.999
    # close to it the regular formula stays exact and orthonormal; within Blender's 2.5e-4
    # threshold the fixed frame is used, so the y axis is off the bone by less than that
    for x, tol in ((1e-3, 1e-12), (3e-4, 1e-12), (1e-4, 2.5e-4), (1e-9, 2.5e-4)):
        d = np.array([x, 0, 1.0]) / np.hypot(x, 1.0)
        near = bone_rest_frames(np.zeros(3), d, np.zeros(()))
        np.testing.assert_allclose(near[:, 1], d, atol=tol)
        np.testing.assert_allclose(near.T @ near, np.eye(3), atol=1e-12)


def test_bone_rest_frames_on_the_rig(rig, body):
    heads, tails = rig.heads(body), rig.tails(body)
    F = bone_rest_frames(heads, tails, rig.roll)
    np.testing.assert_allclose(F.transpose(0, 2, 1) @ F, np.broadcast_to(np.eye(3), F.shape), atol=1e-12)
    d = tails - heads
    np.testing.assert_allclose(F[:, :, 1], d / np.linalg.norm(d, axis=1, keepdims=True), atol=1e-12)
    # MakeHuman's rolls make the knee a hinge about the lower leg's local x (close to our X)
    knee = rig.bone_index("lowerleg01.L")
    assert F[knee][0, 0] > 0.95
    # rolls are mirror-authored: reflecting a right bone's frame through x = 0 gives the left
    # bone's frame with its local x negated (a reflection flips handedness). The tiny midline
    # tongue bones are left out: their head/tail asymmetry of ~1 mm swings their frames
    # (the neck bones, also short and on the midline, are off by a few hundredths).
    m = mirrored_bone_index(rig)
    mirrored = np.diag(FLIP_X) @ F[m] @ np.diag(FLIP_X)
    body_bones = [i for i, b in enumerate(rig.bone_names) if not b.startswith("tongue")]
    assert np.abs(mirrored - F)[body_bones].max() < 0.05  # a wrong convention is off by ~2


# ------------------------------------------------------------------------------ the library

def test_library_has_many_unique_documented_poses(library, rig):
    assert len(library) >= 28
    assert len(set(library.names)) == len(library.names)
    assert "rest" in library
    for name in library.names:
        assert len(library.description(name)) > 10
        rv = library.rotvecs(name, rig)
        assert rv.shape == (rig.n_bones, 3) and np.isfinite(rv).all()
        assert np.linalg.norm(rv, axis=1).max() <= np.pi + 1e-9
    np.testing.assert_array_equal(library.rotations("rest", rig), np.broadcast_to(np.eye(3), (rig.n_bones, 3, 3)))
    with pytest.raises(ParameterError, match="known poses"):
        library.description("no_such_pose")


def test_mirror_poses_have_mirrored_rotations(library, rig):
    m = mirrored_bone_index(rig)
    pairs = 0
    for name in library.names:
        other = library.mirror(name)
        if other is None:
            continue
        pairs += other != name
        a, b = library.rotvecs(name, rig), library.rotvecs(other, rig)
        np.testing.assert_allclose(b[m] * np.array([1.0, -1.0, -1.0]), a, atol=1e-9, err_msg=name)
    assert pairs >= 16  # 8+ left/right pairs, counted from both sides


def test_unknown_bone_names_pose_and_bone(tmp_path, rig):
    data = json.loads(LIBRARY_PATH.read_text())
    data["poses"] = [{"name": "wave", "description": "x", "rotations": {"upperarm01.L": [0, 0, 90],
                                                                          "tentacle.L": [1, 0, 0]}}]
    path = tmp_path / "poses.json"
    path.write_text(json.dumps(data))
    lib = load_pose_library(path)
    with pytest.raises(ParameterError, match=r"'wave'.*'tentacle\.L'"):
        lib.rotations("wave", rig)
    data["poses"][0]["rotations"] = {"upperarm01.L": [0, 90]}
    path.write_text(json.dumps(data))
    with pytest.raises(ParameterError, match=r"'wave'.*'upperarm01\.L'"):
        load_pose_library(path)


# ------------------------------------------------------------------------ poses on a body

def test_arms_overhead_lifts_the_wrists_above_the_head(template, rig, posed_library):
    verts, _ = posed_library
    head_top = verts["arms_overhead"][bone_vertices(template, rig, ["head"]), 1].max()
    for side in (".L", ".R"):
        wrist = bone_vertices(template, rig, ["wrist"], side)
        assert verts["arms_overhead"][wrist, 1].min() > head_top + 0.1
    left, right = bone_vertices(template, rig, ["wrist"], ".L"), bone_vertices(template, rig, ["wrist"], ".R")
    raised = verts["arm_raised_left"]
    assert raised[left, 1].min() > raised[bone_vertices(template, rig, ["head"]), 1].max()
    assert raised[right, 1].max() < 1.2
    # T-pose: wrists at shoulder height, far out to the sides
    t = verts["t_pose"]
    shoulder_y = rig.heads(t)[rig.bone_index("upperarm01.L"), 1]
    assert abs(t[left, 1].mean() - shoulder_y) < 0.12 and t[left, 0].min() > 0.6


def test_squat_lowers_the_pelvis_and_keeps_feet_flat(template, rig, posed_library, rest_on_ground):
    verts, joints = posed_library
    rest_v, rest_j = rest_on_ground
    root = rig.bone_index("root")
    assert joints["squat"][root, 1] < rest_j[root, 1] - 0.3
    assert joints["half_squat"][root, 1] < rest_j[root, 1] - 0.1
    np.testing.assert_allclose(joints["squat"][root, [0, 2]], rest_j[root, [0, 2]], atol=1e-9)
    for name in ("squat", "half_squat", "rest"):
        v = verts[name]
        assert abs(v[:, 1].min()) < 1e-12
        for side in (".L", ".R"):
            foot = bone_vertices(template, rig, ["foot", "toe"], side)
            z = v[foot, 2]
            heel, toes = foot[z <= np.quantile(z, 0.05)], foot[z >= np.quantile(z, 0.95)]
            assert v[heel, 1].min() < 0.03 and v[toes, 1].min() < 0.03, (name, side)
    # knees bend the right way: in the squat the knees are in front of the ankles
    for side in (".L", ".R"):
        knee, ankle = joints["squat"][rig.bone_index("lowerleg01" + side)], joints["squat"][rig.bone_index("foot" + side)]
        assert knee[2] > ankle[2] + 0.1


def test_knee_lift_and_one_leg_stand_move_the_right_joints(rig, posed_library, rest_on_ground):
    _, joints = posed_library
    _, rest_j = rest_on_ground
    kl, kr = rig.bone_index("lowerleg01.L"), rig.bone_index("lowerleg01.R")
    al = rig.bone_index("foot.L")
    j = joints["knee_lift_left"]
    assert j[kl, 1] > rest_j[kl, 1] + 0.2 and j[kl, 2] > rest_j[kl, 2] + 0.2   # up and forward
    np.testing.assert_allclose(j[kr], rest_j[kr], atol=0.01)                  # standing knee stays
    j = joints["knee_lift_right"]
    assert j[kr, 1] > rest_j[kr, 1] + 0.2
    # knee flexion moves the foot back (-Z), never forward
    j = joints["one_leg_stand_left"]
    assert j[al, 2] < rest_j[al, 2] - 0.2 and j[al, 1] > rest_j[al, 1] + 0.2


def edge_stretch(faces, rest, posed):
    e = np.unique(np.sort(faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1), axis=0)
    return np.linalg.norm(posed[e[:, 0]] - posed[e[:, 1]], axis=1) / np.linalg.norm(rest[e[:, 0]] - rest[e[:, 1]], axis=1)


def test_every_pose_is_finite_and_unstretched(template, body, posed_library):
    """No edge stretches past 3x its rest length, except a few dozen (< 0.15% of 40k) short
    edges in the armpit and groin folds, where MakeHuman's weights blend an arm or thigh
    rotated by 90-170 degrees with the trunk: the classic LBS fold, bounded by 10x. A wrong
    pivot, sign or weight matrix moves whole limbs and breaks these bounds by far."""
    verts, _ = posed_library
    for name, v in verts.items():
        assert np.isfinite(v).all(), name
        ratio = edge_stretch(template.faces, body, v)
        assert ratio.max() < 10.0 and (ratio > 3.0).mean() < 0.0015 and ratio.min() > 0.03, \
            (name, ratio.max(), (ratio > 3.0).sum(), ratio.min())
        assert np.quantile(ratio, 0.99) < 2.0, name
        height = v[:, 1].max() - v[:, 1].min()
        assert 0.8 < height < 2.4, (name, height)


def test_stretch_check_catches_a_wrong_pivot(template, rig, body, library):
    # Rotating bones about the origin instead of their heads (a classic FK bug) must fail the
    # bounds above: guard that the test has teeth.
    R = library.rotations("t_pose", rig)
    G = forward_kinematics(R[None], np.zeros((rig.n_bones, 3)), rig.parents)
    ratio = edge_stretch(template.faces, body, linear_blend_skinning(body, rig.weights, G)[0])
    assert ratio.max() >= 10.0 or (ratio > 3.0).mean() >= 0.0015


def test_mirror_poses_give_mirror_image_meshes(template, library, posed_library):
    verts, _ = posed_library
    checked = 0
    for name in library.names:
        other = library.mirror(name)
        if other is None:
            continue
        a, b = verts[name], verts[other]
        err = np.abs(b[template.mirror] * FLIP_X - a).max()
        # the bone-head regressors are only nearly symmetric (0.1 mm here, 1.5 mm on the tongue)
        assert err < 0.002, (name, other, err)
        checked += 1
    assert checked >= len(library) - 2


def test_pose_bodies_batches_and_shapes(rig, body, library):
    R = library.stack(["rest", "squat", "t_pose"], rig)
    batch = pose_bodies(np.stack([body] * 3), rig, R)
    for k in range(3):
        np.testing.assert_allclose(pose_bodies(body, rig, R[k]), batch[k], atol=1e-12)
    shared = pose_bodies(np.stack([body, body]), rig, R[1])
    np.testing.assert_allclose(shared[0], batch[1], atol=1e-12)
    np.testing.assert_array_equal(pose_bodies(body, rig, R[0]), body)
    for skinning in ("lbs", "dqs"):                      # float32 output, computed in float32
        single = pose_bodies(np.stack([body] * 3), rig, R, skinning=skinning, dtype=np.float32)
        assert single.dtype == np.float32
        np.testing.assert_allclose(single, pose_bodies(np.stack([body] * 3), rig, R, skinning=skinning), atol=2e-6)
    with pytest.raises(ParameterError):
        pose_bodies(body, rig, R[:, :10])
    # ground placement: lowest vertex at 0 and the pelvis over its rest x/z
    moved = place_on_ground(batch + 1.0, np.ones((3, 3)), np.zeros((3, 3)))
    np.testing.assert_allclose(moved[:, :, 1].min(axis=1), 0, atol=1e-12)
    np.testing.assert_allclose(moved[:, :, [0, 2]], batch[:, :, [0, 2]], atol=1e-12)


def test_pose_bodies_one_body_over_frames(rig, body, library):
    """A (V, 3) body with (N, B, 3, 3) rotations is posed once per frame, as the same body
    repeated N times (or broadcast) would be; joints too."""
    R = library.stack(["squat", "t_pose", "rest"], rig)
    frames, joints = pose_bodies(body, rig, R, on_ground=True, return_joints=True)
    repeated, joints_rep = pose_bodies(np.repeat(body[None], 3, axis=0), rig, R, on_ground=True, return_joints=True)
    assert frames.shape == (3,) + body.shape and joints.shape == (3, rig.n_bones, 3)
    np.testing.assert_allclose(frames, repeated, atol=1e-12)
    np.testing.assert_allclose(joints, joints_rep, atol=1e-12)
    np.testing.assert_allclose(pose_bodies(np.broadcast_to(body, (3,) + body.shape), rig, R, skinning="dqs"),
                               pose_bodies(np.repeat(body[None], 3, axis=0), rig, R, skinning="dqs"), atol=1e-12)


def test_dqs_matches_lbs_for_rigid_parts_and_keeps_identity():
    rng = np.random.default_rng(2)
    V, B, N = 40, 4, 3
    G = np.tile(np.eye(4), (N, B, 1, 1))
    G[..., :3, :3] = rotvec_to_matrix(rng.normal(size=(N, B, 3)))
    G[..., :3, 3] = rng.normal(size=(N, B, 3))
    v = rng.normal(size=(N, V, 3))
    W = np.zeros((V, B))
    W[np.arange(V), rng.integers(0, B, V)] = 1.0                # one bone per vertex: rigid
    np.testing.assert_allclose(dual_quaternion_skinning(v, sp.csr_matrix(W), G), linear_blend_skinning(v, W, G),
                               atol=1e-12)
    W = rng.uniform(size=(V, B))
    W /= W.sum(1, keepdims=True)
    same = np.broadcast_to(G[:, :1], G.shape)                  # every bone moves alike
    np.testing.assert_allclose(dual_quaternion_skinning(v, W, same), linear_blend_skinning(v, W, same), atol=1e-12)
    np.testing.assert_array_equal(dual_quaternion_skinning(v, W, np.tile(np.eye(4), (N, B, 1, 1))), v)


def test_count_folded_triangles_on_a_grid():
    # a flat 2x2 grid of 8 triangles: no folds; pushing the centre far through a neighbour folds
    xy = np.array([[x, y, 0.0] for y in range(3) for x in range(3)])
    faces = np.array([[0, 1, 4], [0, 4, 3], [1, 2, 5], [1, 5, 4], [3, 4, 7], [3, 7, 6], [4, 5, 8], [4, 8, 7]])
    assert count_folded_triangles(xy, faces) == 0
    bent = xy.copy()
    bent[4] = [2.6, 2.6, 0.0]                                      # the centre crosses vertex 8
    assert count_folded_triangles(np.stack([xy, bent]), faces).tolist()[0] == 0
    assert count_folded_triangles(bent, faces) > 0
    mask = folded_triangles(np.stack([xy, bent]), faces)           # the faces themselves, (N, F)
    assert mask.shape == (2, 8) and not mask[0].any() and mask[1].sum() == count_folded_triangles(bent, faces)


# Folded triangles a library pose may add to its rest mesh (docs/poses.md, "Folds"): with the
# smoothed weights the worst scan (squat, heavy body) adds 18; MakeHuman's weights as
# shipped add up to 62.
MAX_NEW_FOLDS = 24


def test_library_poses_fold_little_with_smoothed_weights(template, rig, library):
    from bodyspace.synth.phenotype import PhenotypeModel
    bodies = PhenotypeModel(template).vertices({"gender": [1.0, 0.0, 1.0], "weight": [0.5, 0.5, 1.0],
                                                "muscle": [0.5, 0.5, 0.0], "height": [0.6, 0.4, 0.5]})
    R = library.stack(library.names, rig)
    rest = count_folded_triangles(bodies, template.faces)       # fingers/toes of some phenotypes
    total_old = total_new = 0
    for body, r in zip(bodies, rest):
        many = np.broadcast_to(body, (len(R),) + body.shape)
        new = dict(zip(library.names, count_folded_triangles(pose_bodies(many, rig, R, weights="smoothed"),
                                                             template.faces) - r))
        old = count_folded_triangles(pose_bodies(many, rig, R, weights="original"), template.faces) - r
        assert max(new.values()) <= MAX_NEW_FOLDS, new
        # the armpit no longer folds when the arms go up
        for name in ("arms_overhead", "arm_raised_left", "arm_raised_right", "hands_behind_head", "t_pose"):
            assert new[name] <= 0, (name, new[name])
        total_new += sum(max(c, 0) for c in new.values())
        total_old += np.clip(old, 0, None).sum()
    assert total_new < 0.5 * total_old, (total_new, total_old)
