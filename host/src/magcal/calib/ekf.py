"""The multiplicative EKF for orientation (paper Section 5.2): the one place for the filter.

State: ``q̃_nb`` plus a navigation-frame orientation error ``η`` with covariance ``P``
(rad², 3×3); ``q_nb = exp_q(½ η) ⊙ q̃_nb``.

* Time update with the gyroscope as input, sample ``t−1`` → ``t``:
  ``q̃ ← q̃ ⊙ exp_q(½ T (y_ω − δ_ω))``, ``P ← P + T² R Σ_ω Rᵀ`` with ``R = R(q̃)``.
* Measurement ``y = (y_a, y_m)``: ``ŷ = (−R_bn g_n, D R_bn m_n + o)``,
  ``H = (−R_bn [g_n×], D R_bn [m_n×])``, ``S = H P Hᵀ + blockdiag(Σ_a,t, Σ_m)``.
  ``Σ_a,t = Σ_a + c_t I`` where ``c_t`` (m/s²)² is a data-only inflation that makes the
  accelerometer count less at outliers (knocks; see :func:`accelerometer_extra_variance`).
* The first sample is only a measurement update from the given prior ``(q₀, P₀)``.

Two implementations compute the same numbers:

* :func:`run_filter` calls the C kernel (``host/csrc/mekf_likelihood.c``), which works in
  information form (3×3 instead of 6×6 inverses) and also provides the exact reverse-mode
  gradient used by ``cost.py``;
* :func:`run_filter_reference` is a plain numpy loop with the textbook 6×6 innovation
  covariance. It is slow and exists to check the kernel.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.linalg

from magcal.calib import frames
from magcal.calib.params import ModelParams
from magcal.errors import CalibrationError

# Prior on the initial orientation error: ≈ 10° per axis. The initial attitude comes from
# the first samples and the initial calibration, so it is good to a few degrees; a prior
# this wide lets the first measurements correct it without a long transient in the cost.
INITIAL_ATTITUDE_SIGMA_RAD = np.deg2rad(10.0)


@dataclass(frozen=True)
class FilterData:
    """Everything the filter consumes besides θ, on one time base.

    dt            : (N,) s; dt[0] is unused, dt[t] = time of sample t − time of sample t−1
    gyr, acc, mag : (N, 3) rad/s, m/s², normalised magnetometer units
    acc_extra_var : (N,) (m/s²)², data-only inflation c_t of Σ_a (zeros for none)
    g             : gravity magnitude, m/s²
    q0            : (4,) prior attitude q_nb at sample 0
    P0            : (3, 3) rad², prior covariance of the orientation error
    """

    dt: np.ndarray
    gyr: np.ndarray
    acc: np.ndarray
    mag: np.ndarray
    acc_extra_var: np.ndarray
    g: float
    q0: np.ndarray
    P0: np.ndarray

    def __len__(self) -> int:
        return int(self.dt.shape[0])


@dataclass(frozen=True)
class FilterOutput:
    """cost        : float, V(θ) of eq. (6) (without the constant 3 log 2π per sample)
    q_filt      : (N, 4) filtered attitude q_nb after each measurement update
    innovations : (N, 6) y_t − ŷ_t|t−1 (acc then mag)
    normalised  : (N, 6) L_t⁻¹ (y_t − ŷ_t|t−1), S_t = L_t L_tᵀ (Cholesky)
    """

    cost: float
    q_filt: np.ndarray
    innovations: np.ndarray
    normalised: np.ndarray


def make_filter_data(
    t: np.ndarray,
    gyr: np.ndarray,
    acc: np.ndarray,
    mag: np.ndarray,
    q0: np.ndarray,
    *,
    acc_extra_var: np.ndarray | None = None,
    g: float | None = None,
    prior_sigma_rad: float = INITIAL_ATTITUDE_SIGMA_RAD,
) -> FilterData:
    """Assemble :class:`FilterData`; ``g`` defaults to the median accelerometer norm, so a
    small accelerometer scale error or local gravity does not bias the inclination."""
    t = np.asarray(t, dtype=float)
    dt = np.empty_like(t)
    dt[0] = 0.0
    dt[1:] = np.diff(t)
    acc = np.ascontiguousarray(acc, dtype=float)
    if g is None:
        g = float(np.median(np.linalg.norm(acc, axis=1)))
    if acc_extra_var is None:
        acc_extra_var = np.zeros(len(t))
    return FilterData(
        dt=dt,
        gyr=np.ascontiguousarray(gyr, dtype=float),
        acc=acc,
        mag=np.ascontiguousarray(mag, dtype=float),
        acc_extra_var=np.ascontiguousarray(acc_extra_var, dtype=float),
        g=float(g),
        q0=frames.quat_normalize(np.asarray(q0, dtype=float)),
        P0=np.eye(3) * prior_sigma_rad**2,
    )


def run_filter_reference(p: ModelParams, data: FilterData, use_mag: bool = True) -> FilterOutput:
    """Textbook MEKF with the full 6×6 (or 3×3) innovation covariance. Slow; for tests."""
    n = len(data)
    g_n = frames.gravity_n(data.g)
    m_n = p.m_n
    G = frames.skew(g_n)
    Mx = frames.skew(m_n)
    q = data.q0.copy()
    P = data.P0.copy()
    ny = 6 if use_mag else 3
    cost = 0.0
    q_filt = np.empty((n, 4))
    innov = np.zeros((n, 6))
    normed = np.zeros((n, 6))
    for t in range(n):
        if t > 0:
            dt = data.dt[t]
            q = frames.quat_multiply(q, frames.quat_exp(0.5 * dt * (data.gyr[t - 1] - p.gyro_bias)))
            R = frames.quat_to_matrix(q)
            P = P + dt * dt * R @ p.Sigma_gyr @ R.T
        else:
            R = frames.quat_to_matrix(q)
        Rt = R.T
        y_pred = np.concatenate([-Rt @ g_n, p.D @ Rt @ m_n + p.o])[:ny]
        H = np.vstack([-Rt @ G, p.D @ Rt @ Mx])[:ny]
        Rm = np.zeros((ny, ny))
        Rm[:3, :3] = p.Sigma_acc + data.acc_extra_var[t] * np.eye(3)
        if use_mag:
            Rm[3:, 3:] = p.Sigma_mag
        y = np.concatenate([data.acc[t], data.mag[t]])[:ny]
        eps = y - y_pred
        S = H @ P @ H.T + Rm
        L = np.linalg.cholesky(S)
        w = scipy.linalg.solve_triangular(L, eps, lower=True)
        cost += 0.5 * (w @ w + 2.0 * np.sum(np.log(np.diag(L))))
        # K = P Hᵀ S⁻¹ with the Cholesky factor already at hand, not an explicit inverse.
        K = scipy.linalg.cho_solve((L, True), H @ P).T
        eta = K @ eps
        # Joseph form keeps P symmetric positive definite in finite precision.
        IKH = np.eye(3) - K @ H
        P = IKH @ P @ IKH.T + K @ Rm @ K.T
        q = frames.quat_normalize(frames.quat_multiply(frames.quat_exp(0.5 * eta), q))
        q_filt[t] = q
        innov[t, :ny] = eps
        normed[t, :ny] = w
    return FilterOutput(cost=float(cost), q_filt=q_filt, innovations=innov, normalised=normed)


def run_filter(p: ModelParams, data: FilterData, use_mag: bool = True) -> FilterOutput:
    """The C kernel's forward pass with all diagnostics (attitude, innovations)."""
    from magcal.calib import native

    n = len(data)
    q_filt = np.empty((n, 4))
    innov = np.zeros((n, 6))
    normed = np.zeros((n, 6))
    cost = native.filter_pass(p, data, use_mag, q_filt, innov, normed)
    if not np.isfinite(cost):
        raise CalibrationError(
            "the orientation filter diverged (non-finite likelihood): check that the session's "
            "units are rad/s and m/s², and that the initial calibration is sensible"
        )
    return FilterOutput(cost=cost, q_filt=q_filt, innovations=innov, normalised=normed)


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
