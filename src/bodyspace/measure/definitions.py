"""Measurement sets are data: named landmarks plus a method per measurement, one JSON per template.

File layout (``bodyspace/data/measurements/hm08.json`` is the default; docs/measurements.md):

```
{"format": "bodyspace-measurements", "template": "hm08", "n_vertices": 13380,
 "landmarks": {"crotch": 4372,                                          # a vertex id, or
               "knee_joint_l": {"vertices": [1, 2, 3], "weights": [0.2, 0.3, 0.5]}},  # a weighted set
 "conditions": {"upright": {"axes": [[A, B], ...], "max_angle_deg": 12},
                "arms_as_at_rest": {"axes": [...], "relative_to": [C, D], "directed": true,
                                    "min_angle_deg": 129, "max_angle_deg": 149},
                "head_up": {"axes": [[A, B]], "relative_to": [C, D], "max_angle_deg": 20}},
 "measurements": [{"name": ..., "method": ..., ...}, ...]}
```

Landmarks come in two kinds. A *surface* landmark is one vertex id (head top, acromion). A
*weighted* landmark is a convex combination of vertices (``weights`` non-negative, summing to
1; omitted: equal weights): a barycentric point on a face, or a point inside the body such as a
joint centre (``shoulder_joint_l``: the skinning-consistent joint regressor of
``tools/make_hm08.py``, which follows the joint through posing). Either kind may
be given for any name, so a user landmark file can put a plain vertex id where the default set
has a joint centre (a cruder but valid choice; docs/measurements.md).

A *point* in a measurement is a landmark name or a list of names (their mean: the mean of a
front and a back landmark is a point inside the body). An *axis* is ``"up"`` (world +Y) or a
pair of points ``[from, to]`` (so it follows a limb or the torso in any pose), or a joint axis
``{"from", "to", "fallback"}`` between two joint centres given inline as weighted vertices of the
set's topology (the neck girth's: neck joint to head joint). A landmark file for another
topology (``with_landmarks``) drops the joints (the axis is then its fallback pair) until one
standing body of that topology places them there (``with_standing_body``; ``points``).

Methods are registered in ``methods.METHODS`` (one function per method, each with a check of
its fields that runs here); a set naming an unregistered method is refused on load. The
built-in ones:

- ``loop``: ``vertices`` (ordered ring on the mean model, Rupprecht §3.1.2), ``axis``;
  closed length after projecting onto the plane normal to the axis. Template-only.
- ``slice``: plane through ``at`` (a point) with normal ``normal`` (an axis); the contour that
  contains ``pick`` (default ``at``) projected on the plane, else the nearest; girth = its
  convex-hull perimeter. With ``band`` = {"from", "to", "start", "stop", "steps", "mode"} the
  plane origin runs from ``start`` to ``stop`` (fractions) of the segment from→to and the
  girth is the ``mode`` ("max" or "min") over the planes.
  With ``part`` (a body part of ``parts.PARTS`` or a list of them) only the part's edges are
  cut and all their crossings in a plane are the contour (the tape goes round that part only).
- ``top``: height of the highest vertex of ``part`` over the lowest vertex (stature: the top of
  the head, whichever vertex is highest).
- ``distance``: ``from``, ``to`` (a point or ``"floor"``: the lowest vertex's level), ``axis``
  (none: straight; else the extent along the axis).
- ``path``: ``through`` (points); summed straight segments.
- ``volume``, ``surface_area``; ``mass`` (``stature``: the name of a length measurement,
  ``age_years``, ``male`` 0/1 or null for unknown; ``stature_estimate`` {"through", "plus_mean_of",
  "scale"}: the stature a body that does not stand is given, so mass is defined for every closed
  body) and ``bmi`` (``mass``, ``stature``).

Any measurement may say ``"requires": ["upright"]``: on a body whose condition fails its value
is NaN with a note, never silently wrong; and ``"plausible": {"range": [lo, hi], "ratio_to":
{earlier name: [lo, hi]}, "adult_stature": 1.5}``: a value outside is NaN with the reason
(``evaluate``); with ``adult_stature`` the range is an adult's and its low end shrinks in
proportion on a body whose measured stature is shorter (a child's wrist). The body
part of every vertex is the optional ``"vertex_parts"`` (one letter a vertex, ``parts``).

A condition holds when every axis in ``axes`` is within ``max_angle_deg`` of ``relative_to``
(an axis; default ``"up"``, world vertical), as lines (direction does not matter), and at least
``min_angle_deg`` (default 0) from it; with ``"directed": true`` the angle is between directions
(0-180°: an arm hanging down is not an arm raised up).
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import scipy.sparse as sp

from bodyspace.errors import MeasurementError
from bodyspace.measure.methods import METHODS, known_methods, template_vertices
from bodyspace.measure.parts import axis_joints, decode_parts, encode_parts, part_landmarks, parts_from_landmarks
from bodyspace.measure.points import (axis, axis_points, check_axis, check_inline_point, fail, format_point,
                                     point_names)

FORMAT = "bodyspace-measurements"
DEFAULT_PATH = Path(__file__).resolve().parents[1] / "data" / "measurements" / "hm08.json"
MAX_USER_LANDMARKS = 25
# Vertex ids index meshes that fit in memory, and the formats bodyspace reads (PLY, glTF) index
# with 32 bits: an id at or above 2^31 is a typo or garbage, not a vertex.
MAX_VERTEX_ID = 2 ** 31 - 1

@dataclass(frozen=True)
class MeasurementSet:
    """Landmarks and measurement definitions of one template.

    landmarks: name → (vertex ids (k,), weights (k,)).
    measurements: validated definition dicts, in file order.
    conditions: name → {"axes": [[a, b], ...], "max_angle_deg": float}.
    n_vertices: vertex count the set was made for (None: any mesh the ids fit).
    vertex_parts: (V,) int8 body part of each vertex (``parts.PARTS``, -1 none), what a
        measurement's ``part`` restricts its slice to; None: assigned from the landmarks of
        the first measured body that stands (``parts.parts_from_landmarks``; give a standing
        body's labels with ``with_vertex_parts`` to measure posed bodies of another topology).
    parts_unknown: why the parts could not be assigned (``with_standing_body`` was given a body
        that does not stand): the measurements that go round a part are NaN with it.
    """

    landmarks: dict[str, tuple[np.ndarray, np.ndarray]]
    measurements: tuple[dict, ...]
    conditions: dict[str, dict] = field(default_factory=dict)
    n_vertices: int | None = None
    template: str = "hm08"
    source: str = "<memory>"
    vertex_parts: np.ndarray | None = field(default=None, compare=False, repr=False)
    parts_unknown: str | None = field(default=None, compare=False, repr=False)

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(m["name"] for m in self.measurements)

    @property
    def landmark_names(self) -> tuple[str, ...]:
        return tuple(self.landmarks)

    def landmark_matrix(self, n_vertices: int) -> sp.csr_matrix:
        """Sparse (L, V) matrix: ``M @ vertices`` gives the landmark points (L, 3)."""
        rows, cols, vals = [], [], []
        for r, (ids, w) in enumerate(self.landmarks.values()):
            rows += [r] * len(ids)
            cols += list(ids)
            vals += list(w)
        return sp.csr_matrix((vals, (rows, cols)), shape=(len(self.landmarks), n_vertices))

    def max_vertex_id(self) -> int:
        ids = [int(i.max()) for i, _ in self.landmarks.values()]
        ids += [max(template_vertices(m)) for m in self.measurements if template_vertices(m)]
        return max(ids, default=-1)

    def to_dict(self) -> dict:
        """The whole set as a JSON-able document that ``measurement_set_from_dict`` reads back
        into an equal set (how a BodyModel file stores it: data, never code). A one-vertex
        landmark is its id, a weighted one ``{"vertices": [...], "weights": [...]}`` (floats
        round-trip exactly through JSON); measurements and conditions as validated."""
        landmarks = {}
        for name, (ids, w) in self.landmarks.items():
            landmarks[name] = (int(ids[0]) if len(ids) == 1 and float(w[0]) == 1.0 else
                               {"vertices": [int(i) for i in ids], "weights": [float(x) for x in w]})
        out = {"format": FORMAT, "template": self.template, "n_vertices": self.n_vertices,
               "source": self.source, "landmarks": landmarks, "conditions": _plain(self.conditions),
               "measurements": _plain(list(self.measurements))}
        if self.vertex_parts is not None:
            out["vertex_parts"] = encode_parts(self.vertex_parts)
        return out


def _parse_landmark(src: str, name: str, val: Any) -> tuple[np.ndarray, np.ndarray]:
    """A landmark value → (vertex ids (k,), convex weights (k,)); errors name the landmark."""
    where = f"{src}: landmark {name!r}"
    expected = "expected a vertex id or {\"vertices\": [ids], \"weights\": [w]} (non-negative, summing to 1)"
    if isinstance(val, (int, np.integer)) and not isinstance(val, bool):
        ids, w = np.array([_vertex_id(where, val)]), np.array([1.0])
    elif isinstance(val, dict) and "vertices" in val:
        extra = set(val) - {"vertices", "weights"}
        if extra:
            raise fail(where, f"unknown field(s) {sorted(extra)}; {expected}")
        raw_ids, raw_w = val["vertices"], val.get("weights")
        if not isinstance(raw_ids, list) or not all(isinstance(i, int) and not isinstance(i, bool) for i in raw_ids):
            raise fail(where, f"'vertices' is {raw_ids!r}, expected a list of integer vertex ids")
        ids = np.asarray([_vertex_id(where, i) for i in raw_ids], dtype=np.int64).ravel()
        if len(ids) == 0:
            raise fail(where, "'vertices' is empty, expected at least one vertex id")
        if raw_w is None:
            w = np.full(len(ids), 1.0 / len(ids))
        else:
            if not isinstance(raw_w, list) or not all(isinstance(x, (int, float)) and not isinstance(x, bool)
                                                      for x in raw_w):
                raise fail(where, f"'weights' is {raw_w!r}, expected a list of numbers")
            w = np.asarray(raw_w, dtype=float).ravel()
        if len(ids) != len(w):
            raise fail(where, f"{len(ids)} vertices and {len(w)} weights, expected one weight per vertex")
        if not np.isfinite(w).all() or (w < 0).any():
            bad = w[~np.isfinite(w) | (w < 0)][0]
            raise fail(where, f"weight {bad} is negative or not finite; expected convex weights "
                               "(non-negative, summing to 1)")
        if not np.isclose(w.sum(), 1.0, rtol=0, atol=1e-6):
            raise fail(where, f"weights sum to {w.sum():.6g}; expected convex weights (non-negative, "
                               "summing to 1)")
        uniq, count = np.unique(ids, return_counts=True)
        if (count > 1).any():
            dup = int(uniq[count > 1][0])
            raise fail(where, f"vertex {dup} is listed twice, expected each vertex once (add its weights)")
    else:
        raise fail(where, f"got {val!r}, {expected}")
    if (ids < 0).any():
        raise fail(where, f"vertex id {int(ids.min())} is negative: the landmark is off the mesh")
    return ids, w


def _validate_measurement(src: str, i: int, m: Any, landmarks, conditions, seen: set) -> dict:
    """One measurement's definition, checked by its method's ``check`` (``methods.METHODS``)."""
    if not isinstance(m, dict) or not isinstance(m.get("name"), str) or not m["name"]:
        raise fail(f"{src}: measurements[{i}]", f"got {m!r}, expected an object with a 'name'")
    name = m["name"]
    where = f"{src}: measurement {name!r}"
    if name in seen:
        raise fail(where, "defined twice")
    method = METHODS.get(m.get("method")) if isinstance(m.get("method"), str) else None
    if method is None:
        raise fail(where, f"method {m.get('method')!r}, expected one of {known_methods()} "
                          "(the methods registered in bodyspace.measure.methods)")
    requires = m.get("requires", [])
    if not isinstance(requires, list):
        raise fail(where + " field 'requires'", f"got {requires!r}, expected a list of condition names")
    for c in requires:
        if c not in conditions:
            raise fail(where, f"requires unknown condition {c!r}; defined: {', '.join(conditions) or 'none'}")
    if method.check is not None:
        method.check(where, m, landmarks, seen)
    _check_plausible(where, m.get("plausible"), seen)
    out = dict(m)
    out.setdefault("unit", method.unit)
    out.setdefault("requires", [])
    return out


def _check_plausible(where: str, rule: Any, earlier: set) -> None:
    """The optional ``plausible`` field: {"range": [lo, hi], "ratio_to": {earlier name: [lo, hi]}}."""
    if rule is None:
        return
    where += " field 'plausible'"

    def bounds(x, what):
        if (not isinstance(x, list) or len(x) != 2 or not all(isinstance(b, (int, float)) and not isinstance(b, bool)
                                                               for b in x) or not x[0] < x[1]):
            raise fail(where, f"{what} is {x!r}, expected [low, high] with low < high")

    if not isinstance(rule, dict) or set(rule) - {"range", "ratio_to", "adult_stature"}:
        raise fail(where, f"got {rule!r}, expected {{\"range\": [low, high], \"ratio_to\": {{name: [low, high]}}, "
                          "\"adult_stature\": metres}")
    if "range" in rule:
        bounds(rule["range"], "'range'")
    if "adult_stature" in rule:
        a = rule["adult_stature"]
        if "range" not in rule or isinstance(a, bool) or not isinstance(a, (int, float)) or not 0.5 <= a <= 2.6:
            raise fail(where, f"'adult_stature' is {a!r}, expected a stature in metres (0.5-2.6) beside a 'range'")
        if "stature" not in earlier:
            raise fail(where, "'adult_stature' needs a measurement 'stature' defined earlier in the file")
    ratios = rule.get("ratio_to", {})
    if not isinstance(ratios, dict):
        raise fail(where, f"'ratio_to' is {ratios!r}, expected {{measurement name: [low, high]}}")
    for name, b in ratios.items():
        if name not in earlier:
            raise fail(where, f"'ratio_to' names {name!r}, expected a measurement defined earlier in the file")
        bounds(b, f"'ratio_to.{name}'")


def measurement_set_from_dict(d: Any, source: str = "<memory>") -> MeasurementSet:
    """Validate a parsed measurement-set document; errors name the field and measurement."""
    if not isinstance(d, dict):
        raise fail(source, f"top level is {type(d).__name__}, expected an object")
    if d.get("format", FORMAT) != FORMAT:
        raise fail(source, f"format {d.get('format')!r}, expected {FORMAT!r}")
    raw = d.get("landmarks")
    if not isinstance(raw, dict):
        raise fail(source, "'landmarks' is missing or not an object of name → vertex id")
    landmarks = {str(k): _parse_landmark(source, k, v) for k, v in raw.items()}
    conditions = d.get("conditions", {})
    if not isinstance(conditions, dict):
        raise fail(source, "'conditions' is not an object of name → {'axes': ..., 'max_angle_deg': ...}")
    for cname, c in conditions.items():
        where = f"{source}: condition {cname!r}"
        if not isinstance(c, dict) or not isinstance(c.get("axes"), list) or not c["axes"]:
            raise fail(where, "expected {'axes': [[from, to], ...], 'max_angle_deg': x, 'relative_to': axis?}")
        for a in c["axes"]:
            check_axis(where + " axis", a, landmarks)
        check_axis(where + " field 'relative_to'", c.get("relative_to", "up"), landmarks)
        directed = c.get("directed", False)
        if not isinstance(directed, bool):
            raise fail(where + " field 'directed'", f"got {directed!r}, expected true or false")
        top = 180 if directed else 90
        lim = c.get("max_angle_deg", 12)
        if not isinstance(lim, (int, float)) or isinstance(lim, bool) or not 0 < lim <= top:
            raise fail(where + " field 'max_angle_deg'", f"got {lim!r}, expected a number of degrees in (0, {top}]")
        low = c.get("min_angle_deg", 0)
        if not isinstance(low, (int, float)) or isinstance(low, bool) or not 0 <= low < lim:
            raise fail(where + " field 'min_angle_deg'", f"got {low!r}, expected a number of degrees in "
                                                         f"[0, max_angle_deg={lim})")
    ms = d.get("measurements")
    if not isinstance(ms, list):
        raise fail(source, "'measurements' is missing or not a list")
    seen: set = set()
    out = []
    for i, m in enumerate(ms):
        vm = _validate_measurement(source, i, m, landmarks, conditions, seen)
        seen.add(vm["name"])
        out.append(vm)
    n = _n_vertices(source, d.get("n_vertices"))
    parts = None
    if d.get("vertex_parts") is not None:     # older files have none: parts from the landmarks
        parts = decode_parts(d["vertex_parts"], f"{source} field 'vertex_parts'")
        _check_parts_length(f"{source} field 'vertex_parts'", parts, n, landmarks)
    return MeasurementSet(landmarks, tuple(out), dict(conditions), n, str(d.get("template", "")), source,
                          parts)


def _check_parts_length(where: str, parts: np.ndarray, n: int | None, landmarks: dict) -> None:
    """Labels for exactly the set's vertices: ``n`` if declared, else at least every landmark's."""
    top = max((int(i.max()) for i, _ in landmarks.values()), default=-1)
    if (n is not None and len(parts) != n) or len(parts) <= top:
        want = n if n is not None else f"more than {top}"
        raise fail(where, f"{len(parts)} vertex labels, expected one per vertex ({want}); re-make the labels for "
                          "this topology (with_vertex_parts) or drop the field")


def with_vertex_parts(mset: MeasurementSet, vertex_parts: np.ndarray) -> MeasurementSet:
    """``mset`` with the body part of every vertex (V,) (``parts.parts_from_weights`` on a rigged
    template, ``parts.parts_from_landmarks`` on a standing body of any topology)."""
    labels = np.asarray(vertex_parts).astype(np.int8).ravel()
    _check_parts_length("vertex_parts", labels, mset.n_vertices, mset.landmarks)
    return replace(mset, vertex_parts=labels)


def _plain(x: Any) -> Any:
    """``x`` with numpy scalars and arrays as Python numbers and lists (for ``to_dict``)."""
    if isinstance(x, dict):
        return {str(k): _plain(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_plain(v) for v in x]
    if isinstance(x, np.ndarray):
        return _plain(x.tolist())
    if isinstance(x, np.generic):
        return x.item()
    return x


def _vertex_id(where: str, val: Any) -> int:
    """A JSON vertex id as an int that fits the (L, V) matrix's int64 indices."""
    if val > MAX_VERTEX_ID:     # negative ids are refused with the landmark's other checks
        raise fail(where, f"vertex id {val} is out of range, expected an id below the mesh's vertex count "
                          f"(at most {MAX_VERTEX_ID})")
    return int(val)


def _n_vertices(where: str, n: Any) -> int | None:
    """The optional ``n_vertices`` field: None or a positive integer."""
    if n is None:
        return None
    if not isinstance(n, int) or isinstance(n, bool) or n < 1:
        raise fail(where + " field 'n_vertices'", f"got {n!r}, expected a positive integer vertex count "
                                                  "(or no n_vertices field)")
    return n


def _read_json(path: Path) -> Any:
    if path.is_dir():
        raise MeasurementError(f"{path}: is a folder, expected a JSON file")
    if not path.is_file():
        raise MeasurementError(f"{path}: file not found")
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except UnicodeDecodeError as exc:
        raise MeasurementError(f"{path}: not UTF-8 text (byte {exc.start}), expected a JSON file") from None
    except json.JSONDecodeError as exc:
        raise MeasurementError(f"{path}: not valid JSON ({exc})") from None
    except OSError as exc:
        raise MeasurementError(f"{path}: could not read ({exc.strerror or exc})") from None


def load_measurement_set(path: str | os.PathLike | None = None) -> MeasurementSet:
    """Read and validate a measurement set (default: the hm08 set shipped with bodyspace)."""
    path = Path(path) if path is not None else DEFAULT_PATH
    return measurement_set_from_dict(_read_json(path), str(path))


def load_landmarks(path: str | os.PathLike) -> tuple[dict[str, tuple[np.ndarray, np.ndarray]], int | None]:
    """A user's landmark file for another topology: ``{"landmarks": {name: value}, "n_vertices": V?}``.

    A value is a vertex id or a weighted vertex set ``{"vertices": [...], "weights": [...]}``
    (convex weights). At most 25 landmarks (the names of the default set, docs/measurements.md).
    Returns the landmarks and the declared vertex count (None if not given).
    """
    path = Path(path)
    d = _read_json(path)
    raw = d.get("landmarks", d) if isinstance(d, dict) else None
    if not isinstance(raw, dict) or not raw:
        raise MeasurementError(f"{path}: expected {{\"landmarks\": {{name: vertex id or "
                               "{\"vertices\": [...], \"weights\": [...]}, ...}}")
    if len(raw) > MAX_USER_LANDMARKS:
        raise MeasurementError(f"{path}: {len(raw)} landmarks, expected at most {MAX_USER_LANDMARKS}")
    lms = {str(k): _parse_landmark(str(path), k, v) for k, v in raw.items() if k != "n_vertices"}
    n = _n_vertices(str(path), d.get("n_vertices") if isinstance(d, dict) else None)
    for name, (ids, _) in lms.items():
        if n is not None and ids.max() >= n:
            raise fail(f"{path}: landmark {name!r}", f"vertex id {int(ids.max())} is off the mesh: the file's "
                                                     f"n_vertices is {n} (ids 0..{n - 1})")
    return lms, n


def load_landmark_parts(path: str | os.PathLike) -> np.ndarray | None:
    """The body part of every vertex (V,) int8 a landmark file carries (its optional
    ``"vertex_parts"``, one letter a vertex as in a measurement set; ``bodyspace landmarks``
    writes it), or None."""
    path = Path(path)
    d = _read_json(path)
    text = d.get("vertex_parts") if isinstance(d, dict) else None
    if text is None:
        return None
    if not isinstance(text, str):
        raise MeasurementError(f"{path}: field 'vertex_parts' is {type(text).__name__}; expected a string of one "
                               "letter a vertex (as bodyspace landmarks writes), or no such field")
    return decode_parts(text, f"{path} field 'vertex_parts'")


def load_landmark_joints(path: str | os.PathLike) -> dict | None:
    """The joints a landmark file carries for the set's joint axes (its optional ``"joints"``:
    measurement name → axis field → {"from", "to"} inline points; ``bodyspace landmarks`` writes
    the template's, ``synth.foreign.carry_joints``), or None. Checked here, applied by
    ``with_axis_joints``."""
    path = Path(path)
    d = _read_json(path)
    joints = d.get("joints") if isinstance(d, dict) else None
    if joints is None:
        return None
    expected = ("an object of measurement name → {\"normal\" or \"axis\": {\"from\": point, \"to\": point}} "
                "(as bodyspace landmarks writes), or no such field")
    if not isinstance(joints, dict):
        raise MeasurementError(f"{path}: field 'joints' is {type(joints).__name__}; expected {expected}")
    for name, fields in joints.items():
        if not isinstance(fields, dict) or not fields or set(fields) - {"normal", "axis"}:
            raise MeasurementError(f"{path}: field 'joints' entry {name!r} is {fields!r}; expected {expected}")
        for key, ends in fields.items():
            where = f"{path}: field 'joints' {name}.{key}"
            if not isinstance(ends, dict) or set(ends) != {"from", "to"}:
                raise MeasurementError(f"{where} is {ends!r}; expected {{\"from\": point, \"to\": point}}")
            for end in ("from", "to"):
                check_inline_point(f"{where}.{end}", ends[end])
    return joints


def with_axis_joints(mset: MeasurementSet, joints: dict, source: str = "joints") -> MeasurementSet:
    """``mset`` with the joints of its joint axes set from ``joints`` (``load_landmark_joints``):
    each measurement named there whose axis field is a joint axis gets its "from" and "to".
    Names the set does not have (a measurement dropped for a missing landmark) are skipped; a
    vertex id beyond the set's topology is an error naming ``source``."""
    measurements = []
    for m in mset.measurements:
        for key, ends in joints.get(m["name"], {}).items():
            a = m.get(key)
            if not isinstance(a, dict):
                continue
            for end in ("from", "to"):
                top = max(ends[end]["vertices"])
                if mset.n_vertices is not None and top >= mset.n_vertices:
                    raise MeasurementError(f"{source}: joint {m['name']}.{key}.{end} uses vertex {top}, but the "
                                           f"topology has {mset.n_vertices} vertices; expected the joints of this "
                                           "mesh (write the file again with bodyspace landmarks MESH)")
            m = dict(m, **{key: dict(a, **{"from": ends["from"], "to": ends["to"]})})
        measurements.append(m)
    return replace(mset, measurements=tuple(measurements))


def with_landmarks(base: MeasurementSet, landmarks: dict, n_vertices: int | None = None,
                   source: str = "<landmarks>") -> MeasurementSet:
    """The topology-free part of ``base`` re-pointed at another topology's ``landmarks``.

    Loops (vertex rings of the template) are dropped; so is every measurement (and condition)
    that needs a landmark the file does not name, and everything derived from a dropped
    measurement (mass needs stature). Nothing else changes. A name the set does not know is an
    error (a typo would otherwise silently drop measurements).
    """
    unknown = sorted(set(landmarks) - set(base.landmarks))
    if unknown:
        raise MeasurementError(f"{source}: landmark name(s) {unknown} are not used by the measurement set "
                               f"{base.source}; expected names from {sorted(base.landmarks)}")
    conditions = {}
    for cname, c in base.conditions.items():
        axes = c["axes"] + [c.get("relative_to", "up")]
        if all(point_names(p) <= set(landmarks) for a in axes for p in axis_points(a)):
            conditions[cname] = c
    kept, have = [], set()
    for m in base.measurements:
        method = METHODS.get(m["method"])
        if method is None or not method.topology_free or not _uses_only(m, landmarks):
            continue
        if any(r not in conditions for r in m["requires"]):
            continue
        if any(m.get(k) not in have for k in ("stature", "mass") if k in m):
            continue                       # derived from a dropped measurement
        # A joint axis's inline joints are the template's vertices: dropped here, the axis is its
        # fallback until a standing body of this topology places them (``with_standing_body``).
        m = dict(m, **{k: _without_joints(m[k], landmarks) for k in ("normal", "axis") if isinstance(m.get(k), dict)})
        kept.append(m)
        have.add(m["name"])
    if not any(m["method"] not in ("volume", "surface_area") for m in kept):
        raise MeasurementError(f"{source}: the landmarks {sorted(landmarks)} are not enough for any measurement "
                               f"of {base.source} but volume and surface area; {_closest(base, landmarks)}")
    return replace(base, landmarks=dict(landmarks), measurements=tuple(kept), conditions=conditions,
                   n_vertices=n_vertices, source=source, vertex_parts=None)


def _without_joints(a: dict, landmarks) -> dict:
    """A joint axis for another topology: no joints (the template's vertex ids), its fallback, and
    its ``sideways`` pair only if the landmarks have it."""
    out = {"fallback": a["fallback"]}
    side = a.get("sideways")
    if side is not None and all(point_names(p) <= set(landmarks) for p in side):
        out["sideways"] = side
    return out


# The condition that says a body stands: body parts are assigned from the landmarks only on a body
# that does (a seated or bent body's limbs lie nearer to the torso's lines than to their own bones).
STANDING_CONDITION = "upright"


def condition_notes(conditions: dict[str, dict], lm: dict, n: int) -> dict[str, list]:
    """Per condition (``MeasurementSet.conditions``), per body: None if it holds, else the reason
    it fails. lm: point name → (N, 3) of ``n`` bodies (``points.axis`` reads them)."""
    out = {}
    for cname, c in conditions.items():
        lo, hi = float(c.get("min_angle_deg", 0.0)), float(c.get("max_angle_deg", 12.0))
        directed = bool(c.get("directed", False))
        rel = c.get("relative_to", "up")
        ref = axis(rel, lm, n)
        ref_name = "vertical" if rel == "up" else f"axis {format_point(rel[0])}→{format_point(rel[1])}"
        limit = f"at most {hi:.0f}°" if lo == 0 else f"expected {lo:.0f}-{hi:.0f}°"
        notes: list = [None] * n
        for a in c["axes"]:
            # An axis is a line unless the condition is directed (an arm down is not an arm up).
            cos = np.sum(axis(a, lm, n) * ref, axis=-1)
            ang = np.degrees(np.arccos(np.clip(cos if directed else np.abs(cos), -1, 1)))
            for i in np.flatnonzero((ang > hi) | (ang < lo)):
                if notes[i] is None:
                    notes[i] = (f"not {cname}: axis {format_point(a[0])}→{format_point(a[1])} is {ang[i]:.0f}° "
                                f"from {ref_name} ({limit})")
        out[cname] = notes
    return out


def standing_notes(mset: MeasurementSet, lm: dict, n: int) -> list:
    """Per body of ``n`` whose landmark points are ``lm`` (name → (n, 3)): None if it stands by the
    set's ``STANDING_CONDITION`` (or the set has none), else the reason it does not."""
    c = mset.conditions.get(STANDING_CONDITION)
    return [None] * n if c is None else condition_notes({STANDING_CONDITION: c}, lm, n)[STANDING_CONDITION]


def standing_note(mset: MeasurementSet, vertices: np.ndarray) -> str | None:
    """None if the body (V, 3) of the set's topology stands (``standing_notes``), else the reason."""
    points = mset.landmark_matrix(len(vertices)) @ np.asarray(vertices, dtype=float)
    return standing_notes(mset, {name: points[i][None] for i, name in enumerate(mset.landmarks)}, 1)[0]


def parts_on_standing_body(mset: MeasurementSet, vertices: np.ndarray, points: np.ndarray,
                           faces: np.ndarray | None = None) -> tuple[np.ndarray | None, str | None]:
    """Body parts (V,) assigned from the landmarks of the first of the bodies ``vertices``
    (N, V, 3) that stands (``points``: their landmark points (N, L, 3) in the set's order;
    ``parts.parts_from_landmarks``) and None; or None and the note of the measurements that go
    round a part when none stands (a seated or bent body's limbs lie nearer to the torso's lines
    than to their own bones)."""
    notes = standing_notes(mset, {name: points[:, k] for k, name in enumerate(mset.landmarks)}, len(vertices))
    i = next((i for i, note in enumerate(notes) if note is None), None)
    if i is None:
        return None, (f"body parts unknown: the landmark file has none for this topology and they are assigned "
                      f"only on a standing body ({notes[0]}); give a landmark file with them (bodyspace landmarks "
                      "MESH writes one), or measure a standing body of this topology in the same call")
    return parts_from_landmarks(vertices[i], {name: points[i, k] for k, name in enumerate(mset.landmarks)}, faces), None


def with_standing_body(mset: MeasurementSet, vertices: np.ndarray, faces: np.ndarray | None = None) -> MeasurementSet:
    """``mset`` ready to measure posed bodies of its topology, from one standing body (V, 3) of it
    (metres, +Y up; e.g. a model's mean rest body): the body part of every vertex if the set has
    none and a measurement names a part (``parts.parts_from_landmarks``), and the joints of every
    joint axis that has none on this topology (``with_landmarks`` drops the template's;
    ``parts.axis_joints``: rings of the neck's skin where the template has its neck and head
    joints). Both are vertex data, so they follow the skin into every pose: the tape keeps its
    part and the neck girth's plane leans with the neck, not with a head tilted on it.
    Labels and joints the set already has are kept; the set is returned unchanged when it needs
    neither. A body that does not stand (``STANDING_CONDITION``) gets no labels: the set then says
    why (``parts_unknown``), and its part-aware measurements are NaN with that reason."""
    needs_parts = mset.vertex_parts is None and any(m.get("part") for m in mset.measurements)
    needs_joints = any(isinstance(m.get(k), dict) and m[k].get("from") is None
                       for m in mset.measurements for k in ("normal", "axis"))
    if not (needs_parts or needs_joints):
        return mset
    v = np.asarray(vertices, dtype=float)
    if v.ndim != 2 or v.shape[1] != 3 or (mset.n_vertices is not None and len(v) != mset.n_vertices):
        raise MeasurementError(f"{mset.source}: the standing body has shape {v.shape}, expected "
                               f"({mset.n_vertices or 'V'}, 3) vertices of the set's topology")
    points = mset.landmark_matrix(len(v)) @ v
    lm = {name: points[i] for i, name in enumerate(mset.landmarks)}
    labels, unknown = mset.vertex_parts, mset.parts_unknown
    if needs_parts:
        labels, unknown = parts_on_standing_body(mset, v[None], points[None], faces)
    measurements = []
    for m in mset.measurements:
        for k in ("normal", "axis"):
            a = m.get(k)
            if isinstance(a, dict) and a.get("from") is None:
                joints = axis_joints(v, lm, a["fallback"], labels)
                if joints is not None:            # else the fallback (a mesh too coarse for a ring)
                    m = dict(m, **{k: dict(a, **{"from": joints[0], "to": joints[1]})})
        measurements.append(m)
    return replace(mset, measurements=tuple(measurements), vertex_parts=labels, parts_unknown=unknown)


def _closest(base: MeasurementSet, landmarks) -> str:
    """Which names the measurement nearest to being measurable still needs (its points and its
    conditions' axes), for a message."""
    best = None
    for m in base.measurements:
        method = METHODS.get(m["method"])
        if method is None or not method.topology_free or m["method"] in ("volume", "surface_area"):
            continue
        need = _point_fields(m)
        for r in m["requires"]:
            c = base.conditions[r]
            need |= {n for a in c["axes"] + [c.get("relative_to", "up")] for p in axis_points(a)
                     for n in point_names(p)}
        missing = sorted(need - set(landmarks) - {"floor"})
        if missing and (best is None or len(missing) < len(best[1])):
            best = (m["name"], missing)
    if best is None:
        return f"expected names from {sorted(base.landmarks)}"
    return f"e.g. {best[0]!r} also needs {best[1]} (names from {sorted(base.landmarks)})"


def _uses_only(m: dict, landmarks) -> bool:
    return _point_fields(m) - {"floor"} <= set(landmarks)


def _point_fields(m: dict) -> set:
    """The landmark names a measurement's point and axis fields use ("floor" included)."""
    pts = []
    for key in ("at", "pick", "from", "to"):
        if m.get(key) is not None:
            pts.append(m[key])
    for key in ("normal", "axis"):
        pts += axis_points(m.get(key))
    if m.get("band"):
        pts += [m["band"]["from"], m["band"]["to"]] + axis_points(m["band"].get("front"))
    pts += m.get("through", [])
    names = set().union(*(point_names(p) for p in pts)) if pts else set()
    if m.get("method") == "top":
        # The highest point of a part: on a topology labelled from its landmarks, the landmarks
        # of that part's skeleton segments say which vertices it is (the head: neck → head top).
        names |= part_landmarks(m["part"])
    return names


# Public name of ``_point_fields`` (the landmarks a measurement uses, for messages elsewhere).
point_fields = _point_fields
