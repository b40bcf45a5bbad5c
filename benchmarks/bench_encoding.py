"""Benchmark of the relative rotation encoding on the 13,380-vertex template.

Prints, in one run:
- decode ms per body, one body at a time, with the chosen method (``rotation_solver="exact"``:
  consistent codes by the tree rotations, all others by a compiled block Cholesky
  factorization of Hasler Equation 9 on a pattern analysed once, on two threads for one body), the same on
  one thread (``n_jobs=1``), and the baseline that assembles and factors the rotation system
  with SuperLU for every body (``"direct"``), for: a round trip (encoded scan), halfway
  between rest and each pose of one subject, PCA samples of the shape-only (rest scans) and of
  the pose+shape model (all scans); the chosen method's CPU ms (CPU time of the calling
  thread), how many bodies needed a factorization, the speed-up over the baseline and the
  largest vertex distance (mm) from the baseline's decode;
- batch decode of 20 PCA samples (two threads);
- encode bodies/s;
- batch decode: 100 bodies at once vs one at a time, ms per body;
- the halfway-pose distortion (edge length, volume) of both encodings.

Data: a synthetic population (``bodyspace.synth.population``) built in a temporary folder.
Usage: ``python benchmarks/bench_encoding.py [--subjects 25] [--poses 3] [--repeat 5]``.
"""

from __future__ import annotations

import argparse
import statistics
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
from bodyspace.encoding import RelativeRotationEncoder, VertexEncoder
from bodyspace.shape import ShapeSpace, interpolation_distortion
from bodyspace.synth.population import build_population


def timed(fn, repeat: int) -> tuple[float, object]:
    """Median wall time (s) of ``fn()`` over ``repeat`` runs after one warm-up, and its result."""
    out = fn()
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times), out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--subjects", type=int, default=25)
    ap.add_argument("--poses", type=int, default=3)
    ap.add_argument("--repeat", type=int, default=5)
    args = ap.parse_args()

    t = load_template()
    print(f"template: {t.n_vertices} vertices, {len(t.faces)} triangles")
    with tempfile.TemporaryDirectory() as tmp:
        db = build_population(t, Path(tmp) / "population", args.subjects, args.poses, rng=0)
        scans = np.asarray(db.vertices, dtype=float)
        subject = np.asarray(db.scans["subject"]).astype(str)
        pose = np.asarray(db.scans["pose"]).astype(str)
    print(f"population: {len(scans)} scans ({args.subjects} subjects x rest + {args.poses} poses)")

    t0 = time.perf_counter()
    # The synthetic population is posed by linear blend skinning, which folds a few triangles in
    # some poses (armpits): accept them here (on_flipped="ignore"); see docs/encoding.md.
    enc = RelativeRotationEncoder(t.vertices, t.faces, on_flipped="ignore")
    setup = time.perf_counter() - t0
    t0 = time.perf_counter()
    enc.fit(scans)
    fit = time.perf_counter() - t0
    print(f"encoder setup (adjacency, tree, factorizations) {setup * 1e3:.0f} ms; fit (mean model) {fit * 1e3:.0f} ms")

    # --- encode
    t0 = time.perf_counter()
    codes = enc.encode(scans)
    enc_s = (time.perf_counter() - t0) / len(scans)
    print(f"encode: {1 / enc_s:.0f} bodies/s ({enc_s * 1e3:.1f} ms per body, {len(scans)} bodies)")

    # --- decode one body: fast vs refactorize-every-body, three kinds of code
    space = ShapeSpace(enc, n_components=min(30, len(scans) - 1)).fit(codes)
    rest = np.flatnonzero((pose == "rest") & (subject == subject[0]))[0]
    posed = np.flatnonzero((pose != "rest") & (subject == subject[0]))[0]
    shape_space = ShapeSpace(enc, n_components=min(30, int((pose == "rest").sum()) - 1)).fit(codes[pose == "rest"])
    n_samples = 4
    cases = {"round trip (encoded scan)": codes[posed][None]}
    for p in np.flatnonzero((pose != "rest") & (subject == subject[0])):
        cases[f"halfway rest -> {pose[p]}"] = (0.5 * (codes[rest] + codes[p]))[None]
    cases["PCA sample, shape-only model (rest scans)"] = shape_space.inverse_transform(
        shape_space.sample_coefficients(n_samples, sigma_range=2.0, rng=0))
    cases["PCA sample, pose+shape model (all scans)"] = space.inverse_transform(
        space.sample_coefficients(n_samples, sigma_range=2.0, rng=0))
    height = np.ptp(enc.mean_vertices_, axis=0).max()
    one_lane = RelativeRotationEncoder(t.vertices, t.faces, on_flipped="ignore", n_jobs=1).fit(scans)
    print("\ndecode one body, ms (median of %d; PCA rows: mean over %d samples, 2 sigma, all components):"
          % (args.repeat, n_samples))
    print(f"  {'code':44s} {'chosen':>7s} {'cpu':>6s} {'1 lane':>7s} {'fact.':>5s} {'baseline':>9s} "
          f"{'ratio':>6s} {'dev. mm':>8s}")
    for name, rows in cases.items():
        res = {}
        for label, encoder, solver in (("chosen", enc, "exact"), ("one lane", one_lane, "exact"),
                                       ("baseline", enc, "direct")):
            encoder.rotation_solver = solver
            times, cpus, outs, fact = [], [], [], 0
            for code in rows:
                repeat = args.repeat if solver != "direct" else max(1, args.repeat // 2)
                c0 = time.thread_time()
                el, out = timed(lambda: encoder.decode(code), repeat)
                cpus.append((time.thread_time() - c0) / (repeat + 1))
                times.append(el)
                outs.append(out)
                fact += encoder.last_factorized_
            res[label] = (float(np.mean(times)), np.concatenate(outs), fact, float(np.mean(cpus)))
        enc.rotation_solver = "exact"
        fast, a, fact, cpu = res["chosen"]
        base, ref = res["baseline"][0], res["baseline"][1]
        dev = np.linalg.norm(a - ref, axis=-1).max() * 1e3
        assert dev < 1e-6 * height * 1e3  # the chosen method is exact: equal to the baseline
        print(f"  {name:44s} {fast * 1e3:7.1f} {cpu * 1e3:6.1f} {res['one lane'][0] * 1e3:7.1f} "
              f"{fact:2d}/{len(rows):<2d} {base * 1e3:9.1f} {base / fast:6.1f} {dev:8.4f}")

    # --- batch decode
    def per_body(fn, items, runs=2):
        best = np.inf
        for _ in range(runs):
            t0 = time.perf_counter()
            fn(items)
            best = min(best, (time.perf_counter() - t0) / len(items))
        return best

    batch = codes[np.arange(100) % len(codes)]
    single = per_body(lambda cs: [enc.decode(c) for c in cs], batch[:20])
    many = per_body(enc.decode, batch)
    print(f"\nbatch decode (round-trip codes, best of 2): one at a time {single * 1e3:.1f} ms/body, "
          f"100 at once {many * 1e3:.1f} ms/body ({single / many:.2f}x)")
    rest_rows = np.flatnonzero(pose == "rest")
    mixed = np.stack([0.5 * (codes[i] + codes[i + 1]) for i in rest_rows[:10]])
    single = per_body(lambda cs: [enc.decode(c) for c in cs], mixed, runs=1)
    many = per_body(enc.decode, mixed, runs=1)
    print(f"batch decode (halfway codes, {len(mixed)}): one at a time {single * 1e3:.1f} ms/body, "
          f"all at once {many * 1e3:.1f} ms/body ({single / many:.2f}x)")
    for name, sp_ in (("shape-only", shape_space), ("pose+shape", space)):
        samples = sp_.inverse_transform(sp_.sample_coefficients(20, sigma_range=2.0, rng=1))
        single = per_body(lambda cs: [enc.decode(c) for c in cs], samples, runs=1)
        many = per_body(enc.decode, samples, runs=1)
        print(f"batch decode (20 PCA samples, {name}): one at a time {single * 1e3:.1f} ms/body, "
              f"all at once {many * 1e3:.1f} ms/body ({single / many:.2f}x)")
    t0 = time.perf_counter()
    for x in scans[:20]:
        enc.encode(x)
    one = (time.perf_counter() - t0) / 20
    print(f"encode one at a time: {1 / one:.0f} bodies/s ({one * 1e3:.1f} ms per body)")

    # --- interpolation: RRE vs vertex encoding
    venc = VertexEncoder(t.vertices, t.faces).fit(scans)
    print("\nhalfway between rest and a pose of one subject (mean relative edge-length change, volume change):")
    for p in np.flatnonzero(subject == subject[0])[1:]:
        r = interpolation_distortion(enc, scans[rest], scans[p])
        v = interpolation_distortion(venc, scans[rest], scans[p])
        print(f"  {pose[p]:22s} RRE edge {r['edge_change']:.2%} volume {r['volume_change']:+.2%}   "
              f"vertex edge {v['edge_change']:.2%} volume {v['volume_change']:+.2%}")


if __name__ == "__main__":
    main()
