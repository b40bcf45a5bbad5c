"""Retarget and skin a 1,000-frame clip onto a 13,380-vertex body (issue 14: under 2 s on 2 cores).

The pipeline of ``bodyspace animate`` after the body is made: match the clip's skeleton to the
rig (done once per body and clip, timed apart), retarget (``motion.retarget``), lock the feet
(``motion.ik.lock_feet`` with the sole kept above the floor), forward kinematics and linear
blend skinning of every frame (float32 out, as the command writes). The baseline in the same
run is the same retargeting and IK followed by the plain numpy FK and LBS
(``kinematics.forward_kinematics_numpy``, ``linear_blend_skinning_numpy``, float64): what the
pipeline costs without the compiled kernels.

The clip is the shared CMU 131_02 (1,247 frames at 120 Hz), its first 1,000 frames; without the
shared data the benchmark says so and stops. Run: python benchmarks/bench_retarget.py
"""

from __future__ import annotations

import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import best_time, report  # noqa: E402

from bodyspace.data.template import load_template  # noqa: E402
from bodyspace.motion.bvh import read_bvh  # noqa: E402
from bodyspace.motion.ik import lock_feet, sole_points  # noqa: E402
from bodyspace.motion.matching import graph_from_motion, graph_from_skeleton, match_skeletons  # noqa: E402
from bodyspace.motion.retarget import retarget  # noqa: E402
from bodyspace.rig.kinematics import (  # noqa: E402
    forward_kinematics,
    forward_kinematics_numpy,
    linear_blend_skinning,
    linear_blend_skinning_numpy,
)
from bodyspace.rig.skeleton import body_skeleton  # noqa: E402

FRAMES = 1000


def clip_path() -> Path | None:
    roots = [Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "mocap",
             Path(os.environ.get("BODYSPACE_SHARED_DATA", "/work/shared/data")) / "mocap"]
    return next((r / "131_02.bvh" for r in roots if (r / "131_02.bvh").is_file()), None)


def main() -> None:
    path = clip_path()
    if path is None:
        print("the shared CMU clip 131_02.bvh was not found (../shared/data/mocap or $BODYSPACE_SHARED_DATA); "
              "nothing measured")
        return
    template = load_template()
    rig = template.rigs["default"]
    body = template.vertices
    skeleton = body_skeleton(rig, body)
    clip = read_bvh(path).frames(slice(0, FRAMES))
    floor = float(body[:, 1].min())
    t = time.perf_counter()
    match = match_skeletons(graph_from_motion(clip), graph_from_skeleton(skeleton))
    match_s = time.perf_counter() - t

    def motion():
        out = retarget(clip, skeleton, match, target_floor=floor)
        return lock_feet(out, sole=sole_points(out, rig.weights, body))[0]

    def fast():
        c = motion()
        G = forward_kinematics(c.rotations, skeleton.heads, skeleton.parents, c.translation)
        return linear_blend_skinning(body, rig.weights, G, dtype=np.float32)

    def plain():
        c = motion()
        G = forward_kinematics_numpy(c.rotations, skeleton.heads, skeleton.parents, c.translation)
        return linear_blend_skinning_numpy(body, rig.weights, G)

    a, b = fast(), plain()                             # compile, warm the caches, check agreement
    assert np.abs(a - b).max() < 1e-5, np.abs(a - b).max()
    steps = {"retarget": best_time(lambda: retarget(clip, skeleton, match, target_floor=floor))}
    out = retarget(clip, skeleton, match, target_floor=floor)
    steps["foot IK"] = best_time(lambda: lock_feet(out, sole=sole_points(out, rig.weights, body)))
    c = motion()
    steps["FK"] = best_time(lambda: forward_kinematics(c.rotations, skeleton.heads, skeleton.parents, c.translation))
    G = forward_kinematics(c.rotations, skeleton.heads, skeleton.parents, c.translation)
    steps["LBS float32"] = best_time(lambda: linear_blend_skinning(body, rig.weights, G, dtype=np.float32))
    fast_s = best_time(fast)
    plain_s = best_time(plain, repeat=2)
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    print(f"{clip.n_frames} frames of {path.name} onto a {len(body):,}-vertex body ({skeleton.n_bones} bones), "
          f"load average {load:.1f} on {os.cpu_count()} cores")
    print(f"match (once per clip and body): {match_s:.3f} s")
    print("steps: " + ", ".join(f"{k} {v:.3f} s" for k, v in steps.items()))
    print(f"retarget + foot IK + FK + LBS: {fast_s:.2f} s (target < 2 s); with numpy FK and LBS: {plain_s:.2f} s")
    report("retarget and skin", fast_s, plain_s, clip.n_frames, "frames")


if __name__ == "__main__":
    main()
