# SPDX-License-Identifier: Apache-2.0
"""The ML parameter vector θ (35 numbers) and its map to model quantities.

Layout of θ (paper Section 5.3, eq. 17):

====== ===== =====================================================================
slice  count  meaning
====== ===== =====================================================================
0:9    9      D, row-major (normalised magnetometer units per unit field)
9:12   3      o (normalised magnetometer units)
12     1      dip δ (rad, positive down): ``m_n = (cos δ, 0, −sin δ)`` (eq. 8b)
13:16  3      gyroscope bias δ_ω (rad/s)
16:22  6      Cholesky parameters of Σ_ω ((rad/s)²)
22:28  6      Cholesky parameters of Σ_a ((m/s²)²)
28:34  6      Cholesky parameters of Σ_m (normalised units²)
34     1      time offset τ (s): the magnetometer's delay against the inertial sensors
====== ===== =====================================================================

Each covariance is ``Σ = L Lᵀ`` with the lower-triangular factor written as
``L = diag(exp(l)) U``, ``U`` unit lower-triangular; the six numbers are
``(l₀, l₁, l₂, u₁₀, u₂₀, u₂₁)``. This is the paper's Cholesky parametrisation, rewritten so
that every number is dimensionless or a log-scale: Σ stays positive definite for any θ, and
the optimiser sees variables of comparable size whatever the sensor's units.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from magcal.calib.frames import field_direction

N_PARAMS = 35
SLICE_D = slice(0, 9)
SLICE_O = slice(9, 12)
INDEX_DIP = 12
SLICE_BIAS = slice(13, 16)
SLICE_CHOL_GYR = slice(16, 22)
SLICE_CHOL_ACC = slice(22, 28)
SLICE_CHOL_MAG = slice(28, 34)
INDEX_TIME_OFFSET = 34

PARAM_NAMES = (
    [f"D{i}{j}" for i in range(3) for j in range(3)]
    + ["o0", "o1", "o2", "dip"]
    + ["bias_x", "bias_y", "bias_z"]
    + [
        f"{s}_{n}"
        for s in ("chol_gyr", "chol_acc", "chol_mag")
        for n in ("l0", "l1", "l2", "u10", "u20", "u21")
    ]
    + ["time_offset"]
)

_TRIL_OFF = ((1, 0), (2, 0), (2, 1))


@dataclass(frozen=True)
class ModelParams:
    """Model quantities of the ML problem.

    D         : (3, 3) magnetometer units per unit field
    o         : (3,)   magnetometer units
    dip_rad   : float, rad, positive down
    gyro_bias : (3,)   rad/s
    Sigma_gyr : (3, 3) (rad/s)²
    Sigma_acc : (3, 3) (m/s²)²
    Sigma_mag : (3, 3) magnetometer units²
    time_offset_s : float, s, the magnetometer's delay against the inertial sensors: its
                sample at time t measured the field at t − τ (positive: it lags)
    gyro_gain_error : float, the 1-σ relative error of each entry of the gyroscope's gain
                matrix that the filter allows for (0: the gain is exact). Not in θ: the
                ML step chooses it by a test (``ml.py``)
    """

    D: np.ndarray
    o: np.ndarray
    dip_rad: float
    gyro_bias: np.ndarray
    Sigma_gyr: np.ndarray
    Sigma_acc: np.ndarray
    Sigma_mag: np.ndarray
    time_offset_s: float = 0.0
    gyro_gain_error: float = 0.0

    @property
    def m_n(self) -> np.ndarray:
        return field_direction(self.dip_rad)

    def scaled_magnetometer(self, centre: np.ndarray, scale: float) -> ModelParams:
        """The same model for data ``y' = (y − centre) / scale`` (scale > 0)."""
        return ModelParams(
            D=self.D / scale,
            o=(self.o - centre) / scale,
            dip_rad=self.dip_rad,
            gyro_bias=self.gyro_bias,
            Sigma_gyr=self.Sigma_gyr,
            Sigma_acc=self.Sigma_acc,
            Sigma_mag=self.Sigma_mag / scale**2,
            time_offset_s=self.time_offset_s,
            gyro_gain_error=self.gyro_gain_error,
        )

    def unscaled_magnetometer(self, centre: np.ndarray, scale: float) -> ModelParams:
        """Inverse of :meth:`scaled_magnetometer`."""
        return ModelParams(
            D=self.D * scale,
            o=self.o * scale + centre,
            dip_rad=self.dip_rad,
            gyro_bias=self.gyro_bias,
            Sigma_gyr=self.Sigma_gyr,
            Sigma_acc=self.Sigma_acc,
            Sigma_mag=self.Sigma_mag * scale**2,
            time_offset_s=self.time_offset_s,
            gyro_gain_error=self.gyro_gain_error,
        )


def cov_to_chol_params(Sigma: np.ndarray) -> np.ndarray:
    """(3, 3) SPD covariance → the six numbers ``(l₀, l₁, l₂, u₁₀, u₂₀, u₂₁)``."""
    L = np.linalg.cholesky(np.asarray(Sigma, dtype=float))
    d = np.diag(L)
    U = L / d[:, None]
    return np.concatenate([np.log(d), [U[i, j] for i, j in _TRIL_OFF]])


def chol_params_to_factor(c: np.ndarray) -> np.ndarray:
    """Six numbers → lower-triangular ``L = diag(exp(l)) U``."""
    U = np.eye(3)
    for k, (i, j) in enumerate(_TRIL_OFF):
        U[i, j] = c[3 + k]
    # A line-search trial far out in log σ overflows to inf; the filter then reports a
    # non-finite cost and the line search backs off, so the overflow is not an error here.
    with np.errstate(over="ignore", invalid="ignore"):
        return np.exp(c[:3])[:, None] * U


def chol_params_to_cov(c: np.ndarray) -> np.ndarray:
    L = chol_params_to_factor(c)
    with np.errstate(over="ignore", invalid="ignore"):
        return L @ L.T


def chol_params_grad(c: np.ndarray, Sigma_bar: np.ndarray) -> np.ndarray:
    """Chain rule: gradient w.r.t. the six numbers from ``∂V/∂Σ`` (3, 3), any symmetry."""
    L = chol_params_to_factor(c)
    # Σ = L Lᵀ ⇒ ∂V/∂L = (Σ̄ + Σ̄ᵀ) L, restricted to the lower triangle.
    L_bar = np.tril((Sigma_bar + Sigma_bar.T) @ L)
    with np.errstate(over="ignore"):
        d = np.exp(c[:3])
    # L_ij = d_i U_ij (U_ii = 1) ⇒ ∂/∂l_i = Σ_j L̄_ij L_ij ; ∂/∂u_ij = L̄_ij d_i.
    g = np.empty(6)
    g[:3] = np.sum(L_bar * L, axis=1)
    for k, (i, j) in enumerate(_TRIL_OFF):
        g[3 + k] = L_bar[i, j] * d[i]
    return g


def pack(p: ModelParams) -> np.ndarray:
    """ModelParams → θ (35,)."""
    theta = np.empty(N_PARAMS)
    theta[SLICE_D] = np.asarray(p.D, dtype=float).ravel()
    theta[SLICE_O] = p.o
    theta[INDEX_DIP] = p.dip_rad
    theta[SLICE_BIAS] = p.gyro_bias
    theta[SLICE_CHOL_GYR] = cov_to_chol_params(p.Sigma_gyr)
    theta[SLICE_CHOL_ACC] = cov_to_chol_params(p.Sigma_acc)
    theta[SLICE_CHOL_MAG] = cov_to_chol_params(p.Sigma_mag)
    theta[INDEX_TIME_OFFSET] = p.time_offset_s
    return theta


def unpack(theta: np.ndarray) -> ModelParams:
    """θ (35,) → ModelParams."""
    theta = np.asarray(theta, dtype=float)
    if theta.shape != (N_PARAMS,):
        raise ValueError(f"θ must have shape ({N_PARAMS},), got {theta.shape}")
    return ModelParams(
        D=theta[SLICE_D].reshape(3, 3).copy(),
        o=theta[SLICE_O].copy(),
        dip_rad=float(theta[INDEX_DIP]),
        gyro_bias=theta[SLICE_BIAS].copy(),
        Sigma_gyr=chol_params_to_cov(theta[SLICE_CHOL_GYR]),
        Sigma_acc=chol_params_to_cov(theta[SLICE_CHOL_ACC]),
        Sigma_mag=chol_params_to_cov(theta[SLICE_CHOL_MAG]),
        time_offset_s=float(theta[INDEX_TIME_OFFSET]),
    )


def model_vector(theta: np.ndarray) -> np.ndarray:
    """θ (35,) → the model in the native kernel's flat layout (46,): D (9, row-major), o,
    m_n, the gyroscope bias, Σ_ω, Σ_a, Σ_m (9 each, row-major) and τ. Works on complex θ, so
    that :func:`model_jacobian` can take complex steps."""

    def cov(c):
        U = np.eye(3, dtype=c.dtype)
        for k, (i, j) in enumerate(_TRIL_OFF):
            U[i, j] = c[3 + k]
        L = np.exp(c[:3])[:, None] * U
        return (L @ L.T).ravel()

    dip = theta[INDEX_DIP]
    return np.concatenate(
        [
            theta[SLICE_D],
            theta[SLICE_O],
            [np.cos(dip), 0.0 * dip, -np.sin(dip)],
            theta[SLICE_BIAS],
            cov(theta[SLICE_CHOL_GYR]),
            cov(theta[SLICE_CHOL_ACC]),
            cov(theta[SLICE_CHOL_MAG]),
            [theta[INDEX_TIME_OFFSET]],
        ]
    )


#: Imaginary step of the complex-step derivative: far below rounding, exact to it.
COMPLEX_STEP = 1e-30


def model_jacobian(theta: np.ndarray) -> np.ndarray:
    """∂(model vector)/∂θ (46, 35) at θ, exact to rounding by complex steps (every entry of
    :func:`model_vector` is an analytic function of θ)."""
    theta = np.asarray(theta, dtype=float)
    J = np.empty((46, N_PARAMS))
    for k in range(N_PARAMS):
        z = theta.astype(complex)
        z[k] += 1j * COMPLEX_STEP
        J[:, k] = model_vector(z).imag / COMPLEX_STEP
    return J


def model_grad_to_theta(
    theta: np.ndarray,
    D_bar: np.ndarray,
    o_bar: np.ndarray,
    m_bar: np.ndarray,
    bias_bar: np.ndarray,
    Sigma_gyr_bar: np.ndarray,
    Sigma_acc_bar: np.ndarray,
    Sigma_mag_bar: np.ndarray,
    time_offset_bar: float,
) -> np.ndarray:
    """Gradient w.r.t. θ from gradients w.r.t. the model quantities (m_bar w.r.t. m_n)."""
    g = np.empty(N_PARAMS)
    g[SLICE_D] = np.asarray(D_bar).ravel()
    g[SLICE_O] = o_bar
    dip = theta[INDEX_DIP]
    # m_n = (cos δ, 0, −sin δ)
    g[INDEX_DIP] = -np.sin(dip) * m_bar[0] - np.cos(dip) * m_bar[2]
    g[SLICE_BIAS] = bias_bar
    g[SLICE_CHOL_GYR] = chol_params_grad(theta[SLICE_CHOL_GYR], Sigma_gyr_bar)
    g[SLICE_CHOL_ACC] = chol_params_grad(theta[SLICE_CHOL_ACC], Sigma_acc_bar)
    g[SLICE_CHOL_MAG] = chol_params_grad(theta[SLICE_CHOL_MAG], Sigma_mag_bar)
    g[INDEX_TIME_OFFSET] = time_offset_bar
    return g
