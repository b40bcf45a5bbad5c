"""Does a measurement set fit a collection of bodies? The check before a model keeps the set.

A landmark file is typed by hand or carried over by a tool; the ids can be off the mesh, on a
vertex no face uses, or on the wrong place of the body (a swapped pair, a head-top id that is a
heel). ``check_set_on_bodies`` runs the set on a few bodies that must measure (the rest-pose
scans of a database) and refuses what cannot be a human measurement, naming the measurement,
what it measured, what was expected and the landmarks it uses. A measurement that is undefined
on some of the bodies (a condition failed, e.g. a tilted head) is reported, not refused: the
set is still right, the body is not upright.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from bodyspace.measure.definitions import (
    MeasurementError,
    MeasurementSet,
    load_landmark_joints,
    load_landmark_parts,
    load_landmarks,
    load_measurement_set,
    point_fields,
    with_axis_joints,
    with_landmarks,
    with_vertex_parts,
)
from bodyspace.measure.evaluate import check_compatible, evaluate

# Plausible medians over adults' rest scans (metres; outside: wrong landmarks, or not metres).
PLAUSIBLE_M = {"stature": (1.0, 2.5), "height": (1.0, 2.5)}
# Any other length or girth of a body: above a millimetre, below a body's size.
LENGTH_RANGE_M = (0.001, 2.6)
# Bodies measured for the check (evenly spread over the ones given).
MAX_CHECKED = 16


@dataclass
class SetCheck:
    """What ``check_set_on_bodies`` found: per measurement the bodies it is defined on and its
    median (SI), and the measurements undefined on some bodies with a reason."""

    n_bodies: int
    defined: dict = field(default_factory=dict)
    median: dict = field(default_factory=dict)
    partly_undefined: dict = field(default_factory=dict)


def landmark_measurement_set(path, n_vertices: int | None = None, base: MeasurementSet | None = None,
                             flag: str = "") -> MeasurementSet:
    """The measurement set a landmark file gives for meshes of ``n_vertices``: ``base`` (default:
    the shipped hm08 set) re-pointed at the file's landmarks (``with_landmarks``: loops of the
    template dropped), made for ``n_vertices`` (or the file's own ``n_vertices``), with the body
    parts and joints the file carries (``bodyspace landmarks`` writes them). A file that
    declares another vertex count is refused; ``flag`` names the option in that message."""
    landmarks, declared = load_landmarks(path)
    where = f"{flag} {path}" if flag else str(path)
    if declared is not None and n_vertices is not None and declared != n_vertices:
        raise MeasurementError(f"{where}: the landmark file is for meshes of {declared} vertices (its n_vertices), "
                               f"but these meshes have {n_vertices}; give the landmark file of this topology")
    base = load_measurement_set() if base is None else base
    mset = with_landmarks(base, landmarks, n_vertices if n_vertices is not None else declared, str(path))
    parts = load_landmark_parts(path)      # the template's body parts, carried by bodyspace landmarks
    if parts is not None:
        mset = with_vertex_parts(mset, parts)
    joints = load_landmark_joints(path)    # and the template's neck joints
    return mset if joints is None else with_axis_joints(mset, joints, where)


def check_set_on_bodies(mset: MeasurementSet, vertices: np.ndarray, faces: np.ndarray,
                        bodies: str = "the bodies") -> SetCheck:
    """Refuse (``MeasurementError``) a set that does not measure ``vertices`` (N, V, 3) metres,
    ``faces`` (F, 3): ids off the mesh or on no face (``check_compatible``), a measurement
    undefined on every body, a stature outside ``PLAUSIBLE_M``, a length outside
    ``LENGTH_RANGE_M``. ``bodies`` names them in messages (e.g. "the rest scans of DB").
    Returns a ``SetCheck``."""
    v = np.asarray(vertices, dtype=float)
    if v.ndim == 2:
        v = v[None]
    if len(v) > MAX_CHECKED:
        v = v[np.linspace(0, len(v) - 1, MAX_CHECKED).round().astype(int)]
    faces = np.asarray(faces, dtype=np.int64)
    check_compatible(mset, v, faces, bodies)
    result = evaluate(mset, v, faces, mesh_name=bodies, check_scale=False)
    out = SetCheck(len(v))
    by_name = {m["name"]: m for m in mset.measurements}
    for name, meas in result.items():
        val = np.atleast_1d(np.asarray(meas.value, dtype=float))
        ok = np.isfinite(val)
        notes = [n for n in (meas.note or []) if n]
        uses = sorted(point_fields(by_name[name]) - {"floor"})
        used = f" (it uses the landmarks {', '.join(uses)})" if uses else ""
        out.defined[name] = int(ok.sum())
        if not ok.any():
            raise MeasurementError(f"{mset.source}: measurement {name!r} is undefined on all {len(v)} of {bodies}"
                                   f" ({notes[0] if notes else 'no value'}){used}; expected it to measure bodies "
                                   "standing in the rest pose: check those landmark ids, or which pose is the rest "
                                   "pose (bodyspace import --rest-pose)")
        med = float(np.median(val[ok]))
        out.median[name] = med
        if not ok.all():
            out.partly_undefined[name] = (int((~ok).sum()), notes[0] if notes else "undefined")
        if meas.unit != "m":
            continue
        lo, hi = PLAUSIBLE_M.get(name, LENGTH_RANGE_M)
        if not lo <= med <= hi:
            raise MeasurementError(f"{mset.source}: measurement {name!r} is {100 * med:.1f} cm on {bodies} "
                                   f"(median of {int(ok.sum())}){used}; expected {100 * lo:g}-{100 * hi:g} cm "
                                   "for an adult in metres: check those landmark ids (or the meshes' units)")
    return out
