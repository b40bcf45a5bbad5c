"""Topology, operators and the prefactored solvers of the mesh layer."""

import numpy as np
import pytest
import scipy.sparse as sp
import trimesh
from _meshes import open_tube

from bodyspace.errors import MeshError
from bodyspace.mesh.operators import (
    cotangent_laplacian,
    deformation_gradients,
    dual_laplacian,
    gradient_operator,
    triangle_frames,
)
from bodyspace.mesh.solver import FactorizedSolver, PoissonSolver, PositionConstraints
from bodyspace.mesh.topology import (
    check_same_topology,
    check_topology,
    edges,
    face_adjacency,
    face_components,
    spanning_forest,
    vertex_components,
)


def tube(rings=6, around=8, length=1.0, radius=0.2):
    """Open cylinder along +y (two boundary loops), rings of ``around`` vertices."""
    return open_tube(rings, around, length, radius)


@pytest.fixture
def sphere():
    m = trimesh.creation.icosphere(subdivisions=2)
    return np.asarray(m.vertices), np.asarray(m.faces)


def test_edges_and_closed_adjacency(sphere):
    v, f = sphere
    assert len(edges(f)) == 3 * len(f) // 2
    nb, back = face_adjacency(f)
    assert (nb >= 0).all()
    rows = np.repeat(np.arange(len(f)), 3).reshape(-1, 3)
    assert np.array_equal(nb[nb, back], rows)
    # Slot k is edge (f[k], f[k+1]); the neighbour holds the same edge reversed.
    for face, k in [(0, 0), (5, 2), (17, 1)]:
        a, b = f[face, k], f[face, (k + 1) % 3]
        g, kk = nb[face, k], back[face, k]
        assert (f[g, kk], f[g, (kk + 1) % 3]) == (b, a)


def test_boundary_slots_are_explicit():
    v, f = tube()
    nb, back = face_adjacency(f)
    boundary = (nb < 0).sum()
    assert boundary == 2 * 8  # two rims of 8 edges
    assert ((nb < 0) == (back < 0)).all()
    assert face_components(nb)[0] == 1


def test_components_and_forest(sphere):
    v, f = sphere
    f2 = np.concatenate([f, f + len(v)])
    nb, _ = face_adjacency(f2)
    n, labels = face_components(nb)
    assert n == 2 and vertex_components(f2, 2 * len(v))[0] == 2
    roots = np.array([0, len(f)])
    forest = spanning_forest(nb, roots)
    assert sorted(np.concatenate(forest.levels).tolist()) == list(range(len(f2)))
    depth = np.empty(len(f2), int)
    for d, lev in enumerate(forest.levels):
        depth[lev] = d
    child = np.flatnonzero(forest.parent >= 0)
    assert len(child) == len(f2) - 2
    assert (depth[forest.parent[child]] == depth[child] - 1).all()
    assert (nb[child, forest.parent_slot[child]] == forest.parent[child]).all()


@pytest.mark.parametrize("case, message", [
    ("nonmanifold", "non-manifold"),
    ("flipped_face", "same direction"),
    ("unused_vertex", "used by no face"),
    ("pinch", "single vertex"),
    ("repeated_index", "repeat a vertex"),
    ("out_of_range", "only"),
])
def test_check_topology_rejects(sphere, case, message):
    v, f = sphere
    f = f.copy()
    n = len(v)
    if case == "nonmanifold":
        a, b = f[0, 0], f[0, 1]
        f = np.concatenate([f, [[a, b, n]]])
        n += 1
    elif case == "flipped_face":
        f[3] = f[3, ::-1]
    elif case == "unused_vertex":
        n += 1
    elif case == "pinch":
        # A second sphere sharing exactly one vertex with the first.
        g = f + len(v) - 1
        g[g == len(v) - 1 + 0] = 0
        f = np.concatenate([f, g])
        n = 2 * len(v) - 1
    elif case == "repeated_index":
        f[2, 1] = f[2, 0]
    elif case == "out_of_range":
        f[1, 2] = n + 5
    with pytest.raises(MeshError, match=message):
        check_topology(f, n)


def test_check_same_topology(sphere):
    v, f = sphere
    check_same_topology(f.copy(), f)
    g = f.copy()
    g[7] = g[7, [1, 2, 0]]
    with pytest.raises(MeshError, match="face 7"):
        check_same_topology(g, f)
    with pytest.raises(MeshError, match="shape"):
        check_same_topology(f[:-1], f)


def test_gradient_of_linear_function_is_exact(sphere):
    v, f = sphere
    g = gradient_operator(v, f)
    a = np.array([0.3, -1.2, 2.0])
    grad = (g @ (v @ a)).reshape(-1, 3)
    n = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    tangential = a - (n @ a)[:, None] * n  # gradient on a face = projection onto its plane
    np.testing.assert_allclose(grad, tangential, atol=1e-12)


def test_laplacians(sphere):
    v, f = sphere
    lap = cotangent_laplacian(v, f)
    assert abs(lap - lap.T).max() < 1e-12
    np.testing.assert_allclose(lap @ np.ones(len(v)), 0, atol=1e-12)
    x = np.random.default_rng(0).normal(size=len(v))
    assert x @ lap @ x > 0
    nb, _ = face_adjacency(f)
    d = dual_laplacian(nb)
    np.testing.assert_allclose(d @ np.ones(len(f)), 0)
    assert d.diagonal().max() == 3


def test_deformation_gradients_of_affine_map(sphere):
    v, f = sphere
    a = np.array([[1.2, 0.1, 0.0], [0.0, 0.9, 0.3], [0.2, 0.0, 1.1]])
    inv = np.linalg.inv(triangle_frames(v, f))
    u = deformation_gradients(inv, v @ a.T + 3.0, f)
    # The in-plane action of U equals A on every triangle (the normal column differs).
    e = np.stack([v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]], -1)
    np.testing.assert_allclose(u @ e, a @ e, atol=1e-12)


def test_factorized_solver_multiple_rhs():
    rng = np.random.default_rng(1)
    m = sp.random(200, 200, density=0.02, random_state=2)
    a = (m @ m.T + sp.identity(200) * 2).tocsr()
    solver = FactorizedSolver(a)
    b = rng.normal(size=(200, 40))
    np.testing.assert_allclose(a @ solver.solve(b), b, atol=1e-10)
    np.testing.assert_allclose(a @ solver.solve(b[:, 0]), b[:, 0], atol=1e-10)
    with pytest.raises(MeshError, match="rows"):
        solver.solve(b[:10])


def test_poisson_reproduces_mesh_and_honours_constraints():
    v, f = tube(rings=10)
    x = v.copy()
    x[:, 0] += 0.3 * v[:, 1] ** 2  # bend
    poisson = PoissonSolver(v, f)
    u = deformation_gradients(np.linalg.inv(triangle_frames(v, f)), x[None], f)
    y = poisson.solve(u)[0]
    np.testing.assert_allclose(y - y.mean(0), x - x.mean(0), atol=1e-10)
    # A strong constraint on one rim moves it to its target; the shape follows rigidly.
    rim = np.arange(8)
    c = PositionConstraints(rim, x[rim] + [0.5, 0, 0], weight=1e6)
    y = poisson.solve(u, c)[0]
    np.testing.assert_allclose(y, x + [0.5, 0, 0], atol=1e-5)
    with pytest.raises(MeshError, match="indices"):
        poisson.solve(u, PositionConstraints(np.array([10_000]), np.zeros((1, 3))))
