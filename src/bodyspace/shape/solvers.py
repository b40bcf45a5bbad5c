"""PCA solvers for large code matrices: arrays in, ``(singular_values (k,), components (k, D))``
out, the centring applied inside the products so a float32 (N, D) matrix is never copied.

- ``pca_full``: exact, from the (N, N) Gram matrix (few scans, any width).
- ``pca_block_krylov``: randomized block Krylov (Musco and Musco 2015), what ``BodyModel.fit``
  uses beyond its exact-size limit.
- ``pca_randomized``: randomized subspace iteration (Halko, Martinsson and Tropp 2011, Alg.
  4.4), the previous solver, kept as the benchmark's baseline.
- ``mean_and_scatter``: column means and total scatter accumulated in float64.
- ``vertex_ordered_basis``: code-space directions ordered by the vertex-space variance they
  carry (``ShapeSpace(basis="vertex")``).
"""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from bodyspace.mesh.solver import single_threaded_blas
from bodyspace.rowfile import RowFile
from bodyspace.validation import as_generator

__all__ = ["pca_full", "pca_randomized", "pca_block_krylov", "mean_and_scatter", "vertex_ordered_basis"]

# The previous solver, randomized subspace iteration (Halko, Martinsson and Tropp 2011,
# Alg. 4.4; pca_randomized, kept as the benchmark's baseline): extra columns and power
# iterations.
RANDOMIZED_OVERSAMPLES = 10
RANDOMIZED_POWER_ITERATIONS = 2
# Block Krylov PCA (the solver beyond FULL_PCA_MAX_BYTES): blocks of the Krylov basis, and
# the basis size, 2 k + KRYLOV_OVERSAMPLES split over the blocks (70 columns a block for 100
# components; measured on 2,000 RRE codes in docs/encoding.md).
KRYLOV_DEPTH = 3
KRYLOV_OVERSAMPLES = 10
PRODUCT_CHUNKS_PER_JOB = 4
# Codes on disk (a ``RowFile``) are read in blocks of about this many bytes per thread: memory
# stays bounded whatever N (two threads hold ~130 MB of codes; 40 RRE codes a block).
DISK_BLOCK_BYTES = 64 << 20


def _row_block(x, a: int, b: int) -> np.ndarray:
    """Rows a..b of codes in memory (a view) or on disk (read)."""
    return x.read(a, b) if isinstance(x, RowFile) else x[a:b]


def _svd_wide(a: np.ndarray, rel_tol: float = 1e-10) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Thin SVD ``a = u diag(s) vt`` (float64) of a wide matrix (m, D), m << D.

    Through the Gram matrix ``a a^T`` (m x m, one BLAS product; numpy's SVD of a 144 x 401k
    matrix took 32 s, this ~0.5 s) and ``vt = u^T a / s`` (a second product). Squaring costs
    accuracy only in the weakest directions: a direction's error is ~``eps s_max^2 / s^2``, so
    directions with ``s^2 < rel_tol s_max^2`` are dropped (numerically no variance) and the rest
    are accurate to ~1e-6 or better, below the float32 rounding the model keeps components at.
    """
    g = a @ a.T
    lam, u = np.linalg.eigh(g)
    lam, u = lam[::-1], u[:, ::-1]
    keep = lam > rel_tol * max(lam[0], 1e-300)
    lam, u = lam[keep], u[:, keep]
    s = np.sqrt(lam)
    return u, s, (u.T @ a) / s[:, None]


def vertex_ordered_basis(codes: np.ndarray, code_mean: np.ndarray, vertices: np.ndarray
                         ) -> tuple[np.ndarray, np.ndarray]:
    """Orthonormal code-space directions whose leading k span the codes that make vertex PCA's
    leading k components, for every k.

    codes (N, D) float64, centred in place around ``code_mean`` (D,); vertices (N, M): the same
    bodies in vertex space (flattened, rigidly aligned), any centring. With the vertex PCA of the
    bodies ``Y = U diag(s) W^T`` (centred), the combination of the training codes with the
    weights ``U_k`` is the code of "vertex component k" in the training set's code span:
    ``b_k = C^T U_k``. A non-linear decoder (RRE) gives a body near ``mean + sum z_k W_k``
    for small ``z``; the code PCA instead orders its directions by code variance, which puts
    directions that move whole limbs (a few rotations at a joint) late. The ``b_k`` are
    orthonormalized in their order (QR; the span of the first k is kept) and sign-fixed. Code
    variance the vertices do not see (bodies equal up to a rigid motion, or codes of a lower
    rank in vertex space) follows as the code PCA of what is left, vertex variance 0, so the
    basis spans the codes as the code PCA does.
    Returns ``(components (K, D), vertex_variance (K,))``: K = the codes' numerical rank, and
    the vertex variance of vertex component k (``s_k^2 / (N - 1)``).
    """
    n = len(codes)
    codes -= code_mean
    y = np.asarray(vertices, dtype=np.float64)
    y = y - y.mean(axis=0)
    u, s, _ = _svd_wide(y)
    # In the codes' own coordinates, C = Uc diag(sc) Vc^T: b = Vc (diag(sc) Uc^T U), so every
    # orthonormalization below is of (r, K) matrices, never of (D, K) ones (x7 on 60 x 20k codes).
    uc, sc, vct = _svd_wide(codes)
    m = sc[:, None] * (uc.T @ u)                           # (r, K): the b_k in the Vc basis
    q, r = np.linalg.qr(m)
    diag = np.abs(np.diag(r))
    keep = diag > 1e-10 * max(diag.max(initial=0.0), 1e-300)   # a code combination already spanned
    q = q[:, keep]
    vertex_var = (s[keep] ** 2) / max(n - 1, 1)
    coords = uc * sc                                       # (N, r): the codes in the Vc basis
    rest = coords - (coords @ q) @ q.T
    _, rs, rvt = _svd_wide(rest)
    rvt = rvt[rs > 1e-5 * np.linalg.norm(sc)]              # only what the codes hold beyond the vertex order
    small = np.vstack([q.T, rvt - (rvt @ q) @ q.T])
    small /= np.linalg.norm(small, axis=1, keepdims=True)
    return _sign_flip(small @ vct), np.concatenate([vertex_var, np.zeros(len(rvt))])


def _sign_flip(vt: np.ndarray) -> np.ndarray:
    """scikit-learn's convention (as ``ShapeSpace.fit``): each row's largest |entry| positive."""
    signs = np.sign(vt[np.arange(len(vt)), np.argmax(np.abs(vt), axis=1)])
    signs[signs == 0] = 1.0
    return vt * signs[:, None]


def pca_full(x: np.ndarray, mean: np.ndarray, n_keep=None) -> tuple[np.ndarray, np.ndarray]:
    """Exact PCA of float64 codes x (N, D) around ``mean`` (D,); x is centred in place.

    Returns ``(singular_values (K,), components (k, D))``, K = numerical rank; ``n_keep(s)``
    (called with the K singular values, x already centred) says how many components k to form
    (default all K): only those are computed, so the output is not a second (N, D) matrix.
    """
    x -= mean
    g = x @ x.T  # as _svd_wide, with only the kept rows of vt formed
    lam, u = np.linalg.eigh(g)
    del g
    lam, u = lam[::-1], u[:, ::-1]
    rank = lam > 1e-10 * max(lam[0], 1e-300)
    lam, u = lam[rank], u[:, rank]
    s = np.sqrt(lam)
    k = len(s) if n_keep is None else int(n_keep(s))
    vt = (u[:, :k].T @ x) / s[:k, None]
    return s, _sign_flip(vt)


def pca_randomized(x: np.ndarray, mean: np.ndarray, k: int, rng=0,
                   n_iter: int = RANDOMIZED_POWER_ITERATIONS,
                   oversamples: int = RANDOMIZED_OVERSAMPLES) -> tuple[np.ndarray, np.ndarray]:
    """Leading ``k`` principal directions of codes x (N, D) (float32 ok) around ``mean`` (D,).

    Randomized range finder with power iterations (Halko et al. 2011, Alg. 4.4), orthonormalized
    on the small side (N x l) only; the centring is applied inside the products, so x is never
    copied. Cost: ``2 + 2 n_iter`` passes of an (N, D) x (D, l) product, l = k + oversamples.
    Returns ``(singular_values (k,), components (k, D))`` in float64.
    """
    n, d = x.shape
    l = min(n, k + oversamples)
    gen = as_generator(rng)
    dt = x.dtype
    mu = mean.astype(dt)

    def times(m):  # (x - mean) @ m, m (D, l)
        return x @ m - (mu @ m)[None]

    def times_t(y):  # (x - mean)^T @ y, y (N, l)
        return x.T @ y - np.outer(mu, y.sum(axis=0))

    y = times(gen.standard_normal((d, l)).astype(dt))
    for _ in range(n_iter):
        q, _ = np.linalg.qr(y.astype(np.float64))
        y = times(times_t(q.astype(dt)))
    q, _ = np.linalg.qr(y.astype(np.float64))
    b = times_t(q.astype(dt)).T.astype(np.float64)  # (l, D) = q^T (x - mean)
    _, s, vt = _svd_wide(b)
    return s[:k], _sign_flip(vt[:k])


def pca_block_krylov(x: np.ndarray, mean: np.ndarray, k: int, rng=0, depth: int = KRYLOV_DEPTH,
                     oversamples: int = KRYLOV_OVERSAMPLES,
                     n_jobs: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Leading ``k`` principal directions of codes x (N, D) (float32 ok, in memory or a
    ``RowFile`` on disk, read in row blocks) around ``mean`` (D,).

    Randomized block Krylov method (Musco and Musco 2015): with ``C = x - mean`` and a random
    start ``Y_0 = C G`` (G: D x l Gaussian, ``l = ceil((2 k + oversamples) / depth)``), each step
    orthonormalizes ``Y_i`` against the basis so far (block ``Q_i``, N x l), computes
    ``Z_i = C^T Q_i`` (D x l), and the next block ``Y_{i+1} = C Z_i``. The basis
    ``K = [Q_0 .. Q_{depth-1}]`` spans the Krylov space of ``C C^T`` from ``Y_0``, and
    the Rayleigh-Ritz matrix ``K^T C C^T K`` comes from the blocks' images ``C C^T Q_i``
    (and a small l x l product over D for the last block): ``2 depth`` products of
    (N, D) x (D, l) in all, and the components ``V = (K^T C)^T U / s`` from the already
    computed ``Q_i^T C``.
    Subspace iteration (``pca_randomized``, Halko et al. 2011, Alg. 4.4) keeps only its last
    block, so it needs wider blocks: on the 2,000 RRE codes of the benchmark, depth 3 with
    70-column blocks is more accurate for 100 components than 2 power iterations with 110
    columns, at 64% of the products (docs/encoding.md). The centring is applied inside the
    products, so x is never copied.
    Returns ``(singular_values (k,), components (k, D))`` in float64.
    """
    n, d = x.shape
    l = min(n, -(-(2 * k + oversamples) // depth))
    gen = as_generator(rng)
    dt = x.dtype
    mu = np.asarray(mean, dtype=dt)
    jobs = n_jobs or os.cpu_count() or 1
    on_disk = isinstance(x, RowFile)
    # The big products in PRODUCT_CHUNKS_PER_JOB pieces per thread, one BLAS thread each: on
    # the shared machine a multi-threaded BLAS call waits for its slowest (descheduled) thread,
    # while pieces from a queue go to whichever thread runs (measured below). Codes on disk are
    # cut into blocks of DISK_BLOCK_BYTES instead, so only a few blocks are ever in memory.
    pieces = -(-n * d * dt.itemsize // DISK_BLOCK_BYTES) if on_disk else PRODUCT_CHUNKS_PER_JOB * jobs
    row_cuts = np.linspace(0, n, min(n, max(pieces, PRODUCT_CHUNKS_PER_JOB * jobs)) + 1).astype(int)
    col_cuts = np.linspace(0, d, PRODUCT_CHUNKS_PER_JOB * jobs + 1).astype(int)

    def each(cuts, work):
        if jobs <= 1:
            for a, b in zip(cuts[:-1], cuts[1:]):
                work(a, b)
            return
        with single_threaded_blas(), ThreadPoolExecutor(jobs) as pool:
            for future in [pool.submit(work, a, b) for a, b in zip(cuts[:-1], cuts[1:])]:
                future.result()

    def times(m):  # (x - mean) @ m, m (D, l)
        out = np.empty((n, m.shape[1]), dtype=np.result_type(dt, m.dtype))

        def work(a, b):
            out[a:b] = _row_block(x, a, b) @ m
        each(row_cuts, work)
        return out - (mu @ m)[None]

    def t_times(y):  # y^T (x - mean), y (N, l); measured 1.3x faster than x^T @ y
        yt = np.ascontiguousarray(y.T)
        if on_disk:
            # Row blocks, each thread summing its own share into its own (l, D) total.
            totals = [np.zeros((yt.shape[0], d), dtype=np.result_type(dt, yt.dtype)) for _ in range(min(jobs, n))]
            cuts = list(zip(row_cuts[:-1], row_cuts[1:]))

            def share(j, _):
                for a, b in cuts[j::len(totals)]:
                    totals[j] += yt[:, a:b] @ x.read(a, b)
            each(np.arange(len(totals) + 1), share)
            out = totals[0]
            for other in totals[1:]:
                out += other
            del totals
        else:
            out = np.empty((yt.shape[0], d), dtype=np.result_type(x, y))

            def work(a, b):
                out[:, a:b] = yt @ x[:, a:b]
            each(col_cuts, work)
        out -= np.outer(yt.sum(axis=1), mu)
        return out

    start = gen.standard_normal((d, l), dtype=np.float32 if dt == np.float32 else np.float64)
    y = times(start).astype(np.float64)
    del start
    basis = np.zeros((n, 0))
    blocks, images = [], []
    for step in range(depth):
        width = min(l, n - basis.shape[1])
        if width <= 0:
            break
        # Householder QR of [basis, y]: the new columns are orthonormal and orthogonal to the
        # basis even where y has (numerically) lost rank against it. Small (N x L): one BLAS
        # thread (two threads spinning against a loaded machine measured 10x slower).
        with single_threaded_blas():
            full = np.linalg.qr(np.hstack([basis, y]))[0]
        q = full[:, basis.shape[1]:basis.shape[1] + width]
        basis = np.hstack([basis, q])
        blocks.append(t_times(q.astype(dt)))  # B_i = Q_i^T C (width, D)
        if step + 1 < depth and basis.shape[1] < n:
            y = times(blocks[-1].T).astype(np.float64)  # C C^T Q_i (N, width): the next block
            images.append(y)
    # Rayleigh-Ritz on the basis K: M = K^T C C^T K = B B^T (L x L). Its columns of block i <
    # last are K^T (C C^T Q_i), the images computed anyway; only the last block's diagonal
    # block B_last B_last^T is a product over D (small: width^2 D, in float64 by chunks).
    sizes = [len(bk) for bk in blocks]
    starts = np.concatenate([[0], np.cumsum(sizes)])
    ritz = np.zeros((starts[-1],) * 2)
    with single_threaded_blas():
        for i, image in enumerate(images):
            ritz[:, starts[i]:starts[i + 1]] = basis.T @ image
    last = len(images)
    if last < len(blocks):
        for i in range(last):
            ritz[starts[i]:starts[i + 1], starts[last]:] = ritz[starts[last]:, starts[i]:starts[i + 1]].T
        chunk = 1 << 16
        with single_threaded_blas():  # a 70 x 70 output: 2 BLAS threads measured 8x slower
            for s in range(0, d, chunk):
                bc = blocks[last][:, s:s + chunk].astype(np.float64)
                ritz[starts[last]:, starts[last]:] += bc @ bc.T
    with single_threaded_blas():
        lam, u = np.linalg.eigh(0.5 * (ritz + ritz.T))
    lam, u = lam[::-1][:k], u[:, ::-1][:, :k]
    sv = np.sqrt(np.maximum(lam, 0.0))
    # Components V = B^T U / s (k, D): one (k, L) x (L, D) product.
    comps = (u.T.astype(dt) @ np.concatenate(blocks, axis=0)).astype(np.float64)
    comps /= np.where(sv > 0, sv, 1.0)[:, None]
    return sv, _sign_flip(comps)


def mean_and_scatter(x: np.ndarray, block: int = 64) -> tuple[np.ndarray, float]:
    """Column means (D,) and total scatter ``sum |x_i - mean|^2`` of codes x (N, D) (an array
    or a ``RowFile``), both
    accumulated in float64 over row blocks (no float64 copy of a float32 x)."""
    total = np.zeros(x.shape[1])
    sq = 0.0
    if isinstance(x, RowFile):
        block = max(1, min(block, DISK_BLOCK_BYTES // max(1, x.shape[1] * x.dtype.itemsize)))
    for s in range(0, len(x), block):
        rows = _row_block(x, s, s + block)
        total += np.add.reduce(rows, axis=0, dtype=np.float64)
        sq += float(np.einsum("ij,ij->", rows, rows, dtype=np.float64))
    mean = total / len(x)
    # sum |x_i - m|^2 = sum |x_i|^2 - N |m|^2; the codes are relative to the encoder's mean
    # model, so |m| is small against the spread and the difference loses no precision.
    return mean, max(sq - len(x) * float(mean @ mean), 0.0)
