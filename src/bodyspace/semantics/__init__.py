"""Semantic control of a body model (Hasler §4, Hasler §4.1, Hasler §5.1), on arrays.

- ``regressors``: label = f(body): simple linear (Hasler Equation 10), filtered linear (PCA, rejection in
  ascending order of contribution, cross-validated), non-linear (RBF kernel ridge / SVR), all with
  ``predict`` and ``gradient`` (the morphing direction).
- ``morph``: minimum-norm multi-constraint steps (Hasler Equation 11), iterated walks for non-linear
  regressors, directions from pairwise comparisons (Hasler §5.1).
- ``basis``: the semantic model basis (Hasler §4.1): Gram-Schmidt of the semantic directions + PCA of
  the rest.
- ``evaluation``: Hasler Table 1 (cross-validated RMSE) and Hasler Table 2 (angles between morphing directions).
- ``labels``: which labels a database gives (measured on rest scans, subject columns, lengths).
- ``masks``: body regions and the masked Poisson solve of a masked morph (Hasler §5.1).
- ``closed_loop``: the pure closed loop (Hasler Equation 11, then Gauss-Newton on measured values).
- ``model``: ``SemanticModel``, the estimator that holds the regressors and calls these; it is
  stored inside the BodyModel file (import it from ``bodyspace.semantics.model``).
"""

from bodyspace.semantics.basis import SemanticBasis, gram_schmidt
from bodyspace.semantics.closed_loop import LoopResult, closed_loop
from bodyspace.semantics.evaluation import (
                                            RegressionTable,
                                            cross_validated_rmse,
                                            default_regressors,
                                            direction_angles,
                                            format_angle_table,
                                            format_rmse_table,
)
from bodyspace.semantics.masks import (
                                            REGIONS,
                                            MaskedPoissonBlend,
                                            masked_poisson_blend,
                                            region_weights_from_template,
)
from bodyspace.semantics.morph import (
                                            ComparisonRegressor,
                                            comparison_direction,
                                            morph,
                                            morph_directions,
)
from bodyspace.semantics.regressors import (
                                            FilteredLinearRegressor,
                                            KernelRegressor,
                                            SimpleLinearRegressor,
                                            kfold_indices,
)

__all__ = [
    "SimpleLinearRegressor", "FilteredLinearRegressor", "KernelRegressor", "ComparisonRegressor", "kfold_indices",
    "morph_directions", "morph", "comparison_direction",
    "SemanticBasis", "gram_schmidt",
    "RegressionTable", "cross_validated_rmse", "default_regressors", "direction_angles",
    "format_rmse_table", "format_angle_table",
    "closed_loop", "LoopResult", "MaskedPoissonBlend", "masked_poisson_blend", "region_weights_from_template",
    "REGIONS",
]
