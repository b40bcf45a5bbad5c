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
from bodyspace.mesh.geometry import face_normals, sample_surface
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


@dataclass(frozen=True)
class RawScan:
    """A raw scan and its truth.

    points: (P, 3) in the scan's frame (``frame``: ``to_frame`` arguments; millimetres).
    truth_vertex: (P,) the template vertex each point was sampled next to, -1 for an outlier.
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
        """(P,) bool: points on the body (not outliers)."""
        return self.truth_vertex >= 0

    def landmark_file(self) -> dict:
        """The landmarks as a ``--landmarks`` document: {"landmarks": {name: [x, y, z]}, "unit": ...}."""
        unit = {1.0: "m", 100.0: "cm", 1000.0: "mm"}.get(float(self.frame["scale"]), "m")
        return {"landmarks": {k: [float(c) for c in v] for k, v in self.landmarks.items()}, "unit": unit}


def raw_scan(template: Template, phenotype_model, rng=None, *, n_points: int = 80_000, sigma: float = 0.002,
             outlier_share: float | None = None, phenotype: np.ndarray | None = None, pose: str | None = None,
             frame: dict | None = None, holes: bool = True, mset: MeasurementSet | None = None,
             weights: str = "original", preserve_volume: bool = False) -> RawScan:
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
    """
    rng = as_generator(rng)
    if not 100 <= int(n_points) <= 2_000_000:
        raise ParameterError(f"n_points={n_points}; expected 100 to 2,000,000")
    if sigma < 0:
        raise ParameterError(f"sigma={sigma}; expected a noise level >= 0 (metres)")
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
    all_points = np.concatenate([points, outliers])
    all_truth = np.concatenate([truth, np.full(len(outliers), -1)])
    order = rng.permutation(len(all_points))          # a scanner's order tells nothing
    return RawScan(to_frame(all_points[order], **frame), all_truth[order], body,
                   {k: to_frame(v, **frame) for k, v in lm.items()}, phenotype, pose, frame)
