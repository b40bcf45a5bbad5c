"""Tests for bodyspace.rig.volume: the volume-preserving correction on top of LBS, on a bent
capsule with known rest volume (cheap) and one template body in the squat."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp

from bodyspace.errors import MeshError, ParameterError
from bodyspace.mesh.geometry import capped_volume
from bodyspace.rig.kinematics import forward_kinematics, rotvec_to_matrix
from bodyspace.rig.posing import count_folded_triangles, pose_bodies
from bodyspace.rig.skinning import linear_blend_skinning
from bodyspace.rig.volume import preserve_volume, volume_rig
from bodyspace.synth.poses import load_pose_library

from _meshes import open_tube

PARENTS = np.array([-1, 0])
HEADS = np.array([[[0.0, 0.0, 0.0], [0.0, 1.0, 0.0]]])
TAILS = np.array([[[0.0, 1.0, 0.0], [0.0, 2.0, 0.0]]])


def closed_tube(length=2.0, radius=0.2, rings=61, around=24):
    """A closed, outward-oriented tube along +y from 0 to ``length`` with a pole vertex
    ``radius`` beyond each end: (V, 3), (F, 3)."""
    v, f = open_tube(rings, around, length, radius)
    n, a = len(v), np.arange(around)
    bottom = np.stack([np.full(around, n), a, (a + 1) % around], 1)
    top = np.stack([np.full(around, n + 1), (rings - 1) * around + (a + 1) % around, (rings - 1) * around + a], 1)
    poles = np.array([[0.0, -radius, 0.0], [0.0, length + radius, 0.0]])
    return np.vstack([v, poles]), np.vstack([f, bottom, top])


def two_bone_weights(v, blend=0.4):
    """(V, 2) weights of a tube along +y: bone 0 below the joint at y = 1, bone 1 above, a
    smoothstep blend ``blend`` long across the joint."""
    t = np.clip((v[:, 1] - 1.0) / blend + 0.5, 0.0, 1.0)
    w1 = t * t * (3 - 2 * t)
    return sp.csr_matrix(np.stack([1 - w1, w1], 1))


def bend(angles_deg):
    """(N, 2, 4, 4) transforms: bone 1 turned about +z (about its head) by each angle."""
    rv = np.zeros((len(angles_deg), 2, 3))
    rv[:, 1, 2] = np.radians(angles_deg)
    return forward_kinematics(rotvec_to_matrix(rv), HEADS[0], PARENTS)


@pytest.fixture(scope="module")
def tube():
    v, f = closed_tube()
    assert capped_volume(v, f) > 0.9 * np.pi * 0.2 ** 2 * 2.0
    W = two_bone_weights(v)
    return v, f, W, volume_rig(W, PARENTS, f)


def test_bent_capsule_keeps_its_volume_without_new_folds(tube):
    v, f, W, vrig = tube
    G = bend([45.0, 90.0, 120.0])
    lbs = linear_blend_skinning(v, W, G)
    posed = lbs.copy()
    s = preserve_volume(posed, v[None], G, HEADS, TAILS, vrig)
    rest = capped_volume(v, f)
    lost = capped_volume(lbs, f) / rest - 1
    assert lost[1] < -0.02                               # LBS itself loses volume at 90 degrees
    np.testing.assert_allclose(capped_volume(posed, f) / rest - 1, 0.0, atol=5e-3)
    np.testing.assert_allclose(capped_volume(posed, f), rest, rtol=1e-9)   # exact by construction
    assert np.all(s > 0)
    assert np.all(count_folded_triangles(posed, f) <= count_folded_triangles(lbs, f))
    # contact-aware: the skin bulges on the outer side of the bend (-x for a turn about +z
    # with the upper bone swinging toward -x), less on the inner side
    d = posed[1] - lbs[1]
    near = np.abs(v[:, 1] - 1.0) < 0.25
    outer = near & (v[:, 0] > 0.1)
    inner = near & (v[:, 0] < -0.1)
    assert np.linalg.norm(d[outer], axis=1).mean() > 2 * np.linalg.norm(d[inner], axis=1).mean()
    # far from the joint the skin is left as LBS put it (the bump is 0 where nothing blends)
    far = np.abs(v[:, 1] - 1.0) > 0.8
    assert np.abs(d[far]).max() < 0.02 * np.abs(d).max() + 1e-12
    # smooth: no vertex moves much more than its neighbours (the largest step, 27 % of the
    # largest displacement, is around the ring of the outer bulge: 24 vertices a ring)
    e = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    assert np.linalg.norm(d[e[:, 0]] - d[e[:, 1]], axis=1).max() < 0.3 * np.linalg.norm(d, axis=1).max()


def test_identity_pose_is_unchanged_and_float32_frames(tube):
    v, f, W, vrig = tube
    G = bend([0.0, 90.0])
    lbs = linear_blend_skinning(v, W, G)
    posed = lbs.copy()
    s = preserve_volume(posed, v[None], G, HEADS, TAILS, vrig, lanes=2)
    assert s[0] == 0.0 and np.array_equal(posed[0], lbs[0])
    p32 = linear_blend_skinning(v, W, G, dtype=np.float32)
    preserve_volume(p32, v[None], G, HEADS, TAILS, vrig, lanes=1)
    assert p32.dtype == np.float32
    np.testing.assert_allclose(p32, posed, atol=2e-5)


def test_holes_are_capped_like_capped_volume():
    v, f = open_tube(41, 20, 2.0, 0.2)
    W = two_bone_weights(v)
    G = bend([90.0])
    posed = linear_blend_skinning(v, W, G)
    preserve_volume(posed, v[None], G, HEADS, TAILS, volume_rig(W, PARENTS, f))
    np.testing.assert_allclose(capped_volume(posed, f), capped_volume(v, f), rtol=1e-9)


def test_bad_inputs_raise_clear_errors(tube):
    v, f, W, vrig = tube
    G = bend([90.0])
    with pytest.raises(MeshError, match="posed"):
        preserve_volume(np.zeros((1, 5, 3)), v[None], G, HEADS, TAILS, vrig)
    with pytest.raises(ParameterError, match="transforms"):
        preserve_volume(linear_blend_skinning(v, W, G), v[None], G[:, :1, :3], HEADS, TAILS, vrig)
    with pytest.raises(ParameterError, match="parents"):
        volume_rig(W, np.array([-1]), f)
    with pytest.raises(MeshError, match="faces"):
        volume_rig(W, PARENTS, f + len(v))


def test_template_squat_keeps_its_volume(template):
    rig = template.rigs["default"]
    R = load_pose_library().rotations("squat", rig)
    lbs = pose_bodies(template.vertices, rig, R)
    posed = pose_bodies(template.vertices, rig, R, preserve_volume=True)
    rest = capped_volume(template.vertices, template.faces)
    assert capped_volume(lbs, template.faces) / rest - 1 < -0.05
    assert abs(capped_volume(posed, template.faces) / rest - 1) < 1e-6
    assert count_folded_triangles(posed, template.faces) <= count_folded_triangles(lbs, template.faces)


def test_each_body_keeps_its_own_rest_volume(tube):
    v, f, W, vrig = tube
    rest = np.stack([v, v * np.array([1.3, 1.0, 1.3])])          # a thicker second tube
    G = bend([90.0, 60.0])
    posed = linear_blend_skinning(rest, W, G)
    preserve_volume(posed, rest, G, np.repeat(HEADS, 2, 0), np.repeat(TAILS, 2, 0), vrig)
    np.testing.assert_allclose(capped_volume(posed, f), capped_volume(rest, f), rtol=1e-9)
