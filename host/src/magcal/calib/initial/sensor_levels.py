"""What a session says about its sensors before any calibration: the data-only levels.

One function, :func:`measure_sensor_levels`, computes them for every step that needs them
(the initial estimate and the likelihood problem), from the readings alone:

* the longest stationary stretch, and from it (or from priors) the gyroscope bias and the
  noise covariances (``rest.py``);
* the gravity magnitude g, the median accelerometer norm, so that a small accelerometer
  scale error or local gravity does not bias the inclination;
* the sample rate;
* the accelerometer bump inflation ``c_t`` (:func:`accelerometer_extra_variance`);
* Σ_a for the ML step: the accelerometer noise plus the motion's acceleration.

None of them depends on the calibration θ, so the likelihood stays smooth in θ.
"""

from __future__ import annotations

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


@dataclass(frozen=True)
class SensorLevels:
    """The data-only levels of one session.

    noise         : gyroscope bias and noise covariances, from the stationary stretch
                    (``noise.stationary``) or from priors (``rest.NoiseInit``)
    g             : gravity magnitude, m/s² (median accelerometer norm)
    rate_hz       : mean sample rate, Hz
    acc_extra_var : (N,) (m/s²)², the bump inflation c_t of Σ_a
    Sigma_acc     : (3, 3) (m/s²)², Σ_a for the ML step: ``noise.Sigma_acc`` plus the
                    motion's acceleration share (isotropic)
    """

    noise: rest.NoiseInit
    g: float
    rate_hz: float
    acc_extra_var: np.ndarray
    Sigma_acc: np.ndarray

    @property
    def stationary_samples(self) -> int:
        """Samples of the stationary stretch the noise was measured on (0: none)."""
        still = self.noise.stationary
        return 0 if still is None else still.stop - still.start


def measure_sensor_levels(session: Session) -> SensorLevels:
    """The data-only levels of ``session`` (see :class:`SensorLevels`).

    Raises ``InsufficientDataError`` as ``rest.initial_noise_and_bias`` does.
    """
    still = rest.find_stationary(session.t, session.gyr, session.acc, session.mag)
    noise = rest.initial_noise_and_bias(session.t, session.gyr, session.acc, session.mag, still)
    g = float(np.median(np.linalg.norm(session.acc, axis=1)))
    rate_hz = (len(session) - 1) / float(session.t[-1] - session.t[0])
    sigma_acc = float(np.sqrt(np.trace(noise.Sigma_acc) / 3.0))
    acc_extra_var = accelerometer_extra_variance(session.acc, g, sigma_acc, rate_hz)
    # The ML step starts with e_a as sensor noise plus the acceleration of the motion (its
    # share on top of the noise measured at rest, isotropic). The inertial attitude of the
    # initial estimate keeps the noise alone: it down-weights accelerated samples itself,
    # and with the larger Σ_a its misalignment was worse on accelerated MEMS sessions
    # (`make accuracy`, init 0.11° → 0.16°) though better on hand-held ones (1.19° → 0.89°).
    shake = rest.motion_acceleration_variance(session.acc, g, noise.stationary)
    Sigma_acc = noise.Sigma_acc + max(0.0, shake - sigma_acc**2) * np.eye(3)
    return SensorLevels(
        noise=noise,
        g=g,
        rate_hz=rate_hz,
        acc_extra_var=acc_extra_var,
        Sigma_acc=Sigma_acc,
    )
