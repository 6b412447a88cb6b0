"""Algorithm 1, step 2: minimise V(θ) (eq. 6) from θ₀ with damped BFGS.

Numerical choices, each a fix for a way the plain problem fails:

* The magnetometer data are centred on the ellipsoid's centre and divided by its mean
  radius first, so D ≈ rotation, o ≈ 0 whatever the sensor's units; the result is mapped
  back (``ModelParams.unscaled_magnetometer``).
* BFGS runs in variables scaled by the expected statistical uncertainty of each parameter
  (:func:`parameter_scales`), so its identity start is close to the true curvature.
* A log-normal prior on the gyroscope noise (:func:`gyro_noise_prior`). At IMU rates the
  likelihood hardly depends on Σ_ω once it is small, so without one its Cholesky
  parameters drift towards −∞ along an almost flat valley and BFGS never converges. And
  with translational accelerations, which the model lacks, the likelihood prefers a large
  Σ_ω: a filter that follows the accelerometer explains them best, but its tilted
  attitude biases the misalignment (without a prior: 6× the known-attitude floor on
  hand-moved sessions with 0.3 m/s² accelerations). The gyroscope's white noise can be
  measured, at rest or from second differences during motion; the prior is that
  measurement with its uncertainty.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from magcal.calib.initial.estimate import InitialEstimate, starting_attitude
from magcal.calib.likelihood import cost, mekf, params
from magcal.calib.likelihood.optimize import OptimizeOptions, OptimizeReport, minimize_bfgs
from magcal.calib.likelihood.params import ModelParams
from magcal.io.session import Session

#: 1-σ width of the prior on log σ_ω when a stationary stretch did not measure it: the
#: initial value then comes from second differences of the gyroscope during motion
#: (``stationary.gyro_noise_from_differences``), good to a few per cent for white noise,
#: so it gets the same ±10 % as a stationary measurement (measured: 0.2 let the likelihood
#: pull σ_ω up 1.7× on accelerated sessions, 2.4× the floor instead of 1.6×). Same width,
#: centred on 0, for the unit lower-triangular entries of its Cholesky factor.
GYRO_NOISE_PRIOR_WIDTH_FROM_MOTION = 0.1
#: Smallest width when a stationary stretch measured it: a gyroscope's noise at rest and in
#: motion differ by about this much (vibration, quantisation), however long the stretch.
GYRO_NOISE_PRIOR_WIDTH_MIN = 0.1


@dataclass(frozen=True)
class Normalisation:
    """y' = (y − centre) / scale; centre (3,) and scale in magnetometer units."""

    centre: np.ndarray
    scale: float

    def apply(self, mag: np.ndarray) -> np.ndarray:
        return (np.asarray(mag, dtype=float) - self.centre) / self.scale


@dataclass(frozen=True)
class MLEstimate:
    params: ModelParams  # raw magnetometer units
    theta: np.ndarray  # (34,) normalised
    theta0: np.ndarray  # (34,) normalised
    report: OptimizeReport


def normalisation_for(p: ModelParams) -> Normalisation:
    return Normalisation(
        centre=np.asarray(p.o, dtype=float).copy(),
        scale=float(abs(np.linalg.det(p.D)) ** (1.0 / 3.0)),
    )


def filter_data_for(
    session: Session, init: InitialEstimate, p_norm: ModelParams, norm: Normalisation
) -> mekf.FilterData:
    mag_n = norm.apply(session.mag)
    q0 = starting_attitude(session.acc, mag_n, p_norm)
    return mekf.make_filter_data(
        session.t,
        session.gyr,
        session.acc,
        mag_n,
        q0,
        acc_extra_var=init.acc_extra_var,
        g=init.g,
    )


def parameter_scales(p_norm: ModelParams, n: int) -> np.ndarray:
    """Rough 1-σ uncertainty of each θ component for n samples (34,).

    D, o and the dip are measured against the magnetometer noise; the bias through the
    attitude it makes drift, about half as well; the noise parameters as log-scales, the
    gyroscope's a few times more weakly than the others (its noise is small next to the
    measurement updates). Only ratios matter much, as BFGS rescales after one step; these
    were tuned on simulated MEMS, hand-held, accelerated and Table 2 sessions (≈35 % fewer
    iterations than the first guess of bias σ_m and gyroscope 10).
    """
    sigma_m = float(np.sqrt(np.trace(p_norm.Sigma_mag) / 3.0))
    s = np.empty(params.N_PARAMS)
    s[params.SLICE_D] = sigma_m
    s[params.SLICE_O] = sigma_m
    s[params.INDEX_DIP] = sigma_m
    s[params.SLICE_BIAS] = 2.0 * sigma_m
    s[params.SLICE_CHOL_GYR] = 3.0
    s[params.SLICE_CHOL_ACC] = 1.5
    s[params.SLICE_CHOL_MAG] = 0.7
    return s / np.sqrt(n)


def gyro_noise_prior(theta0: np.ndarray, stationary_samples: int) -> tuple[np.ndarray, np.ndarray]:
    """Mean and diagonal precision (34,) of the prior on the gyroscope noise parameters.

    Centred on θ₀'s Σ_ω. With ``stationary_samples`` = n > 0 it was measured there: a
    log-σ estimated from n samples has standard error 1/√(2n), a correlation 1/√n; both
    are floored at :data:`GYRO_NOISE_PRIOR_WIDTH_MIN`. Otherwise it was measured during
    motion (:data:`GYRO_NOISE_PRIOR_WIDTH_FROM_MOTION`), with uncorrelated axes.
    """
    mean = np.zeros(params.N_PARAMS)
    precision = np.zeros(params.N_PARAMS)
    sl = params.SLICE_CHOL_GYR
    mean[sl] = theta0[sl]
    if stationary_samples > 0:
        w_log = max(GYRO_NOISE_PRIOR_WIDTH_MIN, 1.0 / np.sqrt(2.0 * stationary_samples))
        w_corr = max(GYRO_NOISE_PRIOR_WIDTH_MIN, 1.0 / np.sqrt(stationary_samples))
    else:
        mean[sl.start + 3 : sl.stop] = 0.0
        w_log = w_corr = GYRO_NOISE_PRIOR_WIDTH_FROM_MOTION
    precision[sl.start : sl.start + 3] = 1.0 / w_log**2
    precision[sl.start + 3 : sl.stop] = 1.0 / w_corr**2
    return mean, precision


def penalised_cost_functions(
    data: mekf.FilterData, theta0: np.ndarray, stationary_samples: int, gradient: str = "exact"
) -> tuple[Callable, Callable]:
    """(θ ↦ (V + prior, ∇), θ ↦ V + prior) with the gradient exact or finite-difference."""
    mean, precision = gyro_noise_prior(theta0, stationary_samples)
    tape = mekf.new_tape(len(data))
    typical = np.maximum(np.abs(theta0), 1e-3)

    def penalty(theta):
        r = theta - mean
        return 0.5 * float(np.sum(precision * r * r)), precision * r

    def f(theta):
        return cost.cost(theta, data) + penalty(theta)[0]

    if gradient == "exact":

        def fg(theta):
            v, g = cost.cost_and_gradient(theta, data, tape)
            pv, pg = penalty(theta)
            return v + pv, g + pg

    elif gradient == "numeric":

        def fg(theta):
            v = cost.cost(theta, data)
            g = cost.numeric_gradient(theta, data, "forward", typical=typical, value=v)
            pv, pg = penalty(theta)
            return v + pv, g + pg

    else:
        raise ValueError(f"unknown gradient {gradient!r}: use 'exact' or 'numeric'")
    return fg, f


def canonical_twin(theta: np.ndarray) -> np.ndarray:
    """θ moved onto the branch det D > 0, m_x = cos δ > 0 by the likelihood's symmetries.

    The cost is exactly invariant under (D, δ) → (−D, δ + π), i.e. ``(D, m_n) → (−D, −m_n)``
    (the filter never inverts D, so BFGS can cross det D = 0 from a poor start), and,
    with the navigation frame turned 180° in heading, under δ → π − δ (parametrisation 8b
    drops eq. 17c's m_x > 0). The paper's Assumption 1 (magnetometer axes rotated, not
    mirrored, against the inertial ones) picks det D > 0; eq. 17c picks the dip."""
    theta = np.array(theta, dtype=float)
    dip = theta[params.INDEX_DIP]
    if np.linalg.det(theta[params.SLICE_D].reshape(3, 3)) < 0.0:
        theta[params.SLICE_D] = -theta[params.SLICE_D]
        dip += np.pi
    dip = float(np.arctan2(np.sin(dip), np.cos(dip)))
    if np.cos(dip) < 0.0:
        dip = float(np.arctan2(np.sin(np.pi - dip), np.cos(np.pi - dip)))
    theta[params.INDEX_DIP] = dip
    return theta


def maximum_likelihood(
    session: Session,
    init: InitialEstimate,
    gradient: str = "exact",
    options: OptimizeOptions = OptimizeOptions(),
    progress: Callable[[int, float, float], None] | None = None,
) -> MLEstimate:
    """Algorithm 1 step 2 from the initial estimate."""
    norm = normalisation_for(init.params)
    p0 = init.params.scaled_magnetometer(norm.centre, norm.scale)
    data = filter_data_for(session, init, p0, norm)
    theta0 = params.pack(p0)
    still = init.noise.stationary
    n_still = 0 if still is None else still.stop - still.start
    fg, f = penalised_cost_functions(data, theta0, n_still, gradient)
    # Exact gradients: cost and gradient together at every trial point, since nearly every
    # step is accepted at α = 1 and a cost-only line search would pay for the forward pass
    # twice. Finite differences (the paper's way): the line search tries points by cost
    # alone, as a gradient there costs n_θ + 1 passes.
    line_search_cost = f if gradient == "numeric" else None
    report = minimize_bfgs(
        fg,
        theta0,
        parameter_scales(p0, len(data)),
        options,
        fun=line_search_cost,
        progress=progress,
    )
    theta = canonical_twin(report.x)
    p_hat = params.unpack(theta).unscaled_magnetometer(norm.centre, norm.scale)
    return MLEstimate(
        params=p_hat,
        theta=theta,
        theta0=theta0,
        report=report,
    )
