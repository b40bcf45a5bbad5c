"""Shape spaces over encoded bodies: PCA (``pca``), its solvers for large code matrices
(``solvers``), coefficients fitted to a mesh in vertex space through the decoder
(``vertex_fit``) and measures of how intact a body is (``compare``)."""

from bodyspace.shape.compare import (
                                     edge_lengths,
                                     interpolate,
                                     interpolation_distortion,
                                     mean_relative_edge_change,
                                     relative_volume_change,
)
from bodyspace.shape.pca import BASES, PROJECTIONS, ShapeSpace
from bodyspace.shape.vertex_fit import VertexFit, fit_coefficients

__all__ = ["BASES", "PROJECTIONS", "ShapeSpace", "VertexFit", "fit_coefficients", "edge_lengths", "interpolate",
           "interpolation_distortion", "mean_relative_edge_change", "relative_volume_change"]
