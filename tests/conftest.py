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


# The README test runs every README command in order (about 250 s, far the longest test). Run
# first, it overlaps the rest of the suite on the other pytest-xdist worker; left at its place in
# the alphabet it started about 60 % of the way through and the other worker idled at the end.
RUN_FIRST = ("tests/test_readme.py::test_readme_runs_top_to_bottom",)


def pytest_collection_modifyitems(config, items):
    first = [item for item in items if item.nodeid in RUN_FIRST]
    items[:] = first + [item for item in items if item.nodeid not in RUN_FIRST]
