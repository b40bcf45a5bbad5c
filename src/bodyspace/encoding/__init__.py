"""Encodings of registered meshes as flat feature vectors (codes), and back.

- ``RelativeRotationEncoder`` (``rre``): Hasler §3: per-triangle stretch and
  relative rotations to the edge neighbours, relative to the mean model; decoded by two sparse
  solves (rotations, then Poisson).
- ``VertexEncoder`` (``vertex``): vertex positions after rigid Procrustes alignment
  (Rupprecht Equation 1).

Shared parts: ``deformation`` (per-triangle deformation gradients and their closed-form polar
decomposition), ``rotations`` (quaternions, rotation vectors, polar factors, batched) and
``tangent`` (exact derivatives of a decode).

Both: ``Encoder(template_vertices, faces).fit(scans)``, ``encode(vertices) -> (N, D)``,
``decode(codes, constraints=None) -> (N, V, 3)``, ``n_features_``, ``mean_vertices_``;
``to_arrays(prefix)`` / ``from_arrays(arrays, prefix, template_vertices, faces, **params)``
(their state; ``PARAMS`` names the constructor keywords a file keeps); ``linearize(space, k)``
(a ``DecoderLinearization``: exact for the vertex encoding, the tangent at the mean for RRE);
``tangent(code)`` (the decoder at one code with its exact Jacobian: ``jvp``/``vjp``,
``encoding.tangent``);
``is_linear`` (decoding is affine, so measuring needs no decode); ``last_flipped_`` (folded
triangles per mesh of the last ``encode``, or None when not looked for); ``kind``, the name
``ENCODERS`` knows it by. Nothing above this package asks which encoder it has.
"""

from bodyspace.encoding.linearize import DecoderLinearization
from bodyspace.encoding.rre import RelativeRotationEncoder
from bodyspace.encoding.vertex import VertexEncoder
from bodyspace.mesh.alignment import rigid_procrustes
from bodyspace.mesh.solver import PositionConstraints

# Encoders by the name a model file and the CLI use (``kind``).
ENCODERS = {cls.kind: cls for cls in (RelativeRotationEncoder, VertexEncoder)}

__all__ = ["ENCODERS", "DecoderLinearization", "RelativeRotationEncoder", "VertexEncoder", "PositionConstraints",
           "rigid_procrustes"]
