"""`bodyspace import`: a user's own folder of registered meshes and a labels CSV become a scan
database the other commands read: the rest-pose choice, label names and plausible values,
`build MESHDIR`'s pointer to import, and the output policy."""

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from bodyspace.cli import app
from bodyspace.data.database import ScanDatabase
from bodyspace.mesh.io import load_mesh, save_mesh
from bodyspace.model import BodyModel
from bodyspace.synth import foreign as fo

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


# -- meshes that are not ours: another topology, posed, in mm, Z up, off the origin ---------------

FOREIGN_SUBJECTS = ("p0", "p1", "p2", "p3")
FOREIGN_POSES = ("rest", "t_pose")


@pytest.fixture(scope="module")
def foreign(template, phenotype_model, tmp_path_factory):
    """4 subjects x 2 poses of a 4,000-vertex foreign topology (synth.foreign: remeshed, vertices
    shuffled, edge-of-population phenotypes) in millimetres, Z up, turned and off the origin, as
    OBJ files with a labels CSV; and each body's true internal vertices (metres, +Y up)."""
    folder = tmp_path_factory.mktemp("foreign") / "scans"
    folder.mkdir()
    rng = np.random.default_rng(12)
    topology = fo.foreign_topology(template, 4000, rng)
    truth, rows = {}, []
    for s, subject in enumerate(FOREIGN_SUBJECTS):
        phenotype = None
        for pose in FOREIGN_POSES:
            body = fo.foreign_body(template, phenotype_model, topology, rng, phenotype=phenotype, pose=pose)
            phenotype = body.phenotype
            name = f"{subject}_{pose}.obj"
            save_mesh(folder / name, body.vertices, body.faces)
            truth[name] = fo.transfer(topology.correspondence, template.faces, body.template_vertices)
            rows.append(f"{name},{subject},{pose},{158 + 6 * s},{52 + 9 * s}")
    (folder / "labels.csv").write_text("mesh,subject,pose,stature_cm,mass_kg\n" + "\n".join(rows) + "\n")
    return folder, truth, topology


def _copy(foreign, folder: Path, convert=None, suffix=".obj", names=None):
    """The foreign folder rewritten: each mesh's vertices through ``convert`` and saved as
    ``suffix`` (".npy": vertices only); the CSV's mesh names follow."""
    source, _, _ = foreign
    folder.mkdir()
    csv = (source / "labels.csv").read_text()
    for path in sorted(source.glob("*.obj")):
        if names is not None and path.name not in names:
            continue
        v, f = load_mesh(path)
        v = convert(path.name, v) if convert else v
        target = folder / (path.stem + suffix)
        if suffix == ".npy":
            np.save(target, v)
        else:
            save_mesh(target, v, f)
        csv = csv.replace(path.name, target.name)
    (folder / "labels.csv").write_text(csv)
    return folder


def test_import_foreign_meshes_in_mm_z_up(foreign, tmp_path):
    """--units mm --up z: stored in metres, +Y up; the bodies are the true ones turned about the
    vertical and moved (what to_frame did besides the axis and unit), nothing else."""
    folder, truth, _ = foreign
    result = run("import", folder, "--labels", folder / "labels.csv", "--out", tmp_path / "db", "--units", "mm",
                 "--up", "z")
    assert result.exit_code == 0, result.output
    assert "8 scans of 4 subjects, 4000 vertices (read in mm; turned from z up to +Y)" in " ".join(result.output.split())
    db = ScanDatabase.load(tmp_path / "db")
    assert db.meta["provenance"]["up"] == "z" and db.meta["rest_pose"] == {"pose": "rest"}
    np.testing.assert_allclose(db.subjects["stature_cm"], [158, 164, 170, 176])
    for i, name in enumerate(f"{s}_{p}.obj" for s in FOREIGN_SUBJECTS for p in FOREIGN_POSES):
        got, true = db.mesh(i), truth[name]
        lift = got[:, 1] - true[:, 1]                    # y kept up to the floor's offset
        assert np.ptp(lift) < 1e-5, name
        horizontal = lambda v: np.linalg.norm(v[:, [0, 2]] - v[:1, [0, 2]], axis=1)  # noqa: E731
        np.testing.assert_allclose(horizontal(got), horizontal(true), atol=1e-5)


@pytest.mark.parametrize("args, words", [
    ((), ["are they in mm? pass --units mm"]),
    (("--units", "mm"), ["tallest along Z", "expected +Y up; pass --up z"]),
    (("--units", "cm", "--up", "z"), ["are they in mm? pass --units mm"]),
    (("--units", "mm", "--up", "w"), ["--up 'w'", "expected one of y, -y, z, -z, x, -x"]),
])
def test_foreign_folder_in_another_frame_is_refused_with_the_flag(foreign, tmp_path, args, words):
    folder, _, _ = foreign
    refused(run("import", folder, "--labels", folder / "labels.csv", "--out", tmp_path / "db", *args),
            str(folder) if args[-1:] != ("w",) else "--up", *words)
    assert not (tmp_path / "db").exists()


def test_upside_down_and_x_up_folders(foreign, tmp_path):
    """A Z-up folder standing on its head and an X-up folder are recognised; --up turns them."""
    flip = _copy(foreign, tmp_path / "flip", lambda n, v: v * np.array([1.0, -1.0, -1.0]))   # 180 deg about X
    refused(run("import", flip, "--labels", flip / "labels.csv", "--out", tmp_path / "a", "--units", "mm"),
            "pass --up -z")
    sideways = _copy(foreign, tmp_path / "side", lambda n, v: v[:, [2, 0, 1]])               # Z -> X, X -> Y
    refused(run("import", sideways, "--labels", sideways / "labels.csv", "--out", tmp_path / "b", "--units", "mm"),
            "tallest along X", "pass --up x")
    upside = _copy(foreign, tmp_path / "upside", lambda n, v: v[:, [0, 2, 1]] * np.array([1.0, -1.0, 1.0]))
    refused(run("import", upside, "--labels", upside / "labels.csv", "--out", tmp_path / "c", "--units", "mm"),
            "stand on their heads along Y", "pass --up -y")
    ok = run("import", flip, "--labels", flip / "labels.csv", "--out", tmp_path / "d", "--units", "mm", "--up", "-z")
    assert ok.exit_code == 0, ok.output
    reference = run("import", foreign[0], "--labels", foreign[0] / "labels.csv", "--out", tmp_path / "e",
                    "--units", "mm", "--up", "z")
    assert reference.exit_code == 0, reference.output
    # Turned 180 degrees about X and read with --up -z: the same bodies as the folder read with --up z.
    np.testing.assert_allclose(ScanDatabase.load(tmp_path / "d").vertices, ScanDatabase.load(tmp_path / "e").vertices,
                               atol=1e-6)


def test_one_foreign_mesh_in_metres_among_mm_is_refused(foreign, tmp_path):
    mixed = _copy(foreign, tmp_path / "mixed", lambda n, v: v / 1000 if n == "p2_t_pose.obj" else v)
    refused(run("import", mixed, "--labels", mixed / "labels.csv", "--out", tmp_path / "db", "--units", "mm",
                "--up", "z"), "p2_t_pose.obj", "x smaller than the other meshes", "mm among meshes in m (or m among mm)",
            "convert this one")


@pytest.mark.parametrize("header, value, words", [
    ("stature", "170", ["'stature'", "did you mean stature_cm?"]),
    ("waist_girth", "80", ["did you mean waist_girth_cm?"]),
    ("age_yrs", "40", ["'age_yrs'", "did you mean age_years?"]),
    ("Stature (cm)", "170", ["did you mean stature_cm?"]),
    ("stature_mm", "1700", ["did you mean stature_cm?", "convert them from mm"]),
    ("stature_cm", "1700", ["1700 cm", "40 to 280 cm"]),
    ("stature_cm", "1.70", ["1.7 cm", "40 to 280 cm"]),
    ("mass_kg", "-60", ["-60 kg", "2 to 650 kg"]),
])
def test_foreign_labels_named_and_plausible(foreign, tmp_path, header, value, words):
    folder, _, _ = foreign
    rows = [f"{s}_{p}.obj,{s},{p},{value}" for s in FOREIGN_SUBJECTS for p in FOREIGN_POSES]
    csv = tmp_path / "labels.csv"
    csv.write_text("\n".join([f"mesh,subject,pose,{header}", *rows]) + "\n")
    refused(run("import", folder, "--labels", csv, "--out", tmp_path / "db", "--units", "mm", "--up", "z"),
            str(csv), *words)


def _imported(folder, out, *args):
    result = run("import", folder, "--labels", folder / "labels.csv", "--out", out, "--units", "mm", "--up", "z",
                 *args)
    assert result.exit_code == 0, result.output
    return ScanDatabase.load(out)


def test_stl_meshes(foreign, tmp_path):
    """STL stores triangle corners only: welded into shared vertices (numbered in the order the
    triangles use them), the same bodies as the OBJ files; an STL among OBJ files takes the OBJ
    numbering; an STL with its triangles in another order is refused."""
    reference = _imported(foreign[0], tmp_path / "obj")
    stl = _copy(foreign, tmp_path / "stl", suffix=".stl")
    db = _imported(stl, tmp_path / "stl_db")
    assert (db.n_vertices, len(db.faces)) == (reference.n_vertices, len(reference.faces))
    np.testing.assert_allclose(db.vertices[:, db.faces], reference.vertices[:, reference.faces], atol=1e-6)
    # An OBJ first, STL files after: the OBJ's vertex numbering.
    (stl / "p0_rest.stl").unlink()
    shutil.copy(foreign[0] / "p0_rest.obj", stl / "p0_rest.obj")
    (stl / "labels.csv").write_text((stl / "labels.csv").read_text().replace("p0_rest.stl", "p0_rest.obj"))
    mixed = _imported(stl, tmp_path / "mixed_db")
    np.testing.assert_array_equal(mixed.faces, reference.faces)
    np.testing.assert_allclose(mixed.vertices, reference.vertices, atol=1e-6)
    # Triangles in another order: the corners of one vertex disagree.
    v, f = load_mesh(foreign[0] / "p1_rest.obj")
    save_mesh(stl / "p1_rest.stl", v, np.roll(f, 1, axis=0))
    refused(run("import", stl, "--labels", stl / "labels.csv", "--out", tmp_path / "bad", "--units", "mm", "--up", "z"),
            "p1_rest.stl: corner", "expected STL files written from one registered topology with the triangles in "
            "one order")


def test_npy_meshes_take_their_faces_from_a_mesh_or_faces_file(foreign, tmp_path):
    reference = _imported(foreign[0], tmp_path / "obj")
    npy = _copy(foreign, tmp_path / "npy", suffix=".npy")
    refused(run("import", npy, "--labels", npy / "labels.csv", "--out", tmp_path / "a", "--units", "mm", "--up", "z"),
            "p0_rest.npy' is a .npy file of vertices only", "pass --faces FILE")
    db = _imported(npy, tmp_path / "b", "--faces", foreign[0] / "p0_rest.obj")
    np.testing.assert_array_equal(db.faces, reference.faces)
    np.testing.assert_allclose(db.vertices, reference.vertices, atol=1e-6)
    np.save(tmp_path / "faces.npy", reference.faces.astype(np.int32))
    db = _imported(npy, tmp_path / "c", "--faces", tmp_path / "faces.npy")
    np.testing.assert_allclose(db.vertices, reference.vertices, atol=1e-6)
    # A mesh of the CSV with faces gives them to the NPY files.
    shutil.copy(foreign[0] / "p3_t_pose.obj", npy / "p3_t_pose.obj")
    (npy / "labels.csv").write_text((npy / "labels.csv").read_text().replace("p3_t_pose.npy", "p3_t_pose.obj"))
    db = _imported(npy, tmp_path / "d")
    np.testing.assert_allclose(db.vertices, reference.vertices, atol=1e-6)


@pytest.mark.parametrize("array, faces, words", [
    (np.zeros((4000, 2)), None, ["p1_rest.npy: found an array of shape (4000, 2)", "expected (V, 3) vertex coordinates"]),
    (np.zeros((3999, 3)), None, ["p1_rest.npy: 3999 vertices", "are for 4000 vertices", "mixed topology", "leave it out of the CSV"]),
    (np.full((4000, 3), np.nan), None, ["p1_rest.npy: 4000 vertices contain NaN"]),
    (b"not numpy" * 20, None, ["p1_rest.npy: not a .npy file", "expected a numeric array written by numpy.save"]),
    (np.array([{"x": 1}], dtype=object), None, ["p1_rest.npy: holds Python objects, which bodyspace never loads"]),
    (None, np.zeros((5, 2), dtype=np.int64), ["--faces", "shape (5, 2)", "expected (F, 3) integer vertex ids"]),
    (None, np.full((5, 3), 0.5), ["--faces", "dtype float64", "expected (F, 3) integer vertex ids"]),
])
def test_bad_npy_files_are_refused(foreign, tmp_path, array, faces, words):
    npy = _copy(foreign, tmp_path / "npy", suffix=".npy")
    if isinstance(array, bytes):
        (npy / "p1_rest.npy").write_bytes(array)
    elif array is not None:
        np.save(npy / "p1_rest.npy", array, allow_pickle=array.dtype == object)
    faces_file = foreign[0] / "p0_rest.obj"
    if faces is not None:
        faces_file = tmp_path / "faces.npy"
        np.save(faces_file, faces)
    refused(run("import", npy, "--labels", npy / "labels.csv", "--out", tmp_path / "db", "--units", "mm", "--up", "z",
                "--faces", faces_file), *words)


def test_landmarks_stand_the_folder_in_our_frame(foreign, tmp_path):
    """A scanner's folder (turned 25°, off the origin, the floor not at zero) imported with its
    landmarks faces +Z on the floor over the origin: one rigid move for all scans (each equals
    the true body moved by one shift); --keep-placement keeps the scanner's frame."""
    folder, truth, topology = foreign
    lm = tmp_path / "landmarks.json"
    lm.write_text(json.dumps(topology.landmark_file()))
    result = run("import", folder, "--labels", folder / "labels.csv", "--out", tmp_path / "db", "--units", "mm",
                 "--up", "z", "--landmarks", lm)
    assert result.exit_code == 0, result.output
    said = " ".join(result.output.split())
    assert "placed: the bodies faced +25° from +Z" in said and "floor at y = 0.93 m" in said, said
    db = ScanDatabase.load(tmp_path / "db")
    names = [f"{s}_{p}.obj" for s in FOREIGN_SUBJECTS for p in FOREIGN_POSES]
    shift = np.stack([np.asarray(db.vertices[i], float) - truth[n] for i, n in enumerate(names)])   # (N, V, 3)
    assert np.abs(shift - shift.mean(axis=(0, 1))).max() < 0.004          # one rigid move, the same turn
    assert abs(shift[..., 1].mean()) < 0.003          # truth stands on y = 0 (the remeshed sole 1.5 mm higher)
    assert np.abs(shift.mean(axis=(0, 1))[[0, 2]]).max() < 0.05             # over the origin
    assert db.meta["provenance"]["placement"]["faced_degrees"] == pytest.approx(25.0, abs=1.0)
    kept = run("import", folder, "--labels", folder / "labels.csv", "--out", tmp_path / "kept", "--units", "mm",
               "--up", "z", "--landmarks", lm, "--keep-placement")
    assert kept.exit_code == 0 and "placed:" not in kept.output, kept.output
    raw = np.asarray(ScanDatabase.load(tmp_path / "kept").vertices[0], float)
    assert raw[:, 1].min() == pytest.approx(0.93, abs=0.002)               # the scanner's floor


def test_labels_written_on_the_rest_rows_only(foreign, tmp_path):
    """A CSV filled in on each subject's rest-pose row only (sex too, as a clinic writes it): the
    subject's other scans take its values (the sex was refused as '' on the first empty row); a
    subject with no sex on any row is refused saying so."""
    folder, _, _ = foreign
    rows = [f"{s}_{p}.obj,{s},{p}," + (f"{'female' if i % 2 else 'male'},{160 + i}" if p == "rest" else ",")
            for i, s in enumerate(FOREIGN_SUBJECTS) for p in FOREIGN_POSES]
    csv = tmp_path / "labels.csv"
    csv.write_text("\n".join(["mesh,subject,pose,sex,stature_cm", *rows]) + "\n")
    result = run("import", folder, "--labels", csv, "--out", tmp_path / "db", "--units", "mm", "--up", "z")
    assert result.exit_code == 0, result.output
    db = ScanDatabase.load(tmp_path / "db")
    assert list(db.subjects["sex"]) == ["male", "female", "male", "female"]
    assert list(db.subjects["stature_cm"]) == [160.0, 161.0, 162.0, 163.0]
    csv.write_text("\n".join(["mesh,subject,pose,sex,stature_cm", *[r.replace(",male,", ",,") for r in rows]]) + "\n")
    refused(run("import", folder, "--labels", csv, "--out", tmp_path / "db2", "--units", "mm", "--up", "z"),
            "column 'sex': ''", "at least one of the subject's rows")


def test_a_semicolon_csv_with_decimal_commas(foreign, tmp_path):
    """A spreadsheet's export in a decimal-comma locale (fields separated by ';', '171,5') reads as
    the comma CSV it stands for (it was refused: "no 'mesh' column ... found ['mesh;subject;...']")."""
    folder, _, _ = foreign
    rows = [f"{s}_{p}.obj;{s};{p};{160 + i},5;{55 + i},25" for i, s in enumerate(FOREIGN_SUBJECTS) for p in FOREIGN_POSES]
    csv = tmp_path / "labels.csv"
    csv.write_text("\n".join(["mesh;subject;pose;stature_cm;mass_kg", *rows]) + "\n")
    result = run("import", folder, "--labels", csv, "--out", tmp_path / "db", "--units", "mm", "--up", "z")
    assert result.exit_code == 0, result.output
    db = ScanDatabase.load(tmp_path / "db")
    assert list(db.subjects["stature_cm"]) == [160.5, 161.5, 162.5, 163.5]
    assert list(db.subjects["mass_kg"]) == [55.25, 56.25, 57.25, 58.25]
