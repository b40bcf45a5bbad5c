"""Issue 15's remaining command-line items: CAESAR .lnd landmark files, a user's BodyModel as the
registration's shape space (--model), and ``bodyspace import SCANDIR --register``.

One registration for the whole file (a module-scoped ``import --register`` run: one good scan
with a CAESAR sidecar, fitted with a user's model; the bad scans are refused before any fit);
the other tests are on small inputs. docs/registration.md.
"""

import csv
import json
import tempfile
from pathlib import Path

import numpy as np
import pytest
import trimesh
from scipy.spatial import cKDTree
from typer.testing import CliRunner

from bodyspace.cli import app
from bodyspace.data.database import ScanDatabase
from bodyspace.encoding.vertex import VertexEncoder
from bodyspace.errors import RegistrationError, RigError
from bodyspace.measure.definitions import load_landmarks, load_measurement_set
from bodyspace.measure.landmark_check import landmark_measurement_set
from bodyspace.model import BodyModel
from bodyspace.register.caesar import CAESAR_TO_BODYSPACE, caesar_to_bodyspace, read_lnd
from bodyspace.register.landmark_files import read_scan_landmarks, sidecar_landmarks
from bodyspace.register.landmarks import carry_vertex_data, landmark_document
from bodyspace.rig.carried_weights import load_carried_weights
from bodyspace.register.user_model import basis_from_model, check_model_topology
from bodyspace.shape import ShapeSpace
from bodyspace.synth.foreign import foreign_body, to_frame
from bodyspace.synth.population import build_population
from bodyspace.synth.scans import raw_scan

runner = CliRunner()


def said(result) -> str:
    """The command's output with its line wrapping undone."""
    return " ".join(result.output.split())


def lnd_text(landmarks: dict, cut_every: int = 5) -> str:
    """A CAESAR .lnd file of a scan's true landmarks: each bodyspace joint centre as two bony
    points 15 mm either side of it, every ``cut_every``-th name cut short as in real files."""
    lines = ["Civilian American and European Surface Anthropometry Resource", "subject 0001", "AUX ="]
    k = 1
    for ours, names in CAESAR_TO_BODYSPACE.items():
        offs = [np.zeros(3)] if len(names) == 1 else [np.array([15.0, 0, 0]), np.array([-15.0, 0, 0])]
        for name, off in zip(names, offs):
            x = landmarks[ours] + off
            shown = name[:-1] if k % cut_every == 0 else name
            lines.append(f"{k:3d}   0   1   12.50 {x[0]:9.2f} {x[1]:9.2f} {x[2]:9.2f} {shown}")
            k += 1
    lines += [" 90   0   1   1.00   1.00   2.00   3.00 AUX LAND 90", " 91   0   1   1.00   4.00   5.00   6.00 Sellion",
              "END =", "  this line is after the end"]
    return "\n".join(lines) + "\n"


def test_caesar_lnd_read_and_mapped(tmp_path):
    rng = np.random.default_rng(0)
    truth = {name: rng.uniform(-900, 900, 3) for name in CAESAR_TO_BODYSPACE}
    path = tmp_path / "subject.lnd"
    path.write_text(lnd_text(truth))
    caesar, notes = read_lnd(path)
    assert "Sellion" in caesar and not any(n.startswith("AUX") for n in caesar)
    assert "Lt. Acromion" in caesar and len(caesar) == 1 + sum(len(v) for v in CAESAR_TO_BODYSPACE.values())
    ours = caesar_to_bodyspace(caesar)
    assert set(ours) == set(CAESAR_TO_BODYSPACE)
    for name, p in truth.items():           # joint centres: the middle of the two bony points
        assert np.allclose(ours[name], p, atol=0.01), name
    lms, notes = read_scan_landmarks(path)
    assert set(lms) == set(ours) and "16" in notes[-1]
    # a bad name is reported, not guessed; a file with no landmark line is refused
    path.write_text("AUX =\n1 0 1 2.0 1.0 2.0 3.0 Lt. Elbow Thing\n2 0 1 2 4 5 6 Crotch\nEND =\n")
    caesar, notes = read_lnd(path)
    assert list(caesar) == ["Crotch"] and "no CAESAR landmark name" in notes[0]
    with pytest.raises(RegistrationError, match="give 1 of the measurement set's"):
        read_scan_landmarks(path)
    path.write_text("AUX =\nnothing here\nEND =\n")
    with pytest.raises(RegistrationError, match="no landmark line"):
        read_lnd(path)
    scan = tmp_path / "a.ply"
    scan.write_bytes(b"")
    assert sidecar_landmarks(scan) is None
    (tmp_path / "a.landmarks.json").write_text("{}")
    assert sidecar_landmarks(scan) == tmp_path / "a.landmarks.json"


@pytest.fixture(scope="module")
def user_model(template, tmp_path_factory):
    """A BodyModel of the template's topology (5 synthetic bodies, vertex encoding), saved."""
    root = tmp_path_factory.mktemp("user_model")
    db = build_population(template, root / "db", 5, 0, rng=0)
    model = BodyModel.fit(db, "vertex", "rest")
    model.save(root / "model.npz")
    return root / "model.npz", model


def test_basis_from_model_spans_the_models_bodies(user_model, template):
    """The basis decodes the model's own bodies: a body of the model is the basis mean plus
    its components, to rounding; the standard deviations are the model's."""
    _, model = user_model
    basis = basis_from_model(model)
    assert basis.components.shape[1:] == (template.n_vertices, 3)
    assert np.allclose(np.linalg.norm(basis.components.reshape(len(basis.sigma), -1), axis=1), 1.0)
    z = np.zeros(model.n_components)
    z[:2] = [1.0, -0.5]
    body = model.reconstruct(z)[0]
    flat = basis.components.reshape(len(basis.sigma), -1)
    coef = np.linalg.lstsq(flat.T, (body - basis.mean).ravel(), rcond=None)[0]
    assert np.abs(basis.body(coef) - body).max() < 1e-5
    check_model_topology(model, template)      # the template's own topology passes


def test_model_of_another_topology_is_refused(template, tmp_path):
    s = trimesh.creation.icosphere(subdivisions=2, radius=0.2)
    v = np.asarray(s.vertices)
    bodies = v + np.random.default_rng(0).normal(0, 0.01, (4,) + v.shape)
    enc = VertexEncoder(v, np.asarray(s.faces)).fit(bodies)
    space = ShapeSpace(enc, n_components=2).fit(bodies)
    model = BodyModel(v, np.asarray(s.faces), enc, space, encoding="vertex")
    model.save(tmp_path / "ball.npz")
    with pytest.raises(RegistrationError, match="162 vertices and 320 faces.*13380 vertices"):
        check_model_topology(model, template, "--model ball.npz")
    scan = tmp_path / "scan.xyz"
    np.savetxt(scan, np.random.default_rng(0).normal(size=(3000, 3)))
    r = runner.invoke(app, ["register", str(scan), "--model", str(tmp_path / "ball.npz"), "--out", str(tmp_path / "f")])
    assert r.exit_code == 2 and "162 vertices" in said(r) and "bodyspace landmarks MESH" in said(r)
    assert not (tmp_path / "f").exists()


@pytest.fixture(scope="module")
def imported(template, phenotype_model, user_model, tmp_path_factory):
    """``import SCANDIR --register`` on: one good scan (mm, Z up, turned, its CAESAR landmarks
    beside it), a scan of 100 points, an empty file and a scan with unusable landmarks; one
    registration in all (the others are refused before a fit)."""
    root = tmp_path_factory.mktemp("import_register")
    scans = root / "scans"
    scans.mkdir()
    good = raw_scan(template, phenotype_model, 7, pose="rest", n_points=15_000)
    trimesh.PointCloud(good.points).export(scans / "anna.ply")
    (scans / "anna.lnd").write_text(lnd_text(good.landmarks))
    np.savetxt(scans / "tiny.xyz", good.points[:100])
    (scans / "empty.ply").write_bytes(b"")
    np.save(scans / "badlm.npy", good.points)
    (scans / "badlm.landmarks.json").write_text(json.dumps({"landmarks": {"navel": [0, 0, 0]}}))
    labels = root / "labels.csv"
    with open(labels, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["mesh", "subject", "stature_cm"])
        w.writerows([["anna.ply", "", "170"], ["tiny.xyz", "t", "160"], ["empty.ply", "e", "150"],
                     ["badlm.npy", "b", "165"]])
    out = root / "db"
    result = runner.invoke(app, ["import", str(scans), "--register", "--labels", str(labels), "--model",
                                 str(user_model[0]), "--up", "z", "--steps", "2", "--out", str(out)])
    return result, out, good, scans, labels


def test_import_register_builds_a_database_and_lists_refusals(imported, template):
    result, out, good, _, _ = imported
    assert result.exit_code == 0, result.output
    db = ScanDatabase.load(out)
    assert db.n_scans == 1 and db.n_vertices == template.n_vertices and np.array_equal(db.faces, template.faces)
    assert list(db.subjects["subject"]) == ["anna"]          # the file stem when the CSV leaves it empty
    assert db.subjects["stature_cm"][0] == pytest.approx(170)
    # the registered body is the scan's, in metres +Y up: its height is the true body's
    v = np.asarray(db.vertices[0], dtype=float)
    assert abs(np.ptp(v[:, 1]) - np.ptp(good.body[:, 1])) < 0.03
    # every refused scan is named with its reason, on screen and in registration.csv
    text = said(result)
    for name, why in (("tiny.xyz", "at least 2000"), ("empty.ply", "empty.ply: REFUSED"), ("badlm.npy", "navel")):
        assert name in text and why in text, (name, why)
    rows = list(csv.DictReader(open(out / "registration.csv")))
    assert [r["scan"] for r in rows] == ["anna.ply", "tiny.xyz", "empty.ply", "badlm.npy"]
    assert [r["accepted"] for r in rows] == ["1", "0", "0", "0"]
    assert float(rows[0]["quality"]) >= 0.9 and rows[0]["landmarks"] == "anna.lnd" and all(r["reason"] for r in rows[1:])
    assert "3 refused and left out" in text
    # what was found rather than given is said per scan and kept: the unit here (--up was given)
    assert "[assumed] units: mm" in text and "read in mm, z up" in text and "same up axis" not in text
    assert rows[0]["units"] == "mm" and rows[0]["up"] == "z" and "units: mm" in rows[0]["assumed"]
    assert rows[0]["turned_degrees"] != "" and rows[1]["turned_degrees"] == ""
    # a fit standing otherwise than the rest pose, taken for a rest scan (no pose column), is named
    # (this 2-step fit with the test's small user model turns a joint far from the A-pose)
    assert rows[1]["pose_degrees"] == ""
    assert ("has no 'pose' column" in text) == (float(rows[0]["pose_degrees"]) > 25)


def test_import_register_refuses_before_work(imported, tmp_path):
    _, _, _, scans, labels = imported
    bad = tmp_path / "labels.csv"
    bad.write_text("mesh,stature_cm\nnobody.ply,170\n")
    r = runner.invoke(app, ["import", str(scans), "--register", "--labels", str(bad), "--out", str(tmp_path / "db")])
    assert r.exit_code == 2 and "not found" in said(r) and "nobody.ply" in said(r)
    r = runner.invoke(app, ["import", str(scans), "--register", "--labels", str(labels), "--landmarks",
                            str(scans / "anna.lnd"), "--out", str(tmp_path / "db")])
    assert r.exit_code == 2 and "NAME.lnd" in said(r)
    only_bad = tmp_path / "bad.csv"
    only_bad.write_text("mesh\ntiny.xyz\nempty.ply\n")
    r = runner.invoke(app, ["import", str(scans), "--register", "--labels", str(only_bad), "--out",
                            str(tmp_path / "db")])
    assert r.exit_code == 2 and "none of the 2 scans" in said(r)
    assert not (tmp_path / "db").exists()


def test_registered_scan_is_near_the_truth(imported, template):
    """The one fit (with the user's model and the CAESAR landmarks) lands near the true body."""
    _, out, good, _, _ = imported
    db = ScanDatabase.load(out)
    v = np.asarray(db.vertices[0], dtype=float)
    # both in bodyspace's frame (metres, +Y up, +Z front): vertex i to vertex i, centred
    truth = good.body - good.body.mean(axis=0)
    fit = v - v.mean(axis=0)
    err = np.linalg.norm(fit - truth, axis=1).mean()
    assert err < 0.03, err
    # standing as the truth stands, not only up to a rigid move: facing +Z, on the floor, over the
    # origin (the fit kept its scan's turn and floor: 0.83 m under y = 0, turned up to 25°)
    assert abs(v[:, 1].min()) < 1e-6
    shift = (v - good.body).mean(axis=0)
    assert abs(shift[1]) < 0.02                                          # the floor is the truth's (a 2-step fit)
    turned_err = np.linalg.norm(v - shift - good.body, axis=1).mean()    # no rotation allowed
    assert turned_err < 0.03, turned_err


def test_parts_and_skin_weights_carried_to_another_topology(template, phenotype_model, tmp_path):
    """The template's body parts and skin weights on a remeshed body (5,000 vertices, mm, Z up),
    carried from the template laid on it (here the true one; ``bodyspace landmarks`` uses its
    registration): each vertex gets the part and the main bone of the template's nearest vertex,
    and the landmark document brings them to ``measure``/``build --landmarks`` and ``rig --weights``."""
    body = foreign_body(template, phenotype_model, rng=3, pose="rest", target_vertices=5000)
    on_mesh = to_frame(body.template_vertices, **body.frame)
    carried = carry_vertex_data(on_mesh, template, body.vertices, body.faces)
    mset = load_measurement_set()
    nearest = cKDTree(on_mesh).query(body.vertices)[1]
    assert np.mean(carried.vertex_parts == mset.vertex_parts[nearest]) > 0.95
    rig = template.rigs["default"]
    main = np.asarray(rig.weights.argmax(axis=1)).ravel()[nearest]
    assert np.mean(carried.bone_ids[:, 0] == main) > 0.9
    assert np.allclose(carried.weights.sum(axis=1), 1.0)
    doc = landmark_document(body_landmarks(body), len(body.vertices), carried, written_by="test")
    path = tmp_path / "lm.json"
    path.write_text(json.dumps(doc))
    ms = landmark_measurement_set(path, len(body.vertices))
    assert np.array_equal(ms.vertex_parts, carried.vertex_parts)
    w = load_carried_weights(path, len(body.vertices), rig)
    assert w.shape == (len(body.vertices), rig.n_bones) and np.allclose(np.asarray(w.sum(axis=1)).ravel(), 1.0)
    with pytest.raises(RigError, match="rig 'default', not"):
        load_carried_weights(path, len(body.vertices), template.rigs[next(r for r in template.rigs if r != "default")])
    with pytest.raises(RigError, match="another mesh"):
        load_carried_weights(path, 10, rig)


def body_landmarks(body) -> dict:
    """The true landmarks of a remeshed body, as ``mesh_landmarks`` returns them."""
    p = Path(tempfile.mkdtemp()) / "truth.json"
    p.write_text(json.dumps(body.landmark_file))
    return load_landmarks(p)[0]
