"""Algorithm 1, step 2: minimise V(θ) (eq. 6) plus the priors (gyroscope noise and bias, and
the misalignment when asked) from θ₀ with damped BFGS: a MAP estimate.

The problem (data, normalisation, scales, priors, cost and gradients) is built by
``problem.py``; this module runs the optimiser on it and maps the result back to raw
magnetometer units on the canonical branch of the likelihood's symmetries.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from magcal.calib.initial.estimate import InitialEstimate
from magcal.calib.likelihood.optimize import OptimizeOptions, OptimizeReport, minimize_bfgs
from magcal.calib.likelihood.params import ModelParams
from magcal.calib.likelihood.problem import LikelihoodProblem, Priors, on_canonical_branch
from magcal.io.session import Session


@dataclass(frozen=True)
class MLEstimate:
    params: ModelParams  # raw magnetometer units
    theta: np.ndarray  # (34,) normalised
    theta0: np.ndarray  # (34,) normalised
    report: OptimizeReport


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
    report = minimize_bfgs(
        fun_and_grad,
        problem.theta0,
        problem.scales,
        options,
        fun=line_search_cost,
        progress=progress,
    )
    theta = on_canonical_branch(report.x)
    return MLEstimate(
        params=problem.model_params(theta),
        theta=theta,
        theta0=problem.theta0,
        report=report,
    )
