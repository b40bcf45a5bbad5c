"""Masked morphing (Hasler §5.1): a change confined to body regions by a masked Poisson solve.

Hasler §5.1: "A multiplicative mask allows deformation to occur in selected areas. The
reconstruction process spreads out" the change at the mask's border. Here the mask multiplies
the change of every triangle's gradient, and a Poisson solve (Yu et al. 2004, the same
reconstruction as Hasler's encoding) rebuilds the surface with the vertices outside the mask
held fixed:

    minimise  sum_f area_f || grad_f(d') - w_f grad_f(d) ||^2   over d' (V, 3),  d' = 0 where w = 0,

``grad_f`` the gradient operator on the rest mesh (``mesh.operators.gradient_operator``), ``w_f``
the mean weight of face f's corners. The normal matrix is the cotangent Laplacian
(``mesh.operators.cotangent_laplacian``) restricted to the free vertices, factored once per mask
(``mesh.solver.FactorizedSolver``); a morph then pays three triangular solves. Inside the mask
the change is kept, at the seam it fades over the blended triangles, outside nothing moves
(exactly 0.000 mm: those rows are never written).

Regions (``REGIONS``) are per-vertex weights from the template's default rig (sums of skinning
weights over a region's bones, smooth across joints) and its left/right vertex groups.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from bodyspace.errors import ParameterError
from bodyspace.mesh.operators import cotangent_laplacian, gradient_operator
from bodyspace.mesh.solver import FactorizedSolver

__all__ = ["REGIONS", "region_weights_from_template", "MaskedPoissonBlend", "masked_poisson_blend"]

REGIONS = ("upper_body", "lower_body", "arms", "legs", "torso", "head", "left", "right")
_ARM = ("shoulder01", "upperarm", "lowerarm", "wrist", "finger", "metacarpal")
_LEG = ("upperleg", "lowerleg", "foot", "toe")
_LOWER = _LEG + ("pelvis", "spine05", "root")
_TORSO = ("spine", "pelvis", "breast", "clavicle", "root")


def region_weights_from_template(template) -> dict[str, np.ndarray]:
    """Per-vertex weights (V,) in [0, 1] of every region in ``REGIONS``: sums of the default
    rig's skinning weights over the region's bones (smooth across joints); left/right from the
    template's vertex groups (1 on the side, 0.5 on the symmetry plane)."""
    rig = template.rigs["default"]
    w = sp.csc_matrix(rig.weights)

    def bones(prefixes):
        cols = [i for i, b in enumerate(rig.bone_names) if b.startswith(prefixes)]
        return np.clip(np.asarray(w[:, cols].sum(axis=1)).ravel(), 0.0, 1.0)

    nv = template.n_vertices
    lower = bones(_LOWER)
    arms, legs, torso = bones(_ARM), bones(_LEG), bones(_TORSO)
    left, right = np.zeros(nv), np.zeros(nv)
    left[template.left] = 1.0
    right[template.right] = 1.0
    left[template.mid] = right[template.mid] = 0.5
    head = np.clip(1.0 - arms - legs - torso, 0.0, 1.0)
    out = {"upper_body": 1.0 - lower, "lower_body": lower, "arms": arms, "legs": legs, "torso": torso,
           "head": head, "left": left, "right": right}
    return {k: np.where(v < 1e-4, 0.0, np.where(v > 1 - 1e-4, 1.0, v)) for k, v in out.items()}


class MaskedPoissonBlend:
    """The masked Poisson solve of one mask on one rest mesh, factored once, for many changes.

    Args:
        rest_vertices: (V, 3) the mesh the gradients are taken on (the model's mean body).
        faces: (F, 3) int.
        weights: (V,) mask in [0, 1]; 0 = held fixed, 1 = changed in full.

    ``blend(d)`` maps a change d (V, 3) to the masked change (V, 3), 0.0 exactly where the
    weight is 0. Raises ``ParameterError`` for weights of another shape, outside [0, 1], or all 0.
    """

    def __init__(self, rest_vertices, faces, weights):
        x0 = np.asarray(rest_vertices, dtype=float)
        faces = np.asarray(faces, dtype=np.int64)
        w = np.asarray(weights, dtype=float)
        if w.shape != (len(x0),) or not np.isfinite(w).all() or w.min() < 0 or w.max() > 1:
            raise ParameterError(f"mask: weights of shape {w.shape}, expected ({len(x0)},) values in [0, 1]")
        self.weights = w
        self.free = np.flatnonzero(w > 0)
        if self.free.size == 0:
            raise ParameterError("mask: every weight is 0, expected a region to change")
        # 1. gradient operator G (3F, V) and the area-weighted, masked gradient target
        self.gradient = gradient_operator(x0, faces)
        a, b, c = (x0[faces[:, i]] for i in range(3))
        self.area3 = np.repeat(0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1), 3)
        self.face_weight3 = np.repeat(w[faces].mean(axis=1), 3)
        # 2. normal matrix G^T diag(area) G = the cotangent Laplacian, restricted to the free vertices
        laplacian = cotangent_laplacian(x0, faces)
        self.holds_nothing = self.free.size == len(w)
        sub = laplacian[self.free][:, self.free]
        if self.holds_nothing:  # nothing held: pin one vertex of weight 1 (translation)
            sub = sub + sp.diags(np.r_[1e-8 * laplacian.diagonal().mean(), np.zeros(self.free.size - 1)])
        self.solver = FactorizedSolver(sub)

    def __call__(self, change) -> np.ndarray:
        """The masked change (V, 3) of ``change`` (V, 3)."""
        d = np.asarray(change, dtype=float)
        if self.holds_nothing and np.all(self.weights == 1):
            return d.copy()
        # 3. right-hand side G^T diag(area) (w_f grad d), solved on the free vertices only
        target = (self.gradient @ d) * self.face_weight3[:, None]
        rhs = self.gradient.T @ (self.area3[:, None] * target)
        out = np.zeros_like(d)
        out[self.free] = self.solver.solve(rhs[self.free])
        return out


def masked_poisson_blend(rest_vertices, faces, weights, change) -> np.ndarray:
    """One masked Poisson solve (see the module docstring): the change (V, 3) of ``change``
    (V, 3) confined to ``weights`` (V,) on the rest mesh ``rest_vertices`` (V, 3), ``faces``
    (F, 3). For many changes of one mask, build ``MaskedPoissonBlend`` once."""
    return MaskedPoissonBlend(rest_vertices, faces, weights)(change)
