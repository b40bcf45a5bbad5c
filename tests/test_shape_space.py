"""PCA shape space over encoded bodies, sampling, projection, and the comparison metrics."""

import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from bodyspace.encoding import RelativeRotationEncoder, VertexEncoder
from bodyspace.errors import ParameterError
from bodyspace.mesh.alignment import rigid_procrustes
from bodyspace.shape import (
    ShapeSpace,
    fit_coefficients,
    mean_relative_edge_change,
    relative_volume_change,
)
from bodyspace.shape.refine import _free_directions, _with_components, refine_basis


@pytest.fixture(scope="module")
def population():
    """A small closed-mesh population: an ellipsoid family with two shape parameters and a
    random pose (rigid motion) each."""
    m = trimesh.creation.icosphere(subdivisions=2)
    v, f = np.asarray(m.vertices), np.asarray(m.faces)
    rng = np.random.default_rng(3)
    params = rng.normal(size=(12, 2)) * [0.15, 0.1]
    scans = []
    for k, (a, b) in enumerate(params):
        x = v * [1 + a, 1.7 + b, 1 - a]
        x = x + 0.02 * np.sin(3 * v[:, [1, 2, 0]]) * (k % 3)
        scans.append(x @ Rotation.random(random_state=k).as_matrix().T + rng.normal(size=3))
    return v * [1, 1.7, 1], f, np.stack(scans)


@pytest.fixture(scope="module")
def rre(population):
    v, f, scans = population
    enc = RelativeRotationEncoder(v, f).fit(scans)
    return enc, enc.encode(scans)


def test_pca_attributes_and_round_trip(rre):
    enc, codes = rre
    space = ShapeSpace(enc).fit(codes)
    k = space.n_components_
    assert k == len(codes) - 1
    assert space.components_.shape == (k, codes.shape[1])
    np.testing.assert_allclose(space.components_ @ space.components_.T, np.eye(k), atol=1e-10)
    r = space.explained_variance_ratio_
    assert np.all(np.diff(space.explained_variance_) <= 1e-12) and abs(r.sum() - 1) < 1e-10
    z = space.transform(codes)
    np.testing.assert_allclose(space.inverse_transform(z), codes, atol=1e-10)
    np.testing.assert_allclose(z.mean(0), 0, atol=1e-10)
    np.testing.assert_allclose(z.var(0, ddof=1), space.explained_variance_, rtol=1e-8)


def test_matches_sklearn(rre):
    sk = pytest.importorskip("sklearn.decomposition")
    _, codes = rre
    ours = ShapeSpace(n_components=4).fit(codes)
    ref = sk.PCA(n_components=4, svd_solver="full").fit(codes)
    np.testing.assert_allclose(ours.explained_variance_ratio_, ref.explained_variance_ratio_, rtol=1e-8)
    np.testing.assert_allclose(ours.transform(codes), ref.transform(codes), atol=1e-8)


def test_n_components_and_selection(rre):
    _, codes = rre
    space = ShapeSpace(n_components=0.9).fit(codes)
    assert space.explained_variance_ratio_.sum() >= 0.9
    assert space.explained_variance_ratio_[:-1].sum() < 0.9
    sub = ShapeSpace(n_components=2).fit(codes, select=np.arange(12) < 6)
    assert sub.n_samples_ == 6 and sub.n_components_ == 2
    np.testing.assert_allclose(sub.mean_, codes[:6].mean(0))
    with pytest.raises(ParameterError, match="n_components"):
        ShapeSpace(n_components=50).fit(codes)
    with pytest.raises(ParameterError, match="expected"):
        sub.transform(codes[:, :-1])
    with pytest.raises(ParameterError, match="not fitted"):
        ShapeSpace().transform(codes)


def test_solvers_share_one_fit_path_and_one_n_components_rule(rre, tmp_path, monkeypatch):
    _, codes = rre
    full = ShapeSpace(n_components=3, solver="full").fit(codes)
    # the Krylov solver on a float32 memory map of the codes (not copied), its basis capped at
    # the 12 codes: the exact PCA to float32 precision, the same learned attributes
    mm = np.lib.format.open_memmap(tmp_path / "codes.npy", mode="w+", dtype=np.float32, shape=codes.shape)
    mm[:] = codes
    krylov = ShapeSpace(n_components=3, solver="krylov", rng=0).fit(mm)
    assert full.solver_ == "full" and krylov.solver_ == "krylov"
    for name in ("mean_", "singular_values_", "explained_variance_", "explained_variance_ratio_"):
        np.testing.assert_allclose(getattr(krylov, name), getattr(full, name), rtol=1e-4, atol=1e-6, err_msg=name)
    np.testing.assert_allclose(np.abs(np.sum(krylov.components_ * full.components_, axis=1)), 1, atol=1e-4)
    np.testing.assert_allclose(krylov.total_variance_, full.total_variance_, rtol=1e-5)
    # "auto": exact below FULL_PCA_MAX_BYTES or for a variance fraction, Krylov beyond
    assert ShapeSpace(n_components=3).fit(codes).solver_ == "full"
    monkeypatch.setattr("bodyspace.shape.pca.FULL_PCA_MAX_BYTES", 8)
    assert ShapeSpace(n_components=3).fit(codes).solver_ == "krylov"
    assert ShapeSpace(n_components=0.9).fit(codes).solver_ == "full"
    with pytest.raises(ParameterError, match="variance fraction needs the exact PCA"):
        ShapeSpace(n_components=0.9, solver="krylov").fit(codes)
    for bad in (0, -1, 1.5, "3", True):
        with pytest.raises(ParameterError, match="n_components"):
            ShapeSpace(n_components=bad).fit(codes)
    with pytest.raises(ParameterError, match="solver='svd'"):
        ShapeSpace(solver="svd").fit(codes)
    with pytest.raises(ParameterError, match="n_components=12, expected 1..11"):
        ShapeSpace(n_components=12, solver="krylov").fit(codes)
    bad = codes.copy()
    bad[3, 7] = np.nan
    for solver in ("full", "krylov"):
        with pytest.raises(ParameterError, match="NaN"):
            ShapeSpace(solver=solver).fit(bad)
    # copy=True (the default) leaves the caller's matrix alone
    before = codes.copy()
    ShapeSpace().fit(codes)
    np.testing.assert_array_equal(codes, before)


def test_state_round_trips_through_arrays(rre):
    enc, codes = rre
    space = ShapeSpace(enc, n_components=4).fit(codes)
    arrays = space.to_arrays("pca_")
    assert arrays["pca_components"].dtype == np.float32 and arrays["pca_n_samples"] == 12
    back = ShapeSpace.from_arrays(arrays, "pca_", enc)
    np.testing.assert_array_equal(back.mean_, space.mean_)
    np.testing.assert_array_equal(back.explained_variance_ratio_, space.explained_variance_ratio_)
    assert back.n_components_ == 4 and back.n_samples_ == 12 and back.n_features_in_ == codes.shape[1]
    np.testing.assert_allclose(back.components_, space.components_, atol=1e-6)  # float32 on disk
    broken = dict(arrays, pca_singular_values=arrays["pca_singular_values"][:2])
    with pytest.raises(ParameterError, match="'pca_singular_values' has shape"):
        ShapeSpace.from_arrays(broken, "pca_")
    with pytest.raises(ParameterError, match="pca_mean missing"):
        ShapeSpace.from_arrays({k: v for k, v in arrays.items() if k != "pca_mean"}, "pca_")
    # the encoder's state too
    enc_back = RelativeRotationEncoder.from_arrays(enc.to_arrays("e_"), "e_", enc.template_vertices, enc.faces)
    np.testing.assert_array_equal(enc_back.encode(enc.mean_vertices_), enc.encode(enc.mean_vertices_))
    with pytest.raises(ParameterError, match="e_mean_stretch"):
        RelativeRotationEncoder.from_arrays({"e_mean_vertices": enc.mean_vertices_}, "e_", enc.template_vertices,
                                            enc.faces)


def test_sampling(rre):
    enc, codes = rre
    space = ShapeSpace(enc).fit(codes)
    z1 = space.sample_coefficients(500, n_components=3, sigma_range=2.0, rng=5)
    z2 = space.sample_coefficients(500, n_components=3, sigma_range=2.0, rng=np.random.default_rng(5))
    np.testing.assert_array_equal(z1, z2)
    sd = np.sqrt(space.explained_variance_)
    assert np.all(np.abs(z1[:, :3]) <= 2.0 * sd[:3] + 1e-12)
    assert np.all(z1[:, 3:] == 0)
    assert np.all(np.abs(z1[:, 0]).max() > 1.5 * sd[0])  # the range is used, not just the middle
    lo = space.sample_coefficients(200, sigma_range=(1.0, 2.0), rng=1)
    assert np.all(lo[:, 0] >= sd[0] - 1e-12)
    bodies = space.sample(3, n_components=2, rng=0)
    assert bodies.shape == (3, enc.n_vertices, 3) and np.isfinite(bodies).all()
    with pytest.raises(ParameterError, match="sigma_range"):
        space.sample_coefficients(2, sigma_range=(1.0, -1.0))


@pytest.mark.parametrize("encoder_cls", [RelativeRotationEncoder, VertexEncoder])
def test_project_and_reconstruct(population, encoder_cls):
    v, f, scans = population
    enc = encoder_cls(v, f).fit(scans)
    space = ShapeSpace(enc).fit(scans)  # meshes are encoded on the way in
    z = space.project(scans[:3])
    assert z.shape == (3, space.n_components_)
    back = space.reconstruct(z)
    target = rigid_procrustes(scans[:3], enc.mean_vertices_)[0]
    assert np.abs(back - target).max() < 1e-6 * np.ptp(scans[..., 1])
    # The mean body (zero coefficients) is intact: close to the population average.
    mean_body = space.reconstruct(np.zeros(1))[0]
    assert abs(relative_volume_change(enc.mean_vertices_, mean_body, f)) < 0.05


def test_metrics_on_known_deformations():
    m = trimesh.creation.icosphere(subdivisions=2)
    v, f = np.asarray(m.vertices), np.asarray(m.faces)
    assert mean_relative_edge_change(v, v, f) == 0
    np.testing.assert_allclose(mean_relative_edge_change(v, 1.1 * v, f), 0.1)
    np.testing.assert_allclose(relative_volume_change(v, 1.1 * v, f), 1.1 ** 3 - 1)
    r = Rotation.random(random_state=0).as_matrix()
    np.testing.assert_allclose(mean_relative_edge_change(v, v @ r.T + 2, f), 0, atol=1e-12)
    assert mean_relative_edge_change(v, np.stack([v, 2 * v]), f).shape == (2,)


def test_vertex_ordered_basis(rre, population):
    """basis="vertex": orthonormal code directions whose first k span the training codes that
    make vertex PCA's first k components; the same from the scans or from decoding the codes."""
    enc, codes = rre
    _, _, scans = population
    space = ShapeSpace(enc, basis="vertex").fit(codes, vertices=scans)
    k = space.n_components_
    assert space.basis_ == "vertex" and k == len(codes) - 1 and space.vertex_variance_.shape == (k,)
    assert np.all(np.diff(space.vertex_variance_) <= 1e-12)      # ordered by vertex variance
    np.testing.assert_allclose(space.components_ @ space.components_.T, np.eye(k), atol=1e-10)
    # The first k span C^T U_k: U from the vertex PCA of the rigidly aligned scans.
    aligned = VertexEncoder(scans.mean(0), enc.faces).fit(scans).encode(scans)
    u = np.linalg.svd(aligned - aligned.mean(0), full_matrices=False)[0]
    b = (codes - codes.mean(0)).T @ u
    for j in (1, 3, 6):
        q = space.components_[:j]
        residual = b[:, :j] - q.T @ (q @ b[:, :j])
        assert np.linalg.norm(residual) < 1e-8 * np.linalg.norm(b[:, :j])
        if j < k:   # not the code PCA's order: its first j directions span another space
            code_pca = ShapeSpace(enc, n_components=j).fit(codes).components_
            assert np.linalg.norm(b[:, :j] - code_pca.T @ (code_pca @ b[:, :j])) > 1e-3 * np.linalg.norm(b[:, :j])
    # Without the scans the codes are decoded: the same basis (decoding is exact up to a rigid motion).
    decoded = ShapeSpace(enc, basis="vertex").fit(codes)
    np.testing.assert_allclose(np.abs(decoded.components_ @ space.components_.T), np.eye(k), atol=1e-5)
    # Coefficients still reconstruct the training codes exactly (the same span, all components).
    np.testing.assert_allclose(space.inverse_transform(space.transform(codes)), codes, atol=1e-9)
    back = ShapeSpace.from_arrays(space.to_arrays(), encoder=enc)
    assert back.basis_ == "vertex"
    np.testing.assert_allclose(back.vertex_variance_, space.vertex_variance_)
    assert ShapeSpace.from_arrays(ShapeSpace(enc).fit(codes).to_arrays(), encoder=enc).basis_ == "code"
    # A float fraction counts vertex variance; the Krylov solver cannot order by it.
    frac = ShapeSpace(enc, 0.9, basis="vertex").fit(codes, vertices=scans)
    share = np.cumsum(space.vertex_variance_) / space.vertex_variance_.sum()
    assert frac.n_components_ == int(np.searchsorted(share, 0.9) + 1)
    with pytest.raises(ParameterError, match="basis='vertex' needs the exact PCA"):
        ShapeSpace(enc, 3, basis="vertex", solver="krylov").fit(codes)
    with pytest.raises(ParameterError, match="basis='banana'"):
        ShapeSpace(enc, basis="banana").fit(codes)
    with pytest.raises(ParameterError, match="vertices: shape"):
        ShapeSpace(enc, basis="vertex").fit(codes, vertices=scans[:3])


def test_vertex_basis_of_the_vertex_encoding_is_vertex_pca(population):
    v, f, scans = population
    enc = VertexEncoder(v, f).fit(scans)
    codes = enc.encode(scans)
    a, b = ShapeSpace(enc, basis="vertex").fit(codes), ShapeSpace(enc).fit(codes)
    np.testing.assert_allclose(a.components_, b.components_)
    # Its vertex variance is its code variance, and the space round-trips through a file's arrays.
    np.testing.assert_allclose(a.vertex_variance_, a.explained_variance_)
    back = ShapeSpace.from_arrays(a.to_arrays(), encoder=enc)
    assert back.basis_ == "vertex" and np.allclose(back.vertex_variance_, a.vertex_variance_)


def test_refined_basis(rre, population):
    """basis="refined": the vertex order's leading components rotated inside each level's span
    (the spans, and so every k >= span, unchanged; the first k of a level kept by the next), the
    training bodies' vertex fit error at each level's k lowered, and a file's arrays round-trip
    (a file without the levels loads as the vertex order, as files written before)."""
    enc, codes = rre
    _, _, scans = population
    vertex = ShapeSpace(enc, 6, basis="vertex").fit(codes, vertices=scans)
    space = ShapeSpace(enc, 6, basis="refined", refine_levels=[(1, 3), (2, 5)]).fit(codes, vertices=scans)
    c, v = space.components_, vertex.components_
    np.testing.assert_allclose(c @ c.T, np.eye(6), atol=1e-10)
    # The last level's span is kept (the first 5 vertex components lie in the refined ones' span),
    # and so are the components past it and the first one (``refine.KEEP``).
    np.testing.assert_allclose((v[:5] @ c[:5].T) @ c[:5], v[:5], atol=1e-9)
    np.testing.assert_allclose(c[5:], v[5:], atol=1e-12)
    np.testing.assert_allclose(c[0], v[0], atol=1e-12)
    rep = space.refine_report_
    assert rep.levels.tolist() == [[1, 3], [2, 5]] and space.refine_levels_.tolist() == [[1, 3], [2, 5]]
    assert rep.train_error_m[0] == []          # k = 1 <= KEEP: nothing to turn
    assert np.all(np.diff(rep.train_error_m[1]) < 0)
    # From a bad order (vertex components 1 and 5 swapped) the refinement finds the first one
    # again: the training bodies' fit at k = 1 as good as the vertex order's, not the swapped one's.
    swapped = _with_components(vertex, v[[4, 1, 2, 3, 0, 5]].copy())
    comps, rep1 = refine_basis(swapped, scans, [(1, 5)], keep=0)
    before, vertex_order = (fit_coefficients(s, scans, 1).error_m.mean() for s in (swapped, vertex))
    after = fit_coefficients(_with_components(vertex, comps), scans, 1).error_m.mean()
    assert before > 2 * vertex_order and after < 1.02 * vertex_order and rep1.alternations[0] >= 1
    # The explained variances are the codes' variance along the new components.
    z = space.transform(codes)
    np.testing.assert_allclose(space.explained_variance_, z.var(axis=0, ddof=1), rtol=1e-9)
    back = ShapeSpace.from_arrays(space.to_arrays(), encoder=enc)
    assert back.basis_ == "refined" and back.refine_levels_.tolist() == [[1, 3], [2, 5]]
    np.testing.assert_allclose(back.components_, c.astype(np.float32))
    old = {key: a for key, a in space.to_arrays().items() if key != "pca_refine_levels"}
    assert ShapeSpace.from_arrays(old, encoder=enc).basis_ == "vertex"
    bad = dict(space.to_arrays(), pca_refine_levels=np.array([[3, 2]]))
    with pytest.raises(ParameterError, match="refine levels"):
        ShapeSpace.from_arrays(bad, encoder=enc)
    with pytest.raises(ParameterError, match=r"refine levels: \[\[2, 9\]\].*span <= 6"):
        ShapeSpace(enc, 6, basis="refined", refine_levels=[(2, 9)]).fit(codes, vertices=scans)
    # Default levels are cut to the components kept; an affine decoder has nothing to refine.
    assert ShapeSpace(enc, 3, basis="refined").fit(codes).refine_levels_.tolist() == []
    venc = VertexEncoder(*population[:2]).fit(scans)
    lin = ShapeSpace(venc, basis="refined").fit(venc.encode(scans))
    assert lin.basis_ == "refined" and lin.refine_levels_.shape == (0, 2)
    assert ShapeSpace.from_arrays(lin.to_arrays(), encoder=venc).basis_ == "refined"


def test_refine_free_directions():
    """The basis step: the new free directions are the targets' principal ones in the metric M,
    after the fixed coordinates took what they can (M's Schur complement)."""
    rng = np.random.default_rng(0)
    d = np.array([0.0, 0.6, 0.8, 0.0])                   # free coordinates 1..4 (fixed: coordinate 0)
    w = np.zeros((20, 5))
    w[:, 0] = rng.normal(size=20)
    w[:, 1:] = rng.normal(size=(20, 1)) * d + 1e-3 * rng.normal(size=(20, 4))
    rot = _free_directions(w[:, 1:], np.eye(5), fixed=1)
    np.testing.assert_allclose(rot @ rot.T, np.eye(4), atol=1e-12)
    assert abs(rot[0] @ d) > 0.999
    # A coupled metric: moving coordinate 1 also moves what coordinate 0 does, and the fixed
    # coordinate 0 takes that part: the best free direction for targets along coordinate 0 is
    # then none in particular, and for targets along d the Schur metric weighs coordinate 1 less.
    m = np.eye(5)
    m[0, 1] = m[1, 0] = 0.9
    rot_m = _free_directions(w[:, 1:], m, fixed=1)
    schur = np.eye(4)
    schur[0, 0] = 1 - 0.81
    lam, vec = np.linalg.eigh(schur)
    half = (vec * np.sqrt(lam)) @ vec.T
    best = np.linalg.solve(half, np.linalg.svd(w[:, 1:] @ half)[2][0])
    assert abs(rot_m[0] @ best / np.linalg.norm(best)) > 0.999
