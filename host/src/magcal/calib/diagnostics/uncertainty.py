# SPDX-License-Identifier: Apache-2.0
"""Uncertainty of a calibration: the inverse Hessian of the ML cost at the estimate.

For many samples the ML estimate θ̂ is close to Gaussian around the truth with covariance
H⁻¹, H = ∂²V/∂θ² at θ̂ (the observed Fisher information; V is eq. 6's negative
log-likelihood plus the gyroscope noise prior, i.e. the cost the optimiser minimised, as
``likelihood/problem.py`` builds it). Quantities derived from θ (D⁻¹, the misalignment
angles, the dip in degrees) get their standard deviations by linearisation, σ² = J H⁻¹ Jᵀ.

How H is computed, and why:

* **Central differences of the exact gradient**, column i being
  ``(∇V(θ + hᵢeᵢ) − ∇V(θ − hᵢeᵢ)) / 2hᵢ``: 2·n_θ = 68 reverse-mode passes, about a second on
  a 10-minute session. n_θ is small, so this is cheap, and since each gradient is exact to
  rounding, the only error is the O(h²) truncation, negligible at steps of a hundredth of a
  standard deviation (:data:`HESSIAN_STEP_FRACTION`). Second differences of V itself would
  need ≈ 2·n_θ² ≈ 2,300 passes and lose half the digits to cancellation (error ∝ ε/h²); an
  exact Hessian (reverse over reverse through the filter) would need a second hand-derived
  adjoint of the C kernel for what is here one second of run time; and BFGS's inverse-Hessian
  approximation is only accurate along the directions the search happened to explore.
* In the **scaled variables** z = θ / s (s: each parameter's expected σ,
  ``problem.parameter_scales``) H's eigenvalues are of order one, so "not positive definite" and
  "nearly singular" can be judged against a relative threshold, and a direction of
  (near-)zero curvature is reported as *not identifiable*, with the parameters it moves.
* The **calibration's quantities are judged apart from the noise model's** (the Cholesky
  parameters of Σ_ω, Σ_a, Σ_m), each with the other marginalised
  (:func:`marginal_covariance`): a direction that only the noise model leaves free (on a
  hand-held recording whose accelerations switch most accelerometer updates off, Σ_a's
  correlations) leaves D, o and the rest as determined as they are. Read off the
  eigenvectors of the whole Hessian instead, such a direction carries components of a
  percent on D and o (less than a nearly singular eigenvector is resolved to, yet enough
  to mark them unbounded), and a calibration the data determine to hundredths of a degree
  came out "not identifiable".
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import scipy.linalg

from magcal.calib import frames
from magcal.calib.diagnostics import replay
from magcal.calib.likelihood import params
from magcal.calib.likelihood.problem import LikelihoodProblem, Normalisation, Priors
from magcal.errors import CalibrationError
from magcal.io.result import CalibrationResult
from magcal.io.session import Session

#: Central-difference step, as a fraction of each parameter's expected σ. The gradient is
#: exact, so the step only has to be small against the scale on which the cost stops being
#: quadratic (many σ) and large against rounding: H's entries agree to < 1e-4 (relative to
#: the largest) for fractions from 1e-3 to 1e-1 on simulated sessions.
HESSIAN_STEP_FRACTION = 1e-2
#: A scaled Hessian eigenvalue at or below this fraction of the largest is a direction the
#: data do not determine. Measured on simulated sessions (``mems``, ``handheld``, ``table2``,
#: ``raw-counts``): the smallest eigenvalue is 1e-3 to 3e-2 of the largest when every
#: parameter is determined, and below 1e-5 along the directions yaw-only or small motion
#: leaves free (a standard deviation over 300 times the expected one).
IDENTIFIABILITY_RTOL = 1e-5
#: A derived quantity is "not identifiable" when a non-identifiable direction (unit vector in
#: scaled variables) moves it by more than this fraction of its total sensitivity: in
#: theory any share makes its variance unbounded; rounding in the eigenvectors is ~1e-6.
NULL_LOADING_RTOL = 1e-4
#: Step of the linearisation of derived quantities, as a fraction of each expected σ.
JACOBIAN_STEP_FRACTION = 1e-4
#: A point whose Newton step to the cost's minimum is longer than this many standard
#: deviations is not the ML estimate: its curvature does not describe an estimate's spread.
AT_MINIMUM_NEWTON_STEP_SIGMA = 1.0
#: Components smaller than this (unit eigenvector) are left out of a direction's text.
DIRECTION_TEXT_MIN = 0.1

#: Derived quantities and their shapes (units: see :func:`derived_quantities`).
QUANTITIES: tuple[tuple[str, tuple[int, ...]], ...] = (
    ("D", (3, 3)),
    ("D_inv", (3, 3)),
    ("o", (3,)),
    ("misalignment_deg", (3,)),
    ("misalignment_angle_deg", ()),
    ("dip_deg", ()),
    ("m_n", (3,)),
    ("gyro_bias", (3,)),
    ("noise_std_gyr", (3,)),
    ("noise_std_acc", (3,)),
    ("noise_std_mag", (3,)),
    ("time_offset_s", ()),
)


# --------------------------------------------------------------------------------------------
# Generic numerics


def central_difference_hessian(
    gradient: Callable[[np.ndarray], np.ndarray],
    x: np.ndarray,
    steps: np.ndarray,
    progress: Callable[[int, int], None] | None = None,
) -> np.ndarray:
    """Symmetric Hessian (n, n) by central differences of an exact ``gradient`` (n,) → (n,).

    steps    : (n,) step per coordinate, in x's units
    progress : called as ``progress(done, total)`` after each gradient evaluation
    Raises :class:`CalibrationError` when a gradient is not finite.
    """
    x = np.asarray(x, dtype=float)
    steps = np.asarray(steps, dtype=float)
    n = x.size
    H = np.empty((n, n))
    total = 2 * n
    for i in range(n):
        hi, lo = x.copy(), x.copy()
        hi[i] += steps[i]
        lo[i] -= steps[i]
        g_hi = np.asarray(gradient(hi), dtype=float)
        if progress:
            progress(2 * i + 1, total)
        g_lo = np.asarray(gradient(lo), dtype=float)
        if progress:
            progress(2 * i + 2, total)
        if not (np.isfinite(g_hi).all() and np.isfinite(g_lo).all()):
            raise CalibrationError(
                f"Hessian: the gradient is not finite at a step of coordinate {i}: the point "
                "is not a usable estimate (the filter breaks down next to it)"
            )
        # hi[i] − lo[i] rather than 2·steps[i]: the step as actually represented.
        H[:, i] = (g_hi - g_lo) / (hi[i] - lo[i])
    return 0.5 * (H + H.T)


@dataclass(frozen=True)
class HessianCovariance:
    """The inverse of a Hessian on the subspace where it is positive definite.

    cov              : (n, n), x's units²; zero curvature directions are left out (see
                       ``null_directions``: the variance along them is unbounded)
    null_directions  : (k, n) unit vectors in the scaled variables x / scales along which
                       the Hessian is not positive definite (k = 0: identifiable)
    null_eigenvalues : (k,) their scaled curvature (≤ ``rtol`` × the largest)
    scales           : (n,) the scaling used
    eigenvalues      : (n,) all scaled eigenvalues, ascending
    """

    cov: np.ndarray
    null_directions: np.ndarray
    null_eigenvalues: np.ndarray
    scales: np.ndarray
    eigenvalues: np.ndarray

    @property
    def identifiable(self) -> bool:
        return self.null_directions.shape[0] == 0


def covariance_from_hessian(
    H: np.ndarray,
    scales: np.ndarray,
    rtol: float = IDENTIFIABILITY_RTOL,
    largest: float | None = None,
) -> HessianCovariance:
    """H⁻¹ (n, n) via the eigendecomposition of the scaled Hessian ``S H S``.

    scales  : (n,) positive, about each coordinate's σ, so that S H S is of order one.
    largest : the scaled eigenvalue ``rtol`` is relative to; default S H S's largest. A block
              of a Hessian passes the whole one's: the finite differences are accurate
              relative to that, not to the block's.
    """
    scales = np.asarray(scales, dtype=float)
    lam, V = np.linalg.eigh(_scaled(H, scales))
    top = float(lam.max()) if largest is None else float(largest)
    good = lam > rtol * top if top > 0.0 else np.zeros_like(lam, bool)
    Cz = (V[:, good] / lam[good]) @ V[:, good].T
    return HessianCovariance(
        cov=scales[:, None] * Cz * scales[None, :],
        null_directions=V[:, ~good].T.copy(),
        null_eigenvalues=lam[~good].copy(),
        scales=scales,
        eigenvalues=lam,
    )


def _scaled(H: np.ndarray, scales: np.ndarray) -> np.ndarray:
    """S H S, symmetrised."""
    Hz = scales[:, None] * np.asarray(H, dtype=float) * scales[None, :]
    return 0.5 * (Hz + Hz.T)


def is_noise_model_parameter(name: str) -> bool:
    """Whether θ's component ``name`` (:data:`params.PARAM_NAMES`) describes the noise model
    (a covariance's Cholesky parameter) rather than the calibration."""
    return name.startswith("chol_")


def marginal_covariance(
    H: np.ndarray, scales: np.ndarray, keep: np.ndarray, rtol: float = IDENTIFIABILITY_RTOL
) -> HessianCovariance:
    """The covariance of the coordinates ``keep`` ((n,) bool) with the others marginalised:
    the inverse of the Schur complement ``H_kk − H_ko H_oo⁺ H_ok``, H_oo⁺ the inverse of the
    others' block on the directions where it curves (:func:`covariance_from_hessian`). Both
    blocks judge "curves" against the whole Hessian's largest scaled eigenvalue.

    For a positive semi-definite H a direction along which the others' block does not curve
    at all does not couple to the kept coordinates, so leaving it out of H_oo⁺ changes
    nothing there. One that curves too little to be resolved (below ``rtol``) is held at the
    estimate: the kept coordinates' σ is the one given it, where the whole Hessian's
    eigenvectors would call every coordinate it touches by rounding unbounded. The kept
    coordinates' own directions of no curvature are those of the Schur complement. Returned
    over all n coordinates, zero on the others."""
    H = np.asarray(H, dtype=float)
    scales = np.asarray(scales, dtype=float)
    keep = np.asarray(keep, dtype=bool)
    other = ~keep
    if not other.any():
        return covariance_from_hessian(H, scales, rtol)
    n = H.shape[0]
    largest = float(np.linalg.eigvalsh(_scaled(H, scales)).max())
    others = covariance_from_hessian(H[np.ix_(other, other)], scales[other], rtol, largest=largest)
    schur = H[np.ix_(keep, keep)] - (H[np.ix_(keep, other)] @ others.cov @ H[np.ix_(other, keep)])
    own = covariance_from_hessian(schur, scales[keep], rtol, largest=largest)
    cov = np.zeros((n, n))
    cov[np.ix_(keep, keep)] = own.cov
    null = np.zeros((own.null_directions.shape[0], n))
    null[:, keep] = own.null_directions
    return HessianCovariance(
        cov=cov,
        null_directions=null,
        null_eigenvalues=own.null_eigenvalues,
        scales=scales,
        eigenvalues=own.eigenvalues,
    )


def direction_text(direction: np.ndarray, names: list[str] | tuple[str, ...]) -> str:
    """ "0.71·o2 − 0.70·D22" for a unit vector; components below DIRECTION_TEXT_MIN left out."""
    v = np.asarray(direction, dtype=float)
    v = v * np.sign(v[np.argmax(np.abs(v))])  # the largest component positive: one text
    parts: list[str] = []
    for i in np.argsort(-np.abs(v)):
        if parts and abs(v[i]) < DIRECTION_TEXT_MIN:
            break
        term = f"{abs(v[i]):.2f}·{names[i]}"
        parts.append(term if not parts else ("− " if v[i] < 0 else "+ ") + term)
    return " ".join(parts)


# --------------------------------------------------------------------------------------------
# The calibration's quantities as functions of θ


def misalignment_deg(D: np.ndarray) -> np.ndarray:
    """(3,) degrees: the rotation of the magnetometer's axes against the body axes, as a
    rotation vector in body axes. With the left polar decomposition D = P U (P symmetric
    positive definite: scale factors and soft iron; U a rotation) it is Uᵀ's. NaN when
    det D ≤ 0 (a mirrored triad has no such rotation)."""
    U, _ = scipy.linalg.polar(np.asarray(D, dtype=float), side="left")
    if np.linalg.det(U) <= 0.0:
        return np.full(3, np.nan)
    return np.rad2deg(frames.quat_to_rotvec(frames.matrix_to_quat(U.T)))


def derived_quantities(theta: np.ndarray, norm: Normalisation) -> dict[str, np.ndarray]:
    """Everything :data:`QUANTITIES` lists, from normalised θ (35,).

    D, o, noise_std_mag : the session's magnetometer unit (D per unit field); D_inv its
        inverse; dip_deg and the misalignment in degrees; m_n unitless; gyro_bias and
        noise_std_gyr rad/s; noise_std_acc m/s² (the standard deviations per axis: the
        square roots of the noise covariances' diagonals); time_offset_s s.

    misalignment_deg : :func:`misalignment_deg` of D; misalignment_angle_deg : its length.
    """
    p = params.unpack(theta).unscaled_magnetometer(norm.centre, norm.scale)
    misalignment = misalignment_deg(p.D)
    # The angle's derivative is undefined at zero; an estimate is never exactly aligned.
    angle = np.linalg.norm(misalignment)
    return {
        "D": p.D,
        "D_inv": np.linalg.inv(p.D),
        "o": p.o,
        "misalignment_deg": misalignment,
        "misalignment_angle_deg": np.array(angle),
        "dip_deg": np.array(np.rad2deg(p.dip_rad)),
        "m_n": p.m_n,
        "gyro_bias": p.gyro_bias,
        "noise_std_gyr": np.sqrt(np.diag(p.Sigma_gyr)),
        "noise_std_acc": np.sqrt(np.diag(p.Sigma_acc)),
        "noise_std_mag": np.sqrt(np.diag(p.Sigma_mag)),
        "time_offset_s": np.array(p.time_offset_s),
    }


def _flatten(q: dict[str, np.ndarray]) -> np.ndarray:
    return np.concatenate([np.asarray(q[name], dtype=float).ravel() for name, _ in QUANTITIES])


def _unflatten(v: np.ndarray) -> dict[str, np.ndarray]:
    out, k = {}, 0
    for name, shape in QUANTITIES:
        size = math.prod(shape)
        out[name] = v[k : k + size].reshape(shape)
        k += size
    return out


def propagate(
    f: Callable[[np.ndarray], np.ndarray], theta: np.ndarray, hc: HessianCovariance
) -> tuple[np.ndarray, np.ndarray]:
    """Values and standard deviations (inf where not identifiable) of f(θ) (m,) by
    linearisation: σ² = diag(J cov Jᵀ), J by central differences of f."""
    value, J = _jacobian(f, theta, JACOBIAN_STEP_FRACTION * hc.scales)
    return value, _linear_sigma(J, hc)


def _jacobian(
    f: Callable[[np.ndarray], np.ndarray], theta: np.ndarray, steps: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """f(θ) (m,) and its Jacobian (m, n) by central differences of ``steps`` (n,)."""
    value = f(theta)
    J = np.empty((value.size, theta.size))
    for i in range(theta.size):
        hi, lo = theta.copy(), theta.copy()
        hi[i] += steps[i]
        lo[i] -= steps[i]
        J[:, i] = (f(hi) - f(lo)) / (hi[i] - lo[i])
    return value, J


def _linear_sigma(J: np.ndarray, hc: HessianCovariance) -> np.ndarray:
    """σ (m,) of the linear map J (m, n) under ``hc``: √diag(J cov Jᵀ), inf where a null
    direction moves it by more than :data:`NULL_LOADING_RTOL` of its total sensitivity."""
    var = np.einsum("ij,jk,ik->i", J, hc.cov, J)
    sigma = np.sqrt(np.maximum(var, 0.0))
    if not hc.identifiable:
        Jz = J * hc.scales[None, :]  # sensitivity per unit scaled variable
        loading = np.abs(Jz @ hc.null_directions.T).max(axis=1)
        total = np.linalg.norm(Jz, axis=1)
        sigma = np.where(loading > NULL_LOADING_RTOL * total, np.inf, sigma)
    return sigma


# --------------------------------------------------------------------------------------------
# A calibration's uncertainty


@dataclass(frozen=True)
class CalibrationUncertainty:
    """Standard deviations of a calibration from the ML cost's curvature on a session.

    values, sigma    : name → array for each of :data:`QUANTITIES` (σ = inf where the data do
                       not determine it, NaN where undefined)
    theta_sigma      : (35,) σ of θ in the normalised units of ``params.py``
    null_directions  : text of each direction of θ the cost does not determine (empty: all
                       identifiable), e.g. "0.71·o2 − 0.70·D22"
    newton_step_sigma: size of the Newton step to the cost's minimum in standard deviations,
                       √(gᵀ H⁻¹ g): ≪ 1 at an ML estimate; large when the point is another
                       method's estimate
    min_scaled_eigenvalue : the smallest eigenvalue of the scaled Hessian (order one when
                       every parameter is well determined)
    negative_curvature : an eigenvalue is below −IDENTIFIABILITY_RTOL × the largest: the
                       cost curves down there, so the point is not a minimum
    gradient_evaluations, seconds, n_samples
    """

    values: dict[str, np.ndarray]
    sigma: dict[str, np.ndarray]
    theta_sigma: np.ndarray
    null_directions: list[str]
    newton_step_sigma: float
    min_scaled_eigenvalue: float
    negative_curvature: bool
    gradient_evaluations: int
    seconds: float
    n_samples: int
    notes: list[str] = field(default_factory=list)

    @property
    def identifiable(self) -> bool:
        return not self.null_directions

    @property
    def at_minimum(self) -> bool:
        """The point is (close to) a minimum of the ML cost, as an ML estimate is."""
        return (
            not self.negative_curvature and self.newton_step_sigma <= AT_MINIMUM_NEWTON_STEP_SIGMA
        )


def penalised_gradient(problem: LikelihoodProblem) -> Callable[[np.ndarray], np.ndarray]:
    """θ ↦ ∇(V + gyroscope noise prior) (35,), exact; all NaN where V is not finite."""

    def gradient(theta: np.ndarray) -> np.ndarray:
        value, g = problem.cost_and_gradient(theta)
        if not np.isfinite(value):
            return np.full_like(g, np.nan)
        return g

    return gradient


def calibration_uncertainty(
    result: CalibrationResult,
    session: Session,
    progress: Callable[[int, int], None] | None = None,
) -> CalibrationUncertainty:
    """σ of a result's quantities from the Hessian of the ML cost at its parameters on the
    session it was fitted on (2 exact gradient passes per parameter; ``progress(done, total)``).
    The time offset counts only where the result kept one (``time_offset_test``): held at
    0, its σ is 0.

    Raises ``replay.ModelUnavailableError`` when the result lacks the noise covariances
    or the gyroscope bias the cost needs, and :class:`CalibrationError` when the cost is not
    finite there.
    """
    t0 = time.perf_counter()
    p = replay.model_params_from_result(result)
    # The cost the estimate minimised: with the priors the result records (none for older
    # results and methods without the ML step).
    priors = Priors.from_dict(result.extra.get("priors"))
    problem = LikelihoodProblem.at_parameters(session, p, priors)
    # The time offset is a parameter only where the estimate kept one; otherwise it was held
    # at 0, and the curvature is that of the other parameters.
    free = np.ones(params.N_PARAMS, dtype=bool)
    free[params.INDEX_TIME_OFFSET] = bool(result.extra.get("time_offset_test", {}).get("kept"))
    full_gradient = penalised_gradient(problem)

    def embed(theta_free: np.ndarray) -> np.ndarray:
        theta = problem.theta0.copy()
        theta[free] = theta_free
        return theta

    def gradient(theta_free: np.ndarray) -> np.ndarray:
        return full_gradient(embed(theta_free))[free]

    theta0, scales = problem.theta0[free], problem.scales[free]
    g0 = gradient(theta0)
    if not np.isfinite(g0).all():
        raise CalibrationError(
            "uncertainty: the ML cost is not finite at the result's parameters on this "
            "session: the result does not describe this session"
        )
    H = central_difference_hessian(gradient, theta0, HESSIAN_STEP_FRACTION * scales, progress)
    names = [name for name, keep in zip(params.PARAM_NAMES, free, strict=True) if keep]
    noise_model = np.array([is_noise_model_parameter(name) for name in names])
    hc = covariance_from_hessian(H, scales)
    hc_calibration = marginal_covariance(H, scales, ~noise_model)
    hc_noise_model = marginal_covariance(H, scales, noise_model)

    def quantities(th: np.ndarray) -> np.ndarray:
        return _flatten(derived_quantities(embed(th), problem.norm))

    # One linearisation, read under each block's covariance: the noise model's quantities
    # and coordinates under its own, everything else under the calibration's.
    values, J = _jacobian(quantities, theta0, JACOBIAN_STEP_FRACTION * scales)
    of_noise_model = _flatten(
        {name: np.full(shape, name.startswith("noise_std_")) for name, shape in QUANTITIES}
    ).astype(bool)
    sigma = np.where(
        of_noise_model, _linear_sigma(J, hc_noise_model), _linear_sigma(J, hc_calibration)
    )
    coordinates = np.eye(len(theta0))
    theta_sigma = np.zeros(params.N_PARAMS)
    theta_sigma[free] = np.where(
        noise_model,
        _linear_sigma(coordinates, hc_noise_model),
        _linear_sigma(coordinates, hc_calibration),
    )
    null_directions = [
        direction_text(v, names)
        for v in (*hc_calibration.null_directions, *hc_noise_model.null_directions)
    ]
    notes = []
    if result.method != "ml":
        notes.append(
            f"the result comes from method {result.method!r}, not ml: these are the ML cost's "
            "curvature at its parameters, i.e. the uncertainty an ML estimate near this point "
            "would have, not this method's own"
        )
    return CalibrationUncertainty(
        values=_unflatten(values),
        sigma=_unflatten(sigma),
        theta_sigma=theta_sigma,
        null_directions=null_directions,
        newton_step_sigma=float(np.sqrt(max(float(g0 @ hc.cov @ g0), 0.0))),
        min_scaled_eigenvalue=float(hc.eigenvalues[0]),
        negative_curvature=bool(hc.eigenvalues[0] < -IDENTIFIABILITY_RTOL * hc.eigenvalues[-1]),
        gradient_evaluations=2 * int(free.sum()) + 1,
        seconds=time.perf_counter() - t0,
        n_samples=problem.n_samples,
        notes=notes,
    )
