"""Benchmark: training data from the model and exact refinement (Rupprecht §3.1.2, Rupprecht §4.1).

A vertex-encoding BodyModel (shape only) is fitted on a synthetic population (60 subjects by
default, built into a temporary folder; not timed). Printed, all in the same run:

  * the 10,000-sample training set (25 coefficients uniform in ±3 sigma, Rupprecht's six
    measurements; target < 20 s) against the naive per-sample loop ``model.reconstruct`` +
    ``measure.measure`` (timed on 200 samples, scaled), and that both give the same numbers;
  * exact refinement from the forest's prediction, ms per request over 1,000 held-out requests
    in one batch (target < 50 ms), against a naive per-request Gauss-Newton whose Jacobian is
    finite differences over the 25 coefficients, each a reconstruct + measure (timed on a few);
  * the three-method table (mean / variance of measured − requested, cm) and the share of
    requests within 1 mm after refinement (target >= 99 %).

``--encoding rre``: an RRE model (24 subjects, 400 training bodies, 40 held-out requests by
default; every body is decoded): training-set time, refinement ms/request, iterations, and the
table (no naive baselines: they would take hours).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from threadpoolctl import threadpool_limits

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import report  # noqa: E402

from bodyspace.data.template import load_template  # noqa: E402
from bodyspace.mapping.gradients import RUPPRECHT_SIX, subset  # noqa: E402
from bodyspace.mapping.refine import refine  # noqa: E402
from bodyspace.mapping.training import make_training_set, sample_uniform  # noqa: E402
from bodyspace.measure import load_measurement_set, measure  # noqa: E402
from bodyspace.model import BodyModel  # noqa: E402
from bodyspace.report.mapping_report import mapping_tables_markdown  # noqa: E402
from bodyspace.studies.mapping import decode_seconds, estimate_seconds, evaluate_mapping  # noqa: E402
from bodyspace.synth.population import build_population


def naive_measure(model, z, mset):
    out = np.empty((len(z), len(RUPPRECHT_SIX)))
    for i, zi in enumerate(z):
        v = model.reconstruct(zi)[0]
        m = measure(mset, v, model.faces)
        out[i] = [100 * m[n] for n in RUPPRECHT_SIX]
    return out


def naive_refine(model, z0, target, mset, k, iters=8, h=1e-4, w=1e-4):
    """Gauss-Newton with forward-difference Jacobians through reconstruct + measure."""
    sd = np.sqrt(model.space.explained_variance_[:k])
    s = z0[:k] / sd
    for _ in range(iters):
        m0 = naive_measure(model, (s * sd)[None], mset)[0]
        J = np.empty((len(target), k))
        for j in range(k):
            e = s.copy()
            e[j] += h
            J[:, j] = (naive_measure(model, (e * sd)[None], mset)[0] - m0) / h
        g = J.T @ (m0 - target) + w * s
        s = np.clip(s - np.linalg.solve(J.T @ J + w * np.eye(k), g), -3, 3)
    return s * sd


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--subjects", type=int, default=None, help="60 (vertex) / 24 (rre)")
    ap.add_argument("--samples", type=int, default=None, help="10,000 (vertex) / 400 (rre)")
    ap.add_argument("--held-out", type=int, default=None, help="1,000 (vertex) / 40 (rre)")
    ap.add_argument("--encoding", choices=("vertex", "rre"), default="vertex")
    args = ap.parse_args()
    rre = args.encoding == "rre"
    args.subjects = args.subjects or (24 if rre else 60)
    args.samples = args.samples or (400 if rre else 10_000)
    args.held_out = args.held_out or (40 if rre else 1_000)
    if not rre:
        threadpool_limits(1)
    template = load_template()
    with tempfile.TemporaryDirectory() as tmp:
        t = time.perf_counter()
        db = build_population(template, Path(tmp) / "db", args.subjects, 0, rng=0)
        model = BodyModel.fit(db, encoding=args.encoding, selection="rest", template=template,
                              on_flipped="ignore" if rre else "raise")
        print(f"model: {model!r} in {time.perf_counter() - t:.1f} s (not timed)")
    if rre:
        bench_rre(model, args)
        return
    mset = subset(load_measurement_set(), RUPPRECHT_SIX)

    # 1. training set
    t = time.perf_counter()
    train = make_training_set(model, args.samples, 25, rng=0)
    fast = time.perf_counter() - t
    n_naive = 200
    z = sample_uniform(model, n_naive, 25, rng=0)
    t = time.perf_counter()
    ref = naive_measure(model, z, mset)
    naive = (time.perf_counter() - t) * args.samples / n_naive
    ok = np.isfinite(ref)
    diff = np.abs(ref[ok] - train.measurements[:n_naive][ok]).max()
    print(f"training set of {args.samples}: {fast:.2f} s (target < 20 s); naive loop (scaled from {n_naive}): "
          f"{naive:.1f} s; max difference {diff:.2e} cm")
    report("training set", fast, naive, args.samples, "bodies")

    # 2. the three methods, refinement timing
    ev, fitted = evaluate_mapping(model, args.samples, args.held_out, rng=0, n_jobs=2, sweep=True)
    per = ev.timings["refine_ms_per_request"]
    print(f"refinement: {per:.2f} ms/request over {args.held_out} requests (target < 50 ms)")
    n_slow = 3
    held = make_training_set(model, n_slow, 25, rng=1)
    z0 = fitted["forest"].predict(held.measurements)
    t = time.perf_counter()
    for i in range(n_slow):
        naive_refine(model, z0[i], held.measurements[i], mset, z0.shape[1])
    slow = (time.perf_counter() - t) / n_slow
    t = time.perf_counter()
    for i in range(n_slow):
        refine(model, z0[i], held.measurements[i])
    one = (time.perf_counter() - t) / n_slow
    print(f"naive finite-difference refinement: {1000 * slow:.0f} ms/request; ours one request alone: "
          f"{1000 * one:.1f} ms, batched: {per:.2f} ms")
    report("refinement (batched)", per / 1000, slow, 1, "requests")
    print()
    print(mapping_tables_markdown(ev))
    print(f"timings: { {k: round(v, 3) for k, v in ev.timings.items()} }")


def bench_rre(model, args) -> None:
    """RRE model: every body is decoded; training set, refinement ms/request, iterations, decodes."""
    per_body = decode_seconds(model)
    print(f"decode: {1000 * per_body:.0f} ms per ±3σ body; estimated run "
          f"{estimate_seconds(model, args.samples, args.held_out, per_body, sweep=False):.0f} s")
    ev, fitted = evaluate_mapping(model, args.samples, args.held_out, rng=0, n_trees=10, n_jobs=2, sweep=False)
    lin = fitted["linearization"]
    print(f"training set of {args.samples}: {ev.timings['training_set_s']:.1f} s "
          f"({ev.timings['training_set_s'] / (args.samples + args.held_out):.2f} s/body, held-out included); "
          f"linearization RMS {100 * lin.residual_rms_:.2f} cm")
    print(f"refinement: {ev.timings['refine_ms_per_request']:.0f} ms/request over {args.held_out} requests, "
          f"{ev.settings['refine_iterations_mean']:.1f} iterations (max {ev.settings['refine_iterations_max']}), "
          f"{ev.settings['refine_misses']} missed")
    print()
    print(mapping_tables_markdown(ev))
    print(f"timings: { {k: round(v, 3) for k, v in ev.timings.items()} }")


if __name__ == "__main__":
    main()
