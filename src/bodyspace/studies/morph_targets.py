"""How exact is a morph target? Shape keys at a weight against the true ``morph`` of that amount.

A glTF morph target is a straight line: ``x0 + w * delta``. ``morph_target_errors`` compares it,
for each target and weight ``w``, with what ``bodyspace morph --set NAME=+(w * change)`` makes of
the same body (``BodyModel.morph``: the closed loop, lengths refined to 1 mm), and with what
the variable should measure. Returns rows of data; docs/export.md shows them.
"""

from __future__ import annotations

import numpy as np

from bodyspace.export.gltf import MorphTarget
from bodyspace.units import Target

__all__ = ["morph_target_errors"]

WEIGHTS = (0.5, 1.0, -0.5, -1.0)


def morph_target_errors(body_model, vertices: np.ndarray, targets: list[MorphTarget],
                        weights=WEIGHTS) -> list[dict]:
    """One row per (target, weight): ``variable``, ``weight``, ``asked_change`` (SI), the
    change the shape key makes (``key_change``: measured on the mesh for measured variables,
    the regressor's for the others) and the true morph's (``morph_change``), and the vertex
    distance between the shape-keyed body and the true morph (``max_m``, ``mean_m``).

    body_model: a ``BodyModel`` with semantics; vertices: (V, 3) the basis body the targets were
    made on; targets: ``semantic_morph_targets`` of it (their ``meaning`` names the variable
    and the change at weight 1).
    """
    sm = body_model.semantics
    x0 = np.asarray(vertices, dtype=float)
    rows = []
    for t in targets:
        name, change = t.meaning["variable"], float(t.meaning["change"])
        measured = name in sm.measured_ or name in sm.lengths_

        def value(x):
            if measured:
                return float(sm.measure_body(x, [name])[name])
            return float(sm.regressor(name).predict(sm.project_mesh(x).reshape(-1)))

        before = value(x0)
        for w in weights:
            keyed = x0 + w * np.asarray(t.deltas, dtype=float)
            true = np.asarray(body_model.morph(x0, {name: Target(name, "delta", value=w * change)}).vertices)
            d = np.linalg.norm(keyed - true, axis=1)
            rows.append({"target": t.name, "variable": name, "method": t.meaning.get("method"), "weight": float(w),
                         "asked_change": w * change, "key_change": value(keyed) - before,
                         "morph_change": value(true) - before, "max_m": float(d.max()), "mean_m": float(d.mean())})
    return rows
