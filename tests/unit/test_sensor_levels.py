# SPDX-License-Identifier: Apache-2.0
"""The data-only levels of a session: the accelerometer bump inflation of Σ_a, the time scale
of the accelerometer's errors and the samples whose accelerometer reading is used."""

import numpy as np
import pytest

from magcal.calib.initial import sensor_levels
from magcal.calib.initial.sensor_levels import (
    acceleration_correlation_time_s,
    accelerometer_updates,
)


def test_acc_inflation_is_zero_at_rest_and_spreads_a_bump_over_its_window():
    rng = np.random.default_rng(0)
    acc = np.tile([0.0, 0.0, 9.81], (200, 1)) + 0.02 * rng.normal(size=(200, 3))
    assert not np.any(sensor_levels.accelerometer_extra_variance(acc, 9.81, 0.02, 100.0))
    acc[100] += [8.0, 0.0, 5.0]
    c = sensor_levels.accelerometer_extra_variance(acc, 9.81, 0.02, 100.0)
    excess = abs(np.linalg.norm(acc[100]) - 9.81) - (3 * 0.02 + sensor_levels.BUMP_THRESHOLD_M_S2)
    half = round(sensor_levels.BUMP_WINDOW_S * 100.0)
    np.testing.assert_allclose(c[100 - half : 100 + half + 1], sensor_levels.BUMP_GAIN * excess**2)
    assert c[100 - half - 1] == 0.0 and c[100 + half + 1] == 0.0


def test_acc_inflation_ignores_smooth_accelerations():
    # 0.3 m/s² of smooth motion is the ML step's Σ_a business, not an outlier.
    t = np.arange(1000) / 100.0
    acc = np.column_stack([0.3 * np.sin(2 * t), 0.3 * np.cos(3 * t), 9.81 + 0.3 * np.sin(t)])
    assert not np.any(sensor_levels.accelerometer_extra_variance(acc, 9.81, 0.02, 100.0))


def _ar1(rng, n, rho, sigma):
    """A first-order autoregressive series with lag-1 correlation rho and std sigma."""
    e = rng.normal(scale=sigma * np.sqrt(1.0 - rho * rho), size=n)
    x = np.empty(n)
    x[0] = rng.normal(scale=sigma)
    for i in range(1, n):
        x[i] = rho * x[i - 1] + e[i]
    return x


def _vertical_acc(deviation):
    acc = np.zeros((deviation.shape[0], 3))
    acc[:, 2] = 9.81 + deviation
    return acc


def test_white_accelerometer_noise_has_a_time_scale_of_one_sample():
    rng = np.random.default_rng(1)
    t = np.arange(20000) / 100.0
    tau = acceleration_correlation_time_s(
        t, _vertical_acc(rng.normal(scale=0.02, size=t.size)), 9.81
    )
    assert tau == pytest.approx(0.01, rel=0.1)
    assert accelerometer_updates(t, tau).all()


@pytest.mark.parametrize("rho", [0.9, 0.98])
def test_correlated_accelerations_give_their_integral_time_scale(rho):
    # An AR(1) series has ρ_k = ρ^k and integral time scale T (1 + ρ) / (1 − ρ).
    rng = np.random.default_rng(2)
    t = np.arange(60000) / 200.0
    tau = acceleration_correlation_time_s(t, _vertical_acc(_ar1(rng, t.size, rho, 1.0)), 9.81)
    expected = (1.0 / 200.0) * (1.0 + rho) / (1.0 - rho)
    assert tau == pytest.approx(expected, rel=0.2)


def test_updates_are_spaced_by_the_correlation_time():
    t = np.arange(1000) / 100.0
    used = accelerometer_updates(t, 0.1)
    assert used[0]
    assert np.all(np.diff(np.flatnonzero(used)) == 10)
    # Irregular times: every used sample at least the spacing (less half a median interval)
    # after the last one, and none skipped that could have been used.
    rng = np.random.default_rng(3)
    t = np.cumsum(rng.uniform(0.005, 0.015, 2000))
    used = accelerometer_updates(t, 0.1)
    gaps = np.diff(t[used])
    assert gaps.min() >= 0.1 - 0.5 * np.median(np.diff(t)) - 1e-12
    assert gaps.max() < 0.1 + 0.015


def test_turn_variance_sees_a_rate_jump_not_a_ramp_nor_the_noise_and_sums_over_rows():
    t = np.arange(8) * 0.01
    no_noise = np.zeros((3, 3))
    # A ramp: the held rate is a constant half step behind, which the time offset takes up
    ramp = np.outer(np.arange(8), [0.1, -0.2, 0.05])
    np.testing.assert_allclose(sensor_levels.turn_variance(t, ramp, no_noise), 0.0, atol=1e-30)
    # A jump of 0.5 rad/s between samples 3 and 4: uncertain within (t_3, t_4], and half as
    # much in the steps on either side, whose ends see it too
    gyr = np.zeros((8, 3))
    gyr[4:] = [0.3, 0.0, -0.4]
    v = sensor_levels.turn_variance(t, gyr, no_noise)
    jump = 0.5**2 * 0.01**2 / 12
    np.testing.assert_allclose(v, jump * np.array([0, 0, 0, 0.5, 1, 0.5, 0, 0]))
    # White noise alone is the gyroscope noise's business: its expected share is taken off
    # (what stays is the part of its fluctuations above that expectation)
    rng = np.random.default_rng(1)
    sigma = 0.01
    noisy = sensor_levels.turn_variance(
        np.arange(20000) * 0.01, sigma * rng.standard_normal((20000, 3)), sigma**2 * np.eye(3)
    )
    assert noisy.mean() < 0.5 * (18 * sigma**2) * 0.01**2 / 12
    # With a magnetometer's rows in between, the step's variance is shared by the rows
    # within it in proportion to their steps, and sums to the IMU's
    rows = np.sort(np.concatenate([t, [0.0325, 0.0375]]))
    spread = sensor_levels._steps_at_rows(rows, t, v)
    within = (rows > t[3]) & (rows <= t[4])
    assert within.sum() == 3
    np.testing.assert_allclose(spread[within], v[4] * np.array([0.25, 0.5, 0.25]))
    np.testing.assert_allclose(spread.sum(), v.sum())


def test_turn_squared_is_the_held_samples_turn_and_sums_over_rows():
    t = np.array([0.0, 0.01, 0.03, 0.04])
    gyr = np.array([[1.0, 2.0, 2.0], [0.0, 3.0, 4.0], [0.0, 0.0, 0.0], [9.0, 9.0, 9.0]])
    # Step k turns by the sample held from k − 1: |ω|² T²
    np.testing.assert_allclose(
        sensor_levels.turn_squared(t, gyr), [0.0, 9 * 0.01**2, 25 * 0.02**2, 0.0]
    )
    # A multi-rate session's rows in between share it, and it sums to the IMU's
    session_t = np.array([0.0, 0.005, 0.01, 0.02, 0.03, 0.04])
    rows = sensor_levels._steps_at_rows(session_t, t, sensor_levels.turn_squared(t, gyr))
    np.testing.assert_allclose(rows.sum(), sensor_levels.turn_squared(t, gyr).sum())
    np.testing.assert_allclose(rows[[3, 4]], 0.5 * 25 * 0.02**2)
