"""Reading a 10,000-frame BVH clip: the compiled number scanner against a plain per-line float() parser.

The clip is the shared CMU walk (131_01.bvh, 994 frames, 96 channels) repeated to 10,000 frames
(960,000 numbers, 6 MB); without the shared data a synthetic clip of the same size is used.
Run: python benchmarks/bench_bvh.py
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import best_time, report  # noqa: E402

from bodyspace.motion.bvh import format_bvh, parse_bvh, read_bvh  # noqa: E402

FRAMES = 10_000


def clip_text() -> bytes:
    roots = [Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "mocap",
             Path(os.environ.get("BODYSPACE_SHARED_DATA", "/work/shared/data")) / "mocap"]
    path = next((r / "131_01.bvh" for r in roots if (r / "131_01.bvh").is_file()), None)
    if path is None:
        rng = np.random.default_rng(0)
        head = "HIERARCHY\nROOT a\n{\nOFFSET 0 0 0\nCHANNELS 6 Xposition Yposition Zposition Zrotation Yrotation Xrotation\n"
        head += "".join(f"JOINT j{k}\n{{\nOFFSET 0 1 0\nCHANNELS 3 Zrotation Yrotation Xrotation\n" for k in range(30))
        head += "End Site\n{\nOFFSET 0 1 0\n}\n" + "}\n" * 31
        rows = "\n".join(" ".join(f"{v:.4f}" for v in r) for r in rng.normal(0, 30, (FRAMES, 96)))
        return (head + f"MOTION\nFrames: {FRAMES}\nFrame Time: .0083333\n{rows}\n").encode()
    text = path.read_bytes()
    header, body = text.split(b"Frame Time:", 1)
    rows = body.split(b"\n", 1)[1].strip().split(b"\n")
    rows = (rows * (FRAMES // len(rows) + 1))[:FRAMES]
    header = header.replace(header[header.index(b"Frames:"):], f"Frames: {FRAMES}\n".encode())
    return header + b"Frame Time: .0083333\n" + b"\n".join(rows) + b"\n"


def plain_parse(data: bytes) -> np.ndarray:
    """The baseline: what a plain reader does (pymotion-style), one float() per token, line by line."""
    lines = data.decode().splitlines()
    start = next(i for i, line in enumerate(lines) if line.startswith("Frame Time")) + 1
    return np.array([[float(x) for x in line.split()] for line in lines[start:] if line.strip()])


def main() -> None:
    data = clip_text()
    parse_bvh(data[:data.index(b"\n", data.index(b"Frame Time")) + 1].replace(
        f"Frames: {FRAMES}".encode(), b"Frames: 0"))  # compile the scanner outside the timing
    motion = parse_bvh(data, "bench.bvh")
    np.testing.assert_array_equal(motion.values, plain_parse(data))
    fast = best_time(lambda: parse_bvh(data, "bench.bvh"))
    slow = best_time(lambda: plain_parse(data), repeat=2)
    n = motion.values.size
    print(f"{motion.n_frames} frames x {motion.values.shape[1]} channels ({len(data) / 1e6:.1f} MB): "
          f"parse_bvh {fast:.3f} s, plain float() {slow:.3f} s")
    report("read BVH", fast, slow, n, "numbers")
    fk = best_time(lambda: motion.global_positions(), repeat=2)
    print(f"global positions (FK) of all {motion.n_frames} frames: {fk:.3f} s")
    w = best_time(lambda: format_bvh(motion, precision=4), repeat=1)
    print(f"format_bvh (4 decimals): {w:.3f} s")


if __name__ == "__main__":
    main()
