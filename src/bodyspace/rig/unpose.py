"""Unposing: estimate the pose of a posed body of the rig's topology and bring it back to rest.

Given only a posed mesh (V, 3) of the rig's topology (no rest body: the person's own rest shape is
unknown), ``unpose`` finds the bone transforms that posed it and inverts linear blend skinning
vertex by vertex, so the rest-pose body keeps the person's own shape and detail.

Why a shape prior is needed. Any set of bone transforms can be "undone": inverting LBS with a
wrong pose still gives *a* body, just one whose arms hang at another angle. What singles out the
true pose is that the body it gives back is one a person has *at rest*. Fitting the bones to the
template as rest estimate and iterating "unpose, use the result as the next rest estimate" (the
obvious route) stops at its first step: the unposed body is by construction consistent with the
fitted pose, so the next fit returns the same rotations, which still hold the person's shape
against the template (on two library bodies the median vertex error was 11-123 mm after one
round and 21-238 mm after three, docs/unposing.md). Here the rest estimate is constrained
instead: the unposed body must lie in a linear *rest-shape space* (``RestShapePrior``, by default
the span of MakeHuman's macro targets around the template, which holds every phenotype body
exactly).

The fit (one Levenberg-Marquardt problem per body, batched over bodies):

- unknowns: a rigid transform ``G_p = [Q_p | t_p]`` for each *solved bone* p (the bones whose
  skin reaches far enough to show their pose, ``solved_bones``; the others move with their
  nearest solved ancestor, as in every pose of the library);
- the unposed vertex is ``x_v = M_v^-1 (y_v - m_v)`` with ``[M_v | m_v] = sum_p w_vp G_p``, the
  blended 3x4 transform of the posed vertex ``y_v``, inverted;
- residuals: (a) the part of the unposed body outside the rest-shape space,
  ``(I - U U^T)(x - mean)`` on a fixed sample of vertices (every solved bone's skin sampled,
  ``SAMPLES_PER_BONE``, plus ``SPREAD_SAMPLES`` spread over the body), and (b) the joints stay
  connected: ``JOINT_WEIGHT * (G_p - G_parent(p)) h_p``, with ``h_p`` the bone's rest head
  regressed from the unposed body itself (``Rig.head_regressor``), so the joints are the
  person's own; and two weak ones, each bone's rotation against its parent's (``_pose_prior``)
  and the skinless root's orientation against its children's (``_gauge``);
- exact Jacobians (the head term through the regressor rows), Gauss-Newton steps damped by
  Levenberg-Marquardt, started from a weighted Kabsch fit of each bone's dominant vertices
  against the prior's mean body.

Free per-bone translations tied by the joint residual (rather than forward kinematics, where
each joint depends on the rest heads, which depend on the unknown body) keep every Jacobian row
local to the few bones of one vertex; with the heads held inside FK, the same solver stalled at
about 10 mm. On bodies posed by our own LBS (``pose_bodies``) the fit comes back to the true
rest body to a few hundredths of a millimetre (docs/unposing.md has the numbers).

The result: the rest body (placed on the ground, pelvis x/z where the posed pelvis was), the
rotations in the convention of ``pose_bodies`` (``pose_bodies(rest, rig, rotations)`` gives the
posed mesh back, translated by ``info.translation``), and what was undone.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numba
import numpy as np
import scipy.sparse as sp
from scipy.linalg.blas import dsyrk
from scipy.linalg.lapack import dposv

from bodyspace.data.template import Rig, Template, load_template
from bodyspace.errors import MeshError, ParameterError, UnposeError
from bodyspace.mesh.solver import single_threaded_blas
from bodyspace.rig.kinematics import forward_kinematics, matrix_to_rotvec, rotvec_to_matrix, topological_order
from bodyspace.rig.posing import smoothed_weights

__all__ = ["RestShapePrior", "UnposeInfo", "fits_template", "solved_bones", "unpose", "unpose_known"]

# A bone is solved when its subtree's skin reaches at least this share of the body's height from
# its head (fingers, toes, eyes and lips reach a few centimetres and follow their parents; so do
# the metacarpals, whose 8-10 % would cost a tenth of the fit's time).
MIN_REACH = 0.10
# A solved bone without solved children must carry some vertex (with its unsolved descendants)
# at least this strongly, or its rotation hardly shows in the skin.
MIN_LEAF_WEIGHT = 0.8
# Vertices whose residual the fit uses: this many per solved bone (its dominant skin, spread by
# farthest-point sampling) plus this many spread over the whole body.
SAMPLES_PER_BONE = 10
SPREAD_SAMPLES = 100
# Directions of the rest-shape space kept on the sample: singular values above this share of the
# largest (178 directions on the default rig's sample, plus the three translations). Measured on 8
# library poses of 2 bodies: worst vertex 0.1 mm at 1e-5, 0.5 mm at 1e-4, 3 mm at 3e-4, 6 mm at
# 1e-3 (the span's small directions hold the phenotypes' differences in posture, which a pose
# would otherwise absorb).
PRIOR_RANK_TOLERANCE = 1e-5
# Weight of the joint residual against the shape residual (both in metres).
JOINT_WEIGHT = 1.0
# Weight (metres per radian) holding the root's orientation to its children's mean (_gauge).
GAUGE_WEIGHT = 0.01
# Weight (metres per radian) of the weak pull of each bone toward its parent's rotation (_pose_prior).
POSE_WEIGHT = 1e-3
# Levenberg-Marquardt: the starting damping (relative to the normal matrix's diagonal) and the
# most rejected steps in a row before a body is taken as converged.
LM_START = 1e-6
LM_MAX_TRIES = 10
MAX_ITERATIONS = 25
# A step that moves no bone by more than this (radians + metres), or lowers the cost by less than
# this share, ends the fit (under noise the cost stops falling long before the steps vanish).
STEP_TOLERANCE = 1e-6
COST_TOLERANCE = 1e-5
# Bones whose dominant skin has fewer vertices start at their parent's rotation.
MIN_DOMINANT_VERTICES = 4
# A vertex whose blended 3x3 transform has a determinant below this is folded (the blend of two
# very different rotations nearly collapses it); it is unposed with its heaviest bone alone.
MIN_BLEND_DETERMINANT = 0.05
# The unposed body must come within this RMS distance (metres) of the rest-shape space on the
# sample vertices, or the mesh is refused: it is not a posed body of this topology in its vertex
# order (a library body: < 0.001 mm; with 3 mm noise per coordinate: 2.5 mm; a shuffled vertex
# order: hundreds of mm).
MAX_SHAPE_DISTANCE = 0.03
# ``unpose_known``: a recorded pose explains a scan when the body it gives back is within this RMS
# distance (metres) of the rest-shape space on the sample vertices. The exact pose of a library
# body gives about 1e-7 m (the float32 rounding of the stored vertices and rotations); a wrong
# pose, or a body posed by another skinning, gives millimetres or more (then ``unpose`` fits it).
KNOWN_POSE_TOLERANCE = 1e-4
# Largest side of a posed body's bounding box, metres (a child curled up .. a tall adult in a star
# jump or reaching overhead), and the unit mistakes named when a mesh is outside it (their factor
# to metres; as ``measure`` names them).
POSED_EXTENT_M = (0.3, 3.5)
_UNIT_FACTORS = {"mm": 1000.0, "cm": 100.0, "inches": 1 / 0.0254, "km": 1e-3, "μm": 1e6}


# ------------------------------------------------------------------------------ the prior

@dataclass(frozen=True)
class RestShapePrior:
    """The linear space rest-pose bodies of one topology lie in: ``mean + span(directions)``.

    mean: (V, 3) a rest body (metres); directions: (K, V, 3) displacements spanning the space
    (any spanning set: MakeHuman's macro targets, or a shape model's principal components).
    Global translation is always allowed; rotation is not (rest bodies stand upright, +Y up,
    facing +Z).
    """

    mean: np.ndarray
    directions: np.ndarray
    name: str = "custom"

    @classmethod
    def from_template(cls, template: Template | None = None) -> "RestShapePrior":
        """The template's base mesh and its macro targets: every phenotype body lies in it."""
        template = template if template is not None else load_template()
        return cls(np.asarray(template.vertices, dtype=float), template.target_deltas,
                   name=f"{template.template_id} macro targets")


@lru_cache(maxsize=2)
def _default_prior() -> RestShapePrior:
    return RestShapePrior.from_template(load_template())


# ---------------------------------------------------------------------------- the solved bones

def solved_bones(rig: Rig, rest: np.ndarray, min_reach: float = MIN_REACH, weights: sp.spmatrix | None = None) -> np.ndarray:
    """Indices (P,) of the bones whose pose the fit estimates, parents before children.

    rig: the skeleton; rest: (V, 3) a rest body of its topology (its heads and skin extent);
    weights: the (V, B) skin weights (the rig's by default).
    A bone is solved when it carries skin, the skin of its subtree reaches at least
    ``min_reach`` x the body's height from its head, and its rotation shows in the skin: it has
    solved children, or some vertex follows it (with its unsolved descendants) with a weight of
    at least ``MIN_LEAF_WEIGHT``. That is the trunk, limbs, neck, head, jaw, hands and feet: 37
    bones of the 163 of MakeHuman's default rig. MakeHuman's breast bones reach far enough but
    blend at most 0.68 with the chest; free, they turned by up to 130 degrees to soak up a misfit
    (dual-quaternion-posed bodies), so they follow the chest. The root is always solved: it
    anchors the body's orientation and position.
    """
    parents = np.asarray(rig.parents)
    B = rig.n_bones
    W = sp.csc_matrix(rig.weights if weights is None else weights)
    heads = rig.heads(rest)
    height = float(np.ptp(rest[:, 1]))
    order = topological_order(parents)
    # Skin of each subtree: union of the bones' vertices, children first.
    skin: list[set] = [set(W.indices[W.indptr[b]:W.indptr[b + 1]].tolist()) for b in range(B)]
    for b in order[::-1]:
        if parents[b] >= 0:
            skin[parents[b]] |= skin[b]
    keep = np.zeros(B, dtype=bool)
    for b in order:
        if parents[b] < 0:
            keep[b] = True
        elif W.indptr[b + 1] > W.indptr[b] and skin[b]:
            keep[b] = np.linalg.norm(rest[list(skin[b])] - heads[b], axis=1).max() >= min_reach * height
    while True:
        follow = _follow(parents, keep, order)
        collapsed = sp.csc_matrix(W @ sp.csr_matrix((np.ones(B), (np.arange(B), follow)), shape=(B, B)))
        has_child = np.zeros(B, dtype=bool)
        for b in np.flatnonzero(keep):
            if parents[b] >= 0:
                has_child[follow[parents[b]]] = True
        strongest = np.asarray(collapsed.max(axis=0).todense()).ravel()
        weak = keep & ~has_child & (strongest < MIN_LEAF_WEIGHT) & (parents >= 0)
        if not weak.any():
            break
        keep &= ~weak
    return np.array([b for b in order if keep[b]], dtype=np.int64)


def _follow(parents: np.ndarray, keep: np.ndarray, order: np.ndarray) -> np.ndarray:
    """(B,) the nearest kept ancestor-or-self of every bone (a bone index)."""
    follow = np.arange(len(parents))
    for b in order:
        if not keep[b] and parents[b] >= 0:
            follow[b] = follow[parents[b]]
    return follow


# --------------------------------------------------------------------------------- the plan

def _farthest_points(points: np.ndarray, k: int) -> np.ndarray:
    """Indices of ``k`` points spread by farthest-point sampling (deterministic: starts at the
    point farthest from the centroid)."""
    n = len(points)
    if k >= n:
        return np.arange(n)
    chosen = [int(np.argmax(np.linalg.norm(points - points.mean(0), axis=1)))]
    dist = np.linalg.norm(points - points[chosen[0]], axis=1)
    for _ in range(k - 1):
        i = int(np.argmax(dist))
        chosen.append(i)
        dist = np.minimum(dist, np.linalg.norm(points - points[i], axis=1))
    return np.array(chosen)


@dataclass
class _Plan:
    """Everything about a (rig, weights, prior) that does not depend on the body: built once."""

    rig: Rig
    solved: np.ndarray            # (P,) bone indices, parents first, root first
    follow: np.ndarray            # (B,) position in ``solved`` of each bone's nearest solved ancestor-or-self
    parent: np.ndarray            # (P,) position of each solved bone's nearest solved ancestor (-1: root)
    collapsed: sp.csr_matrix      # (V, P) skin weights summed onto the solved bones
    dominant: np.ndarray          # (V,) solved bone (position) with the largest collapsed weight
    dominant_weight: np.ndarray   # (V,)
    mean: np.ndarray              # (V, 3) the prior's mean body (the start's rest estimate)
    mean_heads: np.ndarray        # (B, 3)
    work: np.ndarray              # (n_w,) vertices evaluated in the fit: samples first, then head regressors
    n_sample: int
    work_weights: sp.csr_matrix   # (n_w, P)
    e_vertex: np.ndarray          # (E,) entries of work_weights: local vertex, bone position, weight
    e_param: np.ndarray
    e_weight: np.ndarray
    basis: np.ndarray             # (r, 3 n_sample) orthonormal rows: the prior on the samples (+ translation)
    basis_mean: np.ndarray        # (3 n_sample,)
    per_param: list               # (entries, basis columns (r, 3k)) of each bone on the samples
    sample_slot: np.ndarray       # (E,) row of each sample entry in the bone-major layout, -1 off the sample
    param_ptr: np.ndarray         # (P + 1,) each bone's rows in that layout
    joints: np.ndarray            # (nc, 2) (bone, parent) positions connected by a joint residual
    jr_indptr: np.ndarray         # the rest heads of the connected bones from work vertices (CSR)
    jr_vertex: np.ndarray
    jr_coef: np.ndarray
    indptr: np.ndarray            # (n_w + 1,) entries of each work vertex
    root_children: np.ndarray     # positions of the solved bones whose solved parent is the root
    segments: np.ndarray          # positions of the solved bones dominating some skin (body parts)
    segment_skin: np.ndarray      # their dominated vertex counts


_PLANS: dict = {}


def _plan(rig: Rig, weights: sp.spmatrix, weights_key: str, prior: RestShapePrior) -> _Plan:
    key = (id(rig), weights_key, id(prior))
    hit = _PLANS.get(key)
    if hit is not None and hit[0] is rig and hit[1] is prior:
        return hit[2]
    plan = _build_plan(rig, weights, prior)
    _PLANS[key] = (rig, prior, plan)
    if len(_PLANS) > 8:
        _PLANS.pop(next(iter(_PLANS)))
    return plan


def _build_plan(rig: Rig, weights: sp.spmatrix, prior: RestShapePrior) -> _Plan:
    V = rig.weights.shape[0]
    mean = np.asarray(prior.mean, dtype=float)
    directions = np.asarray(prior.directions)
    if mean.shape != (V, 3) or directions.ndim != 3 or directions.shape[1:] != (V, 3):
        raise ParameterError(f"prior {prior.name!r}: mean {mean.shape} and directions {directions.shape}; "
                             f"expected ({V}, 3) and (K, {V}, 3) for rig {rig.name!r}")
    parents = np.asarray(rig.parents)
    solved = solved_bones(rig, mean, weights=weights)
    P = len(solved)
    position = -np.ones(rig.n_bones, dtype=np.int64)
    position[solved] = np.arange(P)
    follow = np.empty(rig.n_bones, dtype=np.int64)
    for b in topological_order(parents):
        follow[b] = position[b] if position[b] >= 0 else follow[parents[b]]
    parent = np.array([follow[parents[b]] if parents[b] >= 0 else -1 for b in solved], dtype=np.int64)

    onto = sp.csr_matrix((np.ones(rig.n_bones), (np.arange(rig.n_bones), follow)), shape=(rig.n_bones, P))
    collapsed = sp.csr_matrix(weights @ onto)
    collapsed.sum_duplicates()
    collapsed.eliminate_zeros()
    dense_rows = collapsed.toarray()
    dominant = dense_rows.argmax(1)
    dominant_weight = dense_rows.max(1)

    # Sample vertices: each solved bone's dominant skin, spread; and the body, spread.
    picks = [_farthest_points(mean, SPREAD_SAMPLES)]
    for p in range(P):
        own = np.flatnonzero((dominant == p) & (dominant_weight >= 0.5))
        if len(own):
            picks.append(own[_farthest_points(mean[own], SAMPLES_PER_BONE)])
    sample = np.unique(np.concatenate(picks))
    heads = rig.head_regressor[solved].tocsr()
    regressed = np.setdiff1d(np.unique(heads.indices), sample)
    work = np.concatenate([sample, regressed])
    n_s = len(sample)

    ww = collapsed[work].tocoo()
    e_vertex, e_param, e_weight = ww.row.astype(np.int64), ww.col.astype(np.int64), ww.data.astype(float)
    order = np.lexsort((e_param, e_vertex))
    e_vertex, e_param, e_weight = e_vertex[order], e_param[order], e_weight[order]

    # The prior restricted to the sample coordinates, with the three translations, orthonormal.
    # Right singular vectors through the small Gram matrix (K x K): a few times faster than the
    # SVD, and accurate to ~1e-11 for the singular values kept (>= 1e-5 of the largest).
    D = directions[:, sample].reshape(len(directions), -1).astype(float)
    lam, vec = np.linalg.eigh(D @ D.T)
    big = lam > (PRIOR_RANK_TOLERANCE ** 2) * lam.max() if len(lam) else np.zeros(0, dtype=bool)
    keep = (vec[:, big].T @ D) / np.sqrt(lam[big])[:, None]
    shift = np.zeros((3, n_s, 3))
    for a in range(3):
        shift[a, :, a] = 1.0
    q, r = np.linalg.qr(np.concatenate([keep, shift.reshape(3, -1)]).T)
    basis = q[:, np.abs(np.diag(r)) > 1e-9 * np.abs(np.diag(r)).max()].T
    basis_mean = mean[sample].ravel()

    in_sample = e_vertex < n_s
    per_param = []
    for p in range(P):
        ent = np.flatnonzero(in_sample & (e_param == p))
        cols = (3 * e_vertex[ent][:, None] + np.arange(3)).ravel()
        per_param.append((ent, np.ascontiguousarray(basis[:, cols])))
    indptr = np.searchsorted(e_vertex, np.arange(len(work) + 1)).astype(np.int64)
    sample_slot = -np.ones(len(e_vertex), dtype=np.int64)
    ordered = np.concatenate([ent for ent, _ in per_param])
    sample_slot[ordered] = np.arange(len(ordered))
    param_ptr = np.concatenate([[0], np.cumsum([len(ent) for ent, _ in per_param])]).astype(np.int64)

    joints = np.array([(i, parent[i]) for i in range(P) if parent[i] >= 0], dtype=np.int64).reshape(-1, 2)
    local = -np.ones(V, dtype=np.int64)
    local[work] = np.arange(len(work))
    H = heads[joints[:, 0]].tocsr()
    H.sort_indices()
    return _Plan(rig, solved, follow, parent, collapsed, dominant, dominant_weight, mean, rig.heads(mean),
                 work, n_s, sp.csr_matrix(collapsed[work]), e_vertex, e_param, e_weight, basis, basis_mean,
                 per_param, sample_slot, param_ptr, np.ascontiguousarray(joints), H.indptr.astype(np.int64),
                 local[H.indices].astype(np.int64), H.data.astype(float), indptr, np.flatnonzero(parent == 0),
                 *np.unique(dominant[dominant_weight >= 0.5], return_counts=True))


# ------------------------------------------------------------------------------ small maths

def _kabsch(H: np.ndarray) -> np.ndarray:
    """Rotations (..., 3, 3) maximizing tr(R^T H) for cross-covariances H = sum target source^T."""
    U, _, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(U @ Vt))
    d = np.where(d == 0, 1.0, d)
    U = U.copy()
    U[..., :, 2] *= d[..., None]
    return U @ Vt


def _blend(weights: sp.csr_matrix, Q: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Blended transforms of the rows of ``weights`` (n, P): M (N, n, 3, 3), m (N, n, 3)."""
    N, P = Q.shape[:2]
    A = np.concatenate([Q.reshape(N, P, 9), t], axis=2).transpose(1, 0, 2).reshape(P, N * 12)
    out = np.asarray(weights @ A).reshape(-1, N, 12).transpose(1, 0, 2)
    return out[..., :9].reshape(N, -1, 3, 3), out[..., 9:]


# --------------------------------------------------------------------------------- the fit

@dataclass
class UnposeInfo:
    """What ``unpose`` did, per body (arrays (N,), or scalars for one body).

    largest_rotation_deg / largest_rotation_bone: the largest turn of a body part (a solved bone
        that carries skin of its own) against the body's root, that was undone: e.g. 125 degrees
        for the lower leg in a deep squat.
    orientation_deg: how far the whole body was turned from upright, facing +Z.
    shape_distance_m: RMS distance of the unposed body from the rest-shape space on the sample
        vertices (0 for a library body; the person's own detail and the scan's noise for others).
    joint_gap_m: largest distance between a joint as its bone and as its parent place it.
    iterations, converged: of the Levenberg-Marquardt fit.
    folded_vertices: vertices whose blended transform was nearly singular (unposed rigidly).
    translation: (N, 3) ``pose_bodies(rest, rig, rotations) + translation`` is the posed mesh.
    """

    largest_rotation_deg: np.ndarray
    largest_rotation_bone: object
    orientation_deg: np.ndarray
    shape_distance_m: np.ndarray
    joint_gap_m: np.ndarray
    iterations: np.ndarray
    converged: np.ndarray
    folded_vertices: np.ndarray
    translation: np.ndarray

    def describe(self, i: int | None = None) -> str:
        """One line for people: what was undone (body ``i`` of a batch)."""
        pick = (lambda a: a) if i is None else (lambda a: a[i])
        return (f"largest rotation undone {float(pick(self.largest_rotation_deg)):.0f}° "
                f"({pick(self.largest_rotation_bone)} against the pelvis), body turned "
                f"{float(pick(self.orientation_deg)):.0f}° from upright facing +Z, "
                f"{1000 * float(pick(self.shape_distance_m)):.1f} mm from the rest-shape space")


def _initial_pose(plan: _Plan, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Start: each solved bone's rotation by weighted Kabsch of its dominant vertices (prior mean
    against the posed mesh), bones without enough of them at their parent's; translations from
    the joints chained from the root, then one shift so the mean residual is zero."""
    N = len(y)
    P = len(plan.solved)
    S, h = plan.mean, plan.mean_heads[plan.solved]
    cS = S.mean(0)
    cY = y.mean(1)
    Q = np.empty((N, P, 3, 3))
    whole = _kabsch(np.einsum("nvi,vj->nij", y - cY[:, None], S - cS))
    for p in range(P):
        Q[:, p] = whole if plan.parent[p] < 0 else Q[:, plan.parent[p]]
        own = np.flatnonzero((plan.dominant == p) & (plan.dominant_weight >= 0.5))
        if len(own) < MIN_DOMINANT_VERTICES:
            continue
        w = plan.dominant_weight[own]
        cs = w @ S[own] / w.sum()
        cy = np.einsum("v,nvi->ni", w, y[:, own]) / w.sum()
        H = np.einsum("v,nvi,vj->nij", w, y[:, own] - cy[:, None], S[own] - cs)
        Q[:, p] = _kabsch(H)
    j = np.empty((N, P, 3))
    for p in range(P):
        q = plan.parent[p]
        j[:, p] = (np.einsum("nij,j->ni", whole, h[p] - cS) + cY if q < 0 else
                   j[:, q] + np.einsum("nij,j->ni", Q[:, q], h[p] - h[q]))
    t = j - np.einsum("npij,pj->npi", Q, h)
    M, m = _blend(plan.work_weights, Q, t)
    posed = np.einsum("nvij,vj->nvi", M, S[plan.work]) + m
    t += (y[:, plan.work] - posed).mean(1)[:, None, :]
    return Q, t


# ------------------------------------------------------------------------ compiled kernels

_kernel = numba.njit(cache=True, nogil=True, fastmath={"contract"}, error_model="numpy")


@_kernel
def _unpose_work(Q, t, y, indptr, param, weight, x, Minv):
    """x_v = M_v^-1 (y_v - m_v) for the work vertices of one body; M_v^-1 kept for the Jacobian."""
    for v in range(len(indptr) - 1):
        a = b = c = d = e_ = f = g = h = i = 0.0
        m0 = m1 = m2 = 0.0
        for e in range(indptr[v], indptr[v + 1]):
            p, w = param[e], weight[e]
            m0 += w * t[p, 0]
            m1 += w * t[p, 1]
            m2 += w * t[p, 2]
            a += w * Q[p, 0, 0]
            b += w * Q[p, 0, 1]
            c += w * Q[p, 0, 2]
            d += w * Q[p, 1, 0]
            e_ += w * Q[p, 1, 1]
            f += w * Q[p, 1, 2]
            g += w * Q[p, 2, 0]
            h += w * Q[p, 2, 1]
            i += w * Q[p, 2, 2]
        A, B, C = e_ * i - f * h, f * g - d * i, d * h - e_ * g
        inv = 1.0 / (a * A + b * B + c * C)
        Minv[v, 0, 0], Minv[v, 0, 1], Minv[v, 0, 2] = A * inv, (c * h - b * i) * inv, (b * f - c * e_) * inv
        Minv[v, 1, 0], Minv[v, 1, 1], Minv[v, 1, 2] = B * inv, (a * i - c * g) * inv, (c * d - a * f) * inv
        Minv[v, 2, 0], Minv[v, 2, 1], Minv[v, 2, 2] = C * inv, (b * g - a * h) * inv, (a * e_ - b * d) * inv
        u0, u1, u2 = y[v, 0] - m0, y[v, 1] - m1, y[v, 2] - m2
        for r in range(3):
            x[v, r] = Minv[v, r, 0] * u0 + Minv[v, r, 1] * u1 + Minv[v, r, 2] * u2


@_kernel
def _unpose_all(Q, t, y, indptr, param, weight, dominant, min_det, out):
    """Every vertex of every body unposed: out[n, v] = M_v^-1 (y_v - m_v); a vertex whose blend is
    folded (det M_v < min_det) is unposed by its dominant bone alone. Returns folded counts (N,)."""
    N, V = y.shape[0], y.shape[1]
    folded = np.zeros(N, dtype=np.int64)
    for n in range(N):
        for v in range(V):
            a = b = c = d = e_ = f = g = h = i = 0.0
            m0 = m1 = m2 = 0.0
            for e in range(indptr[v], indptr[v + 1]):
                p, w = param[e], weight[e]
                m0 += w * t[n, p, 0]
                m1 += w * t[n, p, 1]
                m2 += w * t[n, p, 2]
                a += w * Q[n, p, 0, 0]
                b += w * Q[n, p, 0, 1]
                c += w * Q[n, p, 0, 2]
                d += w * Q[n, p, 1, 0]
                e_ += w * Q[n, p, 1, 1]
                f += w * Q[n, p, 1, 2]
                g += w * Q[n, p, 2, 0]
                h += w * Q[n, p, 2, 1]
                i += w * Q[n, p, 2, 2]
            A, B, C = e_ * i - f * h, f * g - d * i, d * h - e_ * g
            det = a * A + b * B + c * C
            u0, u1, u2 = y[n, v, 0] - m0, y[n, v, 1] - m1, y[n, v, 2] - m2
            if det > min_det:
                inv = 1.0 / det
                out[n, v, 0] = (A * u0 + (c * h - b * i) * u1 + (b * f - c * e_) * u2) * inv
                out[n, v, 1] = (B * u0 + (a * i - c * g) * u1 + (c * d - a * f) * u2) * inv
                out[n, v, 2] = (C * u0 + (b * g - a * h) * u1 + (a * e_ - b * d) * u2) * inv
            else:
                folded[n] += 1
                p = dominant[v]
                u0, u1, u2 = y[n, v, 0] - t[n, p, 0], y[n, v, 1] - t[n, p, 1], y[n, v, 2] - t[n, p, 2]
                for r in range(3):
                    out[n, v, r] = Q[n, p, 0, r] * u0 + Q[n, p, 1, r] * u1 + Q[n, p, 2, r] * u2
    return folded


@numba.njit(cache=True, nogil=True)
def _translate(x, shift):
    """x[n, v] += shift[n] for x (N, V, 3), shift (N, 3): numpy's broadcast add runs an inner
    loop of three elements per vertex (8x slower)."""
    for n in range(x.shape[0]):
        s0, s1, s2 = shift[n, 0], shift[n, 1], shift[n, 2]
        for v in range(x.shape[1]):
            x[n, v, 0] += s0
            x[n, v, 1] += s1
            x[n, v, 2] += s2


@_kernel
def _known_heads(M, y, p_indptr, p_index, p_data, h_indptr, h_index, h_data, D, turned, heads):
    """``unpose_known``'s rest heads of the turned bones, per body n: the linear system
    h_j + sum_k T[j, k] D[n, k] h_k = sum_v Hd[j, v] K_v y[n, v] over the bones j, k that body n
    turns (``turned[n]``), with T[j, k] = sum_v P[(j, k), v] K_v and K_v = M[n, v]^-1 (adjugate),
    solved by Gaussian elimination with partial pivoting into heads[n, j] (the rest stay 0).

    M (N, S, 3, 3) blended rotations and y (N, S, 3) posed points of the regressor's vertices; P
    (r*r, S) and Hd (r, S) as CSR arrays; D (N, r, 3, 3); turned (N, r) bool; heads (N, r, 3).
    """
    N, S, r = M.shape[0], M.shape[1], D.shape[1]
    K = np.empty((S, 3, 3))
    T = np.empty((3, 3))
    idx = np.empty(r, dtype=np.int64)
    system = np.empty((3 * r, 3 * r))
    rhs = np.empty(3 * r)
    for n in range(N):
        m = 0
        for k in range(r):
            if turned[n, k]:
                idx[m] = k
                m += 1
        if m == 0:
            continue
        for v in range(S):
            a, b, c = M[n, v, 0, 0], M[n, v, 0, 1], M[n, v, 0, 2]
            d, e, f = M[n, v, 1, 0], M[n, v, 1, 1], M[n, v, 1, 2]
            g, h, i = M[n, v, 2, 0], M[n, v, 2, 1], M[n, v, 2, 2]
            A, B, C = e * i - f * h, f * g - d * i, d * h - e * g
            inv = 1.0 / (a * A + b * B + c * C)
            K[v, 0, 0], K[v, 0, 1], K[v, 0, 2] = A * inv, (c * h - b * i) * inv, (b * f - c * e) * inv
            K[v, 1, 0], K[v, 1, 1], K[v, 1, 2] = B * inv, (a * i - c * g) * inv, (c * d - a * f) * inv
            K[v, 2, 0], K[v, 2, 1], K[v, 2, 2] = C * inv, (b * g - a * h) * inv, (a * e - b * d) * inv
        for jj in range(m):
            j = idx[jj]
            for a in range(3):
                rhs[3 * jj + a] = 0.0
            for q in range(h_indptr[j], h_indptr[j + 1]):
                v, w = h_index[q], h_data[q]
                for a in range(3):
                    rhs[3 * jj + a] += w * (K[v, a, 0] * y[n, v, 0] + K[v, a, 1] * y[n, v, 1]
                                            + K[v, a, 2] * y[n, v, 2])
            for kk in range(m):
                k = idx[kk]
                T[:] = 0.0
                row = j * r + k
                for q in range(p_indptr[row], p_indptr[row + 1]):
                    v, w = p_index[q], p_data[q]
                    for a in range(3):
                        for c in range(3):
                            T[a, c] += w * K[v, a, c]
                for a in range(3):
                    for b in range(3):
                        system[3 * jj + a, 3 * kk + b] = (T[a, 0] * D[n, k, 0, b] + T[a, 1] * D[n, k, 1, b]
                                                          + T[a, 2] * D[n, k, 2, b]
                                                          + (1.0 if jj == kk and a == b else 0.0))
        size = 3 * m
        for col in range(size):                          # elimination, partial pivoting
            piv = col
            for row in range(col + 1, size):
                if abs(system[row, col]) > abs(system[piv, col]):
                    piv = row
            if piv != col:
                for c in range(col, size):
                    system[col, c], system[piv, c] = system[piv, c], system[col, c]
                rhs[col], rhs[piv] = rhs[piv], rhs[col]
            for row in range(col + 1, size):
                f = system[row, col] / system[col, col]
                if f != 0.0:
                    for c in range(col + 1, size):
                        system[row, c] -= f * system[col, c]
                    rhs[row] -= f * rhs[col]
        for row in range(size - 1, -1, -1):             # back substitution
            s = rhs[row]
            for c in range(row + 1, size):
                s -= system[row, c] * rhs[c]
            rhs[row] = s / system[row, row]
        for jj in range(m):
            for a in range(3):
                heads[n, idx[jj], a] = rhs[3 * jj + a]
    return 0


@_kernel
def _residuals_kernel(Q, t, y, indptr, param, weight, n_sample, mean_s, ji, jp, jr_indptr, jr_vertex, jr_coef,
                      joint_weight, rs, C, heads, x, Minv):
    """Per body n: the sample residual before projection rs[n] (3 n_s), joint residuals C[n]
    (nc, 3) and rest heads heads[n] (nc, 3); x[n], Minv[n] of the work vertices."""
    for n in range(Q.shape[0]):
        _unpose_work(Q[n], t[n], y[n], indptr, param, weight, x[n], Minv[n])
        for v in range(n_sample):
            for r in range(3):
                rs[n, 3 * v + r] = x[n, v, r] - mean_s[3 * v + r]
        for c in range(len(ji)):
            h0 = h1 = h2 = 0.0
            for k in range(jr_indptr[c], jr_indptr[c + 1]):
                v = jr_vertex[k]
                h0 += jr_coef[k] * x[n, v, 0]
                h1 += jr_coef[k] * x[n, v, 1]
                h2 += jr_coef[k] * x[n, v, 2]
            heads[n, c, 0], heads[n, c, 1], heads[n, c, 2] = h0, h1, h2
            i, p = ji[c], jp[c]
            for r in range(3):
                C[n, c, r] = joint_weight * (t[n, i, r] - t[n, p, r] + (Q[n, i, r, 0] - Q[n, p, r, 0]) * h0
                                             + (Q[n, i, r, 1] - Q[n, p, r, 1]) * h1 + (Q[n, i, r, 2] - Q[n, p, r, 2]) * h2)


@_kernel
def _jacobian_kernel(Q, t, x, Minv, indptr, param, weight, n_sample, ji, jp, jr_indptr, jr_vertex, jr_coef,
                     joint_weight, C, heads, slot, Bk, Bs, normal, grad):
    """Per body n: the Jacobian blocks Bk (N, E, 3, 6) of every work entry (the sample entries
    also into Bs (E_s, 3, N, 6), bone by bone at ``slot[e]``), the sparse part of
    the normal matrix (J^T J on the sample, the joint rows' J^T J; upper triangle) and the joint
    rows' gradient."""
    N, P = Q.shape[0], Q.shape[1]
    D = 6 * P
    nc = len(ji)
    rows = np.zeros((3, D))
    Dq = np.empty((3, 3))
    touched = np.zeros(P, dtype=np.bool_)
    plist = np.empty(P, dtype=np.int64)
    for n in range(N):
        for v in range(len(indptr) - 1):
            for e in range(indptr[v], indptr[v + 1]):
                p, w = param[e], weight[e]
                q0 = Q[n, p, 0, 0] * x[n, v, 0] + Q[n, p, 0, 1] * x[n, v, 1] + Q[n, p, 0, 2] * x[n, v, 2]
                q1 = Q[n, p, 1, 0] * x[n, v, 0] + Q[n, p, 1, 1] * x[n, v, 1] + Q[n, p, 1, 2] * x[n, v, 2]
                q2 = Q[n, p, 2, 0] * x[n, v, 0] + Q[n, p, 2, 1] * x[n, v, 1] + Q[n, p, 2, 2] * x[n, v, 2]
                for r in range(3):
                    m0, m1, m2 = w * Minv[n, v, r, 0], w * Minv[n, v, r, 1], w * Minv[n, v, r, 2]
                    # (w M^-1) [Q x]_x : columns of the skew matrix [[0,-q2,q1],[q2,0,-q0],[-q1,q0,0]]
                    Bk[n, e, r, 0] = m1 * q2 - m2 * q1
                    Bk[n, e, r, 1] = -m0 * q2 + m2 * q0
                    Bk[n, e, r, 2] = m0 * q1 - m1 * q0
                    Bk[n, e, r, 3] = -m0
                    Bk[n, e, r, 4] = -m1
                    Bk[n, e, r, 5] = -m2
                    k = slot[e]
                    if k >= 0:   # a sample entry: also in the layout of the prior's gemm (bone-major)
                        for a in range(6):
                            Bs[k, r, n, a] = Bk[n, e, r, a]
        # J^T J of the sample residual: pairs of entries on one vertex, upper triangle only (the
        # entries of a vertex are sorted by bone, so e2 >= e1 is a block on or above the diagonal).
        for v in range(n_sample):
            for e1 in range(indptr[v], indptr[v + 1]):
                o1 = 6 * param[e1]
                for e2 in range(e1, indptr[v + 1]):
                    o2 = 6 * param[e2]
                    for a in range(6):
                        x0, x1, x2 = Bk[n, e1, 0, a], Bk[n, e1, 1, a], Bk[n, e1, 2, a]
                        for b in range(6):
                            normal[n, o1 + a, o2 + b] += x0 * Bk[n, e2, 0, b] + x1 * Bk[n, e2, 1, b] + x2 * Bk[n, e2, 2, b]
        # Joint rows: d/dparams of (Q_i - Q_p) h + t_i - t_p, h regressed from the unposed body.
        for c in range(nc):
            i, p = ji[c], jp[c]
            count = 0
            for k in range(jr_indptr[c], jr_indptr[c + 1]):
                v = jr_vertex[k]
                for e in range(indptr[v], indptr[v + 1]):
                    q = param[e]
                    if not touched[q]:
                        touched[q] = True
                        plist[count] = q
                        count += 1
            for q in (i, p):
                if not touched[q]:
                    touched[q] = True
                    plist[count] = q
                    count += 1
            # rows = (Q_i - Q_p) dh, dh = sum_v coef_v sum_e B_e
            for r in range(3):
                for s in range(3):
                    Dq[r, s] = Q[n, i, r, s] - Q[n, p, r, s]
            for k in range(jr_indptr[c], jr_indptr[c + 1]):
                v = jr_vertex[k]
                h = jr_coef[k]
                for e in range(indptr[v], indptr[v + 1]):
                    o = 6 * param[e]
                    for a in range(6):
                        b0, b1, b2 = h * Bk[n, e, 0, a], h * Bk[n, e, 1, a], h * Bk[n, e, 2, a]
                        for r in range(3):
                            rows[r, o + a] += Dq[r, 0] * b0 + Dq[r, 1] * b1 + Dq[r, 2] * b2
            hi0 = Q[n, i, 0, 0] * heads[n, c, 0] + Q[n, i, 0, 1] * heads[n, c, 1] + Q[n, i, 0, 2] * heads[n, c, 2]
            hi1 = Q[n, i, 1, 0] * heads[n, c, 0] + Q[n, i, 1, 1] * heads[n, c, 1] + Q[n, i, 1, 2] * heads[n, c, 2]
            hi2 = Q[n, i, 2, 0] * heads[n, c, 0] + Q[n, i, 2, 1] * heads[n, c, 1] + Q[n, i, 2, 2] * heads[n, c, 2]
            hp0 = Q[n, p, 0, 0] * heads[n, c, 0] + Q[n, p, 0, 1] * heads[n, c, 1] + Q[n, p, 0, 2] * heads[n, c, 2]
            hp1 = Q[n, p, 1, 0] * heads[n, c, 0] + Q[n, p, 1, 1] * heads[n, c, 1] + Q[n, p, 1, 2] * heads[n, c, 2]
            hp2 = Q[n, p, 2, 0] * heads[n, c, 0] + Q[n, p, 2, 1] * heads[n, c, 1] + Q[n, p, 2, 2] * heads[n, c, 2]
            oi, op = 6 * i, 6 * p
            # -[Q_i h]_x on the rotation of i, +[Q_p h]_x on the rotation of p; +I / -I on the translations.
            rows[0, oi + 1] += hi2
            rows[0, oi + 2] -= hi1
            rows[1, oi + 0] -= hi2
            rows[1, oi + 2] += hi0
            rows[2, oi + 0] += hi1
            rows[2, oi + 1] -= hi0
            rows[0, op + 1] -= hp2
            rows[0, op + 2] += hp1
            rows[1, op + 0] += hp2
            rows[1, op + 2] -= hp0
            rows[2, op + 0] -= hp1
            rows[2, op + 1] += hp0
            for r in range(3):
                rows[r, oi + 3 + r] += 1.0
                rows[r, op + 3 + r] -= 1.0
            w2 = joint_weight * joint_weight
            for a_ in range(count):
                oa = 6 * plist[a_]
                for a in range(6):
                    r0, r1, r2 = rows[0, oa + a], rows[1, oa + a], rows[2, oa + a]
                    grad[n, oa + a] += joint_weight * (r0 * C[n, c, 0] + r1 * C[n, c, 1] + r2 * C[n, c, 2])
                    r0, r1, r2 = w2 * r0, w2 * r1, w2 * r2
                    for b_ in range(count):
                        if plist[b_] < plist[a_]:
                            continue   # lower triangle: not read
                        ob = 6 * plist[b_]
                        for b in range(6):
                            normal[n, oa + a, ob + b] += r0 * rows[0, ob + b] + r1 * rows[1, ob + b] + r2 * rows[2, ob + b]
            for a_ in range(count):
                oa = 6 * plist[a_]
                touched[plist[a_]] = False
                for r in range(3):
                    for a in range(6):
                        rows[r, oa + a] = 0.0


@_kernel
def _gradient_kernel(Bk, F, indptr, param, n_sample, grad):
    """grad[n] += J^T F[n] over the sample vertices (Bk (N, E, 3, 6), F (N, 3 n_s))."""
    for n in range(F.shape[0]):
        for v in range(n_sample):
            for e in range(indptr[v], indptr[v + 1]):
                o = 6 * param[e]
                for a in range(6):
                    grad[n, o + a] += (Bk[n, e, 0, a] * F[n, 3 * v] + Bk[n, e, 1, a] * F[n, 3 * v + 1]
                                       + Bk[n, e, 2, a] * F[n, 3 * v + 2])


def _left_jacobian_inverse(phi: np.ndarray) -> np.ndarray:
    """J_l^-1(phi) (..., 3, 3) of SO(3): d rotvec(exp(w) R) = J_l^-1(rotvec R) w for small w."""
    theta = np.linalg.norm(phi, axis=-1)
    small = theta < 1e-6
    th = np.where(small, 1.0, theta)
    coef = np.where(small, 1.0 / 12.0, (1.0 / th ** 2 - (1.0 + np.cos(th)) / (2.0 * th * np.sin(th))))
    K = _skew(phi)
    return np.eye(3) - 0.5 * K + coef[..., None, None] * (K @ K)


def _skew(a: np.ndarray) -> np.ndarray:
    """Cross-product matrices (..., 3, 3) of vectors (..., 3)."""
    z = np.zeros(a.shape[:-1])
    x, y, w = a[..., 0], a[..., 1], a[..., 2]
    return np.stack([np.stack([z, -w, y], -1), np.stack([w, z, -x], -1), np.stack([-y, x, z], -1)], -2)


def _pose_prior(plan: _Plan, Q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each solved bone's rotation relative to its parent: (rotation vectors (N, nc, 3), cost (N,)).

    The residual ``POSE_WEIGHT * rotvec(Q_bone Q_parent^T)`` is far too weak to move a bone the
    skin determines (on library bodies it changes nothing measurable), but it keeps a bone the
    skin hardly constrains (a breast, a clavicle under noise or under skinning that LBS cannot
    reproduce exactly) from turning freely to soak up the misfit.
    """
    i, p = plan.joints[:, 0], plan.joints[:, 1]
    phi = matrix_to_rotvec(Q[:, i] @ np.swapaxes(Q[:, p], -1, -2))
    return phi, POSE_WEIGHT ** 2 * np.einsum("nci,nci->n", phi, phi)


def _gauge(plan: _Plan, Q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The root's orientation against the mean of its solved children's: (rotation vector
    (N, 3), cost term (N,)).

    MakeHuman's root carries no skin and its children (spine05, pelvis.L/R) share their head, so
    the root may turn about that head without changing any residual; undamped, that direction
    drifted by 50 degrees. A weak residual ``GAUGE_WEIGHT * rotvec(Q_root Qbar^T)`` (Qbar: the
    chordal mean of the children's rotations) fixes it without biasing what the data decide.
    """
    kids = plan.root_children
    if not len(kids):
        return np.zeros((len(Q), 3)), np.zeros(len(Q))
    mean = _kabsch(Q[:, kids].sum(1))
    rho = matrix_to_rotvec(Q[:, 0] @ np.swapaxes(mean, -1, -2))
    return rho, GAUGE_WEIGHT ** 2 * np.einsum("ni,ni->n", rho, rho)


def _add_priors(plan: _Plan, Q: np.ndarray, normal: np.ndarray, grad: np.ndarray) -> None:
    """Add the Gauss-Newton terms of the pose prior and the root's gauge to ``normal`` (N, 6P, 6P)
    and ``grad`` (N, 6P), in place."""
    # The weak pose prior (see _pose_prior): d phi = J_l^-1 w_bone - J_l^-1^T w_parent.
    phi, _ = _pose_prior(plan, Q)
    A = _left_jacobian_inverse(phi)                                     # (N, nc, 3, 3)
    w2 = POSE_WEIGHT ** 2
    for c, (i, p) in enumerate(plan.joints):
        a, b = A[:, c], -np.swapaxes(A[:, c], -1, -2)
        si, sp_ = slice(6 * i, 6 * i + 3), slice(6 * p, 6 * p + 3)
        normal[:, si, si] += w2 * np.swapaxes(a, -1, -2) @ a
        normal[:, sp_, sp_] += w2 * np.swapaxes(b, -1, -2) @ b
        normal[:, sp_, si] += w2 * np.swapaxes(b, -1, -2) @ a
        normal[:, si, sp_] += w2 * np.swapaxes(a, -1, -2) @ b
        grad[:, si] += w2 * np.einsum("nji,nj->ni", a, phi[:, c])
        grad[:, sp_] += w2 * np.einsum("nji,nj->ni", b, phi[:, c])
    # The root's orientation: held to its children's mean (see _gauge).
    rho, _ = _gauge(plan, Q)
    kids = plan.root_children
    if not len(kids):
        return
    cols = [slice(0, 3)] + [slice(6 * k, 6 * k + 3) for k in kids]
    coef = [1.0] + [-1.0 / len(kids)] * len(kids)
    w2 = GAUGE_WEIGHT ** 2
    for ca, sa in zip(coef, cols):
        grad[:, sa] += w2 * ca * rho
        for cb, sb in zip(coef, cols):
            normal[:, sa, sb] += w2 * ca * cb * np.eye(3)


class _State:
    """Residuals (and the Gauss-Newton normal equations) of the fit for a batch of posed bodies."""

    def __init__(self, plan: _Plan, y_work: np.ndarray):
        self.plan = plan
        self.y = np.ascontiguousarray(y_work)                   # (N, n_w, 3)

    def _residuals(self, Q, t, y):
        plan = self.plan
        N = len(Q)
        nw, ns, nc = len(plan.work), plan.n_sample, len(plan.joints)
        rs, C = np.empty((N, 3 * ns)), np.empty((N, nc, 3))
        heads, x, Minv = np.empty((N, nc, 3)), np.empty((N, nw, 3)), np.empty((N, nw, 3, 3))
        _residuals_kernel(Q, t, y, plan.indptr, plan.e_param, plan.e_weight, ns, plan.basis_mean,
                          plan.joints[:, 0], plan.joints[:, 1], plan.jr_indptr, plan.jr_vertex, plan.jr_coef,
                          JOINT_WEIGHT, rs, C, heads, x, Minv)
        F = rs - (rs @ plan.basis.T) @ plan.basis
        cost = (np.einsum("ni,ni->n", F, F) + np.einsum("nci,nci->n", C, C) + _gauge(plan, Q)[1]
                + _pose_prior(plan, Q)[1])
        return F, C, heads, x, Minv, cost

    def cost(self, Q, t, rows=None):
        y = self.y if rows is None else self.y[rows]
        return self._residuals(np.ascontiguousarray(Q), np.ascontiguousarray(t), y)[-1]

    def residuals(self, Q, t):
        F, C, _, _, _, _ = self._residuals(np.ascontiguousarray(Q), np.ascontiguousarray(t), self.y)
        return F, C

    def normal_equations(self, Q, t, rows):
        """(cost (N,), normal (N, 6P, 6P), gradient (N, 6P)) of the Gauss-Newton step at (Q, t)."""
        plan = self.plan
        Q, t = np.ascontiguousarray(Q), np.ascontiguousarray(t)
        y = self.y[rows]
        N, P = Q.shape[:2]
        F, C, heads, x, Minv, cost = self._residuals(Q, t, y)
        E = len(plan.e_param)
        Bk = np.empty((N, E, 3, 6))
        Bs = np.empty((plan.param_ptr[-1], 3, N, 6))
        normal = np.zeros((N, 6 * P, 6 * P))
        grad = np.zeros((N, 6 * P))
        _jacobian_kernel(Q, t, x, Minv, plan.indptr, plan.e_param, plan.e_weight, plan.n_sample,
                         plan.joints[:, 0], plan.joints[:, 1], plan.jr_indptr, plan.jr_vertex, plan.jr_coef,
                         JOINT_WEIGHT, C, heads, plan.sample_slot, Bk, Bs, normal, grad)
        _gradient_kernel(Bk, F, plan.indptr, plan.e_param, plan.n_sample, grad)
        # The part of J^T J inside the prior, (U J)^T (U J): U J gathered bone by bone, then a
        # symmetric rank-r update of the upper triangle (the solver reads only that triangle).
        r = plan.basis.shape[0]
        UJ = np.zeros((N, r, 6 * P))
        for p, (ent, cols) in enumerate(plan.per_param):
            if len(ent):   # one gemm for the whole batch: the bone's blocks, (3k, N * 6), a view
                block = Bs[plan.param_ptr[p]:plan.param_ptr[p + 1]].reshape(3 * len(ent), N * 6)
                UJ[:, :, 6 * p:6 * p + 6] = (cols @ block).reshape(r, N, 6).transpose(1, 0, 2)
        for n in range(N):
            dsyrk(-1.0, UJ[n].T, beta=1.0, c=normal[n].T, trans=0, lower=1, overwrite_c=1)
        _add_priors(plan, Q, normal, grad)
        return cost, normal, grad


def _solve_spd(A: np.ndarray, b: np.ndarray) -> np.ndarray:
    """x (N, n) solving A[k] x[k] = b[k] for symmetric positive definite A (N, n, n) of which only
    the upper triangle is read (Cholesky, LAPACK dposv on the transposed view: no copy, half the
    work of LU). A matrix that is not positive definite is solved by least squares. A is overwritten."""
    x = np.empty_like(b)
    for k in range(len(A)):
        _, xk, info = dposv(A[k].T, b[k], lower=True, overwrite_a=True, overwrite_b=False)
        if info == 0:
            x[k] = xk
        else:
            full = np.triu(A[k]) + np.triu(A[k], 1).T
            x[k] = np.linalg.lstsq(full, b[k], rcond=None)[0]
    return x


def _fit(plan: _Plan, y: np.ndarray, max_iterations: int, start=None,
         state_type=None) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Levenberg-Marquardt over every body of the batch: (Q, t, iterations, converged).

    The damping follows Nielsen's rule (Madsen, Nielsen & Tingleff, "Methods for non-linear
    least squares problems", 2004, §3.2): after a step with gain ratio rho (actual over predicted
    decrease) lambda *= max(1/3, 1 - (2 rho - 1)^3); a rejected step multiplies it by nu, which
    doubles on each rejection in a row.
    """
    N = len(y)
    P = len(plan.solved)
    Q, t = _initial_pose(plan, y) if start is None else (start[0].copy(), start[1].copy())
    state = (state_type or _State)(plan, y[:, plan.work])
    lam = np.full(N, LM_START)
    nu = np.full(N, 2.0)
    active = np.ones(N, dtype=bool)
    iterations = np.zeros(N, dtype=np.int64)
    converged = np.zeros(N, dtype=bool)
    for _ in range(max_iterations):
        idx = np.flatnonzero(active)
        if not len(idx):
            break
        cost, normal, g = state.normal_equations(Q[idx], t[idx], idx)
        diag = np.einsum("nii->ni", normal).copy()
        diag += 1e-12 * diag.max(1, keepdims=True) + 1e-30
        pending = np.ones(len(idx), dtype=bool)
        for _try in range(LM_MAX_TRIES):
            k = np.flatnonzero(pending)
            if not len(k):
                break
            A = normal[k].copy()
            A[:, np.arange(6 * P), np.arange(6 * P)] += lam[idx[k], None] * diag[k]
            step = -_solve_spd(A, g[k])
            predicted = -np.einsum("ni,ni->n", g[k], step) + lam[idx[k]] * np.einsum("ni,ni,ni->n", step, diag[k], step)
            step = step.reshape(len(k), P, 6)
            Qn = rotvec_to_matrix(step[..., :3]) @ Q[idx[k]]
            tn = t[idx[k]] + step[..., 3:]
            new = state.cost(Qn, tn, idx[k])
            ok = np.isfinite(new) & (new < cost[k])
            rho = (cost[k] - new) / np.maximum(predicted, 1e-300)
            for j in np.flatnonzero(ok):
                b = idx[k[j]]
                Q[b], t[b] = Qn[j], tn[j]
                lam[b] *= max(1.0 / 3.0, 1.0 - (2.0 * min(rho[j], 1.0) - 1.0) ** 3)
                nu[b] = 2.0
                iterations[b] += 1
                # Done when no vertex within a metre of its joint moves by STEP_TOLERANCE.
                moved = np.abs(step[j, :, :3]).max() + np.abs(step[j, :, 3:]).max()
                if moved < STEP_TOLERANCE or cost[k[j]] - new[j] <= COST_TOLERANCE * cost[k[j]]:
                    active[b] = False
                    converged[b] = True
            bad = idx[k[~ok]]
            lam[bad] *= nu[bad]
            nu[bad] *= 2.0
            pending[k[ok]] = False
        # A body no step improves any more is at its minimum (to the damping's resolution).
        for j in np.flatnonzero(pending):
            active[idx[j]] = False
            converged[idx[j]] = True
    return Q, t, iterations, converged


def fits_template(vertices: np.ndarray, faces: np.ndarray, template: Template) -> bool:
    """Whether a mesh (V, 3), (F, 3) is of the template's topology in its vertex order: the
    template's vertex count, and every face one of the template's (a mesh with holes punched in
    it still fits; a remeshed or reordered one does not)."""
    f = np.asarray(faces, dtype=np.int64)
    if np.shape(vertices)[-2] != template.n_vertices or f.ndim != 2 or f.shape[1] != 3 or len(f) > len(template.faces):
        return False
    if f.shape == template.faces.shape and np.array_equal(f, template.faces):
        return True
    V = template.n_vertices

    def keys(tri):   # a triangle whatever its starting corner: the rotation with the smallest index first
        r = np.argmin(tri, axis=1)
        t = np.stack([tri[np.arange(len(tri)), (r + k) % 3] for k in range(3)], axis=1)
        return (t[:, 0] * V + t[:, 1]) * V + t[:, 2]

    return bool(np.isin(keys(f), keys(np.asarray(template.faces, dtype=np.int64))).all())


def _check_scale(y: np.ndarray, mesh_name: str) -> None:
    """Refuse bodies (N, V, 3) that are not human-sized in metres in any pose (a person reaching
    up and out spans more than standing: the limits are wider than ``measure``'s), naming the
    unit the mesh is probably in."""
    extent = (y.max(axis=1) - y.min(axis=1)).max(axis=1)
    lo, hi = POSED_EXTENT_M
    bad = np.flatnonzero(~((extent >= lo) & (extent <= hi)))
    if not len(bad):
        return
    i, size = int(bad[0]), float(extent[bad[0]])
    which = mesh_name if len(y) == 1 else f"body {i} of {mesh_name}"
    if not np.isfinite(size) or size == 0:
        raise MeshError(f"{which}: its bounding box is {size:g} m across; expected a posed human body in metres "
                        f"({lo:g}-{hi:g} m)")
    factor = size / 1.7   # against a body of average height
    unit = min(_UNIT_FACTORS, key=lambda u: abs(np.log(factor / _UNIT_FACTORS[u])))
    near = abs(np.log(factor / _UNIT_FACTORS[unit])) < np.log(2.0)
    shown = _UNIT_FACTORS[unit] if near else factor
    guess = (f"the mesh is {max(shown, 1 / shown):.4g}x too {'large' if factor > 1 else 'small'}"
             + (f": is it in {unit}? scale it to metres (multiply by {1 / _UNIT_FACTORS[unit]:g})" if near else
                "; scale it to metres"))
    raise MeshError(f"{which}: its bounding box is {size:.3g} m across, a posed human body's is {lo:g}-{hi:g} m; "
                    f"{guess}")


def _resolve_weights(rig: Rig, weights: str, faces) -> tuple[sp.csr_matrix, str]:
    if weights == "original":
        return rig.weights.tocsr(), "original"
    if weights == "smoothed":
        return smoothed_weights(rig, faces), "smoothed"
    raise ParameterError(f"weights={weights!r}; expected 'original' (MakeHuman's, as pose_bodies uses by "
                         "default) or 'smoothed'")


def unpose(vertices: np.ndarray, rig: Rig, *, prior: RestShapePrior | None = None, weights: str = "original",
           faces: np.ndarray | None = None, max_iterations: int = MAX_ITERATIONS, check: bool = True,
           mesh_name: str = "vertices"):
    """The rest-pose body, the pose and what was undone, from posed bodies of the rig's topology.

    vertices: (V, 3) or (N, V, 3) posed bodies of the rig's topology (metres, any position and
        heading), e.g. from ``pose_bodies`` or a registered scan.
    rig: the skeleton that posed them (e.g. ``load_template().rigs["default"]``).
    prior: the rest-shape space (default: the template's macro-target span,
        ``RestShapePrior.from_template``).
    weights: the skin weights of the skinning to invert: ``"original"`` (the default, as
        ``pose_bodies`` and the synthetic population use) or ``"smoothed"``.
    faces: (F, 3) only for ``weights="smoothed"`` (the template's by default).
    check: refuse (UnposeError) a mesh the fit cannot bring within ``MAX_SHAPE_DISTANCE`` of the
        rest-shape space: not a posed body of this topology in its vertex order.
    Returns ``(rest, rotations, info)``: rest (N, V, 3) bodies on the ground (lowest vertex at
    y = 0, root head x/z where the posed one is), rotations (N, B, 3, 3) in the convention of
    ``pose_bodies`` (bones that are not solved keep the identity), and an ``UnposeInfo``. One
    body (V, 3) in gives (V, 3), (B, 3, 3) and scalars.
    """
    y = np.asarray(vertices, dtype=float)
    single = y.ndim == 2
    if single:
        y = y[None]
    V = rig.weights.shape[0]
    if y.ndim != 3 or y.shape[1:] != (V, 3):
        raise MeshError(f"{mesh_name}: shape {np.shape(vertices)}, but rig {rig.name!r} skins meshes of {V} "
                        f"vertices; expected ({V}, 3) or (N, {V}, 3) in the template's vertex order")
    if not np.isfinite(y).all():
        raise MeshError(f"{mesh_name}: holds NaN or infinite coordinates; expected finite vertices")
    if len(y) == 0:
        raise MeshError(f"{mesh_name}: no bodies (shape {y.shape}); expected at least one")
    _check_scale(y, mesh_name)
    y = np.ascontiguousarray(y)
    prior = prior if prior is not None else _default_prior()
    W, wkey = _resolve_weights(rig, weights, faces)
    with single_threaded_blas():
        plan = _plan(rig, W, wkey, prior)
    # One lane, BLAS on one thread: the matrices are small (a few hundred rows), and half of each
    # step is Python-level numpy work; two lanes (parallel.run_both, one half of the bodies each)
    # measured 1.5x the CPU and more wall time on the shared 2-core machine (GIL hand-offs).
    with single_threaded_blas():
        Q, t, iterations, converged = _fit(plan, y, max_iterations)

    # Every vertex unposed by its inverted blend; folded ones by their heaviest bone alone.
    rest = np.empty_like(y)
    W = plan.collapsed
    folded = _unpose_all(np.ascontiguousarray(Q), np.ascontiguousarray(t), y, W.indptr.astype(np.int64),
                         W.indices.astype(np.int64), W.data, plan.dominant, MIN_BLEND_DETERMINANT, rest)

    state = _State(plan, y[:, plan.work])
    F, C = state.residuals(Q, t)
    shape_distance = np.sqrt(np.einsum("ni,ni->n", F, F) / F.shape[1])
    joint_gap = np.linalg.norm(C, axis=2).max(1) / JOINT_WEIGHT if C.shape[1] else np.zeros(len(y))
    if check:
        bad = np.flatnonzero(~(shape_distance <= MAX_SHAPE_DISTANCE))
        if len(bad):
            i = int(bad[0])
            which = mesh_name if single else f"body {i} of {mesh_name}"
            raise UnposeError(f"{which}: cannot be unposed: after the best fit of rig {rig.name!r} its rest body is "
                            f"still {1000 * shape_distance[i]:.0f} mm (RMS) from any rest body of the template "
                            f"(at most {1000 * MAX_SHAPE_DISTANCE:.0f} mm); expected a posed body of the template "
                            "topology with its vertices in the template's order (is the vertex order shuffled, or "
                            "the mesh not a human body?)")

    # World rotations of every bone, rotations relative to the parent in pose_bodies' convention.
    parents = np.asarray(rig.parents)
    Qall = Q[:, plan.follow]                                           # (N, B, 3, 3)
    R = np.empty_like(Qall)
    roots = parents < 0
    R[:, roots] = Qall[:, roots]
    nonroot = np.flatnonzero(~roots)
    R[:, nonroot] = np.swapaxes(Qall[:, parents[nonroot]], -1, -2) @ Qall[:, nonroot]
    largest, names, orientation, translation = _report_and_place(plan, rig, rest, Q, t)
    info = UnposeInfo(largest, names, orientation, shape_distance, joint_gap,
                      iterations, converged, folded, translation)
    if single:
        info = UnposeInfo(*(getattr(info, f)[0] for f in info.__dataclass_fields__))
        return rest[0], R[0], info
    return rest, R, info


@lru_cache(maxsize=4)
def _below_cached(parents: bytes) -> np.ndarray:
    p = np.frombuffer(parents, dtype=np.int64)
    below = np.eye(len(p), dtype=bool)                 # below[b, k]: bone b is k or one of k's descendants
    for b in topological_order(p):
        if p[b] >= 0:
            below[b] |= below[p[b]]
    return below


def _below(parents: np.ndarray) -> np.ndarray:
    """(B, B) bool: ``[b, k]`` when bone b is k or below k in the tree ``parents`` (B,)."""
    return _below_cached(np.ascontiguousarray(parents, dtype=np.int64).tobytes())


def unpose_known(vertices: np.ndarray, rig: Rig, rotations: np.ndarray, *, prior: RestShapePrior | None = None,
                 mesh_name: str = "vertices", in_place: bool = False):
    """Inverse linear blend skinning with a *known* pose: the rest bodies of posed bodies whose
    bone rotations were recorded (a scan database written by ``bodyspace population`` keeps
    them), without ``unpose``'s fit; about a millisecond a body against tens.

    vertices: (N, V, 3) posed bodies of the rig's topology (``pose_bodies(rest, rig, R)``, on the
        ground or moved anywhere); rotations: (N, B, 3) axis-angle or (N, B, 3, 3) matrices, the
        ``R`` that posed them (rest-pose world axes, about the bone heads).
    Returns ``(rest, R, info)`` as ``unpose`` does (rest placed the same way: lowest vertex at
    y = 0, the pelvis x/z where the posed one is; ``info.iterations`` 0). The caller checks
    ``info.shape_distance_m`` (RMS distance of each rest body from the rest-shape space, as in
    ``unpose``) against ``KNOWN_POSE_TOLERANCE``: above it the recorded pose does not explain
    the mesh (another skinning, edited vertices) and ``unpose`` should estimate the pose instead.
    ``in_place``: ``vertices`` (a C-contiguous float64 array) is overwritten by the rest bodies and
    returned as ``rest`` (no second (N, V, 3) array: a chunk of 128 scans is 41 MB of fresh pages).

    The rest body x is unknown, and the bones' transforms depend on it through the rest heads
    h = H x (``rig.head_regressor``). With the rotations fixed, FK is affine in the heads: bone b's
    world transform is ``[A_b | c_b]``, ``c_b = sum_k D_k h_k`` over its ancestors-or-self k with
    ``D_k = A_parent(k) - A_k`` (zero for an unrotated bone). So the posed vertex is
    ``y_v = M_v x_v + sum_b w_vb c_b`` with ``M_v = sum_b w_vb A_b``, and the heads solve one
    small linear system: ``h_j + sum_v H_jv M_v^-1 sum_k Wa_vk D_k h_k = sum_v H_jv M_v^-1 y_v``
    over the rotated bones j, k (``Wa = W Anc``: a vertex's weight on bones below k), with only the
    regressor's vertices v (175 for the default rig). Then every vertex is
    ``x_v = M_v^-1 (y_v - sum_b w_vb c_b)`` (``_unpose_all``; a folded blend by its dominant bone,
    as ``unpose``). A translation of the posed body translates the rest body alike (the regressor's
    rows sum to one), so ``place_on_ground``'s offset needs no undoing.
    """
    y = np.ascontiguousarray(np.asarray(vertices, dtype=float))
    if in_place and y is not vertices:
        raise ParameterError(f"{mesh_name}: in_place needs a C-contiguous float64 array, got "
                             f"{np.asarray(vertices).dtype} {'' if np.asarray(vertices).flags.c_contiguous else 'non-'}"
                             "contiguous; pass such an array or in_place=False")
    V, B = rig.weights.shape
    if y.ndim != 3 or y.shape[1:] != (V, 3):
        raise MeshError(f"{mesh_name}: shape {np.shape(vertices)}, but rig {rig.name!r} skins meshes of {V} "
                        f"vertices; expected (N, {V}, 3) in the template's vertex order")
    N = len(y)
    R = np.asarray(rotations, dtype=float)
    if R.shape == (N, B, 3):
        R = rotvec_to_matrix(R)
    if R.shape != (N, B, 3, 3):
        raise ParameterError(f"{mesh_name}: rotations of shape {np.shape(rotations)}, expected ({N}, {B}, 3) "
                             f"axis-angle or ({N}, {B}, 3, 3) matrices for rig {rig.name!r}")
    if not (np.isfinite(y).all() and np.isfinite(R).all()):
        raise MeshError(f"{mesh_name}: holds NaN or infinite coordinates or rotations; expected finite values")
    prior = prior if prior is not None else _default_prior()
    W, wkey = _resolve_weights(rig, "original", None)
    with single_threaded_blas():
        plan = _plan(rig, W, wkey, prior)
    parents = np.asarray(rig.parents)
    A = forward_kinematics(R, np.zeros((B, 3)), parents)[..., :3, :3]            # (N, B, 3, 3) world rotations
    rotated = np.flatnonzero((np.abs(R - np.eye(3)) > 0).any(axis=(0, 2, 3)))    # (r,) bones turned in any body
    r = len(rotated)
    heads = np.zeros((N, B, 3))
    if r:
        ancestor_of = _below(parents)[:, rotated].astype(float)                   # bone b is k or below k
        A_parent = np.where((parents[rotated] >= 0)[None, :, None, None],
                            A[:, np.maximum(parents[rotated], 0)], np.eye(3))
        D = A_parent - A[:, rotated]                                              # (N, r, 3, 3)
        Hr = rig.head_regressor[rotated].tocsc()
        support = np.flatnonzero(np.diff(Hr.indptr))                              # (S,) regressor vertices
        Hd = Hr[:, support].toarray()                                             # (r, S)
        Wa = np.asarray(W[support] @ ancestor_of)                                 # (S, r)
        M, _ = _blend(W[support].tocsr(), A, np.zeros((N, B, 3)))                 # (N, S, 3, 3)
        # P[(j, k), v] = Hd[j, v] Wa[v, k]: 1.5 % of its entries are non-zero (a head's few
        # regressor vertices, the bones above them), so the system is built from them alone, in
        # one compiled pass a body (``_known_heads_system``), not from dense (r*r, S) products.
        P = sp.csr_matrix((Hd[:, None, :] * Wa.T[None, :, :]).reshape(r * r, len(support)))
        Hs = sp.csr_matrix(Hd)
        # A bone body n does not turn (R = I) has D = 0 and its head moves nothing (T(h) I T(-h)
        # is the identity), so each body solves for the heads of its own turned bones only (6 of
        # the chunk's 22 on average for the pose library): a (3 r_n)^2 system, not (3 r)^2.
        turned = (np.abs(R[:, rotated] - np.eye(3)) > 0).any(axis=(2, 3))        # (N, r)
        solved_heads = np.zeros((N, r, 3))
        _known_heads(np.ascontiguousarray(M), np.ascontiguousarray(y[:, support]),
                     P.indptr.astype(np.int64), P.indices.astype(np.int64), P.data,
                     Hs.indptr.astype(np.int64), Hs.indices.astype(np.int64), Hs.data,
                     np.ascontiguousarray(D), turned, solved_heads)
        heads[:, rotated] = solved_heads
    G = forward_kinematics(R, heads, parents)
    # In place is safe: each vertex's posed point is read before its rest point is written.
    rest = y if in_place else np.empty_like(y)
    if np.isin(rotated, plan.solved).all():
        # Every turned bone is solved (as in the pose library): the others move exactly with their
        # nearest solved ancestor, so the weights collapsed onto the solved bones (31 % fewer
        # entries) give the same blend.
        Wc, bones, dominant = plan.collapsed, plan.solved, plan.dominant
    else:
        Wc, bones, dominant = W.tocsr(), np.arange(B), plan.solved[plan.dominant]
    Gb = G[:, bones]                     # (N, P, 4, 4); not G[:, bones, :3, 3] (numpy moves that axis first)
    folded = _unpose_all(np.ascontiguousarray(Gb[..., :3, :3]), np.ascontiguousarray(Gb[..., :3, 3]), y,
                         Wc.indptr.astype(np.int64), Wc.indices.astype(np.int64), Wc.data.astype(float),
                         dominant.astype(np.int64), MIN_BLEND_DETERMINANT, rest)
    # The shape check of ``unpose`` on the same sample vertices.
    sample = plan.work[:plan.n_sample]
    dev = rest[:, sample].reshape(N, -1) - plan.basis_mean
    dev -= (dev @ plan.basis.T) @ plan.basis
    shape_distance = np.sqrt(np.einsum("ni,ni->n", dev, dev) / dev.shape[1])

    solved = G[:, plan.solved]                                                    # (N, P, 4, 4)
    largest, names, orientation, translation = _report_and_place(plan, rig, rest, solved[..., :3, :3],
                                                                 solved[..., :3, 3])
    info = UnposeInfo(largest, names, orientation, shape_distance, np.zeros(N), np.zeros(N, dtype=np.int64),
                      np.ones(N, dtype=bool), folded, translation)
    return rest, R, info


def _report_and_place(plan, rig: Rig, rest: np.ndarray, Q: np.ndarray, t: np.ndarray) -> tuple:
    """What was undone, for people, and the rest bodies placed: ``unpose``'s and ``unpose_known``'s
    last step. Q (N, P, 3, 3), t (N, P, 3): the world transforms of the plan's solved bones;
    rest (N, V, 3) is moved in place. Returns (largest turn (N,) degrees, its bone's name (N,),
    the root's orientation (N,) degrees, the root translation (N, 3) that ``pose_bodies`` needs).

    The largest turn is of a body part (a solved bone with skin of its own) against the root.
    Rotations relative to the parent are not used for this: how a turn is split along a chain of
    weakly skinned bones (clavicle, shoulder, neck) is barely determined by the skin, and under
    noise a neck bone may twist one way and the head back. Placement: lowest vertex at y = 0;
    x/z: the head of the root's first solved child (the pelvis) where it is posed (the root's own
    head turns with the root's gauge, _gauge).
    """
    N = len(rest)
    segments = plan.segments
    turned = np.swapaxes(Q[:, :1], -1, -2) @ Q[:, segments]
    angles = np.degrees(np.linalg.norm(matrix_to_rotvec(turned), axis=-1))   # (N, S)
    # Ties (the jaw turns with the head) go to the part with more skin.
    pick = (np.round(angles, 1) * 1e6 + plan.segment_skin).argmax(1)
    worst = plan.solved[segments[pick]]
    largest = angles[np.arange(N), pick]
    orientation = np.degrees(np.linalg.norm(matrix_to_rotvec(Q[:, 0]), axis=-1))

    anchor_pos = int(plan.root_children[0]) if len(plan.root_children) else 0
    anchor, root = int(plan.solved[anchor_pos]), int(plan.solved[0])
    # Only two heads are needed: the regressor rows on their vertices (``rig.heads`` would form every bone's).
    heads = {}
    for b in (anchor, root):
        row = rig.head_regressor[b]
        heads[b] = np.einsum("v,nvi->ni", row.data, rest[:, row.indices])
    posed_anchor = np.einsum("nij,nj->ni", Q[:, anchor_pos], heads[anchor]) + t[:, anchor_pos]
    shift = np.zeros((N, 3))
    shift[:, [0, 2]] = posed_anchor[:, [0, 2]] - heads[anchor][:, [0, 2]]
    shift[:, 1] = -rest[..., 1].min(1)
    _translate(rest, shift)
    # pose_bodies(rest, rig, R) keeps the root head h where it is; the fit puts it at Q_0 h + t_0.
    translation = np.einsum("nij,nj->ni", Q[:, 0], heads[root]) + t[:, 0] - heads[root] - shift
    return largest, np.array(rig.bone_names, dtype=object)[worst], orientation, translation
