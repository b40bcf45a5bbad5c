"""A user's BodyModel as the registration's shape space (``bodyspace register --model MODEL``).

The model fit (``model_fit.fit_shape``) needs a shape space in vertex space: a mean rest body
(V, 3), unit directions (K, V, 3) and their standard deviations (K,) (``ShapeBasis``). A
``BodyModel`` gives one through its encoder's linearization of its decoder
(``encoder.linearize(space, k)``: exact for the vertex encoding, the tangent at the mean for the
relative rotation encoding): base (V, 3) and ``basis[k]`` (V, 3), the displacement per unit
coefficient k, whose variance is ``space.explained_variance_[k]``; so direction k is
``basis[k] / |basis[k]|`` with standard deviation ``sqrt(explained_variance_[k]) · |basis[k]|``.

The skeleton pose fit moves the template's own rig (joint regressors and skin weights of the
template's 13,380 vertices), so the model must have the template's topology: a model of
another topology is refused with what it has and what would work (``check_model_topology``).
"""

from __future__ import annotations

import numpy as np

from bodyspace.data.template import Template
from bodyspace.errors import RegistrationError
from bodyspace.register.model_fit import BASIS_COMPONENTS, ShapeBasis

__all__ = ["basis_from_model", "check_model_topology"]


def check_model_topology(model, template: Template, where: str = "--model") -> None:
    """Raise ``RegistrationError`` unless ``model`` (a ``BodyModel``) has ``template``'s topology."""
    v = np.asarray(model.template_vertices)
    f = np.asarray(model.faces)
    if len(v) == template.n_vertices and f.shape == template.faces.shape and np.array_equal(f, template.faces):
        return
    same_count = len(v) == template.n_vertices
    raise RegistrationError(
        f"{where}: the model's template has {len(v)} vertices and {len(f)} faces"
        f"{' in another face order' if same_count and f.shape == template.faces.shape else ''}; registration "
        f"fits the pose with the rig and landmarks of bodyspace's template ({template.n_vertices} vertices, "
        f"{len(template.faces)} faces), which this topology has no copy of. Give a model built from meshes of "
        "the template's topology (bodyspace import, population or register), or register without --model and "
        "carry the result to your topology (bodyspace landmarks MESH)")


def basis_from_model(model, n_components: int = BASIS_COMPONENTS, where: str = "--model") -> ShapeBasis:
    """The shape space (``ShapeBasis``) of a ``BodyModel``'s first ``n_components`` components
    (module docstring). Mean (V, 3) metres, components (K, V, 3) unit norm, sigma (K,) metres."""
    space = model.space
    k = min(int(n_components), int(space.n_components_))
    if k < 1:
        raise RegistrationError(f"{where}: the model's shape space has no components; expected a built model "
                                "(bodyspace build)")
    lin = model.encoder.linearize(space, k)
    basis = np.asarray(lin.basis_, dtype=float)[:k]
    norms = np.linalg.norm(basis.reshape(k, -1), axis=1)
    keep = norms > 1e-12
    if not keep.any():
        raise RegistrationError(f"{where}: the model's components move no vertex; expected a shape space with "
                                "variation (bodyspace build on more than one body)")
    sigma = np.sqrt(np.maximum(np.asarray(space.explained_variance_[:k], dtype=float), 0.0)) * norms
    keep &= sigma > 1e-9                  # a component of no variance would only add a zero column
    comps = basis[keep] / norms[keep][:, None, None]
    return ShapeBasis(np.asarray(lin.base_, dtype=float), comps, sigma[keep], name="model")
