"""How close two values of one measurement must be to count as the same: the maximum allowable
errors of ISO 20685-1 (3-D scanning methodologies for internationally compatible anthropometric
databases), per category of measurement.

ISO 20685-1:2018 gives a maximum allowable error per *kind* of measurement (Table 1; the figures
as quoted in "Anthropometry, Apparel Sizing and Design", 2nd ed., 2020, p. 45, and ISO 20685-1's
own abstract): segment lengths 5 mm, body heights 4 mm, large circumferences 9 mm, small
circumferences 4 mm, body breadths 4 mm, body depths 5 mm (head 2 mm, hand 1 mm, foot 2 mm:
bodyspace's sets have no head, hand or foot dimensions). Values without an ISO figure (volume,
area, mass, BMI) are held to 1 %.

Each measurement's category (``iso_category``) follows from its definition by one rule, so a
user's own measurement set gets categories too:

1. not a length (``unit`` not "m"): ``NO_ISO`` (1 %);
2. a vertical measure over the floor (``method`` "top", or a "distance" along the ``axis``
   "up"): ``HEIGHT``;
3. a circumference (``method`` "slice" or "loop"): ``LARGE_CIRCUMFERENCE`` when the part it goes
   round is the torso (the standard's examples: chest, waist, hip), else ``SMALL_CIRCUMFERENCE``
   (neck, arm, wrist, thigh, calf). The part is the definition's ``part`` (the first when it names
   several: the hip girth's torso and thighs, the neck girth's neck and torso), or, for a vertex
   ring (Rupprecht's loops), the part most of its vertices are on (the set's ``vertex_parts``, or
   ``parts.parts_from_landmarks`` on a standing body);
4. a straight "distance" between two points: its direction on a standing body, mostly sideways
   ``BREADTH``, mostly front to back ``DEPTH``, else ``SEGMENT_LENGTH`` (without a body: a
   left-right pair of one landmark name, ``X_l`` to ``X_r``, is a breadth);
5. anything else of unit "m" (a "path" through joint centres, a method bodyspace does not
   know): ``SEGMENT_LENGTH``.

Named exceptions (``ISO_EXCEPTIONS``) override the rule for a measurement name; the shipped hm08
set needs none (its 31 measurements: 5 heights, 7 small and 8 large circumferences, one breadth,
4 segment lengths, 4 without an ISO figure; ``docs/registration.md``).
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np

from bodyspace.measure.definitions import load_measurement_set
from bodyspace.measure.parts import PARTS, parts_from_landmarks

__all__ = ["HEIGHT", "SMALL_CIRCUMFERENCE", "LARGE_CIRCUMFERENCE", "BREADTH", "DEPTH", "SEGMENT_LENGTH",
           "NO_ISO", "ALLOWABLE_ERROR", "ISO_EXCEPTIONS", "iso_category", "iso_categories", "iso_allowable",
           "iso_tolerance"]

HEIGHT = "body height"
SMALL_CIRCUMFERENCE = "small circumference"
LARGE_CIRCUMFERENCE = "large circumference"
BREADTH = "body breadth"
DEPTH = "body depth"
SEGMENT_LENGTH = "segment length"
NO_ISO = "no ISO figure"

# Maximum allowable error per category: (value, relative). Metres for the ISO 20685-1 figures, a
# share of the reference value for NO_ISO.
ALLOWABLE_ERROR = {
    HEIGHT: (0.004, False),
    SMALL_CIRCUMFERENCE: (0.004, False),
    LARGE_CIRCUMFERENCE: (0.009, False),
    BREADTH: (0.004, False),
    DEPTH: (0.005, False),
    SEGMENT_LENGTH: (0.005, False),
    NO_ISO: (0.01, True),
}
# Measurement name → category where the rule of the module docstring would be wrong (none for
# the shipped set).
ISO_EXCEPTIONS: dict[str, str] = {}
# A straight distance is a breadth (depth) when this share of its length runs sideways (front to
# back): cos 30°; between, a segment length.
DIRECTION_SHARE = 0.866


def _part_of_ring(ids, vertex_parts) -> str | None:
    labels = np.asarray(vertex_parts)[np.asarray(ids, dtype=np.int64)]
    labels = labels[labels >= 0]
    if len(labels) == 0:
        return None
    return PARTS[int(np.bincount(labels).argmax())]


def iso_category(definition: dict, *, landmarks: dict | None = None, vertex_parts=None) -> str:
    """The ISO 20685-1 category of one measurement definition (a measurement set's dict), by the
    rule of the module docstring.

    landmarks: name → (3,) the set's landmark points on a standing body (metres, +Y up, +X the
    body's left, +Z front), for a straight distance's direction; vertex_parts: (V,) the set's
    part labels (``parts.PARTS`` indices), for a vertex ring. Without landmarks a distance between
    a left and a right landmark of one name (``X_l``, ``X_r``) is a breadth, any other a segment
    length; without parts a ring is a small circumference.
    """
    name, method = definition.get("name", ""), definition.get("method")
    if name in ISO_EXCEPTIONS:
        return ISO_EXCEPTIONS[name]
    if definition.get("unit", "m") != "m":
        return NO_ISO
    if method == "top" or (method == "distance" and definition.get("axis") == "up"):
        return HEIGHT
    if method in ("slice", "loop"):
        part = definition.get("part")
        if isinstance(part, (list, tuple)):
            part = part[0] if part else None
        if part is None and method == "loop" and vertex_parts is not None and definition.get("vertices"):
            part = _part_of_ring(definition["vertices"], vertex_parts)
        return LARGE_CIRCUMFERENCE if part == "torso" else SMALL_CIRCUMFERENCE
    if method == "distance" and landmarks is None:
        a, b = str(definition.get("from")), str(definition.get("to"))
        if {a[-2:], b[-2:]} == {"_l", "_r"} and a[:-2] == b[:-2]:      # a left-right pair: across the body
            return BREADTH
    if method == "distance" and landmarks is not None:
        a, b = landmarks.get(definition.get("from")), landmarks.get(definition.get("to"))
        if a is not None and b is not None:
            d = np.asarray(b, dtype=float) - np.asarray(a, dtype=float)
            n = float(np.linalg.norm(d))
            if n > 0 and abs(d[0]) >= DIRECTION_SHARE * n:
                return BREADTH
            if n > 0 and abs(d[2]) >= DIRECTION_SHARE * n:
                return DEPTH
    return SEGMENT_LENGTH


def iso_categories(mset, body: np.ndarray | None = None) -> dict[str, str]:
    """name → ISO 20685-1 category of every measurement of ``mset`` (``iso_category``).

    body: a standing body (V, 3) of the set's topology (metres, +Y up; e.g. the template's mean
    body), or an object with such ``vertices`` (a ``Template``), or None. With it, a straight
    distance's direction decides breadth, depth or segment length, and the rings of a set without
    part labels get parts (``parts.parts_from_landmarks``); without it, a distance between a left
    and a right landmark of one name (``X_l``, ``X_r``) is a breadth, other distances segment
    lengths, and rings take the set's own part labels (small circumferences without them).
    """
    if body is not None and hasattr(body, "vertices"):
        body = body.vertices
    landmarks = None
    parts = mset.vertex_parts
    if body is not None:
        body = np.asarray(body, dtype=float)
        points = mset.landmark_matrix(len(body)) @ body
        landmarks = {n: points[i] for i, n in enumerate(mset.landmarks)}
        if parts is None and any(m.get("method") == "loop" for m in mset.measurements):
            parts = parts_from_landmarks(body, landmarks)
    return {m["name"]: iso_category(m, landmarks=landmarks, vertex_parts=parts) for m in mset.measurements}


def iso_allowable(category: str) -> tuple[float, bool]:
    """(maximum allowable error, relative) of a category: metres, or a share when relative."""
    return ALLOWABLE_ERROR[category]


@lru_cache(maxsize=1)
def _shipped_categories() -> dict[str, str]:
    return iso_categories(load_measurement_set())


def iso_tolerance(name: str, measurement, category: str | None = None) -> tuple[float, bool]:
    """(tolerance, relative) for the measurement ``name`` of a ``Measurement`` (its ``unit`` and
    ``method``): an absolute tolerance in metres, or a relative one (``relative`` True).

    category: the measurement's ISO 20685-1 category (``iso_categories`` of its set); None: the
    shipped hm08 set's for its names, else from the method alone (a slice a small circumference).
    """
    if category is None:
        if measurement.unit != "m":
            category = NO_ISO
        else:
            category = _shipped_categories().get(name) or iso_category(
                {"name": name, "method": measurement.method, "unit": measurement.unit})
    return ALLOWABLE_ERROR[category]
