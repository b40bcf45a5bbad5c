"""The skating / penetration table of docs/motion.md: both shared CMU clips on bodies of 150,
165, 180 and 195 cm, before and after the foot IK, against the source clip
(``studies.retargeting``). Bodies: the phenotype model's (the synthetic population's
generator; women at 150 and 165 cm, men at 180 and 195 cm, average weight), their height
parameter bisected to the stature.

Run: python benchmarks/study_retarget.py   (about a minute; prints Markdown and JSON)
"""

from __future__ import annotations

import json
import os
import sys
from pathlib import Path

import numpy as np

from bodyspace.data.template import load_template
from bodyspace.motion.bvh import read_bvh
from bodyspace.studies.retargeting import retargeting_study
from bodyspace.synth.phenotype import PhenotypeModel

STATURES = (("150 cm woman", 1.50, 0.0), ("165 cm woman", 1.65, 0.0), ("180 cm man", 1.80, 1.0),
            ("195 cm man", 1.95, 1.0))


def body_of_stature(model: PhenotypeModel, stature_m: float, gender: float) -> np.ndarray:
    lo, hi = 0.0, 1.0
    for _ in range(30):
        mid = 0.5 * (lo + hi)
        v = model.vertices({"gender": np.array([gender]), "height": np.array([mid]), "weight": np.array([0.5])})[0]
        lo, hi = (mid, hi) if np.ptp(v[:, 1]) < stature_m else (lo, mid)
    return v


def main() -> None:
    roots = [Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "mocap",
             Path(os.environ.get("BODYSPACE_SHARED_DATA", "/work/shared/data")) / "mocap"]
    root = next((r for r in roots if (r / "131_01.bvh").is_file()), None)
    if root is None:
        print("the shared CMU clips were not found; nothing measured")
        return
    clips = {p.stem: read_bvh(p) for p in sorted(root.glob("*.bvh"))}
    pm = PhenotypeModel(load_template())
    bodies = {label: body_of_stature(pm, s, g) for label, s, g in STATURES}
    rows = retargeting_study(clips, bodies, progress=lambda m, f: print(f"  {m} ({f:.0%})", file=sys.stderr))
    cm, pct = (lambda x: f"{100 * x:.1f}"), (lambda x: f"{100 * x:.1f} %")
    print("| clip | body | leg ratio | stage | sliding > 2.5 cm | mean speed in contact (cm/s) | foot joints below "
          "floor (cm) | feet's skin below floor (cm) | other skin below floor (cm) | fastest knee (deg/s) |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        for stage in ("source", "retargeted", "foot_ik"):
            s = r[stage]
            print(f"| {r['clip']} | {r['body']} | {r['leg_ratio']:.3f} | {stage.replace('_', ' ')} | "
                  f"{pct(s['share_sliding'])} | {cm(s['mean_speed_m_per_s'])} | {cm(s['foot_joints_below_floor_m'])} | "
                  f"{cm(s['feet_skin_below_floor_m']) if 'feet_skin_below_floor_m' in s else ''} | "
                  f"{cm(s['other_skin_below_floor_m']) if 'other_skin_below_floor_m' in s else ''} | "
                  f"{s['fastest_knee_deg_per_s']:.0f} |")
    print()
    print("| clip | body | arms in the torso > 5 mm (frames) | deepest (cm) | seconds |")
    print("|---|---|---|---|---|")
    for r in rows:
        a = r["arms_in_torso"]
        print(f"| {r['clip']} | {r['body']} | {a['frames_intersecting']} of {r['frames']} | {cm(a['max_depth_m'])} | "
              f"{r['seconds']:.1f} |")
    print()
    print(json.dumps(rows))


if __name__ == "__main__":
    main()
