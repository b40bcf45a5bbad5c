"""Evaluate a measurement set on bodies (V, 3) or batches (N, V, 3).

Everything but the slices is one vectorized expression over the batch (landmarks are a sparse
(L, V) product, loops/distances/paths are sums of segment lengths, volume and area are the
mesh/geometry sums). Slices are batched too (``slicing.band_contours`` cuts all bodies and all
planes of a band at once; ``slicing.hull_perimeters`` takes all the hulls at once, Qhull only
for degenerate contours or drawn polylines). Bodies are processed in chunks to bound the memory.

Values are SI inside (metres, kilograms, m³); ``Measurement.display`` converts lengths to cm
for people (the CLI and JSON).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp

from bodyspace.measure.composition import mass_from_volume
from bodyspace.measure.definitions import MeasurementError, MeasurementSet
from bodyspace.measure.slicing import (
    approx_heights,
    band_contours,
    contour_girths,
    edge_neighbours,
    mesh_edges,
    pick_contours,
    support_perimeters,
)
from bodyspace.mesh.geometry import boundary_loops, capped_volume, check_mesh

CHUNK = 64
# A body without a stated age or sex: age 30, and the mean of the male and female masses.
DEFAULT_AGE_YEARS = 30.0
UP = np.array([0.0, 1.0, 0.0])
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


@dataclass
class _Geometry:
    """Per-topology caches: edges, face→edge map, boundary loops."""

    faces: np.ndarray
    edges: np.ndarray = field(init=False)
    edge_faces: np.ndarray = field(init=False)
    neighbours: tuple = field(init=False)
    loops: list = field(init=False)

    cache_key: object = None
    cache_val: object = None

    def __post_init__(self):
        self.edges, self.edge_faces = mesh_edges(self.faces)
        self.neighbours = edge_neighbours(self.faces, self.edges, self.edge_faces)
        self.loops = boundary_loops(self.faces)


_GEOMETRY_CACHE: dict = {}


def _geometry(faces: np.ndarray) -> _Geometry:
    key = (faces.shape, hash(faces.tobytes()))
    g = _GEOMETRY_CACHE.get(key)
    if g is None:
        g = _GEOMETRY_CACHE[key] = _Geometry(faces)
        if len(_GEOMETRY_CACHE) > 8:
            _GEOMETRY_CACHE.pop(next(iter(_GEOMETRY_CACHE)))
    return g


def check_compatible(mset: MeasurementSet, vertices: np.ndarray, faces: np.ndarray) -> None:
    """Raise MeasurementError unless the mesh fits the set: vertex count, ids in range, on faces."""
    nv = vertices.shape[-2]
    if mset.n_vertices is not None and nv != mset.n_vertices:
        raise MeasurementError(f"{mset.source}: made for meshes of {mset.n_vertices} vertices, the mesh has {nv}; "
                               "give a landmark file for this topology (--landmarks)")
    used = np.zeros(nv, dtype=bool)
    used[faces.ravel()] = True
    for name, (ids, _) in mset.landmarks.items():
        if ids.max() >= nv or not used[ids].all():
            bad = int(ids[(ids >= nv) | ~used[np.minimum(ids, nv - 1)]][0])
            raise MeasurementError(f"{mset.source}: landmark {name!r} is vertex {bad}, which is off the mesh "
                                   f"({nv} vertices; ids must be 0..{nv - 1} and used by a face)")
    for m in mset.measurements:
        if m["method"] == "loop" and max(m["vertices"]) >= nv:
            raise MeasurementError(f"{mset.source}: measurement {m['name']!r} loops through vertex "
                                   f"{max(m['vertices'])}, but the mesh has {nv} vertices")


def _point(spec, lm: dict, v: np.ndarray) -> np.ndarray:
    """(N, 3) point of a landmark name, a list of names (their mean) or "floor"."""
    if isinstance(spec, str):
        if spec == "floor":
            raise AssertionError("floor is handled by the distance method")
        return lm[spec]
    return np.mean([lm[s] for s in spec], axis=0)


def _axis(spec, lm: dict, n: int) -> np.ndarray:
    """(N, 3) unit axis: "up" or a pair of points."""
    if spec is None or spec == "up":
        return np.broadcast_to(UP, (n, 3)).copy()
    a = _point(spec[1], lm, None) - _point(spec[0], lm, None)
    return a / np.maximum(np.linalg.norm(a, axis=-1, keepdims=True), 1e-12)


def _fmt_point(p) -> str:
    return p if isinstance(p, str) else "+".join(p)


def _conditions(mset: MeasurementSet, lm: dict, n: int) -> dict[str, list]:
    """Per condition, per body: None if it holds, else the reason it fails."""
    out = {}
    for cname, c in mset.conditions.items():
        lim = float(c.get("max_angle_deg", 12.0))
        rel = c.get("relative_to", "up")
        ref = _axis(rel, lm, n)
        ref_name = "vertical" if rel == "up" else f"axis {_fmt_point(rel[0])}→{_fmt_point(rel[1])}"
        notes: list = [None] * n
        for a in c["axes"]:
            # An axis is a line: its direction (up or down the body) does not matter.
            cos = np.abs(np.sum(_axis(a, lm, n) * ref, axis=-1))
            ang = np.degrees(np.arccos(np.clip(cos, 0, 1)))
            for i in np.flatnonzero(ang > lim):
                if notes[i] is None:
                    notes[i] = (f"not {cname}: axis {_fmt_point(a[0])}→{_fmt_point(a[1])} is {ang[i]:.0f}° "
                                f"from {ref_name} (at most {lim:.0f}°)")
        out[cname] = notes
    return out


def _slice(m: dict, v: np.ndarray, lm: dict, geo: _Geometry, keep_polylines: bool, heights: dict | None = None):
    """Girths (N,) and polylines of one slice measurement over a chunk of bodies.

    ``heights`` caches the chunk's float32 coordinate planes and the approximate vertex heights
    per normal axis across the measurements of a chunk (chest, underbust, waist and hip share
    the torso axis).
    """
    n = len(v)
    normal = _axis(m["normal"], lm, n)
    key = repr(m["normal"])
    if heights is None:
        heights = {}
    if key not in heights:
        if "planes" not in heights:
            heights["planes"] = tuple(np.ascontiguousarray(v[..., k], dtype=np.float32) for k in range(3))
            heights["scale"] = float(np.abs(v).sum(axis=-1).max())
        heights[key] = approx_heights(heights["planes"], normal, heights["scale"])
    band = m.get("band")
    if band is None:
        origins = [_point(m["at"], lm, v)]
    else:
        a, b = _point(band["from"], lm, v), _point(band["to"], lm, v)
        ts = np.linspace(float(band.get("start", 0.0)), float(band.get("stop", 1.0)), int(band.get("steps", 12)))
        origins = [a + t * (b - a) for t in ts]
    pick_fixed = _point(m["pick"], lm, v) if m.get("pick") is not None else None
    # Every plane of the band in one Contours: group p * n + i is plane p of body i.
    n_planes = len(origins)
    cuts = band_contours(v, geo.edges, geo.edge_faces, np.stack(origins), normal,
                         heights=heights[key], neighbours=geo.neighbours)
    normals = np.tile(normal, (n_planes, 1))
    picks = np.concatenate(origins if pick_fixed is None else [pick_fixed] * n_planes)
    chosen = pick_contours(cuts, picks, normals)
    missed = np.flatnonzero(chosen < 0)
    if len(missed):
        raise MeasurementError(f"measurement {m['name']!r}: the plane through {m.get('at', band)} hits "
                               f"nothing on body {int(missed[0]) % n} (the landmarks are off the body or "
                               "the normal axis is degenerate)")
    if n_planes == 1:
        k = np.zeros(n, dtype=np.int64)
    else:
        # Pick the band's extreme plane by the fast support-function estimate, then measure
        # only that plane exactly: one hull per body instead of one per plane.
        est = support_perimeters(cuts, chosen, normals).reshape(n_planes, n)
        k = np.argmax(est, axis=0) if band["mode"] == "max" else np.argmin(est, axis=0)
    group = k * n + np.arange(n)
    ch = np.full(n_planes * n, -1, dtype=np.int64)
    ch[group] = chosen[group]
    g, pl = contour_girths(cuts, ch, normals, keep_polylines)
    value = g[group]
    return value, ([pl[i] for i in group] if keep_polylines else None)


def _evaluate_chunk(mset: MeasurementSet, v: np.ndarray, geo: _Geometry, L, keep_polylines: bool,
                    age_years, male) -> dict:
    n = len(v)
    P = _landmarks(L, v)
    lm = {name: P[:, i] for i, name in enumerate(mset.landmarks)}
    cond = _conditions(mset, lm, n)
    res: dict = {}
    heights: dict = {}
    for m in mset.measurements:
        meth, poly = m["method"], None
        if meth == "slice":
            val, poly = _slice(m, v, lm, geo, keep_polylines, heights)
        elif meth == "loop":
            ring = v[:, m["vertices"]]
            ax = _axis(m.get("axis", "up"), lm, n)[:, None, :]
            flat = ring - np.sum(ring * ax, axis=-1, keepdims=True) * ax  # Rupprecht: project first
            val = np.linalg.norm(flat - np.roll(flat, -1, axis=1), axis=-1).sum(axis=1)
            if keep_polylines:
                poly = [np.concatenate([r, r[:1]]) for r in ring]
        elif meth == "distance":
            a = _point(m["from"], lm, v)
            if m["to"] == "floor":
                b = a.copy()
                b[:, 1] = v[:, :, 1].min(axis=1)
            else:
                b = _point(m["to"], lm, v)
            if m.get("axis") is None:
                val = np.linalg.norm(b - a, axis=-1)
            else:
                val = np.abs(np.sum((b - a) * _axis(m["axis"], lm, n), axis=-1))
            if keep_polylines:
                poly = [np.stack([p, q]) for p, q in zip(a, b)]
        elif meth == "path":
            pts = np.stack([_point(p, lm, v) for p in m["through"]], axis=1)   # (N, K, 3)
            val = np.linalg.norm(np.diff(pts, axis=1), axis=-1).sum(axis=1)
            if keep_polylines:
                poly = list(pts)
        elif meth == "volume":
            val = _volume_area(v, geo)[0]
        elif meth == "surface_area":
            val = _volume_area(v, geo)[1]
        elif meth == "mass":
            vol = _volume_area(v, geo)[0]
            h = res[m["stature"]][0]
            age = m.get("age_years", DEFAULT_AGE_YEARS) if age_years is None else age_years
            sex = m.get("male") if male is None else male
            if sex is None:     # unknown: the mean of the male and female solutions
                val = 0.5 * (mass_from_volume(vol, h, age, 1.0)[0] + mass_from_volume(vol, h, age, 0.0)[0])
            else:
                val = mass_from_volume(vol, h, age, float(sex))[0]
        elif meth == "bmi":
            val = res[m["mass"]][0] / res[m["stature"]][0] ** 2
        else:  # pragma: no cover - definitions validate the method
            raise MeasurementError(f"measurement {m['name']!r}: unknown method {meth!r}")
        val = np.asarray(val, dtype=float).copy()
        notes: list = [None] * n
        for r in m["requires"]:
            for i, why in enumerate(cond[r]):
                if why is not None:
                    val[i] = np.nan
                    notes[i] = notes[i] or why
        if meth in ("mass", "bmi"):
            # NaN stature (not upright) would poison mass: say so rather than guess.
            for i in np.flatnonzero(np.isnan(val)):
                notes[i] = notes[i] or f"needs {m['stature']!r}, which is undefined for this body"
        res[m["name"]] = (val, poly, notes)
    return res


def _volume_area(v: np.ndarray, geo: _Geometry) -> tuple[np.ndarray, np.ndarray]:
    """Capped volume (N,) and surface area (N,) from one cross product per face.

    With n = (b - a) x (c - a): area = |n| / 2 and a.n = a.(b x c), the divergence-theorem
    tetrahedron (x6). Same result as ``mesh.geometry.capped_volume``/``surface_area``, but
    written per component: ``np.cross`` on (N, F, 3) costs several times more. Cached per chunk.
    """
    # Keyed by identity while holding a reference, so a freed chunk's id can never be reused.
    if geo.cache_key is v:
        return geo.cache_val
    f0, f1, f2 = (np.ascontiguousarray(geo.faces[:, k]) for k in range(3))
    n = len(v)
    vol, area = np.empty(n), np.empty(n)
    # One body at a time: its (F,) temporaries stay in cache (2x faster than (N, F) arrays).
    # Summed in the order numpy summed the (N, F) gathers (column-major, so sequential; one
    # body: pairwise), to keep every bit of the earlier values.
    total = np.sum if n == 1 else (lambda a: np.cumsum(a)[-1])
    for i in range(n):
        x, y, z = (np.ascontiguousarray(v[i, :, k]) for k in range(3))
        ax, ay, az = x[f0], y[f0], z[f0]
        e1x, e1y, e1z = x[f1] - ax, y[f1] - ay, z[f1] - az
        e2x, e2y, e2z = x[f2] - ax, y[f2] - ay, z[f2] - az
        nx = e1y * e2z - e1z * e2y
        ny = e1z * e2x - e1x * e2z
        nz = e1x * e2y - e1y * e2x
        area[i] = 0.5 * total(np.sqrt(nx * nx + ny * ny + nz * nz))
        vol[i] = total(ax * nx + ay * ny + az * nz) / 6.0
    if geo.loops:
        vol = vol + capped_volume(v, np.zeros((0, 3), dtype=np.int64), geo.loops)
    geo.cache_key, geo.cache_val = v, (vol, area)
    return vol, area


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
             chunk: int = CHUNK, workers: int = 1) -> dict[str, Measurement]:
    """Measure bodies: ``vertices`` (V, 3) or (N, V, 3), ``faces`` (F, 3) of the set's topology.

    Returns name → Measurement (values float for one body, (N,) for a batch), in the set's
    order. ``age_years`` and ``male`` (scalars or (N,)) override the set's mass defaults.
    ``keep_polylines`` adds the measured lines (for drawing; costs a little). ``workers`` > 1
    spreads the chunks over that many processes (bodies are independent).
    """
    v = np.asarray(vertices, dtype=float)
    faces = np.asarray(faces, dtype=np.int64)
    check_mesh(v, faces, "measured mesh")
    single = v.ndim == 2
    if single:
        v = v[None]
    check_compatible(mset, v, faces)
    geo = _geometry(faces)
    L = mset.landmark_matrix(v.shape[1])
    jobs = []
    for s in range(0, len(v), chunk):
        sl = slice(s, s + chunk)
        a = None if age_years is None or np.ndim(age_years) == 0 else np.asarray(age_years)[sl]
        mm = None if male is None or np.ndim(male) == 0 else np.asarray(male)[sl]
        a = age_years if a is None else a
        mm = male if mm is None else mm
        jobs.append((mset, v[sl], geo, L, keep_polylines, a, mm))
    if workers > 1 and len(jobs) > 1:
        import multiprocessing as mp
        from concurrent.futures import ProcessPoolExecutor
        geo.cache_key = geo.cache_val = None
        # The forked workers inherit the jobs: only (token, index) is pickled, not ~20 MB of
        # vertices per chunk (that pickling cost ~10 % of the CPU time).
        token = object()
        _FORKED[id(token)] = jobs
        try:
            with ProcessPoolExecutor(workers, mp_context=mp.get_context("fork")) as pool:
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
        out[name] = Measurement(name, val, m["unit"], m["method"], m.get("iso", ""), poly, note)
    return out


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
    """{name: {"value": ..., "unit": ...}} with lengths in cm (one body); NaN → null plus a note."""
    out = {}
    for name, m in measurements.items():
        val, unit = m.display()
        val = np.asarray(val, dtype=float)
        if val.ndim == 0:
            entry = {"value": None if np.isnan(val) else round(float(val), 6 if unit in ("m^3",) else 3),
                     "unit": unit}
            if m.note:
                entry["note"] = m.note
        else:
            entry = {"value": [None if np.isnan(x) else float(x) for x in val], "unit": unit}
        out[name] = entry
    return out
