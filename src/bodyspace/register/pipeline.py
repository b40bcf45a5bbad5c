"""The registration of a raw scan, stage by stage (Hasler §2.2–2.3; docs/registration.md).

``register_scan`` runs, each stage a function of its own module usable alone:

1. ``prepare.prepare_scan``: metres, +Y up, unoriented normals (units and up found or given);
2. ``align.initial_alignment``: landmarks (similarity) or principal axes with the heading and
   the start pose chosen by short pose fits;
3. ``model_fit.fit_shape``: the shape coefficients and scale with the pose held;
4. ``pose_fit.fit_pose``: the skeleton's pose by twist ICP with the shape held, then pose, shape
   and scale together in one Gauss-Newton problem (``POSE_ROUNDS``, gates narrowing);
   Then every body part is checked (``quality.assess``) and a limb off its points is restarted
   from library limb poses (``align.restart_limbs``) and the joint rounds fitted again; then
   ``model_fit.reach_shape``: the shape once more with the pose held and a light prior (large,
   low breasts stopped short of their scan points under the joint rounds' prior);
5. ``nicp.nonrigid_icp``: per-vertex affine refinement, stiffness annealed 3000 → 10;
6. ``quality.assess``: how much of the scan the fit explains, as a whole and per body part both
   ways; refused below ``MIN_QUALITY``, the failed parts named;
7. ``pose_refit.refit_pose`` and ``pose_refit.standing_body``: the model refitted to the scan with
   a light shape prior, its rest body plus the scan's normal offsets (from the scan points, the
   registered mesh's over holes): the body standing, to be measured (``Registration.standing``);
8. optionally ``detail.detail_offsets``: the scan's relief as normal offsets on the fit
   subdivided at mid-edges (Hasler §3, end), to be re-added after a morph.

The result is in the template's topology, both in the scan's own frame and units (to lay over
it) and in bodyspace's (metres, +Y up, +Z front: to measure, to morph, to add to a database).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree

from bodyspace.data.template import Template, load_template
from bodyspace.errors import RegistrationError
from bodyspace.mesh.geometry import face_areas, vertex_normals
from bodyspace.measure.definitions import MeasurementSet, load_measurement_set
from bodyspace.register.align import SCORE_ITERATIONS, initial_alignment, restart_limbs
from bodyspace.register.correspondences import orient_normals
from bodyspace.register.detail import Detail, detail_offsets
from bodyspace.register.model_fit import SCALE_PRIOR, SHAPE_PRIOR, ShapeBasis, fit_shape, phenotype_basis, reach_shape
from bodyspace.register.nicp import nonrigid_icp
from bodyspace.register.pose_fit import PoseState, fit_pose, posed_vertices
from bodyspace.register.pose_refit import refit_pose, standing_body
from bodyspace.register.prepare import prepare_scan
from bodyspace.register.quality import EXPLAINED_GOOD, Quality, assess

__all__ = ["Registration", "register_scan", "DEFAULT_STEPS"]

# Pose-fit rounds: the correspondence gate's start and end (metres), whether the shape and scale
# are fitted with the pose (jointly, one Gauss-Newton problem), and the pose prior's weight. The
# first round places the limbs with the shape held and a firm prior (free, a hand on the hip
# went astray); then pose and shape together with the prior relaxed. Alternating pose and shape
# fits instead crawled along the valley where the two trade off: 9.2 mm after three rounds on an
# elbows-flexed scan, 1.4 mm jointly (docs/registration.md).
POSE_ROUNDS = ((0.10, 0.03, False, 0.004), (0.05, 0.02, True, 0.002), (0.04, 0.015, True, 0.001),
               (0.03, 0.01, True, 0.001))
# Joint pose rounds fitted again (the last ones of POSE_ROUNDS) after a limb was restarted.
RESTART_ROUNDS = 2
# Limbs are restarted only on a scan the pose fit explains this much of (a step-forward scan that
# lost a hand: 93.5 %; a heavy woman with her hands behind her head, both arms lost by every
# start pose: 83 %, fitted to 1.5 mm by the restarts, refused at 0.00 without them: 0.85 was the
# bound before); below it the scan is not one body (two people about 50 %, a chair 35 %, a body
# beside a box 51 %) and the fit is refused without spending the restarts on it. The final
# quality check refuses a bad scan either way: the bound only saves the restarts' time.
RESTART_MIN_EXPLAINED = 0.70
# NICP stiffness levels and iterations per level, and the last level's stiffness (measured:
# docs/registration.md). After the joint pose and shape fit the model explains the body to about
# 0.5 mm; the NICP is there for what it cannot (detail), so it stops stiffer than Hasler's 0.01:
# on an elbows-flexed scan from 1.41 mm, ending at 1 took the correspondence to 2.54 mm, at 10 to
# 1.85 mm, at 30 to 1.54 mm (surface 0.79, 0.61, 0.52 mm). With the targets raised by each
# vertex's sagitta (correspondences.cell_sagitta), closest-point targets refused over holes and
# folding steps stiffened locally, 10 measures better: on three test scans 22, 25, 28 of 31
# measurements within ISO 20685-1 at 10 against 20, 20, 26 at 30 (correspondence 1.49-1.86 mm
# against 1.37-1.84 mm, no folds at either; docs/registration.md).
DEFAULT_STEPS = 6
DEFAULT_INNER = 2
NICP_STIFFNESS_END = 10.0
# Scan points the fits use at most (a subsample spread at random: 60 k points hold the surface
# to well under a millimetre at 2 mm noise, and the KD-tree and plane fits scale with them).
MAX_POINTS = 60_000
# A single view (one Kinect, structured-light or phone LiDAR capture; a rig with its cameras on one
# side) sees one side of the body: about half of the template finds scan points and the quality's
# coverage refuses it, though the fit lies on what was seen (a front-only test scan: 3.0 mm to the
# truth, 0.75 mm from the seen surface, 3.6 mm on the unseen side from the shape model's prior).
# Such a scan is accepted when the surface the fit found points for faces one way (its
# area-weighted mean normal, horizontal part, at least ONE_SIDED_FACING: 0.55 on front-only and
# back-only test scans, under 0.02 all round), at least ONE_SIDED_COVERAGE of the template found
# points, the fit explains the scan (``EXPLAINED_GOOD``) and no body part failed; a scan cut
# across (the legs missing) faces every way and stays refused.
# A body part with under this share of its vertices near a scan point is not in the scan at all
# (a scan cut across at the waist: the legs 0.0; a front-only scan's least part 0.5; a hole
# under the soles or the top of the head leaves 0.77 and more of its part): the quality, which
# takes a part the scanner missed for a hole, accepted such a scan at 1.00 with the legs made up
# by the shape model; it is refused, the parts named.
UNSEEN_PART = 0.10
ONE_SIDED_FACING = 0.3
ONE_SIDED_COVERAGE = 0.35
ONE_SIDED_SEEN = 0.010


@dataclass
class Registration:
    """A registered scan.

    vertices: (V, 3) the template fitted to the scan, in the scan file's frame and units.
    internal: (V, 3) the same in metres, +Y up, +Z front (bodyspace's frame); faces: (F, 3).
    distance: (V,) metres from each registered vertex to its nearest scan point.
    pose: the fitted ``PoseState`` (rotations (B, 3, 3) of the default rig, scale, translation;
        its ``rest`` is the model fit's rest body); coefficients: (K,) shape coefficients.
    quality: the ``Quality`` figure; to_scan: (4, 4) internal → the scan file's frame.
    points: (P, 3) the scan points used, internal frame. units, up: the scan's; assumed: what
        was found rather than given; seconds: time per stage.
    detail: the scan's relief over ``internal`` subdivided (``register_scan(detail_levels=...)``),
        or None. restarted: the limbs the per-part check found off the scan after the pose fit and
        restarted (``align.restart_limbs``), e.g. ["left arm"].
    standing: (V, 3) the registered body brought back to the rest pose (metres, +Y up, lowest
        vertex at y = 0): what its measurements are taken on (``pose_refit.standing_body``);
        standing_pose: the refitted model's ``PoseState`` that split pose and shape for it.
    accepted: the quality accepted it, or it is a one-sided scan fitted on its seen side
        (``one_sided``: the sentence saying so, also in ``assumed``; ``one_sided_view``).
    """

    vertices: np.ndarray
    internal: np.ndarray
    faces: np.ndarray
    distance: np.ndarray
    pose: PoseState
    coefficients: np.ndarray
    quality: Quality
    to_scan: np.ndarray
    points: np.ndarray
    units: str
    up: str
    assumed: list[str] = field(default_factory=list)
    seconds: dict = field(default_factory=dict)
    detail: Detail | None = None
    restarted: list[str] = field(default_factory=list)
    standing: np.ndarray | None = None
    standing_pose: PoseState | None = None
    accepted: bool = True
    one_sided: str | None = None


def _landmark_pairs(landmarks: dict, mset: MeasurementSet, template: Template, to_prepared) -> tuple:
    names = [n for n in landmarks if n in mset.landmarks]
    unknown = sorted(set(landmarks) - set(names))
    if unknown:
        raise RegistrationError(f"landmarks: unknown name(s) {', '.join(unknown)}; expected names of the measurement "
                                f"set: {', '.join(mset.landmark_names)}")
    if len(names) < 3:
        raise RegistrationError(f"landmarks: {len(names)} given; expected at least 3 (better 6 or more, spread over "
                                "the body: head_top, ankles, wrists, ...)")
    sub = MeasurementSet({n: mset.landmarks[n] for n in names}, ())
    M = sub.landmark_matrix(template.n_vertices)
    scan = to_prepared(np.array([np.asarray(landmarks[n], dtype=float) for n in names]))
    return M, scan


def unseen_parts(quality: Quality) -> list[str]:
    """The body parts (``quality.PARTS`` names) the scan holds nothing of (``UNSEEN_PART``)."""
    return [p.name for p in quality.parts if p.seen < UNSEEN_PART]


def one_sided_view(vertices: np.ndarray, faces: np.ndarray, scan_tree: cKDTree, quality: Quality) -> str | None:
    """A sentence naming the side a one-sided scan was seen from (``ONE_SIDED_*``), or None when
    the fit is not one of a one-sided scan (all round, or failing for another reason).

    vertices: (V, 3) the fit, metres, +Y up, +Z front (the scan's points in ``scan_tree``).
    """
    if quality.explained < EXPLAINED_GOOD or quality.failed_parts or quality.coverage < ONE_SIDED_COVERAGE:
        return None
    seen = scan_tree.query(vertices)[0] < ONE_SIDED_SEEN
    normals = vertex_normals(vertices, faces)
    area = np.bincount(faces.ravel(), np.repeat(face_areas(vertices, faces), 3), len(vertices))
    mean = (normals[seen] * area[seen, None]).sum(axis=0) / max(area[seen].sum(), 1e-12)
    facing = float(np.hypot(mean[0], mean[2]))
    if facing < ONE_SIDED_FACING:
        return None
    # +Z is the body's front, +X its left.
    angle = np.degrees(np.arctan2(mean[0], mean[2])) % 360
    side = ("the front", "the left", "the back", "the right")[int(((angle + 45) % 360) // 90)]
    return (f"one-sided scan: seen from {side} only ({100 * seen.mean():.0f} % of the fit within "
            f"{1000 * ONE_SIDED_SEEN:.0f} mm of a scan point; the surface seen faces one way, {facing:.2f} of its "
            f"normals' mean against under 0.02 all round): the unseen side is the shape model's prior, and so "
            f"are the girths and depths through it (quality {quality.quality:.2f} on the whole body)")


def register_scan(points: np.ndarray, faces: np.ndarray | None = None, *, template: Template | None = None,
                  units: str | None = None, up: str | None = None, landmarks: dict | None = None,
                  basis: ShapeBasis | None = None, steps: int = DEFAULT_STEPS, inner: int = DEFAULT_INNER,
                  pose_iterations: int = 12, align_iterations: int = SCORE_ITERATIONS, check: bool = True,
                  name: str = "the scan", detail_levels: int | None = None, mset: MeasurementSet | None = None,
                  standing: bool = True, progress=None, trace=None, rng=0) -> Registration:
    """Register the template to a raw scan (module docstring).

    points: (P, 3) in the file's frame; faces: (F, 3) if the scan is a mesh. units, up: the
    file's ("mm", "z", ...), or None to find them. landmarks: name → (3,) scan positions (file
    frame) of measurement-set landmarks, optional (at least 3). basis: the shape space (default
    ``phenotype_basis``). steps, inner: NICP stiffness levels and iterations per level.
    pose_iterations, align_iterations: pose-fit iterations per round and per alignment candidate.
    check: refuse (``RegistrationError``) a fit whose quality is below ``MIN_QUALITY``.
    detail_levels: 1 or 2 to also take the scan's relief (``detail.detail_offsets`` on all the
    prepared scan's points), None not to. mset: the measurement set whose landmark names
    ``landmarks`` uses (default the shipped hm08 set; a user model's own: ``--model``).
    standing: also bring the body back to standing for its measurements (``pose_refit``, about
    a second of CPU; ``Registration.standing`` is None without it).
    progress: callback(message, fraction). trace: callback(stage, vertices (V, 3) in the scan
    file's frame) after each stage, to see where the error comes from (benchmarks/diag_register.py).
    """
    report = progress or (lambda message, fraction: None)
    template = template if template is not None else load_template()
    rig = template.rigs["default"]
    seconds = {}
    t0 = time.perf_counter()

    report("reading the scan", 0.0)
    prep = prepare_scan(points, faces, units=units, up=up, name=name, keep_dense=detail_levels is not None)
    rng = np.random.default_rng(rng)
    q = prep.points
    qn = prep.normals
    if len(q) > MAX_POINTS:
        keep = rng.choice(len(q), MAX_POINTS, replace=False)
        q, qn = q[keep], qn[keep]
    seconds["prepare"] = time.perf_counter() - t0

    basis = basis if basis is not None else phenotype_basis(template)
    lm_pairs = None
    if landmarks:
        def to_prepared(p):    # the file's frame → the prepared scan's (units and up applied)
            return np.linalg.solve(prep.to_scan[:3, :3], p.T).T

        M, lm_scan = _landmark_pairs(landmarks, mset if mset is not None else load_measurement_set(), template,
                                     to_prepared)
        lm_template = M @ basis.mean
        lm_pairs = (M, lm_scan)
    report("initial alignment", 0.05)
    t = time.perf_counter()
    align = initial_alignment(q, qn, template, up_known=prep.up_known, rest=basis.mean,
                              landmarks=None if lm_pairs is None else (lm_template, lm_pairs[1]),
                              iterations=align_iterations, rng=rng)
    q = align.apply(q)
    qn = qn @ align.rotation.T
    lm_fit = None if lm_pairs is None else (lm_pairs[0], align.apply(lm_pairs[1]))
    tree = cKDTree(q)
    seconds["align"] = time.perf_counter() - t
    # internal → file: undo the alignment, then the prepare step (units and up).
    to_internal = np.eye(4)
    to_internal[:3, :3] = align.rotation @ np.linalg.inv(prep.to_scan[:3, :3])
    to_internal[:3, 3] = align.translation
    to_scan = np.linalg.inv(to_internal)

    def _trace(stage, state_or_vertices):
        if trace is not None:
            x = state_or_vertices
            if isinstance(x, PoseState):
                x = posed_vertices(rig, x)[0]
            trace(stage, x @ to_scan[:3, :3].T + to_scan[:3, 3])

    _trace("align", align.state)

    # The shape first (the alignment's short fit holds the pose), then the pose, then both jointly
    # with the gates narrowing: a thin template's pose fitted to a heavy body first drifts (on a
    # heavy 1.46 m man: 46 → 34 mm with the pose first, 46 → 16 mm with the shape first).
    report("model fit", 0.25)
    t = time.perf_counter()
    state = align.state
    state, coef = fit_shape(q, qn, template, state, basis, scan_tree=tree, max_distance=0.08, rng=rng)
    seconds["model"] = time.perf_counter() - t
    _trace("model", state)
    seconds["pose"] = 0.0
    for k, (start, end, joint, prior) in enumerate(POSE_ROUNDS):
        report("skeleton pose fit" if not joint else "pose and model fit", 0.3 + 0.05 * k)
        t = time.perf_counter()
        state, _ = fit_pose(q, qn, template, state, iterations=pose_iterations, landmarks=lm_fit, scan_tree=tree,
                            start_distance=start, end_distance=end, fit_scale=joint, pose_prior=prior,
                            shape=(basis, coef, SHAPE_PRIOR, SCALE_PRIOR) if joint else None, rng=rng)
        if joint:
            coef = state.coefficients
        seconds["pose"] += time.perf_counter() - t
        _trace(f"pose {k + 1}", state)

    # Every body part checked on the pose fit: a limb that every start of the alignment lost (a
    # hand swinging behind a stepping body, a hand on the hip) is restarted from the library's
    # limb poses, the best by the limb's own residual both ways, then the joint rounds are fitted
    # again (align.restart_limbs; nothing is done when every part is on its points).
    report("checking the limbs", 0.48)
    t = time.perf_counter()
    x, _, _ = posed_vertices(rig, state)
    # Every patch of unexplained scan flags its part here, also beside parts on their points (a
    # belly the pose fit placed 4 cm off is mended by the legs' restart; docs/registration.md).
    check_pose = assess(x, template.faces, q, np.ones(len(x), dtype=bool), template=template, scan_tree=tree,
                        bridged_counts=True)
    restarted = []
    if check_pose.explained >= RESTART_MIN_EXPLAINED:
        state, restarted = restart_limbs(q, qn, template, state, {p.name: p.quality for p in check_pose.parts},
                                         tree, rng=rng)
    for k, (start, end, joint, prior) in enumerate(POSE_ROUNDS[-RESTART_ROUNDS:] if restarted else ()):
        state, _ = fit_pose(q, qn, template, state, iterations=pose_iterations, landmarks=lm_fit, scan_tree=tree,
                            start_distance=start, end_distance=end, fit_scale=joint, pose_prior=prior,
                            shape=(basis, coef, SHAPE_PRIOR, SCALE_PRIOR) if joint else None, rng=rng)
        coef = state.coefficients if joint else coef
        _trace(f"limbs {k + 1}", state)
    seconds["limbs"] = time.perf_counter() - t

    # The shape once more with the pose held and a light prior: a body far out along a few
    # components (large, low breasts) stops short of its scan under the joint rounds' prior
    # (model_fit.REACH_PRIOR; docs/registration.md, "Tenth round").
    t = time.perf_counter()
    state, coef = reach_shape(q, qn, template, state, basis, scan_tree=tree, rng=rng)
    seconds["model"] += time.perf_counter() - t
    _trace("reach", state)

    report("non-rigid refinement", 0.5)
    t = time.perf_counter()
    x, _, _ = posed_vertices(rig, state)
    qn = orient_normals(q, qn, x, vertex_normals(x, template.faces))
    nicp = nonrigid_icp(x, template.faces, template.vertices, q, qn, steps=steps, inner=inner,
                        stiffness_end=NICP_STIFFNESS_END, landmarks=lm_fit, scan_tree=tree,
                        progress=lambda f: report("non-rigid refinement", 0.5 + 0.45 * f))
    seconds["nicp"] = time.perf_counter() - t
    _trace("nicp", nicp.vertices)

    t = time.perf_counter()
    quality = assess(nicp.vertices, template.faces, q, nicp.has_target, template=template, scan_tree=tree)
    seconds["quality"] = time.perf_counter() - t
    assumed = list(prep.assumed)
    one_sided = None if quality.accepted else one_sided_view(nicp.vertices, template.faces, tree, quality)
    if one_sided is not None:
        assumed.append(one_sided)
    unseen = unseen_parts(quality)
    if check and (unseen or (not quality.accepted and one_sided is None)):
        reasons = []
        # Parts are named unseen only on a fit that lies on the scan: a fit off its points
        # (quality 0.00) "sees" nothing anywhere, and the quality's own reason says more.
        if unseen and (quality.accepted or quality.explained >= EXPLAINED_GOOD):
            reasons.append(f"the scan holds nothing of the {', '.join(unseen)} (under {100 * UNSEEN_PART:.0f} % of each "
                           f"within {1000 * ONE_SIDED_SEEN:.0f} mm of a scan point: a partial scan, whose missing parts "
                           "the fit could only make up from the shape model)")
        if not quality.accepted:
            lost = [p.name for p in quality.failed_parts]
            what = ("the fit does not explain the scan" if not lost or quality.explained < EXPLAINED_GOOD else
                    f"the fit lost the {', '.join(lost)}")
            reasons.append(f"{what}: {quality.describe()}")
        raise RegistrationError(f"{name}: refused, {'; '.join(reasons)}; a scan of one person standing alone, limbs "
                                "apart from the body where possible, is expected (two people, an object or a partial "
                                "scan are refused)")
    # The body standing, for its measurements: the model refitted to the scan with a light shape
    # prior splits pose and shape (the pose fit's split left 145 of 186 measurements within ISO
    # 20685-1 on the test scans, this one 159; docs/registration.md), the scan's surface kept as
    # normal offsets on the model's rest body: from the scan points where it has them, from the
    # registered mesh over its holes (the NICP stops stiff and kept the model's short girths:
    # pose_refit.scan_offsets).
    standing_pose = stand = None
    if standing:
        report("standing body", 0.96)
        t = time.perf_counter()
        standing_pose = refit_pose(q, qn, template, state, basis, scan_tree=tree, rng=rng)
        stand = standing_body(nicp.vertices, template.faces, template, standing_pose, points=q, normals=qn)
        seconds["standing"] = time.perf_counter() - t
    verts = nicp.vertices @ to_scan[:3, :3].T + to_scan[:3, 3]
    distance = tree.query(nicp.vertices)[0]
    detail = None
    if detail_levels is not None:
        report("detail", 0.97)
        t = time.perf_counter()
        detail = detail_offsets(nicp.vertices, template.faces, align.apply(prep.all_points), levels=detail_levels)
        seconds["detail"] = time.perf_counter() - t
    seconds["total"] = time.perf_counter() - t0
    report("done", 1.0)
    return Registration(verts, nicp.vertices, template.faces, distance, state, coef, quality, to_scan, q,
                        prep.units, prep.up, assumed, seconds, detail, restarted, stand, standing_pose,
                        (quality.accepted or one_sided is not None) and not unseen, one_sided)
