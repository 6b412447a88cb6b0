# SPDX-License-Identifier: Apache-2.0
"""Shared fixtures."""

import pytest

from tests.synthetic import synthetic_filter_problem


@pytest.fixture(params=["mixed", "none", "all"])
def filter_problem(request):
    """A short session with known parameters, for each accelerometer-inflation pattern."""
    return synthetic_filter_problem(inflation=request.param)
