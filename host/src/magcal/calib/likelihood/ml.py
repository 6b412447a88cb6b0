"""Algorithm 1, step 2: minimise V(θ) (eq. 6) plus the priors (gyroscope noise and bias, and
the misalignment when asked) from θ₀ with damped BFGS: a MAP estimate.

The magnetometer's time offset τ is fitted last: first the paper's model (τ = 0), then, from
there, with τ free. The delay is kept only when it explains the data better than chance
would: a likelihood-ratio test at :data:`TIME_OFFSET_TEST_LEVEL` (χ² with one degree of
freedom). Where the data cannot tell, τ = 0, so a sensor without a delay does not pay the
variance of a parameter that is confounded with the misalignment when the body turns mostly
about one axis (τ ω then acts like a fixed rotation).

The problem (data, normalisation, scales, priors, cost and gradients) is built by
``problem.py``; this module runs the optimiser on it and maps the result back to raw
magnetometer units on the canonical branch of the likelihood's symmetries.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import scipy.stats

from magcal.calib.initial.estimate import InitialEstimate
from magcal.calib.likelihood.optimize import OptimizeOptions, OptimizeReport, minimize_bfgs
from magcal.calib.likelihood.params import INDEX_TIME_OFFSET, ModelParams
from magcal.calib.likelihood.problem import LikelihoodProblem, Priors, on_canonical_branch
from magcal.io.session import Session

#: Significance level of the test that keeps a time offset (1 %: twice the log-likelihood
#: must rise by χ²₁(0.99) = 6.63 when τ is freed).
TIME_OFFSET_TEST_LEVEL = 0.01


@dataclass(frozen=True)
class TimeOffsetTest:
    """The likelihood-ratio test of τ ≠ 0: statistic 2 (cost at τ = 0 − cost with τ free),
    the threshold it had to pass, the τ it was freed to (s) and whether it was kept."""

    statistic: float
    threshold: float
    fitted_s: float
    kept: bool

    def as_dict(self) -> dict:
        return dataclasses.asdict(self)


@dataclass(frozen=True)
class MLEstimate:
    params: ModelParams  # raw magnetometer units
    theta: np.ndarray  # (35,) normalised
    theta0: np.ndarray  # (35,) normalised
    report: OptimizeReport  # both fits together (iterations, evaluations, time)
    time_offset_test: TimeOffsetTest | None = None


def maximum_likelihood(
    session: Session,
    init: InitialEstimate,
    gradient: str = "exact",
    options: OptimizeOptions = OptimizeOptions(),
    progress: Callable[[int, float, float], None] | None = None,
    priors: Priors = Priors(),
) -> MLEstimate:
    """Algorithm 1 step 2 from the initial estimate; ``gradient`` "exact" or "numeric";
    ``priors`` make it a MAP estimate (:class:`~magcal.calib.likelihood.problem.Priors`)."""
    problem = LikelihoodProblem.for_ml_step(session, init, priors=priors)
    # Exact gradients: cost and gradient together at every trial point, since nearly every
    # step is accepted at α = 1 and a cost-only line search would pay for the forward pass
    # twice. Finite differences (the paper's way): the line search tries points by cost
    # alone, as a gradient there costs n_θ + 1 passes.
    if gradient == "exact":
        fun_and_grad, line_search_cost = problem.cost_and_gradient, None
    elif gradient == "numeric":
        fun_and_grad, line_search_cost = problem.cost_and_numeric_gradient, problem.cost
    else:
        raise ValueError(f"unknown gradient {gradient!r}: use 'exact' or 'numeric'")

    def without_time_offset(theta: np.ndarray) -> tuple[float, np.ndarray]:
        # A zero gradient component keeps BFGS from ever moving τ from its start, 0.
        value, grad = fun_and_grad(theta)
        grad = grad.copy()
        grad[INDEX_TIME_OFFSET] = 0.0
        return value, grad

    theta0 = problem.theta0.copy()
    theta0[INDEX_TIME_OFFSET] = 0.0

    def run(fun_and_grad, x0, budget: int, done: int) -> OptimizeReport:
        def progress_after(iteration: int, cost: float, decrement: float) -> None:
            if progress:
                progress(done + iteration, cost, decrement)

        return minimize_bfgs(
            fun_and_grad,
            x0,
            problem.scales,
            dataclasses.replace(options, max_iter=budget),
            fun=line_search_cost,
            progress=progress_after,
        )

    plain = run(without_time_offset, theta0, options.max_iter, 0)
    chosen, report, test = plain, plain, None
    if plain.iterations < options.max_iter:  # budget left to test a delay
        delayed = run(fun_and_grad, plain.x, options.max_iter - plain.iterations, plain.iterations)
        statistic = 2.0 * (plain.cost - delayed.cost)
        threshold = float(scipy.stats.chi2.isf(TIME_OFFSET_TEST_LEVEL, df=1))
        test = TimeOffsetTest(
            statistic=float(statistic),
            threshold=threshold,
            fitted_s=float(delayed.x[INDEX_TIME_OFFSET]),
            kept=bool(statistic > threshold),
        )
        chosen = delayed if test.kept else plain
        report = dataclasses.replace(
            chosen,
            iterations=plain.iterations + delayed.iterations,
            cost_evaluations=plain.cost_evaluations + delayed.cost_evaluations,
            gradient_evaluations=plain.gradient_evaluations + delayed.gradient_evaluations,
            seconds=plain.seconds + delayed.seconds,
            history=plain.history + delayed.history,
            hessian_resets=plain.hessian_resets + delayed.hessian_resets,
        )
    theta = on_canonical_branch(chosen.x)
    return MLEstimate(
        params=problem.model_params(theta),
        theta=theta,
        theta0=problem.theta0,
        report=report,
        time_offset_test=test,
    )
