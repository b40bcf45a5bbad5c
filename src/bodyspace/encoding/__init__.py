"""Encodings of registered meshes as flat feature vectors (codes), and back.

- ``RelativeRotationEncoder`` (``rre``): Hasler et al. (2009), Sec. 3: per-triangle stretch and
  relative rotations to the edge neighbours, relative to the mean model; decoded by two sparse
  solves (rotations, then Poisson).
- ``VertexEncoder`` (``vertex``): vertex positions after rigid Procrustes alignment
  (Rupprecht et al., Eq. 1).

Shared parts: ``deformation`` (per-triangle deformation gradients and their closed-form polar
decomposition) and ``rotations`` (quaternions, rotation vectors, polar factors, batched).

Both: ``Encoder(template_vertices, faces).fit(scans)``, ``encode(vertices) -> (N, D)``,
``decode(codes, constraints=None) -> (N, V, 3)``, ``n_features_``, ``mean_vertices_``.
"""

from bodyspace.encoding.rre import RelativeRotationEncoder
from bodyspace.encoding.vertex import VertexEncoder
from bodyspace.mesh.alignment import rigid_procrustes
from bodyspace.mesh.solver import PositionConstraints

__all__ = ["RelativeRotationEncoder", "VertexEncoder", "PositionConstraints", "rigid_procrustes"]
