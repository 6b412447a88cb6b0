# SPDX-License-Identifier: Apache-2.0
"""The maximum-likelihood problem of Algorithm 1, step 2, built in one place for every caller.

:class:`LikelihoodProblem` holds everything the cost needs besides θ: the filter's data
(magnetometer normalised, starting attitude, gravity magnitude, accelerometer bump
inflation), the normalisation, θ's layout scales and the gyroscope-noise prior. It gives

* ``V(θ) = ½ Σ_t [ ‖y_t − ŷ_t|t−1(θ)‖²_{S_t⁻¹} + log det S_t(θ) ]`` (eq. 6) through the MEKF
  of ``mekf.py`` (:meth:`~LikelihoodProblem.negative_log_likelihood`), and V plus the prior
  (:meth:`~LikelihoodProblem.cost`), the objective the optimiser minimises;
* their gradients, exact (one forward and one reverse pass of the C kernel: about 2.4 times
  the price of the cost, ``make bench``) or by finite differences, the paper's way
  (n_θ + 1 forward or 2 n_θ central filter passes);
* θ mapped back to raw magnetometer units (:meth:`~LikelihoodProblem.model_params`).

θ is the 35-vector of ``params.py``. Two constructors share one path: :meth:`for_ml_step`
(from the initial estimate, as the ML step sets it up) and :meth:`at_parameters` (at given
parameters, e.g. a result's). The data-only levels come from
``initial.sensor_levels.measure_sensor_levels``, the same function step 1 uses.

Numerical choices, each a fix for a way the plain problem fails:

* The magnetometer data are centred on the ellipsoid's centre and divided by its mean
  radius first (:class:`Normalisation`), so D ≈ rotation, o ≈ 0 whatever the sensor's
  units; results are mapped back (``ModelParams.unscaled_magnetometer``).
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

import dataclasses
import functools
from dataclasses import dataclass, field

import numpy as np

from magcal.calib import frames, samples
from magcal.calib.initial.estimate import InitialEstimate
from magcal.calib.initial.sensor_levels import SensorLevels, measure_sensor_levels
from magcal.calib.likelihood import mekf, params
from magcal.calib.likelihood.mekf import FilterData
from magcal.calib.likelihood.params import ModelParams
from magcal.io.session import Session

#: 1-σ width of the prior on log σ_ω when a stationary stretch did not measure it: the
#: initial value then comes from second differences of the gyroscope during motion
#: (``rest.gyro_noise_from_differences``), good to a few per cent for white noise. Same
#: width, centred on 0, for the unit lower-triangular entries of its Cholesky factor.
#: Narrow on purpose: what the held rate misses within a step is the turn variance
#: (``sensor_levels.turn_variance``), and whatever else the model lacks (the room's field
#: changing over position, translational accelerations) the likelihood would rather explain
#: as gyroscope noise about one axis, since a random walk of the attitude fits slow,
#: correlated errors better than white magnetometer noise does. With ±10 % on the real
#: recordings of ``make real`` one axis's σ_ω went up 27–270× and the gyroscope bias
#: strayed to 10× the optical reference's; with ±3 % and the turn variance σ_ω stays put
#: and ArduPilot SITL's aligned compasses are calibrated to 0.05–0.07° (was 0.07–0.09°).
GYRO_NOISE_PRIOR_WIDTH_FROM_MOTION = 0.03
#: Smallest width when a stationary stretch measured it: the same as during motion, as a
#: gyroscope's noise at rest and in motion differ by a few per cent (vibration,
#: quantisation) however long the stretch.
GYRO_NOISE_PRIOR_WIDTH_MIN = 0.03

# Forward differences have truncation error O(h) and rounding error O(ε|V|/h); h ∝ √ε
# balances them. Central differences: O(h²) against O(ε|V|/h), so h ∝ ∛ε.
_FORWARD_REL_STEP = np.sqrt(np.finfo(float).eps)
_CENTRAL_REL_STEP = np.cbrt(np.finfo(float).eps)


# --------------------------------------------------------------------------------------------
# V(θ) and its gradient on given filter data


def negative_log_likelihood(theta: np.ndarray, data: FilterData) -> float:
    """V(θ) (float, nats). NaN when the filter's covariances break down."""
    return mekf.filter_pass(params.unpack(theta), data, True)


def negative_log_likelihood_and_gradient(
    theta: np.ndarray, data: FilterData, tape: np.ndarray | None = None
) -> tuple[float, np.ndarray]:
    """V(θ) and ∂V/∂θ (35,), exact (reverse mode through the filter); ``tape`` is the
    workspace of ``mekf.new_tape`` (allocated here when None)."""
    theta = np.asarray(theta, dtype=float)
    value, mg = mekf.cost_and_model_gradient(params.unpack(theta), data, tape=tape)
    if not np.isfinite(value) or not all(np.all(np.isfinite(p)) for p in vars(mg).values()):
        # The filter broke down at θ (a trial point far out in a line search): there is no
        # gradient to carry over to θ, and the optimiser rejects a point without one.
        return value, np.full(theta.shape, np.nan)
    grad = params.model_grad_to_theta(
        theta,
        mg.D,
        mg.o,
        mg.m,
        mg.gyro_bias,
        mg.Sigma_gyr,
        mg.Sigma_acc,
        mg.Sigma_mag,
        float(mg.time_offset_s),
    )
    return value, grad


def numeric_gradient(
    theta: np.ndarray,
    data: FilterData,
    scheme: str = "forward",
    typical: np.ndarray | None = None,
    value: float | None = None,
) -> np.ndarray:
    """∂V/∂θ by finite differences (35,). ``typical`` (35,) sets each step's scale
    (h_i = rel · max(|θ_i|, typical_i)); ``value`` is V(θ) if already known (forward)."""
    theta = np.asarray(theta, dtype=float)
    scale = np.maximum(np.abs(theta), 1.0 if typical is None else typical)
    grad = np.empty_like(theta)
    if scheme == "forward":
        v0 = negative_log_likelihood(theta, data) if value is None else value
        for i in range(theta.size):
            h = _FORWARD_REL_STEP * scale[i]
            e = theta.copy()
            e[i] += h
            grad[i] = (negative_log_likelihood(e, data) - v0) / (e[i] - theta[i])
    elif scheme == "central":
        for i in range(theta.size):
            h = _CENTRAL_REL_STEP * scale[i]
            hi, lo = theta.copy(), theta.copy()
            hi[i] += h
            lo[i] -= h
            grad[i] = (negative_log_likelihood(hi, data) - negative_log_likelihood(lo, data)) / (
                hi[i] - lo[i]
            )
    else:
        raise ValueError(f"unknown finite-difference scheme {scheme!r}: use 'forward' or 'central'")
    return grad


# --------------------------------------------------------------------------------------------
# The parts of the problem


@dataclass(frozen=True)
class Normalisation:
    """y' = (y − centre) / scale; centre (3,) and scale in magnetometer units."""

    centre: np.ndarray
    scale: float

    @classmethod
    def of(cls, p: ModelParams) -> Normalisation:
        """Centred on ``p``'s o, divided by ``|det D|^⅓`` (raw units): D ≈ a rotation after."""
        return cls(
            centre=np.asarray(p.o, dtype=float).copy(),
            scale=float(abs(np.linalg.det(p.D)) ** (1.0 / 3.0)),
        )

    def apply(self, mag: np.ndarray) -> np.ndarray:
        return (np.asarray(mag, dtype=float) - self.centre) / self.scale


def starting_attitude(acc: np.ndarray, mag: np.ndarray, p: ModelParams) -> np.ndarray:
    """q_nb (4,) at sample 0 by TRIAD from the first few samples and calibration ``p``.

    acc : (N, 3) m/s²; mag : (N, 3) in ``p``'s magnetometer units; NaN rows (no sample
    there, a multi-rate session) are skipped: the first few samples of each are used.
    """
    acc = acc[~np.isnan(acc[:, 0])]
    mag = mag[~np.isnan(mag[:, 0])]
    up_b = acc[: mekf.INITIAL_ATTITUDE_SAMPLES].mean(axis=0)
    field_b = np.linalg.solve(p.D, mag[: mekf.INITIAL_ATTITUDE_SAMPLES].mean(axis=0) - p.o)
    return frames.triad(up_b, field_b, p.m_n)


def parameter_scales(p_norm: ModelParams, n: int, rate_rms_rad_s: float) -> np.ndarray:
    """Rough 1-σ uncertainty of each θ component for n samples (35,).

    D, o and the dip are measured against the magnetometer noise; the bias through the
    attitude it makes drift, about half as well; the noise parameters as log-scales, the
    gyroscope's a few times more weakly than the others (its noise is small next to the
    measurement updates). Only ratios matter much, as BFGS rescales after one step; these
    were tuned on simulated MEMS, hand-held, accelerated and Table 2 sessions (≈35 % fewer
    iterations than the first guess of bias σ_m and gyroscope 10). The time offset τ moves the
    predicted field by about ω τ, so it is measured to σ_m / ω at the session's RMS rate ω
    (at least 0.1 rad/s).
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
    s[params.INDEX_TIME_OFFSET] = sigma_m / max(rate_rms_rad_s, 0.1)
    return s / np.sqrt(n)


def gyro_noise_prior(
    Sigma_gyr: np.ndarray, stationary_samples: int
) -> tuple[np.ndarray, np.ndarray]:
    """Mean and diagonal precision (35,) of the prior on the gyroscope noise parameters.

    Centred on the measured Σ_ω (3, 3), (rad/s)². With ``stationary_samples`` = n > 0 it
    was measured there: a log-σ estimated from n samples has standard error 1/√(2n), a
    correlation 1/√n; both are floored at :data:`GYRO_NOISE_PRIOR_WIDTH_MIN`. Otherwise it
    was measured during motion (:data:`GYRO_NOISE_PRIOR_WIDTH_FROM_MOTION`), with
    uncorrelated axes.
    """
    mean = np.zeros(params.N_PARAMS)
    precision = np.zeros(params.N_PARAMS)
    sl = params.SLICE_CHOL_GYR
    mean[sl] = params.cov_to_chol_params(Sigma_gyr)
    if stationary_samples > 0:
        w_log = max(GYRO_NOISE_PRIOR_WIDTH_MIN, 1.0 / np.sqrt(2.0 * stationary_samples))
        w_corr = max(GYRO_NOISE_PRIOR_WIDTH_MIN, 1.0 / np.sqrt(stationary_samples))
    else:
        mean[sl.start + 3 : sl.stop] = 0.0
        w_log = w_corr = GYRO_NOISE_PRIOR_WIDTH_FROM_MOTION
    precision[sl.start : sl.start + 3] = 1.0 / w_log**2
    precision[sl.start + 3 : sl.stop] = 1.0 / w_corr**2
    return mean, precision


#: Default 1-σ width of the prior on each axis of the gyroscope bias, °/s, centred on 0. MEMS
#: gyroscopes' zero-rate offsets are ±1–5 °/s for most parts; the prior only matters where the
#: data cannot tell a bias from something else (a still or slowly turned sensor, accelerations).
GYRO_BIAS_PRIOR_DEG_S = 5.0
#: A width for the prior on the rotation between the magnetometer's axes and the inertial
#: ones (``magcal calibrate --misalignment-prior 5deg``), degrees, centred on the nearest axis
#: permutation: a magnetometer mounted along the IMU's axes up to one of the 24 permutations,
#: plus a few degrees of tolerance. Not on by default: sensors whose soft iron is strongly
#: skewed have a large rotation part in D whatever the mounting (the paper's Table 2 sensors,
#: skews up to 30°: a 5° prior there raised the median ML heading error from 9.3° to 11.8°,
#: 20 seeds), while on a real hand-held recording (fiumarg_rec11_undist, `make real`) it
#: lowered it from 5.7° to 3.5°.
MISALIGNMENT_PRIOR_DEG = 5.0
#: 1-σ width of the prior on the time offset τ, s, centred on 0. A magnetometer's delay
#: against its IMU is up to tens of milliseconds (phones, autopilots' compass buses); the
#: prior only matters where the rotation is too slow to show the delay, and keeps τ to
#: where the model's constant rate over τ holds.
TIME_OFFSET_PRIOR_S = 0.1
#: 1-σ width of the prior on the coupling entries u of the accelerometer's and the
#: magnetometer's noise covariances (``params``: Σ = L Lᵀ, L = diag(exp(l)) U; for two axes
#: u = ρ/√(1 − ρ²), ρ their noise correlation), centred on 0. 10 is a correlation of 0.995
#: at 1 σ: no correlation a real sensor shows is penalised, but a covariance cannot
#: collapse onto a plane. Without it, a recording whose accelerometer residual is nearly
#: confined to a plane (tyrex_iphone5_d4, `make real`) has no interior optimum: the
#: smallest eigenvalue of Σ_a falls without end (2.6·10⁻⁸ of the largest after 680
#: iterations) while the cost creeps down by 10⁻⁶ nats per step.
NOISE_COUPLING_PRIOR = 10.0


#: 1-σ relative error of each entry of a gyroscope's 3×3 gain matrix (scale factors and
#: cross-axis sensitivities) that the filter allows for where a session shows one (the test
#: in ``ml.py``): each step's turn then has a variance ``k² |ω|² T²`` per axis
#: (``sensor_levels.turn_squared``), none while still, many times the white noise's while
#: turning fast. MEMS datasheets give ±1–3 % for the scale factor and ±1–2 % for the
#: cross-axis sensitivity; this is the low end. A gain error is the same at every step, so
#: this treats a slowly varying error as white; estimating the gain matrix instead adds
#: parameters that the magnetometer's own rotation in D trades against (a symmetric gain,
#: fitted on the real recordings of ``make real``, did not lower their heading error).
GYRO_GAIN_ERROR = 0.01


@dataclass(frozen=True)
class Priors:
    """The MAP estimate's priors on what a session may not determine (1 σ; None: none).

    gyro_bias_rad_s  : rad/s, per axis, centred on 0 (default :data:`GYRO_BIAS_PRIOR_DEG_S`)
    misalignment_rad : rad, the rotation part of D against the axis permutation nearest to the
                       starting estimate's (:func:`misalignment_vector`); none by default
                       (:data:`MISALIGNMENT_PRIOR_DEG` says why)
    time_offset_s    : s, the magnetometer's delay, centred on 0 (default
                       :data:`TIME_OFFSET_PRIOR_S`)
    noise_coupling   : dimensionless, the coupling entries of the accelerometer's and
                       the magnetometer's noise covariances, centred on 0 (default
                       :data:`NOISE_COUPLING_PRIOR`)
    """

    gyro_bias_rad_s: float | None = float(np.deg2rad(GYRO_BIAS_PRIOR_DEG_S))
    misalignment_rad: float | None = None
    time_offset_s: float | None = TIME_OFFSET_PRIOR_S
    noise_coupling: float | None = NOISE_COUPLING_PRIOR

    @classmethod
    def from_dict(cls, widths: dict | None) -> Priors:
        """The priors a result file records (:meth:`as_dict`); none for a result without."""
        if not widths:
            return NO_PRIORS

        def rad(key: str):
            value = widths.get(key)
            return None if value is None else float(np.deg2rad(float(value)))

        offset = widths.get("time_offset_s")
        coupling = widths.get("noise_coupling")
        return cls(
            gyro_bias_rad_s=rad("gyro_bias_deg_s"),
            misalignment_rad=rad("misalignment_deg"),
            time_offset_s=None if offset is None else float(offset),
            noise_coupling=None if coupling is None else float(coupling),
        )

    def as_dict(self) -> dict:
        """The widths in degrees and °/s, for a result file (None where there is no prior)."""

        def deg(x):
            return None if x is None else float(np.rad2deg(x))

        return {
            "gyro_bias_deg_s": deg(self.gyro_bias_rad_s),
            "misalignment_deg": deg(self.misalignment_rad),
            "time_offset_s": self.time_offset_s,
            "noise_coupling": self.noise_coupling,
        }


#: No priors: the plain maximum-likelihood estimate of the paper.
NO_PRIORS = Priors(
    gyro_bias_rad_s=None, misalignment_rad=None, time_offset_s=None, noise_coupling=None
)


def misalignment_vector(D: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """(3,) rad: the rotation vector φ of D's rotation part against ``reference`` (3, 3), to
    first order in φ.

    With D = P R and R referenceᵀ = I + [φ×] + O(φ²), M = D referenceᵀ has the skew part
    ½ (P [φ×] + [φ×] P) = ½ [((tr P) I − P) φ ×] (an identity for symmetric P), so
    φ = 2 ((tr P) I − P)⁻¹ vex(skew M) with P ≈ sym M. It is a smooth (analytic) function of
    D's entries, so its derivatives are exact by complex steps (:func:`misalignment_penalty`).
    Works on complex arrays too.
    """
    M = D @ reference.T
    P = 0.5 * (M + M.T)
    skew = 0.5 * (M - M.T)
    vex = np.array([skew[2, 1], skew[0, 2], skew[1, 0]])
    return 2.0 * np.linalg.solve(np.trace(P) * np.eye(3) - P, vex)


def misalignment_penalty(
    D_flat: np.ndarray, reference: np.ndarray, sigma_rad: float
) -> tuple[float, np.ndarray]:
    """½ ‖φ‖² / σ² (nats) and its gradient w.r.t. D's 9 entries (row-major), φ the
    :func:`misalignment_vector`. The gradient is by complex steps: for an analytic function,
    Im f(x + i h e_k) / h is ∂f/∂x_k without cancellation, exact to rounding."""

    def half_square(x: np.ndarray):
        phi = misalignment_vector(x.reshape(3, 3), reference)
        return 0.5 * (phi @ phi) / sigma_rad**2

    D_flat = np.asarray(D_flat, dtype=float)
    grad = np.empty(9)
    for k in range(9):
        x = D_flat.astype(complex)
        x[k] += 1j * params.COMPLEX_STEP
        grad[k] = half_square(x).imag / params.COMPLEX_STEP
    return float(half_square(D_flat)), grad


def on_canonical_branch(theta: np.ndarray) -> np.ndarray:
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


def typical_changes() -> np.ndarray:
    """(35,) how far one step of the trust-region optimiser may move each θ component at
    first: a tenth of the normalised field for D and o (≈ 6° of rotation, 10 % of scale),
    0.1 rad of dip, 1 °/s of gyroscope bias, half a unit of each noise covariance's log-scale
    and correlation entries (σ × 1.6) and 10 ms of time offset. The region grows by doubling
    where the model predicts well, so these only pace the first steps from a poor start."""
    t = np.empty(params.N_PARAMS)
    t[params.SLICE_D] = 0.1
    t[params.SLICE_O] = 0.1
    t[params.INDEX_DIP] = 0.1
    t[params.SLICE_BIAS] = np.deg2rad(1.0)
    t[params.SLICE_CHOL_GYR] = 0.5
    t[params.SLICE_CHOL_ACC] = 0.5
    t[params.SLICE_CHOL_MAG] = 0.5
    t[params.INDEX_TIME_OFFSET] = 0.01
    return t


# --------------------------------------------------------------------------------------------
# The problem


@dataclass(frozen=True)
class LikelihoodProblem:
    """V(θ) with its prior on one session.

    data            : the filter's input, magnetometer normalised by ``norm``
    norm            : y' = (y − centre) / scale
    theta0          : (35,) where the problem was set up, in the normalised units (params.py)
    scales          : (35,) rough 1-σ uncertainty of each θ component (:func:`parameter_scales`)
    prior_mean      : (35,) mean of the diagonal Gaussian priors: the gyroscope noise's, the
                      gyroscope bias's and the time offset's (:class:`Priors`)
    prior_precision : (35,) their diagonal precision (zero where there is no prior)
    misalignment_reference : (3, 3) the axis permutation the misalignment prior is centred on
    misalignment_sigma_rad : its width, or None for no misalignment prior
    levels          : the data-only levels the filter's input was made with
    gyro_gain_error : the gyroscope's gain error the filter allows for (ModelParams'),
                      in ``data.turn_var``
    """

    data: FilterData
    norm: Normalisation
    theta0: np.ndarray
    scales: np.ndarray
    prior_mean: np.ndarray
    prior_precision: np.ndarray
    misalignment_reference: np.ndarray = field(default_factory=lambda: np.eye(3))
    misalignment_sigma_rad: float | None = None
    levels: SensorLevels | None = None
    gyro_gain_error: float = 0.0

    @classmethod
    def for_ml_step(
        cls,
        session: Session,
        init: InitialEstimate,
        at: ModelParams | None = None,
        priors: Priors = Priors(),
    ) -> LikelihoodProblem:
        """The ML step's problem: magnetometer normalised by the initial estimate's o and
        ``|det D|^⅓``, data-only levels and gyroscope prior from its step 1a. ``at`` (raw
        units; default the initial estimate) is where it is set up: θ₀ and the filter's
        starting attitude come from it."""
        p = init.params if at is None else at
        return cls._build(session, init.levels, Normalisation.of(init.params), p, priors)

    @classmethod
    def at_parameters(
        cls, session: Session, p: ModelParams, priors: Priors = Priors()
    ) -> LikelihoodProblem:
        """The problem at ``p`` (raw magnetometer units, e.g. a result's) on ``session``.

        The data-only levels are measured on the session as the initial estimate measures
        them for the ML step: gravity magnitude, the bump inflation of Σ_a with the
        accelerometer noise of the stationary stretch (or the prior), and the gyroscope
        noise prior centred on its measurement. Only the magnetometer normalisation differs
        (centred on ``p``'s o, divided by its ``|det D|^⅓``, instead of the initial
        estimate's): V changes by a constant and θ by an affine map, so gradients and
        curvature carry over exactly. The magnetometer's glitches are left out as the
        calibration leaves them out (:func:`samples.drop_magnetometer_glitches`), so the
        cost is the one the estimate minimised.
        """
        session, _ = samples.drop_magnetometer_glitches(session)
        return cls._build(session, measure_sensor_levels(session), Normalisation.of(p), p, priors)

    @classmethod
    def _build(
        cls,
        session: Session,
        levels: SensorLevels,
        norm: Normalisation,
        p: ModelParams,
        priors: Priors,
    ) -> LikelihoodProblem:
        p_norm = p.scaled_magnetometer(norm.centre, norm.scale)
        mag_n = norm.apply(session.mag)
        data = mekf.make_filter_data(
            session.t,
            session.gyr,
            session.acc,
            mag_n,
            starting_attitude(session.acc, mag_n, p_norm),
            acc_extra_var=levels.acc_extra_var,
            g=levels.g,
            # A multi-rate session: every row propagates, each sensor updates where it
            # measured (levels.acc_used is False where the row has no accelerometer).
            has_acc=levels.acc_used,
            has_mag=session.has_mag,
            turn_var=levels.turn_var_with_gain_error(p.gyro_gain_error),
        )
        prior_mean, prior_precision = gyro_noise_prior(
            levels.noise.Sigma_gyr, levels.stationary_samples
        )
        if priors.gyro_bias_rad_s is not None:
            prior_mean[params.SLICE_BIAS] = 0.0
            prior_precision[params.SLICE_BIAS] = 1.0 / priors.gyro_bias_rad_s**2
        if priors.time_offset_s is not None:
            prior_mean[params.INDEX_TIME_OFFSET] = 0.0
            prior_precision[params.INDEX_TIME_OFFSET] = 1.0 / priors.time_offset_s**2
        if priors.noise_coupling is not None:
            for block in (params.SLICE_CHOL_ACC, params.SLICE_CHOL_MAG):
                coupling = np.arange(block.start + 3, block.stop)  # u₁₀, u₂₀, u₂₁
                prior_mean[coupling] = 0.0
                prior_precision[coupling] = 1.0 / priors.noise_coupling**2
        return cls(
            data=data,
            norm=norm,
            theta0=params.pack(p_norm),
            scales=parameter_scales(
                p_norm,
                int(data.has_mag.sum()),
                float(np.sqrt(np.mean(np.sum(session.gyr**2, axis=1)))),
            ),
            prior_mean=prior_mean,
            prior_precision=prior_precision,
            misalignment_reference=frames.nearest_axis_permutation(frames.nearest_rotation(p.D)),
            misalignment_sigma_rad=priors.misalignment_rad,
            levels=levels,
            gyro_gain_error=p.gyro_gain_error,
        )

    def with_gyro_gain_error(self, k: float) -> LikelihoodProblem:
        """The same problem with the filter allowing for a gyroscope gain error ``k``
        (:data:`GYRO_GAIN_ERROR`); θ keeps its meaning."""
        turn_var = self.levels.turn_var_with_gain_error(k)
        return dataclasses.replace(
            self, data=dataclasses.replace(self.data, turn_var=turn_var), gyro_gain_error=k
        )

    @property
    def typical_changes(self) -> np.ndarray:
        """(35,) a large but sane change of each θ component in one optimiser step
        (:func:`typical_changes`)."""
        return typical_changes()

    @property
    def n_samples(self) -> int:
        return len(self.data)

    @functools.cached_property
    def _tape(self) -> np.ndarray:
        # One reverse-mode workspace for all gradients on this problem.
        return mekf.new_tape(len(self.data))

    @functools.cached_property
    def _typical(self) -> np.ndarray:
        # Finite-difference step scales: θ₀'s magnitudes, for parameters near zero 1e-3.
        return np.maximum(np.abs(self.theta0), 1e-3)

    def negative_log_likelihood(self, theta: np.ndarray) -> float:
        """V(θ) alone (nats); NaN when the filter breaks down."""
        return negative_log_likelihood(theta, self.data)

    def negative_log_likelihood_and_gradient(self, theta: np.ndarray) -> tuple[float, np.ndarray]:
        """V(θ) alone and its exact gradient (35,)."""
        return negative_log_likelihood_and_gradient(theta, self.data, self._tape)

    def prior(self, theta: np.ndarray) -> tuple[float, np.ndarray]:
        """The priors' negative log density (up to a constant) and its gradient (35,)."""
        r = theta - self.prior_mean
        with np.errstate(over="ignore"):  # a trial point far out: an infinite cost, refused
            value = 0.5 * float(np.sum(self.prior_precision * r * r))
        grad = self.prior_precision * r
        if self.misalignment_sigma_rad is not None:
            v, g = misalignment_penalty(
                theta[params.SLICE_D], self.misalignment_reference, self.misalignment_sigma_rad
            )
            value += v
            grad[params.SLICE_D] += g
        return value, grad

    def prior_curvature(self, theta: np.ndarray) -> np.ndarray:
        """The priors' Hessian (35, 35): their diagonal precision, plus the misalignment
        prior's curvature by central differences of its exact gradient."""
        H = np.diag(self.prior_precision)
        if self.misalignment_sigma_rad is not None:
            D = np.asarray(theta[params.SLICE_D], dtype=float)
            h = 1e-6
            block = np.empty((9, 9))
            for k in range(9):
                e = np.zeros(9)
                e[k] = h
                g_hi = misalignment_penalty(
                    D + e, self.misalignment_reference, self.misalignment_sigma_rad
                )[1]
                g_lo = misalignment_penalty(
                    D - e, self.misalignment_reference, self.misalignment_sigma_rad
                )[1]
                block[:, k] = (g_hi - g_lo) / (2.0 * h)
            H[params.SLICE_D, params.SLICE_D] += 0.5 * (block + block.T)
        return H

    def cost_gradient_and_information(
        self, theta: np.ndarray
    ) -> tuple[float, np.ndarray, np.ndarray]:
        """V(θ) + prior, its exact gradient (35,) and the curvature a Gauss–Newton step
        uses (35, 35): the Fisher information of V (forward sensitivities of the filter,
        ``mekf.fisher_information``) plus the priors' exact Hessian. On a non-finite V the
        gradient is NaN."""
        theta = np.asarray(theta, dtype=float)
        J = params.model_jacobian(theta)
        value, info, grad = mekf.fisher_information(params.unpack(theta), self.data, J.T)
        if not np.isfinite(value):
            return value, np.full(theta.shape, np.nan), np.zeros((theta.size, theta.size))
        pv, pg = self.prior(theta)
        return value + pv, grad + pg, info + self.prior_curvature(theta)

    def cost(self, theta: np.ndarray) -> float:
        """V(θ) + prior: the objective of the ML step."""
        return negative_log_likelihood(theta, self.data) + self.prior(theta)[0]

    def cost_and_gradient(self, theta: np.ndarray) -> tuple[float, np.ndarray]:
        """V(θ) + prior and its exact gradient (35,)."""
        v, g = negative_log_likelihood_and_gradient(theta, self.data, self._tape)
        pv, pg = self.prior(theta)
        return v + pv, g + pg

    def cost_and_numeric_gradient(self, theta: np.ndarray) -> tuple[float, np.ndarray]:
        """V(θ) + prior and its gradient by forward differences (n_θ + 1 filter passes)."""
        v = negative_log_likelihood(theta, self.data)
        g = numeric_gradient(theta, self.data, "forward", typical=self._typical, value=v)
        pv, pg = self.prior(theta)
        return v + pv, g + pg

    def numeric_gradient(self, theta: np.ndarray, scheme: str = "forward") -> np.ndarray:
        """∂V/∂θ alone by finite differences, ``scheme`` "forward" or "central"; steps
        scaled by θ₀'s magnitudes."""
        return numeric_gradient(theta, self.data, scheme, typical=self._typical)

    def model_params(self, theta: np.ndarray) -> ModelParams:
        """θ (35,) normalised → the model in raw magnetometer units."""
        p = params.unpack(theta).unscaled_magnetometer(self.norm.centre, self.norm.scale)
        return dataclasses.replace(p, gyro_gain_error=self.gyro_gain_error)

    def run_filter(self, theta: np.ndarray) -> mekf.FilterOutput:
        """The filter at θ (35,) normalised, with all diagnostics (attitude, innovations)."""
        return mekf.run_filter(params.unpack(theta), self.data)

    def run_filter_raw(self, p: ModelParams) -> mekf.FilterOutput:
        """The filter at ``p`` in raw magnetometer units (normalised here, not through θ)."""
        return mekf.run_filter(p.scaled_magnetometer(self.norm.centre, self.norm.scale), self.data)
