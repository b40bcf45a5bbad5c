"""Skeleton pose fit (Hasler §2.2): the template's kinematic chain fitted to a scan by ICP.

The posed template is ``x = s · LBS(rest, FK(R)) + t``: the rest body (the template's mean, or
the model fit's body), per-bone rotations R in the convention of ``pose_bodies`` (rest-pose world
axes, about the bone heads), a global scale s and translation t. The unknowns are a twist of
each *solved* bone (``rig.unpose.solved_bones``: the 37 bones whose skin shows their pose; the
others follow their nearest solved ancestor) plus s and t, as in Hasler §2.2 after Bregler &
Malik: a small rotation ω_j about bone j's posed head moves every vertex v by
``ω_j × a_vj`` with ``a_vj = Σ_{b in subtree(j)} w_vb (G_b x̄_v − J_j)``, so each correspondence
gives a linear constraint on all twists at once. Rotations are general (three angles per bone)
rather than Hasler's single-angle revolute joints: the rig's bones carry no joint axes.

Correspondences are taken both ways (template vertex → nearest scan point, scan point → nearest
template vertex: the second pulls a limb the template misplaced back onto its points), gated by
distance (annealed from ``START_DISTANCE`` to ``END_DISTANCE``) and by the normals' angle (the
scan's normals are unoriented here), with point-to-plane residuals and a weak point-to-point
term. Optional landmarks enter as point-to-point rows. A weak prior pulls each bone's rotation
towards its rest (``POSE_PRIOR``). Each iteration is one damped Gauss-Newton step (Marquardt's
damping, per unknown).

With ``shape=(basis, coefficients, shape_prior, scale_prior)`` the shape coefficients c and the
scale are unknowns of the same step: with the rotations held posing is affine in the rest body,
so ``d x / d c_k = s · P_k`` (``P_k``: component k posed at the current rotations, recomputed
each iteration), with a prior ``c_k / σ_k`` and the scale pulled towards 1. Alternating pose and
shape fits crawls along the valley where they trade off (a thigh's twist against its girth).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
import numpy as np
import scipy.sparse as sp
from scipy.spatial import cKDTree

from bodyspace.data.template import Rig, Template
from bodyspace.mesh.geometry import vertex_normals
from bodyspace.mesh.solver import single_threaded_blas
from bodyspace.register.correspondences import closest_pairs
from bodyspace.rig.kinematics import forward_kinematics, matrix_to_rotvec, rotvec_to_matrix
from bodyspace.rig.posing import pose_bodies
from bodyspace.rig.skinning import linear_blend_skinning
from bodyspace.rig.unpose import solved_bones

__all__ = ["PoseState", "posed_vertices", "fit_pose", "rest_state", "sample_vertices"]

# Correspondence gates: the distance (metres) annealed from START to END over the iterations,
# and the least |cos| between a pair's normals (60°: the scan's normals are unoriented).
START_DISTANCE = 0.20
END_DISTANCE = 0.04
MIN_COS = 0.5
# Weight of the point-to-point part of each pair against its point-to-plane part.
POINT_WEIGHT = 0.3
# Prior on each bone's rotation (metres per radian, against RMS residuals in metres).
POSE_PRIOR = 0.004
# Landmark rows: weight against one correspondence row (20 pulled a thin template onto a heavy
# body's landmarks before its shape was fitted: 16.0 mm against 10.7 mm at 3 on one scan).
LANDMARK_WEIGHT = 3.0
# Largest rotation of one bone in one step (radians); larger steps are scaled down.
MAX_STEP = 0.25
# Levenberg-Marquardt damping relative to the normal matrix's mean diagonal.
DAMPING = 1e-3
# Template vertices used as ICP queries (spread by area) and scan points used the other way.
TEMPLATE_SAMPLES = 3000
SCAN_SAMPLES = 5000


@dataclass(frozen=True)
class PoseState:
    """rest: (V, 3) the rest body; rotations: (B, 3, 3); scale: float; translation: (3,);
    coefficients: (K,) the shape coefficients of ``rest`` when a shape fit made it, else None."""

    rest: np.ndarray
    rotations: np.ndarray
    scale: float
    translation: np.ndarray
    coefficients: np.ndarray | None = None


def rest_state(template: Template, rig: Rig, rest: np.ndarray | None = None) -> PoseState:
    """The template's rest body, unposed, unit scale, at the origin."""
    rest = np.asarray(template.vertices if rest is None else rest, dtype=float)
    return PoseState(rest, np.repeat(np.eye(3)[None], rig.n_bones, axis=0), 1.0, np.zeros(3))


def posed_vertices(rig: Rig, state: PoseState) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(x (V, 3) posed and placed, y (V, 3) posed before scale/translation, G (B, 4, 4))."""
    heads = rig.heads(state.rest)
    G = forward_kinematics(state.rotations[None], heads, rig.parents)[0]
    y = linear_blend_skinning(state.rest, rig.weights, G[None])[0]
    return state.scale * y + state.translation, y, G


_STRUCTURES: dict = {}


def _structure(rig: Rig, rest: np.ndarray):
    """Solved bones (S,) (on the template's rest body) and subtree membership A (B, S), kept per rig."""
    key = (id(rig), rig.name)
    if key in _STRUCTURES:
        return _STRUCTURES[key]
    solved = solved_bones(rig, rest)
    B = rig.n_bones
    col = {int(j): k for k, j in enumerate(solved)}
    A = np.zeros((B, len(solved)))
    for b in range(B):
        a = b
        while a >= 0:
            if a in col:
                A[b, col[a]] = 1.0
            a = int(rig.parents[a])
    _STRUCTURES[key] = (solved, sp.csr_matrix(A))
    return _STRUCTURES[key]


def sample_vertices(vertices: np.ndarray, faces: np.ndarray, n: int, rng=0) -> np.ndarray:
    """``n`` distinct vertex ids (V,) drawn with probability proportional to their area."""
    rng = np.random.default_rng(rng)
    tri = vertices[faces]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    va = np.zeros(len(vertices))
    for c in range(3):
        va += np.bincount(faces[:, c], area, minlength=len(vertices))
    n = min(int(n), int((va > 0).sum()))
    return np.sort(rng.choice(len(vertices), size=n, replace=False, p=va / va.sum()))


def _lever_arms(rig: Rig, state: PoseState, G: np.ndarray, A: sp.csr_matrix, rows: np.ndarray) -> np.ndarray:
    """a (R, S, 3): ``Σ_{b in subtree(j)} w_vb (G_b x̄_v − J_j)`` for the rows' vertices, in the
    posed, unscaled frame."""
    W = rig.weights[rows].tocoo()
    v, b, w = W.row, W.col, W.data
    x = state.rest[rows][v]
    yb = np.einsum("kij,kj->ki", G[b, :3, :3], x) + G[b, :3, 3]
    n = len(rows)
    C = (sp.csr_matrix((w, (v, b)), shape=(n, rig.n_bones)) @ A).toarray()            # (R, S)
    S = np.stack([(sp.csr_matrix((w * yb[:, d], (v, b)), shape=(n, rig.n_bones)) @ A).toarray()
                  for d in range(3)], axis=-1)                                            # (R, S, 3)
    heads = rig.heads(state.rest)
    return S, C, heads


def _nearest_rotation(M: np.ndarray) -> np.ndarray:
    """The rotations (..., 3, 3) nearest to M (..., 3, 3): products of many small steps drift off
    SO(3)."""
    u, _, vt = np.linalg.svd(M)
    u = u.copy()
    u[..., :, 2] *= np.sign(np.linalg.det(u @ vt))[..., None]
    return u @ vt


def _cross_rows(a: np.ndarray, n: np.ndarray) -> np.ndarray:
    """``a × n`` for lever arms a (R, S, 3) and one direction per row n (R, 3) → (R, S, 3),
    written out (np.cross's broadcasting copies cost more than the fit's solve)."""
    nx, ny, nz = (n[:, None, k] for k in range(3))
    ax, ay, az = a[..., 0], a[..., 1], a[..., 2]
    return np.stack([ay * nz - az * ny, az * nx - ax * nz, ax * ny - ay * nx], axis=-1)


def _cross_axis(a: np.ndarray, d: int) -> np.ndarray:
    """``a × e_d`` for lever arms a (R, S, 3) and the unit axis e_d → (R, S, 3)."""
    out = np.zeros_like(a)
    i, j = (d + 1) % 3, (d + 2) % 3
    out[..., i] = a[..., j]       # e.g. a × e_x = (0, a_z, -a_y)
    out[..., j] = -a[..., i]
    return out


def fit_pose(points: np.ndarray, normals: np.ndarray, template: Template, state: PoseState, **kw
             ) -> tuple[PoseState, float]:
    """Fit the pose (and global scale and translation) of the template to scan points.

    points (P, 3), normals (P, 3) (unit, any sign): the scan in the template's frame (metres,
    +Y up, roughly aligned: ``align.initial_alignment``). state: the start (``rest_state``).
    landmarks: (template landmark matrix as a sparse (L, V) matrix, scan positions (L, 3)),
    optional. iterations, start_distance, end_distance (the gate's annealing, metres),
    fit_scale, rig_name, scan_tree (a ``cKDTree(points)`` to reuse), rng: see the module
    docstring. pose_prior: the prior's weight, one for every bone, or (B, 3, 3) a matrix per bone
    applied to its local rotation vector (``pose_refit.refit_prior``). Returns the fitted state
    and the final RMS point-to-plane residual (metres).
    """
    # Small dense products: BLAS threads only wait on each other here (measured 0.3 s against
    # 2 ms for one 115 x 115 solve on the shared machine).
    with single_threaded_blas():
        return _fit_pose(points, normals, template, state, **kw)


def _fit_pose(points: np.ndarray, normals: np.ndarray, template: Template, state: PoseState, *,
             iterations: int = 30, landmarks: tuple[np.ndarray, np.ndarray] | None = None,
             start_distance: float = START_DISTANCE, end_distance: float = END_DISTANCE,
             fit_scale: bool = True, rig_name: str = "default", scan_tree: cKDTree | None = None,
             template_samples: int = TEMPLATE_SAMPLES, scan_samples: int = SCAN_SAMPLES,
             shape=None, pose_prior: float | np.ndarray = POSE_PRIOR, rng=0) -> tuple[PoseState, float]:
    rig = template.rigs[rig_name]
    # Joint shape unknowns: (basis, coefficients (K,), prior weight, scale prior weight) or None.
    if shape is not None:
        basis, coef, shape_prior, scale_prior = shape
        coef = np.asarray(coef, dtype=float).copy()
        K = len(basis.components)
        stack = np.concatenate([basis.mean[None], basis.mean[None] + basis.components])
        state = replace(state, rest=basis.body(coef))
    else:
        K = 0
    faces = template.faces
    solved, A = _structure(rig, template.vertices)
    Sn = len(solved)
    parents = np.asarray(rig.parents)
    tree = scan_tree if scan_tree is not None else cKDTree(points)
    rng = np.random.default_rng(rng)
    tsample = sample_vertices(state.rest, faces, template_samples, rng)
    ssample = rng.choice(len(points), size=min(scan_samples, len(points)), replace=False)
    lm_matrix, lm_points = landmarks if landmarks is not None else (None, None)
    # The prior's weight per bone as (B, 3, 3) matrices on the local rotation vector: one weight for
    # every bone and axis (a float), or each bone's own (a swing-only prior weighs two axes).
    pose_prior = np.asarray(pose_prior, dtype=float)
    bone_prior = (pose_prior * np.eye(3) if pose_prior.ndim == 0 else pose_prior) * np.ones((rig.n_bones, 1, 1))
    rms = np.nan
    for it in range(int(iterations)):
        frac = it / max(1, iterations - 1)
        gate = start_distance * (end_distance / start_distance) ** frac
        x, y, G = posed_vertices(rig, state)
        xn = vertex_normals(x, faces)
        if K:
            # Posed shape directions at the current rotations: posing is affine in the rest body
            # with the rotations held, so d x / d c_k = s · Pk[k] exactly at this pose.
            posed = pose_bodies(stack, rig, state.rotations)
            Pk = posed[1:] - posed[0]
        # template → scan
        fwd = closest_pairs(x[tsample], xn[tsample], tree, normals, gate, MIN_COS, oriented=False)
        fv, fp = tsample[fwd.query], fwd.match
        # scan → template
        bwd = closest_pairs(points[ssample], normals[ssample], cKDTree(x), xn, gate, MIN_COS, oriented=False)
        bv, bp = bwd.match, ssample[bwd.query]
        if len(fv) + len(bv) < 50:
            break
        rows_v = np.concatenate([fv, bv])
        rows_p = points[np.concatenate([fp, bp])]
        nrm = np.concatenate([normals[fp] * np.sign((normals[fp] * xn[fv]).sum(1))[:, None], xn[bv]])
        wrow = np.concatenate([np.full(len(fv), 1 / np.sqrt(max(len(fv), 1))),
                               np.full(len(bv), 1 / np.sqrt(max(len(bv), 1)))])
        uniq, inv = np.unique(rows_v, return_inverse=True)
        S, C, heads = _lever_arms(rig, state, G, A, uniq)
        J_head = np.einsum("sij,sj->si", G[solved, :3, :3], heads[solved]) + G[solved, :3, 3]     # (S, 3)
        a = S - C[:, :, None] * J_head[None]                                                     # (U, S, 3)
        # Residual rows: point-to-plane (n), and point-to-point (e_x, e_y, e_z) at POINT_WEIGHT.
        dirs = [nrm] + [np.broadcast_to(np.eye(3)[d], nrm.shape) for d in range(3)]
        dw = [wrow] + [wrow * POINT_WEIGHT] * 3
        res, jac = [], []
        diff = x[rows_v] - rows_p
        a_rows = a[inv]
        P_rows = Pk[:, rows_v] if K else None                                                   # (K, R, 3)
        for d, (n_d, w_d) in enumerate(zip(dirs, dw)):
            res.append(w_d * (diff * n_d).sum(1))
            cross = _cross_rows(a_rows, n_d) if d == 0 else _cross_axis(a_rows, d - 1)
            jw = state.scale * cross.reshape(len(rows_v), 3 * Sn)
            js = (y[rows_v] * n_d).sum(1, keepdims=True)
            blocks = [jw, n_d, js]
            if K:
                shape_cols = np.einsum("kvd,vd->vk", P_rows, n_d) if d == 0 else P_rows[:, :, d - 1].T
                blocks.insert(0, state.scale * shape_cols)
            jac.append(w_d[:, None] * np.concatenate(blocks, axis=1))
        if lm_matrix is not None:
            lx = lm_matrix @ x
            ly = lm_matrix @ y
            # Landmark lever arms: the landmark matrix mixes vertices' lever arms.
            lv = np.unique(lm_matrix.indices)
            Sl, Cl, _ = _lever_arms(rig, state, G, A, lv)
            al = Sl - Cl[:, :, None] * J_head[None]
            M = lm_matrix[:, lv]
            al = np.einsum("lu,usd->lsd", M.toarray(), al)
            wl = LANDMARK_WEIGHT / np.sqrt(max(len(fv), 1))
            for d in range(3):
                e = np.broadcast_to(np.eye(3)[d], (len(lx), 3))
                res.append(wl * (lx - lm_points)[:, d])
                jw = state.scale * _cross_axis(al, d).reshape(len(lx), 3 * Sn)
                blocks = [jw, e, ly[:, d:d + 1]]
                if K:
                    blocks.insert(0, state.scale * (lm_matrix @ Pk[:, :, d].T))
                jac.append(wl * np.concatenate(blocks, axis=1))
        r = np.concatenate(res)
        Jm = np.concatenate(jac)
        rms = float(np.sqrt(np.mean(((diff * nrm).sum(1)) ** 2)))
        H = Jm.T @ Jm
        g = Jm.T @ r
        # Prior: each solved bone's local rotation vector towards zero (the root's is global).
        Qp = np.stack([G[parents[j], :3, :3] if parents[j] >= 0 else np.eye(3) for j in solved])
        rv = matrix_to_rotvec(state.rotations[solved])
        for k, j in enumerate(solved):
            if parents[j] < 0:
                continue
            Jp = bone_prior[j] @ Qp[k].T
            o = K + 3 * k
            H[o:o + 3, o:o + 3] += Jp.T @ Jp
            g[o:o + 3] += Jp.T @ (bone_prior[j] @ rv[k])
        if K:
            # Shape prior c_k / σ_k, and the scale towards 1 (the shape space spans statures).
            H[:K, :K] += np.diag((shape_prior / basis.sigma) ** 2)
            g[:K] += (shape_prior / basis.sigma) ** 2 * coef
            H[-1, -1] += scale_prior ** 2
            g[-1] += scale_prior ** 2 * (state.scale - 1.0)
        if not fit_scale:
            H[-1, :] = 0.0
            H[:, -1] = 0.0
            H[-1, -1] = 1.0
            g[-1] = 0.0
        # Marquardt's damping, per unknown: scaled by the mean diagonal it held back the
        # weakly seen unknowns (a thigh's twist, a foot) far more than the strongly seen ones.
        dH = np.diag(H).copy()
        H[np.diag_indices_from(H)] += DAMPING * dH + 1e-9 * np.mean(dH) + 1e-12
        step = -np.linalg.solve(H, g)
        w = step[K:K + 3 * Sn].reshape(Sn, 3)
        big = np.linalg.norm(w, axis=1).max()
        if big > MAX_STEP:
            step *= MAX_STEP / big
            w = step[K:K + 3 * Sn].reshape(Sn, 3)
        if K:
            coef = coef + step[:K]
            state = replace(state, rest=basis.body(coef), coefficients=coef)
        step = step[K:]
        # Each solved bone's update uses only its own rotation and its parent's frame before the
        # step (Qp), so all are applied at once.
        R = state.rotations.copy()
        QpT = Qp.transpose(0, 2, 1)
        R[solved] = _nearest_rotation(QpT @ rotvec_to_matrix(w) @ Qp @ R[solved])
        state = replace(state, rotations=R, translation=state.translation + step[3 * Sn:3 * Sn + 3],
                        scale=float(state.scale * (1.0 + step[-1] / max(state.scale, 1e-9)) if fit_scale else state.scale))
    return state, rms
