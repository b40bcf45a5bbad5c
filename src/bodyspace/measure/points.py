"""The point and axis grammar every measurement method shares: checked on load, evaluated per batch.

A *point* is a landmark name or a list of names (their mean: the mean of a front and a back
landmark is a point inside the body). An *axis* is ``"up"`` (world +Y), a pair of points
``[from, to]`` (so it follows a limb or the torso in any pose), or a *part axis*
``{"part": P, "from": A, "to": B, "fallback": axis}``: the axis of body part P itself, from the
centroid of its vertices bordering part A to the centroid of those bordering part B (the neck from
the torso to the head: it follows the neck, not a line to the head's top, so a tilted head does
not tilt the neck girth's plane). The border centroids are computed per chunk from the vertex part
labels (``border_points``; on any topology the labels come from the landmark skeleton); without
labels, or where a border is empty, the ``fallback`` axis (a pair of points) is used. Evaluated on a batch, a point
is (N, 3) and an axis (N, 3) of unit vectors; ``landmarks`` maps a name to its (N, 3) points.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from bodyspace.errors import MeasurementError
from bodyspace.measure.parts import PARTS

UP = np.array([0.0, 1.0, 0.0])
# A part axis is trusted within this angle of its fallback axis. The hm08 neck (rig labels): 0.5°
# standing, at most 21° over the library's head poses and a head tilted alone by 30°; on a remeshed
# topology with skeleton labels the neck's rims gave 30° standing (its border with the torso is
# only at the back), so there the fallback is used for upright heads.
PART_AXIS_MAX_DEG = 25.0


def fail(where: str, msg: str) -> MeasurementError:
    """The error of a measurement-set field: ``where`` names the file and the field."""
    return MeasurementError(f"{where}: {msg}")


def check_point(where: str, p: Any, landmarks, allow_floor: bool = False) -> None:
    """Raise MeasurementError unless ``p`` is a known landmark name or a list of them (or "floor")."""
    names = [p] if isinstance(p, str) else p
    if not isinstance(names, list) or not names or not all(isinstance(n, str) for n in names):
        raise fail(where, f"got {p!r}, expected a landmark name or a list of names")
    for n in names:
        if allow_floor and n == "floor" and isinstance(p, str):
            continue
        if n not in landmarks:
            raise fail(where, f"unknown landmark {n!r}; known: {', '.join(sorted(landmarks))}")


def check_axis(where: str, a: Any, landmarks, required: bool = True) -> None:
    """Raise MeasurementError unless ``a`` is "up" or a pair of points (or None when optional)."""
    if a is None and not required:
        return
    if a == "up":
        return
    if isinstance(a, dict):
        extra = set(a) - {"part", "from", "to", "fallback"}
        for key in ("part", "from", "to"):
            if a.get(key) not in PARTS:
                raise fail(where + f" field {key!r}", f"got {a.get(key)!r}, expected a body part, one of "
                                                      f"{', '.join(PARTS)}")
        if extra:
            raise fail(where, f"unknown field(s) {', '.join(sorted(extra))} of a part axis; expected part, "
                              "from, to, fallback")
        fallback = a.get("fallback")
        if not (isinstance(fallback, list) and len(fallback) == 2):
            raise fail(where + " field 'fallback'", f"got {fallback!r}, expected a pair of points [from, to] "
                                                    "(the axis where the mesh has no part labels)")
        for p in fallback:
            check_point(where + " field 'fallback'", p, landmarks)
        return
    if not (isinstance(a, list) and len(a) == 2):
        raise fail(where, f"got {a!r}, expected \"up\", a pair of points [from, to] or a part axis "
                          "{\"part\", \"from\", \"to\", \"fallback\"}")
    for p in a:
        check_point(where, p, landmarks)


def point(spec, landmarks: dict) -> np.ndarray:
    """(N, 3) point of a landmark name or a list of names (their mean); "floor" is the distance
    method's and never reaches here."""
    if isinstance(spec, str):
        if spec == "floor":
            raise AssertionError("floor is handled by the distance method")
        return landmarks[spec]
    return np.mean([landmarks[s] for s in spec], axis=0)


def border_key(part: str, other: str) -> tuple:
    """The key of the centroid (N, 3) of ``part``'s vertices bordering ``other`` among a chunk's
    points (a tuple: never a landmark name of a JSON file)."""
    return ("border", part, other)


def part_axes(specs) -> set:
    """The (part, other) borders the part axes among ``specs`` (axis fields) need."""
    out = set()
    for a in specs:
        if isinstance(a, dict):
            out |= {(a["part"], a["from"]), (a["part"], a["to"])}
    return out


def axis(spec, landmarks: dict, n: int) -> np.ndarray:
    """(N, 3) unit axis: "up" (or None), a pair of points, or a part axis (its border centroids
    from ``landmarks``, ``border_key``; the fallback per body where they are missing or coincide)."""
    if spec is None or spec == "up":
        return np.broadcast_to(UP, (n, 3)).copy()
    if isinstance(spec, dict):
        fallback = axis(spec["fallback"], landmarks, n)
        a, b = landmarks.get(border_key(spec["part"], spec["from"])), landmarks.get(border_key(spec["part"], spec["to"]))
        if a is None or b is None:
            return fallback
        d = b - a
        length = np.linalg.norm(d, axis=-1, keepdims=True)
        ok = np.isfinite(length) & (length > 1e-6)
        d = d / np.where(ok, length, 1.0)
        # Rims that are not whole loops (a part cut from the landmark skeleton can meet its
        # neighbour on one side only) put a centroid off the part's middle: an axis that far from
        # the fallback is not the part's, and the fallback is used (see PART_AXIS_MAX_DEG).
        ok &= np.sum(d * fallback, axis=-1, keepdims=True) >= np.cos(np.radians(PART_AXIS_MAX_DEG))
        return np.where(ok, d, fallback)
    a = point(spec[1], landmarks) - point(spec[0], landmarks)
    return a / np.maximum(np.linalg.norm(a, axis=-1, keepdims=True), 1e-12)


def format_point(p) -> str:
    """A point as people read it in a note: ``neck_front+neck_back``."""
    return p if isinstance(p, str) else "+".join(p)


def point_names(p) -> set:
    """The landmark names a point uses."""
    return {p} if isinstance(p, str) else set(p)


def axis_points(a) -> list:
    """The points an axis field uses: none for "up", the pair, or a part axis's fallback pair."""
    if isinstance(a, dict):
        return list(a.get("fallback") or [])
    return list(a) if isinstance(a, list) else []
