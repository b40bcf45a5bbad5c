"""How intact a body is: edge-length and volume changes, and interpolation between bodies.

Hasler Figure 5: halfway between two poses of one subject, the relative rotation
encoding gives an intact body while vertex interpolation collapses the limbs. A pose change
of one subject keeps edge lengths and volume nearly constant, so the halfway mesh's change
in both, against the endpoints' average, measures the damage.
"""

from __future__ import annotations

import numpy as np

from bodyspace.mesh.geometry import boundary_loops, capped_volume
from bodyspace.mesh.topology import edges as mesh_edges


def edge_lengths(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Lengths (..., E) of the unique edges (``topology.edges`` order) of (..., V, 3)."""
    e = mesh_edges(faces)
    v = np.asarray(vertices, dtype=float)
    return np.linalg.norm(v[..., e[:, 0], :] - v[..., e[:, 1], :], axis=-1)


def mean_relative_edge_change(reference: np.ndarray, vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Mean over edges of ``|l - l_ref| / l_ref``, (...,): 0 for an isometric deformation."""
    ref = edge_lengths(reference, faces)
    return np.mean(np.abs(edge_lengths(vertices, faces) - ref) / ref, axis=-1)


def relative_volume_change(reference: np.ndarray, vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """``(vol - vol_ref) / vol_ref`` (...,) of the capped volumes (holes closed by fans)."""
    loops = boundary_loops(faces)
    ref = capped_volume(reference, faces, loops)
    return (capped_volume(vertices, faces, loops) - ref) / ref


def interpolate(encoder, a: np.ndarray, b: np.ndarray, t: float | np.ndarray = 0.5) -> np.ndarray:
    """Bodies (T, V, 3) at fractions ``t`` between meshes a and b (V, 3), linear in code space."""
    codes = encoder.encode(np.stack([a, b]))
    t = np.atleast_1d(np.asarray(t, dtype=float))[:, None]
    return encoder.decode((1 - t) * codes[0] + t * codes[1])


def interpolation_distortion(encoder, a: np.ndarray, b: np.ndarray, t: float = 0.5) -> dict:
    """Interpolate a and b (V, 3) with ``encoder`` and measure the damage of the result.

    Returns a dict: ``mesh`` (V, 3), ``edge_change`` (mean relative edge-length change) and
    ``volume_change`` (relative), both against the linear mix of the endpoints' edge lengths
    and volumes (for two poses of one subject, the endpoints' own values).
    """
    faces = encoder.faces
    mid = interpolate(encoder, a, b, t)[0]
    la, lb = edge_lengths(a, faces), edge_lengths(b, faces)
    ref_len = (1 - t) * la + t * lb
    loops = boundary_loops(faces)
    va, vb = capped_volume(a, faces, loops), capped_volume(b, faces, loops)
    ref_vol = (1 - t) * va + t * vb
    return {
        "mesh": mid,
        "edge_change": float(np.mean(np.abs(edge_lengths(mid, faces) - ref_len) / ref_len)),
        "volume_change": float((capped_volume(mid, faces, loops) - ref_vol) / ref_vol),
    }
