"""Measurement methods: one function per method, all registered in ``METHODS``.

As trimesh's ``exchange`` loaders are one function per format merged into one dict, a method
here is one function with one signature, registered under the name a measurement-set JSON
gives in its ``"method"`` field:

    compute(m, chunk) -> (values (N,), polylines, notes)

- ``m``: the measurement's definition (a validated dict of the JSON, docs/measurements.md).
- ``chunk``: a ``Chunk`` of N bodies: vertices (N, V, 3), landmark points name → (N, 3), the
  topology's caches, and the values (N,) of the measurements earlier in the set.
- ``values``: (N,) float, SI units (the method's ``unit``); NaN where undefined.
- ``polylines``: None unless ``chunk.keep_polylines``; then a list of N arrays (K, 3), the
  measured line of each body (closed loops repeat their first point).
- ``notes``: None, or a list of N reasons (str or None) for the bodies whose value is NaN.

Each method also has a ``check(where, m, landmarks, earlier)`` that validates its fields when a
set is loaded (``where`` names the file and measurement, ``landmarks`` the set's landmark
names, ``earlier`` the names of the measurements before it) and raises MeasurementError.
``register_method`` adds a method; ``definitions`` validates every ``"method"`` against
``METHODS`` and ``evaluate`` looks each one up there, so a new method needs no other change.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import numba
import numpy as np

from bodyspace.errors import MeasurementError
from bodyspace.measure.composition import mass_from_volume
from bodyspace.measure.parts import PART_INDEX, PARTS
from bodyspace.measure.points import axis, check_axis, check_point, fail, inline_points, point
from bodyspace.measure.slicing import (
    MODE_MAX,
    MODE_MIN,
    MODE_ONE,
    Contours,
    PartMesh,
    approx_heights,
    band_contours,
    contour_girths,
    edge_neighbours,
    face_edge_ids,
    fold_coarse,
    fold_planes,
    mesh_edges,
    part_fronts,
    part_girths,
    part_mesh,
    part_sections,
    pick_contours,
    ring_runs,
    support_perimeters,
)
from bodyspace.mesh.geometry import boundary_loops, capped_volume

# A body without a stated age or sex: age 30, and the mean of the male and female masses.
DEFAULT_AGE_YEARS = 30.0


@dataclass
class Topology:
    """Per-topology caches shared by every chunk: edges (E, 2), edge→faces (E, 2), the face
    neighbours through each edge, and the boundary loops (for capping open meshes)."""

    faces: np.ndarray
    edges: np.ndarray = field(init=False)
    edge_faces: np.ndarray = field(init=False)
    neighbours: tuple = field(init=False)
    loops: list = field(init=False)

    def __post_init__(self):
        self.edges, self.edge_faces = mesh_edges(self.faces)
        self.neighbours = edge_neighbours(self.faces, self.edges, self.edge_faces)
        self.loops = boundary_loops(self.faces)
        self._part_edges: dict = {}
        self._face_edges = None

    def part_edges(self, labels: np.ndarray, part) -> tuple[np.ndarray, np.ndarray]:
        """The edges (E', 2) whose two ends are on ``part`` (a part name or a list of them) by the
        vertex ``labels`` (V,), and which of them lie on the part's border (E',) bool (a face
        beside them reaches off the part). Cached: labels are per topology."""
        names = (part,) if isinstance(part, str) else tuple(part)
        key = (hash(labels.tobytes()), names)
        if key not in self._part_edges:
            on = np.isin(labels, [PART_INDEX[p] for p in names])
            keep = on[self.edges[:, 0]] & on[self.edges[:, 1]]
            face_on = on[self.faces].all(axis=1)
            ef = self.edge_faces[keep]
            inside = np.where(ef >= 0, face_on[np.maximum(ef, 0)], False).all(axis=1)
            self._part_edges[key] = (self.edges[keep], ~inside)
            if len(self._part_edges) > 64:
                self._part_edges.pop(next(iter(self._part_edges)))
        return self._part_edges[key]

    def part_mesh(self, labels: np.ndarray, part) -> PartMesh:
        """``part_edges`` as ``slicing.part_girths`` takes them (``slicing.PartMesh``), cached."""
        names = (part,) if isinstance(part, str) else tuple(part)
        key = ("mesh", hash(labels.tobytes()), names)
        if key not in self._part_edges:
            # With the whole mesh, so a min band follows a plane off the part (``slicing.ring_runs``).
            on = np.isin(labels, [PART_INDEX[p] for p in names])
            if self._face_edges is None:
                self._face_edges = face_edge_ids(self.faces, self.edges)
            mesh = {"faces": self.faces, "edges": self.edges, "edge_faces": self.edge_faces,
                    "face_edges": self._face_edges, "gid": np.flatnonzero(on[self.edges].all(axis=1)), "on": on}
            self._part_edges[key] = part_mesh(*self.part_edges(labels, part), mesh=mesh)
        return self._part_edges[key]


@dataclass
class Chunk:
    """N bodies being measured, as every method sees them.

    vertices: (N, V, 3) float64.
    landmarks: landmark name → (N, 3) points.
    topology: the mesh's ``Topology``.
    keep_polylines: whether methods return the measured lines.
    parts: (V,) body part of each vertex (``parts.PARTS`` index), or None (a slice with a
        ``part`` then falls back to the contour around its point).
    age_years, male: None, scalars or (N,): the caller's overrides of the mass defaults.
    values: measurement name → (N,) values of the measurements done so far (file order).
    cache: scratch shared by the methods within this chunk (slice heights, volume and area).
    """

    vertices: np.ndarray
    landmarks: dict
    topology: Topology
    keep_polylines: bool = False
    age_years: object = None
    male: object = None
    parts: np.ndarray | None = None
    values: dict = field(default_factory=dict)
    cache: dict = field(default_factory=dict)

    @property
    def n(self) -> int:
        return len(self.vertices)


@dataclass(frozen=True)
class Method:
    """A registered method: its function, the SI unit of its values, its field check, and
    whether it carries over to another topology through a landmark file (only landmarks used)."""

    compute: Callable[[dict, Chunk], tuple]
    unit: str
    check: Callable[[str, dict, dict, set], None] | None = None
    topology_free: bool = True


# --- loop: Rupprecht's vertex rings -----------------------------------------------------------

def loop_girth(m: dict, chunk: Chunk) -> tuple:
    """Closed length of the ring ``m["vertices"]`` projected on the plane normal to ``m["axis"]``
    (Rupprecht §3.1.2: project first, then measure). Template-only (vertex ids)."""
    ring = chunk.vertices[:, m["vertices"]]                                   # (N, K, 3)
    ax = axis(m.get("axis", "up"), chunk.landmarks, chunk.n)[:, None, :]
    flat = ring - np.sum(ring * ax, axis=-1, keepdims=True) * ax
    val = np.linalg.norm(flat - np.roll(flat, -1, axis=1), axis=-1).sum(axis=1)
    poly = [np.concatenate([r, r[:1]]) for r in ring] if chunk.keep_polylines else None
    return val, poly, None


def check_loop(where: str, m: dict, landmarks, earlier: set) -> None:
    ring = m.get("vertices")
    if not isinstance(ring, list) or len(ring) < 3 or not all(isinstance(k, int) and k >= 0 for k in ring):
        raise fail(where, "'vertices' must be a list of at least 3 non-negative vertex ids")
    check_axis(where + " field 'axis'", m.get("axis", "up"), landmarks)


# --- slice: tape-measure girths of plane sections ---------------------------------------------

def slice_girth(m: dict, chunk: Chunk) -> tuple:
    """Convex-hull girth of the contour of the plane through ``at`` with normal ``normal``; with a
    ``band``, the max or min over planes along a segment (so it follows a limb).

    A girth round a body part (``part``, with the chunk's part labels) runs compiled, one pass a
    body (``slicing.part_girths``); drawn polylines and sets without parts take the numpy path
    below, whose float32 coordinate planes and approximate vertex heights per normal axis are
    cached across the chunk's slices (chest, underbust, waist and hip share the torso axis).

    A ``fold`` band (the underbust) measures just below a breast's underside where the breast
    hangs below the band's first plane, else on that plane (``slicing.fold_planes``): the planes
    it measures are chosen from the fronts of its planes first, then it is a min band over them.
    """
    v, lm, geo, n = chunk.vertices, chunk.landmarks, chunk.topology, chunk.n
    normal = axis(m["normal"], lm, n)
    band = m.get("band")
    part = m.get("part")
    if band is not None and band["mode"] == "fold":
        a, b = point(band["from"], lm), point(band["to"], lm)
        coarse, ts = fold_coarse(a, b, band.get("start", 0.0), band.get("stop", 1.0), band.get("steps", 12))
        forward = axis(band["front"], lm, n)
        forward = forward - np.sum(forward * normal, axis=-1, keepdims=True) * normal       # in the planes
        forward /= np.maximum(np.linalg.norm(forward, axis=-1, keepdims=True), 1e-12)
        steep, below = float(band["steep"]), float(band.get("below", 0.0))
        if part is not None and chunk.parts is not None and not chunk.keep_polylines:
            # Compiled: the band's fronts and the girth of its first plane in one pass a body; the
            # fine planes and the planes below a fold only for the bodies with one.
            pm = geo.part_mesh(chunk.parts, part)
            fronts, girth, missed = part_fronts(v, pm, coarse, normal, forward, hull_plane=1)
            window, folded = fold_planes(a, b, normal, coarse, ts, fronts, steep, below,
                                         lambda o, act: part_fronts(v, pm, o, normal, forward, active=act)[0])
            if window is not None:
                girth = np.where(folded, part_girths(v, pm, window, normal, MODE_MIN, active=folded)[0], girth)
            return girth, None, _missed_notes(part, missed)
        window, _ = fold_planes(a, b, normal, coarse, ts, _plane_fronts(m, chunk, normal, coarse, forward), steep,
                                below, lambda o, act: _plane_fronts(m, chunk, normal, o, forward))
        origins = [coarse[1]] if window is None else list(window)
        band = None if window is None else dict(band, mode="min")
    elif band is None:
        origins = [point(m["at"], lm)]
    else:
        a, b = point(band["from"], lm), point(band["to"], lm)
        ts = np.linspace(float(band.get("start", 0.0)), float(band.get("stop", 1.0)), int(band.get("steps", 12)))
        origins = [a + t * (b - a) for t in ts]
    pick_fixed = point(m["pick"], lm) if m.get("pick") is not None else None
    # Every plane of the band in one Contours: group p * n + i is plane p of body i.
    n_planes = len(origins)
    normals = np.tile(normal, (n_planes, 1))
    notes = None
    if part is not None and chunk.parts is not None and not chunk.keep_polylines:
        # The compiled slicer: the same planes, crossings, choice and hull as below, one pass a body.
        mode = MODE_ONE if band is None else (MODE_MAX if band["mode"] == "max" else MODE_MIN)
        girth, _, missed = part_girths(v, geo.part_mesh(chunk.parts, part), np.stack(origins), normal, mode)
        return girth, None, _missed_notes(part, missed)
    heights = _chunk_heights(m, chunk, normal)
    if part is not None and chunk.parts is not None:
        # The tape round one body part: only the part's edges are cut, and all its crossings
        # in a plane are the contour (``slicing.part_sections``).
        part_edges, border = geo.part_edges(chunk.parts, part)
        cuts, edge = part_sections(v, part_edges, np.stack(origins), normal, heights=heights)
        # A plane that crosses the part's border leaves the part (at a joint, or grazing a
        # triangle of another part). In a "min" band its ring goes on along the other parts'
        # skin it meets until it is back on the part (``slicing.ring_runs``: the tape's ring
        # there, as ``part_girths`` measures it); a plane whose ring does not come back (a hole
        # of the mesh) is left out while another plane exists.
        opened = np.bincount(cuts.body[border[edge]], minlength=n_planes * n) > 0
        if band is not None and band["mode"] == "min":
            run_points, run_group, closed = ring_runs(v, geo.part_mesh(chunk.parts, part), np.stack(origins), normal)
            opened &= ~closed
            cuts = Contours(np.concatenate([cuts.points, run_points]), np.concatenate([cuts.body, run_group]),
                            np.concatenate([cuts.label, run_group]), cuts.seg, cuts.n_labels)
        chosen = np.where(np.bincount(cuts.body, minlength=n_planes * n) >= 3, np.arange(n_planes * n), -1)
        notes = _missed_notes(part, (chosen < 0).reshape(n_planes, n).all(axis=0))
    else:
        cuts = band_contours(v, geo.edges, geo.edge_faces, np.stack(origins), normal,
                             heights=heights, neighbours=geo.neighbours)
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
        if part is not None and chunk.parts is not None and band["mode"] == "min":
            whole = ~opened.reshape(n_planes, n)
            est = np.where(whole | ~whole.any(axis=0), est, np.nan)
        est = np.where(np.isnan(est), -np.inf if band["mode"] == "max" else np.inf, est)
        k = np.argmax(est, axis=0) if band["mode"] == "max" else np.argmin(est, axis=0)
    group = k * n + np.arange(n)
    ch = np.full(n_planes * n, -1, dtype=np.int64)
    ch[group] = chosen[group]
    g, pl = contour_girths(cuts, ch, normals, chunk.keep_polylines)
    return g[group], ([pl[i] for i in group] if chunk.keep_polylines else None), notes


def _chunk_heights(m: dict, chunk: Chunk, normal: np.ndarray):
    """The approximate vertex heights along the slice's normal (``slicing.approx_heights``), cached
    per normal within the chunk (chest, underbust, waist and hip share the torso axis)."""
    heights = chunk.cache.setdefault("heights", {})
    key = repr(m["normal"])
    if key not in heights:
        if "planes" not in heights:
            v = chunk.vertices
            heights["planes"] = tuple(np.ascontiguousarray(v[..., k], dtype=np.float32) for k in range(3))
            heights["scale"] = float(np.abs(v).sum(axis=-1).max())
        heights[key] = approx_heights(heights["planes"], normal, heights["scale"])
    return heights[key]


def _plane_fronts(m: dict, chunk: Chunk, normal: np.ndarray, origins: np.ndarray, forward: np.ndarray) -> np.ndarray:
    """The numpy path's fronts (P, N) of planes through ``origins`` (P, N, 3): the largest
    coordinate along ``forward`` (N, 3) of the crossings with the part (``slicing.part_fronts``'
    value), or without part labels of the contour containing the origin (else the nearest)."""
    v, geo, n = chunk.vertices, chunk.topology, chunk.n
    n_planes = len(origins)
    heights = _chunk_heights(m, chunk, normal)
    part = m.get("part")
    if part is not None and chunk.parts is not None:
        part_edges, _ = geo.part_edges(chunk.parts, part)
        cuts, _ = part_sections(v, part_edges, origins, normal, heights=heights)
        keep = np.ones(len(cuts.points), dtype=bool)
    else:
        cuts = band_contours(v, geo.edges, geo.edge_faces, origins, normal, heights=heights, neighbours=geo.neighbours)
        chosen = pick_contours(cuts, origins.reshape(-1, 3), np.tile(normal, (n_planes, 1)))
        keep = cuts.label == chosen[cuts.body]
    out = np.full(n_planes * n, -np.inf)
    np.maximum.at(out, cuts.body[keep], np.einsum("ki,ki->k", cuts.points[keep], forward[cuts.body[keep] % n]))
    return np.where(np.isinf(out), np.nan, out).reshape(n_planes, n)


def _missed_notes(part, missed: np.ndarray) -> list | None:
    """The note of each body (N,) whose girth planes all miss ``part`` (``missed`` (N,) bool)."""
    if not missed.any():
        return None
    what = part if isinstance(part, str) else " or ".join(part)
    return [f"no plane of this girth crosses the {what.replace('_', ' ')} (its landmarks are off that "
            "part, or the part labels do not fit this mesh)" if x else None for x in missed]


def check_slice(where: str, m: dict, landmarks, earlier: set) -> None:
    check_axis(where + " field 'normal'", m.get("normal"), landmarks)
    band = m.get("band")
    if band is None:
        check_point(where + " field 'at'", m.get("at"), landmarks)
    else:
        if not isinstance(band, dict):
            raise fail(where + " field 'band'", f"got {band!r}, expected an object")
        check_point(where + " field 'band.from'", band.get("from"), landmarks)
        check_point(where + " field 'band.to'", band.get("to"), landmarks)
        if band.get("mode") not in ("max", "min", "fold"):
            raise fail(where + " field 'band.mode'", f"got {band.get('mode')!r}, expected \"max\", \"min\" or \"fold\"")
        steps = band.get("steps", 12)
        if not isinstance(steps, int) or isinstance(steps, bool) or steps < (2 if band["mode"] == "fold" else 1):
            raise fail(where + " field 'band.steps'", f"got {steps!r}, expected a positive integer"
                       + (" of at least 2 with mode \"fold\"" if band["mode"] == "fold" else ""))
        extra = {"front", "steep", "below"} & set(band)
        if band["mode"] == "fold":
            check_axis(where + " field 'band.front'", band.get("front"), landmarks)
            if band.get("front") == "up" or isinstance(band.get("front"), dict):
                raise fail(where + " field 'band.front'", f"got {band.get('front')!r}, expected a pair of points "
                                                          "[back, front] (the body's forward direction)")
            for key, lo in (("steep", 0.0), ("below", None)):
                x = band.get(key, 0.0 if key == "below" else None)
                if isinstance(x, bool) or not isinstance(x, (int, float)) or not (x > lo if lo is not None else x >= 0):
                    raise fail(where + f" field 'band.{key}'", f"got {x!r}, expected " + (
                        "a number > 0 (metres the front recedes per metre down the band at a breast's underside)"
                        if key == "steep" else "a number >= 0 (metres below the fold the girth may be taken)"))
        elif extra:
            raise fail(where + " field 'band'", f"{', '.join(sorted(extra))} with mode {band['mode']!r}: only a "
                                                "\"fold\" band has them")
    if m.get("pick") is not None:
        check_point(where + " field 'pick'", m["pick"], landmarks)
    check_part(where, m.get("part"))


# --- top: the height of a body part's highest point ------------------------------------------

def part_top(m: dict, chunk: Chunk) -> tuple:
    """Height (N,) of the highest vertex of ``m["part"]`` (world +Y) over the body's lowest vertex:
    stature as the top of the head, whichever vertex is highest (a tilted head has a stature)."""
    v = chunk.vertices
    floor = floor_height(chunk)
    if chunk.parts is None:
        on = np.arange(v.shape[1])
    else:
        on = np.flatnonzero(np.isin(chunk.parts, [PART_INDEX[p] for p in _part_names(m["part"])]))
    if not len(on):
        return np.full(len(v), np.nan), None, [f"no vertex is on the {m['part']} part"] * len(v)
    y = v[:, on, 1]
    val = y.max(axis=1) - floor
    poly = None
    if chunk.keep_polylines:                 # which vertex is highest: only the drawing needs it
        top = on[np.argmax(y, axis=1)]
        p = v[np.arange(len(v)), top]
        q = p.copy()
        q[:, 1] = floor
        poly = [np.stack([a, b]) for a, b in zip(p, q)]
    return val, poly, None


def floor_height(chunk: Chunk) -> np.ndarray:
    """The lowest vertex's height (N,) of each body, once a chunk (stature and the lengths to the
    floor each read it: a strided pass over all the vertices)."""
    if "floor" not in chunk.cache:
        chunk.cache["floor"] = chunk.vertices[:, :, 1].min(axis=1)
    return chunk.cache["floor"]


def _part_names(part) -> list:
    return [part] if isinstance(part, str) else list(part)


def check_part(where: str, part, required: bool = False) -> None:
    """Raise MeasurementError unless ``part`` is a body part name or a list of them (``parts.PARTS``)."""
    if part is None and not required:
        return
    names = [part] if isinstance(part, str) else part
    if not isinstance(names, list) or not names or not all(isinstance(p, str) and p in PARTS for p in names):
        raise fail(where + " field 'part'", f"got {part!r}, expected a body part or a list of them, from "
                                            f"{', '.join(PARTS)}")


def check_top(where: str, m: dict, landmarks, earlier: set) -> None:
    check_part(where, m.get("part"), required=True)


# --- distance and path: lengths between landmarks ---------------------------------------------

def distance(m: dict, chunk: Chunk) -> tuple:
    """Straight distance ``from`` → ``to`` (a point or "floor", the lowest vertex's level), or
    its extent along ``axis``."""
    lm, n = chunk.landmarks, chunk.n
    a = point(m["from"], lm)
    if m["to"] == "floor":
        b = a.copy()
        b[:, 1] = floor_height(chunk)
    else:
        b = point(m["to"], lm)
    if m.get("axis") is None:
        val = np.linalg.norm(b - a, axis=-1)
    else:
        val = np.abs(np.sum((b - a) * axis(m["axis"], lm, n), axis=-1))
    poly = [np.stack([p, q]) for p, q in zip(a, b)] if chunk.keep_polylines else None
    return val, poly, None


def check_distance(where: str, m: dict, landmarks, earlier: set) -> None:
    check_point(where + " field 'from'", m.get("from"), landmarks)
    check_point(where + " field 'to'", m.get("to"), landmarks, allow_floor=True)
    check_axis(where + " field 'axis'", m.get("axis"), landmarks, required=False)


def path_length(m: dict, chunk: Chunk) -> tuple:
    """Summed straight segments through the points ``through`` (joint centres for limbs)."""
    pts = np.stack([point(p, chunk.landmarks) for p in m["through"]], axis=1)   # (N, K, 3)
    val = np.linalg.norm(np.diff(pts, axis=1), axis=-1).sum(axis=1)
    return val, (list(pts) if chunk.keep_polylines else None), None


def check_path(where: str, m: dict, landmarks, earlier: set) -> None:
    pts = m.get("through")
    if not isinstance(pts, list) or len(pts) < 2:
        raise fail(where + " field 'through'", f"got {pts!r}, expected a list of at least 2 points")
    for p in pts:
        check_point(where + " field 'through'", p, landmarks)


# --- volume, surface area, mass, BMI ----------------------------------------------------------

def volume(m: dict, chunk: Chunk) -> tuple:
    """Enclosed volume (m³), open boundaries capped."""
    return volume_and_area(chunk)[0], None, None


def surface_area(m: dict, chunk: Chunk) -> tuple:
    """Surface area (m²)."""
    return volume_and_area(chunk)[1], None, None


def mass(m: dict, chunk: Chunk) -> tuple:
    """Mass (kg) from the volume and the stature measurement ``m["stature"]`` through the body
    composition fixed point (``composition.mass_from_volume``); ``age_years`` and ``male`` from
    the caller, else the definition (``male`` null: the mean of the male and female masses)."""
    vol = volume_and_area(chunk)[0]
    h = stature_for_mass(m, chunk)
    age = m.get("age_years", DEFAULT_AGE_YEARS) if chunk.age_years is None else chunk.age_years
    sex = m.get("male") if chunk.male is None else chunk.male
    if sex is None:
        val = 0.5 * (mass_from_volume(vol, h, age, 1.0)[0] + mass_from_volume(vol, h, age, 0.0)[0])
    else:
        # A scalar or one value per body (N,): ``float(sex)`` would refuse the array.
        val = mass_from_volume(vol, h, age, np.asarray(sex, dtype=float))[0]
    return val, None, _needs_stature(m, val)


def stature_for_mass(m: dict, chunk: Chunk) -> np.ndarray:
    """(N,) the stature mass uses: the measurement ``m["stature"]``, and where it is undefined (a
    body that does not stand) the estimate ``m["stature_estimate"]`` if the definition has one:
    ``scale`` x (the summed segments ``through`` its points + the mean of the earlier lengths
    ``plus_mean_of``). The hm08 set's: 1.038 x (mean leg joint path + hip centre to neck + neck to
    head top), within 0.6 % of the stature of 40 standing bodies and 1.6 % in every library pose
    (bend_forward, squat worst), so mass (density from BMI) moves by less than 0.3 %: mass is
    defined for every closed body, posed or not (issue 12 §3). NaN where the estimate's
    landmarks or lengths are missing (another topology's landmark file without them)."""
    h = np.asarray(chunk.values[m["stature"]], dtype=float)
    est = m.get("stature_estimate")
    missing = ~np.isfinite(h)
    if est is None or not missing.any():
        return h
    names = {n for p in est["through"] for n in ([p] if isinstance(p, str) else p)}
    if not names <= set(chunk.landmarks) or not all(k in chunk.values for k in est.get("plus_mean_of", [])):
        return h
    pts = np.stack([point(p, chunk.landmarks) for p in est["through"]], axis=1)          # (N, K, 3)
    length = np.linalg.norm(np.diff(pts, axis=1), axis=-1).sum(axis=1)
    if est.get("plus_mean_of"):
        length = length + np.mean([chunk.values[k] for k in est["plus_mean_of"]], axis=0)
    return np.where(missing, float(est["scale"]) * length, h)


def check_mass(where: str, m: dict, landmarks, earlier: set) -> None:
    _check_earlier("stature")(where, m, landmarks, earlier)
    est = m.get("stature_estimate")
    if est is None:
        return
    where += " field 'stature_estimate'"
    if not isinstance(est, dict) or set(est) - {"through", "plus_mean_of", "scale"}:
        raise fail(where, f"got {est!r}, expected {{\"through\": [points], \"plus_mean_of\": [lengths], "
                          "\"scale\": number}")
    pts = est.get("through")
    if not isinstance(pts, list) or len(pts) < 2:
        raise fail(where + ".through", f"got {pts!r}, expected a list of at least 2 points")
    for p in pts:
        check_point(where + ".through", p, landmarks)
    plus = est.get("plus_mean_of", [])
    if not isinstance(plus, list) or any(k not in earlier for k in plus):
        raise fail(where + ".plus_mean_of", f"got {plus!r}, expected names of length measurements defined earlier")
    scale = est.get("scale")
    if not isinstance(scale, (int, float)) or isinstance(scale, bool) or not 0.5 <= scale <= 2.0:
        raise fail(where + ".scale", f"got {scale!r}, expected a number between 0.5 and 2")


def bmi(m: dict, chunk: Chunk) -> tuple:
    """Body-mass index (kg/m²) from the measurements ``m["mass"]`` and ``m["stature"]``."""
    val = chunk.values[m["mass"]] / chunk.values[m["stature"]] ** 2
    return val, None, _needs_stature(m, val)


def _needs_stature(m: dict, val: np.ndarray) -> list:
    # A NaN stature (not upright) would poison mass and BMI: say so rather than guess.
    return [f"needs {m['stature']!r}, which is undefined for this body" if np.isnan(x) else None
            for x in np.asarray(val, dtype=float)]


def _check_earlier(*fields: str):
    """A check that each of ``fields`` names a measurement defined earlier in the set."""
    def check(where: str, m: dict, landmarks, earlier: set) -> None:
        for key in fields:
            if m.get(key) not in earlier:
                raise fail(where + f" field {key!r}", f"got {m.get(key)!r}, expected the name of a measurement "
                                                       "defined earlier in the file")
    return check


@numba.njit(cache=True, nogil=True)
def _volume_area_kernel(v, f0, f1, f2, vol, area):
    """Per body n of (N, V, 3): vol[n] = sum a.(e1 x e2) / 6, area[n] = sum |e1 x e2| / 2 over the
    faces in order (sequential sums: the same rounding as ``np.cumsum(...)[-1]``; no fastmath)."""
    for n in range(v.shape[0]):
        sv = 0.0
        sa = 0.0
        for k in range(len(f0)):
            a, b, c = f0[k], f1[k], f2[k]
            ax, ay, az = v[n, a, 0], v[n, a, 1], v[n, a, 2]
            e1x, e1y, e1z = v[n, b, 0] - ax, v[n, b, 1] - ay, v[n, b, 2] - az
            e2x, e2y, e2z = v[n, c, 0] - ax, v[n, c, 1] - ay, v[n, c, 2] - az
            nx = e1y * e2z - e1z * e2y
            ny = e1z * e2x - e1x * e2z
            nz = e1x * e2y - e1y * e2x
            sa += np.sqrt(nx * nx + ny * ny + nz * nz)
            sv += ax * nx + ay * ny + az * nz
        area[n] = 0.5 * sa
        vol[n] = sv / 6.0


def volume_and_area(chunk: Chunk) -> tuple[np.ndarray, np.ndarray]:
    """Capped volume (N,) and surface area (N,) from one cross product per face, cached per chunk.

    With n = (b - a) x (c - a): area = |n| / 2 and a.n = a.(b x c), the divergence-theorem
    tetrahedron (x6). Same result as ``mesh.geometry.capped_volume``/``surface_area``, but
    written per component: ``np.cross`` on (N, F, 3) costs several times more.
    """
    if "volume_area" in chunk.cache:
        return chunk.cache["volume_area"]
    v, geo = chunk.vertices, chunk.topology
    f0, f1, f2 = (np.ascontiguousarray(geo.faces[:, k]) for k in range(3))
    n = len(v)
    vol, area = np.empty(n), np.empty(n)
    # One body at a time: its (F,) temporaries stay in cache (2x faster than (N, F) arrays).
    # Summed in the order numpy summed the (N, F) gathers (column-major, so sequential; one
    # body: pairwise), to keep every bit of the earlier values.
    if n == 1:   # one body: numpy's pairwise sums, as before
        x, y, z = (np.ascontiguousarray(v[0, :, k]) for k in range(3))
        ax, ay, az = x[f0], y[f0], z[f0]
        e1x, e1y, e1z = x[f1] - ax, y[f1] - ay, z[f1] - az
        e2x, e2y, e2z = x[f2] - ax, y[f2] - ay, z[f2] - az
        nx = e1y * e2z - e1z * e2y
        ny = e1z * e2x - e1x * e2z
        nz = e1x * e2y - e1y * e2x
        area[0] = 0.5 * np.sum(np.sqrt(nx * nx + ny * ny + nz * nz))
        vol[0] = np.sum(ax * nx + ay * ny + az * nz) / 6.0
    else:        # a batch: one compiled pass a body, summed in order as numpy's (N, F) sums did
        _volume_area_kernel(np.ascontiguousarray(v), f0, f1, f2, vol, area)
    if geo.loops:
        vol = vol + capped_volume(v, np.zeros((0, 3), dtype=np.int64), geo.loops)
    chunk.cache["volume_area"] = (vol, area)
    return vol, area


# --- the registry ----------------------------------------------------------------------------

METHODS: dict[str, Method] = {
    "loop": Method(loop_girth, "m", check_loop, topology_free=False),
    "slice": Method(slice_girth, "m", check_slice),
    "distance": Method(distance, "m", check_distance),
    "path": Method(path_length, "m", check_path),
    "volume": Method(volume, "m^3"),
    "surface_area": Method(surface_area, "m^2"),
    "mass": Method(mass, "kg", check_mass),
    "bmi": Method(bmi, "kg/m^2", _check_earlier("mass", "stature")),
    "top": Method(part_top, "m", check_top),
}


def register_method(name: str, compute: Callable[[dict, Chunk], tuple], unit: str,
                    check: Callable[[str, dict, dict, set], None] | None = None, *,
                    topology_free: bool = True, replace: bool = False) -> None:
    """Add a method under ``name`` (the JSON's ``"method"``); ``compute`` and ``check`` have the
    signatures of the module docstring, ``unit`` is the SI unit of its values ("m", "kg", ...).

    Sets loaded afterwards may use it; an existing name is refused unless ``replace``.
    """
    if not isinstance(name, str) or not name:
        raise MeasurementError(f"method name {name!r}: expected a non-empty string")
    if name in METHODS and not replace:
        raise MeasurementError(f"method {name!r} is already registered (known: {', '.join(METHODS)}); "
                               "pass replace=True to replace it")
    if not callable(compute) or (check is not None and not callable(check)):
        raise MeasurementError(f"method {name!r}: compute and check must be functions "
                               "(compute(m, chunk), check(where, m, landmarks, earlier))")
    METHODS[name] = Method(compute, unit, check, topology_free)


def known_methods() -> str:
    """The registered method names, for messages."""
    return ", ".join(METHODS)


def template_vertices(m: dict) -> list:
    """The template vertex ids a measurement uses directly: the ``vertices`` field of a
    template-only method (a loop's ring), and the inline joints of a joint axis; else none."""
    method = METHODS.get(m["method"])
    ids = list(m.get("vertices", [])) if method is not None and not method.topology_free else []
    return ids + [i for p in inline_points([m.get("normal"), m.get("axis")]) for i in p["vertices"]]
