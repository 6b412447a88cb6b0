# SPDX-License-Identifier: Apache-2.0
"""Cramér–Rao bound on the calibration-induced heading error when translational
accelerations are unknown (the accelerated MEMS accuracy check).

The known-attitude floor of :mod:`magcal_evaluation.accuracy` is what a fit achieves when the
attitude is given. An estimator that must find the attitude from gyroscope, accelerometer
and magnetometer while the body also accelerates has less information: the accelerations
hide part of the gravity direction that ties the magnetometer's axes to the inertial ones.
This module computes how much less, as the Cramér–Rao bound of the correctly specified
model, so that a bound on the ML error can be compared with what any unbiased estimator
can reach.

The model is the calibration MEKF of :mod:`magcal.calib.likelihood.mekf` with the translational
acceleration ``a_n`` as extra states: per navigation axis a damped second-order process
(natural frequency ``f0``, damping ``ζ``, stationary RMS ``σ``) with its rate ``ȧ_n``, so the
state is ``(η, a_n, ȧ_n)`` (9). The accelerometer measures ``R_bn (a_n − g_n) + e_a``. With
σ = 0 it is the calibration MEKF exactly (a test checks it against the C kernel).

Fisher information: by the prediction-error decomposition the per-sample score increments
``s_t = ∂ℓ_t/∂θ`` are martingale differences, so ``I = E Σ_t s_t s_tᵀ``; the sum at the true
parameters is its estimate (the outer product of gradients), which is positive semidefinite
by construction. The scores come from central differences of the per-sample costs, with all
perturbed parameter sets run as one batch. The ML estimator's gyroscope-noise prior is added,
as the estimator uses it. The process parameters (σ, f0, ζ) are held at their true values:
knowing them can only lower the bound.

Slow (a numpy loop over samples); an analysis tool, not used for calibration.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.linalg

from magcal.calib import frames
from magcal.calib.diagnostics import quality
from magcal.calib.likelihood import params
from magcal.calib.likelihood.mekf import FilterData
from magcal.errors import MagcalError

#: Step of the central differences, in θ's units (log-scales, normalised field units, rad,
#: rad/s): the scores' truncation error is O(h²), their rounding error about
#: ε·|ℓ_t|/h ≈ 1e-9 of a score that is O(1/σ_m) ≈ 100 or more.
SCORE_STEP = 1e-6

#: Relative spread of the sample interval up to which one discretisation of the
#: acceleration process serves every step.
MAX_DT_SPREAD = 1e-6


@dataclass(frozen=True)
class AccelerationProcess:
    """Per navigation axis: ä = −ω₀² a − 2ζω₀ ȧ + w, ω₀ = 2π f0_hz, with stationary RMS
    rms_m_s2 (m/s²) of a. rms_m_s2 = 0 switches the acceleration states off."""

    rms_m_s2: float
    f0_hz: float
    zeta: float

    def discretised(self, dt_s: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(F, Q, P∞), each (2, 2), of the state (a, ȧ) of one axis over dt_s seconds."""
        w = 2.0 * np.pi * self.f0_hz
        var = self.rms_m_s2**2
        A = np.array([[0.0, 1.0], [-w * w, -2.0 * self.zeta * w]])
        # White jerk density that makes var the stationary variance of a: var = q/(4ζω₀³).
        Qc = np.array([[0.0, 0.0], [0.0, 4.0 * self.zeta * w**3 * var]])
        # Van Loan: exp([[−A, Qc], [0, Aᵀ]] dt) holds F = exp(A dt) and Q = ∫ F Qc Fᵀ.
        E = scipy.linalg.expm(np.block([[-A, Qc], [np.zeros((2, 2)), A.T]]) * dt_s)
        F = E[2:, 2:].T
        Q = F @ E[:2, 2:]
        P_inf = np.diag([var, var * w * w])
        return F, 0.5 * (Q + Q.T), P_inf


def _skew(v: np.ndarray) -> np.ndarray:
    """(..., 3) → (..., 3, 3) cross-product matrices."""
    z = np.zeros(v.shape[:-1])
    x, y, w = v[..., 0], v[..., 1], v[..., 2]
    return np.stack(
        [np.stack([z, -w, y], -1), np.stack([w, z, -x], -1), np.stack([-y, x, z], -1)], -2
    )


def per_sample_costs(
    thetas: np.ndarray, data: FilterData, process: AccelerationProcess
) -> np.ndarray:
    """ℓ_t = ½ (ε_tᵀ S_t⁻¹ ε_t + log det S_t) of the augmented MEKF for a batch of parameter
    vectors: thetas (B, 35) as :mod:`magcal.calib.likelihood.params` → (B, N) nats (without the
    constant 3 log 2π). Their sum over t is V(θ) of eq. (6) when process.rms_m_s2 = 0."""
    thetas = np.atleast_2d(np.asarray(thetas, dtype=float))
    b, n = thetas.shape[0], len(data)
    dts = data.dt[1:]
    if n > 1 and np.ptp(dts) > MAX_DT_SPREAD * np.median(dts):
        raise MagcalError(
            "Cramér–Rao bound: the sample interval varies; the acceleration process is "
            "discretised once, so this analysis needs evenly sampled data"
        )
    F2, Q2, P2 = process.discretised(float(np.median(dts)) if n > 1 else 0.0)
    eye3 = np.eye(3)
    F_acc, Q_acc = np.kron(F2, eye3), np.kron(Q2, eye3)
    ps = [params.unpack(t) for t in thetas]
    D = np.stack([p.D for p in ps])
    o = np.stack([p.o for p in ps])
    m = np.stack([p.m_n for p in ps])
    bias = np.stack([p.gyro_bias for p in ps])
    Sw = np.stack([p.Sigma_gyr for p in ps])
    Sa = np.stack([p.Sigma_acc for p in ps])
    Sm = np.stack([p.Sigma_mag for p in ps])
    delay = np.array([p.time_offset_s for p in ps])
    m_cross = _skew(m)
    g_n = frames.gravity_n(data.g)

    q = np.tile(data.q0, (b, 1))
    x_acc = np.zeros((b, 6))  # (a_n, ȧ_n)
    P = np.zeros((b, 9, 9))
    P[:, :3, :3] = data.P0
    P[:, 3:, 3:] = np.kron(P2, eye3)
    noise = np.zeros((b, 6, 6))
    noise[:, 3:, 3:] = Sm
    costs = np.empty((b, n))
    for t in range(n):
        if t > 0:
            dt = data.dt[t]
            q = frames.quat_multiply(q, frames.quat_exp(0.5 * dt * (data.gyr[t - 1] - bias)))
            R = frames.quat_to_matrix(q)
            P[:, 3:, :3] = F_acc @ P[:, 3:, :3]
            P[:, :3, 3:] = np.swapaxes(P[:, 3:, :3], 1, 2)
            P[:, 3:, 3:] = F_acc @ P[:, 3:, 3:] @ F_acc.T + Q_acc
            P[:, :3, :3] += dt * dt * R @ Sw @ np.swapaxes(R, 1, 2)
            if data.turn_var is not None:  # as the calibration filter (mekf.py)
                P[:, :3, :3] += data.turn_var[t] * eye3
            x_acc = x_acc @ F_acc.T
        else:
            R = frames.quat_to_matrix(q)
        Rt = np.swapaxes(R, 1, 2)
        # The magnetometer's delay τ: it sees the body turned back by τ times the rate.
        rate = data.gyr[max(t - 1, 0)] - bias
        E = frames.rotvec_to_matrix(delay[:, None] * rate)
        ERt = E @ Rt
        f = x_acc[:, :3] - g_n  # specific force in n
        eps = np.concatenate(
            [
                data.acc[t] - np.einsum("bij,bj->bi", Rt, f),
                data.mag[t] - np.einsum("bij,bj->bi", D @ ERt, m) - o,
            ],
            axis=1,
        )
        # y_bn = Rᵀ Exp(−η) v ≈ Rᵀ v + Rᵀ [v×] η for the error η in n.
        H = np.zeros((b, 6, 9))
        H[:, :3, :3] = Rt @ _skew(f)
        H[:, :3, 3:6] = Rt
        H[:, 3:, :3] = D @ ERt @ m_cross
        noise[:, :3, :3] = Sa + data.acc_extra_var[t] * eye3
        # The measurements sample t has (FilterData.has_acc, has_mag), as the kernel does.
        rows = [r for r, present in ((0, data.has_acc[t]), (3, data.has_mag[t])) if present]
        if not rows:
            costs[:, t] = 0.0
            continue
        rows = np.concatenate([np.arange(r, r + 3) for r in rows])
        eps, H, noise_t = eps[:, rows], H[:, rows], noise[:, rows][:, :, rows]
        HP = H @ P
        S = HP @ np.swapaxes(H, 1, 2) + noise_t
        L = np.linalg.cholesky(S)  # log det via Cholesky
        white = np.linalg.solve(L, eps[..., None])[..., 0]
        costs[:, t] = 0.5 * np.sum(white * white, axis=1) + np.sum(
            np.log(np.diagonal(L, axis1=1, axis2=2)), axis=1
        )
        K = np.swapaxes(np.linalg.solve(S, HP), 1, 2)  # P Hᵀ S⁻¹ (S symmetric)
        dx = np.einsum("bij,bj->bi", K, eps)
        # Joseph form: the covariance stays symmetric positive semidefinite in rounding.
        IKH = np.eye(9) - K @ H
        P = IKH @ P @ np.swapaxes(IKH, 1, 2) + K @ noise_t @ np.swapaxes(K, 1, 2)
        P = 0.5 * (P + np.swapaxes(P, 1, 2))
        q = frames.quat_normalize(frames.quat_multiply(frames.quat_exp(0.5 * dx[:, :3]), q))
        x_acc = x_acc + dx[:, 3:]
    return costs


def fisher_information(
    theta: np.ndarray, data: FilterData, process: AccelerationProcess
) -> np.ndarray:
    """Σ_t s_t s_tᵀ (35, 35) at θ: the outer product of the per-sample scores."""
    theta = np.asarray(theta, dtype=float)
    k = theta.size
    steps = SCORE_STEP * np.eye(k)
    costs = per_sample_costs(np.concatenate([theta + steps, theta - steps]), data, process)
    scores = (costs[:k] - costs[k:]) / (2.0 * SCORE_STEP)  # (35, N)
    return scores @ scores.T


def heading_error_jacobian(
    D_true: np.ndarray, o_true: np.ndarray, m_n: np.ndarray, centre: np.ndarray, scale: float
) -> np.ndarray:
    """∂(per-orientation heading error, rad)/∂(θ's D and o in normalised units), (K, 12), at
    the truth (where every error is 0), by central differences."""
    theta_do = np.concatenate([D_true.ravel() / scale, (o_true - centre) / scale])

    def errors(z):
        D = z[:9].reshape(3, 3) * scale
        return quality.calibration_heading_errors(D_true, o_true, m_n, D, z[9:] * scale + centre)

    cols = []
    for i in range(12):
        e = np.zeros(12)
        e[i] = SCORE_STEP
        cols.append((errors(theta_do + e) - errors(theta_do - e)) / (2.0 * SCORE_STEP))
    return np.stack(cols, axis=1)


def heading_bound_deg(information: np.ndarray, jacobian: np.ndarray) -> float:
    """RMS heading error (degrees) an unbiased estimator with this Fisher information (35, 35)
    cannot beat on average: sqrt(tr(J Σ_DO Jᵀ)/K), Σ = I⁻¹, J the (K, 12) Jacobian above."""
    cov = np.linalg.inv(information)[:12, :12]
    return float(np.rad2deg(np.sqrt(np.trace(jacobian @ cov @ jacobian.T) / jacobian.shape[0])))
