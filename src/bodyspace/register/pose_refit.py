"""The registered body brought back to standing for its measurements: the stage after the NICP.

A registered scan is measured standing (the ISO 20685-1 definitions are of the rest pose), so
the posed fit must be split into a pose and a rest body. ``rig.unpose`` estimates that split
from the registered mesh alone, and the pose fit's own rotations are another; on the test scans
neither is the true one (measurements within ISO 20685-1: 145 and 141 of 186 on six fits,
against 164 with the true pose; docs/registration.md). Two things make the split:

1. ``refit_pose``: the rigged shape model (pose, shape coefficients, scale, translation) fitted
   once more to the *scan*, starting from the pose fit's result, with the shape prior
   ``REFIT_SHAPE_PRIOR``, half the pose fit's ``SHAPE_PRIOR``. The pose fit's prior keeps
   its shape near the population's mean while the limbs are still being placed; at the end it
   held an edge-of-population body's last components (the limb girths, the hip's bulge) back,
   and the pose made up for them (a hip flexed 2-5°, the clavicles lifted 3-4° on a body standing
   in the rest pose; the unposed stature 5 mm tall). The same start with a prior a tenth as
   heavy put the model's rest body within ISO 20685-1 on 29-31 of 31 measurements on the
   rest-pose scan.
2. ``standing_body``: the rest body of that model (its pose undone exactly, since the model is
   posed by the rig) plus the registered mesh's own offset along the normal from the refitted
   model's posed surface, carried to the same vertex of the rest body. The model holds the
   skeleton's split of pose and shape; the scan's surface, with whatever the model cannot
   express (a real body's detail, another skinning's bulges), is kept as normal offsets, as
   Hasler §3 keeps detail. Measured alone the model's rest body loses what it cannot express:
   on the hands-on-hips scan 11-13 of 31 within ISO, against 18 with the offsets.

Vertex to vertex instead of to the scan (the registered mesh's vertices as targets, exact
correspondence): measured and not kept. The registered vertices carry the pose fit's tangential
placement (the NICP keeps it), so a model fitted to them returns the pose fit's split (ISO 21 of
31 on the rest-pose scan before and after; on the true posed body the same fit recovers the pose
within 2.4° and all 31).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from bodyspace.data.template import Template
from bodyspace.mesh.geometry import vertex_normals
from bodyspace.register.model_fit import SCALE_PRIOR, ShapeBasis
from bodyspace.register.pose_fit import PoseState, fit_pose, posed_vertices

__all__ = ["refit_pose", "standing_body", "REFIT_SHAPE_PRIOR", "REFIT_ITERATIONS", "REFIT_GATE", "REFIT_POSE_PRIOR"]

# Shape prior of the refit (metres of RMS residual per standard deviation of a component): half
# model_fit.SHAPE_PRIOR. Measurements within ISO 20685-1 of the standing body at 0.0001, 0.00005,
# 0.00002: 155, 159, 159 of 186 on six fits of LBS-posed scans (``rig.unpose``: 145), 109, 104, 99
# of 155 on five scans posed with smoothed weights or the volume correction (``rig.unpose``:
# 103). The lighter the prior, the more of another skinning the shape takes up; the heavier
# one is kept for real bodies, whose skinning is nobody's LBS.
REFIT_SHAPE_PRIOR = 0.0001
# Gauss-Newton iterations (12: 162 of 186 at twice the time), the correspondence gate (metres,
# held: the pose fit has placed the body; starting at 2 cm: 154) and the pose prior (the pose
# fit's last rounds').
REFIT_ITERATIONS = 6
REFIT_GATE = 0.01
REFIT_POSE_PRIOR = 0.001


def refit_pose(points: np.ndarray, normals: np.ndarray, template: Template, state: PoseState, basis: ShapeBasis, *,
               landmarks=None, scan_tree: cKDTree | None = None, iterations: int = REFIT_ITERATIONS,
               shape_prior: float = REFIT_SHAPE_PRIOR, rng=0) -> PoseState:
    """The pose fit's state refitted to the scan with a light shape prior (module docstring, 1).

    points (P, 3), normals (P, 3): the scan in the fit's frame (metres, +Y up); state: the pose
    fit's ``PoseState`` (rotations (B, 3, 3), scale, translation, ``coefficients`` (K,) of
    ``basis``); landmarks: as ``fit_pose``'s. Returns the refitted ``PoseState`` (its ``rest``
    is ``basis.body(coefficients)``, unscaled).
    """
    coef = state.coefficients if state.coefficients is not None else np.zeros(len(basis.components))
    refit, _ = fit_pose(points, normals, template, state, iterations=iterations, landmarks=landmarks,
                        scan_tree=scan_tree, start_distance=REFIT_GATE, end_distance=REFIT_GATE, fit_scale=True,
                        pose_prior=REFIT_POSE_PRIOR, shape=(basis, coef, shape_prior, SCALE_PRIOR), rng=rng)
    return refit


def standing_body(vertices: np.ndarray, faces: np.ndarray, template: Template, state: PoseState) -> np.ndarray:
    """The registered body standing (module docstring, 2): (V, 3) metres, +Y up, lowest vertex at y = 0.

    vertices: (V, 3) the registered mesh in the frame of ``state`` (``Registration.internal``);
    faces: (F, 3); state: the model posed to it (``refit_pose``).
    """
    rig = template.rigs["default"]
    posed, _, _ = posed_vertices(rig, state)
    offset = ((np.asarray(vertices, dtype=float) - posed) * vertex_normals(posed, faces)).sum(axis=1)   # (V,)
    rest = state.scale * state.rest
    rest = rest + offset[:, None] * vertex_normals(rest, faces)
    rest[:, 1] -= rest[:, 1].min()
    return rest
