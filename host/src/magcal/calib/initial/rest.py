# SPDX-License-Identifier: Apache-2.0
"""Step 1a of Kok & Schön (2016), Section 6: gyro bias and noise covariances.

The paper takes them from "a short batch of stationary data" at the start of the recording,
or from prior sensor knowledge. Hand-held recordings often have no stationary start, so:

* :func:`find_stationary` looks for the longest stationary stretch *anywhere* in the session;
* :func:`initial_noise_and_bias` estimates from it, or falls back to conservative priors
  (the maximum-likelihood step estimates bias and covariances afterwards anyway).

A stretch is stationary when, over moving windows of :data:`WINDOW_S`,

1. the gyro *variation* (per-axis standard deviation, not the magnitude: a constant bias is
   allowed) and the accelerometer variation are at the noise floor — a few times the
   quietest windows' level, capped by absolute limits (raised for sensors whose white noise,
   seen in second differences, is larger);
2. the mean gyro magnitude is below :data:`GYRO_BIAS_MAX_RAD_S` (faster is no bias);
3. the accelerometer norm is near gravity;

and, over the whole stretch, the accelerometer direction (and the magnetometer reading, when
given) does not drift. The last test rejects a slow constant-rate rotation, which the gyro
alone cannot tell from a bias; a rotation about the vertical leaves the accelerometer
unchanged and only the magnetometer reveals it. A stretch failing it is trimmed at the edge
that deviates more (a slow start of motion leaks into the edge windows), by at most
:data:`MAX_EDGE_TRIM_WINDOWS` windows per edge.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np

from magcal.calib.frames import GRAVITY_M_S2
from magcal.errors import InsufficientDataError

# --- detection ---------------------------------------------------------------------------

#: Length of the moving window, seconds.
WINDOW_S = 0.5
#: Fewest samples in a window (for slow sample rates), samples.
WINDOW_MIN_SAMPLES = 10
#: Shortest accepted stretch: at least MIN_STATIONARY_SAMPLES samples *or* at least
#: MIN_STATIONARY_S seconds (the paper's Table 2 sessions rest for 100 samples); never less
#: than WINDOW_MIN_SAMPLES samples.
MIN_STATIONARY_S = 1.0
MIN_STATIONARY_SAMPLES = 50
#: Noise floor = this quantile of the windows' variation (the quietest windows) ...
NOISE_FLOOR_QUANTILE = 0.05
#: ... and a window is quiet when its variation is below this multiple of the floor
#: (a window standard deviation scatters by ~10 % for 50 samples; 4× is a safe margin).
NOISE_FLOOR_FACTOR = 4.0
#: Absolute limits on the per-axis RMS standard deviation of a quiet window. The upper limits
#: guard against calling the quietest part of a session without any rest "stationary"; they
#: are raised to NOISE_FLOOR_FACTOR × the white-noise level seen in second differences for
#: a noisy sensor (the paper's Table 2 has gyro σ up to 0.1 rad/s and accelerometer σ up to
#: 0.3 m/s²). The lower limits keep quantised sensors (which can read constant) from getting
#: a zero threshold.
GYR_STD_MAX_RAD_S = 0.02
GYR_STD_MIN_RAD_S = 2e-3
ACC_STD_MAX_M_S2 = 0.1
ACC_STD_MIN_M_S2 = 0.02
#: A gyro bias of an uncalibrated MEMS gyro stays below about 5 °/s; a larger constant rate
#: is a rotation. rad/s.
GYRO_BIAS_MAX_RAD_S = 0.1
#: Tolerance on the accelerometer norm at rest (uncalibrated accelerometers are off by a few
#: per cent of g), m/s².
ACC_NORM_TOL_M_S2 = 1.0
#: A drift over a stretch is rejected when it is statistically significant (χ² with 3
#: degrees of freedom above this: p < 1e-8 for white noise) *and* larger than an absolute
#: floor: the accelerometer direction turning by more than ACC_DRIFT_MIN_RAD, or the
#: magnetometer changing by more than MAG_DRIFT_MIN_FRACTION of the field scale.
DRIFT_CHI2_MAX = 40.0
ACC_DRIFT_MIN_RAD = 0.005
MAG_DRIFT_MIN_FRACTION = 0.005

#: Most a stretch's edge may be trimmed to pass the drift tests, in windows.
MAX_EDGE_TRIM_WINDOWS = 2

# --- priors (used without a stationary stretch) --------------------------------------------

#: Gyro noise standard deviation prior, rad/s per axis (conservative for MEMS gyros).
GYR_NOISE_PRIOR_RAD_S = 0.01
#: Accelerometer noise standard deviation prior, m/s² per axis.
ACC_NOISE_PRIOR_M_S2 = 0.1
#: Magnetometer noise standard deviation prior, as a fraction of the median field norm about
#: the data centre (dimensionless; the unit of the data is arbitrary).
MAG_NOISE_PRIOR_FRACTION = 0.01
#: Floor on each estimated standard deviation, as a fraction of the prior: a quantised sensor
#: at rest can read constant, which would give a singular covariance.
NOISE_FLOOR_FRACTION = 0.05
#: Fewest samples to estimate covariances from.
MIN_COVARIANCE_SAMPLES = 10


@dataclass(frozen=True, eq=False)
class NoiseInit:
    """Initial gyro bias and noise covariances.

    gyro_bias : (3,) float, rad/s
    Sigma_gyr : (3, 3) float, (rad/s)², gyro noise covariance
    Sigma_acc : (3, 3) float, (m/s²)², accelerometer noise covariance
    Sigma_mag : (3, 3) float, (raw magnetometer units)², magnetometer noise covariance
    source    : ``"stationary"`` (estimated from ``stationary``) or ``"prior"``
    stationary: the stretch used, or None
    """

    gyro_bias: np.ndarray
    Sigma_gyr: np.ndarray
    Sigma_acc: np.ndarray
    Sigma_mag: np.ndarray
    source: Literal["stationary", "prior"]
    stationary: slice | None = None


# --------------------------------------------------------------------------- helpers


def _check_xyz(name: str, x: np.ndarray, n: int) -> np.ndarray:
    x = np.asarray(x, dtype=float)
    if x.shape != (n, 3):
        raise ValueError(f"{name} must have shape ({n}, 3), got {x.shape}")
    return x


def _moving_mean_var(x: np.ndarray, w: int) -> tuple[np.ndarray, np.ndarray]:
    """Mean and (biased) variance of each length-``w`` window: x (N, d) → 2 × (N−w+1, d).

    Cumulative sums of data centred on their median (to limit cancellation).
    """
    x = x - np.median(x, axis=0)
    zero = np.zeros((1, x.shape[1]))
    s1 = np.concatenate([zero, np.cumsum(x, axis=0)])
    s2 = np.concatenate([zero, np.cumsum(x * x, axis=0)])
    mean = (s1[w:] - s1[:-w]) / w
    var = (s2[w:] - s2[:-w]) / w - mean * mean
    return mean, np.clip(var, 0.0, None)


def white_noise_std(x: np.ndarray) -> float:
    """White-noise standard deviation of consecutive samples x (N, 3), their unit, RMS over
    the axes (0.0 for N < 3). Second differences (:func:`second_differences`) cancel an
    offset and any motion that is smooth at the sample rate (1 rad/s at 100 Hz leaves 1e-4
    of a magnetometer's field) and keep white noise of variance 6σ²; the robust spread
    (1.4826 × median |·|) ignores the rare jumps."""
    x = np.asarray(x, dtype=float)
    if x.shape[0] < 3:
        return 0.0
    d2 = second_differences(x)
    sigma = 1.4826 * np.median(np.abs(d2), axis=0) / np.sqrt(SECOND_DIFFERENCE_NOISE_GAIN)
    return float(np.sqrt(np.mean(sigma * sigma)))


def _threshold(std: np.ndarray, x: np.ndarray, lo: float, hi: float) -> float:
    """Quiet-window threshold: NOISE_FLOOR_FACTOR × the quietest windows' level, at least
    ``lo``, at most ``hi`` (raised for a sensor whose white noise alone exceeds it)."""
    floor = float(np.quantile(std, NOISE_FLOOR_QUANTILE))
    hi = max(hi, NOISE_FLOOR_FACTOR * white_noise_std(x))
    return float(np.clip(NOISE_FLOOR_FACTOR * floor, lo, hi))


def _runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """Maximal runs ``[start, stop)`` of True."""
    d = np.diff(np.concatenate([[0], mask.astype(np.int8), [0]]))
    starts = np.flatnonzero(d == 1)
    stops = np.flatnonzero(d == -1)
    return list(zip(starts.tolist(), stops.tolist(), strict=True))


def _drift(t: np.ndarray, x: np.ndarray) -> tuple[float, float]:
    """Linear trend of x (n, 3) over t (n,): total change over the stretch (norm, x units)
    and its χ² statistic (3 degrees of freedom for white noise without a trend)."""
    tc = t - t.mean()
    stt = float(tc @ tc)
    xc = x - x.mean(axis=0)
    slope = tc @ xc / stt
    resid = xc - np.outer(tc, slope)
    var = np.sum(resid * resid, axis=0) / max(len(t) - 2, 1)
    scale2 = np.mean(x * x) * 1e-24 + 1e-300  # keeps a constant (quantised) signal finite
    chi2 = float(np.sum(slope * slope * stt / np.maximum(var, scale2)))
    return float(np.linalg.norm(slope) * (t[-1] - t[0])), chi2


# --------------------------------------------------------------------------- public API


def find_stationary(
    t: np.ndarray,
    gyr: np.ndarray,
    acc: np.ndarray,
    mag: np.ndarray | None = None,
) -> slice | None:
    """The longest stationary stretch of a session, anywhere in it, or None.

    t   : (N,) float, s, increasing
    gyr : (N, 3) float, rad/s
    acc : (N, 3) float, m/s²
    mag : optional (N, 3) float, raw magnetometer units; when given, a slow rotation about
          the vertical (invisible to gyro variation and accelerometer) is rejected too.

    Returns ``slice(start, stop)`` into the sample arrays, with at least
    :data:`MIN_STATIONARY_SAMPLES` samples or :data:`MIN_STATIONARY_S` long, or None when
    there is no such stretch. See the module docstring for the tests.
    """
    t = np.asarray(t, dtype=float)
    n = t.shape[0]
    gyr = _check_xyz("gyr", gyr, n)
    acc = _check_xyz("acc", acc, n)
    if mag is not None:
        mag = _check_xyz("mag", mag, n)
    if n < WINDOW_MIN_SAMPLES:
        return None
    dt = float(np.median(np.diff(t)))
    if not dt > 0.0:
        return None
    w = max(WINDOW_MIN_SAMPLES, round(WINDOW_S / dt))
    if n < w:
        return None

    g_mean, g_var = _moving_mean_var(gyr, w)
    a_mean, a_var = _moving_mean_var(acc, w)
    g_mean += np.median(gyr, axis=0)
    a_mean += np.median(acc, axis=0)
    g_std = np.sqrt(np.mean(g_var, axis=1))  # per-axis RMS standard deviation
    a_std = np.sqrt(np.mean(a_var, axis=1))
    g_thr = _threshold(g_std, gyr, GYR_STD_MIN_RAD_S, GYR_STD_MAX_RAD_S)
    a_thr = _threshold(a_std, acc, ACC_STD_MIN_M_S2, ACC_STD_MAX_M_S2)
    quiet = (
        (g_std <= g_thr)
        & (a_std <= a_thr)
        & (np.linalg.norm(g_mean, axis=1) <= GYRO_BIAS_MAX_RAD_S)
        & (np.abs(np.linalg.norm(a_mean, axis=1) - GRAVITY_M_S2) <= ACC_NORM_TOL_M_S2)
    )
    # Samples covered by a quiet window.
    cover = np.zeros(n + 1, dtype=np.int64)
    idx = np.flatnonzero(quiet)
    np.add.at(cover, idx, 1)
    np.add.at(cover, idx + w, -1)
    stationary = np.cumsum(cover[:n]) > 0

    if mag is not None:
        mag_c = mag - mag.mean(axis=0)
        mag_scale = float(np.sqrt(np.mean(np.sum(mag_c * mag_c, axis=1))))

    def long_enough(start: int, stop: int) -> bool:
        count = stop - start
        return count >= WINDOW_MIN_SAMPLES and (
            count >= MIN_STATIONARY_SAMPLES or t[stop - 1] - t[start] >= MIN_STATIONARY_S
        )

    def steady(sl: slice) -> bool:
        """Whole-stretch tests: no rotation posing as a bias, no drift."""
        if np.linalg.norm(gyr[sl].mean(axis=0)) > GYRO_BIAS_MAX_RAD_S:
            return False
        ts = t[sl]
        change, chi2 = _drift(ts, acc[sl])
        a_norm = float(np.linalg.norm(acc[sl].mean(axis=0)))
        if chi2 > DRIFT_CHI2_MAX and change > ACC_DRIFT_MIN_RAD * a_norm:
            return False
        if mag is not None:
            change, chi2 = _drift(ts, mag[sl])
            if chi2 > DRIFT_CHI2_MAX and change > MAG_DRIFT_MIN_FRACTION * mag_scale:
                return False
        return True

    signals = [gyr, acc] if mag is None else [gyr, acc, mag]

    def edge_deviation(sl: slice, edge: slice) -> float:
        """How far an edge's mean is from the stretch's median, in robust noise units."""
        total = 0.0
        for x in signals:
            med = np.median(x[sl], axis=0)
            sigma = 1.4826 * np.median(np.abs(x[sl] - med), axis=0) + 1e-12 * (1.0 + np.abs(med))
            total += float(np.linalg.norm((x[edge].mean(axis=0) - med) / sigma))
        return total

    # A gradual start of motion leaks into the edge windows: trim a quarter window at an
    # edge that is not the end of the data; then, while the whole-stretch tests fail, trim
    # the edge that deviates more, by a half window at a time and at most MAX_EDGE_TRIM_WINDOWS
    # windows per edge: a slow motion onset is cut away, while a stretch that drifts
    # throughout (a slow constant-rate rotation) is rejected rather than shrunk until its
    # drift is too small to detect.
    trim = w // 4
    runs = []
    for start, stop in _runs(stationary):
        start = start + (trim if start > 0 else 0)
        stop = stop - (trim if stop < n else 0)
        if long_enough(start, stop):
            runs.append((start, stop))
    runs.sort(key=lambda r: r[1] - r[0], reverse=True)

    best: slice | None = None
    max_trim = MAX_EDGE_TRIM_WINDOWS * w
    for run_start, run_stop in runs:
        if best is not None and run_stop - run_start <= best.stop - best.start:
            break
        start, stop = run_start, run_stop
        while long_enough(start, stop):
            if steady(slice(start, stop)):
                if best is None or stop - start > best.stop - best.start:
                    best = slice(start, stop)
                break
            cut = max(w // 2, 1)
            can_head = start + cut - run_start <= max_trim
            can_tail = run_stop - (stop - cut) <= max_trim
            if not (can_head or can_tail):
                break
            head = edge_deviation(slice(start, stop), slice(start, start + cut))
            tail = edge_deviation(slice(start, stop), slice(stop - cut, stop))
            if can_tail and (tail >= head or not can_head):
                stop -= cut
            else:
                start += cut
    return best


def _lsb(x: np.ndarray) -> np.ndarray:
    """Per-axis resolution estimate: the smallest non-zero step between samples, (3,).
    Zero for a signal that never changes."""
    d = np.abs(np.diff(x, axis=0))
    d = np.where(d > 0.0, d, np.inf)
    lsb = d.min(axis=0) if d.shape[0] else np.full(x.shape[1], np.inf)
    return np.where(np.isfinite(lsb), lsb, 0.0)


def _floored_cov(x: np.ndarray, floor_std: np.ndarray) -> np.ndarray:
    """Sample covariance of x (n, 3) with each variance floored at ``floor_std²`` and all
    eigenvalues at ``min(floor_std)²`` (so the result is positive definite)."""
    cov = np.atleast_2d(np.cov(x, rowvar=False))
    cov = 0.5 * (cov + cov.T)
    floor_var = floor_std**2
    cov = cov + np.diag(np.clip(floor_var - np.diag(cov), 0.0, None))
    lam, v = np.linalg.eigh(cov)
    lam = np.maximum(lam, float(floor_var.min()))
    return (v * lam) @ v.T


def _mag_scale(mag: np.ndarray) -> float:
    """Median field norm about the data centre (the mean), raw units; 1.0 if zero."""
    r = np.linalg.norm(mag - mag.mean(axis=0), axis=1)
    s = float(np.median(r))
    return s if s > 0.0 else 1.0


#: The variance of a second difference of white noise of variance σ²: 6σ².
SECOND_DIFFERENCE_NOISE_GAIN = 6.0


def second_differences(x: np.ndarray) -> np.ndarray:
    """``x[t+1] − 2 x[t] + x[t−1]`` (N − 2, ...) of samples x (N, ...): they cancel an offset
    and any motion that is smooth at the sample rate, and leave white noise of variance
    :data:`SECOND_DIFFERENCE_NOISE_GAIN` σ²."""
    return x[2:] - 2.0 * x[1:-1] + x[:-2]


def gyro_noise_from_differences(gyr: np.ndarray, floor_std: np.ndarray | float = 0.0) -> np.ndarray:
    """Gyroscope white-noise covariance (3, 3), (rad/s)², measured during motion.

    Second differences (:func:`second_differences`) cancel the bias and any motion that is
    smooth at the sample rate (at 100 Hz a hand's angular jerk leaves ~1e-3 rad/s there)
    and leave white noise of variance 6σ². A robust spread (1.4826 × median absolute
    deviation) ignores the rare jerks of knocks. Axes are taken as uncorrelated.

    gyr : (N, 3) rad/s, N ≥ 3; floor_std : lowest σ per axis, rad/s (quantisation).
    """
    d2 = second_differences(gyr)
    mad = np.median(np.abs(d2 - np.median(d2, axis=0)), axis=0)
    std = np.maximum(
        1.4826 * mad / np.sqrt(SECOND_DIFFERENCE_NOISE_GAIN), np.maximum(floor_std, 1e-6)
    )
    return np.diag(std**2)


def motion_acceleration_variance(acc: np.ndarray, g: float, stationary: slice | None) -> float:
    """Per-axis variance (m/s²)² of the translational acceleration during motion.

    The model's e_a must carry the hand's acceleration as well as the sensor noise: a
    filter that starts with only the noise measured at rest reads a 0.3 m/s² shake as a
    10σ tilt at every sample, and the ML search starts a million nats from home (seen on
    accelerated MEMS sessions). ``‖y_a‖ − g`` sees the acceleration's component along
    gravity, one axis' worth when it is isotropic; a robust spread (1.4826 × median absolute
    deviation) ignores knocks. The stationary stretch is left out; with no motion, 0.

    acc : (N, 3) m/s²; g : m/s²; stationary : the stretch from :func:`find_stationary`.
    """
    keep = np.ones(acc.shape[0], dtype=bool)
    if stationary is not None:
        keep[stationary] = False
    if not keep.any():
        return 0.0
    dev = np.linalg.norm(acc[keep], axis=1) - g
    return float((1.4826 * np.median(np.abs(dev - np.median(dev)))) ** 2)


def initial_noise_and_bias(
    t: np.ndarray,
    gyr: np.ndarray,
    acc: np.ndarray,
    mag: np.ndarray,
    stationary: slice | None,
) -> NoiseInit:
    """Initial gyro bias and noise covariances (Algorithm 1, step 1a).

    t   : (N,) float, s
    gyr : (N, 3) float, rad/s
    acc : (N, 3) float, m/s²
    mag : (N, 3) float, raw magnetometer units
    stationary : a stretch from :func:`find_stationary`, or None

    With a stretch: bias = mean gyro over it; covariances = sample covariances over it, each
    standard deviation floored at ``max(NOISE_FLOOR_FRACTION × prior, LSB/√12)`` (the
    quantisation noise; a quantised sensor at rest can read constant).

    Without: the priors — bias 0, :data:`GYR_NOISE_PRIOR_RAD_S`,
    :data:`ACC_NOISE_PRIOR_M_S2`, and :data:`MAG_NOISE_PRIOR_FRACTION` of the median field
    norm about the data centre — all isotropic. The maximum-likelihood step refines them.

    Raises :class:`InsufficientDataError` when the given stretch has fewer than
    :data:`MIN_COVARIANCE_SAMPLES` samples.
    """
    t = np.asarray(t, dtype=float)
    n = t.shape[0]
    gyr = _check_xyz("gyr", gyr, n)
    acc = _check_xyz("acc", acc, n)
    mag = _check_xyz("mag", mag, n)
    if n == 0:
        raise InsufficientDataError("noise initialisation: the session is empty: record data")
    mag_prior = MAG_NOISE_PRIOR_FRACTION * _mag_scale(mag)
    prior_std = {"gyr": GYR_NOISE_PRIOR_RAD_S, "acc": ACC_NOISE_PRIOR_M_S2, "mag": mag_prior}

    if stationary is None:
        return NoiseInit(
            gyro_bias=np.zeros(3),
            Sigma_gyr=gyro_noise_from_differences(gyr, floor_std=_lsb(gyr) / np.sqrt(12.0)),
            Sigma_acc=ACC_NOISE_PRIOR_M_S2**2 * np.eye(3),
            Sigma_mag=mag_prior**2 * np.eye(3),
            source="prior",
            stationary=None,
        )

    count = len(range(*stationary.indices(n)))
    if count < MIN_COVARIANCE_SAMPLES:
        raise InsufficientDataError(
            f"noise initialisation: the stationary stretch has {count} samples; at least "
            f"{MIN_COVARIANCE_SAMPLES} are needed: pass a longer stretch, or None to use priors"
        )
    covs = {}
    for name, x in (("gyr", gyr), ("acc", acc), ("mag", mag)):
        floor_std = np.maximum(NOISE_FLOOR_FRACTION * prior_std[name], _lsb(x) / np.sqrt(12.0))
        covs[name] = _floored_cov(x[stationary], floor_std)
    return NoiseInit(
        gyro_bias=gyr[stationary].mean(axis=0),
        Sigma_gyr=covs["gyr"],
        Sigma_acc=covs["acc"],
        Sigma_mag=covs["mag"],
        source="stationary",
        stationary=stationary,
    )
