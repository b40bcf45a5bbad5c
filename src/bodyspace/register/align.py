"""Initial alignment of a prepared scan (metres, +Y up or its axis found) to the template's frame.

Stage 2 of the registration. With landmarks: the similarity transform (Umeyama 1991) taking the
scan's named points onto the template's (``similarity_from_landmarks``). Without: the scan's
principal axes give the candidates (the up axis, its sign if it was found rather than given,
and the heading: the horizontal axis of least spread is front/back for a standing body, the
other one in a T-pose) and each candidate is put feet to feet on the template's rest body and
scored by a short pose fit (``pose_fit.fit_pose``) on a subsample: front and back are told
apart by the body itself (feet, face, chest), not by a rule (``initial_alignment``).
"""

from __future__ import annotations

from contextlib import contextmanager
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from bodyspace.data.template import Template
from bodyspace.errors import ParameterError
from bodyspace.parallel import cores, forked_pool
from bodyspace.register.pose_fit import PoseState, fit_pose, posed_vertices, rest_state
from bodyspace.register.quality import MIN_QUALITY, PARTS, body_parts
from bodyspace.rig.kinematics import rotvec_to_matrix
from bodyspace.synth.poses import load_pose_library

__all__ = ["Alignment", "similarity_from_landmarks", "heading_candidates", "initial_alignment", "restart_limbs",
           "limb_score", "LIMBS"]

# Points of the subsample the candidates are scored on, and the pose-fit iterations per candidate.
SCORE_POINTS = 6000
SCORE_ITERATIONS = 8
# Library poses the pose fit is also started from (besides the template's A-pose) once the
# heading is chosen.
START_POSES = ("t_pose", "arms_overhead", "arms_forward")
# Strides the pose fit is also started from: (bone, rotation vector in degrees) pairs, one leg
# forward and the other back, either way. From the A-pose's parallel legs an ICP puts a
# stepping scan's legs on the wrong scan legs (48-56 mm, legs swapped): each leg follows the
# nearest points, and the hips cannot swing a leg through the other. Started from both
# assignments, the better short fit is kept.
STRIDES = {"stride_left": (("upperleg01.L", (-20.0, 0.0, 0.0)), ("upperleg01.R", (15.0, 0.0, 0.0))),
           "stride_right": (("upperleg01.R", (-20.0, 0.0, 0.0)), ("upperleg01.L", (15.0, 0.0, 0.0)))}
# Degrees the principal-axis headings of the best candidate's up direction are also turned by
# (the diagonals between them), then the best heading either way.
DIAGONAL_TURN = 45.0
HEADING_TURN = 25.0
# The limbs whose rotations are mixed between the start fits (each with its subtree).
LIMB_ROOTS = ("clavicle.L", "clavicle.R", "upperleg01.L", "upperleg01.R")
# Processes the independent short fits (headings, start poses, limb restarts) are spread over:
# forked (``parallel.forked_pool``), so the scan and the template are inherited, only a start's
# rotations and its fitted state cross; each fit is a pure function of its arguments, so the
# result is the same with 1. One fit is 0.1-0.3 s of numpy and KD-tree work; on two threads six
# of them took x0.8-0.9 the time of one after another (the GIL); two processes add no CPU
# (docs/registration.md, fifth round).
WORKERS = 2
# What the forked fits read (set for the length of one ``_pool``).
_JOB: dict | None = None


@contextmanager
def _pool(job: dict):
    """``run(fn, tasks)`` on up to ``WORKERS`` processes forked with ``job`` in ``_JOB``."""
    global _JOB
    _JOB = job
    try:
        with forked_pool(min(WORKERS, cores()), died="register the scan again") as run:
            yield run
    finally:
        _JOB = None


@dataclass(frozen=True)
class Alignment:
    """A rigid motion ``p' = rotation @ p + translation`` of the prepared scan into the template's
    frame; ``scale``: the template's size against the scan (landmarks), 1 otherwise; ``state``:
    the pose the scoring fit reached (a warm start), or None; ``scores``: each candidate's RMS
    residual (metres)."""

    rotation: np.ndarray
    translation: np.ndarray
    scale: float = 1.0
    state: PoseState | None = None
    scores: tuple = ()

    def apply(self, points: np.ndarray) -> np.ndarray:
        return points @ self.rotation.T + self.translation


def similarity_from_landmarks(source: np.ndarray, target: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Umeyama's similarity ``target ≈ s R source + t`` from (L, 3) pairs (L >= 3, not collinear).

    Returns (s, R (3, 3) proper, t (3,)).
    """
    src, dst = np.asarray(source, dtype=float), np.asarray(target, dtype=float)
    if src.shape != dst.shape or src.ndim != 2 or src.shape[1] != 3 or len(src) < 3:
        raise ParameterError(f"landmarks: {len(src)} pairs of shape {src.shape}; expected at least 3 points (L, 3)")
    mu_s, mu_d = src.mean(0), dst.mean(0)
    xs, xd = src - mu_s, dst - mu_d
    cov = xd.T @ xs / len(src)
    u, sig, vt = np.linalg.svd(cov)
    d = np.sign(np.linalg.det(u @ vt)) or 1.0
    D = np.diag([1.0, 1.0, d])
    R = u @ D @ vt
    var = (xs ** 2).sum() / len(src)
    if var <= 0:
        raise ParameterError("landmarks: all at one point; expected landmarks spread over the body")
    s = float(np.trace(np.diag(sig) @ D) / var)
    return s, R, mu_d - s * R @ mu_s


def _subtree(parents: np.ndarray, root: int) -> np.ndarray:
    """Bone indices (n,) of ``root`` and all its descendants."""
    parents = np.asarray(parents)
    inside = np.zeros(len(parents), dtype=bool)
    inside[root] = True
    changed = True
    while changed:
        grow = ~inside & (parents >= 0) & inside[np.maximum(parents, 0)]
        changed = bool(grow.any())
        inside |= grow
    return np.flatnonzero(inside)


def _yaw(theta: float) -> np.ndarray:
    c, s = np.cos(theta), np.sin(theta)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def heading_candidates(points: np.ndarray, up_known: bool = True) -> list[np.ndarray]:
    """Rotations (3, 3) that may bring a scan (P, 3), +Y up, to face +Z.

    The horizontal principal axes: the one of least spread (front/back of a standing body) and
    the other (a T-pose's arms), each in both directions; with ``up_known=False`` also the same
    for the scan turned upside down (about X).
    """
    out = []
    flips = (np.eye(3), np.diag([1.0, -1.0, -1.0])) if not up_known else (np.eye(3),)
    for flip in flips:
        # The axes of the scan as turned (turning about X mirrors the heading: the axes are
        # taken after it, not before).
        pts = points @ flip.T
        h = (pts - pts.mean(axis=0))[:, [0, 2]]
        _, vecs = np.linalg.eigh(h.T @ h)
        for axis in (vecs[:, 0], vecs[:, 1]):
            for sign in (1.0, -1.0):
                fx, fz = sign * axis
                theta = np.arctan2(fx, fz)            # heading of the candidate front
                out.append(_yaw(-theta) @ flip)       # turn it onto +Z
    return out


def _place(points: np.ndarray, rest: np.ndarray) -> np.ndarray:
    """Translation putting the points' floor on the template's and their vertical axis on its."""
    lo = np.percentile(points[:, 1], 0.5)
    mid = np.median(points[:, [0, 2]], axis=0)
    rmid = np.median(rest[:, [0, 2]], axis=0)
    return np.array([rmid[0] - mid[0], rest[:, 1].min() - lo, rmid[1] - mid[1]])


def _score(template: Template, state: PoseState, points: np.ndarray, tree: cKDTree) -> float:
    """Mean distance both ways (each capped at 10 cm), not the residual the fit minimized (a fit
    that lost its points has a small residual)."""
    x, _, _ = posed_vertices(template.rigs["default"], state)
    d1 = tree.query(x[::4])[0]
    d2 = cKDTree(x).query(points)[0]
    return float(np.mean(np.minimum(d1, 0.1)) + np.mean(np.minimum(d2, 0.1)))


def _short_fit(points, normals, tree, template, state, iterations=SCORE_ITERATIONS):
    # The scale stays the height ratio: fitted, it trades stature for girth on a body wider than
    # the template (a heavy 1.46 m man came out 1.65 m tall); the shape fit takes the girth.
    state, _ = fit_pose(points, normals, template, state, iterations=iterations, scan_tree=tree,
                        start_distance=0.25, end_distance=0.06, template_samples=1500, scan_samples=2500,
                        fit_scale=False)
    return state, _score(template, state, points, tree)


def _start(template: Template, rest: np.ndarray, q: np.ndarray, rotations: np.ndarray | None = None) -> PoseState:
    """The rest body (V, 3) posed by ``rotations`` (B, 3, 3) (None: unposed), scaled to the
    height of the points q (P, 3) about the origin and stood on their floor."""
    rig = template.rigs["default"]
    state = rest_state(template, rig, rest)
    height = np.percentile(q[:, 1], 99.5) - np.percentile(q[:, 1], 0.5)
    R = state.rotations if rotations is None else rotations
    state = PoseState(state.rest, R, 1.0, np.zeros(3))
    x0, _, _ = posed_vertices(rig, state)
    scale = float(height / np.ptp(x0[:, 1]))
    return PoseState(state.rest, R, scale, np.array([0.0, q[:, 1].min() - scale * x0[:, 1].min(), 0.0]))


def _candidate_fit(R: np.ndarray, t: np.ndarray, rotations, iterations: int) -> tuple[PoseState, float]:
    """A short fit of the job's subsample turned by R (3, 3) and moved by t (3,), started from
    ``rotations`` (B, 3, 3) or the rest pose (None): (state, score)."""
    p, n, template, rest = _JOB["points"], _JOB["normals"], _JOB["template"], _JOB["rest"]
    q = p @ R.T + t
    return _short_fit(q, n @ R.T, cKDTree(q), template, _start(template, rest, q, rotations), iterations)


def initial_alignment(points: np.ndarray, normals: np.ndarray, template: Template, *,
                      up_known: bool = True, landmarks: tuple | None = None, rest: np.ndarray | None = None,
                      iterations: int = SCORE_ITERATIONS, rng=0) -> Alignment:
    """The rigid motion of the prepared scan (P, 3) (normals (P, 3)) onto the template's frame.

    landmarks: (template landmark positions (L, 3) on the rest body, scan positions (L, 3)),
    or None (principal axes and candidate scoring; see the module docstring). rest: (V, 3) the
    rest body the pose is fitted with (default: the template's; the pipeline passes its shape
    space's mean), scaled to the scan's height. Either way the
    pose is then started from each of ``START_POSES`` (a limb ICP cannot swing far: an A-pose
    template's arm does not reach a T-pose scan's) and the best short fit is kept as
    ``Alignment.state``. iterations: pose-fit iterations of each short fit.
    """
    rest = np.asarray(template.vertices if rest is None else rest, dtype=float)
    rig = template.rigs["default"]
    rng = np.random.default_rng(rng)
    sub = rng.choice(len(points), size=min(SCORE_POINTS, len(points)), replace=False)
    p, n = points[sub], normals[sub]

    if landmarks is not None:
        tmpl, scan = landmarks
        s, R, _ = similarity_from_landmarks(scan, tmpl)
        trans = tmpl.mean(0) - R @ scan.mean(0)
        candidates = [(R, trans)]
        scale = 1.0 / s
    else:
        candidates = []
        for R in heading_candidates(p, up_known):
            candidates.append((R, _place(p @ R.T, rest)))
        scale = 1.0
    job = {"points": p, "normals": n, "template": template, "rest": rest}
    with _pool(job) as run:
        fitted = run(_candidate_fit, [(R, t, None, iterations) for R, t in candidates])
        scores = [sc for _, sc in fitted]
        k = int(np.argmin(scores))
        score, (R, t), state = scores[k], candidates[k], fitted[k][0]
        if landmarks is None:
            # A stepping body's principal axes lie between its front and its side (its stride
            # spreads it front to back as much as its shoulders do side to side: 26-44° off on
            # step-forward scans); 45° off, front and back scored alike and a thin tall man was
            # fitted facing backwards (592 mm; docs/registration.md, "Facing backwards"). The
            # diagonals of the best candidate's up direction are scored too.
            upright = [(R2, t2) for R2, t2 in candidates if R2[1, 1] * R[1, 1] > 0]
            diagonal = []
            for R1, _ in upright:
                R2 = _yaw(np.radians(DIAGONAL_TURN)) @ R1
                diagonal.append((R2, _place(p @ R2.T, rest)))
            for (R2, t2), (s2, sc2) in zip(diagonal, run(_candidate_fit, [(R2, t2, None, iterations)
                                                                          for R2, t2 in diagonal])):
                scores.append(sc2)
                if sc2 < score:
                    score, R, t, state = sc2, R2, t2, s2
            # The principal axes miss a stepping or twisting body's heading (by 29° on a
            # step-forward scan, which the pose fit took up as a twist between pelvis and chest):
            # the best candidate turned either way is scored too.
            turned = []
            for turn in (-HEADING_TURN, HEADING_TURN):
                R2 = _yaw(np.radians(turn)) @ R
                turned.append((R2, _place(p @ R2.T, rest)))
            refits = run(_candidate_fit, [(R2, t2, None, iterations) for R2, t2 in turned])
            for (R2, t2), (s2, sc2) in zip(turned, refits):
                if sc2 < score:
                    score, R, t, state = sc2, R2, t2, s2
        q = p @ R.T + t
        tree = cKDTree(q)
        library = load_pose_library()
        starts = [library.rotations(name, rig) for name in START_POSES]
        for bones in STRIDES.values():
            rv = np.zeros((rig.n_bones, 3))
            for bone, degrees in bones:
                rv[rig.bone_index(bone)] = np.radians(degrees)
            starts.append(rotvec_to_matrix(rv))
        fits = [state]
        for s2, sc2 in run(_candidate_fit, [(R, t, rotations, iterations) for rotations in starts]):
            fits.append(s2)
            if sc2 < score:
                score, state = sc2, s2
    # Limb by limb: the best start for the whole body may have lost one arm (a hand on the hip,
    # an arm swinging with a step) that another start placed; each limb's rotations are taken
    # from whichever fit makes the whole body score best, then the mix is fitted once more.
    mixed, mixed_score = state, score
    for root in LIMB_ROOTS:
        bones = _subtree(rig.parents, rig.bone_index(root))
        for other in fits:
            rot = mixed.rotations.copy()
            rot[bones] = other.rotations[bones]
            trial = PoseState(mixed.rest, rot, mixed.scale, mixed.translation)
            sc = _score(template, trial, q, tree)
            if sc < mixed_score:
                mixed, mixed_score = trial, sc
    if mixed is not state:
        s2, sc2 = _short_fit(q, n @ R.T, tree, template, mixed, iterations)
        if sc2 < score:
            score, state = sc2, s2
    return Alignment(R, t, scale, state, tuple(scores))


# Limbs restarted when the quality check finds one of their parts off the scan: the limb's root
# bone (its subtree is restarted) and its ``quality.PARTS``.
LIMBS = {"left arm": ("clavicle.L", ("left upper arm", "left forearm", "left hand")),
         "right arm": ("clavicle.R", ("right upper arm", "right forearm", "right hand")),
         "left leg": ("pelvis.L", ("left thigh", "left lower leg", "left foot")),
         "right leg": ("pelvis.R", ("right thigh", "right lower leg", "right foot"))}
# Library poses whose limb rotations a lost limb is restarted from: the arm poses (hanging,
# forward, back, out, up, elbows bent, hands on the hips, crossed, behind the head) and the leg
# poses (parallel, wide, a stride either way, a knee lifted, sitting). A limb's rotations are
# relative to its parent, so an arm start is the same whatever the legs do.
LIMB_START_POSES = {"arm": ("rest", "t_pose", "arms_forward", "arms_at_sides", "arms_back", "elbows_flexed",
                            "hands_on_hips", "arms_crossed", "hands_behind_head", "arms_overhead"),
                    "leg": ("rest", "wide_stance", "lunge_left", "lunge_right", "knee_lift_left", "knee_lift_right",
                            "sitting", "half_squat")}
# Pose-fit iterations of each restart: every start the first number, the RESTART_KEEP best by
# score the second more (on the step-forward scan the start that found the hand was the best
# after 3 iterations too); scan points the score is taken on.
RESTART_ITERATIONS = (3, 6)
RESTART_KEEP = 2
RESTART_POINTS = 10_000


_MIRROR = np.diag([-1.0, 1.0, 1.0])


def _other_side(name: str) -> str:
    """The bone of the other side: 'upperarm01.L' → 'upperarm01.R' (and back)."""
    return name[:-2] + {".L": ".R", ".R": ".L"}[name[-2:]]


def limb_score(template: Template, state: PoseState, points: np.ndarray, tree: cKDTree, limb_vertices: np.ndarray,
               limb_share: float) -> float:
    """A limb's residual both ways (metres): the mean distance of its vertices (ids (n,)) to the
    scan, plus the summed distance of the scan points (P, 3) to the posed body per point the
    limb should hold (``limb_share`` of the body's area times P); each distance capped at 10 cm.
    Both ways: a limb placed on points another part already explains scores well one way and
    badly the other."""
    x, _, _ = posed_vertices(template.rigs["default"], state)
    d1 = np.minimum(tree.query(x[limb_vertices])[0], 0.1).mean()
    d2 = np.minimum(cKDTree(x).query(points)[0], 0.1).sum()
    return float(d1 + d2 / max(1.0, limb_share * len(points)))


def _restart_fit(state: PoseState, iterations: int, start: float, end: float, seed: int, ids: np.ndarray,
                 share: float) -> tuple[float, PoseState]:
    """One restart's short fit of the whole pose on the job's scan (gate from ``start`` to ``end``
    metres) and its ``limb_score`` for the limb's vertices ``ids`` (n,): (score, state)."""
    template, tree = _JOB["template"], _JOB["tree"]
    state, _ = fit_pose(_JOB["points"], _JOB["normals"], template, state, iterations=iterations, scan_tree=tree,
                        start_distance=start, end_distance=end, template_samples=1500, scan_samples=2500,
                        fit_scale=False, rng=seed)
    return limb_score(template, state, _JOB["sub"], tree, ids, share), state


def restart_limbs(points: np.ndarray, normals: np.ndarray, template: Template, state: PoseState, parts: dict,
                  tree: cKDTree, *, poses: dict | None = None, rng=0) -> tuple[PoseState, list[str]]:
    """Restart each limb with a part the quality check failed (a leg also when the trunk failed),
    from the limb rotations of
    ``LIMB_START_POSES`` (or ``poses``: "arm"/"leg" → pose names) and from the other side's limb
    mirrored, and keep the start whose fit has the least ``limb_score`` if it is less than the
    state's own.

    points (P, 3), normals (P, 3): the scan in the template's frame, ``tree`` its KD-tree; state:
    the pose fit's result; parts: part name → its quality in [0, 1] (``quality.assess_parts``).
    Each start is a short fit of the whole pose (the limb alone, the trunk held, reached 42 mm
    at the hand where the whole reached 4 mm: the shoulder follows the arm), in two stages: every
    start ``RESTART_ITERATIONS[0]`` iterations, the ``RESTART_KEEP`` best by score
    ``RESTART_ITERATIONS[1]`` more. Returns the state and the limbs whose rotations changed.
    """
    rig = template.rigs["default"]
    rng = np.random.default_rng(rng)
    poses = LIMB_START_POSES if poses is None else poses
    labels = body_parts(template)
    names = list(PARTS)
    library = load_pose_library()
    sub = points[rng.choice(len(points), size=min(RESTART_POINTS, len(points)), replace=False)]
    x, _, _ = posed_vertices(rig, state)
    tri = x[template.faces]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)

    job = {"points": points, "normals": normals, "template": template, "tree": tree, "sub": sub}
    changed = []
    with _pool(job) as run:
        for limb, (root, limb_parts) in LIMBS.items():
            # A leg is restarted for its trunk too: the hips' skin is the trunk's (pelvis, belly).
            if all(parts[p] >= MIN_QUALITY for p in limb_parts + (("trunk",) if "leg" in limb else ())):
                continue
            ids = np.flatnonzero(np.isin(labels, [names.index(p) for p in limb_parts]))
            share = float(area[np.isin(labels[template.faces[:, 0]], [names.index(p) for p in limb_parts])].sum()
                          / area.sum())
            bones = _subtree(rig.parents, rig.bone_index(root))
            starts = [library.rotations(pose, rig)[bones] for pose in poses["arm" if "arm" in limb else "leg"]]
            # The other side's limb mirrored (x → -x): a symmetric pose (hands on the hips) whose
            # one side the fit placed gives the other side's start, whatever the library holds.
            other = [rig.bone_index(_other_side(rig.bone_names[b])) for b in bones]
            starts.append(_MIRROR @ state.rotations[other] @ _MIRROR)
            # One seed per fit, drawn here: each fit is the same whichever process runs it.
            seeds = rng.integers(1 << 31, size=len(starts) + RESTART_KEEP)
            tasks = []
            for start, seed in zip(starts, seeds):
                rot = state.rotations.copy()
                rot[bones] = start
                tasks.append((PoseState(state.rest, rot, state.scale, state.translation, state.coefficients),
                              RESTART_ITERATIONS[0], 0.15, 0.06, int(seed), ids, share))
            trials = [(score, k, trial) for k, (score, trial) in enumerate(run(_restart_fit, tasks))]
            best_score, best = limb_score(template, state, sub, tree, ids, share), state
            best_starts = sorted(trials, key=lambda t: t[:2])[:RESTART_KEEP]
            kept = [(trial, RESTART_ITERATIONS[1], 0.06, 0.03, int(seed), ids, share)
                    for (_, _, trial), seed in zip(best_starts, seeds[len(starts):])]
            for score, trial in run(_restart_fit, kept):
                if score < best_score:
                    best, best_score = trial, score
            if best is not state:
                state = best
                changed.append(limb)
    return state, changed
