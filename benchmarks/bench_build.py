"""Benchmark: build a BodyModel (RRE, pose and shape, all scans) from 2,000 scans.

Target: under 60 s and under 6 GB peak memory on the 2-core machine.

Prints, in one run:
- the population build (100 subjects x 20 scans by default, into a temporary folder; not timed
  against the target);
- ``BodyModel.fit(db, "rre", "all", n_components=100)``: wall time per stage (encoder mean
  model, encoding pass, PCA) and the peak resident memory of the process (``ru_maxrss``);
- the baselines in the same run, each on a sample and extrapolated to all scans:
  encoding one scan per ``encode`` call; the previous encoding kernel (whole-body arrays, 3x3
  deformation gradients by Newton polar iteration); and the previous PCA solver (randomized
  subspace iteration, 2 power iterations) against the block Krylov solver on the codes of
  ``--pca-sample`` scans, with the variance each captures;
- the machine load (``os.getloadavg``) before and after: the machine is shared and noisy.

Usage: ``python benchmarks/bench_build.py [--subjects 100] [--poses 19] [--components 100]``.
"""

from __future__ import annotations

import argparse
import os
import resource
import sys
import tempfile
import time
from pathlib import Path

try:
    import bodyspace  # noqa: F401
except ImportError:  # run from a source checkout without installing
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "src"))

import numpy as np

from bodyspace.data.template import load_template
from bodyspace.encoding.rotations import (
    polar_decomposition,
    quaternion_conjugate,
    quaternion_from_matrix,
    quaternion_log,
    quaternion_multiply,
)
from bodyspace.mesh.operators import triangle_frames
from bodyspace.model import BodyModel
from bodyspace.shape.solvers import pca_block_krylov, pca_randomized
from bodyspace.synth.population import build_population


def peak_rss_gb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024 ** 2  # Linux: kB


def load() -> str:
    return "load average {:.2f} {:.2f} {:.2f}".format(*os.getloadavg())


def previous_encode(enc, x: np.ndarray) -> np.ndarray:
    """The previous encoding kernel, for the baseline: whole-body (N, F, 3, 3) deformation
    gradients, polar decomposition by the scaled Newton iteration, relative rotations as
    quaternions (same codes, to round-off)."""
    rest_inv = np.linalg.inv(triangle_frames(enc.template_vertices, enc.faces))
    u = triangle_frames(x, enc.faces) @ rest_inv
    r, s = polar_decomposition(u)
    q = quaternion_from_matrix(r)  # (N, F, 4)
    q_rel = quaternion_multiply(quaternion_conjugate(q)[:, :, None], q[:, enc.neighbors])
    mean_q = np.moveaxis(enc._mean_q, 0, -1)  # (F, slot, 4)
    rot = quaternion_log(quaternion_multiply(q_rel, quaternion_conjugate(mean_q)))
    stretch = s[..., [0, 0, 0, 1, 1, 2], [0, 1, 2, 1, 2, 2]] - enc.mean_stretch_
    return np.concatenate([rot.reshape(len(x), enc.n_faces, 9), stretch], axis=-1).reshape(len(x), -1)


def captured_variance(codes: np.ndarray, mean: np.ndarray, comps: np.ndarray) -> float:
    """Variance of ``codes`` (n, D) inside the span of ``comps`` (k, D), summed."""
    c = np.asarray(comps, dtype=np.float32)
    return float(np.sum((codes @ c.T - (mean.astype(np.float32) @ c.T)[None]).astype(np.float64) ** 2))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--subjects", type=int, default=100)
    ap.add_argument("--poses", type=int, default=19, help="poses per subject besides the rest pose")
    ap.add_argument("--components", type=int, default=100)
    ap.add_argument("--baseline-scans", type=int, default=40)
    ap.add_argument("--pca-sample", type=int, default=400, help="codes the two PCA solvers are compared on")
    args = ap.parse_args()
    print(f"start: {load()}, {os.cpu_count()} cores")

    template = load_template()
    with tempfile.TemporaryDirectory() as tmp:
        t = time.perf_counter()
        db = build_population(template, Path(tmp) / "population", args.subjects, args.poses, rng=0)
        print(f"population: {db!r} in {time.perf_counter() - t:.1f} s (not part of the target); "
              f"peak RSS so far {peak_rss_gb():.2f} GB")
        del db
        from bodyspace.data.database import ScanDatabase
        db = ScanDatabase.load(Path(tmp) / "population", check_values=False)

        t = time.perf_counter()
        model = BodyModel.fit(db, "rre", "all", n_components=args.components, template=template,
                              on_flipped="ignore")
        wall = time.perf_counter() - t
        print(f"BodyModel.fit: {model!r}")
        print(f"  stages (s): {model.provenance['timings_s']}  (PCA: {model.provenance['pca_method']}); {load()}")
        print(f"  wall {wall:.1f} s (target < 60 s), {db.n_scans / wall:.0f} scans/s; peak RSS "
              f"{peak_rss_gb():.2f} GB (target < 6 GB); explained variance "
              f"{model.space.explained_variance_ratio_.sum():.3f}")

        # Baselines, same process: one scan per encode call, and the previous kernel.
        rows = np.linspace(0, db.n_scans - 1, args.baseline_scans).round().astype(int)
        enc = model.encoder
        t = time.perf_counter()
        for r in rows:
            model.encode(db.mesh(r))
        one = (time.perf_counter() - t) / len(rows)
        x = np.asarray(db.vertices[rows], dtype=float)
        t = time.perf_counter()
        for s in range(0, len(rows), 4):  # 4 bodies per call: it was fastest per body in small batches
            previous_encode(enc, x[s:s + 4])
        prev = (time.perf_counter() - t) / len(rows)
        err = np.abs(previous_encode(enc, x[:4]) - enc.encode(x[:4])).max()
        batched = model.provenance["timings_s"]["encode_s"] / db.n_scans
        print(f"encoding: batched {1 / batched:.0f} scans/s; baselines: one scan per call {1 / one:.0f} scans/s "
              f"(x{one / batched:.1f}), previous kernel single-threaded {1 / prev:.0f} scans/s (x{prev / batched:.1f}, "
              f"all {db.n_scans} scans {prev * db.n_scans:.0f} s); codes agree to {err:.1e}; {load()}")

        # PCA: previous solver (subspace iteration, 2 power iterations) against block Krylov.
        rows = np.linspace(0, db.n_scans - 1, args.pca_sample).round().astype(int)
        codes = np.empty((len(rows), enc.n_features_), dtype=np.float32)
        for s in range(0, len(rows), 64):
            enc.encode(np.asarray(db.vertices[rows[s:s + 64]], dtype=float), out=codes[s:s + 64])
        mean = codes.mean(axis=0, dtype=np.float64)
        k = min(args.components, len(rows) - 1)
        res = {}
        for name, solver in (("previous", pca_randomized), ("block Krylov", pca_block_krylov)):
            t = time.perf_counter()
            _, comps = solver(codes, mean, k, rng=0)
            res[name] = (time.perf_counter() - t, captured_variance(codes, mean, comps))
        (tp, vp), (tk, vk) = res["previous"], res["block Krylov"]
        print(f"PCA on {len(rows)} codes, {k} components: previous {tp:.1f} s, block Krylov {tk:.1f} s, speed-up "
              f"x{tp / tk:.2f}; captured variance block Krylov / previous = {vk / vp:.5f}; {load()}")
        with tempfile.TemporaryDirectory() as tmp2:
            t = time.perf_counter()
            path = model.save(Path(tmp2) / "model.npz")
            size = path.stat().st_size / 1e6
            save_s = time.perf_counter() - t
            t = time.perf_counter()
            BodyModel.load(path)
            print(f"save {save_s:.1f} s ({size:.0f} MB), load {time.perf_counter() - t:.1f} s")


if __name__ == "__main__":
    main()
