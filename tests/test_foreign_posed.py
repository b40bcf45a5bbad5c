"""Posed bodies of another topology (issue 12 §3). "Planes follow the part": the neck girth's plane
leans with the neck's own axis, whose joints (rings of the neck's skin) one standing body of the
topology places (``with_standing_body``, ``parts.axis_joints``); a head tilted sideways then keeps
the girth. Body parts assigned on a posed body keep each part in one piece
(``parts.merge_islands``). Mass of a body that does not stand. The CLI's --json/--csv."""

from __future__ import annotations

import json

import numpy as np
import pytest
from typer.testing import CliRunner

from bodyspace.cli import app
from bodyspace.errors import MeasurementError
from bodyspace.measure import evaluate, load_landmarks, load_measurement_set, with_standing_body
from bodyspace.measure.definitions import measurement_set_from_dict, with_landmarks
from bodyspace.measure.landmark_check import landmark_measurement_set
from bodyspace.measure.methods import Chunk, stature_for_mass
from bodyspace.measure.parts import PART_INDEX, merge_islands, parts_from_landmarks
from bodyspace.mesh.io import save_mesh
from bodyspace.rig.kinematics import rotvec_to_matrix
from bodyspace.rig.posing import pose_bodies
from bodyspace.register.landmarks import carry_vertex_data, landmark_document
from bodyspace.synth.foreign import carry_joints, foreign_topology, transfer
from bodyspace.synth.poses import load_pose_library

NECK_AND_HEAD = ["neck01", "neck02", "neck03", "head"]
# (bones the sideways tilt is shared by, degrees): over the neck and the head as the library's
# head_tilt poses, and at the head joint alone (the neck stays upright: the hardest case).
TILTS = [(NECK_AND_HEAD, 20), (NECK_AND_HEAD, -30), (["head"], 25), (["head"], -30)]


@pytest.fixture(scope="module")
def case(template, phenotype_model, tmp_path_factory):
    """A 5,000-vertex remeshed, reordered topology with its landmark file, the mean body upright
    and with the head tilted (``TILTS``) on it, the set re-pointed at it and the set with its
    joints placed on the upright body."""
    mset = load_measurement_set()
    v = phenotype_model.vertices({})[0]
    v = v - np.array([0.0, v[:, 1].min(), 0.0])
    rig = template.rigs["default"]
    bodies = [v]
    for bones, degrees in TILTS:
        rv = np.zeros((rig.n_bones, 3))
        for b in bones:
            rv[rig.bone_index(b)] = [0.0, 0.0, np.radians(degrees / len(bones))]
        bodies.append(pose_bodies(v, rig, rotvec_to_matrix(rv), on_ground=True))
    topo = foreign_topology(template, 5000, rng=3, mset=mset)
    path = tmp_path_factory.mktemp("neck") / "landmarks.json"
    path.write_text(json.dumps(topo.landmark_file()))
    lms, nv = load_landmarks(path)
    fset = with_landmarks(mset, lms, nv, str(path))
    foreign = transfer(topo.correspondence, template.faces, np.stack(bodies))
    return topo, fset, with_standing_body(fset, foreign[0], topo.faces), foreign


def _neck(ms, bodies, faces):
    return evaluate(ms, bodies, faces, check_scale=False)["neck_girth"]


def test_neck_girth_keeps_when_the_head_tilts_on_another_topology(case):
    topo, fset, placed, bodies = case
    got = _neck(placed, bodies, topo.faces)
    assert np.isfinite(got.value).all(), got.note
    change = got.value[1:] - got.value[0]
    # Measured: at most 1.05 cm (the head alone tilted 30°; 0.05-0.39 cm the other tilts). Its
    # band's top plane grazes the jaw on one side: since issue 15 that plane's ring is measured
    # (314 mm, 1 cm under the upright body's smallest, 324 mm a plane lower) where the old rule
    # left it out for touching one head triangle (0.49 cm, on that one edge).
    assert np.abs(change).max() < 0.011, change
    # The landmarks' axis (neck → head top), what this topology had before: leans with the head.
    before = _neck(fset, bodies, topo.faces).value
    # (3.2 cm before issue 15's rings, 1.5 cm with them: still more than the joints' axis)
    assert np.abs(before[1:] - before[0]).max() > np.abs(change).max() + 0.003
    assert abs(got.value[0] - before[0]) < 0.002               # upright, the same girth


def test_joints_are_vertices_of_the_topology_and_kept_in_the_file(case):
    topo, fset, placed, bodies = case
    axis = next(m for m in placed.measurements if m["name"] == "neck_girth")["normal"]
    dropped = next(m for m in fset.measurements if m["name"] == "neck_girth")["normal"]
    assert "from" not in dropped and dropped["fallback"] == axis["fallback"]   # template ids dropped
    for joint in (axis["from"], axis["to"]):
        assert len(joint["vertices"]) >= 6 and max(joint["vertices"]) < bodies.shape[1]
        assert sum(joint["weights"]) == pytest.approx(1.0)
    assert placed.vertex_parts is not None and len(placed.vertex_parts) == bodies.shape[1]
    back = measurement_set_from_dict(json.loads(json.dumps(placed.to_dict())))
    assert np.array_equal(_neck(back, bodies, topo.faces).value, _neck(placed, bodies, topo.faces).value)
    assert with_standing_body(placed, bodies[0], topo.faces) is placed        # nothing left to place
    with pytest.raises(MeasurementError, match="standing body has shape"):
        with_standing_body(fset, bodies[0][:100], topo.faces)
    # One joint without the other is refused where the set is read.
    d = placed.to_dict()
    neck = next(m for m in d["measurements"] if m["name"] == "neck_girth")
    half = dict(neck, normal={k: val for k, val in neck["normal"].items() if k != "to"})
    with pytest.raises(MeasurementError, match="only one of 'from' and 'to'"):
        measurement_set_from_dict(dict(d, measurements=[half]))


def test_mass_of_a_body_that_does_not_stand(template, phenotype_model):
    """Issue 12 §3: mass is defined for every closed body. A squatting body has no stature; its
    mass uses the stature estimated from its leg, trunk and head lengths (``stature_estimate``)."""
    mset = load_measurement_set()
    v = phenotype_model.vertices({})[0]
    lib = load_pose_library()
    rig = template.rigs["default"]
    names = ["rest", "squat", "bend_forward"]
    bodies = pose_bodies(np.repeat(v[None], 3, 0), rig, lib.stack(names, rig), on_ground=True)
    r = evaluate(mset, bodies, template.faces, check_scale=False)
    assert np.isnan(r["stature"].value[1:]).all()
    assert np.isfinite(r["mass"].value).all() and np.isnan(r["bmi"].value[1:]).all()
    # The estimate itself, on every body (as if none stood): within 2 % of the standing stature.
    mass = next(m for m in mset.measurements if m["name"] == "mass")
    L = mset.landmark_matrix(bodies.shape[1])
    P = np.stack([L @ b for b in bodies])
    chunk = Chunk(bodies, {n: P[:, i] for i, n in enumerate(mset.landmarks)}, None)
    chunk.values = {k: r[k].value for k in ("leg_length_l", "leg_length_r")}
    chunk.values["stature"] = np.full(3, np.nan)
    est = stature_for_mass(mass, chunk)
    assert np.abs(est / r["stature"].value[0] - 1).max() < 0.02, est
    # A definition with a bad estimate is refused where the set is read.
    d = mset.to_dict()
    bad = [dict(x, stature_estimate=dict(mass["stature_estimate"], scale=9)) if x["name"] == "mass" else x
           for x in d["measurements"]]
    with pytest.raises(MeasurementError, match="stature_estimate.*scale"):
        measurement_set_from_dict(dict(d, measurements=bad))


def test_cli_json_and_csv_take_no_file_name(tmp_path):
    mesh = tmp_path / "a.obj"
    mesh.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    for flag, name in (("--json", "out.json"), ("--csv", "out.csv")):
        res = CliRunner().invoke(app, ["measure", str(mesh), flag, str(tmp_path / name)])
        assert res.exit_code == 2 and "Traceback" not in res.output
        assert f"{flag} takes no file name" in res.output and "redirect" in res.output


def test_parts_of_a_posed_body_keep_each_part_in_one_piece(template, phenotype_model, case):
    """Arms crossed, parts assigned on the posed body itself (a landmark file without labels):
    the right hand lies on the left forearm and the chest under the hands. Without
    ``merge_islands`` the wrist tapes took in the other hand (+9 and +16 cm on a 6,000-vertex
    body) and the chest lost 4.6 cm; now every girth is within 1 cm of the standing body's."""
    topo, fset, placed, _ = case
    v = phenotype_model.vertices({})[0]
    rig = template.rigs["default"]
    lib = load_pose_library()
    posed = pose_bodies(np.repeat(v[None], 2, 0), rig, lib.stack(["rest", "arms_crossed"], rig), on_ground=True)
    bodies = transfer(topo.correspondence, template.faces, posed)
    names = ("chest_girth", "wrist_girth_l", "wrist_girth_r", "upper_arm_girth_l", "waist_girth")
    rest = evaluate(placed, bodies[0], topo.faces)
    own = evaluate(fset, bodies[1], topo.faces, check_scale=False)          # labels from the posed body
    for k in names:
        assert abs(own[k].value - rest[k].value) < 0.01, (k, own[k].value - rest[k].value)
    # Each part one connected piece; on the standing body the cleanup changes a few border vertices.
    P = fset.landmark_matrix(bodies.shape[1]) @ bodies[1]
    lm = {n: P[i] for i, n in enumerate(fset.landmarks)}
    raw = parts_from_landmarks(bodies[1], lm)                                # no faces: no cleanup
    clean = parts_from_landmarks(bodies[1], lm, topo.faces)
    hand_r = placed.vertex_parts == PART_INDEX["hand_r"]
    assert (clean[hand_r] == PART_INDEX["hand_r"]).mean() > 0.9
    assert np.array_equal(merge_islands(clean, topo.faces), clean)           # nothing left to merge
    assert (raw != clean).sum() > 0


def test_parts_are_assigned_only_on_a_standing_body(template, phenotype_model, case, tmp_path):
    """A landmark file without body parts and a seated body: assigned on the seated body itself, a
    6,000-vertex body's chest came out +10 cm and its upper arms +15 cm (the arms lie nearer to
    the torso's lines than to their own bones). Now its part girths are NaN with the reason and
    the fix; measured together with a standing body of the topology, they take that body's parts
    and are within 2 cm of standing (API and command line alike)."""
    topo, fset, _, _ = case
    v = phenotype_model.vertices({})[0]
    posed = pose_bodies(np.repeat(v[None], 2, 0), template.rigs["default"],
                        load_pose_library().stack(["rest", "sitting"], template.rigs["default"]), on_ground=True)
    rest, sitting = transfer(topo.correspondence, template.faces, posed)
    alone = evaluate(fset, sitting, topo.faces, check_scale=False)
    for k in ("chest_girth", "waist_girth", "upper_arm_girth_l", "neck_girth"):
        assert np.isnan(alone[k].value) and alone[k].note.startswith("body parts unknown"), (k, alone[k])
        assert "not upright" in alone[k].note and "bodyspace landmarks" in alone[k].note
    assert np.isfinite(alone["mass"].value) and np.isfinite(alone["arm_length_l"].value)
    unknown = with_standing_body(fset, sitting, topo.faces)
    assert unknown.vertex_parts is None and unknown.parts_unknown is not None
    both = evaluate(fset, np.stack([sitting, rest]), topo.faces, check_scale=False)   # parts of the 2nd
    names = []
    for i, body in enumerate((sitting, rest)):
        names.append(tmp_path / f"b{i}.obj")
        save_mesh(names[-1], body, topo.faces)
    res = CliRunner().invoke(app, ["measure", *map(str, names), "--landmarks", fset.source, "--json"])
    assert res.exit_code == 0, res.output
    cli = json.loads(res.stdout)
    for k in ("chest_girth", "waist_girth", "upper_arm_girth_l", "upper_arm_girth_r", "thigh_girth_l"):
        assert abs(both[k].value[0] - both[k].value[1]) < 0.02, (k, both[k].value)
        assert abs(cli[str(names[0])][k]["value"] - cli[str(names[1])][k]["value"]) < 2.0, k


def test_carried_neck_joints_follow_the_neck_in_every_pose(template, phenotype_model, case, tmp_path):
    """What ``bodyspace landmarks`` writes for a foreign mesh: the template's body parts and its
    neck joints carried across (here from the exact template body, without a registration). The
    neck girth is then within 1 cm of the template's own value in each pose, through the file and
    the command line. (Measured with a registration's parts on a 6,000-vertex 2.27 m body, joints
    placed as rings on the mesh instead put the plane 8-12 cm wrong in a side bend, sitting and
    with the head down; the carried joints within 0.7 cm.)"""
    topo, fset, _, _ = case
    v = phenotype_model.vertices({})[0]
    poses = ["rest", "sitting", "side_bend_left", "look_down"]
    rig = template.rigs["default"]
    posed = pose_bodies(np.repeat(v[None], len(poses), 0), rig, load_pose_library().stack(poses, rig), on_ground=True)
    truth = evaluate(load_measurement_set(), posed, template.faces, check_scale=False)["neck_girth"].value
    bodies = transfer(topo.correspondence, template.faces, posed)
    carried = carry_vertex_data(posed[0], template, bodies[0], topo.faces)
    joints = carry_joints(load_measurement_set(), posed[0], template.faces, bodies[0], topo.faces)
    doc = landmark_document(load_landmarks(fset.source)[0], len(bodies[0]), carried, joints)
    path = tmp_path / "carried.json"
    path.write_text(json.dumps(doc))
    placed = landmark_measurement_set(path)
    neck = evaluate(placed, bodies, topo.faces, check_scale=False)["neck_girth"].value
    assert np.abs(neck - truth).max() < 0.01, (neck, truth)
    save_mesh(tmp_path / "look_down.obj", bodies[3], topo.faces)
    res = CliRunner().invoke(app, ["measure", str(tmp_path / "look_down.obj"), "--landmarks", str(path), "--json"])
    assert res.exit_code == 0, res.output
    assert abs(json.loads(res.stdout)["neck_girth"]["value"] / 100 - truth[3]) < 0.01
    bad = dict(doc, joints={"neck_girth": {"normal": {"from": {"vertices": [len(bodies[0]) + 5], "weights": [1.0]},
                                                      "to": joints["neck_girth"]["normal"]["to"]}}})
    path.write_text(json.dumps(bad))
    with pytest.raises(MeasurementError, match=r"joint neck_girth.normal.from uses vertex \d+, but the topology has"):
        landmark_measurement_set(path)


def test_cli_measure_with_a_landmark_file_places_the_joints_on_the_mesh(case, tmp_path):
    """``measure MESH... --landmarks FILE`` with a landmark file without joints: the first standing
    mesh places the neck joints for all (rings at the neck's base and at the head's pivot lie on
    the neck's axis even with the head tilted). Head tilted 30° sideways: within 1.1 cm of upright
    (measured 0.30 and 1.05 cm: the head alone tilted, the band's top plane grazing the jaw is
    measured since issue 15, where it was left out (0.49 cm); each mesh's own joints measured
    0.89 and 0.93 cm before)."""
    topo, fset, _, bodies = case
    names = []
    for i in (0, 2, 4):                                   # upright; -30° over neck and head; -30° head alone
        names.append(tmp_path / f"b{i}.obj")
        save_mesh(names[-1], bodies[i], topo.faces)
    res = CliRunner().invoke(app, ["measure", *map(str, names), "--landmarks", fset.source, "--json"])
    assert res.exit_code == 0, res.output
    got = json.loads(res.stdout)
    neck = [got[str(n)]["neck_girth"]["value"] for n in names]
    assert max(abs(x - neck[0]) for x in neck[1:]) < 1.1, neck
