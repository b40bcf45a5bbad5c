"""Shape spaces over encoded bodies: PCA (``pca``), its solvers for large code matrices
(``solvers``) and measures of how intact a body is (``compare``)."""

from bodyspace.shape.compare import (
                                     edge_lengths,
                                     interpolate,
                                     interpolation_distortion,
                                     mean_relative_edge_change,
                                     relative_volume_change,
)
from bodyspace.shape.pca import ShapeSpace

__all__ = ["ShapeSpace", "edge_lengths", "interpolate", "interpolation_distortion",
           "mean_relative_edge_change", "relative_volume_change"]
