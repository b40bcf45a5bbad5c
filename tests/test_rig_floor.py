"""``bodyspace rig`` on a scanner's mesh that carries its floor, a turntable or a pole (issue 15,
rigfloor): the body alone is rigged (``rig.scan_body``), found without landmarks or by the
landmark file of ``--weights``, what was left out is said, and the rig matches the rig of the same
body without the floor."""

from __future__ import annotations

import json
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pygltflib
import pytest
from scipy.spatial import cKDTree
from typer.testing import CliRunner

from bodyspace.cli import app
from bodyspace.data.template import load_template
from bodyspace.measure.conventions import UP_ROTATIONS
from bodyspace.mesh.io import save_mesh
from bodyspace.rig.scan_body import scan_body
from bodyspace.synth.foreign import foreign_topology, transfer

from floor_meshes import disc, scanner_meshes, turntable, with_extras

NODE_DIR = Path(__file__).resolve().parent / "node"
Z_UP = UP_ROTATIONS["z"]          # metres +Y up → +Z up (Blender's axes)


@pytest.fixture(scope="module")
def foreign(template):
    """The template's mean body remeshed to 3000 vertices in another order: (V, 3) metres, (F, 3), topology."""
    topo = foreign_topology(template, 3000, rng=11)
    v = transfer(topo.correspondence, template.faces, np.asarray(template.vertices, float))
    return v, np.asarray(topo.faces), topo


@pytest.fixture(scope="module")
def bodies(template, foreign):
    return {"template": (np.asarray(template.vertices, float), np.asarray(template.faces)),
            "foreign": foreign[:2]}


def test_clean_bodies_are_rigged_as_given(bodies):
    for v, f in bodies.values():
        assert scan_body(v @ Z_UP * 1000.0, f, up="z", units="mm") is None
        assert scan_body(v, f) is None


@pytest.mark.parametrize("name", ["template", "foreign"])
def test_the_body_is_found_under_any_scanner_geometry(bodies, name):
    """Every case gives back exactly the body's faces (the welded sheet's soles too: the sheet
    faces up, the soles down); the frame given on the template, found on the remesh."""
    v, f = bodies[name]
    frame = dict(up="z", units="mm") if name == "template" else {}
    for case, (mv, mf) in scanner_meshes(v, f).items():
        got = scan_body(mv @ Z_UP * 1000.0, mf, **frame)
        assert got is not None, case
        assert np.array_equal(got.vertex_ids, np.arange(len(v))), case
        assert np.array_equal(got.faces, f), case
        said = " ".join(got.notes)
        if case == "pole":
            assert said.startswith("left out 1 piece beside the body") and "2.00 m across" in said, said
        else:
            assert said.startswith("left out the floor"), said
        assert ("cut off under the feet" in said) == (case == "welded"), said


def _landmark_file(path: Path, topo, n_vertices: int, weights_of: np.ndarray) -> Path:
    """A landmark file as ``bodyspace landmarks`` writes it for a mesh of ``n_vertices`` whose
    first vertices are the remesh's: its landmarks and skin weights (``weights_of``: (V, 4) bone
    ids of rig default, weights in equal parts; the rest of the vertices on the first bone)."""
    rig = load_template().rigs["default"]
    ids = np.zeros((n_vertices, 4), dtype=int)
    ids[:len(weights_of)] = weights_of
    w = np.full((n_vertices, 4), 0.25)
    doc = {"landmarks": {k: {"vertices": i.tolist(), "weights": w_.tolist()} for k, (i, w_) in topo.landmarks.items()},
           "skin_weights": {"rig": rig.name, "bones": list(rig.bone_names), "bone_ids": ids.tolist(),
                            "weights": w.tolist()}}
    path.write_text(json.dumps(doc))
    return path


def _read_glb(path: Path) -> dict:
    """POSITION, JOINTS_0, WEIGHTS_0 of the first primitive and the joint nodes' heads of a .glb."""
    g = pygltflib.GLTF2().load(str(path))
    blob = g.binary_blob()

    def accessor(i):
        a = g.accessors[i]
        view = g.bufferViews[a.bufferView]
        dtype = {5126: np.float32, 5123: np.uint16, 5121: np.uint8, 5125: np.uint32}[a.componentType]
        width = {"SCALAR": 1, "VEC3": 3, "VEC4": 4, "MAT4": 16}[a.type]
        start = (view.byteOffset or 0) + (a.byteOffset or 0)
        return np.frombuffer(blob, dtype, a.count * width, start).reshape(a.count, width)

    attrs = g.meshes[0].primitives[0].attributes
    joints = g.skins[0].joints
    return {"position": accessor(attrs.POSITION), "joints": accessor(attrs.JOINTS_0),
            "weights": accessor(attrs.WEIGHTS_0), "heads": np.array([g.nodes[j].extras["head"] for j in joints]),
            "extras": g.asset.extras or {}}


def test_rig_command_rigs_the_body_as_without_the_floor(bodies, foreign, tmp_path):
    """Bone heat (no landmarks, frame found) on the welded sheet, carried weights (--weights,
    frame given) on the floor disc with a pole: the glTF holds the body alone, and its joints,
    vertices and weights are those of the clean body's rig; the files pass the glTF validator."""
    v, f = bodies["foreign"]
    topo = foreign[2]
    meshes = scanner_meshes(v, f)
    runner = CliRunner()

    def rig(name, mv, mf, *extra):
        save_mesh(tmp_path / f"{name}.obj", mv @ Z_UP * 1000.0, mf)
        r = runner.invoke(app, ["rig", str(tmp_path / f"{name}.obj"), "--out", str(tmp_path / f"{name}.glb"),
                                *extra])
        assert r.exit_code == 0, r.output
        return " ".join(r.output.split()), _read_glb(tmp_path / f"{name}.glb")

    said, clean = rig("clean", v, f)
    assert "[left out]" not in said and "source_vertices" not in clean["extras"]
    said, welded = rig("welded", *meshes["welded"])
    assert "[left out] " in said and "left out the floor" in said and "cut off under the feet" in said, said
    assert f"the glTF holds the body alone: {len(v)} of {len(meshes['welded'][0])} vertices, renumbered" in said
    assert welded["extras"]["source_vertices"]["ids"] == list(range(len(v)))
    for key in ("position", "heads"):
        assert np.abs(welded[key] - clean[key]).max() < 1e-3, key          # metres: within 1 mm
    assert np.array_equal(welded["joints"], clean["joints"])
    assert np.abs(welded["weights"].astype(float) - clean["weights"]).max() < 1e-5

    # --weights: the file's landmarks say which pieces are the body; its weights are carried.
    bone_ids = cKDTree(v).query(v, 4)[1] % 40
    mv, mf = meshes["disc"]
    mv, mf = np.r_[mv, meshes["pole"][0][len(v):]], np.r_[mf, meshes["pole"][1][len(f):] - len(v) + len(mv)]
    clean_lm = _landmark_file(tmp_path / "clean_lm.json", topo, len(v), bone_ids)
    floor_lm = _landmark_file(tmp_path / "floor_lm.json", topo, len(mv), bone_ids)
    _, carried = rig("carried", v, f, "--weights", str(clean_lm), "--up", "z", "--units", "mm")
    said, floor = rig("floor", mv, mf, "--weights", str(floor_lm), "--up", "z", "--units", "mm")
    assert "left out 2 pieces not joined to the body" in said and "skin weights of" in said, said
    for key in ("position", "heads"):
        assert np.abs(floor[key] - carried[key]).max() < 1e-3, key
    assert np.array_equal(floor["joints"], carried["joints"]) and np.array_equal(floor["weights"], carried["weights"])

    node = shutil.which("node")
    if node is not None and (NODE_DIR / "node_modules" / "gltf-validator").is_dir():
        done = subprocess.run([node, str(NODE_DIR / "validate.mjs"), str(tmp_path / "welded.glb"),
                               str(tmp_path / "floor.glb")], capture_output=True, text=True, timeout=300)
        for report in json.loads(done.stdout):
            assert report["issues"]["numErrors"] == 0 and report["issues"]["numWarnings"] == 0, report["issues"]
            assert report["info"]["hasSkins"]


def test_a_turntable_on_the_ground_and_a_mesh_wound_inwards(bodies):
    """The ground, then the turntable's top (frame and unit found though the floors double the
    area); a welded sheet on a mesh wound inwards: the soles still told from the sheet."""
    v, f = bodies["template"]
    y0, zc = v[:, 1].min(), v[:, 2].mean()
    mv, mf = with_extras(v, f, disc((0.0, 0.0, zc), 1.0, y0 - 0.1), turntable((0.0, 0.0, zc), 0.5, y0, 0.1))
    got = scan_body(mv @ Z_UP * 1000.0, mf)
    assert np.array_equal(got.faces, f)
    assert "left out the floor 2.00 m across" in got.notes[0] and "a turntable's top" in got.notes[1], got.notes
    mv, mf = scanner_meshes(v, f)["welded"]
    got = scan_body(mv @ Z_UP * 1000.0, mf[:, ::-1], up="z", units="mm")
    assert np.array_equal(np.sort(got.faces, axis=1), np.sort(f, axis=1)), len(got.faces)
