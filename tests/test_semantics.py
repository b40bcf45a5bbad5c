"""Semantic regressors, morphing, comparison directions, semantic basis, Tables 1 and 2
(Hasler et al. 2009, §4, §4.1, §5.1) on synthetic data with known label functions."""

import numpy as np
import pytest

from bodyspace.errors import ParameterError
from bodyspace.semantics import (
    ComparisonRegressor,
    FilteredLinearRegressor,
    KernelRegressor,
    SemanticBasis,
    SimpleLinearRegressor,
    comparison_direction,
    cross_validated_rmse,
    direction_angles,
    format_angle_table,
    format_rmse_table,
    gram_schmidt,
    morph,
    morph_directions,
)
from bodyspace.semantics.closed_loop import BACKTRACKS, closed_loop


def shape_like(n, d, seed=0, label_noise=0.5):
    """Bodies as in a shape space: 6 latent factors of decreasing SD along orthonormal axes B
    plus anisotropic noise in all D dims; the label depends on latent factors 0 and 3."""
    rng = np.random.default_rng(seed)
    b = np.linalg.qr(rng.normal(size=(d, 6)))[0].T
    z = rng.normal(size=(n, 6)) * np.array([3, 2.5, 2, 1.5, 1.2, 1.0])
    x = z @ b + 0.3 * rng.normal(size=(n, d)) * np.linspace(1, 0.3, d)
    y = 1.5 * z[:, 0] - 2.0 * z[:, 3] + label_noise * rng.normal(size=n)
    return x, y, b


def nonlinear(n=240, seed=3):
    rng = np.random.default_rng(seed)
    x = rng.uniform(-2, 2, size=(n, 3))
    return x, np.sin(2 * x[:, 0]) + x[:, 1] ** 2


# ---------------------------------------------------------------------------- regressors
def test_simple_linear_recovers_equation_10():
    rng = np.random.default_rng(0)
    x = rng.normal(size=(50, 8))
    s = rng.normal(size=8)
    reg = SimpleLinearRegressor().fit(x, 2.5 + x @ s)
    assert reg.fit(x, 2.5 + x @ s) is reg
    np.testing.assert_allclose(reg.coef_, s, atol=1e-10)
    assert reg.intercept_ == pytest.approx(2.5)
    np.testing.assert_allclose(reg.gradient(x[0]), s, atol=1e-10)
    assert reg.gradient(x).shape == x.shape
    assert isinstance(reg.predict(x[0]), float)


def test_filtered_linear_rejects_noise_components_by_contribution():
    x, y, b = shape_like(60, 70)
    reg = FilteredLinearRegressor(rng=0).fit(x, y)
    assert 2 <= reg.n_kept_ <= 10                       # most of the 59 components are rejected
    assert reg.kept_.sum() == reg.n_kept_
    # the two best-contributing components are the label's latent axes 0 and 3
    top = np.abs(reg.components_[reg.order_[:2]] @ b.T)
    assert top[0, 0] > 0.7 and top[1, 3] > 0.7
    # contribution order, and the gradient is the sum of the kept components only
    c = reg.contribution_[reg.order_]
    assert np.all(np.diff(c) <= 1e-12)
    np.testing.assert_allclose(reg.coef_, (reg.component_coef_ * reg.kept_) @ reg.components_, atol=1e-12)
    assert reg.cv_rmse_.argmin() == reg.n_kept_


def test_filtered_beats_simple_with_few_samples_in_high_d():
    """Table 1's argument: N close to D (or PCA coefficients, K = N - 1), noisy labels."""
    x, y, _ = shape_like(60, 70)
    table = cross_validated_rmse(x, {"y": y}, {
        "simple linear": SimpleLinearRegressor,
        "filtered linear": lambda: FilteredLinearRegressor(rng=0),
        "filtered (variance order)": lambda: FilteredLinearRegressor(order="variance", rng=0),
    }, folds=10, rng=1)
    simple, filtered, classic = table.rmse[:, 0]
    assert filtered < 0.75 * simple and classic < 0.75 * simple
    # (contribution vs variance order: close here, and which wins depends on the data; see
    # docs/semantics.md. Both are exposed so Table 1 can compare them on real scans.)
    # on the PCA coefficients (K = N - 1) too: the internal PCA is then a mere rotation
    xc = x - x.mean(axis=0)
    z = xc @ np.linalg.svd(xc, full_matrices=False)[2][:59].T
    t2 = cross_validated_rmse(z, {"y": y}, {"s": SimpleLinearRegressor, "f": lambda: FilteredLinearRegressor(rng=0)},
                              rng=1)
    assert t2.rmse[1, 0] < 0.75 * t2.rmse[0, 0]


def test_filtered_variance_order_is_classic_truncation():
    x, y, _ = shape_like(60, 70)
    reg = FilteredLinearRegressor(order="variance", n_components=5, rng=0).fit(x, y)
    np.testing.assert_array_equal(reg.order_[:5], np.arange(5))
    assert reg.n_kept_ <= 5 and len(reg.cv_rmse_) == 6


@pytest.mark.parametrize("method", ["kernel_ridge", "svr"])
def test_kernel_regressor_beats_linear_on_nonlinear_label(method):
    x, y = nonlinear()
    table = cross_validated_rmse(x, {"y": y}, {
        "linear": SimpleLinearRegressor,
        "kernel": lambda: KernelRegressor(method=method, C=(10.0, 100.0), cv=3, rng=0),
    }, folds=5, rng=2)
    lin, ker = table.rmse[:, 0]
    assert ker < 0.2 * lin


@pytest.mark.parametrize("method,standardize", [("kernel_ridge", "global"), ("kernel_ridge", "features"),
                                                ("svr", "features")])
def test_kernel_gradient_is_analytic(method, standardize):
    x, y = nonlinear(120)
    x = x * np.array([1.0, 3.0, 0.5])                  # unequal column scales
    reg = KernelRegressor(method=method, standardize=standardize, gamma=0.5, alpha=1e-2, C=10.0).fit(x, y)
    pts = np.random.default_rng(5).uniform(-1.5, 1.5, size=(6, 3))
    g = reg.gradient(pts)
    h = 1e-5
    fd = np.stack([(reg.predict(pts + h * e) - reg.predict(pts - h * e)) / (2 * h) for e in np.eye(3)], axis=1)
    np.testing.assert_allclose(g, fd, rtol=1e-6, atol=1e-7)
    np.testing.assert_allclose(reg.gradient(pts[0]), g[0])


def test_kernel_ridge_selects_hyperparameters_and_round_trips_arrays():
    x, y = nonlinear(100)
    reg = KernelRegressor(standardize="features").fit(x, y)
    assert reg.cv_rmse_.shape == (6, 11)
    assert reg.cv_rmse_.min() == pytest.approx(reg.cv_rmse_[list(reg.cv_rmse_.min(axis=1)).index(
        reg.cv_rmse_.min())].min())
    back = KernelRegressor.from_arrays(reg.to_arrays())
    np.testing.assert_allclose(back.predict(x[:7]), reg.predict(x[:7]))
    np.testing.assert_allclose(back.gradient(x[:7]), reg.gradient(x[:7]))
    f = FilteredLinearRegressor(rng=0).fit(*shape_like(40, 30)[:2])
    f2 = FilteredLinearRegressor.from_arrays(f.to_arrays())
    assert f2.n_kept_ == f.n_kept_ and isinstance(f2.n_kept_, int)


# ---------------------------------------------------------------------------- Eq. 11, morphing
def test_equation_11_two_constraints_linear_exact():
    x, _, _ = shape_like(80, 20, seed=4)
    rng = np.random.default_rng(4)
    stature = SimpleLinearRegressor().fit(x, x @ rng.normal(size=20) + 170)
    weight = SimpleLinearRegressor().fit(x, x @ rng.normal(size=20) + 70)
    g = np.stack([stature.coef_, weight.coef_])
    z = morph_directions(g, [5.0, 0.0])                # "taller but the same weight"
    x0 = x[0]
    assert stature.predict(x0 + z) - stature.predict(x0) == pytest.approx(5.0, abs=1e-9)
    assert weight.predict(x0 + z) - weight.predict(x0) == pytest.approx(0.0, abs=1e-9)
    # minimum norm: z lies in the span of the gradients
    coef, *_ = np.linalg.lstsq(g.T, z, rcond=None)
    np.testing.assert_allclose(g.T @ coef, z, atol=1e-10)
    # Eq. 11 as written, <z, v_i>/|v_i| = |v_i| with v_i = delta_i s_i/|s_i|^2, for delta != 0
    z2 = morph_directions(g, [5.0, -3.0])
    for s, dlt in zip(g, [5.0, -3.0]):
        v = dlt * s / (s @ s)
        assert z2 @ v / np.linalg.norm(v) == pytest.approx(np.linalg.norm(v))
    # one constraint: walk the gradient
    s = g[0]
    np.testing.assert_allclose(morph_directions(s, 2.0), 2.0 * s / (s @ s))
    # weighted minimum norm still meets the constraints
    zw = morph_directions(g, [5.0, 0.0], metric=np.linspace(1, 10, 20))
    np.testing.assert_allclose(g @ zw, [5.0, 0.0], atol=1e-9)
    assert np.linalg.norm(zw) >= np.linalg.norm(z) - 1e-12


def test_morph_walks_nonlinear_regressors_holding_keep():
    rng = np.random.default_rng(7)
    x = rng.uniform(-2, 2, size=(200, 4))
    a = KernelRegressor(standardize="features").fit(x, x[:, 0] + 0.3 * x[:, 1] ** 2)
    b = KernelRegressor(standardize="features").fit(x, np.tanh(x[:, 1]) + x[:, 2])
    x0 = np.zeros(4)
    target = a.predict(x0) + 1.0
    path = morph(x0, {"a": a, "b": b}, {"a": target}, keep=["b"], steps=8)
    assert path.shape[1] == 4 and len(path) >= 9
    np.testing.assert_allclose(path[0], x0)
    assert a.predict(path[-1]) == pytest.approx(target, abs=1e-6)
    assert b.predict(path[-1]) == pytest.approx(b.predict(x0), abs=1e-6)
    # held at an explicit value; linear regressors reach the target in one step
    lin = SimpleLinearRegressor().fit(x, x @ np.array([1.0, 2.0, 0.0, -1.0]))
    p2 = morph(x0, {"l": lin, "b": b}, {"l": 3.0}, keep={"b": 0.5}, steps=1, refine=20)
    assert lin.predict(p2[1]) == pytest.approx(3.0, abs=1e-9)
    assert b.predict(p2[-1]) == pytest.approx(0.5, abs=1e-6)


# ---------------------------------------------------------------------------- §5.1 comparisons
def test_comparison_direction_recovers_known_direction():
    rng = np.random.default_rng(11)
    d = 6
    truth = rng.normal(size=d)
    truth /= np.linalg.norm(truth)
    a, b = rng.normal(size=(2, 3000, d))
    swap = (b - a) @ truth < 0                          # the judge: b is the more muscular
    a[swap], b[swap] = b[swap].copy(), a[swap].copy()
    u = comparison_direction(a, b)
    assert np.linalg.norm(u) == pytest.approx(1.0)
    assert u @ truth > 0.98
    # as a regressor over a database, with index pairs
    x = rng.normal(size=(400, d))
    i, j = rng.integers(0, 400, size=(2, 2000))
    i, j = i[i != j], j[i != j]
    less = np.where((x[j] - x[i]) @ truth > 0, i, j)
    more = np.where((x[j] - x[i]) @ truth > 0, j, i)
    reg = ComparisonRegressor().fit(x, np.stack([less, more], axis=1))
    assert reg.direction_ @ truth > 0.98
    assert np.std(reg.predict(x)) == pytest.approx(1.0)
    step = morph_directions(reg.gradient(x[0]), 1.0)
    assert reg.predict(x[0] + step) - reg.predict(x[0]) == pytest.approx(1.0)


# ---------------------------------------------------------------------------- §4.1 basis
def test_semantic_basis_round_trip_and_semantic_coordinates():
    rng = np.random.default_rng(3)
    x = rng.normal(size=(50, 8)) * np.linspace(3, 0.5, 8)       # PCA-coefficient-like, N - 1 > D
    dirs = rng.normal(size=(2, 8))
    basis = SemanticBasis().fit(dirs, x)
    assert basis.components_.shape == (8, 8)
    np.testing.assert_allclose(basis.components_ @ basis.components_.T, np.eye(8), atol=1e-12)
    c = basis.transform(x)
    np.testing.assert_allclose(basis.inverse_transform(c), x, atol=1e-12)
    new = rng.normal(size=(5, 8))                                # complete basis: any body
    np.testing.assert_allclose(basis.inverse_transform(basis.transform(new)), new, atol=1e-12)
    q, r = np.linalg.qr(dirs.T)
    q = (q * np.sign(np.diag(r))).T                              # Gram-Schmidt = QR with R_ii > 0
    np.testing.assert_allclose(basis.semantic_components_, q, atol=1e-12)
    sem, res = basis.split(c)
    np.testing.assert_allclose(sem, (x - x.mean(axis=0)) @ q.T, atol=1e-12)
    assert res.shape == (50, 6)
    assert np.all(np.diff(basis.explained_variance_) <= 1e-12)
    np.testing.assert_allclose(basis.transform(x[0]), c[0])


def test_semantic_basis_high_d_and_invariance():
    x, y, _ = shape_like(30, 100, seed=2)
    reg = SimpleLinearRegressor().fit(x, y)
    basis = SemanticBasis().fit(reg.coef_[None], x)
    assert basis.n_components_ == 29     # the gradient lies in the data span: 1 + (N - 2) residual
    np.testing.assert_allclose(basis.inverse_transform(basis.transform(x)), x, atol=1e-10)
    # moving along residual coordinates leaves the linear label unchanged
    c = basis.transform(x[0])
    c[1:] += np.random.default_rng(0).normal(size=c.size - 1)
    assert reg.predict(basis.inverse_transform(c)) == pytest.approx(reg.predict(x[0]), abs=1e-8)


# ---------------------------------------------------------------------------- Tables 1 and 2
def test_tables_and_direction_angles():
    x, y = nonlinear(150)
    lin_label = x @ np.array([1.0, -2.0, 0.5])
    table = cross_validated_rmse(x, {"Height": lin_label, "Curved": y}, rng=0)
    assert table.rmse.shape == (3, 2) and table.folds == 10
    assert table.regressors == ["simple linear", "filtered linear", "non-linear"]
    text, md = format_rmse_table(table), table.to_markdown()
    assert "filtered linear" in text and "Height" in text.splitlines()[0]
    assert md.startswith("| Regressor | Height | Curved |") and md.count("\n") == 4
    ker_lin = KernelRegressor(standardize="features").fit(x, lin_label)
    ker_curved = KernelRegressor(standardize="features").fit(x, y)
    m_lin, s_lin = direction_angles(ker_lin, x)
    m_cur, s_cur = direction_angles(ker_curved, x)
    assert m_lin < 5 and m_cur > 20 and s_lin >= 0
    assert direction_angles(SimpleLinearRegressor().fit(x, lin_label), x) == pytest.approx((0.0, 0.0), abs=1e-5)
    pair = direction_angles(ker_lin, x[:20], reference="pairwise")
    assert pair[0] > 0
    angles = format_angle_table({"Height": (m_lin, s_lin), "Curved": (m_cur, s_cur)}, markdown=True)
    assert "| μ |" in angles and "| σ |" in angles
    # missing labels (NaN) are left out; groups keep a subject in one fold
    y2 = lin_label.copy()
    y2[:10] = np.nan
    t2 = cross_validated_rmse(x, {"h": y2}, {"s": SimpleLinearRegressor}, rng=0, groups=np.arange(150) // 3)
    assert t2.n_samples[0] == 140 and t2.rmse[0, 0] < 1e-8


# ---------------------------------------------------------------------------- bad input
def test_bad_inputs_raise_parameter_error():
    x, y, _ = shape_like(20, 8)
    with pytest.raises(ParameterError, match="y: length 19, expected 20"):
        SimpleLinearRegressor().fit(x, y[:-1])
    bad = x.copy()
    bad[0, 0] = np.nan
    with pytest.raises(ParameterError, match="X: contains NaN"):
        FilteredLinearRegressor().fit(bad, y)
    with pytest.raises(ParameterError, match="not fitted"):
        KernelRegressor().predict(x)
    reg = SimpleLinearRegressor().fit(x, y)
    with pytest.raises(ParameterError, match="length 4, expected 8"):
        reg.predict(x[:, :4])
    with pytest.raises(ParameterError, match="order="):
        FilteredLinearRegressor(order="eigen").fit(x, y)
    with pytest.raises(ParameterError, match="method="):
        KernelRegressor(method="gp").fit(x, y)
    with pytest.raises(ParameterError, match="gamma"):
        KernelRegressor(gamma=-1.0).fit(x, y)
    with pytest.raises(ParameterError, match="deltas: length 1, expected 2"):
        morph_directions(np.ones((2, 8)), [1.0])
    with pytest.raises(ParameterError, match="identical"):
        comparison_direction(x[:3], x[:3])
    with pytest.raises(ParameterError, match="linear combination"):
        gram_schmidt(np.array([[1.0, 0, 0], [2.0, 0, 0]]))
    with pytest.raises(ParameterError, match="directions"):
        SemanticBasis().fit(np.ones((2, 8)), x)
    with pytest.raises(ParameterError, match="unknown label 'mass'"):
        morph(x[0], {"h": reg}, {"mass": 3.0})
    with pytest.raises(ParameterError, match="also in targets"):
        morph(x[0], {"h": reg}, {"h": 3.0}, keep=["h"])
    with pytest.raises(ParameterError, match="folds"):
        cross_validated_rmse(x, {"h": y}, folds=1)
    with pytest.raises(ParameterError, match=r"labels\['h'\]: shape"):
        cross_validated_rmse(x, {"h": y[:3]})
    with pytest.raises(ParameterError, match="pairs"):
        ComparisonRegressor().fit(x, np.array([[0, 25]]))


# ----------------------------------------------------------------------------------- the closed loop
def _linear_problem(k=6, seed=0):
    gen = np.random.default_rng(seed)
    a = gen.normal(size=(2, k))
    variances = np.linspace(2.0, 0.5, k)
    return a, variances


def test_closed_loop_converges_on_a_tiny_linear_problem():
    a, var = _linear_problem()
    # the "measured" values are mildly non-linear, the regressors' gradients are a's rows
    calls = []

    def body(c):
        calls.append(c)
        return np.tile(c, (2, 1))  # a stand-in mesh (V=2, K)

    def values_of(x, c):
        return a @ c + 0.05 * np.sum(c ** 2), {"n": len(calls)}

    c0 = np.zeros(6)
    goal = np.array([1.0, -0.5])
    tol = np.array([1e-4, 1e-4])
    r = closed_loop(c0, goal, tol, var, a, body, values_of)
    assert r.converged and not r.missed.any()
    assert np.all(np.abs(values_of(None, r.coefficients)[0] - goal) <= tol)
    assert r.coefficients.shape == (6,) and r.vertices.shape == (2, 6) and r.values.shape == (2,)
    assert 1 <= r.iterations <= 20 and r.solve_s >= 0
    # purely linear: Equation 11 alone lands, one correction, the minimum-norm step in the metric
    r = closed_loop(c0, goal, tol, var, a, body, lambda x, c: (a @ c, {}))
    assert r.converged and r.iterations == 1
    m = var[:, None] * a.T
    np.testing.assert_allclose(r.coefficients, m @ np.linalg.solve(a @ m, goal), atol=1e-10)


def test_closed_loop_reports_a_miss_when_unreachable():
    a, var = _linear_problem()
    # the second value is the first one again: asking 1 and 2 at once cannot be met
    g = np.vstack([a[0], a[0]])
    r = closed_loop(np.zeros(6), np.array([1.0, 2.0]), np.array([1e-3, 1e-3]), var, g, lambda c: c[None],
                    lambda x, c: (g @ c, {}), max_iter=8)
    assert not r.converged and r.missed.any()
    assert r.iterations <= 8 + BACKTRACKS - 1  # checked before a step; its backtracking finishes
    # the loop still found the least-squares compromise between the two
    assert abs(r.values[0] - 1.5) < 0.05
