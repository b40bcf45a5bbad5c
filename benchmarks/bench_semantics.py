"""Semantic generation: a body meeting targets, a (masked) morph, a crowd of 20, with the share of
time in decoding, measuring and solving; then the random-request study (200 requests of stature,
mass and waist together inside the population's 2nd-98th percentiles: success rate, error
percentiles, time per request).

    python benchmarks/bench_semantics.py [--subjects 24] [--encoding vertex|rre] [--requests 200] [--out DIR]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bodyspace.data.population import build_population  # noqa: E402
from bodyspace.data.template import load_template  # noqa: E402
from bodyspace.model import BodyModel  # noqa: E402
from bodyspace.report.semantic_report import format_request_report, request_study, write_request_report  # noqa: E402
from bodyspace.semantics.model import SemanticModel  # noqa: E402


def _share(timings: dict, total: float) -> str:
    parts = [f"{k} {100 * v / total:.0f}%" for k, v in timings.items()]
    return ", ".join(parts + [f"other {100 * max(total - sum(timings.values()), 0) / total:.0f}%"])


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--subjects", type=int, default=24)
    ap.add_argument("--encoding", default="vertex")
    ap.add_argument("--requests", type=int, default=200, help="random requests in the study (0: skip)")
    ap.add_argument("--out", default=None, help="folder for requests.md/json (default: print only)")
    args = ap.parse_args()
    template = load_template()
    with tempfile.TemporaryDirectory() as tmp:
        t = time.perf_counter()
        db = build_population(template, Path(tmp) / "db", args.subjects, 0, rng=0)
        model = BodyModel.fit(db, args.encoding, "rest", on_flipped="ignore")
        sm = SemanticModel(model).fit(db, template=template)
        print(f"setup ({args.subjects} subjects, {args.encoding}, {model.n_components} components, "
              f"semantic fit included): {time.perf_counter() - t:.2f} s")

        targets = {"stature": 1.80, "mass": 80.0, "waist_girth": 0.90}
        sm.generate(targets, rng=0)  # warm caches
        t = time.perf_counter()
        r = sm.generate(targets, rng=1)
        total = time.perf_counter() - t
        print(f"generate {targets}: {total:.3f} s, {r.iterations} corrections, converged={r.converged}, "
              f"residuals {{{', '.join(f'{k}: {v:+.4f}' for k, v in r.residuals().items())}}}; "
              f"{_share(r.timings, total)}")

        x0 = r.vertices
        for mask in (None, "upper_body"):
            t = time.perf_counter()
            m = sm.morph(x0, {"stature": 0.05}, keep=["mass"], mask=mask)
            total = time.perf_counter() - t
            print(f"morph stature +5 cm keep mass, mask={mask}: {total:.3f} s, {m.iterations} corrections, "
                  f"residuals {{{', '.join(f'{k}: {v:+.4f}' for k, v in m.residuals().items())}}}; "
                  f"{_share(m.timings, total)}")

        t = time.perf_counter()
        crowd = sm.crowd(20, {"sex": 0.0, "mass": 65.0, "stature": (1.55, 1.85)}, rng=2)
        total = time.perf_counter() - t
        agg = {k: sum(c.timings[k] for c in crowd) for k in crowd[0].timings}
        its = np.array([c.iterations for c in crowd])
        print(f"crowd of 20 (female, 65 kg, 155-185 cm): {total:.2f} s ({total / 20 * 1000:.0f} ms a body), "
              f"{sum(c.converged for c in crowd)}/20 converged, corrections mean {its.mean():.1f} max {its.max()}; "
              f"{_share(agg, total)}")

        if args.requests > 0:
            study = request_study(sm, n=args.requests, rng=0)
            e = study["errors"]
            print(f"request study: {study['successes']}/{study['n']} ({100 * study['success_rate']:.1f}%) within "
                  f"tolerance; |error| p50/p90/p99/max: "
                  + "; ".join(f"{k} {v['p50']:.2f}/{v['p90']:.2f}/{v['p99']:.2f}/{v['max']:.2f} {v['unit']}"
                              for k, v in e.items())
                  + f"; {study['time_s']['mean']:.2f} s a request (median {study['time_s']['median']:.2f}, "
                  f"max {study['time_s']['max']:.2f})")
            if args.out:
                write_request_report(study, args.out)
            else:
                print(format_request_report(study))


if __name__ == "__main__":
    main()
