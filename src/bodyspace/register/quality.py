"""How well a registration explains its scan, and the refusal of scans it cannot explain.

A fit always returns *a* body; what tells a good fit from a confident wrong one (two people, a
chair, a scan cut in half) is how much of the scan the registered surface explains and how much
of the template found scan points near it:

- ``explained``: the share of scan points within ``EXPLAINED_DISTANCE`` of the registered
  surface (isolated outliers are removed first: a good fit explains 99.5-100 % of the test
  scans; a remeshed body whose stepping leg the fit lost, 80.7 %; two people: about 0.5; a
  chair: the share of the chair a body happens to cover);
- ``coverage``: the share of template vertices that had a target at the last NICP iteration
  (holes under the arms and the soles, and fine parts whose scan normals are too noisy for the
  30° gate: toes, fingers, face, leave 25-30 % without on the test scans);
- ``quality`` = min(explained / EXPLAINED_GOOD, coverage / COVERAGE_GOOD) capped at 1. A scan
  is refused below ``MIN_QUALITY`` (0.9: under 87 % explained, or under 54 % covered).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from bodyspace.synth.foreign import closest_points

__all__ = ["Quality", "assess", "EXPLAINED_DISTANCE", "MIN_QUALITY"]

EXPLAINED_DISTANCE = 0.010
EXPLAINED_GOOD = 0.97
COVERAGE_GOOD = 0.60
MIN_QUALITY = 0.90
# Scan points the shares are computed on (a fixed random subsample: ±0.5 % at 20,000).
ASSESS_POINTS = 20_000


@dataclass(frozen=True)
class Quality:
    """explained, coverage, quality: shares in [0, 1]; point_distance: (n,) metres, the
    distances of a subsample of the scan's points to the registered surface; accepted: quality
    >= MIN_QUALITY; point_index: (n,) which scan points the distances are of."""

    explained: float
    coverage: float
    quality: float
    point_distance: np.ndarray
    point_index: np.ndarray

    @property
    def accepted(self) -> bool:
        return self.quality >= MIN_QUALITY

    def describe(self) -> str:
        return (f"quality {self.quality:.2f} (the fit explains {100 * self.explained:.1f} % of the scan's points "
                f"within {1000 * EXPLAINED_DISTANCE:.0f} mm; {100 * self.coverage:.1f} % of the template found "
                f"scan points; accepted at {MIN_QUALITY:.2f} and above)")


def assess(vertices: np.ndarray, faces: np.ndarray, points: np.ndarray, has_target: np.ndarray) -> Quality:
    """Quality of a registered mesh (V, 3), (F, 3) against scan points (P, 3) (same frame,
    metres); has_target: (V,) the NICP's last correspondences."""
    sub = np.sort(np.random.default_rng(0).choice(len(points), min(len(points), ASSESS_POINTS), replace=False))
    _, dist = closest_points(points[sub], vertices, faces)
    explained = float(np.mean(dist <= EXPLAINED_DISTANCE))
    coverage = float(np.mean(has_target))
    q = min(1.0, explained / EXPLAINED_GOOD, coverage / COVERAGE_GOOD)
    return Quality(explained, coverage, q, dist, sub)
