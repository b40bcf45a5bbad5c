"""Registration of raw scans and landmarks for other topologies (issue 15).

Every test runs on data the pipeline never saw: raw scans of edge-of-population bodies
(``synth.scans``), in millimetres, Z up, turned, with noise, holes and outliers, and remeshed
bodies of another topology (``synth.foreign``). Scans are small (12-20 k points) and the NICP
coarse (2-3 stiffness levels) so the file stays fast; the full-size numbers are in
benchmarks/bench_register.py and docs/registration.md.
"""

import json

import numpy as np
import pytest
import trimesh
from scipy.spatial import cKDTree
from typer.testing import CliRunner

from bodyspace.cli import app
from bodyspace.errors import MeshError, RegistrationError
from bodyspace.measure import evaluate
from bodyspace.measure.definitions import load_landmarks, load_measurement_set
from bodyspace.mesh.io import load_mesh
from bodyspace.register.align import _subtree, initial_alignment, restart_limbs, similarity_from_landmarks
from bodyspace.mesh.geometry import vertex_normals
from bodyspace.register.correspondences import orient_normals
from bodyspace.register.nicp import nonrigid_icp, stiffness_schedule
from bodyspace.register.model_fit import REACH_ITERATIONS, fit_shape, phenotype_basis, reach_shape
from bodyspace.register.pipeline import RESTART_MIN_EXPLAINED, register_scan
from bodyspace.register.pose_fit import PoseState, fit_pose, posed_vertices, rest_state
from bodyspace.register.quality import PARTS, assess, body_parts
from bodyspace.register.prepare import MIN_POINTS, prepare_scan
from bodyspace.rig.kinematics import rotvec_to_matrix
from bodyspace.rig.posing import count_folded_triangles, pose_bodies
from bodyspace.studies.registration import SURFACE_LANDMARKS, registration_errors
from bodyspace.synth.foreign import closest_points, foreign_body, from_frame
from bodyspace.synth.phenotype import phenotype_array, years_to_age
from bodyspace.synth.poses import load_pose_library
from bodyspace.synth.scans import raw_scan, to_frame

runner = CliRunner()


@pytest.fixture(scope="module")
def scan(template, phenotype_model):
    return raw_scan(template, phenotype_model, 7, pose="rest", n_points=15_000)


def test_raw_scan_keeps_its_truth(scan, template):
    """Points are in mm, Z up, turned; inliers lie next to their true template vertex; 2-5 % are
    outliers; the holes removed points (fewer than sampled)."""
    assert 0.02 * 0.9 <= np.mean(~scan.inliers) <= 0.05
    inside = from_frame(scan.points[scan.inliers], **scan.frame)
    d = np.linalg.norm(inside - scan.body[scan.truth_vertex[scan.inliers]], axis=1)
    assert np.percentile(d, 95) < 0.02
    assert scan.inliers.sum() < 15_000
    assert np.ptp(scan.points[:, 2]) > 1000           # Z up, millimetres


def test_prepare_finds_units_and_up_and_refuses_too_little(scan):
    prep = prepare_scan(scan.points)
    assert prep.units == "mm" and prep.up.lstrip("-") == "z" and not prep.up_known
    assert 1.2 < np.ptp(prep.points[:, 1]) < 2.3        # metres, standing along Y
    assert np.allclose(np.linalg.norm(prep.normals, axis=1), 1.0)
    with pytest.raises(MeshError, match="no points"):
        prepare_scan(np.zeros((0, 3)))
    with pytest.raises(MeshError, match=f"at least {MIN_POINTS}"):
        prepare_scan(scan.points[:100])


def test_prepare_welds_a_triangle_soup(template):
    # an STL or a per-face OBJ repeats each corner once per triangle; read as 80,000 points stacked
    # six deep, a clean body lost 1.5 % of its surface as "isolated points"
    v = template.vertices * 1000.0
    welded = prepare_scan(v, template.faces, up="y")
    soup = prepare_scan(v[template.faces].reshape(-1, 3), np.arange(3 * len(template.faces)).reshape(-1, 3), up="y")
    assert any(n.startswith(f"merged {3 * len(template.faces) - template.n_vertices} repeated vertices")
               for n in soup.assumed)
    assert len(soup.mesh_vertices) == template.n_vertices
    assert not any("isolated" in n for n in soup.assumed), soup.assumed
    assert len(soup.points) == len(welded.points)


def test_similarity_from_landmarks_recovers_a_similarity():
    rng = np.random.default_rng(0)
    src = rng.normal(size=(13, 3))
    R, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    R *= np.sign(np.linalg.det(R))
    s, R2, t2 = similarity_from_landmarks(src, 1.7 * src @ R.T + [1.0, 2.0, 3.0])
    assert s == pytest.approx(1.7) and np.allclose(R2, R) and np.allclose(t2, [1.0, 2.0, 3.0])


def test_pose_fit_recovers_a_library_pose(template, phenotype_model):
    """Points of a foreign body in 'elbows_flexed' (a pose not among the alignment's starts):
    the twist ICP from the A-pose brings the template within 25 mm on average (its shape is
    the template's mean, not the body's: the rest is the model fit's)."""
    rig = template.rigs["default"]
    lib = load_pose_library()
    body = pose_bodies(template.vertices, rig, lib.rotations("elbows_flexed", rig))
    n = vertex_normals(body, template.faces)
    start = rest_state(template, rig)
    before = np.linalg.norm(posed_vertices(rig, start)[0] - body, axis=1).mean()
    state, _ = fit_pose(body, n, template, start, iterations=25)
    after = np.linalg.norm(posed_vertices(rig, state)[0] - body, axis=1).mean()
    assert after < 0.4 * before and after < 0.025


def test_nicp_closes_the_gap_without_folding(template, phenotype_model):
    """Per-vertex affine NICP from the mean body onto another body's points: the distance to
    the target surface halves at least, and no triangle folds (local stiffening, then unfold)."""
    other = phenotype_model.vertices({"weight": 0.8, "muscle": 0.7})[0]
    pick = np.random.default_rng(1).choice(len(other), 9000, replace=False)
    pts, nrm = other[pick], vertex_normals(other, template.faces)[pick]
    start = template.vertices
    res = nonrigid_icp(start, template.faces, template.vertices, pts, nrm, steps=3, inner=1)
    before = closest_points(start, other, template.faces)[1].mean()
    after = closest_points(res.vertices, other, template.faces)[1].mean()
    assert after < 0.5 * before
    assert count_folded_triangles(res.vertices, template.faces) == 0 and res.folded == 0
    assert stiffness_schedule(3)[0] == 3000.0


def test_nicp_keeps_the_arms_of_a_folded_armpit(template, phenotype_model):
    """A short heavy man with his arms forward (the lead's holey.ply body): plain LBS folds his
    armpits over 3 cm, and the NICP, started from the true body itself, must end with no folded
    face and still lie on the scan. Before ``unfold`` held its patch within ``UNFOLD_REACH`` the
    patch grew round the upper arm and shrank it by up to 41 mm: refused at quality 0.84."""
    phenotype = np.array([1.0, 0.35955108, 0.82496658, 0.94730592, 0.17237273, 0.95843558, 0.05169352, 0.07605177,
                          0.01143046, 0.43521326, 0.55335628])     # foreign_body(rng=default_rng(11))'s
    s = raw_scan(template, phenotype_model, 3, n_points=30_000, phenotype=phenotype, pose="arms_forward",
                 frame=dict(yaw_degrees=0.0, scale=1.0, up="y", translation=(0.0, 0.0, 0.0)))
    prep = prepare_scan(s.points, units="m", up="y")
    tree = cKDTree(prep.points)
    normals = orient_normals(prep.points, prep.normals, s.body, vertex_normals(s.body, template.faces))
    assert count_folded_triangles(s.body, template.faces) > 10          # the truth's own armpit folds
    res = nonrigid_icp(s.body, template.faces, template.vertices, prep.points, normals, steps=6, inner=2,
                       stiffness_end=10.0, scan_tree=tree)
    assert res.folded == 0 and count_folded_triangles(res.vertices, template.faces) == 0
    q = assess(res.vertices, template.faces, prep.points, res.has_target, template=template, scan_tree=tree)
    assert q.accepted, q.describe()
    upper_arms = np.isin(body_parts(template), [list(PARTS).index(p) for p in ("left upper arm", "right upper arm")])
    error = np.linalg.norm(res.vertices - s.body, axis=1)
    assert error[upper_arms].mean() < 0.004                              # 2.6 mm; 6.6 mm on one arm before


def test_limb_restarts_reach_a_body_with_both_arms_lost(template, phenotype_model):
    """Hands behind the head, both arms left hanging (what every start pose of a heavy woman's
    fit did): the body still explains 78 % of its scan, above the bound under which the limbs are
    not restarted (``RESTART_MIN_EXPLAINED``; at 0.85 the fit was refused at 0.00 without trying
    the restarts, which fit it to 1.5 mm), and the check names the arms."""
    phenotype = phenotype_array({"gender": 0.0, "age": float(years_to_age(np.array(55))), "weight": 1.0}, 1)[0]
    s = raw_scan(template, phenotype_model, 1, n_points=20_000, phenotype=phenotype, pose="hands_behind_head",
                 frame=dict(yaw_degrees=0.0, scale=1.0, up="y", translation=(0.0, 0.0, 0.0)))
    arms_down = pose_bodies(phenotype_model.vertices(phenotype[None])[0], template.rigs["default"],
                            load_pose_library().rotations("rest", template.rigs["default"]), on_ground=True)
    q = assess(arms_down, template.faces, s.points, np.ones(len(arms_down), dtype=bool), template=template,
               bridged_counts=True)
    assert RESTART_MIN_EXPLAINED <= q.explained < 0.85
    assert {"left upper arm", "right upper arm"} <= {p.name for p in q.failed_parts}


def test_register_refuses_two_people(scan, template):
    """Two bodies side by side (every other point of the scan twice, 0.9 m apart): the fit
    explains about half of the points and is refused."""
    half = scan.points[::2]
    pts = np.concatenate([half, half + [900.0, 0.0, 0.0]])
    with pytest.raises(RegistrationError, match="refused"):
        register_scan(pts, template=template, units="mm", up="z", steps=1, pose_iterations=4,
                      align_iterations=3)


@pytest.fixture(scope="module")
def cli_fit(scan, template, phenotype_model, tmp_path_factory):
    """One ``bodyspace register`` run on the scan (mm, Z up not given, turned; 13 landmarks,
    2 NICP levels) standing on a scanned turntable (its top, side and the ground around it: as
    many points again as the body; the same body, frame and landmarks as ``scan``), shared by the
    tests that read its outputs: a registration costs most of this file's time."""
    tmp = tmp_path_factory.mktemp("register")
    path = tmp / "scan.ply"
    on_turntable = raw_scan(template, phenotype_model, 7, pose="rest", n_points=15_000, floor="turntable")
    assert np.allclose(on_turntable.body, scan.body)
    trimesh.PointCloud(on_turntable.points).export(path)
    lm = tmp / "lm.json"
    lm.write_text(json.dumps({"landmarks": {n: scan.landmark_file()["landmarks"][n] for n in SURFACE_LANDMARKS},
                              "unit": "mm"}))
    out = tmp / "fit"
    result = runner.invoke(app, ["register", str(path), "--landmarks", str(lm), "--steps", "2", "--out", str(out)])
    return result, path, out


def test_register_fits_the_scan_and_accepts_it(cli_fit, scan, template):
    """The pipeline on a raw scan on a turntable: the fit is near the truth in the scan's own frame
    (measured on this 15 k-point scan: 2.5 mm, surface 0.8 mm), the units and up axis were found,
    the turntable removed, its quality is accepted."""
    result, _, out = cli_fit
    assert result.exit_code == 0, result.output
    v, f = load_mesh(out / "registered.obj")
    e = registration_errors(v, f, scan)
    assert e["correspondence_mm"] < 8.0
    assert e["surface_mm"] < 2.0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["accepted"] and summary["units"] == "mm" and summary["up"].lstrip("-") == "z"
    # The turntable found and removed (its normal gives the up axis, sign and all).
    assert any(n.startswith("removed the floor") for n in summary["assumed"]), summary["assumed"]
    assert any(n.startswith("removed a platform on it") for n in summary["assumed"]), summary["assumed"]
    assert summary["up"] == "z" and summary["one_sided"] is None
    # Every body part on its points, none restarted (a restart costs seconds: only lost limbs get one).
    assert len(summary["parts"]) == 14 and all(p["accepted"] for p in summary["parts"].values())
    assert summary["failed_parts"] == [] and summary["restarted_limbs"] == []


def test_cli_register_writes_outputs(cli_fit, scan, template, phenotype_model, tmp_path):
    result, path, out = cli_fit
    assert result.exit_code == 0, result.output
    names = {p.name for p in out.iterdir()}
    assert {"registered.obj", "registered_standard.obj", "standing.obj", "distance.csv", "pose.json",
            "measurements.json", "measurements.csv", "summary.json", "quality.csv", "distance.png"} <= names
    rows = (out / "quality.csv").read_text().splitlines()
    assert rows[0].startswith("part,quality,accepted") and len(rows) == 15
    assert any(r.startswith("left hand,") for r in rows)
    m = json.loads((out / "measurements.json").read_text())["measurements"]
    truth = evaluate(load_measurement_set(), phenotype_model.vertices(scan.phenotype[None])[0], template.faces)
    assert abs(m["stature"]["value"] - 100 * truth["stature"].value) < 1.5      # cm
    assert "shape model refitted" in m["unposed"]["note"]
    sv, _ = load_mesh(out / "standing.obj")                                      # metres, on the ground
    assert abs(sv[:, 1].min()) < 1e-6 and abs(np.ptp(sv[:, 1]) - truth["stature"].value) < 0.015
    again = runner.invoke(app, ["register", str(path), "--out", str(out)])
    assert again.exit_code == 2 and "--force" in again.output
    bad = runner.invoke(app, ["register", str(tmp_path / "missing.ply"), "--out", str(tmp_path / "x")])
    assert bad.exit_code == 2 and "no such file" in bad.output


def test_cli_landmarks_on_a_remeshed_body(template, phenotype_model, tmp_path):
    """A body of another topology (5,000 vertices, mm, Z up, turned): the carried landmarks are
    within 2 cm of the truth on average and ``measure --landmarks`` reads the file."""
    body = foreign_body(template, phenotype_model, rng=3, pose="rest", target_vertices=5000)
    mesh = tmp_path / "foreign.obj"
    trimesh.Trimesh(body.vertices, body.faces, process=False).export(mesh)
    out = tmp_path / "lm.json"
    result = runner.invoke(app, ["landmarks", str(mesh), "--out", str(out)])     # up and units found
    assert result.exit_code == 0, result.output
    lms, n = load_landmarks(out)
    v, _ = load_mesh(mesh)
    err = [np.linalg.norm(w @ v[ids] - body.true_landmarks[name]) for name, (ids, w) in lms.items()]
    assert np.mean(err) < 20.0                                   # millimetres
    joints = json.loads(out.read_text())["joints"]["neck_girth"]["normal"]     # carried from the template
    assert all(0 <= i < len(v) for end in ("from", "to") for i in joints[end]["vertices"])
    # The measure command it suggests names the unit and the up axis it found (it once left out
    # the up axis, and that command was refused); the printed line may wrap inside the paths.
    printed = " ".join(result.output.split())
    suggested = printed[printed.index("bodyspace measure "):]
    assert "--units mm --up z)" in suggested, suggested
    measured = runner.invoke(app, ["measure", str(mesh), "--landmarks", str(out), "--units", "mm", "--up", "z",
                                   "--json"])
    assert measured.exit_code == 0, measured.output


def _box_points(lo, hi, n, rng):
    """``n`` points on the surface of an axis-aligned box (lo, hi), spread by area."""
    lo, hi = np.array(lo, dtype=float), np.array(hi, dtype=float)
    size = hi - lo
    areas = np.array([size[1] * size[2], size[0] * size[2], size[0] * size[1]])
    face = rng.choice(6, n, p=np.repeat(areas, 2) / (2 * areas.sum()))
    p = lo + rng.random((n, 3)) * size
    axis, side = face // 2, face % 2
    p[np.arange(n), axis] = np.where(side, hi[axis], lo[axis])
    return p


def test_register_refuses_a_chair(template):
    """A chair (seat, back, four legs; 0.95 m tall, in mm): refused (measured quality 0.35)."""
    rng = np.random.default_rng(0)
    parts = [([0, 0.42, 0], [0.45, 0.47, 0.45], 3000), ([0, 0.47, 0.40], [0.45, 0.95, 0.45], 2500)]
    parts += [([x, 0, z], [x + 0.04, 0.42, z + 0.04], 750) for x in (0, 0.41) for z in (0, 0.41)]
    pts = np.concatenate([_box_points(lo, hi, n, rng) for lo, hi, n in parts]) * 1000
    with pytest.raises(RegistrationError, match="refused"):
        register_scan(pts, template=template, units="mm", up="y", steps=1, pose_iterations=4,
                      align_iterations=3)


def test_quality_names_a_lost_hand(scan, template):
    """The per-part check on the true body against its own scan: every part accepted, also with
    the left forearm twisted 10° (the hand moves up to 18 mm); twisted 65° (the hand turned
    through, up to 11 cm: the step-forward scan's defect) the fit is refused and the left hand,
    alone, named, although the whole body still explains 90 % of the points (measured quality
    0.23, the hand 21 % on the scan)."""
    rig = template.rigs["default"]
    points = from_frame(scan.points, **scan.frame)
    everywhere = np.ones(template.n_vertices, dtype=bool)
    good = assess(scan.body, template.faces, points, everywhere, template=template)
    assert good.accepted and min(p.quality for p in good.parts) >= 0.9 and len(good.parts) == 14
    head, tail = rig.heads(scan.body)[[rig.bone_index("lowerarm02.L"), rig.bone_index("wrist.L")]]
    axis = (tail - head) / np.linalg.norm(tail - head)
    for degrees, accepted in ((10, True), (65, False)):
        R = np.repeat(np.eye(3)[None], rig.n_bones, axis=0)
        R[rig.bone_index("lowerarm02.L")] = rotvec_to_matrix(np.radians(degrees) * axis)
        q = assess(pose_bodies(scan.body, rig, R), template.faces, points, everywhere, template=template)
        assert q.accepted == accepted, q.describe()
        if not accepted:
            assert [p.name for p in q.failed_parts] == ["left hand"] and q.explained > 0.85
            assert "not fitted: left hand" in q.describe() and not q.to_dict()["parts"]["left hand"]["accepted"]


def test_quality_takes_a_part_the_scanner_missed_for_a_hole(scan, template):
    """The true body against its own scan with the left foot's points taken out (a foot the
    scanner missed): nothing of the scan is unexplained, so the unseen foot is a hole, and the fit
    is accepted; the same scan with the left forearm twisted 65° is still refused, the hand named."""
    points = from_frame(scan.points, **scan.frame)
    foot = body_parts(template) == list(PARTS).index("left foot")
    near_foot = cKDTree(scan.body[foot]).query(points)[0] < 0.03
    holed = points[~near_foot]
    everywhere = np.ones(template.n_vertices, dtype=bool)
    q = assess(scan.body, template.faces, holed, everywhere, template=template)
    seen = {p.name: p.seen for p in q.parts}
    assert seen["left foot"] < 0.3 and q.accepted, q.describe()
    rig = template.rigs["default"]
    head, tail = rig.heads(scan.body)[[rig.bone_index("lowerarm02.L"), rig.bone_index("wrist.L")]]
    R = np.repeat(np.eye(3)[None], rig.n_bones, axis=0)
    R[rig.bone_index("lowerarm02.L")] = rotvec_to_matrix(np.radians(65) * (tail - head) / np.linalg.norm(tail - head))
    lost = assess(pose_bodies(scan.body, rig, R), template.faces, holed, everywhere, template=template)
    assert not lost.accepted and "left hand" in [p.name for p in lost.failed_parts]


def test_quality_accepts_a_fold_the_fit_bridges(scan, template):
    """Scan surface the fit bridges while every part lies on its points (the step-forward scan's
    heavy belly: a fold 13-62 mm from a good fit over 580 cm², refused at 0.85 by the old rule):
    the true body against its own scan plus a second layer of the lower belly's points 3 cm in
    front of it (640 cm², 22 % of the trunk: 0.78 by the old rule). Reported as bridged and accepted; with the
    left forearm twisted 65° as well, the lost hand is still refused and named. The check before
    the limb restarts (``bridged_counts``) flags the trunk."""
    points = from_frame(scan.points, **scan.frame)
    F = template.faces
    trunk = body_parts(template) == list(PARTS).index("trunk")
    body_n = vertex_normals(scan.body, F)
    front = trunk & (body_n[:, 2] > 0.7)
    low = np.percentile(scan.body[trunk, 1], 35)                   # the lower belly's height
    belly = scan.body[front][np.argmin(np.abs(scan.body[front, 1] - low) + np.abs(scan.body[front, 0]))]
    tree = cKDTree(scan.body)
    near = np.linalg.norm(points - belly, axis=1) < 0.13
    layer = points[near] + 0.03 * body_n[tree.query(points[near])[1]]
    folded = np.concatenate([points, layer])
    everywhere = np.ones(template.n_vertices, dtype=bool)
    q = assess(scan.body, F, folded, everywhere, template=template)
    parts = {p.name: p for p in q.parts}
    assert q.accepted and parts["trunk"].bridged > 0.03 and parts["trunk"].unexplained == 0, q.describe()
    # Before the limb restarts every patch counts (a restart is cheap): the trunk is flagged.
    strict = assess(scan.body, F, folded, everywhere, template=template, bridged_counts=True)
    assert [p.name for p in strict.failed_parts] == ["trunk"], strict.describe()
    rig = template.rigs["default"]
    head, tail = rig.heads(scan.body)[[rig.bone_index("lowerarm02.L"), rig.bone_index("wrist.L")]]
    R = np.repeat(np.eye(3)[None], rig.n_bones, axis=0)
    R[rig.bone_index("lowerarm02.L")] = rotvec_to_matrix(np.radians(65) * (tail - head) / np.linalg.norm(tail - head))
    lost = assess(pose_bodies(scan.body, rig, R), F, folded, everywhere, template=template)
    assert not lost.accepted and lost.failed_parts[0].name == "left hand", lost.describe()


def _lost_arm(template, pose: str, clavicle: str, hand_name: str, hand_score: float, arm_start=None):
    """The posed mean body of library ``pose`` as the scan, the fit's state with the arm below
    ``clavicle`` set to ``arm_start`` (rotations of that subtree; None: unposed), the hand's
    vertices and per-part scores that flag the hand."""
    rig = template.rigs["default"]
    truth = load_pose_library().rotations(pose, rig)
    body = pose_bodies(template.vertices, rig, truth)
    arm = _subtree(rig.parents, rig.bone_index(clavicle))
    start = truth.copy()
    start[arm] = np.eye(3) if arm_start is None else arm_start[arm]
    state = PoseState(template.vertices, start, 1.0, np.zeros(3))
    hand = body_parts(template) == list(PARTS).index(hand_name)
    parts = {name: 1.0 for name in PARTS} | {hand_name: hand_score}
    return rig, body, state, hand, parts


def _restart_and_hand_error(template, body, state, hand, parts, arm_poses):
    """restart_limbs with the given arm starts (no leg starts): the hand's mean error after it (m)
    and the limbs it changed."""
    fitted, changed = restart_limbs(body, vertex_normals(body, template.faces), template, state, parts,
                                    cKDTree(body), poses={"arm": arm_poses, "leg": ()})
    rig = template.rigs["default"]
    return np.linalg.norm(posed_vertices(rig, fitted)[0][hand] - body[hand], axis=1).mean(), changed


def test_restart_limbs_finds_a_lost_arm(template):
    """A body stepping forward, its left arm swinging back (points: the posed mean body's
    vertices); the fit's left arm held forward (the hand 30 cm off): flagged, the arm is
    restarted from library arm poses and the one whose fit has the least residual both ways
    brings the hand within 2 cm (measured 14 mm after the restart's 9 iterations; the pipeline
    fits the joint rounds after it); the other limbs, not flagged, are left alone."""
    forward = load_pose_library().rotations("arms_forward", template.rigs["default"])
    rig, body, state, hand, parts = _lost_arm(template, "step_forward_left", "clavicle.L", "left hand", 0.2,
                                              arm_start=forward)
    before = np.linalg.norm(posed_vertices(rig, state)[0][hand] - body[hand], axis=1).mean()
    # Three arm starts (the pipeline's 10 cost more time, not more of the test); the truth is none.
    after, changed = _restart_and_hand_error(template, body, state, hand, parts, ("rest", "t_pose", "arms_back"))
    assert changed == ["left arm"] and before > 0.2 and after < 0.02


def test_restart_limbs_mirrors_the_other_arm(template):
    """Hands on the hips, the fit's right arm hanging (the right hand lost, as with 13 landmarks
    on the benchmark's scan): with no library start near the truth (only the A-pose), the left
    arm mirrored is the start that brings the right hand back within 2 cm."""
    _, body, state, hand, parts = _lost_arm(template, "hands_on_hips", "clavicle.R", "right hand", 0.4)
    after, changed = _restart_and_hand_error(template, body, state, hand, parts, ("rest",))
    assert changed == ["right arm"] and after < 0.02


def test_alignment_faces_a_stepping_man_whose_axes_are_diagonal(template, phenotype_model):
    """A thin tall man stepping forward (the ISO study's scan 27, up axis found): his horizontal
    principal axes lie 44° off his heading, and of the four headings they give the backward one
    scored best; fitted from it he came out facing backwards (592 mm, refused). With the
    diagonals scored too the alignment faces him front (measured: 55 mm from the truth after
    the alignment's short fit, 534 mm before)."""
    scan = raw_scan(template, phenotype_model, 1027, pose="step_forward_left", n_points=20_000,
                    weights="original", preserve_volume=False)
    prep = prepare_scan(scan.points)
    assert not prep.up_known
    align = initial_alignment(prep.points, prep.normals, template, up_known=prep.up_known, rng=0)
    x, _, _ = posed_vertices(template.rigs["default"], align.state)
    truth = align.apply(np.linalg.solve(prep.to_scan[:3, :3], to_frame(scan.body, **scan.frame).T).T)
    assert np.linalg.norm(x - truth, axis=1).mean() < 0.1


def test_last_model_fit_reaches_large_low_breasts(template, phenotype_model):
    """The held-out ISO scan 44's woman (cup size 0.93, firmness 0.04): from the shape of the same
    body with ordinary breasts (cup and firmness 0.5: her breast vertices 11 cm off, as the pose
    rounds left them on her scan), the last model fit (light prior, 3 cm gate) brings the breast
    vertices within 15 mm; pairs gated at the joint rounds' last 1 cm never reach them."""
    basis = phenotype_basis(template)
    ph = np.array([0.0, 0.36, 0.96, 0.89, 0.14, 0.93, 0.93, 0.04, 0.9, 0.04, 0.06])
    body = phenotype_model.vertices(ph[None])[0]
    ordinary = ph.copy()
    ordinary[6:8] = 0.5
    start = phenotype_model.vertices(ordinary[None])[0]
    A = np.concatenate([basis.components.reshape(len(basis.components), -1).T,
                        np.tile(np.eye(3), (template.n_vertices, 1))], axis=1)
    sol = np.linalg.lstsq(A, (start - basis.mean).ravel(), rcond=None)[0]
    K = len(basis.components)
    rig = template.rigs["default"]
    state = PoseState(basis.body(sol[:K]), rest_state(template, rig).rotations, 1.0, sol[K:], sol[:K])
    rng = np.random.default_rng(3)
    f = template.faces
    cross = np.cross(body[f[:, 1]] - body[f[:, 0]], body[f[:, 2]] - body[f[:, 0]])
    area = np.linalg.norm(cross, axis=1)
    pick = rng.choice(len(f), 15_000, p=area / area.sum())
    u = rng.random((len(pick), 2))
    u[u.sum(axis=1) > 1] = 1 - u[u.sum(axis=1) > 1]
    corner = body[f[pick, 0]]
    pts = corner + u[:, :1] * (body[f[pick, 1]] - corner) + u[:, 1:] * (body[f[pick, 2]] - corner)
    pts += rng.normal(0.0, 0.002, pts.shape)
    nrm = cross[pick] / area[pick, None]
    breast = [8549, 1877]

    def breast_error(s):
        return np.linalg.norm(posed_vertices(rig, s)[0][breast] - body[breast], axis=1).max()

    assert breast_error(state) > 0.08
    narrow, _ = fit_shape(pts, nrm, template, state, basis, iterations=REACH_ITERATIONS, max_distance=0.01,
                          coefficients=state.coefficients)
    reached, _ = reach_shape(pts, nrm, template, state, basis)
    assert breast_error(narrow) > 0.05
    assert breast_error(reached) < 0.015
