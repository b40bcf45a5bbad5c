"""The non-rigid refinement's parts (issue 15): unbiased tangent-plane targets, no targets over
holes, the compiled conjugate gradients against a direct solve, untangling. Small meshes only
(an icosphere), so the file takes well under a second after numba's cache is warm."""

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
import trimesh
from scipy.spatial import cKDTree

from bodyspace.mesh.geometry import vertex_normals
from bodyspace.mesh.operators import cotangent_laplacian
from bodyspace.register.correspondences import cell_sagitta, tangent_plane_targets
from bodyspace.register.nicp import _System, unfold
from bodyspace.rig.posing import folded_triangles


def _sphere(subdivisions=3, radius=0.1):
    s = trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)
    return np.asarray(s.vertices, dtype=float), np.asarray(s.faces, dtype=np.int64)


def _surface_points(V, F, n, rng):
    """n points uniform over the triangles of (V, F), and the faces' normals for them."""
    mesh = trimesh.Trimesh(V, F, process=False)
    pts, face = trimesh.sample.sample_surface(mesh, n, seed=int(rng.integers(1 << 30)))
    return np.asarray(pts), np.asarray(mesh.face_normals[face])


def test_plane_targets_are_unbiased_on_a_convex_mesh():
    """Points sampled on a polyhedral sphere lie below its vertices (its chords): the bare plane
    projection puts the targets inside, the sagitta-raised ones on the vertices."""
    V, F = _sphere()
    pts, nrm = _surface_points(V, F, 40 * len(V), np.random.default_rng(0))
    vn = vertex_normals(V, F)
    sag = cell_sagitta(V, F, vn)
    assert (sag > 0).all()
    bare, has = tangent_plane_targets(V, vn, pts, nrm, cKDTree(pts))
    raised, has2 = tangent_plane_targets(V, vn, pts, nrm, cKDTree(pts), faces=F)
    assert has.all() and has2.all()
    off_bare = ((bare - V) * vn).sum(axis=1).mean()
    off_raised = ((raised - V) * vn).sum(axis=1).mean()
    assert off_bare < -0.5 * sag.mean()               # the bare projection sinks by about the sagitta
    assert abs(off_raised) < 0.15 * sag.mean()


def test_no_closest_point_targets_over_a_hole():
    """A cap cut out of the scan: the vertices in the middle of the hole get no target (their
    closest scan point is on the rim, beside them), the others keep theirs."""
    V, F = _sphere()
    pts, nrm = _surface_points(V, F, 20 * len(V), np.random.default_rng(1))
    keep = pts[:, 2] < 0.06
    pts, nrm = pts[keep], nrm[keep]
    _, has = tangent_plane_targets(V, vertex_normals(V, F), pts, nrm, cKDTree(pts), faces=F)
    assert not has[V[:, 2] > 0.08].any()
    assert has[V[:, 2] < 0.05].all()


def test_compiled_conjugate_gradients_match_a_direct_solve():
    V, F = _sphere(subdivisions=2)
    n = len(V)
    L = cotangent_laplacian(V, F)
    LL = (L.T @ L).tocsr()
    rng = np.random.default_rng(2)
    a = np.concatenate([V, np.ones((n, 1))], axis=1)
    w = (rng.random(n) < 0.7).astype(float)
    beta = 3.0
    system = _System(LL, a, w, beta)
    b = rng.normal(size=(n, 4, 3))
    x = system.solve(b, np.zeros((n, 4, 3)), 400)
    blocks = sp.block_diag([w[v] * np.outer(a[v], a[v]) for v in range(n)])
    A = (beta * sp.kron(LL, sp.identity(4)) + blocks).tocsc()
    ref = np.stack([spla.spsolve(A, b[:, :, c].ravel()) for c in range(3)], axis=1).reshape(n, 4, 3)
    assert np.abs(x - ref).max() < 1e-6 * np.abs(ref).max()
    assert np.allclose(system.apply(ref), b, atol=1e-8 * np.abs(b).max())


def test_unfold_leaves_no_folded_face():
    """A patch of vertices dragged over their neighbours (the skin folded over itself) is
    untangled to zero folded faces, and vertices far from it do not move."""
    V, F = _sphere()
    bent = V.copy()
    top = np.flatnonzero(V[:, 2] > 0.099)       # the pole and two neighbours
    bent[top, 0] += 0.02                        # two edges sideways: over their neighbours
    assert folded_triangles(bent, F).sum() > 0
    out, left = unfold(bent, F)
    assert left == 0 and not folded_triangles(out, F).any()
    far = V[:, 2] < 0.0
    assert np.array_equal(out[far], bent[far])
