"""Unposing (rig/unpose.py): posed bodies of the template's topology back to rest, the measure
command's default (unposed) and --as-posed paths, and the pose spread study on a small case."""

from __future__ import annotations

import json

import numpy as np
import pytest
from typer.testing import CliRunner

from bodyspace.cli import app
from bodyspace.errors import MeshError, ParameterError, UnposeError
from bodyspace.mesh.io import save_mesh
from bodyspace.rig import unpose as U
from bodyspace.rig.posing import pose_bodies
from bodyspace.rig.unpose import fits_template, unpose
from bodyspace.synth.foreign import add_noise, foreign_body, punch_holes, shuffle_vertices, to_frame
from bodyspace.synth.poses import load_pose_library

POSES = ["t_pose", "squat", "arms_crossed", "torso_twist_left", "reach_over_right", "sitting"]
runner = CliRunner()


def _ground(v):
    return v - np.array([0.0, 1.0, 0.0]) * v[..., 1].min(axis=-1)[..., None, None]


def _shape_error(a, b):
    """(N,) largest vertex distance after removing the mean offset (metres)."""
    d = a - b
    d = d - d.mean(axis=-2, keepdims=True)
    return np.linalg.norm(d, axis=-1).max(axis=-1)


@pytest.fixture(scope="session")
def rig(template):
    return template.rigs["default"]


@pytest.fixture(scope="session")
def rest_bodies(phenotype_model):
    """Two adults unlike the template: a heavy short woman, a tall lean man."""
    return phenotype_model.vertices({"gender": [0.0, 1.0], "weight": [0.9, 0.2], "height": [0.2, 0.9],
                                     "age": [0.7, 0.45], "muscle": [0.3, 0.8]})


@pytest.fixture(scope="session")
def library_case(rig, rest_bodies):
    """Both bodies in POSES, posed like the synthetic database (LBS, original weights, on the ground)."""
    R = load_pose_library().stack(POSES, rig)
    posed = np.concatenate([pose_bodies(np.repeat(b[None], len(POSES), 0), rig, R, on_ground=True)
                            for b in rest_bodies])
    truth = _ground(np.repeat(rest_bodies, len(POSES), axis=0))
    rest, rotations, info = unpose(posed, rig)
    return posed, truth, rest, rotations, info, np.concatenate([R, R])


def test_lbs_posed_library_bodies_come_back_to_their_rest_body(library_case):
    posed, truth, rest, _, info, _ = library_case
    assert _shape_error(rest, truth).max() < 0.5e-3                     # well under a millimetre
    assert np.abs(rest[..., 1].min(axis=1)).max() < 1e-12               # on the ground
    # Placement: the pelvis x/z of the posed body (pose_bodies keeps it), so no offset either.
    offset = np.linalg.norm((rest - truth).mean(axis=1), axis=1)
    assert offset.max() < 1e-3
    assert info.converged.all() and (info.shape_distance_m < 1e-4).all() and (info.joint_gap_m < 1e-4).all()


def test_rotations_pose_the_rest_body_back_into_the_mesh(rig, library_case):
    posed, _, rest, rotations, info, truth_rotations = library_case
    again = pose_bodies(rest, rig, rotations) + info.translation[:, None, :]
    assert np.abs(again - posed).max() < 1e-4
    # What the output reports: the squat's deep hip flexion, not a neck twist.
    squat = POSES.index("squat")
    assert info.largest_rotation_deg[squat] > 90 and "leg" in info.largest_rotation_bone[squat]
    # Bones whose rotation the skin shows come back as posed (squat: knees flexed 125 degrees).
    knee = rig.bone_index("lowerleg01.L")
    assert np.abs(rotations[squat, knee] - truth_rotations[squat, knee]).max() < 0.02


def test_rest_pose_is_stable_and_unposing_twice_does_not_drift(rig, rest_bodies):
    rest0 = _ground(rest_bodies)
    once, rotations, info = unpose(rest0, rig)
    assert np.abs(once - rest0).max() < 1e-4
    assert (info.largest_rotation_deg < 0.5).all() and (info.orientation_deg < 0.5).all()
    twice, _, _ = unpose(once, rig)
    assert np.abs(twice - once).max() < 1e-5
    assert np.abs(rotations - np.eye(3)).max() < 0.01


def test_a_batch_equals_its_bodies_one_by_one(rig, library_case):
    posed, _, rest, rotations, _, _ = library_case
    for k in (1, 8):
        one, r, info = unpose(posed[k], rig)
        assert one.shape == posed[k].shape and r.shape == (rig.n_bones, 3, 3) and np.ndim(info.iterations) == 0
        np.testing.assert_allclose(one, rest[k], atol=1e-9)
        np.testing.assert_allclose(r, rotations[k], atol=1e-7)


def test_jacobian_agrees_with_finite_differences(rig, library_case):
    """The compiled Gauss-Newton system is the gradient of the cost the fit minimizes."""
    posed = library_case[0][1:2]
    plan = U._plan(rig, rig.weights.tocsr(), "original", U._default_prior())
    Q, t = U._initial_pose(plan, posed)
    state = U._State(plan, posed[:, plan.work])
    cost, _, grad = state.normal_equations(Q, t, np.arange(1))
    rng = np.random.default_rng(0)
    for _ in range(3):
        d = rng.normal(size=grad.shape).reshape(1, -1, 6) * 1e-6
        plus = state.cost(U.rotvec_to_matrix(d[..., :3]) @ Q, t + d[..., 3:])
        minus = state.cost(U.rotvec_to_matrix(-d[..., :3]) @ Q, t - d[..., 3:])
        assert np.isclose((plus - minus)[0] / 2, 2 * (grad * d.reshape(1, -1)).sum(), rtol=2e-3)
    assert np.isfinite(cost).all()


def test_foreign_frames_noise_and_holes(template, phenotype_model, rig, rest_bodies):
    """A template-topology body moved, turned by 40 degrees, noisy, or holed, as a user's data comes."""
    truth = _ground(rest_bodies[1])
    posed = pose_bodies(rest_bodies[1], rig, load_pose_library().rotations("lunge_left", rig), on_ground=True)
    moved = to_frame(posed, up="y", scale=1.0, translation=(1.2, 0.3, -2.0), yaw_degrees=40.0)
    rest, _, info = unpose(moved, rig)
    assert _shape_error(rest, truth) < 0.5e-3 and abs(info.orientation_deg - 40) < 1
    assert abs(rest[:, 1].min()) < 1e-12
    noisy = add_noise(posed, 0.001, rng=0)
    rest, _, info = unpose(noisy, rig)
    d = rest - truth
    d -= d.mean(0)
    assert np.linalg.norm(d, axis=1).mean() < 3e-3 and 0.5e-3 < info.shape_distance_m < 3e-3
    holed = punch_holes(posed, template.faces, posed[[4000, 9000]], 0.04)
    assert len(holed) < len(template.faces) and fits_template(posed, holed, template)
    assert fits_template(posed, template.faces[:, [1, 2, 0]], template)      # another starting corner
    v2, f2, _ = shuffle_vertices(posed, template.faces, rng=0)
    assert not fits_template(v2, f2, template)
    fb = foreign_body(template, phenotype_model, rng=1, pose="squat", target_vertices=3000)
    assert not fits_template(fb.vertices, fb.faces, template)


def test_refuses_what_it_cannot_unpose(template, rig, library_case, tmp_path):
    posed = library_case[0][0]
    with pytest.raises(MeshError, match=r"shape \(100, 3\).*13380"):
        unpose(posed[:100], rig)
    bad = posed.copy()
    bad[7] = np.nan
    with pytest.raises(MeshError, match="NaN"):
        unpose(bad, rig)
    with pytest.raises(MeshError, match="is it in mm"):
        unpose(posed * 1000, rig, mesh_name="scan.obj")
    shuffled, _, _ = shuffle_vertices(posed, template.faces, rng=0)
    with pytest.raises(UnposeError, match="cannot be unposed.*shuffled"):
        unpose(shuffled, rig, mesh_name="scan.obj")
    # The command line names the flag that goes on without unposing: a body whose arms are
    # 2.5x as long as any (37 mm from the rest-shape space).
    stretched = template.vertices.copy()
    stretched[np.abs(stretched[:, 0]) > 0.2, 0] *= 2.5
    path = tmp_path / "scan.obj"
    save_mesh(path, stretched, template.faces)
    result = runner.invoke(app, ["measure", str(path)])
    assert result.exit_code == 2 and "cannot be unposed" in result.output, result.output
    assert "--as-posed measures the mesh as it is" in result.output and "Traceback" not in result.output
    with pytest.raises(ParameterError, match="weights='dense'"):
        unpose(posed, rig, weights="dense")
    # Asked not to check, it still returns, and says how far from a rest body the result is.
    _, _, info = unpose(shuffled, rig, check=False)
    assert info.shape_distance_m > U.MAX_SHAPE_DISTANCE


def test_measure_cli_squat_standing_by_default_and_as_posed(template, rig, rest_bodies, tmp_path):
    squat = pose_bodies(rest_bodies[1], rig, load_pose_library().rotations("squat", rig), on_ground=True)
    path = tmp_path / "squat.obj"
    save_mesh(path, squat, template.faces)
    standing = runner.invoke(app, ["measure", str(path), "--json"])
    assert standing.exit_code == 0, standing.output
    data = json.loads(standing.stdout)
    for name in ("stature", "inside_leg_length", "crotch_height", "mass"):
        assert data[name]["value"] is not None, (name, data[name])
    assert abs(data["stature"]["value"] - 100 * np.ptp(rest_bodies[1][:, 1])) < 0.1
    assert data["unposed"]["unit"] == "deg" and data["unposed"]["value"] > 90
    assert "brought back to the rest pose" in data["unposed"]["note"]
    posed = runner.invoke(app, ["measure", str(path), "--json", "--as-posed"])
    assert posed.exit_code == 0, posed.output
    data = json.loads(posed.stdout)
    assert data["stature"]["value"] is None and "not upright" in data["stature"]["note"]
    assert "unposed" not in data
    table = runner.invoke(app, ["measure", str(path)])
    assert table.exit_code == 0 and "[unposed]" in table.stdout and "--as-posed" in table.stdout


def test_measure_cli_other_topology_is_measured_as_posed_with_a_note(template, phenotype_model, tmp_path):
    fb = foreign_body(template, phenotype_model, rng=2, pose="rest", target_vertices=3000,
                      frame=dict(up="y", scale=1.0, translation=(0.0, 0.0, 0.0), yaw_degrees=0.0))
    mesh, landmarks = tmp_path / "foreign.obj", tmp_path / "landmarks.json"
    save_mesh(mesh, fb.vertices, fb.faces)
    landmarks.write_text(json.dumps(fb.landmark_file))
    result = runner.invoke(app, ["measure", str(mesh), "--landmarks", str(landmarks), "--csv"])
    assert result.exit_code == 0, result.output
    row = [line for line in result.stdout.splitlines() if ",unposed," in line]
    assert len(row) == 1 and "not unposed" in row[0] and "3000 vertices" in row[0] and "measured as posed" in row[0]


def test_pose_spread_study_small(template):
    from bodyspace.report.pose_spread_report import pose_spread_markdown
    from bodyspace.studies.pose_spread import pose_spread_study

    result = pose_spread_study(template, 1, ["rest", "squat"], rng=3)
    M = len(result.names)
    assert result.posed.shape == result.unposed.shape == (1, 2, M) and result.rest.shape == (1, M)
    lengths = [i for i, u in enumerate(result.units) if u == "cm"]
    assert np.nanmax(np.abs(result.change("unposed")[..., lengths])) < 1.0
    stature = result.names.index("stature")
    assert np.isnan(result.posed[0, 1, stature]) and "upright" in result.posed_notes[0, 1, stature]
    assert np.abs(result.change("posed")[0, 0]).max() < 1e-6           # the rest pose as posed is the rest body
    text = pose_spread_markdown(result, "header line")
    assert text.startswith("header line") and "| stature | cm |" in text and "within 1 cm" in text


def test_unpose_known_is_exact_and_refuses_a_pose_that_does_not_explain_the_mesh(rig, library_case):
    """With the rotations that posed them, inverse skinning gives the true rest bodies (float
    rounding), the fit's within its tolerance, and the fit's report; other rotations leave the
    body far from the rest-shape space (so ``measure DB`` fits those instead)."""
    posed, truth, fitted, _, fit_info, R = library_case
    rest, rotations, info = U.unpose_known(posed, rig, R)
    assert _shape_error(rest, truth).max() < 1e-8
    assert np.abs(rest[..., 1].min(axis=1)).max() < 1e-12                      # on the ground, as unpose
    assert np.abs(rest - fitted).max() < 5e-4
    assert (info.shape_distance_m < U.KNOWN_POSE_TOLERANCE).all()
    assert np.abs(info.largest_rotation_deg - fit_info.largest_rotation_deg).max() < 3.0
    again = pose_bodies(rest, rig, rotations) + info.translation[:, None, :]
    assert np.abs(again - posed).max() < 1e-8
    # Axis-angle rotations (as a database stores them) give the same bodies.
    from bodyspace.rig.kinematics import matrix_to_rotvec
    assert np.abs(U.unpose_known(posed[:2], rig, matrix_to_rotvec(R[:2]))[0] - rest[:2]).max() < 1e-8
    wrong = U.unpose_known(posed, rig, np.roll(R, 1, axis=0))[2]
    assert (wrong.shape_distance_m > 10 * U.KNOWN_POSE_TOLERANCE).all()
    with pytest.raises(ParameterError, match="rotations of shape"):
        U.unpose_known(posed, rig, R[:, :5])
