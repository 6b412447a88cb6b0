# SPDX-License-Identifier: Apache-2.0
"""Tests of stationary detection and noise/bias initialisation (Algorithm 1, step 1a)."""

from __future__ import annotations

import numpy as np
import pytest

from magcal.calib.frames import (
    field_direction,
    gravity_n,
    quat_exp,
    quat_multiply,
    quat_to_matrix,
)
from magcal.calib.initial import rest as st
from magcal.calib.initial.rest import NoiseInit, find_stationary, initial_noise_and_bias
from magcal.errors import InsufficientDataError

FS_HZ = 100.0
BIAS = np.array([0.03, -0.02, 0.05])  # rad/s
SIGMA_GYR, SIGMA_ACC, SIGMA_MAG = 0.003, 0.03, 0.3


def _session(omega: np.ndarray, rng: np.random.Generator, noise: bool = True, noise_scale=1.0):
    """Integrate body rates omega (N, 3) rad/s from a level start; return t, gyr, acc, mag."""
    n = omega.shape[0]
    t = np.arange(n) / FS_HZ
    q = np.empty((n, 4))
    q[0] = [1.0, 0.0, 0.0, 0.0]
    steps = quat_exp(0.5 * omega / FS_HZ)
    for k in range(n - 1):
        q[k + 1] = quat_multiply(q[k], steps[k])
    R_bn = np.swapaxes(quat_to_matrix(q), -1, -2)
    acc = -(R_bn @ gravity_n())
    mag = 50.0 * (R_bn @ field_direction(1.1)) + [10.0, 20.0, 30.0]
    gyr = omega + BIAS
    if noise:
        gyr = gyr + noise_scale * SIGMA_GYR * rng.normal(size=(n, 3))
        acc = acc + noise_scale * SIGMA_ACC * rng.normal(size=(n, 3))
        mag = mag + noise_scale * SIGMA_MAG * rng.normal(size=(n, 3))
    return t, gyr, acc, mag


def _tumbling_rates(n: int) -> np.ndarray:
    t = np.arange(n) / FS_HZ
    return 1.5 * np.stack([np.sin(1.3 * t), np.cos(0.7 * t), np.sin(2.1 * t + 1.0)], axis=1)


def _with_rest(n: int, rests: list[tuple[float, float]]) -> np.ndarray:
    omega = _tumbling_rates(n)
    t = np.arange(n) / FS_HZ
    for a, b in rests:
        omega[(t >= a) & (t < b)] = 0.0
    return omega


@pytest.mark.parametrize("rest", [(8.0, 11.0), (0.0, 2.5), (17.0, 20.0)])
def test_finds_stretch_anywhere(rest):
    rng = np.random.default_rng(0)
    t, gyr, acc, mag = _session(_with_rest(2000, [rest]), rng)
    sl = find_stationary(t, gyr, acc, mag)
    assert sl is not None
    a, b = int(rest[0] * FS_HZ), int(rest[1] * FS_HZ)
    # Inside the true rest, and covering most of it.
    assert a <= sl.start and sl.stop <= b
    assert sl.stop - sl.start >= 0.8 * (b - a)


def test_picks_the_longest_stretch():
    rng = np.random.default_rng(1)
    t, gyr, acc, _ = _session(_with_rest(3000, [(2.0, 4.0), (12.0, 17.0), (22.0, 25.0)]), rng)
    sl = find_stationary(t, gyr, acc)
    assert sl is not None
    assert 1200 <= sl.start and sl.stop <= 1700


def test_bias_does_not_prevent_detection_and_is_estimated():
    rng = np.random.default_rng(2)
    t, gyr, acc, mag = _session(_with_rest(2000, [(5.0, 10.0)]), rng)
    sl = find_stationary(t, gyr, acc, mag)
    init = initial_noise_and_bias(t, gyr, acc, mag, sl)
    assert isinstance(init, NoiseInit)
    assert init.source == "stationary" and init.stationary == sl
    assert np.allclose(init.gyro_bias, BIAS, atol=5 * SIGMA_GYR / np.sqrt(sl.stop - sl.start))
    for cov, sigma in ((init.Sigma_gyr, SIGMA_GYR), (init.Sigma_acc, SIGMA_ACC)):
        assert np.allclose(np.sqrt(np.diag(cov)), sigma, rtol=0.2)
        assert np.all(np.linalg.eigvalsh(cov) > 0)
    assert np.allclose(np.sqrt(np.diag(init.Sigma_mag)), SIGMA_MAG, rtol=0.2)


def test_noisy_sensors_like_table2():
    # The paper's Table 2: gyro σ up to 0.1 rad/s, accelerometer σ up to 0.3 m/s², beyond the
    # absolute limits; the white-noise estimate raises them.
    rng = np.random.default_rng(13)
    t, gyr, acc, mag = _session(_with_rest(400, [(0.0, 1.0)]), rng, noise_scale=25.0)
    sl = find_stationary(t, gyr, acc, mag)
    assert sl is not None and sl.start == 0 and 50 <= sl.stop <= 100
    t, gyr, acc, mag = _session(_tumbling_rates(2000), rng, noise_scale=25.0)
    assert find_stationary(t, gyr, acc, mag) is None


def test_no_stationary_stretch():
    rng = np.random.default_rng(3)
    t, gyr, acc, mag = _session(_tumbling_rates(2000), rng)
    assert find_stationary(t, gyr, acc, mag) is None


@pytest.mark.parametrize("rate", [0.05, 0.02, 0.01])
def test_slow_tilting_rotation_is_not_stationary(rate):
    # A constant rate about a horizontal axis: constant gyro (looks like a bias), but the
    # accelerometer direction turns.
    rng = np.random.default_rng(4)
    omega = np.tile([rate, 0.0, 0.0], (2000, 1))
    t, gyr, acc, mag = _session(omega, rng)
    assert find_stationary(t, gyr - BIAS, acc) is None
    assert find_stationary(t, gyr - BIAS, acc, mag) is None


@pytest.mark.parametrize("rate", [0.05, 0.02, 0.01])
def test_slow_yaw_is_not_stationary_given_the_magnetometer(rate):
    # About the vertical only the magnetometer changes.
    rng = np.random.default_rng(5)
    omega = np.tile([0.0, 0.0, rate], (2000, 1))
    t, gyr, acc, mag = _session(omega, rng)
    gyr = gyr - BIAS
    assert find_stationary(t, gyr, acc, mag) is None
    # Without the magnetometer it cannot be told from a bias (documented limitation).
    assert find_stationary(t, gyr, acc) == slice(0, 2000)


def test_fast_constant_rate_is_not_a_bias():
    rng = np.random.default_rng(6)
    omega = np.tile([0.0, 0.0, 0.3], (2000, 1))
    t, gyr, acc, _ = _session(omega, rng)
    assert find_stationary(t, gyr - BIAS, acc) is None


def test_short_rest_rejected():
    # 0.45 s: fewer than 50 samples and shorter than 1 s.
    rng = np.random.default_rng(7)
    t, gyr, acc, mag = _session(_with_rest(2000, [(8.0, 8.45)]), rng)
    assert find_stationary(t, gyr, acc, mag) is None


def test_paper_style_rest_of_100_samples_found():
    # Table 2 of the paper: 100 stationary samples, then rotation.
    rng = np.random.default_rng(12)
    t, gyr, acc, mag = _session(_with_rest(400, [(0.0, 1.0)]), rng)
    sl = find_stationary(t, gyr, acc, mag)
    assert sl is not None and sl.start == 0 and 50 <= sl.stop <= 100


def test_too_few_samples_returns_none():
    t = np.arange(20) / FS_HZ
    assert find_stationary(t, np.zeros((20, 3)), np.tile([0, 0, 9.81], (20, 1))) is None


def test_quantised_constant_sensor_gives_positive_definite_covariances():
    rng = np.random.default_rng(8)
    t, gyr, acc, mag = _session(np.zeros((1500, 3)), rng)
    gyr = np.round(gyr / 0.001) * 0.001
    acc = np.round(acc / 0.1) * 0.1
    mag = np.round(mag)
    acc[:, 0] = acc[0, 0]  # an axis that never changes at rest
    acc[:10, 0] += 0.1  # ... except once, so the resolution (LSB) is known
    sl = find_stationary(t, gyr, acc, mag)
    assert sl is not None and sl.stop - sl.start > 1000
    init = initial_noise_and_bias(t, gyr, acc, mag, slice(100, 1500))
    for cov in (init.Sigma_gyr, init.Sigma_acc, init.Sigma_mag):
        assert np.all(np.linalg.eigvalsh(cov) > 0)
    # The constant axis is floored at the quantisation noise LSB/√12.
    assert init.Sigma_acc[0, 0] == pytest.approx(0.1**2 / 12.0, rel=1e-6)


def test_priors_without_stretch():
    rng = np.random.default_rng(9)
    t, gyr, acc, mag = _session(_tumbling_rates(2000), rng)
    init = initial_noise_and_bias(t, gyr, acc, mag, None)
    assert init.source == "prior" and init.stationary is None
    assert np.array_equal(init.gyro_bias, np.zeros(3))
    # The gyroscope's white noise is measured during the motion (second differences).
    np.testing.assert_allclose(np.sqrt(np.diag(init.Sigma_gyr)), SIGMA_GYR, rtol=0.1)
    assert np.count_nonzero(init.Sigma_gyr - np.diag(np.diag(init.Sigma_gyr))) == 0
    assert np.allclose(init.Sigma_acc, st.ACC_NOISE_PRIOR_M_S2**2 * np.eye(3))
    field = np.median(np.linalg.norm(mag - mag.mean(axis=0), axis=1))
    assert np.allclose(init.Sigma_mag, (0.01 * field) ** 2 * np.eye(3))


def test_gyro_noise_from_differences_ignores_bias_and_smooth_motion():
    rng = np.random.default_rng(11)
    t = np.arange(6000) / FS_HZ
    # 3 rad/s hand-like rotation, a bias, and white noise of known σ per axis.
    omega = 3.0 * np.column_stack([np.sin(1.3 * t), np.cos(0.7 * t), np.sin(2.1 * t + 1)])
    sigma = np.array([0.002, 0.005, 0.01])
    gyr = omega + BIAS + sigma * rng.normal(size=omega.shape)
    est = np.sqrt(np.diag(st.gyro_noise_from_differences(gyr)))
    np.testing.assert_allclose(est, sigma, rtol=0.05)


def test_short_given_stretch_raises():
    rng = np.random.default_rng(10)
    t, gyr, acc, mag = _session(np.zeros((200, 3)), rng)
    with pytest.raises(InsufficientDataError, match="at least"):
        initial_noise_and_bias(t, gyr, acc, mag, slice(0, 5))


def test_shape_errors():
    t = np.arange(100) / FS_HZ
    with pytest.raises(ValueError, match="gyr"):
        find_stationary(t, np.zeros((100, 2)), np.zeros((100, 3)))
    with pytest.raises(ValueError, match="mag"):
        initial_noise_and_bias(t, np.zeros((100, 3)), np.zeros((100, 3)), np.zeros((99, 3)), None)


def test_60k_samples_find_the_rest():
    # Correctness at the size of a 10-minute session; its speed is measured by bench/.
    rng = np.random.default_rng(11)
    n = 60000
    t = np.arange(n) / FS_HZ
    # Smooth motion (not integrated: detection does not need consistent sensors) ...
    gyr = 1.5 * np.column_stack([np.sin(1.3 * t), np.cos(0.7 * t), np.sin(2.1 * t + 1.0)])
    up = np.column_stack([np.sin(0.4 * t), np.cos(0.4 * t) * np.sin(0.3 * t), np.cos(0.3 * t)])
    acc = 9.81 * up / np.linalg.norm(up, axis=1, keepdims=True)
    mag = 50.0 * np.roll(up, 1, axis=1)
    # ... with a 10 s rest in the middle.
    rest = slice(30000, 31000)
    gyr[rest] = 0.0
    acc[rest] = acc[30000]
    mag[rest] = mag[30000]
    gyr += SIGMA_GYR * rng.normal(size=(n, 3)) + BIAS
    acc += SIGMA_ACC * rng.normal(size=(n, 3))
    mag += SIGMA_MAG * rng.normal(size=(n, 3))
    sl = find_stationary(t, gyr, acc, mag)
    assert sl is not None and 30000 <= sl.start and sl.stop <= 31000
    assert sl.stop - sl.start > 900


def test_motion_acceleration_variance_measures_the_shake_not_knocks_or_rest():
    from magcal.sim.trajectory import accelerometer_bumps, band_limited_acceleration

    rng = np.random.default_rng(5)
    n_rest, n_move, g = 300, 6000, 9.81
    shake = band_limited_acceleration(rng, n_move, FS_HZ, 0.3)  # ‖a‖ RMS 0.3 m/s²
    _, knocks = accelerometer_bumps(rng, 0, n_move, 20)
    up = np.array([0.0, 0.0, g])
    acc = np.vstack([np.tile(up, (n_rest, 1)), up + shake + knocks])
    acc += 0.02 * rng.normal(size=acc.shape)
    var = st.motion_acceleration_variance(acc, g, slice(0, n_rest))
    # ‖y_a‖ − g sees the vertical component: its variance plus the noise's.
    expected = np.var(shake[:, 2]) + 0.02**2
    assert abs(var - expected) < 0.15 * expected
    # The rest alone shows only noise; a session at rest throughout gives nothing.
    assert st.motion_acceleration_variance(acc[:n_rest], g, None) < 2 * 0.02**2
    assert st.motion_acceleration_variance(acc[:n_rest], g, slice(0, n_rest)) == 0.0
