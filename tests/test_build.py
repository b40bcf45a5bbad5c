"""Building a model from many scans: the closed-form encoder against a straightforward reference
encode (per-triangle SVD polar decomposition, scipy rotation vectors), float32 output, and the
randomized PCA against an exact SVD."""

import warnings

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from bodyspace.encoding import RelativeRotationEncoder
from bodyspace.encoding.deformation import (
    polar_decomposition_svd,
    polar_deformation,
    rest_triangles,
)
from bodyspace.encoding.rre import pack_stretch
from bodyspace.errors import MeshError, ParameterError
from bodyspace.mesh.operators import triangle_frames
from bodyspace.model import BodyModel
from bodyspace.shape.solvers import pca_block_krylov
from bodyspace.synth.population import build_population


@pytest.fixture(scope="module")
def posed(template, tmp_path_factory):
    """2 subjects x (rest + 3 LBS poses): the posed scans fold a few triangles over."""
    db = build_population(template, tmp_path_factory.mktemp("pop") / "db", 2, 3, rng=3)
    return np.asarray(db.vertices, dtype=float)


def _reference_encode(enc, x):
    """Codes (N, 15 F) the slow, obvious way: U = frames(x) frames(template)^-1, R S by SVD,
    Q_ij = R_i^T R_j, r_ij = log(Q_ij exp(mean_ij)^-1) with scipy, s = S - mean S."""
    rest = np.linalg.inv(triangle_frames(enc.template_vertices, enc.faces))
    u = triangle_frames(x, enc.faces) @ rest
    r, s = polar_decomposition_svd(u)
    nbr = enc.neighbors
    q = np.swapaxes(r, -1, -2)[:, :, None] @ r[:, nbr]  # (N, F, slot, 3, 3)
    mean = Rotation.from_rotvec(enc.mean_rotvecs_.reshape(-1, 3)).as_matrix().reshape(q.shape[1:])
    rot = Rotation.from_matrix((q @ np.swapaxes(mean, -1, -2)).reshape(-1, 3, 3)).as_rotvec()
    codes = np.concatenate([rot.reshape(len(x), enc.n_faces, 9), pack_stretch(s) - enc.mean_stretch_], axis=-1)
    return codes.reshape(len(x), -1), q


def test_closed_form_polar_matches_svd(posed, template):
    rest = rest_triangles(template.vertices, template.faces)
    r, s, dbl, normal = polar_deformation(posed[:3], template.faces, rest)
    u = triangle_frames(posed[:3], template.faces) @ np.linalg.inv(triangle_frames(template.vertices, template.faces))
    r_ref, s_ref = polar_decomposition_svd(u)
    np.testing.assert_allclose(np.moveaxis(r, 0, -1).reshape(r_ref.shape), r_ref, atol=1e-12)
    np.testing.assert_allclose(np.moveaxis(s, 0, -1), pack_stretch(s_ref), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(r_ref), 1.0, atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(normal, axis=0), 1.0, atol=1e-12)
    cross = np.cross(*(posed[:3][:, template.faces[:, k]] - posed[:3][:, template.faces[:, 0]] for k in (1, 2)))
    np.testing.assert_allclose(dbl, np.linalg.norm(cross, axis=-1), rtol=1e-12)


@pytest.mark.parametrize("kind", ["posed", "random"])
def test_encode_matches_reference_encode(posed, template, kind):
    x = posed
    if kind == "random":
        rng = np.random.default_rng(0)
        x = posed[:3] + rng.normal(scale=2e-3, size=posed[:3].shape)  # ~2 mm noise on ~1 cm edges
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        enc = RelativeRotationEncoder(template.vertices, template.faces, on_flipped="ignore").fit(x)
    ref, q = _reference_encode(enc, x)
    # the mean model: the mean rotation vector of every Q_ij and the mean stretch
    ref_mean = Rotation.from_matrix(q.reshape(-1, 3, 3)).as_rotvec().reshape(q.shape[:3] + (3,)).mean(axis=0)
    np.testing.assert_allclose(enc.mean_rotvecs_, ref_mean, atol=1e-9)
    codes = enc.encode(x)
    # rotation vectors near 180 degrees (fold-overs) are compared as rotations: r and
    # r - 2 pi r / |r| are the same rotation.
    diff = np.abs(codes - ref).max()
    assert diff < 1e-9, diff
    out = np.empty(codes.shape, dtype=np.float32)
    assert enc.encode(x, out=out) is out
    np.testing.assert_array_equal(out, codes.astype(np.float32))


def test_encode_checks_survive_the_closed_form(template, posed):
    enc = RelativeRotationEncoder(template.vertices, template.faces, on_flipped="raise").fit(template.vertices[None])
    bad = template.vertices.copy()
    f = template.faces[100]
    bad[f[1]] = bad[f[0]]
    with pytest.raises(MeshError, match="mesh 0 has .* degenerate triangle"):
        enc.encode(bad)
    with pytest.raises(MeshError, match="mesh 1 is inside out"):
        enc.encode(np.stack([template.vertices, template.vertices * [-1, 1, 1]]))
    folded = [i for i in range(len(posed)) if _has_flips(template, posed[i])]
    assert folded, "the posed population folds triangles over"
    with pytest.raises(MeshError, match="flipped triangle"):
        enc.encode(posed[folded[0]])
    with pytest.raises(ParameterError, match="out:"):
        enc.encode(posed[:2], out=np.empty((2, 5), dtype=np.float32))


def _has_flips(template, x):
    enc = RelativeRotationEncoder(template.vertices, template.faces, on_flipped="ignore")
    enc.on_flipped = "raise"
    try:
        enc._rotations(x, "x", 0)
    except MeshError:
        return True
    return False


def _low_rank(rng, n, d, decay):
    """(n, d) data whose singular values decay like ``decay ** i``, plus an offset."""
    u = np.linalg.qr(rng.standard_normal((n, n)))[0]
    v = np.linalg.qr(rng.standard_normal((d, n)))[0].T
    return (u * decay ** np.arange(n)) @ v * 10 + rng.standard_normal(d)


def test_block_krylov_pca_agrees_with_exact_svd():
    rng = np.random.default_rng(5)
    x = _low_rank(rng, 300, 4000, 0.97)  # slowly decaying, like the RRE codes of a population
    mean = x.mean(axis=0)
    _, s_ref, vt_ref = np.linalg.svd(x - mean, full_matrices=False)
    k = 30
    s, comps = pca_block_krylov(x.astype(np.float32), mean, k, rng=0)
    var, var_ref = s ** 2, s_ref[:k] ** 2
    rel = np.abs(var - var_ref) / var_ref
    # explained variance: the leading 10 components within 0.1%, the leading 20 within 0.5%,
    # all 30 within 5%, the sum within 0.5% (the tail of a slowly decaying spectrum is the
    # hard part for every randomized solver)
    assert rel[:10].max() < 1e-3 and rel[:20].max() < 5e-3 and rel.max() < 5e-2, rel
    assert abs(var.sum() / var_ref.sum() - 1) < 5e-3
    # subspace angles: the leading 20 directions lie in the found 30-dim subspace (the
    # previous solver, pca_randomized, measured 2.1 degrees here; block Krylov 0.5)
    cos = np.linalg.svd(vt_ref[:20] @ comps.T, compute_uv=False)
    assert np.degrees(np.arccos(min(cos.min(), 1.0))) < 2.0
    # each leading component individually (signs fixed by the convention)
    np.testing.assert_allclose(np.abs(np.sum(comps[:10] * vt_ref[:10], axis=1)), 1, atol=1e-3)
    # the found subspace captures the optimal variance to 0.1%
    captured = np.linalg.norm((x - mean) @ comps.T) ** 2
    assert captured > (1 - 1e-3) * var_ref.sum()
    np.testing.assert_allclose(comps @ comps.T, np.eye(k), atol=1e-5)


def test_block_krylov_is_exact_when_its_basis_spans_all_codes():
    # 12 codes: the Krylov basis (3 blocks of up to (2 k + 10) / 3 columns) is capped at 12
    # columns, which span every centred code, so the result is the exact PCA (to float32).
    rng = np.random.default_rng(7)
    x = rng.standard_normal((12, 500)) * np.linspace(3, 0.1, 500) + 1.0
    mean = x.mean(axis=0)
    _, s_ref, vt_ref = np.linalg.svd(x - mean, full_matrices=False)
    for k in (3, 5, 11):
        s, comps = pca_block_krylov(x.astype(np.float32), mean, k, rng=0)
        np.testing.assert_allclose(s, s_ref[:k], rtol=1e-5)
        np.testing.assert_allclose(np.abs(np.sum(comps * vt_ref[:k], axis=1)), 1, atol=1e-5)


def test_fit_from_float32_codes_matches_exact_fit(template, tmp_path):
    db = build_population(template, tmp_path / "db", 3, 3, rng=1)
    exact = BodyModel.fit(db, "rre", "all", n_components=5, template=template, on_flipped="ignore",
                          pca_solver="full")
    fast = BodyModel.fit(db, "rre", "all", n_components=5, template=template, on_flipped="ignore",
                         pca_solver="krylov")
    assert fast.provenance["pca_solver"] == "krylov" and exact.provenance["pca_solver"] == "full"
    np.testing.assert_allclose(fast.space.mean_, exact.space.mean_, atol=1e-6)
    np.testing.assert_allclose(fast.space.explained_variance_ratio_, exact.space.explained_variance_ratio_,
                               rtol=1e-3)
    np.testing.assert_allclose(np.abs(np.sum(fast.space.components_ * exact.space.components_, axis=1)), 1,
                               atol=1e-3)


def test_mean_model_is_bit_identical_for_any_thread_count(template):
    """The mean model sums fixed chunks in order: one thread and two give the same bits."""
    rng = np.random.default_rng(5)
    scans = template.vertices + 0.01 * rng.standard_normal((5, 1, 3)) + 0.002 * np.sin(
        template.vertices @ rng.standard_normal((5, 3, 3)))
    one = RelativeRotationEncoder(template.vertices, template.faces, n_jobs=1).fit(scans)
    two = RelativeRotationEncoder(template.vertices, template.faces, n_jobs=2).fit(scans)
    assert np.array_equal(one.mean_rotvecs_, two.mean_rotvecs_)
    assert np.array_equal(one.mean_stretch_, two.mean_stretch_)
