"""Mappings from semantic measurements to shape-space coefficients (Rupprecht §3.2).

``LinearLeafForest`` is the paper's regression forest with affine leaves; ``LinearMapping`` the
single affine map of the related work (its baseline). Both are scikit-learn-style estimators
(``fit(X, Y)``, ``predict(X)``) that store themselves as flat arrays (``to_arrays`` /
``from_arrays``) for the model bundle, never pickle. ``DecoderLinearization`` is the affine
stand-in for the RRE decoder that exact refinement of RRE models steps with (encoding/linearize.py).
``MeasurementMapping`` (bundle.py) holds the fitted ones a ``BodyModel`` saves in its file.
"""

from bodyspace.encoding.linearize import DecoderLinearization
from bodyspace.mapping.forest import LinearLeafForest, grow_tree
from bodyspace.mapping.linear import LinearMapping, fit_affine

__all__ = ["DecoderLinearization", "LinearLeafForest", "LinearMapping", "fit_affine", "grow_tree"]
