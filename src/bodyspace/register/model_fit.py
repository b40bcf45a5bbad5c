"""Model fit: the shape coefficients of a body model fitted to the scan in vertex space.

Stage 4 of the registration. The body is ``x = s · LBS(mean + Σ_k c_k B_k, FK(R)) + t`` with
the pose R, scale s from the pose fit held: with the rotations fixed, posing is affine in the
rest vertices (the joints are regressed linearly from them, FK and LBS are linear in the joints
and the vertices), so ``x = s · (P_0 + Σ_k c_k P_k) + t`` with ``P_k`` the posed directions,
exactly, and the fit is a linear least-squares problem in (c, t): point-to-plane residuals
both ways (as the pose fit's), a prior ``c_k / σ_k`` (the directions' standard deviations).

The default shape space (``phenotype_basis``) is the principal components of bodies drawn
uniformly over MakeHuman's whole phenotype range (not the synthetic population's): the model
the template's CC0 assets define. A user's ``BodyModel`` of the vertex encoding gives its own
(``basis_from_model``).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from scipy.spatial import cKDTree

from bodyspace.data.template import Template
from bodyspace.mesh.geometry import vertex_normals
from bodyspace.mesh.solver import single_threaded_blas
from bodyspace.register.correspondences import closest_pairs
from bodyspace.register.pose_fit import MIN_COS, PoseState, sample_vertices
from bodyspace.rig.posing import pose_bodies
from bodyspace.synth.phenotype import PARAMETERS, PhenotypeModel, years_to_age

__all__ = ["ShapeBasis", "phenotype_basis", "fit_shape", "reach_shape", "BASIS_COMPONENTS", "PHENOTYPE_COMPONENTS",
           "REACH_PRIOR", "REACH_ITERATIONS", "REACH_GATE"]

# Components of the default (phenotype) shape space and the bodies its PCA is taken over. 24
# components hold 99.9 % of the variance but not the body's measurements: the least-squares projection of
# three test scans' true bodies onto them kept only 22, 25, 22 of 31 measurements within ISO
# 20685-1 (RMS 0.9-1.6 mm, calves and thighs 2-3 tolerances off), onto 40 and 60 all 31 (RMS
# 0.2-0.3 and 0.13-0.18 mm). Registered with 60: ISO 137 -> 145 of 186 on the good fits,
# correspondence and surface no worse on any of them (docs/registration.md, fourth round).
PHENOTYPE_COMPONENTS = 60
# Components a user's model (``user_model.basis_from_model``) contributes at most: not measured
# beyond 24 (a small database's last components may be noise).
BASIS_COMPONENTS = 24
BASIS_SAMPLES = 300
# Weight of the prior c_k / σ_k against the RMS residual (metres).
SHAPE_PRIOR = 0.0002
# Weight of the prior on the global scale's departure from 1 (metres per unit of scale). The
# shape space spans statures of 1.2-2.4 m, so the scale is left for what it cannot explain:
# held at the alignment's height ratio, a 2.17 m body was a 1.74 m mean body scaled 1.22 times,
# its proportions those of the mean (legs 24 mm, feet 29 mm off after every fit).
SCALE_PRIOR = 0.02
# The last model fit (``reach_shape``): after the pose rounds, the shape refitted with the pose
# held under a prior a quarter of ``SHAPE_PRIOR``'s weight, for ``REACH_ITERATIONS`` iterations
# with pairs gated at ``REACH_GATE`` (metres). Large, low breasts (cup size 0.87-0.93, firmness
# 0.03-0.04) lie 10-13σ out along a few components: at SHAPE_PRIOR the prior outweighed the 4 %
# of the scan on them and the fit stopped with the breast vertices 87-123 mm from the truth's,
# though the shape space holds those bodies to 2 mm; the ICP's pairs then reach the breast's
# lower part a few centimetres at a time (3 iterations: 55-70 mm; 6: 2-4 mm).
# docs/registration.md, "Tenth round".
REACH_PRIOR = 0.00005
REACH_ITERATIONS = 8
REACH_GATE = 0.03


@dataclass(frozen=True)
class ShapeBasis:
    """mean: (V, 3) rest body; components: (K, V, 3) unit-norm directions; sigma: (K,) SDs."""

    mean: np.ndarray
    components: np.ndarray
    sigma: np.ndarray
    name: str = "phenotype"

    def body(self, coefficients: np.ndarray) -> np.ndarray:
        """The rest body (V, 3) of coefficients (K,)."""
        return self.mean + np.tensordot(coefficients, self.components, axes=1)


_BASES: dict = {}


def _phenotype_basis(template: Template, n_components: int, n_samples: int) -> ShapeBasis:
    rng = np.random.default_rng(20261202)
    p = rng.random((n_samples, len(PARAMETERS)))
    race = rng.dirichlet([0.5, 0.5, 0.5], n_samples)
    p[:, [PARAMETERS.index("african"), PARAMETERS.index("asian"), PARAMETERS.index("caucasian")]] = race
    # Adults: ages 18-90 years (MakeHuman's age 0 is a baby).
    p[:, PARAMETERS.index("age")] = years_to_age(rng.uniform(18.0, 90.0, n_samples))
    bodies = PhenotypeModel(template).vertices(p).reshape(n_samples, -1)
    mean = bodies.mean(axis=0)
    centred = bodies - mean
    # Through the (N, N) Gram matrix: N is far below 3V.
    evals, evecs = np.linalg.eigh(centred @ centred.T)
    k = int(n_components)
    evals, evecs = evals[::-1][:k], evecs[:, ::-1][:, :k]
    comps = (evecs.T @ centred) / np.sqrt(np.maximum(evals, 1e-300))[:, None]
    V = template.n_vertices
    return ShapeBasis(mean.reshape(V, 3), comps.reshape(k, V, 3), np.sqrt(np.maximum(evals, 0) / (n_samples - 1)))


def phenotype_basis(template: Template, n_components: int = PHENOTYPE_COMPONENTS,
                    n_samples: int = BASIS_SAMPLES) -> ShapeBasis:
    """PCA of ``n_samples`` adults with phenotypes uniform over [0, 1] (race mix: Dirichlet,
    age 18-90 years),
    ``n_components`` kept (``PHENOTYPE_COMPONENTS`` says why 60, not the 24 that hold 99.9 % of the
    variance). Fixed seed; cached per template."""
    key = (id(template), int(n_components), int(n_samples))
    if key not in _BASES:
        _BASES.clear()            # one template at a time: a basis is PHENOTYPE_COMPONENTS bodies of memory
        _BASES[key] = _phenotype_basis(template, int(n_components), int(n_samples))
    return _BASES[key]


def fit_shape(points: np.ndarray, normals: np.ndarray, template: Template, state: PoseState, basis: ShapeBasis,
              *, iterations: int = 3, max_distance: float = 0.05, scan_tree: cKDTree | None = None,
              coefficients: np.ndarray | None = None, fit_scale: bool = True, prior: float = SHAPE_PRIOR,
              rng=0) -> tuple[PoseState, np.ndarray]:
    """Fit the shape coefficients (and translation, and scale) with the pose held (module docstring).

    points (P, 3), normals (P, 3) (any sign): the scan in the template's frame. state: the pose
    fit's result (its ``rest`` is replaced). fit_scale: also fit the global scale s (as
    ``a = s`` and ``b = s c``, so the problem stays linear), pulled towards 1 by
    ``SCALE_PRIOR``. prior: the weight of the prior c_k / σ_k (``SHAPE_PRIOR``). Returns the
    state with the fitted rest body (and scale) and the coefficients (K,).
    """
    rig = template.rigs["default"]
    faces = template.faces
    K = len(basis.components)
    rng = np.random.default_rng(rng)
    tree = scan_tree if scan_tree is not None else cKDTree(points)
    # Posed directions: posing is affine in the rest body with the rotations held.
    stack = np.concatenate([basis.mean[None], basis.mean[None] + basis.components])
    posed = pose_bodies(stack, rig, state.rotations)
    P0, Pk = posed[0], posed[1:] - posed[0]
    tsample = sample_vertices(basis.mean, faces, 4000, rng)
    ssample = rng.choice(len(points), size=min(6000, len(points)), replace=False)
    c = np.zeros(K) if coefficients is None else np.asarray(coefficients, dtype=float).copy()
    t = state.translation.copy()
    s = state.scale
    with single_threaded_blas():
        for _ in range(int(iterations)):
            y = P0 + np.tensordot(c, Pk, axes=1)
            x = s * y + t
            xn = vertex_normals(x, faces)
            fwd = closest_pairs(x[tsample], xn[tsample], tree, normals, max_distance, MIN_COS, oriented=False)
            bwd = closest_pairs(points[ssample], normals[ssample], cKDTree(x), xn, max_distance, MIN_COS,
                                oriented=False)
            rv = np.concatenate([tsample[fwd.query], bwd.match])
            rp = points[np.concatenate([fwd.match, ssample[bwd.query]])]
            nrm = np.concatenate([normals[fwd.match], xn[bwd.match]])
            w = np.concatenate([np.full(len(fwd.query), 1 / np.sqrt(max(len(fwd.query), 1))),
                                np.full(len(bwd.query), 1 / np.sqrt(max(len(bwd.query), 1)))])
            if fit_scale:
                # r = n · (a P0 + Pk b + t - p): linear in (b = s c, t, a = s); the prior on c
                # taken at this iteration's scale.
                Jc = np.einsum("kvd,vd->vk", Pk[:, rv], nrm)
                Js = (P0[rv] * nrm).sum(1, keepdims=True)
                Jm = w[:, None] * np.concatenate([Jc, nrm, Js], axis=1)
                rhs = Jm.T @ (w * (rp * nrm).sum(1))
                H = Jm.T @ Jm
                H[:K, :K] += np.diag((prior / (s * basis.sigma)) ** 2)
                H[-1, -1] += SCALE_PRIOR ** 2
                rhs[-1] += SCALE_PRIOR ** 2
                sol = np.linalg.solve(H + 1e-12 * np.eye(K + 4), rhs)
                s = float(sol[-1])
                c, t = sol[:K] / s, sol[K:K + 3]
            else:
                # r = n · (s (P0 + Pk c) + t - p): linear in (c, t)
                Jc = s * np.einsum("kvd,vd->vk", Pk[:, rv], nrm)
                Jm = w[:, None] * np.concatenate([Jc, nrm], axis=1)
                b = -w * (((s * P0[rv] - rp) * nrm).sum(1))       # (c, t) are solved for whole
                H = Jm.T @ Jm
                H[:K, :K] += np.diag((prior / basis.sigma) ** 2)
                sol = np.linalg.solve(H + 1e-12 * np.eye(K + 3), Jm.T @ b)
                c, t = sol[:K], sol[K:]
    return replace(state, rest=basis.body(c), translation=t, scale=s, coefficients=c), c


def reach_shape(points: np.ndarray, normals: np.ndarray, template: Template, state: PoseState, basis: ShapeBasis,
                *, scan_tree: cKDTree | None = None, rng=0) -> tuple[PoseState, np.ndarray]:
    """The last model fit: the shape refitted from the pose fit's state with the pose held, a
    light prior (``REACH_PRIOR``) and narrow gates (``REACH_GATE``), so that a body far out along
    a few components (large, low breasts) reaches its scan points. points (P, 3), normals (P, 3):
    the scan (fit frame, metres); state: the pose fit's result, its ``coefficients`` (K,) the
    start. Returns the state and the coefficients (K,), as ``fit_shape``."""
    return fit_shape(points, normals, template, state, basis, iterations=REACH_ITERATIONS, max_distance=REACH_GATE,
                     scan_tree=scan_tree, coefficients=state.coefficients, prior=REACH_PRIOR, rng=rng)
