"""Coefficients fitted to a mesh in vertex space through the decoder (shape.vertex_fit), and the
exact derivatives of the RRE decode it uses (encoding.tangent), on tiny models."""

import numpy as np
import pytest
from _meshes import open_tube
from scipy.spatial.transform import Rotation

from bodyspace.encoding import RelativeRotationEncoder, VertexEncoder
from bodyspace.errors import MeshError, ParameterError
from bodyspace.mesh.alignment import rigid_procrustes
from bodyspace.shape import ShapeSpace, fit_coefficients
from bodyspace.synth.foreign import add_noise, to_frame


def limb(angle, radius, bulge, length=0.8):
    """A tube along +y bent at its middle by ``angle`` about x (an elbow), thickness ``radius``
    and a muscle ``bulge`` on the upper part."""
    v, f = open_tube(16, 10, length, radius)
    y = v[:, 1]
    v = v * (1.0 + bulge * np.exp(-((y - 0.2) / 0.1) ** 2))[:, None] * [1, 0, 1] + v * [0, 1, 0]
    w = np.clip((y - 0.3) / 0.2, 0.0, 1.0)
    w = w * w * (3 - 2 * w)
    out = v.copy()
    for i, (p, wi) in enumerate(zip(v, w)):
        r = Rotation.from_rotvec([angle * wi, 0, 0]).as_matrix()
        out[i] = r @ (p - [0, 0.4, 0]) + [0, 0.4, 0]
    return out, f


@pytest.fixture(scope="module")
def limbs():
    """24 limbs: bend angle, thickness and bulge drawn at random, each in a random rigid placement."""
    rng = np.random.default_rng(5)
    params = np.column_stack([rng.uniform(0.0, 1.6, 24), rng.uniform(0.04, 0.07, 24), rng.uniform(0.0, 0.4, 24)])
    meshes = []
    for k, p in enumerate(params):
        v, f = limb(*p)
        meshes.append(v @ Rotation.random(random_state=k).as_matrix().T + rng.normal(size=3))
    rest, faces = limb(0.0, 0.055, 0.2)
    return rest, faces, np.stack(meshes)


@pytest.fixture(scope="module")
def rre_space(limbs):
    rest, faces, meshes = limbs
    enc = RelativeRotationEncoder(rest, faces).fit(meshes[:18])
    return ShapeSpace(enc).fit(meshes[:18])


def rms(a, b):
    """RMS vertex distance of b aligned rigidly onto a."""
    return float(np.sqrt(np.mean(np.sum((a - rigid_procrustes(b, a)[0]) ** 2, axis=-1))))


def test_tangents_match_finite_differences_and_the_adjoint(rre_space):
    enc = rre_space.encoder
    rng = np.random.default_rng(0)
    # An inconsistent code (a PCA combination): the Hasler Equation 9 system is really solved.
    code = rre_space.inverse_transform(rng.normal(size=4) * np.sqrt(rre_space.explained_variance_[:4]))[0]
    tan = enc.tangent(code)
    np.testing.assert_allclose(tan.vertices, enc.decode(code)[0], atol=1e-9)
    directions = rng.normal(size=(3, enc.n_features_)) * 0.01
    jvp = tan.jvp(directions)
    h = 1e-6
    for d, j in zip(directions, jvp):
        fd = (enc.decode(code + h * d)[0] - enc.decode(code - h * d)[0]) / (2 * h)
        # The placement's own (rigid) change is left out of the tangent: compare after removing
        # the best infinitesimal rigid motion from the difference.
        x = tan.vertices - tan.vertices.mean(axis=0)
        basis = np.concatenate([np.kron(np.ones((len(x), 1)), np.eye(3)),
                                np.stack([np.cross(e, x).ravel() for e in np.eye(3)], axis=1)], axis=1)
        diff = (fd - j).ravel()
        diff -= basis @ np.linalg.lstsq(basis, diff, rcond=None)[0]
        assert np.abs(diff).max() < 1e-6 * np.abs(fd).max() + 1e-9
    cot = rng.normal(size=(2, enc.n_vertices, 3))
    back = tan.vjp(cot)
    np.testing.assert_allclose(back @ directions.T, np.einsum("nvc,mvc->nm", cot, jvp), rtol=1e-9, atol=1e-12)
    with pytest.raises(ParameterError, match="expected one"):
        enc.tangent(np.zeros((2, enc.n_features_)))


def test_vertex_fit_is_never_worse_than_the_code_projection(rre_space, limbs):
    _, _, meshes = limbs
    held = meshes[18:]
    for k in (1, 3, rre_space.n_components_):
        z_code = rre_space.project(held, method="code", n_components=k)
        fit = fit_coefficients(rre_space, held, k)
        z_fit = rre_space.project(held, n_components=k)      # method="vertex" is the default
        np.testing.assert_array_equal(z_fit, fit.coefficients)
        assert (z_fit[:, k:] == 0).all() and (z_code[:, k:] == 0).all()
        for y, zc, zf, e0, e in zip(held, z_code, z_fit, fit.start_error_m, fit.error_m):
            code_rms = rms(rre_space.reconstruct(zc)[0], y)
            fit_rms = rms(rre_space.reconstruct(zf)[0], y)
            assert fit_rms <= code_rms * (1 + 1e-9)
            assert e <= e0 * 1.01
        # With 3 components (the population's bend, thickness, bulge) the code projection
        # leaves the forearm turned by a few mm; the fit brings it back.
        if k == 3:
            assert fit.error_m.mean() < 0.3 * fit.start_error_m.mean()


def test_vertex_fit_is_exact_for_a_mesh_in_the_span(rre_space):
    rng = np.random.default_rng(3)
    k = 5
    z_true = np.zeros((1, rre_space.n_components_))
    z_true[0, :k] = rng.normal(size=k) * np.sqrt(rre_space.explained_variance_[:k])
    body = rre_space.reconstruct(z_true)[0]
    moved = body @ Rotation.random(random_state=9).as_matrix().T + [0.3, -1.2, 2.0]
    z_code = rre_space.project(moved, method="code", n_components=k)
    # A PCA combination is not a consistent code: its code projection is not exact ...
    assert rms(rre_space.reconstruct(z_code)[0], body) > 1e-5
    fit = fit_coefficients(rre_space, moved, k, max_iter=20)
    # ... the vertex fit is (to the tolerance of its stopping rule).
    assert fit.error_m[0] < 1e-6
    np.testing.assert_allclose(fit.coefficients, z_true, atol=1e-4 * np.sqrt(rre_space.explained_variance_[0]))


def test_vertex_model_projections_are_one_and_orthogonal(limbs):
    rest, faces, meshes = limbs
    enc = VertexEncoder(rest, faces).fit(meshes[:18])
    space = ShapeSpace(enc).fit(meshes[:18])
    held = meshes[18:]
    for k in (2, space.n_components_):
        z_vertex = space.project(held, n_components=k)
        z_code = space.project(held, method="code", n_components=k)
        np.testing.assert_array_equal(z_vertex, z_code)
        orthogonal = (enc.encode(held) - space.mean_) @ space.components_[:k].T
        np.testing.assert_allclose(z_vertex[:, :k], orthogonal, atol=1e-12)
    fit = fit_coefficients(space, held)
    assert (fit.iterations == 0).all() and (fit.jacobians == 0).all()
    # Its tangent is the code direction itself.
    code = enc.encode(held[:1])[0]
    tan = enc.tangent(code)
    np.testing.assert_allclose(tan.vertices, enc.decode(code)[0])
    d = np.random.default_rng(0).normal(size=(2, enc.n_features_))
    np.testing.assert_array_equal(tan.jvp(d), d.reshape(2, -1, 3))
    np.testing.assert_array_equal(tan.vjp(d.reshape(2, -1, 3)), d)


def test_foreign_frame_and_noise(rre_space, limbs):
    _, faces, meshes = limbs
    y = meshes[20]
    k = rre_space.n_components_
    ours = fit_coefficients(rre_space, y, k)
    # Z up, turned, off the origin (metres kept: a registered mesh in another frame).
    foreign = to_frame(y, up="z", scale=1.0, translation=(3.0, -2.0, 0.7), yaw_degrees=140.0)
    theirs = fit_coefficients(rre_space, foreign, k)
    np.testing.assert_allclose(theirs.coefficients, ours.coefficients, atol=1e-6)
    assert abs(theirs.error_m[0] - ours.error_m[0]) < 1e-8
    # Noise of 1 mm along the normals: still fitted, the error is the noise and the model's.
    noisy = add_noise(foreign, 0.001, rng=1, faces=faces)
    fit = fit_coefficients(rre_space, noisy, k)
    assert fit.error_m[0] <= fit.start_error_m[0] and fit.error_m[0] < ours.error_m[0] + 0.002


def test_bad_arguments(rre_space, limbs):
    _, _, meshes = limbs
    with pytest.raises(ParameterError, match="method='banana'"):
        rre_space.project(meshes[0], method="banana")
    with pytest.raises(ParameterError, match="n_components=0"):
        rre_space.project(meshes[0], n_components=0)
    with pytest.raises(ParameterError, match="n_components=99"):
        fit_coefficients(rre_space, meshes[0], 99)
    with pytest.raises(ParameterError, match="start"):
        fit_coefficients(rre_space, meshes[0], 3, start=np.zeros((1, 2)))
    with pytest.raises(MeshError):
        fit_coefficients(rre_space, meshes[0][:-1], 3)
    bad = meshes[0].copy()
    bad[3] = np.nan
    with pytest.raises(MeshError, match="NaN"):
        rre_space.project(bad)


def test_rigid_basis_is_orthonormal_and_spans_each_parts_rigid_motions():
    """The closed-form basis (inertia tensor, no QR): orthonormal columns, and a small rigid
    motion of one part (the others still) lies in its span; a part on a line (one rotation
    without effect) gets a zero column, not NaN."""
    from bodyspace.shape.vertex_fit import rigid_basis
    rng = np.random.default_rng(0)
    body = rng.normal(size=(300, 3)) * [0.3, 1.0, 0.2] + [2.0, -1.0, 0.5]
    parts = [np.arange(120), np.arange(120, 300)]
    b = rigid_basis(body, parts)
    assert b.shape == (900, 12)
    np.testing.assert_allclose(b.T @ b, np.eye(12), atol=1e-12)
    move = np.zeros_like(body)
    move[120:] = np.cross([0.1, -0.2, 0.3], body[120:]) + [0.4, 0.0, -0.1]
    assert np.linalg.norm(move.ravel() - b @ (b.T @ move.ravel())) < 1e-12 * np.linalg.norm(move)
    moved = body.copy()
    moved[:120] += rng.normal(size=(120, 3)) * 0.01                  # not rigid: partly outside
    assert np.linalg.norm((moved - body).ravel() - b @ (b.T @ (moved - body).ravel())) > 0.5 * 0.01
    line = np.outer(np.linspace(0.0, 1.0, 10), [0.0, 1.0, 0.0])
    flat = rigid_basis(line, [np.arange(10)])
    assert np.isfinite(flat).all() and np.linalg.matrix_rank(flat) == 5
