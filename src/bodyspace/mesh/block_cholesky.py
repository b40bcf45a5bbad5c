"""Sparse Cholesky factorization of SPD matrices made of 3x3 blocks on a fixed pattern.

The Hasler Equation 9 rotation system of the relative rotation encoding (``encoding.rre``) has one 3x3
block per pair of adjacent triangles: its values change with every body, its pattern never.
So the ordering and the symbolic analysis (elimination tree, the pattern of L) are done once
per template, and each body pays only the numeric factorization, in compiled code (numba)
that works on whole 3x3 blocks: one index lookup per 27 multiply-adds instead of one per
multiply-add for a scalar factorization of the same matrix (qdldl, the previous method, took
~92 ms a body on the 26,756-face template; see docs/encoding.md).

Method: a left-looking block Cholesky ``P A P^T = L L^T`` (L block lower triangular with
lower-triangular 3x3 diagonal blocks). Column j of L gathers the updates
``A_ij - sum_k L_ik L_jk^T`` from the columns k < j that have a block in row j (the row
pattern of L, precomputed with the position of each such block) into a dense per-row work
array, factors its 3x3 pivot and scales the column. The ordering is SuperLU's minimum degree
on the block graph.

Two lanes (``bodyspace.parallel``): the elimination tree is cut into two disjoint subtrees of
nearly equal work and a "top" closed under taking parents. A column depends only on its
descendants, so the two subtrees are factored side by side on two threads (each with its own
work array), then the top on one. The triangular solves split the same way.
"""

from __future__ import annotations

import numba
import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as sla

from bodyspace.errors import MeshError
from bodyspace.parallel import run_both

# ``contract``: multiply-adds may fuse into FMA instructions (no other reassociation); 10%
# faster factorization, results differ from unfused ones in the last bit (measured).
_kernel = numba.njit(cache=True, nogil=True, fastmath={"contract"})


@_kernel
def _subtract_column_update(p0, end, li, lx, loc, w, base):
    """``w -= L_ik L_jk^T`` for the entries ``p0:end`` of source column k, whose first is its
    block in row j: the pivot's lower triangle at ``w[base]``, row i's block at
    ``w[base + loc[i]]``. The inner loop of the factorization (27 multiply-adds a block)."""
    a00, a01, a02 = lx[p0, 0, 0], lx[p0, 0, 1], lx[p0, 0, 2]
    a10, a11, a12 = lx[p0, 1, 0], lx[p0, 1, 1], lx[p0, 1, 2]
    a20, a21, a22 = lx[p0, 2, 0], lx[p0, 2, 1], lx[p0, 2, 2]
    w[base, 0, 0] -= a00 * a00 + a01 * a01 + a02 * a02
    w[base, 1, 0] -= a10 * a00 + a11 * a01 + a12 * a02
    w[base, 1, 1] -= a10 * a10 + a11 * a11 + a12 * a12
    w[base, 2, 0] -= a20 * a00 + a21 * a01 + a22 * a02
    w[base, 2, 1] -= a20 * a10 + a21 * a11 + a22 * a12
    w[base, 2, 2] -= a20 * a20 + a21 * a21 + a22 * a22
    for p in range(p0 + 1, end):
        m = base + loc[li[p]]
        for r in range(3):
            b0, b1, b2 = lx[p, r, 0], lx[p, r, 1], lx[p, r, 2]
            w[m, r, 0] -= b0 * a00 + b1 * a01 + b2 * a02
            w[m, r, 1] -= b0 * a10 + b1 * a11 + b2 * a12
            w[m, r, 2] -= b0 * a20 + b1 * a21 + b2 * a22


@_kernel
def _factor_columns(cols, lp, li, rp, rk, rpos, diag, lx, linv, w, loc, lane_of, only, done, done_start,
                    x, top_pos, acc):
    """Factor the block columns ``cols`` (increasing) of L in place.

    ``lx`` (nnz, 3, 3) holds A's strictly lower blocks (zero at fill) on entry and L's on
    return (columns ``cols`` only); ``diag`` (n, 3, 3) A's diagonal blocks; ``linv`` (n, 3, 3)
    receives the inverse of each lower-triangular pivot factor. With ``only >= 0``, updates
    come only from columns k with ``lane_of[k] == only``; the others' were summed beforehand
    (negated) by ``_top_updates`` into ``done`` (2, S, 3, 3), column ``cols[jj]``'s from slot
    ``done_start[jj]`` on, and are added here. Scratch: ``w`` (m + 1, 3, 3)
    with m the longest column, the column being built (slot 0 its pivot, then its rows in
    order), and ``loc`` (n,) int, each row's slot in w: a compact w stays in the L1 cache
    where one indexed by row (n blocks) did not (measured 1.3x slower).

    With ``x`` (n, 3, 3) non-empty, each column also takes its step of the forward solve
    ``L y = x`` (in place) while it is in the cache, as ``_forward_columns`` does (``top_pos``,
    ``acc``: where updates of top rows go); the separate forward pass then is not needed.
    Returns -1, or the first column whose pivot is not positive definite.
    """
    for jj in range(len(cols)):
        j = cols[jj]
        for r in range(3):
            for c in range(3):
                w[0, r, c] = diag[j, r, c]
        start = lp[j]
        for p in range(start, lp[j + 1]):
            loc[li[p]] = p - start + 1
            for r in range(3):
                for c in range(3):
                    w[p - start + 1, r, c] = lx[p, r, c]
        if only >= 0:
            base = done_start[jj]
            for m in range(lp[j + 1] - start + 1):
                for r in range(3):
                    for c in range(3):
                        w[m, r, c] += done[0, base + m, r, c] + done[1, base + m, r, c]
        for q in range(rp[j], rp[j + 1]):
            k = rk[q]
            if only < 0 or lane_of[k] == only:
                _subtract_column_update(rpos[q], lp[k + 1], li, lx, loc, w, 0)
        # 3x3 Cholesky of the pivot, then its inverse (lower triangular)
        d0 = w[0, 0, 0]
        if not d0 > 0.0:
            return j
        l00 = np.sqrt(d0)
        l10 = w[0, 1, 0] / l00
        l20 = w[0, 2, 0] / l00
        d1 = w[0, 1, 1] - l10 * l10
        if not d1 > 0.0:
            return j
        l11 = np.sqrt(d1)
        l21 = (w[0, 2, 1] - l20 * l10) / l11
        d2 = w[0, 2, 2] - l20 * l20 - l21 * l21
        if not d2 > 0.0:
            return j
        l22 = np.sqrt(d2)
        i00, i11, i22 = 1.0 / l00, 1.0 / l11, 1.0 / l22
        i10 = -l10 * i00 * i11
        i21 = -l21 * i11 * i22
        i20 = -(l20 * i00 + l21 * i10) * i22
        v = linv[j]
        v[0, 0], v[0, 1], v[0, 2] = i00, 0.0, 0.0
        v[1, 0], v[1, 1], v[1, 2] = i10, i11, 0.0
        v[2, 0], v[2, 1], v[2, 2] = i20, i21, i22
        for p in range(start, lp[j + 1]):  # L_ij = W_i L_jj^-T
            m = p - start + 1
            for r in range(3):
                b0, b1, b2 = w[m, r, 0], w[m, r, 1], w[m, r, 2]
                lx[p, r, 0] = b0 * i00
                lx[p, r, 1] = b0 * i10 + b1 * i11
                lx[p, r, 2] = b0 * i20 + b1 * i21 + b2 * i22
        if x.shape[0]:
            _forward_step(j, lp, li, lx, linv, x, top_pos, acc)
    return -1


@_kernel
def _top_updates(top, lane, lane_of, lp, li, rp, rk, rpos, lx, done_start, done, loc):
    """Sum, for each top column j, minus the updates ``L_ik L_jk^T`` from this lane's columns
    k (factored already) into ``done`` (S, 3, 3) from slot ``done_start[jj]`` on (slot 0 the
    pivot's lower triangle, then j's rows in order). Run by both lanes side by side, so the
    work leaving a column is done in its own lane and the top's factorization is left with the
    updates among top columns only."""
    for jj in range(len(top)):
        j, base, start = top[jj], done_start[jj], lp[top[jj]]
        for p in range(start, lp[j + 1]):
            loc[li[p]] = p - start + 1
        for m in range(lp[j + 1] - start + 1):
            done[base + m] = 0.0
        for q in range(rp[j], rp[j + 1]):
            k = rk[q]
            if lane_of[k] == lane:
                _subtract_column_update(rpos[q], lp[k + 1], li, lx, loc, done, base)


@_kernel
def _forward_step(j, lp, li, lx, linv, x, top_pos, acc):
    """Column j's step of ``L y = b`` in place in x (n, 3, 3): ``y_j = L_jj^-1 x_j``, then
    ``x_i -= L_ij y_j`` for its rows; three right-hand sides, held in scalars. Updates of rows
    with ``top_pos[i] >= 0`` go to ``acc[top_pos[i]]`` (added, to be subtracted later) instead
    of x, so two lanes never write the same row; with ``top_pos`` all -1 every update goes to
    x."""
    m = linv[j]
    x0, x1, x2 = x[j, 0, 0], x[j, 0, 1], x[j, 0, 2]
    z0, z1, z2 = x[j, 1, 0], x[j, 1, 1], x[j, 1, 2]
    w0, w1, w2 = x[j, 2, 0], x[j, 2, 1], x[j, 2, 2]
    y00, y01, y02 = m[0, 0] * x0, m[0, 0] * x1, m[0, 0] * x2
    y10, y11, y12 = m[1, 0] * x0 + m[1, 1] * z0, m[1, 0] * x1 + m[1, 1] * z1, m[1, 0] * x2 + m[1, 1] * z2
    y20 = m[2, 0] * x0 + m[2, 1] * z0 + m[2, 2] * w0
    y21 = m[2, 0] * x1 + m[2, 1] * z1 + m[2, 2] * w1
    y22 = m[2, 0] * x2 + m[2, 1] * z2 + m[2, 2] * w2
    x[j, 0, 0], x[j, 0, 1], x[j, 0, 2] = y00, y01, y02
    x[j, 1, 0], x[j, 1, 1], x[j, 1, 2] = y10, y11, y12
    x[j, 2, 0], x[j, 2, 1], x[j, 2, 2] = y20, y21, y22
    for p in range(lp[j], lp[j + 1]):
        i = li[p]
        t = top_pos[i]
        for r in range(3):
            b0, b1, b2 = lx[p, r, 0], lx[p, r, 1], lx[p, r, 2]
            v0 = b0 * y00 + b1 * y10 + b2 * y20
            v1 = b0 * y01 + b1 * y11 + b2 * y21
            v2 = b0 * y02 + b1 * y12 + b2 * y22
            if t >= 0:
                acc[t, r, 0] += v0
                acc[t, r, 1] += v1
                acc[t, r, 2] += v2
            else:
                x[i, r, 0] -= v0
                x[i, r, 1] -= v1
                x[i, r, 2] -= v2


@_kernel
def _forward_columns(cols, lp, li, lx, linv, x, top_pos, acc):
    """``L y = b`` over the block columns ``cols`` (increasing), in place in x (n, 3, 3)
    (``_forward_step`` for each)."""
    for jj in range(len(cols)):
        _forward_step(cols[jj], lp, li, lx, linv, x, top_pos, acc)


@_kernel
def _backward_columns(cols, lp, li, lx, linv, x):
    """``L^T x = y`` over the block columns ``cols`` (taken in decreasing order), in place in
    x (n, 3, 3): each column reads rows above it in the tree (final by then), writes its own."""
    for jj in range(len(cols) - 1, -1, -1):
        j = cols[jj]
        s00, s01, s02 = x[j, 0, 0], x[j, 0, 1], x[j, 0, 2]
        s10, s11, s12 = x[j, 1, 0], x[j, 1, 1], x[j, 1, 2]
        s20, s21, s22 = x[j, 2, 0], x[j, 2, 1], x[j, 2, 2]
        for p in range(lp[j], lp[j + 1]):  # s -= L_ij^T x_i
            i = li[p]
            for r in range(3):
                b0, b1, b2 = lx[p, r, 0], lx[p, r, 1], lx[p, r, 2]
                v0, v1, v2 = x[i, r, 0], x[i, r, 1], x[i, r, 2]
                s00 -= b0 * v0
                s01 -= b0 * v1
                s02 -= b0 * v2
                s10 -= b1 * v0
                s11 -= b1 * v1
                s12 -= b1 * v2
                s20 -= b2 * v0
                s21 -= b2 * v1
                s22 -= b2 * v2
        m = linv[j]  # x_j = L_jj^-T s (L_jj^-1 lower triangular)
        x[j, 0, 0] = m[0, 0] * s00 + m[1, 0] * s10 + m[2, 0] * s20
        x[j, 0, 1] = m[0, 0] * s01 + m[1, 0] * s11 + m[2, 0] * s21
        x[j, 0, 2] = m[0, 0] * s02 + m[1, 0] * s12 + m[2, 0] * s22
        x[j, 1, 0] = m[1, 1] * s10 + m[2, 1] * s20
        x[j, 1, 1] = m[1, 1] * s11 + m[2, 1] * s21
        x[j, 1, 2] = m[1, 1] * s12 + m[2, 1] * s22
        x[j, 2, 0] = m[2, 2] * s20
        x[j, 2, 1] = m[2, 2] * s21
        x[j, 2, 2] = m[2, 2] * s22


@_kernel
def _scatter_blocks(off, pos, flip, lx):
    """``lx[pos[e]] = off[e]`` (transposed where ``flip[e]``); lx (nnz, 3, 3) zeroed first."""
    lx[:] = 0.0
    for e in range(len(pos)):
        p = pos[e]
        for r in range(3):
            for c in range(3):
                lx[p, r, c] = off[e, c, r] if flip[e] else off[e, r, c]


def _symbolic(n: int, rows: np.ndarray, cols: np.ndarray) -> tuple[np.ndarray, np.ndarray, list]:
    """Elimination tree and pattern of L for the block pattern ``{rows[e], cols[e]}`` (already
    in elimination order): column j's rows are A's rows below j in column j plus its children's
    rows (minus j); its parent is its first row. Returns ``(parent (n,), counts (n,), the row
    sets)``."""
    lower = sp.csc_matrix((np.ones(len(rows)), (np.maximum(rows, cols), np.minimum(rows, cols))), shape=(n, n))
    lower.sort_indices()
    parent = np.full(n, -1, dtype=np.int64)
    pattern: list = [None] * n
    kids: list[list[int]] = [[] for _ in range(n)]
    for j in range(n):
        s = set(lower.indices[lower.indptr[j]:lower.indptr[j + 1]].tolist())
        for ch in kids[j]:
            s |= pattern[ch]
        s.discard(j)
        pattern[j] = s
        if s:
            parent[j] = min(s)
            kids[parent[j]].append(j)
    return parent, np.array([len(p) for p in pattern], dtype=np.int64), pattern


def split_elimination_tree(parent: np.ndarray, weight: np.ndarray,
                           balance: float = 0.52) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Cut an elimination tree into two lanes of independent subtrees and a top.

    Starting from the roots, the heaviest subtree of the frontier is opened (its root moves to
    the top, its children join the frontier) until the frontier's subtrees can be packed into
    two lanes, each with at most ``balance`` of their total weight.

    Args:
        parent: (n,) parent of each node, -1 at roots; ``parent[j] > j``.
        weight: (n,) work per node (e.g. flops of its column).
    Returns:
        ``(lane_a, lane_b, top)``, increasing node indices; a partition of ``0..n-1`` with top
        closed under parents and no node of one lane a descendant of the other's.
    """
    n = len(parent)
    subtree = weight.astype(float).copy()
    for j in range(n):  # children before parents (parent[j] > j)
        if parent[j] >= 0:
            subtree[parent[j]] += subtree[j]
    children: list[list[int]] = [[] for _ in range(n)]
    for j in range(n):
        if parent[j] >= 0:
            children[parent[j]].append(j)
    frontier = [j for j in range(n) if parent[j] < 0]
    top: list[int] = []
    while True:
        frontier.sort(key=lambda j: -subtree[j])
        loads, bins = [0.0, 0.0], ([], [])
        for j in frontier:
            side = 0 if loads[0] <= loads[1] else 1
            loads[side] += subtree[j]
            bins[side].append(j)
        total = loads[0] + loads[1]
        if not frontier or max(loads) <= balance * total or not children[frontier[0]]:
            break
        j = frontier.pop(0)
        top.append(j)
        frontier.extend(children[j])
    label = np.full(n, 2, dtype=np.int64)  # 2: top
    for side in (0, 1):
        stack = list(bins[side])
        while stack:
            j = stack.pop()
            label[j] = side
            stack.extend(children[j])
    return (np.flatnonzero(label == 0).astype(np.int64), np.flatnonzero(label == 1).astype(np.int64),
            np.flatnonzero(label == 2).astype(np.int64))


class BlockPattern:
    """Ordering and symbolic factorization of a 3x3-block SPD pattern, made once and shared.

    Args:
        n: number of block rows.
        rows, cols: (E,) the off-diagonal blocks of the pattern, one entry per unordered pair
            ``{rows[e], cols[e]}`` (``rows[e] != cols[e]``, no pair twice).

    ``BlockCholesky(pattern)`` holds one numeric factorization on it (one per thread).
    """

    def __init__(self, n: int, rows: np.ndarray, cols: np.ndarray):
        rows, cols = np.asarray(rows, dtype=np.int64), np.asarray(cols, dtype=np.int64)
        if rows.shape != cols.shape or rows.ndim != 1 or (rows == cols).any():
            raise MeshError("block pattern: rows and cols must be (E,) pairs of distinct block indices")
        if len(rows) and (min(rows.min(), cols.min()) < 0 or max(rows.max(), cols.max()) >= n):
            raise MeshError(f"block pattern: indices outside 0..{n - 1}")
        self.n = n
        self.n_pairs = len(rows)
        # Ordering: minimum degree on the block graph (SuperLU's, on a diagonally dominant
        # matrix with that pattern, so no pivoting changes it).
        graph = sp.coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(n, n)).tocsr()
        graph = ((graph + graph.T) > 0).astype(float)
        if graph.nnz != 2 * len(rows):
            raise MeshError("block pattern: a pair of blocks is listed twice")
        dominant = sp.diags(np.asarray(graph.sum(axis=1)).ravel() + 1.0) - graph
        lu = sla.splu(dominant.tocsc(), permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0,
                      options={"SymmetricMode": True})
        new = np.asarray(lu.perm_c, dtype=np.int64)  # new position of each block row
        # Two lanes, balanced by the work leaving each column (done in its own lane): its
        # multiply-adds plus a fixed cost per column (set-up, pivot, scaling) worth ~30 of them;
        # without that term the lane with more, smaller columns took 20% longer, with it the
        # two are within 1% (measured). Any order that keeps children before parents has the
        # same elimination tree and fill, so the columns are then renumbered lane A, lane B,
        # top: each lane's part of L lies together in memory (lane A 19 -> 15 ms, measured).
        parent, counts, _ = _symbolic(n, new[rows], new[cols])
        a, b, top = split_elimination_tree(parent, counts.astype(float) ** 2 + counts + 30)
        relabel = np.empty(n, dtype=np.int64)
        relabel[np.concatenate([a, b, top])] = np.arange(n)
        new = relabel[new]
        self.order = np.empty(n, dtype=np.int64)
        self.order[new] = np.arange(n)
        a_r, a_c = new[rows], new[cols]
        parent, counts, pattern = _symbolic(n, a_r, a_c)
        lo_r, lo_c = np.maximum(a_r, a_c), np.minimum(a_r, a_c)
        self.lp = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
        self.li = (np.concatenate([np.sort(np.fromiter(p, dtype=np.int64, count=len(p))) for p in pattern])
                   if self.lp[-1] else np.empty(0, dtype=np.int64))
        self.parent = parent
        self.nnz_blocks = int(self.lp[-1])
        self.longest = int(counts.max()) if n else 0
        na, nb = len(a), len(b)
        self.lanes = (np.arange(na), np.arange(na, na + nb), np.arange(na + nb, n))
        # Row pattern: for each row i, the columns k < i with a block L_ik and where it sits.
        col_of = np.repeat(np.arange(n), counts)
        by_row = np.lexsort((col_of, self.li))
        self.rk = col_of[by_row].astype(np.int64)
        self.rpos = by_row.astype(np.int64)
        self.rp = np.concatenate([[0], np.cumsum(np.bincount(self.li, minlength=n))]).astype(np.int64)
        # Where each given block lands in L's storage (transposed when it lies above the diagonal).
        key = self.li * n + col_of
        by_key = np.argsort(key, kind="stable")
        self.pos = by_key[np.searchsorted(key[by_key], lo_r * n + lo_c)].astype(np.int64)
        self.flip = a_r < a_c  # A[r, c] above the diagonal: L stores A[c, r] = A[r, c]^T
        # Index arrays the kernels walk as uint32: numba then knows them non-negative and drops
        # its negative-index wrap-around test from every access (13% faster factorization,
        # measured); top_pos keeps -1 for "not a top row".
        for name in ("lp", "li", "rk", "rpos", "rp", "pos"):
            setattr(self, name, getattr(self, name).astype(np.uint32))
        self.lanes = tuple(lane.astype(np.uint32) for lane in self.lanes)
        top = self.lanes[2]
        self.top_pos = np.full(n, -1, dtype=np.int64)
        self.top_pos[top] = np.arange(len(top))
        self.lane_of = np.full(n, 2, dtype=np.int64)
        self.lane_of[self.lanes[0]], self.lane_of[self.lanes[1]] = 0, 1
        top_sizes = counts[top] + 1
        self.done_start = np.concatenate([[0], np.cumsum(top_sizes)[:-1]]).astype(np.uint32)
        self.done_size = int(top_sizes.sum())
        self.no_top = np.full(n, -1, dtype=np.int64)
        self.all_columns = np.arange(n, dtype=np.uint32)


class BlockCholesky:
    """One numeric Cholesky factorization on a ``BlockPattern`` (buffers kept for reuse).

    ``factor(diag, off)`` takes the values: ``diag`` (n, 3, 3) the diagonal blocks, ``off``
    (E, 3, 3) the blocks ``A[rows[e], cols[e]]`` of the pattern's pairs (``A[cols[e], rows[e]]``
    is their transpose). ``solve(b)`` then solves ``A x = b`` for b (n, 3, 3). Not thread-safe:
    one object per thread.
    """

    def __init__(self, pattern: BlockPattern):
        self.pattern = pattern
        n = pattern.n
        self.lx = np.zeros((pattern.nnz_blocks, 3, 3))
        self.linv = np.zeros((n, 3, 3))
        self._work = [(np.empty((pattern.longest + 1, 3, 3)), np.zeros(n, dtype=np.uint32)) for _ in range(2)]
        self._done = np.zeros((2, pattern.done_size, 3, 3))

    def factor(self, diag: np.ndarray, off: np.ndarray, lanes: int = 1) -> None:
        """Numeric factorization of the matrix with diagonal blocks ``diag`` (n, 3, 3, original
        numbering) and off-diagonal blocks ``off`` (E, 3, 3, in the pattern's pair order).
        ``lanes=2``: on two threads. Raises MeshError if it is not positive definite."""
        self._factor(diag, off, lanes, None)

    def factor_solve(self, diag: np.ndarray, off: np.ndarray, b: np.ndarray, lanes: int = 1) -> np.ndarray:
        """``factor(diag, off)`` then ``solve(b)``, with the forward solve done column by column
        inside the factorization (one pass over L fewer)."""
        x = self._permuted(b)
        self._factor(diag, off, lanes, x)
        return self._backward(x, lanes)

    def solve(self, b: np.ndarray, lanes: int = 1) -> np.ndarray:
        """``x`` (n, 3, 3) with ``A x = b`` (n, 3, 3): three right-hand sides, for the last
        ``factor``. ``lanes=2``: on two threads."""
        pt = self.pattern
        x = self._permuted(b)
        factor = (pt.lp, pt.li, self.lx, self.linv)
        if lanes == 1:
            _forward_columns(pt.all_columns, *factor, x, pt.no_top, x[:0])
        else:
            a, c, top = pt.lanes
            acc = np.zeros((2, len(top), 3, 3))
            run_both(lambda: _forward_columns(a, *factor, x, pt.top_pos, acc[0]),
                     lambda: _forward_columns(c, *factor, x, pt.top_pos, acc[1]))
            x[top] -= acc[0] + acc[1]
            _forward_columns(top, *factor, x, pt.no_top, x[:0])
        return self._backward(x, lanes)

    def _permuted(self, b: np.ndarray) -> np.ndarray:
        pt = self.pattern
        b = np.asarray(b, dtype=float)
        if b.shape != (pt.n, 3, 3):
            raise MeshError(f"right-hand side: shape {b.shape}, expected ({pt.n}, 3, 3)")
        return np.ascontiguousarray(b[pt.order])

    def _factor(self, diag, off, lanes: int, x) -> None:
        """The factorization; with x (n, 3, 3, permuted) also the forward solve, in place."""
        pt = self.pattern
        diag = np.ascontiguousarray(np.asarray(diag, dtype=float)[pt.order])
        off = np.ascontiguousarray(off, dtype=float)
        if diag.shape != (pt.n, 3, 3) or off.shape != (pt.n_pairs, 3, 3):
            raise MeshError(f"block values: diag {diag.shape}, off {off.shape}, expected ({pt.n}, 3, 3) and "
                            f"({pt.n_pairs}, 3, 3)")
        _scatter_blocks(off, pt.pos, pt.flip, self.lx)
        structure = (pt.lp, pt.li, pt.rp, pt.rk, pt.rpos)
        args = structure + (diag, self.lx, self.linv)
        if x is None:
            x = np.empty((0, 3, 3))
        if lanes == 1:
            w, loc = self._work[0]
            bad = [_factor_columns(pt.all_columns, *args, w, loc, pt.lane_of, -1, self._done, pt.done_start,
                                   x, pt.no_top, x[:0])]
        else:
            a, b, top = pt.lanes
            acc = np.zeros((2, len(top), 3, 3))

            def lane(cols, side):
                w, loc = self._work[side]
                bad = _factor_columns(cols, *args, w, loc, pt.lane_of, -1, self._done, pt.done_start,
                                      x, pt.top_pos, acc[side])
                if bad < 0:
                    _top_updates(top, side, pt.lane_of, *structure, self.lx, pt.done_start, self._done[side], loc)
                return bad

            bad = list(run_both(lambda: lane(a, 0), lambda: lane(b, 1)))
            if max(bad) < 0:
                if len(x):
                    x[top] -= acc[0] + acc[1]
                w, loc = self._work[0]
                bad.append(_factor_columns(top, *args, w, loc, pt.lane_of, 2, self._done, pt.done_start,
                                           x, pt.no_top, x[:0]))
        if max(bad) >= 0:
            raise MeshError(f"block matrix: not positive definite at block row {int(pt.order[max(bad)])}")

    def _backward(self, x: np.ndarray, lanes: int) -> np.ndarray:
        """``L^T`` solve of the forward-solved x (permuted, in place); x in original order."""
        pt = self.pattern
        factor = (pt.lp, pt.li, self.lx, self.linv)
        if lanes == 1:
            _backward_columns(pt.all_columns, *factor, x)
        else:
            a, c, top = pt.lanes
            _backward_columns(top, *factor, x)
            run_both(lambda: _backward_columns(a, *factor, x), lambda: _backward_columns(c, *factor, x))
        out = np.empty_like(x)
        out[pt.order] = x
        return out
