# SPDX-License-Identifier: Apache-2.0
"""A simulated log's truth: rest, hand rotation, put down, rest, "flight", rest.

Built from magcal's simulator (:mod:`magcal.sim`, read-only): the hand rotation is a
``"tumble"`` trajectory, the flight a ``"yaw-only"`` one with translational accelerations,
both at the IMU rate, joined so that the attitude is continuous (each segment is rotated as a
whole in the navigation frame to start where the previous one ended; a level vehicle stays
level). The magnetometer reading ``mag`` is the simulator's ``y = D R_bn m_n + o + e`` in mG:
for ArduPilot that is the field after ``rotate_field`` (what the importer recovers), for PX4
the raw sensor-frame field.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from magcal.calib import frames
from magcal.sim import model, trajectory

STATIONARY_S = 3.0
HAND_S = 40.0
REST_S = 4.0
FLIGHT_S = 15.0
END_S = 3.0
#: Boot time of the first sample, s (a log does not start at 0).
T0_S = 5.0
PUT_DOWN_RATE_RAD_S = 0.8


@dataclass(frozen=True)
class BenchDay:
    """What the log generators write, at the IMU rate.

    t        : (N,) s, boot time, multiples of 1 µs
    gyr, acc : (N, 3) rad/s, m/s² (noisy, gyro with bias); as in the simulator, ``gyr[k]`` is
               the mean rate over [t_k, t_k+1] and ``acc[k]`` the specific force at t_k
    gyr_point: (N, 3) rad/s, the rate *at* t_k, (gyr[k−1] + gyr[k]) / 2: what a log that
               stamps instantaneous samples (ArduPilot IMU, RAW_IMU) holds
    mag      : (N, 3) mG, the raw field (see the module docstring)
    sensor   : the true magnetometer model (D, o in mG)
    q_nb     : (N, 4) true attitude
    armed    : (N,) bool;  throttle : (N,) 0–1
    hand     : (start, end) s of the hand rotation (with the put-down)
    flight   : (start, end) s of the flight
    """

    t: np.ndarray
    gyr: np.ndarray
    acc: np.ndarray
    gyr_point: np.ndarray
    mag: np.ndarray
    sensor: model.SensorTruth
    q_nb: np.ndarray
    armed: np.ndarray
    throttle: np.ndarray
    hand: tuple[float, float]
    flight: tuple[float, float]


def _yaw(deg: float) -> np.ndarray:
    return frames.rotvec_to_quat(np.array([0.0, 0.0, np.deg2rad(deg)]))


def _starting_at(q: np.ndarray, start: np.ndarray) -> np.ndarray:
    """The motion ``q`` (M, 4) rotated in n so that it starts at ``start``."""
    r = frames.quat_multiply(start, frames.quat_conjugate(q[0]))
    return frames.quat_multiply(r, q)


def _put_down(q_from: np.ndarray, q_to: np.ndarray, rate_hz: float) -> np.ndarray:
    """Smooth rotation (smoothstep along the geodesic) at about PUT_DOWN_RATE_RAD_S."""
    phi = frames.quat_to_rotvec(frames.quat_multiply(frames.quat_conjugate(q_from), q_to))
    angle = float(np.linalg.norm(phi))
    n = max(2, int(np.ceil(1.5 * angle / PUT_DOWN_RATE_RAD_S * rate_hz)))
    s = np.linspace(0.0, 1.0, n + 1)[1:]
    s = s * s * (3.0 - 2.0 * s)
    return frames.quat_multiply(q_from, frames.rotvec_to_quat(s[:, None] * phi))


def bench_day(
    seed: int = 0,
    rate_hz: float = 200.0,
    field_mG: float = 500.0,
    offset_mG: float = 150.0,
    hand_s: float = HAND_S,
) -> BenchDay:
    """Simulate the day (see the module docstring); equal seeds give equal days."""
    rng_sensor, rng_motion, rng_noise = (
        np.random.default_rng(s) for s in np.random.SeedSequence(seed).spawn(3)
    )
    sensor = model.sample_mems(rng_sensor, scale=field_mG, offset_scale=offset_mG)
    level_a, level_b = _yaw(30.0), _yaw(100.0)
    n_rest = int(round(STATIONARY_S * rate_hz))
    hand = trajectory.make_trajectory(
        rng_motion, rate_hz, 0.0, hand_s, "tumble", max_rate_rad_s=1.5, acc_rms_m_s2=0.3
    )
    q_hand = _starting_at(hand.q_nb, level_a)
    q_down = _put_down(q_hand[-1], level_b, rate_hz)
    flight = trajectory.make_trajectory(
        rng_motion, rate_hz, 0.0, FLIGHT_S, "yaw-only", max_rate_rad_s=0.6, acc_rms_m_s2=1.5
    )
    q_flight = _starting_at(flight.q_nb, level_b)
    n_mid, n_end = int(round(REST_S * rate_hz)), int(round(END_S * rate_hz))
    parts = [
        np.repeat(level_a[None], n_rest, axis=0),
        q_hand,
        q_down,
        np.repeat(level_b[None], n_mid, axis=0),
        q_flight,
        np.repeat(q_flight[-1][None], n_end + 1, axis=0),  # + 1: the last sample's rate
    ]
    q = np.concatenate(parts)
    flips = np.sum(q[:-1] * q[1:], axis=-1) < 0.0
    q = q * np.concatenate([[1.0], np.where(np.cumsum(flips) % 2 == 1, -1.0, 1.0)])[:, None]
    omega = trajectory.body_rates(q, rate_hz)
    q = q[:-1]
    n = q.shape[0]
    acc_n = np.zeros((n, 3))
    i_hand = n_rest
    acc_n[i_hand : i_hand + len(hand)] = hand.acc_n
    i_flight = n_rest + len(q_hand) + len(q_down) + n_mid
    acc_n[i_flight : i_flight + len(flight)] = flight.acc_n
    gyr, acc, mag = model.measure(sensor, q, omega, acc_n, rng_noise)
    t = np.round((T0_S + np.arange(n) / rate_hz) * 1e6) / 1e6
    armed = np.zeros(n, dtype=bool)
    a0, a1 = i_flight - int(rate_hz), i_flight + len(flight) + int(rate_hz)
    armed[a0:a1] = True
    throttle = np.where(armed, 0.45, 0.0)
    return BenchDay(
        t=t,
        gyr=gyr,
        acc=acc,
        gyr_point=np.concatenate([gyr[:1], 0.5 * (gyr[:-1] + gyr[1:])]),
        mag=mag,
        sensor=sensor,
        q_nb=q,
        armed=armed,
        throttle=throttle,
        hand=(float(t[i_hand]), float(t[i_hand + len(q_hand) + len(q_down) - 1])),
        flight=(float(t[i_flight]), float(t[i_flight + len(flight) - 1])),
    )
