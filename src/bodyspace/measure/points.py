"""The point and axis grammar every measurement method shares: checked on load, evaluated per batch.

A *point* is a landmark name or a list of names (their mean: the mean of a front and a back
landmark is a point inside the body). An *axis* is ``"up"`` (world +Y) or a pair of points
``[from, to]`` (so it follows a limb or the torso in any pose). Evaluated on a batch, a point
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
    """Raise MeasurementError unless ``a`` is "up" or a pair of points (or None when optional)."""
    if a is None and not required:
        return
    if a == "up":
        return
    if not (isinstance(a, list) and len(a) == 2):
        raise fail(where, f"got {a!r}, expected \"up\" or a pair of points [from, to]")
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


def axis(spec, landmarks: dict, n: int) -> np.ndarray:
    """(N, 3) unit axis: "up" (or None) or a pair of points."""
    if spec is None or spec == "up":
        return np.broadcast_to(UP, (n, 3)).copy()
    a = point(spec[1], landmarks) - point(spec[0], landmarks)
    return a / np.maximum(np.linalg.norm(a, axis=-1, keepdims=True), 1e-12)


def format_point(p) -> str:
    """A point as people read it in a note: ``neck_front+neck_back``."""
    return p if isinstance(p, str) else "+".join(p)


def point_names(p) -> set:
    """The landmark names a point uses."""
    return {p} if isinstance(p, str) else set(p)
