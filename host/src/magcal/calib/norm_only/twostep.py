# SPDX-License-Identifier: Apache-2.0
"""TWO-STEP: attitude-independent calibration from the field norm (Alonso & Shuster 2002).

R. Alonso, M. D. Shuster, *TWOSTEP: A Fast Robust Algorithm for Attitude-Independent
Magnetometer-Bias Determination*, J. Astronaut. Sci. 50(4), 433–451, 2002, and its extension
to the full linear model, *Complete Linear Attitude-Independent Magnetometer Calibration*,
J. Astronaut. Sci. 50(4), 477–490, 2002. What is implemented (their notation):

Model. ``B_k = (I + D)⁻¹ (Oᵀ H_k + b + ε_k)``, ``D`` symmetric, ``ε_k ~ N(0, Σ)``, a field
of known magnitude ``|H_k|``. With ``E = 2D + D²`` and ``c = (I + D) b`` the scalar
measurement is linear in ``θ = [c; E11 E22 E33 E12 E13 E23]`` but for one term:

    z_k = |B_k|² − |H_k|² = L_k θ − |b(θ)|² + v_k,
    L_k = [2 B_kᵀ, −B1², −B2², −B3², −2B1B2, −2B1B3, −2B2B3],  |b|² = cᵀ (I + E)⁻¹ c,

with ``v_k`` of mean ``μ_k = −tr Σ`` and variance
``σ_k² = 4 ((I + D) B_k − b)ᵀ Σ ((I + D) B_k − b) + 2 tr(Σ²)`` (Gaussian ε; the papers'
Gaussian approximation of ``v_k``).

1. **Centred estimate.** Subtracting the weighted means (weights ``1/σ_k²``,
   ``σ̄² = 1/Σ σ_k⁻²``, ``x̄ = σ̄² Σ x_k/σ_k²``) removes the nonlinear term, which is the same
   for every sample: ``θ̃* = F̃⁻¹ Σ L̃_kᵀ (z̃_k − μ̃_k)/σ_k²`` with the centred Fisher
   information ``F̃ = Σ L̃_kᵀ L̃_k / σ_k²``.
2. **Centre correction.** Fisher scoring (Gauss–Newton) on the full cost
   ``J(θ) = ½ (θ − θ̃*)ᵀ F̃ (θ − θ̃*) + ½ (z̄ − μ̄ − L̄θ + |b(θ)|²)² / σ̄²`` from ``θ = 0``
   (magcal's start: see :func:`_estimate`):
   ``θ ← θ − α (F̃ + F̄)⁻¹ ∇J``, ``F̄ = (L̄ − ∂|b|²/∂θ)ᵀ (L̄ − ∂|b|²/∂θ) / σ̄²``, until the step's
   ``ΔθᵀFΔθ`` is below :data:`STEP_TOL` (a tiny fraction of one standard deviation).
   ``α`` is 1 halved until J does not increase (magcal's addition: the papers' undamped
   step overshoots and wanders when the noise is large beside the field). Known limit: when
   the noise is large beside the field (Zhao et al.'s Table 2, σ ≈ 20 %), J keeps falling
   towards ``θ̃* = [0; −I]``, where the ellipsoid shrinks to a point; the run ends at
   :data:`MAX_ITER` unconverged, with a warning, and the estimate is no use.

Then ``E = U S Uᵀ``, ``D = U (√(1 + S) − 1) Uᵀ`` and ``b = (I + D)⁻¹ c``. In magcal's terms the
calibrated field is ``(I + D) B − b``, so ``A = Tᵀ T`` with ``T = (I + D)`` (in the
coordinates below): ``A = I + E`` and ``o = (I + E)⁻¹ c``.

magcal's choices:

* ``|H| = 1`` (the field norm the result is normalised to) in coordinates
  ``B = (y − ȳ)/s``, ``s`` the readings' RMS distance from their mean: the problem is O(1)
  whatever the unit, and exactly invariant to the data's scale and offset.
* ``Σ = σ² I`` with σ from second differences of the readings
  (:func:`~magcal.calib.initial.rest.white_noise_std`), unless given.
* The weights ``σ_k²`` depend on ``D`` and ``b``. They are evaluated at the a-priori
  ``D = 0, b = 0`` for a first centred estimate, then once more at that estimate for the
  final centred estimate (with a field of constant norm they become nearly equal, as they
  should).

As for the CKF, ``D`` is symmetric: the rotation between magnetometer and inertial axes comes
from Algorithm 1's alignment step (``pipeline.py``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from magcal.calib.initial import rest
from magcal.calib.initial.ellipsoid import EllipsoidFit
from magcal.calib.norm_only import norm_ellipsoid
from magcal.errors import InsufficientDataError

#: Fisher-scoring iteration cap.
MAX_ITER = 50
#: Step halvings tried per Fisher-scoring step before giving up (2⁻³⁰ of the step: below
#: float64's resolution of J near its minimum).
MAX_HALVINGS = 30
#: A step is accepted when it raises J by at most this fraction of J: J's rounding, so the
#: last steps, whose change of J float64 cannot resolve, are taken as the papers' are.
COST_RTOL = 1e-12
#: Stop when the step's ``ΔθᵀFΔθ`` (its size in standard deviations, squared) is below this.
STEP_TOL = 1e-16
#: ``F̃`` with a second-smallest/largest eigenvalue ratio below this does not determine θ
#: (data on a plane or a line); also the cut-off of the centred estimate's pseudo-inverse.
MIN_FISHER_RATIO = 1e-12
#: With ``force`` on such data, ``F̃`` gets this ridge (relative to its mean eigenvalue),
#: which pulls the undetermined directions towards ``D = 0, b = 0``: a sphere about the
#: readings' mean.
FORCED_RIDGE = 1e-3
#: σ is at least this fraction of the field (noise-free data).
MIN_NOISE_FRACTION = 1e-9


@dataclass(frozen=True, eq=False)
class TwoStepFit:
    """TWO-STEP's estimate in raw units.

    A          : (3, 3) float, (raw units)⁻², ``(y − b)ᵀ A (y − b) = 1`` on the ellipsoid
    b          : (3,) float, raw units, the offset
    theta      : (9,) float, ``[c, E11, E22, E33, E12, E13, E23]`` in the normalised
                 coordinates (centre ``centre``, scale ``scale``)
    theta_cov  : (9, 9) float, the inverse Fisher information at the estimate (same
                 coordinates)
    iterations : Fisher-scoring steps taken
    converged  : the step fell below :data:`STEP_TOL` before :data:`MAX_ITER`
    noise_std  : float, raw units, the σ used
    warnings   : tuple of str (forced regularisation, no convergence)
    costs      : the centre correction's cost J (module docstring) at its start (θ = 0)
                 and after each accepted step of the final pass: non-increasing (step
                 halving), the last being the returned θ's
    """

    A: np.ndarray
    b: np.ndarray
    theta: np.ndarray
    theta_cov: np.ndarray
    centre: np.ndarray
    scale: float
    iterations: int
    converged: bool
    noise_std: float
    warnings: tuple[str, ...] = ()
    costs: tuple[float, ...] = ()


def _design(B: np.ndarray) -> np.ndarray:
    """``L_k`` rows (N, 9)."""
    b0, b1, b2 = B.T
    return np.column_stack(
        [2.0 * B, -b0 * b0, -b1 * b1, -b2 * b2, -2.0 * b0 * b1, -2.0 * b0 * b2, -2.0 * b1 * b2]
    )


def _sym(e: np.ndarray) -> np.ndarray:
    return np.array([[e[0], e[3], e[4]], [e[3], e[1], e[5]], [e[4], e[5], e[2]]])


def _offset(theta: np.ndarray) -> np.ndarray:
    """``o = (I + E)⁻¹ c`` (3,), normalised coordinates: the point the calibrated field
    ``(I + D) B − b`` is centred on, since ``(I + D)⁻¹ b = (I + D)⁻² c``."""
    return np.linalg.solve(np.eye(3) + _sym(theta[3:]), theta[:3])


def _bsq_and_grad(theta: np.ndarray) -> tuple[float, np.ndarray]:
    """``|b|² = cᵀ (I + E)⁻¹ c`` and its gradient w.r.t. θ (9,).

    With ``g = (I + E)⁻¹ c`` (the offset, :func:`_offset`): ``|b|² = cᵀg``, ``∂/∂c = 2g``,
    ``∂/∂E_ii = −g_i²``, ``∂/∂E_ij = −2 g_i g_j`` (i < j: each off-diagonal parameter
    appears twice in E).
    """
    g = _offset(theta)
    grad = np.concatenate(
        [2.0 * g, -g * g, [-2.0 * g[0] * g[1], -2.0 * g[0] * g[2], -2.0 * g[1] * g[2]]]
    )
    return float(theta[:3] @ g), grad


def _weights(B: np.ndarray, theta: np.ndarray | None, sigma2: float) -> np.ndarray:
    """``σ_k²`` (N,) for ``Σ = σ² I`` at θ (None: the a priori ``D = 0, b = 0``)."""
    if theta is None:
        m = B
    else:
        E = _sym(theta[3:])
        lam, U = np.linalg.eigh(np.eye(3) + E)
        root = (U * np.sqrt(np.clip(lam, 0.0, None))) @ U.T  # I + D
        b = np.linalg.solve(root, theta[:3])
        m = B @ root - b  # root symmetric: rows (I + D) B_k − b
    return 4.0 * sigma2 * np.einsum("ij,ij->i", m, m) + 6.0 * sigma2 * sigma2


def _centred(L, z, var, ridge):
    """Weighted centring and the centred estimate: (θ̃*, F̃, L̄, z̄, σ̄²)."""
    w = 1.0 / var
    var_bar = 1.0 / float(w.sum())
    L_bar = var_bar * (w @ L)
    z_bar = var_bar * float(w @ z)
    Lc = L - L_bar
    F = (Lc * w[:, None]).T @ Lc
    F = 0.5 * (F + F.T)
    if ridge:
        F = F + ridge * np.trace(F) / 9.0 * np.eye(9)
    # With a field of constant norm the centred problem cannot see the field's scale (the
    # readings' own quadric is a null vector of F̃ when noise-free): the minimum-norm
    # solution here, and the centre correction fixes that direction.
    theta = np.linalg.lstsq(F, (Lc * w[:, None]).T @ (z - z_bar), rcond=MIN_FISHER_RATIO)[0]
    return theta, F, L_bar, z_bar, var_bar


def _cost(theta, theta_c, F_c, L_bar, z_bar, mu, var_bar) -> float:
    """The centre correction's cost ``J(θ)`` (module docstring, step 2); inf where
    ``I + E`` is singular (``|b|²`` undefined)."""
    try:
        bsq = _bsq_and_grad(theta)[0]
    except np.linalg.LinAlgError:
        return np.inf
    d = theta - theta_c
    resid = z_bar - mu - L_bar @ theta + bsq
    cost = 0.5 * float(d @ F_c @ d) + 0.5 * resid * resid / var_bar
    return cost if np.isfinite(cost) else np.inf


def _estimate(L, z, mu, var, ridge):
    """Step 1 (centred estimate) and step 2 (Fisher scoring) with weights ``1/var``:
    (θ, F at θ, iterations, converged, costs: J at the start and after each step)."""
    theta_c, F_c, L_bar, z_bar, var_bar = _centred(L, z, var, ridge)
    # Start from the a-priori sphere (D = 0, b = 0: |B| = 1 about the readings' mean), not
    # from θ̃*: with noise F̃ has no exact null direction and θ̃* is then [0; −I] exactly
    # (L_k [0; −I] = |B_k|² = z_k + 1 for any data), where I + E = 0 and |b|² is undefined.
    theta = np.zeros(9)
    cost = _cost(theta, theta_c, F_c, L_bar, z_bar, mu, var_bar)
    costs = [cost]
    iterations, converged = 0, False
    while iterations < MAX_ITER and not converged:
        iterations += 1
        bsq, dbsq = _bsq_and_grad(theta)
        lin = L_bar - dbsq
        resid = z_bar - mu - L_bar @ theta + bsq
        grad = F_c @ (theta - theta_c) - resid * lin / var_bar
        F = F_c + np.outer(lin, lin) / var_bar
        step = np.linalg.solve(F, grad)
        if float(step @ F @ step) < STEP_TOL:
            # At the minimum to rounding: J's change is below what float64 resolves.
            theta = theta - step
            converged = True
            break
        # Step halving: the Gauss–Newton step is a descent direction of J (F positive
        # definite) but far from the minimum, where |b(θ)|² is strongly nonlinear (noise of
        # 20 % of the field), the full step can overshoot and undamped scoring then wanders.
        # Every accepted iterate lowers J (to rounding), so the last is the lowest seen.
        for _ in range(MAX_HALVINGS + 1):
            trial = theta - step
            trial_cost = _cost(trial, theta_c, F_c, L_bar, z_bar, mu, var_bar)
            if trial_cost <= cost + COST_RTOL * abs(cost):
                break
            step = 0.5 * step
        else:
            break  # no lower J along the step: a minimum to rounding, or a stall (warned)
        theta, cost = trial, trial_cost
        costs.append(cost)
    bsq, dbsq = _bsq_and_grad(theta)
    lin = L_bar - dbsq
    F = F_c + np.outer(lin, lin) / var_bar
    return theta, 0.5 * (F + F.T), iterations, converged, tuple(costs)


def _real(theta: np.ndarray) -> bool:
    """Whether ``I + E`` is positive definite (a real ellipsoid)."""
    return bool(np.linalg.eigvalsh(np.eye(3) + _sym(theta[3:]))[0] > 0.0)


def two_step(mag: np.ndarray, *, noise_std: float | None = None, force: bool = False) -> TwoStepFit:
    """TWO-STEP on raw readings (see the module docstring).

    mag       : (N, 3) float, raw magnetometer units
    noise_std : σ of each axis' white noise, raw units (default: from second differences)
    force     : on readings that do not determine the ellipsoid (data on a plane or a line),
                regularise towards a sphere with a warning instead of raising
                InsufficientDataError

    Returns a :class:`TwoStepFit` in raw units.
    """
    mag = norm_ellipsoid.check_readings(mag, "two-step")
    centre = mag.mean(axis=0)
    scale = float(np.sqrt(np.mean(np.sum((mag - centre) ** 2, axis=1))))
    if not scale > 0.0:
        raise InsufficientDataError(
            "two-step: all magnetometer samples are identical: check that the magnetometer is "
            "working and rotate the sensor through all orientations"
        )
    B = (mag - centre) / scale
    sigma = rest.white_noise_std(mag) if noise_std is None else noise_std
    sigma = max(float(sigma), MIN_NOISE_FRACTION * scale)
    sigma2 = (sigma / scale) ** 2
    L = _design(B)
    z = np.einsum("ij,ij->i", B, B) - 1.0
    mu = -3.0 * sigma2  # tr Σ, the same for every sample: it centres away but for z̄ − μ̄

    warnings: list[str] = []
    ridge = 0.0
    # The centred information F̃ has one null direction by nature (the field's scale, see
    # _centred), which the centre correction fixes; a second one means the readings do not
    # determine the ellipsoid, and so do readings close to a plane.
    Lc = L - L.mean(axis=0)
    eig = np.linalg.eigvalsh(Lc.T @ Lc)
    problem = norm_ellipsoid.planarity_problem(mag, "two-step")
    if problem is None and not eig[1] > MIN_FISHER_RATIO * eig[-1]:
        problem = (
            "two-step: the readings do not determine the ellipsoid (Fisher information "
            f"eigenvalue ratio {eig[1] / eig[-1]:.2g} < {MIN_FISHER_RATIO:g}): the sensor was "
            "rotated too little; rotate it through all orientations (tilt it nose up/down and "
            "roll it over, not only yaw)"
        )
    if problem is not None:
        if not force:
            raise InsufficientDataError(problem)
        ridge = FORCED_RIDGE
        warnings.append(
            f"{problem}. Forced: regularised towards a sphere, so the scale and offset along "
            "the directions the data do not cover are guesses"
        )

    # Both steps with weights at the a priori, then again with weights at that estimate.
    theta, F, iterations, converged, costs = _estimate(L, z, mu, _weights(B, None, sigma2), ridge)
    if _real(theta):
        theta, F, iterations, converged, costs = _estimate(
            L, z, mu, _weights(B, theta, sigma2), ridge
        )
    if not converged:
        warnings.append(
            f"two-step: the centre correction did not converge ({iterations} Fisher-scoring "
            "steps with step halving; the lowest-cost estimate is kept): the estimate may be "
            "poor; check that the readings cover all orientations and the noise is small "
            "beside the field"
        )
    A_n = np.eye(3) + _sym(theta[3:])  # (I + D)² = I + E
    return TwoStepFit(
        A=A_n / scale**2,
        b=centre + scale * _offset(theta),
        theta=theta,
        theta_cov=np.linalg.inv(F),
        centre=centre,
        scale=scale,
        iterations=iterations,
        converged=converged,
        noise_std=sigma,
        warnings=tuple(warnings),
        costs=costs,
    )


def calibration_ellipsoid(mag: np.ndarray, *, force: bool = False) -> tuple[EllipsoidFit, dict]:
    """The session's ellipsoid by TWO-STEP in Algorithm 1's form, for the alignment step, and
    what the result file records about the run (JSON-ready dict)."""
    ts = two_step(mag, force=force)
    fit = norm_ellipsoid.ellipsoid_fit_from(ts.A, ts.b, mag, "two-step", ts.warnings)
    details = {
        "A": ts.A.tolist(),
        "b": ts.b.tolist(),
        "iterations": ts.iterations,
        "converged": ts.converged,
        "noise_std": ts.noise_std,
    }
    return fit, details
