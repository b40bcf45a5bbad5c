"""Skeleton matching: which joint of a source skeleton drives which bone of a target (Rupprecht §3.3.2).

Both skeletons are read as a ``JointGraph``: named joints with parents and rest-pose pivots in
metres (a BVH joint's position; a rig bone's head), plus the end of each joint's own segment
(a BVH End Site, a bone's tail). The match is decided by **structure and rest-pose geometry
only**, in the order Rupprecht gives (``body_anatomy``):

1. **Leaves**: the five extremities are the terminal joints farthest apart in the tree (greedy
   farthest-point selection on tree distances, four limbs first); of the four limbs, the pair
   whose common parent is deeper in the tree (or, on a tie, nearer each other) is the hands, the
   other the feet; the head is the terminal outside the limbs farthest from the pelvis.
2. **Common parents**: the pelvis is the feet's lowest common ancestor, the chest the hands'.
3. **Joints between**, chain by chain (legs and arms from pelvis/chest to hand/foot, the spine
   from pelvis to chest, the neck from chest to head), at landmarks found by geometry:
   hip = first leg joint off the mid-plane; ankle = first joint whose bone turns forward (the
   foot), else the leg's end; knee = the joint nearest the middle of hip→ankle; wrist = the
   first branching joint in the hand's part of the arm (fingers), else the arm's last joint;
   elbow and shoulder = the starts of the last two straight pieces before the wrist (cut where
   the arm bends more than 20°; the upper arm's start is the joint of its piece that gives it an
   upper arm's length; one straight upper arm + forearm is split in that proportion); head = the
   common parent of every end joint above the neck. Landmarks match landmarks; the joints
   between two landmarks match by their position along the arc (a monotone dynamic programme
   that may leave joints unmatched: twist bones, extra spine joints). A chain's first joints
   (clavicles, pelvis bones) match.
4. Whatever hangs off a matched pair and is not on a chain (fingers, toes, face, breasts, helper
   bones) is matched child to child by bone direction, after turning the source's frame
   (incoming bone, body front) onto the target's (Hungarian assignment, up to 60°), recursively.

Left and right come from geometry: left = up × front, front from the feet (toes point forward),
else from name hints (``joint_names.json``: Left/L/.L/_l ...), else the skeleton is assumed to
face +Z. Name hints never change a structural match: they label the report and flag a pair whose
names disagree. A user overrides any pair with a JSON map file (``load_joint_map``).

The result (``SkeletonMatch``) is what retargeting needs: ``pairs`` (source joint -> target bone,
with the body part, the role and the reason), ``unmatched`` joints of both sides with the reason,
``segments`` (for each matched pair, its nearest matched ancestor pair and the joints of both
skeletons between them: a source bone that spans several target bones, or the reverse), the
``landmarks`` of both skeletons (hips, knees, ankles, toes for leg lengths, contacts and IK) and
both skeletons' body axes (up, left, front) in their own coordinates.
"""

from __future__ import annotations

import json
import re
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path

import numpy as np
from scipy.optimize import linear_sum_assignment

from bodyspace.data.template import RIG_NAMES, load_template
from bodyspace.errors import MotionError, ParameterError
from bodyspace.motion.bvh import Motion
from bodyspace.rig.kinematics import bone_depths
from bodyspace.rig.skeleton import Skeleton, body_skeleton

__all__ = ["Anatomy", "JointGraph", "JointPair", "Segment", "SkeletonMatch", "body_anatomy", "graph_from_motion",
           "graph_from_skeleton", "load_joint_map", "match_skeletons", "name_roles", "rig_graph"]

NAME_HINTS = Path(__file__).with_name("joint_names.json")
# Fractions of the skeleton's size (tree distance foot -> head) and angles that define landmarks.
_HIP_OFF_MIDPLANE = 0.03      # a hip pivot is this far from the mid-plane (pelvis bones are on it)
_FOOT_TURN_DEG = 50.0         # the foot's bone points this far from straight down
_HAND_START = 0.6             # fingers branch past this fraction of the arm's arc
_BEND_DEG = 20.0              # an arm chain turning more than this at a joint starts a new straight piece
_STRAIGHT_ARM = 1.6           # a last straight piece this much longer than the one before holds the elbow too
_UPPER_TO_FOREARM = 1.1       # upper arm / forearm, joint to joint: 1.0 in MakeHuman rigs, 1.3 in CMU
_SKIP_COST = 0.15             # a joint between landmarks stays unmatched rather than move this far on the arc
_MAX_CHILD_ANGLE_DEG = 60.0   # children off the chains pair up to this angle apart
_SNAP_DEG = 30.0              # body axes within this of a coordinate axis are snapped to it


# ----------------------------------------------------------------------------- graphs

@dataclass(frozen=True)
class JointGraph:
    """A skeleton as matching sees it.

    names: (J,); parents: (J,) int, -1 for a root, parents before children not required;
    pivots: (J, 3) rest-pose joint positions (a bone's head), metres; tips: (J, 3) the end of
    each joint's own segment (End Site, bone tail, or its single child's pivot), NaN if unknown.
    """

    name: str
    names: tuple[str, ...]
    parents: np.ndarray
    pivots: np.ndarray
    tips: np.ndarray

    def __post_init__(self):
        J = len(self.names)
        object.__setattr__(self, "names", tuple(str(n) for n in self.names))
        object.__setattr__(self, "parents", np.asarray(self.parents, dtype=np.int64))
        object.__setattr__(self, "pivots", np.asarray(self.pivots, dtype=float))
        object.__setattr__(self, "tips", np.asarray(self.tips, dtype=float))
        if self.parents.shape != (J,) or self.pivots.shape != (J, 3) or self.tips.shape != (J, 3):
            raise MotionError(f"skeleton {self.name!r}: parents/pivots/tips of shapes {self.parents.shape}, "
                              f"{self.pivots.shape}, {self.tips.shape}; expected ({J},), ({J}, 3), ({J}, 3)")
        if len(set(self.names)) != J:
            raise MotionError(f"skeleton {self.name!r}: joint names repeat; expected unique names")
        if not np.isfinite(self.pivots).all():
            raise MotionError(f"skeleton {self.name!r}: joint positions hold NaN or infinity")
        _depths(self.parents, self.name)  # refuses cycles and bad indices

    @property
    def n_joints(self) -> int:
        return len(self.names)

    def index(self, name: str) -> int:
        try:
            return self.names.index(name)
        except ValueError:
            raise MotionError(f"joint {name!r}: not in skeleton {self.name!r}") from None


def _depths(parents: np.ndarray, label: str) -> np.ndarray:
    """(J,) depth of each joint of the skeleton ``label``; ``MotionError`` naming it for a parent
    index out of range or a cycle."""
    try:
        return bone_depths(parents)
    except ParameterError as exc:
        raise MotionError(f"skeleton {label!r}: {exc}") from None


def graph_from_motion(motion: Motion) -> JointGraph:
    """The rest skeleton of a BVH motion (every channel zero), metres, the file's axes."""
    sk = motion.skeleton
    pivots = motion.rest_positions()
    tips = np.full_like(pivots, np.nan)
    ends = sk.rest_end_sites() * motion.unit
    for j in range(sk.n_joints):
        own = ends[sk.end_site_parents == j]
        kids = sk.children(j)
        if len(own):
            tips[j] = own.mean(axis=0)
        elif len(kids) == 1:
            tips[j] = pivots[kids[0]]
    return JointGraph(motion.name, sk.names, sk.parents, pivots, tips)


def graph_from_skeleton(skeleton: Skeleton) -> JointGraph:
    """A rig's skeleton: pivots are bone heads, tips bone tails (metres, our axes)."""
    return JointGraph(skeleton.name, skeleton.bone_names, skeleton.parents, skeleton.heads, skeleton.tails)


def rig_graph(rig: str, vertices: np.ndarray | None = None) -> JointGraph:
    """The graph of a CC0 rig on a body of the template topology (default: the template)."""
    if rig not in RIG_NAMES:
        raise MotionError(f"rig {rig!r}: not a CC0 rig of the template; expected one of {', '.join(RIG_NAMES)}")
    template = load_template()
    return graph_from_skeleton(body_skeleton(template.rigs[rig], template.vertices if vertices is None else vertices))


# ----------------------------------------------------------------------------- name hints

@lru_cache(maxsize=1)
def _hints() -> tuple[dict[str, set[str]], dict[str, list[re.Pattern]]]:
    data = json.loads(NAME_HINTS.read_text())
    roles: dict[str, set[str]] = {}
    for role, names in data["roles"].items():
        for n in names:
            roles.setdefault(n.lower(), set()).add(role)
    sides = {s: [re.compile(p) for p in pats] for s, pats in data["sides"].items()}
    return roles, sides


def _bare(name: str) -> str:
    return name.rsplit(":", 1)[-1]


def name_roles(name: str) -> set[str]:
    """Body roles a joint name stands for in known namings (``joint_names.json``), e.g.
    ``"mixamorig:LeftForeArm"`` -> ``{"elbow.L"}``; empty for an unknown name."""
    return set(_hints()[0].get(_bare(name).lower(), set()))


def _name_side(name: str) -> str | None:
    hits = [s for s, pats in _hints()[1].items() if any(p.search(_bare(name)) for p in pats)]
    return hits[0] if len(hits) == 1 else None


# ----------------------------------------------------------------------------- anatomy

@dataclass(frozen=True)
class Anatomy:
    """Body parts and landmarks of one skeleton (joint indices of its graph).

    chains: part name -> joint indices from the trunk outwards ("leg.L", "leg.R", "arm.L",
    "arm.R", "spine" (pelvis excluded, chest included), "neck" (chest excluded, head included)).
    landmarks: role -> joint index ("pelvis", "chest", "head", "hip.L", "knee.L", "ankle.L",
    "toe.L", "clavicle.L", "shoulder.L", "elbow.L", "wrist.L", ... and ".R"); a role the skeleton
    lacks is absent. axes: (3, 3) rows up, left, front in the skeleton's coordinates.
    scale: tree distance from a foot's tip to the head's (metres). notes: how sides were decided.
    """

    graph: JointGraph
    chains: dict[str, tuple[int, ...]]
    landmarks: dict[str, int]
    axes: np.ndarray
    scale: float
    notes: tuple[str, ...] = ()


class _Tree:
    """Tree queries on a graph: children, depths, paths, lowest common ancestors, tree distances."""

    def __init__(self, g: JointGraph):
        self.g = g
        self.parents = g.parents
        self.depth = _depths(g.parents, g.name)
        self.children = [[] for _ in range(g.n_joints)]
        for j, p in enumerate(g.parents):
            if p >= 0:
                self.children[p].append(j)
        self.leaves = [j for j in range(g.n_joints) if not self.children[j]]
        self.tip = np.where(np.isfinite(g.tips).all(axis=1)[:, None], g.tips, g.pivots)
        # length along the bones from each joint's pivot up to its root's
        self.to_root = np.zeros(g.n_joints)
        for j in np.argsort(self.depth, kind="stable"):
            p = g.parents[j]
            if p >= 0:
                self.to_root[j] = self.to_root[p] + float(np.linalg.norm(g.pivots[j] - g.pivots[p]))

    def up_path(self, j: int) -> list[int]:
        """j, its parent, ... the root."""
        out = []
        while j >= 0:
            out.append(j)
            j = int(self.parents[j])
        return out

    def lca(self, a: int, b: int) -> int:
        pa = set(self.up_path(a))
        for x in self.up_path(b):
            if x in pa:
                return x
        return -1

    def path(self, a: int, b: int) -> list[int]:
        """Joints from a to b (both included) through their lowest common ancestor."""
        c = self.lca(a, b)
        if c < 0:
            return []
        up_a = self.up_path(a)
        up_b = self.up_path(b)
        return up_a[:up_a.index(c) + 1] + list(reversed(up_b[:up_b.index(c)]))

    def distance(self, a: int, b: int, tips: bool = True) -> float:
        """Tree distance between the tips of terminals a and b along the bones; a common
        ancestor's own pivot is skipped when the path only passes by it (two children attached
        at a bone's tail are next to each other, not a bone's length apart)."""
        x, y, ca, cb = a, b, -1, -1  # walk up to the common ancestor, remembering its children
        while x != y:
            if self.depth[x] >= self.depth[y]:
                ca, x = x, int(self.parents[x])
            else:
                cb, y = y, int(self.parents[y])
            if x < 0 or y < 0:
                return np.inf
        c, P = x, self.g.pivots
        if ca < 0 or cb < 0:  # one is an ancestor of the other
            d = abs(self.to_root[a] - self.to_root[b])
        else:
            d = (self.to_root[a] - self.to_root[ca]) + float(np.linalg.norm(P[ca] - P[cb])) \
                + (self.to_root[b] - self.to_root[cb])
        if tips:
            d += float(np.linalg.norm(self.tip[a] - P[a])) + float(np.linalg.norm(self.tip[b] - P[b]))
        return d

    def arc(self, chain: list[int] | tuple[int, ...]) -> np.ndarray:
        """Cumulative pivot-to-pivot length along a chain, starting at 0."""
        P = self.g.pivots[list(chain)]
        return np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(P, axis=0), axis=1))])

    def subtree(self, j: int) -> list[int]:
        out, todo = [], [j]
        while todo:
            x = todo.pop()
            out.append(x)
            todo.extend(self.children[x])
        return out


def _snap(v: np.ndarray) -> np.ndarray:
    """A unit vector snapped to the nearest coordinate axis when within _SNAP_DEG of it."""
    v = v / np.linalg.norm(v)
    k = int(np.argmax(np.abs(v)))
    if abs(v[k]) >= np.cos(np.radians(_SNAP_DEG)):
        out = np.zeros(3)
        out[k] = np.sign(v[k])
        return out
    return v


def body_anatomy(graph: JointGraph) -> Anatomy:
    """Find the body parts and landmarks of a skeleton by structure and rest-pose geometry
    (module docstring, steps 1-3). Raises MotionError naming what could not be found."""
    t = _Tree(graph)
    label = graph.name
    if len(t.leaves) < 5:
        raise MotionError(f"skeleton {label!r}: {len(t.leaves)} end joints; a body needs at least five (head, two "
                          "hands, two feet) to be matched by structure; give a map file (--map) instead")
    leaves = t.leaves
    D = np.array([[t.distance(a, b) if a != b else 0.0 for b in leaves] for a in leaves])
    if not np.isfinite(D).all():
        raise MotionError(f"skeleton {label!r}: has more than one root; expected one connected tree")
    # 1. leaves: four limbs by farthest-point selection (start from an end of the tree's diameter)
    first = int(np.argmax(D[int(np.argmax(D[0]))]))
    picks = [int(np.argmax(D[first])), first][::-1]
    while len(picks) < 4:
        picks.append(int(np.argmax(np.min(D[:, picks], axis=1))))
    limbs = [leaves[i] for i in picks]
    pairings = [((0, 1), (2, 3)), ((0, 2), (1, 3)), ((0, 3), (1, 2))]

    def pair_key(pair):
        a, b = limbs[pair[0]], limbs[pair[1]]
        return t.depth[t.lca(a, b)], -D[picks[pair[0]], picks[pair[1]]]

    best = None
    for p1, p2 in pairings:  # the hands are the pair whose common parent is deeper (tie: nearer)
        hands, feet = (p1, p2) if pair_key(p1) > pair_key(p2) else (p2, p1)
        score = pair_key(hands)
        # a valid split keeps each pair's common parent off the other pair's paths
        lca_h = t.lca(limbs[hands[0]], limbs[hands[1]])
        lca_f = t.lca(limbs[feet[0]], limbs[feet[1]])
        ok = lca_h not in t.path(limbs[feet[0]], limbs[feet[1]]) or lca_h == lca_f
        cand = (ok, score, hands, feet)
        if best is None or cand[:2] > best[:2]:
            best = cand
    _, _, hands_i, feet_i = best
    hands = [limbs[i] for i in hands_i]
    feet = [limbs[i] for i in feet_i]
    # 2. common parents
    pelvis = t.lca(*feet)
    chest = t.lca(*hands)
    if pelvis in t.path(*hands) and pelvis != chest:
        raise MotionError(f"skeleton {label!r}: the feet's common parent {graph.names[pelvis]!r} lies between the "
                          "hands; cannot tell the legs from the arms by structure; give a map file (--map)")

    def limb_chain(base: int, end: int) -> list[int]:
        p = t.path(base, end)
        return p[1:] if p and p[0] == base else p

    legs = [limb_chain(pelvis, f) for f in feet]
    arms = [limb_chain(chest, h) for h in hands]
    limb_joints = set()
    for ch in legs + arms:
        if ch:
            limb_joints.update(t.subtree(ch[0]))
    head_candidates = [j for j in leaves if j not in limb_joints and j not in (pelvis, chest)]
    if not head_candidates:
        raise MotionError(f"skeleton {label!r}: no end joint besides the hands and feet, so no head; give a map "
                          "file (--map)")
    head_leaf = max(head_candidates, key=lambda j: t.distance(pelvis, j))
    neck_full = limb_chain(chest, head_leaf)
    head = head_leaf
    if neck_full:  # the head holds every end joint above the neck (face, eyes, jaw): their common parent
        ends = [j for j in t.subtree(neck_full[0]) if not t.children[j]]
        head = ends[0]
        for j in ends[1:]:
            head = t.lca(head, j)
    scale = float(np.mean([t.distance(f, head) for f in feet]))
    if not scale > 0:
        raise MotionError(f"skeleton {label!r}: has no size (every joint at one point)")

    # body axes: up from the feet to the head; left across the hands (or feet); front = left x up
    P = graph.pivots
    up = _snap(t.tip[head] - 0.5 * (P[feet[0]] + P[feet[1]]))
    across = t.tip[hands[0]] - t.tip[hands[1]]
    across = across - up * (across @ up)
    if np.linalg.norm(across) < 1e-6 * scale:
        across = P[feet[0]] - P[feet[1]]
        across = across - up * (across @ up)
    across = _snap(across)
    front0 = np.cross(across, up)  # the front if limb 0 of each pair is the left one
    notes = []
    toe_dir = sum(t.tip[f] - P[ch[0]] for f, ch in zip(feet, legs) if ch)
    toe_dir = toe_dir - up * (toe_dir @ up)
    if np.linalg.norm(toe_dir) > 0.05 * scale:
        first_is_left = bool(toe_dir @ front0 > 0)
        notes.append("left/right from the feet: the toes point to the front")
    else:
        votes = sum(+1 if _name_side(graph.names[j]) == "L" else -1 if _name_side(graph.names[j]) == "R" else 0
                    for j in arms[0] + legs[0]) - \
            sum(+1 if _name_side(graph.names[j]) == "L" else -1 if _name_side(graph.names[j]) == "R" else 0
                for j in arms[1] + legs[1])
        if votes:
            first_is_left = votes > 0
            notes.append("left/right from the joint names (the feet have no forward bones)")
        else:
            first_is_left = bool(front0 @ np.array([0.0, 0.0, 1.0]) >= 0)
            notes.append("left/right assumed: the skeleton faces +Z (no forward feet, no side in the names)")
    left = across if first_is_left else -across
    front = np.cross(left, up)

    def side_of(chain: list[int], end: int) -> float:  # mean lateral position of a limb
        return float(np.mean(np.vstack([P[chain], t.tip[end][None]]) @ left)) if chain else float(t.tip[end] @ left)

    if side_of(legs[0], feet[0]) < side_of(legs[1], feet[1]):
        feet, legs = feet[::-1], legs[::-1]
    if side_of(arms[0], hands[0]) < side_of(arms[1], hands[1]):
        hands, arms = hands[::-1], arms[::-1]
    axes = np.stack([up, left, front])

    landmarks = {"pelvis": pelvis, "chest": chest}
    chains: dict[str, tuple[int, ...]] = {}
    mid = float(np.mean(P[t.path(pelvis, chest)] @ left)) if chest != pelvis else float(P[pelvis] @ left)
    for side, leg, arm in (("L", legs[0], arms[0]), ("R", legs[1], arms[1])):
        marks = _leg_landmarks(t, leg, side, up, left, mid, scale)
        marks.update(_arm_landmarks(t, arm, side, left, mid, scale))
        landmarks.update(marks)
        # chains end at the foot's toe (or ankle) and at the wrist: what lies beyond (toes, fingers)
        # is matched child by child
        foot_end = marks.get(f"toe.{side}", marks.get(f"ankle.{side}"))
        chains[f"leg.{side}"] = tuple(leg[:leg.index(foot_end) + 1] if foot_end in leg else leg)
        wrist = marks.get(f"wrist.{side}")
        chains[f"arm.{side}"] = tuple(arm[:arm.index(wrist) + 1] if wrist in arm else arm)
    spine = limb_chain(pelvis, chest) if chest != pelvis else []
    chains["spine"] = tuple(spine)
    chains["neck"] = tuple(neck_full[:neck_full.index(head) + 1]) if head in neck_full else ()
    landmarks["head"] = head
    return Anatomy(graph, chains, landmarks, axes, scale, tuple(notes))


def _segment_dir(t: _Tree, chain, k: int) -> np.ndarray:
    P = t.g.pivots
    end = P[chain[k + 1]] if k + 1 < len(chain) else t.tip[chain[k]]
    return end - P[chain[k]]


def _leg_landmarks(t: _Tree, leg, side, up, left, mid, scale) -> dict[str, int]:
    out: dict[str, int] = {}
    if not leg:
        return out
    P = t.g.pivots
    hip_k = next((k for k, j in enumerate(leg) if abs(P[j] @ left - mid) >= _HIP_OFF_MIDPLANE * scale), None)
    if hip_k is None:
        return out
    out[f"hip.{side}"] = leg[hip_k]
    arc = t.arc(leg)
    ankle_k = None
    for k in range(hip_k + 1, len(leg)):
        d = _segment_dir(t, leg, k)
        n = np.linalg.norm(d)
        if n > 1e-9 and np.degrees(np.arccos(np.clip(-(d @ up) / n, -1, 1))) > _FOOT_TURN_DEG:
            ankle_k = k
            break
    end_arc = arc[ankle_k] if ankle_k is not None else arc[-1] + float(np.linalg.norm(t.tip[leg[-1]] - P[leg[-1]]))
    if ankle_k is not None:
        out[f"ankle.{side}"] = leg[ankle_k]
        if ankle_k + 1 < len(leg):
            out[f"toe.{side}"] = leg[ankle_k + 1]
    stop = ankle_k if ankle_k is not None else len(leg)
    inner = [k for k in range(hip_k + 1, stop)]
    if inner:
        span = end_arc - arc[hip_k]
        frac = [(arc[k] - arc[hip_k]) / span for k in inner]
        k = inner[int(np.argmin(np.abs(np.array(frac) - 0.5)))]
        if 0.3 <= (arc[k] - arc[hip_k]) / span <= 0.7:
            out[f"knee.{side}"] = leg[k]
    return out


def _arm_landmarks(t: _Tree, arm, side, left, mid, scale) -> dict[str, int]:
    out: dict[str, int] = {}
    if not arm:
        return out
    P = t.g.pivots
    arc = t.arc(arm)
    total = arc[-1] + float(np.linalg.norm(t.tip[arm[-1]] - P[arm[-1]]))
    wrist_k = len(arm) - 1
    for k, j in enumerate(arm):
        if len(t.children[j]) > 1 and arc[k] >= _HAND_START * total:
            wrist_k = k
            break
    out[f"wrist.{side}"] = arm[wrist_k]

    # straight pieces of the arm up to the wrist: a new piece starts where the chain bends
    d = [P[arm[k + 1]] - P[arm[k]] for k in range(wrist_k)]
    starts, last_dir = [0], None
    for k in range(wrist_k):
        n = np.linalg.norm(d[k])
        if n < 1e-9:
            continue
        u = d[k] / n
        if last_dir is not None and np.degrees(np.arccos(np.clip(u @ last_dir, -1, 1))) > _BEND_DEG:
            starts.append(k)
        last_dir = u
    if wrist_k == 0:
        return out
    pieces = [(a, b) for a, b in zip(starts, starts[1:] + [wrist_k])]
    length = [arc[b] - arc[a] for a, b in pieces]
    last = pieces[-1]
    if len(pieces) >= 2 and length[-1] <= _STRAIGHT_ARM * length[-2]:
        elbow_k = last[0]
        fore = arc[wrist_k] - arc[elbow_k]
        # the upper arm starts at the joint of its piece that gives it an upper arm's length (a
        # clavicle bent less than _BEND_DEG from the upper arm shares its piece)
        shoulder_k = min(range(*pieces[-2]),
                         key=lambda k: abs(np.log(max(arc[elbow_k] - arc[k], 1e-12) / fore / _UPPER_TO_FOREARM)))
    elif last[1] - last[0] >= 2:  # upper arm and forearm in one straight line: split it
        inner = range(last[0] + 1, last[1])
        target = _UPPER_TO_FOREARM / (1 + _UPPER_TO_FOREARM)
        elbow_k = min(inner, key=lambda k: abs((arc[k] - arc[last[0]]) / length[-1] - target))
        shoulder_k = last[0]
    else:
        return out
    while shoulder_k < elbow_k - 1 and abs(P[arm[shoulder_k]] @ left - mid) < _HIP_OFF_MIDPLANE * scale:
        shoulder_k += 1  # a clavicle's root on the mid-plane is not a shoulder
    out[f"shoulder.{side}"] = arm[shoulder_k]
    out[f"elbow.{side}"] = arm[elbow_k]
    if shoulder_k > 0:
        out[f"clavicle.{side}"] = arm[0]
    return out


# ----------------------------------------------------------------------------- match result

@dataclass(frozen=True)
class JointPair:
    """One source joint driving one target bone."""

    source: str
    target: str
    part: str      # "leg.L", "arm.R", "spine", "neck", "hand.L", "trunk", ... or "map file"
    role: str      # the landmark both share ("knee.L"), or "" for a joint between landmarks
    reason: str


@dataclass(frozen=True)
class Segment:
    """The joints between a matched pair and its nearest matched ancestor pair, in both skeletons.

    ``source`` and ``target`` list the joints strictly between ``parent`` and ``child`` (pairs
    given as (source joint, target bone)); a retargeter spreads the source's rotation over the
    target bones of the segment (e.g. one CMU spine joint over three spine bones). ``parent`` is
    None for the root pair.
    """

    parent: tuple[str, str] | None
    child: tuple[str, str]
    source: tuple[str, ...]
    target: tuple[str, ...]


@dataclass(frozen=True)
class SkeletonMatch:
    """Result of ``match_skeletons`` (module docstring)."""

    source: str
    target: str
    pairs: tuple[JointPair, ...]
    unmatched_source: tuple[tuple[str, str], ...]   # (joint, why)
    unmatched_target: tuple[tuple[str, str], ...]
    segments: tuple[Segment, ...]
    source_landmarks: dict[str, str]
    target_landmarks: dict[str, str]
    source_axes: np.ndarray   # (3, 3) rows up, left, front in the source's coordinates
    target_axes: np.ndarray
    notes: tuple[str, ...] = ()
    warnings: tuple[str, ...] = ()

    @property
    def mapping(self) -> dict[str, str]:
        """source joint -> target bone."""
        return {p.source: p.target for p in self.pairs}

    def to_dict(self) -> dict:
        return {
            "source": self.source, "target": self.target,
            "pairs": [vars(p) for p in self.pairs],
            "unmatched_source": [{"joint": j, "why": w} for j, w in self.unmatched_source],
            "unmatched_target": [{"joint": j, "why": w} for j, w in self.unmatched_target],
            "segments": [{"parent": list(s.parent) if s.parent else None, "child": list(s.child),
                          "source_between": list(s.source), "target_between": list(s.target)} for s in self.segments],
            "landmarks": {"source": self.source_landmarks, "target": self.target_landmarks},
            "axes": {side: {k: a[i].round(6).tolist() for i, k in enumerate(("up", "left", "front"))}
                     for side, a in (("source", self.source_axes), ("target", self.target_axes))},
            "notes": list(self.notes), "warnings": list(self.warnings),
        }

    def report(self) -> str:
        """A plain-text report: what matched what, what was left unmatched and why."""
        lines = [f"{self.source} -> {self.target}: {len(self.pairs)} pairs, {len(self.unmatched_source)} source "
                 f"joints and {len(self.unmatched_target)} target bones unmatched"]
        w = max([len(p.source) for p in self.pairs] + [6])
        for p in self.pairs:
            role = f" [{p.role}]" if p.role else ""
            lines.append(f"  {p.source:<{w}} -> {p.target}{role}  ({p.part}: {p.reason})")
        if self.unmatched_source:
            lines.append("unmatched source joints:")
            lines += [f"  {j}: {why}" for j, why in self.unmatched_source]
        if self.unmatched_target:
            lines.append("unmatched target bones:")
            lines += [f"  {j}: {why}" for j, why in self.unmatched_target]
        lines += [f"note: {n}" for n in self.notes]
        lines += [f"warning: {x}" for x in self.warnings]
        return "\n".join(lines)


# ----------------------------------------------------------------------------- matching

def _dp_align(a: np.ndarray, b: np.ndarray, skip: float = _SKIP_COST) -> list[tuple[int, int]]:
    """Monotone one-to-one alignment of positions a (n,) and b (m,) minimizing the summed
    distance of matched pairs plus ``skip`` for every unmatched element of either side."""
    n, m = len(a), len(b)
    C = np.zeros((n + 1, m + 1))
    C[:, 0] = np.arange(n + 1) * skip
    C[0, :] = np.arange(m + 1) * skip
    move = np.zeros((n + 1, m + 1), dtype=np.int8)
    move[1:, 0], move[0, 1:] = 1, 2
    for i in range(1, n + 1):
        for k in range(1, m + 1):
            opts = (C[i - 1, k - 1] + abs(a[i - 1] - b[k - 1]), C[i - 1, k] + skip, C[i, k - 1] + skip)
            move[i, k] = int(np.argmin(opts))
            C[i, k] = opts[move[i, k]]
    pairs, i, k = [], n, m
    while i > 0 or k > 0:
        mv = move[i, k] if i > 0 and k > 0 else (1 if i > 0 else 2)
        if mv == 0:
            pairs.append((i - 1, k - 1))
            i, k = i - 1, k - 1
        elif mv == 1:
            i -= 1
        else:
            k -= 1
    return pairs[::-1]


class _Matcher:
    def __init__(self, src: Anatomy, tgt: Anatomy):
        self.src, self.tgt = src, tgt
        self.ts, self.tt = _Tree(src.graph), _Tree(tgt.graph)
        self.pairs: dict[int, tuple[int, str, str, str]] = {}  # source -> (target, part, role, reason)
        self.taken: set[int] = set()
        self.why_s: dict[int, str] = {}
        self.why_t: dict[int, str] = {}

    def add(self, s: int, t: int, part: str, role: str, reason: str) -> None:
        if s in self.pairs or t in self.taken:
            return
        self.pairs[s] = (t, part, role, reason)
        self.taken.add(t)

    def chain_spans(self, part: str, roles: list[str]) -> None:
        """Match a chain's landmarks, its first joints, and the joints between by arc position."""
        cs, ct = self.src.chains.get(part, ()), self.tgt.chains.get(part, ())
        if not cs or not ct:
            for j in cs:
                self.why_s.setdefault(j, f"{part}: the target has no {part}")
            for j in ct:
                self.why_t.setdefault(j, f"{part}: the source has no {part}")
            return
        ls, lt = self.src.landmarks, self.tgt.landmarks
        anchors = []
        for role in roles:
            if role in ls and role in lt and ls[role] in cs and lt[role] in ct:
                anchors.append((cs.index(ls[role]), ct.index(lt[role]), role, "landmark found by structure"))
        anchors.sort()
        if not anchors or (anchors[0][0] > 0 and anchors[0][1] > 0):
            anchors.insert(0, (0, 0, "", "the first joint of the chain in both"))
        kept, last = [], (-1, -1)
        for a in anchors:  # keep anchors in order along both chains
            if a[0] > last[0] and a[1] > last[1]:
                kept.append(a)
                last = a[:2]
            elif a[:2] == last and a[2]:
                kept[-1] = a
        for i, k, role, why in kept:
            self.add(cs[i], ct[k], part, role, why)
        arc_s, arc_t = self.ts.arc(cs), self.tt.arc(ct)
        ends = kept + [(len(cs), len(ct), None, None)]
        for (i0, k0, *_), (i1, k1, *_) in zip(ends[:-1], ends[1:]):
            si, ti = list(range(i0 + 1, i1)), list(range(k0 + 1, k1))
            if not si or not ti:
                for i in si:
                    self.why_s.setdefault(cs[i], f"{part}: between {self.src.graph.names[cs[i0]]} and the next "
                                          "landmark; the target has no joint there")
                for k in ti:
                    self.why_t.setdefault(ct[k], f"{part}: between {self.tgt.graph.names[ct[k0]]} and the next "
                                          "landmark; the source has no joint there")
                continue

            def frac(arc, lo, hi, idx, chain, tree):
                end = arc[hi] if hi < len(arc) else arc[-1] + float(np.linalg.norm(tree.tip[chain[-1]]
                                                                                    - tree.g.pivots[chain[-1]]))
                span = max(end - arc[lo], 1e-12)
                return np.array([(arc[x] - arc[lo]) / span for x in idx])

            fs, ft = frac(arc_s, i0, i1, si, cs, self.ts), frac(arc_t, k0, k1, ti, ct, self.tt)
            done_s, done_t = set(), set()
            for a, b in _dp_align(fs, ft):
                self.add(cs[si[a]], ct[ti[b]], part, "", f"between landmarks at {fs[a]:.2f} and {ft[b]:.2f} of the "
                         "span")
                done_s.add(a)
                done_t.add(b)
            for a in set(range(len(si))) - done_s:
                self.why_s.setdefault(cs[si[a]], f"{part}: at {fs[a]:.2f} of its span no target joint is within "
                                      f"{2 * _SKIP_COST:.2f} (a split or twist joint)")
            for b in set(range(len(ti))) - done_t:
                self.why_t.setdefault(ct[ti[b]], f"{part}: at {ft[b]:.2f} of its span no source joint is within "
                                      f"{2 * _SKIP_COST:.2f} (a split or twist bone)")

    def children(self, s: int, t: int, part: str) -> None:
        """Match unmatched children of a matched pair by direction (module docstring, step 4)."""
        gs, gt = self.src.graph, self.tgt.graph
        Us = [c for c in self.ts.children[s] if c not in self.pairs]
        Ut = [c for c in self.tt.children[t] if c not in self.taken]
        if not Us or not Ut:
            return
        turn = self._turn(s, t)

        def direction(tree: _Tree, j: int, base: int) -> np.ndarray:
            pts = np.array([tree.tip[x] for x in tree.subtree(j)] + [tree.g.pivots[j]])
            d = pts.mean(axis=0) - tree.g.pivots[base]
            n = np.linalg.norm(d)
            return d / n if n > 1e-12 else d

        ds = np.array([turn @ direction(self.ts, c, s) for c in Us])
        dt = np.array([direction(self.tt, c, t) for c in Ut])
        ang = np.degrees(np.arccos(np.clip(ds @ dt.T, -1, 1)))
        rows, cols = linear_sum_assignment(ang)
        for r, c in zip(rows, cols):
            if ang[r, c] <= _MAX_CHILD_ANGLE_DEG:
                self.add(Us[r], Ut[c], part, "", f"child of {gs.names[s]} -> {gt.names[t]}, bone directions "
                         f"{ang[r, c]:.0f} deg apart")
            else:
                self.why_s.setdefault(Us[r], f"child of {gs.names[s]}: the closest child of {gt.names[t]} "
                                      f"({gt.names[Ut[c]]}) points {ang[r, c]:.0f} deg away")

    @staticmethod
    def _incoming(tree: _Tree, j: int) -> np.ndarray:
        """The bone arriving at j: from the nearest ancestor pivot that is not at j's pivot."""
        P = tree.g.pivots
        for a in tree.up_path(j)[1:]:
            d = P[j] - P[a]
            if np.linalg.norm(d) > 1e-9:
                return d
        return np.zeros(3)

    def _turn(self, s: int, t: int) -> np.ndarray:
        """Rotation taking source directions to target directions near pair (s, t): it turns the
        frame (incoming bone, body front across it) of the source onto the target's, so a hand
        held down with the thumb forward meets a hand held out in an A-pose thumb forward."""
        a, b = self._incoming(self.ts, s), self._incoming(self.tt, t)
        if np.linalg.norm(a) < 1e-9 or np.linalg.norm(b) < 1e-9:
            return self.tgt.axes.T @ self.src.axes
        return self._frame(b, self.tgt.axes) @ self._frame(a, self.src.axes).T

    @staticmethod
    def _frame(incoming: np.ndarray, axes: np.ndarray) -> np.ndarray:
        u = incoming / np.linalg.norm(incoming)
        ref = axes[2] if abs(axes[2] @ u) < 0.9 else axes[0]  # the front, or the up axis along it
        v = ref - (ref @ u) * u
        v /= np.linalg.norm(v)
        return np.stack([u, v, np.cross(u, v)], axis=1)


def match_skeletons(source: JointGraph | Anatomy, target: JointGraph | Anatomy,
                    overrides: dict[str, str | None] | None = None) -> SkeletonMatch:
    """Match a source skeleton to a target (module docstring).

    overrides: source joint -> target bone (or None to leave the joint unmatched), as from
    ``load_joint_map``; they replace whatever the structural match paired with either name.
    """
    src = source if isinstance(source, Anatomy) else body_anatomy(source)
    tgt = target if isinstance(target, Anatomy) else body_anatomy(target)
    m = _Matcher(src, tgt)
    ls, lt = src.landmarks, tgt.landmarks
    m.add(ls["pelvis"], lt["pelvis"], "trunk", "pelvis", "common parent of the feet in both")
    m.add(ls["chest"], lt["chest"], "trunk", "chest", "common parent of the hands in both")
    for part, roles in (("spine", ["chest"]), ("neck", ["head"]),
                        ("leg.L", ["hip.L", "knee.L", "ankle.L", "toe.L"]),
                        ("leg.R", ["hip.R", "knee.R", "ankle.R", "toe.R"]),
                        ("arm.L", ["clavicle.L", "shoulder.L", "elbow.L", "wrist.L"]),
                        ("arm.R", ["clavicle.R", "shoulder.R", "elbow.R", "wrist.R"])):
        m.chain_spans(part, roles)
    # the pelvis's own ancestors (a floor root above the hips) match upward
    s, t = src.graph.parents[ls["pelvis"]], tgt.graph.parents[lt["pelvis"]]
    while s >= 0 and t >= 0:
        m.add(int(s), int(t), "trunk", "", "above the pelvis in both")
        s, t = src.graph.parents[s], tgt.graph.parents[t]
    # 4. what hangs off matched pairs, breadth first from the root
    todo = sorted(m.pairs, key=lambda j: m.ts.depth[j])
    while todo:
        s = todo.pop(0)
        t, part, _, _ = m.pairs[s]
        before = set(m.pairs)
        m.children(s, t, _part_below(part, src, s))
        todo.extend(sorted(set(m.pairs) - before, key=lambda j: m.ts.depth[j]))
    gs, gt = src.graph, tgt.graph
    pairs = {gs.names[s]: (gt.names[t], part, role, reason) for s, (t, part, role, reason) in m.pairs.items()}
    if overrides:
        for a, b in overrides.items():
            gs.index(a)
            if b is not None:
                gt.index(b)
            pairs = {k: v for k, v in pairs.items() if k != a and v[0] != b}
            if b is not None:
                pairs[a] = (b, "map file", "", "given in the map file")
    order_s = {n: i for i, n in enumerate(gs.names)}
    pair_list = tuple(JointPair(s, *pairs[s]) for s in sorted(pairs, key=order_s.get))
    matched_s = set(pairs)
    matched_t = {v[0] for v in pairs.values()}
    un_s = tuple((n, m.why_s.get(j, _default_why(m.ts, j, "target"))) for j, n in enumerate(gs.names)
                 if n not in matched_s)
    un_t = tuple((n, m.why_t.get(j, _default_why(m.tt, j, "source"))) for j, n in enumerate(gt.names)
                 if n not in matched_t)
    segments, warnings = _segments(gs, gt, pairs)
    for p in pair_list:
        rs, rt = name_roles(p.source), name_roles(p.target)
        if p.role and rs and p.role not in rs:
            warnings.append(f"{p.source} -> {p.target}: found as {p.role} by structure, but the name "
                            f"{p.source!r} usually means {', '.join(sorted(rs))}")
        if p.role and rt and p.role not in rt:
            warnings.append(f"{p.source} -> {p.target}: found as {p.role} by structure, but the name "
                            f"{p.target!r} usually means {', '.join(sorted(rt))}")
    return SkeletonMatch(gs.name, gt.name, pair_list, un_s, un_t, tuple(segments),
                         {r: gs.names[j] for r, j in src.landmarks.items()},
                         {r: gt.names[j] for r, j in tgt.landmarks.items()},
                         src.axes, tgt.axes,
                         tuple(f"source: {n}" for n in src.notes) + tuple(f"target: {n}" for n in tgt.notes),
                         tuple(warnings))


def _part_below(part: str, anatomy: Anatomy, j: int) -> str:
    for side in ("L", "R"):
        if anatomy.landmarks.get(f"wrist.{side}") == j:
            return f"hand.{side}"
        if anatomy.landmarks.get(f"ankle.{side}") == j:
            return f"foot.{side}"
    return "head" if anatomy.landmarks.get("head") == j else part


def _default_why(tree: _Tree, j: int, other: str) -> str:
    p = tree.parents[j]
    if p >= 0:
        return f"below {tree.g.names[p]}: the {other} has no joint in that place"
    return f"a root with no counterpart in the {other}"


def _segments(gs: JointGraph, gt: JointGraph, pairs: dict) -> tuple[list[Segment], list[str]]:
    ts, tt = _Tree(gs), _Tree(gt)
    idx_t = {n: i for i, n in enumerate(gt.names)}
    matched = {gs.index(s): idx_t[v[0]] for s, v in pairs.items()}
    segments, warnings = [], []
    for s in sorted(matched, key=lambda j: ts.depth[j]):
        t = matched[s]
        up = ts.up_path(s)[1:]
        anc = next((a for a in up if a in matched), None)
        if anc is None:
            between_s = tuple(gs.names[a] for a in reversed(up))
            up_t = tt.up_path(t)[1:]
            segments.append(Segment(None, (gs.names[s], gt.names[t]), between_s,
                                    tuple(gt.names[a] for a in reversed(up_t))))
            continue
        ta = matched[anc]
        between_s = tuple(gs.names[a] for a in reversed(up[:up.index(anc)]))
        up_t = tt.up_path(t)[1:]
        if ta not in up_t:
            warnings.append(f"{gs.names[s]} -> {gt.names[t]}: its source parent pair {gs.names[anc]} -> "
                            f"{gt.names[ta]} is not above it in the target (crossed chains)")
            between_t = ()
        else:
            between_t = tuple(gt.names[a] for a in reversed(up_t[:up_t.index(ta)]))
        segments.append(Segment((gs.names[anc], gt.names[ta]), (gs.names[s], gt.names[t]), between_s, between_t))
    return segments, warnings


def load_joint_map(path: str | Path, source: JointGraph | None = None,
                   target: JointGraph | None = None) -> dict[str, str | None]:
    """A user's joint map: a JSON object ``{"source joint": "target bone" or null, ...}``
    (a top-level ``"map"`` object is also accepted). Names are checked against the skeletons
    when given; errors name the file and the entry."""
    path = Path(path)
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise MotionError(f"{path}: no such map file; expected a JSON object {{\"source joint\": \"target bone\"}}") \
            from None
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise MotionError(f"{path}: not valid JSON ({exc}); expected {{\"source joint\": \"target bone\"}}") from None
    if isinstance(data, dict) and isinstance(data.get("map"), dict):
        data = data["map"]
    if not isinstance(data, dict):
        raise MotionError(f"{path}: a JSON {type(data).__name__}; expected an object {{\"source joint\": \"target "
                          "bone\" or null}")
    out: dict[str, str | None] = {}
    targets_seen: dict[str, str] = {}
    for k, v in data.items():
        if k in ("written_by",):
            continue
        if v is not None and not isinstance(v, str):
            raise MotionError(f"{path}: entry {k!r} maps to {v!r}; expected a target bone name or null")
        if source is not None and k not in source.names:
            raise MotionError(f"{path}: {k!r} is not a joint of the source skeleton {source.name!r}; expected one of "
                              f"{', '.join(source.names)}")
        if target is not None and v is not None and v not in target.names:
            raise MotionError(f"{path}: {k!r} maps to {v!r}, not a bone of the target {target.name!r}; expected one "
                              f"of {', '.join(target.names)}")
        if v is not None and v in targets_seen:
            raise MotionError(f"{path}: {k!r} and {targets_seen[v]!r} both map to {v!r}; expected one source joint "
                              "per target bone")
        if v is not None:
            targets_seen[v] = k
        out[k] = v
    return out
