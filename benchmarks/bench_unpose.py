"""Unposing posed bodies of the template: speed against a plain numpy baseline, and accuracy.

Speed: ``unpose`` (compiled residual/Jacobian kernels, the prior's part of the normal matrix as
one gemm per bone and a symmetric rank-r update, Cholesky solves) against the same
Levenberg-Marquardt fit whose Gauss-Newton system is assembled the plain way in numpy (dense
Jacobian built with ``np.add.at``, dense projection ``(I - U^T U) J``, ``J^T J`` by matmul,
LU solves), in the same run; both must give the same bodies. Target: at most 20 ms a body on
top of measuring (issue 12).

Accuracy: subjects drawn like the synthetic database (``sample_subjects``) in all 39 library
poses, posed (a) by LBS as ``pose_bodies`` does by default, (b) by dual-quaternion skinning,
(c) by LBS plus Gaussian noise; the unposed body against the true rest body (both on the
ground; the mean offset removed, so the numbers are shape error, not placement).

Run: python benchmarks/bench_unpose.py [subjects]
"""

from __future__ import annotations

import os
import sys
import time
from pathlib import Path

import numpy as np
import scipy.sparse as sp

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import report  # noqa: E402

from bodyspace.data.template import load_template  # noqa: E402
from bodyspace.rig import unpose as U  # noqa: E402
from bodyspace.rig.posing import pose_bodies  # noqa: E402
from bodyspace.synth.phenotype import PhenotypeModel  # noqa: E402
from bodyspace.synth.population import sample_subjects  # noqa: E402
from bodyspace.synth.poses import load_pose_library  # noqa: E402

N_SPEED = 64      # bodies timed on the fast path
N_BASELINE = 8    # bodies timed on the baseline (it is slow), scaled


class DenseState(U._State):
    """The Gauss-Newton system of the same fit, assembled the plain way (the baseline)."""

    def _plain_residuals(self, Q, t, y):
        plan = self.plan
        N, P = Q.shape[:2]
        A = np.concatenate([Q.reshape(N, P, 9), t], axis=2).transpose(1, 0, 2).reshape(P, -1)
        blend = np.asarray(plan.work_weights @ A).reshape(-1, N, 12).transpose(1, 0, 2)
        M, m = blend[..., :9].reshape(N, -1, 3, 3), blend[..., 9:]
        Minv = np.linalg.inv(M)
        x = np.einsum("nvij,nvj->nvi", Minv, y - m)
        r = x[:, :plan.n_sample].reshape(N, -1) - plan.basis_mean
        F = r - (r @ plan.basis.T) @ plan.basis
        jr = sp.csr_matrix((plan.jr_coef, plan.jr_vertex, plan.jr_indptr), shape=(len(plan.joints), len(plan.work)))
        heads = np.einsum("cv,nvi->nci", jr.toarray(), x)
        i, p = plan.joints[:, 0], plan.joints[:, 1]
        C = U.JOINT_WEIGHT * (np.einsum("ncij,ncj->nci", Q[:, i] - Q[:, p], heads) + t[:, i] - t[:, p])
        cost = (np.einsum("ni,ni->n", F, F) + np.einsum("nci,nci->n", C, C) + U._gauge(plan, Q)[1]
                + U._pose_prior(plan, Q)[1])
        return F, C, heads, x, Minv, cost, jr

    def cost(self, Q, t, rows=None):
        return self._plain_residuals(Q, t, self.y if rows is None else self.y[rows])[-2]

    def normal_equations(self, Q, t, rows):
        plan = self.plan
        N, P = Q.shape[:2]
        F, C, heads, x, Minv, cost, jr = self._plain_residuals(Q, t, self.y[rows])
        ev, ep, ew = plan.e_vertex, plan.e_param, plan.e_weight
        QX = np.einsum("neij,nej->nei", Q[:, ep], x[:, ev])
        Me = Minv[:, ev] * ew[None, :, None, None]
        B = np.concatenate([Me @ U._skew(QX), -Me], axis=3)                  # (N, E, 3, 6)
        J = np.zeros((N, len(plan.work), 3, P, 6))
        np.add.at(J, (slice(None), ev, slice(None), ep), B.transpose(1, 0, 2, 3))
        J = J.reshape(N, len(plan.work) * 3, 6 * P)
        Js = J[:, :3 * plan.n_sample]
        JF = Js - plan.basis.T @ (plan.basis @ Js)                           # (I - U^T U) J
        normal = np.swapaxes(JF, 1, 2) @ JF
        grad = np.einsum("nik,ni->nk", JF, F)
        dh = np.einsum("cv,nvk->nck", jr.toarray(), J.reshape(N, len(plan.work), 3 * 6 * P)).reshape(N, -1, 3, 6 * P)
        i, p = plan.joints[:, 0], plan.joints[:, 1]
        JC = np.einsum("ncij,ncjk->ncik", Q[:, i] - Q[:, p], dh).reshape(N, -1, 3, P, 6)
        c = np.arange(len(i))
        JC[:, c, :, i, :3] -= U._skew(np.einsum("ncij,ncj->nci", Q[:, i], heads)).transpose(1, 0, 2, 3)
        JC[:, c, :, p, :3] += U._skew(np.einsum("ncij,ncj->nci", Q[:, p], heads)).transpose(1, 0, 2, 3)
        JC[:, c, :, i, 3:] += np.eye(3)
        JC[:, c, :, p, 3:] -= np.eye(3)
        JC = (U.JOINT_WEIGHT * JC).reshape(N, -1, 6 * P)
        normal += np.swapaxes(JC, 1, 2) @ JC
        grad += np.einsum("nck,nc->nk", JC, C.reshape(N, -1))
        U._add_priors(plan, Q, normal, grad)
        return cost, normal, grad


def _cpu() -> float:
    t = os.times()
    return t.user + t.system


def speed(rig, bodies) -> None:
    plan = U._plan(rig, rig.weights.tocsr(), "original", U._default_prior())
    U.unpose(bodies[:2], rig)                                                   # compile, warm
    c, t = _cpu(), time.perf_counter()
    rest, _, info = U.unpose(bodies, rig)
    t_fast, c_fast = time.perf_counter() - t, _cpu() - c
    c, t = _cpu(), time.perf_counter()
    one = [U.unpose(b, rig)[0] for b in bodies[:8]]
    t_one = (time.perf_counter() - t) / 8
    np.testing.assert_allclose(one, rest[:8], atol=1e-9)
    sub = bodies[:N_BASELINE]
    with U.single_threaded_blas():
        c0, t0 = _cpu(), time.perf_counter()
        Qf, tf, _, _ = U._fit(plan, sub, U.MAX_ITERATIONS)
        t_fit1, c_fit1 = time.perf_counter() - t0, _cpu() - c0
        c0, t0 = _cpu(), time.perf_counter()
        Qd, td, _, _ = U._fit(plan, sub, U.MAX_ITERATIONS, state_type=DenseState)
        t_dense, c_dense = time.perf_counter() - t0, _cpu() - c0
    # Same fit: same transforms to the LM's precision (both stop at the same tolerance).
    assert np.abs(Qf - Qd).max() < 1e-5 and np.abs(tf - td).max() < 1e-6, (np.abs(Qf - Qd).max(), np.abs(tf - td).max())
    n = len(bodies)
    print(f"unpose {n} bodies: {1000 * t_fast / n:.1f} ms a body wall, {1000 * c_fast / n:.1f} ms CPU "
          f"(iterations {info.iterations.mean():.1f} mean, {info.iterations.max()} max); one body alone "
          f"{1000 * t_one:.1f} ms; target <= 20 ms a body: {'PASS' if t_fast / n <= 0.020 else 'FAIL'} (wall), "
          f"{'PASS' if c_fast / n <= 0.020 else 'FAIL'} (CPU)")
    print(f"fit only, {N_BASELINE} bodies: compiled {1000 * t_fit1 / N_BASELINE:.1f} ms a body "
          f"({1000 * c_fit1 / N_BASELINE:.1f} CPU), dense numpy {1000 * t_dense / N_BASELINE:.1f} ms "
          f"({1000 * c_dense / N_BASELINE:.1f} CPU)")
    report("unpose fit", t_fit1, t_dense, N_BASELINE, "bodies")


def accuracy(rig, rest, library) -> None:
    names = list(library.names)
    R = library.stack(names, rig)
    truth = np.repeat(rest, len(names), axis=0)
    truth = truth - truth[..., 1].min(1)[:, None, None] * np.array([0.0, 1.0, 0.0])
    rows = []
    for label, skinning, noise in (("LBS (as pose_bodies)", "lbs", 0.0), ("dual-quaternion", "dqs", 0.0),
                                   ("LBS + 1 mm noise", "lbs", 0.001), ("LBS + 3 mm noise", "lbs", 0.003)):
        posed = np.concatenate([pose_bodies(np.repeat(b[None], len(names), 0), rig, R, on_ground=True,
                                            skinning=skinning) for b in rest])
        if noise:
            posed = posed + np.random.default_rng(1).normal(0.0, noise, posed.shape)
        t = time.perf_counter()
        got, _, info = U.unpose(posed, rig, check=False)
        elapsed = time.perf_counter() - t
        d = got - truth
        d -= d.mean(1, keepdims=True)
        e = np.linalg.norm(d, axis=2) * 1000
        per = e.mean(1)
        worst = int(e.max(1).argmax())
        rows.append((label, np.median(per), per.max(), np.percentile(e, 99), e.max(), names[worst % len(names)],
                     info.converged.mean() * 100, 1000 * elapsed / len(posed)))
    print(f"\naccuracy over {len(rest)} subjects x {len(names)} poses (mm, unposed vs true rest body):")
    print("| posed by | median of body means | worst body mean | 99th pct vertex | worst vertex (pose) | converged | ms a body |")
    print("|---|---|---|---|---|---|---|")
    for label, med, wmean, p99, wmax, pose, conv, ms in rows:
        print(f"| {label} | {med:.3f} | {wmean:.3f} | {p99:.2f} | {wmax:.2f} ({pose}) | {conv:.0f} % | {ms:.1f} |")


def main(subjects: int = 3) -> None:
    template = load_template()
    rig = template.rigs["default"]
    library = load_pose_library()
    model = PhenotypeModel(template)
    drawn = sample_subjects(model, subjects, rng=0)
    rest = model.vertices(drawn.phenotypes)
    names = [library.names[i % len(library.names)] for i in range(N_SPEED)]
    bodies = pose_bodies(np.repeat(rest[:1], N_SPEED, 0), rig, library.stack(names, rig), on_ground=True)
    speed(rig, bodies)
    accuracy(rig, rest, library)


if __name__ == "__main__":
    main(int(sys.argv[1]) if len(sys.argv) > 1 else 3)
