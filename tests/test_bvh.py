"""BVH reading and writing (bodyspace.motion.bvh): the shared CMU clips, every channel order,
translation channels, units, round trips, errors that name the line, and a fuzz of mutated files.

The CMU clips are read where CI lays them (``<repository>/../shared/data/mocap``), else under
``$BODYSPACE_SHARED_DATA``, else ``/work/shared/data``; they are never copied into the repository.
"""

from __future__ import annotations

import os
import signal
import time
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pytest

from bodyspace.errors import MotionError
from bodyspace.motion.bvh import (
    CMU_UNIT,
    Motion,
    MotionSkeleton,
    euler_to_matrix,
    format_bvh,
    matrix_to_euler,
    parse_bvh,
    read_bvh,
    skeleton_from_rig,
    write_bvh,
)
from bodyspace.rig.kinematics import forward_kinematics


def shared_mocap() -> Path:
    here = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "mocap"
    if here.is_dir():
        return here
    return Path(os.environ.get("BODYSPACE_SHARED_DATA", "/work/shared/data")) / "mocap"


MOCAP = shared_mocap()
CLIPS = sorted(MOCAP.glob("*.bvh"))
needs_clips = pytest.mark.skipif(not CLIPS, reason=f"the shared CMU clips are not at {MOCAP}")

SMALL = """HIERARCHY
ROOT Hips
{
\tOFFSET 0 0 0
\tCHANNELS 6 Xposition Yposition Zposition Zrotation Xrotation Yrotation
\tJOINT Chest
\t{
\t\tOFFSET 0 10 0
\t\tCHANNELS 3 Xrotation Yrotation Zrotation
\t\tEnd Site
\t\t{
\t\t\tOFFSET 0 5 0
\t\t}
\t}
\tJOINT Leg
\t{
\t\tOFFSET 2 -1 0
\t\tCHANNELS 6 Xposition Yposition Zposition Yrotation Zrotation Xrotation
\t\tEnd Site
\t\t{
\t\t\tOFFSET 0 -9 1
\t\t}
\t}
}
MOTION
Frames: 3
Frame Time: 0.04
1 90 0 0 0 0 10 20 30 2 -1 0 5 6 7
0 91 1 90 0 0 0 0 0 2 -1 0 0 0 0
-1 92 2 0 90 0 0 0 90 2.5 -1.5 0.5 0 0 90
"""


def plain_values(path: Path) -> np.ndarray:
    """The frame values of a BVH by the plain per-line float() reading (the reference)."""
    lines = path.read_text().splitlines()
    start = next(i for i, line in enumerate(lines) if line.strip().lower().startswith("frame time")) + 1
    return np.array([[float(x) for x in line.split()] for line in lines[start:] if line.strip()])


# ----------------------------------------------------------------------------- reading

@needs_clips
@pytest.mark.parametrize("clip", CLIPS, ids=lambda p: p.name)
def test_cmu_clips_read_exactly(clip):
    m = read_bvh(clip)
    sk = m.skeleton
    assert sk.n_joints == 31 and sk.names[0] == "Hips" and sk.channels[0][:3] == ("Xposition", "Yposition", "Zposition")
    orders = {sk.rotation_order(j) for j in range(sk.n_joints)}
    assert orders == {"ZYX", "ZXY"}  # CMU mixes orders in one file
    assert m.frame_time == pytest.approx(1 / 120, rel=1e-4) and len(sk.end_sites) == 7
    np.testing.assert_array_equal(m.values, plain_values(clip))  # bit for bit, like float()
    assert m.unit == pytest.approx(CMU_UNIT) and m.unit_note.startswith("auto")
    # in metres: hips at an adult's hip height, both feet down on the floor; bones keep their length
    p = m.global_positions()
    assert 0.75 < np.median(p[:, 0, 1]) < 1.05
    toe = p[:, [sk.index("LeftToe"), sk.index("RightToe")], 1]
    assert np.all((toe.min(axis=0) > -0.05) & (toe.min(axis=0) < 0.1))
    knee, ankle = sk.index("LeftKnee"), sk.index("LeftAnkle")
    shin = np.linalg.norm(p[:, knee] - p[:, ankle], axis=1)
    np.testing.assert_allclose(shin, np.linalg.norm(sk.offsets[ankle]) * CMU_UNIT, rtol=1e-9)


@needs_clips
def test_fk_agrees_with_rig_kinematics():
    """Local BVH rotations are rotations in rest-pose world axes about the joint: the project's
    forward_kinematics gives the same positions."""
    m = read_bvh(CLIPS[0]).frames(slice(0, 200))
    R = m.local_rotations()
    rest = m.rest_positions()
    root = m.local_translations()[:, 0] - rest[0]
    G = forward_kinematics(R, rest, m.skeleton.parents, translation=root)
    ours = m.global_positions()
    theirs = np.einsum("fjik,jk->fji", G[..., :3, :3], rest) + G[..., :3, 3]
    np.testing.assert_allclose(ours, theirs, atol=1e-12)


def test_channel_order_and_translations():
    m = parse_bvh(SMALL, "small.bvh", unit="cm")
    sk = m.skeleton
    assert sk.channels[2] == ("Xposition", "Yposition", "Zposition", "Yrotation", "Zrotation", "Xrotation")
    assert m.translation == "replace"  # the Leg's position channels sit at its offset
    R = m.local_rotations()
    E = euler_to_matrix
    np.testing.assert_allclose(R[0, 0], np.eye(3), atol=1e-12)
    # the Chest's X Y Z = (10, 20, 30) means R = Rx(10) Ry(20) Rz(30); the Leg's Y Z X = (5, 6, 7)
    np.testing.assert_allclose(R[0, 1], E([10.0], "X") @ E([20.0], "Y") @ E([30.0], "Z"), atol=1e-12)
    np.testing.assert_allclose(R[0, 2], E([5.0], "Y") @ E([6.0], "Z") @ E([7.0], "X"), atol=1e-12)
    assert not np.allclose(R[0, 1], E([30.0], "Z") @ E([20.0], "Y") @ E([10.0], "X"))
    np.testing.assert_allclose(R[2, 0], E([90.0], "X"), atol=1e-12)
    p = m.global_positions() / 0.01
    np.testing.assert_allclose(p[1, 0], [0, 91, 1])
    # frame 1: root turned 90 degrees about Z: the chest (0, 10, 0) goes to (-10, 0, 0)
    np.testing.assert_allclose(p[1, 1], [-10, 91, 1], atol=1e-9)
    # frame 2: the Leg's translation replaces its offset, rotated by the root's 90 degrees about X
    np.testing.assert_allclose(p[2, 2], [-1 + 2.5, 92 - 0.5, 2 - 1.5], atol=1e-9)
    added = parse_bvh(SMALL.replace("2 -1 0 5 6 7", "0 0 0 5 6 7").replace("2 -1 0 0 0 0", "0 0 0 0 0 0")
                      .replace("2.5 -1.5 0.5", "0.5 -0.5 0.5"), unit="cm")
    assert added.translation == "add"  # values near zero: deltas on top of the offset
    np.testing.assert_allclose(added.global_positions()[2, 2] / 0.01, p[2, 2], atol=1e-9)


@pytest.mark.parametrize("order", ["XYZ", "XZY", "YXZ", "YZX", "ZXY", "ZYX"])
def test_euler_round_trip(order):
    rng = np.random.default_rng(0)
    angles = rng.uniform(-180, 180, (500, 3))
    angles[:50, 1] = rng.choice([-90.0, 90.0], 50)  # gimbal lock
    R = euler_to_matrix(angles, order)
    back = matrix_to_euler(R, order)
    np.testing.assert_allclose(euler_to_matrix(back, order), R, atol=1e-9)
    assert np.all(np.abs(back[:, 1]) <= 90 + 1e-9)


def test_numbers_parse_like_float():
    tokens = ["1e-30", "-0", "+.5", "5.", "123456789012345678901234567890", "0.1", "-2.5E+3", "7e22", "1e23",
              "3.141592653589793238", "0.000000000000000000000001", "-1.7976931348623157e308", "4.9e-324",
              "12.313", "-0.0000", "00012.5000"]
    text = SMALL.split("MOTION")[0] + f"MOTION\nFrames: 1\nFrame Time: 0.1\n{' '.join(tokens[:15])}\n"
    m = parse_bvh(text, unit="m")
    assert m.values.ravel().tolist() == [float(t) for t in tokens[:15]]


def test_units():
    sk = parse_bvh(SMALL).skeleton
    assert parse_bvh(SMALL).unit == CMU_UNIT  # spans 25 units: 1.41 m in CMU's units, the closest to 1.7 m
    true_unit = 1.7 / 25  # metres per unit if this were a 1.7 m skeleton
    from bodyspace.motion.bvh import resolve_unit
    for name, u in (("m", 1.0), ("cm", 0.01), ("mm", 0.001), ("in", 0.0254)):
        k = true_unit / u
        scaled = MotionSkeleton(sk.names, sk.parents, sk.offsets * k, sk.channels, sk.end_sites * k, sk.end_site_parents)
        unit, note = resolve_unit("auto", scaled)
        assert unit == u and f"in {name} " in note, note
    assert parse_bvh(SMALL, unit="in").unit == 0.0254
    assert parse_bvh(SMALL, unit=0.5).unit == 0.5
    for bad in ("furlong", "-1", "0", "nan"):
        with pytest.raises(MotionError, match="unit"):
            parse_bvh(SMALL, unit=bad)


# ----------------------------------------------------------------------------- writing

@needs_clips
@pytest.mark.parametrize("clip", CLIPS, ids=lambda p: p.name)
def test_round_trip_keeps_everything(clip, tmp_path):
    m = read_bvh(clip)
    out = write_bvh(tmp_path / "out.bvh", m, precision=6)
    back = read_bvh(out, unit=m.unit)
    a, b = m.skeleton, back.skeleton
    assert a.names == b.names and a.channels == b.channels
    np.testing.assert_array_equal(a.parents, b.parents)
    np.testing.assert_array_equal(a.offsets, b.offsets)
    np.testing.assert_array_equal(a.end_sites, b.end_sites)
    np.testing.assert_array_equal(a.end_site_parents, b.end_site_parents)
    np.testing.assert_array_equal(m.values, back.values)  # the file has at most 6 decimals: exact
    assert back.frame_time == m.frame_time and back.n_frames == m.n_frames
    coarse = read_bvh(write_bvh(tmp_path / "coarse.bvh", m, precision=2))
    assert np.abs(coarse.values - m.values).max() <= 0.005 + 1e-12
    again = read_bvh(write_bvh(tmp_path / "again.bvh", coarse, precision=2))
    np.testing.assert_array_equal(again.values, coarse.values)  # stable once rounded


def test_round_trip_of_rotations(tmp_path):
    sk = parse_bvh(SMALL).skeleton
    rng = np.random.default_rng(3)
    from bodyspace.rig.kinematics import rotvec_to_matrix
    R = rotvec_to_matrix(rng.normal(0, 1.0, (20, 3, 3)))
    t = rng.normal(0, 5, (20, 3, 3))
    m = Motion.from_rotations(sk, R, t, frame_time=0.05, unit=0.01)
    np.testing.assert_allclose(m.local_rotations(), R, atol=1e-12)
    back = read_bvh(write_bvh(tmp_path / "r.bvh", m, precision=10), unit=0.01, translation="replace")
    np.testing.assert_allclose(back.local_rotations(), R, atol=1e-9)
    np.testing.assert_allclose(back.local_translations()[:, 2], t[:, 2] * 0.01, atol=1e-11)


def test_rig_skeleton_as_bvh(template, tmp_path):
    """A rig's skeleton written as a BVH rest pose: joints at the bone heads, End Sites at the
    tails of end bones, the same hierarchy."""
    from bodyspace.rig.skeleton import body_skeleton
    sk = body_skeleton(template.rigs["game_engine"], template.vertices)
    motion = skeleton_from_rig(sk, frames=2)
    back = read_bvh(write_bvh(tmp_path / "rig.bvh", motion, precision=9), unit="m")
    order = [back.skeleton.index(n) for n in sk.bone_names]
    np.testing.assert_allclose(back.rest_positions()[order], sk.heads, atol=1e-6)
    parents = [back.skeleton.names[p] if p >= 0 else None for p in back.skeleton.parents]
    assert [parents[i] for i in order] == [sk.bone_names[p] if p >= 0 else None for p in sk.parents]
    leaves = [b for b in range(sk.n_bones) if b not in set(sk.parents)]
    ends = back.skeleton.rest_end_sites()
    assert len(ends) == len(leaves)
    np.testing.assert_allclose(np.sort(ends, axis=0), np.sort(sk.tails[leaves], axis=0), atol=1e-6)


# ----------------------------------------------------------------------------- bad files

HEADER, FRAMES = SMALL.split("MOTION\n")
BAD = {
    "empty": ("", "line 1: found an empty file; expected the keyword HIERARCHY"),
    "not bvh": ("solid cube\nfacet normal 0 0 1\n", "line 1: found 'solid cube'; expected the keyword HIERARCHY"),
    "truncated hierarchy": (SMALL[:SMALL.index("\tJOINT Leg")], "line 14: the file ends inside joint 'Hips'; expected '}'"),
    "truncated frames": (SMALL[:SMALL.rindex("\n-1 92")] + "\n", "line 29: the file ends after 2 frame lines; "
                         "Frames: declares 3"),
    "cut frame line": (SMALL[:-12] + "\n", "line 30: frame 3 has 11 values; expected 15"),
    "too many values": (SMALL.replace("0 0 0 0\n-1 92", "0 0 0 0 0\n-1 92", 1), "line 29: frame 2 has 16 values; "
                        "expected 15"),
    "wrong channel count": (SMALL.replace("CHANNELS 3 Xrotation Yrotation Zrotation", "CHANNELS 4 Xrotation "
                            "Yrotation Zrotation"), "line 9: CHANNELS 4 is followed by 3 channel names"),
    "too many channel names": (SMALL.replace("CHANNELS 3 Xrotation", "CHANNELS 2 Xrotation"),
                               "line 9: CHANNELS 2 is followed by 3 channel names"),
    "bad channel": (SMALL.replace("Yrotation Zrotation\n", "Yrotation Wrotation\n", 1), "line 9: channel "
                    "'Wrotation' of joint 'Chest'; expected one of"),
    "repeated channel": (SMALL.replace("Xrotation Yrotation Zrotation", "Xrotation Xrotation Zrotation"),
                         "line 9: joint 'Chest' lists a channel twice"),
    "non-number": (SMALL.replace("-1 92 2", "-1 9,2 2"), "line 30: '9,2' is not a number (frame 3)"),
    "nan value": (SMALL.replace("-1 92 2", "-1 nan 2"), "line 30: 'nan' is not a number"),
    "inf offset": (SMALL.replace("OFFSET 0 10 0", "OFFSET 0 inf 0"), "line 8: OFFSET: 'inf' is not finite"),
    "short offset": (SMALL.replace("OFFSET 0 10 0", "OFFSET 0 10"), "line 8: OFFSET with 2 values; expected "
                     "OFFSET x y z"),
    "10^7 frames declared": (SMALL.replace("Frames: 3", "Frames: 10000000"), "the file ends after 3 frame lines; "
                             "Frames: declares 10000000"),
    "extra frames": (SMALL.replace("Frames: 3", "Frames: 2"), "line 30: frame line 3 found; Frames: declares 2"),
    "negative frames": (SMALL.replace("Frames: 3", "Frames: -3"), "line 26: Frames: -3; expected a count >= 0"),
    "no frame time": (SMALL.replace("Frame Time: 0.04\n", ""), "line 27: found '1 90 0 0 0 0 10 20 30 2 -1 0 5 6 "),
    "zero frame time": (SMALL.replace("Frame Time: 0.04", "Frame Time: 0"), "line 27: Frame Time: '0'; expected a "
                        "positive number of seconds"),
    "repeated name (a cycle)": (SMALL.replace("JOINT Leg", "JOINT Chest"), "line 15: joint name 'Chest' already "
                                "used on line 6"),
    "unbalanced close": (SMALL.replace("MOTION", "}\nMOTION"), "line 25: found '}' with no open block"),
    "missing close": (SMALL.replace("\t}\n}\nMOTION", "\t}\nMOTION"), "line 24: MOTION while joint 'Hips' is still "
                      "open"),
    "missing brace": (SMALL.replace("JOINT Chest\n\t{", "JOINT Chest\n"), "line 8: found 'OFFSET' after joint "
                      "'Chest'; expected '{'"),
    "joint outside root": (SMALL.replace("ROOT Hips", "JOINT Hips"), "line 2: JOINT Hips outside any ROOT"),
    "no offset": (SMALL.replace("\t\t\tOFFSET 0 5 0\n", ""), "line 12: an End Site closes without an OFFSET"),
    "no channels": (SMALL.replace("\t\tCHANNELS 3 Xrotation Yrotation Zrotation\n", ""),
                    "line 13: joint 'Chest' closes without CHANNELS"),
    "channels count word": (SMALL.replace("CHANNELS 3 X", "CHANNELS three X"), "line 9: CHANNELS count 'three'"),
    "seven channels": (SMALL.replace("CHANNELS 3 X", "CHANNELS 7 X"), "line 9: CHANNELS 7; expected 0 to 6"),
    "end site in end site": (SMALL.replace("\t\t\tOFFSET 0 5 0\n", "\t\t\tOFFSET 0 5 0\nEnd Site\n{\nOFFSET 1 1 1\n}\n"),
                             "line 13: End Site inside an End Site"),
    "no motion": (HEADER, "the file ends after the hierarchy; expected MOTION"),
}


@pytest.mark.parametrize("case", BAD, ids=list(BAD))
def test_bad_files_name_the_line(case, tmp_path):
    text, message = BAD[case]
    path = tmp_path / "clip.bvh"
    path.write_text(text)
    with pytest.raises(MotionError) as err:
        read_bvh(path)
    assert str(err.value).startswith(f"{path} "), str(err.value)
    assert message in str(err.value), str(err.value)


def test_missing_file_and_folder(tmp_path):
    with pytest.raises(MotionError, match="no such file"):
        read_bvh(tmp_path / "nope.bvh")
    with pytest.raises(MotionError, match="is a folder"):
        read_bvh(tmp_path)


# ----------------------------------------------------------------------------- fuzz

@contextmanager
def time_limit(seconds: float):
    def stop(signum, frame):
        raise TimeoutError(f"parsing took more than {seconds} s")
    old = signal.signal(signal.SIGALRM, stop)
    signal.setitimer(signal.ITIMER_REAL, seconds)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, old)


def mutations(base: bytes, n: int, seed: int = 0):
    """``n`` mutated copies of a BVH file: truncations, dropped/doubled/swapped lines, tokens
    replaced by junk, numbers changed, random bytes; deterministic."""
    rng = np.random.default_rng(seed)
    lines = base.split(b"\n")
    junk = [b"", b"{", b"}", b"nan", b"inf", b"-", b"1e999", b"ROOT", b"JOINT x", b"End Site", b"OFFSET",
            b"CHANNELS 3", b"CHANNELS 99", b"MOTION", b"Frames: 99999999", b"Frame Time: -1", b"\x00\xff",
            b"0x10", b"1,5", b"Xrotation", b"\t", b"1" * 400, b"HIERARCHY"]
    for k in range(n):
        kind = k % 8
        out = list(lines)
        if kind == 0:
            yield base[:int(rng.integers(0, len(base)))]
            continue
        if kind == 1:
            del out[int(rng.integers(0, len(out)))]
        elif kind == 2:
            i = int(rng.integers(0, len(out)))
            out.insert(i, out[i])
        elif kind == 3:
            i, j = rng.integers(0, len(out), 2)
            out[i], out[j] = out[j], out[i]
        elif kind in (4, 5):
            i = int(rng.integers(0, len(out)))
            toks = out[i].split()
            if toks:
                toks[int(rng.integers(0, len(toks)))] = junk[int(rng.integers(0, len(junk)))]
            out[i] = b" ".join(toks)
        elif kind == 6:
            i = int(rng.integers(0, len(out)))
            out[i] = out[i] + b" " + junk[int(rng.integers(0, len(junk)))]
        else:
            b = bytearray(base)
            for _ in range(int(rng.integers(1, 5))):
                b[int(rng.integers(0, len(b)))] = int(rng.integers(0, 256))
            yield bytes(b)
            continue
        yield b"\n".join(out)


@needs_clips
def test_fuzz_mutated_files_never_traceback_or_hang():
    """1,200 mutated files: each parses to a valid motion or raises MotionError, within 2 s."""
    m = read_bvh(CLIPS[0]).frames(slice(0, 12))
    base = format_bvh(m, precision=4).encode()
    outcomes = {"ok": 0, "refused": 0}
    slowest = 0.0
    for k, data in enumerate(mutations(base, 1200)):
        t = time.perf_counter()
        with time_limit(2.0):
            try:
                got = parse_bvh(data, f"case{k}.bvh")
            except MotionError as exc:
                assert f"case{k}.bvh" in str(exc) or "unit" in str(exc), str(exc)
                outcomes["refused"] += 1
            else:
                assert np.isfinite(got.values).all() and got.values.shape[1] == got.skeleton.n_channels
                outcomes["ok"] += 1
        slowest = max(slowest, time.perf_counter() - t)
    assert outcomes["refused"] > 600 and outcomes["ok"] > 50, outcomes


def test_byte_order_mark_and_many_long_numbers(monkeypatch):
    assert parse_bvh(b"\xef\xbb\xbf" + SMALL.encode()).n_frames == 3
    import bodyspace.motion.bvh as bvh
    monkeypatch.setattr(bvh, "_SLOW_TOKENS", 2)  # more long numbers than the scanner's buffer holds
    rng = np.random.default_rng(5)
    numbers = [repr(float(x)) + "1234" for x in rng.normal(0, 100, 45)]  # 17+ significant digits
    text = HEADER + "MOTION\nFrames: 3\nFrame Time: 0.04\n" + "\n".join(
        " ".join(numbers[15 * f:15 * f + 15]) for f in range(3)) + "\n"
    m = parse_bvh(text)
    assert m.values.ravel().tolist() == [float(t) for t in numbers]
