"""Regression forest with linear leaves: the semantic mapping of Rupprecht §3.2.

Measurements x (n = 6, cm) map to shape coefficients y (m = 25) through T decision trees
whose leaves each hold an affine map ``g(x) = A x + b`` (Rupprecht Equation 2) fitted by least squares to
the training samples that reach it (Rupprecht Equation 3); the forest averages the trees (Rupprecht §3.2.2).

Growing a tree (Rupprecht §3.2.1, randomized node optimization after Criminisi et al. 2012):
at each node, ``n_trials`` candidate splits are drawn, each an axis-aligned test
``x[d] <= t`` on one random input dimension d with a random threshold t, and the one with the
largest information gain is kept. A node becomes a leaf at ``max_depth``, when it holds fewer
than ``2 * min_samples_leaf`` samples, or when no candidate gains anything.

Split criterion (the "information gain"). We minimise the summed least-squares residual of the
leaf model in the two children,

    gain = R(S) - R(S_left) - R(S_right),
    R(S) = sum_{(x,y) in S} ||A_S x + b_S - y||^2,   (A_S, b_S) = the ridge fit of Rupprecht Equation 3 on S,

i.e. the reduction of the trace of the *residual* scatter of the linear fit (for constant
leaves, ``leaf_model="constant"``, A = 0 and R is the plain sum of squared errors: CART's
variance reduction). Why not the differential entropy of a Gaussian, ``log det Cov``, that the
forest literature writes: with m = 25 outputs and 30-sample leaves the covariance is near
singular, and when an output is an exact linear function of the inputs (stature is carried by
one PCA coefficient, Rupprecht §4.2) its residual variance is 0 and ``log det`` is -inf: the gain is
then decided by the smallest, least visible coefficients. ``log det`` is also invariant to
rescaling outputs, so a coefficient that moves the mesh by 0.1 mm counts as much as one that
moves it by 10 cm. The residual sum of squares weights outputs by their squared size, which
for orthonormal PCA components is the squared vertex error on the mesh -- what we want to be
small -- and it is finite and well-posed for any leaf (the ridge term makes the solve
regular). Scoring the *linear* residual rather than the variance matters: a variance split
cuts where y changes most, which is wasted on a leaf that fits a slope anyway; the residual
split cuts where the slope changes (at the kink of a piecewise-linear function): measured,
3.5-4x lower held-out error on piecewise-linear and smooth nonlinear maps, a tie on the body
benchmark (docs/forest.md).

Vectorized candidate evaluation: for the node's samples z = [x - mean, 1] (inputs
standardized over the whole training set), one matrix product of the (N, (n+1) T) array of
z masked by each trial's left side with [z, y, ||y||^2] gives every trial's left-child sums of
z z^T, z y^T and ||y||^2; the right child is the node total minus the left. Each child's
residual is then ``S_yy - <C_xy, W> - lambda ||W||^2`` with ``W = (C_xx + lambda I)^-1 C_xy``
from centred statistics, one batched 6x6 inverse for all 2T children. With 13 random
thresholds per node this is cheaper than sorting and prefix-summing every column (which scores
all N thresholds to use 13). The winning children's W are kept: a child that ends as a leaf
takes its Rupprecht Equation 3 fit from there, without another pass over its samples.

A tree grows level by level: the nodes of one depth are scored together, small ones in
padded batches (``_best_splits``), so numpy's per-call overhead is paid per batch, not per node.

Thresholds are drawn as a random rank r in [min_samples_leaf, N - min_samples_leaf] along the
chosen dimension, at the midpoint between the r-th and (r+1)-th values: every trial is a legal
split (ties aside, which are checked), thresholds follow the data density, and no trial is
wasted on an empty side.

Trees grow in parallel (``n_jobs``) in worker processes: the Python between numpy calls holds
the GIL, so threads overlap less (measured, 20 trees: 1 thread 2.03 s, 2 threads 1.40 s,
2 processes 1.13 s). Every tree has its own seed spawned from ``rng``, so the forest
is the same for any ``n_jobs``.

Storage: flat arrays (``to_arrays``), no pickle. Node i of the forest has ``node_feature[i]``
(-1 for a leaf), ``node_threshold[i]``, children ``node_left[i]``/``node_right[i]`` (global
node indices, -1 for a leaf) and ``node_leaf[i]`` (row in ``leaf_A``/``leaf_b``, -1 for an
internal node); tree t's nodes are ``tree_offset[t]:tree_offset[t+1]``, its root first, in
breadth-first order (children always after their parent).
``leaf_A`` (L, m, n) and ``leaf_b`` (L, m) are in the units of X and Y.
"""

from __future__ import annotations

import contextlib
import multiprocessing
import numbers
import os
import warnings
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool

import numpy as np

try:  # optional: installed with scikit-learn; without it BLAS keeps its own thread count
    from threadpoolctl import threadpool_limits
except ImportError:  # pragma: no cover
    threadpool_limits = None

from bodyspace.errors import ParameterError
from bodyspace.mapping.linear import FORMAT_VERSION, solve_ridge
from bodyspace.validation import as_nonnegative_float, as_samples, as_targets, check_rng, check_state_arrays

LEAF_MODELS = ("linear", "constant")


# ---------------------------------------------------------------------- growing one tree
def _child_residuals(szz: np.ndarray, szy: np.ndarray, syy: np.ndarray, ridge: float, linear: bool):
    """Least-squares residual R (B,) of each child's leaf model, and its slopes W (B, n, m) or None.

    ``szz`` (B, q, q) sums of z z^T and ``szy`` (B, q, m) of z y^T with z = [x, 1] (the count,
    the sums of x and of y in the last row); ``syy`` (B,) sums of ||y||^2. Centring here
    (``C = S - s s^T / N``) keeps the residual exact up to rounding of the node-centred sums.
    """
    cnt = szz[:, -1, -1]
    sy = szy[:, -1, :]
    resid = syy - np.einsum("bk,bk->b", sy, sy) / cnt
    if not linear:
        return resid, None
    sx = szz[:, :-1, -1]
    cxx = szz[:, :-1, :-1] - sx[:, :, None] * sx[:, None, :] / cnt[:, None, None]
    cxy = szy[:, :-1, :] - sx[:, :, None] * sy[:, None, :] / cnt[:, None, None]
    w, lam = solve_ridge(cxx, cxy, ridge, return_lambda=True)
    # Residual of the fitted leaf model itself, penalty excluded: with W = (C_xx + lam I)^-1 C_xy,
    # ||Y - X W||^2 = S_yy - 2 <C_xy, W> + <W, C_xx W> = S_yy - <C_xy, W> - lam ||W||^2.
    resid = resid - np.einsum("bik,bik->b", cxy, w) - lam * np.einsum("bik,bik->b", w, w)
    return resid, w


_SMALL_NODE = 1024   # nodes up to this size are split in padded batches per level; larger ones alone


def _best_splits(xt: np.ndarray, g: np.ndarray, nodes: list[np.ndarray], rng: np.random.Generator,
                 n_trials: int, min_leaf: int, ridge: float, linear: bool) -> list:
    """Best of ``n_trials`` random axis-aligned splits for each of B nodes, in one batch.

    ``xt`` (n, N + 1) raw inputs, transposed (thresholds are in these units), and ``g``
    (N + 1, n + 1 + m + 1) the rows ``[standardized x, 1, y, 0]``, both with a padding sample
    last (``xt`` +inf, ``g`` 0); ``nodes``: B arrays of sample indices, each of at least
    ``2 * min_leaf``. Node i is block i of a batch of n_max samples, short nodes padded with the
    padding sample: a zero row of ``g`` adds nothing to any sum, and +inf never goes left.
    Batching the many small nodes of a level pays numpy's ~70 calls once per batch instead of
    once per node (they were half the time of a tree), and the masking runs with samples along
    the last axis, in long contiguous inner loops (7x faster than with the 13 trials there).

    Returns, per node, (dimension, threshold, (left model, right model)), or None when no trial
    is legal or none reduces the residual; a model is what ``_fit_leaf`` returns for that child.
    """
    b, p, pad = len(nodes), xt.shape[0], xt.shape[1] - 1
    counts = np.array([idx.size for idx in nodes])
    n_max = int(counts.max())
    cols = np.full((b, n_max), pad)
    for i, idx in enumerate(nodes):
        cols[i, :idx.size] = idx
    # np.take, not fancy indexing: 25x faster for this gather along the last axis (measured).
    xb = np.ascontiguousarray(np.take(xt, cols, axis=1).transpose(1, 0, 2))   # (B, n, n_max)
    gb = np.take(g, cols, axis=0)                                      # (B, n_max, n + m + 2)
    bi = np.arange(b)[:, None]
    dims = rng.integers(0, p, (b, n_trials))
    ranks = rng.integers(min_leaf, (counts - min_leaf + 1)[:, None], (b, n_trials))   # samples that go left
    if n_max <= _SMALL_NODE:                                            # one sort beats 6 partitions
        srt = np.sort(xb, axis=2)
        thr = 0.5 * (srt[bi, dims, ranks - 1] + srt[bi, dims, ranks])
    else:                                                              # a big node alone: O(N) selection
        thr = np.empty((1, n_trials))
        for d in range(p):
            sel = dims[0] == d
            if sel.any():
                r = ranks[0, sel]
                col = np.partition(xb[0, d], np.concatenate([r - 1, r]))
                thr[0, sel] = 0.5 * (col[r - 1] + col[r])
    left = xb[bi, dims] <= thr[:, :, None]                             # (B, T, n_max)
    n_left = np.count_nonzero(left, axis=2)
    ok = (n_left >= min_leaf) & (counts[:, None] - n_left >= min_leaf)   # ties can break a rank

    # Centre each node on its means (padding stays 0: the constant column is 0 there): same
    # residuals, but sums of O(spread) numbers, not O(offset).
    mean = gb.sum(axis=1) / counts[:, None]
    mean[:, p] = 0.0
    gb -= gb[:, :, p:p + 1] * mean[:, None, :]
    yc = gb[:, :, p + 1:-1]
    gb[:, :, -1] = np.einsum("bnk,bnk->bn", yc, yc)                    # ||y||^2 rides in the last column
    zy = gb if linear else gb[:, :, p:]                                # (B, n_max, q + m + 1): [z, y, ||y||^2]
    q, t = (p + 1 if linear else 1), n_trials
    zt = np.ascontiguousarray(zy[:, :, :q].transpose(0, 2, 1))         # (B, q, n_max): [x, 1] or [1]
    zm = (zt[:, :, None, :] * left[:, None, :, :].astype(np.float64)).reshape(b, q * t, n_max)  # z masked per trial
    s_left = (zm @ zy).reshape(b, q, t, -1).transpose(0, 2, 1, 3)      # (B, T, q, q + m + 1)
    s_all = zt @ zy                                                    # (B, q, q + m + 1)
    # An illegal trial may have an empty side; give it harmless statistics and never pick it.
    s_left = np.where(ok[:, :, None, None], s_left, 0.5 * s_all[:, None])
    s = np.concatenate([s_left, s_all[:, None] - s_left, s_all[:, None]], axis=1)   # left, right, node
    s_flat = s.reshape(b * (2 * t + 1), q, -1)
    r, w = _child_residuals(s_flat[:, :, :q], s_flat[:, :, q:-1], s_flat[:, -1, -1], ridge, linear)
    r = r.reshape(b, 2 * t + 1)
    children = np.where(ok, r[:, :t] + r[:, t:2 * t], np.inf)
    best = np.argmin(children, axis=1)
    out = []
    for i in range(b):
        k = int(best[i])
        # Gains at rounding level (e.g. exactly linear data under linear leaves) are not real.
        if not ok[i, k] or not r[i, -1] - children[i, k] > 1e-10 * max(s[i, -1, -1, -1], 1e-300):
            out.append(None)
            continue
        # The children's leaf models come free with the winning statistics: (slopes (m, n) in
        # standardized x, mean of standardized x (n,), mean of y (m,)), used if a child stays a leaf.
        models = []
        for c in (k, t + k):
            means = s[i, c, -1] / s[i, c, -1, q - 1]                  # of [z, y, .], node-centred
            y_mean = means[q:-1] + mean[i, p + 1:-1]
            if linear:
                models.append((w[i * (2 * t + 1) + c].T, means[:p] + mean[i, :p], y_mean))
            else:
                models.append((np.zeros((y_mean.size, p)), np.zeros(p), y_mean))
        out.append((int(dims[i, k]), float(thr[i, k]), models))
    return out


def _fit_leaf(xs: np.ndarray, y: np.ndarray, ridge: float, linear: bool):
    """Leaf model in standardized inputs: (A_s (m, n), x mean (n,), y mean (m,)), y = y_mean + A_s (xs - x_mean)."""
    x_mean = xs.mean(axis=0)
    y_mean = y.mean(axis=0)
    if not linear:
        return np.zeros((y.shape[1], xs.shape[1])), x_mean, y_mean
    xc = xs - x_mean
    w = solve_ridge((xc.T @ xc)[None], (xc.T @ (y - y_mean))[None], ridge)[0]
    return w.T, x_mean, y_mean


def _batches(sizes: list[int]) -> list[list[int]]:
    """Positions of the nodes to split together: big nodes alone, small ones by size class (<= 2x padding)."""
    groups: dict[int, list[int]] = {}
    out = []
    for k, n in enumerate(sizes):
        if n > _SMALL_NODE:
            out.append([k])
        else:
            groups.setdefault(int(n - 1).bit_length(), []).append(k)
    return out + [groups[c] for c in sorted(groups)]


def grow_tree(x: np.ndarray, y: np.ndarray, rng, *, x_mean: np.ndarray, x_scale: np.ndarray,
              max_depth: int, n_trials: int, min_samples_leaf: int, ridge: float,
              linear: bool = True) -> dict[str, np.ndarray]:
    """Grow one tree on x (N, n), y (N, m); returns its flat arrays (local node indices).

    ``x_mean``/``x_scale`` (n,) standardize the inputs for the statistics (the ridge is then
    relative to unit-variance inputs); ``rng`` is a Generator, a SeedSequence, a seed or None.
    The tree grows level by level (all nodes of a depth are split in a few batches); nodes are
    numbered in that breadth-first order, so children always come after their parent.
    """
    rng = np.random.default_rng(rng)
    n_all, p = x.shape
    xs = (x - x_mean) / x_scale
    # Rows [standardized x, 1, y, scratch] and the raw x transposed, each with a padding sample.
    g_ext = np.zeros((n_all + 1, p + y.shape[1] + 2))
    g_ext[:n_all, :p], g_ext[:n_all, p], g_ext[:n_all, p + 1:-1] = xs, 1.0, y
    x_ext = np.concatenate([x, np.full((1, p), np.inf)]).T.copy()
    feature, threshold, left, right, leaf = [-1], [0.0], [-1], [-1], [-1]
    leaf_a, leaf_b = [], []
    level = [(0, np.arange(n_all), None)]                              # (node, samples, leaf model)
    for depth in range(max_depth + 1):
        if not level:
            break
        splits = [None] * len(level)
        if depth < max_depth:
            todo = [k for k, (_, idx, _) in enumerate(level) if idx.size >= 2 * min_samples_leaf]
            for batch in _batches([level[k][1].size for k in todo]):
                found = _best_splits(x_ext, g_ext, [level[todo[j]][1] for j in batch], rng, n_trials,
                                     min_samples_leaf, ridge, linear)
                for j, f in zip(batch, found):
                    splits[todo[j]] = f
        below = []
        for (node, idx, model), split in zip(level, splits):
            if split is None:
                a_s, xm_s, ym = model if model is not None else _fit_leaf(xs[idx], y[idx], ridge, linear)
                a = a_s / x_scale                                      # back to the units of x
                leaf[node] = len(leaf_a)
                leaf_a.append(a)
                leaf_b.append(ym - a @ (xm_s * x_scale + x_mean))
                continue
            d, t, (model_left, model_right) = split
            go_left = x[idx, d] <= t
            child = len(feature)
            feature[node], threshold[node], left[node], right[node] = d, t, child, child + 1
            feature += [-1, -1]; threshold += [0.0, 0.0]; left += [-1, -1]; right += [-1, -1]; leaf += [-1, -1]
            below += [(child, idx[go_left], model_left), (child + 1, idx[~go_left], model_right)]
        level = below
    return {
        "feature": np.asarray(feature, dtype=np.int32),
        "threshold": np.asarray(threshold, dtype=np.float64),
        "left": np.asarray(left, dtype=np.int32),
        "right": np.asarray(right, dtype=np.int32),
        "leaf": np.asarray(leaf, dtype=np.int32),
        "leaf_A": np.asarray(leaf_a, dtype=np.float64),
        "leaf_b": np.asarray(leaf_b, dtype=np.float64),
    }


def _one_blas_thread():
    """Single-threaded BLAS while growing trees.

    The node products are mid-sized (at most (91 x N) @ (N x 34)): OpenBLAS threads them, and
    its threads spin-wait for each other, which on a shared 2-core machine made growing a
    tree 6x slower (1.46 s vs 0.24 s per tree, measured). Parallelism goes across trees instead.
    """
    return threadpool_limits(1, user_api="blas") if threadpool_limits is not None else contextlib.nullcontext()


def _grow_trees(x, y, seeds, kwargs, limit_blas=False) -> list[dict[str, np.ndarray]]:
    """A worker's share of the forest (module level so a process pool can call it)."""
    with _one_blas_thread() if limit_blas else contextlib.nullcontext():
        return [grow_tree(x, y, s, **kwargs) for s in seeds]


def _grow_in_processes(x, y, seeds, kwargs, workers: int):
    """Trees grown by ``workers`` processes, or None when this process cannot start any.

    Processes, not threads: the Python between numpy calls holds the GIL; for 20 trees two
    threads took 1.40 s, two processes 1.13 s, one 2.03 s (measured). Each worker grows a
    contiguous chunk of trees, so the data crosses the process boundary once. The result does
    not depend on who grew what (one seed per tree), so falling back to this process changes
    the time only.
    """
    if multiprocessing.current_process().daemon:                      # daemons may not have children
        return None
    chunks = [c for c in np.array_split(np.arange(len(seeds)), workers) if c.size]
    try:
        with ProcessPoolExecutor(len(chunks)) as pool:
            parts = pool.map(_grow_trees, [x] * len(chunks), [y] * len(chunks),
                             [[seeds[i] for i in c] for c in chunks], [kwargs] * len(chunks),
                             [True] * len(chunks))
            return [t for part in parts for t in part]
    except (BrokenProcessPool, OSError) as exc:
        warnings.warn(f"LinearLeafForest: could not grow trees in worker processes ({exc!r}); "
                      "growing them in this process (same forest, slower)", RuntimeWarning, stacklevel=3)
        return None


def _seed_sequence(rng) -> np.random.SeedSequence:
    if isinstance(rng, np.random.SeedSequence):
        return rng
    if isinstance(rng, np.random.Generator):                  # draws from (advances) the generator
        return np.random.SeedSequence(int(rng.integers(2 ** 63)))
    return np.random.SeedSequence(rng)


def _n_workers(n_jobs, n_tasks: int) -> int:
    if n_jobs is None:
        return 1
    if isinstance(n_jobs, bool) or not isinstance(n_jobs, numbers.Integral) or n_jobs == 0:
        raise ParameterError(f"n_jobs={n_jobs!r}, expected None, a positive int, or -1 for all cores")
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    n = cores + 1 + int(n_jobs) if n_jobs < 0 else int(n_jobs)       # -1 = all cores, as in scikit-learn
    return max(1, min(n, n_tasks))


# ---------------------------------------------------------------------- estimator
class LinearLeafForest:
    """Regression forest with affine leaf models, measurements -> shape coefficients.

    Rupprecht §3.2 (Rupprecht Equations 2 and 3); defaults from Rupprecht §4.2.

    Args:
        n_trees: number of trees T; predictions are their mean.
        max_depth: depth limit (the root is depth 0; 15 allows 15 levels of splits).
        n_trials: random (dimension, threshold) candidates scored per node.
        min_samples_leaf: every leaf holds at least this many training samples ("to find a
            reliable probabilistic line"; must be >= 1; a linear leaf wants > n_features).
        ridge: Tikhonov weight on each leaf's A, relative to the node's mean input variance
            (inputs standardized over the training set); see ``linear.fit_affine``. Also used in
            the split criterion, so a split is scored by the model the leaf will hold.
        leaf_model: "linear" (Rupprecht Equation 2, the paper) or "constant" (mean of y, CART's criterion):
            the ablation of the paper's contribution with everything else equal.
        rng: None, an int, a ``np.random.SeedSequence`` or a ``np.random.Generator`` (one draw
            seeds the forest). Equal ints give bit-identical
            forests, for any ``n_jobs``.
        n_jobs: worker processes for growing trees: None or 1 = in this process, -1 = all cores.
            Where processes start by spawning (Windows, macOS, Linux from Python 3.14), a
            script calling ``fit`` with ``n_jobs > 1`` needs the ``if __name__ == "__main__":``
            guard, as for any ``multiprocessing`` use.

    Attributes (after ``fit`` or ``from_arrays``):
        n_features_in_, n_outputs_, n_trees_, n_leaves_: ints.
        node_feature_, node_threshold_, node_left_, node_right_, node_leaf_: (nodes,) flat trees.
        tree_offset_: (T + 1,) node range of each tree.
        leaf_A_: (L, m, n), leaf_b_: (L, m) the leaf models in the units of X and Y.
        max_depth_: the deepest leaf's depth.
    """

    def __init__(self, n_trees: int = 50, max_depth: int = 15, n_trials: int = 13, min_samples_leaf: int = 30,
                 ridge: float = 1e-6, leaf_model: str = "linear", rng=None, n_jobs: int | None = None):
        self.n_trees = n_trees
        self.max_depth = max_depth
        self.n_trials = n_trials
        self.min_samples_leaf = min_samples_leaf
        self.ridge = ridge
        self.leaf_model = leaf_model
        self.rng = rng
        self.n_jobs = n_jobs

    # ------------------------------------------------------------------ validation
    def _check_params(self) -> None:
        for name, low in (("n_trees", 1), ("max_depth", 0), ("n_trials", 1), ("min_samples_leaf", 1)):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, numbers.Integral) or v < low:
                raise ParameterError(f"{name}={v!r}, expected an int >= {low}")
        as_nonnegative_float(self.ridge, "ridge")
        if self.leaf_model not in LEAF_MODELS:
            raise ParameterError(f"leaf_model={self.leaf_model!r}, expected one of {LEAF_MODELS}")
        check_rng(self.rng)

    def _require_fit(self):
        if not hasattr(self, "leaf_A_"):
            raise ParameterError("LinearLeafForest is not fitted; call fit(X, Y) first")

    # ------------------------------------------------------------------ estimator API
    def fit(self, X, Y) -> "LinearLeafForest":
        """Grow the forest on measurements X (N, n) and coefficients Y (N, m) or (N,)."""
        self._check_params()
        x, _ = as_samples(X)
        y, one_d = as_targets(Y, x.shape[0])
        if x.shape[0] < self.min_samples_leaf:
            raise ParameterError(f"X: {x.shape[0]} samples, expected at least min_samples_leaf="
                                 f"{self.min_samples_leaf} (one leaf's worth)")
        x = np.ascontiguousarray(x)
        y = np.ascontiguousarray(y)
        x_mean = x.mean(axis=0)
        x_scale = x.std(axis=0)
        x_scale[x_scale == 0] = 1.0
        seeds = _seed_sequence(self.rng).spawn(self.n_trees)  # one stream per tree: n_jobs-independent
        kwargs = dict(x_mean=x_mean, x_scale=x_scale, max_depth=int(self.max_depth), n_trials=int(self.n_trials),
                      min_samples_leaf=int(self.min_samples_leaf), ridge=float(self.ridge),
                      linear=self.leaf_model == "linear")
        workers = _n_workers(self.n_jobs, self.n_trees)
        trees = None
        if workers > 1:
            trees = _grow_in_processes(x, y, seeds, kwargs, workers)
        if trees is None:
            with _one_blas_thread():
                trees = _grow_trees(x, y, seeds, kwargs)
        self._set_trees(trees)
        self.n_features_in_, self.n_outputs_ = x.shape[1], y.shape[1]
        self._y_1d = one_d
        return self

    def _set_trees(self, trees) -> None:
        sizes = np.array([t["feature"].size for t in trees])
        n_leaves = np.array([t["leaf_A"].shape[0] for t in trees])
        node_off = np.concatenate([[0], np.cumsum(sizes)])
        leaf_off = np.concatenate([[0], np.cumsum(n_leaves)])

        def shift(a, off):
            return np.where(a >= 0, a + off, -1).astype(np.int32)
        self.node_feature_ = np.concatenate([t["feature"] for t in trees])
        self.node_threshold_ = np.concatenate([t["threshold"] for t in trees])
        self.node_left_ = np.concatenate([shift(t["left"], o) for t, o in zip(trees, node_off)])
        self.node_right_ = np.concatenate([shift(t["right"], o) for t, o in zip(trees, node_off)])
        self.node_leaf_ = np.concatenate([shift(t["leaf"], o) for t, o in zip(trees, leaf_off)])
        self.tree_offset_ = node_off.astype(np.int64)
        self.leaf_A_ = np.concatenate([t["leaf_A"] for t in trees])
        self.leaf_b_ = np.concatenate([t["leaf_b"] for t in trees])
        self._finish()

    def _finish(self) -> None:
        """Derived state for prediction: leaves route to themselves, so traversal needs no mask."""
        n = self.node_feature_.size
        is_leaf = self.node_feature_ < 0
        self.n_trees_ = self.tree_offset_.size - 1
        self.n_leaves_ = self.leaf_A_.shape[0]
        self._go_feature = np.where(is_leaf, 0, self.node_feature_).astype(np.intp)
        self._go_left = np.where(is_leaf, np.arange(n), self.node_left_).astype(np.intp)
        self._go_right = np.where(is_leaf, np.arange(n), self.node_right_).astype(np.intp)
        self._leaf_Ab = np.concatenate([self.leaf_A_, self.leaf_b_[:, :, None]], axis=2)   # (L, m, n + 1)
        depth, level = 0, self.tree_offset_[:-1]                       # the roots
        while True:                                                    # children follow parents: ends
            level = level[~is_leaf[level]]
            if level.size == 0:
                break
            level = np.concatenate([self.node_left_[level], self.node_right_[level]]).astype(np.intp)
            depth += 1
        self.max_depth_ = depth

    def apply(self, X) -> np.ndarray:
        """Leaf (row of ``leaf_A_``) that each sample reaches in each tree, (N, T)."""
        self._require_fit()
        x, _ = as_samples(X, self.n_features_in_)
        return self._apply(x)

    def _apply(self, x: np.ndarray) -> np.ndarray:
        node = np.broadcast_to(self.tree_offset_[:-1], (x.shape[0], self.n_trees_)).astype(np.intp)
        flat = np.ascontiguousarray(x).ravel()
        row = (np.arange(x.shape[0]) * x.shape[1])[:, None]
        for _ in range(self.max_depth_):                               # all trees, all samples, level by level
            value = flat[row + self._go_feature[node]]
            node = np.where(value <= self.node_threshold_[node], self._go_left[node], self._go_right[node])
        return self.node_leaf_[node]

    def predict(self, X) -> np.ndarray:
        """Coefficients (N, m) of measurements (N, n): the mean of the trees' A x + b (Rupprecht §3.2.2).

        A single sample (n,) gives (m,); a forest fitted on 1-D Y gives (N,).
        """
        self._require_fit()
        x, single = as_samples(X, self.n_features_in_)
        out = np.empty((x.shape[0], self.n_outputs_))
        chunk = 2048                                                   # bounds the (chunk, m, n+1) buffer
        for s in range(0, x.shape[0], chunk):
            xc = x[s:s + chunk]
            leaves = self._apply(xc)
            # The mean of affine maps is the affine map of the mean: sum the trees' [A b] first,
            # then one product with [x, 1] per sample.
            ab = self._leaf_Ab[leaves[:, 0]]                               # a copy (fancy indexing)
            for t in range(1, self.n_trees_):
                ab += self._leaf_Ab[leaves[:, t]]
            xa = np.concatenate([xc, np.ones((xc.shape[0], 1))], axis=1)
            out[s:s + chunk] = np.einsum("ikj,ij->ik", ab, xa) / self.n_trees_
        if self._y_1d:
            out = out[:, 0]
        return out[0] if single else out

    # ------------------------------------------------------------------ serialization
    def to_arrays(self) -> dict[str, np.ndarray]:
        """Flat arrays (no object dtype) for an npz loadable with ``allow_pickle=False``.

        Keys: ``kind``, ``format_version``, the hyper-parameters (``rng`` only if it was an int,
        stored under the key ``random_state`` of format version 1), ``n_features_in``, ``n_outputs``, ``y_1d``, ``node_feature``,
        ``node_threshold``, ``node_left``, ``node_right``, ``node_leaf``, ``tree_offset``,
        ``leaf_A``, ``leaf_b``. A bundle holding several estimators should prefix the keys.
        """
        self._require_fit()
        out = {
            "kind": np.array("LinearLeafForest"),
            "format_version": np.array(FORMAT_VERSION),
            "n_trees": np.array(int(self.n_trees)),
            "max_depth": np.array(int(self.max_depth)),
            "n_trials": np.array(int(self.n_trials)),
            "min_samples_leaf": np.array(int(self.min_samples_leaf)),
            "ridge": np.array(float(self.ridge)),
            "leaf_model": np.array(str(self.leaf_model)),
            "n_features_in": np.array(self.n_features_in_),
            "n_outputs": np.array(self.n_outputs_),
            "y_1d": np.array(self._y_1d),
        }
        if isinstance(self.rng, numbers.Integral):
            out["random_state"] = np.array(int(self.rng))
        for name in ("node_feature", "node_threshold", "node_left", "node_right", "node_leaf", "tree_offset",
                     "leaf_A", "leaf_b"):
            out[name] = getattr(self, name + "_").copy()
        return out

    @classmethod
    def from_arrays(cls, arrays) -> "LinearLeafForest":
        """Inverse of ``to_arrays`` (accepts the dict or an opened ``NpzFile``); checks consistency."""
        keys = ("n_trees", "max_depth", "n_trials", "min_samples_leaf", "ridge", "leaf_model", "n_features_in",
                "n_outputs", "y_1d", "node_feature", "node_threshold", "node_left", "node_right", "node_leaf",
                "tree_offset", "leaf_A", "leaf_b")
        check_state_arrays(arrays, "LinearLeafForest", keys, FORMAT_VERSION)
        a = {k: np.asarray(arrays[k]) for k in keys}
        self = cls(n_trees=int(a["n_trees"]), max_depth=int(a["max_depth"]), n_trials=int(a["n_trials"]),
                   min_samples_leaf=int(a["min_samples_leaf"]), ridge=float(a["ridge"]),
                   leaf_model=str(a["leaf_model"]),
                   rng=int(np.asarray(arrays["random_state"])) if "random_state" in arrays else None)
        self.n_features_in_, self.n_outputs_ = int(a["n_features_in"]), int(a["n_outputs"])
        self._y_1d = bool(a["y_1d"])
        for name in ("node_feature", "node_left", "node_right", "node_leaf"):
            setattr(self, name + "_", a[name].astype(np.int32))
        self.node_threshold_ = a["node_threshold"].astype(np.float64)
        self.tree_offset_ = a["tree_offset"].astype(np.int64)
        self.leaf_A_ = a["leaf_A"].astype(np.float64)
        self.leaf_b_ = a["leaf_b"].astype(np.float64)
        _check_structure(self)
        self._finish()
        return self


def _check_structure(f: LinearLeafForest) -> None:
    """Reject arrays that would index out of range or loop (a corrupted or hand-edited bundle)."""
    n = f.node_feature_.size
    n_leaves = f.leaf_A_.shape[0] if f.leaf_A_.ndim == 3 else -1

    def bad(what, expected):
        raise ParameterError(f"arrays[{what!r}]: inconsistent forest, expected {expected}")
    if any(getattr(f, k).shape != (n,) for k in ("node_threshold_", "node_left_", "node_right_", "node_leaf_")):
        bad("node_*", f"all node arrays of length {n}")
    if f.leaf_A_.shape != (n_leaves, f.n_outputs_, f.n_features_in_) or f.leaf_b_.shape != (n_leaves, f.n_outputs_):
        bad("leaf_A/leaf_b", f"shapes (L, {f.n_outputs_}, {f.n_features_in_}) and (L, {f.n_outputs_})")
    off = f.tree_offset_
    if off.ndim != 1 or off.size < 2 or off[0] != 0 or off[-1] != n or np.any(np.diff(off) < 1):
        bad("tree_offset", f"increasing offsets from 0 to {n}")
    leaf = f.node_feature_ < 0
    if np.any(f.node_feature_ >= f.n_features_in_):
        bad("node_feature", f"values in [-1, {f.n_features_in_})")
    if np.any(leaf != (f.node_leaf_ >= 0)) or np.any(f.node_leaf_ >= n_leaves):
        bad("node_leaf", "a leaf row exactly at the nodes with node_feature -1")
    node = np.arange(n)
    tree_end = np.repeat(off[1:], np.diff(off))
    for child in (f.node_left_, f.node_right_):
        c = child[~leaf]
        if np.any(c <= node[~leaf]) or np.any(c >= tree_end[~leaf]):
            bad("node_left/node_right", "children after their parent, inside the same tree")
    if not np.isfinite(f.node_threshold_).all() or not np.isfinite(f.leaf_A_).all() \
            or not np.isfinite(f.leaf_b_).all():
        bad("node_threshold/leaf_A/leaf_b", "finite numbers")

