"""The decoder at one code, with its exact derivatives: forward tangents and adjoints.

Fitting a body's coefficients to a mesh *in vertex space* (``shape.vertex_fit``) needs the
Jacobian of ``code -> vertices``; a finite difference costs one whole decode (a factorization
of the Hasler Equation 9 system) per direction. The decode's chain is differentiated here
instead, at one code, reusing that code's factorization for every direction:

1. relative rotations ``Q_ik = exp(r_ik) M_ik``: ``dQ_ik = [w_ik]x Q_ik`` with
   ``w_ik = J_l(r_ik) dr_ik`` (``J_l`` the left Jacobian of the rotation-vector exponential);
2. the least-squares rotations of Hasler Equation 9 solve ``A(Q_rel) Q = b``, so
   ``A dQ = sum_k (dQ_ik + dQ_jk'^T) Q_j`` (anchors fixed): three right-hand sides a
   direction, solved with the factor the decode made (``mesh.block_cholesky``'s L, by the
   many-column triangular solves below, several directions in one pass over L);
3. the projection onto SO(3), ``Q = W P`` (W the polar factor, R = W^T): ``dW = W [w]x`` with
   ``(tr(P) I - P) w = vee(W^T dQ - dQ^T W)``;
4. ``U = R S``: ``dU = dR S + R dS``;
5. the Poisson step is linear: ``dx = poisson(dU)``; then the placement's rotation.

The placement's own change with the code is a rigid motion of the body; the vertex fit
aligns the target rigidly anyway, so the tangents here leave it out (``vjp`` is then the exact
gradient of an aligned squared error, see ``shape.vertex_fit``).

``vjp`` runs the same chain backwards (adjoint solves with the same factors: the Hasler
Equation 9 matrix and the Laplacian are symmetric). All kernels work in the mesh's face
order on arrays kept per code (``DecodeTangent``); ``RelativeRotationEncoder.tangent(code)``
makes one, ``VertexEncoder.tangent`` an ``AffineDecodeTangent`` (the decoder is affine: the
tangent is the code itself). Shapes: F faces, V vertices, D = 15 F, m directions.
"""

from __future__ import annotations

import numba
import numpy as np

from bodyspace.mesh.solver import FactorizedSolver
from bodyspace.parallel import run_both

_kernel = numba.njit(cache=True, nogil=True, fastmath={"contract"})

# Directions per pass over the factor L in ``jvp``: wider blocks read L fewer times, narrower
# ones keep the right-hand sides in cache.
JVP_BLOCK = 8


# ---------------------------------------------------------------------------- small kernels

@_kernel
def left_jacobians(code, valid, jl):
    """Left Jacobians ``J_l(r)`` (F, 3, 3, 3) of the rotation vectors r of each edge slot of a
    code (F, 15): ``exp(r + dr) = exp([J_l(r) dr]x) exp(r)`` to first order. Zero at boundary slots."""
    for f in range(code.shape[0]):
        for k in range(3):
            m = jl[f, k]
            if not valid[f, k]:
                m[:, :] = 0.0
                continue
            r0, r1, r2 = code[f, 3 * k], code[f, 3 * k + 1], code[f, 3 * k + 2]
            t2 = r0 * r0 + r1 * r1 + r2 * r2
            t = np.sqrt(t2)
            if t < 1e-4:  # series: a = 1/2 - t^2/24, b = 1/6 - t^2/120
                a = 0.5 - t2 / 24.0
                b = 1.0 / 6.0 - t2 / 120.0
            else:
                a = (1.0 - np.cos(t)) / t2
                b = (t - np.sin(t)) / (t2 * t)
            # I + a [r]x + b [r]x^2, [r]x^2 = r r^T - t^2 I
            m[0, 0] = 1.0 + b * (r0 * r0 - t2)
            m[1, 1] = 1.0 + b * (r1 * r1 - t2)
            m[2, 2] = 1.0 + b * (r2 * r2 - t2)
            m[0, 1] = -a * r2 + b * r0 * r1
            m[1, 0] = a * r2 + b * r0 * r1
            m[0, 2] = a * r1 + b * r0 * r2
            m[2, 0] = -a * r1 + b * r0 * r2
            m[1, 2] = -a * r0 + b * r1 * r2
            m[2, 1] = a * r0 + b * r1 * r2


@_kernel
def _tangent_rhs(dcode, jl, rel, q, nbr, bk, valid, row, x):
    """Right-hand sides of the Hasler Equation 9 tangent: for m code directions dcode (m, F, 15)
    and each free face i, ``h_i = sum_k ([w_ik]x Q_ik - Q_jk'^T [w_jk']x) Q_j`` into
    ``x[row[i], :, 3 d: 3 d + 3]`` (x (n, 3, 3 m), zeroed here). Faces outside, directions
    inside: the per-face state is read once for all directions."""
    x[:] = 0.0
    nd = dcode.shape[0]
    m = np.empty((3, 3))
    for i in range(dcode.shape[1]):
        p = row[i]
        if p < 0:
            continue
        for k in range(3):
            if not valid[i, k]:
                continue
            j, kb = nbr[i, k], bk[i, k]
            a = jl[i, k]
            b = jl[j, kb]
            g = rel[i, k]
            h = rel[j, kb]
            qj = q[j]
            for r in range(3):  # m = Q_ik Q_j
                for c in range(3):
                    m[r, c] = g[r, 0] * qj[0, c] + g[r, 1] * qj[1, c] + g[r, 2] * qj[2, c]
            for d in range(nd):
                d0, d1, d2 = dcode[d, i, 3 * k], dcode[d, i, 3 * k + 1], dcode[d, i, 3 * k + 2]
                w0 = a[0, 0] * d0 + a[0, 1] * d1 + a[0, 2] * d2
                w1 = a[1, 0] * d0 + a[1, 1] * d1 + a[1, 2] * d2
                w2 = a[2, 0] * d0 + a[2, 1] * d1 + a[2, 2] * d2
                e0, e1, e2 = dcode[d, j, 3 * kb], dcode[d, j, 3 * kb + 1], dcode[d, j, 3 * kb + 2]
                v0 = b[0, 0] * e0 + b[0, 1] * e1 + b[0, 2] * e2
                v1 = b[1, 0] * e0 + b[1, 1] * e1 + b[1, 2] * e2
                v2 = b[2, 0] * e0 + b[2, 1] * e1 + b[2, 2] * e2
                c0 = 3 * d
                for c in range(3):
                    # w x (column c of Q_ik Q_j); Q_jk'^T (v x column c of Q_j)
                    n0 = v1 * qj[2, c] - v2 * qj[1, c]
                    n1 = v2 * qj[0, c] - v0 * qj[2, c]
                    n2 = v0 * qj[1, c] - v1 * qj[0, c]
                    x[p, 0, c0 + c] += (w1 * m[2, c] - w2 * m[1, c]) - (h[0, 0] * n0 + h[1, 0] * n1 + h[2, 0] * n2)
                    x[p, 1, c0 + c] += (w2 * m[0, c] - w0 * m[2, c]) - (h[0, 1] * n0 + h[1, 1] * n1 + h[2, 1] * n2)
                    x[p, 2, c0 + c] += (w0 * m[1, c] - w1 * m[0, c]) - (h[0, 2] * n0 + h[1, 2] * n1 + h[2, 2] * n2)


@_kernel
def _tangent_gradients(x, row, rot, stretch, kinv, dcode, du):
    """Deformation-gradient tangents ``dU = dR S + R dS`` (m, F, 3, 3) from the rotation
    tangents dQ in x (n, 3, 3 m) (0 at anchors), with ``dR = -[w]x R``,
    ``w = kinv vee(R dQ - dQ^T R^T)`` (the polar factor's tangent, R = W^T) and dS the
    code's stretch direction (dcode[..., 9:]). Faces outside, directions inside."""
    y = np.empty((3, 3))
    dr = np.empty((3, 3))
    ds = np.empty((3, 3))
    for f in range(dcode.shape[1]):
        p = row[f]
        r = rot[f]
        s = stretch[f]
        k = kinv[f]
        for d in range(dcode.shape[0]):
            c0 = 3 * d
            w0 = w1 = w2 = 0.0
            if p >= 0:
                for a in range(3):  # y = R dQ (W^T dQ)
                    for c in range(3):
                        y[a, c] = r[a, 0] * x[p, 0, c0 + c] + r[a, 1] * x[p, 1, c0 + c] + r[a, 2] * x[p, 2, c0 + c]
                u0, u1, u2 = y[2, 1] - y[1, 2], y[0, 2] - y[2, 0], y[1, 0] - y[0, 1]
                w0 = k[0, 0] * u0 + k[0, 1] * u1 + k[0, 2] * u2
                w1 = k[1, 0] * u0 + k[1, 1] * u1 + k[1, 2] * u2
                w2 = k[2, 0] * u0 + k[2, 1] * u1 + k[2, 2] * u2
            for c in range(3):  # dR = -[w]x R
                dr[0, c] = w2 * r[1, c] - w1 * r[2, c]
                dr[1, c] = w0 * r[2, c] - w2 * r[0, c]
                dr[2, c] = w1 * r[0, c] - w0 * r[1, c]
            g = dcode[d, f]
            ds[0, 0], ds[0, 1], ds[0, 2] = g[9], g[10], g[11]
            ds[1, 0], ds[1, 1], ds[1, 2] = g[10], g[12], g[13]
            ds[2, 0], ds[2, 1], ds[2, 2] = g[11], g[13], g[14]
            out = du[d, f]
            for a in range(3):
                for c in range(3):
                    out[a, c] = (dr[a, 0] * s[0, c] + dr[a, 1] * s[1, c] + dr[a, 2] * s[2, c]
                                 + r[a, 0] * ds[0, c] + r[a, 1] * ds[1, c] + r[a, 2] * ds[2, c])


@_kernel
def _adjoint_gradients(gu, rot, stretch, kinv, row, x, gcode):
    """Adjoint of ``_tangent_gradients`` for n cotangents gu (n, F, 3, 3) of U: the stretch
    part of the code gradient into ``gcode[..., 9:]`` (n, F, 15), and the rotation cotangents
    ``gQ = R^T [kinv g_w]x`` with ``g_w = -vee(gR R^T - R gR^T)``, ``gR = gU S``, into
    ``x[row[f], :, 3 e: 3 e + 3]`` (x (n_rows, 3, 3 n), zeroed here)."""
    x[:] = 0.0
    gr = np.empty((3, 3))
    gs = np.empty((3, 3))
    for e in range(gu.shape[0]):
        c0 = 3 * e
        for f in range(gu.shape[1]):
            g = gu[e, f]
            r = rot[f]
            s = stretch[f]
            for a in range(3):
                for c in range(3):
                    gr[a, c] = g[a, 0] * s[0, c] + g[a, 1] * s[1, c] + g[a, 2] * s[2, c]  # gU S
                    gs[a, c] = r[0, a] * g[0, c] + r[1, a] * g[1, c] + r[2, a] * g[2, c]  # R^T gU
            out = gcode[e, f]
            out[9] = gs[0, 0]
            out[10] = gs[0, 1] + gs[1, 0]
            out[11] = gs[0, 2] + gs[2, 0]
            out[12] = gs[1, 1]
            out[13] = gs[1, 2] + gs[2, 1]
            out[14] = gs[2, 2]
            p = row[f]
            if p < 0:
                continue
            # M = gR R^T (gR W); g_w = -vee(M - M^T)
            m01 = gr[0, 0] * r[1, 0] + gr[0, 1] * r[1, 1] + gr[0, 2] * r[1, 2]
            m02 = gr[0, 0] * r[2, 0] + gr[0, 1] * r[2, 1] + gr[0, 2] * r[2, 2]
            m10 = gr[1, 0] * r[0, 0] + gr[1, 1] * r[0, 1] + gr[1, 2] * r[0, 2]
            m12 = gr[1, 0] * r[2, 0] + gr[1, 1] * r[2, 1] + gr[1, 2] * r[2, 2]
            m20 = gr[2, 0] * r[0, 0] + gr[2, 1] * r[0, 1] + gr[2, 2] * r[0, 2]
            m21 = gr[2, 0] * r[1, 0] + gr[2, 1] * r[1, 1] + gr[2, 2] * r[1, 2]
            a0, a1, a2 = -(m21 - m12), -(m02 - m20), -(m10 - m01)
            k = kinv[f]
            v0 = k[0, 0] * a0 + k[0, 1] * a1 + k[0, 2] * a2
            v1 = k[1, 0] * a0 + k[1, 1] * a1 + k[1, 2] * a2
            v2 = k[2, 0] * a0 + k[2, 1] * a1 + k[2, 2] * a2
            # gQ = W [v]x = R^T [v]x: gQ[a, c] = sum_b R[b, a] [v]x[b, c]
            for a in range(3):
                x[p, a, c0 + 0] = r[1, a] * v2 - r[2, a] * v1
                x[p, a, c0 + 1] = -r[0, a] * v2 + r[2, a] * v0
                x[p, a, c0 + 2] = r[0, a] * v1 - r[1, a] * v0


@_kernel
def _adjoint_relative(lam, row, q, rel, jl, nbr, valid, gcode):
    """Adjoint of ``_tangent_rhs`` for n rotation adjoints lam (n_rows, 3, 3 n) (the solves of
    the cotangents gQ): per edge slot (i, k) with neighbour j, ``G = L_i Q_j^T + Q_i L_j^T``
    (L = 0 at anchors), ``g_w = vee(G Q_ik^T - Q_ik G^T)``, ``g_r = J_l^T g_w`` into
    ``gcode[..., 3 k: 3 k + 3]`` (n, F, 15); 0 at boundary slots."""
    gm = np.empty((3, 3))
    for e in range(gcode.shape[0]):
        c0 = 3 * e
        for i in range(gcode.shape[1]):
            pi = row[i]
            for k in range(3):
                out = gcode[e, i]
                if not valid[i, k]:
                    out[3 * k] = out[3 * k + 1] = out[3 * k + 2] = 0.0
                    continue
                j = nbr[i, k]
                pj = row[j]
                qi, qj = q[i], q[j]
                for a in range(3):
                    for c in range(3):
                        v = 0.0
                        if pi >= 0:
                            v += (lam[pi, a, c0] * qj[c, 0] + lam[pi, a, c0 + 1] * qj[c, 1]
                                  + lam[pi, a, c0 + 2] * qj[c, 2])
                        if pj >= 0:
                            v += (qi[a, 0] * lam[pj, c, c0] + qi[a, 1] * lam[pj, c, c0 + 1]
                                  + qi[a, 2] * lam[pj, c, c0 + 2])
                        gm[a, c] = v
                g = rel[i, k]
                # M = G Q_ik^T
                m01 = gm[0, 0] * g[1, 0] + gm[0, 1] * g[1, 1] + gm[0, 2] * g[1, 2]
                m02 = gm[0, 0] * g[2, 0] + gm[0, 1] * g[2, 1] + gm[0, 2] * g[2, 2]
                m10 = gm[1, 0] * g[0, 0] + gm[1, 1] * g[0, 1] + gm[1, 2] * g[0, 2]
                m12 = gm[1, 0] * g[2, 0] + gm[1, 1] * g[2, 1] + gm[1, 2] * g[2, 2]
                m20 = gm[2, 0] * g[0, 0] + gm[2, 1] * g[0, 1] + gm[2, 2] * g[0, 2]
                m21 = gm[2, 0] * g[1, 0] + gm[2, 1] * g[1, 1] + gm[2, 2] * g[1, 2]
                a0, a1, a2 = m21 - m12, m02 - m20, m10 - m01
                b = jl[i, k]
                out[3 * k] = b[0, 0] * a0 + b[1, 0] * a1 + b[2, 0] * a2
                out[3 * k + 1] = b[0, 1] * a0 + b[1, 1] * a1 + b[2, 1] * a2
                out[3 * k + 2] = b[0, 2] * a0 + b[1, 2] * a1 + b[2, 2] * a2


# ---------------------------------------------------------------------------- many-column solves

@_kernel
def _forward_many(lp, li, lx, linv, x):
    """``L y = b`` in place for x (n, 3, M): M right-hand sides at once (the innermost loop
    runs over them, so one pass over L serves all)."""
    n, mcols = x.shape[0], x.shape[2]
    for j in range(n):
        m = linv[j]
        for c in range(mcols):
            x0, x1, x2 = x[j, 0, c], x[j, 1, c], x[j, 2, c]
            x[j, 0, c] = m[0, 0] * x0
            x[j, 1, c] = m[1, 0] * x0 + m[1, 1] * x1
            x[j, 2, c] = m[2, 0] * x0 + m[2, 1] * x1 + m[2, 2] * x2
        for p in range(lp[j], lp[j + 1]):
            i = li[p]
            for r in range(3):
                b0, b1, b2 = lx[p, r, 0], lx[p, r, 1], lx[p, r, 2]
                for c in range(mcols):
                    x[i, r, c] -= b0 * x[j, 0, c] + b1 * x[j, 1, c] + b2 * x[j, 2, c]


@_kernel
def _backward_many(lp, li, lx, linv, x):
    """``L^T x = y`` in place for x (n, 3, M) (after ``_forward_many``)."""
    n, mcols = x.shape[0], x.shape[2]
    s = np.empty((3, mcols))
    for j in range(n - 1, -1, -1):
        for r in range(3):
            for c in range(mcols):
                s[r, c] = x[j, r, c]
        for p in range(lp[j], lp[j + 1]):
            i = li[p]
            for r in range(3):
                b0, b1, b2 = lx[p, r, 0], lx[p, r, 1], lx[p, r, 2]
                for c in range(mcols):
                    v = x[i, r, c]
                    s[0, c] -= b0 * v
                    s[1, c] -= b1 * v
                    s[2, c] -= b2 * v
        m = linv[j]
        for c in range(mcols):
            x[j, 0, c] = m[0, 0] * s[0, c] + m[1, 0] * s[1, c] + m[2, 0] * s[2, c]
            x[j, 1, c] = m[1, 1] * s[1, c] + m[2, 1] * s[2, c]
            x[j, 2, c] = m[2, 2] * s[2, c]


def solve_many(chol, x: np.ndarray) -> np.ndarray:
    """``A y = x`` in place for x (n, 3, M) in the factor's own (permuted) row order, with the
    numeric factorization held by ``chol`` (a ``mesh.block_cholesky.BlockCholesky``)."""
    pt = chol.pattern
    _forward_many(pt.lp, pt.li, chol.lx, chol.linv, x)
    _backward_many(pt.lp, pt.li, chol.lx, chol.linv, x)
    return x


# ---------------------------------------------------------------------------- the state at one code

class PoissonAdjoint:
    """The transpose of ``mesh.solver.PoissonSolver.solve`` without constraints (anchors
    pinned at the origin): vertex cotangents (n, V, 3) to deformation-gradient cotangents
    (n, F, 3, 3). The Laplacian without the anchors is symmetric, so it is its own adjoint;
    factored once per template."""

    def __init__(self, poisson):
        self.divergence_t = poisson.divergence.T.tocsr()          # (3F, V)
        self.free = np.setdiff1d(np.arange(poisson.n_vertices), poisson.anchors)
        lap = poisson.laplacian.tocsr()
        self.solver = FactorizedSolver(lap[self.free][:, self.free].tocsc())
        self.n_vertices = poisson.n_vertices

    def __call__(self, cotangent: np.ndarray) -> np.ndarray:
        g = np.asarray(cotangent, dtype=float)
        n = len(g)
        lam = np.zeros((self.n_vertices, 3 * n))
        rhs = np.ascontiguousarray(g.transpose(1, 0, 2)).reshape(self.n_vertices, 3 * n)
        lam[self.free] = self.solver.solve(rhs[self.free])
        gu = self.divergence_t @ lam                                 # rows (f, d), columns (n, c)
        nf = gu.shape[0] // 3
        return np.ascontiguousarray(gu.reshape(nf, 3, n, 3).transpose(2, 0, 3, 1))  # (n, F, c, d)


class DecodeTangent:
    """The relative rotation decoder at one code: the body and the exact derivatives there.

    Made by ``RelativeRotationEncoder.tangent(code)`` (see the module docstring for the chain).

    Attributes:
        code: (D,) the code.
        vertices: (V, 3) ``decode(code)``, placed on the mean model.

    Methods:
        jvp(dcodes (m, D)) -> (m, V, 3): the change of ``vertices`` per code direction, in the
            placed frame, without the placement's own (rigid) change.
        vjp(cotangents (n, V, 3)) -> (n, D): the transposed map.
    """

    def __init__(self, code, vertices, *, jl, rel, q, rot, stretch, kinv, row, nbr, bk, valid, chol,
                 poisson, adjoint, part_vertices, part_rotations, lanes: int = 1):
        self.code = code
        self.vertices = vertices
        self._jl, self._rel, self._q, self._rot, self._stretch, self._kinv = jl, rel, q, rot, stretch, kinv
        self._row, self._nbr, self._bk, self._valid = row, nbr, bk, valid
        self._chol, self._poisson, self._adjoint = chol, poisson, adjoint
        self._parts, self._part_rot = part_vertices, part_rotations
        self._n_rows = chol.pattern.n
        self._lanes = lanes
        self.n_faces = len(q)

    def _placed(self, x: np.ndarray) -> np.ndarray:
        """Unplaced vertex changes (m, V, 3) turned as the placement turned each part."""
        if len(self._parts) == 1:
            return x @ self._part_rot[0].T
        out = np.empty_like(x)
        for idx, r in zip(self._parts, self._part_rot):
            out[:, idx] = x[:, idx] @ r.T
        return out

    def _unplaced(self, g: np.ndarray) -> np.ndarray:
        if len(self._parts) == 1:
            return g @ self._part_rot[0]
        out = np.empty_like(g)
        for idx, r in zip(self._parts, self._part_rot):
            out[:, idx] = g[:, idx] @ r
        return out

    def _jvp_block(self, dcode: np.ndarray) -> np.ndarray:
        """Gradient tangents dU (m, F, 3, 3) of code directions (m, F, 15)."""
        m = len(dcode)
        x = np.empty((self._n_rows, 3, 3 * m))
        _tangent_rhs(dcode, self._jl, self._rel, self._q, self._nbr, self._bk, self._valid, self._row, x)
        solve_many(self._chol, x)
        du = np.empty((m, self.n_faces, 3, 3))
        _tangent_gradients(x, self._row, self._rot, self._stretch, self._kinv, dcode, du)
        return du

    def jvp(self, dcodes: np.ndarray) -> np.ndarray:
        """Vertex changes (m, V, 3) of code directions (m, D) or (D,)."""
        dc = np.ascontiguousarray(np.atleast_2d(dcodes), dtype=float).reshape(-1, self.n_faces, 15)
        m = len(dc)
        blocks = [dc[s:s + JVP_BLOCK] for s in range(0, m, JVP_BLOCK)]
        if self._lanes == 2 and len(blocks) > 1:
            half = len(blocks) // 2
            first, second = run_both(lambda: [self._jvp_block(b) for b in blocks[:half]],
                                     lambda: [self._jvp_block(b) for b in blocks[half:]])
            du = first + second
        else:
            du = [self._jvp_block(b) for b in blocks]
        return self._placed(self._poisson.solve(np.concatenate(du)))

    def vjp(self, cotangents: np.ndarray) -> np.ndarray:
        """Code gradients (n, D) of vertex cotangents (n, V, 3) or (V, 3) (placed frame)."""
        g = np.asarray(cotangents, dtype=float)
        if g.ndim == 2:
            g = g[None]
        gu = self._adjoint(self._unplaced(g))
        n = len(gu)
        gcode = np.empty((n, self.n_faces, 15))
        x = np.empty((self._n_rows, 3, 3 * n))
        _adjoint_gradients(gu, self._rot, self._stretch, self._kinv, self._row, x, gcode)
        solve_many(self._chol, x)
        _adjoint_relative(x, self._row, self._q, self._rel, self._jl, self._nbr, self._valid, gcode)
        return gcode.reshape(n, -1)


class AffineDecodeTangent:
    """The same interface for an affine decoder (the vertex encoding): ``vertices = base + code``
    reshaped, so a tangent is the code direction itself."""

    def __init__(self, code, vertices):
        self.code = code
        self.vertices = vertices

    def jvp(self, dcodes: np.ndarray) -> np.ndarray:
        dc = np.atleast_2d(np.asarray(dcodes, dtype=float))
        return dc.reshape(len(dc), -1, 3)

    def vjp(self, cotangents: np.ndarray) -> np.ndarray:
        g = np.asarray(cotangents, dtype=float)
        return g.reshape(1 if g.ndim == 2 else len(g), -1)
