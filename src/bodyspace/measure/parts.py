"""Body parts per vertex: which part (torso, one thigh, one upper arm, neck, ...) each vertex is on.

A girth's tape goes round one body part (issue 12 §3): the chest around the torso and not the
arms that touch it, a thigh without the other leg, the neck without the chin. A measurement
names its part (``"part": "thigh_l"``) and the slice keeps only the mesh faces of that part
(``methods.slice_girth``). The labels are a property of the topology, not of the pose: they are
assigned once on a standing body and then follow every vertex through any pose, so an arm
pressed against the chest stays an arm.

Two sources, one vocabulary (``PARTS``):

- ``parts_from_weights``: the template's CC0 rig skin weights (V, B) and bone names; each
  vertex goes to the part whose bones hold most of its weight (``BONE_PARTS``). The shipped
  hm08 set carries these labels (``tools/make_hm08.py``).
- ``parts_from_landmarks``: any topology, from the landmarks of a measurement set on one
  standing body: each vertex goes to the nearest segment of the skeleton the landmarks define
  (``SKELETON``: joint centres for the limbs, crotch-neck and a hip/shoulder frame for the
  torso). Where the limb chains end (hands, feet, head) the vertices past the last joint go
  to the end part.

Labels are (V,) int8 indices into ``PARTS`` (-1: no part, e.g. a set without the landmarks a
part needs); ``encode_parts`` / ``decode_parts`` write them as one letter a vertex, the form a
measurement-set JSON (and so a BodyModel file) stores them in.
"""

from __future__ import annotations

import re

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from bodyspace.errors import MeasurementError
from bodyspace.mesh.geometry import vertex_normals

PARTS = ("torso", "neck", "head",
         "upper_arm_l", "forearm_l", "hand_l", "upper_arm_r", "forearm_r", "hand_r",
         "thigh_l", "calf_l", "foot_l", "thigh_r", "calf_r", "foot_r")
PART_INDEX = {p: i for i, p in enumerate(PARTS)}
# One letter a part in a stored label string; "." is a vertex of no part.
_LETTERS = "TNHABCabcDEFdef"
NO_PART = -1

# MakeHuman/MPFB2 rig bone names (default, default_no_toes, game_engine, cmu_mb, mixamo) → part,
# first match wins; side from a ".L"/".R", "_l"/"_r", "Left"/"Right" in the name.
BONE_PARTS = (
    (r"upperarm|upper_arm|shoulder01|humerus|arm$|^(left|right)arm", "upper_arm"),
    (r"lowerarm|forearm|lower_arm", "forearm"),
    (r"wrist|hand|finger|metacarpal|thumb|index|middle|ring|pinky", "hand"),
    (r"ball", "foot"),
    (r"upperleg|thigh|upleg|femur", "thigh"),
    (r"lowerleg|calf|shin|(^|[^p])leg$|tibia", "calf"),
    (r"foot|toe|ankle", "foot"),
    (r"neck", "neck"),
    (r"head|jaw|eye|oculi|orbicularis|oris|risorius|temporalis|levator|tongue|special|skull", "head"),
    (r"root|hip|pelvis|spine|chest|breast|clavicle|shoulder|abdomen|torso|back", "torso"),
)
# A part that claims a vertex whose largest share is the head's when it holds at least this
# share of the vertex's weight: the skin under the jaw moves mostly with the head bone, yet a
# tape round the neck below the larynx goes over it (with it the hm08 neck girth of a standing
# body is the same as the unrestricted contour's, and the chin stays out when the head bends).
CLAIMS_FROM_HEAD = {"neck": 0.15}
SIDED = {"upper_arm", "forearm", "hand", "thigh", "calf", "foot"}

NECK = ("neck_front", "neck_back")
# The skeleton the landmarks define: (part, from, to) segments; a point is a landmark name, a
# tuple of names (their mean) or ("@t", a, b), the point a + t (b - a). The torso is a spine
# line, the hip line and two flanks (hip joint to shoulder joint, stopped a fifth short of the
# shoulder so the armpit stays with the arm), so it is as wide as it is; the spine and flanks
# start a tenth of the way up, or the inner thigh by the crotch would be nearer to the spine's
# end than to the thigh's axis. On the template these labels agree with the skin weights' on
# 93 % of the vertices (most of the rest: the jaw's underside, neck here and head there), and
# every hm08 girth and the stature of 4 subjects with them is within 1 mm of the value with the
# weights' labels.
SKELETON = (
    ("torso", ("@0.1", "crotch", NECK), NECK),
    ("torso", "hip_joint_l", "hip_joint_r"),
    ("torso", ("@0.1", "hip_joint_l", "shoulder_joint_l"), ("@0.8", "hip_joint_l", "shoulder_joint_l")),
    ("torso", ("@0.1", "hip_joint_r", "shoulder_joint_r"), ("@0.8", "hip_joint_r", "shoulder_joint_r")),
    ("neck", NECK, ("@0.4", NECK, "head_top")),
    ("head", ("@0.4", NECK, "head_top"), "head_top"),
    ("upper_arm_l", "shoulder_joint_l", "elbow_joint_l"),
    ("forearm_l", "elbow_joint_l", "wrist_joint_l"),
    ("hand_l", "wrist_joint_l", ("@1.45", "elbow_joint_l", "wrist_joint_l")),
    ("upper_arm_r", "shoulder_joint_r", "elbow_joint_r"),
    ("forearm_r", "elbow_joint_r", "wrist_joint_r"),
    ("hand_r", "wrist_joint_r", ("@1.45", "elbow_joint_r", "wrist_joint_r")),
    ("thigh_l", "hip_joint_l", "knee_joint_l"),
    ("calf_l", "knee_joint_l", "ankle_joint_l"),
    ("thigh_r", "hip_joint_r", "knee_joint_r"),
    ("calf_r", "knee_joint_r", "ankle_joint_r"),
)
# Torso distances of vertices below the hip joints count this much more (``parts_from_landmarks``).
BELOW_TORSO = 1.5
# Limb ends: vertices that project past the last joint of a chain belong to the end part.
CHAIN_ENDS = (("calf_l", "foot_l", "knee_joint_l", "ankle_joint_l"),
              ("calf_r", "foot_r", "knee_joint_r", "ankle_joint_r"))

# A joint axis on another topology (``axis_joints``): its joints are rings of skin at these
# fractions of the line from the neck landmarks to the head top, on these parts. They are where
# the hm08 joint regressor puts the neck joint (0.10) and the head joint (0.49) on the mean
# body; on a 5,000-vertex foreign topology, heads tilted sideways 20-30 degrees (over the neck,
# or at the head joint alone) then keep the neck girth within 0.5 cm of upright (the neck
# landmarks → head top line: up to 3.2 cm; tests/test_foreign_neck.py).
JOINT_LEVELS = (0.10, 0.49)
JOINT_PARTS = ("neck", "head")
RING_HALF_WIDTH = 0.03


def part_of_bone(name: str) -> int:
    """The ``PARTS`` index of a rig bone (by name, ``BONE_PARTS``), or -1 if none matches."""
    name = name.split(":")[-1]                      # mixamo's "mixamorig:" prefix
    low = name.lower()
    side = ""
    if re.search(r"(\.|_|-)l$|left", low) or re.match(r"L[A-Z]", name):
        side = "_l"
    elif re.search(r"(\.|_|-)r$|right", low) or re.match(r"R[A-Z]", name):
        side = "_r"
    stem = re.sub(r"(\.|_|-)(l|r)$|left|right", "", low)
    if re.match(r"[LR][A-Z]", name):
        stem = stem[1:]
    for pattern, part in BONE_PARTS:
        if re.search(pattern, stem):
            if part in SIDED:
                return PART_INDEX[part + side] if side else NO_PART
            return PART_INDEX[part]
    return NO_PART


def parts_from_weights(weights, bone_names) -> np.ndarray:
    """(V,) part labels from skin weights (V, B) (dense or scipy sparse) and the B bone names:
    each vertex's part is the one whose bones hold the largest share of its weight."""
    bone_part = np.array([part_of_bone(b) for b in bone_names])
    if len(bone_part) != weights.shape[1]:
        raise MeasurementError(f"parts_from_weights: {weights.shape[1]} weight columns but {len(bone_part)} bone "
                               "names, expected one name per column")
    # (B, P) indicator of each bone's part; weights @ it sums each vertex's weight per part.
    ind = np.zeros((len(bone_part), len(PARTS)))
    ok = bone_part >= 0
    ind[np.flatnonzero(ok), bone_part[ok]] = 1.0
    per_part = np.asarray(weights @ ind)
    out = np.argmax(per_part, axis=1).astype(np.int8)
    for part, share in CLAIMS_FROM_HEAD.items():
        out[(out == PART_INDEX["head"]) & (per_part[:, PART_INDEX[part]] >= share)] = PART_INDEX[part]
    out[per_part.max(axis=1) <= 0] = NO_PART
    return out


def part_landmarks(part) -> set:
    """The landmark names the ``SKELETON`` segments of ``part`` (a name or a list of them) use:
    what decides which vertices are that part on a topology labelled from its landmarks."""
    names = {part} if isinstance(part, str) else set(part)

    def used(spec) -> set:
        if isinstance(spec, str):
            return {spec}
        if spec and isinstance(spec[0], str) and spec[0].startswith("@"):
            return used(spec[1]) | used(spec[2])
        return set().union(*(used(x) for x in spec))

    return set().union(*(used(a) | used(b) for p, a, b in SKELETON if p in names))


def _point(spec, lm: dict) -> np.ndarray | None:
    """(..., 3) point of a skeleton end: a name, a tuple of names (mean), or ("@t", a, b)."""
    if isinstance(spec, str):
        return lm.get(spec)
    if spec and isinstance(spec[0], str) and spec[0].startswith("@"):
        a, b = _point(spec[1], lm), _point(spec[2], lm)
        if a is None or b is None:
            return None
        t = float(spec[0][1:])
        return a + t * (b - a)
    pts = [_point(s, lm) for s in spec]
    return None if any(p is None for p in pts) else np.mean(pts, axis=0)


def skeleton_segments(landmarks: dict) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The segments of ``SKELETON`` whose landmarks the set has: heads (S, 3), tails (S, 3) and
    their parts (S,), from landmark points name → (3,)."""
    heads, tails, part = [], [], []
    for name, a, b in SKELETON:
        pa, pb = _point(a, landmarks), _point(b, landmarks)
        if pa is not None and pb is not None:
            heads.append(pa)
            tails.append(pb)
            part.append(PART_INDEX[name])
    if not part:
        return np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0, dtype=np.int64)
    return np.array(heads, dtype=float), np.array(tails, dtype=float), np.array(part)


def parts_from_landmarks(vertices: np.ndarray, landmarks: dict, faces: np.ndarray | None = None,
                         chunk: int = 4096) -> np.ndarray:
    """(V,) part labels of one body (V, 3) from its landmark points name → (3,): each vertex on
    the nearest segment of ``SKELETON`` (``skeleton_segments``), feet past the ankles.

    With ``faces`` (F, 3) a segment beside a vertex only takes it when its outward normal points
    away from the segment (the skin faces away from its own bone): the inside of an arm hanging
    against the chest is nearer to the torso's flank line than to the arm's bone, but faces the
    torso, so it stays with the arm. Works on any topology; a standing body is best (the labels are then kept for
    every pose of that topology).
    """
    v = np.asarray(vertices, dtype=float)
    heads, tails, part = skeleton_segments(landmarks)
    out = np.full(len(v), NO_PART, dtype=np.int8)
    if not len(part):
        return out
    normals = vertex_normals(v, np.asarray(faces)) if faces is not None else None
    d = tails - heads
    dd = np.maximum(np.einsum("si,si->s", d, d), 1e-18)
    # The facing rule is for the torso and the long limb bones, whose skin is convex around them;
    # a face (eyes, mouth) and a hand (palm, fingers) have skin facing their own bone.
    trunk_and_limbs = np.isin(part, [PART_INDEX[p] for p in PARTS
                                     if p == "torso" or p.startswith(("upper_arm", "forearm", "thigh", "calf"))])
    torso = part == PART_INDEX["torso"]
    below = None
    hips, spine = _point(("hip_joint_l", "hip_joint_r"), landmarks), _point(("crotch", NECK), landmarks)
    if hips is not None and spine is not None:
        up = _point(NECK, landmarks) - landmarks["crotch"]
        below = (v - hips) @ (up / max(float(np.linalg.norm(up)), 1e-12)) < 0
    for s in range(0, len(v), chunk):
        x = v[s:s + chunk, None, :] - heads[None]                              # (C, S, 3)
        t_free = np.einsum("csi,si->cs", x, d) / dd
        t = np.clip(t_free, 0.0, 1.0)
        r = x - t[..., None] * d[None]
        dist = np.einsum("csi,csi->cs", r, r)
        # Below the hip joints (the buttocks' fold, the top of the thighs) the skin is the
        # thighs' unless the torso is much nearer: a vertex 10 cm behind the thigh's axis is
        # 8 cm from the end of the torso's spine line on a short body.
        if below is not None:
            dist = np.where(torso[None] & below[s:s + chunk, None], dist * BELOW_TORSO ** 2, dist)
        if normals is not None:
            # Skin facing a segment beside it is not that segment's part (the inside of an arm
            # against the chest faces the torso's flank line, the flank faces the arm's bone);
            # unless it faces every segment. Beyond a segment's ends (head top, fingers, the
            # concave skin of a joint) the rule does not apply.
            facing = ((np.einsum("csi,ci->cs", r, normals[s:s + chunk]) <= 0) & (t_free > 0) & (t_free < 1)
                      & trunk_and_limbs[None])
            dist = np.where(facing & ~facing.all(axis=1, keepdims=True), np.inf, dist)
        out[s:s + chunk] = part[np.argmin(dist, axis=1)]
    for calf, foot, knee, ankle in CHAIN_ENDS:
        if knee in landmarks and ankle in landmarks:
            k, a = landmarks[knee], landmarks[ankle]
            t = (v - k) @ (a - k) / max(float((a - k) @ (a - k)), 1e-18)
            out[(out == PART_INDEX[calf]) & (t > 1.0)] = PART_INDEX[foot]
    if faces is not None:
        out = merge_islands(out, np.asarray(faces))
    return out


def merge_islands(labels: np.ndarray, faces: np.ndarray, rounds: int = 50) -> np.ndarray:
    """(V,) labels where every part is one connected piece of the mesh: a part's pieces other
    than its largest (connected through edges between two of its vertices) take the part of
    the vertices around them.

    On a posed body the nearest skeleton segment is not always the vertex's own: with the arms
    crossed, 107 vertices of the right hand lay nearer to the left forearm's segment and 92 of
    the chest under it nearer to the right hand's (a 6,000-vertex foreign body), and the wrist
    tapes went round the other hand too (+9 and +16 cm). Such vertices are an island of the
    part that claimed them, apart from that part's own skin; they go to their neighbours' part
    (the most frequent among their edge neighbours off the island; repeated until every island
    vertex has a part). ``faces`` (F, 3).
    """
    out = np.asarray(labels).astype(np.int8).copy()
    n = len(out)
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    same = out[e[:, 0]] == out[e[:, 1]]
    graph = coo_matrix((np.ones(int(same.sum())), (e[same, 0], e[same, 1])), shape=(n, n))
    _, comp = connected_components(graph, directed=False)
    # The largest piece of each part stays; every other piece is an island.
    size = np.bincount(comp)
    _, first = np.unique(comp, return_index=True)              # a vertex of each piece
    piece_label = out[first].astype(np.int64)
    # Per label, its largest piece (sorted by label, then size descending: the first of each label).
    order = np.lexsort((-size, piece_label))
    keep = order[np.r_[True, piece_label[order][1:] != piece_label[order][:-1]]]
    main = np.zeros(len(size), dtype=bool)
    main[keep] = True
    island = ~main[comp]
    used = np.zeros(n, dtype=bool)
    used[faces.ravel()] = True
    island &= used                                   # a vertex on no face keeps its label
    for _ in range(rounds):
        if not island.any():
            break
        # Votes of settled neighbours, both directions of every edge.
        a = np.concatenate([e[:, 0], e[:, 1]])
        b = np.concatenate([e[:, 1], e[:, 0]])
        ok = island[a] & ~island[b] & (out[b] >= 0)
        if not ok.any():
            break
        votes = np.zeros((n, len(PARTS)), dtype=np.int32)
        np.add.at(votes, (a[ok], out[b[ok]].astype(np.int64)), 1)
        got = island & (votes.sum(axis=1) > 0)
        out[got] = np.argmax(votes[got], axis=1).astype(np.int8)
        island &= ~got
    return out


def axis_joints(vertices: np.ndarray, landmarks: dict, fallback, labels: np.ndarray | None = None,
                levels: tuple[float, float] = JOINT_LEVELS, parts: tuple[str, ...] = JOINT_PARTS,
                min_vertices: int = 6) -> tuple[dict, dict] | None:
    """The two joints of a joint axis on any topology, placed on one standing body (V, 3): rings of
    skin around the ``fallback`` line (a pair of points, e.g. neck landmarks → head top) at the
    fractions ``levels`` of it, as inline points ``{"vertices": [...], "weights": [...]}`` of
    this topology (``points.axis``), or None if a ring has fewer than ``min_vertices`` vertices.

    A ring is the vertices of ``parts`` (by ``labels`` (V,); all vertices without labels) within
    3 % of the line's length of the level, and within 1.5x the median distance of them from the
    line (the slab at the neck's base also reaches the shoulders), equally weighted. Like the
    template's joint regressor rows they are skin vertices, so they follow the neck into any pose:
    its axis leans with the neck and not with a head tilted on it. The slab is widened (up to
    4x) on a coarse mesh until it holds ``min_vertices``.
    """
    v = np.asarray(vertices, dtype=float)
    a, b = _point(fallback[0], landmarks), _point(fallback[1], landmarks)
    if a is None or b is None:
        return None
    d = b - a
    length = float(np.linalg.norm(d))
    if not np.isfinite(length) or length < 1e-6:
        return None
    d = d / length
    rel = v - a
    t = rel @ d / length                                                             # (V,)
    radial = np.linalg.norm(rel - np.outer(rel @ d, d), axis=1)                      # (V,)
    allowed = np.ones(len(v), dtype=bool)
    if labels is not None:
        allowed = np.isin(np.asarray(labels), [PART_INDEX[p] for p in parts])
    rings = []
    for level in levels:
        for widen in (1.0, 2.0, 4.0):
            ids = np.flatnonzero(allowed & (np.abs(t - level) < RING_HALF_WIDTH * widen))
            if len(ids):
                ids = ids[radial[ids] <= 1.5 * np.median(radial[ids])]
            if len(ids) >= min_vertices:
                break
        if len(ids) < min_vertices:
            return None
        rings.append({"vertices": [int(i) for i in ids], "weights": [1.0 / len(ids)] * len(ids)})
    return rings[0], rings[1]


def encode_parts(labels: np.ndarray) -> str:
    """(V,) labels as one letter a vertex (``_LETTERS``; "." for no part), for JSON."""
    letters = np.frombuffer((_LETTERS + ".").encode(), dtype=np.uint8)
    return letters[np.asarray(labels, dtype=np.int64)].tobytes().decode()


def decode_parts(text: str, where: str) -> np.ndarray:
    """The inverse of ``encode_parts``; errors name ``where`` and the bad letter."""
    if not isinstance(text, str):
        raise MeasurementError(f"{where}: got {type(text).__name__}, expected a string of one letter a vertex "
                               f"({_LETTERS} for {', '.join(PARTS)}; '.' for none)")
    lut = np.full(256, -2, dtype=np.int8)
    for i, c in enumerate(_LETTERS):
        lut[ord(c)] = i
    lut[ord(".")] = NO_PART
    raw = np.frombuffer(text.encode("latin-1", errors="replace"), dtype=np.uint8)
    out = lut[raw]
    if (out == -2).any():
        i = int(np.flatnonzero(out == -2)[0])
        raise MeasurementError(f"{where}: letter {text[i]!r} at vertex {i} is no part; expected one of "
                               f"{_LETTERS} ({', '.join(PARTS)}) or '.'")
    return out
