"""The point and axis grammar every measurement method shares: checked on load, evaluated per batch.

A *point* is a landmark name or a list of names (their mean: the mean of a front and a back
landmark is a point inside the body). An *axis* is ``"up"`` (world +Y), a pair of points
``[from, to]`` (so it follows a limb or the torso in any pose), or a *joint axis*
``{"from": J, "to": J, "fallback": [from, to]}`` whose ends J are joint centres given inline as
weighted vertices of the set's own topology (``{"vertices": [...], "weights": [...]}``, e.g. a row of
the template's joint regressor): the neck's axis from the neck joint to the head joint follows the
neck itself, so a head tilted on its neck does not tilt the neck girth's plane. Its points are
computed per chunk (``inline_key``). On another topology (``with_landmarks``) the template's joints
are dropped and the axis is its ``fallback``, a pair of landmark points, until one standing body
of that topology places the joints there (``definitions.with_standing_body``: rings of the neck's
own skin, ``parts.axis_joints``), so the axis follows the neck on any topology. Evaluated on a batch, a point
is (N, 3) and an axis (N, 3) of unit vectors; ``landmarks`` maps a name to its (N, 3) points.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from bodyspace.errors import MeasurementError

UP = np.array([0.0, 1.0, 0.0])


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
    """Raise MeasurementError unless ``a`` is "up", a pair of points or a joint axis (or None when optional)."""
    if a is None and not required:
        return
    if a == "up":
        return
    if isinstance(a, dict):
        extra = set(a) - {"from", "to", "fallback", "sideways"}
        if extra:
            raise fail(where, f"unknown field(s) {', '.join(sorted(extra))} of a joint axis; expected from, to, "
                              "fallback, sideways")
        if a.get("sideways") is not None:
            side = a["sideways"]
            if not (isinstance(side, list) and len(side) == 2):
                raise fail(where + " field 'sideways'", f"got {side!r}, expected a pair of points [right, left]")
            for p in side:
                check_point(where + " field 'sideways'", p, landmarks)
        if (a.get("from") is None) != (a.get("to") is None):
            raise fail(where, "has only one of 'from' and 'to'; expected both joints (or neither: the axis is its "
                              "fallback until a standing body places them, definitions.with_standing_body)")
        for key in ("from", "to"):
            if a.get(key) is not None:
                check_inline_point(where + f" field {key!r}", a[key])
        fallback = a.get("fallback")
        if not (isinstance(fallback, list) and len(fallback) == 2):
            raise fail(where + " field 'fallback'", f"got {fallback!r}, expected a pair of points [from, to] "
                                                    "(the axis on another topology)")
        for p in fallback:
            check_point(where + " field 'fallback'", p, landmarks)
        return
    if not (isinstance(a, list) and len(a) == 2):
        raise fail(where, f"got {a!r}, expected \"up\", a pair of points [from, to] or a joint axis "
                          "{\"from\", \"to\", \"fallback\"}")
    for p in a:
        check_point(where, p, landmarks)


def check_inline_point(where: str, p: Any) -> None:
    """Raise MeasurementError unless ``p`` is ``{"vertices": [ids], "weights": [w]}``: non-negative
    vertex ids and as many non-negative weights summing to 1 (a convex combination)."""
    if not isinstance(p, dict) or set(p) != {"vertices", "weights"}:
        raise fail(where, f"got {p!r}, expected {{\"vertices\": [ids], \"weights\": [weights]}}")
    ids, w = p["vertices"], p["weights"]
    if not (isinstance(ids, list) and ids and all(isinstance(i, int) and i >= 0 for i in ids)):
        raise fail(where + ".vertices", f"got {ids!r}, expected a non-empty list of vertex ids")
    if not (isinstance(w, list) and len(w) == len(ids) and all(isinstance(x, (int, float)) and x >= 0 for x in w)
            and abs(sum(w) - 1.0) < 1e-6):
        raise fail(where + ".weights", f"expected {len(ids)} non-negative weights summing to 1, got {w!r}")


def point(spec, landmarks: dict) -> np.ndarray:
    """(N, 3) point of a landmark name or a list of names (their mean); "floor" is the distance
    method's and never reaches here."""
    if isinstance(spec, str):
        if spec == "floor":
            raise AssertionError("floor is handled by the distance method")
        return landmarks[spec]
    return np.mean([landmarks[s] for s in spec], axis=0)


def _unit(d: np.ndarray) -> np.ndarray:
    return d / np.maximum(np.linalg.norm(d, axis=-1, keepdims=True), 1e-12)


def inline_key(p: dict) -> tuple:
    """The key of an inline point's (N, 3) positions among a chunk's points (a tuple: never a
    landmark name of a JSON file)."""
    return ("inline",) + tuple(p["vertices"])


def inline_points(specs) -> list:
    """The inline points (dicts) the joint axes among ``specs`` (axis fields) use (none for a joint
    axis whose joints are not placed on this topology yet)."""
    return [a[k] for a in specs if isinstance(a, dict) for k in ("from", "to") if a.get(k) is not None]


def axis(spec, landmarks: dict, n: int) -> np.ndarray:
    """(N, 3) unit axis: "up" (or None), a pair of points, or a joint axis (its inline points from
    ``landmarks``, ``inline_key``; the fallback where they are missing or coincide)."""
    if spec is None or spec == "up":
        return np.broadcast_to(UP, (n, 3)).copy()
    if isinstance(spec, dict):
        fallback = axis(spec["fallback"], landmarks, n)
        if spec.get("from") is None or spec.get("to") is None:
            return fallback                       # joints not placed on this topology
        a, b = landmarks.get(inline_key(spec["from"])), landmarks.get(inline_key(spec["to"]))
        if a is None or b is None:
            return fallback
        d = b - a
        if spec.get("sideways") is not None:
            # Only the joints' lean along the body's left-right direction s; the rest of the
            # direction is the fallback's (see ``check_axis``).
            s = axis(spec["sideways"], landmarks, n)
            d = fallback + (np.sum(_unit(d) * s, axis=-1, keepdims=True)
                            - np.sum(fallback * s, axis=-1, keepdims=True)) * s
        length = np.linalg.norm(d, axis=-1, keepdims=True)
        ok = np.isfinite(length) & (length > 1e-6)
        return np.where(ok, d / np.where(ok, length, 1.0), fallback)
    a = point(spec[1], landmarks) - point(spec[0], landmarks)
    return a / np.maximum(np.linalg.norm(a, axis=-1, keepdims=True), 1e-12)


def format_point(p) -> str:
    """A point as people read it in a note: ``neck_front+neck_back``."""
    return p if isinstance(p, str) else "+".join(p)


def point_names(p) -> set:
    """The landmark names a point uses."""
    return {p} if isinstance(p, str) else set(p)


def axis_points(a) -> list:
    """The landmark points an axis field needs on any topology: none for "up", the pair, or a
    joint axis's fallback (what it is on a topology without its joints; its ``sideways`` pair is
    only used with the joints, and ``with_landmarks`` drops it when the landmarks lack it)."""
    if isinstance(a, dict):
        return list(a.get("fallback") or [])
    return list(a) if isinstance(a, list) else []
