"""The floor a scanned body stands on: a ground sheet, a turntable's top, found in points.

Photogrammetry and booth scans carry the ground or the turntable the body stands on, a separate
component or welded to the soles. ``find_floor`` finds such a plane by RANSAC in a body's points
(metres) and ``remove_floors`` takes every floor away (a turntable: the ground, then its top).
Used by the registration (``register.prepare``) on a scan's points; ``mesh_floor`` finds it in
points sampled from a mesh's faces, for the measurement door (``measure.conventions.body_faces``)
and the rigging (``rig.scan_body``).
"""

from __future__ import annotations

import numpy as np

from bodyspace.mesh.geometry import sample_surface

__all__ = ["find_floor", "remove_floors", "mesh_floor", "sheet_width"]

# The floor (photogrammetry and booth scans carry the ground or the turntable the body stands on):
# a plane found by RANSAC (``FLOOR_TRIALS`` planes through three points of a ``FLOOR_SAMPLE``
# subsample) holding at least ``FLOOR_MIN_SHARE`` of the points within ``FLOOR_TOLERANCE``
# (metres; the scanner's noise is 2-5 mm), spread over at least ``FLOOR_MIN_WIDTH`` both ways (a
# sheet, not a flat patch of a back or a thigh), with the rest of the scan standing on it: at
# least ``FLOOR_MIN_HEIGHT`` of it along the plane's normal and all but ``FLOOR_BELOW_SHARE`` on
# one side (a wall behind the body holds the body within 0.4 m of it and is not a floor; a
# turntable's side, at most ``FLOOR_BELOW_SHARE`` of the points and ``FLOOR_BELOW_DEPTH`` deep, may
# lie below its top; a plane through a body's middle has half the body beyond it). Found,
# the plane and everything beyond it are removed, then the next one is looked for (a turntable:
# the ground around it, then its top with its side below): at most ``FLOOR_ROUNDS``.
FLOOR_SAMPLE = 20_000
FLOOR_TRIALS = 300
FLOOR_TOLERANCE = 0.012
FLOOR_MIN_SHARE = 0.03
FLOOR_MIN_WIDTH = 0.5
FLOOR_MIN_HEIGHT = 1.0
FLOOR_BELOW_SHARE = 0.25
FLOOR_BELOW_DEPTH = 0.4
FLOOR_ROUNDS = 3
# Points within this many of the plane's noise widths (1.4826 times the median absolute height of
# the points within FLOOR_TOLERANCE of it, at least FLOOR_MIN_NOISE) are the floor's: the soles that touch it go with it (a scanner never sees
# them) and the rest of the feet stay.
FLOOR_CUT_SIGMAS = 3.0
FLOOR_MIN_NOISE = 0.002
# A floor's normal within this angle of a given up axis (--up): a plane at another angle is not
# the floor of a body standing along that axis.
FLOOR_UP_DEGREES = 25.0


def find_floor(points: np.ndarray, up: np.ndarray | None = None, rng=0, below_share: float = FLOOR_BELOW_SHARE
               ) -> tuple[np.ndarray, float] | None:
    """The floor a scanned body stands on (module constants ``FLOOR_*``), or None.

    points: (P, 3) metres; up: (3,) the up direction if known (the floor's normal must be within
    ``FLOOR_UP_DEGREES`` of it), None to accept any plane the rest of the scan stands on.
    below_share: the share of the rest that may lie below it (a scan sees little of a turntable's
    side; a mesh has all of it: ``measure.conventions`` gives more).
    Returns (normal (3,) unit, pointing to the body; offset d): the plane ``points @ normal = d``,
    and the points' signed heights over it are ``points @ normal - d``.
    """
    rng = np.random.default_rng(rng)
    if len(points) < 100:
        return None
    sub = points[rng.choice(len(points), min(FLOOR_SAMPLE, len(points)), replace=False)]
    tri = sub[rng.integers(0, len(sub), (FLOOR_TRIALS, 3))]                    # (T, 3, 3)
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    length = np.linalg.norm(n, axis=1)
    ok = length > 1e-9
    n, tri = n[ok] / length[ok, None], tri[ok]
    if up is not None:
        n = np.where((n @ up)[:, None] < 0, -n, n)
        good = n @ up > np.cos(np.radians(FLOOR_UP_DEGREES))
        n, tri = n[good], tri[good]
    if not len(n):
        return None
    d = np.einsum("tj,tj->t", n, tri[:, 0])
    # Inlier counts of every trial plane, in blocks (T × P distances at once would be 48 MB).
    counts = np.concatenate([(np.abs(sub @ n[i:i + 64].T - d[i:i + 64]) < FLOOR_TOLERANCE).sum(axis=0)
                             for i in range(0, len(n), 64)])
    best = int(np.argmax(counts))
    if counts[best] < FLOOR_MIN_SHARE * len(sub):
        return None
    # Least squares on the inliers (twice: the first pass's inliers may take in a sole).
    normal, offset = n[best], d[best]
    for _ in range(2):
        on = sub[np.abs(sub @ normal - offset) < FLOOR_TOLERANCE]
        centre = on.mean(axis=0)
        _, _, vt = np.linalg.svd(on - centre, full_matrices=False)
        normal = vt[2] * (1.0 if vt[2] @ normal >= 0 else -1.0)
        offset = float(normal @ centre)
    on = sub[np.abs(sub @ normal - offset) < FLOOR_TOLERANCE]
    if len(on) < FLOOR_MIN_SHARE * len(sub):
        return None
    # A sheet: spread at least FLOOR_MIN_WIDTH along both of its in-plane axes (robust extents).
    flat = (on - on.mean(axis=0)) @ vt[:2].T
    width = np.percentile(flat, 98, axis=0) - np.percentile(flat, 2, axis=0)
    if width.min() < FLOOR_MIN_WIDTH:
        return None
    # The rest stands on it: on one side, and tall along the normal.
    height = sub @ normal - offset
    rest = height[np.abs(height) >= FLOOR_TOLERANCE]
    if len(rest) < FLOOR_MIN_SHARE * len(sub):
        return None
    if np.median(rest) < 0:
        normal, offset, rest = -normal, -offset, -rest
    below = rest[rest < 0]
    if np.percentile(rest, 99) < FLOOR_MIN_HEIGHT or len(below) > below_share * len(rest) or (
            len(below) > 0.01 * len(rest) and np.percentile(-below, 99) > FLOOR_BELOW_DEPTH):
        return None
    if up is not None and normal @ up < np.cos(np.radians(FLOOR_UP_DEGREES)):
        return None
    return normal, offset


def remove_floors(points: np.ndarray, up: np.ndarray | None = None, rng=0) -> tuple[np.ndarray, list[str], list]:
    """Points (P, 3) metres without the floors ``find_floor`` finds (a ground plane, a turntable's
    top and the ground around it): (the (P,) bool mask of points kept, a sentence per floor, the
    floors as (normal (3,) towards the body, offset, cut): a point x is kept when
    ``x @ normal - offset >= cut`` for every one)."""
    keep = np.ones(len(points), dtype=bool)
    notes, planes = [], []
    for _ in range(FLOOR_ROUNDS):
        idx = np.flatnonzero(keep)
        found = find_floor(points[idx], up, rng)
        if found is None:
            break
        normal, offset = found
        height = points[idx] @ normal - offset
        near = np.abs(height) < FLOOR_TOLERANCE
        # The median absolute height of the points near it (a turntable's side below its top
        # would inflate an RMS).
        noise = max(1.4826 * float(np.median(np.abs(height[near]))), FLOOR_MIN_NOISE)
        cut = height < FLOOR_CUT_SIGMAS * noise
        keep[idx[cut]] = False
        planes.append((normal, offset, FLOOR_CUT_SIGMAS * noise))
        what = "the floor" if not notes else "a platform on it (a turntable's top with its side)"
        notes.append(f"removed {what}: {int(cut.sum())} points ({100 * cut.mean():.1f} %) on a flat sheet "
                     f"{100 * sheet_width(points[idx[near]], normal):.0f} cm across the body stands "
                     f"on, within {1000 * FLOOR_CUT_SIGMAS * noise:.0f} mm of it or below it")
        if up is None:
            up = normal           # a second floor (a turntable's top) is parallel to the first
    return keep, notes, planes


# A mesh holds all of a turntable's side below its top (a scan sees little of it: 0.25 there):
# up to this share of the rest may lie below the floor's plane.
FLOOR_BELOW_SHARE_MESH = 0.45
# Points sampled from a mesh's faces to look for the floor in (find_floor takes a subsample of 20,000).
FLOOR_SAMPLES = 20_000


def mesh_floor(vertices: np.ndarray, faces: np.ndarray, scale: float,
               up: np.ndarray | None = None) -> tuple[np.ndarray, float, float] | None:
    """The floor under a mesh (``find_floor`` in ``FLOOR_SAMPLES`` points sampled from ``faces``),
    or None: (normal (3,) towards the body, offset (metres), noise (metres): the robust spread of
    the sampled points within ``FLOOR_TOLERANCE`` of the plane, at least ``FLOOR_MIN_NOISE``).

    vertices: (V, 3) mesh units, ``scale`` metres each; faces: (F, 3) the faces to look in; up: as
    in ``find_floor``. A vertex x's height over the floor is ``x @ normal * scale - offset``.
    """
    points = sample_surface(vertices, faces, FLOOR_SAMPLES, 0)[0] * scale
    found = find_floor(points, up, 0, FLOOR_BELOW_SHARE_MESH)
    if found is None:
        return None
    normal, offset = found
    near = np.abs(points @ normal - offset)
    near = near[near < FLOOR_TOLERANCE]
    noise = max(1.4826 * float(np.median(near)), FLOOR_MIN_NOISE) if len(near) else FLOOR_MIN_NOISE
    return normal, offset, noise


def sheet_width(points: np.ndarray, normal: np.ndarray) -> float:
    """How far across a floor's points (P, 3) are within its plane (``normal`` (3,)): twice the
    98th percentile of their distances from their centroid (the same units as ``points``)."""
    flat = points - points.mean(axis=0)
    flat = flat - np.outer(flat @ normal, normal)
    return 2 * float(np.percentile(np.linalg.norm(flat, axis=1), 98))
