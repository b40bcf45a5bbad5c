"""Skeleton matching (bodyspace.motion.matching, Rupprecht §3.3.2): the shared CMU clips onto all
six CC0 rigs, and the same clips renamed (nonsense, MotionBuilder, Mixamo names) and restructured
(joints merged, split, an extra spine joint, missing toes, Z-up in millimetres), written to BVH
files and read back; BVH to BVH; the map file; the report."""

from __future__ import annotations

import json

import numpy as np
import pytest
from test_bvh import CLIPS, needs_clips

from bodyspace.data.template import RIG_NAMES
from bodyspace.errors import MotionError
from bodyspace.motion.bvh import Motion, MotionSkeleton, read_bvh, write_bvh
from bodyspace.motion.matching import (
    body_anatomy,
    graph_from_motion,
    load_joint_map,
    match_skeletons,
    name_roles,
    rig_graph,
)

pytestmark = needs_clips

# The CMU joint each rig's bone should be driven by (landmarks; the thumbs matched by direction).
KEYS = ["Hips", "LeftHip", "LeftKnee", "LeftAnkle", "LeftToe", "RightHip", "RightKnee", "RightAnkle", "RightToe",
        "Chest2", "Head", "LeftCollar", "LeftShoulder", "LeftElbow", "LeftWrist", "RightCollar", "RightShoulder",
        "RightElbow", "RightWrist", "LThumb", "RThumb"]


def _side(bones: str) -> list[str]:
    return bones.split()


DEFAULT = _side("root upperleg01.L lowerleg01.L foot.L toe1-1.L upperleg01.R lowerleg01.R foot.R toe1-1.R spine01 head "
                "clavicle.L upperarm01.L lowerarm01.L wrist.L clavicle.R upperarm01.R lowerarm01.R wrist.R finger1-1.L "
                "finger1-1.R")
GAME = _side("pelvis thigh_l calf_l foot_l ball_l thigh_r calf_r foot_r ball_r spine_03 head clavicle_l upperarm_l "
             "lowerarm_l hand_l clavicle_r upperarm_r lowerarm_r hand_r thumb_01_l thumb_01_r")
CMU_MB = _side("Hips LeftUpLeg LeftLeg LeftFoot LeftToeBase RightUpLeg RightLeg RightFoot RightToeBase Spine1 Head "
               "LeftShoulder LeftArm LeftForeArm LeftHand RightShoulder RightArm RightForeArm RightHand LThumb RThumb")
MIXAMO = ["mixamorig:" + b for b in _side(
    "Hips LeftUpLeg LeftLeg LeftFoot LeftToeBase RightUpLeg RightLeg RightFoot RightToeBase Spine2 Head LeftShoulder "
    "LeftArm LeftForeArm LeftHand RightShoulder RightArm RightForeArm RightHand LeftHandThumb1 RightHandThumb1")]
EXPECTED = {"default": DEFAULT, "default_no_toes": DEFAULT, "game_engine": GAME, "game_engine_with_breast": GAME,
            "cmu_mb": CMU_MB, "mixamo": MIXAMO}

MOTIONBUILDER = {"LeftHip": "LeftUpLeg", "LeftKnee": "LeftLeg", "LeftAnkle": "LeftFoot", "LeftToe": "LeftToeBase",
                 "RightHip": "RightUpLeg", "RightKnee": "RightLeg", "RightAnkle": "RightFoot",
                 "RightToe": "RightToeBase", "lowerback": "LowerBack", "Chest": "Spine", "Chest2": "Spine1",
                 "lowerneck": "Neck", "Neck": "Neck1", "LeftCollar": "LeftShoulder", "LeftShoulder": "LeftArm",
                 "LeftElbow": "LeftForeArm", "LeftWrist": "LeftHand", "lhand": "LeftFingerBase",
                 "LFingers": "LeftHandFinger1", "RightCollar": "RightShoulder", "RightShoulder": "RightArm",
                 "RightElbow": "RightForeArm", "RightWrist": "RightHand", "rhand": "RightFingerBase",
                 "RFingers": "RightHandFinger1"}
MIXAMO_NAMES = {k: "mixamorig:" + v for k, v in {
    "Hips": "Hips", "LeftHip": "LeftUpLeg", "LeftKnee": "LeftLeg", "LeftAnkle": "LeftFoot", "LeftToe": "LeftToeBase",
    "RightHip": "RightUpLeg", "RightKnee": "RightLeg", "RightAnkle": "RightFoot", "RightToe": "RightToeBase",
    "lowerback": "Spine", "Chest": "Spine1", "Chest2": "Spine2", "Neck": "Neck", "Head": "Head",
    "LeftCollar": "LeftShoulder", "LeftShoulder": "LeftArm", "LeftElbow": "LeftForeArm", "LeftWrist": "LeftHand",
    "LFingers": "LeftHandMiddle1", "LThumb": "LeftHandThumb1", "RightCollar": "RightShoulder",
    "RightShoulder": "RightArm", "RightElbow": "RightForeArm", "RightWrist": "RightHand",
    "RFingers": "RightHandMiddle1", "RThumb": "RightHandThumb1"}.items()}


# ----------------------------------------------------------------------------- clip variants

def edit(motion: Motion, remove=(), insert=(), rename=None, transform=None, scale=1.0) -> Motion:
    """The clip with joints removed (children and End Sites re-attached to the parent; a removed
    end joint leaves an End Site where it was), joints inserted (``(new, child, fraction)``: a
    joint on the bone into ``child``, ``fraction`` of the way), renamed, and the whole skeleton
    turned by ``transform`` (3x3) and scaled."""
    sk = motion.skeleton
    names, parents = list(sk.names), [int(p) for p in sk.parents]
    offsets = [np.array(o) for o in sk.offsets]
    channels = list(sk.channels)
    ends = [(int(p), np.array(e)) for p, e in zip(sk.end_site_parents, sk.end_sites)]
    cols = [list(range(s, s + len(c))) for s, c in zip(sk.channel_starts, sk.channels)]
    values = [motion.values[:, c] for c in cols]
    for name in remove:
        r = names.index(name)
        p = parents[r]
        kids = [j for j, q in enumerate(parents) if q == r]
        for j in kids:
            parents[j] = p
            offsets[j] = offsets[j] + offsets[r]
        own = [e for e in ends if e[0] == r]
        ends = [e for e in ends if e[0] != r] + ([(p, offsets[r] + e[1]) for e in own] if kids else [(p, offsets[r])])
        for lst in (names, offsets, channels, values):
            del lst[r]
        del parents[r]
        parents = [q - (q > r) for q in parents]
        ends = [(q - (q > r), e) for q, e in ends]
    for new, child, fraction in insert:
        c = names.index(child)
        names.insert(c, new)
        parents = [q + (q >= c) for q in parents]
        parents.insert(c, parents[c])          # the child's old parent (already shifted)
        parents[c + 1] = c
        offsets.insert(c, fraction * offsets[c])
        offsets[c + 1] = (1 - fraction) * offsets[c + 1]
        channels.insert(c, ("Zrotation", "Yrotation", "Xrotation"))
        values.insert(c, np.zeros((motion.n_frames, 3)))
        ends = [(q + (q >= c), e) for q, e in ends]
    T = np.eye(3) if transform is None else np.asarray(transform)
    order = np.argsort([q for q, _ in ends], kind="stable")
    skeleton = MotionSkeleton(tuple((rename or {}).get(n, n) for n in names), np.array(parents),
                              np.array(offsets) @ T.T * scale, tuple(channels),
                              np.array([ends[i][1] for i in order]).reshape(-1, 3) @ T.T * scale,
                              np.array([ends[i][0] for i in order], dtype=np.int64))
    return Motion(skeleton, np.hstack(values), motion.frame_time, motion.unit / scale, "given", motion.translation,
                  motion.name)


@pytest.fixture(scope="session")
def clips():
    return {c.name: read_bvh(c).frames(slice(0, 10)) for c in CLIPS}


@pytest.fixture(scope="session")
def rigs():
    return {r: body_anatomy(rig_graph(r)) for r in RIG_NAMES}


def through_file(motion: Motion, tmp_path, name: str) -> Motion:
    """Write the variant as a BVH and read it back (unit found again by the reader)."""
    return read_bvh(write_bvh(tmp_path / f"{name}.bvh", motion), unit="auto")


def check_landmarks(result, rig: str, rename=None, missing=()):
    rename = rename or {}
    for key, bone in zip(KEYS, EXPECTED[rig]):
        if key in missing:
            continue
        assert result.mapping.get(rename.get(key, key)) == bone, (rig, key, result.report())


# ----------------------------------------------------------------------------- the clips as they are

@pytest.mark.parametrize("rig", RIG_NAMES)
def test_cmu_clips_onto_every_rig(clips, rigs, rig):
    for name, motion in clips.items():
        result = match_skeletons(graph_from_motion(motion), rigs[rig])
        check_landmarks(result, rig)
        assert result.source_landmarks["knee.L"] == "LeftKnee" and result.source_landmarks["wrist.R"] == "RightWrist"
        assert [tuple(a) for a in result.source_axes] == [(0, 1, 0), (1, 0, 0), (0, 0, 1)]
        # every source joint is either matched or explained; every pair's parent pair is above it
        matched = set(result.mapping)
        assert matched | {j for j, _ in result.unmatched_source} == set(motion.skeleton.names)
        assert all(why for _, why in result.unmatched_source + result.unmatched_target)
        assert not [w for w in result.warnings if "crossed" in w], result.warnings


def test_rigs_match_themselves(rigs):
    for rig, anatomy in rigs.items():
        result = match_skeletons(anatomy, anatomy)
        assert result.mapping == {n: n for n in anatomy.graph.names}, rig


def test_segments_spread_one_joint_over_several_bones(clips, rigs):
    result = match_skeletons(graph_from_motion(next(iter(clips.values()))), rigs["default"])
    seg = {s.child: s for s in result.segments}
    spine = seg[("Chest", "spine02")]
    assert spine.parent == ("lowerback", "spine05") and spine.source == () and spine.target == ("spine04", "spine03")
    knee = seg[("LeftKnee", "lowerleg01.L")]
    assert knee.parent == ("LeftHip", "upperleg01.L") and knee.target == ("upperleg02.L",)
    root = seg[("Hips", "root")]
    assert root.parent is None
    assert result.target_landmarks["ankle.L"] == "foot.L" and result.source_landmarks["toe.R"] == "RightToe"


# ----------------------------------------------------------------------------- renamed

def nonsense(motion: Motion) -> dict[str, str]:
    rng = np.random.default_rng(7)
    names = list(motion.skeleton.names)
    return {n: f"j{k:02d}" for n, k in zip(names, rng.permutation(len(names)))}


@pytest.mark.parametrize("naming", ["nonsense", "motionbuilder", "mixamo"])
def test_renamed_clips_match_the_same(clips, rigs, naming, tmp_path):
    for name, motion in clips.items():
        rename = {"nonsense": nonsense(motion), "motionbuilder": MOTIONBUILDER, "mixamo": MIXAMO_NAMES}[naming]
        renamed = through_file(edit(motion, rename=rename), tmp_path, f"{naming}-{name}")
        original = graph_from_motion(motion)
        for rig in ("default", "game_engine", "mixamo", "cmu_mb"):
            before = match_skeletons(original, rigs[rig]).mapping
            after = match_skeletons(graph_from_motion(renamed), rigs[rig]).mapping
            assert after == {rename.get(s, s): t for s, t in before.items()}, (naming, rig)
    if naming == "motionbuilder":  # names and structure agree: matched to the rig of those names, one to one
        result = match_skeletons(graph_from_motion(renamed), rigs["cmu_mb"])
        assert result.mapping == {n: n for n in renamed.skeleton.names} and not result.warnings


def test_names_only_label_and_warn(clips, rigs):
    """A clip whose names lie (left and right swapped) still matches by structure, with warnings."""
    motion = next(iter(clips.values()))
    swap = {n: n.replace("Left", "Tmp").replace("Right", "Left").replace("Tmp", "Right") for n in motion.skeleton.names}
    result = match_skeletons(graph_from_motion(edit(motion, rename=swap)), rigs["cmu_mb"])
    assert result.mapping["RightKnee"] == "LeftLeg"  # the joint that is on the left
    assert any("usually means knee.R" in w for w in result.warnings)
    assert name_roles("mixamorig:LeftForeArm") == {"elbow.L"} and name_roles("j07") == set()


# ----------------------------------------------------------------------------- restructured

RESTRUCTURED = {
    "merged": dict(remove=["LHipJoint", "RHipJoint", "lhand", "rhand"]),
    "split": dict(insert=[("LeftThighTwist", "LeftKnee", 0.5), ("RightForeArmTwist", "RightWrist", 0.5),
                          ("Chest1b", "Chest2", 0.5)]),
    "missing_toes": dict(remove=["LeftToe", "RightToe"]),
    "zup_mm": dict(transform=[[1, 0, 0], [0, 0, -1], [0, 1, 0]], scale=56.444),
}


@pytest.mark.parametrize("variant", RESTRUCTURED)
def test_restructured_clips(clips, rigs, variant, tmp_path):
    spec = RESTRUCTURED[variant]
    for name, motion in clips.items():
        changed = through_file(edit(motion, **spec), tmp_path, f"{variant}-{name}")
        if variant == "zup_mm":
            assert changed.unit == 0.001  # read back as millimetres by the size heuristic
        graph = graph_from_motion(changed)
        for rig in RIG_NAMES:
            result = match_skeletons(graph, rigs[rig])
            check_landmarks(result, rig, missing=spec.get("remove", ()))
            added = {n for n, *_ in spec.get("insert", ())}
            landmark_bones = set(EXPECTED[rig])
            assert not [a for a in added if result.mapping.get(a) in landmark_bones], (rig, result.report())
            if variant == "missing_toes":
                toes = {EXPECTED[rig][4], EXPECTED[rig][8]}
                assert not toes & set(result.mapping.values())
            if variant == "zup_mm":
                assert [tuple(a) for a in result.source_axes] == [(0, 0, 1), (1, 0, 0), (0, -1, 0)]


def test_bvh_to_bvh(clips, tmp_path):
    """A clip onto a restructured copy of itself: every joint both have maps to itself."""
    motion = next(iter(clips.values()))
    for variant, spec in RESTRUCTURED.items():
        other = through_file(edit(motion, **spec), tmp_path, variant)
        result = match_skeletons(graph_from_motion(motion), graph_from_motion(other))
        common = set(motion.skeleton.names) & set(other.skeleton.names)
        wrong = {s: t for s, t in result.mapping.items() if s in common and t != s}
        assert not wrong, (variant, wrong, result.report())
        if variant in ("zup_mm", "split"):
            assert set(result.mapping) == set(motion.skeleton.names)


# ----------------------------------------------------------------------------- map file, errors, report

def test_map_file_overrides(clips, rigs, tmp_path):
    motion = next(iter(clips.values()))
    graph = graph_from_motion(motion)
    path = tmp_path / "map.json"
    path.write_text(json.dumps({"LeftShoulder": "shoulder01.L", "Neck": None}))
    result = match_skeletons(graph, rigs["default"], load_joint_map(path, graph, rigs["default"].graph))
    assert result.mapping["LeftShoulder"] == "shoulder01.L" and "Neck" not in result.mapping
    assert "upperarm01.L" not in result.mapping.values()
    assert [p.part for p in result.pairs if p.source == "LeftShoulder"] == ["map file"]
    bad = {"unknown joint": ({"Elbow": "head"}, "'Elbow' is not a joint of the source skeleton"),
           "unknown bone": ({"Head": "skull"}, "maps to 'skull', not a bone of the target"),
           "twice": ({"Head": "head", "Neck": "head"}, "both map to 'head'"),
           "not a name": ({"Head": 3}, "maps to 3; expected a target bone name or null"),
           "list": ([1, 2], "a JSON list; expected an object")}
    for case, (data, message) in bad.items():
        path.write_text(json.dumps(data))
        with pytest.raises(MotionError, match=str(path)) as err:
            load_joint_map(path, graph, rigs["default"].graph)
        assert message in str(err.value), case
    path.write_text("{not json")
    with pytest.raises(MotionError, match="not valid JSON"):
        load_joint_map(path)


def test_too_simple_skeletons_are_refused(tmp_path):
    text = ("HIERARCHY\nROOT a\n{\nOFFSET 0 0 0\nCHANNELS 3 Zrotation Xrotation Yrotation\nJOINT b\n{\nOFFSET 0 1 0\n"
            "CHANNELS 3 Zrotation Xrotation Yrotation\nEnd Site\n{\nOFFSET 0 1 0\n}\n}\n}\nMOTION\nFrames: 1\n"
            "Frame Time: 0.1\n0 0 0 0 0 0\n")
    path = tmp_path / "stick.bvh"
    path.write_text(text)
    with pytest.raises(MotionError, match="1 end joints; a body needs at least five"):
        match_skeletons(graph_from_motion(read_bvh(path)), rig_graph("mixamo"))


def test_report_says_what_and_why(clips, rigs):
    result = match_skeletons(graph_from_motion(next(iter(clips.values()))), rigs["game_engine"])
    text = result.report()
    assert "LeftKnee" in text and "calf_l [knee.L]" in text and "unmatched source joints:" in text
    assert "LHipJoint:" in text and "Root: a root with no counterpart in the source" in text
    data = json.loads(json.dumps(result.to_dict()))
    assert data["landmarks"]["target"]["wrist.L"] == "hand_l" and data["axes"]["source"]["up"] == [0, 1, 0]


# ----------------------------------------------------------------------------- command line

def test_cli_info_and_match(tmp_path):
    from typer.testing import CliRunner

    from bodyspace.cli import app
    runner = CliRunner()
    clip = str(CLIPS[0])
    res = runner.invoke(app, ["motion", "info", clip])
    assert res.exit_code == 0 and "rotation orders:      ZYX x19, ZXY x12" in res.output
    assert "120 per second" in res.output and "cmu" in res.output
    out = tmp_path / "match.json"
    res = runner.invoke(app, ["motion", "match", clip, "--rig", "game_engine", "--json", str(out)])
    assert res.exit_code == 0 and "LeftKnee      -> calf_l [knee.L]" in res.output
    data = json.loads(out.read_text())
    assert data["written_by"] == "bodyspace" and {"pairs", "unmatched_source", "segments"} <= set(data)
    res = runner.invoke(app, ["motion", "match", clip, "--target", clip, "--json", str(out), "--force"])
    assert res.exit_code == 0 and "31 pairs, 0 source joints" in res.output
    mapfile = tmp_path / "map.json"
    mapfile.write_text(json.dumps({"Head": "nothing"}))
    bad = {("motion", "match", clip): "give one target: --rig NAME",
           ("motion", "match", clip, "--rig", "robot"): "--rig 'robot': not a CC0 rig",
           ("motion", "match", clip, "--rig", "mixamo", "--json", str(out)): "already exists; pass --force",
           ("motion", "match", clip, "--rig", "mixamo", "--map", str(mapfile)): "maps to 'nothing', not a bone",
           ("motion", "info", str(tmp_path / "none.bvh")): "no such file",
           ("motion", "info", clip, "--bvh-unit", "furlong"): "unit 'furlong': expected auto, one of m, dm"}
    for args, message in bad.items():
        res = runner.invoke(app, list(args))
        assert res.exit_code == 2 and message in res.output and "Traceback" not in res.output, (args, res.output)


def test_other_bodies_turned_and_moved(clips, phenotype_model, template):
    """The rigs regressed on a tall heavy body and on a small light one, and a target skeleton
    turned to face +X and moved: the same landmark bones."""
    from bodyspace.motion.matching import JointGraph
    from bodyspace.synth.phenotype import PARAMETERS
    source = graph_from_motion(next(iter(clips.values())))
    params = np.full((2, len(PARAMETERS)), 0.5)
    params[0] = 0.95
    params[1] = 0.05
    bodies = phenotype_model.vertices(params)
    turn = np.array([[0.0, 0, 1], [0, 1, 0], [-1, 0, 0]])  # +Z front becomes +X front
    for body in bodies:
        for rig in ("default", "mixamo"):
            g = rig_graph(rig, body)
            check_landmarks(match_skeletons(source, g), rig)
            moved = JointGraph(g.name, g.names, g.parents, g.pivots @ turn.T + [3.0, -1.0, 2.0],
                               g.tips @ turn.T + [3.0, -1.0, 2.0])
            result = match_skeletons(source, moved)
            check_landmarks(result, rig)
            assert [tuple(a) for a in result.target_axes] == [(0, 1, 0), (0, 0, -1), (1, 0, 0)]
