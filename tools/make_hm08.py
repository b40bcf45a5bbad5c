"""Regenerate ``hm08.json``: pick the landmarks and Rupprecht loops on the mean body.

Run once (``python tools/make_hm08.py``); the ids and weights are stored
in the JSON so measuring never depends on this script. The measurement definitions in the JSON
are hand-written data; this script rewrites only the landmarks and the loop rings. Two kinds of
landmark, each rule a comment below; left landmarks are picked on the left and mirrored with
``template.mirror`` so the set is exactly symmetric:

- *surface* landmarks: one vertex of the mean body (default phenotype, rest pose), chosen from
  the joint cubes and the extreme vertices (head top, acromion, bust point, ...);
- *joint* landmarks (``shoulder_joint_l``, ...): a joint centre as a convex weighted set of
  vertices, the **skinning-consistent joint regressor** ``fit_joint_landmark``. A plain
  regressor row (``template.joint_regressor``: the hm08 joint cube from the skin around it)
  drifts by 1-4 cm when the joint bends, because linear blend skinning collapses the skin at a
  flexed joint; the weights here are fitted on bodies of many shapes *posed* with the pose
  library so the weighted vertices follow the joint through posing (SMPL's joint regressor is
  trained the same way, on posed registrations). Limb lengths measured between them are then
  pose-invariant (docs/measurements.md gives the residuals).
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import scipy.optimize

from bodyspace.data.template import load_template
from bodyspace.measure.parts import encode_parts, parts_from_weights
from bodyspace.measure.slicing import mesh_edges, pick_contours, slice_contours
from bodyspace.synth.phenotype import PARAMETERS, PhenotypeModel

OUT = Path(__file__).resolve().parents[1] / "src" / "bodyspace" / "data" / "measurements" / "hm08.json"

# Joint landmarks: (name, hm08 joint cube, rig bone whose head the cube is, candidate radius m).
JOINTS = (
    ("shoulder_joint_l", "joint-l-shoulder", "upperarm01.L", 0.10),   # glenohumeral centre
    ("elbow_joint_l", "joint-l-elbow", "lowerarm01.L", 0.08),
    ("wrist_joint_l", "joint-l-hand", "wrist.L", 0.06),
    ("hip_joint_l", "joint-l-upper-leg", "upperleg01.L", 0.14),       # femoral head centre
    ("knee_joint_l", "joint-l-knee", "lowerleg01.L", 0.10),
    ("ankle_joint_l", "joint-l-ankle", "foot.L", 0.08),
)
# Poses the joint fit never sees: tests/test_measure.py checks pose invariance on exactly these
# (and their mirror images, which the mirrored right landmarks would otherwise learn from).
HELD_OUT_POSES = ("arms_overhead", "t_pose", "elbows_flexed", "knee_lift_left", "torso_twist_left",
                  "head_turn_left", "step_forward_left")
N_SHAPES = 12          # random phenotypes besides the mean body
RIDGE = 0.02           # spreads the weights over more vertices (robust to noise on scans)
REST_WEIGHT = 10.0     # weight of the sum-to-one row


def _dominant_bone(template) -> np.ndarray:
    W = template.rigs["default"].weights.tocsr()
    return np.asarray(W.argmax(axis=1)).ravel()


def pick_landmarks(template, v: np.ndarray) -> dict[str, int]:
    """Surface landmarks (vertex ids) on the mean body ``v`` (V, 3); right ones mirrored."""
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
    # Calf: most posterior vertex of the lower leg (the calf bulge).
    cand = on(["lowerleg01.L", "lowerleg02.L"])
    cand = cand[(v[cand, 1] < J("joint-l-knee")[1] - 0.05) & (v[cand, 1] > J("joint-l-ankle")[1] + 0.1)]
    lm["calf_l"] = int(cand[np.argmin(v[cand, 2])])
    for k in list(lm):
        if k.endswith("_l"):
            lm[k[:-2] + "_r"] = int(template.mirror[lm[k]])
    return lm


def training_bodies(template, model: PhenotypeModel, rng=0):
    """Rest bodies (S, V, 3) of the mean and ``N_SHAPES`` random adult phenotypes, the training
    pose names (the library minus ``HELD_OUT_POSES`` and their mirrors), and the bodies posed
    with them (S*P, V, 3) with their posed bone heads (S*P, B, 3)."""
    from bodyspace.rig.posing import pose_bodies
    from bodyspace.synth.poses import load_pose_library

    rng = np.random.default_rng(rng)
    phen = rng.uniform(0.1, 0.9, (N_SHAPES, len(PARAMETERS)))
    phen[:, PARAMETERS.index("age")] = rng.uniform(0.4, 0.9, N_SHAPES)     # adults
    phen = np.vstack([np.full(len(PARAMETERS), 0.5), phen])
    rest = model.vertices(phen)
    lib = load_pose_library()
    rig = template.rigs["default"]
    held = set(HELD_OUT_POSES) | {lib.mirror(p) for p in HELD_OUT_POSES if lib.mirror(p)}
    poses = [p for p in lib.names if p not in held]
    R = lib.stack(poses, rig)
    posed, heads = pose_bodies(np.repeat(rest, len(poses), axis=0), rig, np.tile(R, (len(rest), 1, 1, 1)),
                               return_joints=True)
    return rest, poses, posed, heads


def fit_joint_landmark(template, posed: np.ndarray, heads: np.ndarray, bone: str, centre: np.ndarray,
                       radius: float) -> tuple[np.ndarray, np.ndarray]:
    """Skinning-consistent joint regressor: convex weights over the vertices near a joint.

    posed: (M, V, 3) bodies of many shapes in many poses (including rest); heads: (M, B, 3) their
    posed bone heads (forward kinematics); ``bone`` names the rig bone whose head is the joint;
    candidates are the mesh vertices within ``radius`` of ``centre`` (3,) (the joint on the mean
    body). Solves, by NNLS with a sum-to-one row and a small ridge,

        min_w  sum_m |sum_k w_k posed[m, k] - heads[m, bone]|^2 + RIDGE^2 |w|^2,  w >= 0, sum w = 1,

    so the weighted vertices land on the joint in every training pose and shape. Returns the
    vertex ids (k,) and weights (k,) (weights below 1e-3 of the largest dropped, renormalized).
    """
    rig = template.rigs["default"]
    b = rig.bone_index(bone)
    used = np.zeros(template.n_vertices, dtype=bool)
    used[template.faces.ravel()] = True
    cand = np.flatnonzero((np.linalg.norm(posed[0] - centre, axis=1) < radius) & used)
    A = (posed[:, cand, :] - heads[:, b, None, :]).transpose(0, 2, 1).reshape(-1, len(cand))
    A = np.vstack([A, np.full((1, len(cand)), REST_WEIGHT), RIDGE * np.eye(len(cand))])
    y = np.zeros(len(A))
    y[-len(cand) - 1] = REST_WEIGHT
    w, _ = scipy.optimize.nnls(A, y, maxiter=100 * len(cand))
    keep = w > 1e-3 * w.max()
    return cand[keep], w[keep] / w[keep].sum()


def joint_landmarks(template, model: PhenotypeModel) -> tuple[dict[str, dict], dict[str, float]]:
    """Joint landmarks {name: {"vertices", "weights"}} (left fitted, right mirrored) and the
    worst distance (m) of each to its posed bone head over the training bodies."""
    rest, poses, posed, heads = training_bodies(template, model)
    rig = template.rigs["default"]
    out, err = {}, {}
    for name, cube, bone, radius in JOINTS:
        centre = template.joint(rest[0], cube)
        ids, w = fit_joint_landmark(template, posed, heads, bone, centre, radius)
        order = np.argsort(-w)
        ids, w = ids[order], np.round(w[order], 8)
        w[0] = round(1.0 - w[1:].sum(), 8)             # convex after rounding
        out[name] = {"vertices": [int(i) for i in ids], "weights": [float(x) for x in w]}
        out[name[:-2] + "_r"] = {"vertices": [int(template.mirror[i]) for i in ids], "weights": [float(x) for x in w]}
        p = np.einsum("k,mkc->mc", w, posed[:, ids])
        err[name] = float(np.linalg.norm(p - heads[:, rig.bone_index(bone)], axis=1).max())
    return out, err


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


def _dumps(spec: dict) -> str:
    """JSON with one line per landmark and per measurement (lists of numbers stay on one line)."""
    def one(x):
        return json.dumps(x, separators=(", ", ": "))
    lines = ["{"]
    keys = list(spec)
    for i, k in enumerate(keys):
        end = "," if i < len(keys) - 1 else ""
        val = spec[k]
        if isinstance(val, dict) and val and k in ("landmarks", "conditions"):
            items = [f"  {json.dumps(n)}: {one(x)}" for n, x in val.items()]
            lines.append(f" {json.dumps(k)}: {{\n" + ",\n".join(items) + f"\n }}{end}")
        elif isinstance(val, list) and val:
            items = [f"  {one(x)}" for x in val]
            lines.append(f" {json.dumps(k)}: [\n" + ",\n".join(items) + f"\n ]{end}")
        else:
            lines.append(f" {json.dumps(k)}: {one(val)}{end}")
    return "\n".join(lines) + "\n}\n"


# The body part each girth's tape goes round (measure/parts.py); a list is a union of parts
# (the wrist plane lies on the forearm/hand border).
GIRTH_PARTS = {
    "chest_girth": "torso", "underbust_girth": "torso", "waist_girth": "torso",
    "hip_girth": ["torso", "thigh_l", "thigh_r"],      # the buttocks are on the thighs' bones too
    "thigh_girth_l": "thigh_l", "calf_girth_l": "calf_l", "upper_arm_girth_l": "upper_arm_l",
    "wrist_girth_l": ["forearm_l", "hand_l"],
    "thigh_girth_r": "thigh_r", "calf_girth_r": "calf_r", "upper_arm_girth_r": "upper_arm_r",
    "wrist_girth_r": ["forearm_r", "hand_r"],
    "neck_girth": ["neck", "torso"],       # the neck base is on the spine's bones; the chin (head) never enters
}


def add_parts(spec: dict, template) -> None:
    """Each girth's ``part`` and the template's ``vertex_parts`` (from the default rig's skin weights)."""
    rig = template.rigs["default"]
    for m in spec.get("measurements", []):
        if m["name"] in GIRTH_PARTS:
            m["part"] = GIRTH_PARTS[m["name"]]
    spec["vertex_parts"] = encode_parts(parts_from_weights(rig.weights, rig.bone_names))


def main() -> None:
    from bodyspace.measure.definitions import measurement_set_from_dict

    if "--parts-only" in sys.argv:       # only the part labels and fields, landmarks as they are
        spec = json.loads(OUT.read_text())
        add_parts(spec, load_template())
        text = _dumps(spec)
        measurement_set_from_dict(json.loads(text), str(OUT))
        OUT.write_text(text)
        return

    template = load_template()
    model = PhenotypeModel(template)
    v = model.vertices({})[0]
    lm: dict = dict(pick_landmarks(template, v))
    joints, err = joint_landmarks(template, model)
    lm.update(joints)
    up = np.array([0.0, 1.0, 0.0])
    P = {k: v[i] for k, i in lm.items() if isinstance(i, int)}
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
    add_parts(spec, template)
    for m in spec.get("measurements", []):
        if m.get("method") == "loop" and m["name"] in loops:
            m["vertices"] = loops[m["name"]]
    text = _dumps(spec)
    measurement_set_from_dict(json.loads(text), str(OUT))      # the set must still validate
    OUT.write_text(text)
    print(f"{len(lm)} landmarks; loop sizes {({k: len(x) for k, x in loops.items()})}")
    print("joint landmarks, worst distance to the posed joint over the training bodies (mm): "
          + ", ".join(f"{k} {1000 * e:.1f}" for k, e in err.items()))


if __name__ == "__main__":
    main()
