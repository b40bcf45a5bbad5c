import numpy as np
import pytest

from bodyspace.errors import ParameterError
from bodyspace.mesh.geometry import capped_volume
from bodyspace.synth.phenotype import (
    PARAMETERS,
    age_to_years,
    category_weights,
    phenotype_array,
    years_to_age,
)


def stature(v):
    return np.ptp(v[..., 1], axis=-1)


def test_category_weights_are_makehuman_rules():
    w = category_weights("muscle", np.array([0.0, 0.25, 0.5, 0.75, 1.0]))
    np.testing.assert_allclose(w, [[1, 0, 0], [0.5, 0.5, 0], [0, 1, 0], [0, 0.5, 0.5], [0, 0, 1]])
    a = category_weights("age", np.array([0.1875, 0.34375]))
    np.testing.assert_allclose(a, [[0, 1, 0, 0], [0, 0.5, 0.5, 0]])
    np.testing.assert_allclose(age_to_years([0, 0.1875, 0.5, 1]), [1, 10, 25, 90])
    np.testing.assert_allclose(years_to_age(age_to_years(np.linspace(0, 1, 7))), np.linspace(0, 1, 7))


def test_height_parameter_raises_stature(phenotype_model):
    V = phenotype_model.vertices({"height": np.linspace(0, 1, 5)})
    assert (np.diff(stature(V)) > 0.05).all()


def test_weight_parameter_raises_volume(phenotype_model, template):
    for muscle in (0.0, 0.5, 1.0):
        V = phenotype_model.vertices({"weight": np.linspace(0, 1, 5), "muscle": muscle})
        assert (np.diff(capped_volume(V, template.faces)) > 0).all()


def test_gender_changes_shoulder_to_hip_ratio(phenotype_model, template):
    V = phenotype_model.vertices({"gender": np.array([0.0, 1.0])})

    def ratio(v):
        # Shoulder joints apart over hip joints apart: broad shoulders and narrow hips for men.
        sh = np.linalg.norm(template.joint(v, "joint-l-shoulder") - template.joint(v, "joint-r-shoulder"))
        hip = np.linalg.norm(template.joint(v, "joint-l-upper-leg") - template.joint(v, "joint-r-upper-leg"))
        return sh / hip

    assert ratio(V[1]) > ratio(V[0]) * 1.08


def test_symmetric_phenotype_is_symmetric(phenotype_model, template, rng):
    P = rng.random((8, len(PARAMETERS)))
    V = phenotype_model.vertices(P)
    err = np.abs(V[:, template.mirror] * [-1, 1, 1] - V).max()
    assert err < 1e-6


def test_no_nan_in_parameter_box(phenotype_model):
    corners = np.array(np.meshgrid(*[[0.0, 1.0]] * 8, indexing="ij")).reshape(8, -1).T
    P = np.concatenate([corners, np.full((len(corners), 3), 1 / 3)], axis=1)
    V = phenotype_model.vertices(P)
    assert np.isfinite(V).all()
    assert (stature(V) > 0.3).all(), "even the smallest baby is a body"


def test_batch_equals_single(phenotype_model, rng):
    P = rng.random((5, len(PARAMETERS)))
    batch = phenotype_model.vertices(P)
    for i in range(5):
        np.testing.assert_allclose(batch[i], phenotype_model.vertices(P[i])[0], atol=1e-6)


def test_sparse_weights_touch_few_targets(phenotype_model, rng):
    W = phenotype_model.weights(rng.random((20, len(PARAMETERS))))
    assert W.nnz / 20 < 0.25 * W.shape[1]


def test_bad_parameters_are_named():
    with pytest.raises(ParameterError, match="'heigth'"):
        phenotype_array({"heigth": 0.5})
    with pytest.raises(ParameterError, match="'weight' = 1.5"):
        phenotype_array({"weight": 1.5})
    with pytest.raises(ParameterError, match="'age' is NaN"):
        phenotype_array({"age": float("nan")})
    with pytest.raises(ParameterError, match=r"\(N, 11\)"):
        phenotype_array(np.zeros((2, 3)))
