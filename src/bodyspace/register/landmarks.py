"""Landmarks for a mesh of any topology: register the template to it, carry the landmarks across.

``bodyspace measure --landmarks`` needs a landmark file for a mesh that is not of the template's
topology. ``mesh_landmarks`` makes one: the template is registered to the mesh as to a scan
(``pipeline.register_scan``: the mesh's vertices and points sampled on its faces), and each
landmark of the measurement set (a weighted set of template vertices) is carried onto the
mesh by ``synth.foreign.carry_landmarks``: every template vertex it uses replaced by its closest
point of the mesh's surface (three vertices, barycentric weights). The result is a
``load_landmarks`` document for the mesh's own vertex ids.
"""

from __future__ import annotations

import numpy as np

from bodyspace.data.template import Template, load_template
from bodyspace.measure.definitions import MeasurementSet, load_measurement_set
from bodyspace.register.pipeline import Registration, register_scan
from bodyspace.synth.foreign import carry_landmarks

__all__ = ["mesh_landmarks", "landmark_document"]


def mesh_landmarks(vertices: np.ndarray, faces: np.ndarray, *, template: Template | None = None,
                   mset: MeasurementSet | None = None, units: str | None = None, up: str | None = None,
                   progress=None, **kw) -> tuple[dict[str, tuple[np.ndarray, np.ndarray]], Registration]:
    """The measurement set's landmarks on a mesh (V2, 3), (F2, 3) of any topology.

    units, up: the mesh's (None: found); kw: passed to ``register_scan``.
    Returns name → (vertex ids (k,), convex weights (k,)) of the mesh, and the registration.
    """
    template = template if template is not None else load_template()
    mset = mset if mset is not None else load_measurement_set()
    vertices = np.asarray(vertices, dtype=float)
    faces = np.asarray(faces, dtype=np.int64)
    reg = register_scan(vertices, faces, template=template, units=units, up=up, progress=progress,
                        name="the mesh", **kw)
    return carry_landmarks(mset, reg.vertices, template.faces, vertices, faces), reg


def landmark_document(landmarks: dict[str, tuple[np.ndarray, np.ndarray]], n_vertices: int, **extra) -> dict:
    """The landmarks as a ``load_landmarks`` JSON document (``extra`` fields added first)."""
    out = {}
    for name, (ids, w) in landmarks.items():
        out[name] = int(ids[0]) if len(ids) == 1 else {"vertices": [int(i) for i in ids],
                                                       "weights": [float(x) for x in w]}
    return {**extra, "landmarks": out, "n_vertices": int(n_vertices)}
