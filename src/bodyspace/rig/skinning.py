"""Compiled linear blend and dual-quaternion skinning over sparse weights, batched over frames.

The numpy formulation (``kinematics.linear_blend_skinning_numpy``) blends all vertices' 3x4
matrices with one sparse x dense product and then applies them with broadcasts: every step
writes a temporary of (V, 12, N) or (V, 3, N) doubles, so it runs at a fraction of the memory
bandwidth on one core. Here each vertex's few influences (the CSR row of the (V, B) weights, at
most a handful) are blended and applied in registers, and only the posed vertex is written.

Layout of the work: frames (or bodies) go in blocks of up to ``FRAME_BLOCK``; for one block
the bones' ``G_b - I`` (LBS) or unit dual quaternions (DQS) are rearranged once into a table
(B, 12 or 8, frames), frames contiguous, so every inner loop runs over the frames of the block
in SIMD lanes, on 1-D rows (the form LLVM vectorizes): for a vertex,
``A_f = sum_k w_k (G_{b_k, f} - I)`` for all the block's frames f at once, then
``v'_f = v + A_f [v; 1]``. Rows of the weights are padded to a multiple of four influences
(weight 0, exact), four blended per pass. The table of one block (1 MB for the 163-bone rig)
stays in the L2 cache; the rest vertices are read once a block (shared rest) or once a frame
(per-body rest). The last step, three strided stores a vertex-frame into the (N, V, 3)
output, now costs about as much as the blend. Two lanes (``bodyspace.parallel.run_both``) take
the two halves of the frames, or of the vertices for a single frame.

Properties kept from the numpy reference, exactly:

* what is blended is ``G_b - I`` and the result is added to the rest vertex, so the identity
  pose returns the input bit for bit and rows that sum to one only up to rounding do not scale
  the rest mesh;
* DQS flips each bone's quaternion into the hemisphere of the vertex's heaviest bone (its
  "pivot", the first largest weight of the row) before blending, so ``q`` and ``-q`` blend as
  the same rotation (Kavan et al. 2008, §4.1 "antipodality");
* the results equal the reference to rounding (1e-12 relative in float64; FMA contraction is
  the only difference).

``dtype=np.float32`` computes in float64 and stores float32: half the bytes written, which is
what bounds the speed here. ``out=`` writes into a preallocated (or memory-mapped) array.
"""

from __future__ import annotations

import numba
import numpy as np
import scipy.sparse as sp

from bodyspace.errors import MeshError, ParameterError
from bodyspace.parallel import halves, run_both

# ``contract``: multiply-adds may fuse into FMA instructions (no other reassociation): results
# differ from unfused ones only in the last bit. ``error_model="numpy"``: a float division does
# not test for zero (that branch kept DQS's normalization loop from vectorizing; the blended
# quaternion's norm is not zero for non-negative weights in one hemisphere).
_kernel = numba.njit(cache=True, nogil=True, fastmath={"contract"}, error_model="numpy")

# Frames skinned together, in SIMD lanes (8 doubles fill an AVX-512 register): the most a block
# takes; its (B, 12, 64) table is 1 MB for 163 bones, within a core's L2 (measured: 64 beat 16, 32).
FRAME_BLOCK = 64
# Rows of the weights must sum to one within this (float32-stored weights still pass).
WEIGHT_SUM_TOLERANCE = 1e-6
# Below this many vertex-frames a call stays on one lane (a thread hand-off costs ~50 us).
_TWO_LANES_MIN_WORK = 200_000
_OUTPUT_DTYPES = (np.dtype(np.float64), np.dtype(np.float32))


# ------------------------------------------------------------------------------------ inputs

def csr_skin_weights(weights, n_vertices: int, n_bones: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Validated CSR arrays of (V, B) skin weights: ``indptr`` (V+1,), ``indices`` (nnz,) uint32,
    ``data`` (nnz,) float64, duplicates summed, explicit zeros dropped, column indices sorted.

    weights: scipy sparse or dense (V, B), finite, every row summing to one.
    """
    shape = weights.shape if hasattr(weights, "shape") else np.shape(weights)
    if tuple(shape) != (n_vertices, n_bones):
        raise ParameterError(f"weights: shape {tuple(shape)}, expected ({n_vertices}, {n_bones}) for "
                             f"{n_vertices} vertices and {n_bones} bones")
    W = sp.csr_matrix(weights, dtype=np.float64, copy=True)
    W.sum_duplicates()
    W.eliminate_zeros()
    W.sort_indices()
    if not np.isfinite(W.data).all():
        bad = int(np.searchsorted(W.indptr, np.flatnonzero(~np.isfinite(W.data))[0], side="right") - 1)
        raise ParameterError(f"weights: row {bad} (vertex {bad}) holds NaN or infinity; expected finite weights")
    sums = np.add.reduceat(W.data, W.indptr[:-1]) if W.nnz else np.zeros(n_vertices)
    sums[np.diff(W.indptr) == 0] = 0.0                        # reduceat repeats a value at empty rows
    off = np.abs(sums - 1.0)
    bad = np.flatnonzero(off > WEIGHT_SUM_TOLERANCE)
    if len(bad):
        i = int(bad[0])
        raise ParameterError(f"weights: row {i} (vertex {i}) sums to {sums[i]:.9g} over {int(np.diff(W.indptr)[i])} "
                             f"bones ({len(bad)} rows off in all); expected every row to sum to 1 (within "
                             f"{WEIGHT_SUM_TOLERANCE:g}): normalize the weights (divide each row by its sum)")
    return W.indptr.astype(np.int64), W.indices.astype(np.uint32), W.data


def _batch_inputs(vertices, transforms, dtype, out) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Validate transforms (N, B, 4, 4), rest vertices (V, 3) or (N, V, 3) and the output.

    Returns G (N, B, 4, 4) float64 C-contiguous, rest (1 or N, V, 3) float64 and out (N, V, 3).
    A (N, V, 3) array broadcast from one body (stride 0 on its first axis) counts as shared.
    """
    G = np.ascontiguousarray(transforms, dtype=np.float64)
    if G.ndim != 4 or G.shape[-2:] != (4, 4):
        raise ParameterError(f"transforms: shape {G.shape}, expected (N, B, 4, 4)")
    if not np.isfinite(G).all():
        raise ParameterError("transforms: NaN or infinity found; expected finite rigid bone transforms")
    N = G.shape[0]
    v = np.asarray(vertices, dtype=np.float64)
    if v.ndim == 3 and v.shape[0] == N and N > 1 and v.strides[0] == 0:
        v = v[:1]
    elif v.ndim == 2:
        v = v[None]
    if v.ndim != 3 or v.shape[0] not in (1, N) or v.shape[2] != 3:
        raise MeshError(f"vertices: shape {np.shape(vertices)}, expected ({N}, V, 3) or (V, 3) rest vertices "
                        f"for {N} transform sets")
    dtype = np.dtype(dtype)
    if dtype not in _OUTPUT_DTYPES:
        raise ParameterError(f"dtype: {dtype}, expected float64 or float32")
    V = v.shape[1]
    if out is None:
        out = np.empty((N, V, 3), dtype=dtype)
    else:
        out = np.asarray(out)            # a memmap as a plain ndarray view (no copy)
        if out.shape != (N, V, 3) or out.dtype not in _OUTPUT_DTYPES or not out.flags.writeable:
            raise ParameterError(f"out: {out.dtype} array of shape {out.shape}"
                                 f"{'' if out.flags.writeable else ', read-only'}; expected a writable float64 "
                                 f"or float32 array of shape ({N}, {V}, 3)")
        if np.may_share_memory(out, v) or np.may_share_memory(out, G):
            raise ParameterError("out: overlaps the rest vertices or the transforms; pass a separate array")
    return G, v, out


def _padded_rows(indptr, indices, data, multiple: int = 4):
    """CSR arrays with every row padded to a multiple of ``multiple`` entries: weight 0 on the
    row's first bone (its table rows are in the cache already). Adding ``0 * G`` is exact."""
    counts = np.diff(indptr)
    padded = -(-counts // multiple) * multiple
    pptr = np.zeros(len(counts) + 1, dtype=np.int64)
    np.cumsum(padded, out=pptr[1:])
    pind = np.repeat(indices[indptr[:-1]], padded).astype(np.uint32)
    pdat = np.zeros(pptr[-1])
    pos = np.repeat(pptr[:-1] - indptr[:-1], counts) + np.arange(len(indices))
    pind[pos] = indices
    pdat[pos] = data
    return pptr, pind, pdat


def _frame_block(frames: int) -> int:
    """Frames per block: FRAME_BLOCK, or fewer (a multiple of 8) for a short batch."""
    return int(min(FRAME_BLOCK, max(8, -(-frames // 8) * 8)))


def _lane_ranges(N: int, V: int, lanes: int | None) -> tuple[int, list[tuple[int, int, int, int]]]:
    """Frame block and work split: [(n0, n1, i0, i1)], one range per lane; two lanes take
    the halves of the frames (whole blocks on the first), or of the vertices for one frame."""
    if lanes is None:
        lanes = 2 if N * V >= _TWO_LANES_MIN_WORK else 1
    if lanes not in (1, 2):
        raise ParameterError(f"lanes={lanes!r}; expected 1, 2 or None (automatic)")
    if lanes == 1:
        return _frame_block(N), [(0, N, 0, V)]
    if N >= 2:
        (_, m), _ = halves(N)
        fb = _frame_block(m)
        if m > fb:
            m -= m % fb
        return fb, [(0, m, 0, V), (m, N, 0, V)]
    (a0, a1), (b0, b1) = halves(V)
    return _frame_block(N), [(0, N, a0, a1), (0, N, b0, b1)]


def _run(kernel, split, *args) -> float:
    """Run ``kernel(*args, fb, n0, n1, i0, i1, check)`` on each range of ``split`` (two lanes:
    side by side); return the sum of the non-finite checks (0 when every rest vertex was finite)."""
    fb, ranges = split
    checks = [np.zeros(fb) for _ in ranges]
    if len(ranges) == 1:
        kernel(*args, fb, *ranges[0], checks[0])
    else:
        run_both(lambda: kernel(*args, fb, *ranges[0], checks[0]), lambda: kernel(*args, fb, *ranges[1], checks[1]))
    return float(sum(c.sum() for c in checks))


def _raise_if_not_finite(check: float) -> None:
    if check != 0.0:
        raise MeshError("vertices: NaN or infinity found in the rest vertices; expected finite coordinates "
                        "(the output holds NaN where they were)")


# ------------------------------------------------------------------------------- LBS kernel

@_kernel
def _rest_rows(rest, s, nf, i, xyz, check):
    """Rest vertex i of frames s:s+nf into the rows ``xyz`` (3, fb) (one copy for a shared rest);
    ``check`` gets ``0 * v`` added, so it stays zero unless a coordinate is NaN or infinite."""
    fb = xyz.shape[1]
    if rest.shape[0] > 1:
        for f in range(nf):
            for c in range(3):
                xyz[c, f] = rest[s + f, i, c]
        for f in range(nf, fb):
            for c in range(3):
                xyz[c, f] = 0.0
    else:
        for c in range(3):
            v = rest[0, i, c]
            for f in range(fb):
                xyz[c, f] = v
    for c in range(3):
        row = xyz[c]
        for f in range(fb):
            check[f] += 0.0 * row[f]


@_kernel
def _apply_rows(m, xyz, res):
    """``res[r] = v_r + m[4r+3] + m[4r] x + m[4r+1] y + m[4r+2] z`` over the frame lanes: the
    blended ``(A - I | t)`` rows m (12, fb) applied to the rest rows xyz (3, fb)."""
    fb = xyz.shape[1]
    x, y, z = xyz[0], xyz[1], xyz[2]
    for r in range(3):
        o, v, ax, ay, az, at = res[r], xyz[r], m[4 * r], m[4 * r + 1], m[4 * r + 2], m[4 * r + 3]
        for f in range(fb):
            o[f] = v[f] + (at[f] + ax[f] * x[f] + ay[f] * y[f] + az[f] * z[f])


@_kernel
def _lbs_kernel(indptr, indices, data, G, rest, out, fb, n0, n1, i0, i1, check):
    """``out[n, i] = v + sum_k w_k (G_{b_k} - I) [v; 1]`` for frames n0:n1 and vertices i0:i1.

    indptr/indices/data: the weights' CSR arrays with every row padded to a multiple of 4
    entries (weight 0); fb: frames per block; rest (1 or N, V, 3); check (fb,), see
    ``_rest_rows``. Every inner loop runs over the fb frames of a block (SIMD lanes), on 1-D
    rows, which is the form LLVM vectorizes; four influences are blended per pass so the
    accumulator is written once for a vertex of up to four bones.
    """
    B = G.shape[1]
    table = np.zeros((B, 12, fb))       # G - I of the block's frames, frames last
    acc = np.empty((12, fb))
    xyz = np.empty((3, fb))
    res = np.empty((3, fb))
    for s in range(n0, n1, fb):
        nf = min(fb, n1 - s)
        for b in range(B):
            for f in range(fb):
                for r in range(3):
                    for c in range(4):
                        table[b, 4 * r + c, f] = (G[s + f, b, r, c] - (1.0 if r == c else 0.0)) if f < nf else 0.0
        for i in range(i0, i1):
            p0, p1 = indptr[i], indptr[i + 1]
            b0, b1, b2, b3 = indices[p0], indices[p0 + 1], indices[p0 + 2], indices[p0 + 3]
            w0, w1, w2, w3 = data[p0], data[p0 + 1], data[p0 + 2], data[p0 + 3]
            for j in range(12):
                a, t0, t1, t2, t3 = acc[j], table[b0, j], table[b1, j], table[b2, j], table[b3, j]
                for f in range(fb):
                    a[f] = w0 * t0[f] + w1 * t1[f] + w2 * t2[f] + w3 * t3[f]
            for k in range(p0 + 4, p1, 4):
                b0, b1, b2, b3 = indices[k], indices[k + 1], indices[k + 2], indices[k + 3]
                w0, w1, w2, w3 = data[k], data[k + 1], data[k + 2], data[k + 3]
                for j in range(12):
                    a, t0, t1, t2, t3 = acc[j], table[b0, j], table[b1, j], table[b2, j], table[b3, j]
                    for f in range(fb):
                        a[f] += w0 * t0[f] + w1 * t1[f] + w2 * t2[f] + w3 * t3[f]
            _rest_rows(rest, s, nf, i, xyz, check)
            _apply_rows(acc, xyz, res)
            for f in range(nf):
                out[s + f, i, 0] = res[0, f]
                out[s + f, i, 1] = res[1, f]
                out[s + f, i, 2] = res[2, f]


def linear_blend_skinning(vertices: np.ndarray, weights: sp.spmatrix | np.ndarray, transforms: np.ndarray, *,
                          dtype=np.float64, out: np.ndarray | None = None, lanes: int | None = None) -> np.ndarray:
    """Linear blend skinning: ``v'_i = v_i + (sum_b w_ib (G_b - I)) [v_i; 1]``, compiled.

    vertices: (N, V, 3) rest vertices per body, or (V, 3) shared by every frame.
    weights: (V, B) skin weights (sparse or dense), finite, rows summing to one.
    transforms: (N, B, 4, 4) bone transforms (``forward_kinematics``).
    dtype: float64 (default) or float32 output; the arithmetic is float64 either way.
    out: optional (N, V, 3) float64 or float32 array (e.g. a ``np.memmap``) to write into.
    lanes: 1 or 2 threads; None: two when the call has >= 200,000 vertex-frames.
    Returns (N, V, 3) posed vertices (``out`` when given).
    """
    G, v, out = _batch_inputs(vertices, transforms, dtype, out)
    N, B = G.shape[:2]
    V = v.shape[1]
    indptr, indices, data = _padded_rows(*csr_skin_weights(weights, V, B))
    _raise_if_not_finite(_run(_lbs_kernel, _lane_ranges(N, V, lanes), indptr, indices, data, G, v, out))
    return out


# ------------------------------------------------------------------------------- DQS kernel

@_kernel
def _dual_quaternion(G, n, b, table, f):
    """Unit dual quaternion ``(q, q')`` of the rigid ``G[n, b]`` into ``table[b, 0:8, f]``.

    ``q`` by Shepperd's method exactly as ``kinematics.matrix_to_quaternion`` (largest of the
    four square-root arguments, normalized, w >= 0); ``q' = (0, t) q / 2``.
    """
    m00, m01, m02 = G[n, b, 0, 0], G[n, b, 0, 1], G[n, b, 0, 2]
    m10, m11, m12 = G[n, b, 1, 0], G[n, b, 1, 1], G[n, b, 1, 2]
    m20, m21, m22 = G[n, b, 2, 0], G[n, b, 2, 1], G[n, b, 2, 2]
    c0 = 1.0 + m00 + m11 + m22
    c1 = 1.0 + m00 - m11 - m22
    c2 = 1.0 - m00 + m11 - m22
    c3 = 1.0 - m00 - m11 + m22
    d21, d02, d10 = m21 - m12, m02 - m20, m10 - m01
    s01, s02, s12 = m01 + m10, m02 + m20, m12 + m21
    best, cb = 0, c0
    if c1 > cb:
        best, cb = 1, c1
    if c2 > cb:
        best, cb = 2, c2
    if c3 > cb:
        best, cb = 3, c3
    s = np.sqrt(max(cb, 1e-300))
    ss = s * s
    if best == 0:
        w, x, y, z = ss, d21, d02, d10
    elif best == 1:
        w, x, y, z = d21, ss, s01, s02
    elif best == 2:
        w, x, y, z = d02, s01, ss, s12
    else:
        w, x, y, z = d10, s02, s12, ss
    h = 2.0 * s
    w, x, y, z = w / h, x / h, y / h, z / h
    norm = np.sqrt(w * w + x * x + y * y + z * z)
    w, x, y, z = w / norm, x / norm, y / norm, z / norm
    if w < 0:
        w, x, y, z = -w, -x, -y, -z
    tx, ty, tz = G[n, b, 0, 3], G[n, b, 1, 3], G[n, b, 2, 3]
    table[b, 0, f] = w
    table[b, 1, f] = x
    table[b, 2, f] = y
    table[b, 3, f] = z
    table[b, 4, f] = 0.5 * (-tx * x - ty * y - tz * z)
    table[b, 5, f] = 0.5 * (tx * w + ty * z - tz * y)
    table[b, 6, f] = 0.5 * (-tx * z + ty * w + tz * x)
    table[b, 7, f] = 0.5 * (tx * y - ty * x + tz * w)


@_kernel
def _dqs_kernel(indptr, indices, data, pivot, G, rest, out, fb, n0, n1, i0, i1, check):
    """Dual-quaternion skinning of frames n0:n1, vertices i0:i1 (``dual_quaternion_skinning``).

    Arguments as ``_lbs_kernel``; pivot (V,): each vertex's heaviest bone. Per vertex and
    frame lane: each bone's dual quaternion, flipped into the pivot's hemisphere, is weighted
    and summed; the sum ``(q, e)`` is normalized and applied as the rigid motion
    ``v' = v + (R(q) - I) v + t`` with ``t = 2 (e conj(q)).xyz``; ``R(q) - I`` is formed from
    ``q``'s products (its diagonal as ``-2 (q_j^2 + q_k^2)``), so ``q = 1`` gives exactly 0.
    """
    B = G.shape[1]
    table = np.zeros((B, 8, fb))
    for b in range(B):
        for f in range(fb):
            table[b, 0, f] = 1.0                 # frames past the end: identity
    acc = np.empty((8, fb))
    m = np.empty((12, fb))
    inv = np.empty(fb)
    sw = np.empty((4, fb))
    xyz = np.empty((3, fb))
    res = np.empty((3, fb))
    for s in range(n0, n1, fb):
        nf = min(fb, n1 - s)
        for b in range(B):
            for f in range(nf):
                _dual_quaternion(G, s + f, b, table, f)
        for i in range(i0, i1):
            p = pivot[i]
            pw, px, py, pz = table[p, 0], table[p, 1], table[p, 2], table[p, 3]
            for k in range(indptr[i], indptr[i + 1], 4):
                for e in range(4):
                    b, w, sg = indices[k + e], data[k + e], sw[e]
                    tw, tx, ty, tz = table[b, 0], table[b, 1], table[b, 2], table[b, 3]
                    for f in range(fb):
                        d = tw[f] * pw[f] + tx[f] * px[f] + ty[f] * py[f] + tz[f] * pz[f]
                        sg[f] = -w if d < 0.0 else w
                b0, b1, b2, b3 = indices[k], indices[k + 1], indices[k + 2], indices[k + 3]
                s0, s1, s2, s3 = sw[0], sw[1], sw[2], sw[3]
                for j in range(8):
                    a, t0, t1, t2, t3 = acc[j], table[b0, j], table[b1, j], table[b2, j], table[b3, j]
                    if k == indptr[i]:
                        for f in range(fb):
                            a[f] = s0[f] * t0[f] + s1[f] * t1[f] + s2[f] * t2[f] + s3[f] * t3[f]
                    else:
                        for f in range(fb):
                            a[f] += s0[f] * t0[f] + s1[f] * t1[f] + s2[f] * t2[f] + s3[f] * t3[f]
            # normalize, then as (R - I | t) rows: every loop reads few rows and writes one,
            # the form LLVM vectorizes (one loop doing it all was left scalar)
            aw, ax, ay, az = acc[0], acc[1], acc[2], acc[3]
            for f in range(fb):
                inv[f] = 1.0 / np.sqrt(aw[f] * aw[f] + ax[f] * ax[f] + ay[f] * ay[f] + az[f] * az[f])
            for j in range(8):
                a = acc[j]
                for f in range(fb):
                    a[f] = a[f] * inv[f]
            qw, qx, qy, qz, dw, dx, dy, dz = acc[0], acc[1], acc[2], acc[3], acc[4], acc[5], acc[6], acc[7]
            m0, m1, m2, m3, m4, m5, m6, m7, m8, m9, m10, m11 = (m[0], m[1], m[2], m[3], m[4], m[5], m[6], m[7],
                                                               m[8], m[9], m[10], m[11])
            for f in range(fb):
                m0[f] = -2.0 * (qy[f] * qy[f] + qz[f] * qz[f])
            for f in range(fb):
                m1[f] = 2.0 * (qx[f] * qy[f] - qw[f] * qz[f])
            for f in range(fb):
                m2[f] = 2.0 * (qx[f] * qz[f] + qw[f] * qy[f])
            for f in range(fb):
                m4[f] = 2.0 * (qx[f] * qy[f] + qw[f] * qz[f])
            for f in range(fb):
                m5[f] = -2.0 * (qx[f] * qx[f] + qz[f] * qz[f])
            for f in range(fb):
                m6[f] = 2.0 * (qy[f] * qz[f] - qw[f] * qx[f])
            for f in range(fb):
                m8[f] = 2.0 * (qx[f] * qz[f] - qw[f] * qy[f])
            for f in range(fb):
                m9[f] = 2.0 * (qy[f] * qz[f] + qw[f] * qx[f])
            for f in range(fb):
                m10[f] = -2.0 * (qx[f] * qx[f] + qy[f] * qy[f])
            for f in range(fb):        # t = 2 (e conj(q)).xyz
                m3[f] = 2.0 * (qw[f] * dx[f] - dw[f] * qx[f] + (qy[f] * dz[f] - qz[f] * dy[f]))
            for f in range(fb):
                m7[f] = 2.0 * (qw[f] * dy[f] - dw[f] * qy[f] + (qz[f] * dx[f] - qx[f] * dz[f]))
            for f in range(fb):
                m11[f] = 2.0 * (qw[f] * dz[f] - dw[f] * qz[f] + (qx[f] * dy[f] - qy[f] * dx[f]))
            _rest_rows(rest, s, nf, i, xyz, check)
            _apply_rows(m, xyz, res)
            for f in range(nf):
                out[s + f, i, 0] = res[0, f]
                out[s + f, i, 1] = res[1, f]
                out[s + f, i, 2] = res[2, f]


@_kernel
def _row_pivots(indptr, indices, data):
    """(V,) the bone of each row's first largest weight (the DQS hemisphere reference)."""
    V = len(indptr) - 1
    pivot = np.empty(V, dtype=np.uint32)
    for i in range(V):
        best = indptr[i]
        for k in range(indptr[i] + 1, indptr[i + 1]):
            if data[k] > data[best]:
                best = k
        pivot[i] = indices[best]
    return pivot


def dual_quaternion_skinning(vertices: np.ndarray, weights: sp.spmatrix | np.ndarray, transforms: np.ndarray, *,
                             dtype=np.float64, out: np.ndarray | None = None, lanes: int | None = None) -> np.ndarray:
    """Dual-quaternion skinning (Kavan et al. 2008), compiled: blend unit dual quaternions.

    vertices: (N, V, 3) rest vertices per body, or (V, 3) shared by every frame.
    weights: (V, B) skin weights (sparse or dense), finite, rows summing to one.
    transforms: (N, B, 4, 4) rigid bone transforms (``forward_kinematics``).
    dtype, out, lanes: as ``linear_blend_skinning``.
    Returns (N, V, 3) posed vertices (``out`` when given).

    Per vertex, each bone's dual quaternion is flipped into the hemisphere of the vertex's
    heaviest bone, weighted, summed, normalized and applied as a rigid motion; all ``G_b = I``
    returns the input bit for bit.
    """
    G, v, out = _batch_inputs(vertices, transforms, dtype, out)
    N, B = G.shape[:2]
    V = v.shape[1]
    indptr, indices, data = csr_skin_weights(weights, V, B)
    pivot = _row_pivots(indptr, indices, data)
    indptr, indices, data = _padded_rows(indptr, indices, data)
    _raise_if_not_finite(_run(_dqs_kernel, _lane_ranges(N, V, lanes), indptr, indices, data, pivot, G, v, out))
    return out
