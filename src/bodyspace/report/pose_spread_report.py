"""The Markdown table of ``studies.pose_spread.pose_spread_study``: every measurement's change
from the rest value over the library poses, measured as posed and after unposing."""

from __future__ import annotations

import numpy as np

__all__ = ["pose_spread_markdown"]


def _num(x: float) -> str:
    """A change for the table: 2 decimals, 2 significant digits below 0.01 (volumes in m^3)."""
    if not np.isfinite(x):
        return "–"
    if 0 < abs(x) < 0.01:
        return f"{x:.2g}"
    return f"{x:.2f}" if abs(x) < 100 else f"{x:.0f}"


def pose_spread_markdown(result, header: str = "") -> str:
    """Markdown: a per-measurement table (median and worst |change| from the rest value, the
    worst pose, undefined values, poses within tolerance) for both ways of measuring, then the
    unposing accuracy. ``header``: lines put first (date, code version, machine)."""
    rows = result.summary()
    S, P = result.posed.shape[:2]
    lines = [header.rstrip(), ""] if header else []
    lines += [f"{S} subjects (drawn like the synthetic database) x {P} poses. |change| = |value in the pose - "
              "value of the same body at rest|, in the measurement's unit. *within*: poses in which every "
              "subject is within the tolerance (1 cm, 1 kg, else 1 % of the rest value). *undef.*: values "
              "the measurement leaves undefined (NaN with a reason).", "",
              "| measurement | unit | tol. | as posed: median | worst (pose) | undef. | within | unposed: median "
              "| worst (pose) | undef. | within |",
              "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        a, b = r["posed"], r["unposed"]
        lines.append(f"| {r['name']} | {r['unit']} | {_num(r['tolerance'])} | {_num(a['median'])} | "
                     f"{_num(a['worst'])} ({a['worst_pose']}) | {a['undefined']} | {a['poses_within']}/{P} | "
                     f"{_num(b['median'])} | {_num(b['worst'])} ({b['worst_pose']}) | {b['undefined']} | "
                     f"{b['poses_within']}/{P} |")
    lengths = [r for r in rows if r["unit"] == "cm"]
    ok = [r for r in lengths if r["unposed"]["poses_within"] == P]
    lines += ["", f"Unposed: {len(ok)} of {len(lengths)} girths and lengths within 1 cm of the rest value in every "
              f"pose (as posed: {sum(r['posed']['poses_within'] == P for r in lengths)})."]
    missed = [r for r in lengths if r["unposed"]["poses_within"] < P]
    if missed:
        lines.append("Missed: " + ", ".join(f"{r['name']} (worst {_num(r['unposed']['worst'])} cm in "
                                            f"{r['unposed']['worst_pose']})" for r in missed) + ".")
    err = result.unpose_error_mm
    lines += [f"Unposing: mean vertex distance from the true rest body {np.median(err):.3f} mm median, "
              f"{err.max():.3f} mm worst body; {1000 * result.unpose_seconds / err.size:.0f} ms a body (wall)."]
    return "\n".join(lines) + "\n"
