"""`bodyspace import`: a user's own folder of registered meshes and a labels CSV become a scan
database the other commands read: the rest-pose choice, label names and plausible values,
`build MESHDIR`'s pointer to import, and the output policy."""

import json
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from bodyspace.cli import app
from bodyspace.data.database import ScanDatabase
from bodyspace.mesh.io import load_mesh, save_mesh
from bodyspace.model import BodyModel

runner = CliRunner()
SUBJECTS = ("ann", "bob", "cy")
POSES = ("a_pose", "t_pose")


def run(*args):
    result = runner.invoke(app, [str(a) for a in args])
    assert "Traceback" not in result.output, result.output
    return result


def refused(result, *words):
    """Exit 2 with one ``error:`` line holding every one of ``words``."""
    assert result.exit_code == 2, result.output
    assert sum(line.startswith("error:") for line in result.output.splitlines()) == 1, result.output
    text = " ".join(result.output.split())
    for word in words:
        assert word in text, (word, text)
    return text


@pytest.fixture(scope="module")
def meshes(template, tmp_path_factory):
    """Three subjects (the template scaled and stretched) in two 'poses' each, as OBJ files."""
    folder = tmp_path_factory.mktemp("import") / "scans"
    folder.mkdir()
    rng = np.random.default_rng(0)
    base = np.asarray(template.vertices, dtype=float)
    for s, subject in enumerate(SUBJECTS):
        body = base * np.array([1.0 + 0.05 * s, 0.95 + 0.04 * s, 1.0 - 0.03 * s])
        for p, pose in enumerate(POSES):
            save_mesh(folder / f"{subject}_{pose}.obj", body + 0.002 * p * rng.standard_normal(body.shape),
                      template.faces)
    return folder


def labels(folder: Path, name: str, header: str = "mesh,subject,pose,stature_cm,mass_kg", rows=None) -> Path:
    rows = rows or [f"{s}_{p}.obj,{s},{p},{165 + 5 * i},{60 + 8 * i}"
                    for i, s in enumerate(SUBJECTS) for p in POSES]
    path = folder.parent / name
    path.write_text("\n".join([header, *rows]) + "\n")
    return path


def test_import_then_build(meshes, tmp_path):
    csv = labels(meshes, "labels.csv")
    result = run("import", meshes, "--labels", csv, "--out", tmp_path / "db", "--rest-pose", "a_pose")
    assert result.exit_code == 0, result.output
    assert "rest pose: pose 'a_pose', 3 scans" in " ".join(result.output.split())
    db = ScanDatabase.load(tmp_path / "db")
    assert (db.n_scans, db.n_subjects, db.n_vertices) == (6, 3, len(load_mesh(meshes / 'ann_a_pose.obj')[0]))
    np.testing.assert_allclose(db.subjects["stature_cm"], [165, 170, 175])
    assert json.loads((tmp_path / "db" / "meta.json").read_text())["rest_pose"] == {"pose": "a_pose"}
    built = run("build", tmp_path / "db", "--out", tmp_path / "model.npz", "--encoding", "vertex")
    assert built.exit_code == 0, built.output
    model = BodyModel.load(tmp_path / "model.npz")
    # --selection rest took the a_pose scans (rows 0, 2, 4), not "no scan has pose 'rest'".
    assert sorted(np.asarray(model.fitted_scans).tolist()) == [0, 2, 4]


def test_rest_pose_first_and_default(meshes, tmp_path):
    csv = labels(meshes, "labels_first.csv")
    default = run("import", meshes, "--labels", csv, "--out", tmp_path / "none")
    refused(default, "no scan of pose 'rest'", "--rest-pose")
    assert not (tmp_path / "none").exists()
    result = run("import", meshes, "--labels", csv, "--out", tmp_path / "db", "--rest-pose", "first")
    assert result.exit_code == 0, result.output
    assert "each subject's first mesh" in " ".join(result.output.split())
    db = ScanDatabase.load(tmp_path / "db")
    assert db.rest_rows().tolist() == [0, 2, 4]
    assert db.rest_pose().n_subjects == 3
    missing = run("import", meshes, "--labels", csv, "--out", tmp_path / "db2", "--rest-pose", "squat")
    refused(missing, "'squat'", "a_pose", "t_pose")


def test_all_rest_is_the_default(meshes, tmp_path):
    rows = [f"{s}_a_pose.obj,{s},{160 + i}" for i, s in enumerate(SUBJECTS)]
    csv = labels(meshes, "labels_rest.csv", "mesh,subject,stature_cm", rows)
    result = run("import", meshes, "--labels", csv, "--out", tmp_path / "db")
    assert result.exit_code == 0, result.output
    assert "pose 'rest' (the default" in " ".join(result.output.split())


@pytest.mark.parametrize("header, value, words", [
    ("stature", "170", ["'stature'", "did you mean stature_cm?"]),
    ("weight", "70", ["did you mean mass_kg?"]),
    ("stature_cm", "1700", ["1700 cm", "40 to 280 cm"]),
    ("stature_cm", "1.70", ["1.7 cm", "40 to 280 cm"]),
    ("mass_kg", "-60", ["-60 kg", "2 to 650 kg"]),
    ("mass_kg", "5000", ["5000 kg"]),
    ("waist_cm", "-3", ["'waist_cm'", "0 to 300 cm"]),
])
def test_label_names_and_ranges(meshes, tmp_path, header, value, words):
    rows = [f"{s}_a_pose.obj,{s},{value}" for s in SUBJECTS]
    csv = labels(meshes, f"labels_{header}.csv", f"mesh,subject,{header}", rows)
    refused(run("import", meshes, "--labels", csv, "--out", tmp_path / "db"), *words)
    assert not (tmp_path / "db").exists()


def test_mesh_in_mm_among_metres(meshes, template, tmp_path):
    folder = tmp_path / "mixed"
    folder.mkdir()
    for s, subject in enumerate(SUBJECTS):
        scale = 1000.0 if subject == "cy" else 1.0
        save_mesh(folder / f"{subject}.obj", np.asarray(template.vertices) * scale, template.faces)
    csv = folder / "labels.csv"
    csv.write_text("mesh,stature_cm\n" + "".join(f"{s}.obj,170\n" for s in SUBJECTS))
    refused(run("import", folder, "--labels", csv, "--out", tmp_path / "db"), "cy.obj", "mm among meshes in m")


def test_build_on_a_mesh_folder_says_import(meshes, tmp_path):
    text = refused(run("build", meshes, "--out", tmp_path / "m.npz"), "is a folder of meshes, not a scan database;",
                   f"run `bodyspace import {meshes} --labels CSV --out DB` first")
    assert "missing meta.json" not in text


def test_existing_out_needs_force(meshes, tmp_path):
    csv = labels(meshes, "labels_force.csv")
    out = tmp_path / "db"
    out.mkdir()
    (out / "mine.txt").write_text("keep")
    refused(run("import", meshes, "--labels", csv, "--out", out, "--rest-pose", "first"), "already exists", "--force")
    # --force replaces only a database bodyspace wrote, not a folder of the user's.
    refused(run("import", meshes, "--labels", csv, "--out", out, "--rest-pose", "first", "--force"))
    assert (out / "mine.txt").read_text() == "keep"
    written = tmp_path / "db2"
    assert run("import", meshes, "--labels", csv, "--out", written, "--rest-pose", "first").exit_code == 0
    again = run("import", meshes, "--labels", csv, "--out", written, "--rest-pose", "a_pose", "--force")
    assert again.exit_code == 0, again.output
    assert ScanDatabase.load(written).meta["rest_pose"] == {"pose": "a_pose"}
