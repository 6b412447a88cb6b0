# SPDX-License-Identifier: Apache-2.0
import warnings

import numpy as np
import pytest

from magcal.calib.likelihood.optimize import OptimizeOptions, minimize_bfgs
from magcal.errors import CalibrationError


def rosenbrock(x):
    v = 100 * (x[1] - x[0] ** 2) ** 2 + (1 - x[0]) ** 2
    g = np.array([-400 * x[0] * (x[1] - x[0] ** 2) - 2 * (1 - x[0]), 200 * (x[1] - x[0] ** 2)])
    return v, g


def test_bfgs_converges_on_rosenbrock_and_says_why():
    rep = minimize_bfgs(
        rosenbrock,
        np.array([-1.2, 1.0]),
        np.ones(2),
        OptimizeOptions(decrement_tol=1e-16, gradient_tol=1e-8),
    )
    np.testing.assert_allclose(rep.x, [1.0, 1.0], atol=1e-6)
    assert rep.converged
    assert rep.stopping_rule in ("gradient", "step")
    assert rep.iterations > 5


def test_scaling_makes_badly_scaled_quadratic_easy():
    s = np.array([1e-4, 1.0, 1e3])

    def f(x):
        z = x / s
        return 0.5 * float(z @ z), z / s

    rep = minimize_bfgs(f, s * 3.0, s, OptimizeOptions(decrement_tol=1e-20, gradient_tol=1e-10))
    assert rep.iterations <= 3
    np.testing.assert_allclose(rep.x / s, 0.0, atol=1e-8)


def test_iteration_cap_is_reported():
    rep = minimize_bfgs(rosenbrock, np.array([-1.2, 1.0]), np.ones(2), OptimizeOptions(max_iter=3))
    assert rep.stopping_rule == "max_iter"
    assert not rep.converged


def test_non_finite_start_raises():
    with pytest.raises(CalibrationError, match="not finite at the initial estimate"):
        minimize_bfgs(lambda x: (float("nan"), x), np.zeros(2), np.ones(2))


def test_lost_positive_definiteness_restarts_and_still_converges(monkeypatch):
    # Rounding can leave the damped-BFGS matrix indefinite after a step into extreme
    # curvature (seen on an accelerated session); simulate that on the third iteration.
    real_cholesky = np.linalg.cholesky
    calls = {"n": 0}

    def flaky_cholesky(a):
        calls["n"] += 1
        if calls["n"] == 3:
            raise np.linalg.LinAlgError("Matrix is not positive definite")
        return real_cholesky(a)

    monkeypatch.setattr(np.linalg, "cholesky", flaky_cholesky)
    rep = minimize_bfgs(
        rosenbrock,
        np.array([-1.2, 1.0]),
        np.ones(2),
        OptimizeOptions(decrement_tol=1e-16, gradient_tol=1e-8),
    )
    assert rep.hessian_resets == 1
    assert rep.converged
    np.testing.assert_allclose(rep.x, [1.0, 1.0], atol=1e-6)


def test_a_step_that_rounds_to_nothing_ends_the_run_without_invalid_arithmetic():
    # At the minimum of a steep quadratic far from the start, a gradient off by a little
    # asks for a step below the position's round-off: it is accepted (the cost cannot
    # change) and is exactly zero, which carries no curvature for the BFGS update.
    K, c = 1e12, 1e5

    def f(x):
        u = x[0] - c
        return 1e3 + 0.5 * K * u * u, np.array([K * u - 1.0])

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        rep = minimize_bfgs(f, np.zeros(1), np.ones(1))
    assert rep.stopping_rule == "step"
    assert rep.x[0] == c
