"""The C kernel against the textbook numpy MEKF, and the filter against the truth."""

import numpy as np
import pytest

from magcal.calib import frames
from magcal.calib.likelihood import mekf


@pytest.mark.parametrize("use_mag", [True, False])
def test_native_filter_matches_reference(filter_problem, use_mag):
    p, data, _ = filter_problem
    ref = mekf.run_filter_reference(p, data, use_mag)
    nat = mekf.run_filter(p, data, use_mag)
    assert nat.cost == pytest.approx(ref.cost, rel=1e-12)
    np.testing.assert_allclose(
        frames.quat_to_matrix(nat.q_filt), frames.quat_to_matrix(ref.q_filt), atol=1e-10
    )
    np.testing.assert_allclose(nat.innovations, ref.innovations, atol=1e-10)
    np.testing.assert_allclose(nat.normalised, ref.normalised, atol=1e-9)


def test_filter_tracks_true_attitude(filter_problem):
    p, data, q_true = filter_problem
    out = mekf.run_filter(p, data)
    err = frames.quat_to_rotvec(frames.quat_multiply(out.q_filt, frames.quat_conjugate(q_true)))
    # After the first second, the attitude error is a fraction of a degree.
    assert np.rad2deg(np.abs(err[100:]).max()) < 1.0
    # With true parameters the magnetometer's normalised innovations are close to N(0, 1)
    # (the fixture inflates Σ_a by acc_extra_var, so the accelerometer's are smaller).
    z = out.normalised[100:, 3:]
    assert abs(z.mean()) < 0.1
    assert 0.85 < z.std() < 1.15


def test_gradient_and_cost_kernels_agree_on_cost(filter_problem):
    p, data, _ = filter_problem
    c, _ = mekf.cost_and_model_gradient(p, data)
    assert c == pytest.approx(mekf.filter_pass(p, data, True), rel=1e-14)


def test_non_positive_definite_noise_gives_an_error(filter_problem):
    p, data, _ = filter_problem
    import dataclasses

    from magcal.errors import CalibrationError

    bad = dataclasses.replace(p, Sigma_mag=-np.eye(3))
    with pytest.raises(CalibrationError, match="diverged"):
        mekf.run_filter(bad, data)


def test_acc_inflation_is_zero_at_rest_and_spreads_a_bump_over_its_window():
    rng = np.random.default_rng(0)
    acc = np.tile([0.0, 0.0, 9.81], (200, 1)) + 0.02 * rng.normal(size=(200, 3))
    assert not np.any(mekf.accelerometer_extra_variance(acc, 9.81, 0.02, 100.0))
    acc[100] += [8.0, 0.0, 5.0]
    c = mekf.accelerometer_extra_variance(acc, 9.81, 0.02, 100.0)
    excess = abs(np.linalg.norm(acc[100]) - 9.81) - (3 * 0.02 + mekf.BUMP_THRESHOLD_M_S2)
    half = round(mekf.BUMP_WINDOW_S * 100.0)
    np.testing.assert_allclose(c[100 - half : 100 + half + 1], mekf.BUMP_GAIN * excess**2)
    assert c[100 - half - 1] == 0.0 and c[100 + half + 1] == 0.0


def test_acc_inflation_ignores_smooth_accelerations():
    # 0.3 m/s² of smooth motion is the ML step's Σ_a business, not an outlier.
    t = np.arange(1000) / 100.0
    acc = np.column_stack([0.3 * np.sin(2 * t), 0.3 * np.cos(3 * t), 9.81 + 0.3 * np.sin(t)])
    assert not np.any(mekf.accelerometer_extra_variance(acc, 9.81, 0.02, 100.0))
