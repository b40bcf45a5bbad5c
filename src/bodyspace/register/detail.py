"""Detail transfer (Hasler §3, end): the scan's fine relief kept as normal offsets on a
subdivided fit, and re-added after a morph.

A registered template (13,380 vertices, edges 6 mm at the median) cannot hold a scan's wrinkles,
its face or the noise-free part of what the scanner saw finer than that; the model's shape space
holds even less. Hasler keeps it apart: "after fitting, the base mesh is subdivided using the
simple mid-edge scheme and projected onto the scan. The offsets of the subdivision vertices in
normal direction of the base mesh are stored [...]. During recall the mesh is subdivided again
and the stored offsets are added." Here:

1. ``midpoint_subdivide``: every edge split at its middle, every triangle into four (``levels``
   times); the subdivided vertices are the base vertices, then one per edge of the base mesh
   (``mesh.topology.edges`` order), so a subdivided vertex is the same point of the body on any
   mesh of the topology (a fit, a morph of it, another scan's fit).
2. ``detail_offsets``: each subdivided vertex p, with the normal n of the subdivided base
   surface there, is moved along n onto the scan: a plane fitted to the ``neighbours`` scan
   points nearest p, and the line p + h n cut with it. One signed offset h per subdivided
   vertex (the per-vertex form of Hasler's per-triangle offsets: a mid-edge vertex is shared by
   two triangles and gets one value, so the detailed mesh has no cracks). Where the scan has a
   hole, where the patch's normal disagrees with n by more than ``MAX_ANGLE_DEG`` or the cut is
   farther than ``max_offset`` (another body part across a gap), the vertex is marked invalid
   and keeps h = 0: the fit's own smooth surface. Then only what the scan can vouch for is
   kept (``shrink``): an offset that stands out of the scan's noise, among neighbours that do
   too, measured by a patch narrow enough for relief finer than the mesh; elsewhere h = 0, so
   a sparse or noisy scan's detail never takes the body farther from the scan's truth than the
   smooth fit (``Detail.kept``, ``Detail.notice``).
3. ``apply_detail``: any mesh of the base topology (the morphed body) subdivided the same way,
   each subdivided vertex moved by its stored h along the new surface's normal: the relief rides
   on the morphed body, rotated and stretched with it.

``Detail`` holds the offsets with what they are for (levels, the base topology's size and a
hash of its faces); ``save_detail`` / ``load_detail`` keep it as one ``.npz`` (no pickle, a JSON
header checked on load), the file ``bodyspace register --detail`` writes beside the registered
mesh and ``bodyspace morph --detail`` re-applies. docs/registration.md.
"""

from __future__ import annotations

import hashlib
import json
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from bodyspace.atomic import atomic_path
from bodyspace.errors import RegistrationError
from bodyspace.mesh.geometry import check_mesh, vertex_normals
from bodyspace.mesh.topology import edges

__all__ = ["Detail", "midpoint_subdivide", "detail_offsets", "apply_detail", "save_detail", "load_detail",
           "faces_digest", "DETAIL_FORMAT", "MAX_LEVELS"]

DETAIL_FORMAT = "bodyspace.Detail"
DETAIL_VERSION = 1
# Subdivision levels allowed: 1 quadruples the faces (the paper's one step: 107 k faces, 3 mm
# edges at the median on hm08), 2 gives 428 k faces and 1.6 mm; 3 would be 1.7 M faces.
MAX_LEVELS = 2
# Scan points each local height field is fitted to (6 coefficients). Measured on a body with a
# 2 mm relief (benchmarks/bench_detail.py's surface, the true base): mean offset error at 200 k
# points, σ = 0.5 mm: 0.47 / 0.48 / 0.57 mm with 12 / 20 / 32 points; at 80 k points, σ = 2 mm:
# 1.69 / 1.63 / 1.91 mm. Fewer points follow the relief, more average the noise.
NEIGHBOURS = 16
# The scan's patch must face within this angle of the base normal (else it is another part of
# the body, or too noisy to say where the surface is).
MAX_ANGLE_DEG = 60.0
# Residuals (metres) under this never mark a point as another surface's (noise-free scans).
ROBUST_FLOOR = 0.0003
# Subdivided vertices whose patches are fitted at once (bounds the memory: ~200 MB a block).
CHUNK = 40_000
# Offsets beyond this (metres) are not relief but a misfit or a gap crossed: left out.
MAX_OFFSET = 0.015
# Which measured offsets are kept (``shrink=True``; measured on bench_detail.py's bodies at
# 200 k / 80 k / 40 k points and on the user walk's f07, 40 k points, σ = 2 mm, no relief):
# - an offset must stand out of its noise by SIGNIFICANCE standard deviations (the noise's
#   variance pooled over the scan: one patch's 10 residual degrees of freedom say little);
SIGNIFICANCE = 2.5
# - a patch both wider than PATCH_RADIUS (RMS distance of its points from p, metres) and wider
#   than PATCH_EDGES local subdivided edges measures the base mesh's own shape, not finer relief:
#   on a sparse scan (points ~7 mm apart) it spans a finger, a toe, the nose, and its quadratic
#   is biased by millimetres there (f07's hands: 0.54 -> 1.87 mm with such offsets);
PATCH_RADIUS = 0.006
PATCH_EDGES = 1.5
# - relief is a surface, not a speck: offsets are kept only where COHERENT of the
#   COHERENT_NEIGHBOURS subdivided vertices nearest stand out of the noise (noise alone passes a
#   2.5σ test at ~1-3 % of vertices, scattered). f07 against its smooth fit's 0.5600 mm: 0.5610
#   with 2σ, 0.5605 with 2.5σ, 0.5602 with 3σ; the 200 k bench body on its true base: 0.39 / 0.40
#   / 0.42 mm (0.38 before these tests, 0.94 smooth);
COHERENT = 0.3
COHERENT_NEIGHBOURS = 48
# - a patch whose surface lies farther from p than p's nearest scan point (by more than
#   NEAR_SLACK times the points' noise) fitted another surface (f07's hands: the next finger's,
#   -6 to -10 mm, where the smooth fit was within 0.4 mm of the truth); it counts as no relief.
NEAR_SLACK = 1.0


@dataclass(frozen=True)
class Detail:
    """Normal offsets of a subdivided registration.

    offsets: (S,) metres along the subdivided base surface's normals (0 where not valid);
    valid: (S,) bool, the offset was measured on the scan; levels: mid-edge subdivisions;
    n_base_vertices, n_base_faces, faces_sha256: the base topology they belong to.
    noise: metres, the median standard deviation the scan's noise leaves in an offset (NaN: unknown).
    kept: share of the S offsets kept (non-zero) after the noise tests; wide: share of the S
    vertices whose scan patch was too wide for relief finer than the mesh (a sparse scan); NaN:
    unknown (a file of version 1 without them).
    S = the subdivided mesh's vertex count (``midpoint_subdivide``).
    """

    offsets: np.ndarray
    valid: np.ndarray
    levels: int
    n_base_vertices: int
    n_base_faces: int
    faces_sha256: str
    noise: float = float("nan")
    kept: float = float("nan")
    wide: float = float("nan")

    def notice(self) -> str | None:
        """Why little or no detail was kept (None when most of the measured relief was kept)."""
        if not np.isfinite(self.kept) or self.kept >= 0.2:
            return None
        why = []
        if np.isfinite(self.wide) and self.wide >= 0.05:
            why.append(f"at {100 * self.wide:.0f} % of the body the scan's points are farther apart than the "
                       "subdivided mesh's edges (too sparse for relief finer than the mesh)")
        if np.isfinite(self.noise):
            why.append(f"{'elsewhere ' if why else ''}the offsets do not stand {SIGNIFICANCE:g} times out of the "
                       f"scan's noise ({1000 * self.noise:.2f} mm in an offset, median)")
        return (f"only {100 * self.kept:.1f} % of the detail was kept: {', '.join(why) or 'the scan holds none'}; the "
                "detailed mesh is the smooth fit there. For more detail, scan denser (points closer than 3 mm) or "
                "with less noise")

    def describe(self) -> str:
        h = self.offsets[self.offsets != 0]
        spread = f"{1000 * np.sqrt(np.mean(h ** 2)):.2f} mm RMS, {1000 * np.abs(h).max():.1f} mm at most" if h.size \
            else "none kept"
        kept = "" if not np.isfinite(self.kept) else f", {100 * self.kept:.1f} % kept"
        text = (f"{len(self.offsets)} subdivided vertices ({self.levels} level(s)), {100 * self.valid.mean():.1f} % "
                f"on the scan{kept}; offsets {spread}")
        if np.isfinite(self.noise):
            text += f"; the scan's noise leaves {1000 * self.noise:.2f} mm of uncertainty in an offset (median)"
        note = self.notice()
        return text if note is None else f"{text}. Notice: {note}"


def faces_digest(faces: np.ndarray) -> str:
    """SHA-256 of a faces array (F, 3) as int64: which topology a detail file belongs to."""
    return hashlib.sha256(np.ascontiguousarray(np.asarray(faces, dtype=np.int64)).tobytes()).hexdigest()


def midpoint_subdivide(vertices: np.ndarray, faces: np.ndarray, levels: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """Mid-edge subdivision, ``levels`` times.

    vertices: (V, 3) or (N, V, 3); faces: (F, 3). Each level appends one vertex per edge (the
    middle of the edge, edges in ``mesh.topology.edges`` order) after the existing ones and
    splits each triangle (a, b, c) into (a, ab, ca), (ab, b, bc), (ca, bc, c), (ab, bc, ca), so
    the faces keep their orientation. Returns vertices (S, 3) or (N, S, 3) and faces (4^levels F, 3).
    """
    v = np.asarray(vertices, dtype=float)
    f = np.asarray(faces, dtype=np.int64)
    for _ in range(int(levels)):
        n = v.shape[-2]
        e = edges(f)
        mid = 0.5 * (v[..., e[:, 0], :] + v[..., e[:, 1], :])
        # The id of the middle of edge (i, j), i < j: a sorted key looked up in the sorted edges.
        keys = e[:, 0] * n + e[:, 1]

        def middle(i, j):
            lo, hi = np.minimum(i, j), np.maximum(i, j)
            return n + np.searchsorted(keys, lo * n + hi)

        a, b, c = f[:, 0], f[:, 1], f[:, 2]
        ab, bc, ca = middle(a, b), middle(b, c), middle(c, a)
        f = np.concatenate([np.stack(t, axis=1) for t in ((a, ab, ca), (ab, b, bc), (ca, bc, c), (ab, bc, ca))])
        v = np.concatenate([v, mid], axis=-2)
    return v, f


def _check_levels(levels) -> int:
    if not isinstance(levels, (int, np.integer)) or not 1 <= int(levels) <= MAX_LEVELS:
        raise RegistrationError(f"detail levels={levels!r}; expected 1 (the paper's one mid-edge subdivision) or "
                                f"up to {MAX_LEVELS}")
    return int(levels)


def _patch_offsets(sv, n, pts, tree, neighbours, max_offset, max_angle_deg):
    """Of subdivided vertices sv (S, 3) with normals n (S, 3) against scan points pts (P, 3)
    (``detail_offsets``): offsets (S,) unshrunk, the patch fits' residual variances (S,), the
    factors (AᵀA)⁻¹₀₀ (S,) that turn a residual variance into the offset's, validity (S,) and the
    patches' RMS radii (S,) in metres."""
    dist, nb = tree.query(sv, k=neighbours)                                  # (S, k)
    # The scan near p as a height field over p's tangent plane, t = a + b u + c v + d u² + e uv + f v²
    # (least squares over the k points): the line p + h n meets it at (u, v) = (0, 0), h = a. A
    # plane through the patch's centroid would average the relief over the patch instead.
    d = pts[nb] - sv[:, None]                                                # (S, k, 3)
    e1 = np.cross(n, np.where(np.abs(n[:, :1]) < 0.9, [[1.0, 0, 0]], [[0, 1.0, 0]]))
    e1 /= np.maximum(np.linalg.norm(e1, axis=1, keepdims=True), 1e-300)
    e2 = np.cross(n, e1)
    u, w = np.einsum("skd,sd->sk", d, e1), np.einsum("skd,sd->sk", d, e2)
    t = np.einsum("skd,sd->sk", d, n)
    # Scaled by the patch's size so the normal equations are well conditioned in any unit.
    r = np.maximum(np.sqrt((u ** 2 + w ** 2).mean(axis=1, keepdims=True)), 1e-12)
    u, w = u / r, w / r
    A = np.stack([np.ones_like(u), u, w, u * u, u * w, w * w], axis=2)       # (S, k, 6)
    wt = np.ones_like(t)
    for _ in range(2):
        # The second pass leaves out the patch's points far off the first fit: points of another
        # surface close by (a finger beside a finger, the other lip, the ear's fold).
        used = wt
        AtA = np.einsum("sk,ski,skj->sij", used, A, A) + 1e-9 * np.eye(6)
        coef = np.linalg.solve(AtA, np.einsum("sk,ski,sk->si", used, A, t)[..., None])[..., 0]
        res = np.abs(np.einsum("ski,si->sk", A, coef) - t)
        wt = (res <= 3.0 * np.maximum(np.median(res, axis=1, keepdims=True), ROBUST_FLOOR)).astype(float)
    h = coef[:, 0]
    # The scan's noise passes into h with variance σ² (AᵀA)⁻¹₀₀, σ² from the fit's own residuals.
    dof = np.maximum(used.sum(axis=1) - 6, 1)
    resvar = (used * res ** 2).sum(axis=1) / dof
    slope = np.hypot(coef[:, 1], coef[:, 2]) / r[:, 0]                       # tan of the patch's tilt
    valid = (slope <= np.tan(np.radians(max_angle_deg))) & np.isfinite(h) & (np.abs(h) <= max_offset)
    # Over a hole the nearest scan point is off to one side, farther than any relief.
    valid &= dist[:, 0] <= max_offset
    return np.where(valid, h, 0.0), resvar, np.linalg.inv(AtA)[:, 0, 0], valid, r[:, 0], dist[:, 0]


def detail_offsets(vertices: np.ndarray, faces: np.ndarray, points: np.ndarray, *, levels: int = 1,
                   neighbours: int = NEIGHBOURS, max_offset: float = MAX_OFFSET,
                   max_angle_deg: float = MAX_ANGLE_DEG, shrink: bool = True) -> Detail:
    """The scan's relief over a registered mesh (module docstring, step 2).

    shrink: keep only the offsets the scan can vouch for (else every measured offset is kept as
    it is): an offset is set to 0 where its patch is wider than PATCH_RADIUS and PATCH_EDGES local
    edges (a sparse scan), and where fewer than COHERENT of its COHERENT_NEIGHBOURS nearest
    subdivided vertices are significant: standing SIGNIFICANCE standard deviations out of the
    scan's noise (var = the residual variance, at least the scan's median, times (AᵀA)⁻¹₀₀), and
    no farther than the nearest scan point (+ NEAR_SLACK times the points' noise). A kept offset
    is shrunk by 1 - var/h² (James-Stein: nearly unbiased for an offset well out of the noise). ``Detail.kept``, ``.wide`` and ``.notice()`` say how much was kept and why.

    vertices: (V, 3) the registration (metres, the frame of ``points``); faces: (F, 3);
    points: (P, 3) the scan's points (outliers may stay: a patch is fitted per vertex and an
    offset beyond ``max_offset`` is dropped). Returns a ``Detail`` with S offsets, S the
    subdivided vertex count.
    """
    levels = _check_levels(levels)
    check_mesh(vertices, faces, "the registered mesh")
    pts = np.asarray(points, dtype=float)
    if pts.ndim != 2 or pts.shape[1] != 3 or len(pts) < neighbours:
        raise RegistrationError(f"detail: the scan has points of shape {pts.shape}; expected (P, 3) with at least "
                                f"{neighbours} points")
    sv, sf = midpoint_subdivide(vertices, faces, levels)
    n = vertex_normals(sv, sf)                                               # (S, 3)
    tree = cKDTree(pts)
    S = len(sv)
    h, resvar, inv00, radius, nearest = np.zeros(S), np.zeros(S), np.zeros(S), np.zeros(S), np.zeros(S)
    valid = np.zeros(S, dtype=bool)
    # In blocks: the per-vertex patches (S, k, 6) of two levels would take a gigabyte at once.
    for lo in range(0, S, CHUNK):
        block = slice(lo, lo + CHUNK)
        h[block], resvar[block], inv00[block], valid[block], radius[block], nearest[block] = _patch_offsets(
            sv[block], n[block], pts, tree, int(neighbours), max_offset, max_angle_deg)
    if not valid.any():
        return Detail(np.zeros(S), valid, levels, len(vertices), len(faces), faces_digest(faces), float("nan"),
                      0.0, float("nan"))
    e = edges(sf)
    length = np.linalg.norm(sv[e[:, 0]] - sv[e[:, 1]], axis=1)
    local_edge = (np.bincount(e.ravel(), np.repeat(length, 2), S) / np.maximum(np.bincount(e.ravel(), minlength=S), 1))
    wide = valid & (radius > PATCH_RADIUS) & (radius > PATCH_EDGES * local_edge)
    # The noise pooled over the scan (where the patches are narrow enough to measure it: a wide
    # patch's residuals hold its misfit too): a patch's own residuals (10 degrees of freedom) can
    # be small by chance, and a small variance would pass its noise as relief.
    narrow = valid & ~wide if (valid & ~wide).any() else valid
    var = np.maximum(resvar, np.median(resvar[narrow])) * inv00
    noise = float(np.sqrt(np.median(var[narrow])))
    if not shrink:
        return Detail(h, valid, levels, len(vertices), len(faces), faces_digest(faces), noise,
                      float(np.mean(h != 0)), float(wide.mean()))
    significant = valid & ~wide & (h ** 2 > SIGNIFICANCE ** 2 * var)
    # A scan point nearer p than the surface the patch found (by more than the points' noise):
    # the patch fitted another surface (the next finger), not relief under p.
    significant &= np.abs(h) <= nearest + NEAR_SLACK * np.sqrt(np.median(resvar[narrow]))
    k = min(COHERENT_NEIGHBOURS, S)
    _, near = cKDTree(sv).query(sv, k=k)
    # Inside a region of relief every offset is kept (shrunk): dropping the ones under the test
    # would flatten the relief where it crosses 0 (200 k-point bench body: 0.42 against 0.46 mm).
    kept = valid & ~wide & (significant[near].mean(axis=1) >= COHERENT)
    with np.errstate(divide="ignore", invalid="ignore"):
        h = np.where(kept, h * np.clip(1 - var / h ** 2, 0, 1), 0.0)
    return Detail(h, valid, levels, len(vertices), len(faces), faces_digest(faces), noise,
                  float(np.mean(h != 0)), float(wide.mean()))


def apply_detail(vertices: np.ndarray, faces: np.ndarray, detail: Detail, *,
                 name: str = "the mesh") -> tuple[np.ndarray, np.ndarray]:
    """The detailed mesh of a body of the base topology (module docstring, step 3).

    vertices: (V, 3) any body of the topology the detail was taken on (the fit, a morph of it),
    metres; faces: (F, 3). Returns vertices (S, 3) and faces (4^levels F, 3).
    """
    v = np.asarray(vertices, dtype=float)
    f = np.asarray(faces, dtype=np.int64)
    check_mesh(v, f, name)
    if v.ndim != 2 or len(v) != detail.n_base_vertices or len(f) != detail.n_base_faces \
            or faces_digest(f) != detail.faces_sha256:
        raise RegistrationError(f"{name}: {len(v)} vertices and {len(f)} faces; the detail was taken on a mesh of "
                                f"{detail.n_base_vertices} vertices and {detail.n_base_faces} faces (another "
                                "topology or face order): give a mesh of the registration's topology (the "
                                "registered mesh, or a morph of it)")
    sv, sf = midpoint_subdivide(v, f, detail.levels)
    if len(sv) != len(detail.offsets):
        raise RegistrationError(f"{name}: subdivided {detail.levels} time(s) it has {len(sv)} vertices, but the "
                                f"detail holds {len(detail.offsets)} offsets; the detail file is damaged")
    return sv + detail.offsets[:, None] * vertex_normals(sv, sf), sf


def save_detail(path: str | os.PathLike, detail: Detail, **provenance) -> Path:
    """Write ``detail`` as one ``.npz``: ``header`` (UTF-8 JSON: format, version, levels, the base
    topology, units, ``provenance``), ``offsets`` (S,) float32 metres, ``valid`` (S,) bool."""
    path = Path(path)
    header = {"format": DETAIL_FORMAT, "format_version": DETAIL_VERSION, "units": "m",
              "levels": detail.levels, "n_base_vertices": detail.n_base_vertices,
              "n_base_faces": detail.n_base_faces, "faces_sha256": detail.faces_sha256,
              "n_subdivided_vertices": len(detail.offsets),
              "noise_m": None if not np.isfinite(detail.noise) else round(float(detail.noise), 7),
              "kept_share": None if not np.isfinite(detail.kept) else round(float(detail.kept), 5),
              "wide_share": None if not np.isfinite(detail.wide) else round(float(detail.wide), 5), **provenance}
    raw = np.frombuffer(json.dumps(header).encode("utf-8"), dtype=np.uint8)
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            np.savez(fh, header=raw, offsets=detail.offsets.astype(np.float32), valid=detail.valid.astype(bool))
    return path


def load_detail(path: str | os.PathLike) -> Detail:
    """Read a detail file written by ``save_detail`` (checked; never executes code from it)."""
    path = Path(path)
    expected = "a detail file written by bodyspace register --detail (detail.npz)"
    try:
        with np.load(path, allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files}
    except FileNotFoundError:
        raise RegistrationError(f"{path}: no such file; expected {expected}") from None
    except (OSError, ValueError, EOFError) as exc:
        raise RegistrationError(f"{path}: could not read it ({exc}); expected {expected}") from None
    missing = [k for k in ("header", "offsets", "valid") if k not in arrays]
    if missing:
        raise RegistrationError(f"{path}: lacks the array(s) {', '.join(missing)}; expected {expected}")
    try:
        header = json.loads(arrays["header"].tobytes().decode("utf-8"))
    except (ValueError, UnicodeDecodeError) as exc:
        raise RegistrationError(f"{path}: field 'header' is not UTF-8 JSON ({exc}); expected {expected}") from None
    if not isinstance(header, dict) or header.get("format") != DETAIL_FORMAT:
        raise RegistrationError(f"{path}: field 'header' names format "
                                f"{header.get('format') if isinstance(header, dict) else header!r}; expected "
                                f"{DETAIL_FORMAT!r} ({expected})")
    if header.get("format_version") != DETAIL_VERSION:
        raise RegistrationError(f"{path}: format_version {header.get('format_version')!r}; this bodyspace reads "
                                f"version {DETAIL_VERSION}")
    offsets = np.asarray(arrays["offsets"], dtype=float)
    valid = np.asarray(arrays["valid"])
    try:
        levels = _check_levels(header.get("levels"))
        nv, nf = int(header["n_base_vertices"]), int(header["n_base_faces"])
        digest = str(header["faces_sha256"])
    except (KeyError, TypeError, ValueError) as exc:
        raise RegistrationError(f"{path}: field 'header' lacks or garbles {exc}; expected {expected}") from None
    # The subdivided vertex count depends on the base mesh's edges: it is checked on apply.
    if offsets.ndim != 1 or valid.shape != offsets.shape or valid.dtype != bool:
        raise RegistrationError(f"{path}: field 'offsets' has shape {offsets.shape} and 'valid' {valid.shape} "
                                f"({valid.dtype}); expected two (S,) arrays, float and bool")
    if not np.isfinite(offsets).all() or np.abs(offsets).max(initial=0.0) > 1.0:
        raise RegistrationError(f"{path}: field 'offsets' holds non-finite values or values over 1 m; expected "
                                "offsets in metres of a few millimetres")
    if len(offsets) < nv:
        raise RegistrationError(f"{path}: {len(offsets)} offsets for a base mesh of {nv} vertices; expected more "
                                "(one per subdivided vertex)")
    noise = header.get("noise_m")
    noise = float(noise) if isinstance(noise, (int, float)) and np.isfinite(noise) and noise >= 0 else float("nan")
    shares = [header.get(k) for k in ("kept_share", "wide_share")]
    kept, wide = (float(x) if isinstance(x, (int, float)) and 0 <= x <= 1 else float("nan") for x in shares)
    return Detail(offsets, valid, levels, nv, nf, digest, noise, kept, wide)

