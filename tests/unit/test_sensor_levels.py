"""The data-only levels of a session: the accelerometer bump inflation of Σ_a."""

import numpy as np

from magcal.calib.initial import sensor_levels


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
