"""The registered body brought back to standing (register.pose_refit, issue 15's measurements).

A small shape space (6 components of 12 phenotype bodies) keeps the fits cheap; the numbers on
full test scans are in docs/registration.md (benchmarks/diag_iso.py).
"""

import numpy as np
import pytest
from scipy.spatial import cKDTree

from bodyspace.mesh.geometry import vertex_normals
from bodyspace.register.model_fit import ShapeBasis
from bodyspace.register.pose_fit import PoseState, posed_vertices
from bodyspace.measure import evaluate
from bodyspace.measure.definitions import load_measurement_set
from bodyspace.register.pose_refit import (REFIT_POSE_PRIOR, REFIT_SWING_PRIOR, UPPER_ARM_TWIST_BONES, refit_pose,
                                           refit_prior, skinning_uncertainty, standing_body)
from bodyspace.rig.posing import pose_bodies
from bodyspace.rig.kinematics import matrix_to_rotvec, rotvec_to_matrix
from bodyspace.synth.poses import load_pose_library
from bodyspace.synth.scans import sample_surface


@pytest.fixture(scope="module")
def small_basis(template, phenotype_model):
    rng = np.random.default_rng(5)
    bodies = phenotype_model.vertices(rng.random((12, 11))).reshape(12, -1)
    mean = bodies.mean(axis=0)
    u, s, vt = np.linalg.svd(bodies - mean, full_matrices=False)
    V = template.n_vertices
    return ShapeBasis(mean.reshape(V, 3), vt[:6].reshape(6, V, 3), s[:6] / np.sqrt(11))


@pytest.fixture(scope="module")
def posed_truth(template, small_basis):
    """A body of the basis (a few millimetres from its mean: the phenotypes span babies to
    giants) in the elbows-flexed pose, placed and scaled: the state that made it, and its vertices."""
    rig = template.rigs["default"]
    coef = small_basis.sigma * np.array([0.012, -0.012, 0.01, -0.01, 0.012, 0.006])
    R = np.asarray(load_pose_library().rotations("elbows_flexed", rig))
    truth = PoseState(small_basis.body(coef), R, 1.04, np.array([0.02, 0.9, -0.01]), coef)
    return truth, posed_vertices(rig, truth)[0]


def test_refit_splits_pose_and_shape_again(template, small_basis, posed_truth):
    """From a start whose shape was held at the mean and whose pose made up for it (elbows and a
    hip 1° off), the refit to the body's points finds the body again: its
    rest body a third as far from the true one as the start's (2 mm), its posed surface within 1 mm."""
    rig = template.rigs["default"]
    truth, x = posed_truth
    names = list(rig.bone_names)
    R = truth.rotations.copy()
    for b in ("lowerarm01.L", "lowerarm01.R", "upperleg01.L"):
        R[names.index(b)] = rotvec_to_matrix(np.array([0.015, 0.0, 0.01])) @ R[names.index(b)]
    start = PoseState(small_basis.mean, R, truth.scale, truth.translation, np.zeros(6))
    n = vertex_normals(x, template.faces)
    refit = refit_pose(x, n, template, start, small_basis, scan_tree=cKDTree(x), iterations=6)

    def error(state):    # mean vertex distance (m) of the scaled rest bodies, centred (scale and shift trade)
        a, b = state.scale * state.rest, truth.scale * truth.rest
        return np.linalg.norm(a - a.mean(axis=0) - b + b.mean(axis=0), axis=1).mean()

    err_start, err = error(start), error(refit)
    assert err_start > 0.0015 and err < err_start / 3, (err_start, err)
    assert np.linalg.norm(posed_vertices(rig, refit)[0] - x, axis=1).mean() < 0.001


def test_standing_body_is_the_rest_body_with_the_fit_s_normal_offsets(template, posed_truth):
    """On the model's own posed surface the standing body is the scaled rest body on the ground;
    a relief added along the posed normals comes back along the rest normals, the same size."""
    truth, x = posed_truth
    rest = truth.scale * truth.rest
    stand = standing_body(x, template.faces, template, truth)
    assert np.allclose(stand[:, 1].min(), 0.0)
    shift = stand.mean(axis=0) - rest.mean(axis=0)
    assert np.abs(stand - shift - rest).max() < 1e-9
    relief = 0.003 * np.sin(40.0 * x[:, 1]) * (x[:, 1] > x[:, 1].min() + 0.5)      # (V,) m, feet kept
    bumpy = x + relief[:, None] * vertex_normals(x, template.faces)
    bumped = standing_body(bumpy, template.faces, template, truth, skin_uncertainty=None)
    got = ((bumped - stand) * vertex_normals(stand, template.faces)).sum(axis=1)
    assert np.abs(got - relief).mean() < 2e-4
    # By default the same where the pose's skinning is certain (elsewhere test_..._another_skinning).
    certain = skinning_uncertainty(template, truth) < 0.0005
    bumped = standing_body(bumpy, template.faces, template, truth)
    got = ((bumped - stand) * vertex_normals(stand, template.faces)).sum(axis=1)
    assert certain.mean() > 0.5 and np.abs(got - relief)[certain].mean() < 2e-4


def test_standing_body_takes_its_offsets_from_the_scan_where_it_has_points(template, posed_truth):
    """A scan 2 mm outside the model's posed surface (noise σ 1 mm, the head cut out, floating
    outliers 3 cm off): where it has points the standing body is 2 mm outside the rest body, the
    registered mesh's offsets (none here: the mesh is the model's own surface) are ignored; in the
    hole it keeps the registered mesh's (scan_offsets). Without the scan the offsets are the mesh's."""
    truth, x = posed_truth
    faces = template.faces
    rng = np.random.default_rng(3)
    points, face, bary = sample_surface(x, faces, 60_000, rng)
    n_face = vertex_normals(x, faces)[faces[face]]
    normal = (n_face * bary[:, :, None]).sum(axis=1)
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    head = x[:, 1].max() - 0.25
    scan = points + 0.002 * normal + rng.normal(0.0, 0.001, points.shape)
    keep = scan[:, 1] < head
    outliers = points[:2000] + 0.03 * normal[:2000]
    scan = np.concatenate([scan[keep], outliers])
    normals = np.concatenate([normal[keep], normal[:2000]])
    rest = truth.scale * truth.rest
    plain = standing_body(x, faces, template, truth)
    stand = standing_body(x, faces, template, truth, points=scan, normals=normals)
    body = x[:, 1] < head - 0.05
    hole = x[:, 1] > head + 0.05
    shift = np.median((stand - plain)[hole, 1])          # both stand on the ground: the soles moved out
    got = ((stand - plain - [0.0, shift, 0.0]) * vertex_normals(rest, faces)).sum(axis=1)    # (V,) m
    assert abs(np.median(got[body]) - 0.002) < 0.0002, np.median(got[body])
    assert np.abs(got[body] - 0.002).mean() < 0.0004
    # (where the pose's skinning is uncertain, at the neck's base, the hole's offsets are filled in
    # from the scan's around it: standing_body's skin_uncertainty)
    certain = skinning_uncertainty(template, truth) < 0.0005
    assert (hole & certain).sum() > 0.8 * hole.sum() and np.abs(got[hole & certain]).max() < 0.0003


def test_standing_body_does_not_keep_what_another_skinning_did_to_the_neck(template, phenotype_model):
    """A body posed with other skin weights than ours (the smoothed ones: a real body's skin is
    nobody's LBS) with its head turned, unposed by our LBS with the true pose and shape: the
    offsets where bones turned against each other meet are another skinning's, not the body's
    (the neck girth 15 mm short: the smoothed weights wring the neck); the standing body fills
    them in from the trusted offsets around, keeping SKIN_KEEP of their own (5 mm short). Where
    nothing turns the uncertainty is 0 and the body is kept exactly."""
    rig = template.rigs["default"]
    rest = phenotype_model.vertices(np.full((1, 11), 0.5))[0]
    R = np.asarray(load_pose_library().rotations("head_turn_left", rig))
    state = PoseState(rest, R, 1.0, np.zeros(3))
    u = skinning_uncertainty(template, state)                          # (V,) m
    still = PoseState(rest, np.repeat(np.eye(3)[None], rig.n_bones, axis=0), 1.0, np.zeros(3))
    assert np.abs(skinning_uncertainty(template, still)).max() < 1e-12
    feet = rest[:, 1] < rest[:, 1].min() + 0.3
    assert u[feet].max() < 1e-12 and u.max() > 0.01, u.max()
    mset = load_measurement_set()

    def neck(v):
        return evaluate(mset, v, template.faces, check_scale=False)["neck_girth"].value

    x = pose_bodies(rest, rig, R, weights="smoothed", faces=template.faces)
    truth = neck(rest)
    kept = neck(standing_body(x, template.faces, template, state, skin_uncertainty=None))
    stand = standing_body(x, template.faces, template, state)
    assert abs(kept - truth) > 0.01, (kept, truth)
    assert abs(neck(stand) - truth) < abs(kept - truth) / 2.5, (neck(stand), kept, truth)
    moved = np.abs(stand - (rest - [0.0, rest[:, 1].min(), 0.0])).max(axis=1)
    assert moved[feet].max() < 1e-9


def test_refit_prior_holds_the_upper_arm_twist_bones_in_line_across_their_axis_only(template):
    """``refit_prior``: every bone REFIT_POSE_PRIOR on each axis; the upper arm's twist bones also
    REFIT_SWING_PRIOR across their own axis (their swing), not along it (their twist)."""
    rig = template.rigs["default"]
    prior = refit_prior(template)
    assert prior.shape == (rig.n_bones, 3, 3)
    heads, tails = rig.heads(template.vertices), rig.tails(template.vertices)
    for b in range(rig.n_bones):
        if rig.bone_names[b] in UPPER_ARM_TWIST_BONES:
            axis = (tails[b] - heads[b]) / np.linalg.norm(tails[b] - heads[b])
            across = np.cross(axis, [0.0, 0.0, 1.0])
            across /= np.linalg.norm(across)
            assert np.allclose(prior[b] @ axis, REFIT_POSE_PRIOR * axis)
            assert np.allclose(prior[b] @ across, (REFIT_POSE_PRIOR + REFIT_SWING_PRIOR) * across)
        else:
            assert np.array_equal(prior[b], REFIT_POSE_PRIOR * np.eye(3))
    assert np.array_equal(refit_prior(template, 0.0), REFIT_POSE_PRIOR * np.eye(3) * np.ones((rig.n_bones, 1, 1)))


def test_refit_puts_an_upper_arm_bent_at_its_twist_bone_back_in_line(template, small_basis, posed_truth):
    """The split the pose fit found on scans posed with another skinning (ISO study scans 43, 49:
    the arm's swing moved from upperarm01 to its twist bone upperarm02, 15-20° each, the elbow in
    place; the shoulders then came out 12-20 mm narrow): from such a start the refit with the swing
    prior brings upperarm02 back in line with the upper arm, without it the bend stays."""
    rig = template.rigs["default"]
    truth, x = posed_truth
    names = list(rig.bone_names)
    R = truth.rotations.copy()
    bend = {"L": rotvec_to_matrix(np.array([0.0, 0.0, 0.25])), "R": rotvec_to_matrix(np.array([0.0, 0.0, -0.25]))}
    for side, S in bend.items():          # upperarm01 turned back by S, upperarm02 forward by S
        R[names.index(f"upperarm01.{side}")] = R[names.index(f"upperarm01.{side}")] @ S.T
        R[names.index(f"upperarm02.{side}")] = S @ R[names.index(f"upperarm02.{side}")]
    start = PoseState(truth.rest, R, truth.scale, truth.translation, truth.coefficients)
    n = vertex_normals(x, template.faces)

    def swing(state):      # degrees of upperarm02's rotation, both sides' largest
        return max(np.degrees(np.linalg.norm(matrix_to_rotvec(state.rotations[names.index(f"upperarm02.{s}")][None])))
                   for s in "LR")

    held = refit_pose(x, n, template, start, small_basis, scan_tree=cKDTree(x), iterations=4)
    free = refit_pose(x, n, template, start, small_basis, scan_tree=cKDTree(x), iterations=4, swing_prior=0.0)
    assert swing(start) > 14.0
    assert swing(held) < swing(free) / 2, (swing(held), swing(free))
