"""How close two values of one measurement must be to count as the same: the ISO 20685-1
tolerances of 3-D scan anthropometry, as the tests, studies and benchmarks compare them.

Stature, heights and the smaller girths 4 mm; other lengths and breadths 5 mm; chest,
underbust, waist and hip girths 9 mm; values without an ISO figure (volume, area, mass, BMI) 1 %.
"""

from __future__ import annotations

ISO_LARGE_GIRTHS = ("chest_girth", "underbust_girth", "waist_girth", "hip_girth")
ISO_HEIGHTS = ("stature", "height", "crotch_height", "inside_leg_length", "leg_length")


def iso_tolerance(name: str, measurement) -> tuple[float, bool]:
    """(tolerance, relative) for the measurement ``name`` of a ``Measurement`` (its ``unit`` and
    ``method``): an absolute tolerance in metres, or a relative one (``relative`` True)."""
    if measurement.unit != "m":
        return 0.01, True
    if name in ISO_LARGE_GIRTHS:
        return 0.009, False
    if measurement.method == "slice" or name in ISO_HEIGHTS:
        return 0.004, False
    return 0.005, False
