"""Skeletons for bodies: bone heads, tails and rolls of a rig, recomputed for each body.

A ``Skeleton`` is what an exporter or a posing tool needs of one body's rig: bone names,
parents, heads, tails and Blender rolls, in metres and our axes (+Y up, +Z front). For a body
of the template topology ``body_skeleton(rig, vertices)`` regresses heads and tails from the
body's own vertices (the rig's sparse regressors), so a taller body gets longer bones and a
heavier one a wider pelvis. Skeletons from other sources (skeleton embedding into any mesh)
build a ``Skeleton`` directly and plug into the same exporters.

Rolls. MPFB2 stores one roll per bone for its base mesh. A roll is measured against Blender's
reference frame of the bone direction (the minimal rotation taking +Y to it), so keeping the
stored number on a body whose bone points elsewhere turns the bone's local axes with that
reference, by a large amount for bones near Blender's singular direction (feet, toes and
breasts point forward, along Blender's -Y). ``body_skeleton`` instead carries the template
bone's local x axis to the body: rotated by the best rotation of the skin the bone carries
(weighted Kabsch, template -> body; a bone without skin of its own, such as an eye or a root,
takes its parent's), then made orthogonal to the body's bone direction; the roll is the angle
that gives that axis. On the template itself this returns the stored rolls;
on a body whose limb is twisted (a posed model) the roll follows the twist of the skin.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from bodyspace.data.template import Rig, load_template
from bodyspace.errors import MeshError, ParameterError
from bodyspace.rig.kinematics import bone_rest_frames, topological_order

__all__ = ["Skeleton", "body_skeleton", "roll_from_x_axis", "skin_rotations"]

# A bone whose skin weights sum to less than this (in vertices' worth) or whose weighted skin is
# nearly flat or collinear takes its parent's rotation instead of a Kabsch fit of its own.
_MIN_SKIN_WEIGHT = 3.0
_MIN_SPREAD = 1e-10  # m^2: second-smallest eigenvalue of the weighted covariance


@dataclass(frozen=True)
class Skeleton:
    """One body's skeleton: (B,) bones in metres, our axes (+Y up, +Z front, +X the person's left).

    heads, tails: (B, 3); roll: (B,) Blender bone roll (radians); parents: (B,) int, -1 for a
    root. ``frames`` are the bones' rest orientations (columns local x, y = head -> tail, z).
    """

    name: str
    bone_names: tuple[str, ...]
    parents: np.ndarray
    heads: np.ndarray
    tails: np.ndarray
    roll: np.ndarray

    def __post_init__(self):
        object.__setattr__(self, "bone_names", tuple(str(b) for b in self.bone_names))
        B = len(self.bone_names)
        parents = np.asarray(self.parents, dtype=np.int64)
        heads, tails = np.asarray(self.heads, dtype=float), np.asarray(self.tails, dtype=float)
        roll = np.asarray(self.roll, dtype=float)
        if B == 0:
            raise ParameterError(f"skeleton {self.name!r}: no bones; expected at least one")
        if len(set(self.bone_names)) != B:
            dup = sorted({b for b in self.bone_names if self.bone_names.count(b) > 1})
            raise ParameterError(f"skeleton {self.name!r}: bone names {dup} appear twice; expected unique names")
        for label, a, shape in (("parents", parents, (B,)), ("heads", heads, (B, 3)), ("tails", tails, (B, 3)),
                                ("roll", roll, (B,))):
            if a.shape != shape:
                raise ParameterError(f"skeleton {self.name!r}: {label} has shape {a.shape}, expected {shape} "
                                     f"for {B} bones")
            if not np.isfinite(a).all():
                raise ParameterError(f"skeleton {self.name!r}: {label} holds NaN or infinity, expected finite values")
        topological_order(parents)  # refuses indices out of range and cycles
        length = np.linalg.norm(tails - heads, axis=1)
        if (length <= 0).any():
            b = int(np.argmin(length))
            raise MeshError(f"skeleton {self.name!r}: bone {self.bone_names[b]!r} has zero length (head == tail); "
                            "expected distinct ends")
        object.__setattr__(self, "parents", parents)
        object.__setattr__(self, "heads", heads)
        object.__setattr__(self, "tails", tails)
        object.__setattr__(self, "roll", roll)

    @property
    def n_bones(self) -> int:
        return len(self.bone_names)

    @property
    def lengths(self) -> np.ndarray:
        """(B,) bone lengths in metres."""
        return np.linalg.norm(self.tails - self.heads, axis=1)

    @property
    def frames(self) -> np.ndarray:
        """(B, 3, 3) rest orientations: columns the bone's local x, y (head -> tail), z (Blender's)."""
        return bone_rest_frames(self.heads, self.tails, self.roll)

    def bind_matrices(self) -> np.ndarray:
        """(B, 4, 4) world matrices of the bones at rest: ``[frame | head]``; their inverses are a
        glTF skin's inverse bind matrices."""
        M = np.zeros((self.n_bones, 4, 4))
        M[:, :3, :3] = self.frames
        M[:, :3, 3] = self.heads
        M[:, 3, 3] = 1.0
        return M

    def bone_index(self, name: str) -> int:
        try:
            return self.bone_names.index(name)
        except ValueError:
            raise ParameterError(f"bone {name!r}: not a bone of skeleton {self.name!r}; expected one of "
                                 f"{', '.join(self.bone_names)}") from None


def roll_from_x_axis(heads: np.ndarray, tails: np.ndarray, x_axis: np.ndarray) -> np.ndarray:
    """Blender rolls (...,) whose bone frames have local x closest to ``x_axis`` (..., 3).

    heads, tails, x_axis: (..., 3) in our axes. The frame of roll r is Blender's reference frame
    of the bone direction turned by r about it: ``x(r) = cos r x0 - sin r z0`` (columns x0, z0
    of ``bone_rest_frames`` at roll 0), so ``r = atan2(-x.z0, x.x0)``. An ``x_axis`` parallel to
    the bone gives roll 0.
    """
    h, t = np.asarray(heads, dtype=float), np.asarray(tails, dtype=float)
    x = np.asarray(x_axis, dtype=float)
    F0 = bone_rest_frames(h[..., None, :], t[..., None, :], np.zeros(1))[..., 0, :, :]
    return np.arctan2(-np.einsum("...i,...i->...", x, F0[..., :, 2]), np.einsum("...i,...i->...", x, F0[..., :, 0]))


def skin_rotations(weights: sp.spmatrix, rest: np.ndarray, body: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Best rotation per bone of the skin it carries, rest -> body (weighted Kabsch).

    weights: (V, B) skin weights; rest, body: (V, 3) the same vertices on two bodies.
    Returns rotations (B, 3, 3) and a mask (B,) of the bones whose skin determined one (enough
    weight, not flat or collinear); the others get the identity.
    """
    W = sp.csc_matrix(weights, dtype=float)
    x, y = np.asarray(rest, dtype=float), np.asarray(body, dtype=float)
    mass = np.asarray(W.sum(axis=0)).ravel()                                       # (B,)
    safe = np.maximum(mass, 1e-300)[:, None]
    mx, my = (W.T @ x) / safe, (W.T @ y) / safe                                    # (B, 3)
    xy = (W.T @ (x[:, :, None] * y[:, None, :]).reshape(-1, 9)).reshape(-1, 3, 3)  # sum w x y^T
    xx = (W.T @ (x[:, :, None] * x[:, None, :]).reshape(-1, 9)).reshape(-1, 3, 3)
    C = xy - mass[:, None, None] * mx[:, :, None] * my[:, None, :]
    S = xx - mass[:, None, None] * mx[:, :, None] * mx[:, None, :]
    spread = np.linalg.eigvalsh(S / safe[:, :, None])[:, 1]
    ok = (mass >= _MIN_SKIN_WEIGHT) & (spread > _MIN_SPREAD)
    U, _, Vt = np.linalg.svd(C[ok])
    d = np.sign(np.linalg.det(U @ Vt))
    D = np.ones((len(d), 3))
    D[:, 2] = d
    R = np.tile(np.eye(3), (len(mass), 1, 1))
    R[ok] = np.einsum("bji,bj,bkj->bik", Vt, D, U)          # V diag(1, 1, d) U^T
    return R, ok


def body_skeleton(rig: Rig, vertices: np.ndarray, rest_vertices: np.ndarray | None = None, *,
                  heads: np.ndarray | None = None, tails: np.ndarray | None = None) -> Skeleton:
    """The skeleton of ``rig`` on one body of the template topology.

    rig: a ``Rig`` of the template (``load_template().rigs[name]``).
    vertices: (V, 3) the body, metres, our axes.
    rest_vertices: (V, 3) the body the rig's rolls were authored on; by default the shipped
        template's vertices (``load_template().vertices``).
    heads, tails: (B, 3) the bones' ends when known otherwise (skeleton embedding places them by
        forward kinematics); by default regressed from ``vertices``.
    Returns a ``Skeleton`` with heads and tails regressed from ``vertices`` (or as given) and
    rolls carried over by the skin's rotation (module docstring).
    """
    v = np.asarray(vertices, dtype=float)
    V = rig.weights.shape[0]
    if v.shape != (V, 3):
        raise MeshError(f"vertices: shape {v.shape}, expected ({V}, 3): a body of the template topology for "
                        f"rig {rig.name!r}")
    if not np.isfinite(v).all():
        raise MeshError("vertices: contain NaN or infinity, expected finite coordinates")
    heads = rig.heads(v) if heads is None else np.asarray(heads, dtype=float)
    tails = rig.tails(v) if tails is None else np.asarray(tails, dtype=float)
    if heads.shape != (rig.n_bones, 3) or tails.shape != (rig.n_bones, 3):
        raise MeshError(f"heads, tails: shapes {heads.shape}, {tails.shape}; expected ({rig.n_bones}, 3) for rig "
                        f"{rig.name!r}")
    r = np.asarray(load_template().vertices if rest_vertices is None else rest_vertices, dtype=float)
    if r.shape != (V, 3):
        raise MeshError(f"rest_vertices: shape {r.shape}, expected ({V}, 3)")
    h0, t0 = rig.heads(r), rig.tails(r)
    x0 = bone_rest_frames(h0, t0, rig.roll)[:, :, 0]
    R, ok = skin_rotations(rig.weights, r, v)
    # A bone without skin of its own (eyes, a root, IK helpers) turns with its nearest ancestor
    # that has some, or with the whole body: the frames stay equivariant under a rigid motion.
    R_body, _ = skin_rotations(sp.csr_matrix(np.ones((V, 1))), r, v)
    for b in topological_order(rig.parents):
        if not ok[b]:
            p = rig.parents[b]
            R[b] = R[p] if p >= 0 else R_body[0]
    roll = roll_from_x_axis(heads, tails, np.einsum("bij,bj->bi", R, x0))
    return Skeleton(rig.name, rig.bone_names, np.asarray(rig.parents), heads, tails, roll)
