# SPDX-License-Identifier: Apache-2.0
"""Simulated sensor parameters (the "truth") and the measurement model.

The measurement model is the paper's (Kok & Schön 2016, eqs. 7-8), with the conventions of
:mod:`magcal.calib.frames`:

* gyroscope     ``y_ω = ω_b + δ_ω + e_ω``,             ``e_ω ~ N(0, Σ_ω)``, rad/s
* accelerometer ``y_a = R_bn (a_n − g_n) + e_a``,      ``e_a ~ N(0, Σ_a)``, m/s²
* magnetometer  ``y_m = D R_bn m_n + o + e_m``,        ``e_m ~ N(0, Σ_m)``, magnetometer units

``m_n = (cos δ, 0, −sin δ)`` has unit norm, so ``D`` carries the field magnitude: a sensor that
reads the field in "normalised" units has ``‖D‖ ≈ 1``; one that reads raw counts (field of,
say, 50 counts) has ``D`` about 50 times larger, and ``o`` in the same counts.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from magcal.calib import frames
from magcal.calib.likelihood.params import ModelParams
from magcal.errors import MagcalError

# Dip angle in Linköping, Sweden (58.41° N, 15.62° E). The paper's simulation (Section 8) only
# says "the local magnetic field is equal to that in Linköping" and gives no number; ≈71.6° is
# the approximate inclination there in the world magnetic models of that time (not re-derived
# here from a model run; any value near 72° serves the simulation equally well).
DIP_LINKOPING_DEG = 71.6

# MEMS-like noise levels (standard deviations) used by sample_mems / sample_handheld_magnet.
MEMS_GYRO_SIGMA_RAD_S = 0.005
MEMS_ACC_SIGMA_M_S2 = 0.02
MEMS_MAG_SIGMA_REL = 0.005  # fraction of the field magnitude
MEMS_GYRO_BIAS_DEG_S = 1.0  # typical magnitude of the gyroscope bias


@dataclass(frozen=True)
class SensorTruth(ModelParams):
    """True parameters of one simulated sensor unit: the calibration model's own
    quantities (:class:`magcal.calib.likelihood.params.ModelParams`, same fields and units), with D
    carrying the field magnitude in magnetometer units."""

    @property
    def field_norm(self) -> float:
        """Mean field magnitude in magnetometer units, ``(|det D|)^(1/3)``."""
        return float(abs(np.linalg.det(self.D)) ** (1.0 / 3.0))


def d_skew(zeta: float, eta: float, rho: float) -> np.ndarray:
    """Non-orthogonality of the magnetometer axes, paper eq. 32; angles in rad."""
    return np.array(
        [
            [1.0, 0.0, 0.0],
            [np.sin(zeta), np.cos(zeta), 0.0],
            [-np.sin(eta), np.cos(eta) * np.sin(rho), np.cos(eta) * np.cos(rho)],
        ]
    )


def compose_d(diag: np.ndarray, skew_angles: np.ndarray, rot_angles: np.ndarray) -> np.ndarray:
    """``D = D_diag D_skew D_rot`` (paper eq. 31).

    diag        : (3,) D11, D22, D33
    skew_angles : (3,) ζ, η, ρ in rad (eq. 32)
    rot_angles  : (3,) ψ, θ, φ in rad, z-y-x Euler angles of ``D_rot``
    """
    return (
        np.diag(np.asarray(diag, dtype=float))
        @ d_skew(*skew_angles)
        @ frames.euler_zyx_to_matrix(*rot_angles)
    )


def _uniform_direction(rng: np.random.Generator) -> np.ndarray:
    v = rng.standard_normal(3)
    return v / np.linalg.norm(v)


def sample_table2(rng: np.random.Generator, dip_deg: float = DIP_LINKOPING_DEG) -> SensorTruth:
    """One sensor drawn from the paper's Monte Carlo settings (Table 2), normalised field.

    Interpretations (the table gives bare numbers):

    * ``δ_ω,i ~ U(−1, 1)`` is read as **degrees per second** (a bias of up to 1 rad/s = 57°/s
      would be physically absurd for any gyroscope); stored in rad/s.
    * ``Σ_ω,i``, ``Σ_a,i``, ``Σ_m,i`` are the diagonal entries of the covariance matrices, i.e.
      **variances**: gyro σ ≈ 0.03-0.1 rad/s, accelerometer and magnetometer σ ≈ 0.03-0.3.
    """
    deg = np.pi / 180.0
    diag = rng.uniform(0.5, 1.5, 3)
    skew_angles = rng.uniform(-30.0, 30.0, 3) * deg
    rot_angles = rng.uniform(-10.0, 10.0, 3) * deg
    o = rng.uniform(-1.0, 1.0, 3)
    gyro_bias = rng.uniform(-1.0, 1.0, 3) * deg
    var_gyr = rng.uniform(1e-3, 1e-2, 3)
    var_acc = rng.uniform(1e-3, 1e-1, 3)
    var_mag = rng.uniform(1e-3, 1e-1, 3)
    return SensorTruth(
        D=compose_d(diag, skew_angles, rot_angles),
        o=o,
        dip_rad=dip_deg * deg,
        gyro_bias=gyro_bias,
        Sigma_gyr=np.diag(var_gyr),
        Sigma_acc=np.diag(var_acc),
        Sigma_mag=np.diag(var_mag),
    )


def _mems_noise(rng: np.random.Generator, scale: float) -> tuple[np.ndarray, ...]:
    """Gyro bias and diagonal covariances of a MEMS unit; σ per axis within ±20 % of nominal."""
    deg = np.pi / 180.0
    bias = _uniform_direction(rng) * MEMS_GYRO_BIAS_DEG_S * rng.uniform(0.5, 1.5) * deg
    s_gyr = MEMS_GYRO_SIGMA_RAD_S * rng.uniform(0.8, 1.2, 3)
    s_acc = MEMS_ACC_SIGMA_M_S2 * rng.uniform(0.8, 1.2, 3)
    s_mag = MEMS_MAG_SIGMA_REL * scale * rng.uniform(0.8, 1.2, 3)
    return bias, np.diag(s_gyr**2), np.diag(s_acc**2), np.diag(s_mag**2)


def sample_mems(
    rng: np.random.Generator,
    scale: float = 1.0,
    offset_scale: float | None = None,
    dip_deg: float = DIP_LINKOPING_DEG,
) -> SensorTruth:
    """A MEMS-like unit with moderate soft iron and misalignment.

    scale        : field magnitude in magnetometer units (1.0 normalised, e.g. 50.0 raw counts)
    offset_scale : o_i ~ U(−offset_scale, offset_scale), magnetometer units; default ``scale``
                   (offsets comparable to the field)

    ``D = scale · D_diag D_skew D_rot`` with D_ii ~ U(0.85, 1.15), skew angles ~ U(−5°, 5°),
    rotation angles ~ U(−5°, 5°). Noise σ: gyro 0.005 rad/s, accelerometer 0.02 m/s²,
    magnetometer 0.5 % of ``scale`` (each ±20 % per axis). Gyro bias: magnitude
    U(0.5, 1.5) °/s in a uniformly random direction.
    """
    _check_positive("sample_mems", scale=scale)
    offset_scale = scale if offset_scale is None else float(offset_scale)
    deg = np.pi / 180.0
    diag = rng.uniform(0.85, 1.15, 3)
    skew_angles = rng.uniform(-5.0, 5.0, 3) * deg
    rot_angles = rng.uniform(-5.0, 5.0, 3) * deg
    o = rng.uniform(-1.0, 1.0, 3) * offset_scale
    return _mems_unit(rng, scale, dip_deg, diag, skew_angles, rot_angles, o)


def sample_handheld_magnet(
    rng: np.random.Generator,
    scale: float = 1.0,
    offset_scale: float | None = None,
    dip_deg: float = DIP_LINKOPING_DEG,
) -> SensorTruth:
    """A MEMS unit with a strong magnet about a centimetre from the sensor.

    scale        : field magnitude in magnetometer units
    offset_scale : the offset has norm ``offset_scale · U(3, 6)`` in a random direction;
                   default ``scale`` (so the offset is 3-6 times the field)

    Strong soft iron and anisotropy: ``D = scale · D_diag D_skew D_rot`` with
    D_ii ~ U(0.5, 1.5), skew ~ U(−20°, 20°), rotation ~ U(−10°, 10°). Noise as
    :func:`sample_mems`.
    """
    _check_positive("sample_handheld_magnet", scale=scale)
    offset_scale = scale if offset_scale is None else float(offset_scale)
    deg = np.pi / 180.0
    diag = rng.uniform(0.5, 1.5, 3)
    skew_angles = rng.uniform(-20.0, 20.0, 3) * deg
    rot_angles = rng.uniform(-10.0, 10.0, 3) * deg
    o = _uniform_direction(rng) * rng.uniform(3.0, 6.0) * offset_scale
    return _mems_unit(rng, scale, dip_deg, diag, skew_angles, rot_angles, o)


def _mems_unit(
    rng: np.random.Generator,
    scale: float,
    dip_deg: float,
    diag: np.ndarray,
    skew_angles: np.ndarray,
    rot_angles: np.ndarray,
    o: np.ndarray,
) -> SensorTruth:
    """A MEMS-noise unit with ``D = scale · D_diag D_skew D_rot`` (angles in rad); draws the
    bias and noise from ``rng`` after the caller's draws, so the sequence is fixed."""
    bias, s_gyr, s_acc, s_mag = _mems_noise(rng, scale)
    return SensorTruth(
        D=scale * compose_d(diag, skew_angles, rot_angles),
        o=o,
        dip_rad=dip_deg * (np.pi / 180.0),
        gyro_bias=bias,
        Sigma_gyr=s_gyr,
        Sigma_acc=s_acc,
        Sigma_mag=s_mag,
    )


def _check_positive(op: str, **values: float) -> None:
    for name, v in values.items():
        if not np.isfinite(v) or v <= 0.0:
            raise MagcalError(f"{op}: {name} must be a positive number, got {v!r}")


def noise_factor(Sigma: np.ndarray) -> np.ndarray:
    """A factor ``L`` with ``L Lᵀ = Σ`` for a symmetric positive semi-definite Σ (3, 3).

    Cholesky when Σ is positive definite; otherwise (e.g. Σ = 0 for noise-free runs) the
    symmetric square root from an eigendecomposition, with negative round-off clipped.
    """
    Sigma = np.asarray(Sigma, dtype=float)
    try:
        return np.linalg.cholesky(Sigma)
    except np.linalg.LinAlgError:
        w, V = np.linalg.eigh(0.5 * (Sigma + Sigma.T))
        if w.min() < -1e-12 * max(1.0, abs(w.max())):
            raise MagcalError(
                "simulate: a noise covariance is not positive semi-definite "
                f"(eigenvalues {w}); give variances ≥ 0"
            ) from None
        return V * np.sqrt(np.clip(w, 0.0, None))


def ideal_measurements(
    sensor: SensorTruth, q_nb: np.ndarray, omega_b: np.ndarray, acc_n: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Noise-free gyroscope, accelerometer and magnetometer readings.

    q_nb    : (N, 4) body→nav quaternions
    omega_b : (N, 3) rad/s true body rate
    acc_n   : (N, 3) m/s² true translational acceleration in n
    returns : gyr (N, 3) rad/s (including the bias), acc (N, 3) m/s², mag (N, 3) mag units
    """
    R_nb = frames.quat_to_matrix(q_nb)
    # R_bn v = R_nbᵀ v, batched: out[k, i] = Σ_j R_nb[k, j, i] v[k, j].
    f_n = acc_n - frames.gravity_n()
    acc = np.einsum("kji,kj->ki", R_nb, f_n)
    mag = ideal_magnetometer(sensor, R_nb)
    gyr = omega_b + sensor.gyro_bias
    return gyr, acc, mag


def ideal_magnetometer(sensor: SensorTruth, R_nb: np.ndarray) -> np.ndarray:
    """(N, 3) noise-free magnetometer readings, mag units, at the attitudes R_nb (N, 3, 3)."""
    return np.einsum("kji,j->ki", R_nb, sensor.m_n) @ sensor.D.T + sensor.o


def measure(
    sensor: SensorTruth,
    q_nb: np.ndarray,
    omega_b: np.ndarray,
    acc_n: np.ndarray,
    rng: np.random.Generator,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Noisy readings: :func:`ideal_measurements` plus Gaussian noise with the sensor's Σ.

    The noise is ``e = L z``, ``z ~ N(0, I)``, ``L`` from :func:`noise_factor`; it is drawn in
    the order gyroscope, accelerometer, magnetometer (all samples of one sensor at a time).
    """
    gyr, acc, mag = ideal_measurements(sensor, q_nb, omega_b, acc_n)
    n = gyr.shape[0]
    out = []
    for y, Sigma in ((gyr, sensor.Sigma_gyr), (acc, sensor.Sigma_acc), (mag, sensor.Sigma_mag)):
        L = noise_factor(Sigma)
        out.append(y + rng.standard_normal((n, 3)) @ L.T)
    return out[0], out[1], out[2]
