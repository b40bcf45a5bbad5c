"""The semantic-mapping estimators (Rupprecht et al., Sec. 3.2): linear-leaf forest and linear mapping.

Small synthetic problems only (no body model), so the file runs in seconds.
"""

import io

import numpy as np
import pytest

from bodyspace.errors import ParameterError
from bodyspace.mapping import LinearLeafForest, LinearMapping, fit_affine


def rmse(a, b):
    return float(np.sqrt(np.mean(np.sum((a - b) ** 2, axis=-1))))


def leaf_sizes(forest, X):
    """Training samples per leaf, per tree: list of arrays."""
    leaves = forest.apply(X)
    return [np.bincount(leaves[:, t], minlength=forest.n_leaves_)[np.unique(leaves[:, t])]
            for t in range(forest.n_trees_)]


def sample_kinked(rng, n):
    x = rng.uniform(-1, 1, (n, 3))
    x[:, 0] = np.where(x[:, 0] < 0, x[:, 0] - 0.2, x[:, 0] + 0.2)
    return x


def tree_depth(forest):
    """Deepest leaf, by walking the flat arrays from each root."""
    best = 0
    for root in forest.tree_offset_[:-1]:
        stack = [(root, 0)]
        while stack:
            node, d = stack.pop()
            best = max(best, d)
            if forest.node_feature_[node] >= 0:
                stack += [(forest.node_left_[node], d + 1), (forest.node_right_[node], d + 1)]
    return best


@pytest.fixture(scope="module")
def kinked():
    """Piecewise-linear map R^3 -> R^4 with a kink at x0 = 0 and no samples within 0.2 of it."""
    rng = np.random.default_rng(0)
    x = sample_kinked(rng, 1500)
    a_neg = rng.normal(size=(4, 3))
    a_pos = a_neg.copy()
    a_pos[:, 0] += rng.normal(size=4) * 3.0                       # the slope along x0 changes at 0
    b = rng.normal(size=4)

    def f(x):
        return np.where(x[:, :1] < 0, x @ a_neg.T, x @ a_pos.T) + b
    return x, f(x), f, (a_neg, a_pos, b)


# ---------------------------------------------------------------------- correctness
def test_fit_affine_recovers_an_affine_map():
    rng = np.random.default_rng(1)
    x = rng.normal(170, 10, (200, 6))                            # cm-scale offsets
    a, b = rng.normal(size=(25, 6)), rng.normal(size=25)
    A, B = fit_affine(x, x @ a.T + b, ridge=0.0)
    assert np.allclose(A, a, atol=1e-9) and np.allclose(B, b, atol=1e-6)


def test_exactly_linear_data_gives_single_leaf_trees_and_exact_predictions():
    rng = np.random.default_rng(2)
    x = rng.normal(100, 20, (400, 6))
    a, b = rng.normal(size=(5, 6)), rng.normal(size=5)
    y = x @ a.T + b
    f = LinearLeafForest(n_trees=5, ridge=0.0, rng=0).fit(x, y)
    assert f.n_leaves_ == 5 and f.max_depth_ == 0                # no split gains anything
    xt = rng.normal(100, 20, (50, 6))
    assert np.allclose(f.predict(xt), xt @ a.T + b, atol=1e-8)
    assert np.allclose(LinearMapping(ridge=0.0).fit(x, y).predict(xt), xt @ a.T + b, atol=1e-8)


def test_linear_leaves_are_exact_on_each_piece_of_piecewise_linear_data(kinked):
    x, y, _, (a_neg, a_pos, b) = kinked
    f = LinearLeafForest(n_trees=8, min_samples_leaf=20, ridge=0.0, rng=0).fit(x, y)
    leaves = f.apply(x)
    exact = 0
    for t in range(f.n_trees_):
        for leaf in np.unique(leaves[:, t]):
            side = x[leaves[:, t] == leaf, 0] > 0
            if side.all() or not side.any():                     # one piece: Eq. 3 must recover it
                a = a_pos if side.all() else a_neg
                assert np.allclose(f.leaf_A_[leaf], a, atol=1e-8)
                assert np.allclose(f.leaf_b_[leaf], b, atol=1e-8)
                exact += 1
    assert exact >= 0.8 * f.n_leaves_
    # Once a node lies on one side its residual is zero and it stops splitting: few leaves.
    assert f.n_leaves_ < 8 * 10


def test_each_leaf_holds_the_least_squares_fit_of_its_samples():
    rng = np.random.default_rng(12)
    x = rng.normal(170, 10, (2000, 6))
    y = np.sin(x / 15) @ rng.normal(size=(6, 25))
    f = LinearLeafForest(n_trees=2, ridge=0.0, rng=0).fit(x, y)
    leaves = f.apply(x)
    for leaf in range(0, f.n_leaves_, 7):
        inside = (leaves == leaf).any(axis=1)
        a, b = fit_affine(x[inside], y[inside], ridge=0.0)           # Eq. 3 on the leaf's samples
        assert np.allclose(f.leaf_A_[leaf], a, atol=1e-9) and np.allclose(f.leaf_b_[leaf], b, atol=1e-7)


def test_linear_leaves_beat_constant_leaves(kinked):
    x, y, fn, _ = kinked
    xt = sample_kinked(np.random.default_rng(3), 500)
    kw = dict(n_trees=10, min_samples_leaf=20, rng=0)
    err_lin = rmse(LinearLeafForest(**kw).fit(x, y).predict(xt), fn(xt))
    err_const = rmse(LinearLeafForest(leaf_model="constant", **kw).fit(x, y).predict(xt), fn(xt))
    assert err_lin < 0.05 * err_const


def test_forest_beats_the_linear_mapping_on_a_nonlinear_problem():
    rng = np.random.default_rng(4)

    def f(x):
        return np.stack([np.sin(2 * x[:, 0]) + x[:, 1], x[:, 1] ** 2 - x[:, 2], x[:, 0] * x[:, 2]], axis=1)
    x, xt = rng.uniform(-2, 2, (3000, 3)), rng.uniform(-1.8, 1.8, (500, 3))
    forest = LinearLeafForest(n_trees=10, rng=0).fit(x, f(x))
    linear = LinearMapping().fit(x, f(x))
    err_forest, err_linear = rmse(forest.predict(xt), f(xt)), rmse(linear.predict(xt), f(xt))
    assert err_forest < 0.25 * err_linear


def test_min_samples_leaf_and_max_depth_are_respected():
    rng = np.random.default_rng(5)
    x = rng.normal(size=(2000, 4))
    y = np.stack([np.sin(3 * x[:, 0]) * x[:, 1], np.abs(x[:, 2]) + x[:, 3] ** 2], axis=1)
    for msl, depth in ((30, 15), (7, 4)):
        f = LinearLeafForest(n_trees=4, min_samples_leaf=msl, max_depth=depth, rng=1).fit(x, y)
        assert min(s.min() for s in leaf_sizes(f, x)) >= msl
        assert f.max_depth_ == tree_depth(f) <= depth
        assert all(s.sum() == len(x) for s in leaf_sizes(f, x))
    assert f.max_depth_ == 4                                     # 2000 samples in leaves of 7 reach depth 4
    # Ties: on a column that is 0 but for 15 samples, every rank's threshold is 0 and would leave
    # 15 on the right; such trials must be rejected, not produce a short leaf.
    x[:1985, 0] = 0.0
    f = LinearLeafForest(n_trees=4, min_samples_leaf=30, rng=2).fit(x, y)
    assert min(s.min() for s in leaf_sizes(f, x)) >= 30


def test_shapes_single_sample_and_one_output():
    rng = np.random.default_rng(6)
    x = rng.normal(size=(300, 6))
    y = x @ rng.normal(size=(6, 25)) + np.sin(x[:, :1])
    for est in (LinearLeafForest(n_trees=3, rng=0), LinearMapping()):
        est.fit(x, y)
        assert est.predict(x[:7]).shape == (7, 25)
        assert np.array_equal(est.predict(x[3]), est.predict(x[3:4])[0])
        est.fit(x, y[:, 0])
        assert est.predict(x[:7]).shape == (7,)
        assert np.ndim(est.predict(x[0])) == 0


# ---------------------------------------------------------------------- determinism
def test_same_rng_same_forest_for_any_n_jobs():
    rng = np.random.default_rng(7)
    x = rng.normal(size=(1500, 6))
    y = np.tanh(x @ rng.normal(size=(6, 8)))
    a = LinearLeafForest(n_trees=6, rng=42).fit(x, y).to_arrays()
    b = LinearLeafForest(n_trees=6, rng=42).fit(x, y).to_arrays()
    c = LinearLeafForest(n_trees=6, rng=42, n_jobs=2).fit(x, y).to_arrays()
    d = LinearLeafForest(n_trees=6, rng=43).fit(x, y).to_arrays()
    for k in a:
        assert np.array_equal(a[k], b[k]) and np.array_equal(a[k], c[k]), k
    assert not np.array_equal(a["node_threshold"], d["node_threshold"])


# ---------------------------------------------------------------------- serialization
@pytest.mark.parametrize("make", [lambda: LinearLeafForest(n_trees=5, rng=3), lambda: LinearMapping()])
def test_round_trip_through_npz_without_pickle_is_bit_exact(make):
    rng = np.random.default_rng(8)
    x = rng.normal(150, 15, (800, 6))
    y = np.sin(x / 20) @ rng.normal(size=(6, 25))
    est = make().fit(x, y)
    arrays = est.to_arrays()
    assert all(isinstance(v, np.ndarray) and v.dtype != object for v in arrays.values())
    buf = io.BytesIO()
    np.savez(buf, **{f"mapping/{k}": v for k, v in arrays.items()})     # as inside a bundle
    buf.seek(0)
    with np.load(buf, allow_pickle=False) as npz:
        loaded = {k.split("/", 1)[1]: npz[k] for k in npz.files}
    back = type(est).from_arrays(loaded)
    for k, v in arrays.items():
        assert np.array_equal(v, back.to_arrays()[k]) and v.dtype == back.to_arrays()[k].dtype, k
    xt = rng.normal(150, 15, (100, 6))
    assert np.array_equal(est.predict(xt), back.predict(xt))       # bit-exact, not allclose


def test_from_arrays_rejects_corrupt_input():
    rng = np.random.default_rng(9)
    x = rng.normal(size=(300, 3))
    arrays = LinearLeafForest(n_trees=2, rng=0).fit(x, np.sin(x)).to_arrays()
    with pytest.raises(ParameterError, match="missing.*leaf_A"):
        LinearLeafForest.from_arrays({k: v for k, v in arrays.items() if k != "leaf_A"})
    with pytest.raises(ParameterError, match="kind"):
        LinearMapping.from_arrays(arrays)
    broken = dict(arrays, node_left=np.where(arrays["node_left"] >= 0, 10 ** 6, -1).astype(np.int32))
    with pytest.raises(ParameterError, match="node_left"):
        LinearLeafForest.from_arrays(broken)


# ---------------------------------------------------------------------- bad input
@pytest.mark.parametrize("est", [LinearLeafForest(n_trees=2), LinearMapping()], ids=["forest", "linear"])
def test_bad_input_names_the_field(est):
    rng = np.random.default_rng(10)
    x, y = rng.normal(size=(100, 6)), rng.normal(size=(100, 25))
    with pytest.raises(ParameterError, match=r"X: shape \(100,\), expected a 2-D"):
        est.fit(x[:, 0], y)
    with pytest.raises(ParameterError, match=r"Y: 99 rows, expected 100"):
        est.fit(x, y[:99])
    bad = x.copy()
    bad[7, 2] = np.nan
    with pytest.raises(ParameterError, match=r"X: contains NaN.*row 7, column 2"):
        est.fit(bad, y)
    bad = y.copy()
    bad[3, 4] = np.inf
    with pytest.raises(ParameterError, match=r"Y: contains NaN or infinity.*row 3"):
        est.fit(x, bad)
    with pytest.raises(ParameterError, match="not fitted"):
        type(est)().predict(x)
    est.fit(x, y)
    with pytest.raises(ParameterError, match=r"X: 5 features per sample, expected 6"):
        est.predict(x[:, :5])
    with pytest.raises(ParameterError, match=r"X: shape \(2, 3, 6\)"):
        est.predict(x[:6].reshape(2, 3, 6))


def test_too_few_samples_and_bad_hyper_parameters():
    rng = np.random.default_rng(11)
    x, y = rng.normal(size=(20, 6)), rng.normal(size=(20, 25))
    with pytest.raises(ParameterError, match=r"X: 20 samples, expected at least min_samples_leaf=30"):
        LinearLeafForest().fit(x, y)
    with pytest.raises(ParameterError, match=r"X: 1 sample\(s\), expected at least 2"):
        LinearMapping().fit(x[:1], y[:1])
    for kw, field in ((dict(n_trees=0), "n_trees=0"), (dict(max_depth=-1), "max_depth=-1"),
                      (dict(n_trials=2.5), "n_trials=2.5"), (dict(min_samples_leaf=0), "min_samples_leaf=0"),
                      (dict(ridge=-1.0), "ridge=-1.0"), (dict(leaf_model="quadratic"), "leaf_model='quadratic'"),
                      (dict(n_jobs=0), "n_jobs=0"), (dict(rng="seed"), "rng='seed'")):
        with pytest.raises(ParameterError, match=field.replace("(", r"\(").replace(".", r"\.")):
            LinearLeafForest(**{"min_samples_leaf": 5, **kw}).fit(x, y)
