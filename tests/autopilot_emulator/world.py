# SPDX-License-Identifier: Apache-2.0
"""The emulated vehicle's world: motion from ``magcal.sim``, IMU readings, the true field.

Frames: the navigation frame is magcal's (x magnetic north, y west, z up, field
``m_n = (cos δ, 0, −sin δ)``); the body frame is the vehicle's (x forward, y right, z down as
ArduPilot and PX4 define it: at rest and level the accelerometer reads about (0, 0, −9.81)
m/s², which is what ``R_bn (a_n − g_n)`` gives for a body whose z axis points down).

The motion is a ``magcal.sim.trajectory`` path sampled at :data:`SIM_RATE_HZ`: a short rest,
then (by default) a tumble through all orientations with some translational acceleration.
After its end the vehicle **holds still** at the last attitude (angular rate 0, no
acceleration); the noise sequences repeat with the sample index modulo the path length.
Sample ``k`` is at simulated time ``k / SIM_RATE_HZ`` seconds after boot.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from magcal.calib import frames
from magcal.sim.trajectory import make_trajectory

SIM_RATE_HZ = 200.0
#: Length of the simulated path (rest + motion), s; then the vehicle holds still.
PATH_S = 150.0
REST_S = 2.0
MAX_RATE_RAD_S = 1.2
ACC_RMS_M_S2 = 0.2
DIP_DEG = 64.0
FIELD_STRENGTH_GAUSS = 0.50
N_IMUS = 3
GYRO_NOISE_RAD_S = 0.005
ACC_NOISE_M_S2 = 0.02
#: Residual gyro bias after the autopilot's boot-time gyro calibration, deg/s (range).
GYRO_BIAS_DEG_S = (0.05, 0.3)
#: Orientations used by the heading error (a subsample of the path).
HEADING_ATTITUDES = 3000


@dataclass(frozen=True)
class World:
    """True motion and IMU noise at the sample times.

    R_nb      : (N, 3, 3) body→nav rotations
    omega_b   : (N, 3) rad/s body rate;  f_b : (N, 3) m/s² specific force in the body
    m_b       : (N, 3) unit field in the body, ``R_bn m_n``
    gyro_bias : (N_IMUS, 3) rad/s;  gyro_noise, acc_noise : (N_IMUS, N, 3) in rad/s, m/s²
    mag_noise : (3, N, 3) standard normal draws, one set per compass
    """

    rate_hz: float
    dip_deg: float
    R_nb: np.ndarray
    omega_b: np.ndarray
    f_b: np.ndarray
    m_b: np.ndarray
    gyro_bias: np.ndarray
    gyro_noise: np.ndarray
    acc_noise: np.ndarray
    mag_noise: np.ndarray

    def __len__(self) -> int:
        return int(self.R_nb.shape[0])

    @property
    def m_n(self) -> np.ndarray:
        return frames.field_direction(np.deg2rad(self.dip_deg))

    def attitude(self, k: int) -> np.ndarray:
        """R_nb (3, 3) at sample k (held after the end of the path)."""
        return self.R_nb[min(k, len(self) - 1)]

    def field_body(self, k: int) -> np.ndarray:
        """Unit field in the body (3,) at sample k."""
        return self.m_b[min(k, len(self) - 1)]

    def imu(self, k: int, imu: int) -> tuple[np.ndarray, np.ndarray]:
        """(accelerometer m/s², gyroscope rad/s) of IMU ``imu`` (0-based) at sample k,
        body frame, calibrated (as the autopilots publish them), with noise."""
        n = len(self)
        j = k % n
        if k < n:
            f, w = self.f_b[k], self.omega_b[k]
        else:  # holding still at the last attitude
            f = self.R_nb[-1].T @ -frames.gravity_n()
            w = np.zeros(3)
        return f + self.acc_noise[imu, j], w + self.gyro_bias[imu] + self.gyro_noise[imu, j]

    def heading_attitudes(self) -> np.ndarray:
        """Indices of the samples the heading error is taken over (evenly spaced)."""
        return np.unique(np.linspace(0, len(self) - 1, HEADING_ATTITUDES).astype(np.int64))


def make_world(
    rng: np.random.Generator,
    motion: str = "tumble",
    *,
    path_s: float = PATH_S,
    dip_deg: float = DIP_DEG,
    rate_hz: float = SIM_RATE_HZ,
) -> World:
    """Draw the motion and the IMU noise (in that order) from ``rng``."""
    tr = make_trajectory(
        rng,
        rate_hz,
        REST_S,
        path_s - REST_S,
        motion,
        max_rate_rad_s=MAX_RATE_RAD_S,
        acc_rms_m_s2=ACC_RMS_M_S2,
    )
    R_nb = frames.quat_to_matrix(tr.q_nb)
    f_n = tr.acc_n - frames.gravity_n()
    f_b = np.einsum("kji,kj->ki", R_nb, f_n)
    m_b = np.einsum("kji,j->ki", R_nb, frames.field_direction(np.deg2rad(dip_deg)))
    n = len(tr)
    direction = rng.standard_normal((N_IMUS, 3))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    bias = direction * np.deg2rad(rng.uniform(*GYRO_BIAS_DEG_S, (N_IMUS, 1)))
    gyro_noise = GYRO_NOISE_RAD_S * rng.standard_normal((N_IMUS, n, 3))
    acc_noise = ACC_NOISE_M_S2 * rng.standard_normal((N_IMUS, n, 3))
    mag_noise = rng.standard_normal((3, n, 3))
    return World(
        rate_hz, dip_deg, R_nb, tr.omega_b, f_b, m_b, bias, gyro_noise, acc_noise, mag_noise
    )


def random_rotation_deg(rng: np.random.Generator, angle_deg: float) -> np.ndarray:
    """(3, 3) rotation by exactly ``angle_deg`` about a uniformly random axis."""
    axis = rng.standard_normal(3)
    axis /= np.linalg.norm(axis)
    return frames.quat_to_matrix(frames.rotvec_to_quat(np.deg2rad(angle_deg) * axis))


def heading_errors_rad(R_nb: np.ndarray, field_b: np.ndarray) -> np.ndarray:
    """Heading (rad) of body-frame fields (K, 3) rotated into n with the true attitudes
    (K, 3, 3): the angle of the horizontal part from magnetic north; 0 for a perfect field."""
    back_n = np.einsum("kij,kj->ki", R_nb, field_b)
    return frames.wrap_angle(frames.heading_of(back_n))


def rms_deg(angles_rad: np.ndarray) -> float:
    return float(np.rad2deg(np.sqrt(np.mean(np.square(angles_rad)))))
