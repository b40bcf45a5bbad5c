"""Skeletons for every body, rigged glTF export, morph targets, and the two outside oracles:
the Khronos glTF validator and three.js (GLTFLoader + its skinning), both run with node.

The node packages are installed from tests/node/package-lock.json (``npm ci``, done by .ci/run;
done here too when tests/node/node_modules is missing). Tests needing node skip only when no
``node`` is on the PATH (CI has it).
"""

from __future__ import annotations

import fcntl
import json
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pygltflib
import pytest
import scipy.sparse as sp
from typer.testing import CliRunner

from bodyspace.cli import app
from bodyspace.data.template import RIG_NAMES
from bodyspace.errors import MeshError, ParameterError, UnitError
from bodyspace.export.gltf import (
    MorphTarget,
    gltf_bytes,
    influences_matrix,
    joint_local_transforms,
    top_influences,
    write_gltf,
)
from bodyspace.export.morphs import parse_morph_specs, semantic_morph_targets
from bodyspace.mesh.io import save_mesh
from bodyspace.model import BodyModel
from bodyspace.rig.kinematics import bone_rest_frames, forward_kinematics, linear_blend_skinning, rotvec_to_matrix
from bodyspace.rig.skeleton import Skeleton, body_skeleton, roll_from_x_axis
from bodyspace.semantics.model import SemanticModel
from bodyspace.studies.morph_targets import morph_target_errors
from bodyspace.synth.foreign import foreign_body, transfer
from bodyspace.synth.poses import load_pose_library
from bodyspace.synth.population import build_population
from bodyspace.units import Target

NODE_DIR = Path(__file__).resolve().parent / "node"
EXPECTED_BONES = {"default": 163, "default_no_toes": 137, "game_engine": 53, "game_engine_with_breast": 55,
                  "cmu_mb": 31, "mixamo": 52}


# ------------------------------------------------------------------------------------ fixtures

@pytest.fixture(scope="session")
def node():
    """The node executable with the oracle packages installed (npm ci from the lockfile)."""
    exe = shutil.which("node")
    if exe is None:
        pytest.skip("node is not installed (CI has it: Debian's nodejs and npm); the glTF validator and three.js "
                    "oracles need it")
    with open(NODE_DIR / ".install.lock", "w") as lock:   # two xdist workers: one installs
        fcntl.flock(lock, fcntl.LOCK_EX)
        if not (NODE_DIR / "node_modules" / "three").is_dir() or not (NODE_DIR / "node_modules" / "gltf-validator").is_dir():
            npm = shutil.which("npm")
            assert npm, "node is installed but npm is not: install npm, then `npm ci --prefix tests/node`"
            done = subprocess.run([npm, "ci", "--no-audit", "--no-fund"], cwd=NODE_DIR, capture_output=True, text=True)
            assert done.returncode == 0, f"npm ci in tests/node failed:\n{done.stderr[-2000:]}"
    return exe


def validate(node, *paths) -> list[dict]:
    done = subprocess.run([node, str(NODE_DIR / "validate.mjs"), *map(str, paths)], capture_output=True, text=True,
                          timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    return json.loads(done.stdout)


def three_skin(node, path, tmp_path, bones: dict | None = None, morphs=None) -> tuple[np.ndarray, dict]:
    """Vertices (V, 3) as three.js poses and skins the file, and what it read."""
    pose = tmp_path / "pose.json"
    pose.write_text(json.dumps({"bones": bones or {}, **({"morphs": list(morphs)} if morphs is not None else {})}))
    out = tmp_path / "three.bin"
    done = subprocess.run([node, str(NODE_DIR / "skin.mjs"), str(path), str(pose), str(out)], capture_output=True,
                          text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    return np.fromfile(out).reshape(-1, 3), json.loads(done.stdout)


def pose_dict(skeleton: Skeleton, G: np.ndarray) -> dict:
    t, q = joint_local_transforms(skeleton, G)
    return {b: {"translation": t[i].tolist(), "rotation": q[i].tolist()} for i, b in enumerate(skeleton.bone_names)}


@pytest.fixture(scope="session")
def tall_short(phenotype_model):
    return phenotype_model.vertices({"gender": np.array([1.0, 0.0]), "height": np.array([0.9, 0.1]),
                                     "weight": np.array([0.7, 0.3])})


@pytest.fixture(scope="module")
def semantic_model(template, tmp_path_factory):
    root = tmp_path_factory.mktemp("gltf_model")
    db = build_population(template, root / "db", 24, 0, rng=0)
    model = BodyModel.fit(db, "vertex", "rest")
    model.semantics = SemanticModel(model).fit(db, template=template)
    model.save(root / "model.npz")
    return root, model


def read_glb(path_or_bytes) -> pygltflib.GLTF2:
    data = path_or_bytes if isinstance(path_or_bytes, bytes) else Path(path_or_bytes).read_bytes()
    return pygltflib.GLTF2.load_from_bytes(data)


def accessor(g: pygltflib.GLTF2, index: int) -> np.ndarray:
    acc = g.accessors[index]
    view = g.bufferViews[acc.bufferView]
    dtype = {5126: np.float32, 5123: np.uint16, 5121: np.uint8, 5125: np.uint32}[acc.componentType]
    width = {"SCALAR": 1, "VEC3": 3, "VEC4": 4, "MAT4": 16}[acc.type]
    blob = g.binary_blob()
    a = np.frombuffer(blob, dtype=dtype, count=acc.count * width, offset=view.byteOffset + (acc.byteOffset or 0))
    return a.reshape(acc.count, width)


# ------------------------------------------------------------------------------------ skeletons

def test_the_six_rigs_are_there_with_their_bones(template):
    assert set(RIG_NAMES) == set(EXPECTED_BONES)
    for name, n in EXPECTED_BONES.items():
        rig = template.rigs[name]
        assert rig.n_bones == n and rig.weights.shape == (template.n_vertices, n)
        assert np.allclose(np.asarray(rig.weights.sum(axis=1)).ravel(), 1.0)


def test_default_no_toes_weights_fold_the_toes_into_one_bone(template):
    full, no_toes = template.rigs["default"], template.rigs["default_no_toes"]
    Wf, Wn = full.weights.tocsc(), no_toes.weights.tocsc()
    for side in ("L", "R"):
        toes = [i for i, b in enumerate(full.bone_names) if b.startswith("toe") and b.endswith(side)]
        assert len(toes) == 14
        merged = np.asarray(Wf[:, toes].sum(axis=1)).ravel()
        assert np.allclose(Wn[:, no_toes.bone_index(f"toe1-1.{side}")].toarray().ravel(), merged)
    for b in no_toes.bone_names:
        if not b.startswith("toe"):
            assert np.array_equal(Wn[:, no_toes.bone_index(b)].toarray(), Wf[:, full.bone_index(b)].toarray()), b
    # its own bone geometry: the toe bone starts at the ball of the foot, the foot bone ends there
    s = body_skeleton(no_toes, template.vertices)
    assert np.allclose(s.tails[s.bone_index("foot.L")], s.heads[s.bone_index("toe1-1.L")], atol=1e-9)


@pytest.mark.parametrize("rig_name", RIG_NAMES)
def test_skeleton_on_the_template_keeps_mpfb_rolls(template, rig_name):
    rig = template.rigs[rig_name]
    s = body_skeleton(rig, template.vertices)
    assert np.allclose(np.angle(np.exp(1j * (s.roll - rig.roll))), 0.0, atol=1e-9)
    assert s.n_bones == EXPECTED_BONES[rig_name] and (s.lengths > 0.003).all()
    # the frames are Blender's: local y runs head -> tail, right-handed and orthonormal
    F = s.frames
    d = (s.tails - s.heads) / s.lengths[:, None]
    assert np.allclose(F[:, :, 1], d, atol=1e-12)
    assert np.allclose(F.transpose(0, 2, 1) @ F, np.eye(3), atol=1e-12) and np.allclose(np.linalg.det(F), 1.0)


def test_a_taller_body_gets_longer_bones(template, tall_short):
    rig = template.rigs["default"]
    tall, short = (body_skeleton(rig, v) for v in tall_short)
    stature = np.ptp(tall_short[0][:, 1]) / np.ptp(tall_short[1][:, 1])
    assert stature > 1.1
    legs = [rig.bone_index(b) for b in ("upperleg01.L", "upperleg02.L", "lowerleg01.L", "lowerleg02.L")]
    ratio = tall.lengths[legs].sum() / short.lengths[legs].sum()

    def leg(v):  # hip to knee to ankle through the body's own joint centres
        hip, knee, ankle = (template.joint(v, f"joint-l-{j}") for j in ("upper-leg", "knee", "ankle"))
        return np.linalg.norm(knee - hip) + np.linalg.norm(ankle - knee)
    assert ratio > 1.2 and abs(ratio / (leg(tall_short[0]) / leg(tall_short[1])) - 1) < 0.05
    # heads are the body's own joints, not the template's: the knee is where this body's knee is
    knee = template.joint(tall_short[0], "joint-l-knee")
    assert np.linalg.norm(tall.heads[rig.bone_index("lowerleg01.L")] - knee) < 0.02


@pytest.mark.parametrize("rig_name", ["default", "mixamo"])
def test_skeleton_follows_a_rigid_motion_of_the_body(template, tall_short, rig_name):
    rig = template.rigs[rig_name]
    R = rotvec_to_matrix(np.array([0.4, -1.1, 0.3]))
    s = body_skeleton(rig, tall_short[0])
    moved = body_skeleton(rig, tall_short[0] @ R.T + np.array([1.0, -2.0, 0.5]))
    assert np.allclose(moved.frames, R @ s.frames, atol=1e-8)
    assert np.allclose(moved.heads, s.heads @ R.T + np.array([1.0, -2.0, 0.5]), atol=1e-9)


def test_rolls_are_carried_where_stored_rolls_would_turn_the_bone(template, tall_short):
    """On another body a stored roll turns near-singular bones (toes point forward, Blender's
    -Y) by up to ~140 degrees; the carried roll keeps the local x axis within a few degrees of
    the template bone's, rotated with the skin."""
    rig = template.rigs["default"]
    s0, s = body_skeleton(rig, template.vertices), body_skeleton(rig, tall_short[0])
    stored = Skeleton("stored", s.bone_names, s.parents, s.heads, s.tails, rig.roll)
    turn = np.degrees(np.arccos(np.clip(np.einsum("bi,bi->b", s.frames[:, :, 0], s0.frames[:, :, 0]), -1, 1)))
    turn_stored = np.degrees(np.arccos(np.clip(np.einsum("bi,bi->b", stored.frames[:, :, 0], s0.frames[:, :, 0]),
                                               -1, 1)))
    assert turn.max() < 20 and turn_stored.max() > 60


def test_roll_from_x_axis_inverts_bone_frames(rng):
    heads, tails = rng.normal(size=(50, 3)), rng.normal(size=(50, 3))
    roll = rng.uniform(-np.pi, np.pi, 50)
    x = bone_rest_frames(heads, tails, roll)[:, :, 0]
    assert np.allclose(roll_from_x_axis(heads, tails, x), roll, atol=1e-9)


def test_skeleton_refuses_bad_input(template):
    rig = template.rigs["cmu_mb"]
    with pytest.raises(MeshError, match=r"expected \(13380, 3\)"):
        body_skeleton(rig, template.vertices[:100])
    s = body_skeleton(rig, template.vertices)
    with pytest.raises(MeshError, match="zero length"):
        Skeleton("x", s.bone_names, s.parents, s.heads, s.heads, s.roll)
    with pytest.raises(ParameterError, match="cycle"):
        Skeleton("x", s.bone_names, np.roll(np.arange(s.n_bones), 1), s.heads, s.tails, s.roll)
    with pytest.raises(ParameterError, match="twice"):
        Skeleton("x", ("a", "a"), np.array([-1, 0]), s.heads[:2], s.tails[:2], s.roll[:2])


# ------------------------------------------------------------------------------------ influences

def test_top_influences_keeps_the_four_largest(rng):
    dense = rng.random((200, 12)) * (rng.random((200, 12)) < 0.5)
    dense[:, 3] += 0.01
    joints, w = top_influences(sp.csr_matrix(dense))
    for i in range(len(dense)):
        order = np.argsort(-dense[i], kind="stable")[:4]
        keep = dense[i, order] > 0
        assert set(joints[i][w[i] > 0]) == set(order[keep])
        assert np.allclose(w[i][w[i] > 0], np.sort(dense[i, order[keep]])[::-1] / dense[i, order[keep]].sum())
    assert np.allclose(w.sum(axis=1), 1.0)
    W = influences_matrix(joints, w, 12)
    assert (np.diff(W.indptr) <= 4).all()
    # with the skeleton: a dropped bone's weight goes to its nearest kept kin, nothing is rescaled
    parents = np.array([-1, 0, 1, 2, 3, 0, 5, 6, 7, 8, 9, 10])        # two chains from bone 0
    row = np.array([[0.0, 0.3, 0.0, 0.05, 0.0, 0.0, 0.25, 0.2, 0.0, 0.0, 0.0, 0.2]])
    j1, w1 = top_influences(sp.csr_matrix(row), parents=parents)
    got = dict(zip(j1[0].tolist(), w1[0].tolist()))
    assert got == pytest.approx({1: 0.3 + 0.05, 6: 0.25, 7: 0.2, 11: 0.2})
    assert np.allclose(w1.sum(axis=1), 1.0)
    j2, w2 = top_influences(sp.csr_matrix(dense), parents=np.r_[-1, np.arange(11)])
    assert np.allclose(w2.sum(axis=1), 1.0)
    for i in range(len(dense)):   # the same four bones are kept, only their weights differ
        assert set(j2[i][w2[i] > 0]) == set(joints[i][w[i] > 0])
    with pytest.raises(ParameterError, match="vertex 0 has no skin weight"):
        top_influences(sp.csr_matrix((3, 4)))


# ------------------------------------------------------------------------------------ the file

def _world_matrices(g: pygltflib.GLTF2) -> dict[int, np.ndarray]:
    """Each node's world matrix (4x4) from its TRS, walking the scene."""
    out = {}

    def local(n):
        T = np.eye(4)
        if n.translation:
            T[:3, 3] = n.translation
        if n.rotation:
            x, y, z, w = n.rotation
            T[:3, :3] = _quat(w, x, y, z)
        return T

    def walk(i, parent):
        out[i] = parent @ local(g.nodes[i])
        for c in g.nodes[i].children:
            walk(c, out[i])

    for i in g.scenes[0].nodes:
        walk(i, np.eye(4))
    return out


def _quat(w, x, y, z):
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def test_glb_holds_skin_bind_pose_extras_and_morphs(template, tall_short):
    rig = template.rigs["default"]
    v = tall_short[0]
    s = body_skeleton(rig, v)
    bump = MorphTarget("bump", np.tile([0.0, 0.01, 0.0], (len(v), 1)), {"variable": "test"})
    g = read_glb(gltf_bytes(v, template.faces, s, rig.weights, [bump]))
    prim = g.meshes[0].primitives[0]
    assert np.allclose(accessor(g, prim.attributes.POSITION), v, atol=1e-6)   # metres, our axes = glTF's
    n = accessor(g, prim.attributes.NORMAL)
    assert np.allclose(np.linalg.norm(n, axis=1), 1.0, atol=1e-6)
    assert (n[np.argmax(v[:, 2])] @ [0, 0, 1]) > 0.5                         # the nose looks to +Z
    assert np.array_equal(accessor(g, prim.indices).reshape(-1, 3), template.faces)
    w = accessor(g, prim.attributes.WEIGHTS_0)
    assert np.allclose(w.sum(axis=1), 1.0, atol=1e-6) and (w >= 0).all()
    skin = g.skins[0]
    names = [g.nodes[j].name for j in skin.joints]
    assert names == list(rig.bone_names)
    # the hierarchy is the rig's
    parent_of = {c: i for i, node in enumerate(g.nodes) for c in node.children}
    for b, p in enumerate(rig.parents):
        if p >= 0:
            assert parent_of[skin.joints[b]] == skin.joints[p]
        else:
            assert g.nodes[parent_of[skin.joints[b]]].name == "default"
    # bind pose = rest pose: every joint's world matrix times its inverse bind matrix is I
    world = _world_matrices(g)
    ibm = accessor(g, skin.inverseBindMatrices).reshape(-1, 4, 4).transpose(0, 2, 1)
    for b, j in enumerate(skin.joints):
        assert np.allclose(world[j] @ ibm[b], np.eye(4), atol=2e-5)
        assert np.allclose(world[j][:3, 3], s.heads[b], atol=1e-6)
        # the joint's local +Y runs from head to tail (Blender rebuilds the bone from it)
        d = s.tails[b] - s.heads[b]
        assert np.allclose(world[j][:3, 1], d / np.linalg.norm(d), atol=1e-6)
        ex = g.nodes[j].extras
        assert np.allclose(ex["tail"], s.tails[b]) and np.isclose(ex["roll"], s.roll[b])
    assert g.meshes[0].extras["targetNames"] == ["bump"] and g.meshes[0].weights == [0.0]
    assert np.allclose(accessor(g, prim.targets[0]["POSITION"]), bump.deltas, atol=1e-7)
    assert g.materials[0].name == "skin" and g.materials[0].pbrMetallicRoughness.metallicFactor == 0
    assert g.asset.extras["units"] == "metre" and g.asset.generator.startswith("bodyspace ")


def test_export_refuses_what_it_cannot_write(template, phenotype_model, tmp_path):
    rig = template.rigs["default"]
    s = body_skeleton(rig, template.vertices)
    fb = foreign_body(template, phenotype_model, rng=0, pose="rest", target_vertices=3000)   # mm, Z up
    with pytest.raises(MeshError, match="expected a body in metres"):
        gltf_bytes(fb.vertices, fb.faces)
    with pytest.raises(ParameterError, match=r"weights: shape \(13380, 31\), expected \(13380, 163\)"):
        gltf_bytes(template.vertices, template.faces, s, template.rigs["cmu_mb"].weights)
    with pytest.raises(ParameterError, match="pass both"):
        gltf_bytes(template.vertices, template.faces, s)
    with pytest.raises(ParameterError, match="morph 'x': deltas of shape"):
        gltf_bytes(template.vertices, template.faces, s, rig.weights, [MorphTarget("x", np.zeros((5, 3)))])
    with pytest.raises(ParameterError, match="ending in .glb"):
        write_gltf(tmp_path / "a.gltf", template.vertices, template.faces, s, rig.weights)


# ------------------------------------------------------------------------------------ oracles

@pytest.fixture(scope="module")
def oracle_files(template, phenotype_model, tall_short, tmp_path_factory):
    """Rigged files: every rig on a tall body, the default rig with two morph targets, and a
    foreign body (another topology, weights carried by its correspondence)."""
    root = tmp_path_factory.mktemp("oracles")
    files = {}
    v = tall_short[0]
    for name in RIG_NAMES:
        rig = template.rigs[name]
        files[name] = write_gltf(root / f"{name}.glb", v, template.faces, body_skeleton(rig, v), rig.weights)
    rig = template.rigs["default"]
    up = MorphTarget("up", np.tile([0.0, 0.02, 0.0], (len(v), 1)))
    wide = MorphTarget("wide", v * np.array([0.05, 0.0, 0.05]))
    files["morphs"] = write_gltf(root / "morphs.glb", v, template.faces, body_skeleton(rig, v), rig.weights,
                                 [up, wide])
    fb = foreign_body(template, phenotype_model, rng=3, pose="rest", target_vertices=5000)
    fv = fb.internal_vertices()
    fw = transfer(fb.topology.correspondence, template.faces, rig.weights.toarray())
    # the foreign body is turned and moved (internal_vertices undoes only units and up axis):
    # its skeleton is the template body's carried by the same rigid motion
    src = fb.template_vertices
    tv = transfer(fb.topology.correspondence, template.faces, src)
    A = np.c_[tv, np.ones(len(tv))]
    M = np.linalg.lstsq(A, fv, rcond=None)[0]
    s = body_skeleton(rig, src @ M[:3] + M[3])
    files["foreign"] = write_gltf(root / "foreign.glb", fv, fb.faces, s, sp.csr_matrix(fw))
    return root, files, {"foreign": (fv, fb.faces, s, fw)}


def test_khronos_validator_reports_no_errors(node, oracle_files):
    _, files, _ = oracle_files
    reports = validate(node, *files.values())
    for (name, path), report in zip(files.items(), reports):
        issues = report["issues"]
        assert issues["numErrors"] == 0, (name, issues["messages"][:10])
        assert issues["numWarnings"] == 0, (name, issues["messages"][:10])
        assert report["info"]["hasSkins"] and report["info"]["maxInfluences"] == 4
    assert reports[list(files).index("morphs")]["info"]["hasMorphTargets"]


@pytest.mark.parametrize("pose", ["squat", "arms_overhead", "torso_twist_left"])
def test_threejs_skinning_matches_our_lbs(node, template, tall_short, oracle_files, tmp_path, pose):
    """three.js loads the skinned mesh (bone names, morph names) and its skinning of a posed
    frame equals our linear blend skinning with the file's 4 influences within 0.1 mm."""
    _, files, _ = oracle_files
    rig = template.rigs["default"]
    v = tall_short[0]
    s = body_skeleton(rig, v)
    R = load_pose_library().rotations(pose, rig)
    R[rig.bone_index("root")] = rotvec_to_matrix(np.array([0.0, 0.7, 0.0]))   # the whole body turned too
    G = forward_kinematics(R[None], s.heads, s.parents)[0]
    j, w = top_influences(rig.weights, parents=rig.parents)
    W4 = influences_matrix(j, w, rig.n_bones)
    theirs, info = three_skin(node, files["morphs"], tmp_path, pose_dict(s, G), morphs=[0.5, -1.0])
    assert info["bone_names"] == list(rig.bone_names) and info["vertices"] == len(v)
    assert info["morph_targets"] == {"up": 0, "wide": 1} and info["has_normals"] and info["material"] == "skin"
    rest = v + 0.5 * np.array([0.0, 0.02, 0.0]) - 1.0 * v * np.array([0.05, 0.0, 0.05])
    ours = linear_blend_skinning(rest, W4, G[None])[0]
    err = np.linalg.norm(theirs - ours, axis=1)
    assert err.max() < 1e-4, f"three.js vs our LBS: {1000 * err.max():.4f} mm"
    assert np.linalg.norm(ours - rest, axis=1).max() > 0.05   # the pose moved the body


def test_threejs_bind_pose_is_the_rest_pose_for_every_rig(node, template, tall_short, oracle_files, tmp_path):
    _, files, _ = oracle_files
    for name in RIG_NAMES:
        theirs, info = three_skin(node, files[name], tmp_path)
        assert info["bones"] == EXPECTED_BONES[name]
        assert np.abs(theirs - tall_short[0]).max() < 1e-5, name


def test_foreign_topology_exports_and_skins_alike(node, template, oracle_files, tmp_path):
    """Another triangulation (5,000 vertices, turned, moved), its weights carried from the
    template: the exporter takes any mesh; three.js skins it as we do."""
    _, files, extra = oracle_files
    fv, ff, s, fw = extra["foreign"]
    R = load_pose_library().rotations("star", template.rigs["default"])
    G = forward_kinematics(R[None], s.heads, s.parents)[0]
    j, w = top_influences(sp.csr_matrix(fw), parents=s.parents)
    ours = linear_blend_skinning(fv, influences_matrix(j, w, s.n_bones), G[None])[0]
    theirs, info = three_skin(node, files["foreign"], tmp_path, pose_dict(s, G))
    assert info["vertices"] == len(fv) != template.n_vertices
    assert np.linalg.norm(theirs - ours, axis=1).max() < 1e-4


# ------------------------------------------------------------------------------------ morph targets

def test_parse_morph_specs():
    assert parse_morph_specs("stature,mass=+5kg, waist_girth=-3cm") == {"stature": 0.10, "mass": 5.0,
                                                                        "waist_girth": -0.03}
    assert parse_morph_specs("weight,muscle") == {"mass": 10.0, "muscle": 0.25}
    for bad, match in (("stature,,mass", "empty name"), ("mass=80kg", "signed amount"), ("stature=+5", "unit"),
                       ("mass,mass", "asked twice"), ("mass=+0kg", "non-zero")):
        with pytest.raises(UnitError, match=match):
            parse_morph_specs(bad)


def test_semantic_morph_targets_are_the_true_morph_at_weight_one(semantic_model):
    _, model = semantic_model
    x0 = model.generate({"stature": 1.70, "mass": 65.0}, rng=1).vertices
    targets = semantic_morph_targets(model, x0, {"stature": 0.10, "mass": 10.0})
    assert [t.name for t in targets] == ["stature +10 cm", "mass +10 kg"]
    for t, (name, change) in zip(targets, (("stature", 0.10), ("mass", 10.0))):
        true = model.morph(x0, {name: Target(name, "delta", value=change)}).vertices
        assert np.abs(x0 + t.deltas - true).max() < 1e-9
        tol = 0.004 if name == "stature" else 0.5
        assert abs(t.meaning["reached_change"] - change) <= tol
    rows = morph_target_errors(model, x0, targets[:1], weights=(0.5, -1.0))
    # a vertex model decodes linearly: stature's morph is the straight line (one step, no correction)
    assert all(r["max_m"] < 1e-6 for r in rows)
    grad = semantic_morph_targets(model, x0, {"stature": 0.10}, method="gradient")[0]
    assert grad.meaning["method"] == "gradient"
    assert np.abs(grad.deltas - targets[0].deltas).max() < 0.01
    with pytest.raises(ParameterError, match="unknown semantic variable 'nose'"):
        semantic_morph_targets(model, x0, {"nose": 0.01})


# ------------------------------------------------------------------------------------ command line

def test_generate_writes_a_rigged_glb_with_morphs_and_a_picture(node, semantic_model, tmp_path):
    root, _ = semantic_model
    out, png = tmp_path / "man.glb", tmp_path / "rig.png"
    r = CliRunner().invoke(app, ["generate", str(root / "model.npz"), "--set", "stature=180cm", "--set", "mass=80kg",
                                 "--out", str(out), "--rig", "default", "--morphs", "stature,mass=+5kg",
                                 "--png", str(png), "--bones", "upperarm01.L,spine03"])
    assert r.exit_code == 0, r.output
    g = read_glb(out)
    assert g.meshes[0].extras["targetNames"] == ["stature +10 cm", "mass +5 kg"]
    assert len(g.skins[0].joints) == 163 and png.stat().st_size > 10_000
    assert validate(node, out)[0]["issues"]["numErrors"] == 0
    # --force replaces the rigged file (it carries bodyspace's signature), not a plain one
    r = CliRunner().invoke(app, ["generate", str(root / "model.npz"), "--set", "stature=170cm", "--out", str(out),
                                 "--rig", "cmu_mb", "--force"])
    assert r.exit_code == 0, r.output
    assert len(read_glb(out).skins[0].joints) == 31


@pytest.mark.parametrize("args, message", [
    (["--morphs", "stature"], "--morphs needs --rig"),
    (["--rig", "default", "--out-obj"], "expected a name ending in .glb"),
    (["--rig", "skeleton"], "--rig 'skeleton': not a rig of the template"),
    (["--rig", "default", "--morphs", "nose"], "unknown semantic variable 'nose'"),
    (["--rig", "default", "--morphs", "mass=80kg"], "signed amount"),
    (["--rig", "default", "--bones", "head"], "--bones chooses the weight maps of --png"),
])
def test_generate_rig_errors_are_one_line(semantic_model, tmp_path, args, message):
    root, _ = semantic_model
    out = tmp_path / ("body.obj" if "--out-obj" in args else "body.glb")
    args = [a for a in args if a != "--out-obj"]
    r = CliRunner().invoke(app, ["generate", str(root / "model.npz"), "--set", "stature=175cm", "--out", str(out),
                                 *args])
    assert r.exit_code == 2, r.output
    assert message in " ".join(r.output.split()) and "Traceback" not in r.output
    assert not out.exists()


def test_rig_command_on_a_template_mesh_and_a_foreign_one(template, phenotype_model, tall_short, semantic_model,
                                                         tmp_path):
    root, _ = semantic_model
    mesh = tmp_path / "body.obj"
    save_mesh(mesh, tall_short[1], template.faces)
    out = tmp_path / "body.glb"
    r = CliRunner().invoke(app, ["rig", str(mesh), "--out", str(out), "--rig", "mixamo", "--model",
                                 str(root / "model.npz"), "--morphs", "muscle"])
    assert r.exit_code == 0, r.output
    g = read_glb(out)
    assert g.nodes[g.skins[0].joints[0]].name.startswith("mixamorig:")
    assert g.meshes[0].extras["targetNames"] == ["muscle +0.25"]
    fb = foreign_body(template, phenotype_model, rng=0, pose="rest", target_vertices=3000)
    other = tmp_path / "other.obj"
    save_mesh(other, fb.internal_vertices(), fb.faces)
    r = CliRunner().invoke(app, ["rig", str(other), "--out", str(tmp_path / "other.glb"), "--rig", "cmu_mb"])
    assert r.exit_code == 0 and "skeleton embedded" in " ".join(r.output.split()), r.output
    g = read_glb(tmp_path / "other.glb")                     # another topology: embedding + bone heat
    assert len(g.skins[0].joints) == EXPECTED_BONES["cmu_mb"]
    r = CliRunner().invoke(app, ["rig", str(other), "--out", str(tmp_path / "o2.glb"), "--model", str(root / "model.npz"),
                                 "--morphs", "muscle"])
    assert r.exit_code == 2 and "--morphs" in r.output and "topology" in " ".join(r.output.split())
    r = CliRunner().invoke(app, ["rig", str(mesh), "--out", str(tmp_path / "x.glb"), "--model", str(mesh)])
    assert r.exit_code == 2 and "--model is read for --morphs only" in " ".join(r.output.split())
