"""How well a registration explains its scan, body part by body part, and the refusal of fits
that do not.

A fit always returns *a* body; what tells a good fit from a confident wrong one (two people, a
chair, a scan cut in half, a hand placed on the thigh while the scan's hand hangs 20 cm away) is
how much of the scan the registered surface explains and how much of the registered surface lies
on the scan. The whole-body shares alone cannot see a lost hand: a hand is 1-2 % of a body's
area, so a fit that lost one still explains 98 % of the points (measured: a step-forward scan
whose left hand ended 236 mm off the truth had quality 0.96 and was accepted). So every body part
is checked both ways too:

Whole body:

- ``explained``: the share of scan points within ``EXPLAINED_DISTANCE`` of the registered
  surface (isolated outliers are removed first: a good fit explains 99.5-100 % of the test
  scans; two people: about 0.5; a chair: the share of the chair a body happens to cover);
- ``coverage``: the share of template vertices that had a target at the last NICP iteration
  (holes under the arms and the soles, and fine parts whose scan normals are too noisy for the
  30° gate: toes, fingers, face, leave 25-30 % without on the test scans).

Per body part (``PARTS``: the head, the trunk, and each side's upper arm, forearm, hand, thigh,
lower leg and foot; a vertex's part is its dominant bone's, ``body_parts``):

- fit → scan, ``seen``: the share of the part's vertices with a scan point within
  ``SEEN_DISTANCE`` (a placed part lies on its points; the holes of a scan, the soles and the top
  of the head, are allowed for by ``SEEN_GOOD`` per part); ``distance``: their mean distance to
  the nearest scan point;
- scan → fit, ``unexplained``: the area (m²) of scan surface, in patches of at least
  ``PATCH_MIN_AREA``, farther than ``EXPLAINED_DISTANCE`` from the fit, whose nearest registered
  surface is the part's: a lost hand leaves its scan points unexplained beside whatever part of
  the fit is nearest them (the forearm it hangs from, the thigh it swings by). Isolated outliers
  make no patch.

A lost part leaves both marks: its own vertices off the scan and its scan points unexplained. So
the two are read together: a part's seen share counts only when a patch of unexplained scan lies
within ``LOST_REACH`` of it (a part the scanner missed is a hole, not a lost part), and a patch
counts as ``unexplained`` only when a part below its ``SEEN_GOOD`` lies within ``LOST_REACH`` of it;
a patch with every part near it on its points is surface the fit bridges (a heavy belly's fold,
an object beside the body), reported per part as ``bridged`` and not refused (the whole-body
``explained`` share still sees it). A part's quality is ``min(seen / SEEN_GOOD[part], 1 -
unexplained / (UNEXPLAINED_SHARE · the part's area))`` clipped to [0, 1]; the whole's ``quality`` is the least of
``explained / EXPLAINED_GOOD``, ``coverage / COVERAGE_GOOD``, every part's quality and 1. A scan is
refused below ``MIN_QUALITY`` and the refusal names the part (``Quality.describe``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from bodyspace.data.template import Template
from bodyspace.errors import RigError
from bodyspace.mesh.geometry import face_areas
from bodyspace.synth.foreign import closest_points

__all__ = ["Quality", "PartQuality", "assess", "assess_parts", "body_parts", "PARTS", "EXPLAINED_DISTANCE",
           "MIN_QUALITY"]

EXPLAINED_DISTANCE = 0.010
EXPLAINED_GOOD = 0.97
COVERAGE_GOOD = 0.60
MIN_QUALITY = 0.90
# Scan points the shares are computed on (a fixed random subsample: ±0.5 % at 20,000).
ASSESS_POINTS = 20_000
# Body parts: name → the bones whose skin is the part (with every bone below them that is not
# itself listed). A vertex belongs to the part of its dominant bone.
PARTS = {
    "head": ("neck01",), "trunk": ("root",),
    "left upper arm": ("clavicle.L",), "left forearm": ("lowerarm01.L",), "left hand": ("wrist.L",),
    "right upper arm": ("clavicle.R",), "right forearm": ("lowerarm01.R",), "right hand": ("wrist.R",),
    "left thigh": ("pelvis.L",), "left lower leg": ("lowerleg01.L",), "left foot": ("foot.L",),
    "right thigh": ("pelvis.R",), "right lower leg": ("lowerleg01.R",), "right foot": ("foot.R",),
}
# A part's vertices with a scan point this near are seen (metres; the scan's noise is ~2 mm a
# coordinate, its points ~6 mm apart at 60,000 points).
SEEN_DISTANCE = 0.010
# The share of a well-placed part's vertices that is seen: less where scans have holes (soles,
# head top, armpits) or thin parts' noisy points (fingers). Measured on the 8 benchmark fits
# (docs/registration.md): well-placed parts 0.93-1.00 (upper arms 0.93, the armpits), feet
# 0.61-0.93; lost hands 0.60-0.78.
SEEN_GOOD = {"head": 0.90, "trunk": 0.90, "upper arm": 0.85, "forearm": 0.90, "hand": 0.90, "thigh": 0.90,
             "lower leg": 0.90, "foot": 0.50}
# Unexplained scan surface (patches of points farther than EXPLAINED_DISTANCE from the fit, each
# of at least PATCH_MIN_AREA, m²) beside a part, as a share of the part's own area, that takes its
# quality to zero; patches are points within PATCH_LINK (metres) of each other.
UNEXPLAINED_SHARE = 1.0
PATCH_MIN_AREA = 0.002
PATCH_LINK = 0.03
# A part's unseen share counts only with an unexplained patch this near it, and a patch only with
# a part off its points this near it (metres): where a lost limb's own points are (the
# step-forward scan's hand: 24 cm from the fitted one).
LOST_REACH = 0.30


@dataclass(frozen=True)
class PartQuality:
    """One body part's fit, both ways. name: ``PARTS`` key; area: m² of the part on the fit;
    seen: share of its vertices within SEEN_DISTANCE of a scan point; distance: their mean
    distance to the scan (metres); unexplained: m² of scan surface beside it the fit does not
    explain (patches near a part off its points: a lost part's); bridged: m² of unexplained scan
    beside it with every part near it on its points (surface the fit bridges; not refused);
    quality: in [0, 1]."""

    name: str
    area: float
    seen: float
    distance: float
    unexplained: float
    quality: float
    bridged: float = 0.0

    def describe(self) -> str:
        return (f"{self.name}: {100 * self.seen:.0f} % of its surface on the scan (expected at least "
                f"{100 * SEEN_GOOD[_kind(self.name)]:.0f} %; mean distance {1000 * self.distance:.1f} mm), "
                f"{1e4 * self.unexplained:.0f} cm² of scan beside it unexplained (its own area "
                f"{1e4 * self.area:.0f} cm²)")

    def to_dict(self) -> dict:
        """JSON-ready, in the CLI's units (cm², mm, shares)."""
        return {"quality": round(self.quality, 4), "seen_share": round(self.seen, 4),
                "mean_distance_mm": round(1000 * self.distance, 2),
                "unexplained_cm2": round(1e4 * self.unexplained, 1), "bridged_cm2": round(1e4 * self.bridged, 1),
                "area_cm2": round(1e4 * self.area, 1),
                "accepted": self.quality >= MIN_QUALITY}


@dataclass(frozen=True)
class Quality:
    """explained, coverage, quality: shares in [0, 1]; point_distance: (n,) metres, the
    distances of a subsample of the scan's points to the registered surface; point_index: (n,)
    which scan points the distances are of; parts: one ``PartQuality`` per ``PARTS`` entry
    (empty when no template was given); accepted: quality >= MIN_QUALITY."""

    explained: float
    coverage: float
    quality: float
    point_distance: np.ndarray
    point_index: np.ndarray
    parts: tuple = ()

    @property
    def accepted(self) -> bool:
        return self.quality >= MIN_QUALITY

    @property
    def failed_parts(self) -> list[PartQuality]:
        """The parts below MIN_QUALITY, worst first."""
        return sorted((p for p in self.parts if p.quality < MIN_QUALITY), key=lambda p: p.quality)

    def describe(self) -> str:
        text = (f"quality {self.quality:.2f} (the fit explains {100 * self.explained:.1f} % of the scan's points "
                f"within {1000 * EXPLAINED_DISTANCE:.0f} mm; {100 * self.coverage:.1f} % of the template found "
                f"scan points")
        bad = self.failed_parts
        if bad:
            # The worst three in full (a chair fails every part: the list would bury the figure).
            text += "; not fitted: " + "; ".join(p.describe() for p in bad[:3])
            text += f"; and {', '.join(p.name for p in bad[3:])}" if len(bad) > 3 else ""
        elif self.parts:
            text += f"; every body part on its points (the least: {min(self.parts, key=lambda p: p.quality).name} " \
                    f"{min(p.quality for p in self.parts):.2f})"
        return text + f"; accepted at {MIN_QUALITY:.2f} and above)"

    def to_dict(self) -> dict:
        """JSON-ready figures (shares; per part: ``PartQuality.to_dict``)."""
        return {"quality": round(self.quality, 4), "explained_share": round(self.explained, 4),
                "coverage_share": round(self.coverage, 4), "accepted": self.accepted,
                "failed_parts": [p.name for p in self.failed_parts],
                "parts": {p.name: p.to_dict() for p in self.parts}}


def _kind(name: str) -> str:
    return name.removeprefix("left ").removeprefix("right ")


_PARTS_CACHE: dict = {}


def body_parts(template: Template, rig_name: str = "default") -> np.ndarray:
    """Each template vertex's part (V,) int: an index into ``list(PARTS)``, from the dominant
    bone of ``rig_name``'s skin weights (a bone's part is that of its nearest listed ancestor)."""
    key = (template.template_id, rig_name)
    if key not in _PARTS_CACHE:
        rig = template.rigs[rig_name]
        missing = [b for bones in PARTS.values() for b in bones if b not in rig.bone_names]
        if missing:
            raise RigError(f"rig {rig_name}: no bone(s) {', '.join(missing)}; the per-part quality check expects "
                           "MakeHuman's default rig (its bones name the body parts: quality.PARTS)")
        root_part = {rig.bone_index(b): k for k, bones in enumerate(PARTS.values()) for b in bones}
        per_bone = np.empty(rig.n_bones, dtype=int)
        for b in range(rig.n_bones):
            a = b
            while a >= 0 and a not in root_part:
                a = int(rig.parents[a])
            per_bone[b] = root_part.get(a, list(PARTS).index("trunk"))     # below no part's bone: the trunk
        dominant = np.asarray(rig.weights.tocsr().argmax(axis=1)).ravel()
        _PARTS_CACHE[key] = per_bone[dominant]
    return _PARTS_CACHE[key]


def _patches(points: np.ndarray, link: float) -> np.ndarray:
    """Connected patches (P,) int labels of points (P, 3) linked within ``link`` metres."""
    if len(points) == 0:
        return np.zeros(0, dtype=int)
    pairs = cKDTree(points).query_pairs(link, output_type="ndarray")
    g = sp.coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(len(points), len(points)))
    return connected_components(g, directed=False)[1]


def assess_parts(vertices: np.ndarray, faces: np.ndarray, labels: np.ndarray, scan_tree: cKDTree,
                 sub_points: np.ndarray, sub_distance: np.ndarray, sub_face: np.ndarray,
                 bridged_counts: bool = False) -> tuple[PartQuality, ...]:
    """Per-part quality (module docstring). vertices (V, 3), faces (F, 3): the fit;
    labels (V,): part of each vertex (``body_parts``); scan_tree: the KD-tree of the scan's
    points (same frame, metres); sub_points (n, 3), sub_distance (n,), sub_face (n,): a random
    subsample of the scan's points, their distance to the fit and their nearest face.
    bridged_counts: count every unexplained patch against its part, also with no part off its
    points near it (the check before the limb restarts: a restart is cheap, a refusal final)."""
    n_parts = len(PARTS)
    fa = face_areas(vertices, faces)
    face_part = labels[faces[:, 0]]
    part_area = np.bincount(face_part, fa, minlength=n_parts)
    # Scan surface per subsample point: the fit's area over the points it explains (the scan's
    # own area is unknown: points, holes, outliers).
    per_point = fa.sum() / max(1, int(np.sum(sub_distance <= EXPLAINED_DISTANCE)))
    far = np.flatnonzero(sub_distance > EXPLAINED_DISTANCE)
    d = scan_tree.query(vertices)[0]
    seen = np.array([np.mean(d[labels == k] <= SEEN_DISTANCE) for k in range(n_parts)])
    under = seen < np.array([SEEN_GOOD[_kind(name)] for name in PARTS])
    # A lost part leaves both marks: its own vertices off the scan and its scan points
    # unexplained. Unexplained scan with every part within LOST_REACH on its points is surface
    # the fit bridges (a heavy belly's fold: 580 cm² 13-62 mm from a fit whose every part was on
    # its points, docs/registration.md), reported as ``bridged``, not a lost part; a part off its
    # points with no unexplained scan within LOST_REACH is the scan's hole (a foot the scanner
    # missed: the true body's own foot 28 % seen on a step-forward scan), not judged by it.
    unexplained = np.zeros(n_parts)
    bridged = np.zeros(n_parts)
    near_lost = np.zeros(n_parts, dtype=bool)
    if len(far):
        lab = _patches(sub_points[far], PATCH_LINK)
        size = np.bincount(lab) * per_point
        big = size[lab] >= PATCH_MIN_AREA
        if big.any():
            lost_points = sub_points[far[big]]
            reach = cKDTree(lost_points).query(vertices, distance_upper_bound=LOST_REACH)[0] <= LOST_REACH
            near_lost[np.unique(labels[reach])] = True
            lost = np.zeros(len(far), dtype=bool)
            suspects = np.isin(labels, np.flatnonzero(under))
            if bridged_counts:
                lost[:] = big
            elif suspects.any():
                dist = cKDTree(vertices[suspects]).query(lost_points, distance_upper_bound=LOST_REACH)[0]
                lost[np.flatnonzero(big)] = np.isin(lab[big], np.unique(lab[big][dist <= LOST_REACH]))
            np.add.at(unexplained, face_part[sub_face[far[lost]]], per_point)
            np.add.at(bridged, face_part[sub_face[far[big & ~lost]]], per_point)
    out = []
    for k, name in enumerate(PARTS):
        inside = labels == k
        q_seen = seen[k] / SEEN_GOOD[_kind(name)] if near_lost[k] else 1.0
        q_unexp = 1.0 - unexplained[k] / (UNEXPLAINED_SHARE * part_area[k])
        q = float(np.clip(min(q_seen, q_unexp), 0.0, 1.0))
        out.append(PartQuality(name, float(part_area[k]), float(seen[k]), float(d[inside].mean()),
                               float(unexplained[k]), q, float(bridged[k])))
    return tuple(out)


def assess(vertices: np.ndarray, faces: np.ndarray, points: np.ndarray, has_target: np.ndarray,
           template: Template | None = None, scan_tree: cKDTree | None = None,
           bridged_counts: bool = False) -> Quality:
    """Quality of a registered mesh (V, 3), (F, 3) against scan points (P, 3) (same frame,
    metres); has_target: (V,) the NICP's last correspondences. template: the registered
    template (its rig gives the body parts), or None for the whole-body figures only;
    scan_tree: ``cKDTree(points)`` to reuse; bridged_counts: see ``assess_parts``."""
    sub = np.sort(np.random.default_rng(0).choice(len(points), min(len(points), ASSESS_POINTS), replace=False))
    corr, dist = closest_points(points[sub], vertices, faces)
    explained = float(np.mean(dist <= EXPLAINED_DISTANCE))
    coverage = float(np.mean(has_target))
    q = min(1.0, explained / EXPLAINED_GOOD, coverage / COVERAGE_GOOD)
    parts = ()
    if template is not None:
        tree = scan_tree if scan_tree is not None else cKDTree(points)
        parts = assess_parts(vertices, faces, body_parts(template), tree, points[sub], dist, corr.face, bridged_counts)
        q = min(q, min(p.quality for p in parts))
    return Quality(explained, coverage, q, dist, sub, parts)
