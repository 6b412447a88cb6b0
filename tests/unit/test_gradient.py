# SPDX-License-Identifier: Apache-2.0
"""The exact (reverse-mode) gradient of V(θ) against central finite differences."""

import numpy as np
import pytest

from magcal.calib.likelihood import params
from magcal.calib.likelihood.problem import (
    negative_log_likelihood,
    negative_log_likelihood_and_gradient,
    numeric_gradient,
)
from tests.synthetic import random_masks, synthetic_filter_problem, with_masks


def central_difference(f, theta, h):
    """Fourth-order central differences: truncation O(h⁴), so a large h keeps rounding low."""
    g = np.empty_like(theta)
    for i in range(theta.size):
        e = np.zeros_like(theta)
        e[i] = h[i]
        g[i] = (8 * (f(theta + e) - f(theta - e)) - (f(theta + 2 * e) - f(theta - 2 * e))) / (
            12 * h[i]
        )
    return g


@pytest.mark.parametrize("masked", [False, True])
@pytest.mark.parametrize(("seed", "inflation"), [(0, "mixed"), (1, "none"), (2, "all")])
def test_exact_gradient_matches_central_differences_at_random_points(seed, inflation, masked):
    p, data, _ = synthetic_filter_problem(n=300, seed=seed, inflation=inflation)
    if masked:  # some samples without accelerometer, magnetometer or either
        data = with_masks(data, *random_masks(len(data), 10 + seed))
    rng = np.random.default_rng(100 + seed)
    theta = params.pack(p)
    # A random point away from the truth: perturb every parameter.
    theta = (
        theta
        + rng.normal(size=theta.size)
        * np.r_[np.full(12, 0.02), 0.02, np.full(3, 0.005), np.full(18, 0.2), 0.02]
    )
    _, g = negative_log_likelihood_and_gradient(theta, data)
    fd = central_difference(
        lambda th: negative_log_likelihood(th, data), theta, 1e-4 * np.maximum(1, abs(theta))
    )
    err = np.abs(g - fd)
    # Norm-wise 1e-6 relative; and each component to 1e-6 of its own size or of the
    # rounding floor of the differences (components near zero cannot do better).
    assert np.linalg.norm(g - fd) <= 1e-6 * np.linalg.norm(fd)
    floor = 1e-6 * np.linalg.norm(fd, np.inf) * 1e-2
    assert np.all(err <= 1e-6 * np.abs(fd) + floor), params.PARAM_NAMES[int(np.argmax(err))]


def test_numeric_gradient_schemes_agree_with_exact():
    p, data, _ = synthetic_filter_problem(n=200, seed=3)
    theta = params.pack(p)
    _, g = negative_log_likelihood_and_gradient(theta, data)
    for scheme, tol in (("forward", 1e-3), ("central", 1e-6)):
        fd = numeric_gradient(theta, data, scheme)
        assert np.linalg.norm(fd - g) <= tol * np.linalg.norm(g)


def test_numeric_gradient_rejects_unknown_scheme():
    p, data, _ = synthetic_filter_problem(n=50)
    with pytest.raises(ValueError, match="unknown finite-difference scheme"):
        numeric_gradient(params.pack(p), data, "backward")
