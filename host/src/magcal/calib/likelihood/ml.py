# SPDX-License-Identifier: Apache-2.0
"""Algorithm 1, step 2: minimise V(θ) (eq. 6) plus the priors (gyroscope noise and bias, the
noise couplings, and the misalignment when asked) from θ₀: a MAP estimate, with a trust
region on the Fisher information (the default) or damped BFGS from the identity, the
paper's method (:data:`OPTIMIZERS`).

The magnetometer's time offset τ is fitted last: first the paper's model (τ = 0), then, from
there, with τ free. The delay is kept only when it explains the data better than chance
would: a likelihood-ratio test at :data:`TIME_OFFSET_TEST_LEVEL` (χ² with one degree of
freedom). Where the data cannot tell, τ = 0, so a sensor without a delay does not pay the
variance of a parameter that is confounded with the misalignment when the body turns mostly
about one axis (τ ω then acts like a fixed rotation).

Then the gyroscope's gain: the filter takes it as exact unless the session shows otherwise.
At the estimate, the filter is run again allowing for a gain error of
:data:`~magcal.calib.likelihood.problem.GYRO_GAIN_ERROR` per entry; where that raises the
likelihood by more than the time offset's test asks of a parameter, the estimate is refitted
from there with it. A simulated gyroscope with an exact gain, or a gyroscope whose gain
errors are too small to show, keeps the first estimate; a real one turned fast shows its
gain error as turns that miss by a share of their size.

Beside the fit of the paper's model from θ₀, the same fit runs from every other starting
point the caller gives (``other_starts``: the pipeline gives the initial estimate with its
ellipsoid from TWO-STEP), on a second thread; the estimate goes on from the best optimum,
and :meth:`MLEstimate.different_optima` names clearly different ones.

The problem (data, normalisation, scales, priors, cost and gradients) is built by
``problem.py``; this module runs the optimiser on it and maps the result back to raw
magnetometer units on the canonical branch of the likelihood's symmetries.
"""

from __future__ import annotations

import dataclasses
import statistics
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np

from magcal.calib.initial.estimate import InitialEstimate
from magcal.calib.likelihood.optimize import (
    OptimizeOptions,
    OptimizeReport,
    minimize_bfgs,
    minimize_trust_region,
)
from magcal.calib.likelihood.params import INDEX_TIME_OFFSET, ModelParams
from magcal.calib.likelihood.problem import (
    GYRO_GAIN_ERROR,
    LikelihoodProblem,
    Priors,
    on_canonical_branch,
)
from magcal.errors import CalibrationError
from magcal.io.session import Session

#: The ML step's optimisers (``optimize.py``), the default first: the trust region on the
#: Fisher information, which converges in tens of iterations on real recordings where BFGS
#: takes hundreds, and BFGS from the identity, the paper's.
OPTIMIZERS = ("trust-region", "bfgs")

#: The tolerances of the fits whose optimum is only compared with another's by cost (the
#: tests of the time offset and the gyroscope's gain): a predicted decrease of 1e-3 nats
#: changes a test statistic by 2e-3 against thresholds of 6.6. The fit finally chosen is
#: refined to ``OptimizeOptions``' own.
INTERMEDIATE_DECREMENT_TOL = 1e-3
INTERMEDIATE_GRADIENT_TOL = 1e-2

#: Significance level of the test that keeps a time offset (1 %: twice the log-likelihood
#: must rise by χ²₁(0.99) = 6.63 when τ is freed: :func:`chi2_one_dof_quantile`).
TIME_OFFSET_TEST_LEVEL = 0.01
#: The fits, as :func:`maximum_likelihood` announces them to its ``stage`` callback.
STAGE_PLAIN = "ML, the paper's model (no time offset)"
STAGE_FROM_OTHER = "ML, from the other starting point's better optimum"
STAGE_TIME_OFFSET = "ML, with the magnetometer's time offset"
STAGE_GYRO_GAIN = "ML, allowing for the gyroscope's gain error"
STAGE_REFINE = "ML, refining the chosen fit"

#: Two fits stopped at the tests' tolerance whose costs differ by less than this (nats)
#: found the same optimum: the estimate moves to another starting point's only beyond it.
SAME_OPTIMUM_NATS = 10.0 * INTERMEDIATE_DECREMENT_TOL
#: A fit from another starting point is left unfinished (its optimum unknown) once it has
#: run this many times the iterations the initial estimate's fit took (at least
#: :data:`CHECK_MIN_ITERATIONS`): fits that reach the same optimum take about as many
#: (19 and 20 on broad35_magnet4cm), and the estimate waits for the check.
CHECK_ITERATIONS_FACTOR = 1.5
CHECK_MIN_ITERATIONS = 10
#: Two starting points' optima are "clearly different" when twice their cost difference
#: exceeds the χ²₁ quantile at this level, as a parameter the tests would keep.
DIFFERENT_OPTIMA_LEVEL = TIME_OFFSET_TEST_LEVEL
#: Significance level of the test that allows for the gyroscope's gain error: the same as
#: the time offset's, as if the gain error were one more parameter.
GYRO_GAIN_TEST_LEVEL = TIME_OFFSET_TEST_LEVEL


class _Abandoned(Exception):
    """Raised through the optimiser to leave a check's fit unfinished."""

    def __init__(self, iterations: int) -> None:
        super().__init__(iterations)
        self.iterations = iterations


def chi2_one_dof_quantile(level: float) -> float:
    """The χ² quantile with one degree of freedom exceeded with probability ``level``:
    the square of the normal quantile at 1 − level/2 (the standard library's, so that a
    calibration does not import scipy.stats for one number)."""
    return statistics.NormalDist().inv_cdf(1.0 - 0.5 * level) ** 2


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
class GyroGainTest:
    """The test of the gyroscope's gain error: statistic 2 (cost at the estimate with the
    gain exact − cost there allowing for ``gain_error``), the threshold it had to pass and
    whether the gain error was allowed for (and the estimate refitted with it). The
    statistic is taken before the refit, which only lowers the cost further."""

    statistic: float
    threshold: float
    gain_error: float
    kept: bool

    def as_dict(self) -> dict:
        return dataclasses.asdict(self)


@dataclass(frozen=True)
class StartingPoint:
    """Where the paper's model (τ = 0) was fitted from, and the optimum it reached: its
    ``cost`` on the estimate's own problem (the same normalisation, priors and starting
    attitude), so that the starting points' optima compare; None for a fit left unfinished
    (:data:`CHECK_ITERATIONS_FACTOR`)."""

    name: str
    cost: float | None
    iterations: int
    converged: bool

    def as_dict(self) -> dict:
        return dataclasses.asdict(self)


@dataclass(frozen=True)
class MLEstimate:
    params: ModelParams  # raw magnetometer units
    theta: np.ndarray  # (35,) normalised
    theta0: np.ndarray  # (35,) normalised
    report: OptimizeReport  # every fit together (iterations, evaluations, time)
    time_offset_test: TimeOffsetTest | None = None
    gyro_gain_test: GyroGainTest | None = None
    #: the initial estimate's fit first, then each other starting point's
    starting_points: tuple[StartingPoint, ...] = ()

    def different_optima(self) -> tuple[StartingPoint, StartingPoint] | None:
        """The best and the worst starting point's optima when they are clearly different
        (2 ΔV beyond the tests' threshold, :data:`DIFFERENT_OPTIMA_LEVEL`), else None."""
        ranked = sorted(
            (p for p in self.starting_points if p.cost is not None), key=lambda p: p.cost
        )
        if len(ranked) >= 2 and different(ranked[0], ranked[-1]):
            return ranked[0], ranked[-1]
        return None


def different(a: StartingPoint, b: StartingPoint) -> bool:
    """Whether two starting points' fits ended in clearly different optima: both converged
    (a fit stopped short has not found its optimum) and 2 |ΔV| beyond the χ²₁ quantile at
    :data:`DIFFERENT_OPTIMA_LEVEL`, as a parameter the tests would keep."""
    return (
        a.converged
        and b.converged
        and 2.0 * abs(a.cost - b.cost) > chi2_one_dof_quantile(DIFFERENT_OPTIMA_LEVEL)
    )


def maximum_likelihood(
    session: Session,
    init: InitialEstimate,
    gradient: str = "exact",
    options: OptimizeOptions = OptimizeOptions(),
    progress: Callable[[int, float, float], None] | None = None,
    priors: Priors = Priors(),
    optimizer: str = OPTIMIZERS[0],
    other_starts: Sequence[tuple[str, ModelParams]]
    | Callable[[], Sequence[tuple[str, ModelParams]]] = (),
    stage: Callable[[str], None] | None = None,
) -> MLEstimate:
    """Algorithm 1 step 2 from the initial estimate; ``gradient`` "exact" or "numeric";
    ``priors`` make it a MAP estimate (:class:`~magcal.calib.likelihood.problem.Priors`);
    ``optimizer`` one of :data:`OPTIMIZERS`. The trust region needs exact gradients.

    ``other_starts``: (name, parameters in raw units) of other starting points, or a
    function that returns them (called on the second thread, so that finding them costs
    no wall time either). The paper's model is fitted from each as well, on a second
    thread beside the initial estimate's fit; the estimate continues from the best optimum
    reached, and :attr:`MLEstimate.starting_points` records them all.

    ``stage(text)`` is told as each fit starts (the model it fits); ``progress(iteration,
    cost, decrement)`` at each iteration of the fits, numbered across them."""
    problem = LikelihoodProblem.for_ml_step(session, init, priors=priors)
    if gradient not in ("exact", "numeric"):
        raise ValueError(f"unknown gradient {gradient!r}: use 'exact' or 'numeric'")
    if optimizer not in OPTIMIZERS:
        raise ValueError(f"unknown optimizer {optimizer!r}: use one of {', '.join(OPTIMIZERS)}")
    if optimizer == "trust-region" and gradient != "exact":
        raise ValueError("the trust-region optimizer needs exact gradients: use optimizer='bfgs'")

    def run(
        pr: LikelihoodProblem,
        hold_time_offset: bool,
        x0: np.ndarray,
        done: list,
        final: bool = True,
        start: OptimizeReport | None = None,
        report_progress: bool = True,
        label: str = "",
        abandon: Callable[[int], bool] | None = None,
    ) -> OptimizeReport:
        # Exact gradients: cost and gradient together at every trial point, since nearly
        # every step is accepted at α = 1 and a cost-only line search would pay for the
        # forward pass twice. Finite differences (the paper's way): the line search tries
        # points by cost alone, as a gradient there costs n_θ + 1 passes.
        if gradient == "exact":
            fun_and_grad, line_search_cost = pr.cost_and_gradient, None
        else:
            fun_and_grad, line_search_cost = pr.cost_and_numeric_gradient, pr.cost

        def held(theta: np.ndarray) -> tuple[float, np.ndarray]:
            # A zero gradient component keeps BFGS from ever moving τ from its start.
            value, grad = fun_and_grad(theta)
            grad = grad.copy()
            grad[INDEX_TIME_OFFSET] = 0.0
            return value, grad

        before = sum(r.iterations for r in done)
        if stage and label:
            stage(label)

        def progress_after(iteration: int, cost: float, decrement: float) -> None:
            if abandon and abandon(iteration):
                raise _Abandoned(iteration)
            if progress and report_progress:
                progress(before + iteration, cost, decrement)

        budget = dataclasses.replace(options, max_iter=options.max_iter - before)
        if optimizer == "trust-region" and not final:
            budget = dataclasses.replace(
                budget,
                decrement_tol=max(budget.decrement_tol, INTERMEDIATE_DECREMENT_TOL),
                gradient_tol=max(budget.gradient_tol, INTERMEDIATE_GRADIENT_TOL),
            )
        if optimizer == "bfgs":
            report = minimize_bfgs(
                held if hold_time_offset else fun_and_grad,
                x0,
                pr.scales,
                budget,
                fun=line_search_cost,
                progress=progress_after,
            )
        else:
            hold = np.zeros(pr.scales.size, dtype=bool)
            hold[INDEX_TIME_OFFSET] = hold_time_offset
            # Each fit starts from the model the previous one (or ``start``) ended with:
            # the same likelihood, one parameter freed or the gyroscope's gain allowed
            # for, rather than from a new pass of the information.
            previous = start or (done[-1] if done else None)
            curvature = None if previous is None else previous.curvature
            report = minimize_trust_region(
                pr.cost_gradient_and_information,
                fun_and_grad,
                pr.cost,
                x0,
                pr.scales,
                pr.typical_changes,
                budget,
                progress=progress_after,
                held=hold,
                curvature=curvature,
            )
        done.append(report)
        return report

    def budget_left(done: list) -> bool:
        return sum(r.iterations for r in done) < options.max_iter

    theta0 = problem.theta0.copy()
    theta0[INDEX_TIME_OFFSET] = 0.0
    fits: list[OptimizeReport] = []

    main_iterations: list[int] = []  # the initial estimate's fit's, once it has ended

    def too_long(iteration: int) -> bool:
        return bool(main_iterations) and iteration > CHECK_ITERATIONS_FACTOR * max(
            main_iterations[0], CHECK_MIN_ITERATIONS
        )

    def fit_from(p: ModelParams) -> OptimizeReport | int | None:
        """The paper's model fitted from ``p``; None where the cost is not finite there,
        the iterations run where it was left unfinished."""
        other = LikelihoodProblem.for_ml_step(session, init, at=p, priors=priors)
        x0 = other.theta0.copy()
        x0[INDEX_TIME_OFFSET] = 0.0
        try:
            return run(other, True, x0, [], final=False, report_progress=False, abandon=too_long)
        except CalibrationError:
            return None
        except _Abandoned as stop:
            return stop.iterations

    def finish(
        plain: OptimizeReport, fits: list
    ) -> tuple[OptimizeReport, TimeOffsetTest | None, GyroGainTest | None, LikelihoodProblem]:
        """The fits after the paper's model's, from its optimum ``plain``: the time offset's
        test, the gyroscope gain's, the refinement. Returns the chosen fit, the tests and the
        problem it was fitted on."""
        chosen, time_test, gain_test, final = plain, None, None, problem
        if budget_left(fits):  # budget left to test a delay
            delayed = run(problem, False, plain.x, fits, final=False, label=STAGE_TIME_OFFSET)
            statistic = 2.0 * (plain.cost - delayed.cost)
            threshold = chi2_one_dof_quantile(TIME_OFFSET_TEST_LEVEL)
            time_test = TimeOffsetTest(
                statistic=float(statistic),
                threshold=threshold,
                fitted_s=float(delayed.x[INDEX_TIME_OFFSET]),
                kept=bool(statistic > threshold),
            )
            chosen = delayed if time_test.kept else plain
        if budget_left(fits):  # and to test the gyroscope's gain
            gained = problem.with_gyro_gain_error(GYRO_GAIN_ERROR)
            statistic = 2.0 * (chosen.cost - gained.cost(chosen.x))
            threshold = chi2_one_dof_quantile(GYRO_GAIN_TEST_LEVEL)
            gain_test = GyroGainTest(
                statistic=float(statistic),
                threshold=threshold,
                gain_error=GYRO_GAIN_ERROR,
                kept=bool(statistic > threshold),
            )
            if gain_test.kept:
                final = gained
                chosen = run(
                    gained,
                    not (time_test and time_test.kept),
                    chosen.x,
                    fits,
                    label=STAGE_GYRO_GAIN,
                )
        if optimizer == "trust-region" and not (gain_test and gain_test.kept) and budget_left(fits):
            # The chosen fit stopped at the tests' tolerance: refined from where it stopped.
            chosen = run(
                problem,
                not (time_test and time_test.kept),
                chosen.x,
                fits,
                start=chosen,
                label=STAGE_REFINE,
            )
        return chosen, time_test, gain_test, final

    with ThreadPoolExecutor(max_workers=1) as pool:
        # The kernels release the GIL: on two cores the other starting points cost little
        # wall time.
        def fit_others() -> list[tuple[str, OptimizeReport | int | None]]:
            starts = other_starts() if callable(other_starts) else other_starts
            return [(name, fit_from(p)) for name, p in starts]

        pending = pool.submit(fit_others)
        # The fits before the last are compared by their cost alone (the tests), so they stop
        # once their remaining decrease is far below what a test can see; whichever is chosen
        # is refined to the final tolerance.
        plain = run(problem, True, theta0, fits, final=False, label=STAGE_PLAIN)
        main_iterations.append(plain.iterations)
        # The other starting points nearly always end where this fit did: the fits after it
        # go on from its optimum while they finish, and are redone from another optimum only
        # where one is better (below), so that the result is the same as in sequence.
        ahead_fits = list(fits)
        try:
            ahead: tuple | BaseException = finish(plain, ahead_fits)
        except Exception as exc:  # raised below, unless another starting point is better
            ahead = exc
        others = pending.result()
    starting_points = [
        StartingPoint("the initial estimate", plain.cost, plain.iterations, plain.converged)
    ]
    reached = {}
    for name, rep in others:
        if isinstance(rep, OptimizeReport):
            reached[len(starting_points)] = rep
            starting_points.append(
                StartingPoint(name, float(problem.cost(rep.x)), rep.iterations, rep.converged)
            )
        elif rep is not None:
            starting_points.append(StartingPoint(name, None, rep, False))
    best = min(reached, key=lambda i: starting_points[i].cost, default=0)
    if best > 0 and starting_points[best].cost < plain.cost - SAME_OPTIMUM_NATS:
        # Another starting point reached a better optimum: the estimate goes on from there.
        better = reached[best]
        plain = run(
            problem, True, better.x, fits, final=False, start=better, label=STAGE_FROM_OTHER
        )
        chosen, time_test, gain_test, problem = finish(plain, fits)
    elif isinstance(ahead, BaseException):
        raise ahead
    else:
        fits = ahead_fits
        chosen, time_test, gain_test, problem = ahead
    report = dataclasses.replace(
        chosen,
        iterations=sum(r.iterations for r in fits),
        cost_evaluations=sum(r.cost_evaluations for r in fits),
        gradient_evaluations=sum(r.gradient_evaluations for r in fits),
        seconds=sum(r.seconds for r in fits),
        history=[h for r in fits for h in r.history],
        hessian_resets=sum(r.hessian_resets for r in fits),
        information_evaluations=sum(r.information_evaluations for r in fits),
    )
    theta = on_canonical_branch(chosen.x)
    return MLEstimate(
        params=problem.model_params(theta),
        theta=theta,
        theta0=problem.theta0,
        report=report,
        time_offset_test=time_test,
        gyro_gain_test=gain_test,
        starting_points=tuple(starting_points),
    )
