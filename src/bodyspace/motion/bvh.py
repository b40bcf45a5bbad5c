"""BVH motion capture files: read, write, and the motion they hold.

A BVH file is a joint hierarchy (``HIERARCHY``: nested ``ROOT``/``JOINT`` blocks with an
``OFFSET`` from the parent, a ``CHANNELS`` list, and ``End Site`` blocks that give the last
bone of a chain its length) followed by ``MOTION``: ``Frames: N``, ``Frame Time: t`` and N lines
of channel values, the joints' channels in file order. A ``Motion`` keeps exactly that:

- ``skeleton``: a ``MotionSkeleton`` (names, parents, offsets, each joint's channel names in
  file order, End Sites), all lengths in file units;
- ``values``: (F, C) float64, the channel values as written (rotations in degrees);
- ``frame_time`` (seconds) and ``unit`` (metres per file unit, with ``unit_note`` saying how it
  was found).

Conventions (those of Biovision's format as CMU, MotionBuilder, Blender and three.js read it):

- A joint's local transform is ``T(translation) · R``, with ``R`` the product of its rotation
  channels *in the order listed*: ``CHANNELS 3 Zrotation Xrotation Yrotation`` means
  ``R = Rz(z) @ Rx(x) @ Ry(y)``. Any order per joint, any subset of the three axes; CMU files mix
  ZYX and ZXY in one file.
- The translation is the OFFSET, except where the joint has position channels: they *replace*
  the offset's components (MotionBuilder's convention; on a root whose OFFSET is zero, as in CMU
  files, both readings agree) or are *added* to them. ``translation="auto"`` decides per file:
  values that sit near the offsets replace them, values that sit near zero are added.
- At rest (all channels zero, translations = offsets) every joint frame is the file's axes, so
  a local rotation is also a rotation in rest-pose world axes about the joint: the convention of
  ``bodyspace.rig.kinematics`` (``forward_kinematics`` reproduces this module's positions for a
  file without non-root translation channels; tested).

Units. A BVH has no unit field. ``unit=`` takes metres per file unit or a name (``m``, ``dm``,
``cm``, ``mm``, ``in``, ``ft``, ``cmu`` = 0.0254/0.45 m, CMU's scale); ``"auto"`` (the default)
reads the rest skeleton's largest extent (joints and End Sites, any axis: a standing body is
about as tall as its arm span) and takes the unit of that list that makes it closest to a
standing adult, 1.7 m. The choice and the reasoning are in ``Motion.unit_note``.

Speed. Frame values are parsed by a compiled scanner (``_scan_numbers``) over the raw bytes: a
10,000-frame CMU clip (~1 M numbers) in a few tens of milliseconds; every number it cannot
convert exactly by the fast path (more than 15 significant digits, exponents beyond 10^±22)
goes through Python's ``float`` so the values are bit-identical to ``float()`` of each token.
``benchmarks/bench_bvh.py`` compares it with a plain per-line ``float()`` parser.

Errors. Every malformed file raises ``MotionError`` naming the file, the line, what was found
and what was expected; nothing is allocated from a declared frame count (a file that declares
10^7 frames and holds 3 is refused by counting its lines).
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from pathlib import Path

import numba
import numpy as np

from bodyspace.atomic import atomic_path
from bodyspace.errors import MotionError
from bodyspace.rig.kinematics import matrix_to_quaternion
from bodyspace.rig.skeleton import Skeleton

__all__ = ["CHANNEL_NAMES", "CMU_UNIT", "UNITS", "Motion", "MotionSkeleton", "euler_to_matrix", "format_bvh",
           "matrix_to_euler", "parse_bvh", "read_bvh", "resolve_unit", "skeleton_from_rig", "write_bvh"]

CHANNEL_NAMES = ("Xposition", "Yposition", "Zposition", "Xrotation", "Yrotation", "Zrotation")
_CHANNEL_LOOKUP = {c.lower(): c for c in CHANNEL_NAMES}
_AXIS = {"X": 0, "Y": 1, "Z": 2}
CMU_UNIT = 0.0254 / 0.45  # m: CMU's skeletons are in units of 1/0.45 inch
UNITS = {"m": 1.0, "dm": 0.1, "cm": 0.01, "mm": 0.001, "in": 0.0254, "ft": 0.3048, "cmu": CMU_UNIT}
# "auto" picks the unit of UNITS that makes the rest skeleton's extent closest to this (metres).
_TYPICAL_EXTENT_M = 1.7
_TRANSLATION_MODES = ("auto", "replace", "add")
# Room for numbers the compiled scanner hands to float() (more than 15 digits ...) before it
# retries with room for every token.
_SLOW_TOKENS = 65_536
# Below this, |cos(middle angle)| means gimbal lock in matrix_to_euler.
_GIMBAL_EPS = 1e-9


# ----------------------------------------------------------------------------- rotations

def _axis_rotations(angles_rad: np.ndarray, axis: int) -> np.ndarray:
    """Rotation matrices (..., 3, 3) about coordinate axis 0/1/2 by ``angles_rad`` (...)."""
    c, s = np.cos(angles_rad), np.sin(angles_rad)
    R = np.zeros(angles_rad.shape + (3, 3))
    i, j = (axis + 1) % 3, (axis + 2) % 3
    R[..., axis, axis] = 1.0
    R[..., i, i] = c
    R[..., j, j] = c
    R[..., i, j] = -s
    R[..., j, i] = s
    return R


def euler_to_matrix(degrees: np.ndarray, order: str) -> np.ndarray:
    """Rotations (..., 3, 3) of BVH Euler angles: ``R = R_order[0] @ R_order[1] @ ...``.

    degrees: (..., k) angles in the order of ``order`` (k = len(order), 0 to 3 axes from
    "XYZ", e.g. "ZXY"). An empty order gives identities.
    """
    a = np.asarray(degrees, dtype=float)
    if a.shape[-1:] != (len(order),):
        raise MotionError(f"euler_to_matrix: angles of shape {a.shape} for order {order!r}; expected (..., "
                          f"{len(order)})")
    R = np.broadcast_to(np.eye(3), a.shape[:-1] + (3, 3)).copy()
    for k, axis in enumerate(order):
        R = R @ _axis_rotations(np.radians(a[..., k]), _AXIS[axis])
    return R


def matrix_to_euler(matrices: np.ndarray, order: str) -> np.ndarray:
    """Euler angles (..., 3) in degrees, ``R = R_order[0](a) @ R_order[1](b) @ R_order[2](c)``.

    order: three distinct axes ("ZYX", "ZXY", ...), the order BVH channels list them.
    The middle angle is in [-90, 90]; at gimbal lock (middle angle ±90) the last angle is 0.
    """
    R = np.asarray(matrices, dtype=float)
    if len(order) != 3 or sorted(order) != ["X", "Y", "Z"]:
        raise MotionError(f"matrix_to_euler: order {order!r}; expected three distinct axes such as 'ZXY'")
    i, j, k = (_AXIS[a] for a in order)
    s = 1.0 if (j - i) % 3 == 1 else -1.0  # +1 for cyclic orders (XYZ, YZX, ZXY)
    cos_b = np.hypot(R[..., i, i], R[..., i, j])
    b = np.arctan2(s * R[..., i, k], cos_b)
    a = np.arctan2(-s * R[..., j, k], R[..., k, k])
    c = np.arctan2(-s * R[..., i, j], R[..., i, i])
    lock = cos_b < _GIMBAL_EPS
    if lock.any():  # R = R_i(a) R_j(±90): column j of R is R_i(a) e_j
        a = np.where(lock, np.arctan2(s * R[..., k, j], R[..., j, j]), a)
        c = np.where(lock, 0.0, c)
    return np.degrees(np.stack([a, b, c], axis=-1))


# ----------------------------------------------------------------------------- data model

@dataclass(frozen=True)
class MotionSkeleton:
    """The joint hierarchy of a BVH file, lengths in file units.

    names: (J,) joint names, file order (depth first: every parent precedes its children).
    parents: (J,) int, -1 for a root.
    offsets: (J, 3) each joint's OFFSET from its parent (a root's from the origin).
    channels: (J,) tuples of channel names in file order (``CHANNEL_NAMES``), possibly empty.
    end_sites: (E, 3) End Site offsets from their joint; end_site_parents: (E,) joint indices.
    """

    names: tuple[str, ...]
    parents: np.ndarray
    offsets: np.ndarray
    channels: tuple[tuple[str, ...], ...]
    end_sites: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    end_site_parents: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))

    def __post_init__(self):
        names = tuple(str(n) for n in self.names)
        J = len(names)
        parents = np.asarray(self.parents, dtype=np.int64).reshape(-1)
        offsets = np.asarray(self.offsets, dtype=float)
        ends = np.asarray(self.end_sites, dtype=float).reshape(-1, 3)
        end_parents = np.asarray(self.end_site_parents, dtype=np.int64).reshape(-1)
        channels = tuple(tuple(str(c) for c in ch) for ch in self.channels)
        if J == 0:
            raise MotionError("skeleton: no joints; expected at least a ROOT")
        if len(set(names)) != J:
            dup = sorted({n for n in names if names.count(n) > 1})
            raise MotionError(f"skeleton: joint names {dup} appear more than once; expected unique names")
        if any(not n or any(ch.isspace() for ch in n) or n in "{}" for n in names):
            bad = next(n for n in names if not n or any(ch.isspace() for ch in n) or n in "{}")
            raise MotionError(f"skeleton: joint name {bad!r} is empty, holds white space or is a brace; BVH names "
                              "are single words")
        if parents.shape != (J,) or offsets.shape != (J, 3) or len(channels) != J:
            raise MotionError(f"skeleton: parents {parents.shape}, offsets {offsets.shape}, {len(channels)} channel "
                              f"lists; expected ({J},), ({J}, 3) and {J} for {J} joints")
        if not ((parents >= -1) & (parents < np.arange(J))).all():
            j = int(np.flatnonzero(~((parents >= -1) & (parents < np.arange(J))))[0])
            raise MotionError(f"skeleton: joint {names[j]!r} has parent index {parents[j]}; expected -1 or an "
                              "earlier joint (parents precede children, as in a file)")
        if not np.isfinite(offsets).all() or not np.isfinite(ends).all():
            raise MotionError("skeleton: offsets hold NaN or infinity; expected finite numbers")
        if end_parents.shape != (len(ends),) or ((end_parents < 0) | (end_parents >= J)).any():
            raise MotionError(f"skeleton: {len(ends)} End Sites with parents {end_parents.tolist()}; expected one "
                              "joint index each")
        for name, ch in zip(names, channels):
            if len(set(ch)) != len(ch) or any(c not in CHANNEL_NAMES for c in ch):
                raise MotionError(f"skeleton: joint {name!r} has channels {list(ch)}; expected distinct names from "
                                  f"{', '.join(CHANNEL_NAMES)}")
        object.__setattr__(self, "names", names)
        object.__setattr__(self, "parents", parents)
        object.__setattr__(self, "offsets", offsets)
        object.__setattr__(self, "channels", channels)
        object.__setattr__(self, "end_sites", ends)
        object.__setattr__(self, "end_site_parents", end_parents)

    @property
    def n_joints(self) -> int:
        return len(self.names)

    @property
    def n_channels(self) -> int:
        return sum(len(c) for c in self.channels)

    @property
    def channel_starts(self) -> np.ndarray:
        """(J,) index of each joint's first channel in a frame's values."""
        return np.concatenate([[0], np.cumsum([len(c) for c in self.channels])[:-1]]).astype(np.int64)

    def rotation_order(self, j: int) -> str:
        """The joint's rotation axes in channel order, e.g. ``"ZXY"`` ("" without rotation channels)."""
        return "".join(c[0] for c in self.channels[j] if c.endswith("rotation"))

    def index(self, name: str) -> int:
        try:
            return self.names.index(name)
        except ValueError:
            raise MotionError(f"joint {name!r}: not in the skeleton; expected one of {', '.join(self.names)}") from None

    def children(self, j: int) -> list[int]:
        return [int(c) for c in np.flatnonzero(self.parents == j)]

    def rest_positions(self) -> np.ndarray:
        """(J, 3) joint positions at rest (every channel zero, translations = offsets), file units."""
        pos = np.zeros((self.n_joints, 3))
        for j, p in enumerate(self.parents):
            pos[j] = self.offsets[j] + (pos[p] if p >= 0 else 0.0)
        return pos

    def rest_end_sites(self) -> np.ndarray:
        """(E, 3) End Site positions at rest, file units."""
        return self.rest_positions()[self.end_site_parents] + self.end_sites

    def renamed(self, mapping: dict[str, str]) -> "MotionSkeleton":
        """The same skeleton with joints renamed by ``mapping`` (names not in it are kept)."""
        return MotionSkeleton(tuple(mapping.get(n, n) for n in self.names), self.parents, self.offsets,
                              self.channels, self.end_sites, self.end_site_parents)


@dataclass(frozen=True)
class Motion:
    """A skeleton and its channel values per frame (see the module docstring).

    values: (F, C) channel values in file order, degrees and file units.
    frame_time: seconds between frames. unit: metres per file unit.
    translation: how position channels combine with offsets, "replace" or "add" (resolved).
    """

    skeleton: MotionSkeleton
    values: np.ndarray
    frame_time: float
    unit: float = 1.0
    unit_note: str = "given"
    translation: str = "replace"
    name: str = "motion"

    def __post_init__(self):
        v = np.asarray(self.values, dtype=float)
        C = self.skeleton.n_channels
        if v.ndim != 2 or v.shape[1] != C:
            raise MotionError(f"{self.name}: values of shape {v.shape}; expected (frames, {C}) for the skeleton's "
                              f"{C} channels")
        if not np.isfinite(v).all():
            raise MotionError(f"{self.name}: values hold NaN or infinity; expected finite numbers")
        if not (math.isfinite(self.frame_time) and self.frame_time > 0):
            raise MotionError(f"{self.name}: frame time {self.frame_time!r}; expected a positive number of seconds")
        if not (math.isfinite(self.unit) and self.unit > 0):
            raise MotionError(f"{self.name}: unit {self.unit!r}; expected positive metres per file unit")
        if self.translation not in ("replace", "add"):
            raise MotionError(f"{self.name}: translation {self.translation!r}; expected 'replace' or 'add'")
        object.__setattr__(self, "values", v)
        object.__setattr__(self, "frame_time", float(self.frame_time))
        object.__setattr__(self, "unit", float(self.unit))

    @property
    def n_frames(self) -> int:
        return self.values.shape[0]

    @property
    def fps(self) -> float:
        return 1.0 / self.frame_time

    @property
    def duration(self) -> float:
        """Seconds from the first frame to the last."""
        return max(self.n_frames - 1, 0) * self.frame_time

    def joint_values(self, name: str) -> np.ndarray:
        """(F, k) the channel values of one joint, in its channel order."""
        j = self.skeleton.index(name)
        s = self.skeleton.channel_starts[j]
        return self.values[:, s:s + len(self.skeleton.channels[j])]

    def local_rotations(self) -> np.ndarray:
        """(F, J, 3, 3) each joint's rotation relative to its parent (rest-pose world axes)."""
        sk = self.skeleton
        F, J = self.n_frames, sk.n_joints
        R = np.broadcast_to(np.eye(3), (F, J, 3, 3)).copy()
        starts = sk.channel_starts
        groups: dict[str, list[tuple[int, list[int]]]] = {}
        for j in range(J):
            cols = [int(starts[j]) + k for k, c in enumerate(sk.channels[j]) if c.endswith("rotation")]
            if cols:
                groups.setdefault(sk.rotation_order(j), []).append((j, cols))
        for order, members in groups.items():  # one vectorized call per distinct rotation order
            joints = [j for j, _ in members]
            cols = np.array([c for _, c in members])                  # (Jg, k)
            R[:, joints] = euler_to_matrix(self.values[:, cols], order)
        return R

    def local_quaternions(self) -> np.ndarray:
        """(F, J, 4) local rotations as unit quaternions (w, x, y, z), w >= 0."""
        return matrix_to_quaternion(self.local_rotations())

    def local_translations(self) -> np.ndarray:
        """(F, J, 3) each joint's translation from its parent, metres (offsets and position channels)."""
        sk = self.skeleton
        t = np.broadcast_to(sk.offsets, (self.n_frames, sk.n_joints, 3)).copy()
        starts = sk.channel_starts
        for j, ch in enumerate(sk.channels):
            for k, c in enumerate(ch):
                if c.endswith("position"):
                    a = _AXIS[c[0]]
                    v = self.values[:, starts[j] + k]
                    t[:, j, a] = v if self.translation == "replace" else t[:, j, a] + v
        return t * self.unit

    def global_transforms(self) -> tuple[np.ndarray, np.ndarray]:
        """World rotations (F, J, 3, 3) and positions (F, J, 3, metres, file axes) of every joint."""
        L, t = self.local_rotations(), self.local_translations()
        Rg, pos = np.empty_like(L), np.empty_like(t)
        for j, p in enumerate(self.skeleton.parents):
            if p < 0:
                Rg[:, j], pos[:, j] = L[:, j], t[:, j]
            else:
                Rg[:, j] = Rg[:, p] @ L[:, j]
                pos[:, j] = pos[:, p] + (Rg[:, p] @ t[:, j, :, None])[..., 0]
        return Rg, pos

    def global_positions(self) -> np.ndarray:
        """(F, J, 3) joint positions in metres, file axes."""
        return self.global_transforms()[1]

    def end_site_positions(self) -> np.ndarray:
        """(F, E, 3) End Site positions in metres, file axes."""
        Rg, pos = self.global_transforms()
        p = self.skeleton.end_site_parents
        return pos[:, p] + np.einsum("feij,ej->fei", Rg[:, p], self.skeleton.end_sites * self.unit)

    def rest_positions(self) -> np.ndarray:
        """(J, 3) rest-pose joint positions in metres (every channel zero), file axes."""
        return self.skeleton.rest_positions() * self.unit

    def with_skeleton(self, skeleton: MotionSkeleton) -> "Motion":
        """The same values on another skeleton with the same channel layout (renamed joints)."""
        if [len(c) for c in skeleton.channels] != [len(c) for c in self.skeleton.channels]:
            raise MotionError(f"{self.name}: the new skeleton's channel layout differs; expected the same channels "
                              "per joint")
        return Motion(skeleton, self.values, self.frame_time, self.unit, self.unit_note, self.translation, self.name)

    def frames(self, index) -> "Motion":
        """The motion restricted to some frames (a slice or indices)."""
        v = self.values[index]
        return Motion(self.skeleton, v.reshape(-1, self.values.shape[1]), self.frame_time, self.unit, self.unit_note,
                      self.translation, self.name)

    @classmethod
    def from_rotations(cls, skeleton: MotionSkeleton, rotations: np.ndarray, translations: np.ndarray | None = None,
                       frame_time: float = 1 / 30, unit: float = 1.0, name: str = "motion") -> "Motion":
        """A motion whose channels give local ``rotations`` (F, J, 3, 3) and, for joints with
        position channels, the local ``translations`` (F, J, 3, file units; "replace" convention).
        Each joint's rotation channels must hold three axes (any order) or none."""
        R = np.asarray(rotations, dtype=float)
        F, J = R.shape[:2]
        if R.shape != (F, skeleton.n_joints, 3, 3):
            raise MotionError(f"rotations: shape {R.shape}; expected (frames, {skeleton.n_joints}, 3, 3)")
        t = None if translations is None else np.asarray(translations, dtype=float)
        values = np.zeros((F, skeleton.n_channels))
        starts = skeleton.channel_starts
        for j, ch in enumerate(skeleton.channels):
            order = skeleton.rotation_order(j)
            if order:
                if len(order) != 3:
                    raise MotionError(f"joint {skeleton.names[j]!r}: rotation channels {order!r}; from_rotations "
                                      "needs all three axes")
                ang = matrix_to_euler(R[:, j], order)
            for k, c in enumerate(ch):
                if c.endswith("rotation"):
                    values[:, starts[j] + k] = ang[:, order.index(c[0])]
                else:
                    a = _AXIS[c[0]]
                    values[:, starts[j] + k] = skeleton.offsets[j, a] if t is None else t[:, j, a]
        return cls(skeleton, values, frame_time, unit, "given", "replace", name)


# ----------------------------------------------------------------------------- units

def resolve_unit(unit, skeleton: MotionSkeleton) -> tuple[float, str]:
    """Metres per file unit and how it was found: a number, a name of ``UNITS``, or "auto"/None
    (the rest skeleton's extent, module docstring)."""
    if unit is None or (isinstance(unit, str) and unit.strip().lower() == "auto"):
        pts = np.vstack([skeleton.rest_positions(), skeleton.rest_end_sites()])
        extent = float((pts.max(axis=0) - pts.min(axis=0)).max())
        if not extent > 0:
            raise MotionError("unit: the rest skeleton has no extent (every joint at one point), so its unit cannot "
                              f"be guessed; give it (unit= / --bvh-unit: one of {', '.join(UNITS)} or metres per unit)")
        name = min(UNITS, key=lambda u: abs(math.log(extent * UNITS[u] / _TYPICAL_EXTENT_M)))
        return UNITS[name], (f"auto: the rest skeleton spans {extent:.4g} file units; in {name} "
                             f"({UNITS[name]:.6g} m) that is {extent * UNITS[name]:.2f} m, of the units "
                             f"{', '.join(UNITS)} the closest to a standing adult ({_TYPICAL_EXTENT_M} m); "
                             "give the unit (unit= / --bvh-unit) if that is wrong")
    if isinstance(unit, str):
        key = unit.strip().lower()
        if key in UNITS:
            return UNITS[key], f"given: {key} ({UNITS[key]:.6g} m)"
        try:
            value = float(key)
        except ValueError:
            raise MotionError(f"unit {unit!r}: expected auto, one of {', '.join(UNITS)}, or metres per file unit "
                              "(e.g. 0.01)") from None
    else:
        value = float(unit)
    if not (math.isfinite(value) and value > 0):
        raise MotionError(f"unit {unit!r}: expected a positive number of metres per file unit")
    return value, f"given: {value:.6g} m per file unit"


# ----------------------------------------------------------------------------- parsing

@numba.njit(cache=True, nogil=True)
def _scan_numbers(buf, out, line_counts, slow):
    """Parse whitespace-separated decimal numbers of ``buf`` (uint8) into ``out``.

    Counts the numbers of each line (``line_counts``, lines split at b"\\n"). Returns
    (numbers read, numbers needing Python's float (their indices in ``slow[:, 0]`` and byte
    ranges in ``slow[:, 1:]``), byte offset of the first bad token, or -1, or -2 when ``slow``
    is full).
    Fast path: up to 15 significant digits and a power of ten within 10^±22, which a double
    holds exactly, so ``m * 10^e`` / ``m / 10^-e`` is correctly rounded (Clinger's fast path).
    """
    n = 0
    n_slow = 0
    line = 0
    i = 0
    L = buf.shape[0]
    while i < L:
        ch = buf[i]
        if ch == 10:
            line += 1
            i += 1
            continue
        if ch == 32 or ch == 9 or ch == 13 or ch == 11 or ch == 12:
            i += 1
            continue
        start = i
        neg = False
        if ch == 45 or ch == 43:  # - +
            neg = ch == 45
            i += 1
        mant = 0
        digits = 0
        frac = 0
        seen = False
        while i < L and 48 <= buf[i] <= 57:
            if mant != 0 or buf[i] != 48:
                digits += 1
            if digits <= 18:
                mant = mant * 10 + (buf[i] - 48)
            else:
                frac -= 1  # digits beyond 18 only scale
            seen = True
            i += 1
        if i < L and buf[i] == 46:  # .
            i += 1
            while i < L and 48 <= buf[i] <= 57:
                if mant != 0 or buf[i] != 48:
                    digits += 1
                if digits <= 18:
                    mant = mant * 10 + (buf[i] - 48)
                    frac += 1
                seen = True
                i += 1
        if not seen:
            return n, n_slow, start
        exp = 0
        if i < L and (buf[i] == 101 or buf[i] == 69):  # e E
            i += 1
            eneg = False
            if i < L and (buf[i] == 45 or buf[i] == 43):
                eneg = buf[i] == 45
                i += 1
            edigits = 0
            while i < L and 48 <= buf[i] <= 57:
                if exp < 100000:
                    exp = exp * 10 + (buf[i] - 48)
                edigits += 1
                i += 1
            if edigits == 0:
                return n, n_slow, start
            if eneg:
                exp = -exp
        if i < L and not (buf[i] == 32 or buf[i] == 9 or buf[i] == 10 or buf[i] == 13 or buf[i] == 11
                          or buf[i] == 12):
            return n, n_slow, start
        e10 = exp - frac
        if mant == 0:
            v = 0.0
        elif digits <= 15 and -22 <= e10 <= 22:
            if e10 >= 0:
                v = float(mant) * 10.0 ** e10
            else:
                v = float(mant) / 10.0 ** (-e10)
        else:
            v = 0.0
            if n_slow == slow.shape[0]:
                return n, n_slow, -2  # too many slow tokens for the buffer: the caller falls back
            slow[n_slow, 0] = n
            slow[n_slow, 1] = start
            slow[n_slow, 2] = i
            n_slow += 1
        out[n] = -v if neg else v
        line_counts[line] += 1
        n += 1
    return n, n_slow, -1




class _Lines:
    """Lines of the header (HIERARCHY .. Frame Time) with 1-based numbers, read on demand."""

    def __init__(self, data: bytes, label: str):
        self.data, self.label, self.pos, self.number = data, label, 0, 0

    def next(self) -> tuple[int, str] | None:
        if self.pos >= len(self.data):
            return None
        end = self.data.find(b"\n", self.pos)
        end = len(self.data) if end < 0 else end + 1
        raw = self.data[self.pos:end]
        self.pos = end
        self.number += 1
        return self.number, raw.decode("utf-8", errors="replace").strip()

    def fail(self, line: int, message: str) -> MotionError:
        return MotionError(f"{self.label} line {line}: {message}")


def _numbers(lines: _Lines, line: int, tokens: list[str], what: str) -> list[float]:
    out = []
    for t in tokens:
        try:
            v = float(t)
        except ValueError:
            raise lines.fail(line, f"{what}: {t!r} is not a number; expected {len(tokens)} numbers") from None
        if not math.isfinite(v):
            raise lines.fail(line, f"{what}: {t!r} is not finite; expected finite numbers")
        out.append(v)
    return out


def _parse_hierarchy(lines: _Lines) -> MotionSkeleton:
    """Read HIERARCHY ... up to and including the MOTION line."""
    first = lines.next()
    while first is not None and not first[1]:
        first = lines.next()
    if first is None or first[1].split()[0].upper() != "HIERARCHY":
        found = "an empty file" if first is None else repr(first[1][:40])
        where = 1 if first is None else first[0]
        raise lines.fail(where, f"found {found}; expected the keyword HIERARCHY (is this a BVH file?)")
    names, name_lines, parents, offsets, channels = [], [], [], [], []
    end_sites, end_parents = [], []
    stack: list[tuple[str, int]] = []  # open blocks: ("joint", index) or ("end", index)
    pending: tuple[str, int] | None = None  # a ROOT/JOINT/End Site line waiting for its "{"
    has_offset: dict[tuple[str, int], bool] = {}
    has_channels: set[int] = set()
    while True:
        item = lines.next()
        if item is None:
            what = f"inside {_describe(stack[-1], names)}" if stack else "after the hierarchy"
            raise lines.fail(lines.number, f"the file ends {what}; expected "
                             + ("'}'" if stack else "MOTION, Frames: and Frame Time: lines"))
        number, text = item
        tokens = text.split()
        while tokens:
            head = tokens[0]
            key = head.upper()
            if pending is not None and head != "{":
                raise lines.fail(number, f"found {head!r} after {_describe(pending, names)}; expected '{{'")
            if head == "{":
                if pending is None:
                    raise lines.fail(number, "found '{' without a ROOT, JOINT or End Site before it")
                stack.append(pending)
                has_offset[pending] = False
                pending = None
                tokens = tokens[1:]
            elif head == "}":
                if not stack:
                    raise lines.fail(number, "found '}' with no open block; expected MOTION after the hierarchy")
                block = stack.pop()
                if not has_offset[block]:
                    raise lines.fail(number, f"{_describe(block, names)} closes without an OFFSET; expected "
                                     "OFFSET x y z")
                if block[0] == "joint" and block[1] not in has_channels:
                    raise lines.fail(number, f"{_describe(block, names)} closes without CHANNELS; expected "
                                     "CHANNELS n followed by n channel names")
                tokens = tokens[1:]
            elif key in ("ROOT", "JOINT"):
                if key == "ROOT" and stack:
                    raise lines.fail(number, f"ROOT inside {_describe(stack[-1], names)}; expected JOINT")
                if key == "JOINT" and (not stack or stack[-1][0] != "joint"):
                    where = "outside any ROOT" if not stack else f"inside {_describe(stack[-1], names)}"
                    raise lines.fail(number, f"JOINT {' '.join(tokens[1:2])} {where}; expected it inside a ROOT or "
                                     "JOINT block")
                rest = tokens[1:]
                brace = rest.index("{") if "{" in rest else len(rest)
                if brace == 0:
                    raise lines.fail(number, f"{head} without a name; expected {head} NAME")
                name = "_".join(rest[:brace])  # a name with spaces becomes one word
                if name in names:
                    first_line = name_lines[names.index(name)]
                    raise lines.fail(number, f"joint name {name!r} already used on line {first_line}; expected unique "
                                     "names (a repeated name would make the hierarchy ambiguous or cyclic)")
                names.append(name)
                name_lines.append(number)
                parents.append(stack[-1][1] if stack else -1)
                offsets.append(None)
                channels.append(())
                pending = ("joint", len(names) - 1)
                tokens = rest[brace:]
            elif key == "END":
                if len(tokens) < 2 or tokens[1].upper() != "SITE":
                    raise lines.fail(number, f"found {' '.join(tokens[:2])!r}; expected 'End Site'")
                if not stack or stack[-1][0] != "joint":
                    where = f"inside {_describe(stack[-1], names)}" if stack else "outside any joint"
                    raise lines.fail(number, f"End Site {where}; expected it inside a ROOT or JOINT block")
                end_sites.append(None)
                end_parents.append(stack[-1][1])
                pending = ("end", len(end_sites) - 1)
                rest = tokens[2:]
                tokens = rest[rest.index("{"):] if "{" in rest else []
            elif key == "OFFSET":
                if not stack:
                    raise lines.fail(number, "OFFSET outside any block; expected it inside ROOT, JOINT or End Site")
                block = stack[-1]
                if has_offset[block]:
                    raise lines.fail(number, f"a second OFFSET for {_describe(block, names)}; expected one")
                if len(tokens) < 4:
                    raise lines.fail(number, f"OFFSET with {len(tokens) - 1} values; expected OFFSET x y z")
                xyz = _numbers(lines, number, tokens[1:4], "OFFSET")
                if block[0] == "joint":
                    offsets[block[1]] = xyz
                else:
                    end_sites[block[1]] = xyz
                has_offset[block] = True
                tokens = tokens[4:]
            elif key == "CHANNELS":
                if not stack or stack[-1][0] != "joint":
                    raise lines.fail(number, "CHANNELS outside a joint; expected it inside ROOT or JOINT")
                j = stack[-1][1]
                if j in has_channels:
                    raise lines.fail(number, f"a second CHANNELS line for joint {names[j]!r}; expected one")
                if len(tokens) < 2:
                    raise lines.fail(number, "CHANNELS without a count; expected CHANNELS n and n channel names")
                try:
                    count = int(tokens[1])
                except ValueError:
                    raise lines.fail(number, f"CHANNELS count {tokens[1]!r} is not a whole number; expected 0 to 6")
                if not 0 <= count <= 6:
                    raise lines.fail(number, f"CHANNELS {count}; expected 0 to 6 channels")
                given = tokens[2:2 + count]
                if len(given) != count or (len(tokens) > 2 + count and tokens[2 + count] not in ("{", "}")
                                           and tokens[2 + count].upper() not in ("JOINT", "END", "OFFSET")):
                    found = len(tokens) - 2
                    raise lines.fail(number, f"CHANNELS {count} is followed by {found} channel names; expected "
                                     f"exactly {count} of {', '.join(CHANNEL_NAMES)}")
                chs = []
                for c in given:
                    if c.lower() not in _CHANNEL_LOOKUP:
                        raise lines.fail(number, f"channel {c!r} of joint {names[j]!r}; expected one of "
                                         f"{', '.join(CHANNEL_NAMES)}")
                    chs.append(_CHANNEL_LOOKUP[c.lower()])
                if len(set(chs)) != len(chs):
                    raise lines.fail(number, f"joint {names[j]!r} lists a channel twice ({' '.join(given)}); "
                                     "expected distinct channels")
                channels[j] = tuple(chs)
                has_channels.add(j)
                tokens = tokens[2 + count:]
            elif key == "MOTION":
                if stack or pending is not None:
                    raise lines.fail(number, f"MOTION while {_describe(stack[-1] if stack else pending, names)} is "
                                     "still open; expected '}' first")
                if not names:
                    raise lines.fail(number, "MOTION before any ROOT; expected a ROOT block in the HIERARCHY")
                return MotionSkeleton(tuple(names), np.array(parents), np.array(offsets, dtype=float),
                                      tuple(channels), np.array(end_sites, dtype=float).reshape(-1, 3),
                                      np.array(end_parents, dtype=np.int64))
            else:
                inside = f" inside {_describe(stack[-1], names)}" if stack else ""
                raise lines.fail(number, f"found {head[:40]!r}{inside}; expected ROOT, JOINT, End Site, OFFSET, "
                                 "CHANNELS, '{', '}' or MOTION")


def _describe(block: tuple[str, int], names: list[str]) -> str:
    kind, i = block
    return f"joint {names[i]!r}" if kind == "joint" else "an End Site"


def _motion_header(lines: _Lines) -> tuple[int, float]:
    """The ``Frames: N`` and ``Frame Time: t`` lines after MOTION."""
    def next_line(expected: str) -> tuple[int, str]:
        item = lines.next()
        while item is not None and not item[1]:
            item = lines.next()
        if item is None:
            raise lines.fail(lines.number, f"the file ends after MOTION; expected a line {expected}")
        return item

    number, text = next_line("'Frames: N'")
    m = re.fullmatch(r"frames\s*:?\s*(\S+)", text, re.IGNORECASE)
    if not m:
        raise lines.fail(number, f"found {text[:40]!r}; expected 'Frames: N' (the number of frames)")
    try:
        frames = int(m.group(1))
    except ValueError:
        raise lines.fail(number, f"Frames: {m.group(1)[:20]!r} is not a whole number; expected Frames: N, N >= 0") \
            from None
    if frames < 0:
        raise lines.fail(number, f"Frames: {frames}; expected a count >= 0")
    number, text = next_line("'Frame Time: t' (seconds per frame)")
    m = re.fullmatch(r"frame\s*time\s*:?\s*(\S+)", text, re.IGNORECASE)
    if not m:
        raise lines.fail(number, f"found {text[:40]!r}; expected 'Frame Time: t' (seconds per frame)")
    try:
        frame_time = float(m.group(1))
    except ValueError:
        frame_time = float("nan")
    if not (math.isfinite(frame_time) and frame_time > 0):
        raise lines.fail(number, f"Frame Time: {m.group(1)[:20]!r}; expected a positive number of seconds "
                         "(e.g. 0.0083333 for 120 frames per second)")
    return frames, frame_time


def _parse_frames(data: bytes, first_line: int, n_channels: int, declared: int, lines: _Lines) -> np.ndarray:
    """(F, C) values of the frame lines in ``data`` (whose first line is file line ``first_line``)."""
    buf = np.frombuffer(data, dtype=np.uint8)
    n_lines = int(np.count_nonzero(buf == 10)) + 1
    counts = np.zeros(n_lines, dtype=np.int64)
    out = np.empty(len(buf) // 2 + 1)
    slow = np.empty((min(len(buf) // 2 + 1, _SLOW_TOKENS), 3), dtype=np.int64)
    n, n_slow, bad = _scan_numbers(buf, out, counts, slow)
    if bad == -2:  # many long or extreme numbers: every token through float(), same values
        counts[:] = 0
        slow = np.empty((len(buf) // 2 + 1, 3), dtype=np.int64)
        n, n_slow, bad = _scan_numbers(buf, out, counts, slow)
    if bad >= 0:
        line = first_line + int(np.count_nonzero(buf[:bad] == 10))
        end = bad
        while end < len(buf) and buf[end] not in b" \t\r\n\v\f":
            end += 1
        token = data[bad:end].decode("utf-8", errors="replace")
        frame = int(np.count_nonzero(counts[:line - first_line])) + 1
        raise lines.fail(line, f"{token[:40]!r} is not a number (frame {frame}); expected {n_channels} numbers per "
                         "frame line")
    for k in range(n_slow):
        i, s, e = slow[k]
        out[i] = float(data[s:e])
    values = out[:n]
    if not np.isfinite(values).all():
        i = int(np.flatnonzero(~np.isfinite(values))[0])
        line = first_line + int(np.searchsorted(np.cumsum(counts), i, side="right"))
        raise lines.fail(line, f"a value overflows to infinity; expected finite channel values")
    filled = np.flatnonzero(counts)
    wrong = filled[counts[filled] != n_channels]
    if len(wrong):
        line = first_line + int(wrong[0])
        frame = int(np.searchsorted(filled, wrong[0])) + 1
        raise lines.fail(line, f"frame {frame} has {int(counts[wrong[0]])} values; expected {n_channels} (one per "
                         "channel of the hierarchy)")
    if n_channels == 0:
        found = declared  # with no channels, frame lines are empty: the count cannot be checked
    else:
        found = len(filled)
    if found != declared:
        last = first_line + (int(filled[-1]) if len(filled) else 0)
        if found < declared:
            raise lines.fail(last, f"the file ends after {found} frame lines; Frames: declares {declared} "
                             "(truncated file, or a wrong Frames: count)")
        extra = first_line + int(filled[declared])
        raise lines.fail(extra, f"frame line {declared + 1} found; Frames: declares {declared} (fix the count or "
                         "remove the extra lines)")
    return values.reshape(declared, n_channels) if n_channels else np.zeros((declared, 0))


def _resolve_translation(mode: str, skeleton: MotionSkeleton, values: np.ndarray) -> str:
    if mode not in _TRANSLATION_MODES:
        raise MotionError(f"translation {mode!r}: expected one of {', '.join(_TRANSLATION_MODES)}")
    if mode != "auto":
        return mode
    starts = skeleton.channel_starts
    near_offset, near_zero = [], []
    for j, ch in enumerate(skeleton.channels):
        for k, c in enumerate(ch):
            if c.endswith("position") and skeleton.offsets[j, _AXIS[c[0]]] != 0 and len(values):
                v = values[:, starts[j] + k]
                near_offset.append(np.median(np.abs(v - skeleton.offsets[j, _AXIS[c[0]]])))
                near_zero.append(np.median(np.abs(v)))
    if not near_offset:
        return "replace"  # every translated joint has a zero offset: both readings agree
    return "replace" if np.median(near_offset) <= np.median(near_zero) else "add"


def parse_bvh(data: bytes | str, name: str = "<bvh>", unit="auto", translation: str = "auto") -> Motion:
    """A ``Motion`` from the text of a BVH file (``name`` labels error messages).

    unit: metres per file unit, a unit name or "auto" (``resolve_unit``); translation: "auto",
    "replace" or "add" (module docstring).
    """
    raw = data.encode("utf-8") if isinstance(data, str) else bytes(data)
    if raw.startswith(b"\xef\xbb\xbf"):  # a UTF-8 byte order mark, as some Windows tools write
        raw = raw[3:]
    lines = _Lines(raw, name)
    skeleton = _parse_hierarchy(lines)
    declared, frame_time = _motion_header(lines)
    values = _parse_frames(raw[lines.pos:], lines.number + 1, skeleton.n_channels, declared, lines)
    unit_m, note = resolve_unit(unit, skeleton)
    mode = _resolve_translation(translation, skeleton, values)
    return Motion(skeleton, values, frame_time, unit_m, note, mode, Path(name).stem if name != "<bvh>" else "motion")


def read_bvh(path: str | Path, unit="auto", translation: str = "auto") -> Motion:
    """Read a BVH file (see ``parse_bvh``); errors name the file and line."""
    path = Path(path)
    try:
        raw = path.read_bytes()
    except IsADirectoryError:
        raise MotionError(f"{path}: is a folder; expected a .bvh file") from None
    except FileNotFoundError:
        raise MotionError(f"{path}: no such file; expected a .bvh motion capture file") from None
    return parse_bvh(raw, str(path), unit=unit, translation=translation)


# ----------------------------------------------------------------------------- writing

def _fmt(x: float, precision: int) -> str:
    s = f"{x:.{precision}f}"
    return "0." + "0" * precision if s.lstrip("-").strip("0.") == "" and precision > 0 else s


def format_bvh(motion: Motion, precision: int = 6) -> str:
    """The BVH text of ``motion``: offsets and values with ``precision`` decimals, each joint's
    channels in its own order, End Sites where the skeleton has them, tabs for nesting."""
    if not (isinstance(precision, (int, np.integer)) and 0 <= precision <= 17):
        raise MotionError(f"precision {precision!r}: expected a whole number of decimals from 0 to 17")
    sk = motion.skeleton
    out = ["HIERARCHY"]
    children = [[] for _ in range(sk.n_joints)]
    for j, p in enumerate(sk.parents):
        if p >= 0:
            children[p].append(j)
    ends = [[] for _ in range(sk.n_joints)]
    for e, p in enumerate(sk.end_site_parents):
        ends[p].append(e)
    order = []  # joints in the order written: must match the channel order of the values

    def offset(v) -> str:
        return " ".join(_fmt(x, precision) for x in v)

    def joint(j: int, depth: int) -> None:
        tab = "\t" * depth
        order.append(j)
        out.append(f"{tab}{'ROOT' if sk.parents[j] < 0 else 'JOINT'} {sk.names[j]}")
        out.append(f"{tab}{{")
        out.append(f"{tab}\tOFFSET {offset(sk.offsets[j])}")
        out.append(f"{tab}\tCHANNELS {len(sk.channels[j])}" + "".join(f" {c}" for c in sk.channels[j]))
        for c in children[j]:
            joint(c, depth + 1)
        for e in ends[j]:
            out.extend([f"{tab}\tEnd Site", f"{tab}\t{{", f"{tab}\t\tOFFSET {offset(sk.end_sites[e])}", f"{tab}\t}}"])
        out.append(f"{tab}}}")

    for r in np.flatnonzero(sk.parents < 0):
        joint(int(r), 0)
    starts, counts = sk.channel_starts, [len(c) for c in sk.channels]
    cols = np.concatenate([np.arange(starts[j], starts[j] + counts[j]) for j in order]).astype(np.int64)
    values = motion.values[:, cols]
    out += ["MOTION", f"Frames: {motion.n_frames}", f"Frame Time: {motion.frame_time:.10g}"]
    if values.shape[1]:
        row = " ".join([f"%.{precision}f"] * values.shape[1])
        rounded = np.round(values, precision) + 0.0  # + 0.0 turns -0.0 into 0.0
        out.extend(row % tuple(r) for r in rounded.tolist())
    else:
        out.extend([""] * motion.n_frames)
    return "\n".join(out) + "\n"


def write_bvh(path: str | Path, motion: Motion, precision: int = 6) -> Path:
    """Write ``motion`` as a BVH file (atomically: a temporary name, then a rename).

    Joints are written depth first; a skeleton whose joints are already in that order (any
    skeleton read from a file) keeps its joint and channel order exactly, so a read of the
    result gives the same skeleton and the values rounded to ``precision`` decimals.
    """
    text = format_bvh(motion, precision)
    path = Path(path)
    with atomic_path(path) as tmp:
        Path(tmp).write_text(text, encoding="utf-8")
    return path


def skeleton_from_rig(skeleton: Skeleton, frames: int = 1, frame_time: float = 1 / 30,
                      order: str = "ZXY") -> Motion:
    """A rig's skeleton as a BVH motion held at rest (metres, our axes: +Y up, +Z front).

    Joints are the bones in depth-first order (each at its head, OFFSET = head - parent's head),
    the root with position and rotation channels, the others with rotations in ``order``; an
    end bone gets an End Site at its tail. ``frames`` frames of the rest pose.
    """
    if sorted(order) != ["X", "Y", "Z"]:
        raise MotionError(f"order {order!r}: expected three distinct axes such as 'ZXY'")
    children = [[] for _ in range(skeleton.n_bones)]
    for b, p in enumerate(skeleton.parents):
        if p >= 0:
            children[p].append(b)
    seq, todo = [], [int(r) for r in np.flatnonzero(skeleton.parents < 0)][::-1]
    while todo:
        b = todo.pop()
        seq.append(b)
        todo.extend(children[b][::-1])
    where = {b: i for i, b in enumerate(seq)}
    parents = np.array([where[skeleton.parents[b]] if skeleton.parents[b] >= 0 else -1 for b in seq])
    heads = skeleton.heads[seq]
    offsets = heads - np.where(parents[:, None] >= 0, heads[np.maximum(parents, 0)], 0.0)
    rot = tuple(f"{a}rotation" for a in order)
    channels = tuple((("Xposition", "Yposition", "Zposition") + rot) if p < 0 else rot for p in parents)
    leaves = [i for i, b in enumerate(seq) if not children[b]]
    ends = skeleton.tails[[seq[i] for i in leaves]] - heads[leaves]
    sk = MotionSkeleton(tuple(skeleton.bone_names[b] for b in seq), parents, offsets, channels, ends,
                        np.array(leaves, dtype=np.int64))
    values = np.zeros((int(frames), sk.n_channels))
    for j in np.flatnonzero(parents < 0):
        s0 = sk.channel_starts[j]
        values[:, s0:s0 + 3] = offsets[j]
    return Motion(sk, values, frame_time, 1.0, "given: metres (a rig's skeleton)", "replace", skeleton.name)
