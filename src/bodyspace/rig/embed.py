"""Skeleton embedding into any humanoid mesh: the template's rig fitted into a mesh of any topology.

Input: one closed (or nearly closed) mesh of a person standing in an A- or T-pose, any vertex
count, any placement, heading, up axis and unit. Output: the joints of the default CC0 rig inside
it (``embed_skeleton``) and, from them, every bone of any CC0 rig (``embedded_skeleton``).

Method, and why not Pinocchio's. Baran & Popović (2007; Rupprecht §3.3.1 uses it) embed a
simplified skeleton into a discretized medial surface by a discrete search with hand-tuned
penalties, then refine continuously; it places ~17 joints, needs the skeleton's proportions
given, and has no notion of where a knee sits inside a leg beyond "near the medial axis". We
have more to go on: the template carries a 163-bone rig whose joints are regressed from its
vertices (``Rig.head_regressor``), a skinning that poses it, and 576 MakeHuman macro targets
whose span holds every phenotype's rest shape. So the embedding is a *model fit*, coarse to
fine, and the joints come from the fitted template, where they are known:

1. **Frame** (``body_frame``): the up axis, front and unit from the geometry alone, or as the
   caller states them (``up=``, ``units=``, named as in ``measure.conventions``). Up and the
   left-right axis are the two largest principal axes of the surface (a T-pose is as wide as
   it is tall); the left-right one is the axis the surface is mirror-symmetric across. Up points
   away from the end whose cross-section is split in two (the legs); the front is where the
   toes point. The unit is the one in which the body's height and area are human
   (``plausible_units``).
2. **Coarse start**: the template scaled to the mesh's height, standing where it stands, each
   upper arm turned so its fingertips point where the mesh's lateral-most points are (an A- and
   a T-pose differ by 45° at the shoulder, more than closest-point matching recovers).
3. **Fit** (``_fit``): the template body ``mean + basis c`` (the leading ``SHAPE_DIRECTIONS``
   principal directions of the macro targets), posed by linear blend skinning with a rotation
   for each of ``FITTED_BONES`` (the others follow their parent), scaled and moved, against the
   mesh by iterated closest points in both directions (template -> mesh and mesh -> template,
   so a limb the template misses still pulls), point-to-plane residuals with the mesh's normals,
   pairs whose normals disagree dropped and far pairs down-weighted (Huber). Each round is one
   Levenberg-Marquardt step with the exact Jacobian: shape through the vertices *and* the joints
   (the heads are regressed from the shaped body, so a longer leg moves the knee), rotations as
   world-frame turns of a bone's whole subtree about its posed joint. Weak priors keep the shape
   coefficients and the unsupported rotations small.
4. **Joints**: forward kinematics of the fitted pose on the fitted rest body's regressed heads:
   the default rig's posed joints. Any other CC0 rig's heads and tails are regressed on the
   fitted rest body and carried by the fitted pose ("joint skinning": each point moved by the
   blend of the bone transforms its regressor's skin carries, which is exact forward kinematics
   at a joint between two bones), and rolls follow the skin (``rig.skeleton.body_skeleton``).
5. **Into the interior** (``into_interior``): a body joint the fit leaves outside the mesh
   (generalized winding number below 1/2; the few millimetres of fit residual can put a shoulder
   joint just outside) is moved in along its limb (toward its parent's joint or its own tail,
   whichever enters sooner) to ``INTERIOR_DEPTH`` inside, by at most ``MAX_INTERIOR_MOVE``.
   Bone heat needs its bones inside.

Why this beats a discrete medial embedding here: every one of the 163 bones (fingers, toes, face)
is placed, not only the ~17 a medial graph resolves, and the joints sit where the template's
anatomy puts them inside the flesh (a knee is not at the centre of the leg's cross-section).
What it assumes: a person in an A- or T-pose (measured: arms at the sides, a wide stance and a
star pose work too; hands on hips does not, and arms forward is refused: docs/embedding.md); a
mesh that is not a humanoid has no legs to find or leaves a large residual and is refused
(``RigError``), as are several components and meshes far from closed (``check_riggable``).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numba
import numpy as np
import scipy.sparse as sp
from scipy.spatial import cKDTree

from bodyspace.data.template import Rig, Template, load_template
from bodyspace.errors import ParameterError, RigError
from bodyspace.measure.conventions import MESH_UNITS, plausible_units, signed_volume
from bodyspace.mesh.geometry import face_areas, vertex_normals
from bodyspace.mesh.solver import single_threaded_blas
from bodyspace.mesh.topology import vertex_components
from bodyspace.rig.kinematics import forward_kinematics, matrix_to_rotvec, rotvec_to_matrix, topological_order
from bodyspace.rig.skeleton import Skeleton, body_skeleton, roll_from_x_axis

__all__ = ["BodyFrame", "Embedding", "FITTED_BONES", "JOINT_GROUPS", "body_frame", "check_riggable",
           "embed_skeleton", "embedded_skeleton", "into_interior", "joint_group", "winding_numbers"]

# The bones whose rotation the fit estimates (the others turn with their parent): the trunk, the
# limbs down to hands and feet. Twist bones, fingers, toes and the face follow; an A- or T-pose
# holds them at rest.
FITTED_BONES = ("root", "spine05", "spine04", "spine03", "spine02", "spine01", "neck01", "head",
                "clavicle.L", "clavicle.R", "upperarm01.L", "upperarm01.R", "lowerarm01.L", "lowerarm01.R",
                "wrist.L", "wrist.R", "pelvis.L", "pelvis.R", "upperleg01.L", "upperleg01.R",
                "lowerleg01.L", "lowerleg01.R", "foot.L", "foot.R")
# Principal directions of the macro targets the fit uses (of 576): on the study's bodies the
# joint error stops falling beyond this (docs/embedding.md).
SHAPE_DIRECTIONS = 40
# Template vertices and mesh points matched in each round.
MODEL_SAMPLES = 3000
MESH_SAMPLES = 3000
ITERATIONS = 30
# Priors (metres^2 per unit^2 of the mean residual): shape coefficients (each direction scaled to
# the spread of the targets along it) and bone rotations (radians) against the start.
SHAPE_PRIOR = 1e-7
POSE_PRIOR = 1e-6
# Pairs whose unit normals have a dot product below this are dropped (the far side of a limb).
MIN_NORMAL_DOT = 0.3
# Huber threshold: this many times the median pair distance, at least HUBER_MIN metres.
HUBER_FACTOR = 2.0
HUBER_MIN = 0.005
# Levenberg-Marquardt: starting damping (share of the normal matrix's diagonal), tries per round,
# and the least relative decrease of a round's cost that continues the fit.
LM_START = 1e-3
LM_MAX_TRIES = 6
COST_TOLERANCE = 3e-3
# A mesh whose fitted template stays farther than this share of its height (RMS, both
# directions) is not a humanoid standing in an A- or T-pose.
MAX_RESIDUAL_SHARE = 0.02
# A mesh is "nearly closed" when its boundary edges are at most this share of its edges.
MAX_BOUNDARY_SHARE = 0.02
# Surface points near the mirror plane, as a share of a band 5-15 % of the height from an end: a
# standing body has none between its shins (0.0-0.5 % on the study's bodies); the band around the
# head, a sphere's or a box's end cross each other's plane (6-40 %).
MAX_LEG_GAP_SHARE = 0.02
# Parts smaller than this share of the surface area are debris (a scanner's floaters) and are
# not counted as components; the fit ignores nothing, though (they are matched like the rest).
MIN_COMPONENT_SHARE = 0.002

# A joint of the body that the fit leaves outside the mesh is moved to this depth under the
# mesh's nearest vertex (bone heat needs bones inside; MakeHuman's shoulder joints sit a few mm
# under the skin, and the fit's few millimetres of residual can put them just outside). Only
# points within NEAR_SURFACE of a vertex are tested. The face's control bones (lips, eyelids,
# tongue) and skinless helpers (the root) lie outside a closed body surface by design and stay.
INTERIOR_DEPTH = 0.005
NEAR_SURFACE = 0.03
INTERIOR_STEPS = 16
# ... but by at most this much: farther, the limb runs under the skin (a clavicle) or the mesh is too
# coarse to hold it (a 3,000-vertex mesh's fingers are thinner than the true ones), and moving
# would cost more accuracy than it gains (the study's worst joint: 3.3 cm unmoved, 5.1 cm moved
# without this bound).
MAX_INTERIOR_MOVE = 0.01

# Joint groups of the default rig, for the accuracy table: (group, bone-name prefixes).
JOINT_GROUPS = (
    ("spine, pelvis", ("root", "spine", "pelvis")),
    ("neck, head", ("neck", "head")),
    ("face", ("jaw", "eye", "levator", "oculi", "orbicularis", "oris", "risorius", "special", "temporalis",
              "tongue")),
    ("shoulders", ("clavicle", "shoulder", "breast")),
    ("arms", ("upperarm", "lowerarm")),
    ("hands", ("wrist", "metacarpal", "finger")),
    ("legs", ("upperleg", "lowerleg")),
    ("feet", ("foot", "toe")),
)


def joint_group(bone_name: str) -> str:
    """The ``JOINT_GROUPS`` name of a default-rig bone (``"other"`` if none matches)."""
    for group, prefixes in JOINT_GROUPS:
        if bone_name.startswith(prefixes):
            return group
    return "other"


# ------------------------------------------------------------------------------ checks

def check_riggable(vertices: np.ndarray, faces: np.ndarray, mesh_name: str = "the mesh") -> None:
    """Refuse (``RigError``) a mesh that cannot be rigged as one body, naming what was found.

    vertices (V, 3), faces (F, 3). Several components (parts above ``MIN_COMPONENT_SHARE`` of the
    area), or more than ``MAX_BOUNDARY_SHARE`` of the edges on a boundary (far from closed: a
    surface, not a body). Whether it is a humanoid is known only after the fit (``embed_skeleton``).
    """
    v = np.asarray(vertices, dtype=float)
    f = np.asarray(faces, dtype=np.int64)
    if v.ndim != 2 or v.shape[1] != 3 or len(v) < 4 or not np.isfinite(v).all():
        raise RigError(f"{mesh_name}: vertices of shape {v.shape} (finite: {bool(np.isfinite(v).all())}); expected "
                       "(V, 3) finite coordinates of a body mesh")
    if f.ndim != 2 or f.shape[1] != 3 or len(f) < 4 or f.min() < 0 or f.max() >= len(v):
        raise RigError(f"{mesh_name}: faces of shape {f.shape}; expected (F, 3) triangles indexing its {len(v)} vertices")
    area = face_areas(v, f)
    n, labels = vertex_components(f, len(v))
    if n > 1:
        part_area = np.bincount(labels[f[:, 0]], weights=area, minlength=n)
        big = np.sort(part_area[part_area > MIN_COMPONENT_SHARE * area.sum()])[::-1]
        if len(big) > 1:
            shares = ", ".join(f"{100 * a / area.sum():.1f} %" for a in big[:5])
            raise RigError(f"{mesh_name}: {len(big)} separate parts (shares of the surface area: {shares}"
                           f"{', ...' if len(big) > 5 else ''}); expected one connected body. Join or delete the "
                           "extra parts (clothing, props, a second person) before rigging")
    # Boundary edges: used by one face only (counted directly: a scan's boundary need not form loops).
    edges = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
    _, uses = np.unique(edges[:, 0] * len(v) + edges[:, 1], return_counts=True)
    n_boundary, n_edges = int((uses == 1).sum()), len(uses)
    if n_boundary > MAX_BOUNDARY_SHARE * n_edges:
        raise RigError(f"{mesh_name}: far from closed: {n_boundary} of {n_edges} edges lie on hole boundaries "
                       f"({100 * n_boundary / n_edges:.1f} %, at most "
                       f"{100 * MAX_BOUNDARY_SHARE:g} % allowed); expected a closed or nearly closed body surface. "
                       "Fill the holes (a watertight scan or remesh) before rigging")


# ------------------------------------------------------------------------------ frame

@dataclass(frozen=True)
class BodyFrame:
    """The mesh's frame: ``internal = scale * points @ rotation.T + translation``.

    rotation: (3, 3) proper rotation taking the mesh's axes to ours (+Y up, +Z the person's
    front, +X their left); scale: metres per mesh unit; translation: (3,) metres, putting the
    lowest point at y = 0 and the surface's centre of area at x = z = 0. ``up`` and ``units``
    say what was found (or given).
    """

    rotation: np.ndarray
    scale: float
    translation: np.ndarray
    up: str
    units: str

    def to_internal(self, points: np.ndarray) -> np.ndarray:
        """(..., 3) mesh coordinates to metres in our axes."""
        return self.scale * np.asarray(points, dtype=float) @ self.rotation.T + self.translation

    def from_internal(self, points: np.ndarray) -> np.ndarray:
        """(..., 3) metres in our axes back to the mesh's coordinates."""
        return ((np.asarray(points, dtype=float) - self.translation) / self.scale) @ self.rotation


_AXES = {"x": (1.0, 0, 0), "-x": (-1.0, 0, 0), "y": (0, 1.0, 0), "-y": (0, -1.0, 0), "z": (0, 0, 1.0),
         "-z": (0, 0, -1.0)}


def _axis_name(u: np.ndarray) -> str:
    names = list(_AXES)
    k = int(np.argmax([np.dot(u, _AXES[a]) for a in names]))
    return names[k] if np.dot(u, _AXES[names[k]]) > 0.9 else "(%.2f, %.2f, %.2f)" % tuple(u)


def _surface_samples(v: np.ndarray, f: np.ndarray, n: int, rng: np.random.Generator) -> np.ndarray:
    """(n, 3) points spread over the surface by area (face centroids drawn by area)."""
    area = face_areas(v, f)
    pick = rng.choice(len(f), size=n, p=area / area.sum())
    return v[f[pick]].mean(axis=1)


def body_frame(vertices: np.ndarray, faces: np.ndarray, up: str | None = None, units: str | None = None,
               mesh_name: str = "the mesh") -> BodyFrame:
    """The frame of a standing body mesh (V, 3), (F, 3): up, front and unit (module docstring, 1).

    up: the mesh's up axis if known ("y", "-y", "x", "-x", "z", "-z"); units: "m", "cm", "mm" or
    "in" if known. Raises ``RigError`` when no unit makes it human-sized or no legs are found.
    """
    v = np.asarray(vertices, dtype=float)
    f = np.asarray(faces, dtype=np.int64)
    if up is not None and up not in _AXES:
        raise ParameterError(f"up={up!r}; expected one of {', '.join(_AXES)}")
    if units is not None and units not in MESH_UNITS:
        raise ParameterError(f"units={units!r}; expected one of {', '.join(MESH_UNITS)}")
    rng = np.random.default_rng(0)
    p = _surface_samples(v, f, 6000, rng)
    centre = p.mean(axis=0)
    q = p - centre
    _, vecs = np.linalg.eigh(q.T @ q)
    e1, e2, depth = vecs[:, 2], vecs[:, 1], vecs[:, 0]
    tree = cKDTree(p)
    if up is None:
        # The left-right axis is the one the surface is mirror-symmetric across.
        def mirror_gap(e):
            r = p - 2.0 * np.outer(q @ e, e)
            return float(np.median(tree.query(r)[0]))
        lr = e1 if mirror_gap(e1) < mirror_gap(e2) else e2
        up_vec = e2 if lr is e1 else e1
        # Up points away from the end split in two (the legs): few points near the mirror plane.
        along = q @ up_vec
        lo, hi = along.min(), along.max()
        height = hi - lo
        side = q @ lr
        def central_share(end_lo, end_hi):
            band = (along >= end_lo) & (along <= end_hi)
            return float(np.mean(np.abs(side[band]) < 0.03 * height)) if band.any() else 0.0
        feet_low = central_share(lo + 0.05 * height, lo + 0.15 * height)
        feet_high = central_share(hi - 0.15 * height, hi - 0.05 * height)
        if feet_high < feet_low:
            up_vec = -up_vec
        if min(feet_low, feet_high) > MAX_LEG_GAP_SHARE:
            raise RigError(f"{mesh_name}: no two legs found at either end of its long axes (share of the surface "
                           f"near the mirror plane {100 * feet_low:.0f} % and {100 * feet_high:.0f} % at the ends, a "
                           "standing body has almost none between its shins); expected a humanoid standing in an "
                           "A- or T-pose. Give its up axis (--up) if it stands otherwise")
    else:
        up_vec = np.array(_AXES[up])
    # The depth axis: the principal axis most orthogonal to up; front: where the toes point.
    depth = depth - (depth @ up_vec) * up_vec
    if np.linalg.norm(depth) < 0.5:
        cand = [e for e in (e1, e2, vecs[:, 0]) if abs(e @ up_vec) < 0.7]
        depth = cand[-1] - (cand[-1] @ up_vec) * up_vec
    depth /= np.linalg.norm(depth)
    along = q @ up_vec
    lo, height = along.min(), np.ptp(along)
    soles = along < lo + 0.04 * height
    shins = (along > lo + 0.08 * height) & (along < lo + 0.15 * height)
    if soles.sum() < 5 or shins.sum() < 5:
        raise RigError(f"{mesh_name}: no feet found at its lowest 4 % (along up {_axis_name(up_vec)}); expected a "
                       "humanoid standing in an A- or T-pose")
    if (q[soles] @ depth).mean() < (q[shins] @ depth).mean():
        depth = -depth
    left = np.cross(up_vec, depth)
    rotation = np.stack([left, up_vec, depth])           # rows: our x, y, z in the mesh's axes
    size = float(np.sqrt(signed_volume(v, f)[1]))
    if units is None:
        fits = plausible_units(float(height), size)
        if not fits:
            raise RigError(f"{mesh_name}: {height:.4g} units tall and {size:.4g} units of sqrt(area); no unit "
                           f"({', '.join(MESH_UNITS)}) makes that a human body. Scale it, or give --units")
        units = fits[0]
    scale = float(MESH_UNITS[units])
    internal = scale * p @ rotation.T
    translation = np.array([-internal[:, 0].mean(), -scale * (v @ up_vec).min(), -internal[:, 2].mean()])
    return BodyFrame(rotation, scale, translation, up if up is not None else _axis_name(up_vec), units)


# ------------------------------------------------------------------------------ the model

@dataclass(frozen=True)
class _Model:
    """The template as a posable, shapeable body (everything the fit needs, built once)."""

    rig: Rig
    mean: np.ndarray            # (V, 3)
    basis: np.ndarray           # (V, 3, K) shape directions (vertex-major: rows gather fast)
    head_mean: np.ndarray       # (B, 3)
    head_basis: np.ndarray      # (B, 3, K) their heads
    parents: np.ndarray         # (B,)
    order: np.ndarray           # (B,) parents first
    fitted: np.ndarray          # (P,) bone ids of FITTED_BONES
    subtree: np.ndarray         # (B, P) float: bone b turns with fitted bone p
    faces: np.ndarray


def _shape_basis(template: Template, k: int) -> np.ndarray:
    """(k, V, 3) leading principal directions of the macro targets (uncentred: bodies are the
    mean plus combinations of targets), each scaled to the targets' RMS spread along it. The
    directions come from the SVD on every 7th vertex (the targets are smooth), then are carried
    to all vertices through the targets themselves."""
    D = np.asarray(template.target_deltas, dtype=float).reshape(len(template.target_deltas), -1)   # (T, 3V)
    cols = (np.arange(0, template.n_vertices, 7)[:, None] * 3 + np.arange(3)).ravel()
    U, s, _ = np.linalg.svd(D[:, cols], full_matrices=False)
    coef = U[:, :k] / s[:k]                                              # (T, k)
    basis = coef.T @ D                                                   # (k, 3V), unit norm on the sample
    spread = s[:k] / np.sqrt(len(D))                                     # RMS coefficient of a target
    return (basis * spread[:, None]).reshape(k, template.n_vertices, 3)


@lru_cache(maxsize=1)
def _model() -> _Model:
    with single_threaded_blas():
        return _build_model()


def _build_model() -> _Model:
    template = load_template()
    rig = template.rigs["default"]
    basis = np.ascontiguousarray(_shape_basis(template, SHAPE_DIRECTIONS).transpose(1, 2, 0))   # (V, 3, K)
    mean = np.asarray(template.vertices, dtype=float)
    parents = np.asarray(rig.parents)
    fitted = np.array([rig.bone_index(b) for b in FITTED_BONES])
    order = topological_order(parents)
    P, B = len(fitted), rig.n_bones
    # nearest fitted ancestor (itself included) of every bone; subtree[b, p]: p is an ancestor-or-self
    # of b among the fitted bones
    subtree = np.zeros((B, P))
    pos = {int(b): i for i, b in enumerate(fitted)}
    for b in range(B):
        a = b
        while a >= 0:
            if a in pos:
                subtree[b, pos[a]] = 1.0
            a = parents[a]
    head_mean = rig.heads(mean)
    head_basis = np.asarray(rig.head_regressor @ basis.reshape(len(mean), -1)).reshape(rig.n_bones, 3, -1)
    return _Model(rig, mean, basis, head_mean, head_basis, parents, order, fitted, subtree,
                  np.asarray(template.faces, dtype=np.int64))


@dataclass
class _State:
    """Parameters of the fit: shape c (K,), relative rotations R (B, 3, 3), scale s, shift t (3,)."""

    c: np.ndarray
    R: np.ndarray
    s: float
    t: np.ndarray

    def copy(self) -> "_State":
        return _State(self.c.copy(), self.R.copy(), float(self.s), self.t.copy())


def _pose(model: _Model, st: _State):
    """Rest heads (B, 3) and world transforms (B, 4, 4) of the state."""
    heads = model.head_mean + model.head_basis @ st.c
    G = forward_kinematics(st.R[None], heads[None], model.parents)[0]
    return heads, G


def _posed(model: _Model, st: _State, ids: np.ndarray, G: np.ndarray) -> np.ndarray:
    """Posed vertices (n, 3) of template vertices ``ids``."""
    x = model.mean[ids] + model.basis[ids] @ st.c
    W = model.rig.weights[ids].tocoo()
    gx = np.einsum("nij,nj->ni", G[W.col, :3, :3], x[W.row]) + G[W.col, :3, 3]
    blend = sp.csr_matrix((W.data, (W.row, np.arange(len(W.row)))), shape=(len(ids), len(W.row)))
    return st.s * (blend @ gx) + st.t


def _jacobian(model: _Model, st: _State, ids: np.ndarray, heads: np.ndarray, G: np.ndarray):
    """Posed vertices (n, 3) of ``ids`` and their derivatives (n, 3, 3P + K + 4): world-frame turns
    of each fitted bone's subtree about its posed joint, shape coefficients, scale, shift."""
    n, P, K = len(ids), len(model.fitted), len(st.c)
    U = model.basis[ids]                                                # (n, 3, K)
    x = model.mean[ids] + U @ st.c
    W = model.rig.weights[ids].tocoo()
    r, b, w = W.row, W.col, W.data
    A, tau = G[:, :3, :3], G[:, :3, 3]
    gx = np.einsum("nij,nj->ni", A[b], x[r]) + tau[b]                   # (nnz, 3)
    Mrow = sp.csr_matrix((w, (r, np.arange(len(r)))), shape=(n, len(r)))
    unscaled = Mrow @ gx                                                # (n, 3)
    J = np.zeros((n, 3, 3 * P + K + 4))
    # rotations: d y = s * delta x q_vp, q_vp = sum_{b in sub(p)} w_vb g_vb - W_sub J_p
    joints = np.einsum("bij,bj->bi", A, heads) + tau                    # posed heads (B, 3)
    sub = model.subtree[b]                                              # (nnz, P)
    Wsub = Mrow @ sub                                                   # (n, P)
    Psub = np.stack([Mrow @ (sub * gx[:, k:k + 1]) for k in range(3)], axis=-1)   # (n, P, 3)
    q = Psub - Wsub[:, :, None] * joints[model.fitted][None]            # (n, P, 3)
    # d(delta x q)/d delta = -[q]x
    qx = np.zeros((n, P, 3, 3))
    qx[..., 0, 1], qx[..., 0, 2] = q[..., 2], -q[..., 1]
    qx[..., 1, 0], qx[..., 1, 2] = -q[..., 2], q[..., 0]
    qx[..., 2, 0], qx[..., 2, 1] = q[..., 1], -q[..., 0]
    J[:, :, :3 * P] = st.s * qx.transpose(0, 2, 1, 3).reshape(n, 3, 3 * P)
    # shape: through the vertices and the joints (tau_b = tau_parent + (A_parent - A_b) h_b)
    dtau = np.zeros((len(A), 3, K))
    for bone in model.order:
        p = model.parents[bone]
        dh = model.head_basis[bone]                                     # (3, K)
        if p < 0:
            dtau[bone] = (np.eye(3) - A[bone]) @ dh
        else:
            dtau[bone] = dtau[p] + (A[p] - A[bone]) @ dh
    per = np.einsum("nij,njk->nik", A[b], U[r]) + dtau[b]               # (nnz, 3, K)
    J[:, :, 3 * P:3 * P + K] = st.s * (Mrow @ per.reshape(len(r), 3 * K)).reshape(n, 3, K)
    J[:, :, 3 * P + K] = unscaled
    J[:, :, 3 * P + K + 1:] = np.eye(3)[None]
    return st.s * unscaled + st.t, J


def _apply_step(model: _Model, st: _State, step: np.ndarray, G: np.ndarray) -> _State:
    """The state after a step: turns delta_p (world frame) of each fitted bone's subtree,
    ``R_p <- A_par^T exp(delta) A_par R_p`` (A_par the parent's world rotation)."""
    P, K = len(model.fitted), len(st.c)
    new = st.copy()
    A = G[:, :3, :3]
    for i, bone in enumerate(model.fitted):
        p = model.parents[bone]
        Ap = A[p] if p >= 0 else np.eye(3)
        new.R[bone] = Ap.T @ rotvec_to_matrix(step[3 * i:3 * i + 3]) @ Ap @ st.R[bone]
    new.c = st.c + step[3 * P:3 * P + K]
    new.s = st.s + step[3 * P + K]
    new.t = st.t + step[3 * P + K + 1:]
    return new


def _rotation_about(axis: np.ndarray, angle: float) -> np.ndarray:
    return rotvec_to_matrix(np.asarray(axis, dtype=float) * angle)


def _start(model: _Model, points: np.ndarray) -> _State:
    """Template scaled to the mesh's height, on its feet, arms turned toward its hands."""
    B, K = model.rig.n_bones, model.basis.shape[2]
    st = _State(np.zeros(K), np.tile(np.eye(3), (B, 1, 1)), 1.0, np.zeros(3))
    height = points[:, 1].max() - points[:, 1].min()
    st.s = height / float(np.ptp(model.mean[:, 1]))
    st.t = np.array([0.0, -st.s * model.mean[:, 1].min(), 0.0])
    st.t[[0, 2]] -= st.s * model.mean[:, [0, 2]].mean(axis=0)
    upper = points[points[:, 1] > 0.45 * height]
    m_upper = model.mean[model.mean[:, 1] > model.mean[:, 1].min() + 0.45 * np.ptp(model.mean[:, 1])]
    for side, sign in (("L", 1.0), ("R", -1.0)):
        bone = model.rig.bone_index(f"upperarm01.{side}")
        shoulder = model.head_mean[bone]
        tip_m = m_upper[np.argmax(sign * m_upper[:, 0])]
        tip_t = (upper[np.argmax(sign * upper[:, 0])] - st.t) / st.s
        a_m = np.arctan2(tip_m[1] - shoulder[1], sign * (tip_m[0] - shoulder[0]))
        a_t = np.arctan2(tip_t[1] - shoulder[1], sign * (tip_t[0] - shoulder[0]))
        st.R[bone] = _rotation_about([0.0, 0.0, sign], a_t - a_m)
    return st


def _pairs(model: _Model, st: _State, target: np.ndarray, target_normals: np.ndarray, target_tree: cKDTree,
           sample: np.ndarray, mesh_pick: np.ndarray):
    """Closest-point pairs of one round in both directions: (template vertex ids, mesh points,
    mesh normals, Huber weights)."""
    _, G = _pose(model, st)
    V = len(model.mean)
    everything = np.arange(V)
    posed = _posed(model, st, everything, G)
    normals = vertex_normals(posed, model.faces)
    # template -> mesh
    d1, j1 = target_tree.query(posed[sample])
    ok1 = (normals[sample] * target_normals[j1]).sum(1) > MIN_NORMAL_DOT
    # mesh -> template (over the sampled template vertices)
    model_tree = cKDTree(posed[sample])
    d2, k2 = model_tree.query(target[mesh_pick])
    ok2 = (normals[sample[k2]] * target_normals[mesh_pick]).sum(1) > MIN_NORMAL_DOT
    ids = np.concatenate([sample[ok1], sample[k2[ok2]]])
    pts = np.concatenate([target[j1[ok1]], target[mesh_pick[ok2]]])
    nrm = np.concatenate([target_normals[j1[ok1]], target_normals[mesh_pick[ok2]]])
    dist = np.concatenate([d1[ok1], d2[ok2]])
    huber = max(HUBER_FACTOR * float(np.median(dist)), HUBER_MIN)
    wts = np.where(dist <= huber, 1.0, huber / np.maximum(dist, 1e-12))
    return ids, pts, nrm, wts


def _cost(model: _Model, st: _State, start: _State, ids, pts, nrm, wts) -> float:
    _, G = _pose(model, st)
    y = _posed(model, st, ids, G)
    r = ((y - pts) * nrm).sum(1)
    return float((wts * r * r).sum() / wts.sum()) + _prior_cost(model, st, start)


def _prior_cost(model: _Model, st: _State, start: _State) -> float:
    rel = matrix_to_rotvec(st.R[model.fitted[1:]] @ np.swapaxes(start.R[model.fitted[1:]], -1, -2))
    return SHAPE_PRIOR * float(st.c @ st.c) + POSE_PRIOR * float((rel * rel).sum())


def _fit(model: _Model, target: np.ndarray, target_normals: np.ndarray, iterations: int = ITERATIONS):
    """Levenberg-Marquardt over iterated closest points (module docstring, 3): new pairs every
    round, one damped Gauss-Newton step on them, kept only if it lowers their cost. Ends after
    ``iterations`` rounds, or when a round lowers the cost by less than ``COST_TOLERANCE`` of it
    (the pairs' point-to-plane distance has reached the meshes' sampling floor, ~3 mm at 5,000
    vertices). Returns the state, the RMS distance (metres) of the last pairs and the rounds."""
    rng = np.random.default_rng(0)
    V = len(model.mean)
    sample = np.sort(rng.choice(V, size=min(MODEL_SAMPLES, V), replace=False))
    mesh_pick = np.sort(rng.choice(len(target), size=min(MESH_SAMPLES, len(target)), replace=False))
    tree = cKDTree(target)
    st = _start(model, target)
    start = st.copy()
    P, K = len(model.fitted), len(st.c)
    lam = LM_START
    rms = np.inf
    rounds = 0
    for rounds in range(1, iterations + 1):
        ids, pts, nrm, wts = _pairs(model, st, target, target_normals, tree, sample, mesh_pick)
        heads, G = _pose(model, st)
        y, J = _jacobian(model, st, ids, heads, G)
        r = ((y - pts) * nrm).sum(1)
        rms = float(np.sqrt(np.mean(r * r)))
        Jr = np.einsum("nij,ni->nj", J, nrm)                            # (n, 3P + K + 4)
        sw = wts / wts.sum()
        H = Jr.T @ (Jr * sw[:, None])
        g = Jr.T @ (sw * r)
        # priors: shape coefficients toward 0, the fitted bones' turns (but the root's) toward the start
        H[3 * P:3 * P + K, 3 * P:3 * P + K] += SHAPE_PRIOR * np.eye(K)
        g[3 * P:3 * P + K] += SHAPE_PRIOR * st.c
        H[3:3 * P, 3:3 * P] += POSE_PRIOR * np.eye(3 * P - 3)
        g[3:3 * P] += POSE_PRIOR * _turns(model, st, start, G)[1:].ravel()
        cost0 = _cost(model, st, start, ids, pts, nrm, wts)
        gain = 0.0
        for _try in range(LM_MAX_TRIES):
            step = -np.linalg.solve(H + lam * np.diag(np.diag(H) + 1e-12), g)
            cand = _apply_step(model, st, step, G)
            new = _cost(model, cand, start, ids, pts, nrm, wts)
            if new < cost0:
                st, gain = cand, (cost0 - new) / cost0
                lam = max(lam / 3.0, 1e-7)
                break
            lam *= 4.0
        if gain < COST_TOLERANCE:
            break
    return st, rms, rounds


def _turns(model: _Model, st: _State, start: _State, G: np.ndarray) -> np.ndarray:
    """(P, 3) each fitted bone's turn from the start, as a world-frame rotation vector."""
    rel = matrix_to_rotvec(st.R[model.fitted] @ np.swapaxes(start.R[model.fitted], -1, -2))
    par = model.parents[model.fitted]
    A = np.where((par >= 0)[:, None, None], G[np.maximum(par, 0), :3, :3], np.eye(3))
    return np.einsum("pij,pj->pi", A, rel)


# ------------------------------------------------------------------------------ the interior

@numba.njit(cache=True, nogil=True)
def _winding_kernel(points, a, b, c, out):
    """Sum over triangles (a, b, c) (F, 3) of signed solid angles seen from each point, / 4 pi."""
    for i in range(points.shape[0]):
        px, py, pz = points[i, 0], points[i, 1], points[i, 2]
        total = 0.0
        for f in range(a.shape[0]):
            ax, ay, az = a[f, 0] - px, a[f, 1] - py, a[f, 2] - pz
            bx, by, bz = b[f, 0] - px, b[f, 1] - py, b[f, 2] - pz
            cx, cy, cz = c[f, 0] - px, c[f, 1] - py, c[f, 2] - pz
            la = np.sqrt(ax * ax + ay * ay + az * az)
            lb = np.sqrt(bx * bx + by * by + bz * bz)
            lc = np.sqrt(cx * cx + cy * cy + cz * cz)
            det = ax * (by * cz - bz * cy) - ay * (bx * cz - bz * cx) + az * (bx * cy - by * cx)
            den = (la * lb * lc + (ax * bx + ay * by + az * bz) * lc + (bx * cx + by * cy + bz * cz) * la
                   + (cx * ax + cy * ay + cz * az) * lb)
            total += np.arctan2(det, den)
        out[i] = total / (2.0 * np.pi)


def winding_numbers(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Generalized winding numbers (P,) of points (P, 3) for a mesh (V, 3), (F, 3): about 1 inside
    a closed outward-wound surface, 0 outside, in between near holes (Jacobson et al. 2013: the
    sum of the faces' signed solid angles over 4 pi, each by Van Oosterom & Strackee 1983). A
    compiled loop: P x F triangle terms (100 points of a 48,000-face mesh in ~0.1 s)."""
    v = np.asarray(vertices, dtype=float)
    f = np.asarray(faces, dtype=np.int64)
    out = np.empty(len(points))
    _winding_kernel(np.ascontiguousarray(points, dtype=float), np.ascontiguousarray(v[f[:, 0]]),
                    np.ascontiguousarray(v[f[:, 1]]), np.ascontiguousarray(v[f[:, 2]]), out)
    return out


def into_interior(points: np.ndarray, anchors: np.ndarray, movable: np.ndarray, vertices: np.ndarray,
                  faces: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """Points (P, 3) with every ``movable`` (P,) one that lies outside the mesh (winding number
    below 1/2) moved toward one of its anchors (P, 3) or (P, A, 3) (points of the same limb
    inside the body: its bone's other end, its parent's joint; the one giving the shortest move)
    to ``INTERIOR_DEPTH`` past where the segment enters the body (found on ``INTERIOR_STEPS``
    points of the segment), never past the segment's middle. A point whose anchors are outside
    too, or that would move more than ``MAX_INTERIOR_MOVE``, stays. vertices (V, 3), faces
    (F, 3), normals (V, 3) outward unit normals, metres. Returns (P, 3). Moving along the limb,
    not to the nearest surface, keeps a fingertip on its own finger (the nearest surface may be
    the next finger's)."""
    pts = np.array(points, dtype=float)
    anchors = np.asarray(anchors, dtype=float)
    dist, nearest = cKDTree(vertices).query(pts)
    # Only points near the surface and not deep under their nearest vertex's tangent plane are
    # tested (the winding number costs a pass over the faces per point; at a fingertip of a coarse
    # mesh a point 2.5 mm under that plane can still be outside).
    above = np.einsum("ij,ij->i", pts - vertices[nearest], normals[nearest]) > -2.0 * INTERIOR_DEPTH
    test = np.flatnonzero(np.asarray(movable) & (dist < NEAR_SURFACE) & above)
    if not len(test):
        return pts
    outside = test[winding_numbers(pts[test], vertices, faces) < 0.5]
    fractions = np.linspace(0.0, 1.0, INTERIOR_STEPS + 1)[1:]              # from the point toward the anchor
    for i in outside:
        best = None
        ends = anchors[i].reshape(-1, 3)
        along = pts[i] + fractions[None, :, None] * (ends[:, None, :] - pts[i])          # (A, S, 3)
        w_along = winding_numbers(along.reshape(-1, 3), vertices, faces).reshape(len(ends), -1)
        for anchor, w in zip(ends, w_along):                                # the shortest way in
            length = float(np.linalg.norm(anchor - pts[i]))
            if length < 1e-9:
                continue
            inside = np.flatnonzero(w > 0.5)
            if not len(inside):
                continue                                                   # this anchor is outside too
            # never past the segment's middle: an anchor is often the bone's other end, and a
            # bone keeps a length
            if fractions[inside[0]] > 0.5:
                continue
            f = min(fractions[inside[0]] + INTERIOR_DEPTH / length, 0.5)
            if f * length <= MAX_INTERIOR_MOVE and (best is None or f * length < best[0]):
                best = (f * length, pts[i] + f * (anchor - pts[i]))
        if best is not None:
            pts[i] = best[1]
    return pts


def _movable(rig: Rig) -> np.ndarray:
    """(B,) bones whose ends are kept inside the mesh: skinned, not the face's control bones."""
    skinned = np.asarray(abs(rig.weights).sum(axis=0)).ravel() > 0
    return skinned & np.array([joint_group(b) != "face" for b in rig.bone_names])


# ------------------------------------------------------------------------------ the embedding

@dataclass(frozen=True)
class Embedding:
    """The default rig fitted into one mesh.

    joints: (B, 3) the default rig's posed bone heads in the mesh's own coordinates (units, axes).
    frame: the mesh's ``BodyFrame`` (``frame.to_internal`` gives metres, our axes).
    rest_body: (V, 3) the fitted template body at rest (metres, our axes, at the template's
        origin); posed_body: (V, 3) the fitted template posed into the mesh (metres, our axes,
        the internal frame of ``frame``); transforms: (B, 4, 4) the fitted bone transforms
        (rest -> posed, the internal frame; the fit's scale included).
    residual_m: RMS point-to-plane distance (metres) of the last round's closest-point pairs.
    rounds: closest-point rounds the fit took.
    mesh_vertices, mesh_faces, mesh_normals: the mesh in the internal frame (metres, our axes),
        with outward unit vertex normals: joints are kept inside it (``into_interior``).
    """

    joints: np.ndarray
    frame: BodyFrame
    rest_body: np.ndarray
    posed_body: np.ndarray
    transforms: np.ndarray
    residual_m: float
    rounds: int
    mesh_vertices: np.ndarray
    mesh_faces: np.ndarray
    mesh_normals: np.ndarray

    @property
    def internal_joints(self) -> np.ndarray:
        """(B, 3) the joints in metres, our axes (the internal frame of ``frame``)."""
        return self.frame.to_internal(self.joints)


def embed_skeleton(vertices: np.ndarray, faces: np.ndarray, *, up: str | None = None, units: str | None = None,
                   mesh_name: str = "the mesh", iterations: int = ITERATIONS) -> Embedding:
    """Embed the default CC0 rig into a humanoid mesh of any topology (module docstring).

    vertices (V, 3), faces (F, 3): one body standing in an A- or T-pose, any vertex count, frame and
    unit; up, units: as in ``body_frame`` (found from the geometry when None).
    Returns an ``Embedding``; raises ``RigError`` for several components, a mesh far from closed,
    or one the template cannot be fitted to (not a humanoid in an A- or T-pose).
    """
    check_riggable(vertices, faces, mesh_name)
    v = np.asarray(vertices, dtype=float)
    f = np.asarray(faces, dtype=np.int64)
    frame = body_frame(v, f, up, units, mesh_name)
    x = frame.to_internal(v)
    used = np.unique(f)
    if signed_volume(x, f)[0] < 0:                 # wound inwards: turn it out (normals, winding numbers)
        f = f[:, ::-1].copy()
    normals = vertex_normals(x, f)
    model = _model()
    # Small dense matrices (a few thousand rows, 116 columns): BLAS threads only contend.
    with single_threaded_blas():
        st, rms, rounds = _fit(model, x[used], normals[used], iterations)
    height = float(np.ptp(x[used, 1]))
    if not rms <= MAX_RESIDUAL_SHARE * height:
        raise RigError(f"{mesh_name}: not a humanoid in an A- or T-pose: the best fit of the template body leaves "
                       f"{1000 * rms:.0f} mm RMS between the surfaces (at most {100 * MAX_RESIDUAL_SHARE:g} % of its "
                       f"{height:.2f} m height, {1000 * MAX_RESIDUAL_SHARE * height:.0f} mm, for a body; read "
                       f"with up {frame.up} ({'given' if up else 'found'}) and units {frame.units} "
                       f"({'given' if units else 'found'})); expected a "
                       "person standing with arms out (A- or T-pose)"
                       + ("" if up is not None and units is not None else
                          ". If the up axis or the unit is wrong, give them (--up, --units)"))
    heads, G = _pose(model, st)
    T = G.copy()
    T[:, :3, :] *= st.s
    T[:, :3, 3] += st.t
    joints = np.einsum("bij,bj->bi", T[:, :3, :3], heads) + T[:, :3, 3]
    par = model.parents
    tails = np.einsum("bij,bj->bi", T[:, :3, :3], model.rig.tails(model.mean + model.basis @ st.c)) + T[:, :3, 3]
    anchors = np.stack([joints[np.where(par >= 0, par, np.arange(len(par)))], tails], axis=1)   # (B, 2, 3)
    joints = into_interior(joints, anchors, _movable(model.rig), x, f, normals)
    rest = model.mean + model.basis @ st.c
    posed = _posed(model, st, np.arange(len(rest)), G)
    return Embedding(frame.from_internal(joints), frame, rest, posed, T, rms, rounds, x, f, normals)


def embedded_skeleton(embedding: Embedding, rig: Rig, frame: str = "internal") -> Skeleton:
    """Every bone of a CC0 rig (any of ``load_template().rigs``) placed from an embedding.

    Heads and tails are regressed on the fitted rest body and carried by the fitted pose: for the
    default rig (the one fitted) by its own bone transforms (forward kinematics); for another rig
    each point by the blend of the default rig's bone transforms that its regressor's skin
    carries (at a joint between two bones both give the same point). Rolls follow the skin
    (``body_skeleton``). frame: "internal" (metres, our axes: what glTF wants)
    or "mesh" (the mesh's own coordinates).
    """
    if frame not in ("internal", "mesh"):
        raise ParameterError(f"frame={frame!r}; expected 'internal' or 'mesh'")
    model = _model()
    Wd = model.rig.weights.tocsr()
    T = embedding.transforms

    def carry(regressor: sp.csr_matrix, points: np.ndarray) -> np.ndarray:
        mix = regressor @ Wd                                         # (B', B) skin of each point
        mix = sp.csr_matrix(mix)
        mix.data = np.maximum(mix.data, 0.0)
        mix = sp.diags(1.0 / np.maximum(np.asarray(mix.sum(axis=1)).ravel(), 1e-12)) @ mix
        moved = np.einsum("bij,nj->nbi", T[:, :3, :3], points) + T[None, :, :3, 3]   # (B', B, 3)
        return np.asarray(np.einsum("nb,nbi->ni", mix.toarray(), moved))

    rest = embedding.rest_body
    if rig.bone_names == model.rig.bone_names:       # the fitted rig itself: forward kinematics exactly
        heads = np.einsum("bij,bj->bi", T[:, :3, :3], rig.heads(rest)) + T[:, :3, 3]
        tails = np.einsum("bij,bj->bi", T[:, :3, :3], rig.tails(rest)) + T[:, :3, 3]
    else:
        heads = carry(rig.head_regressor, rig.heads(rest))
        tails = carry(rig.tail_regressor, rig.tails(rest))
    keep_inside = _movable(rig)
    mesh = (embedding.mesh_vertices, embedding.mesh_faces, embedding.mesh_normals)
    par = np.asarray(rig.parents)
    anchors = np.stack([heads[np.where(par >= 0, par, np.arange(len(par)))], tails], axis=1)    # (B, 2, 3)
    moved_heads = into_interior(heads, anchors, keep_inside, *mesh)
    moved_tails = into_interior(tails, moved_heads, keep_inside, *mesh)
    # a bone the moves would shorten to nothing keeps its fitted ends
    short = np.linalg.norm(moved_tails - moved_heads, axis=1) < 1e-6
    heads = np.where(short[:, None], heads, moved_heads)
    tails = np.where(short[:, None], tails, moved_tails)
    skeleton = body_skeleton(rig, embedding.posed_body, heads=heads, tails=tails)
    if frame == "internal":
        return skeleton
    fr = embedding.frame
    h, t = fr.from_internal(skeleton.heads), fr.from_internal(skeleton.tails)
    x_axis = skeleton.frames[:, :, 0] @ fr.rotation                 # rotation.T applied to each row
    return Skeleton(skeleton.name, skeleton.bone_names, skeleton.parents, h, t, roll_from_x_axis(h, t, x_axis))
