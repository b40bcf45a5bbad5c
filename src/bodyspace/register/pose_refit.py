"""The registered body brought back to standing for its measurements: the stage after the NICP.

A registered scan is measured standing (the ISO 20685-1 definitions are of the rest pose), so
the posed fit must be split into a pose and a rest body. ``rig.unpose`` estimates that split
from the registered mesh alone, and the pose fit's own rotations are another; on the test scans
neither is the true one (measurements within ISO 20685-1: 145 and 141 of 186 on six fits,
against 164 with the true pose; docs/registration.md). Two things make the split:

1. ``refit_pose``: the rigged shape model (pose, shape coefficients, scale, translation) fitted
   once more to the *scan*, starting from the pose fit's result, with the shape prior
   ``REFIT_SHAPE_PRIOR``, half the pose fit's ``SHAPE_PRIOR``. The pose fit's prior keeps
   its shape near the population's mean while the limbs are still being placed; at the end it
   held an edge-of-population body's last components (the limb girths, the hip's bulge) back,
   and the pose made up for them (a hip flexed 2-5°, the clavicles lifted 3-4° on a body standing
   in the rest pose; the unposed stature 5 mm tall). The same start with a prior a tenth as
   heavy put the model's rest body within ISO 20685-1 on 29-31 of 31 measurements on the
   rest-pose scan.
2. ``standing_body``: the rest body of that model (its pose undone exactly, since the model is
   posed by the rig) plus the registered mesh's own offset along the normal from the refitted
   model's posed surface, carried to the same vertex of the rest body. The model holds the
   skeleton's split of pose and shape; the scan's surface, with whatever the model cannot
   express (a real body's detail, another skinning's bulges), is kept as normal offsets, as
   Hasler §3 keeps detail. Measured alone the model's rest body loses what it cannot express:
   on the hands-on-hips scan 11-13 of 31 within ISO, against 18 with the offsets.
3. ``scan_offsets``: the offsets taken from the scan points rather than from the registered
   mesh where the scan has points. The NICP stops stiff (``pipeline.NICP_STIFFNESS_END``) and so
   leaves part of the model's residual in place; the model, fitted with a shape prior, is pulled
   towards the population's mean, and an edge-of-population body's girths come out short: on 39
   test scans the registered mesh unposed with the true pose had the upper arm girths 2.9 mm
   short on average, the breast ring 6.4 mm (the surface 0.4-1 mm inside the scan), and the
   ISO 20685-1 protocol rejected both upper arm girths. Each vertex's offset is the mean height
   of the scan points nearest to it over the refitted model's posed surface, less the same mean
   of points on that surface itself (its curvature), blended with the registered mesh's where a vertex has few points and averaged
   with its neighbours: upper arms -2.5 -> -0.3 mm, breast ring -6.1 -> -3.4 mm, the chest -3.6
   -> -2.2 mm, volume -0.3 % -> +0.1 % (docs/registration.md).
4. ``skinning_uncertainty``: the offsets are not trusted where the pose's skinning is uncertain.
   They carry whatever the model cannot express, and on a body not skinned by MakeHuman's
   weights (a real body, or a test scan posed with other weights) that includes the difference
   between its skinning and ours, largest where differently turned bones meet: a body posed
   with the smoothed weights and unposed by our LBS with its true pose and shape has its neck
   girth 15 mm short with the head turned, 29 mm long with the elbows flexed (the shoulders
   drag the neck's base); on the 7 of 40 ISO study scans posed so the standing neck was 17-26
   mm off and the ISO 20685-1 protocol rejected the neck girth. A vertex's uncertainty u is the
   farthest the transform of any bone weighting a vertex within ``SKIN_RINGS`` edges of it
   would carry it from where our LBS does (the most other weights diffused that far could move
   it; 0 where nothing turns). Its offset is trusted by c = 1 / (1 + (u / ``SKIN_UNCERTAINTY``)^2);
   the rest is filled in smoothly from the trusted offsets around (``_fill``), keeping at most
   ``SKIN_KEEP`` of the offset's own departure from that fill (a model's local error is smaller
   than that, another skinning's larger). On the 40 scans: neck -1.3 (SD 9.9) [-4.3, +1.8] mm
   -> -0.6 (6.7) [-2.7, +1.5] mm, accepted; the 7 scans 22.0 -> 12.4 mm mean |error| (the
   refitted model's own neck keeps the rest: its shape took up part of the other skinning);
   the other 33 2.5 -> 3.4 mm; 31 of 31 measurements accepted, scan by scan 1043 -> 1033 of
   1,238 values within their allowable error (docs/registration.md "Eighth round").
   Down-weighting the same vertices in ``refit_pose`` (so the shape would not take it up)
   was measured and not kept: the shape, unseen there, went astray (shoulder ring -65 to -99 mm
   on scan 25, the neck -26 mm on scan 14).
5. ``refit_prior``: the upper arm's twist bones (``upperarm02``) held in line with the upper arm.
   On the ISO study's scans posed with the smoothed weights and the arms moved (elbows flexed,
   step forward) the pose fit splits the arm's swing between ``upperarm01`` and its twist bone
   ``upperarm02`` (13-20° of swing each where the truth has all of it on ``upperarm01``; 4-7° on
   scans posed with our weights), the elbow within 6 mm: with less of the swing on
   ``upperarm01`` the shoulder's skin, which our weights tie to it, follows the arm less, as the
   other weights' does, and the shape makes up the rest with narrow shoulders (shoulder width
   -12 to -20 mm, shoulder ring -22 to -64 mm on scans 43 and 49, in the model's rest body as in
   the standing body; unposing the true posed body with the true pose and shape gives -0.2 to
   -0.9 mm and -0.2 to -2.9 mm, so neither the offsets nor the skinning gate carry it). The
   humerus does not bend between the two bones, so a prior (``REFIT_SWING_PRIOR``) on the twist
   bone's rotation across its own axis keeps the swing on ``upperarm01``; the twist stays free
   but for the plain prior. Scans 43 and 49: width -20.5 / -12.6 -> -5.4 / -4.8 mm, ring -62.8 /
   -26.6 -> -18.1 / -7.1 mm (docs/registration.md "Tenth round: shoulders").

Vertex to vertex instead of to the scan (the registered mesh's vertices as targets, exact
correspondence): measured and not kept. The registered vertices carry the pose fit's tangential
placement (the NICP keeps it), so a model fitted to them returns the pose fit's split (ISO 21 of
31 on the rest-pose scan before and after; on the true posed body the same fit recovers the pose
within 2.4° and all 31).
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from scipy.spatial import cKDTree

from bodyspace.data.template import Template
from bodyspace.mesh.geometry import sample_surface, vertex_normals
from bodyspace.mesh.topology import edges as mesh_edges
from bodyspace.parallel import cores
from bodyspace.register.model_fit import SCALE_PRIOR, ShapeBasis
from bodyspace.register.pose_fit import PoseState, fit_pose, posed_vertices

__all__ = ["refit_pose", "refit_prior", "standing_body", "scan_offsets",
           "skinning_uncertainty", "skin_trust", "REFIT_SHAPE_PRIOR",
           "REFIT_ITERATIONS", "REFIT_GATE", "REFIT_POSE_PRIOR", "REFIT_SWING_PRIOR", "SKIN_RINGS",
           "SKIN_UNCERTAINTY"]

# Shape prior of the refit (metres of RMS residual per standard deviation of a component): half
# model_fit.SHAPE_PRIOR. Measurements within ISO 20685-1 of the standing body at 0.0001, 0.00005,
# 0.00002: 155, 159, 159 of 186 on six fits of LBS-posed scans (``rig.unpose``: 145), 109, 104, 99
# of 155 on five scans posed with smoothed weights or the volume correction (``rig.unpose``:
# 103). The lighter the prior, the more of another skinning the shape takes up; the heavier
# one is kept for real bodies, whose skinning is nobody's LBS.
REFIT_SHAPE_PRIOR = 0.0001
# Gauss-Newton iterations (12: 162 of 186 at twice the time), the correspondence gate (metres,
# held: the pose fit has placed the body; starting at 2 cm: 154) and the pose prior (the pose
# fit's last rounds').
REFIT_ITERATIONS = 6
REFIT_GATE = 0.01
REFIT_POSE_PRIOR = 0.001
# The standing body's offsets from the scan points (module docstring, 3): a point counts for its
# nearest vertex within 15 mm of it, 10 mm along the normal, normals within 60°; a vertex takes
# the mean over the points of the vertices within 2 edges of it (about 19 vertices; 60 k points
# give ~4 a vertex), weighted k / (k + 2) against the registered mesh's offset for k points
# (holes keep the mesh's). Measured on 39 test scans (benchmarks/study_iso.py,
# docs/registration.md "ISO 20685-1 as the standard evaluates it").
OFFSET_GATE = 0.015
OFFSET_GATE_NORMAL = 0.010
OFFSET_MAX_ANGLE = 60.0
OFFSET_RINGS = 2
OFFSET_PRIOR_POINTS = 2.0
# Where the pose's skinning is uncertain (module docstring, 4): a vertex's skinning uncertainty is
# the farthest any bone weighting a vertex within SKIN_RINGS edges of it would carry it from where
# our LBS puts it; its offset is trusted by 1 / (1 + (u / SKIN_UNCERTAINTY)^2) and filled in from
# the trusted offsets around it for the rest (SKIN_FILL: the fill's edge weight against the data),
# keeping up to SKIN_KEEP (metres) of its own departure from the fill. Chosen on the ISO study's 40
# scans (no held-out set; docs/registration.md "Eighth round"): rings 4-8 and 1-5 mm gave the neck
# [-2.6, +2.4] at worst with SKIN_KEEP 0 (scan by scan 1002-1020 of 1,238 within, the upper arm
# girths -1.3 to -1.8 mm), SKIN_KEEP 1 mm kept 1038-1041 but the neck at [-3.6, +1.3].
SKIN_RINGS = 8
SKIN_UNCERTAINTY = 0.002
SKIN_FILL = 1.0
SKIN_KEEP = 0.0005
# The upper arm's twist bones held in line with it (module docstring, 5): a prior of
# REFIT_SWING_PRIOR (the pose prior's units) on their rotation across their own axis. 0.03, 0.1 and
# 0.3 gave the same shoulders within 1 mm on scans 43, 49 and 41 of the ISO study.
UPPER_ARM_TWIST_BONES = ("upperarm02.L", "upperarm02.R")
REFIT_SWING_PRIOR = 0.1


def refit_prior(template: Template, swing_prior: float = REFIT_SWING_PRIOR) -> np.ndarray:
    """The refit's pose prior (B, 3, 3) (module docstring, 5): ``REFIT_POSE_PRIOR`` on every bone's
    local rotation vector, plus ``swing_prior`` on the part of ``UPPER_ARM_TWIST_BONES``' rotation
    across their own axis (the template's rest bone, head to tail); their twist keeps the plain
    prior. A rig without those bones (a user's model) gets the plain prior only."""
    rig = template.rigs["default"]
    prior = REFIT_POSE_PRIOR * np.eye(3) * np.ones((rig.n_bones, 1, 1))
    heads, tails = rig.heads(template.vertices), rig.tails(template.vertices)
    for name in UPPER_ARM_TWIST_BONES:
        if name not in rig.bone_names:
            continue
        b = rig.bone_names.index(name)
        axis = (tails[b] - heads[b]) / np.linalg.norm(tails[b] - heads[b])
        prior[b] += swing_prior * (np.eye(3) - np.outer(axis, axis))
    return prior


def refit_pose(points: np.ndarray, normals: np.ndarray, template: Template, state: PoseState, basis: ShapeBasis, *,
               landmarks=None, scan_tree: cKDTree | None = None, iterations: int = REFIT_ITERATIONS,
               shape_prior: float = REFIT_SHAPE_PRIOR, swing_prior: float = REFIT_SWING_PRIOR, rng=0) -> PoseState:
    """The pose fit's state refitted to the scan with a light shape prior (module docstring, 1 and 5).

    points (P, 3), normals (P, 3): the scan in the fit's frame (metres, +Y up); state: the pose
    fit's ``PoseState`` (rotations (B, 3, 3), scale, translation, ``coefficients`` (K,) of
    ``basis``); landmarks: as ``fit_pose``'s. swing_prior: the upper arm's twist bones held in
    line with the upper arm (``refit_prior``; 0: off). Returns the refitted ``PoseState`` (its
    ``rest`` is ``basis.body(coefficients)``, unscaled).
    """
    coef = state.coefficients if state.coefficients is not None else np.zeros(len(basis.components))
    prior = refit_prior(template, swing_prior) if swing_prior else REFIT_POSE_PRIOR
    refit, _ = fit_pose(points, normals, template, state, iterations=iterations, landmarks=landmarks,
                        scan_tree=scan_tree, start_distance=REFIT_GATE, end_distance=REFIT_GATE, fit_scale=True,
                        pose_prior=prior, shape=(basis, coef, shape_prior, SCALE_PRIOR), rng=rng)
    return refit


def _heights(posed, n, tree, points, normals):
    """Each point's nearest vertex (K,) and height over it along its normal (K,), the points kept
    by the gates of ``scan_offsets``."""
    dist, near = tree.query(points, workers=cores())
    h = ((points - posed[near]) * n[near]).sum(axis=1)
    keep = (dist < OFFSET_GATE) & (np.abs(h) < OFFSET_GATE_NORMAL)
    if normals is not None:
        keep &= (normals * n[near]).sum(axis=1) > np.cos(np.radians(OFFSET_MAX_ANGLE))
    return near[keep], h[keep]


def scan_offsets(posed: np.ndarray, faces: np.ndarray, points: np.ndarray, normals: np.ndarray | None = None,
                 rings: int | None = None, rng=0) -> tuple[np.ndarray, np.ndarray]:
    """Each vertex's height under the scan along its normal, from the scan points themselves
    (module docstring, 3): (V,) metres (positive: the scan lies outside) and (V,) the count of
    points that gave it.

    posed: (V, 3) the refitted model posed (its faces ``faces`` (F, 3)); points (P, 3) and their
    normals (P, 3) (oriented outwards, or None) in the same frame. Each point goes to its nearest
    vertex when within ``OFFSET_GATE`` of it, within ``OFFSET_GATE_NORMAL`` along its normal and,
    with normals, facing the same way within ``OFFSET_MAX_ANGLE``; a vertex's offset is the mean
    height of the points of the vertices within ``rings`` edges of it (default ``OFFSET_RINGS``,
    so that a few points a vertex still give a steady mean) less the same mean over as many
    points sampled on the posed surface itself: a point beside a vertex lies below its tangent
    plane by the surface's curvature, and the difference takes that out exactly (``rng``: the seed
    of those surface points).
    """
    rings = OFFSET_RINGS if rings is None else rings
    V = len(posed)
    n = vertex_normals(posed, faces)
    tree = cKDTree(posed)
    near, h = _heights(posed, n, tree, points, normals)
    # The same count of points on the model's own surface (area-uniform), heights taken alike.
    own = sample_surface(posed, faces, max(len(points), 1000), rng)[0]
    own_near, own_h = _heights(posed, n, tree, own, None)
    total, count = np.bincount(near, h, minlength=V), np.bincount(near, minlength=V).astype(float)
    own_total, own_count = np.bincount(own_near, own_h, minlength=V), np.bincount(own_near, minlength=V).astype(float)
    if rings:
        ring = _ring_matrix(faces, V)
        for _ in range(rings):
            total, count, own_total, own_count = ring @ total, ring @ count, ring @ own_total, ring @ own_count
    offset = total / np.maximum(count, 1e-12) - own_total / np.maximum(own_count, 1e-12)
    return offset, count


def _ring_matrix(faces: np.ndarray, V: int) -> sp.csr_matrix:
    """(V, V) each vertex joined to itself and its edge neighbours (ones)."""
    e = mesh_edges(faces)
    return sp.coo_matrix((np.ones(2 * len(e)), (np.r_[e[:, 0], e[:, 1]], np.r_[e[:, 1], e[:, 0]])),
                         shape=(V, V)).tocsr() + sp.identity(V, format="csr")


def skinning_uncertainty(template: Template, state: PoseState, rings: int | None = None) -> np.ndarray:
    """How far the pose's skinning could place each vertex otherwise (module docstring, 4): (V,) metres.

    For vertex v, the largest distance between where LBS with the rig's weights puts it
    (``posed_vertices``) and where the transform of any bone that weights a vertex within
    ``rings`` edges of v (default ``SKIN_RINGS``) would carry it, times ``state.scale``. A vertex
    moved rigidly with its neighbourhood's bones (every bone's transform the same there: the rest pose, the middle of a
    segment) scores 0; one where differently turned bones meet scores their spread, the most
    another set of weights diffused over ``rings`` edges could move it.
    """
    rings = SKIN_RINGS if rings is None else rings
    rig = template.rigs["default"]
    _, y, G = posed_vertices(rig, state)                              # y (V, 3) unscaled, G (B, 4, 4)
    W = sp.csr_matrix(rig.weights)
    influence = (W > 0).astype(float)
    ring = _ring_matrix(template.faces, len(y))
    for _ in range(rings):
        influence = ring @ influence
    influence = influence.tocoo()                                     # the (vertex, bone) pairs
    v, b = influence.row, influence.col
    carried = np.einsum("kij,kj->ki", G[b, :3, :3], state.rest[v]) + G[b, :3, 3]
    d = np.linalg.norm(carried - y[v], axis=1)
    out = np.zeros(len(y))
    np.maximum.at(out, v, d)
    return state.scale * out


def skin_trust(template: Template, state: PoseState, skin_uncertainty: float = SKIN_UNCERTAINTY) -> np.ndarray:
    """(V,) in (0, 1]: 1 / (1 + (u / skin_uncertainty)^2) of ``skinning_uncertainty`` u."""
    return 1.0 / (1.0 + (skinning_uncertainty(template, state) / skin_uncertainty) ** 2)


def _fill(values: np.ndarray, trust: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(V,) ``values`` where ``trust`` (V,) in [0, 1] is high, carried smoothly from the trusted
    vertices over the untrusted ones: argmin sum trust (h - values)^2 + SKIN_FILL sum over edges
    (h_i - h_j)^2 (a harmonic fill where trust is 0)."""
    V = len(values)
    ring = _ring_matrix(faces, V)
    degree = np.asarray(ring.sum(axis=1)).ravel() - 1.0
    lap = sp.diags(degree) - (ring - sp.identity(V, format="csr"))
    A = (sp.diags(trust + 1e-9) + SKIN_FILL * lap).tocsc()
    return spla.spsolve(A, trust * values)


def standing_body(vertices: np.ndarray, faces: np.ndarray, template: Template, state: PoseState,
                  points: np.ndarray | None = None, normals: np.ndarray | None = None,
                  skin_uncertainty: float | None = SKIN_UNCERTAINTY) -> np.ndarray:
    """The registered body standing (module docstring, 2-4): (V, 3) metres, +Y up, lowest vertex at y = 0.

    vertices: (V, 3) the registered mesh in the frame of ``state`` (``Registration.internal``);
    faces: (F, 3); state: the model posed to it (``refit_pose``). points (P, 3), normals (P, 3):
    the scan in the same frame; with them the normal offsets are taken from the scan where it has
    points (``scan_offsets``), from the registered mesh elsewhere (holes). skin_uncertainty
    (metres; None: off): where ``skinning_uncertainty`` reaches it the offset is half trusted,
    the rest filled in from the trusted offsets around.
    """
    rig = template.rigs["default"]
    posed, _, _ = posed_vertices(rig, state)
    offset = ((np.asarray(vertices, dtype=float) - posed) * vertex_normals(posed, faces)).sum(axis=1)   # (V,)
    if points is not None and len(points):
        from_scan, count = scan_offsets(posed, faces, np.asarray(points, dtype=float),
                                        None if normals is None else np.asarray(normals, dtype=float))
        w = count / (count + OFFSET_PRIOR_POINTS)        # the registered mesh's where the scan has a hole
        offset = w * from_scan + (1.0 - w) * offset
    if skin_uncertainty:
        trust = skin_trust(template, state, skin_uncertainty)
        fill = _fill(offset, trust, faces)
        # Beyond SKIN_KEEP from the fill the offset is taken for another skinning's, not the body's.
        offset = fill + trust * (offset - fill) + (1.0 - trust) * np.clip(offset - fill, -SKIN_KEEP, SKIN_KEEP)
    rest = state.scale * state.rest
    rest = rest + offset[:, None] * vertex_normals(rest, faces)
    rest[:, 1] -= rest[:, 1].min()
    return rest
