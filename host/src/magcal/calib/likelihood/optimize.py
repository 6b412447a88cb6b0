# SPDX-License-Identifier: Apache-2.0
"""The ML step's optimisers, in the scaled variables z = (x − x₀) / scale.

* :func:`minimize_trust_region` (the default): a trust-region quasi-Newton method whose
  model starts from, and is periodically reset to, the Fisher information of the cost
  (``host/csrc/mekf_fisher.c``), the curvature a quasi-Newton method would otherwise learn
  over hundreds of iterations; between resets it is refined by damped BFGS updates, which
  learn where the observed curvature departs from the expected one (a model that the data
  only approximately follow).
* :func:`minimize_bfgs`: damped BFGS with a backtracking line search (Nocedal & Wright,
  Procedure 18.2 and Algorithm 3.1), the quasi-Newton method of the paper's Section 5.1,
  from a scaled identity.

Written here rather than taken from scipy because the calibration needs to report *which*
stopping rule fired, to certify convergence by the gradient *and* the predicted decrease,
and to keep going with Powell damping where the curvature condition fails (scipy's BFGS
skips such updates).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from magcal.errors import CalibrationError

ARMIJO_C1 = 1e-4
BACKTRACK_FACTOR = 0.5
MAX_BACKTRACKS = 40
POWELL_DAMPING = 0.2


@dataclass(frozen=True)
class OptimizeOptions:
    """Stopping rules, all in the scaled variables z = (x − x₀) / scale.

    decrement_tol : stop when the predicted decrease ½ gᵀB⁻¹g (nats) is below this. A
                    change of 1e-6 nats in a log-likelihood is far below any statistical
                    meaning, yet cheap to reach with exact gradients.
    gradient_tol  : and the largest scaled gradient component is below this.
    step_tol      : or the largest scaled step is below this, with the cost no longer
                    decreasing by more than ``cost_tol`` (relative).
    max_iter      : hard cap; reaching it is reported, never silent. Simulated sessions
                    converge in 30–100 iterations; real hand-held recordings, whose errors
                    the model only approximates, in 200–800 (`make real`: 757 on
                    fiumarg_rec11_undist, which a cap of 500 cut short at 4.89° of heading
                    error instead of 4.11°).
    """

    decrement_tol: float = 1e-6
    gradient_tol: float = 1e-3
    step_tol: float = 1e-9
    cost_tol: float = 1e-13
    max_iter: int = 2000


@dataclass(frozen=True)
class OptimizeReport:
    x: np.ndarray
    cost: float
    iterations: int
    cost_evaluations: int
    gradient_evaluations: int
    stopping_rule: str
    seconds: float
    history: list[float] = field(default_factory=list)
    #: times the Hessian approximation lost positive definiteness in floating point and
    #: was restarted from a scaled identity
    hessian_resets: int = 0

    #: evaluations of the Fisher information (trust region only)
    information_evaluations: int = 0
    #: the trust region's model matrix at x (in x's units): where a following fit of a
    #: related cost can start instead of evaluating the information again
    curvature: np.ndarray | None = None

    @property
    def converged(self) -> bool:
        return self.stopping_rule in CONVERGED_RULES


#: The stopping rules that certify a minimum: "gradient" (the scaled gradient and the
#: predicted decrease both small). BFGS's "step" (a step shorter than round-off with the
#: cost no longer decreasing) also counts for it, as its line search can stall only there.
CONVERGED_RULES = ("gradient", "step")


def _damped_bfgs_update(B: np.ndarray, s: np.ndarray, y: np.ndarray) -> np.ndarray:
    """B updated with the pair (s, y), Powell-damped where sᵀy < 0.2 sᵀBs so that B stays
    positive definite; unchanged for a step that carries no curvature (sᵀBs = 0)."""
    Bs = B @ s
    sBs = float(s @ Bs)
    if not sBs > 0.0:
        return B
    sy = float(s @ y)
    if sy < POWELL_DAMPING * sBs:
        theta = (1.0 - POWELL_DAMPING) * sBs / (sBs - sy)
        r = theta * y + (1.0 - theta) * Bs
    else:
        r = y
    B = B - np.outer(Bs, Bs) / sBs + np.outer(r, r) / float(s @ r)
    return 0.5 * (B + B.T)


def minimize_bfgs(
    fun_and_grad: Callable[[np.ndarray], tuple[float, np.ndarray]],
    x0: np.ndarray,
    scale: np.ndarray,
    options: OptimizeOptions = OptimizeOptions(),
    fun: Callable[[np.ndarray], float] | None = None,
    progress: Callable[[int, float, float], None] | None = None,
) -> OptimizeReport:
    """Minimise f from x0. ``scale`` (n,) are typical sizes of each variable's uncertainty;
    the iteration runs in z = (x − x₀)/scale, where BFGS starts best. ``fun`` (cost only)
    is used in the line search when given, as it is cheaper than cost + gradient.
    ``progress(iteration, cost, decrement)`` is called once per iteration."""
    t_start = time.perf_counter()
    x0 = np.asarray(x0, dtype=float)
    scale = np.asarray(scale, dtype=float)
    n = x0.size
    n_f = n_g = 0

    def fg(z):
        nonlocal n_f, n_g
        n_f += 1
        n_g += 1
        v, g = fun_and_grad(x0 + scale * z)
        return v, g * scale

    def f_only(z):
        nonlocal n_f
        n_f += 1
        return fun(x0 + scale * z)

    z = np.zeros(n)
    v, g = fg(z)
    if not np.isfinite(v) or not np.all(np.isfinite(g)):
        raise CalibrationError(
            "the ML cost is not finite at the initial estimate: the initial calibration is "
            "unusable (check units: gyroscope rad/s, accelerometer m/s²)"
        )
    B = np.eye(n)
    curvature = 1.0  # the Shanno–Phua scale, kept for restarts
    resets = 0
    first = True
    history = [v]
    rule = "max_iter"
    iteration = 0
    for iteration in range(1, options.max_iter + 1):
        try:
            L = np.linalg.cholesky(B)
        except np.linalg.LinAlgError:
            # Damped BFGS keeps B positive definite in exact arithmetic only: after a step
            # into a region of very high curvature (seen: eigenvalues 1e-3 to 1e18 when a
            # noise scale collapsed) rounding can break it. Restart, as L-BFGS would.
            resets += 1
            B = np.eye(n) * curvature
            L = np.linalg.cholesky(B)
        with np.errstate(over="ignore", invalid="ignore"):
            d = -np.linalg.solve(L.T, np.linalg.solve(L, g))
        if not np.all(np.isfinite(d)):
            # B positive definite but so ill-conditioned that its step overflows: restart
            # from the scaled identity, as for a B that stopped being positive definite.
            resets += 1
            B = np.eye(n) * curvature
            d = -g / curvature
        decrement = -0.5 * float(g @ d)
        if progress:
            progress(iteration, v, decrement)
        if decrement < options.decrement_tol and np.max(np.abs(g)) < options.gradient_tol:
            rule = "gradient"
            iteration -= 1
            break
        slope = float(g @ d)
        alpha = 1.0
        accepted = False
        for _ in range(MAX_BACKTRACKS):
            z_new = z + alpha * d
            if fun is not None:
                v_new = f_only(z_new)
                ok = np.isfinite(v_new) and v_new <= v + ARMIJO_C1 * alpha * slope
                if ok:
                    v_new, g_new = fg(z_new)
            else:
                v_new, g_new = fg(z_new)
                ok = np.isfinite(v_new) and v_new <= v + ARMIJO_C1 * alpha * slope
            if ok and np.all(np.isfinite(g_new)):
                accepted = True
                break
            # Quadratic interpolation of the step, kept within [0.1, 0.5] of the last one.
            if np.isfinite(v_new):
                denom = 2.0 * (v_new - v - alpha * slope)
                a_q = -slope * alpha * alpha / denom if denom > 0 else BACKTRACK_FACTOR * alpha
                alpha = float(np.clip(a_q, 0.1 * alpha, BACKTRACK_FACTOR * alpha))
            else:
                alpha *= 0.1
        if not accepted:
            rule = "line_search"
            break
        s = z_new - z
        y = g_new - g
        if first:
            # Shanno–Phua: scale the initial B to the curvature seen along the first step.
            sy = float(s @ y)
            if sy > 0:
                curvature = float(y @ y) / sy
                B = np.eye(n) * curvature
            first = False
        # A step the line search shrank to nothing (or below round-off) carries no
        # curvature: B stays, and the step rule below ends the run.
        B = _damped_bfgs_update(B, s, y)
        dv = v - v_new
        z, v, g = z_new, v_new, g_new
        history.append(v)
        if np.max(np.abs(s)) < options.step_tol and dv <= options.cost_tol * max(1.0, abs(v)):
            rule = "step"
            break
    return OptimizeReport(
        x=x0 + scale * z,
        cost=float(v),
        iterations=iteration,
        cost_evaluations=n_f,
        gradient_evaluations=n_g,
        stopping_rule=rule,
        seconds=time.perf_counter() - t_start,
        history=history,
        hessian_resets=resets,
    )


#: A trial step is accepted when it achieves at least this share of the decrease its model
#: predicted; the radius shrinks below TR_SHRINK_BELOW and grows above TR_GROW_ABOVE
#: (Nocedal & Wright, Algorithm 4.1).
TR_ACCEPT = 1e-4
TR_SHRINK_BELOW = 0.25
TR_GROW_ABOVE = 0.75
#: Accepted steps between two evaluations of the Fisher information, each of which costs
#: about ten to fourteen cost+gradient evaluations. On five real recordings of `make real`
#: (broad35, broad21, fiumarg_rec11_undist, tyrex_iphone5_d3, tyrex_iphone4s_d3; the three
#: fits of the ML step together) an evaluation every 5 steps took 24–63 iterations, every
#: 10 26–59, every 20 35–70, and only at the start of each fit 44–154; BFGS from the
#: identity takes 281–669 there.
INFORMATION_EVERY = 10
#: Radius below which no step can change the cost (scaled variables): the run ends there.
TR_MIN_RADIUS = 1e-10
#: How far the trapezoid rule with the gradients at a step's ends may miss the cost's change
#: along it, in units of that change (:func:`gradient_agrees`): loose enough for the
#: third-order error of any step the region allows, far below the misses of a derivative
#: that has become rounding noise (10⁴⁹ on fiumarg_rec11_full, forced).
GRADIENT_AGREEMENT = 10.0


def trust_region_step(
    B: np.ndarray, g: np.ndarray, radius: float, weight: np.ndarray | None = None
) -> np.ndarray:
    """The minimiser of gᵀs + ½ sᵀBs over ‖weight ⊙ s‖ ≤ radius (B symmetric, not
    necessarily definite; ``weight`` (n,) > 0, ones by default): the Newton step when it
    fits, else (B + μW²)⁻¹(−g) with μ ≥ max(0, −λ_min) on the boundary, found by Newton's
    method on 1/‖s(μ)‖ (Moré & Sorensen) in the eigenbasis of W⁻¹BW⁻¹. The hard case (g
    orthogonal to the lowest eigenvector) is treated as its limit."""
    if weight is not None:
        B = B / np.outer(weight, weight)
        g = g / weight
        return trust_region_step(B, g, radius) / weight
    lam, Q = np.linalg.eigh(B)
    gq = Q.T @ g
    if lam[0] > 0.0:
        s = -gq / lam
        if np.linalg.norm(s) <= radius:
            return Q @ s
    # μ is kept in a bracket [lo, hi] with ‖s(μ)‖ ≥ radius at lo and ≤ radius at hi; for
    # μ ≥ max(0, −λ_min) + ‖g‖/radius every denominator is at least ‖g‖/radius, so hi starts
    # feasible. Newton steps on φ(μ) = 1/‖s(μ)‖ − 1/radius (nearly linear in μ) where they
    # stay inside, bisection where they do not or where rounding makes them meaningless.
    lo = max(0.0, -float(lam[0]))
    hi = lo + float(np.linalg.norm(gq)) / radius
    mu = hi
    with np.errstate(all="ignore"):
        for _ in range(100):
            d = lam + mu
            s = -gq / d
            norm = float(np.linalg.norm(s))
            if norm > radius:
                lo = mu
            else:
                hi = mu
            if abs(norm - radius) <= 1e-6 * radius:
                return Q @ (s * min(1.0, radius / norm))
            if hi - lo <= 1e-15 * max(hi, 1.0):
                break
            dphi = float(np.sum(gq**2 / d**3)) / norm**3
            mu_next = mu - (1.0 / norm - 1.0 / radius) / dphi
            mu = mu_next if np.isfinite(mu_next) and lo < mu_next < hi else 0.5 * (lo + hi)
        s = -gq / (lam + hi)  # the feasible end of the bracket
    return Q @ s


def minimize_trust_region(
    fun_grad_info: Callable[[np.ndarray], tuple[float, np.ndarray, np.ndarray]],
    fun_and_grad: Callable[[np.ndarray], tuple[float, np.ndarray]],
    fun: Callable[[np.ndarray], float],
    x0: np.ndarray,
    scale: np.ndarray,
    typical_change: np.ndarray,
    options: OptimizeOptions = OptimizeOptions(),
    progress: Callable[[int, float, float], None] | None = None,
    held: np.ndarray | None = None,
    curvature: np.ndarray | None = None,
) -> OptimizeReport:
    """Minimise f from x0 in the scaled variables z = (x − x₀)/scale.

    The trust region bounds ‖Δx / typical_change‖: ``typical_change`` (n,) is the size of a
    large but sane change of each variable in one step, and the first region has radius 1.
    A Gauss–Newton step from a poor start can ask for far more (a noise scale shrunk by
    orders of magnitude, where the cost is finite but its gradient explodes), and a region
    in the statistical scale alone would let the first step take it.

    ``fun_grad_info(x)`` gives f, its gradient and a positive semi-definite curvature (the
    Fisher information with the priors' Hessian); ``fun_and_grad`` and ``fun`` the cheaper
    parts. The model's matrix is that curvature at the start, at every
    :data:`INFORMATION_EVERY`-th accepted step and where the updates lost definiteness to
    rounding, and a damped BFGS update of it in between. Converged ("gradient") only when
    the largest scaled gradient component is below ``gradient_tol`` *and* the predicted
    decrease ½ gᵀB⁻¹g below ``decrement_tol``; "max_iter" and "radius" (the trust region
    shrank to nothing, or the model overflowed, without meeting them) are reported as not
    converged.

    ``held`` (n,) bool: variables kept at x0. The steps and the convergence test see only
    the others, while the model keeps its curvature along the held ones, learnt from their
    gradient, so that a following fit that frees them starts from the whole model
    (``curvature``: that fit's :attr:`OptimizeReport.curvature`, used at x0 in place of a
    first evaluation of the information)."""
    t_start = time.perf_counter()
    x0 = np.asarray(x0, dtype=float)
    scale = np.asarray(scale, dtype=float)
    n = x0.size
    counts = {"f": 0, "g": 0, "i": 0}
    S = np.outer(scale, scale)
    free = np.ones(n, dtype=bool) if held is None else ~np.asarray(held, dtype=bool)

    def on_free(B: np.ndarray, g: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        # A held variable: no gradient, no coupling, unit curvature, so that the model is
        # definite and its steps are exactly zero there.
        if free.all():
            return B, g
        B = np.where(np.outer(free, free), B, 0.0)
        B[~free, ~free] = 1.0
        return B, np.where(free, g, 0.0)

    def fgi(z):
        counts["f"] += 1
        counts["g"] += 1
        counts["i"] += 1
        v, g, F = fun_grad_info(x0 + scale * z)
        return v, g * scale, F * S

    def fg(z):
        counts["f"] += 1
        counts["g"] += 1
        v, g = fun_and_grad(x0 + scale * z)
        return v, g * scale

    def f_only(z):
        counts["f"] += 1
        return fun(x0 + scale * z)

    z = np.zeros(n)
    if curvature is None:
        v, g, B = fgi(z)
    else:
        (v, g), B = fg(z), np.asarray(curvature, dtype=float) * S
    if not np.isfinite(v) or not np.all(np.isfinite(g)):
        raise CalibrationError(
            "the ML cost is not finite at the initial estimate: the initial calibration is "
            "unusable (check units: gyroscope rad/s, accelerometer m/s²)"
        )
    weight = scale / np.asarray(typical_change, dtype=float)
    since_information = 0
    radius = 1.0
    history = [v]
    rule = "max_iter"
    iteration = 0
    for iteration in range(1, options.max_iter + 1):
        B_free, g_free = on_free(B, g)
        decrement = _decrement(B_free, g_free)
        if not np.isfinite(decrement) and since_information > 0:
            # The updates lost B's definiteness to rounding (curvatures spanning many
            # orders of magnitude): start again from the information here.
            v, g, B = fgi(z)
            since_information = 0
            B_free, g_free = on_free(B, g)
            decrement = _decrement(B_free, g_free)
        if progress:
            progress(iteration, v, decrement)
        if decrement < options.decrement_tol and np.max(np.abs(g_free)) < options.gradient_tol:
            rule = "gradient"
            iteration -= 1
            break
        with np.errstate(all="ignore"):
            s = trust_region_step(B_free, g_free, radius, weight)
        if not np.all(np.isfinite(s)):
            # The model overflowed (curvatures beyond the floating-point range far from any
            # optimum): nothing to try at this radius.
            rule = "radius"
            break
        norm_s = float(np.linalg.norm(weight * s))
        predicted = -float(g_free @ s + 0.5 * s @ B_free @ s)
        # The trial point's cost, with its gradient where an accepted step would need that
        # next (every step but one that refreshes the information): nearly every step is
        # accepted, and a cost+gradient pass costs about three cost passes where a cost
        # pass and then a cost+gradient pass cost four. Both passes give the same cost, to
        # the bit, so the steps are those of a cost-only trial.
        refresh = since_information + 1 >= INFORMATION_EVERY
        if refresh:
            v_new, g_trial = f_only(z + s), None
        else:
            v_new, g_trial = fg(z + s)
        rho = (v - v_new) / predicted if np.isfinite(v_new) and predicted > 0.0 else -np.inf
        accepted = rho >= TR_ACCEPT
        if accepted:
            since_information += 1
            if refresh:
                v_new, g_new, B_new = fgi(z + s)
            else:
                g_new = g_trial
            # A point where the gradient is not finite, or does not agree with the cost
            # along the step just taken (a covariance at the edge of breaking down, where
            # the cost is still finite but its derivatives are rounding noise), is no
            # place to continue from, whatever its cost: the step fails.
            accepted = gradient_agrees(v, g, v_new, g_new, s, predicted)
            if not accepted:
                rho = -np.inf
        if accepted:
            if refresh:
                B, since_information = B_new, 0
            else:
                B = _damped_bfgs_update(B, s, g_new - g)
            z, v, g = z + s, v_new, g_new
            history.append(v)
        if not accepted and since_information > 0:
            # The step failed on a model partly learnt elsewhere: the information here
            # first, before any smaller step (a cost whose curvature grew by orders of
            # magnitude since the last evaluation, as when the noise levels fall from a
            # conservative start, otherwise costs a collapse of the region and its regrowth).
            v, g, B = fgi(z)
            since_information = 0
        if rho < TR_SHRINK_BELOW:
            radius = 0.25 * norm_s
        elif rho > TR_GROW_ABOVE and norm_s >= 0.9 * radius:
            radius = 2.0 * radius
        if radius < TR_MIN_RADIUS:
            rule = "radius"
            break
    return OptimizeReport(
        x=x0 + scale * z,
        cost=float(v),
        iterations=iteration,
        cost_evaluations=counts["f"],
        gradient_evaluations=counts["g"],
        stopping_rule=rule,
        seconds=time.perf_counter() - t_start,
        history=history,
        information_evaluations=counts["i"],
        curvature=B / S,
    )


def gradient_agrees(
    v: float, g: np.ndarray, v_new: float, g_new: np.ndarray, s: np.ndarray, predicted: float
) -> bool:
    """Whether the gradient at the end of step ``s`` is finite and agrees with the cost: the
    trapezoid rule ½ (g + g_new)·s matches the cost's change v_new − v to within
    :data:`GRADIENT_AGREEMENT` times the larger of that change and the predicted decrease.
    A smooth cost meets it for any step a trust region accepts; rounding noise in a
    derivative misses it by orders of magnitude."""
    if not np.all(np.isfinite(g_new)):
        return False
    change = v_new - v
    secant = 0.5 * float((g + g_new) @ s)
    return abs(secant - change) <= GRADIENT_AGREEMENT * max(abs(change), abs(predicted))


def _decrement(B: np.ndarray, g: np.ndarray) -> float:
    """½ gᵀB⁻¹g, the decrease the quadratic model predicts for its Newton step; inf where B
    is not positive definite (the model has no minimum: not converged)."""
    try:
        L = np.linalg.cholesky(B)
    except np.linalg.LinAlgError:
        return np.inf
    w = np.linalg.solve(L, g)
    return 0.5 * float(w @ w)
