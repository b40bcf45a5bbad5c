"""Shared fixtures: the real CC0 template (fetched into the user cache on first use)."""

import numpy as np
import pytest

from bodyspace.data.phenotype import PhenotypeModel
from bodyspace.data.template import load_template


@pytest.fixture(scope="session")
def template():
    return load_template()


@pytest.fixture(scope="session")
def phenotype_model(template):
    return PhenotypeModel(template)


@pytest.fixture(scope="session")
def rng():
    return np.random.default_rng(1234)
