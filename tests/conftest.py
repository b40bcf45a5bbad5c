"""Shared fixtures: the real CC0 template (fetched into the user cache on first use)."""

import numpy as np
import pytest
from threadpoolctl import threadpool_limits

# Two pytest-xdist workers share the 2 cores: BLAS threads on top of that oversubscribe them
# (a kernel-ridge fit measured 31 s threaded against 1.2 s single-threaded under load).
threadpool_limits(1)

from bodyspace.data.template import load_template
from bodyspace.synth.phenotype import PhenotypeModel


@pytest.fixture(scope="session")
def template():
    return load_template()


@pytest.fixture(scope="session")
def phenotype_model(template):
    return PhenotypeModel(template)


@pytest.fixture(scope="session")
def rng():
    return np.random.default_rng(1234)
