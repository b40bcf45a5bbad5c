"""Mesh reading/writing keeps vertex order and count exactly; bad files raise MeshError naming them."""

import numpy as np
import pytest
import trimesh

from bodyspace.errors import MeshError
from bodyspace.mesh.io import load_mesh, save_mesh, triangulate_polygons


def scrambled_sphere(seed=0):
    """An icosphere with shuffled vertex order plus two vertices trimesh would merge or drop.

    Returns vertices (V, 3), faces (F, 3): vertex V-2 duplicates vertex 0's position (a UV seam)
    and vertex V-1 is used by no face.
    """
    sphere = trimesh.creation.icosphere(subdivisions=1)
    rng = np.random.default_rng(seed)
    permutation = rng.permutation(len(sphere.vertices))
    vertices = sphere.vertices[permutation]
    faces = np.argsort(permutation)[sphere.faces]
    duplicate = vertices[0]
    vertices = np.vstack([vertices, duplicate, [9.0, 9.0, 9.0]])
    faces = np.vstack([faces, [len(vertices) - 2, faces[0, 1], faces[0, 2]]])
    return vertices, faces


@pytest.mark.parametrize("suffix", [".obj", ".ply", ".glb"])
def test_round_trip_keeps_vertex_order_and_count(tmp_path, suffix):
    vertices, faces = scrambled_sphere()
    path = tmp_path / f"body{suffix}"
    save_mesh(path, vertices, faces)
    loaded_vertices, loaded_faces = load_mesh(path)
    assert loaded_vertices.shape == vertices.shape and loaded_vertices.dtype == np.float64
    assert loaded_faces.dtype == np.int64
    np.testing.assert_allclose(loaded_vertices, vertices, atol=1e-7)
    np.testing.assert_array_equal(loaded_faces, faces)
    assert [p.name for p in tmp_path.iterdir()] == [path.name]  # no temporary file left behind


def test_stl_writes_and_reads_triangles(tmp_path):
    vertices, faces = scrambled_sphere()
    save_mesh(tmp_path / "body.stl", vertices, faces)
    loaded_vertices, loaded_faces = load_mesh(tmp_path / "body.stl")
    # STL has no shared vertices: three per triangle, same triangles.
    np.testing.assert_allclose(loaded_vertices[loaded_faces], vertices[faces], atol=1e-5)


def test_obj_with_uvs_normals_and_quads_matches_trimesh_triangles(tmp_path):
    text = "\n".join([
        "mtllib none.mtl",
        "v 0 0 0", "v 1 0 0", "v 1 1 0", "v 0 1 0", "v 0 0 1", "v 1 0 1",
        "vt 0 0", "vt 1 0", "vt 1 1", "vt 0 1",
        "vn 0 0 1",
        "usemtl skin",
        "f 1/1/1 2/2/1 3/3/1 4/4/1",
        "f 1/1/1 2/2/1 6/3/1 5/4/1",
        "f 2/2/1 3/3/1 6/1/1",
        "f 4/1/1 3/2/1 6/3/1 5/4/1 1/1/1",
    ]) + "\n"
    path = tmp_path / "quads.obj"
    path.write_text(text)
    vertices, faces = load_mesh(path)
    assert vertices.shape == (6, 3)  # UV seams must not split vertices
    reference = trimesh.load(path, force="mesh", process=False, maintain_order=True, skip_materials=True)
    np.testing.assert_array_equal(faces, reference.faces)
    assert len(faces) == 2 + 2 + 1 + 3


def test_obj_with_several_objects_keeps_file_order(tmp_path):
    # trimesh would split this into two geometries and duplicate vertices when joining them.
    text = "o a\nv 0 0 0\nv 1 0 0\nv 0 1 0\nv 5 5 5\nv 0 0 1\nf 1 2 3\no b\nf 2 3 5\nf -4 -3 -1\n"
    path = tmp_path / "objects.obj"
    path.write_text(text)
    vertices, faces = load_mesh(path)
    np.testing.assert_array_equal(vertices, [[0, 0, 0], [1, 0, 0], [0, 1, 0], [5, 5, 5], [0, 0, 1]])
    np.testing.assert_array_equal(faces, [[0, 1, 2], [1, 2, 4], [1, 2, 4]])


def test_triangulate_polygons_only_quads_lists_halves_in_blocks():
    faces = triangulate_polygons(np.arange(8), np.array([4, 4]))
    np.testing.assert_array_equal(faces, [[0, 1, 2], [4, 5, 6], [2, 3, 0], [6, 7, 4]])


def test_missing_file(tmp_path):
    with pytest.raises(MeshError, match="nothere.obj.*not found"):
        load_mesh(tmp_path / "nothere.obj")


def test_unreadable_ply(tmp_path):
    path = tmp_path / "broken.ply"
    path.write_bytes(b"this is not a ply file")
    with pytest.raises(MeshError, match="broken.ply"):
        load_mesh(path)


def test_obj_with_bad_number(tmp_path):
    path = tmp_path / "bad.obj"
    path.write_text("v 0 0 0\nv 1 x 0\nv 0 1 0\nf 1 2 3\n")
    with pytest.raises(MeshError, match="bad.obj.*non-numeric"):
        load_mesh(path)


def test_no_faces(tmp_path):
    path = tmp_path / "points.obj"
    path.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\n")
    with pytest.raises(MeshError, match="points.obj.*3 vertices and no faces"):
        load_mesh(path)


def test_point_cloud_ply_has_no_faces(tmp_path):
    path = tmp_path / "cloud.ply"
    trimesh.PointCloud(np.random.default_rng(0).normal(size=(10, 3))).export(path)
    with pytest.raises(MeshError, match="cloud.ply.*no faces"):
        load_mesh(path)


def test_nan_vertices(tmp_path):
    path = tmp_path / "nan.obj"
    path.write_text("v 0 0 0\nv nan 0 0\nv 0 1 0\nf 1 2 3\n")
    with pytest.raises(MeshError, match="nan.obj.*NaN"):
        load_mesh(path)


def test_face_index_out_of_range(tmp_path):
    path = tmp_path / "range.obj"
    path.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 4\n")
    with pytest.raises(MeshError, match="range.obj.*3 vertices"):
        load_mesh(path)


def test_save_rejects_unknown_suffix_and_bad_arrays(tmp_path):
    vertices, faces = scrambled_sphere()
    with pytest.raises(MeshError, match="body.xyz"):
        save_mesh(tmp_path / "body.xyz", vertices, faces)
    with pytest.raises(MeshError, match="NaN"):
        save_mesh(tmp_path / "body.obj", np.full_like(vertices, np.nan), faces)
    assert not any(tmp_path.iterdir())


def test_repeated_topology_returns_independent_faces(tmp_path):
    vertices, faces = scrambled_sphere()
    save_mesh(tmp_path / "a.obj", vertices, faces)
    save_mesh(tmp_path / "b.obj", vertices + 1.0, faces)
    _, faces_a = load_mesh(tmp_path / "a.obj")
    faces_a[:] = 0  # must not leak into the next read of the same face lines
    vertices_b, faces_b = load_mesh(tmp_path / "b.obj")
    np.testing.assert_array_equal(faces_b, faces)
    np.testing.assert_allclose(vertices_b, vertices + 1.0, atol=1e-7)


def test_bodyspace_obj_cut_at_a_line_break_is_refused(tmp_path):
    """A file save_mesh wrote declares its counts: a copy cut short is blamed on that file."""
    vertices, faces = scrambled_sphere()
    path = tmp_path / "m.obj"
    save_mesh(path, vertices, faces)
    lines = path.read_text().splitlines(keepends=True)
    for keep in (len(lines) - 1, len(lines) - len(faces) - 1):  # one face short; every face gone
        cut = tmp_path / f"cut{keep}.obj"
        cut.write_text("".join(lines[:keep]))
        with pytest.raises(MeshError, match=rf"cut{keep}\.obj.*truncated"):
            load_mesh(cut)
    # Another program's OBJ without our header line reads as before.
    (tmp_path / "foreign.obj").write_text("".join(lines[1:-1]))
    assert len(load_mesh(tmp_path / "foreign.obj")[1]) == len(faces) - 1


@pytest.mark.parametrize("path", [None, 42, ["m.obj"], b"m.obj", ""])
def test_a_path_that_is_not_a_file_name_is_refused(path):
    with pytest.raises(MeshError, match="expected a file name"):
        load_mesh(path)
    with pytest.raises(MeshError, match="expected a file name"):
        save_mesh(path, np.zeros((3, 3)), np.array([[0, 1, 2]]))


@pytest.mark.parametrize("suffix", [".obj", ".ply", ".stl", ".glb"])
def test_truncated_file_is_blamed_on_itself_with_what_was_expected(tmp_path, suffix):
    vertices, faces = scrambled_sphere()
    path = tmp_path / f"whole{suffix}"
    save_mesh(path, vertices, faces)
    data = path.read_bytes()
    cut = tmp_path / f"cut{suffix}"
    cut.write_bytes(data[: len(data) // 2 + 3])  # +3: inside a line of the OBJ, not at a line break
    with pytest.raises(MeshError, match=rf"cut\{suffix}: .*(truncated|expected)") as caught:
        load_mesh(cut)
    assert "landmark" not in str(caught.value)
    cut.write_bytes(b"")
    with pytest.raises(MeshError, match=rf"cut\{suffix}: .*(empty|expected)"):
        load_mesh(cut)
