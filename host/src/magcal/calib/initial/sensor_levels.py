# SPDX-License-Identifier: Apache-2.0
"""What a session says about its sensors before any calibration: the data-only levels.

One function, :func:`measure_sensor_levels`, computes them for every step that needs them
(the initial estimate and the likelihood problem), from the readings alone:

* the longest stationary stretch, and from it (or from priors) the gyroscope bias and the
  noise covariances (``rest.py``);
* the gravity magnitude g, the median accelerometer norm, so that a small accelerometer
  scale error or local gravity does not bias the inclination;
* the sample rate;
* the accelerometer bump inflation ``c_t`` (:func:`accelerometer_extra_variance`);
* how uncertain each step's integrated turn is, the rate having left a straight line
  within the step (:func:`turn_variance`), and the size of that turn, which an error of
  the gyroscope's gain is proportional to (:func:`turn_squared`);
* the time over which the accelerometer's errors stay correlated, and from it the samples
  whose accelerometer reading the likelihood uses (:func:`accelerometer_updates`);
* Σ_a for the ML step: the accelerometer noise plus the motion's acceleration.

None of them depends on the calibration θ, so the likelihood stays smooth in θ.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from magcal.calib.initial import rest
from magcal.io.session import Session

#: Accelerometer outliers ("bumps"): a sample whose norm deviates from g by more than
#: 3σ plus this much (m/s²) is not explained by noise or by the smooth accelerations of a
#: calibration motion, which the ML step absorbs in Σ_a instead. Spreading distrust over
#: smooth accelerations too was measured to make the misalignment worse, not better.
BUMP_THRESHOLD_M_S2 = 0.5
#: Half-width of the window over which a bump's inflation is spread, s: a knock rings for
#: a few samples, and its norm deviation can pass through zero while it does.
BUMP_WINDOW_S = 0.05
#: Inflation per unit squared excess deviation. A horizontal knock of size b changes the
#: norm by only ≈ b²/2g, far less than b, so the excess understates it: weight it up.
BUMP_GAIN = 10.0


#: Lags (s) over which the autocorrelation of the accelerometer norm is summed at most: a
#: hand's accelerations decorrelate within a second; a longer sum only adds the noise of
#: the estimate.
MAX_CORRELATION_LAG_S = 2.0


def acceleration_correlation_time_s(t: np.ndarray, acc: np.ndarray, g: float) -> float:
    """The integral time scale (s) of the accelerometer's error, seen in ``‖y_a‖ − g``.

    The model ``y_a = −R_bn g_n + e_a`` takes ``e_a`` as white, but a hand's translational
    accelerations are correlated over a few tenths of a second. The integral time scale
    ``T (1 + 2 Σ_k ρ_k)`` (T the sample interval, ρ_k the autocorrelation at lag k, summed up
    to its first zero crossing and at most :data:`MAX_CORRELATION_LAG_S`) is the spacing at
    which samples count as independent: white sensor noise gives one sample interval, a
    sensor held still or turned gently hardly more.

    t : (N,) s; acc : (N, 3) m/s²; g : m/s². Returns seconds, at least one sample interval.
    """
    dt = float(np.median(np.diff(t))) if len(t) > 1 else 0.0
    dev = np.linalg.norm(acc, axis=1) - g
    dev = dev - dev.mean()
    n = dev.shape[0]
    if n < 3 or not np.any(dev):
        return dt
    spectrum = np.fft.rfft(dev, 2 * n)
    rho = np.fft.irfft(spectrum * np.conj(spectrum))[:n]
    rho /= rho[0]
    max_lag = min(n - 1, max(1, int(MAX_CORRELATION_LAG_S / dt)))
    rho = rho[1 : max_lag + 1]
    crossing = np.flatnonzero(rho <= 0.0)
    lags = rho[: crossing[0]] if crossing.size else rho
    return dt * (1.0 + 2.0 * float(lags.sum()))


def accelerometer_updates(t: np.ndarray, correlation_time_s: float) -> np.ndarray:
    """Which samples' accelerometer readings the likelihood uses: (N,) bool.

    One per ``correlation_time_s`` (the first sample, then each first sample at least that
    long after the last one used). Using every sample would count one acceleration episode
    as dozens of independent measurements of the tilt, and the likelihood then explains it
    by tilting the attitude, through the gyroscope bias and the misalignment. Readings spaced
    by the errors' time scale are nearly independent, as the model assumes; with white
    errors every sample is used. The gyroscope still propagates, and the magnetometer
    updates, at every sample.
    """
    t = np.asarray(t, dtype=float)
    used = np.zeros(t.shape[0], dtype=bool)
    if t.shape[0] == 0:
        return used
    # Half a sample interval of slack, so that a uniform rate keeps every k-th sample.
    dt = float(np.median(np.diff(t))) if t.shape[0] > 1 else 0.0
    spacing = max(correlation_time_s - 0.5 * dt, 0.0)
    next_t = -np.inf
    for i, ti in enumerate(t):
        if ti >= next_t:
            used[i] = True
            next_t = ti + spacing
    return used


def accelerometer_extra_variance(
    acc: np.ndarray, g: float, sigma_acc: float, rate_hz: float
) -> np.ndarray:
    """Data-only inflation ``c_t`` (m/s²)² of Σ_a for accelerometer outliers (bumps).

    The model ``y_a = −R_bn g_n + e_a`` has no room for a knock: a filter that trusts such a
    sample tilts its attitude and, through it, the misalignment estimate. ``c_t`` is
    ``BUMP_GAIN`` times the largest squared excess of ``|‖y_a‖ − g|`` over
    ``3σ + BUMP_THRESHOLD_M_S2`` within ±``BUMP_WINDOW_S``; clean samples get 0. It
    depends on the data only, never on θ, so the cost stays smooth in θ.

    acc : (N, 3) m/s²; g : m/s²; sigma_acc : accelerometer noise std, m/s²; rate_hz : Hz.
    Returns (N,) (m/s²)².
    """
    dev = np.abs(np.linalg.norm(acc, axis=1) - g)
    excess = np.maximum(dev - (3.0 * sigma_acc + BUMP_THRESHOLD_M_S2), 0.0)
    half = max(1, int(round(BUMP_WINDOW_S * rate_hz)))
    padded = np.pad(excess, half, mode="edge")
    windows = np.lib.stride_tricks.sliding_window_view(padded, 2 * half + 1)
    return BUMP_GAIN * windows.max(axis=1) ** 2


def turn_variance(t: np.ndarray, gyr: np.ndarray, Sigma_gyr: np.ndarray) -> np.ndarray:
    """Data-only uncertainty (N,) rad² of the turn that each step integrates.

    The filter holds each gyroscope sample over the step that follows it: ``gyr[k−1]`` from
    t_{k−1} to t_k. A rate that changes along a straight line across the samples makes that
    turn short by ``½ Δω T`` at every step: a constant half-step delay, which the
    magnetometer's time offset takes up. What no sample tells is how the rate left that
    line within the step. A rate that jumps by Δω at a random time within it (the start of
    a flip, a knock) leaves the turn uncertain by a variance ``|Δω|² T² / 12``, and shows
    as second differences (``rest.second_differences``) of size |Δω| at the step's two
    ends. So the step to sample k gets ``T_k² / 12`` times the mean of the squared second
    differences at its two ends, less what the gyroscope's white noise makes of them on
    its own (``6 tr Σ_ω``, already in the model), never below 0: 0 for smooth motion.

    The gyroscope's noise Σ_ω cannot stand in for it: measured at rest, where the rate does
    not change, it can be the quantisation alone. Without this term the likelihood raised
    one axis's σ_ω 27 to 270 times on real hand-held recordings, and ArduPilot SITL's
    calibration-stand flips needed the same (``bench/real.md``; tests/autopilot_sitl).

    t : (N,) s; gyr : (N, 3) rad/s; Sigma_gyr : (3, 3) (rad/s)², the gyroscope's white
    noise. Returns (N,) rad² (0 at the first sample, whose step is not taken).
    """
    v = np.zeros(len(t))
    if len(t) < 3:
        return v
    bend = np.zeros(len(t))  # |second difference|² beyond the noise's share, per sample
    bend[1:-1] = np.sum(rest.second_differences(gyr) ** 2, axis=1)
    noise_share = rest.SECOND_DIFFERENCE_NOISE_GAIN * float(np.trace(Sigma_gyr))
    bend = np.maximum(bend - noise_share, 0.0)
    v[1:] = 0.5 * (bend[1:] + bend[:-1]) * np.diff(t) ** 2 / 12.0
    return v


def turn_squared(t: np.ndarray, gyr: np.ndarray) -> np.ndarray:
    """The squared size (N,) rad² of the turn each step integrates, ``|ω|² T²`` with the
    gyroscope sample held over the step that follows it.

    A gyroscope gain off the identity by ΔG turns the step's rotation by ``ΔG ω T``; with
    ΔG's entries independent of 1-σ k, each axis of that turn has variance ``k² |ω|² T²``,
    which is k² times this (``problem.GYRO_GAIN_ERROR``). Returns 0 at the first sample,
    whose step is not taken.
    """
    v = np.zeros(len(t))
    if len(t) >= 2:
        v[1:] = np.sum(gyr[:-1] ** 2, axis=1) * np.diff(t) ** 2
    return v


def _steps_at_rows(row_t: np.ndarray, imu_t: np.ndarray, v_imu: np.ndarray) -> np.ndarray:
    """A variance per step of the IMU's samples (``v_imu`` at times ``imu_t``:
    :func:`turn_variance`, :func:`turn_squared`) spread over a multi-rate session's rows
    (``row_t``): the rows between two IMU samples share that step's variance in proportion
    to their own steps (a random walk), so that it sums to the IMU's whatever other
    streams' rows fall in between."""
    out = np.zeros(len(row_t))
    if len(row_t) < 2 or len(imu_t) < 2:
        return out
    step = np.diff(row_t)
    i = np.searchsorted(imu_t, row_t[1:], side="left")  # the IMU sample ending each row's step
    inside = (i > 0) & (i < len(imu_t))
    i = i[inside]
    span = imu_t[i] - imu_t[i - 1]
    share = np.divide(step[inside], span, out=np.zeros_like(span), where=span > 0)
    out[1:][inside] = v_imu[i] * share
    return out


@dataclass(frozen=True)
class SensorLevels:
    """The data-only levels of one session.

    noise         : gyroscope bias and noise covariances, from the stationary stretch
                    (``noise.stationary``) or from priors (``rest.NoiseInit``)
    g             : gravity magnitude, m/s² (median accelerometer norm)
    rate_hz       : mean sample rate, Hz (the IMU's rows in a multi-rate session)
    acc_extra_var : (N,) (m/s²)², the bump inflation c_t of Σ_a
    turn_var      : (N,) rad², how uncertain each step's integrated turn is
                    (:func:`turn_variance`)
    turn_sq       : (N,) rad², the squared size of each step's turn (:func:`turn_squared`)
    acc_correlation_s : s, the accelerometer errors' integral time scale
                    (:func:`acceleration_correlation_time_s`)
    acc_used      : (N,) bool, the samples whose accelerometer reading the likelihood uses
                    (:func:`accelerometer_updates`)
    Sigma_acc     : (3, 3) (m/s²)², Σ_a for the ML step: ``noise.Sigma_acc`` plus the
                    motion's acceleration share (isotropic)
    """

    noise: rest.NoiseInit
    g: float
    rate_hz: float
    acc_extra_var: np.ndarray
    turn_var: np.ndarray
    turn_sq: np.ndarray
    acc_correlation_s: float
    acc_used: np.ndarray
    Sigma_acc: np.ndarray

    def turn_var_with_gain_error(self, k: float) -> np.ndarray:
        """(N,) rad², each step's turn variance allowing for a gyroscope gain error of 1-σ
        ``k`` per entry (:func:`turn_squared`): ``turn_var + k² turn_sq``."""
        return self.turn_var + k**2 * self.turn_sq

    @property
    def stationary_samples(self) -> int:
        """Samples of the stationary stretch the noise was measured on (0: none)."""
        still = self.noise.stationary
        return 0 if still is None else still.stop - still.start


def measure_sensor_levels(session: Session) -> SensorLevels:
    """The data-only levels of ``session`` (see :class:`SensorLevels`).

    On a multi-rate session each stream is measured at its own rate: the stationary stretch,
    the gyroscope's and the accelerometer's levels on the rows with the accelerometer (the
    IMU's rows), the magnetometer's noise on its own samples within that stretch's time
    span; the per-row arrays have the session's length (no update where no accelerometer).
    Raises ``InsufficientDataError`` as ``rest.initial_noise_and_bias`` does.
    """
    if not session.multi_rate:
        return _measure(session.t, session.gyr, session.acc, session.mag)
    imu = session.has_acc
    has_mag = session.has_mag
    t = session.t[imu]
    # The magnetometer at the IMU's rows, for the stationary test's drift check only.
    mag_at = np.column_stack(
        [np.interp(t, session.t[has_mag], session.mag[has_mag, j]) for j in range(3)]
    )
    levels = _measure(t, session.gyr[imu], session.acc[imu], mag_at)
    noise = levels.noise
    mag = session.mag[has_mag]
    prior_std = rest.MAG_NOISE_PRIOR_FRACTION * rest._mag_scale(mag)
    Sigma_mag = prior_std**2 * np.eye(3)
    if noise.stationary is not None:
        t0, t1 = t[noise.stationary.start], t[noise.stationary.stop - 1]
        still = (session.t[has_mag] >= t0) & (session.t[has_mag] <= t1)
        if still.sum() >= rest.MIN_COVARIANCE_SAMPLES:
            floor = np.maximum(rest.NOISE_FLOOR_FRACTION * prior_std, rest._lsb(mag) / np.sqrt(12))
            Sigma_mag = rest._floored_cov(mag[still], floor)
    noise = dataclasses.replace(noise, Sigma_mag=Sigma_mag)

    def spread(x: np.ndarray, fill) -> np.ndarray:
        out = np.full(len(session), fill, dtype=x.dtype)
        out[imu] = x
        return out

    return dataclasses.replace(
        levels,
        noise=noise,
        acc_extra_var=spread(levels.acc_extra_var, 0.0),
        turn_var=_steps_at_rows(session.t, t, levels.turn_var),
        turn_sq=_steps_at_rows(session.t, t, levels.turn_sq),
        acc_used=spread(levels.acc_used, False),
    )


def _measure(t: np.ndarray, gyr: np.ndarray, acc: np.ndarray, mag: np.ndarray) -> SensorLevels:
    """The levels of single-rate data (every row has every sensor)."""
    still = rest.find_stationary(t, gyr, acc, mag)
    noise = rest.initial_noise_and_bias(t, gyr, acc, mag, still)
    g = float(np.median(np.linalg.norm(acc, axis=1)))
    rate_hz = (len(t) - 1) / float(t[-1] - t[0])
    sigma_acc = float(np.sqrt(np.trace(noise.Sigma_acc) / 3.0))
    acc_extra_var = accelerometer_extra_variance(acc, g, sigma_acc, rate_hz)
    # The ML step starts with e_a as sensor noise plus the acceleration of the motion (its
    # share on top of the noise measured at rest, isotropic). The inertial attitude of the
    # initial estimate keeps the noise alone: it down-weights accelerated samples itself,
    # and with the larger Σ_a its misalignment was worse on accelerated MEMS sessions
    # (`make accuracy`, init 0.11° → 0.16°) though better on hand-held ones (1.19° → 0.89°).
    shake = rest.motion_acceleration_variance(acc, g, noise.stationary)
    Sigma_acc = noise.Sigma_acc + max(0.0, shake - sigma_acc**2) * np.eye(3)
    acc_correlation_s = acceleration_correlation_time_s(t, acc, g)
    return SensorLevels(
        noise=noise,
        g=g,
        rate_hz=rate_hz,
        acc_extra_var=acc_extra_var,
        turn_var=turn_variance(t, gyr, noise.Sigma_gyr),
        turn_sq=turn_squared(t, gyr),
        acc_correlation_s=acc_correlation_s,
        acc_used=accelerometer_updates(t, acc_correlation_s),
        Sigma_acc=Sigma_acc,
    )
