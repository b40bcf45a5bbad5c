"""Compiled linear blend and dual-quaternion skinning over sparse weights, batched over frames.

The numpy formulation (``kinematics.linear_blend_skinning_numpy``) blends all vertices' 3x4
matrices with one sparse x dense product and then applies them with broadcasts: every step
writes a temporary of (V, 12, N) or (V, 3, N) doubles, so it runs at a fraction of the memory
bandwidth on one core. Here each vertex's few influences (the CSR row of the (V, B) weights)
are blended and applied in vector registers, and only the posed vertex is written.

Layout of the work (docs/skinning.md measures each choice):

* frames (or bodies) go in blocks of ``L`` = two 64-byte vectors of the output dtype (16
  frames for float64, 32 for float32); for one block the bones' ``G_b - I`` (LBS) or unit dual
  quaternions (DQS) are rearranged once into a table (B, 12 or 8, L), frames contiguous, so a
  table row is two vector registers and a vertex's blend is a few dozen vector
  multiply-adds: ``A_f = sum_k w_k (G_{b_k, f} - I)`` for the L frames at once, then
  ``v'_f = v + A_f [v; 1]``;
* the arithmetic is in the output dtype: float32 output blends a float32 table (half the
  bytes, twice the lanes); the table itself is formed in float64 and rounded once;
* each row is blended with exactly its own number of influences (passes of 4, 3, 2 or 1
  bones; the default rig averages 3.0 a vertex, where padding every row to 4 cost 58 % more);
* vertices go in tiles of ``W`` (one vector of lanes: 8 float64, 16 float32); a tile's
  results (3W rows of L frame lanes) are turned into W x W blocks by shuffles in registers
  (``_transpose``) and written as, for every frame, one contiguous run of the tile's 3W
  coordinates: three vector stores a frame instead of 3W scattered scalar ones (the scatter
  was the largest cost of the previous kernel). Per-body rest vertices are read the same way
  backwards (``_frames_to_tile``);
* ``STAGED_TILES`` full tiles are staged so a frame's run is 3WC values long, then copied out;
  outputs of ``STREAM_MIN_BYTES`` or more with non-temporal stores for the run's whole cache
  lines (a plain store reads each line before writing it);
* the vector code is written directly in LLVM IR (numba ``intrinsic``s below): LLVM's
  auto-vectorizer left the constant-length frame loops scalar (it fully unrolls them and then
  cannot prove the buffers do not alias).

Two lanes (``bodyspace.parallel.run_both``) take the two halves of the frames, or of the
vertices for a single frame.

Properties kept from the numpy reference, exactly:

* what is blended is ``G_b - I`` and the result is added to the rest vertex, so the identity
  pose returns the input bit for bit (float64; float32 output returns the input rounded to
  float32) and rows that sum to one only up to rounding do not scale the rest mesh;
* DQS flips each bone's quaternion into the hemisphere of the vertex's heaviest bone (its
  "pivot", the first largest weight of the row) before blending, so ``q`` and ``-q`` blend as
  the same rotation (Kavan et al. 2008, §4.1 "antipodality");
* float64 results equal the reference to rounding (1e-12 relative; FMA contraction and the
  order of the sums are the only differences). float32 results are computed in float32: within
  1e-6 of the reference relative to the mesh's extent; measured on the default rig, one body
  over 200 frames of the pose library: LBS 0.00035 mm, DQS 0.00054 mm at most (rounding the
  float64 result to float32 alone: 0.00006 mm).

``out=`` writes into a preallocated (or memory-mapped) array.
"""

from __future__ import annotations

import numba
import numpy as np
import scipy.sparse as sp
from llvmlite import ir
from numba.core import cgutils, types
from numba.extending import intrinsic

from bodyspace.errors import MeshError, ParameterError
from bodyspace.parallel import halves, run_both

# ``contract``: multiply-adds may fuse into FMA instructions (no other reassociation): results
# differ from unfused ones only in the last bit. ``error_model="numpy"``: a float division does
# not test for zero.
_kernel = numba.njit(cache=True, nogil=True, fastmath={"contract"}, error_model="numpy")
_inline = numba.njit(inline="always", nogil=True, fastmath={"contract"}, error_model="numpy")

# One vector register (AVX-512): W = 8 float64 or 16 float32 lanes, the vertices of a tile.
VECTOR_BYTES = 64
# A table row (the frames of a block) is this many vectors: two gave 10-40 % over one (the
# per-vertex work, CSR row and branches, is shared by twice the frames), in both dtypes.
ROW_VECTORS = 2
# The most frames a block takes (float32: 2 x 16); float64 blocks take 16.
FRAME_BLOCK = ROW_VECTORS * VECTOR_BYTES // 4
# Full vertex tiles staged before their frame runs are copied out (runs of 3 W C values a frame:
# 384 float32 = 24 cache lines, so the two partial lines at the ends of a run are few).
STAGED_TILES = 8
# Outputs at least this large are written with non-temporal (streaming) stores: they do not fit
# the 32 MB L3 anyway, and a plain store reads every line before writing it.
STREAM_MIN_BYTES = 16 * 2**20
# Rows of the weights must sum to one within this (float32-stored weights still pass).
WEIGHT_SUM_TOLERANCE = 1e-6
# Below this many vertex-frames a call stays on one lane (a thread hand-off costs ~50 us).
_TWO_LANES_MIN_WORK = 200_000
_OUTPUT_DTYPES = (np.dtype(np.float64), np.dtype(np.float32))
_I64 = ir.IntType(64)


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


# ---------------------------------------------------------------------- vector code (LLVM IR)

def vector_lanes(dtype) -> int:
    """W: the lanes of one vector register for ``dtype`` (8 float64, 16 float32)."""
    return VECTOR_BYTES // np.dtype(dtype).itemsize


def frame_block(dtype) -> int:
    """L: the frames of a block for ``dtype`` (16 float64, 32 float32)."""
    return ROW_VECTORS * vector_lanes(dtype)


def _const(v: int) -> ir.Constant:
    return ir.Constant(_I64, v)


class _Rows:
    """Vector loads and stores at element offsets of a C-contiguous array (the kernels' own
    buffers): vectors of a table row (L lanes) or, ``native``, of one register (W lanes)."""

    def __init__(self, context, builder, arr_type, arr, native: bool = False):
        dtype = np.dtype(str(arr_type.dtype))
        self.builder = builder
        self.L, self.W = frame_block(dtype), vector_lanes(dtype)
        self.vec = ir.VectorType(context.get_value_type(arr_type.dtype), self.W if native else self.L)
        self.array = context.make_array(arr_type)(context, builder, arr)
        self.align = dtype.itemsize

    def pointer(self, offset):
        return self.builder.bitcast(self.builder.gep(self.array.data, [offset]), self.vec.as_pointer())

    def load(self, offset):
        return self.builder.load(self.pointer(offset), align=self.align)

    def store(self, value, offset) -> None:
        self.builder.store(value, self.pointer(offset), align=self.align)

    def row_length(self):
        """Elements per step of the first axis (a 2-D (N, 3V) view of the output or rest)."""
        return self.builder.sdiv(self.builder.extract_value(self.array.strides, 0), _const(self.align))


def _vector_intrinsic(builder, name: str, vec: ir.VectorType, n_args: int):
    suffix = f"v{vec.count}{'f32' if isinstance(vec.element, ir.FloatType) else 'f64'}"
    fn = cgutils.get_or_insert_function(builder.module, ir.FunctionType(vec, [vec] * n_args), f"{name}.{suffix}")
    return lambda *args: builder.call(fn, list(args))


def _splat(builder, vec: ir.VectorType, scalar):
    """``scalar`` in every lane of ``vec``."""
    one = builder.insert_element(ir.Constant(vec, ir.Undefined), scalar, ir.Constant(ir.IntType(32), 0))
    mask = ir.Constant(ir.VectorType(ir.IntType(32), vec.count), [0] * vec.count)
    return builder.shuffle_vector(one, ir.Constant(vec, ir.Undefined), mask)


def _transpose(builder, rows: list) -> list:
    """The W x W matrix of ``rows`` (W vectors of W lanes, W a power of two) transposed: log2(W)
    stages, each swapping the off-diagonal h x h blocks (h = 1, 2, 4, ...) of every 2h x 2h
    block with one two-source shuffle a row (W log2 W shuffles for W^2 values)."""
    W = len(rows)
    mask_type = ir.VectorType(ir.IntType(32), W)
    h = 1
    while h < W:
        new = list(rows)
        for r in range(W):
            if r & h:
                continue
            # new[r][c] = rows[r][c] (c & h == 0) or rows[r + h][c - h]; new[r + h] mirrors it
            low = [c if not c & h else W + c - h for c in range(W)]
            high = [c + h if not c & h else W + c for c in range(W)]
            new[r] = builder.shuffle_vector(rows[r], rows[r + h], ir.Constant(mask_type, low))
            new[r + h] = builder.shuffle_vector(rows[r], rows[r + h], ir.Constant(mask_type, high))
        rows = new
        h *= 2
    return rows


def _bone_offset(builder, bone, row_elements: int):
    """Element offset of bone ``bone``'s first table row (rows of ``row_elements``)."""
    b = builder.zext(bone, _I64) if bone.type.width < 64 else bone
    return builder.mul(b, _const(row_elements))


def _lbs_blend_intrinsic(accumulate: bool):
    def blend(typingctx, acc, table, bones, weights):
        """acc[j] (+)= sum_k weights[k] table[bones[k], j] for the 12 rows j of ``G - I``:
        acc (12, L), table (B, 12, L), bones/weights tuples of 1 to 4 influences."""
        n = len(bones)

        def codegen(context, builder, signature, args):
            a = _Rows(context, builder, signature.args[0], args[0])
            t = _Rows(context, builder, signature.args[1], args[1])
            L, fma = a.L, _vector_intrinsic(builder, "llvm.fmuladd", a.vec, 3)
            offs = [_bone_offset(builder, builder.extract_value(args[2], k), 12 * L) for k in range(n)]
            ws = [_splat(builder, a.vec, builder.extract_value(args[3], k)) for k in range(n)]
            for j in range(12):
                rows = [t.load(builder.add(o, _const(j * L))) for o in offs]
                s = a.load(_const(j * L)) if accumulate else None
                for k in range(n):
                    s = builder.fmul(ws[k], rows[k]) if s is None else fma(ws[k], rows[k], s)
                a.store(s, _const(j * L))
            return context.get_dummy_value()
        return types.void(acc, table, bones, weights), codegen
    return intrinsic(blend)


_lbs_blend_set = _lbs_blend_intrinsic(False)
_lbs_blend_add = _lbs_blend_intrinsic(True)


@intrinsic
def _lbs_vertex(typingctx, table, bones, weights, xyz, tile, t):
    """A vertex of at most four influences in one pass, in registers: for r = 0, 1, 2, the
    blended row ``m = sum_k weights[k] table[bones[k], 4r : 4r + 4]`` applied,
    ``tile[3t + r] = v_r + (m_3 + m_0 x + m_1 y + m_2 z)`` (as ``_lbs_blend_set`` + ``_apply``
    without the blended matrix's trip through memory)."""
    n = len(bones)

    def codegen(context, builder, signature, args):
        tb = _Rows(context, builder, signature.args[0], args[0])
        x = _Rows(context, builder, signature.args[3], args[3])
        o = _Rows(context, builder, signature.args[4], args[4])
        L, fma = tb.L, _vector_intrinsic(builder, "llvm.fmuladd", tb.vec, 3)
        offs = [_bone_offset(builder, builder.extract_value(args[1], k), 12 * L) for k in range(n)]
        ws = [_splat(builder, tb.vec, builder.extract_value(args[2], k)) for k in range(n)]
        base = builder.mul(args[5], _const(3 * L))
        p = [x.load(builder.add(base, _const(c * L))) for c in range(3)]
        res = []
        for r in range(3):
            m = []
            for c in range(4):
                rows = [tb.load(builder.add(off, _const((4 * r + c) * L))) for off in offs]
                s = builder.fmul(ws[0], rows[0])
                for k in range(1, n):
                    s = fma(ws[k], rows[k], s)
                m.append(s)
            res.append(builder.fadd(p[r], fma(m[2], p[2], fma(m[1], p[1], fma(m[0], p[0], m[3])))))
        for r in range(3):
            o.store(res[r], builder.add(base, _const(r * L)))
        return context.get_dummy_value()
    return types.void(table, bones, weights, xyz, tile, t), codegen


def _dqs_blend_values(builder, t: _Rows, pivot, bones, weights, n: int, acc: list) -> list:
    """The 8 rows of ``acc`` (vectors, or None to start from zero) plus ``sum_k s_k w_k
    table[bones[k], 0:8]`` for the n influences of the tuples ``bones``, ``weights``; table
    (B, 8, L) of unit dual quaternions; s_k = -1 in the frame lanes where bone k's rotation
    quaternion has a negative dot product with the pivot bone's, else 1 (antipodality)."""
    L, fma = t.L, _vector_intrinsic(builder, "llvm.fmuladd", t.vec, 3)
    po = _bone_offset(builder, pivot, 8 * L)
    p = [t.load(builder.add(po, _const(j * L))) for j in range(4)]
    zero = ir.Constant(t.vec, None)
    acc = list(acc)
    for k in range(n):
        o = _bone_offset(builder, builder.extract_value(bones, k), 8 * L)
        rows = [t.load(builder.add(o, _const(j * L))) for j in range(8)]
        d = builder.fmul(rows[0], p[0])
        for j in range(1, 4):
            d = fma(rows[j], p[j], d)
        w = _splat(builder, t.vec, builder.extract_value(weights, k))
        w = builder.select(builder.fcmp_ordered("<", d, zero), builder.fneg(w), w)
        for j in range(8):
            acc[j] = builder.fmul(w, rows[j]) if acc[j] is None else fma(w, rows[j], acc[j])
    return acc


def _rigid_rows(builder, vec: ir.VectorType, r: list) -> list:
    """The blended dual quaternion ``(q, e)`` (8 vectors), normalized, as the 12 rows of
    ``(R(q) - I | t)``, t = 2 (e conj(q)).xyz. ``R - I`` is formed from q's products (its
    diagonal as ``-2 (q_j^2 + q_k^2)``), so q = 1 gives exactly 0."""
    L = vec.count
    fma = _vector_intrinsic(builder, "llvm.fmuladd", vec, 3)
    sqrt = _vector_intrinsic(builder, "llvm.sqrt", vec, 1)
    mul, sub, add = builder.fmul, builder.fsub, builder.fadd
    n2 = mul(r[0], r[0])
    for j in range(1, 4):
        n2 = fma(r[j], r[j], n2)
    inv = builder.fdiv(ir.Constant(vec, [1.0] * L), sqrt(n2))
    qw, qx, qy, qz, dw, dx, dy, dz = (mul(v, inv) for v in r)
    two, minus_two = ir.Constant(vec, [2.0] * L), ir.Constant(vec, [-2.0] * L)

    def diagonal(u, v):
        return mul(minus_two, fma(u, u, mul(v, v)))
    return [diagonal(qy, qz), mul(two, sub(mul(qx, qy), mul(qw, qz))), mul(two, add(mul(qx, qz), mul(qw, qy))),
            mul(two, add(sub(mul(qw, dx), mul(dw, qx)), sub(mul(qy, dz), mul(qz, dy)))),
            mul(two, add(mul(qx, qy), mul(qw, qz))), diagonal(qx, qz), mul(two, sub(mul(qy, qz), mul(qw, qx))),
            mul(two, add(sub(mul(qw, dy), mul(dw, qy)), sub(mul(qz, dx), mul(qx, dz)))),
            mul(two, sub(mul(qx, qz), mul(qw, qy))), mul(two, add(mul(qy, qz), mul(qw, qx))), diagonal(qx, qy),
            mul(two, add(sub(mul(qw, dz), mul(dw, qz)), sub(mul(qx, dy), mul(qy, dx))))]


def _apply_rows(builder, vec: ir.VectorType, m: list, x, o, t) -> None:
    """``o[3t + r] = v_r + (m[4r+3] + m[4r] x + m[4r+1] y + m[4r+2] z)`` for r = 0, 1, 2: the 12
    rows m of ``(A - I | t)`` applied to rest vertex t of the rows x (3W, L) into the tile rows o
    (3W, L) (vectors over the frame lanes; x and o are ``_Rows``, t an IR index)."""
    fma = _vector_intrinsic(builder, "llvm.fmuladd", vec, 3)
    base = builder.mul(t, _const(3 * x.L))
    p = [x.load(builder.add(base, _const(c * x.L))) for c in range(3)]
    for r in range(3):
        v = builder.fadd(p[r], fma(m[4 * r + 2], p[2], fma(m[4 * r + 1], p[1], fma(m[4 * r], p[0], m[4 * r + 3]))))
        o.store(v, builder.add(base, _const(r * x.L)))


def _dqs_blend_intrinsic(accumulate: bool):
    def blend(typingctx, acc, table, pivot, bones, weights):
        """acc[0:8] (+)= the antipodal blend of ``_dqs_blend_values``: acc (12, L), rows 0-7 used."""
        n = len(bones)

        def codegen(context, builder, signature, args):
            a = _Rows(context, builder, signature.args[0], args[0])
            t = _Rows(context, builder, signature.args[1], args[1])
            start = [a.load(_const(j * a.L)) if accumulate else None for j in range(8)]
            for j, v in enumerate(_dqs_blend_values(builder, t, args[2], args[3], args[4], n, start)):
                a.store(v, _const(j * a.L))
            return context.get_dummy_value()
        return types.void(acc, table, pivot, bones, weights), codegen
    return intrinsic(blend)


_dqs_blend_set = _dqs_blend_intrinsic(False)
_dqs_blend_add = _dqs_blend_intrinsic(True)


@intrinsic
def _dual_quaternion_rows(typingctx, acc):
    """In place: the blended dual quaternion in acc rows 0-7 becomes the 12 rows of
    ``(R(q) - I | t)`` (``_rigid_rows``) in acc (12, L)."""
    def codegen(context, builder, signature, args):
        a = _Rows(context, builder, signature.args[0], args[0])
        rows = _rigid_rows(builder, a.vec, [a.load(_const(j * a.L)) for j in range(8)])
        for j, v in enumerate(rows):
            a.store(v, _const(j * a.L))
        return context.get_dummy_value()
    return types.void(acc), codegen


@intrinsic
def _dqs_vertex(typingctx, table, pivot, bones, weights, xyz, tile, t):
    """A vertex of at most four influences in registers: blend (``_dqs_blend_values``),
    normalize and form ``(R - I | t)`` (``_rigid_rows``), apply to rest vertex t of xyz into
    tile rows 3t:3t+3 (xyz and tile (3W, L))."""
    n = len(bones)

    def codegen(context, builder, signature, args):
        tb = _Rows(context, builder, signature.args[0], args[0])
        x = _Rows(context, builder, signature.args[4], args[4])
        o = _Rows(context, builder, signature.args[5], args[5])
        q = _dqs_blend_values(builder, tb, args[1], args[2], args[3], n, [None] * 8)
        _apply_rows(builder, tb.vec, _rigid_rows(builder, tb.vec, q), x, o, args[6])
        return context.get_dummy_value()
    return types.void(table, pivot, bones, weights, xyz, tile, t), codegen


@intrinsic
def _apply(typingctx, acc, xyz, tile, t):
    """Vertex t of a tile: ``tile[3t + r] = v_r + (m[4r+3] + m[4r] x + m[4r+1] y + m[4r+2] z)``
    for r = 0, 1, 2 over the L frame lanes; m = acc (12, L), (x, y, z) = xyz[3t : 3t + 3]
    (xyz and tile (3W, L))."""
    def codegen(context, builder, signature, args):
        a = _Rows(context, builder, signature.args[0], args[0])
        x = _Rows(context, builder, signature.args[1], args[1])
        o = _Rows(context, builder, signature.args[2], args[2])
        _apply_rows(builder, a.vec, [a.load(_const(j * a.L)) for j in range(12)], x, o, args[3])
        return context.get_dummy_value()
    return types.void(acc, xyz, tile, t), codegen


@intrinsic
def _tile_to_frames(typingctx, tile, out2, s, nf, col):
    """Write a full tile, (3W rows (3t + c), L frame lanes), to ``out2[s + f, col : col + 3W]``
    for the frames f < nf: each W x W block transposed in registers, then one contiguous run
    of 3W values (three vector stores) a frame. out2: the (N, 3V) view of the output."""
    def codegen(context, builder, signature, args):
        t = _Rows(context, builder, signature.args[0], args[0], native=True)
        o = _Rows(context, builder, signature.args[1], args[1], native=True)
        L, W = t.L, t.W
        row_length = o.row_length()
        for h in range(L // W):
            blocks = [_transpose(builder, [t.load(_const((q * W + k) * L + h * W)) for k in range(W)]) for q in range(3)]
            for k in range(W):
                f = h * W + k
                with builder.if_then(builder.icmp_signed("<", _const(f), args[3]), likely=True):
                    start = builder.add(builder.mul(builder.add(args[2], _const(f)), row_length), args[4])
                    for q in range(3):
                        o.store(blocks[q][k], builder.add(start, _const(q * W)))
        return context.get_dummy_value()
    return types.void(tile, out2, s, nf, col), codegen


@intrinsic
def _frames_to_tile(typingctx, rest2, s, nf, col, xyz):
    """Read ``rest2[s + f, col : col + 3W]`` for the L frames of a block (past nf: frame nf - 1
    again) into xyz (3W rows (3t + c), L frame lanes): the inverse of ``_tile_to_frames``."""
    def codegen(context, builder, signature, args):
        src = _Rows(context, builder, signature.args[0], args[0], native=True)
        x = _Rows(context, builder, signature.args[4], args[4], native=True)
        L, W = x.L, x.W
        row_length = src.row_length()
        last = builder.sub(args[2], _const(1))
        for h in range(L // W):
            rows = [[None] * W for _ in range(3)]
            for k in range(W):
                f = builder.select(builder.icmp_signed("<", _const(h * W + k), args[2]), _const(h * W + k), last)
                start = builder.add(builder.mul(builder.add(args[1], f), row_length), args[3])
                for q in range(3):
                    rows[q][k] = src.load(builder.add(start, _const(q * W)))
            for q in range(3):
                for k, v in enumerate(_transpose(builder, rows[q])):
                    x.store(v, _const((q * W + k) * L + h * W))
        return context.get_dummy_value()
    return types.void(rest2, s, nf, col, xyz), codegen


def _copy_rows_intrinsic(nontemporal: bool):
    def copy_rows(typingctx, staging, out2, s, nf, col, n):
        """``out2[s + f, col : col + n] = staging[f, :n]`` for the frames f < nf. With
        ``nontemporal``, the whole 64-byte lines of each run are written by streaming stores
        (no read of the line first, no cache pollution; the unaligned load from the L1 staging
        row does the realignment) and the partial lines at both ends by plain stores; a fence at
        the end orders the streaming stores before any later access."""
        def codegen(context, builder, signature, args):
            st = _Rows(context, builder, signature.args[0], args[0], native=True)
            o = _Rows(context, builder, signature.args[1], args[1], native=True)
            W, item = st.W, st.align
            elem = st.vec.element
            s_len, o_len = st.row_length(), o.row_length()
            n = args[5]
            with cgutils.for_range(builder, args[3]) as loop:
                f = loop.index
                src = builder.gep(st.array.data, [builder.mul(f, s_len)])
                dst = builder.gep(o.array.data, [builder.add(builder.mul(builder.add(args[2], f), o_len), args[4])])
                if nontemporal:
                    address = builder.ptrtoint(dst, _I64)
                    head = builder.udiv(builder.and_(builder.sub(_const(0), address), _const(VECTOR_BYTES - 1)),
                                        _const(item))
                    head = builder.select(builder.icmp_signed("<", n, head), n, head)
                else:
                    head = _const(0)
                body = builder.sdiv(builder.sub(n, head), _const(W))
                with cgutils.for_range(builder, head) as h:
                    builder.store(builder.load(builder.gep(src, [h.index])), builder.gep(dst, [h.index]))
                with cgutils.for_range(builder, body) as b:
                    k = builder.add(head, builder.mul(b.index, _const(W)))
                    v = builder.load(builder.bitcast(builder.gep(src, [k]), st.vec.as_pointer()), align=item)
                    store = builder.store(v, builder.bitcast(builder.gep(dst, [k]), st.vec.as_pointer()),
                                          align=VECTOR_BYTES if nontemporal else item)
                    if nontemporal:
                        store.set_metadata("nontemporal", builder.module.add_metadata([ir.Constant(ir.IntType(32), 1)]))
                done = builder.add(head, builder.mul(body, _const(W)))
                with cgutils.for_range(builder, builder.sub(n, done)) as t:
                    e = builder.add(done, t.index)
                    builder.store(builder.load(builder.gep(src, [e])), builder.gep(dst, [e]))
            if nontemporal:
                builder.fence("seq_cst")
            return context.get_dummy_value()
        return types.void(staging, out2, s, nf, col, n), codegen
    return intrinsic(copy_rows)


_copy_rows = _copy_rows_intrinsic(False)
_stream_rows = _copy_rows_intrinsic(True)


def _lane_ranges(N: int, V: int, lanes: int | None, L: int) -> list[tuple[int, int, int, int]]:
    """Work split: [(n0, n1, i0, i1)], one range per lane; two lanes take the halves of the
    frames (whole blocks of L on the first), or of the vertices for one frame."""
    if lanes is None:
        lanes = 2 if N * V >= _TWO_LANES_MIN_WORK else 1
    if lanes not in (1, 2):
        raise ParameterError(f"lanes={lanes!r}; expected 1, 2 or None (automatic)")
    if lanes == 1:
        return [(0, N, 0, V)]
    if N >= 2:
        (_, m), _ = halves(N)
        if m > L:
            m -= m % L
        return [(0, m, 0, V), (m, N, 0, V)]
    (a0, a1), (b0, b1) = halves(V)
    return [(0, N, a0, a1), (0, N, b0, b1)]


def _skin(kernel, n_rows: int, head: tuple, G, v, out, lanes) -> np.ndarray:
    """Run ``kernel(*head, G, rest, rest2, out, out2, table, acc, xyz, tile, n0, n1, i0, i1,
    check)`` over the lanes' ranges (two lanes: side by side) in the output's dtype, and raise
    when a rest coordinate was not finite. n_rows: 12 (LBS) or 8 (DQS) table rows a bone."""
    N, B = G.shape[:2]
    V = v.shape[1]
    dtype = out.dtype
    L, W = frame_block(dtype), vector_lanes(dtype)
    rest = np.ascontiguousarray(v, dtype=dtype)
    # the kernels write (N, 3V) rows; a non-contiguous ``out`` gets them through a buffer
    target = out if out.flags.c_contiguous else np.empty(out.shape, dtype)
    ranges = _lane_ranges(N, V, lanes, L)
    stream = out.nbytes >= STREAM_MIN_BYTES
    checks = [np.zeros((3 * W, L), dtype) for _ in ranges]
    args = (*head, G, rest, rest.reshape(rest.shape[0], 3 * V), target, target.reshape(N, 3 * V))

    def lane(k):
        buffers = (np.zeros((B, n_rows, L), dtype), np.zeros((12, L), dtype), np.zeros((3 * W, L), dtype),
                   np.zeros((3 * W, L), dtype), np.zeros((L, 3 * W * STAGED_TILES), dtype))
        kernel(*args, *buffers, stream, *ranges[k], checks[k])
    if len(ranges) == 1:
        lane(0)
    else:
        run_both(lambda: lane(0), lambda: lane(1))
    if target is not out:
        out[...] = target
    if any(c.any() for c in checks) or (len(rest) == 1 and not np.isfinite(rest).all()):
        raise MeshError("vertices: NaN or infinity found in the rest vertices; expected finite coordinates "
                        "(the output holds NaN where they were)")
    return out


@intrinsic
def _check_rows(typingctx, check, xyz):
    """``check += 0 * xyz`` over the whole (3W, L) buffers, in vectors: check stays zero unless
    a coordinate read into xyz was NaN or infinite."""
    def codegen(context, builder, signature, args):
        c = _Rows(context, builder, signature.args[0], args[0])
        x = _Rows(context, builder, signature.args[1], args[1])
        zero = ir.Constant(c.vec, None)
        for r in range(3 * c.W):
            off = _const(r * c.L)
            c.store(builder.fadd(c.load(off), builder.fmul(zero, x.load(off))), off)
        return context.get_dummy_value()
    return types.void(check, xyz), codegen


@_inline
def _rest_tile(rest, rest2, s, nf, a, tv, xyz, check):
    """Rest vertices a:a+tv of frames s:s+nf into xyz (3W, L) (rows 3t + c, frames in lanes;
    lanes past nf repeat frame nf - 1). Per-body rest vertices are checked here (``check``),
    a shared rest (1, V, 3) once by the caller."""
    L = xyz.shape[1]
    if rest.shape[0] == 1:
        for t in range(tv):
            for c in range(3):
                v = rest[0, a + t, c]
                row = xyz[3 * t + c]
                for f in range(L):
                    row[f] = v
        return
    if tv * 3 == xyz.shape[0]:
        _frames_to_tile(rest2, s, nf, 3 * a, xyz)
    else:
        for t in range(tv):
            for c in range(3):
                row = xyz[3 * t + c]
                for f in range(L):
                    row[f] = rest[s + min(f, nf - 1), a + t, c]
    _check_rows(check, xyz)


@_inline
def _write_tile(tile, staging, out, out2, s, nf, a, tv, i0, i1, stream):
    """The tile's posed vertices a:a+tv, frames s:s+nf, out: a full tile goes to its slot of the
    staging rows (L, 3 W C), transposed; when the C slots are full or the range ends, the
    staged runs are copied to out2 (the (N, 3V) view of out), streaming when ``stream``. A
    partial tile (the range's last) is written directly."""
    W = tile.shape[0] // 3
    C = staging.shape[1] // (3 * W)
    k = (a - i0) // W % C
    if tv == W:
        _tile_to_frames(tile, staging, 0, nf, 3 * W * k)
        k += 1
        if k < C and a + W < i1:
            return
        start = a - (k - 1) * W
    else:
        for f in range(nf):
            for t in range(tv):
                for c in range(3):
                    out[s + f, a + t, c] = tile[3 * t + c, f]
        if k == 0:
            return
        start = a - k * W
    if stream:
        _stream_rows(staging, out2, s, nf, 3 * start, 3 * W * k)
    else:
        _copy_rows(staging, out2, s, nf, 3 * start, 3 * W * k)


# ------------------------------------------------------------------------------- LBS kernel

@_inline
def _lbs_blend(acc, table, indices, data, p0, p1):
    """acc (12, L) = sum over the row's influences p0:p1 of w (G_b - I): a first pass of up to
    four bones, then passes of 4, 3, 2 or 1 (each influence read exactly once)."""
    n = p1 - p0
    if n >= 4:
        _lbs_blend_set(acc, table, (indices[p0], indices[p0 + 1], indices[p0 + 2], indices[p0 + 3]),
                       (data[p0], data[p0 + 1], data[p0 + 2], data[p0 + 3]))
        k = p0 + 4
        while k < p1:
            m = p1 - k
            if m >= 4:
                _lbs_blend_add(acc, table, (indices[k], indices[k + 1], indices[k + 2], indices[k + 3]),
                               (data[k], data[k + 1], data[k + 2], data[k + 3]))
                k += 4
            elif m == 3:
                _lbs_blend_add(acc, table, (indices[k], indices[k + 1], indices[k + 2]),
                               (data[k], data[k + 1], data[k + 2]))
                k += 3
            elif m == 2:
                _lbs_blend_add(acc, table, (indices[k], indices[k + 1]), (data[k], data[k + 1]))
                k += 2
            else:
                _lbs_blend_add(acc, table, (indices[k],), (data[k],))
                k += 1
    elif n == 3:
        _lbs_blend_set(acc, table, (indices[p0], indices[p0 + 1], indices[p0 + 2]), (data[p0], data[p0 + 1], data[p0 + 2]))
    elif n == 2:
        _lbs_blend_set(acc, table, (indices[p0], indices[p0 + 1]), (data[p0], data[p0 + 1]))
    else:
        _lbs_blend_set(acc, table, (indices[p0],), (data[p0],))


@_kernel
def _lbs_kernel(indptr, indices, data, G, rest, rest2, out, out2, table, acc, xyz, tile, staging, stream, n0, n1,
                i0, i1, check):
    """``out[n, i] = v + sum_k w_k (G_{b_k} - I) [v; 1]`` for frames n0:n1 and vertices i0:i1.

    indptr/indices/data: the weights' CSR arrays (data in the output dtype); G (N, B, 4, 4);
    rest (1 or N, V, 3) and rest2 its (1 or N, 3V) view; out (N, V, 3) and out2 its (N, 3V)
    view; buffers table (B, 12, L), acc (12, L), xyz and tile (3W, L); check (3W, L), see
    ``_rest_tile``. Empty rows of the weights (no bone) are not allowed (rows sum to one).
    """
    B, L, W = G.shape[1], table.shape[2], xyz.shape[0] // 3
    for s in range(n0, n1, L):
        nf = min(L, n1 - s)
        for b in range(B):
            for r in range(3):
                for c in range(4):
                    row, d = table[b, 4 * r + c], (1.0 if r == c else 0.0)
                    for f in range(nf):
                        row[f] = G[s + f, b, r, c] - d
                    for f in range(nf, L):
                        row[f] = 0.0
        for a in range(i0, i1, W):
            tv = min(W, i1 - a)
            _rest_tile(rest, rest2, s, nf, a, tv, xyz, check)
            for t in range(tv):
                p0, p1 = indptr[a + t], indptr[a + t + 1]
                n = p1 - p0
                if n == 1:
                    _lbs_vertex(table, (indices[p0],), (data[p0],), xyz, tile, t)
                elif n == 2:
                    _lbs_vertex(table, (indices[p0], indices[p0 + 1]), (data[p0], data[p0 + 1]), xyz, tile, t)
                elif n == 3:
                    _lbs_vertex(table, (indices[p0], indices[p0 + 1], indices[p0 + 2]),
                                (data[p0], data[p0 + 1], data[p0 + 2]), xyz, tile, t)
                elif n == 4:
                    _lbs_vertex(table, (indices[p0], indices[p0 + 1], indices[p0 + 2], indices[p0 + 3]),
                                (data[p0], data[p0 + 1], data[p0 + 2], data[p0 + 3]), xyz, tile, t)
                else:
                    _lbs_blend(acc, table, indices, data, p0, p1)
                    _apply(acc, xyz, tile, t)
            _write_tile(tile, staging, out, out2, s, nf, a, tv, i0, i1, stream)


def linear_blend_skinning(vertices: np.ndarray, weights: sp.spmatrix | np.ndarray, transforms: np.ndarray, *,
                          dtype=np.float64, out: np.ndarray | None = None, lanes: int | None = None) -> np.ndarray:
    """Linear blend skinning: ``v'_i = v_i + (sum_b w_ib (G_b - I)) [v_i; 1]``, compiled.

    vertices: (N, V, 3) rest vertices per body, or (V, 3) shared by every frame.
    weights: (V, B) skin weights (sparse or dense), finite, rows summing to one.
    transforms: (N, B, 4, 4) bone transforms (``forward_kinematics``).
    dtype: float64 (default) or float32 output; the arithmetic is done in that dtype (float32:
        within 1e-6 of the float64 result relative to the mesh's extent, about twice as fast).
    out: optional (N, V, 3) float64 or float32 array (e.g. a ``np.memmap``) to write into; its
        dtype sets the arithmetic's.
    lanes: 1 or 2 threads; None: two when the call has >= 200,000 vertex-frames.
    Returns (N, V, 3) posed vertices (``out`` when given).
    """
    G, v, out = _batch_inputs(vertices, transforms, dtype, out)
    N, B = G.shape[:2]
    indptr, indices, data = csr_skin_weights(weights, v.shape[1], B)
    return _skin(_lbs_kernel, 12, (indptr, indices, data.astype(out.dtype)), G, v, out, lanes)


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


@_inline
def _dqs_blend(acc, table, pivot, indices, data, p0, p1):
    """acc rows 0-7 = sum over the row's influences of s w (q, q'), s the antipodal sign:
    passes of 4, 3, 2 or 1 bones as ``_lbs_blend``."""
    n = p1 - p0
    if n >= 4:
        _dqs_blend_set(acc, table, pivot, (indices[p0], indices[p0 + 1], indices[p0 + 2], indices[p0 + 3]),
                       (data[p0], data[p0 + 1], data[p0 + 2], data[p0 + 3]))
        k = p0 + 4
        while k < p1:
            m = p1 - k
            if m >= 4:
                _dqs_blend_add(acc, table, pivot, (indices[k], indices[k + 1], indices[k + 2], indices[k + 3]),
                               (data[k], data[k + 1], data[k + 2], data[k + 3]))
                k += 4
            elif m == 3:
                _dqs_blend_add(acc, table, pivot, (indices[k], indices[k + 1], indices[k + 2]),
                               (data[k], data[k + 1], data[k + 2]))
                k += 3
            elif m == 2:
                _dqs_blend_add(acc, table, pivot, (indices[k], indices[k + 1]), (data[k], data[k + 1]))
                k += 2
            else:
                _dqs_blend_add(acc, table, pivot, (indices[k],), (data[k],))
                k += 1
    elif n == 3:
        _dqs_blend_set(acc, table, pivot, (indices[p0], indices[p0 + 1], indices[p0 + 2]),
                       (data[p0], data[p0 + 1], data[p0 + 2]))
    elif n == 2:
        _dqs_blend_set(acc, table, pivot, (indices[p0], indices[p0 + 1]), (data[p0], data[p0 + 1]))
    else:
        _dqs_blend_set(acc, table, pivot, (indices[p0],), (data[p0],))


@_kernel
def _dqs_kernel(indptr, indices, data, pivot, G, rest, rest2, out, out2, table, acc, xyz, tile, staging, stream, n0,
                n1, i0, i1, check):
    """Dual-quaternion skinning of frames n0:n1, vertices i0:i1 (``dual_quaternion_skinning``).

    Arguments as ``_lbs_kernel``, table (B, 8, L); pivot (V,): each vertex's heaviest bone. Per
    vertex and frame lane: each bone's dual quaternion, flipped into the pivot's hemisphere,
    is weighted and summed; the sum is normalized and applied as the rigid motion
    ``v' = v + (R(q) - I) v + t`` (``_dual_quaternion_rows``).
    """
    B, L, W = G.shape[1], table.shape[2], xyz.shape[0] // 3
    for s in range(n0, n1, L):
        nf = min(L, n1 - s)
        for b in range(B):
            for f in range(L):
                if f < nf:
                    _dual_quaternion(G, s + f, b, table, f)
                else:                        # frames past the end: identity
                    for j in range(8):
                        table[b, j, f] = 1.0 if j == 0 else 0.0
        for a in range(i0, i1, W):
            tv = min(W, i1 - a)
            _rest_tile(rest, rest2, s, nf, a, tv, xyz, check)
            for t in range(tv):
                i = a + t
                p0, p1, p = indptr[i], indptr[i + 1], pivot[i]
                n = p1 - p0
                if n == 1:
                    _dqs_vertex(table, p, (indices[p0],), (data[p0],), xyz, tile, t)
                elif n == 2:
                    _dqs_vertex(table, p, (indices[p0], indices[p0 + 1]), (data[p0], data[p0 + 1]), xyz, tile, t)
                elif n == 3:
                    _dqs_vertex(table, p, (indices[p0], indices[p0 + 1], indices[p0 + 2]),
                                (data[p0], data[p0 + 1], data[p0 + 2]), xyz, tile, t)
                elif n == 4:
                    _dqs_vertex(table, p, (indices[p0], indices[p0 + 1], indices[p0 + 2], indices[p0 + 3]),
                                (data[p0], data[p0 + 1], data[p0 + 2], data[p0 + 3]), xyz, tile, t)
                else:
                    _dqs_blend(acc, table, p, indices, data, p0, p1)
                    _dual_quaternion_rows(acc)
                    _apply(acc, xyz, tile, t)
            _write_tile(tile, staging, out, out2, s, nf, a, tv, i0, i1, stream)


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
    dtype, out, lanes: as ``linear_blend_skinning`` (float32: the dual quaternions are formed
        in float64, then blended, normalized and applied in float32).
    Returns (N, V, 3) posed vertices (``out`` when given).

    Per vertex, each bone's dual quaternion is flipped into the hemisphere of the vertex's
    heaviest bone, weighted, summed, normalized and applied as a rigid motion; all ``G_b = I``
    returns the input bit for bit.
    """
    G, v, out = _batch_inputs(vertices, transforms, dtype, out)
    N, B = G.shape[:2]
    indptr, indices, data = csr_skin_weights(weights, v.shape[1], B)
    pivot = _row_pivots(indptr, indices, data)
    return _skin(_dqs_kernel, 8, (indptr, indices, data.astype(out.dtype), pivot), G, v, out, lanes)
