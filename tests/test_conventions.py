"""Input off by a convention (measure/conventions.py): millimetres, inches, Z up, upside down,
faces wound inwards, another vertex order. Each is refused with its fix, measured right with the
fix, and correct input (every library pose, foreign phenotypes, remeshed, noisy, holed bodies) is
never refused (issue 12 §3)."""

import json

import numpy as np
import pytest
from typer.testing import CliRunner

from bodyspace.cli import app
from bodyspace.errors import MeasurementError
from bodyspace.measure import conventions as cv
from bodyspace.measure import evaluate, load_measurement_set, measure, with_landmarks
from bodyspace.measure.tolerances import iso_tolerance
from bodyspace.mesh.io import save_mesh
from bodyspace.rig.posing import pose_bodies
from bodyspace.synth import foreign as fo
from bodyspace.synth.poses import load_pose_library

CLI_FLAGS = {"units": "--units {}", "up": "--up {}", "flip_winding": "--flip-winding", "landmarks": "--landmarks FILE"}
runner = CliRunner()


def assert_iso_equal(got, ref):
    """Every value of ``got`` within the ISO 20685-1 tolerance of ``ref`` (NaN where ref is)."""
    assert got.keys() == ref.keys()
    for name, m in ref.items():
        a, b = float(got[name].value), float(m.value)
        if np.isnan(b):
            assert np.isnan(a), name
            continue
        tol, relative = iso_tolerance(name, m)
        assert abs(a - b) <= (tol * abs(b) if relative else tol), (name, a, b)


@pytest.fixture(scope="module")
def mset():
    return load_measurement_set()


@pytest.fixture(scope="module")
def library_bodies(template, phenotype_model):
    """(3 bodies, 39 poses): the mean body and two phenotypes at the population's edges in every
    library pose, on the ground, template topology (39 x 3 x V x 3)."""
    rng = np.random.default_rng(12)
    phen = np.stack([np.full(11, 0.5), fo.foreign_phenotype(rng), fo.foreign_phenotype(rng)])
    rest = phenotype_model.vertices(phen)
    lib = load_pose_library()
    rig = template.rigs["default"]
    return np.stack([pose_bodies(rest, rig, lib.rotations(name, rig), on_ground=True) for name in lib.names])


@pytest.fixture(scope="module")
def topology(template):
    return fo.foreign_topology(template, 6000, rng=1)


@pytest.fixture(scope="module")
def foreign_bodies(template, phenotype_model, topology):
    """Foreign bodies (6,000 vertices, another order, foreign phenotypes) in four poses."""
    rng = np.random.default_rng(4)
    return [fo.foreign_body(template, phenotype_model, topology, rng, pose=pose)
            for pose in ("rest", "t_pose", "squat", "arms_overhead")]


def _foreign_set(mset, body):
    return with_landmarks(mset, {k: (np.asarray(v["vertices"] if isinstance(v, dict) else [v]),
                                     np.asarray(v["weights"] if isinstance(v, dict) else [1.0]))
                                 for k, v in body.landmark_file["landmarks"].items()},
                          body.landmark_file["n_vertices"], "foreign.json")


# Rotations taking +Y to the other up axes foreign.to_frame does not make (it makes y, z, -y).
_MORE_UPS = {"x": [[0, 1, 0], [-1, 0, 0], [0, 0, 1]], "-x": [[0, -1, 0], [1, 0, 0], [0, 0, 1]],
             "-z": [[1, 0, 0], [0, 0, 1], [0, -1, 0]]}


def _to_frame(v, up, scale, translation, yaw_degrees):
    """foreign.to_frame, for every up axis (x, -x, -z: turned from the +Y frame, then moved)."""
    if up in fo.UP_AXES:
        return fo.to_frame(v, up, scale, translation, yaw_degrees)
    turned = fo.to_frame(v, "y", 1.0, (0.0, 0.0, 0.0), yaw_degrees) @ np.asarray(_MORE_UPS[up], float).T
    return scale * (turned + np.asarray(translation))


# ---------------------------------------------------------------------------- never refused

def test_correct_bodies_are_never_refused(template, mset, library_bodies):
    """All 39 library poses of 3 bodies (2 at the population's edges): nothing found, up is +Y,
    no layout check fails, the unit is metres and prepare returns the mesh unchanged."""
    for pose_bodies_ in library_bodies:
        for v in pose_bodies_:
            conv = cv.inspect(v, template.faces, mset)
            assert cv.find_problems(conv, mset) == []
            assert conv.units[0] == "m" and conv.up == "y" and conv.up_angle < 27
            assert conv.layout_failures == () and conv.layout_checks == 37
            assert conv.volume_ratio > 10 * cv.INWARD_VOLUME_RATIO
    v2, f2 = cv.prepare(library_bodies[0, 0], template.faces, mset)
    np.testing.assert_array_equal(v2, library_bodies[0, 0])
    np.testing.assert_array_equal(f2, template.faces)


def test_foreign_remeshed_noisy_holed_bodies_are_never_refused(mset, foreign_bodies):
    """Remeshed foreign bodies with their landmark files, brought into our frame, as they are,
    with 1 and 3 mm of noise along the normals and with holes at the soles and armpits."""
    rng = np.random.default_rng(2)
    for b in foreign_bodies:
        fset = _foreign_set(mset, b)
        v = b.internal_vertices()
        lm = {k: fo.from_frame(p, **b.frame) for k, p in b.true_landmarks.items()}
        holed = fo.punch_holes(v, b.faces, fo.hole_sites(v, lm)[[2, 4]], 0.03)
        armpits = fo.punch_holes(v, b.faces, fo.hole_sites(v, lm)[[3, 5]], 0.02)
        for vv, ff in ((v, b.faces), (fo.add_noise(v, 0.001, rng, b.faces), b.faces),
                       (fo.add_noise(v, 0.003, rng, b.faces), b.faces), (v, holed), (v, armpits)):
            conv = cv.inspect(vv, ff, fset)
            assert cv.find_problems(conv, fset) == [], (b.pose, [f.what for f in cv.find_problems(conv, fset)])
            assert conv.layout_checks == 37 and len(conv.layout_failures) == 0


# ---------------------------------------------------------------------------- refused with the fix

FRAMES = [  # (up, scale, unit the fix names)
    ("z", 1000.0, "mm"), ("-y", 100.0, "cm"), ("z", 1 / 0.0254, "in"), ("y", 1000.0, "mm"),
    ("-y", 1.0, None), ("x", 1.0, None), ("-z", 1000.0, "mm"), ("-x", 100.0, "cm"),
]


@pytest.mark.parametrize("up,scale,unit", FRAMES, ids=[f"{u}-{s:g}" for u, s, _ in FRAMES])
def test_other_frames_are_refused_and_measured_right_with_the_fix(template, mset, library_bodies, foreign_bodies,
                                                                  up, scale, unit):
    """Moved off the origin, turned about the vertical, another up axis and unit: refused with
    exactly the fix (units, up), and with it every value equals the internal-frame truth."""
    cases = [(library_bodies[i, k], template.faces, mset) for i, k in ((0, 0), (13, 1), (27, 2))]  # rest, squat, bend
    cases += [(b.internal_vertices(), b.faces, _foreign_set(mset, b)) for b in foreign_bodies[1:3]]
    for j, (v, f, s) in enumerate(cases):
        frame = dict(up=up, scale=scale, translation=(0.3, -0.2, 1.1), yaw_degrees=37.0 * j)
        moved = _to_frame(v, **frame)
        want = {**({"units": unit} if unit else {}), **({"up": up} if up != "y" else {})}
        found = cv.find_problems(cv.inspect(moved, f, s), s)
        fixes = {k: (val[0] if isinstance(val, tuple) else val) for x in found for k, val in x.fix.items()}
        assert fixes == want, (j, [x.what for x in found])
        with pytest.raises(MeasurementError) as err:
            cv.prepare(moved, f, s, "body.obj", words=CLI_FLAGS)
        for flag in ([f"--units {unit}"] if unit else []) + ([f"--up {up}"] if up != "y" else []):
            assert flag in str(err.value)
        v2, f2 = cv.prepare(moved, f, s, "body.obj", **want)
        assert_iso_equal(evaluate(s, v2, f2), evaluate(s, v, f))


def test_inches_and_centimetres_are_both_named_when_both_fit(template, mset, library_bodies):
    """A 1.66 m body in inches is 65 across: a 65 cm child too. The size (sqrt of the surface
    area) puts inches first, and the message names both."""
    v = fo.to_frame(library_bodies[0, 0], up="y", scale=1 / 0.0254)
    conv = cv.inspect(v, template.faces, mset)
    assert conv.units == ("in", "cm")
    with pytest.raises(MeasurementError) as err:
        cv.prepare(v, template.faces, mset, "body.obj", words=CLI_FLAGS)
    assert "give --units in (or --units cm)" in str(err.value)
    cv.prepare(v, template.faces, mset, units="cm")      # the user's word decides between the two


def test_reversed_winding_is_refused_and_flipped(template, mset, library_bodies, foreign_bodies):
    b = foreign_bodies[0]
    for v, f, s in ((library_bodies[0, 1], template.faces, mset),
                    (b.internal_vertices(), b.faces, _foreign_set(mset, b))):
        reversed_ = fo.reverse_winding(f)
        with pytest.raises(MeasurementError, match="wound inwards.*--flip-winding"):
            cv.prepare(v, reversed_, s, "body.obj", words=CLI_FLAGS)
        v2, f2 = cv.prepare(v, reversed_, s, flip_winding=True)
        ref = evaluate(s, v, f)
        assert_iso_equal(evaluate(s, v2, f2), ref)
        assert ref["volume"].value > 0.02
    # A mirrored mesh (x -> -x, a left-handed export) reads as wound inwards; flipped, it measures
    # what the body does (mirroring keeps every length, and the landmarks stay on their vertices).
    v = library_bodies[13, 0]
    mirrored = v * np.array([-1.0, 1.0, 1.0])
    with pytest.raises(MeasurementError, match="wound inwards"):
        cv.prepare(mirrored, template.faces, mset)
    assert_iso_equal(evaluate(mset, *cv.prepare(mirrored, template.faces, mset, flip_winding=True)),
                     evaluate(mset, v, template.faces))
    # In millimetres, Z up and reversed at once: one message with all three fixes.
    moved = fo.to_frame(library_bodies[0, 0], "z", 1000.0)
    with pytest.raises(MeasurementError) as err:
        cv.prepare(moved, fo.reverse_winding(template.faces), mset, "body.obj", words=CLI_FLAGS)
    assert "give --units mm --flip-winding --up z" in str(err.value)


def test_shuffled_vertices_are_refused_and_their_landmark_file_measures_them(template, mset, library_bodies):
    """The template's topology in another vertex order: refused on every seed, the fix named;
    with the landmarks renumbered to that order (what a landmark file for it says) the mesh is
    accepted and measures what the ordered mesh does (the template-only loops aside)."""
    rng = np.random.default_rng(3)
    flat = library_bodies.reshape(-1, *library_bodies.shape[2:])
    for k in range(40):
        v, f, perm = fo.shuffle_vertices(flat[rng.integers(len(flat))], template.faces, rng)
        conv = cv.inspect(v, f, mset)
        assert conv.layout_wrong and len(conv.layout_failures) >= 13, len(conv.layout_failures)
        assert conv.up is None
    with pytest.raises(MeasurementError, match="not in the order of the landmarks.*--landmarks FILE"):
        cv.prepare(v, f, mset, "body.obj", words=CLI_FLAGS)
    inverse = np.empty_like(perm)
    inverse[perm] = np.arange(len(perm))
    renumbered = with_landmarks(mset, {k: (inverse[ids], w) for k, (ids, w) in mset.landmarks.items()},
                                len(v), "shuffled.json")
    v2, f2 = cv.prepare(v, f, renumbered)
    ordered = v[inverse]   # the body before shuffling, in the template's order
    assert_iso_equal(evaluate(renumbered, v2, f2), evaluate(with_landmarks(mset, mset.landmarks), ordered,
                                                              template.faces))


def test_another_topologys_landmark_file_is_refused(template, mset, foreign_bodies):
    """A landmark file of another remeshing with the same vertex count (6,000): the landmarks
    land on the wrong body parts."""
    other = fo.foreign_topology(template, 6000, rng=78)
    assert other.n_vertices == foreign_bodies[0].vertices.shape[0]
    wrong = with_landmarks(mset, other.landmarks, other.n_vertices, "other.json")
    for b in foreign_bodies:
        assert cv.inspect(b.internal_vertices(), b.faces, wrong).layout_wrong


def test_claims_the_geometry_contradicts_are_refused(template, mset, library_bodies):
    v = library_bodies[0, 0]
    for kw, words in ((dict(units="mm"), "leave out --units"), (dict(up="z"), "leave out --up"),
                      (dict(flip_winding=True), "leave out --flip-winding")):
        with pytest.raises(MeasurementError, match=words):
            cv.prepare(v, template.faces, mset, "body.obj", words=CLI_FLAGS, **kw)
    moved = fo.to_frame(v, "z", 1.0)
    with pytest.raises(MeasurementError, match=r"points along \+Z .*, not along -Y; give --up z"):
        cv.prepare(moved, template.faces, mset, "body.obj", up="-y", words=CLI_FLAGS)
    with pytest.raises(MeasurementError, match="--units furlong: unknown unit; expected one of m, cm, mm, in"):
        cv.prepare(v, template.faces, mset, words=CLI_FLAGS, units="furlong")
    with pytest.raises(MeasurementError, match="up='w': unknown axis"):
        cv.prepare(v, template.faces, mset, up="w")


def test_too_few_landmarks_leave_the_layout_unchecked(template, mset, library_bodies):
    """A landmark file naming one arm's joints (its length and girths) allows two layout checks and
    no up axis: the layout is not judged on two checks (the unit and winding still are). (Two
    acromions alone no longer give a measurement: shoulder width needs the arms' pose.)"""
    few = with_landmarks(mset, {k: mset.landmarks[k] for k in ("shoulder_joint_l", "elbow_joint_l", "wrist_joint_l")},
                         template.n_vertices)
    assert "arm_length_l" in few.names and "upper_arm_girth_l" in few.names
    v, f, _ = fo.shuffle_vertices(library_bodies[0, 0], template.faces, 1)
    conv = cv.inspect(v, f, few)
    assert conv.layout_checks == 2 < cv.LAYOUT_MIN_CHECKS and conv.up is None
    assert cv.find_problems(conv, few) == []
    assert [x.fix for x in cv.find_problems(cv.inspect(v * 1000, f, few), few)] == [{"units": ("mm",)}]


def test_garbage_scale_fits_no_unit(template, mset, library_bodies):
    """One stray vertex 1 km away, or a body 1000x too small: no unit makes it a body."""
    v = library_bodies[0, 0].copy()
    far = v.copy()
    far[0] = (1000.0, 0.0, 0.0)
    for bad in (far, v / 1000.0):
        conv = cv.inspect(bad, template.faces, mset)
        assert conv.units == ()
        with pytest.raises(MeasurementError, match="bounding box"):
            cv.prepare(bad, template.faces, mset)
    # A body's extent but not a body's surface (its vertices in another order than its faces):
    # no scale is advised ("1x too small: multiply by 1" was).
    scrambled = v[np.random.default_rng(0).permutation(len(v))]
    with pytest.raises(MeasurementError, match=r"m across in metres, but its surface area is [\d.e+]+ m²") as err:
        cv.prepare(scrambled, template.faces, mset)
    assert "multiply by 1)" not in str(err.value) and "1x too" not in str(err.value)


# ---------------------------------------------------------------------------- the batch door

def test_batch_door_checks_units_of_every_body_and_winding(template, mset, library_bodies):
    batch = library_bodies[:4, 0]
    with pytest.raises(MeasurementError, match="body 0 of .*wound inwards"):
        evaluate(mset, batch, fo.reverse_winding(template.faces))
    scaled = batch.copy()
    scaled[2] *= 1000.0
    with pytest.raises(MeasurementError, match="body 2 of .*is it in mm"):
        evaluate(mset, scaled, template.faces)
    assert np.all(measure(mset, batch, template.faces)["volume"] > 0)
    assert np.all(measure(mset, batch, fo.reverse_winding(template.faces), check_faces=False)["volume"] < 0)


# ---------------------------------------------------------------------------- the command line

def _run(*args):
    result = runner.invoke(app, [str(a) for a in args])
    assert "Traceback" not in result.output, result.output
    return result


def _strict_json(text):
    """json.loads that refuses NaN and Infinity (which Python's json would accept)."""
    def bad(token):
        raise AssertionError(f"not JSON: {token}")
    return json.loads(text, parse_constant=bad)


def test_cli_refuses_with_flags_and_measures_with_them(template, mset, library_bodies, foreign_bodies, tmp_path):
    body = library_bodies[0, 0]
    truth = _strict_json(_save_and_run(tmp_path / "truth.obj", body, template.faces, "--json").stdout)
    cases = {
        "mm_z.obj": (fo.to_frame(body, "z", 1000.0), template.faces, ["--units", "mm", "--up", "z"]),
        "upside.obj": (fo.to_frame(body, "-y", 1.0), template.faces, ["--up", "-y"]),
        "inwards.obj": (body, fo.reverse_winding(template.faces), ["--flip-winding"]),
    }
    for name, (v, f, flags) in cases.items():
        refused = _save_and_run(tmp_path / name, v, f, "--json")
        assert refused.exit_code == 2 and refused.stdout == ""
        lines = [ln for ln in refused.output.splitlines() if ln.startswith("error:")]
        assert len(lines) == 1 and " ".join(flags) in lines[0], refused.output
        measured = _strict_json(_run("measure", tmp_path / name, "--json", *flags).stdout)
        for key, entry in truth.items():
            assert entry["unit"] == measured[key]["unit"]
            if entry["value"] is None:
                assert measured[key]["value"] is None
            else:
                assert abs(measured[key]["value"] - entry["value"]) <= 1e-3 * max(1.0, abs(entry["value"])), key
    assert truth["stature"]["unit"] == "cm" and truth["mass"]["unit"] == "kg"
    v, f, _ = fo.shuffle_vertices(body, template.faces, 5)
    refused = _save_and_run(tmp_path / "shuffled.obj", v, f, "--csv")
    assert refused.exit_code == 2 and refused.stdout == ""
    assert "--landmarks FILE" in refused.output and "template's vertex order" in refused.output
    # A foreign body in its own frame (mm, Z up), with its landmark file.
    b = foreign_bodies[0]
    (tmp_path / "foreign.json").write_text(json.dumps(b.landmark_file))
    save_mesh(tmp_path / "foreign.obj", b.vertices, b.faces)
    refused = _run("measure", tmp_path / "foreign.obj", "--landmarks", tmp_path / "foreign.json")
    assert refused.exit_code == 2 and "give --units mm --up z" in refused.output
    ok = _run("measure", tmp_path / "foreign.obj", "--landmarks", tmp_path / "foreign.json", "--units", "mm",
              "--up", "z", "--json")
    assert ok.exit_code == 0, ok.output
    assert _strict_json(ok.stdout)["stature"]["value"] > 100


def _save_and_run(path, v, f, *args):
    save_mesh(path, v, f)
    return _run("measure", path, *args)
