# SPDX-License-Identifier: Apache-2.0
"""Pairing magnetometer and IMU samples (magcal.logs.convert) and the parameter timeline."""

from __future__ import annotations

import numpy as np
import pytest

from magcal.logs.convert import cut, mean_rate, multirate_arrays, pair
from magcal.logs.streams import (
    ImuStream,
    LogImportError,
    LogStreams,
    MagStream,
    ParamTimeline,
    StepSignal,
    untruncate,
)


def test_mean_rate_integrates_the_piecewise_linear_rate_exactly():
    rng = np.random.default_rng(1)
    t = np.sort(rng.uniform(0, 10, 200))
    gyr = rng.normal(size=(200, 3))
    a = rng.uniform(t[0], t[-1] - 1, 30)
    b = a + rng.uniform(0.01, 1, 30)
    fine = np.linspace(0, 1, 20001)
    for k in range(30):
        x = a[k] + fine * (b[k] - a[k])
        y = np.column_stack([np.interp(x, t, gyr[:, j]) for j in range(3)])
        # trapezoid on a grid finer than any kink: error O(h²) ≈ 1e-9 here
        ref = np.trapezoid(y, x, axis=0) / (b[k] - a[k])
        assert np.allclose(mean_rate(t, gyr, a[k : k + 1], b[k : k + 1])[0], ref, atol=1e-6)


def test_a_constant_rotation_is_carried_over_to_the_slower_rows():
    """A row's gyro, held over its interval, turns the attitude as the IMU did."""
    t_imu = np.arange(0, 5, 0.0025)  # 400 Hz
    w = np.array([0.3, -1.2, 0.7])
    up = np.tile([0, 0, 9.8], (t_imu.size, 1))
    imu = ImuStream(t_imu, np.tile(w, (t_imu.size, 1)), up, 1, "")
    t_mag = np.arange(0.013, 4.9, 0.1)  # 10 Hz, not on the IMU grid
    mag = MagStream(t_mag, np.ones((t_mag.size, 3)), 1, "mG", "", "")
    rows = pair(imu, mag)
    assert rows.t.size == t_mag.size - 1  # the last sample only closes an interval
    assert np.allclose(rows.gyr, w) and rows.imu_rate_hz == pytest.approx(400)
    assert rows.mag_rate_hz == pytest.approx(10) and not rows.gap.any()


def test_the_accelerometer_is_interpolated_and_the_magnetometer_kept():
    t_imu = np.arange(0, 2, 0.01)
    acc = np.column_stack([t_imu, 2 * t_imu, np.full_like(t_imu, 9.8)])
    imu = ImuStream(t_imu, np.zeros((t_imu.size, 3)), acc, 1, "")
    t_mag = np.array([0.005, 0.5, 0.777, 1.5, 1.9])
    field = np.arange(15.0).reshape(5, 3)
    rows = pair(imu, MagStream(t_mag, field, 1, "mG", "", ""))
    assert np.allclose(rows.acc[:, 0], t_mag[:-1]) and np.allclose(rows.acc[:, 1], 2 * t_mag[:-1])
    assert np.array_equal(rows.mag, field[:-1])


def test_imu_gaps_are_named_and_a_range_over_them_keeps_its_longest_stretch():
    t_imu = np.concatenate([np.arange(0, 3, 0.01), np.arange(4, 8, 0.01)])  # 1 s lost
    imu = ImuStream(t_imu, np.zeros((t_imu.size, 3)), np.tile([0, 0, 9.8], (t_imu.size, 1)), 1, "")
    t_mag = np.arange(0, 7.9, 0.1)
    mag = MagStream(t_mag, np.ones((t_mag.size, 3)), 1, "mG", "", "")
    rows = pair(imu, mag)
    assert np.all(rows.gap == ((rows.t > 2.9) & (rows.t < 4.0)))
    streams = LogStreams("x.tlog", "tlog", "PX4", imu, mag, ParamTimeline({}))
    assert len(rows.gaps) == 1 and rows.gaps[0] == pytest.approx((2.99, 4.0))
    sel, notes = cut(rows, 4.5, 7.0, streams)
    assert sel.sum() == 26 and notes == ()
    # the gap itself, not the neighbouring magnetometer times; the longer side is kept
    sel, notes = cut(rows, 1.0, 6.0, streams)
    assert rows.t[sel][0] == pytest.approx(4.0) and rows.t[sel][-1] == pytest.approx(6.0)
    assert "missing at 2.99–4.00 s (1.01 s without IMU data: lost messages)" in notes[0]
    paused = LogStreams(
        "x.bin",
        "DataFlash",
        "ardupilot",
        imu,
        mag,
        ParamTimeline({}),
        known_gaps=((2.99, 4.0, "a logging pause"),),
    )
    assert "a logging pause" in cut(rows, 1.0, 6.0, paused)[1][0]
    with pytest.raises(LogImportError, match=r"missing at 2.99–4.00 s .* no stretch"):
        cut(rows, 2.95, 4.05, streams)


def test_no_overlap_in_time():
    imu = ImuStream(np.arange(0, 1, 0.01), np.zeros((100, 3)), np.zeros((100, 3)), 1, "IMU")
    mag = MagStream(np.arange(5, 6, 0.1), np.ones((10, 3)), 1, "mG", "", "MAG")
    with pytest.raises(LogImportError, match="hardly overlap in time"):
        pair(imu, mag)


def test_parameter_timeline_keeps_real_changes_only():
    records = [(0.0, "A", 1.0), (0.0, "B", 2.0), (5.0, "A", 1.0), (7.0, "A", 3.0), (9.0, "B", 4.0)]
    p = ParamTimeline.from_records(records)
    assert p.initial == {"A": 1.0, "B": 2.0}
    assert p.changes == ((7.0, "A", 3.0), (9.0, "B", 4.0))
    assert p.at(6.9) == {"A": 1.0, "B": 2.0} and p.at(8.0) == {"A": 3.0, "B": 2.0}
    assert list(p.change_times({"B"})) == [9.0]


def test_step_signal_before_its_first_record():
    events = StepSignal(np.array([10.0, 20.0]), np.array([1.0, 0.0]), before=0.0)
    assert list(events.at(np.array([5.0, 10.0, 15.0, 25.0]))) == [0.0, 1.0, 1.0, 0.0]
    reports = StepSignal(np.array([10.0, 20.0]), np.array([1.0, 0.0]))
    assert reports.at(np.array([5.0]))[0] == 1.0


def test_untruncate_is_unbiased_for_uniform_fractions():
    rng = np.random.default_rng(0)
    x = rng.uniform(-50, 50, 200_000)
    logged = np.trunc(x)
    assert abs(np.mean(untruncate(logged) - x)) < 0.005
    assert abs(np.mean(logged[x > 1] - x[x > 1])) == pytest.approx(0.5, abs=0.005)


def test_the_multi_rate_session_keeps_every_sample_at_its_own_time():
    t_imu = np.arange(0, 2, 0.01)
    w = np.column_stack([np.sin(t_imu), t_imu, np.ones_like(t_imu)])
    acc = np.column_stack([t_imu, -t_imu, np.full_like(t_imu, 9.8)])
    imu = ImuStream(t_imu, w, acc, 1, "")
    t_mag = np.array([0.105, 0.5, 0.803, 1.5])  # 0.5 and 1.5 coincide with IMU samples
    mag = MagStream(t_mag, np.arange(12.0).reshape(4, 3), 1, "mG", "", "")
    t, gyr, acc_rows, field = multirate_arrays(imu, mag, 0.1, 1.6)
    imu_in = t_imu[(t_imu >= 0.1) & (t_imu <= 1.6)]
    assert np.array_equal(t, np.union1d(imu_in, t_mag)) and t.size == imu_in.size + 2
    has_acc = ~np.isnan(acc_rows).any(axis=1)
    has_mag = ~np.isnan(field).any(axis=1)
    assert np.array_equal(t[has_acc], imu_in) and np.array_equal(t[has_mag], t_mag)
    assert np.array_equal(field[has_mag], mag.mag)
    assert np.array_equal(acc_rows[has_acc], acc[(t_imu >= 0.1) & (t_imu <= 1.6)])
    # the gyroscope of a row turns the attitude through the IMU's angle to the next row
    assert np.allclose(gyr[:-1], mean_rate(t_imu, w, t[:-1], t[1:]))
    assert np.allclose(gyr[:-1, 1], 0.5 * (t[:-1] + t[1:]))  # linear rate: the midpoint
