"""Evaluate a measurement set on bodies (V, 3) or batches (N, V, 3).

Everything but the slices is one vectorized expression over the batch (landmarks are a sparse
(L, V) product, loops/distances/paths are sums of segment lengths, volume and area are the
mesh/geometry sums). A girth round a body part (every girth of the default set) is one compiled
pass a body (``slicing.part_girths``: crossings, hulls and the band's choice); the other slices
are batched numpy (``slicing.band_contours`` cuts all bodies and all planes of a band at once;
``slicing.hull_perimeters`` takes all the hulls at once, Qhull only for degenerate contours or
drawn polylines). Bodies are processed in chunks to bound the memory.

Values are SI inside (metres, kilograms, m³); ``Measurement.display`` converts lengths to cm
for people (the CLI and JSON).
"""

from __future__ import annotations

import multiprocessing
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from bodyspace.errors import MeshError
from bodyspace.measure.conventions import check_body_scale, check_winding
from bodyspace.measure.definitions import MeasurementError, MeasurementSet, condition_notes, parts_on_standing_body
from bodyspace.measure.methods import METHODS, Chunk, Topology, known_methods, template_vertices
from bodyspace.measure.points import inline_key, inline_points
from bodyspace.mesh.geometry import boundary_loops, check_mesh

CHUNK = 64
# A landmark vertex that no face uses is taken from its position when it lies in a hole of the
# mesh (a scan's holes keep their vertices: a registered mesh with its holes cut out): inside a
# boundary loop's sphere (HOLE_REACH x the loop's radius) whose radius is at most HOLE_MAX_SIZE of
# the body's extent, on a mesh whose faces leave at most HOLE_MAX_UNUSED of its vertices. Else
# (a face list cut short, a landmark file of another mesh) it is refused.
HOLE_REACH = 1.25
HOLE_MAX_SIZE = 0.08
HOLE_MAX_UNUSED = 0.1
_DISPLAY = {"m": ("cm", 100.0)}


@dataclass
class Measurement:
    """One measurement of one body or a batch.

    value: float, or (N,) for a batch; SI ``unit`` (NaN where undefined, see ``note``).
    polyline: the measured line for drawing, (K, 3) (closed loops repeat the first point),
        a list of them for a batch, or None.
    note: why a value is NaN (e.g. "not upright: ..."), per body for a batch.
    """

    name: str
    value: float | np.ndarray
    unit: str
    method: str
    iso: str = ""
    polyline: object = None
    note: object = None

    def display(self) -> tuple[object, str]:
        """(value, unit) for people: lengths in cm, the rest as is."""
        unit, scale = _DISPLAY.get(self.unit, (self.unit, 1.0))
        return self.value * scale, unit


_TOPOLOGY_CACHE: dict = {}


def _topology(faces: np.ndarray) -> Topology:
    key = (faces.shape, hash(faces.tobytes()))
    g = _TOPOLOGY_CACHE.get(key)
    if g is None:
        g = _TOPOLOGY_CACHE[key] = Topology(faces)
        if len(_TOPOLOGY_CACHE) > 8:
            _TOPOLOGY_CACHE.pop(next(iter(_TOPOLOGY_CACHE)))
    return g


def check_compatible(mset: MeasurementSet, vertices: np.ndarray, faces: np.ndarray,
                     mesh_name: str = "the measured mesh") -> dict[str, str]:
    """Raise MeasurementError unless the mesh (vertices (..., V, 3), faces (F, 3)) fits the set:
    its vertex count, every landmark and ring vertex in range and on a face or in a hole.

    A landmark vertex that no face uses but that lies in a hole of the mesh (``holed_landmarks``)
    is measured from its position: returned as {landmark name: note}. Any other needed vertex
    that no face uses is blamed on the mesh (``mesh_name``): that is what a face list cut short
    looks like, where the set itself fits the vertex count.
    """
    nv = vertices.shape[-2]
    if mset.n_vertices is not None and nv != mset.n_vertices:
        raise MeasurementError(f"{mesh_name}: {nv} vertices, but the measurement set {mset.source} is made for "
                               f"meshes of {mset.n_vertices} vertices; for another topology give its landmarks "
                               "(load_landmarks and with_landmarks, docs/measurements.md)")
    used = np.zeros(nv, dtype=bool)
    used[faces.ravel()] = True
    orphans = {}
    for name, (ids, _) in mset.landmarks.items():
        if ids.max() >= nv:
            raise MeasurementError(f"{mset.source}: landmark {name!r} is vertex {int(ids.max())}, which is off the "
                                   f"mesh: {mesh_name} has {nv} vertices (ids 0..{nv - 1})")
        if not used[ids].all():
            orphans[name] = ids[~used[ids]]
    holed = holed_landmarks(np.asarray(vertices).reshape(-1, nv, 3)[0], faces, used, orphans) if orphans else {}
    for name, bad in orphans.items():
        if name not in holed:
            loops = len(_hole_loops(faces))
            raise MeasurementError(f"{mesh_name}: its faces use only {int(used.sum())} of its {nv} vertices, and "
                                   f"vertex {int(bad[0])} (landmark {name!r} of {mset.source}) is on none of them"
                                   f"{f' nor in one of its {loops} hole(s)' if loops else ''}; expected every landmark "
                                   "vertex on a face or inside a small hole (is the file truncated or damaged, or "
                                   "the landmark file made for another mesh?)")
    for m in mset.measurements:
        ring = template_vertices(m)
        if ring and max(ring) >= nv:
            raise MeasurementError(f"{mset.source}: measurement {m['name']!r} loops through vertex "
                                   f"{max(ring)}, but {mesh_name} has {nv} vertices")
    return holed


def _hole_loops(faces: np.ndarray) -> list:
    """The boundary loops of the mesh, or none when its boundary is not a set of loops (a face
    list cut short leaves vertices that start two boundary edges: no hole to speak of)."""
    try:
        return boundary_loops(faces)
    except MeshError:
        return []


def holed_landmarks(vertices: np.ndarray, faces: np.ndarray, used: np.ndarray,
                    orphans: dict[str, np.ndarray]) -> dict[str, str]:
    """{landmark name: note} for the landmarks whose unused vertices all lie in a hole.

    vertices (V, 3), faces (F, 3), used (V,) bool (vertex on a face), orphans {name: (K,) ids of
    its vertices on no face}. A hole is a boundary loop of radius at most HOLE_MAX_SIZE of the
    body's extent; a vertex lies in it within HOLE_REACH x that radius of its centre.
    """
    if (~used).mean() > HOLE_MAX_UNUSED:
        return {}
    extent = float(np.ptp(vertices[used], axis=0).max())
    holes = []
    for loop in _hole_loops(faces):
        centre = vertices[loop].mean(axis=0)
        radius = float(np.linalg.norm(vertices[loop] - centre, axis=1).max())
        if radius <= HOLE_MAX_SIZE * extent:
            holes.append((centre, radius))
    out = {}
    for name, ids in orphans.items():
        inside = [min((float(np.linalg.norm(vertices[i] - c) / r) for c, r in holes), default=np.inf)
                  for i in ids]
        if holes and max(inside) <= HOLE_REACH:
            out[name] = (f"landmark {name!r} lies in a hole of the mesh (vertex {int(ids[0])} is on no face): "
                         "its position in the file is used, and a tape across the hole spans it straight")
    return out


def _evaluate_chunk(mset: MeasurementSet, v: np.ndarray, topology: Topology, L, keep_polylines: bool,
                    age_years, male, parts=None, parts_unknown: str | None = None) -> dict:
    """Measure one chunk (N, V, 3): name → (values (N,), polylines or None, notes [N]).
    parts_unknown: why the body parts could not be labelled (no standing body): the measurements
    that go round a part are then NaN with it."""
    n = len(v)
    P = _landmarks(L, v)
    chunk = Chunk(v, {name: P[:, i] for i, name in enumerate(mset.landmarks)}, topology, keep_polylines,
                  age_years, male, parts)
    # The inline joint centres of joint axes (the neck joint and the head joint of the neck girth).
    for p in inline_points([m.get(k) for m in mset.measurements for k in ("normal", "axis")]):
        chunk.landmarks[inline_key(p)] = np.einsum("k,nki->ni", np.asarray(p["weights"], float), v[:, p["vertices"]])
    cond = condition_notes(mset.conditions, chunk.landmarks, n)
    res: dict = {}
    for m in mset.measurements:
        method = METHODS.get(m["method"])
        if method is None:   # a set built in memory, or a method unregistered since loading
            raise MeasurementError(f"{mset.source}: measurement {m['name']!r}: method {m['method']!r} is not "
                                   f"registered; known: {known_methods()}")
        val, poly, method_notes = method.compute(m, chunk)
        val = np.asarray(val, dtype=float).copy()
        notes: list = [None] * n
        if parts_unknown is not None and m.get("part"):
            val[:] = np.nan
            notes = [parts_unknown] * n
        for r in m["requires"]:
            for i, why in enumerate(cond[r]):
                if why is not None:
                    val[i] = np.nan
                    notes[i] = notes[i] or why
        _implausible(m, val, notes, chunk.values)
        for i in np.flatnonzero(~np.isfinite(val)):
            # Every undefined value says why (the method's reason, else the geometry's).
            why = method_notes[i] if method_notes is not None else None
            notes[i] = notes[i] or why or (f"the {m['method']} method gave no finite value on this body "
                                           "(degenerate geometry at the measured place)")
        chunk.values[m["name"]] = val
        res[m["name"]] = (val, poly, notes)
    return res


def _implausible(m: dict, val: np.ndarray, notes: list, earlier: dict) -> None:
    """Set to NaN (with the reason) the values outside the definition's ``plausible`` bounds: the
    ``range`` [lo, hi] a human's value lies in (SI; with ``adult_stature`` the low end shrinks in
    proportion on a body shorter than that), and the ``ratio_to`` bounds against
    measurements made earlier ({name: [lo, hi]}: chest, waist and hip keep an order that holds
    for people). A tape that caught an arm or a chin, or a plane that missed the body, gives
    values these bounds catch; nonsense is never printed as a number (issue 12 §3)."""
    rule = m.get("plausible")
    if not rule:
        return
    unit, scale = _DISPLAY.get(m["unit"], (m["unit"], 1.0))
    label = m["name"].replace("_", " ")
    if "range" in rule:
        lo, hi = rule["range"]
        lo = np.full(len(val), float(lo))
        if "adult_stature" in rule and earlier.get("stature") is not None:
            # A child's girths are an adult's scaled down: the low end follows the measured
            # stature below an adult's (a 1 m child's wrist of 9 cm is no tape error).
            with np.errstate(invalid="ignore"):
                shrink = np.clip(earlier["stature"] / rule["adult_stature"], 0.3, 1.0)
            lo = np.where(np.isfinite(shrink), lo * shrink, lo)
        for i in np.flatnonzero((val < lo) | (val > hi)):
            notes[i] = notes[i] or (f"implausible: {label} {val[i] * scale:.1f} {unit} is outside the "
                                    f"{lo[i] * scale:.3g}-{hi * scale:g} {unit} of a human"
                                    f"{' of this stature' if lo[i] < rule['range'][0] else ''} (the tape caught "
                                    "another body part or missed this one)")
            val[i] = np.nan
    for other, (lo, hi) in rule.get("ratio_to", {}).items():
        ref = earlier.get(other)
        if ref is None:
            continue
        with np.errstate(divide="ignore", invalid="ignore"):
            r = val / ref
        for i in np.flatnonzero((r < lo) | (r > hi)):
            notes[i] = notes[i] or (f"implausible: {label} is {r[i]:.2f} x the {other.replace('_', ' ')}, "
                                    f"expected {lo:g}-{hi:g} x for a human")
            val[i] = np.nan


def _landmarks(L, v: np.ndarray) -> np.ndarray:
    """Landmark points (N, L, 3) from the sparse (L, V) matrix."""
    n, nv, _ = v.shape
    # Only the ~1k vertices the landmarks use are transposed (not the whole (N, V, 3) batch):
    # the same matrix with its columns renumbered, entries in the same order, same sums.
    cols, local = np.unique(L.indices, return_inverse=True)
    L = sp.csr_matrix((L.data, local.ravel(), L.indptr), shape=(L.shape[0], len(cols)))
    flat = v[:, cols].transpose(1, 0, 2).reshape(len(cols), n * 3)
    return np.asarray(L @ flat).reshape(L.shape[0], n, 3).transpose(1, 0, 2)


def evaluate(mset: MeasurementSet, vertices: np.ndarray, faces: np.ndarray, *,
             keep_polylines: bool = False, age_years=None, male=None,
             chunk: int = CHUNK, workers: int = 1, mesh_name: str = "measured mesh",
             check_scale: bool = True, check_faces: bool = True) -> dict[str, Measurement]:
    """Measure bodies: ``vertices`` (V, 3) or (N, V, 3), ``faces`` (F, 3) of the set's topology.

    Returns name → Measurement (values float for one body, (N,) for a batch), in the set's
    order. ``age_years`` and ``male`` (scalars or (N,)) override the set's mass defaults.
    ``keep_polylines`` adds the measured lines (for drawing; costs a little). ``workers`` > 1
    spreads the chunks over that many processes (bodies are independent). ``check_scale``
    refuses a body that is not human-sized in metres (``conventions.check_body_scale``, every
    body); ``check_faces`` refuses faces wound inwards (``conventions.check_winding``, the
    first body: the faces are shared). False measures any mesh. The other conventions (up axis,
    vertex order) are checked where a user's mesh comes in (``conventions.prepare``), not here.
    """
    v = np.asarray(vertices, dtype=float)
    faces = np.asarray(faces, dtype=np.int64)
    check_mesh(v, faces, mesh_name)
    single = v.ndim == 2
    if single:
        v = v[None]
    holed = check_compatible(mset, v, faces, mesh_name)
    if check_scale:
        check_body_scale(v, mesh_name)
    if check_faces:
        check_winding(v, faces, mesh_name)
    topology = _topology(faces)
    L = mset.landmark_matrix(v.shape[1])
    parts, parts_unknown = vertex_parts(mset, v, L, faces)
    jobs = []
    for s in range(0, len(v), chunk):
        sl = slice(s, s + chunk)
        a = None if age_years is None or np.ndim(age_years) == 0 else np.asarray(age_years)[sl]
        mm = None if male is None or np.ndim(male) == 0 else np.asarray(male)[sl]
        a = age_years if a is None else a
        mm = male if mm is None else mm
        jobs.append((mset, v[sl], topology, L, keep_polylines, a, mm, parts, parts_unknown))
    if workers > 1 and len(jobs) > 1:
        # The forked workers inherit the jobs: only (token, index) is pickled, not ~20 MB of
        # vertices per chunk (that pickling cost ~10 % of the CPU time).
        token = object()
        _FORKED[id(token)] = jobs
        try:
            with ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("fork")) as pool:
                parts = list(pool.map(_run_forked, [(id(token), i) for i in range(len(jobs))]))
        finally:
            del _FORKED[id(token)]
    else:
        parts = [_run_job(j) for j in jobs]
    out = {}
    for m in mset.measurements:
        name = m["name"]
        val = np.concatenate([p[name][0] for p in parts])
        poly = sum((p[name][1] or [None] * len(p[name][0]) for p in parts), []) if keep_polylines else None
        note = sum((p[name][2] for p in parts), [])
        if single:
            val, poly, note = float(val[0]), (poly[0] if poly else None), note[0]
        why = next((holed[k] for k in holed if k in _names_in(m)), None)
        if why is not None:     # a value taken from a landmark in a hole says so
            note = (note or why) if single else [n or why for n in note]
        out[name] = Measurement(name, val, m["unit"], m["method"], m.get("iso", ""), poly, note)
    return out


def _names_in(definition) -> set:
    """Every string in a measurement definition (its landmark names among them)."""
    if isinstance(definition, str):
        return {definition}
    if isinstance(definition, dict):
        return set().union(*(_names_in(x) for x in definition.values())) if definition else set()
    if isinstance(definition, (list, tuple)):
        return set().union(*(_names_in(x) for x in definition)) if definition else set()
    return set()


def vertex_parts(mset: MeasurementSet, v: np.ndarray, L, faces: np.ndarray | None = None
                 ) -> tuple[np.ndarray | None, str | None]:
    """The body part of each vertex (V,) for the set's part-aware girths, and None; or None and
    why they are unknown. The set's own labels, else assigned from the landmarks of the first
    body of ``v`` (N, V, 3) that stands (``parts.parts_from_landmarks``; on a seated or bent body
    a limb's skin lies nearer to the torso's lines than to its own bone: a 6,000-vertex body's
    chest came out +10 cm sitting, its upper arms +15 cm). (None, None) when no measurement
    names a part."""
    if not any(m.get("part") for m in mset.measurements):
        return None, None
    if mset.vertex_parts is not None:
        return mset.vertex_parts, None
    if mset.parts_unknown is not None:
        return None, mset.parts_unknown
    return parts_on_standing_body(mset, v, _landmarks(L, v), faces)


def _run_job(job):
    return _evaluate_chunk(*job)


_FORKED: dict = {}


def _run_forked(key):
    token, i = key
    return _evaluate_chunk(*_FORKED[token][i])


def measure(mset: MeasurementSet, vertices: np.ndarray, faces: np.ndarray, **kw) -> dict[str, np.ndarray]:
    """Just the values: name → float or (N,) array (SI units), for tables and training sets."""
    return {k: m.value for k, m in evaluate(mset, vertices, faces, **kw).items()}


def to_json(measurements: dict[str, Measurement]) -> dict:
    """{name: {"value", "unit", "note"?}} with lengths in cm, for one body or a batch (lists).

    Valid JSON: a value that is not finite (NaN) is ``null`` and its ``note`` says why (a
    batch's ``note`` is a list, one reason or null per body, present when any body has one).
    """
    out = {}
    for name, m in measurements.items():
        val, unit = m.display()
        val = np.asarray(val, dtype=float)
        if val.ndim == 0:
            finite = bool(np.isfinite(val))
            entry = {"value": round(float(val), 6 if unit in ("m^3",) else 3) if finite else None, "unit": unit}
            if m.note or not finite:
                entry["note"] = m.note or _UNDEFINED
        else:
            ok = np.isfinite(val)
            entry = {"value": [float(x) if f else None for x, f in zip(val, ok)], "unit": unit}
            notes = list(m.note) if m.note is not None else [None] * len(val)
            notes = [why or (None if f else _UNDEFINED) for why, f in zip(notes, ok)]
            if any(notes):
                entry["note"] = notes
        out[name] = entry
    return out


# The reason for a value evaluate left undefined without one (evaluate always gives one).
_UNDEFINED = "undefined for this body"
