"""Skeleton maths: rotations, forward kinematics, linear blend skinning, Blender bone frames.

Pure batched numpy functions in the manner of smplx's ``lbs.py``; every docstring states the
array shapes. ``N`` is the batch of bodies, ``B`` the bones, ``V`` the vertices.

Pose convention (the one ``poses.py`` and the pose library use): bone ``b`` carries a rotation
``R_b`` expressed in the *rest-pose world axes* and applied about the bone's rest head
``h_b``; the parent's transform then applies on top, so the world transform of a bone is

    G_b = G_parent(b) · T(h_b) · R_b · T(-h_b)        (4x4, homogeneous)

``G_b`` maps a rest-pose point rigidly attached to bone ``b`` to its posed position, so linear
blend skinning needs no inverse bind matrices: ``v' = sum_b w_vb G_b v``. With every
``R_b = I`` the pose is the rest pose exactly. This is SMPL's convention (its joint frames are
world-aligned at rest); Blender's bone-local frames, which BVH data refers to, are available
from ``bone_rest_frames`` for conversion.

Speed: ``forward_kinematics`` is a compiled loop over (N, B); ``linear_blend_skinning`` and
``dual_quaternion_skinning`` are the compiled kernels of ``bodyspace.rig.skinning`` (re-exported
here). The plain numpy formulations are kept as ``*_numpy``: the reference the tests compare
against and the baseline of ``benchmarks/bench_skinning.py``.
"""

from __future__ import annotations

import numba
import numpy as np
import scipy.sparse as sp

from bodyspace.errors import MeshError, ParameterError
from bodyspace.rig.skinning import dual_quaternion_skinning, linear_blend_skinning

__all__ = ["bone_depths", "bone_rest_frames", "dual_quaternion_skinning", "dual_quaternion_skinning_numpy", "forward_kinematics",
           "forward_kinematics_numpy", "linear_blend_skinning", "linear_blend_skinning_numpy",
           "matrix_to_quaternion", "matrix_to_rotvec", "rotvec_to_matrix", "topological_order"]

# Below this angle (radians) Rodrigues' coefficients are replaced by their Taylor series: the
# closed forms divide by theta and lose all precision near the identity.
_SMALL_ANGLE = 1e-6
# Bodies are skinned in chunks so the blended (chunk, V, 3, 4) matrices stay ~100 MB at most.
_LBS_CHUNK_ELEMENTS = 12_000_000

# Our axes (+Y up, +Z front) to Blender's (+Z up, -Y front): blender = _TO_BLENDER @ ours,
# i.e. blender (x, y, z) = (x, -z_ours, y_ours).
_TO_BLENDER = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])


# ------------------------------------------------------------------------------- rotations

def _skew(v: np.ndarray) -> np.ndarray:
    """Cross-product matrices (..., 3, 3) of vectors (..., 3): ``_skew(a) @ b == a x b``."""
    x, y, z = v[..., 0], v[..., 1], v[..., 2]
    o = np.zeros_like(x)
    return np.stack([np.stack([o, -z, y], -1), np.stack([z, o, -x], -1), np.stack([-y, x, o], -1)], -2)


def rotvec_to_matrix(rotvec: np.ndarray) -> np.ndarray:
    """Rodrigues' formula: rotation vectors (..., 3) (axis * angle, radians) → matrices (..., 3, 3).

    ``R = I + a K + b K^2`` with ``K = skew(rotvec)``, ``a = sin(t)/t``, ``b = (1 - cos t)/t^2``,
    ``t = |rotvec|``; ``b`` is evaluated as ``2 sin^2(t/2) / t^2`` (no cancellation for small
    t) and both switch to their Taylor series near ``t = 0``.
    """
    r = np.asarray(rotvec, dtype=float)
    if r.shape[-1:] != (3,):
        raise ParameterError(f"rotvec: shape {r.shape}, expected (..., 3)")
    t2 = np.einsum("...i,...i->...", r, r)
    t = np.sqrt(t2)
    small = t < _SMALL_ANGLE
    ts = np.where(small, 1.0, t)
    a = np.where(small, 1.0 - t2 / 6.0, np.sin(ts) / ts)
    b = np.where(small, 0.5 - t2 / 24.0, 2.0 * (np.sin(0.5 * ts) / ts) ** 2)
    K = _skew(r)
    return np.eye(3) + a[..., None, None] * K + b[..., None, None] * (K @ K)


def matrix_to_quaternion(matrix: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) → unit quaternions (..., 4) as (w, x, y, z) with w >= 0.

    Shepperd's method: of the four algebraically equal formulas, each element uses the one
    whose square root argument is largest, so it stays accurate at every angle including pi.
    """
    m = np.asarray(matrix, dtype=float)
    if m.shape[-2:] != (3, 3):
        raise ParameterError(f"matrix: shape {m.shape}, expected (..., 3, 3)")
    m00, m11, m22 = m[..., 0, 0], m[..., 1, 1], m[..., 2, 2]
    # 4 q_i^2 for i = w, x, y, z
    cand = np.stack([1 + m00 + m11 + m22, 1 + m00 - m11 - m22, 1 - m00 + m11 - m22, 1 - m00 - m11 + m22], -1)
    best = np.argmax(cand, axis=-1)
    s = np.sqrt(np.maximum(np.take_along_axis(cand, best[..., None], -1)[..., 0], 1e-300))  # 2 |q_best|
    d21, d02, d10 = m[..., 2, 1] - m[..., 1, 2], m[..., 0, 2] - m[..., 2, 0], m[..., 1, 0] - m[..., 0, 1]
    s01, s02, s12 = m[..., 0, 1] + m[..., 1, 0], m[..., 0, 2] + m[..., 2, 0], m[..., 1, 2] + m[..., 2, 1]
    rows = np.stack([
        np.stack([s * s, d21, d02, d10], -1),   # w largest
        np.stack([d21, s * s, s01, s02], -1),   # x largest
        np.stack([d02, s01, s * s, s12], -1),   # y largest
        np.stack([d10, s02, s12, s * s], -1),   # z largest
    ], -2)
    q = np.take_along_axis(rows, best[..., None, None], -2)[..., 0, :] / (2.0 * s[..., None])
    q /= np.linalg.norm(q, axis=-1, keepdims=True)
    return np.where(q[..., :1] < 0, -q, q)


def matrix_to_rotvec(matrix: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) → rotation vectors (..., 3), angle in [0, pi].

    Goes through the quaternion (Shepperd) and ``angle = 2 atan2(|q_xyz|, q_w)``, which is well
    conditioned near 0 (series for ``angle / sin(angle/2)``) and near pi (no division by
    ``sin(angle)``, unlike the trace/antisymmetric-part formula).
    """
    q = matrix_to_quaternion(matrix)
    w, xyz = q[..., 0], q[..., 1:]
    s = np.linalg.norm(xyz, axis=-1)
    angle = 2.0 * np.arctan2(s, w)
    small = s < _SMALL_ANGLE
    # angle / s = 2 atan(s / w) / s -> (2 / w)(1 - s^2 / (3 w^2)) as s -> 0 (then w -> 1)
    scale = np.where(small, 2.0 / np.maximum(w, 1e-300) * (1.0 - s * s / 3.0), angle / np.where(small, 1.0, s))
    return xyz * scale[..., None]


# ------------------------------------------------------------------------ forward kinematics

def bone_depths(parents) -> np.ndarray:
    """(B,) int depth of every bone in its tree (0 for a root), for parents (B,) int with -1 for
    a root; ``ParameterError`` for an index out of range or a cycle."""
    parents = np.asarray(parents, dtype=np.int64)
    B = len(parents)
    if parents.ndim != 1 or ((parents < -1) | (parents >= B)).any():
        raise ParameterError(f"parents: expected (B,) indices in [-1, B), got {parents.tolist()}")
    depth = np.full(B, -1)
    for b in range(B):
        chain, p = [], b
        while p >= 0 and depth[p] < 0:
            chain.append(p)
            p = parents[p]
            if len(chain) > B:
                raise ParameterError(f"parents: bone {b} is on a cycle; expected a forest")
        d = depth[p] if p >= 0 else -1
        for c in reversed(chain):
            d += 1
            depth[c] = d
    return depth


def topological_order(parents: np.ndarray) -> np.ndarray:
    """Bone indices (B,) ordered so that every parent comes before its children.

    parents: (B,) int, -1 for a root. MakeHuman rigs list bones alphabetically, not
    parent-first, so forward kinematics cannot simply run in index order.
    """
    return np.argsort(bone_depths(parents), kind="stable")


def _fk_inputs(rotations, heads, parents) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Validated rotations (N, B, 3, 3), heads (1 or N, B, 3) and parents (B,) int64."""
    R = np.asarray(rotations, dtype=float)
    if R.ndim != 4 or R.shape[-2:] != (3, 3):
        raise ParameterError(f"rotations: shape {R.shape}, expected (N, B, 3, 3)")
    N, B = R.shape[:2]
    h = np.asarray(heads, dtype=float)
    h = h[None] if h.ndim == 2 else h
    if h.ndim != 3 or h.shape[0] not in (1, N) or h.shape[1:] != (B, 3):
        raise ParameterError(f"heads: shape {np.shape(heads)}, expected ({N}, {B}, 3) or ({B}, 3)")
    parents = np.asarray(parents, dtype=np.int64)
    if parents.shape != (B,):
        raise ParameterError(f"parents: shape {parents.shape}, expected ({B},)")
    return R, h, parents


@numba.njit(cache=True, nogil=True, fastmath={"contract"})
def _forward_kinematics_kernel(R, heads, parents, order, G):
    """``G[n, b] = G[n, parent] · [R | h - R h]`` for every frame n, bones in ``order``."""
    N = R.shape[0]
    for n in range(N):
        hn = n if heads.shape[0] > 1 else 0
        for b in order:
            p = parents[b]
            h0, h1, h2 = heads[hn, b, 0], heads[hn, b, 1], heads[hn, b, 2]
            t0 = h0 - (R[n, b, 0, 0] * h0 + R[n, b, 0, 1] * h1 + R[n, b, 0, 2] * h2)
            t1 = h1 - (R[n, b, 1, 0] * h0 + R[n, b, 1, 1] * h1 + R[n, b, 1, 2] * h2)
            t2 = h2 - (R[n, b, 2, 0] * h0 + R[n, b, 2, 1] * h1 + R[n, b, 2, 2] * h2)
            if p < 0:
                for r in range(3):
                    for c in range(3):
                        G[n, b, r, c] = R[n, b, r, c]
                G[n, b, 0, 3], G[n, b, 1, 3], G[n, b, 2, 3] = t0, t1, t2
            else:
                for r in range(3):
                    g0, g1, g2 = G[n, p, r, 0], G[n, p, r, 1], G[n, p, r, 2]
                    for c in range(3):
                        G[n, b, r, c] = g0 * R[n, b, 0, c] + g1 * R[n, b, 1, c] + g2 * R[n, b, 2, c]
                    G[n, b, r, 3] = g0 * t0 + g1 * t1 + g2 * t2 + G[n, p, r, 3]
            G[n, b, 3, 0], G[n, b, 3, 1], G[n, b, 3, 2], G[n, b, 3, 3] = 0.0, 0.0, 0.0, 1.0


def forward_kinematics(rotations: np.ndarray, heads: np.ndarray, parents: np.ndarray,
                       translation: np.ndarray | None = None) -> np.ndarray:
    """World transforms of posed bones: ``G_b = G_parent · T(h_b) R_b T(-h_b)``.

    rotations: (N, B, 3, 3) per-bone rotations in rest-pose world axes, about the bone heads.
    heads: (N, B, 3) rest-pose bone heads (the joints), or (B, 3) shared by the batch.
    parents: (B,) int, -1 for a root.
    translation: optional (N, 3) or (3,) offset added to every bone after posing (the root
        motion of an animation).
    Returns (N, B, 4, 4) homogeneous transforms mapping rest-pose points to posed points.

    A compiled loop over frames and bones in parent-first order (``topological_order``): 1,000
    frames of the 163-bone rig take a few milliseconds, against tens for the numpy loop
    (``forward_kinematics_numpy``, the reference).
    """
    R, h, parents = _fk_inputs(rotations, heads, parents)
    N, B = R.shape[:2]
    G = np.empty((N, B, 4, 4))
    _forward_kinematics_kernel(np.ascontiguousarray(R), np.ascontiguousarray(h), parents,
                               topological_order(parents), G)
    if translation is not None:
        G[..., :3, 3] += np.broadcast_to(np.asarray(translation, dtype=float), (N, 3))[:, None, :]
    return G


def forward_kinematics_numpy(rotations: np.ndarray, heads: np.ndarray, parents: np.ndarray,
                       translation: np.ndarray | None = None) -> np.ndarray:
    """World transforms of posed bones: ``G_b = G_parent · T(h_b) R_b T(-h_b)``.

    rotations: (N, B, 3, 3) per-bone rotations in rest-pose world axes, about the bone heads.
    heads: (N, B, 3) rest-pose bone heads (the joints), or (B, 3) shared by the batch.
    parents: (B,) int, -1 for a root.
    translation: optional (N, 3) or (3,) offset added to every bone after posing (the root
        motion of an animation).
    Returns (N, B, 4, 4) homogeneous transforms mapping rest-pose points to posed points.

    Vectorized over N; a Python loop over bones in parent-first order (B <= a few hundred).
    The numpy reference of ``forward_kinematics`` (same arguments, same result to rounding).
    """
    R, h, parents = _fk_inputs(rotations, heads, parents)
    N, B = R.shape[:2]
    h = np.broadcast_to(h, (N, B, 3))
    # Local transform about the head: x -> R (x - h) + h, i.e. translation h - R h.
    local = np.zeros((N, B, 4, 4))
    local[..., :3, :3] = R
    local[..., :3, 3] = h - np.einsum("nbij,nbj->nbi", R, h)
    local[..., 3, 3] = 1.0
    G = np.empty_like(local)
    for b in topological_order(parents):
        p = parents[b]
        G[:, b] = local[:, b] if p < 0 else G[:, p] @ local[:, b]
    if translation is not None:
        G[..., :3, 3] += np.broadcast_to(np.asarray(translation, dtype=float), (N, 3))[:, None, :]
    return G


# ---------------------------------------------------------------------------------- skinning

def _skinning_inputs(vertices, weights, transforms) -> tuple[np.ndarray, np.ndarray]:
    """Validate skinning inputs; return transforms (N, B, 4, 4) and vertices (N, V, 3)."""
    G = np.asarray(transforms, dtype=float)
    if G.ndim != 4 or G.shape[-2:] != (4, 4):
        raise ParameterError(f"transforms: shape {G.shape}, expected (N, B, 4, 4)")
    N, B = G.shape[:2]
    v = np.asarray(vertices, dtype=float)
    if v.ndim == 2:
        v = np.broadcast_to(v, (N,) + v.shape)
    if v.ndim != 3 or v.shape[0] != N or v.shape[2] != 3:
        raise MeshError(f"vertices: shape {np.shape(vertices)}, expected ({N}, V, 3) or (V, 3)")
    V = v.shape[1]
    if weights.shape != (V, B):
        raise ParameterError(f"weights: shape {weights.shape}, expected ({V}, {B}) for {V} vertices and {B} bones")
    return G, v


def linear_blend_skinning_numpy(vertices: np.ndarray, weights: sp.spmatrix | np.ndarray,
                                transforms: np.ndarray) -> np.ndarray:
    """Linear blend skinning in plain numpy: ``v'_i = (sum_b w_ib G_b) v_i``.

    The reference (and benchmark baseline) of the compiled ``skinning.linear_blend_skinning``.

    vertices: (N, V, 3) rest-pose vertices, or (V, 3) shared by the batch.
    weights: (V, B) skin weights (sparse or dense), rows summing to one.
    transforms: (N, B, 4, 4) bone transforms from ``forward_kinematics``.
    Returns (N, V, 3).

    The blended 3x4 matrices of all vertices come from one sparse x dense product
    ``weights @ transforms`` (V, B) x (B, 12*N) → (V, 12*N), laid out (V, column, row, body) so
    that applying them is four broadcast multiply-adds over contiguous (V, 3, N) slabs; no
    (N, V, 4, 4) array is built. Large batches go in chunks to bound memory.

    What is blended is each transform's deviation from the identity, ``G_b - I``, and the
    result is added to the rest vertex: identical maths when rows sum to one, but the identity
    pose returns the input bit for bit, and weights that sum to 1 only up to rounding do not
    scale the rest mesh.
    """
    G, v = _skinning_inputs(vertices, weights, transforms)
    N, B = G.shape[:2]
    V = v.shape[1]
    W = sp.csr_matrix(weights) if sp.issparse(weights) else np.asarray(weights, dtype=float)
    out = np.empty((N, V, 3))
    chunk = max(1, _LBS_CHUNK_ELEMENTS // (V * 12))
    for s in range(0, N, chunk):
        g = G[s:s + chunk, :, :3, :] - np.eye(3, 4)                     # (n, B, 3, 4), G - I
        n = g.shape[0]
        M = np.ascontiguousarray(g.transpose(1, 3, 2, 0)).reshape(B, 12 * n)  # (B, 4*3*n)
        A = np.asarray(W @ M).reshape(V, 4, 3, n)                       # blended, (V, col, row, n)
        x = v[s:s + n].transpose(1, 2, 0)                               # (V, 3, n)
        posed = x + (A[:, 3] + A[:, 0] * x[:, 0:1] + A[:, 1] * x[:, 1:2] + A[:, 2] * x[:, 2:3])
        out[s:s + n] = posed.transpose(2, 0, 1)
    return out


def _quat_mul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton products (..., 4) of quaternions (w, x, y, z)."""
    aw, ax, ay, az = a[..., 0], a[..., 1], a[..., 2], a[..., 3]
    bw, bx, by, bz = b[..., 0], b[..., 1], b[..., 2], b[..., 3]
    return np.stack([aw * bw - ax * bx - ay * by - az * bz, aw * bx + ax * bw + ay * bz - az * by,
                     aw * by - ax * bz + ay * bw + az * bx, aw * bz + ax * by - ay * bx + az * bw], -1)


def dual_quaternion_skinning_numpy(vertices: np.ndarray, weights: sp.spmatrix | np.ndarray,
                                   transforms: np.ndarray) -> np.ndarray:
    """Dual-quaternion skinning (Kavan et al. 2008) in plain numpy: blend unit dual quaternions.

    The reference (and benchmark baseline) of the compiled ``skinning.dual_quaternion_skinning``.

    vertices: (N, V, 3) rest-pose vertices, or (V, 3) shared by the batch.
    weights: (V, B) skin weights (sparse or dense), rows summing to one.
    transforms: (N, B, 4, 4) rigid bone transforms from ``forward_kinematics``.
    Returns (N, V, 3).

    Each bone's ``G_b`` becomes a unit dual quaternion ``q_b + eps q'_b`` with
    ``q'_b = (0, t_b) q_b / 2``; per vertex the weighted sum over its bones (each bone's sign
    flipped into the hemisphere of the vertex's heaviest bone, so ``q`` and ``-q`` blend as the
    same rotation) is normalized and applied as a rigid transform. The blend of rotations
    stays a rotation, so the skin no longer collapses where a joint twists or bends far (LBS's
    candy wrapper and its armpit/groin folds); it bulges slightly instead. All ``G_b = I``
    returns the input bit for bit, like ``linear_blend_skinning``.
    """
    G, v = _skinning_inputs(vertices, weights, transforms)
    N, B = G.shape[:2]
    V = v.shape[1]
    W = sp.csr_matrix(weights)
    W.sum_duplicates()
    W.eliminate_zeros()
    counts = np.diff(W.indptr)
    if (counts == 0).any():
        raise ParameterError(f"weights: vertex {int(np.flatnonzero(counts == 0)[0])} has no bone; "
                             "expected every row to sum to one")
    row = np.repeat(np.arange(V), counts)
    col, w = W.indices, W.data
    pivot = col[W.indptr[:-1] + np.array([np.argmax(W.data[a:b]) for a, b in zip(W.indptr[:-1], W.indptr[1:])])]
    qr = matrix_to_quaternion(G[..., :3, :3])                             # (N, B, 4)
    t = np.concatenate([np.zeros((N, B, 1)), G[..., :3, 3]], -1)
    qd = 0.5 * _quat_mul(t, qr)                                           # (N, B, 4)
    Q = np.concatenate([qr, qd], -1)                                      # (N, B, 8)
    out = np.empty((N, V, 3))
    chunk = max(1, _LBS_CHUNK_ELEMENTS // (len(col) * 8))
    for s in range(0, N, chunk):
        q = Q[s:s + chunk]
        n = q.shape[0]
        sign = np.where(np.einsum("nki,nki->nk", q[:, col, :4], q[:, pivot[row], :4]) < 0, -1.0, 1.0)
        blended = np.add.reduceat(q[:, col] * (w * sign)[..., None], W.indptr[:-1], axis=1)   # (n, V, 8)
        norm = np.linalg.norm(blended[..., :4], axis=-1, keepdims=True)
        b0, be = blended[..., :4] / norm, blended[..., 4:] / norm
        qw, qv = b0[..., :1], b0[..., 1:]
        x = v[s:s + n]
        # R x = x + 2 w (qv × x) + 2 qv × (qv × x); t = 2 (be conj(b0)).xyz
        c = np.cross(qv, x)
        trans = 2.0 * (qw * be[..., 1:] - be[..., :1] * qv + np.cross(qv, be[..., 1:]))
        out[s:s + n] = x + (2.0 * qw * c + 2.0 * np.cross(qv, c) + trans)
    return out


# --------------------------------------------------------------------------- Blender frames

def _blender_vec_roll_to_mat3(nor: np.ndarray, roll: np.ndarray) -> np.ndarray:
    """Blender's ``vec_roll_to_mat3_normalized`` (armature.cc), batched.

    nor: (..., 3) unit bone directions in Blender axes; roll: (...,) radians.
    Returns (..., 3, 3) whose columns are the bone's local x, y (= nor), z axes in Blender
    axes: the minimal rotation taking +Y to ``nor``, then a rotation by ``roll`` about ``nor``.
    """
    x, y, z = nor[..., 0], nor[..., 1], nor[..., 2]
    theta = 1.0 + y
    theta_alt = x * x + z * z
    # Blender's thresholds: at the singularity nor = -Y a fixed frame (symmetric about Z) is
    # used. Near it 1 + y cancels catastrophically; Blender (float32) substitutes a two-term
    # series in x^2 + z^2, we use the exact identity 1 + y = (x^2 + z^2) / (1 - y), which keeps
    # the frame orthonormal to float64 precision (the series is off by ~1e-5 there).
    regular = (theta > 6.1e-3) | (theta_alt > 2.5e-4 ** 2)
    theta = np.where(y < 0, theta_alt / (1.0 - y), theta)
    theta = np.where(regular, theta, 1.0)
    Bm = np.stack([
        np.stack([1 - x * x / theta, x, -x * z / theta], -1),
        np.stack([-x, y, -z], -1),
        np.stack([-x * z / theta, z, 1 - z * z / theta], -1),
    ], -2)
    Bm = np.where(regular[..., None, None], Bm, np.diag([-1.0, -1.0, 1.0]))
    return rotvec_to_matrix(nor * np.asarray(roll, dtype=float)[..., None]) @ Bm


def bone_rest_frames(heads: np.ndarray, tails: np.ndarray, roll: np.ndarray) -> np.ndarray:
    """Rest orientation of each bone as Blender defines it, in our axes.

    heads, tails: (..., B, 3) bone ends in our axes (+Y up, +Z front); roll: (B,) Blender bone
    roll in radians (``Rig.roll``).
    Returns (..., B, 3, 3) rotation matrices whose columns are the bone's local x, y, z axes
    in our world axes; local y points from head to tail (Blender's convention).

    The bone vector is taken to Blender's axes (blender = (x, -z, y)), framed there with
    Blender's ``vec_roll_to_mat3`` (rolls were authored in Blender, so the frame must be built
    where the roll means what Blender meant), and the axes are brought back. A bone pointing up
    (+Y) with roll 0 gets the identity frame: Blender's local z of an upright bone faces the
    front (-Y Blender = +Z ours).
    """
    d = np.asarray(tails, dtype=float) - np.asarray(heads, dtype=float)
    length = np.linalg.norm(d, axis=-1, keepdims=True)
    if (length <= 0).any():
        raise MeshError("bone_rest_frames: a bone has zero length (head == tail); expected distinct ends")
    nor = (d / length) @ _TO_BLENDER.T
    roll = np.broadcast_to(np.asarray(roll, dtype=float), nor.shape[:-1])
    return _TO_BLENDER.T @ _blender_vec_roll_to_mat3(nor, roll)
