"""The NICP's conjugate gradients (issue 15): the compiled loop (``nicp._pcg``) against the numpy
loop it replaced, on the template's 13,380 vertices, in one process, CPU time of this thread.

The system is one level's: ``β LᵀL ⊗ I_4`` plus the data blocks of 70 % of the vertices, the
right-hand side of a random displacement; both loops run ``CG_ITERATIONS`` iterations from zero
and must agree to rounding. Then one whole ``nonrigid_icp`` (6 levels x 2 iterations, a heavier
body's 20,000 points from the mean body) with each loop.

    python benchmarks/bench_nicp.py
"""

from __future__ import annotations

import os
import time

import numpy as np

from _common import best_time, report
from bodyspace.data.template import load_template
from bodyspace.mesh.geometry import vertex_normals
from bodyspace.mesh.operators import cotangent_laplacian
from bodyspace.register import nicp
from bodyspace.synth.phenotype import PhenotypeModel


def numpy_solve(self, b, X, iterations):
    """The numpy loop ``_System.solve`` was before (kept here as the baseline)."""
    def apply(X):
        V = len(X)
        out = self.beta * (self.LL @ X.reshape(V, 12)).reshape(V, 4, 3)
        ax = (self.a[:, :, None] * X).sum(axis=1)
        out += (self.w[:, None] * self.a)[:, :, None] * ax[:, None, :]
        if self.landmark is not None:
            DL, f = self.landmark
            out += f * (DL.T @ (DL @ X.reshape(4 * V, 3))).reshape(V, 4, 3)
        return out
    x = X.copy()
    r = b - apply(x)
    z = self.pre @ r
    p = z.copy()
    rz = (r * z).sum(axis=(0, 1))
    for _ in range(int(iterations)):
        Ap = apply(p)
        pAp = (p * Ap).sum(axis=(0, 1))
        alpha = np.where(pAp > 0, rz / np.where(pAp > 0, pAp, 1.0), 0.0)
        x += alpha * p
        r -= alpha * Ap
        z = self.pre @ r
        rz_new = (r * z).sum(axis=(0, 1))
        p = z + np.where(rz > 0, rz_new / np.where(rz > 0, rz, 1.0), 0.0) * p
        rz = rz_new
    return x


def main():
    template = load_template()
    V = len(template.vertices)
    L = cotangent_laplacian(template.vertices, template.faces)
    LL = (L.T @ L).tocsr()
    rng = np.random.default_rng(0)
    a = np.concatenate([template.vertices, np.ones((V, 1))], axis=1)
    w = (rng.random(V) < 0.7).astype(float)
    system = nicp._System(LL, a, w, 30.0)
    b = system.apply(rng.normal(scale=1e-3, size=(V, 4, 3)))
    x0 = np.zeros((V, 4, 3))
    system.solve(b, x0, 2)                                     # compile / load the cache
    fast = best_time(lambda: system.solve(b, x0, nicp.CG_ITERATIONS), 5, time.thread_time)
    slow = best_time(lambda: numpy_solve(system, b, x0, nicp.CG_ITERATIONS), 5, time.thread_time)
    diff = np.abs(system.solve(b, x0, nicp.CG_ITERATIONS) - numpy_solve(system, b, x0, nicp.CG_ITERATIONS)).max()
    print(f"load average {os.getloadavg()[0]:.1f}; {nicp.CG_ITERATIONS} CG iterations: compiled {1000 * fast:.0f} ms, "
          f"numpy {1000 * slow:.0f} ms (CPU), largest difference {diff:.1e}")
    report("NICP conjugate gradients (25 iterations, 13,380 vertices)", fast, slow, 1, "solves")

    pm = PhenotypeModel(template)
    other = pm.vertices({"weight": 0.8, "muscle": 0.7})[0]
    pick = rng.choice(V, min(V, 20_000), replace=False)
    pts, nrm = other[pick], vertex_normals(other, template.faces)[pick]

    def run():
        return nicp.nonrigid_icp(template.vertices, template.faces, template.vertices, pts, nrm, steps=6, inner=2)
    t = time.thread_time()
    res = run()
    fast = time.thread_time() - t
    original = nicp._System.solve
    nicp._System.solve = numpy_solve
    try:
        t = time.thread_time()
        res_slow = run()
        slow = time.thread_time() - t
    finally:
        nicp._System.solve = original
    print(f"nonrigid_icp (6 levels x 2): compiled {fast:.2f} s, numpy {slow:.2f} s (CPU); folded {res.folded} / "
          f"{res_slow.folded}; largest vertex difference {1000 * np.abs(res.vertices - res_slow.vertices).max():.2g} mm")
    report("nonrigid_icp, 13,380 vertices", fast, slow, 1000, "millifits")


if __name__ == "__main__":
    main()
