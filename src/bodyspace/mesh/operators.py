"""Sparse differential operators on a triangle mesh and per-triangle deformation gradients.

Conventions: ``vertices`` (V, 3) float, ``faces`` (F, 3) int. Laplacians here are positive
semi-definite (``x @ L @ x >= 0``), unlike libigl's ``cotmatrix`` which is its negative.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from bodyspace.errors import MeshError


def _face_geometry(vertices: np.ndarray, faces: np.ndarray):
    v = np.asarray(vertices, dtype=float)
    a, b, c = v[..., faces[:, 0], :], v[..., faces[:, 1], :], v[..., faces[:, 2], :]
    cross = np.cross(b - a, c - a)
    double_area = np.linalg.norm(cross, axis=-1)
    return a, b, c, cross, double_area


def gradient_operator(vertices: np.ndarray, faces: np.ndarray) -> sp.csr_matrix:
    """Per-face gradient of piecewise-linear functions, (3F, V) sparse.

    Row ``3 f + d`` gives component d of the (constant) gradient on face f of the function
    whose vertex values are the column vector: ``grad phi_i = n x (p_k - p_j) / (2 A)`` for the
    corner i of face (i, j, k) with unit normal n and area A.
    """
    faces = np.asarray(faces)
    a, b, c, cross, dbl = _face_geometry(vertices, faces)
    if (dbl <= 0).any():
        bad = np.flatnonzero(dbl <= 0)
        raise MeshError(f"faces {bad[:5].tolist()} have zero area; the gradient needs non-degenerate triangles")
    n = cross / dbl[:, None]
    # Gradient of the hat function of each corner: the opposite edge turned 90 degrees in-plane.
    grads = np.stack([np.cross(n, c - b), np.cross(n, a - c), np.cross(n, b - a)], axis=1) / dbl[:, None, None]
    nf = len(faces)
    rows = (3 * np.arange(nf)[:, None, None] + np.arange(3)[None, None, :]).repeat(3, axis=1)  # (F, corner, d)
    cols = np.broadcast_to(faces[:, :, None], (nf, 3, 3))
    return sp.csr_matrix((grads.ravel(), (rows.ravel(), cols.ravel())), shape=(3 * nf, len(vertices)))


def cotangent_laplacian(vertices: np.ndarray, faces: np.ndarray) -> sp.csr_matrix:
    """Cotangent Laplacian (V, V), positive semi-definite: ``G^T diag(area) G``.

    Built from the gradient operator rather than the cotangent formula so that it is exactly
    the normal matrix of the Poisson least-squares problem that uses the same ``G``.
    """
    g = gradient_operator(vertices, faces)
    area = np.repeat(0.5 * _face_geometry(vertices, np.asarray(faces))[4], 3)
    return (g.T @ sp.diags(area) @ g).tocsr()


def dual_laplacian(neighbors: np.ndarray) -> sp.csr_matrix:
    """Uniform graph Laplacian (F, F) of the triangle adjacency (``D - W``), PSD.

    ``neighbors`` (F, 3) from ``topology.face_adjacency``; -1 slots (boundary) contribute nothing.
    """
    neighbors = np.asarray(neighbors)
    nf = len(neighbors)
    ok = neighbors >= 0
    rows = np.repeat(np.arange(nf), 3).reshape(nf, 3)[ok]
    w = sp.csr_matrix((np.ones(len(rows)), (rows, neighbors[ok])), shape=(nf, nf))
    return (sp.diags(ok.sum(axis=1).astype(float)) - w).tocsr()


def triangle_frames(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Per-face frames (..., F, 3, 3) with columns ``[e1, e2, (e1 x e2) / sqrt(|e1 x e2|)]``.

    The third column is Sumner and Popovic's (2004) fourth vertex: a normal whose length scales
    like an edge, so a uniform scaling of the triangle scales the whole frame uniformly.
    """
    a, b, c, cross, dbl = _face_geometry(vertices, np.asarray(faces))
    n = cross / np.sqrt(np.maximum(dbl, 1e-300))[..., None]
    return np.stack([b - a, c - a, n], axis=-1)


def deformation_gradients(rest_frames_inv: np.ndarray, vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Per-face deformation gradients U (..., F, 3, 3) mapping rest triangles onto ``vertices``'.

    ``U_f @ [e1, e2, n]_rest = [e1, e2, n]_deformed`` (Sumner and Popovic 2004;
    Hasler §3). ``rest_frames_inv`` (F, 3, 3) is ``inv(triangle_frames(rest, faces))``,
    computed once per template.
    """
    return triangle_frames(vertices, faces) @ rest_frames_inv
