"""Mappings from semantic measurements to shape-space coefficients (Rupprecht et al., Sec. 3.2).

``LinearLeafForest`` is the paper's regression forest with affine leaves; ``LinearMapping`` the
single affine map of the related work (its baseline). Both are scikit-learn-style estimators
(``fit(X, Y)``, ``predict(X)``) that store themselves as flat arrays (``to_arrays`` /
``from_arrays``) for the model bundle, never pickle.
"""

from bodyspace.mapping.forest import LinearLeafForest, grow_tree
from bodyspace.mapping.linear import LinearMapping, fit_affine

__all__ = ["LinearLeafForest", "LinearMapping", "fit_affine", "grow_tree"]
