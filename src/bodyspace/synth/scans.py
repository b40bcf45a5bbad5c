"""Raw test scans with known truth: point clouds as a body scanner delivers them.

A registered mesh (``synth.foreign``) already has a surface and a vertex order; a scanner gives
neither. ``raw_scan`` makes what one gives (issue 15): a body the model never saw (an
edge-of-population phenotype, ``foreign_phenotype``), posed by the rig, sampled as a point cloud
of 50-200 k points, area-uniform over the surface, with

- Gaussian noise (σ = 2 mm per coordinate by default),
- holes where scanners see nothing: the top of the head, the soles, the armpits, the crotch
  (``hole_sites``), and every point of a downward-facing face near the floor,
- 2-5 % outliers: half spread over the bounding box (reflections, dust), half floating a few
  centimetres off the skin (hair, clothing),
- millimetres, Z up, turned about the vertical and moved off the origin (``to_frame``).

Optional artefacts of real rigs (``raw_scan(floor=..., view=...)``): the ground the body stands on
(``"plane"``: a scanned disc ``FLOOR_RADIUS`` wide, points under the feet included, as
photogrammetry reconstructs it; ``"turntable"``: a platform ``TURNTABLE_HEIGHT`` high the body
stands on, its top and side), and a single view (``"front"``: only the surface facing the
camera, as one Kinect or phone LiDAR capture sees it; self-occlusion is not modelled).

The truth is kept: every point's template vertex (the corner of its face nearest the point; -1
for an outlier), the body on the template topology (metres, +Y up), its landmarks in the scan's
frame. Registration is scored against it: the registered template vertex ``i`` should land where
the true body's vertex ``i`` is (``correspondence error``), and on the scan (``surface distance``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from bodyspace.data.template import Template
from bodyspace.errors import ParameterError
from bodyspace.measure.definitions import MeasurementSet, load_measurement_set
from bodyspace.mesh.geometry import face_areas, face_normals, sample_surface
from bodyspace.rig.posing import pose_bodies
from bodyspace.synth.foreign import foreign_phenotype, hole_sites, to_frame
from bodyspace.synth.poses import load_pose_library
from bodyspace.validation import as_generator

__all__ = ["RawScan", "raw_scan", "sample_surface", "SCAN_FRAME"]

# The scan's frame: millimetres, Z up (facing -Y before the turn), turned 40° about the vertical,
# the floor 170 mm below the origin and the body off-centre.
SCAN_FRAME = dict(up="z", scale=1000.0, translation=(0.31, -0.17, 0.58), yaw_degrees=40.0)
# Hole radii (metres) around the sites of ``hole_sites``: head top, crotch, soles, armpits.
HOLE_RADIUS = {"head_top": 0.06, "crotch": 0.05, "sole": 0.05, "armpit": 0.05}
# Faces whose normal points this much downwards within this height of the floor are soles.
SOLE_NORMAL_Y = -0.6
SOLE_HEIGHT = 0.04
# Floating outliers: this far off the skin (metres).
FLOATING_RANGE = (0.02, 0.12)
# The scanned ground: a disc of this radius (metres) around the body, sampled as densely as the
# body; a turntable: a cylinder of this radius and height the body stands on.
FLOOR_RADIUS = 0.8
TURNTABLE_RADIUS = 0.45
TURNTABLE_HEIGHT = 0.10
FLOORS = ("plane", "turntable")
# Single views: the direction (body frame, +Z front) the camera looks from; a face is seen when its
# normal points towards it by more than this cosine.
VIEWS = {"front": (0.0, 0.0, 1.0), "back": (0.0, 0.0, -1.0)}
VIEW_COSINE = 0.05


@dataclass(frozen=True)
class RawScan:
    """A raw scan and its truth.

    points: (P, 3) in the scan's frame (``frame``: ``to_frame`` arguments; millimetres).
    truth_vertex: (P,) the template vertex each point was sampled next to, -1 for an outlier,
        -2 for a point of the floor (``raw_scan(floor=...)``).
    body: (V, 3) the true body on the template topology, metres, +Y up, on the ground.
    landmarks: name → (3,) the measurement set's landmarks of ``body`` in the scan's frame.
    phenotype: (11,); pose: its library name; frame: the ``to_frame`` arguments.
    """

    points: np.ndarray
    truth_vertex: np.ndarray
    body: np.ndarray
    landmarks: dict[str, np.ndarray]
    phenotype: np.ndarray
    pose: str
    frame: dict

    @property
    def inliers(self) -> np.ndarray:
        """(P,) bool: points on the body (not outliers, not the floor)."""
        return self.truth_vertex >= 0

    def landmark_file(self) -> dict:
        """The landmarks as a ``--landmarks`` document: {"landmarks": {name: [x, y, z]}, "unit": ...}."""
        unit = {1.0: "m", 100.0: "cm", 1000.0: "mm"}.get(float(self.frame["scale"]), "m")
        return {"landmarks": {k: [float(c) for c in v] for k, v in self.landmarks.items()}, "unit": unit}


def raw_scan(template: Template, phenotype_model, rng=None, *, n_points: int = 80_000, sigma: float = 0.002,
             outlier_share: float | None = None, phenotype: np.ndarray | None = None, pose: str | None = None,
             frame: dict | None = None, holes: bool = True, mset: MeasurementSet | None = None,
             weights: str = "original", preserve_volume: bool = False, floor: str | None = None,
             view: str | None = None) -> RawScan:
    """One raw scan of a body the model never saw (see the module docstring).

    template: the ``Template``; phenotype_model: its ``PhenotypeModel``.
    n_points: points sampled on the body before holes are cut (the scan keeps ~95 % of them)
        plus the outliers. sigma: noise per coordinate, metres. outlier_share: outliers as a
        share of the body's points (default: drawn in [0.02, 0.05]).
    phenotype: (11,) (default ``foreign_phenotype(rng)``); pose: a pose library name (default:
        drawn from the library's standing poses). frame: ``to_frame`` arguments (default
        ``SCAN_FRAME``, its yaw drawn in [0, 360) degrees unless given).
    weights, preserve_volume: how the body is posed (``pose_bodies``'s): a scan posed otherwise than
        the registration's own forward model (MakeHuman's weights, plain LBS) tests a fit that
        does not share the scan's skinning, as a real body's does not.
    floor: None, "plane" (a scanned ground disc) or "turntable" (a platform the body stands on,
        its top, side and the ground around it): points with ``truth_vertex`` -2 (neither body
        nor outlier; ``RawScan.inliers`` leaves them out). view: None (all round) or "front" /
        "back": only the surface facing that camera.
    """
    rng = as_generator(rng)
    if not 100 <= int(n_points) <= 2_000_000:
        raise ParameterError(f"n_points={n_points}; expected 100 to 2,000,000")
    if sigma < 0:
        raise ParameterError(f"sigma={sigma}; expected a noise level >= 0 (metres)")
    if floor is not None and floor not in FLOORS:
        raise ParameterError(f"floor={floor!r}; expected None or one of {', '.join(FLOORS)}")
    if view is not None and view not in VIEWS:
        raise ParameterError(f"view={view!r}; expected None or one of {', '.join(VIEWS)}")
    mset = mset if mset is not None else load_measurement_set()
    library = load_pose_library()
    rig = template.rigs["default"]
    phenotype = foreign_phenotype(rng) if phenotype is None else np.asarray(phenotype, dtype=float)
    if pose is None:
        standing = [p for p in library.names if p not in ("squat", "sitting", "kneeling", "lying")]
        pose = str(rng.choice(standing))
    frame = dict(SCAN_FRAME, yaw_degrees=float(rng.uniform(0.0, 360.0))) | (frame or {})
    rest = phenotype_model.vertices(phenotype[None])[0]
    body = pose_bodies(rest, rig, library.rotations(pose, rig), on_ground=True, weights=weights,
                       preserve_volume=preserve_volume, faces=template.faces)
    faces = template.faces
    lm = dict(zip(mset.landmark_names, mset.landmark_matrix(template.n_vertices) @ body))

    points, face, bary = sample_surface(body, faces, n_points, rng)
    truth = faces[face][np.arange(len(face)), np.argmax(bary, axis=1)]
    keep = np.ones(len(points), dtype=bool)
    if holes:
        sites = hole_sites(body, lm)        # head top, crotch, sole l, armpit l, sole r, armpit r
        radius = [HOLE_RADIUS["head_top"], HOLE_RADIUS["crotch"], HOLE_RADIUS["sole"], HOLE_RADIUS["armpit"],
                  HOLE_RADIUS["sole"], HOLE_RADIUS["armpit"]]
        for site, r in zip(sites, radius):
            keep &= np.linalg.norm(points - site, axis=1) > r
        fn = face_normals(body, faces)[face]
        keep &= ~((fn[:, 1] < SOLE_NORMAL_Y) & (points[:, 1] < body[:, 1].min() + SOLE_HEIGHT))
    if view is not None:
        keep &= face_normals(body, faces)[face] @ np.asarray(VIEWS[view]) > VIEW_COSINE
    points, truth, face = points[keep], truth[keep], face[keep]
    points = points + rng.normal(0.0, sigma, points.shape)

    share = rng.uniform(0.02, 0.05) if outlier_share is None else float(outlier_share)
    n_out = int(round(share * len(points)))
    n_box = n_out // 2
    lo, hi = body.min(axis=0) - 0.1, body.max(axis=0) + 0.1
    box = rng.uniform(lo, hi, (n_box, 3))
    # Floating points: off the skin along the face normal, kept only if no skin is nearer.
    src = rng.integers(0, len(points), n_out - n_box)
    fn = face_normals(body, faces)[face[src]]
    floating = points[src] + fn * rng.uniform(*FLOATING_RANGE, (len(src), 1))
    outliers = np.concatenate([box, floating])
    far = cKDTree(body).query(outliers)[0] > FLOATING_RANGE[0]
    outliers = outliers[far]
    ground = np.zeros((0, 3))
    if floor is not None:
        # As densely sampled as the body (points per square metre of its surface).
        density = n_points / float(face_areas(body, faces).sum())
        ground = _ground(body, floor, density, rng)
        if view is not None:
            ground = ground[ground[:, 2] * VIEWS[view][2] > -0.2]     # the part of the ground in view
        ground = ground + rng.normal(0.0, sigma, ground.shape)
    all_points = np.concatenate([points, outliers, ground])
    all_truth = np.concatenate([truth, np.full(len(outliers), -1), np.full(len(ground), -2)])
    order = rng.permutation(len(all_points))          # a scanner's order tells nothing
    return RawScan(to_frame(all_points[order], **frame), all_truth[order], body,
                   {k: to_frame(v, **frame) for k, v in lm.items()}, phenotype, pose, frame)


def _disc(centre: np.ndarray, radius: float, y: float, n: int, rng) -> np.ndarray:
    """(n, 3) points area-uniform on a horizontal disc at height y."""
    r = radius * np.sqrt(rng.uniform(0.0, 1.0, n))
    a = rng.uniform(0.0, 2 * np.pi, n)
    return np.column_stack([centre[0] + r * np.cos(a), np.full(n, y), centre[1] + r * np.sin(a)])


def _ground(body: np.ndarray, floor: str, density: float, rng) -> np.ndarray:
    """Points (G, 3) of what the body (V, 3), metres, +Y up, on the ground, stands on: ``floor``
    "plane" or "turntable" (the body raised onto its top: the platform's top, its side and a ring
    of ground around it), ``density`` points per square metre."""
    centre = np.median(body[:, [0, 2]], axis=0)
    y0 = float(body[:, 1].min())
    if floor == "plane":
        return _disc(centre, FLOOR_RADIUS, y0, int(density * np.pi * FLOOR_RADIUS ** 2), rng)
    # The turntable's top is at the body's feet; its side goes down TURNTABLE_HEIGHT to the ground.
    r, h = TURNTABLE_RADIUS, TURNTABLE_HEIGHT
    top = _disc(centre, r, y0, int(density * np.pi * r ** 2), rng)
    n_side = int(density * 2 * np.pi * r * h)
    a = rng.uniform(0.0, 2 * np.pi, n_side)
    side = np.column_stack([centre[0] + r * np.cos(a), y0 - rng.uniform(0.0, h, n_side), centre[1] + r * np.sin(a)])
    ring = _disc(centre, FLOOR_RADIUS, y0 - h, int(density * np.pi * FLOOR_RADIUS ** 2), rng)
    ring = ring[np.linalg.norm(ring[:, [0, 2]] - centre, axis=1) > r]
    return np.concatenate([top, side, ring])
