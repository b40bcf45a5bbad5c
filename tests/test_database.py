"""ScanDatabase: write/load round trip, selection, building from meshes, and every bad input."""

import json

import numpy as np
import pytest
import trimesh

from bodyspace.data.database import (
    FORMAT_VERSION,
    ScanDatabase,
    unit_of_label,
    write_database,
)
from bodyspace.errors import DatabaseError
from bodyspace.mesh.io import save_mesh

SPHERE = trimesh.creation.icosphere(subdivisions=1)  # 42 vertices, 80 faces
JOINTS = ["root", "spine", "neck"]


def example_parts(n_scans=5, seed=0):
    """Arguments of write_database: 5 scans of 3 subjects, scans 0, 2, 4 in the rest pose."""
    rng = np.random.default_rng(seed)
    vertices = SPHERE.vertices[None] * (1.0 + 0.05 * rng.normal(size=(n_scans, 1, 1)))
    vertices = vertices + 0.01 * rng.normal(size=vertices.shape)
    subjects = {
        "subject": np.array(["ann", "bob", "cy"]),
        "sex": np.array(["female", "male", "female"]),
        "height_cm": np.array([165.5, 180.25, np.nan]),
        "bmi_kg_m2": np.array([21.0, 24.5, 30.1]),
        "gender_1": np.array([0.0, 1.0, 0.2]),
    }
    scans = {
        "subject": np.array(["ann", "ann", "bob", "bob", "cy"]),
        "pose": np.array(["rest", "a_pose", "rest", "walk", "rest"]),
    }
    rotations = rng.normal(size=(n_scans, len(JOINTS), 3)).astype(np.float32)
    meta = {"template": "icosphere-1", "provenance": {"made_by": "test"}, "licence": "CC0-1.0"}
    return vertices, SPHERE.faces, subjects, scans, meta, rotations


@pytest.fixture
def db_folder(tmp_path):
    vertices, faces, subjects, scans, meta, rotations = example_parts()
    return write_database(tmp_path / "db", vertices, faces, subjects, scans, meta,
                          rotations=rotations, joints=JOINTS)


# -- round trip -----------------------------------------------------------------------------------

def test_round_trip_values_dtypes_and_memmap(db_folder):
    vertices, faces, subjects, scans, meta, rotations = example_parts()
    db = ScanDatabase.load(db_folder)
    assert isinstance(db.vertices, np.memmap) and db.vertices.dtype == np.float32
    assert isinstance(np.load(db_folder / "vertices.npy", mmap_mode="r"), np.memmap)
    np.testing.assert_allclose(db.vertices, vertices, rtol=1e-6)
    assert np.load(db_folder / "faces.npy").dtype == np.int32
    assert db.faces.dtype == np.int64
    np.testing.assert_array_equal(db.faces, faces)
    for name, values in subjects.items():
        np.testing.assert_array_equal(db.subjects[name], values)  # floats exact, NaN kept
    assert db.subjects["height_cm"].dtype == np.float64
    assert db.subjects["subject"].dtype.kind == "U"
    np.testing.assert_array_equal(db.scans["scan"], np.arange(5))
    np.testing.assert_array_equal(db.scans["pose"], scans["pose"])
    np.testing.assert_array_equal(db.rotations, rotations)
    assert db.meta["joints"] == JOINTS and db.meta["format_version"] == FORMAT_VERSION
    assert db.meta["licence"] == "CC0-1.0" and db.meta["template"] == "icosphere-1"
    assert db.meta["units"]["length"] == "m"
    assert (db.n_scans, db.n_vertices, db.n_subjects, len(db)) == (5, 42, 3, 5)
    assert db.meta["n_faces"] == 80


def test_save_again_and_overwrite(db_folder, tmp_path):
    db = ScanDatabase.load(db_folder)
    copy = ScanDatabase.load(db.save(tmp_path / "copy"))
    np.testing.assert_array_equal(copy.vertices, db.vertices)
    np.testing.assert_array_equal(copy.subjects["height_cm"], db.subjects["height_cm"])
    with pytest.raises(DatabaseError, match="already exists"):
        db.save(tmp_path / "copy")
    db.select([0]).save(tmp_path / "copy", overwrite=True)
    assert len(ScanDatabase.load(tmp_path / "copy")) == 1
    assert sorted(p.name for p in tmp_path.iterdir()) == ["copy", "db"]  # no temporary folders left


def test_select_rest_pose_and_labels(db_folder):
    db = ScanDatabase.load(db_folder)
    np.testing.assert_array_equal(db.scan_subject_index(), [0, 0, 1, 1, 2])
    np.testing.assert_array_equal(db.label("bmi_kg_m2"), [21.0, 21.0, 24.5, 24.5, 30.1])

    rest = db.rest_pose()
    assert len(rest) == 3 and not isinstance(rest.vertices, np.memmap)
    np.testing.assert_array_equal(rest.vertices, db.vertices[[0, 2, 4]])
    np.testing.assert_array_equal(rest.scans["scan"], [0, 1, 2])
    np.testing.assert_array_equal(rest.rotations, db.rotations[[0, 2, 4]])

    picked = db.select([3, 1])  # order kept; only bob and ann remain, in subjects.csv order
    np.testing.assert_array_equal(picked.vertices, db.vertices[[3, 1]])
    np.testing.assert_array_equal(picked.subjects["subject"], ["ann", "bob"])
    np.testing.assert_array_equal(picked.scans["subject"], ["bob", "ann"])
    np.testing.assert_array_equal(picked.scan_subject_index(), [1, 0])
    assert picked.meta["n_scans"] == 2

    masked = db.select(db.scans["subject"] == "cy")
    assert masked.n_subjects == 1 and masked.scans["pose"].tolist() == ["rest"]
    with pytest.raises(DatabaseError, match="mask has shape"):
        db.select(np.ones(3, dtype=bool))
    with pytest.raises(DatabaseError, match="label 'waist_cm' not found"):
        db.label("waist_cm")


def test_unit_of_label():
    assert unit_of_label("bmi_kg_m2") == "kg/m^2"
    assert unit_of_label("skin_area_m2") == "m^2"
    assert unit_of_label("gender_1") == "1"
    assert unit_of_label("height") is None


# -- from_meshes ----------------------------------------------------------------------------------

def write_meshes(folder, n, seed=0, faces=SPHERE.faces):
    """n perturbed icospheres as OBJ (even) and PLY (odd); returns their vertices (n, V, 3)."""
    rng = np.random.default_rng(seed)
    folder.mkdir(exist_ok=True)
    all_vertices = []
    for i in range(n):
        vertices = SPHERE.vertices + 0.02 * rng.normal(size=SPHERE.vertices.shape)
        save_mesh(folder / f"m{i}.{'obj' if i % 2 == 0 else 'ply'}", vertices, faces)
        all_vertices.append(vertices)
    return np.array(all_vertices)


def test_from_meshes(tmp_path):
    expected = write_meshes(tmp_path / "meshes", 4)
    labels = tmp_path / "labels.csv"
    labels.write_text("mesh,subject,pose,height_cm,sex\n"
                      "m0.obj,p1,rest,170,female\n"
                      "m1.ply,p1,squat,170,female\n"
                      "m2.obj,p2,,181.5,MALE\n"
                      "m3.ply,,rest,,female\n")
    db = ScanDatabase.from_meshes(tmp_path / "meshes", labels)
    assert db.vertices.shape == (4, 42, 3) and db.vertices.dtype == np.float32
    np.testing.assert_allclose(db.vertices, expected, atol=1e-6)
    np.testing.assert_array_equal(db.faces, SPHERE.faces)
    np.testing.assert_array_equal(db.subjects["subject"], ["p1", "p2", "m3"])  # default: file stem
    np.testing.assert_array_equal(db.subjects["height_cm"], [170, 181.5, np.nan])
    np.testing.assert_array_equal(db.subjects["sex"], ["female", "male", "female"])
    np.testing.assert_array_equal(db.scans["pose"], ["rest", "squat", "rest", "rest"])  # default: rest
    assert len(db.rest_pose()) == 3
    # It saves and loads like any database.
    loaded = ScanDatabase.load(db.save(tmp_path / "db"))
    np.testing.assert_array_equal(loaded.vertices, db.vertices)


def test_from_meshes_minimal_csv_and_length_unit(tmp_path):
    expected = write_meshes(tmp_path / "meshes", 2)
    for i, suffix in enumerate(("obj", "ply")):  # the same spheres in cm: 2 m across, human-sized
        save_mesh(tmp_path / "meshes" / f"m{i}.{suffix}", expected[i] * 100, SPHERE.faces)
    labels = tmp_path / "labels.csv"
    labels.write_text("mesh\nm0.obj\nm1.ply\n")
    db = ScanDatabase.from_meshes(tmp_path / "meshes", labels, length_unit="cm")
    np.testing.assert_allclose(db.vertices, expected, atol=1e-6)
    assert db.subjects["subject"].tolist() == ["m0", "m1"]


def test_from_meshes_different_vertex_count_names_both_files(tmp_path):
    write_meshes(tmp_path / "meshes", 2)
    big = trimesh.creation.icosphere(subdivisions=2)
    save_mesh(tmp_path / "meshes" / "odd.obj", big.vertices, big.faces)
    labels = tmp_path / "labels.csv"
    labels.write_text("mesh\nm0.obj\nm1.ply\nodd.obj\n")
    with pytest.raises(DatabaseError, match=r"odd.obj: 162 vertices, but .*m0.obj has 42"):
        ScanDatabase.from_meshes(tmp_path / "meshes", labels)


def test_from_meshes_different_faces_names_both_files(tmp_path):
    write_meshes(tmp_path / "meshes", 2)
    flipped = SPHERE.faces[:, ::-1]
    save_mesh(tmp_path / "meshes" / "flipped.obj", SPHERE.vertices, flipped)
    labels = tmp_path / "labels.csv"
    labels.write_text("mesh\nm0.obj\nflipped.obj\n")
    with pytest.raises(DatabaseError, match=r"flipped.obj: faces differ from .*m0.obj"):
        ScanDatabase.from_meshes(tmp_path / "meshes", labels)


def test_from_meshes_per_scan_labels_become_one_per_subject(tmp_path):
    """A subject's scans may give different values of a label (weighed twice): the rest-pose
    scan's value is kept, else the mean, and a note says so; values more than 10 % apart, or
    a text label that differs, are refused."""
    write_meshes(tmp_path / "meshes", 3)
    labels = tmp_path / "labels.csv"
    labels.write_text("mesh,subject,pose,mass_kg\nm0.obj,p1,squat,60\nm1.ply,p1,rest,61\nm2.obj,p2,squat,70\n")
    db = ScanDatabase.from_meshes(tmp_path / "meshes", labels)
    np.testing.assert_array_equal(db.subjects["mass_kg"], [61.0, 70.0])
    assert "column 'mass_kg': the scans of 1 subject(s) ('p1') give different values" in db.meta["import_notes"][0]
    labels.write_text("mesh,subject,pose,mass_kg\nm0.obj,p1,a,60\nm1.ply,p1,b,61\nm2.obj,p2,a,\n")
    db = ScanDatabase.from_meshes(tmp_path / "meshes", labels, rest_pose="first")
    np.testing.assert_array_equal(db.subjects["mass_kg"], [60.0, np.nan])
    labels.write_text("mesh,subject,mass_kg\nm0.obj,p1,60\nm1.ply,p1,70\n")
    with pytest.raises(DatabaseError, match=r"labels.csv, column 'mass_kg': subject 'p1' has 60 on line 2 and 70 on "
                                            r"line 3, more than 10% apart"):
        ScanDatabase.from_meshes(tmp_path / "meshes", labels)
    labels.write_text("mesh,subject,sex\nm0.obj,p1,female\nm1.ply,p1,male\n")
    with pytest.raises(DatabaseError, match=r"labels.csv, line 3, column 'sex': subject 'p1' has 'male' here"):
        ScanDatabase.from_meshes(tmp_path / "meshes", labels)


def test_from_meshes_unknown_column_and_missing_mesh(tmp_path):
    write_meshes(tmp_path / "meshes", 1)
    labels = tmp_path / "labels.csv"
    labels.write_text("mesh,height\nm0.obj,170\n")
    with pytest.raises(DatabaseError, match=r"labels.csv: unknown column 'height'.*_cm"):
        ScanDatabase.from_meshes(tmp_path / "meshes", labels)
    labels.write_text("mesh\nm0.obj\nghost.obj\n")
    with pytest.raises(DatabaseError, match=r"labels.csv, line 3: mesh file .*ghost.obj not found"):
        ScanDatabase.from_meshes(tmp_path / "meshes", labels)


# -- bad database folders -------------------------------------------------------------------------

def edit_csv(path, old, new):
    text = path.read_text()
    assert old in text
    path.write_text(text.replace(old, new, 1))


def test_missing_files(db_folder):
    (db_folder / "scans.csv").unlink()
    with pytest.raises(DatabaseError, match="missing scans.csv"):
        ScanDatabase.load(db_folder)


def test_not_a_folder(tmp_path):
    with pytest.raises(DatabaseError, match="nowhere: not a folder"):
        ScanDatabase.load(tmp_path / "nowhere")


@pytest.mark.parametrize("bad_vertices", [
    np.zeros((5, 42), dtype=np.float32),        # wrong ndim
    np.zeros((5, 42, 3), dtype=np.float64),     # wrong dtype
    np.zeros((5, 42, 2), dtype=np.float32),     # last dim not 3
])
def test_bad_vertices_array(db_folder, bad_vertices):
    np.save(db_folder / "vertices.npy", bad_vertices)
    with pytest.raises(DatabaseError, match=r"vertices.npy: shape .*expected \(n_scans, n_vertices, 3\) float32"):
        ScanDatabase.load(db_folder)


def test_object_array_needs_pickle(db_folder):
    np.save(db_folder / "faces.npy", np.array([{"a": 1}], dtype=object), allow_pickle=True)
    with pytest.raises(DatabaseError, match="faces.npy: holds Python objects, which bodyspace never loads"):
        ScanDatabase.load(db_folder)
    (db_folder / "faces.npy").write_bytes(b"garbage" * 10)   # numpy would call this "pickled data"
    with pytest.raises(DatabaseError, match=r"faces.npy: not a .npy file \(it starts with b'garbag'\)"):
        ScanDatabase.load(db_folder)


def test_nan_vertices(db_folder):
    vertices = np.load(db_folder / "vertices.npy")
    vertices[3, 7, 1] = np.nan
    np.save(db_folder / "vertices.npy", vertices)
    with pytest.raises(DatabaseError, match="vertices.npy: scan 3 contains NaN"):
        ScanDatabase.load(db_folder)
    assert ScanDatabase.load(db_folder, check_values=False).n_scans == 5


def test_faces_out_of_range(db_folder):
    faces = np.load(db_folder / "faces.npy")
    faces[0, 0] = 42
    np.save(db_folder / "faces.npy", faces)
    with pytest.raises(DatabaseError, match=r"faces.npy: faces index vertices 0..42, expected 0..41"):
        ScanDatabase.load(db_folder)


def test_scan_count_mismatch(db_folder):
    path = db_folder / "scans.csv"
    path.write_text("\n".join(path.read_text().splitlines()[:-1]) + "\n")
    with pytest.raises(DatabaseError, match=r"scans.csv: 4 scan rows, but .*vertices.npy holds 5 scans"):
        ScanDatabase.load(db_folder)


def test_unknown_subject_column(db_folder):
    edit_csv(db_folder / "subjects.csv", "height_cm", "height")
    with pytest.raises(DatabaseError, match=r"subjects.csv: unknown column 'height'.*_cm.*_kg_m2"):
        ScanDatabase.load(db_folder)


def test_unknown_scan_subject(db_folder):
    edit_csv(db_folder / "scans.csv", "4,cy,rest", "4,dan,rest")
    with pytest.raises(DatabaseError, match=r"scans.csv: subject\(s\) 'dan' not found in .*subjects.csv"):
        ScanDatabase.load(db_folder)


def test_duplicate_subject(db_folder):
    edit_csv(db_folder / "subjects.csv", "\nbob,", "\nann,")
    with pytest.raises(DatabaseError, match=r"subjects.csv, line 3: subject 'ann' already listed on line 2"):
        ScanDatabase.load(db_folder)


def test_non_numeric_label(db_folder):
    edit_csv(db_folder / "subjects.csv", "180.25", "tall")
    with pytest.raises(DatabaseError, match=r"subjects.csv, line 3, column 'height_cm': 'tall' is not a number"):
        ScanDatabase.load(db_folder)


def test_unknown_format_version(db_folder):
    meta = json.loads((db_folder / "meta.json").read_text())
    meta["format_version"] = 99
    (db_folder / "meta.json").write_text(json.dumps(meta))
    with pytest.raises(DatabaseError, match="meta.json: format_version 99, expected 1"):
        ScanDatabase.load(db_folder)


def test_rotations_must_match_joint_names(db_folder):
    np.save(db_folder / "rotations.npy", np.zeros((5, 2, 3), dtype=np.float32))
    with pytest.raises(DatabaseError, match="rotations.npy: 2 joints per scan, but 3 joint names"):
        ScanDatabase.load(db_folder)


def test_writer_validates_input(tmp_path):
    vertices, faces, subjects, scans, meta, _ = example_parts()
    with pytest.raises(DatabaseError, match="subjects: unknown column 'age'"):
        write_database(tmp_path / "db", vertices, faces, {**subjects, "age": [1, 2, 3]}, scans, meta)
    vertices[1, 0, 0] = np.inf
    with pytest.raises(DatabaseError, match="vertices: scan 1 contains NaN or infinity"):
        write_database(tmp_path / "db", vertices, faces, subjects, scans, meta)
    assert not any(tmp_path.iterdir())


def test_in_memory_constructor_validates(tmp_path):
    vertices, faces, subjects, scans, meta, rotations = example_parts()
    db = ScanDatabase(vertices, faces, subjects, scans, {**meta, "joints": JOINTS}, rotations)
    np.testing.assert_array_equal(db.label("sex"), ["female", "female", "male", "male", "female"])
    with pytest.raises(DatabaseError, match=r"subjects, row 1, column 'sex': 'x'"):
        ScanDatabase(vertices, faces, {**subjects, "sex": ["female", "x", "male"]}, scans, meta)
    with pytest.raises(DatabaseError, match="rotations: 3 joints per scan, but none"):
        ScanDatabase(vertices, faces, subjects, scans, meta, rotations)


@pytest.mark.parametrize("folder", [None, 42, b"db", ""])
def test_a_folder_that_is_not_a_path_is_refused(folder, tmp_path):
    with pytest.raises(DatabaseError, match="database folder"):
        ScanDatabase.load(folder)
    with pytest.raises(DatabaseError, match="mesh folder"):
        ScanDatabase.from_meshes(folder, tmp_path / "labels.csv")
    with pytest.raises(DatabaseError, match="labels CSV"):
        ScanDatabase.from_meshes(tmp_path, folder)


def test_meta_joints_must_be_a_list_of_names(db_folder):
    meta = json.loads((db_folder / "meta.json").read_text())
    meta["joints"] = 3
    (db_folder / "meta.json").write_text(json.dumps(meta))
    with pytest.raises(DatabaseError, match="joints 3, expected a list"):
        ScanDatabase.load(db_folder)


def test_length_unit_of_another_type_is_refused(tmp_path):
    with pytest.raises(DatabaseError, match="length_unit"):
        ScanDatabase.from_meshes(tmp_path, tmp_path / "labels.csv", length_unit=["m"])
