"""The registration's default shape space (issue 15): it must be able to hold a body's
measurements, or no model fit can reach ISO 20685-1 (docs/registration.md, fourth round)."""

import numpy as np

from bodyspace.measure import evaluate
from bodyspace.measure.definitions import load_measurement_set
from bodyspace.measure.tolerances import iso_tolerance
from bodyspace.register.model_fit import phenotype_basis
from bodyspace.synth.foreign import foreign_phenotype


def test_default_shape_space_holds_edge_bodies_measurements_within_iso(template, phenotype_model):
    """Edge-of-population bodies (the test scans' kind) projected by least squares onto the
    default basis keep every measurement within ISO 20685-1 (24 components kept 22-25 of 31)."""
    basis = phenotype_basis(template)
    flat = basis.components.reshape(len(basis.sigma), -1)
    mset = load_measurement_set()
    rng = np.random.default_rng(7)
    for _ in range(2):
        truth = phenotype_model.vertices(foreign_phenotype(rng)[None])[0]
        coef = np.linalg.lstsq(flat.T, (truth - basis.mean).ravel(), rcond=None)[0]
        got = evaluate(mset, basis.body(coef), template.faces)
        ref = evaluate(mset, truth, template.faces)
        out = []
        for name, m in got.items():
            r = ref[name].value
            if np.isnan(r):
                continue
            tol, rel = iso_tolerance(name, m)
            err = abs((m.value - r) / r if rel else m.value - r)
            if err > tol:
                out.append(f"{name} {err / tol:.1f}x")
        assert not out, f"measurements outside ISO 20685-1 after projection: {', '.join(out)}"
