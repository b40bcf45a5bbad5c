"""The picture of measured bodies: each body front and side with the tape paths its measurements
took (``bodyspace measure --png``).

A scanner's mesh turned about the vertical showed its back in the "front" view, so each body and
its paths are first stood facing the camera with the set's landmarks
(``conventions.standing_placement``); the values never depend on it. The drawing is
``report.render.contact_sheet``'s.
"""

from __future__ import annotations

import os
from typing import Mapping, Sequence

import numpy as np

from bodyspace.measure import conventions
from bodyspace.measure.definitions import MeasurementSet
from bodyspace.report.render import contact_sheet


def measured_bodies_figure(path: str | os.PathLike, bodies: Sequence[tuple[np.ndarray, np.ndarray]],
                           results: Sequence[Mapping], mset: MeasurementSet, labels: Sequence[str],
                           title: str = "bodyspace measure"):
    """Write a PNG of ``bodies`` ((V_i, 3) vertices, (F_i, 3) faces; metres, +Y up) front and side,
    each with the polylines of its measured values (``results[i]``: name -> Measurement evaluated
    with ``keep_polylines=True``; NaN values and those without a path are not drawn), facing the
    camera where ``mset``'s landmarks place the body. Returns the path written."""
    shown, paths = [], []
    for (v, _), measured in zip(bodies, results):
        lines = [np.asarray(m.polyline) for m in measured.values()
                 if m.polyline is not None and not np.isnan(m.value)]
        found = conventions.standing_placement(mset.landmarks, v[None])
        if found is not None:
            R, t, _ = found
            v, lines = v @ R.T + t, [q @ R.T + t for q in lines]
        shown.append(v)
        paths.append(lines)
    return contact_sheet(shown, [f for _, f in bodies], path, labels=list(labels), views=("front", "side"),
                         polylines=paths, title=title, panel_height=6.0)
