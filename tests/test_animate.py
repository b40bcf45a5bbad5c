"""``bodyspace animate``: a CMU clip on bodies of a model (``--set stature=...``) and on meshes;
the animated glTF checked by the Khronos validator and played by three.js (a sampled frame equals
our LBS within 0.1 mm); the BVH and mesh-sequence outputs; filmstrip and GIF; refusals; and the
arm-torso intersection measure."""

from __future__ import annotations

import json
import subprocess

import numpy as np
import pygltflib
import pytest
from test_bvh import CLIPS, needs_clips
from test_gltf import NODE_DIR, node, validate  # noqa: F401 (node is a fixture)
from typer.testing import CliRunner

from bodyspace.atomic import is_own_file
from bodyspace.cli import app
from bodyspace.errors import ParameterError
from bodyspace.export.gltf import SkeletonAnimation, gltf_bytes, influences_matrix, top_influences
from bodyspace.export.sequence import read_mesh_sequence
from bodyspace.mesh.geometry import capped_volume
from bodyspace.mesh.io import load_mesh, save_mesh
from bodyspace.model import BodyModel
from bodyspace.motion.bvh import Motion, read_bvh
from bodyspace.motion.ik import foot_vertices, lock_feet, sole_points
from bodyspace.motion.intersection import arm_torso_intersections, arm_torso_regions
from bodyspace.motion.retarget import retarget
from bodyspace.rig.kinematics import forward_kinematics, linear_blend_skinning, rotvec_to_matrix
from bodyspace.rig.skeleton import body_skeleton
from bodyspace.semantics.model import SemanticModel
from bodyspace.synth.foreign import foreign_body
from bodyspace.synth.population import build_population

runner = CliRunner()
FRAMES = "200:440:12"          # 20 frames of the walk at 10 per second


def run(*args):
    result = runner.invoke(app, [str(a) for a in args])
    return result.exit_code, result.output


@pytest.fixture(scope="module")
def template_mesh(template, tmp_path_factory):
    path = tmp_path_factory.mktemp("animate") / "template.obj"
    save_mesh(path, template.vertices, template.faces)
    return path


@pytest.fixture(scope="module")
def semantic_model_file(template, tmp_path_factory):
    root = tmp_path_factory.mktemp("animate_model")
    db = build_population(template, root / "db", 24, 0, rng=0)
    model = BodyModel.fit(db, "vertex", "rest")
    model.semantics = SemanticModel(model).fit(db, template=template)
    model.save(root / "model.npz")
    return root / "model.npz"


def api_clip(template, frames=slice(200, 440, 12), ik=True):
    """What the command computes, through the API: the retargeted, foot-locked clip on the template."""
    rig = template.rigs["default"]
    sk = body_skeleton(rig, template.vertices, rest_vertices=template.vertices)
    clip = read_bvh(CLIPS[0]).frames(frames)
    clip = Motion(clip.skeleton, clip.values, clip.frame_time * frames.step, clip.unit, "given", clip.translation)
    out = retarget(clip, sk, target_floor=float(template.vertices[:, 1].min()))
    if not ik:
        return out
    return lock_feet(out, sole=sole_points(out, rig.weights, template.vertices))[0]


# ----------------------------------------------------------------------------- glTF animation

@needs_clips
def test_animated_glb_validates_and_three_js_plays_it_like_our_lbs(node, template, template_mesh,  # noqa: F811
                                                                    tmp_path):
    out = tmp_path / "walk.glb"
    code, text = run("animate", template_mesh, "--motion", CLIPS[0], "--frames", FRAMES, "--out", out)
    assert code == 0, text
    report = validate(node, out)[0]
    issues = report["issues"]
    assert issues["numErrors"] == 0 and issues["numWarnings"] == 0, issues["messages"][:10]
    assert report["info"]["animationCount"] == 1
    g = pygltflib.GLTF2.load(out)
    anim = g.animations[0]
    rig = template.rigs["default"]
    assert len(anim.channels) == rig.n_bones + 1                       # rotations + the root's translation
    assert {c.target.path for c in anim.channels} == {"rotation", "translation"}
    clip = api_clip(template)
    G = clip.transforms()
    j, w = top_influences(rig.weights, parents=rig.parents)
    W4 = influences_matrix(j, w, rig.n_bones)
    for f in (0, 7, 19):
        theirs, info = _three_at(node, out, tmp_path, f * 0.1)
        ours = linear_blend_skinning(template.vertices, W4, G[f:f + 1])[0]
        err = np.linalg.norm(theirs - ours, axis=1)
        assert err.max() < 1e-4, f"frame {f}: three.js vs our LBS {1000 * err.max():.4f} mm"
        assert info["animation"]["tracks"] == rig.n_bones + 1
    # the body moved: the clip walks and turns
    assert np.linalg.norm(G[-1, 0, :3, 3] - G[0, 0, :3, 3]) > 0.1


def _three_at(node, path, tmp_path, t):  # noqa: F811
    pose = tmp_path / "pose.json"
    pose.write_text(json.dumps({"bones": {}, "time": float(np.float32(t))}))
    out = tmp_path / "three.bin"
    done = subprocess.run([node, str(NODE_DIR / "skin.mjs"), str(path), str(pose), str(out)], capture_output=True,
                          text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    return np.fromfile(out).reshape(-1, 3), json.loads(done.stdout)


def test_animation_refuses_wrong_shapes(template):
    rig = template.rigs["cmu_mb"]
    sk = body_skeleton(rig, template.vertices)
    G = forward_kinematics(np.broadcast_to(np.eye(3), (3, sk.n_bones, 3, 3)), sk.heads, sk.parents)
    data = gltf_bytes(template.vertices, template.faces, sk, rig.weights, animation=SkeletonAnimation(G, 0.1))
    assert pygltflib.GLTF2.load_from_bytes(data).animations[0].samplers[0].input is not None
    with pytest.raises(ParameterError, match="expected finite \\(frames, 31, 4, 4\\)"):
        gltf_bytes(template.vertices, template.faces, sk, rig.weights, animation=SkeletonAnimation(G[:, :5], 0.1))
    with pytest.raises(ParameterError, match="needs a skeleton"):
        gltf_bytes(template.vertices, template.faces, animation=SkeletonAnimation(G, 0.1))
    with pytest.raises(ParameterError, match="positive number of seconds"):
        gltf_bytes(template.vertices, template.faces, sk, rig.weights, animation=SkeletonAnimation(G, 0.0))


# ----------------------------------------------------------------------------- other outputs

@needs_clips
def test_bvh_and_mesh_sequence_outputs(template, template_mesh, tmp_path):
    seq, bvh, png, gif, rep = (tmp_path / n for n in ("walk.npz", "walk.bvh", "walk.png", "walk.gif", "walk.json"))
    code, text = run("animate", template_mesh, "--motion", CLIPS[0], "--frames", FRAMES, "--out", seq,
                     "--filmstrip", png, "--every", 5, "--gif", gif, "--report", rep)
    assert code == 0, text
    assert "contact frames" in text and "arms in" in text          # the table (wrapped at 80 columns)
    V, F, dt, header = read_mesh_sequence(seq)
    assert V.shape == (20, len(template.vertices), 3) and np.array_equal(F, template.faces)
    assert dt == pytest.approx(0.1, rel=1e-4) and header["motion"]["foot_ik"]
    clip = api_clip(template)
    ours = linear_blend_skinning(template.vertices, template.rigs["default"].weights, clip.transforms())
    assert np.abs(V - ours).max() < 1e-5                                   # float32 on disk
    feet = foot_vertices(clip, template.rigs["default"].weights)
    assert V[:, feet, 1].min() > -0.01                                      # on the floor, not in it
    # (the clip kneels at 3.1 s: a knee on the floor of CMU's taller subject goes ~3 cm into ours)
    for p in (seq, png, gif, rep):
        assert is_own_file(p), p
    r = json.loads(rep.read_text())
    assert r["frames"] == 20 and r["foot_ik"]["feet_skin_penetration_m"] < 0.01
    assert r["arm_torso_intersections"]["frames_intersecting"] <= 20
    code, text = run("animate", template_mesh, "--motion", CLIPS[0], "--frames", "0:30:3", "--out", bvh)
    assert code == 0, text
    m = read_bvh(bvh, unit="m", translation="replace")
    assert m.n_frames == 10 and m.frame_time == pytest.approx(3 / 120, rel=1e-4)
    assert m.skeleton.n_joints == template.rigs["default"].n_bones
    # outputs are refused when present, replaced with --force when ours
    code, text = run("animate", template_mesh, "--motion", CLIPS[0], "--frames", FRAMES, "--out", seq)
    assert code == 2 and "already exists" in text
    code, text = run("animate", template_mesh, "--motion", CLIPS[0], "--frames", "0:20:4", "--out", seq, "--gif",
                     gif, "--force")
    assert code == 0, text


@needs_clips
def test_numbered_mesh_files_and_a_folder_of_them(template, template_mesh, tmp_path):
    """--out walk_%03d.obj: one mesh a frame, numbered from 0; --out DIR: frame_0000.ply, ... in a
    folder; present files are refused without --force; they equal the .npz sequence's frames."""
    frames = "200:230:10"                                  # 3 frames
    V = linear_blend_skinning(template.vertices, template.rigs["default"].weights,
                              api_clip(template, slice(200, 230, 10), ik=False).transforms())
    code, text = run("animate", template_mesh, "--motion", CLIPS[0], "--frames", frames, "--out",
                     tmp_path / "walk_%03d.obj", "--no-ik")
    assert code == 0, text
    assert sorted(p.name for p in tmp_path.glob("walk_*.obj")) == ["walk_000.obj", "walk_001.obj", "walk_002.obj"]
    for k in range(3):
        v, f = load_mesh(tmp_path / f"walk_{k:03d}.obj")
        assert np.array_equal(f, template.faces) and np.abs(v - V[k]).max() < 1e-5     # float32 skinning
    code, text = run("animate", template_mesh, "--motion", CLIPS[0], "--frames", frames, "--out",
                     tmp_path / "walk_%03d.obj", "--no-ik")
    assert code == 2 and "walk_000.obj: already exists" in text, text
    code, text = run("animate", template_mesh, "--motion", CLIPS[0], "--frames", frames, "--out", tmp_path / "seq",
                     "--no-ik")
    assert code == 0, text
    assert sorted(p.name for p in (tmp_path / "seq").glob("*.ply")) == [f"frame_{k:04d}.ply" for k in range(3)]
    v, f = load_mesh(tmp_path / "seq" / "frame_0002.ply")
    assert np.array_equal(f, template.faces) and np.abs(v - V[2]).max() < 1e-5
    code, text = run("animate", template_mesh, "--motion", CLIPS[0], "--frames", frames, "--out", tmp_path / "seq",
                     "--no-ik")
    assert code == 2 and "already exists" in text, text
    # --preserve-volume: every frame has the rest body's volume (LBS loses some), skin moved little
    code, text = run("animate", template_mesh, "--motion", CLIPS[0], "--frames", frames, "--out",
                     tmp_path / "vol_%03d.ply", "--no-ik", "--preserve-volume")
    assert code == 0, text
    rest = capped_volume(template.vertices, template.faces)
    kept = np.array([capped_volume(load_mesh(tmp_path / f"vol_{k:03d}.ply")[0], template.faces) for k in range(3)])
    np.testing.assert_allclose(kept / rest, 1.0, atol=1e-5)                          # float32 on disk
    assert np.abs(capped_volume(V, template.faces) / rest - 1).max() > 1e-3
    for bad, message in ((tmp_path / "walk.ply", "needs a frame field"), (tmp_path / "w_%d_%d.ply", "one frame field"),
                         (tmp_path / "w_%04d.stl", ".ply or .obj")):
        code, text = run("animate", template_mesh, "--motion", CLIPS[0], "--frames", frames, "--out", bad)
        assert code == 2 and message in text and "Traceback" not in text, text


@needs_clips
def test_a_body_asked_of_the_model_walks(semantic_model_file, tmp_path):
    for stature in (155, 190):
        rep = tmp_path / f"r{stature}.json"
        code, text = run("animate", semantic_model_file, "--set", f"stature={stature}cm", "--motion", CLIPS[-1],
                         "--frames", "100:700:6", "--out", tmp_path / f"b{stature}.bvh", "--report", rep)
        assert code == 0, text
        r = json.loads(rep.read_text())
        assert abs(r["body_stature_m"] - stature / 100) < 0.03
        assert r["foot_ik"]["skating"]["share_sliding"] <= r["source"]["skating"]["share_sliding"]
        assert r["foot_ik"]["feet_skin_penetration_m"] < 0.01
    # without --set: the model's mean body
    code, text = run("animate", semantic_model_file, "--motion", CLIPS[-1], "--frames", "100:300:10", "--out",
                     tmp_path / "mean.glb")
    assert code == 0 and "the model's mean body" in text.replace("\n", " "), text
    # the taller body's root path is longer (leg ratio)
    a, b = (json.loads((tmp_path / f"r{s}.json").read_text())["leg_ratio"] for s in (155, 190))
    assert b > a * 1.1


@needs_clips
@pytest.mark.parametrize("args, message", [
    (["--set", "stature=180cm"], "--set asks a model for a body"),
    (["--frames", "5"], "--frames '5': expected START:STOP"),
    (["--frames", "9000:9100"], "the clip has 994 frames"),
    (["--rig", "nope"], "--rig 'nope': not a rig"),
    (["--every", "3"], "--every spaces the --filmstrip panels"),
    (["--preserve-volume"], "--preserve-volume changes the posed meshes"),
])
def test_refusals_are_one_line(template_mesh, tmp_path, args, message):
    code, text = run("animate", template_mesh, "--motion", CLIPS[0], "--out", tmp_path / "x.glb", *args)
    assert code == 2 and message in text and "Traceback" not in text, text


def test_a_mesh_of_another_topology_is_rigged_by_embedding_and_walks(template, phenotype_model, tmp_path):
    """A remeshed body in millimetres, Z up, turned: embedded, bone-heat weighted, animated; the
    sequence comes back in metres, +Y up, standing on the floor, with the mesh's own faces."""
    fb = foreign_body(template, phenotype_model, rng=0, pose="rest", target_vertices=3000)
    save_mesh(tmp_path / "other.obj", fb.vertices, fb.faces)
    clip = tmp_path / "bad.bvh"
    clip.write_text("HIERARCHY\nROOT Hips\n{\n")
    code, text = run("animate", tmp_path / "other.obj", "--motion", clip, "--out", tmp_path / "x.glb")
    assert code == 2 and "bad.bvh" in text and "Traceback" not in text
    if not CLIPS:
        return
    code, text = run("animate", tmp_path / "other.obj", "--motion", CLIPS[0], "--frames", "0:40:4",
                     "--out", tmp_path / "other.npz")
    assert code == 0 and "skeleton embedded" in text, text
    seq = read_mesh_sequence(tmp_path / "other.npz")
    frames, faces = seq[0], seq[1]
    assert frames.shape == (10, len(fb.vertices), 3) and np.array_equal(faces, fb.faces)
    height = np.ptp(frames[0][:, 1])
    assert 1.4 < height < 2.1 and np.isfinite(frames).all()


@needs_clips
def test_a_scan_with_its_floor_walks_without_the_floor(template, tmp_path):
    """A remeshed body on a scanned floor disc 1.6 m wide: the floor is left out (as ``rig`` leaves
    it out) and said, and the body alone walks with its own faces."""
    from floor_meshes import scanner_meshes
    from bodyspace.synth.foreign import foreign_topology, transfer
    topo = foreign_topology(template, 3000, rng=11)
    v = transfer(topo.correspondence, template.faces, np.asarray(template.vertices, float))
    v[:, 1] -= v[:, 1].min()
    mesh_v, mesh_f = scanner_meshes(v, np.asarray(topo.faces))["disc"]
    save_mesh(tmp_path / "on_floor.obj", mesh_v, mesh_f)
    code, text = run("animate", tmp_path / "on_floor.obj", "--motion", CLIPS[0], "--frames", "0:8:4",
                     "--out", tmp_path / "walk.npz")
    assert code == 0 and "left out" in text and "skeleton embedded" in text, text
    frames, faces = read_mesh_sequence(tmp_path / "walk.npz")[:2]
    assert frames.shape == (2, len(v), 3) and np.array_equal(faces, topo.faces)
    assert 1.4 < np.ptp(frames[0][:, 1]) < 2.1 and np.ptp(frames[0][:, 0]) < 1.2      # no 1.6 m disc


# ----------------------------------------------------------------------------- arms and torso

def test_arm_torso_measure_is_zero_at_rest_and_sees_an_arm_in_the_body(template):
    rig = template.rigs["default"]
    sk = body_skeleton(rig, template.vertices)
    landmarks = {"pelvis": "root", "shoulder.L": "upperarm01.L", "shoulder.R": "upperarm01.R",
                 "hip.L": "upperleg01.L", "hip.R": "upperleg01.R", "head": "head"}
    arm, torso = arm_torso_regions(sk, rig.weights, landmarks, template.vertices)
    assert len(arm) > 1000 and len(torso) > 500
    R = np.broadcast_to(np.eye(3), (3, sk.n_bones, 3, 3)).copy()
    # frame 1: arms raised sideways (away from the body); frame 2: the left upper arm swung down,
    # across the front and into the belly
    R[1, sk.bone_index("upperarm01.L")] = rotvec_to_matrix(np.array([0.0, 0.0, 0.6]))
    R[1, sk.bone_index("upperarm01.R")] = rotvec_to_matrix(np.array([0.0, 0.0, -0.6]))
    R[2, sk.bone_index("upperarm01.L")] = rotvec_to_matrix(np.array([0.0, -1.2, 0.0])) @ \
        rotvec_to_matrix(np.array([0.0, 0.0, -0.6]))
    G = forward_kinematics(R, sk.heads, sk.parents)
    posed = linear_blend_skinning(template.vertices, rig.weights, G)
    result = arm_torso_intersections(posed, template.faces, arm, torso)
    assert result.depth[0] == 0.0 and result.depth[1] == 0.0
    assert result.depth[2] > 0.01 and result.frames == 1 and result.worst_frame == 2
