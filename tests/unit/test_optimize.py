# SPDX-License-Identifier: Apache-2.0
import warnings

import numpy as np
import pytest

from magcal.calib.likelihood.optimize import (
    OptimizeOptions,
    gradient_agrees,
    minimize_bfgs,
    minimize_trust_region,
    trust_region_step,
)
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


def rosenbrock_information(x):
    """Rosenbrock as ½‖r‖², r = (10 (x₁ − x₀²), 1 − x₀): value, gradient and the Gauss–Newton
    matrix JᵀJ, the least-squares analogue of the Fisher information."""
    r = np.array([10.0 * (x[1] - x[0] ** 2), 1.0 - x[0]])
    J = np.array([[-20.0 * x[0], 10.0], [-1.0, 0.0]])
    return 0.5 * float(r @ r), J.T @ r, J.T @ J


def test_trust_region_converges_on_rosenbrock_in_fewer_iterations_than_bfgs():
    rep = minimize_trust_region(
        rosenbrock_information,
        lambda x: rosenbrock_information(x)[:2],
        lambda x: rosenbrock_information(x)[0],
        np.array([-1.2, 1.0]),
        np.ones(2),
        np.ones(2),
        OptimizeOptions(decrement_tol=1e-20, gradient_tol=1e-10),
    )
    np.testing.assert_allclose(rep.x, [1.0, 1.0], atol=1e-8)
    assert rep.converged and rep.stopping_rule == "gradient"
    assert rep.information_evaluations >= 1
    bfgs = minimize_bfgs(
        rosenbrock,
        np.array([-1.2, 1.0]),
        np.ones(2),
        OptimizeOptions(decrement_tol=1e-20, gradient_tol=1e-10),
    )
    assert rep.iterations < bfgs.iterations


def test_trust_region_bounds_the_first_step_by_the_typical_change():
    # A quadratic whose minimum is 1000 typical changes away: the first accepted point moves
    # by at most one typical change, and the region grows from there.
    seen = []

    def fgi(x):
        seen.append(x.copy())
        return 0.5 * float((x - 1000.0) @ (x - 1000.0)), x - 1000.0, np.eye(2)

    rep = minimize_trust_region(
        fgi, lambda x: fgi(x)[:2], lambda x: fgi(x)[0], np.zeros(2), np.ones(2), np.ones(2)
    )
    assert np.linalg.norm(seen[1]) <= 1.0 + 1e-9
    np.testing.assert_allclose(rep.x, [1000.0, 1000.0], atol=1e-6)
    assert rep.converged


def test_trust_region_rejects_points_where_the_cost_is_not_finite():
    # Beyond x = 2 the cost is NaN (a covariance breaking down); the minimum of the
    # quadratic model lies there, the run must stay on the finite side.
    def fgi(x):
        if x[0] > 2.0:
            return float("nan"), np.full(1, np.nan), np.eye(1)
        return 0.5 * float((x[0] - 5.0) ** 2), np.array([x[0] - 5.0]), np.eye(1)

    rep = minimize_trust_region(
        fgi,
        lambda x: fgi(x)[:2],
        lambda x: fgi(x)[0],
        np.zeros(1),
        np.ones(1),
        np.ones(1),
        OptimizeOptions(max_iter=200),
    )
    assert np.isfinite(rep.cost) and rep.x[0] <= 2.0
    assert not rep.converged


def test_trust_region_rejects_points_where_the_gradient_disagrees_with_the_cost():
    # Beyond x = 2 the cost is still right but its gradient is rounding noise of 1e50 (a
    # covariance at the edge of breaking down): no place to continue from.
    def fgi(x):
        g = x - 5.0 if x[0] <= 2.0 else np.full(1, 1e50)
        return 0.5 * float((x[0] - 5.0) ** 2), g, np.eye(1)

    rep = minimize_trust_region(
        fgi,
        lambda x: fgi(x)[:2],
        lambda x: fgi(x)[0],
        np.zeros(1),
        np.ones(1),
        np.ones(1),
        OptimizeOptions(max_iter=200),
    )
    assert rep.x[0] <= 2.0 and not rep.converged


def test_gradient_agreement_along_a_step():
    quad = lambda x: 0.5 * float(x @ x)  # noqa: E731
    x, s = np.array([1.0, 2.0]), np.array([-0.5, 0.3])
    args = (quad(x), x, quad(x + s), x + s, s, 0.1)
    assert gradient_agrees(*args)
    assert not gradient_agrees(*args[:3], 1e6 * (x + s), *args[4:])
    assert not gradient_agrees(*args[:3], np.array([np.nan, 0.0]), *args[4:])


def test_trust_region_reports_a_run_out_of_iterations_as_not_converged():
    rep = minimize_trust_region(
        rosenbrock_information,
        lambda x: rosenbrock_information(x)[:2],
        lambda x: rosenbrock_information(x)[0],
        np.array([-1.2, 1.0]),
        np.ones(2),
        np.ones(2),
        OptimizeOptions(max_iter=2),
    )
    assert rep.stopping_rule == "max_iter" and not rep.converged


def coupled_quadratic(x):
    """½ (x − c)ᵀ A (x − c) with strong coupling between the two variables."""
    A = np.array([[2.0, 1.5], [1.5, 2.0]])
    r = x - np.array([3.0, -1.0])
    return 0.5 * float(r @ A @ r), A @ r, A


def test_trust_region_keeps_held_variables_and_hands_its_model_on():
    held = minimize_trust_region(
        coupled_quadratic,
        lambda x: coupled_quadratic(x)[:2],
        lambda x: coupled_quadratic(x)[0],
        np.zeros(2),
        np.ones(2),
        np.ones(2),
        held=np.array([False, True]),
    )
    # x₁ stays exactly at its start; x₀ reaches the minimum along it, 3 + 1.5/2 · (−1).
    assert held.x[1] == 0.0
    assert held.x[0] == pytest.approx(3.0 - 0.75, abs=1e-6)
    assert held.converged
    np.testing.assert_allclose(held.curvature, coupled_quadratic(held.x)[2])
    # Freed, from the held fit's model: no new evaluation of the information.
    freed = minimize_trust_region(
        coupled_quadratic,
        lambda x: coupled_quadratic(x)[:2],
        lambda x: coupled_quadratic(x)[0],
        held.x,
        np.ones(2),
        np.ones(2),
        curvature=held.curvature,
    )
    np.testing.assert_allclose(freed.x, [3.0, -1.0], atol=1e-6)
    assert freed.converged and freed.information_evaluations == 0


@pytest.mark.parametrize("seed", range(5))
def test_trust_region_step_solves_the_subproblem(seed):
    """Against a brute-force minimisation of the model on the boundary, for definite and
    indefinite matrices, with and without weights."""
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(4, 4))
    B = A @ A.T - (2.0 if seed % 2 else 0.0) * np.eye(4)
    g = rng.normal(size=4)
    weight = np.exp(rng.normal(size=4)) if seed >= 2 else None
    radius = 0.3
    s = trust_region_step(B, g, radius, weight)
    w = np.ones(4) if weight is None else weight
    assert np.linalg.norm(w * s) <= radius * (1 + 1e-6)

    def model(x):
        return float(g @ x + 0.5 * x @ B @ x)

    # Random points on the (weighted) boundary and inside never do better.
    u = rng.normal(size=(20000, 4))
    u = radius * u / np.linalg.norm(u, axis=1)[:, None] * rng.random((20000, 1)) ** 0.25
    candidates = u / w
    best = min(model(c) for c in candidates)
    assert model(s) <= best + 1e-9
