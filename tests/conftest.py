# SPDX-License-Identifier: Apache-2.0
"""Shared fixtures, and one BLAS thread per test process."""

import os

# One BLAS thread per test process, set before numpy is imported (as the accuracy and real
# reports do): the matrices are small, `make test` runs two processes on two cores, and ML
# fits its second starting point on a thread of its own, so OpenBLAS's own threads only
# oversubscribe the cores, where they spin: the quick table2 check took 69 s for 5 seeds with
# them beside one other busy process, 15 s without.
for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import pytest  # noqa: E402

from tests.synthetic import synthetic_filter_problem  # noqa: E402


@pytest.fixture(params=["mixed", "none", "all"])
def filter_problem(request):
    """A short session with known parameters, for each accelerometer-inflation pattern."""
    return synthetic_filter_problem(inflation=request.param)
