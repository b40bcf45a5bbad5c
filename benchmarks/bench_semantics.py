"""Semantic generation: a body meeting targets, a (masked) morph, a crowd of 100, with the share of
time in decoding, measuring and solving, each against a baseline run in the same process (the
same closed loop measuring the whole measurement set at every step, as a loop that does not know
what a request needs would); then the random-request study (200 requests of stature, mass and
waist together inside the population's 2nd-98th percentiles: success rate, error percentiles,
time per request), once with jointly plausible requests (the headline) and once with every
variable drawn independently (box corners included), split by plausibility.

    python benchmarks/bench_semantics.py [--subjects 24] [--encoding vertex|rre] [--crowd 100] [--requests 200] [--out DIR]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bodyspace.data.template import load_template  # noqa: E402
from bodyspace.model import BodyModel  # noqa: E402
from bodyspace.report.semantic_report import requests_in_display_units, write_request_report  # noqa: E402
from bodyspace.semantics.model import SemanticModel  # noqa: E402
from bodyspace.studies.requests import JOINT_QUANTILE, request_study  # noqa: E402
from bodyspace.synth.population import build_population


def _share(timings: dict, total: float) -> str:
    parts = [f"{k} {100 * v / total:.0f}%" for k, v in timings.items()]
    return ", ".join(parts + [f"other {100 * max(total - sum(timings.values()), 0) / total:.0f}%"])


class MeasureEverything(SemanticModel):
    """Baseline: the same closed loop, but every step measures the whole measurement set."""

    def measure_body(self, vertices, names=None) -> dict:
        return super().measure_body(vertices, None)


def _timed(fn):
    t = time.perf_counter()
    out = fn()
    return out, time.perf_counter() - t


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--subjects", type=int, default=24)
    ap.add_argument("--encoding", default="vertex")
    ap.add_argument("--crowd", type=int, default=100, help="crowd size")
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

        base = MeasureEverything(model).fit(db, template=template)
        targets = {"stature": 1.80, "mass": 80.0, "waist_girth": 0.90}
        sm.generate(targets, rng=0)  # warm caches
        base.generate(targets, rng=0)
        r, total = _timed(lambda: sm.generate(targets, rng=1))
        _, total_b = _timed(lambda: base.generate(targets, rng=1))
        print(f"generate {targets}: {total:.3f} s (baseline {total_b:.3f} s, x{total_b / total:.1f}), "
              f"{r.iterations} corrections, converged={r.converged}, "
              f"residuals {{{', '.join(f'{k}: {v:+.4f}' for k, v in r.residuals().items())}}}; "
              f"{_share(r.timings, total)}")

        x0 = r.vertices
        for mask in (None, "upper_body"):
            for s_ in (sm, base):  # warm: a mask's blend matrix is factored once per model
                s_.morph(x0, {"stature": 0.05}, keep=["mass"], mask=mask)
            m, total = _timed(lambda: sm.morph(x0, {"stature": 0.05}, keep=["mass"], mask=mask))
            _, total_b = _timed(lambda: base.morph(x0, {"stature": 0.05}, keep=["mass"], mask=mask))
            print(f"morph stature +5 cm keep mass, mask={mask}: {total:.3f} s (baseline {total_b:.3f} s, "
                  f"x{total_b / total:.1f}), {m.iterations} corrections, "
                  f"residuals {{{', '.join(f'{k}: {v:+.4f}' for k, v in m.residuals().items())}}}; "
                  f"{_share(m.timings, total)}")

        n = args.crowd
        ask = {"sex": 0.0, "mass": 65.0, "stature": (1.55, 1.85)}
        crowd, total = _timed(lambda: sm.crowd(n, ask, rng=2))
        _, total_b = _timed(lambda: base.crowd(min(n, 20), ask, rng=2))
        total_b *= n / min(n, 20)  # the baseline on 20 bodies, scaled
        agg = {k: sum(c.timings[k] for c in crowd) for k in crowd[0].timings}
        its = np.array([c.iterations for c in crowd])
        print(f"crowd of {n} (female, 65 kg, 155-185 cm): {total:.2f} s ({total / n * 1000:.0f} ms a body; "
              f"baseline {total_b:.1f} s, x{total_b / total:.1f}), "
              f"{sum(c.converged for c in crowd)}/{n} converged, corrections mean {its.mean():.1f} max {its.max()}; "
              f"{_share(agg, total)}")

        if args.requests > 0:
            for stem, joint in (("requests", JOINT_QUANTILE), ("requests_independent", None)):
                study = request_study(sm, n=args.requests, rng=0, joint=joint)
                e = requests_in_display_units(study)["errors"]
                split = study["by_plausibility"]
                print(f"request study ({'jointly plausible' if joint else 'independent draws'}): "
                      f"{study['successes']}/{study['n']} ({100 * study['success_rate']:.1f}%) within "
                      f"tolerance [inside the {100 * split['quantile']:g}% joint region "
                      f"{split['inside']['successes']}/{split['inside']['n']}, outside "
                      f"{split['outside']['successes']}/{split['outside']['n']}, silent misses "
                      f"{study['silent_misses']}]; |error| p50/p90/p99/max: "
                      + "; ".join(f"{k} {v['p50']:.2f}/{v['p90']:.2f}/{v['p99']:.2f}/{v['max']:.2f} {v['unit']}"
                                  for k, v in e.items())
                      + f"; {study['time_s']['mean']:.2f} s a request (median {study['time_s']['median']:.2f}, "
                      f"max {study['time_s']['max']:.2f})")
                if args.out:
                    write_request_report(study, args.out, stem=stem)


if __name__ == "__main__":
    main()
