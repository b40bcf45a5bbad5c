"""Part-aware girths (issue 12 §3): the tape goes round one body part, on the template and on
foreign topologies; stature of standing bodies; implausible values are NaN with a reason."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from bodyspace.errors import MeasurementError
from bodyspace.measure import evaluate, load_landmarks, load_measurement_set, measurement_set_from_dict, to_json
from bodyspace.measure.definitions import with_landmarks, with_vertex_parts
from bodyspace.measure.parts import PART_INDEX, PARTS, encode_parts, parts_from_landmarks
from bodyspace.rig.posing import pose_bodies
from bodyspace.synth.foreign import closest_points, foreign_topology, transfer
from bodyspace.synth.poses import load_pose_library

ARMS = {"upper_arm_l", "forearm_l", "hand_l", "upper_arm_r", "forearm_r", "hand_r"}
POSES = ("rest", "arms_crossed", "look_down", "head_tilt_left", "squat", "hands_on_hips")


@pytest.fixture(scope="module")
def mset():
    return load_measurement_set()


@pytest.fixture(scope="module")
def mean_body(phenotype_model):
    v = phenotype_model.vertices({})[0]
    return v - np.array([0.0, v[:, 1].min(), 0.0])


@pytest.fixture(scope="module")
def posed(template, mean_body):
    lib = load_pose_library()
    rig = template.rigs["default"]
    return pose_bodies(np.repeat(mean_body[None], len(POSES), 0), rig, lib.stack(list(POSES), rig), on_ground=True)


def _one(mset, name, **changes):
    """``mset`` with only measurement ``name`` (its fields changed by ``changes``), no conditions."""
    m = dict(next(m for m in mset.measurements if m["name"] == name), **changes)
    m["requires"] = []
    return dataclasses.replace(mset, measurements=(m,), conditions={})


def _labels_under(line: np.ndarray, vertices: np.ndarray, labels: np.ndarray, faces: np.ndarray) -> set:
    """The parts the points of a measured polyline lie on: the majority label of the vertices of
    the mesh face closest to each point. A tape round the thigh may touch the torso where an edge
    leaves the thigh (its crossing is on the thigh's half), never the other leg or an arm."""
    corr, _ = closest_points(line, vertices, faces)
    lab = labels[faces[corr.face]]                                                   # (K, 3)
    major = np.where(lab[:, 0] == lab[:, 1], lab[:, 0], lab[:, 2])
    return {PARTS[i] for i in major}


def test_template_labels_from_the_rig(mset, template):
    counts = np.bincount(mset.vertex_parts + 1, minlength=len(PARTS) + 1)
    assert counts[0] == 0                      # every template vertex is on a part
    assert (counts[1:] > 100).all(), dict(zip(PARTS, counts[1:]))
    # Left and right mirror each other (the template is symmetric).
    left = mset.vertex_parts[template.left]
    right = mset.vertex_parts[template.mirror[template.left]]
    flip = {PART_INDEX[p]: PART_INDEX[p[:-1] + ("r" if p.endswith("l") else "l")] if p[-2:] in ("_l", "_r")
            else PART_INDEX[p] for p in PARTS}
    assert np.mean([flip[a] == b for a, b in zip(left, right)]) > 0.99


def test_arms_crossed_chest_stays_on_the_torso(mset, posed, template):
    """The chest tape in arms_crossed touches only torso vertices: it fails if an arm enters."""
    i = POSES.index("arms_crossed")
    r = evaluate(mset, posed[i], template.faces, keep_polylines=True, check_scale=False)
    assert not _labels_under(r["chest_girth"].polyline, posed[i], mset.vertex_parts, template.faces) & ARMS
    rest = evaluate(mset, posed[0], template.faces)
    assert abs(r["chest_girth"].value - rest["chest_girth"].value) < 0.03


def test_thigh_at_the_crotch_is_one_leg(mset, mean_body, template):
    """A thigh plane as high as the crotch cuts both legs; the tape keeps only the left thigh."""
    tape = _one(mset, "thigh_girth_l", at="crotch", band=None)
    r = evaluate(tape, mean_body, template.faces, keep_polylines=True)
    on = _labels_under(r["thigh_girth_l"].polyline, mean_body, mset.vertex_parts, template.faces)
    assert on <= {"thigh_l", "torso"}
    # One thigh at its top: above the girth at the thigh landmark, far below both legs' ~1 m.
    low = evaluate(mset, mean_body, template.faces)["thigh_girth_l"].value
    assert low < r["thigh_girth_l"].value < 1.3 * low


def test_thigh_plane_hangs_on_the_joints_not_on_a_thigh_vertex(mset, mean_body, template):
    """The thigh girth's plane (31.6 % of the way from the hip to the knee joint, normal to the
    thigh) is the thigh landmark's plane on the mean body, and a thigh landmark slid 15 mm down the
    leg (as a registration slides it: docs/registration.md) no longer moves the value."""
    names = list(mset.landmarks)
    P = np.asarray(mset.landmark_matrix(template.n_vertices) @ mean_body)
    p = {n: P[i] for i, n in enumerate(names)}
    axis = p["knee_joint_l"] - p["hip_joint_l"]
    axis /= np.linalg.norm(axis)
    anchor = p["hip_joint_l"] + 0.316 * (p["knee_joint_l"] - p["hip_joint_l"])
    assert abs((anchor - p["thigh_l"]) @ axis) < 0.0015         # the same level within 1.5 mm
    at_landmark = evaluate(_one(mset, "thigh_girth_l", at="thigh_l", band=None), mean_body, template.faces)
    value = evaluate(_one(mset, "thigh_girth_l"), mean_body, template.faces)["thigh_girth_l"].value
    assert abs(value - at_landmark["thigh_girth_l"].value) < 0.001
    # The vertex nearest the thigh landmark 15 mm further down the thigh, as the landmark.
    slid = int(np.argmin(np.linalg.norm(mean_body - (p["thigh_l"] + 0.015 * axis), axis=1)))
    lms = {n: (ids, w) for n, (ids, w) in mset.landmarks.items()} | {"thigh_l": (np.array([slid]), np.array([1.0]))}
    moved = dataclasses.replace(_one(mset, "thigh_girth_l"), landmarks=lms)
    old_rule = dataclasses.replace(_one(mset, "thigh_girth_l", at="thigh_l", band=None), landmarks=lms)
    assert evaluate(moved, mean_body, template.faces)["thigh_girth_l"].value == pytest.approx(value, abs=1e-9)
    # ... where the plane through the landmark (the old definition) lost ~1 cm.
    assert evaluate(old_rule, mean_body, template.faces)["thigh_girth_l"].value < value - 0.005


def test_neck_in_look_down_keeps_the_chin_out(mset, posed, template):
    i = POSES.index("look_down")
    r = evaluate(mset, posed[i], template.faces, keep_polylines=True, check_scale=False)
    assert "head" not in _labels_under(r["neck_girth"].polyline, posed[i], mset.vertex_parts, template.faces)
    rest = evaluate(mset, posed[0], template.faces)
    assert abs(r["neck_girth"].value - rest["neck_girth"].value) < 0.03     # was 16-34 cm off


def test_stature_of_standing_bodies_and_reasons(mset, posed, template):
    r = evaluate(mset, posed, template.faces, check_scale=False)
    st = dict(zip(POSES, r["stature"].value))
    assert np.isfinite(st["head_tilt_left"]) and abs(st["head_tilt_left"] - st["rest"]) < 0.02
    assert np.isfinite(st["arms_crossed"]) and abs(st["arms_crossed"] - st["rest"]) < 0.005
    assert np.isnan(st["squat"]) and "not upright" in r["stature"].note[POSES.index("squat")]
    assert "not head_level" in r["stature"].note[POSES.index("look_down")]
    doc = to_json(r)
    assert doc["stature"]["value"][POSES.index("squat")] is None
    assert "not upright" in doc["stature"]["note"][POSES.index("squat")]
    json.dumps(doc, allow_nan=False)


def test_implausible_girth_is_nan_with_reason(mset, mean_body, template):
    tight = _one(mset, "chest_girth", plausible={"range": [0.2, 0.5]})
    r = evaluate(tight, np.stack([mean_body, mean_body]), template.faces)
    assert np.isnan(r["chest_girth"].value).all()
    assert r["chest_girth"].note[0].startswith("implausible: chest girth") and "cm" in r["chest_girth"].note[0]
    with pytest.raises(MeasurementError, match="ratio_to"):
        measurement_set_from_dict(dict(mset.to_dict(), measurements=[
            dict(mset.to_dict()["measurements"][1], plausible={"ratio_to": {"hip_girth": [0.5, 2]}})]))


def test_child_girths_are_not_implausible(mset, mean_body, template):
    """A child's girths are an adult's scaled down: a 1 m body's wrist of ~9.6 cm is measured,
    not NaN'd as a tape error (the low end of the range follows the stature); the adult's own
    range still holds, and a bad 'adult_stature' is refused naming the field."""
    adult = evaluate(mset, mean_body, template.faces)
    child = evaluate(mset, 0.6 * mean_body, template.faces)
    assert child["stature"].value < 1.1
    for k in ("wrist_girth_l", "wrist_girth_r", "neck_girth", "chest_girth", "waist_girth"):
        assert child[k].value == pytest.approx(0.6 * adult[k].value, rel=0.02), (k, child[k].note)
    wrist = next(m for m in mset.measurements if m["name"] == "wrist_girth_l")
    assert child["wrist_girth_l"].value < wrist["plausible"]["range"][0]      # NaN before
    d = mset.to_dict()
    stature, chest = (next(m for m in d["measurements"] if m["name"] == k) for k in ("stature", "chest_girth"))
    tight = measurement_set_from_dict(dict(d, measurements=[
        dict(stature, requires=[]), dict(chest, plausible={"adult_stature": 1.5, "range": [1.2, 2.0]})]))
    r = evaluate(tight, np.stack([mean_body, 0.6 * mean_body]), template.faces)
    assert np.isnan(r["chest_girth"].value).all()
    assert "of this stature" in r["chest_girth"].note[1] and "of this stature" not in r["chest_girth"].note[0]
    for bad in (170, "1.5"):
        with pytest.raises(MeasurementError, match="adult_stature"):
            measurement_set_from_dict(dict(d, measurements=[
                stature, dict(chest, plausible={"adult_stature": bad, "range": [0.5, 2.0]})]))


def test_landmark_in_a_hole_is_measured_with_a_note(mset, mean_body, template):
    """A scan's hole that takes a landmark vertex (the vertices stay, as in registered scans) is
    measured from the vertex's position, and the measurements using it say so; a face list cut
    short (a quarter of the faces gone) is still refused."""
    from bodyspace.synth.foreign import punch_holes
    bust = int(mset.landmarks["bust_l"][0][0])
    holed = punch_holes(mean_body, template.faces, mean_body[[bust]], radius=0.03)
    whole = evaluate(mset, mean_body, template.faces)
    r = evaluate(mset, mean_body, holed)
    assert abs(r["chest_girth"].value - whole["chest_girth"].value) < 0.012
    assert "'bust_l' lies in a hole" in r["chest_girth"].note
    assert r["waist_girth"].note is None and r["stature"].note is None
    assert "lies in a hole" in to_json(r)["chest_girth"]["note"]
    with pytest.raises(MeasurementError, match="on none of them"):
        evaluate(mset, mean_body, template.faces[: 3 * len(template.faces) // 4])


def test_parts_round_trip_and_older_files(mset, mean_body, template):
    d = mset.to_dict()
    back = measurement_set_from_dict(json.loads(json.dumps(d)))
    assert np.array_equal(back.vertex_parts, mset.vertex_parts)
    assert [m.get("part") for m in back.measurements] == [m.get("part") for m in mset.measurements]
    old = dict(d)
    del old["vertex_parts"]
    older = measurement_set_from_dict(old)
    assert older.vertex_parts is None
    a, b = evaluate(mset, mean_body, template.faces), evaluate(older, mean_body, template.faces)
    for k in ("chest_girth", "waist_girth", "thigh_girth_l", "upper_arm_girth_r"):
        assert abs(a[k].value - b[k].value) < 0.008, k           # labels from the landmarks instead
    with pytest.raises(MeasurementError, match="vertex_parts.*letter"):
        measurement_set_from_dict(dict(d, vertex_parts="?" * len(d["vertex_parts"])))
    with pytest.raises(MeasurementError, match="vertex_parts.*one per vertex"):
        measurement_set_from_dict(dict(d, vertex_parts=d["vertex_parts"][:-5]))
    with pytest.raises(MeasurementError, match="field 'part'"):
        measurement_set_from_dict(dict(d, measurements=[dict(d["measurements"][1], part="tail")]))
    assert encode_parts(mset.vertex_parts) == d["vertex_parts"]


@pytest.fixture(scope="module")
def foreign(template, mset, tmp_path_factory):
    """A remeshed, reordered topology with its landmark file, and the template's poses on it."""
    topo = foreign_topology(template, 5000, rng=3, mset=mset)
    path = tmp_path_factory.mktemp("foreign") / "landmarks.json"
    path.write_text(json.dumps(topo.landmark_file()))
    lms, nv = load_landmarks(path)
    return topo, with_landmarks(mset, lms, nv, str(path))


def test_foreign_topology_tape_stays_on_its_part(foreign, posed, template, mset):
    """On another topology the parts come from the landmark skeleton; the left thigh at the crotch
    and the chest with crossed arms keep their part (fails if the other leg or an arm enters)."""
    topo, fset = foreign
    bodies = transfer(topo.correspondence, template.faces, posed)
    L = fset.landmark_matrix(bodies.shape[1])
    P = L @ bodies[0]
    labels = parts_from_landmarks(bodies[0], {n: P[i] for i, n in enumerate(fset.landmarks)})
    fset = with_vertex_parts(fset, labels)          # labelled on the standing body, kept in every pose
    i = POSES.index("arms_crossed")
    r = evaluate(fset, bodies[i], topo.faces, keep_polylines=True, check_scale=False)
    assert not _labels_under(r["chest_girth"].polyline, bodies[i], labels, topo.faces) & ARMS
    j = POSES.index("look_down")
    r = evaluate(fset, bodies[[0, j]], topo.faces, keep_polylines=True, check_scale=False)
    assert "head" not in _labels_under(r["neck_girth"].polyline[1], bodies[j], labels, topo.faces)
    assert abs(r["neck_girth"].value[1] - r["neck_girth"].value[0]) < 0.03
    t = evaluate(_one(fset, "thigh_girth_l", at="crotch", band=None), bodies[0], topo.faces, keep_polylines=True)
    assert _labels_under(t["thigh_girth_l"].polyline, bodies[0], labels, topo.faces) <= {"thigh_l", "torso"}
    # Same girths as the template's (its rig labels) within 1 cm, stature within 5 mm.
    ref = evaluate(mset, posed[0], template.faces)
    got = evaluate(fset, bodies[0], topo.faces)
    for k in ("chest_girth", "waist_girth", "hip_girth", "thigh_girth_l", "calf_girth_r", "neck_girth",
              "upper_arm_girth_l"):
        assert abs(got[k].value - ref[k].value) < 0.01, (k, got[k].value, ref[k].value)
    assert abs(got["stature"].value - ref["stature"].value) < 0.005


def test_mass_takes_one_sex_per_body(mset, mean_body, template):
    two = np.stack([mean_body, mean_body])
    r = evaluate(mset, two, template.faces, male=np.array([1.0, 0.0]), age_years=np.array([30.0, 30.0]))
    m = r["mass"].value
    assert np.isfinite(m).all() and m[0] != m[1]
    one = evaluate(mset, mean_body, template.faces, male=1.0)
    assert m[0] == pytest.approx(one["mass"].value)


def _tilted(template, body, bones, degrees):
    """``body`` with the head tilted sideways (about the front axis) by ``degrees``, shared by ``bones``."""
    from bodyspace.rig.kinematics import rotvec_to_matrix
    rig = template.rigs["default"]
    rv = np.zeros((rig.n_bones, 3))
    for b in bones:
        rv[rig.bone_index(b)] = [0.0, 0.0, np.radians(degrees / len(bones))]
    return pose_bodies(body, rig, rotvec_to_matrix(rv), on_ground=True)


def test_neck_plane_follows_the_neck_when_the_head_tilts(mset, mean_body, template):
    """Issue 12 §3: the neck girth's plane leans sideways with the neck's own axis (neck joint to
    head joint), so a head tilted sideways by 20-30° keeps the neck girth within 1 cm of upright
    (here within 0.8 cm); the old axis, neck to head top, leaned with the head (1.4-2 cm at 30°)."""
    neck = next(m for m in mset.measurements if m["name"] == "neck_girth")
    assert isinstance(neck["normal"], dict)
    new, old = _one(mset, "neck_girth"), _one(mset, "neck_girth", normal=neck["normal"]["fallback"])
    cases = [(["neck01", "neck02", "neck03", "head"], 20), (["neck01", "neck02", "neck03", "head"], -30),
             (["head"], 25), (["head"], -30)]
    bodies = np.stack([mean_body] + [_tilted(template, mean_body, bones, deg) for bones, deg in cases])
    got = evaluate(new, bodies, template.faces)["neck_girth"].value
    assert np.abs(got[1:] - got[0]).max() < 0.008, got[1:] - got[0]
    before = evaluate(old, bodies, template.faces)["neck_girth"].value
    assert np.abs(before[1:] - before[0]).max() > 0.01
    assert abs(got[0] - before[0]) < 1e-4           # standing, the same girth (the lean forward is the landmarks')
    # Looking down (a forward turn of neck and head) keeps the old plane: the sideways part only.
    lib = load_pose_library()
    down = pose_bodies(mean_body, template.rigs["default"], lib.rotations("look_down", template.rigs["default"]),
                       on_ground=True)
    assert evaluate(new, down, template.faces)["neck_girth"].value == pytest.approx(
        evaluate(old, down, template.faces)["neck_girth"].value, abs=1e-4)


def test_joint_axis_is_checked_and_becomes_its_fallback_on_another_topology(mset, foreign):
    neck = next(m for m in mset.measurements if m["name"] == "neck_girth")
    d = mset.to_dict()
    joint = neck["normal"]["from"]
    for bad, words in (({"from": joint, "to": {"vertices": [1, 2], "weights": [0.5]}, "fallback": neck["normal"]["fallback"]},
                        "weights"),
                       ({"from": joint, "to": joint}, "field 'fallback'"),
                       ({"from": joint, "to": joint, "fallback": ["x", "head_top"]}, "unknown landmark 'x'"),
                       ({"from": joint, "to": joint, "fallback": neck["normal"]["fallback"], "via": 1}, "via"),
                       ({"from": joint, "to": joint, "fallback": neck["normal"]["fallback"], "sideways": ["x"]},
                        "field 'sideways'")):
        with pytest.raises(MeasurementError, match=words):
            measurement_set_from_dict(dict(d, measurements=[dict(neck, normal=bad)]))
    back = measurement_set_from_dict(json.loads(json.dumps(d)))
    assert next(m for m in back.measurements if m["name"] == "neck_girth")["normal"] == neck["normal"]
    _, fset = foreign
    # Another topology drops the template's joints: the axis is its fallback until a standing body
    # places them (tests/test_foreign_neck.py).
    got = next(m for m in fset.measurements if m["name"] == "neck_girth")["normal"]
    assert got == {"fallback": neck["normal"]["fallback"], "sideways": neck["normal"]["sideways"]}
