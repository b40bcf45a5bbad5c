"""Deformation gradients of triangles and their polar decomposition, batched, in closed form.

The deformation gradient of a triangle (Sumner and Popovic 2004) maps the rest frame
``[e1, e2, n]`` onto the deformed one, ``n = (e1 x e2) / sqrt|e1 x e2|`` (the "fourth vertex":
a normal that scales like an edge). Hasler §3 split it by the polar
decomposition ``U = R S`` into a rotation and a symmetric stretch.

Closed form. Take orthonormal frames ``T = [t1, t2, t3]`` of the rest triangle (``t1`` along
``e1``, ``t3`` the unit normal) and ``W = [w1, w2, w3]`` of the deformed one. In these frames the
edges are upper-triangular 2x2 matrices ``P`` (rest) and ``Q`` (deformed), and the normals
``sqrt|c0| t3`` and ``sqrt|c| w3``, so

    U = W diag(A, s) T^T,    A = Q P^-1 (upper triangular),    s = sqrt(|c| / |c0|).

W and T are rotations, so the polar factors are those of ``diag(A, s)``: ``s > 0`` is its own
stretch, and the rotation of the 2x2 ``A = [[a, b], [0, d]]`` (``a, d > 0``) is the planar
rotation by ``theta = atan2(-b, a + d)``, ``|theta| < 90 deg``. Hence

    R = W diag(rot(theta), 1) T^T,    S = T diag(rot(theta)^T A, s) T^T.

No iteration and no branch: a few dozen elementwise passes over all faces, exact to round-off
(the 3x3 Newton iteration needed ~5 steps of a cofactor matrix each; measured 3x slower). The
determinant of U is always positive here (the deformed normal is built from the deformed edges),
so R is a proper rotation even for a triangle flipped over against its neighbours (a fold-over).

Arrays are *component-first*: a leading axis of components (3 for vectors, 9 for row-major 3x3
matrices, 6 for packed symmetric matrices), each a contiguous array over (..., F): elementwise
passes over contiguous memory are much faster in numpy than matmul on stacks of tiny matrices.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class RestTriangles:
    """Per-face constants of the rest (template) triangles, component-first over F faces.

    Attributes:
        frame: (3, 3, F) orthonormal axes ``t1, t2, t3`` (first index: axis; second: x, y, z).
        p_inv: (3, F) the upper-triangular ``P^-1`` as ``[(0, 0), (0, 1), (1, 1)]`` entries.
        double_area: (F,) ``|e1 x e2|``.
        stretch_basis: (4, 6, F) packed ``t1 t1^T``, ``t1 t2^T + t2 t1^T``, ``t2 t2^T``,
            ``t3 t3^T`` (packed order S00, S01, S02, S11, S12, S22).
    """

    frame: np.ndarray
    p_inv: np.ndarray
    double_area: np.ndarray
    stretch_basis: np.ndarray

    def take(self, faces) -> "RestTriangles":
        """The constants of some faces (a slice or indices), as contiguous arrays."""
        return RestTriangles(*(np.ascontiguousarray(a[..., faces])
                               for a in (self.frame, self.p_inv, self.double_area, self.stretch_basis)))


_PACKED = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))


def _corners(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Corner positions a, b, c, each component-first (3, ..., F), of meshes (..., V, 3)."""
    xt = np.ascontiguousarray(np.moveaxis(np.asarray(vertices, dtype=float), -1, 0))  # (3, ..., V)
    return xt[..., faces[:, 0]], xt[..., faces[:, 1]], xt[..., faces[:, 2]]


def _cross(u, v):
    return (u[1] * v[2] - u[2] * v[1], u[2] * v[0] - u[0] * v[2], u[0] * v[1] - u[1] * v[0])


def _edge_frames(a, b, c):
    """Orthonormal frames and in-frame edge coordinates of triangles with corners a, b, c
    (each 3 component arrays (..., F)).

    Returns ``(t1, t2, t3, q11, q12, q22, double_area)``: the axes (tuples of 3 component
    arrays (..., F)), the upper-triangular edge matrix ``Q`` with ``[e1, e2] = [t1, t2] Q``
    ((..., F) each) and ``|e1 x e2|`` (..., F).
    """
    e1 = (b[0] - a[0], b[1] - a[1], b[2] - a[2])
    e2 = (c[0] - a[0], c[1] - a[1], c[2] - a[2])
    cr = _cross(e1, e2)
    dbl = np.sqrt(cr[0] * cr[0] + cr[1] * cr[1] + cr[2] * cr[2])
    len1 = np.sqrt(e1[0] * e1[0] + e1[1] * e1[1] + e1[2] * e1[2])
    inv1 = 1.0 / np.maximum(len1, 1e-300)
    invc = 1.0 / np.maximum(dbl, 1e-300)
    t1 = (e1[0] * inv1, e1[1] * inv1, e1[2] * inv1)
    t3 = (cr[0] * invc, cr[1] * invc, cr[2] * invc)
    t2 = _cross(t3, t1)
    q12 = e2[0] * t1[0] + e2[1] * t1[1] + e2[2] * t1[2]
    q22 = dbl * inv1  # e2 . t2 = |e1 x e2| / |e1|
    return t1, t2, t3, len1, q12, q22, dbl


def rest_triangles(vertices: np.ndarray, faces: np.ndarray) -> RestTriangles:
    """Per-face constants (``RestTriangles``) of a rest mesh: vertices (V, 3), faces (F, 3)."""
    t1, t2, t3, p11, p12, p22, dbl = _edge_frames(*_corners(vertices, np.asarray(faces, dtype=np.int64)))
    frame = np.array([t1, t2, t3])
    p_inv = np.array([1.0 / p11, -p12 / (p11 * p22), 1.0 / p22])
    basis = np.empty((4, 6, len(faces)))
    for k, (i, j) in enumerate(_PACKED):
        basis[0, k] = t1[i] * t1[j]
        basis[1, k] = t1[i] * t2[j] + t2[i] * t1[j]
        basis[2, k] = t2[i] * t2[j]
        basis[3, k] = t3[i] * t3[j]
    return RestTriangles(frame, p_inv, dbl, basis)


def polar_deformation(vertices: np.ndarray, faces: np.ndarray, rest: RestTriangles):
    """Polar factors of the deformation gradients ``U = R S`` from ``rest`` to ``vertices``.

    Args:
        vertices: (..., V, 3) deformed meshes; faces: (F, 3); rest: ``rest_triangles`` of the
            rest mesh with the same faces.

    Returns:
        rotation: (9, ..., F) row-major R, a proper rotation.
        stretch: (6, ..., F) packed symmetric S (S00, S01, S02, S11, S12, S22).
        double_area: (..., F) ``|e1 x e2|`` of the deformed triangles.
        normal: (3, ..., F) unit normals of the deformed triangles.

    Degenerate deformed triangles (zero area) give meaningless factors; callers reject them.
    """
    rotation, stretch, dbl, normal = polar_from_corners(*_corners(vertices, np.asarray(faces, dtype=np.int64)), rest)
    return rotation, stretch, dbl, np.array(normal)


def polar_from_corners(a, b, c, rest: RestTriangles):
    """``polar_deformation`` of triangles given by their corners a, b, c (each 3 component
    arrays (..., F), e.g. ``(x[f0], y[f0], z[f0])``); returns the same four results, the
    normal as a tuple of 3 component arrays (..., F)."""
    with np.errstate(divide="ignore", invalid="ignore"):  # degenerate triangles: rejected by callers
        u1, u2, u3, q11, q12, q22, dbl = _edge_frames(a, b, c)
        return _polar_factors(u1, u2, u3, q11, q12, q22, dbl, rest)


def _polar_factors(u1, u2, u3, q11, q12, q22, dbl, rest: RestTriangles):
    pi11, pi12, pi22 = rest.p_inv
    # A = Q P^-1 = [[a, b], [0, d]], a, d > 0.
    a = q11 * pi11
    b = q11 * pi12 + q12 * pi22
    d = q22 * pi22
    apd = a + d
    inv_h = 1.0 / np.sqrt(apd * apd + b * b)
    co = apd * inv_h
    si = -b * inv_h
    # The 2x2 stretch rot(theta)^T A: [[a (a + d), a b], [a b, b^2 + (a + d) d]] / h.
    s11 = a * apd * inv_h
    s12 = a * b * inv_h
    s22 = (b * b + apd * d) * inv_h
    s33 = np.sqrt(dbl / rest.double_area)
    basis = rest.stretch_basis.reshape((4, 6) + (1,) * (dbl.ndim - 1) + (-1,))
    stretch = s11 * basis[0] + s12 * basis[1] + s22 * basis[2] + s33 * basis[3]  # (6, ..., F)
    # W = [co u1 + si u2, -si u1 + co u2, u3]; R = W T^T: R_kl = sum_m W_km T_lm.
    w1 = [co * u1[k] + si * u2[k] for k in range(3)]
    w2 = [co * u2[k] - si * u1[k] for k in range(3)]
    t1, t2, t3 = rest.frame
    rotation = np.empty((9,) + dbl.shape)
    for k in range(3):
        for col in range(3):
            rotation[3 * k + col] = w1[k] * t1[col] + w2[k] * t2[col] + u3[k] * t3[col]
    return rotation, stretch, dbl, u3


def polar_decomposition_svd(u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Reference polar decomposition ``U = R S`` of (..., 3, 3) matrices with det(U) > 0 by the
    SVD (``R = V W^T`` for ``U = V diag(sigma) W^T``, ``S = W diag(sigma) W^T``); slow, for checks."""
    v, sigma, wt = np.linalg.svd(np.asarray(u, dtype=float))
    r = v @ wt
    s = np.swapaxes(wt, -1, -2) @ (sigma[..., None] * wt)
    return r, 0.5 * (s + np.swapaxes(s, -1, -2))
