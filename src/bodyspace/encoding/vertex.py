"""The plain vertex encoding (Rupprecht Equation 1), after rigid Procrustes alignment.

A body is the flattened offset of its aligned vertices from the mean mesh:
``code = (align(x) - mean).ravel()`` (D = 3V), and ``x = mean + code`` back. Alignment is
rigid (rotation and translation, no scale: body size is shape, not pose), by the Kabsch
algorithm, onto the mean mesh; the mean itself comes from generalized Procrustes analysis of
the fitted scans, kept in the template's frame.

Same interface as ``RelativeRotationEncoder``, so the shape space works with either.
"""

from __future__ import annotations

import numpy as np

from bodyspace.encoding.linearize import DecoderLinearization
from bodyspace.encoding.tangent import AffineDecodeTangent
from bodyspace.errors import MeshError, ParameterError
from bodyspace.mesh.alignment import rigid_procrustes
from bodyspace.mesh.geometry import check_mesh
from bodyspace.mesh.operators import deformation_gradients, triangle_frames
from bodyspace.mesh.solver import PoissonSolver, PositionConstraints
from bodyspace.mesh.topology import check_registered_meshes, check_topology
from bodyspace.validation import as_codes

# Generalized Procrustes stops when the mean moves less than this (metres) between rounds.
GPA_TOL = 1e-9
GPA_MAX_ROUNDS = 20


class VertexEncoder:
    """Vertex-position encoding of registered meshes, rigidly aligned to the mean mesh.

    Args:
        template_vertices: (V, 3) the template (rest) mesh, metres.
        faces: (F, 3) int, the shared topology.

    Attributes (after ``fit``):
        mean_vertices_: (V, 3) the generalized-Procrustes mean, aligned to the template.
        n_features_: D = 3V.
    """

    kind = "vertex"
    PARAMS = ()
    RUNTIME_PARAMS = ()
    # decode(mean + z C) = mean_vertices_ + (mean + z C) reshaped: affine, so mapping measures
    # bodies through ``linearize`` without decoding them.
    is_linear = True
    # The vertex encoding has no rotations to wrap: folded triangles are not looked for.
    last_flipped_ = None

    def __init__(self, template_vertices: np.ndarray, faces: np.ndarray):
        check_mesh(template_vertices, faces, name="template")
        self.template_vertices = np.asarray(template_vertices, dtype=float)
        self.faces = np.asarray(faces, dtype=np.int64)
        if self.template_vertices.ndim != 2:
            raise MeshError(f"template: vertices have shape {self.template_vertices.shape}, expected (V, 3)")
        check_topology(self.faces, len(self.template_vertices))
        self.n_vertices = len(self.template_vertices)
        self.n_features_ = 3 * self.n_vertices
        self._poisson = None  # built on the first constrained decode

    # ------------------------------------------------------------------ validation
    def _check_vertices(self, vertices, faces=None, name="vertices") -> np.ndarray:
        return check_registered_meshes(vertices, self.n_vertices, self.faces, faces, name)

    def _check_codes(self, codes) -> np.ndarray:
        return as_codes(codes, self.n_features_, f"vertex encoding of this template (3 x {self.n_vertices} vertices)",
                        error=MeshError)

    def _require_fit(self):
        if not hasattr(self, "mean_vertices_"):
            raise MeshError(f"{type(self).__name__} is not fitted; call fit(scans) first "
                            "(fit(template[None]) makes the template the mean)")

    # ------------------------------------------------------------------ API
    def fit(self, scans: np.ndarray, faces: np.ndarray | None = None) -> "VertexEncoder":
        """Compute the mean mesh of ``scans`` (N, V, 3) by generalized Procrustes analysis."""
        x = self._check_vertices(scans, faces, name="scans")
        mean = self.template_vertices
        for _ in range(GPA_MAX_ROUNDS):
            aligned, _, _ = rigid_procrustes(x, mean)
            new = rigid_procrustes(aligned.mean(axis=0), self.template_vertices)[0]
            moved = np.abs(new - mean).max()
            mean = new
            if moved < GPA_TOL:
                break
        self.mean_vertices_ = mean
        return self

    def encode(self, vertices: np.ndarray, faces: np.ndarray | None = None, *,
               out: np.ndarray | None = None) -> np.ndarray:
        """Codes (N, 3V) of meshes (V, 3) or (N, V, 3): aligned vertices minus the mean.

        ``out``: an optional (N, 3V) float64 or float32 array the codes are written into (and
        returned), e.g. rows of a large code matrix.
        """
        self._require_fit()
        x = self._check_vertices(vertices, faces)
        aligned, _, _ = rigid_procrustes(x, self.mean_vertices_)
        codes = (aligned - self.mean_vertices_).reshape(len(x), -1)
        if out is None:
            return codes
        if out.shape != codes.shape or out.dtype not in (np.float64, np.float32):
            raise ParameterError(f"out: {out.dtype} array of shape {out.shape}, expected a float64 or float32 "
                                 f"array of shape {codes.shape}")
        out[...] = codes
        return out

    # ------------------------------------------------------------------ state
    def to_arrays(self, prefix: str = "encoder_") -> dict[str, np.ndarray]:
        """The fitted state: ``mean_vertices`` (V, 3) float64 metres (the template is the caller's)."""
        self._require_fit()
        return {prefix + "mean_vertices": np.asarray(self.mean_vertices_, dtype=np.float64)}

    @classmethod
    def from_arrays(cls, arrays, prefix: str, template_vertices: np.ndarray, faces: np.ndarray,
                    **params) -> "VertexEncoder":
        """A fitted encoder from ``to_arrays`` output (shape checked against the template)."""
        if params:
            raise ParameterError(f"vertex encoder: unexpected parameters {sorted(params)}; it takes none")
        enc = cls(template_vertices, faces)
        name = prefix + "mean_vertices"
        if name not in arrays:
            raise ParameterError(f"vertex encoder: array '{name}' missing")
        mean = np.asarray(arrays[name], dtype=float)
        if mean.shape != (enc.n_vertices, 3):
            raise ParameterError(f"vertex encoder: '{name}' has shape {mean.shape}, expected ({enc.n_vertices}, 3)")
        enc.mean_vertices_ = mean
        return enc

    def linearize(self, space, k: int | None = None) -> DecoderLinearization:
        """The decoder of ``space`` (a fitted ``ShapeSpace`` over this encoder) on its first ``k``
        coefficients (default all), exactly: ``base = mean_vertices_ + mean_``, ``basis =
        components_[:k]``, each reshaped to vertices (V, 3)."""
        self._require_fit()
        k = space.n_components_ if k is None else min(int(k), space.n_components_)
        base = self.mean_vertices_ + space.mean_.reshape(self.n_vertices, 3)
        return DecoderLinearization.exact(base, space.components_[:k].reshape(k, self.n_vertices, 3))

    def tangent(self, code: np.ndarray) -> AffineDecodeTangent:
        """The decoder at one code (3V,): ``.vertices`` its body, ``.jvp``/``.vjp`` the code
        directions themselves (the decoder is affine), as ``RelativeRotationEncoder.tangent``."""
        self._require_fit()
        c = self._check_codes(code)
        if len(c) != 1:
            raise ParameterError(f"code: {len(c)} codes, expected one (D,) code")
        return AffineDecodeTangent(c[0], self.decode(c)[0])

    def decode(self, codes: np.ndarray, constraints: PositionConstraints | None = None) -> np.ndarray:
        """Meshes (N, V, 3) from codes (N, 3V) or (3V,), in the mean mesh's frame.

        With ``constraints`` the decoded mesh is deformed by the same Poisson step as the
        relative rotation encoding uses: its own deformation gradients are kept as targets while
        the chosen vertices are pulled softly to the given positions.
        """
        self._require_fit()
        c = self._check_codes(codes)
        x = self.mean_vertices_ + c.reshape(len(c), self.n_vertices, 3)
        if constraints is None:
            return x
        if self._poisson is None:
            self._poisson = PoissonSolver(self.template_vertices, self.faces)
            self._rest_frames_inv = np.linalg.inv(triangle_frames(self.template_vertices, self.faces))
        u = deformation_gradients(self._rest_frames_inv, x, self.faces)
        return self._poisson.solve(u, constraints, pinned_positions=x)
