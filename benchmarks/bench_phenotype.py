"""Phenotype → mesh: one sparse (N, T) × dense (T, V*3) product against a per-target loop.

Run: python benchmarks/bench_phenotype.py
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import best_time, report  # noqa: E402

from bodyspace.data.template import load_template  # noqa: E402
from bodyspace.synth.phenotype import PARAMETERS, PhenotypeModel


def per_target_loop(model: PhenotypeModel, phenotypes: np.ndarray) -> np.ndarray:
    """The obvious way: for each body, add each weighted target in turn."""
    W = model.weights(phenotypes).toarray()
    out = np.empty((len(phenotypes), model.base.size))
    for i, w in enumerate(W):
        v = model.base.reshape(-1).copy()
        for t in np.flatnonzero(w):
            v += w[t] * model.targets[t]
        out[i] = v
    return out.reshape(len(phenotypes), -1, 3)


def main(n: int = 500) -> None:
    model = PhenotypeModel(load_template())
    P = np.random.default_rng(0).random((n, len(PARAMETERS)))
    np.testing.assert_allclose(model.vertices(P[:20]), per_target_loop(model, P[:20]), atol=1e-5)
    fast = best_time(lambda: model.vertices(P))
    slow = best_time(lambda: per_target_loop(model, P[:100]), repeat=1) * n / 100
    report(f"phenotype→mesh, batch of {n}", fast, slow, n, "bodies")


if __name__ == "__main__":
    main()
