"""The body of a scanner's mesh that carries its floor, a turntable or a pole, for rigging.

Photogrammetry and booth scans come with the ground (a separate disc, or a sheet welded to the
soles), a turntable or a pole. Rigged as they are, the floor makes the signed volume meaningless
(refused as "wound inwards"), the skeleton embedding is fitted into the floor as well as the
body, and bone heat weights the floor. ``scan_body`` finds the body:

- with a landmark file (``bodyspace landmarks`` for this mesh's vertex ids) the landmarks say
  which pieces and faces are the body (``measure.conventions.body_faces``, as ``measure
  --landmarks`` does);
- without one, the floors the scan stands on are found in points sampled from its faces
  (``mesh.floor.find_floor``: a flat sheet the rest stands on, a turntable's top after the ground)
  and their faces cut, then the body is the largest piece left by area; other pieces are left out
  when they are smaller than ``PROP_MAX_SHARE`` of it and lie away from it (a pole, a stand, a
  floor's rim: their median vertex more than ``PROP_MIN_GAP_M`` from the body's surface), while
  pieces on or in the body (eyes, teeth, hair cards) stay. Two bodies of like size stay together
  and are refused by the embedding (``check_riggable``), as before.

A mesh that is all body gives None: it is rigged as given.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from bodyspace.measure.conventions import (AXIS_VECTORS, MESH_UNITS, body_faces, landmark_points, plausible_units,
                                           signed_volume, up_vector)
from bodyspace.measure.definitions import load_measurement_set
from bodyspace.measure.landmark_check import landmark_measurement_set
from bodyspace.mesh.floor import FLOOR_CUT_SIGMAS, FLOOR_ROUNDS, mesh_floor, sheet_width
from bodyspace.mesh.geometry import face_areas
from bodyspace.mesh.topology import vertex_components

__all__ = ["ScanBody", "scan_body", "PROP_MAX_SHARE", "PROP_MIN_GAP_M"]

# A piece beside the body is a prop (left out) when its area is under this share of the body's
# (a second person of like size is not: the embedding refuses two bodies) ...
PROP_MAX_SHARE = 0.5
# ... and its median vertex lies farther than this from the body's vertices (metres; without a
# unit, this share of the body's height times 1.75 m): eyes, teeth and hair cards sit on or in the
# body, a pole or a stand beside it.
PROP_MIN_GAP_M = 0.03

@dataclass(frozen=True)
class ScanBody:
    """The body of a mesh (V, 3), (F, 3) that carried more than a body.

    vertex_ids: (V',) the mesh's vertex ids the body uses, ascending (the body's vertex i is the
        mesh's ``vertex_ids[i]``); faces: (F', 3) the body's faces, a subset of the mesh's in their
        order, renumbered into ``vertex_ids``; notes: one sentence per thing left out.
    """

    vertex_ids: np.ndarray
    faces: np.ndarray
    notes: tuple[str, ...]


def scan_body(vertices: np.ndarray, faces: np.ndarray, *, up: str | None = None, units: str | None = None,
              landmarks=None) -> ScanBody | None:
    """The body of a scanner's mesh (module docstring), or None when the mesh is all body.

    vertices (V, 3) mesh units, faces (F, 3); up, units: the mesh's (``--up``, ``--units``), None
    when unknown (found from the landmarks, or from the mesh's size; no floor is looked for when no
    unit makes it a body's size); landmarks: a landmark file (``bodyspace landmarks``) for this
    mesh's vertex ids, or None.
    """
    v = np.asarray(vertices, dtype=float)
    f = np.asarray(faces, dtype=np.int64)
    if (v.ndim != 2 or v.shape[-1] != 3 or f.ndim != 2 or f.shape[-1] != 3 or len(f) < 4 or not np.isfinite(v).all()
            or f.min() < 0 or f.max() >= len(v)):
        return None             # not a mesh: refused by the rigging's own checks, which name what was found
    if landmarks is not None:
        keep, notes = _landmarked_body(v, f, landmarks, units)
    else:
        keep, notes = _found_body(v, f, up, units)
    if keep is None or keep.all() or not keep.any():
        return None
    ids = np.unique(f[keep])
    new = np.full(len(v), -1, dtype=np.int64)
    new[ids] = np.arange(len(ids))
    return ScanBody(ids, new[f[keep]], tuple(notes))


def _landmarked_body(v: np.ndarray, f: np.ndarray, landmarks, units: str | None):
    """(F,) bool faces of the body the landmark file's points say, and the notes."""
    mset = landmark_measurement_set(landmarks, base=load_measurement_set(), flag="--weights")
    got = body_faces(v, f, mset, units)
    if got.kept is None:
        return None, []
    keep = got.kept
    notes = list(got.notes)
    if got.welded:      # measure's last note speaks of the volume; for a rig: the soles
        u = up_vector(landmark_points(mset, v))
        keep, kept = _restore_soles(v, f, keep, u)
        notes = notes[:-1] + [_welded_note(kept)]
    return keep, notes


def _restore_soles(v: np.ndarray, f: np.ndarray, keep: np.ndarray, u: np.ndarray | None) -> tuple[np.ndarray, int]:
    """``keep`` (F,) with the soles given back: faces cut with a floor welded to the body that do
    not face up (normal more than 60 degrees from ``u``, the body's up (3,)) and join the body
    through faces like them. The floor's sheet faces up, the body's soles face down or sideways (a
    mesh that has them: a body welded onto a ground plane); the underside and rim of a thick floor
    join the body only through the floor's top, which faces up. Returns (keep, faces given back)."""
    if u is None:
        return keep, 0
    n = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    if signed_volume(v, f[keep])[0] < 0:        # wound inwards (refused later, or --flip-winding): normals in
        n = -n
    length = np.linalg.norm(n, axis=1)
    up_facing = (n @ u) > 0.5 * np.maximum(length, 1e-300)
    candidates = ~keep & ~up_facing
    if not candidates.any():
        return keep, 0
    both = keep | candidates
    _, labels = vertex_components(f[both], len(v))
    piece = labels[f[:, 0]]
    body_pieces = np.unique(piece[keep])
    back = candidates & np.isin(piece, body_pieces)
    return keep | back, int(back.sum())


def _welded_note(kept: int) -> str:
    if kept:
        return (f"the floor was joined to the body: cut off under the feet ({kept} faces on it that do not face up, "
                "the soles, kept with the body)")
    return "the floor was joined to the body: cut off under the feet, whose soles are open in the rigged mesh"



def _found_body(v: np.ndarray, f: np.ndarray, up: str | None, units: str | None):
    """(F,) bool faces of the body found without landmarks (module docstring), and the notes."""
    if len(f) == 0:
        return None, []
    area = face_areas(v, f)
    extent = float(np.ptp(v, axis=0).max())
    if units is not None:
        scale = MESH_UNITS[units]
    else:
        # The size (sqrt of the area) first; a floor or a turntable can double the area, so then
        # the extent alone (the body's height or the floor's width: both human-sized).
        fits = plausible_units(extent, float(np.sqrt(area.sum()))) or plausible_units(extent)
        scale = MESH_UNITS[fits[0]] if fits else None
    unit = "m" if scale is not None else "mesh units"
    s = 1.0 if scale is None else scale
    u = np.array(AXIS_VECTORS[up], dtype=float) if up is not None else None
    keep = np.ones(len(f), dtype=bool)
    notes = []
    welded, soles = False, 0
    if scale is not None:
        # Each round: a floor is found; the pieces wholly on it or below it (a separate disc, a
        # turntable with its side) go whole, so a body standing on a separate floor keeps its
        # soles; when none does, the floor is welded to the body and its faces are cut.
        for _ in range(2 * FLOOR_ROUNDS):
            found = mesh_floor(v, f[keep], scale, u)
            if found is None:
                break
            normal, offset, noise = found
            band = v @ normal * scale - offset < FLOOR_CUT_SIGMAS * noise          # (V,) on it or below
            n, labels = vertex_components(f[keep], len(v))
            piece = labels[f[:, 0]]
            above = np.bincount(piece[keep], weights=(~band[f[keep]]).any(axis=1), minlength=n)
            cut = keep & (above[piece] == 0)                    # pieces wholly on the floor or below it
            whole = cut.any()
            if not whole:
                cut = keep & band[f].all(axis=1)
            if not cut.any():
                break
            keep &= ~cut
            if not whole:          # welded to the body: its soles (faces not facing up) given back
                keep, kept = _restore_soles(v, f, keep, normal)
                cut &= ~keep
                on_body = np.zeros(len(v), dtype=bool)
                on_body[f[keep]] = True
                if on_body[f[cut]].any():
                    welded, soles = True, soles + kept
            across = sheet_width(v[np.unique(f[cut])] * scale, normal)
            what = "the floor" if not notes else "a platform on it (a turntable's top with its side)"
            notes.append(f"left out {what} {across:.2f} m across under the feet"
                         f"{' (a piece of its own)' if whole else ''}: {int(cut.sum())} faces, "
                         f"{area[cut].sum() * s * s:.3g} m² of surface")
            if u is None:
                u = normal            # a second floor (a turntable's top) is parallel to the first
            if not keep.any():
                break
    if not keep.any():
        return None, []
    # The pieces left: the body is the largest by area; props beside it are left out.
    n, labels = vertex_components(f[keep], len(v))
    piece = labels[f[:, 0]]
    piece_area = np.bincount(piece[keep], weights=area[keep], minlength=n)
    body = int(np.argmax(piece_area))
    body_v = np.unique(f[keep & (piece == body)])
    tree = cKDTree(v[body_v])
    gap = PROP_MIN_GAP_M / scale if scale is not None else PROP_MIN_GAP_M / 1.75 * extent
    # Each other piece's median distance to the body, all pieces at once (a scan may hold
    # thousands of specks).
    small = (piece_area > 0) & (piece_area < PROP_MAX_SHARE * piece_area[body])
    small[body] = False
    props = []
    if small.any():
        pv = np.unique(f[keep & small[piece]])
        lab, d = labels[pv], tree.query(v[pv])[0]
        order = np.lexsort((d, lab))
        lab, d = lab[order], d[order]
        groups, start, count = np.unique(lab, return_index=True, return_counts=True)
        median = 0.5 * (d[start + (count - 1) // 2] + d[start + count // 2])
        props = groups[median > gap].tolist()
    if props:
        out = keep & np.isin(piece, props)
        keep &= ~out
        w = float(np.ptp(v[np.unique(f[out])], axis=0).max()) * s
        k = len(props)
        notes.append(f"left out {k} piece{'s' if k > 1 else ''} beside the body (a floor, a turntable, a stand?): "
                     f"{int(out.sum())} faces, {area[out].sum() * s * s:.3g} {unit}² of surface, "
                     f"{w:.2f} {unit} across")
    if welded:
        notes.append(_welded_note(soles))
    return keep, notes
