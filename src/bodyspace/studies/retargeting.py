"""Feet, floor and arms of a clip on a body: what retargeting does, before and after the foot IK,
against the source clip (issue 14, "What it must show"; Rupprecht §3.3.3).

``clip_on_body`` puts one clip on one body of the template topology (``body_skeleton`` of a CC0
rig, ``retarget``, ``lock_feet`` with the sole, LBS) and measures, for the source, the retargeted
clip and the foot-locked one: foot skating over the source's contact frames (share of contact
frames sliding more than 2.5 cm, mean speed in contact; ``motion.contacts``), how far the foot
joints and the feet's skin go below the floor, the skin of the rest of the body below the floor
(a knee or hand the clip puts on the floor), the fastest knee (deg/s: a pop shows here) and the
arms inside the torso (``motion.intersection``). ``retargeting_study`` runs it for clips x bodies.
Data only; ``benchmarks/study_retarget.py`` prints the table.
"""

from __future__ import annotations

import time

import numpy as np

from bodyspace.data.template import load_template
from bodyspace.motion.bvh import Motion
from bodyspace.motion.contacts import penetration, skating
from bodyspace.motion.ik import foot_vertices, knee_angles, lock_feet, sole_points
from bodyspace.motion.intersection import arm_torso_intersections, arm_torso_regions
from bodyspace.motion.retarget import retarget
from bodyspace.rig.kinematics import linear_blend_skinning
from bodyspace.rig.skeleton import body_skeleton

__all__ = ["clip_on_body", "retargeting_study"]


def clip_on_body(clip: Motion, vertices: np.ndarray, rig_name: str = "default") -> dict:
    """Measures of ``clip`` on the body ``vertices`` (V, 3), template topology (module docstring).

    Returns a JSON-able dict: ``stature_m``, ``leg_ratio``, ``frames``, and per stage
    (``source``, ``retargeted``, ``foot_ik``) the skating (``share_sliding``,
    ``mean_speed_m_per_s``), ``foot_joints_below_floor_m``, ``feet_skin_below_floor_m``,
    ``other_skin_below_floor_m``, ``fastest_knee_deg_per_s``; ``arms_in_torso`` of the final clip;
    ``seconds`` spent.
    """
    started = time.perf_counter()
    template = load_template()
    rig = template.rigs[rig_name]
    v = np.asarray(vertices, dtype=float)
    skeleton = body_skeleton(rig, v, rest_vertices=template.vertices)
    before = retarget(clip, skeleton, target_floor=float(v[:, 1].min()))
    after, _ = lock_feet(before, sole=sole_points(before, rig.weights, v))
    feet_v = foot_vertices(before, rig.weights)
    others = np.setdiff1d(np.arange(len(v)), feet_v)
    dt = clip.frame_time

    def knee_speed(c, source=False) -> float:
        k = knee_angles(c, source=source)
        return float(np.degrees(np.abs(np.diff(k, axis=0))).max() / dt) if len(k) > 1 else 0.0

    fs = before.feet()
    out = {"stature_m": float(np.ptp(v[:, 1])), "leg_ratio": before.leg_ratio, "frames": clip.n_frames,
           "source": {**skating(fs.source, fs.contacts, dt).to_dict(),
                      "foot_joints_below_floor_m": penetration(fs.source[..., 1]
                                                               - np.percentile(fs.source[..., 1], 5, axis=0)),
                      "fastest_knee_deg_per_s": knee_speed(before, source=True)}}
    posed = None
    for name, c in (("retargeted", before), ("foot_ik", after)):
        f = c.feet()
        posed = linear_blend_skinning(v, rig.weights, c.transforms(), dtype=np.float32)
        out[name] = {**skating(f.target, f.contacts, dt).to_dict(),
                     "foot_joints_below_floor_m": penetration(f.target[..., 1] - f.clearance),
                     "feet_skin_below_floor_m": penetration(posed[:, feet_v, 1]),
                     "other_skin_below_floor_m": penetration(posed[:, others, 1]),
                     "fastest_knee_deg_per_s": knee_speed(c)}
    arm, torso = arm_torso_regions(skeleton, rig.weights, before.match.target_landmarks, v)
    out["arms_in_torso"] = arm_torso_intersections(posed, template.faces, arm, torso).to_dict()
    out["seconds"] = time.perf_counter() - started
    return out


def retargeting_study(clips: dict[str, Motion], bodies: dict[str, np.ndarray], rig_name: str = "default",
                      progress=None) -> list[dict]:
    """``clip_on_body`` for every clip (name -> Motion) and body (label -> (V, 3) vertices):
    rows with ``clip`` and ``body`` added, clips outermost."""
    rows = []
    total = len(clips) * len(bodies)
    for name, clip in clips.items():
        for label, v in bodies.items():
            rows.append({"clip": name, "body": label, **clip_on_body(clip, v, rig_name)})
            if progress is not None:
                progress(f"{name} on {label}", len(rows) / total)
    return rows
