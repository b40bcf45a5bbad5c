"""The underbust girth's fold band (issue 15, docs/measurements.md "Underbust girth") against the
plane through the underbust point it replaces: the whole default set on 1,000 bodies (as
bench_measure draws them: every third or so a woman whose breasts hang below the point), one
process, CPU seconds of this thread, best of 5 runs each, alternating. Also the underbust alone."""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import report  # noqa: E402

from bodyspace.data.template import load_template  # noqa: E402
from bodyspace.measure import evaluate, load_measurement_set  # noqa: E402
from bodyspace.measure.definitions import measurement_set_from_dict  # noqa: E402
from bodyspace.synth.phenotype import PARAMETERS, PhenotypeModel  # noqa: E402

N = 1000


def point_plane(mset):
    """The set with the underbust through the underbust point (one plane): main's definition."""
    d = mset.to_dict()
    for m in d["measurements"]:
        if m["name"] == "underbust_girth":
            m.pop("band")
            m["at"] = "underbust_front"
    return measurement_set_from_dict(d)


def only(mset, name):
    d = mset.to_dict()
    d["measurements"] = [dict(m, plausible=None) for m in d["measurements"] if m["name"] == name]
    return measurement_set_from_dict(d)


def main() -> None:
    template = load_template()
    rng = np.random.default_rng(0)
    phen = rng.uniform(0.1, 0.9, size=(N, len(PARAMETERS)))
    phen[:, 1] = rng.uniform(0.4, 0.8, N)  # adults
    bodies = PhenotypeModel(template).vertices(phen)
    fold = load_measurement_set()
    plane = point_plane(fold)
    sets = {"fold": fold, "plane": plane, "fold alone": only(fold, "underbust_girth"),
            "plane alone": only(plane, "underbust_girth")}
    for s in sets.values():
        evaluate(s, bodies[:2], template.faces)                       # compile and warm the caches
    best = {k: np.inf for k in sets}
    for _ in range(5):
        for k, s in sets.items():
            t = time.thread_time()
            out = evaluate(s, bodies, template.faces)
            best[k] = min(best[k], time.thread_time() - t)
    a = evaluate(fold, bodies, template.faces)["underbust_girth"].value
    b = evaluate(plane, bodies, template.faces)["underbust_girth"].value
    moved = np.abs(a - b) > 0
    print(f"{N} bodies: the fold band moves {int(moved.sum())} underbust values (by {np.round(np.quantile((a - b)[moved] * 100, [0, 0.5, 1]), 1) if moved.any() else []} cm: "
          f"min, median, max); CPU s best of 5: whole set {best['fold']:.3f} (fold) vs {best['plane']:.3f} (plane), "
          f"ratio {best['fold'] / best['plane']:.3f}; underbust alone {best['fold alone']:.3f} vs {best['plane alone']:.3f}, "
          f"ratio {best['fold alone'] / best['plane alone']:.2f}")
    report("measure, underbust fold band", best["fold"], best["plane"], N, "bodies")
    del out


if __name__ == "__main__":
    main()
