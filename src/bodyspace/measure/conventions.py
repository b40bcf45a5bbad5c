"""Input conventions of a body mesh, recognised from its geometry: unit, up axis, winding, vertex order.

bodyspace works in metres, +Y up, faces wound counter-clockwise seen from outside, vertices in
the order of the measurement set's landmarks. A user's mesh can be off by any of these
conventions, and each one makes the measurements wrong without an error (issue 12 §3): a mesh in
millimetres measured a stature of 170,988 cm, a Z-up mesh a stature of 0, reversed winding a
mass of -57 kg, the right topology in another vertex order a waist of 44 cm. Each is recognised
here from the geometry alone, cheaply, and either refused with the fix or corrected when the
caller says which convention the mesh uses (``to_internal``):

- **unit** (``body_extent``, ``plausible_units``): the largest side of the bounding box of a
  human body is 0.5-3.2 m in any pose; the units that bring the mesh into that range (m, cm,
  mm, in) are the candidates, the one that gives the body an adult's size first (sqrt of the
  surface area; centimetres and inches overlap, so both are named then).
- **winding** (``signed_volume``): the divergence-theorem volume is negative when the faces are
  wound inwards. Scale-free test: volume / area^1.5 is about +0.02 for a closed body; below
  ``-INWARD_VOLUME_RATIO`` the faces are reversed. An open scan still gives the sign (the
  origin is the centroid).
- **vertex order** (``layout_checks``): the landmarks of the set in use (any topology, a user
  landmark file too) must land on the body parts their names say. The checks are intrinsic (no
  frame, unit or pose enters): pose-invariant lengths between joint centres relative to the
  body's size (the square root of its surface area), left and right limb segments of equal
  length, surface landmarks near their limb segment (the thigh point near the hip-knee segment,
  the acromion near the shoulder joint) and at the right place along it. On correct bodies (39
  library poses, foreign phenotypes, remeshed) none fails; with the vertices in another order
  most do (docs/measurements.md, "Input conventions").
- **up axis** (``up_axis``): with the layout right, the feet→head direction (ankle→hip joints,
  crotch→neck, neck→head top, summed) is within 26° of +Y in every library pose (bend_forward
  is the worst); its nearest coordinate axis (±x, ±y, ±z) within ``UP_AXIS_MAX_ANGLE`` is the
  mesh's up. Facing is not needed: every measurement is invariant under a turn about the up axis.

Costs (benchmarks/bench_conventions.py, a shared 2-core machine under load): the whole door
for one template mesh (``prepare``) 8 ms, 6-8 % of measuring that mesh (the signed volume and
area, one cross product per face, 2.9 ms; landmarks, layout and up axis 3.4 ms). The batch
door of ``evaluate`` checks only the unit of every body and the winding of the first body (the
faces are shared): 3.6 % of the CPU time of measuring 1,000 bodies. Layout and up axis are
checked at the doors where a user's mesh comes in (``prepare``: ``bodyspace measure``), not in
the batch path, where the bodies are decoded from a model of the set's own topology and frame.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numba
import numpy as np

from bodyspace.errors import MeasurementError
from bodyspace.measure.definitions import DEFAULT_PATH, MeasurementSet
from bodyspace.measure.points import format_point, point
from bodyspace.mesh.floor import FLOOR_CUT_SIGMAS, FLOOR_ROUNDS, mesh_floor, sheet_width
from bodyspace.mesh.geometry import face_areas
from bodyspace.mesh.topology import face_component_roots
from bodyspace.units import UNITS as _QUANTITY_UNITS

# The largest side of a human body's bounding box, metres (a toddler lying down .. a very tall
# adult with the arms up): outside it the mesh is in other units, or garbage.
# (A 2.2 m tall person with the arms overhead is 2.97 m.)
BODY_EXTENT_M = (0.5, 3.2)
TYPICAL_STATURE_M = 1.7
# sqrt(surface area), metres: the pose-invariant size of a body. The template's mean body is
# 1.27 m; the bodies at the population's edges 0.86-1.68 m; a toddler (0.5 m² of skin) 0.7 m.
TYPICAL_SIZE_M = 1.27
BODY_SIZE_M = (0.4, 2.2)
# The largest side of the bounding box of a body's landmarks, metres (a crouching child's ..
# a tall adult's with the arms up; the template's 1.6 m): the landmarks still give the body's size
# when the mesh carries a floor or objects that make the whole mesh fit no unit.
LANDMARK_EXTENT_M = (0.3, 3.2)
TYPICAL_LANDMARK_EXTENT_M = 1.6
# Units a mesh may come in, metres per unit (the names are the length units of bodyspace.units).
MESH_UNITS = {u: _QUANTITY_UNITS["length"][u] for u in ("m", "cm", "mm", "in")}
_UNIT_WORDS = {"m": "metres", "cm": "centimetres", "mm": "millimetres", "in": "inches"}
# Scale mistakes that are no unit a mesh is saved in, named only in messages.
_OTHER_FACTORS = {"km": 1000.0, "μm": 1e-6}

UP_AXES = ("y", "-y", "x", "-x", "z", "-z")
AXIS_VECTORS = {"x": (1, 0, 0), "-x": (-1, 0, 0), "y": (0, 1, 0), "-y": (0, -1, 0), "z": (0, 0, 1), "-z": (0, 0, -1)}
# Rotations taking each up axis to +Y (proper rotations: no mirror). "z" is Blender's convention,
# the person facing -Y, which becomes +Z (our front); "-y" (upside down) turns about X.
UP_ROTATIONS = {
    "y": np.eye(3),
    "-y": np.diag([1.0, -1.0, -1.0]),
    "z": np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]]),
    "-z": np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]]),
    "x": np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]),
    "-x": np.array([[0.0, 1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]),
}
# The feet→head direction is within 26° of +Y in every library pose; an axis within this angle
# is the mesh's up. Further from every axis, the body lies tilted: no convention, and the
# measurements that need an upright body say so themselves (the ``upright`` condition).
UP_AXIS_MAX_ANGLE = 40.0
# Signed volume / area^1.5 below this: faces wound inwards (a closed body: about +0.02).
INWARD_VOLUME_RATIO = 0.002

NECK = ["neck_front", "neck_back"]
# Feet→head segments (from, to), summed for the up direction; those whose names a set has.
UP_SEGMENTS = (("ankle_joint_l", "hip_joint_l"), ("ankle_joint_r", "hip_joint_r"),
               ("crotch", NECK), (NECK, "head_top"))

# The layout checks: where the landmarks of a correctly ordered body are, relative to each
# other, whatever the pose, frame and unit (``layout_checks``). "{s}" is l and r. Bounds from
# 390 bodies (10 phenotypes incl. 6 at the population's edges x 39 library poses): the observed
# range widened to 0.6x its minimum and 1.6x its maximum (twice the maximum for distances that
# start at zero; left/right within 0.15 in log, a 16 % difference, 5x the largest seen, 0.25 for
# hip->crotch), so real people and hand-placed landmark files fit. Lengths are in units of the
# body's size, sqrt(surface area) (0.86-1.68 m on those bodies).
#   ("length", a, b, lo, hi): |a - b| / size in [lo, hi]
#   ("mirror", a, b, -, hi): |log(|a_l - b_l| / |a_r - b_r|)| <= hi (left and right limbs alike)
#   ("near", p, (a, b), -, hi): distance of p from the segment a-b / size <= hi
#   ("along", p, (a, b), lo, hi): where p projects on a→b, as a fraction of it, in [lo, hi]
LAYOUT_CHECKS = (
    ("length", "hip_joint_{s}", "knee_joint_{s}", 0.14, 0.60),
    ("length", "knee_joint_{s}", "ankle_joint_{s}", 0.13, 0.61),
    ("length", "shoulder_joint_{s}", "elbow_joint_{s}", 0.093, 0.36),
    ("length", "elbow_joint_{s}", "wrist_joint_{s}", 0.086, 0.31),
    ("length", "bust_{s}", "shoulder_joint_{s}", 0.08, 0.43),
    ("length", "hip_joint_{s}", "crotch", 0.057, 0.21),
    ("length", "crotch", NECK, 0.23, 0.79),
    ("length", NECK, "head_top", 0.11, 0.40),
    ("length", "shoulder_joint_l", "shoulder_joint_r", 0.13, 0.52),
    ("length", "hip_joint_l", "hip_joint_r", 0.088, 0.31),
    ("length", "shoulder_l", "shoulder_r", 0.099, 0.57),
    ("near", "shoulder_{s}", ("shoulder_joint_{s}", "shoulder_joint_{s}"), None, 0.10),
    ("near", "thigh_{s}", ("hip_joint_{s}", "knee_joint_{s}"), None, 0.13),
    ("near", "calf_{s}", ("knee_joint_{s}", "ankle_joint_{s}"), None, 0.14),
    ("near", "underbust_front", ("crotch", NECK), None, 0.23),
    ("near", "neck_front", ("neck_back", "neck_back"), None, 0.23),
    ("along", "thigh_{s}", ("hip_joint_{s}", "knee_joint_{s}"), 0.0, 0.7),
    ("along", "calf_{s}", ("knee_joint_{s}", "ankle_joint_{s}"), 0.1, 0.8),
    ("along", "underbust_front", ("crotch", NECK), 0.2, 0.8),
    ("mirror", "hip_joint_{s}", "knee_joint_{s}", None, 0.15),
    ("mirror", "knee_joint_{s}", "ankle_joint_{s}", None, 0.15),
    ("mirror", "shoulder_joint_{s}", "elbow_joint_{s}", None, 0.15),
    ("mirror", "elbow_joint_{s}", "wrist_joint_{s}", None, 0.15),
    ("mirror", "thigh_{s}", "knee_joint_{s}", None, 0.15),
    ("mirror", "calf_{s}", "ankle_joint_{s}", None, 0.15),
    ("mirror", "hip_joint_{s}", "crotch", None, 0.25),
)
# The layout is wrong when more than this fraction of the possible checks fail (and at least
# two): correct bodies failed none of 37, 300 bodies in another vertex order 14-32.
LAYOUT_FAIL_FRACTION = 0.25
LAYOUT_MIN_CHECKS = 3


@dataclass(frozen=True)
class Finding:
    """One convention a mesh is off by: what its geometry shows, and the fix.

    what: a clause for people ("its bounding box is 1,712 across: millimetres, not metres").
    fix: the argument that fixes it, {"units": "mm"}, {"up": "z"}, {"flip_winding": True}; a
        tuple of values is alternatives, most likely first ({"units": ("in", "cm")});
        a value of None (False for flip_winding) means "leave the given one out";
        {"landmarks": True}: a landmark set of this vertex order; {}: no automatic fix.
    """

    what: str
    fix: dict = field(default_factory=dict)


@dataclass(frozen=True)
class Conventions:
    """What one mesh's geometry says about its conventions (``inspect``).

    extent: the largest side of its bounding box, mesh units.
    units: the units that make it a human-sized body, most likely first (("m",): metres).
    volume_ratio: signed volume / area^1.5 (scale-free; a closed body about +0.02, negative:
        faces wound inwards). signed_volume: in cubic metres of ``units[0]`` (or mesh units).
    layout_checks: how many layout checks the set's landmark names allow.
    layout_failures: those that fail, one clause each.
    up: the axis ("y", "-z", ...) the feet→head direction is nearest, None when unknown (too
        few landmarks, a wrong layout, or no axis within ``UP_AXIS_MAX_ANGLE``).
    up_angle: degrees between the feet→head direction and that axis (NaN when unknown).
    size: the square root of its surface area, mesh units.
    landmark_extent: the largest side of the bounding box of the set's landmarks, mesh units
        (a body's own size even when the mesh carries a floor or objects besides it).
    """

    extent: float
    units: tuple[str, ...]
    signed_volume: float
    volume_ratio: float
    layout_checks: int
    layout_failures: tuple[str, ...]
    up: str | None
    up_angle: float
    size: float
    landmark_extent: float = float("nan")

    @property
    def layout_wrong(self) -> bool:
        n, bad = self.layout_checks, len(self.layout_failures)
        return n >= LAYOUT_MIN_CHECKS and bad >= 2 and bad > LAYOUT_FAIL_FRACTION * n


# ------------------------------------------------------------------------------ unit

def body_extent(vertices: np.ndarray) -> np.ndarray:
    """The largest side of the bounding box (...,) of bodies (..., V, 3), in their units."""
    v = np.asarray(vertices, dtype=float)
    if v.ndim == 3 and v.shape[-1] == 3 and v.shape[1] > 0:
        # A batch: one compiled pass a body (six strided numpy reductions cost 4x more).
        out = np.empty(len(v))
        _extent_kernel(np.ascontiguousarray(v), out)
        return out
    # Per coordinate: numpy reduces an (..., V, 3) array over V 15-20x slower than each
    # coordinate's strided (..., V) view (1 ms against 60 us a body).
    with np.errstate(over="ignore", invalid="ignore"):
        return np.max([v[..., k].max(axis=-1) - v[..., k].min(axis=-1) for k in range(3)], axis=0)


@numba.njit(cache=True, nogil=True)
def _extent_kernel(v, out):
    """``body_extent`` of bodies (N, V, 3) into out (N,): NaN where a coordinate is NaN (as numpy's
    max and min propagate it), inf - inf is NaN too."""
    for n in range(v.shape[0]):
        lo0, lo1, lo2 = v[n, 0, 0], v[n, 0, 1], v[n, 0, 2]
        hi0, hi1, hi2 = lo0, lo1, lo2
        nan = False
        for i in range(v.shape[1]):
            x, y, z = v[n, i, 0], v[n, i, 1], v[n, i, 2]
            if x != x or y != y or z != z:
                nan = True
            lo0, hi0 = min(lo0, x), max(hi0, x)
            lo1, hi1 = min(lo1, y), max(hi1, y)
            lo2, hi2 = min(lo2, z), max(hi2, z)
        d0, d1, d2 = hi0 - lo0, hi1 - lo1, hi2 - lo2
        if nan or d0 != d0 or d1 != d1 or d2 != d2:
            out[n] = np.nan
        else:
            out[n] = max(d0, max(d1, d2))


def plausible_units(extent: float, size: float | None = None) -> tuple[str, ...]:
    """The ``MESH_UNITS`` in which a mesh is a human body, most likely first; () when none.

    extent: the largest side of its bounding box; size: sqrt of its surface area (same units,
    pose-invariant), or None (the batch door: the extent alone). In a fitting unit the extent is
    within ``BODY_EXTENT_M`` and the size within ``BODY_SIZE_M`` (a speck with one stray vertex
    far away fits no unit). Most likely: the size nearest the mean body's ``TYPICAL_SIZE_M``
    (without a size: the extent nearest an adult's 1.7 m). Centimetres and inches overlap (a
    67 cm child or a 170 cm adult): both are returned then, and the size orders them.
    """
    lo, hi = BODY_EXTENT_M
    fits = [u for u, f in MESH_UNITS.items() if np.isfinite(extent) and lo <= extent * f <= hi]
    if size is None or not np.isfinite(size) or size <= 0:
        return tuple(sorted(fits, key=lambda u: abs(np.log(extent * MESH_UNITS[u] / TYPICAL_STATURE_M))))
    fits = [u for u in fits if BODY_SIZE_M[0] <= size * MESH_UNITS[u] <= BODY_SIZE_M[1]]
    return tuple(sorted(fits, key=lambda u: abs(np.log(size * MESH_UNITS[u] / TYPICAL_SIZE_M))))


def check_body_scale(vertices: np.ndarray, mesh_name: str = "the measured mesh") -> None:
    """Raise MeasurementError unless every body (vertices (..., V, 3), finite) is human-sized in
    metres: the largest side of its bounding box within ``BODY_EXTENT_M``. A mesh in mm or cm
    would otherwise measure 1000x or 100x off (or 0.0 everywhere) without a word. The batch
    door of ``evaluate``: one pass over the vertices."""
    v = vertices.reshape((-1,) + vertices.shape[-2:])
    extent = body_extent(v)
    lo, hi = BODY_EXTENT_M
    bad = np.flatnonzero(~((extent >= lo) & (extent <= hi)))
    if not bad.size:
        return
    i, size = int(bad[0]), float(extent[bad[0]])
    which = f"body {i} of {mesh_name}" if len(v) > 1 else mesh_name
    if not np.isfinite(size) or size == 0:
        raise MeasurementError(f"{which}: its bounding box is {size:g} m across; expected a human body in metres "
                               f"({lo:g}-{hi:g} m)")
    raise MeasurementError(f"{which}: its bounding box is {size:.3g} m across, a human body's is {lo:g}-{hi:g} m; "
                           f"{_scale_advice(size)}")


def _scale_advice(size: float) -> str:
    """'the mesh is 1000x too large: is it in mm? scale it to metres (multiply by 0.001)'."""
    units = plausible_units(size)
    if units:
        unit = units[0]
        shown = 1 / MESH_UNITS[unit]
        return (f"the mesh is {shown:.4g}x too {'large' if shown > 1 else 'small'}: is it in "
                f"{'inches' if unit == 'in' else unit}? scale it to metres (multiply by {MESH_UNITS[unit]:g})")
    factor = size / TYPICAL_STATURE_M
    unit = min(_OTHER_FACTORS, key=lambda u: abs(np.log(factor / (1 / _OTHER_FACTORS[u]))))
    if abs(np.log(factor * _OTHER_FACTORS[unit])) < np.log(2.0):
        return (f"the mesh is {max(factor, 1 / factor):.4g}x too {'large' if factor > 1 else 'small'}: is it in "
                f"{unit}? scale it to metres (multiply by {_OTHER_FACTORS[unit]:g})")
    return f"the mesh is {max(factor, 1 / factor):.4g}x too {'large' if factor > 1 else 'small'}; scale it to metres"


# ------------------------------------------------------------------------------ winding

def signed_volume(vertices: np.ndarray, faces: np.ndarray) -> tuple[float, float]:
    """(signed volume, surface area) of one mesh (V, 3), (F, 3), in its units.

    The divergence theorem with the origin at the vertex centroid (so an open scan's missing
    caps cost little and the sign still holds): positive when the faces are wound
    counter-clockwise seen from outside. One cross product per face, per component.
    """
    v = np.asarray(vertices, dtype=float)
    f = np.asarray(faces)
    x, y, z = (v[:, k] - v[:, k].mean() for k in range(3))     # contiguous copies, origin at the centroid
    f0, f1, f2 = (np.ascontiguousarray(f[:, k]) for k in range(3))
    ax, ay, az = x[f0], y[f0], z[f0]
    e1x, e1y, e1z = x[f1] - ax, y[f1] - ay, z[f1] - az
    e2x, e2y, e2z = x[f2] - ax, y[f2] - ay, z[f2] - az
    nx = e1y * e2z - e1z * e2y
    ny = e1z * e2x - e1x * e2z
    nz = e1x * e2y - e1y * e2x
    volume = float(np.sum(ax * nx + ay * ny + az * nz)) / 6.0
    area = 0.5 * float(np.sum(np.sqrt(nx * nx + ny * ny + nz * nz)))
    return volume, area


def winding_inwards(vertices: np.ndarray, faces: np.ndarray) -> tuple[bool, float]:
    """(faces wound inwards?, volume / area^1.5) of one mesh (V, 3), (F, 3)."""
    volume, area = signed_volume(vertices, faces)
    ratio = volume / area ** 1.5 if area > 0 else 0.0
    return ratio < -INWARD_VOLUME_RATIO, ratio


def check_winding(vertices: np.ndarray, faces: np.ndarray, mesh_name: str = "the measured mesh") -> None:
    """Raise MeasurementError if the faces of the bodies (vertices (V, 3) or (N, V, 3)) are wound
    inwards (negative volume and mass otherwise). The batch door of ``evaluate``: the first body
    only, since the bodies of a batch share the faces (about 0.5 ms)."""
    v = np.asarray(vertices, dtype=float)
    first = v if v.ndim == 2 else v[0]
    inwards, ratio = winding_inwards(first, faces)
    if inwards:
        volume, _ = signed_volume(first, faces)
        which = mesh_name if v.ndim == 2 or len(v) == 1 else f"body 0 of {mesh_name}"
        raise MeasurementError(f"{which}: its faces are wound inwards (signed volume {volume:.3g} m³, expected "
                               "positive: counter-clockwise seen from outside); reverse every face "
                               "(faces[:, ::-1], or to_internal(..., flip_winding=True))")


# ------------------------------------------------------------------------------ landmarks

def landmark_points(mset: MeasurementSet, vertices: np.ndarray) -> dict[str, np.ndarray]:
    """The set's landmark points, name → (1, 3), of one body (V, 3) (the ``points`` grammar's
    batch shape, N = 1)."""
    v = np.asarray(vertices, dtype=float)
    return {name: (w @ v[ids])[None] for name, (ids, w) in mset.landmarks.items()}


def _names(spec) -> list[str]:
    return [spec] if isinstance(spec, str) else list(spec)


def _side(spec, s: str):
    return spec.format(s=s) if isinstance(spec, str) else [n.format(s=s) for n in spec]


def _expand(check: tuple) -> list[tuple]:
    """One layout check with "{s}" → one per side (a mirror check stays one, over both sides)."""
    kind, a, b, lo, hi = check
    text = repr((a, b))
    if kind == "mirror" or "{s}" not in text:
        return [check]
    side = (lambda x, s: tuple(_side(y, s) for y in x)) if isinstance(b, tuple) else _side
    return [(kind, _side(a, s), side(b, s), lo, hi) for s in ("l", "r")]


def _label(spec) -> str:
    return format_point(spec) if isinstance(spec, (str, list)) else "-".join(format_point(x) for x in spec)


def layout_values(points: dict[str, np.ndarray], size: float, metres_per_unit: float | None = None
                  ) -> list[tuple[tuple, float, str]]:
    """The ``LAYOUT_CHECKS`` the landmark names allow, evaluated on one body.

    points: name → (1, 3) landmark points; size: the body's size, sqrt(surface area), same unit;
    metres_per_unit: the mesh's unit if known (the clauses then say cm), else None.
    Returns (check, value, clause) per check run: ``value`` is what the check bounds (a length
    over size, |log| of a left/right ratio, a fraction along a segment) and ``clause`` says,
    for people, what was found and what was expected.
    """
    have = set(points)
    out = []

    def length(x: float, *more: float) -> str:   # mesh lengths for people
        if metres_per_unit is None:
            return "-".join(f"{y:.3g}" for y in (x,) + more) + " (mesh units)"
        return "-".join(f"{100 * metres_per_unit * y:.3g}" for y in (x,) + more) + " cm"

    for check in (c for raw in LAYOUT_CHECKS for c in _expand(raw)):
        kind, a, b, lo, hi = check
        if kind == "mirror":
            specs = [_side(a, s) for s in "lr"] + [_side(b, s) for s in "lr"]
        else:
            specs = [a] + (list(b) if isinstance(b, tuple) else [b])
        if not all(set(_names(sp)) <= have for sp in specs):
            continue
        if kind == "length":
            got = float(np.linalg.norm(point(a, points) - point(b, points))) / size
            clause = f"{_label(a)} is {length(got * size)} from {_label(b)}, expected {length(lo * size, hi * size)}"
        elif kind == "mirror":
            left = float(np.linalg.norm(point(_side(a, "l"), points) - point(_side(b, "l"), points)))
            right = float(np.linalg.norm(point(_side(a, "r"), points) - point(_side(b, "r"), points)))
            got = abs(float(np.log(left / right))) if left > 0 and right > 0 else float("inf")
            clause = (f"{_label(_side(a, 'l'))}-{_label(_side(b, 'l'))} is {length(left)} but "
                      f"{_label(_side(a, 'r'))}-{_label(_side(b, 'r'))} {length(right)}, expected within "
                      f"{np.expm1(hi):.0%} of each other")
        else:
            p, s0, s1 = point(a, points)[0], point(b[0], points)[0], point(b[1], points)[0]
            seg = s1 - s0
            t = float(np.dot(p - s0, seg) / np.dot(seg, seg)) if np.dot(seg, seg) > 0 else 0.0
            if kind == "near":
                got = float(np.linalg.norm(p - (s0 + np.clip(t, 0.0, 1.0) * seg))) / size
                where = _label(b[0]) if b[0] == b[1] else f"the segment {_label(b[0])}-{_label(b[1])}"
                clause = f"{_label(a)} is {length(got * size)} from {where}, expected within {length(hi * size)}"
            else:
                got = t
                clause = f"{_label(a)} lies at {t:.2f} of {_label(b[0])}→{_label(b[1])}, expected {lo:g}-{hi:g}"
        out.append((check, got, clause))
    return out


def layout_checks(points: dict[str, np.ndarray], size: float, metres_per_unit: float | None = None
                  ) -> tuple[int, list[str]]:
    """Run the ``LAYOUT_CHECKS`` the landmark names allow on one body (``layout_values``).
    Returns (number of checks run, the clause of each failed one)."""
    values = layout_values(points, size, metres_per_unit)
    failed = [clause for (kind, _, _, lo, hi), got, clause in values
              if not ((lo is None or got >= lo) and got <= hi)]
    return len(values), failed


def up_vector(points: dict[str, np.ndarray]) -> np.ndarray | None:
    """The body's feet→head direction (3,), unit, in the mesh's frame: the sum of the
    ``UP_SEGMENTS`` the names of ``points`` (name → (1, 3)) allow; None when none."""
    have = set(points)
    u = np.zeros(3)
    for a, b in UP_SEGMENTS:
        if set(_names(a)) | set(_names(b)) <= have:
            u += (point(b, points) - point(a, points))[0]
    norm = np.linalg.norm(u)
    return u / norm if norm > 0 else None


def up_axis(points: dict[str, np.ndarray]) -> tuple[str | None, float]:
    """The coordinate axis the body's feet→head direction is nearest, and the angle (degrees).

    points: name → (1, 3) landmark points of a correctly ordered body. The direction is the sum
    of the ``UP_SEGMENTS`` the names allow (legs, trunk, head); (None, NaN) when none, or when
    no axis is within ``UP_AXIS_MAX_ANGLE``.
    """
    u = up_vector(points)
    if u is None:
        return None, float("nan")
    best = max(UP_AXES, key=lambda k: float(np.dot(u, AXIS_VECTORS[k])))
    angle = float(np.degrees(np.arccos(np.clip(np.dot(u, AXIS_VECTORS[best]), -1.0, 1.0))))
    return (best, angle) if angle <= UP_AXIS_MAX_ANGLE else (None, angle)


# ------------------------------------------------------------------------------ one mesh

def inspect(vertices: np.ndarray, faces: np.ndarray, mset: MeasurementSet) -> Conventions:
    """Everything the geometry of one mesh (V, 3), (F, 3) says about its conventions, for the
    landmarks of ``mset`` (whose vertex ids must fit the mesh: ``evaluate.check_compatible``)."""
    v = np.asarray(vertices, dtype=float)
    extent = float(body_extent(v))
    volume, area = signed_volume(v, faces)
    units = plausible_units(extent, np.sqrt(area))
    ratio = volume / area ** 1.5 if area > 0 else 0.0
    points = landmark_points(mset, v)
    spread = float(body_extent(np.concatenate(list(points.values())))) if points else float("nan")
    size, per_unit = np.sqrt(area), MESH_UNITS[units[0]] if units else None
    if not units and _landmark_unit(spread) is not None:
        # No unit fits the whole mesh but the landmarks are a body's size: other geometry joined
        # to it (a floor) inflates its area, so the layout is judged at the landmarks' own size.
        size, per_unit = spread * TYPICAL_SIZE_M / TYPICAL_LANDMARK_EXTENT_M, MESH_UNITS[_landmark_unit(spread)]
    ran, failed = layout_checks(points, size, per_unit) if area > 0 else (0, [])
    up, angle = up_axis(points)
    conv = Conventions(extent, units, volume * MESH_UNITS[units[0]] ** 3 if units else volume, ratio, ran,
                       tuple(failed), up, angle, float(np.sqrt(area)), spread)
    if conv.layout_wrong:   # landmarks on the wrong body parts say nothing about the up axis
        conv = replace(conv, up=None, up_angle=float("nan"))
    return conv


def to_internal(vertices: np.ndarray, faces: np.ndarray, units: str = "m", up: str = "y",
                flip_winding: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """A mesh (V, 3), (F, 3) in ``units`` with ``up`` as its up axis, in bodyspace's conventions:
    metres, +Y up (a proper rotation; "z" is taken as Blender's, facing -Y, which becomes +Z),
    and with ``flip_winding`` every face reversed. Returns new (vertices (V, 3), faces (F, 3))."""
    if units not in MESH_UNITS:
        raise MeasurementError(f"units={units!r}; expected one of {', '.join(MESH_UNITS)}")
    if up not in UP_ROTATIONS:
        raise MeasurementError(f"up={up!r}; expected one of {', '.join(UP_AXES)}")
    v = (np.asarray(vertices, dtype=float) * MESH_UNITS[units]) @ UP_ROTATIONS[up].T
    f = np.asarray(faces)
    return v, (f[:, ::-1].copy() if flip_winding else f)


# Default fix words: the library's (keyword arguments of ``prepare``/``to_internal``). The CLI
# passes its own (flags). A template's "{}" is the value; "landmarks" is a whole phrase.
LIBRARY_WORDS = {"units": "units={!r}", "up": "up={!r}", "flip_winding": "flip_winding=True",
                 "landmarks": "a landmark set for this mesh's vertex order (load_landmarks, with_landmarks), "
                              "or the mesh in the set's vertex order"}


def find_problems(conv: Conventions, mset: MeasurementSet, units: str | None = None, up: str | None = None,
                  flip_winding: bool = False) -> list[Finding]:
    """The conventions a mesh is off by, given what the caller said about it (``units``, ``up``,
    ``flip_winding``; None/False: nothing said, the defaults m, y, no flip). A claim the geometry
    contradicts is a finding too (its fix: the right value, or leaving the claim out). A units
    fix may be a tuple of alternatives, most likely first (centimetres or inches)."""
    found = []
    lo, hi = BODY_EXTENT_M
    said = units or "m"
    extra = _extra_geometry(conv, units)
    if said not in conv.units and extra is not None:
        found.append(Finding(extra))
    elif said not in conv.units:
        if units is not None and not conv.units:
            # No unit fits (the whole mesh's size): say what the given unit makes of it, never
            # ask about another unit the user did not give unless the landmarks point to it.
            f = MESH_UNITS[units]
            lu = _landmark_unit(conv.landmark_extent)
            hint = (f"; its landmarks span {conv.landmark_extent * MESH_UNITS[lu]:.3g} m in {_UNIT_WORDS[lu]}, a "
                    "body's size" if lu is not None and lu != units else "")
            found.append(Finding(f"in {_UNIT_WORDS[units]}, the unit given, it is {conv.extent * f:.3g} m across with "
                                 f"{(conv.size * f) ** 2:.3g} m² of surface, a human body's is {lo:g}-{hi:g} m and "
                                 f"{BODY_SIZE_M[0] ** 2:.2g}-{BODY_SIZE_M[1] ** 2:.2g} m²{hint}",
                                 {"units": lu} if lu is not None and lu != units else {}))
        elif units is not None and conv.units:
            metres = conv.extent * MESH_UNITS[units]
            fix = {"units": None} if conv.units[0] == "m" else {"units": conv.units}
            found.append(Finding(f"in {_UNIT_WORDS[units]} it would be {metres:.3g} m across, a human body is "
                                 f"{lo:g}-{hi:g} m; it looks like {_unit_list(conv.units)}", fix))
        elif conv.units:
            found.append(Finding(f"its bounding box is {conv.extent:,.4g} across: {_unit_list(conv.units)}, not "
                                 f"metres (a human body is {lo:g}-{hi:g} m)", {"units": conv.units}))
        elif not np.isfinite(conv.extent) or conv.extent == 0:
            found.append(Finding(f"its bounding box is {conv.extent:g} across; expected a human body"))
        elif plausible_units(conv.extent):
            # A body's extent but not a body's surface: no scale fixes that (the advice was "the
            # mesh is 1x too small: multiply by 1" for a scrambled vertex order).
            u = plausible_units(conv.extent)[0]
            metres = MESH_UNITS[u]
            found.append(Finding(f"its bounding box is {conv.extent * metres:.3g} m across in {_UNIT_WORDS[u]}, but "
                                 f"its surface area is {(conv.size * metres) ** 2:.3g} m², a human body's is "
                                 f"{BODY_SIZE_M[0] ** 2:.2g}-{BODY_SIZE_M[1] ** 2:.2g} m²: its faces join vertices "
                                 "far apart (vertices in another order than its faces expect?) or it has almost "
                                 "no faces"))
        else:
            found.append(Finding(f"its bounding box is {conv.extent:.3g} across, a human body's is {lo:g}-{hi:g} m; "
                                 f"{_scale_advice(conv.extent)}"))
    unit_volume = f"{conv.signed_volume:.3g} m³" if conv.units else f"{conv.signed_volume:.3g} (mesh units)³"
    if extra is not None or (not conv.units and _landmark_unit(conv.landmark_extent) is not None):
        pass            # other geometry's faces (the landmarks are a body's, the mesh is not) make
        # the signed volume say nothing of the body's
    elif conv.volume_ratio < -INWARD_VOLUME_RATIO and not flip_winding:
        found.append(Finding(f"its faces are wound inwards (signed volume {unit_volume}, expected positive)",
                             {"flip_winding": True}))
    elif conv.volume_ratio > INWARD_VOLUME_RATIO and flip_winding:
        found.append(Finding(f"its faces are already wound outwards (signed volume {unit_volume})",
                             {"flip_winding": False}))
    if conv.layout_wrong:
        n, bad = conv.layout_checks, conv.layout_failures
        found.append(Finding(f"its vertices are not in the order of the landmarks of {_set_name(mset)}: the landmarks "
                             f"land on the wrong body parts ({len(bad)} of {n} layout checks fail, e.g. "
                             f"{'; '.join(bad[:2])})", {"landmarks": True}))
    elif conv.up is not None and conv.up != (up or "y"):
        pointing = f"its feet→head axis points along {_signed(conv.up)} (within {max(1, round(conv.up_angle))}°)"
        if up is None:
            found.append(Finding(f"{pointing}; expected +Y up", {"up": conv.up}))
        else:
            found.append(Finding(f"{pointing}, not along {_signed(up)}", {"up": None if conv.up == "y" else conv.up}))
    return found


def _landmark_unit(spread: float) -> str | None:
    """The ``MESH_UNITS`` unit in which landmarks spread ``spread`` (mesh units) across are a
    body's (``LANDMARK_EXTENT_M``), nearest the template's 1.6 m; None when none."""
    lo, hi = LANDMARK_EXTENT_M
    fits = [u for u in MESH_UNITS if np.isfinite(spread) and lo <= spread * MESH_UNITS[u] <= hi]
    return min(fits, key=lambda u: abs(np.log(spread * MESH_UNITS[u] / TYPICAL_LANDMARK_EXTENT_M))) if fits else None


def _extra_geometry(conv: Conventions, units: str | None) -> str | None:
    """The finding for a mesh whose landmarks are a body's size in the unit the caller gave (or,
    with none given, in one unit) while the whole mesh is not: it carries more than the body,
    joined to it (``body_faces`` leaves out the pieces without a landmark and a floor sheet; this
    is what it could not tell apart). None when that is not the case (then the unit is wrong)."""
    if conv.layout_wrong or not np.isfinite(conv.landmark_extent):
        return None
    lo, hi = LANDMARK_EXTENT_M
    if units is not None:            # the unit given: its own message, never "is it in mm?"
        if units in conv.units or not lo <= conv.landmark_extent * MESH_UNITS[units] <= hi:
            return None
        u = units
    else:                            # none given and none fits the whole mesh: the landmarks' unit
        u = _landmark_unit(conv.landmark_extent)
        if conv.units or u is None:
            return None
    f = MESH_UNITS[u]
    given = f"in {_UNIT_WORDS[u]}, the unit given," if units is not None else f"in {_UNIT_WORDS[u]}"
    return (f"{given} its landmarks span {conv.landmark_extent * f:.3g} m, a body's size, but the whole mesh's "
            f"bounding box is {conv.extent * f:.3g} m across with {(conv.size * f) ** 2:.3g} m² of surface (a human "
            f"body's: {BODY_EXTENT_M[0]:g}-{BODY_EXTENT_M[1]:g} m, {BODY_SIZE_M[0] ** 2:.2g}-"
            f"{BODY_SIZE_M[1] ** 2:.2g} m²): it carries more than the body, joined to it (a floor that is not flat, a "
            "stand, stray vertices far away, a second body?) and not told apart from it; cut that away in a mesh "
            "editor and measure the body alone")


def _set_name(mset: MeasurementSet) -> str:
    if mset.source == str(DEFAULT_PATH):
        return f"the default measurement set ({DEFAULT_PATH.name}, the {mset.template} template's vertex order)"
    return mset.source


def _signed(axis: str) -> str:
    return axis.upper() if axis.startswith("-") else "+" + axis.upper()


def _unit_list(units: tuple[str, ...]) -> str:
    return " or ".join(_UNIT_WORDS[u] for u in units)


def describe(mesh_name: str, findings: list[Finding], words: dict = LIBRARY_WORDS) -> str:
    """One line: the mesh, what was found, and the fixes in ``words`` (the interface's own:
    a template per fix key, "{}" for the value)."""
    give, leave, other = [], [], []
    for f in findings:
        for key, value in f.fix.items():
            if key == "landmarks":
                other.append("give " + words["landmarks"])
            elif value is None or value is False:
                leave.append(words[key].replace("={!r}", "").replace(" {}", "").replace("=True", ""))
            elif isinstance(value, tuple):
                give.append(" (or ".join(words[key].format(x) for x in value) + ")" * (len(value) - 1))
            else:
                give.append(words[key].format(value))
    fixes = ([f"give {' '.join(give)}"] if give else []) + [f"leave out {x}" for x in leave] + other
    return f"{mesh_name}: {'; '.join(f.what for f in findings)}" + (f"; {'; '.join(fixes)}" if fixes else "")


def check_arguments(units: str | None, up: str | None, words: dict = LIBRARY_WORDS) -> None:
    """Raise MeasurementError unless ``units`` and ``up`` are None or known values (said in
    ``words``, the interface's own), before any work."""
    if units is not None and units not in MESH_UNITS:
        raise MeasurementError(f"{words['units'].format(units)}: unknown unit; expected one of "
                               f"{', '.join(MESH_UNITS)} (in: inches)")
    if up is not None and up not in UP_AXES:
        raise MeasurementError(f"{words['up'].format(up)}: unknown axis; expected one of {', '.join(UP_AXES)}")


def prepare(vertices: np.ndarray, faces: np.ndarray, mset: MeasurementSet, mesh_name: str = "the mesh", *,
            units: str | None = None, up: str | None = None, flip_winding: bool = False,
            words: dict = LIBRARY_WORDS) -> tuple[np.ndarray, np.ndarray]:
    """The door for one user mesh (V, 3), (F, 3): recognise its conventions (``inspect``),
    refuse any it is off by with the fix (MeasurementError, one line, the fixes in ``words``),
    else return it in bodyspace's conventions (``to_internal`` with what the caller said).

    units: "m", "cm", "mm" or "in" (None: metres, checked); up: one of ``UP_AXES`` (None: +Y,
    checked); flip_winding: reverse every face. A claim the geometry contradicts is refused too.
    The vertex ids of ``mset`` must fit the mesh (``evaluate.check_compatible``).
    """
    check_arguments(units, up, words)
    findings = find_problems(inspect(vertices, faces, mset), mset, units, up, flip_winding)
    if findings:
        raise MeasurementError(describe(mesh_name, findings, words))
    return to_internal(vertices, faces, units or "m", up or "y", flip_winding)


# ------------------------------------------------------------------------------ other geometry

# A scanner's mesh often carries more than the body: the floor (a sheet or a disc under the
# feet, a separate piece or welded to the soles), a turntable, a pole or a stool. Their faces
# would add to the volume, the mass and the surface area, their extent to the stature, and they
# make the mesh fit no unit. ``body_faces`` leaves them out: the pieces that carry no landmark,
# then a floor sheet under the feet (``mesh.floor.find_floor`` on points sampled from the faces).
# A floor is looked for only when the surface below the lowest landmark (the ankle joints of
# a standing body) is more than FLOOR_GATE_AREA x (the landmarks' height span)²: the template's
# feet are 0.042, a floor disc 1 m wide under them 0.31 (a false alarm costs only the search).
FLOOR_GATE_AREA = 0.12


@dataclass(frozen=True)
class BodyFaces:
    """The body of a mesh that may carry other geometry (``body_faces``).

    vertices: (V, 3) the mesh's vertices, mesh units; those only the left-out faces used are
        moved onto a vertex of the body (their ids stay: a landmark file's ids keep their meaning;
        no face uses them, and no extent or lowest point sees them).
    faces: (F', 3) the body's faces, a subset of the mesh's in their order.
    notes: one sentence per thing left out (empty: the mesh is all body).
    left_out_area: the surface left out, m² (mesh units² when the unit is unknown).
    welded: the floor was joined to the body: the body is open where it stood on it.
    kept: (F,) bool, the mesh's faces that are ``faces``; None when the mesh is all body.
    """

    vertices: np.ndarray
    faces: np.ndarray
    notes: tuple[str, ...] = ()
    left_out_area: float = 0.0
    welded: bool = False
    kept: np.ndarray | None = None


def _landmarked(faces: np.ndarray, n_vertices: int, ids: np.ndarray) -> np.ndarray:
    """(F,) bool: the faces of the connected pieces of ``faces`` that hold a vertex of ``ids``
    (every face when the mesh is one piece, or when no piece holds one)."""
    roots = face_component_roots(faces, n_vertices)
    if not len(roots) or (roots == roots[0]).all():
        return np.ones(len(faces), dtype=bool)
    on = np.zeros(n_vertices, dtype=bool)
    on[ids] = True
    pieces = np.unique(roots[on[faces].any(axis=1)])
    if not len(pieces):
        return np.ones(len(faces), dtype=bool)
    return np.isin(roots, pieces)


def body_faces(vertices: np.ndarray, faces: np.ndarray, mset: MeasurementSet, units: str | None = None) -> BodyFaces:
    """The body of one mesh (V, 3), (F, 3) without the floor, turntable or objects it carries.

    Left out, in this order: the connected pieces that hold no landmark of ``mset`` (a floor, a
    turntable, a pole beside the body); then a floor sheet under the feet of the rest (joined to
    the soles, or a piece a landmark file put a point on): every face within the floor's noise
    (``mesh.floor``: 3 sigma, at least 6 mm) of its plane or below it, and the pieces this cuts off.
    ``units``: the mesh's unit (None: the one the landmarks' height span gives; without one no
    floor is looked for). The up direction is the landmarks' feet→head (``up_vector``). A mesh
    that is all body comes back as it was (the same arrays), after a union-find and one pass.
    """
    v = np.asarray(vertices, dtype=float)
    f = np.asarray(faces)
    ids = np.unique(np.concatenate([i[np.asarray(w) != 0] for i, w in mset.landmarks.values()]).astype(np.int64))
    keep = _landmarked(f, len(v), ids)
    points = landmark_points(mset, v)
    u = up_vector(points)
    scale = MESH_UNITS[units] if units in MESH_UNITS else None
    floors = []
    if u is not None:
        heights = np.array([float(p[0] @ u) for p in points.values()])
        span = float(heights.max() - heights.min())
        if scale is None:
            fits = plausible_units(span)
            scale = MESH_UNITS[fits[0]] if fits else None
        low = (v @ u) < heights.min()                                   # (V,) below the lowest landmark
        below = keep & low[f[:, 0]] & low[f[:, 1]] & low[f[:, 2]]
        if scale is not None and below.any() and face_areas(v, f[below]).sum() > FLOOR_GATE_AREA * span ** 2:
            keep, floors = _cut_floors(v, f, keep, ids, u, scale)
    if keep.all() or not keep.any():     # all body, or nothing would be left: the door judges it whole
        return BodyFaces(vertices, faces)
    s = 1.0 if scale is None else scale
    unit = "m" if scale is not None else "mesh units"
    areas = face_areas(v, f) * s * s
    out = ~keep
    body_vertices = np.zeros(len(v), dtype=bool)
    body_vertices[f[keep]] = True
    dropped = np.zeros(len(v), dtype=bool)
    dropped[f[out]] = True
    welded = bool(floors) and bool((dropped & body_vertices).any())
    notes = []
    for what, mask in floors:
        w = sheet_width(v[np.unique(f[mask])], u) * s
        notes.append(f"left out {what} {_metres(w, unit)} across under the feet: {int(mask.sum())} faces, "
                     f"{areas[mask].sum():.3g} {unit}² of surface")
    pieces = out.copy()
    for _, mask in floors:
        pieces &= ~mask
    if pieces.any():
        n = len(np.unique(face_component_roots(f[pieces], len(v))))
        w = float(body_extent(v[np.unique(f[pieces])])) * s
        notes.append(f"left out {n} piece{'s' if n > 1 else ''} not joined to the body (no landmark on "
                     f"{'them' if n > 1 else 'it'}: a floor, a turntable, a stand?): {int(pieces.sum())} faces, "
                     f"{areas[pieces].sum():.3g} {unit}² of surface, {_metres(w, unit)} across")
    if welded:
        notes.append("the floor was joined to the body, whose soles are open now: volume and mass count them "
                     "closed by a flat cap on the floor's plane, the surface area leaves them out")
    moved = dropped & ~body_vertices
    moved[ids] = False
    v = v.copy()
    v[moved] = v[f[keep][0, 0]]
    return BodyFaces(v, f[keep], tuple(notes), float(areas[out].sum()), welded, keep)


def _cut_floors(v: np.ndarray, f: np.ndarray, keep: np.ndarray, ids: np.ndarray, u: np.ndarray,
                scale: float) -> tuple[np.ndarray, list]:
    """``keep`` (F,) without the floors found under the body (up to ``FLOOR_ROUNDS``: the ground,
    then a turntable's top), and [(what, (F,) bool faces of that floor)]."""
    keep = keep.copy()
    floors = []
    for _ in range(FLOOR_ROUNDS):
        found = mesh_floor(v, f[keep], scale, u)
        if found is None:
            break
        normal, offset, noise = found
        height = v @ normal * scale - offset
        cut = keep & (height[f] < FLOOR_CUT_SIGMAS * noise).all(axis=1)
        if not cut.any():
            break
        # Pieces the cut parted from the body (a turntable's side under its top, a floor's rim).
        sub = np.flatnonzero(keep & ~cut)
        alone = np.zeros(len(f), dtype=bool)
        alone[sub[~_landmarked(f[sub], len(v), ids)]] = True
        cut |= alone
        keep &= ~cut
        unpinched = _unpinch(f, keep, height < 2 * FLOOR_CUT_SIGMAS * noise)
        cut |= keep & ~unpinched
        keep = unpinched
        floors.append(("the floor" if not floors else "a platform on it (a turntable's top with its side)", cut))
    return keep, floors


def _unpinch(f: np.ndarray, keep: np.ndarray, near: np.ndarray, rounds: int = 8) -> np.ndarray:
    """``keep`` (F,) without the faces that pinch the hole a floor's cut opened: a vertex where
    two holes meet (two boundary edges start there) makes the boundary non-manifold, and the
    holes could not be capped for the volume. The kept faces at such a vertex that touch the
    floor's band (``near`` (V,), twice the cut) go too, a few rounds until none is left."""
    keep = keep.copy()
    for _ in range(rounds):
        kf = f[keep]
        e = np.concatenate([kf[:, [0, 1]], kf[:, [1, 2]], kf[:, [2, 0]]])
        n = int(max(f.max(), 0)) + 1
        code = e[:, 0].astype(np.int64) * n + e[:, 1]
        reverse = e[:, 1].astype(np.int64) * n + e[:, 0]
        boundary = e[~np.isin(code, reverse)]
        starts = np.bincount(boundary[:, 0], minlength=n)
        pinched = starts > 1
        if not pinched.any():
            break
        drop = keep & pinched[f].any(axis=1) & near[f].any(axis=1)
        if not drop.any():
            break
        keep &= ~drop
    return keep


def _metres(x: float, unit: str) -> str:
    return f"{100 * x:.0f} cm" if unit == "m" else f"{x:.3g} {unit}"


# ------------------------------------------------------------------------------ placement

# Landmarks that say which way a body faces: its left side (+X in our frame, so that left x up
# is the front, +Z) from the shoulder and hip joints, and where it stands (between the hips).
PLACEMENT_PAIRS = (("shoulder_joint_l", "shoulder_joint_r"), ("hip_joint_l", "hip_joint_r"))


def standing_placement(landmarks: dict, vertices: np.ndarray) -> tuple[np.ndarray, np.ndarray, float] | None:
    """The rigid move that stands bodies in our frame: facing +Z, the floor at y = 0, the point
    between the hip joints over the origin.

    landmarks: {name: (ids (K,), weights (K,))} of the bodies' topology (``MeasurementSet.landmarks``,
    ``load_landmarks``).
    vertices: (N, V, 3) standing bodies in metres, +Y up (a folder's rest scans): one move for
    all, from the median of their left directions, floors and hip centres, so bodies keep their
    places relative to each other. Returns (R (3, 3), t (3,), yaw in degrees) with ``x' = R x + t``
    (R turns about +Y only), or None when the landmarks lack the shoulder and hip joints.
    """
    names = [n for pair in PLACEMENT_PAIRS for n in pair]
    if any(n not in landmarks for n in names):
        return None
    v = np.asarray(vertices, dtype=float)
    p = {n: np.einsum("k,nkd->nd", np.asarray(landmarks[n][1], float), v[:, np.asarray(landmarks[n][0])])
         for n in names}                                                                               # (N, 3)
    left = sum(p[a] - p[b] for a, b in PLACEMENT_PAIRS)                                              # (N, 3)
    left = np.median(left, axis=0)
    front = np.cross(left, [0.0, 1.0, 0.0])
    yaw = float(np.arctan2(front[0], front[2]))          # front = (sin yaw, 0, cos yaw)
    c, s = np.cos(yaw), np.sin(yaw)
    R = np.array([[c, 0.0, -s], [0.0, 1.0, 0.0], [s, 0.0, c]])                                      # R @ front = +Z
    hips = np.median(0.5 * (p["hip_joint_l"] + p["hip_joint_r"]), axis=0) @ R.T
    floor = float(np.median(v[..., 1].min(axis=1)))
    return R, np.array([-hips[0], -floor, -hips[2]]), float(np.degrees(yaw))
