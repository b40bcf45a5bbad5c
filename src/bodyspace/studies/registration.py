"""How well a registration recovers a test scan's truth (``synth.scans.RawScan``)."""

from __future__ import annotations

import numpy as np

from bodyspace.rig.posing import count_folded_triangles
from bodyspace.synth.foreign import closest_points, to_frame

__all__ = ["SURFACE_LANDMARKS", "registration_errors"]

# The 13 one-vertex (surface) landmarks of the hm08 set: what a user can click on a scan.
SURFACE_LANDMARKS = ("head_top", "crotch", "neck_front", "neck_back", "shoulder_l", "bust_l", "underbust_front",
                     "thigh_l", "calf_l", "shoulder_r", "bust_r", "thigh_r", "calf_r")


def registration_errors(vertices: np.ndarray, faces: np.ndarray, scan) -> dict:
    """Errors of a registered template (V, 3) (the scan's frame and units) against a ``RawScan``.

    correspondence_mm: mean distance of each vertex from the same vertex of the true body;
    surface_mm: mean distance of the vertices from the true (noise-free) body surface;
    folded: triangles folded over (``count_folded_triangles``), and the true body's own count.
    """
    scale = float(scan.frame["scale"])
    truth = to_frame(scan.body, **scan.frame)
    corr = np.linalg.norm(vertices - truth, axis=1) / scale * 1000.0
    _, d = closest_points(vertices / scale, truth / scale, faces)
    return {"correspondence_mm": float(corr.mean()), "correspondence_p95_mm": float(np.percentile(corr, 95)),
            "surface_mm": float(1000.0 * d.mean()),
            "folded": int(count_folded_triangles(vertices, faces)),
            "folded_truth": int(count_folded_triangles(scan.body, faces))}
