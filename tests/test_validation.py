"""bodyspace.validation: the shared argument checks refuse with ParameterError, naming the field."""

import numpy as np
import pytest

from bodyspace.errors import ParameterError
from bodyspace.validation import (
    as_codes,
    as_generator,
    as_int,
    as_matrix,
    as_nonnegative_float,
    as_positive_grid,
    as_samples,
    as_seed,
    as_targets,
    as_vector,
    check_state_arrays,
)


@pytest.mark.parametrize("bad", [-1, "7", 1.5, True, [1, 2]])
def test_rng_refuses_what_numpy_would_trip_on(bad):
    with pytest.raises(ParameterError, match=r"rng=.*expected an integer seed >= 0, a numpy Generator or None"):
        as_generator(bad)


def test_rng_forms():
    gen = np.random.default_rng(3)
    assert as_generator(gen) is gen                       # the caller's stream, not a copy
    assert as_generator(5).integers(1000) == np.random.default_rng(5).integers(1000)
    assert as_seed(7) == 7                                # an int seed is kept (seed + 1 derivations)
    assert as_seed(np.random.default_rng(0)) == as_seed(np.random.default_rng(0))
    assert isinstance(as_seed(None), int)


def test_matrix_and_vector():
    assert as_matrix([1.0, 2.0], allow_vector=True).shape == (1, 2)
    with pytest.raises(ParameterError, match="X: rows have length 2, expected 3"):
        as_matrix([[1.0, 2.0]], n_features=3)
    with pytest.raises(ParameterError, match="y: contains NaN"):
        as_vector([1.0, np.nan], "y")
    with pytest.raises(ParameterError, match="could not be read as numbers"):
        as_matrix([["a", "b"]])


def test_scalars():
    assert as_int(3, "folds", 2) == 3
    for bad in (True, 1, 2.0):
        with pytest.raises(ParameterError, match="folds="):
            as_int(bad, "folds", 2)
    assert as_nonnegative_float(0, "ridge") == 0.0
    with pytest.raises(ParameterError, match="ridge=-1"):
        as_nonnegative_float(-1, "ridge")
    np.testing.assert_array_equal(as_positive_grid(2, "gamma"), [2.0])
    for bad in ([], [1, 0], "x"):
        with pytest.raises(ParameterError, match="gamma="):
            as_positive_grid(bad, "gamma")


def test_samples_targets_codes():
    x, single = as_samples([1, 2, 3], n_features=3)
    assert x.shape == (1, 3) and single
    with pytest.raises(ParameterError, match="expected a 2-D array"):
        as_samples([1, 2, 3])                             # in fit, a 1-D X is ambiguous
    y, one_d = as_targets([1, 2], 2)
    assert y.shape == (2, 1) and one_d
    with pytest.raises(ParameterError, match="Y: 3 rows, expected 2"):
        as_targets([1, 2, 3], 2)
    with pytest.raises(ParameterError, match=r"codes: code 0 has NaN or infinity at entry 1"):
        as_codes([0.0, np.inf], 2, "test codes")


def test_state_arrays():
    good = {"kind": np.array("Thing"), "format_version": np.array(1), "a": np.zeros(2)}
    check_state_arrays(good, "Thing", ("a",), 1)
    with pytest.raises(ParameterError, match="expected 'Thing'"):
        check_state_arrays({**good, "kind": np.array("Other")}, "Thing", ("a",), 1)
    with pytest.raises(ParameterError, match=r"missing \['a'\]"):
        check_state_arrays({"kind": np.array("Thing"), "format_version": np.array(1)}, "Thing", ("a",), 1)
    with pytest.raises(ParameterError, match="written by a newer bodyspace"):
        check_state_arrays({**good, "format_version": np.array(2)}, "Thing", ("a",), 1)
