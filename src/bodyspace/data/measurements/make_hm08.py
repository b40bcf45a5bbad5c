"""Regenerate ``hm08.json``: pick the landmark vertices and Rupprecht loops on the mean body.

Run once (``python -m bodyspace.data.measurements.make_hm08``); the ids are stored in the JSON
so measuring never depends on this script. Landmarks are chosen from the joint cubes and the
extreme vertices of the mean body (default phenotype, rest pose), each rule a comment below;
left landmarks are picked on the left and mirrored with ``template.mirror`` so the set is
exactly symmetric.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from bodyspace.data.phenotype import PhenotypeModel
from bodyspace.data.template import load_template
from bodyspace.measure.slicing import mesh_edges, slice_contours, pick_contours

OUT = Path(__file__).with_name("hm08.json")


def _dominant_bone(template) -> np.ndarray:
    W = template.rigs["default"].weights.tocsr()
    return np.asarray(W.argmax(axis=1)).ravel()


def pick_landmarks(template, v: np.ndarray) -> dict[str, int]:
    rig = template.rigs["default"]
    bone = _dominant_bone(template)
    names = np.array(rig.bone_names)
    J = lambda n: template.joint(v, n)  # noqa: E731
    mid = np.flatnonzero(np.abs(v[:, 0]) < 1e-4)

    def on(bones):
        return np.flatnonzero(np.isin(names[bone], bones))

    def near_y(idx, y, tol=0.008):
        return idx[np.abs(v[idx, 1] - y) < tol]

    lm: dict[str, int] = {}
    lm["head_top"] = int(mid[np.argmax(v[mid, 1])])                 # vertex: highest point of the head
    lm["crotch"] = int(mid[np.argmin(v[mid, 1])])                   # lowest point of the trunk, between the legs
    # Neck base: front (jugular notch) and back (cervicale) on the mid line, at the neck joint - 3 cm.
    yn = J("joint-neck")[1] - 0.03
    cand = near_y(mid, yn, 0.01)
    lm["neck_front"] = int(cand[np.argmax(v[cand, 2])])
    lm["neck_back"] = int(cand[np.argmin(v[cand, 2])])
    # Acromion: highest vertex above the shoulder joint (within 3 cm across).
    sh = J("joint-l-shoulder")
    cand = np.flatnonzero((np.abs(v[:, 0] - (sh[0] + 0.02)) < 0.02) & (np.abs(v[:, 2] - sh[2]) < 0.03))
    lm["shoulder_l"] = int(cand[np.argmax(v[cand, 1])])
    # Bust point: most forward vertex of the left chest.
    chest = np.flatnonzero((v[:, 0] > 0.03) & (v[:, 0] < 0.15) & (v[:, 1] > J("joint-spine-2")[1])
                           & (v[:, 1] < J("joint-l-shoulder")[1] - 0.05))
    lm["bust_l"] = int(chest[np.argmax(v[chest, 2])])
    # Underbust: front mid line 8 cm below the bust point (inframammary fold).
    cand = near_y(mid, v[lm["bust_l"], 1] - 0.08)
    lm["underbust_front"] = int(cand[np.argmax(v[cand, 2])])
    # Thigh: lateral upper thigh 3 cm below the crotch (below the gluteal fold).
    leg = on(["upperleg01.L", "upperleg02.L", "pelvis.L"])
    cand = near_y(leg, v[lm["crotch"], 1] - 0.03)
    lm["thigh_l"] = int(cand[np.argmax(v[cand, 0])])
    # Knee: lateral vertex at the knee joint height.
    cand = near_y(on(["upperleg02.L", "lowerleg01.L"]), J("joint-l-knee")[1])
    lm["knee_l"] = int(cand[np.argmax(v[cand, 0])])
    # Calf: most posterior vertex of the lower leg (the calf bulge).
    cand = on(["lowerleg01.L", "lowerleg02.L"])
    cand = cand[(v[cand, 1] < J("joint-l-knee")[1] - 0.05) & (v[cand, 1] > J("joint-l-ankle")[1] + 0.1)]
    lm["calf_l"] = int(cand[np.argmin(v[cand, 2])])
    # Ankle: lateral malleolus, the outermost vertex at ankle joint height.
    cand = near_y(np.flatnonzero(v[:, 0] > 0.05), J("joint-l-ankle")[1], 0.01)
    lm["ankle_l"] = int(cand[np.argmax(v[cand, 0])])

    def arm_point(joint, bones, direction):
        # Among vertices within 1 cm of the plane through the joint normal to the arm, the
        # one farthest along ``direction`` (olecranon: back and out; ulnar styloid: down).
        p = J(joint)
        axis = J("joint-l-hand") - J("joint-l-shoulder")
        axis /= np.linalg.norm(axis)
        cand = on(bones)
        cand = cand[np.abs((v[cand] - p) @ axis) < 0.01]
        return int(cand[np.argmax((v[cand] - p) @ direction)])

    lm["elbow_l"] = arm_point("joint-l-elbow", ["upperarm02.L", "lowerarm01.L"], np.array([0.3, 0.0, -1.0]))
    lm["wrist_l"] = arm_point("joint-l-hand", ["lowerarm02.L", "wrist.L"], np.array([0.5, -1.0, 0.0]))
    for k in list(lm):
        if k.endswith("_l"):
            lm[k[:-2] + "_r"] = int(template.mirror[lm[k]])
    return lm


def ring(template, v, origin, normal, pick) -> list[int]:
    """Rupprecht's loop: the ordered vertex ring along the plane's contour around ``pick``.

    Each crossed edge gives its nearer endpoint; consecutive repeats are dropped. The ring is
    ordered by angle around the contour centre (the contours here are star-shaped about it).
    """
    edges, fe = mesh_edges(template.faces)
    o, n, p = (np.asarray(x, float)[None] for x in (origin, normal, pick))
    c = slice_contours(v[None], edges, fe, o, n)
    lab = pick_contours(c, p, n)[0]
    sel = np.flatnonzero(c.label == lab)
    d = (v - o[0]) @ n[0]
    # Crossing edges of the chosen contour, via their points.
    side = d >= 0
    crossed = np.flatnonzero(side[edges[:, 0]] != side[edges[:, 1]])
    assert len(crossed) == len(c.points)
    ends = edges[crossed[sel]]
    near = np.where(np.abs(d[ends[:, 0]]) <= np.abs(d[ends[:, 1]]), ends[:, 0], ends[:, 1])
    ids = np.unique(near)
    centre = v[ids].mean(axis=0)
    u = np.cross(n[0], [0, 0, 1.0]) if abs(n[0][2]) < 0.9 else np.array([1.0, 0, 0])
    u /= np.linalg.norm(u)
    w = np.cross(n[0], u)
    ang = np.arctan2((v[ids] - centre) @ w, (v[ids] - centre) @ u)
    out = ids[np.argsort(ang)]
    return [int(i) for i in out]


def main() -> None:
    template = load_template()
    v = PhenotypeModel(template).vertices({})[0]
    lm = pick_landmarks(template, v)
    up = np.array([0.0, 1.0, 0.0])
    P = {k: v[i] for k, i in lm.items()}
    loops = {
        "breast_size": ring(template, v, (P["bust_l"] + P["bust_r"]) / 2, up, (P["bust_l"] + P["bust_r"]) / 2),
        "waist_size": ring(template, v, template.joint(v, "joint-spine-3"), up, template.joint(v, "joint-spine-3")),
        "hip_size": ring(template, v, template.joint(v, "joint-pelvis") - [0, 0.07, 0], up,
                         template.joint(v, "joint-pelvis") - [0, 0.07, 0]),
        "shoulder_size": ring(template, v, template.joint(v, "joint-l-shoulder") * [0, 1, 0] - [0, 0.04, 0], up,
                              template.joint(v, "joint-spine-1")),
    }
    spec = json.loads(OUT.read_text()) if OUT.exists() else {}
    spec["landmarks"] = lm
    for m in spec.get("measurements", []):
        if m.get("method") == "loop" and m["name"] in loops:
            m["vertices"] = loops[m["name"]]
    OUT.write_text(json.dumps(spec, indent=1) + "\n")
    print(json.dumps(lm))
    print({k: len(x) for k, x in loops.items()})


if __name__ == "__main__":
    main()
