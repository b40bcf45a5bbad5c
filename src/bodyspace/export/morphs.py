"""A model's semantic directions as glTF morph targets ("stature +10 cm", "mass +10 kg", ...).

Beyond the papers: Hasler §5 morphs a body along a label's regressor gradient (Hasler Equation 11);
here each such change becomes a shape key an artist drags in Blender or a game engine, with the
same meaning as ``bodyspace morph --set stature=+10cm``.

Two ways to make the displacement of one change ``delta`` of variable ``name`` on a body ``x0``:

- ``"closed_loop"`` (default): the true morph, ``body_model.morph(x0, {name: +delta})`` (the
  Hasler Equation 11 step, then decode, measure, correct; lengths of the measurement set refined
  to 1 mm), minus ``x0``. At weight 1 the shape key *is* the morph, for vertex and RRE models
  alike; at other weights it is the straight line through it, which a vertex model's morph
  nearly is and an RRE model's is not (docs/export.md has the measured errors).
- ``"gradient"``: the one linear step ``dc = S g delta / (g' S g)`` (``g`` the regressor's
  gradient at the body's coefficients, ``S`` the PCA variances: Hasler Equation 11 with one
  constraint) through the model's reconstruct: ``reconstruct(c0 + dc) - reconstruct(c0)``,
  without the measuring loop. Cheaper (one decode), off by what the regressor mispredicts.

The body model is passed in (a ``bodyspace.model.BodyModel`` with semantics: it sits above this
layer and is only called, never imported).
"""

from __future__ import annotations

from typing import Mapping

import numpy as np

from bodyspace.errors import ParameterError
from bodyspace.export.gltf import MorphTarget
from bodyspace.units import ALIASES, Target, UnitError, kind_of, parse_quantity

__all__ = ["DEFAULT_CHANGES", "default_change", "morph_label", "parse_morph_specs", "semantic_morph_targets"]

METHODS = ("closed_loop", "gradient")
# The change a morph target makes when only its name is given (SI units).
DEFAULT_CHANGES = {"stature": 0.10, "height": 0.10, "mass": 10.0, "age": 10.0, "body_fat": 5.0, "muscle": 0.25,
                   "sex": 0.5, "bmi": 2.0}
_DEFAULT_LENGTH_CHANGE = 0.05  # girths and other lengths: +5 cm
_SI_UNIT = {"length": "m", "mass": "kg", "age": "years", "percent": "%", "bmi": "kg/m2", "volume": "m3",
            "area": "m2", "ratio": "1", "sex": "1 (1 = male)"}


def default_change(name: str) -> float:
    """The change (SI) of a morph target asked by name only: stature +10 cm, other lengths +5 cm,
    mass +10 kg, age +10 years, body_fat +5 %, muscle +0.25, sex +0.5 (toward male)."""
    name = ALIASES.get(name, name)
    if name in DEFAULT_CHANGES:
        return DEFAULT_CHANGES[name]
    return _DEFAULT_LENGTH_CHANGE if kind_of(name) == "length" else 0.1


def morph_label(name: str, change: float) -> str:
    """The shape key's name: ``"stature +10 cm"``, ``"mass -5 kg"``, ``"muscle +0.25"``."""
    kind = kind_of(name)
    if kind == "length":
        return f"{name} {change * 100:+.3g} cm"
    unit = {"mass": " kg", "age": " years", "percent": " %", "bmi": " kg/m2"}.get(kind, "")
    return f"{name} {change:+.3g}{unit}"


def parse_morph_specs(text: str, flag: str = "--morphs") -> dict[str, float]:
    """``"stature,mass=+5kg,waist_girth=-3cm"`` -> {name: change (SI)}; a bare name takes
    ``default_change``. Names are checked against the model by ``semantic_morph_targets``."""
    out: dict[str, float] = {}
    for item in str(text).split(","):
        item = item.strip()
        if not item:
            raise UnitError(f"{flag} {text!r}: an empty name; expected NAME[=CHANGE] separated by commas, e.g. "
                            "stature,mass=+5kg")
        name, sep, value = item.partition("=")
        name = ALIASES.get(name.strip(), name.strip())
        if sep:
            v = value.strip()
            if not v or v[0] not in "+-":
                raise UnitError(f"{flag} {item!r}: a morph target is a change; expected a signed amount with its "
                                f"unit, e.g. {name}=+5cm or {name}=-2kg")
            change = parse_quantity(name, v)
        else:
            change = default_change(name)
        if change == 0 or not np.isfinite(change):
            raise UnitError(f"{flag} {item!r}: a change of {change}; expected a non-zero finite change")
        if name in out:
            raise UnitError(f"{flag} {name}: asked twice; give each name once")
        out[name] = float(change)
    return out


def _gradient_step(semantics, c0: np.ndarray, name: str, change: float) -> np.ndarray:
    """Hasler Equation 11 with the one constraint ``g . dc = change``, minimum norm in the
    variance metric: ``dc = S g change / (g' S g)``."""
    g = np.asarray(semantics.regressor(name).gradient(c0), dtype=float)
    s = np.asarray(semantics.variances, dtype=float)
    denom = float(g @ (s * g))
    if not denom > 0:
        raise ParameterError(f"morph target {name!r}: the model's regressor for {name} does not depend on the shape "
                             "coefficients; expected a variable the model can change")
    return s * g * (change / denom)


def semantic_morph_targets(body_model, vertices: np.ndarray, changes: Mapping[str, float],
                           method: str = "closed_loop") -> list[MorphTarget]:
    """Morph targets (one per change) of a body for a model with semantic regressors.

    body_model: a ``BodyModel`` whose ``semantics`` are fitted (``bodyspace generate`` fits them).
    vertices: (V, 3) the body (the model's template topology), the shape keys' basis.
    changes: name -> change in SI units (``parse_morph_specs``), e.g. {"stature": 0.1, "mass": 10}.
    method: ``"closed_loop"`` (the true ``morph``) or ``"gradient"`` (one linear step), see the
        module docstring.
    Returns ``MorphTarget``s named ``morph_label(name, change)`` whose ``meaning`` records the
    variable, the change, its unit, the method and (closed loop) the change the full shape key
    reaches: measured on the mesh for measured variables, the regressor's for the others.
    """
    if method not in METHODS:
        raise ParameterError(f"method={method!r}; expected one of {', '.join(METHODS)}")
    sm = getattr(body_model, "semantics", None)
    if sm is None:
        raise ParameterError("the model holds no semantic regressors; fit them first (bodyspace generate MODEL "
                             "--database DB ... fits and saves them)")
    x0 = np.asarray(vertices, dtype=float)
    if x0.shape != np.shape(body_model.template_vertices):
        raise ParameterError(f"vertices: shape {x0.shape}, expected {np.shape(body_model.template_vertices)}: a body "
                             "of the model's template topology")
    for name in changes:
        sm.regressor(name)  # unknown names refused, naming the accepted ones
    out = []
    c0 = d0 = None
    for name, change in changes.items():
        if method == "closed_loop":
            result = body_model.morph(x0, {name: Target(name, "delta", value=float(change))})
            deltas = np.asarray(result.vertices, dtype=float) - x0
            reached = float(result.values[name])
            if name in sm.measured_ or name in sm.lengths_:       # measured on the mesh
                before = float(sm.measure_body(x0, [name])[name])
            else:                                                 # sex, age, muscle...: the regressor's value
                before = float(sm.regressor(name).predict(sm.project_mesh(x0).reshape(-1)))
        else:
            if c0 is None:
                c0 = sm.project_mesh(x0).reshape(-1)
                d0 = np.asarray(body_model.reconstruct(c0))[0]
            dc = _gradient_step(sm, c0, name, float(change))
            deltas = np.asarray(body_model.reconstruct(c0 + dc))[0] - d0
            reached = before = None
        meaning = {"variable": name, "change": float(change), "unit": _SI_UNIT.get(kind_of(name), "1"),
                   "method": method}
        if reached is not None:
            meaning["reached_change"] = reached - before
        out.append(MorphTarget(morph_label(name, change), deltas, meaning))
    return out
