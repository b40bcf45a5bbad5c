"""Volume-preserving skinning (``pose_bodies(..., preserve_volume=True)``, ``rig.volume``)
against plain LBS in the same run: one body over the 39 library poses repeated to ``frames``
frames, MakeHuman's weights, the default rig. Prints vertex-frames per second of both, their
ratio (the throughput cost of the correction), and the volume error of the corrected frames.

``--png FILE``: also a picture of the mean body with bone-heat weights in the squat, ``sitting``
and ``arms_overhead``, plain LBS beside the corrected mesh, front and side
(docs/volume_preserving_skinning.png).

Run: python benchmarks/bench_volume.py [--frames 390] [--png docs/volume_preserving_skinning.png]
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import best_time  # noqa: E402

from bodyspace.data.template import load_template  # noqa: E402
from bodyspace.mesh.geometry import capped_volume  # noqa: E402
from bodyspace.rig.kinematics import forward_kinematics, linear_blend_skinning  # noqa: E402
from bodyspace.rig.posing import pose_bodies  # noqa: E402
from bodyspace.rig.volume import preserve_volume, volume_rig  # noqa: E402
from bodyspace.report.animation import filmstrip  # noqa: E402
from bodyspace.synth.poses import load_pose_library  # noqa: E402


def picture(path: str) -> None:
    """LBS and LBS + volume side by side in three poses, bone-heat weights, the mean body."""
    template = load_template()
    rig = template.rigs["default"]
    library = load_pose_library()
    poses = ["squat", "sitting", "arms_overhead"]
    R = library.stack(poses, rig)
    v = template.vertices
    plain = pose_bodies(v, rig, R, weights="bone_heat")
    kept = pose_bodies(v, rig, R, weights="bone_heat", preserve_volume=True)
    rest = capped_volume(v, template.faces)
    frames, titles = [], []
    for k, pose in enumerate(poses):
        for mesh, how in ((plain[k], "LBS"), (kept[k], "+ vol.")):
            change = 100 * (capped_volume(mesh, template.faces) / rest - 1)
            frames.append(mesh)
            titles.append(f"{pose} {how}: {0.0 if abs(change) < 0.05 else change:+.1f} %")
    filmstrip(path, np.stack(frames), template.faces, titles, ncols=len(frames),
              title="bone heat, mean body: LBS and LBS + volume correction (volume change)")
    print(f"wrote {path}")


def main(frames: int = 390) -> None:
    template = load_template()
    rig = template.rigs["default"]
    library = load_pose_library()
    names = [library.names[i % len(library.names)] for i in range(frames)]
    R = library.stack(names, rig)
    v = template.vertices
    corrected = pose_bodies(v, rig, R, preserve_volume=True)        # compiles, fills the caches
    error = np.abs(capped_volume(corrected, template.faces) / capped_volume(v, template.faces) - 1).max()
    work = frames * len(v)
    print(f"load average {os.getloadavg()[0]:.1f}; {frames} frames x {len(v):,} vertices; "
          f"{time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}")
    lbs = best_time(lambda: pose_bodies(v, rig, R))
    vol = best_time(lambda: pose_bodies(v, rig, R, preserve_volume=True))
    print(f"pose_bodies LBS: {work / lbs / 1e6:.1f} M vertex-frames/s; with preserve_volume: "
          f"{work / vol / 1e6:.2f} M vertex-frames/s ({frames / vol:.0f} frames/s); "
          f"x{vol / lbs:.1f} the time of LBS alone (both two lanes, wall clock)")
    # One lane, CPU seconds of the calling thread: the figures that carry over to a quiet machine
    # (the wall-clock ones above move x2-3 between runs at load 10).
    heads, tails = rig.heads(v)[None], rig.tails(v)[None]
    G = forward_kinematics(R, heads, rig.parents)
    vrig = volume_rig(rig.weights, rig.parents, template.faces)
    lbs_cpu = best_time(lambda: linear_blend_skinning(v, rig.weights, G, lanes=1), clock=time.thread_time)
    posed = linear_blend_skinning(v, rig.weights, G)
    work = np.empty_like(posed)

    def correct():                                   # (the copy is ~1 % of the time)
        np.copyto(work, posed)
        preserve_volume(work, v[None], G, heads, tails, vrig, lanes=1)

    vol_cpu = best_time(correct, clock=time.thread_time)
    print(f"one lane, CPU: LBS kernel {1000 * lbs_cpu / frames:.2f} ms a frame, the correction "
          f"{1000 * vol_cpu / frames:.2f} ms a frame: x{(lbs_cpu + vol_cpu) / lbs_cpu:.0f} the time of LBS alone")
    print(f"worst volume error of the corrected frames: {100 * error:.2e} %")


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=390)
    parser.add_argument("--png", help="also write the before/after picture here")
    args = parser.parse_args()
    main(args.frames)
    if args.png:
        picture(args.png)
