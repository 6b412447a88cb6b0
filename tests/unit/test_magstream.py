# SPDX-License-Identifier: Apache-2.0
"""The magnetometer screen of ``collect --mavlink`` and the coverage of orientations taken.

A stream at 50 Hz carrying a 10 Hz compass: repeats are IMU-only rows, each value's time is
its first row; a value read during a fast flip, or left frozen while the vehicle turns, is
rejected and counted. Coverage from the attitude: a still vehicle with noisy readings (a
centre fitted to its noise makes them point everywhere) and a yaw-only one never reach the
target; a tumble does.
"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from magcal.autopilot.collect import _Recorder
from magcal.autopilot.magstream import MagnetometerScreen
from magcal.autopilot.rotations import rotation_vector_deg
from magcal.calib.frames import rotvec_to_matrix
from magcal.device.coverage import AttitudeCoverage, CoverageTracker

FIELD = np.array([0.25, 0.05, -0.55]) * 1000  # mG, world frame
RATE_HZ = 50.0
MAG_EVERY = 5  # a 10 Hz compass


def _stream(rates: np.ndarray, glitch: dict[int, np.ndarray] | None = None):
    """Rows of (t, gyr, mag value) for body rates (N, 3) rad/s: the magnetometer reads the
    field in the body frame every MAG_EVERY rows and holds it in between."""
    R = np.eye(3)
    rows = []
    held = None
    for i, w in enumerate(rates):
        if i % MAG_EVERY == 0:
            held = tuple(np.round(R.T @ FIELD).astype(int))
            if glitch and i in glitch:
                held = tuple(glitch[i])
        rows.append((i / RATE_HZ, w, held))
        R = R @ rotvec_to_matrix(w / RATE_HZ)
    return rows


def _scaled_imu(t_ms: int, xmag: int) -> SimpleNamespace:
    """A SCALED_IMU message of a still, level vehicle whose magnetometer x reads ``xmag``."""
    return SimpleNamespace(
        time_boot_ms=t_ms,
        xacc=0,
        yacc=0,
        zacc=1000,
        xgyro=0,
        ygyro=0,
        zgyro=0,
        xmag=xmag,
        ymag=0,
        zmag=0,
    )


def _screen(rows) -> MagnetometerScreen:
    s = MagnetometerScreen()
    for i, (t, w, m) in enumerate(rows):
        s.add(i, t, w, m)
    s.finish()
    return s


def test_only_changes_are_samples_at_their_first_row():
    rates = np.tile([0.3, 0.8, -0.2], (500, 1))
    s = _screen(_stream(rates))
    c = s.counts()
    assert c.rows == 500 and c.accepted == 100 and c.repeats == 400
    assert c.fast_turn == c.frozen == 0
    assert s.rows == list(range(0, 500, MAG_EVERY))
    # the attitude at each sample turns the body-frame reading back into the world field
    for R, y in zip(s.rotations(), s.values, strict=True):
        assert np.linalg.norm(R @ np.array(y) - FIELD) < 2.0


def test_a_fast_flip_and_a_frozen_value_are_rejected_and_counted():
    rates = np.tile([0.0, 0.0, 1.0], (400, 1))
    rates[200:205] = [25.0, 0.0, 0.0]  # a 0.1 s flip of 2.5 rad between two readings
    frozen = _stream(rates)
    s = _screen(frozen)
    c = s.counts()
    assert c.fast_turn == 1 and 205 not in s.rows  # the reading after the flip
    assert c.frozen == 1 and 200 not in s.rows  # the one held through it
    # a value that stays while the vehicle turns by more than MAX_TURN_RAD: held for 50 rows
    # at 1 rad/s, it turns 1 rad
    rows = _stream(np.tile([0.0, 0.0, 1.0], (400, 1)))
    stuck = rows[100][2]
    held = [(t, w, stuck if 100 <= i < 150 else m) for i, (t, w, m) in enumerate(rows)]
    s = _screen(held)
    assert s.counts().frozen == 1 and 100 not in s.rows
    # held for 10 rows it turns 0.2 rad, within MAX_TURN_RAD: kept
    held = [(t, w, stuck if 100 <= i < 110 else m) for i, (t, w, m) in enumerate(rows)]
    s = _screen(held)
    assert s.counts().frozen == 0 and 100 in s.rows


def _coverage(rates: np.ndarray, noise: float, seed: int = 0) -> tuple[float, float]:
    """(attitude coverage, raw field-direction coverage) of a stream with sensor noise."""
    rng = np.random.default_rng(seed)
    offset = np.array([120.0, -40.0, 60.0])
    R = np.eye(3)
    ys, Rs = [], []
    for w in rates:
        ys.append(R.T @ FIELD + offset + noise * rng.standard_normal(3))
        Rs.append(R.copy())
        R = R @ rotvec_to_matrix(w / 10.0)
    att = AttitudeCoverage(min_extent=100.0)
    att.add(np.array(ys), np.array(Rs))
    raw = CoverageTracker(min_extent=100.0)
    raw.add(np.array(ys))
    return att.state(force=True).coverage, raw.state(force=True).coverage


def test_a_still_or_yaw_only_vehicle_never_reaches_the_target_a_tumble_does():
    n = 1200  # two minutes of a 10 Hz compass
    # still, with noise spanning more than the minimum extent (PX4 SIH: 20-30 mG)
    still_att, still_raw = _coverage(np.zeros((n, 3)), noise=30.0)
    assert still_raw > 0.5  # the raw directions are fooled by the noise ...
    assert still_att <= 0.02  # ... the orientations taken are one
    yaw_att, _ = _coverage(np.tile([0.0, 0.0, 1.0], (n, 1)), noise=3.0)
    assert yaw_att < 0.3
    t = np.arange(n) / 10.0
    tumble = np.column_stack([np.sin(0.31 * t), np.cos(0.23 * t), np.sin(0.071 * t + 1)]) * 2.0
    tumble_att, tumble_raw = _coverage(tumble, noise=3.0)
    assert tumble_att >= 0.9 and abs(tumble_att - tumble_raw) < 0.1


def test_a_jittering_millisecond_clock_is_no_gap_and_a_lost_stretch_is_counted():
    rec = _Recorder("SCALED_IMU")
    rng = np.random.default_rng(0)
    t_ms = 1000
    for k in range(400):
        # 100 Hz with a millisecond stamp that jitters by a tick either way; at k = 300 five
        # messages are lost (a 60 ms step).
        t_ms += 60 if k == 300 else 10 + int(rng.integers(-1, 2))
        rec.add(_scaled_imu(t_ms, k), host_s=t_ms / 1000.0)
    assert rec.gaps == 5


def test_a_clock_restart_is_no_gap():
    rec = _Recorder("SCALED_IMU")
    # 100 Hz from 100 s, the vehicle reboots at row 50 (its clock starts again near 1 s).
    for k in range(100):
        t_ms = 100_000 + 10 * k if k < 50 else 1_000 + 10 * k
        rec.add(_scaled_imu(t_ms, k), host_s=k / 100.0)
    assert rec.gaps == 0


def test_the_rotation_vector_of_a_half_turn_keeps_its_axis_signs():
    axis = np.array([1.0, -1.0, 0.0]) / np.sqrt(2.0)
    R = rotvec_to_matrix(np.pi * axis)
    np.testing.assert_allclose(rotation_vector_deg(R), 180.0 * axis, atol=1e-6)
