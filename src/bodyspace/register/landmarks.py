"""Landmarks for a mesh of any topology: register the template to it, carry the landmarks across.

``bodyspace measure --landmarks`` needs a landmark file for a mesh that is not of the template's
topology. ``mesh_landmarks`` makes one: the template is registered to the mesh as to a scan
(``pipeline.register_scan``: the mesh's vertices and points sampled on its faces), and each
landmark of the measurement set (a weighted set of template vertices) is carried onto the
mesh by ``synth.foreign.carry_landmarks``: every template vertex it uses replaced by its closest
point of the mesh's surface (three vertices, barycentric weights). The result is a
``load_landmarks`` document for the mesh's own vertex ids. The joints of the set's joint axes
(the neck girth's neck and head joints) are carried the same way (``mesh_joints``), so the neck
girth's plane leans with the neck in every pose as on the template.

The template's body-part groups and skin weights are carried the other way
(``carry_vertex_data``): each vertex of the mesh finds its closest point on the registered
template (a face and barycentric weights); its body part is that of the face's corner nearest
it (parts are labels, not mixed), its skin weights the barycentric mix of the corners' weights,
cut to the ``MAX_INFLUENCES`` largest and renormalised. ``landmark_document`` stores them beside
the landmarks (``vertex_parts``: one letter a vertex as in a measurement set; ``skin_weights``:
bone names and (V2, 4) bone ids and weights), so ``measure --landmarks`` and ``build
--landmarks`` measure girths round the template's own parts, and ``rig MESH --weights FILE``
skins the mesh with MakeHuman's weights instead of bone heat (``rig.carried_weights`` reads them).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from bodyspace.data.template import Template, load_template
from bodyspace.measure.definitions import MeasurementSet, load_measurement_set
from bodyspace.measure.parts import encode_parts
from bodyspace.mesh.geometry import vertex_normals
from bodyspace.register.pipeline import Registration, register_scan
from bodyspace.synth.foreign import carry_joints, carry_landmarks, closest_points

__all__ = ["mesh_landmarks", "mesh_joints", "landmark_document", "carry_vertex_data", "CarriedData", "MAX_INFLUENCES"]

# Bones kept per vertex of carried skin weights (glTF skins take 4 per vertex).
MAX_INFLUENCES = 4


@dataclass(frozen=True)
class CarriedData:
    """The template's per-vertex data on a mesh of another topology.

    vertex_parts: (V2,) int8 body part (``measure.parts.PARTS``; -1 none); bones: the rig's bone
    names; bone_ids: (V2, MAX_INFLUENCES) int, weights: (V2, MAX_INFLUENCES) float, rows summing
    to 1 (unused slots: bone 0, weight 0); rig: the rig's name; distance: (V2,) from each vertex
    to the registered template, in the mesh's units.
    """

    vertex_parts: np.ndarray | None
    bones: tuple
    bone_ids: np.ndarray
    weights: np.ndarray
    rig: str
    distance: np.ndarray


def carry_vertex_data(registered: np.ndarray, template: Template, vertices: np.ndarray, faces: np.ndarray,
                      mset: MeasurementSet | None = None, rig: str = "default") -> CarriedData:
    """The template's body parts (``mset.vertex_parts``) and ``rig``'s skin weights on a mesh.

    registered: (V, 3) the template registered to the mesh, in the mesh's frame; vertices
    (V2, 3), faces (F2, 3): the mesh. Module docstring.
    """
    mset = mset if mset is not None else load_measurement_set()
    vertices = np.asarray(vertices, dtype=float)
    corr, dist = closest_points(vertices, registered, template.faces,
                                vertex_normals(vertices, np.asarray(faces, dtype=np.int64)))
    corners = template.faces[corr.face]                                     # (V2, 3)
    parts = None
    if mset.vertex_parts is not None and len(mset.vertex_parts) == template.n_vertices:
        nearest = corners[np.arange(len(corners)), np.argmax(corr.barycentric, axis=1)]
        parts = np.asarray(mset.vertex_parts)[nearest].astype(np.int8)
    r = template.rigs[rig]
    mixed = (corr.matrix(template.faces, template.n_vertices) @ r.weights).toarray()    # (V2, B)
    k = min(MAX_INFLUENCES, mixed.shape[1])
    ids = np.argsort(-mixed, axis=1)[:, :k]
    w = np.take_along_axis(mixed, ids, axis=1)
    w = np.where(w > 0, w, 0.0)
    total = w.sum(axis=1, keepdims=True)
    w = np.where(total > 0, w / np.maximum(total, 1e-300), 0.0)
    ids = np.where(w > 0, ids, 0)
    return CarriedData(parts, tuple(r.bone_names), ids.astype(np.int64), w, r.name, dist)


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
                        name="the mesh", standing=False, **kw)
    return carry_landmarks(mset, reg.vertices, template.faces, vertices, faces), reg


def mesh_joints(registration: Registration, template: Template, vertices: np.ndarray, faces: np.ndarray,
                mset: MeasurementSet | None = None) -> dict:
    """The set's joint-axis joints (the neck girth's) carried from the registered template to the
    mesh (V2, 3), (F2, 3) (``synth.foreign.carry_joints``), for ``landmark_document``."""
    mset = mset if mset is not None else load_measurement_set()
    return carry_joints(mset, registration.vertices, template.faces, np.asarray(vertices, dtype=float),
                        np.asarray(faces, dtype=np.int64))


def landmark_document(landmarks: dict[str, tuple[np.ndarray, np.ndarray]], n_vertices: int,
                      carried: CarriedData | None = None, joints: dict | None = None, **extra) -> dict:
    """The landmarks as a ``load_landmarks`` JSON document (``extra`` fields added first), with
    the carried body parts and skin weights, and the joints of the set's joint axes
    (``synth.foreign.carry_joints``), when given (module docstring)."""
    out = {}
    for name, (ids, w) in landmarks.items():
        out[name] = int(ids[0]) if len(ids) == 1 else {"vertices": [int(i) for i in ids],
                                                       "weights": [float(x) for x in w]}
    doc = {**extra, "landmarks": out, "n_vertices": int(n_vertices)}
    if joints:
        doc["joints"] = joints
    if carried is not None:
        if carried.vertex_parts is not None:
            doc["vertex_parts"] = encode_parts(carried.vertex_parts)
        doc["skin_weights"] = {"rig": carried.rig, "bones": list(carried.bones),
                               "bone_ids": carried.bone_ids.tolist(),
                               "weights": np.round(carried.weights, 5).tolist()}
    return doc
