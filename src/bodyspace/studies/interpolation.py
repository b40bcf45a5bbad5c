"""Interpolation study (Hasler Figure 5): halfway between every pair of scans of a few subjects.

Linear in code space, for the relative rotation encoding (RRE) and the vertex encoding; the
halfway mesh's mean relative edge-length change and volume change against the endpoints'
average (``shape.compare``'s definitions). RRE interpolates joint angles and keeps the body
intact; vertex interpolation pulls rotated limbs towards the chord.

Cost: one decode per halfway mesh and encoder (~0.2-0.4 s per RRE decode on 2 cores).
``report.shape_report.write_interpolation_report`` writes the table and the picture.
"""

from __future__ import annotations

import time
from itertools import combinations
from typing import Callable, Sequence

import numpy as np

from bodyspace.errors import ParameterError
from bodyspace.mesh.geometry import boundary_loops, capped_volume
from bodyspace.shape.compare import edge_lengths
from bodyspace.studies.scans import rows_by_subject

__all__ = ["interpolation_study"]


def interpolation_study(db, encoders: dict, n_subjects: int = 2, subjects: Sequence[str] | None = None,
                        progress: Callable[[str, float], None] | None = None) -> dict:
    """Halfway meshes between all pairs of scans of ``n_subjects`` subjects, per encoder.

    Args:
        db: a ``ScanDatabase``.
        encoders: {name: fitted encoder}, e.g. ``{"rre": ..., "vertex": ...}``.
        n_subjects: how many subjects (the first with at least two scans), unless ``subjects``.
    Returns:
        dict with ``rows`` (one per pair: subject, pose_a, pose_b, and per encoder
        ``{name}_edge_change`` / ``{name}_volume_change``, fractions), ``summary`` (per encoder:
        mean and max edge change, mean and max |volume change|), ``example`` (the pair with the
        largest vertex-encoding edge change: scan indices and the halfway meshes), ``cost_s``.
    """
    report = progress or (lambda m, f: None)
    t0 = time.perf_counter()
    by_subject = {s: r for s, r in rows_by_subject(db, np.arange(db.n_scans)).items() if len(r) >= 2}
    chosen = list(subjects) if subjects is not None else list(by_subject)[:n_subjects]
    if not chosen or any(s not in by_subject for s in chosen):
        raise ParameterError(f"interpolation_study: subjects {chosen!r}; expected subjects with at least two scans "
                             f"(available: {', '.join(list(by_subject)[:10]) or 'none'})")
    pairs = [(a, b) for s in chosen for a, b in combinations(by_subject[s].tolist(), 2)]
    rows = np.unique(np.array(pairs).ravel())
    where = {int(r): k for k, r in enumerate(rows)}
    scans = db.read(rows)
    ia = np.array([where[a] for a, _ in pairs])
    ib = np.array([where[b] for _, b in pairs])
    faces = np.asarray(db.faces)
    loops = boundary_loops(faces)
    ref_len = 0.5 * (edge_lengths(scans[ia], faces) + edge_lengths(scans[ib], faces))
    vol = capped_volume(scans, faces, loops)
    ref_vol = 0.5 * (vol[ia] + vol[ib])
    table = [{"subject": str(db.scans["subject"][a]), "pose_a": str(db.scans["pose"][a]),
              "pose_b": str(db.scans["pose"][b]), "scan_a": int(a), "scan_b": int(b)} for a, b in pairs]
    halfway = {}
    for k, (name, enc) in enumerate(encoders.items()):
        report(f"interpolating {len(pairs)} pairs ({name})", k / len(encoders))
        codes = enc.encode(scans)
        mid = enc.decode(0.5 * (codes[ia] + codes[ib]))
        halfway[name] = mid
        edge = np.mean(np.abs(edge_lengths(mid, faces) - ref_len) / ref_len, axis=-1)
        dvol = (capped_volume(mid, faces, loops) - ref_vol) / ref_vol
        for row, e, v in zip(table, edge, dvol):
            row[f"{name}_edge_change"] = float(e)
            row[f"{name}_volume_change"] = float(v)
    summary = {name: {"edge_change_mean": float(np.mean([r[f"{name}_edge_change"] for r in table])),
                      "edge_change_max": float(np.max([r[f"{name}_edge_change"] for r in table])),
                      "volume_change_abs_mean": float(np.mean([abs(r[f"{name}_volume_change"]) for r in table])),
                      "volume_change_abs_max": float(np.max([abs(r[f"{name}_volume_change"]) for r in table]))}
               for name in encoders}
    key = "vertex" if "vertex" in encoders else next(iter(encoders))
    best = int(np.argmax([r[f"{key}_edge_change"] for r in table]))
    example = {"pair": best, "scan_a": pairs[best][0], "scan_b": pairs[best][1],
               "a": scans[ia[best]], "b": scans[ib[best]],
               "halfway": {name: m[best] for name, m in halfway.items()}}
    report("interpolation done", 1.0)
    return {"subjects": chosen, "pairs": len(pairs), "rows": table, "summary": summary, "example": example,
            "cost_s": round(time.perf_counter() - t0, 2)}
