# SPDX-License-Identifier: Apache-2.0
"""The C kernel against the textbook numpy MEKF, and the filter against the truth."""

import dataclasses

import numpy as np
import pytest

from magcal.calib import frames
from magcal.calib.likelihood import mekf


@pytest.mark.parametrize("turned", [False, True])
@pytest.mark.parametrize("time_offset_s", [0.0, 0.03])
@pytest.mark.parametrize("use_mag", [True, False])
def test_native_filter_matches_reference(filter_problem, use_mag, time_offset_s, turned):
    p, data, _ = filter_problem
    p = dataclasses.replace(p, time_offset_s=time_offset_s)
    if turned:  # the turn's variance on one step in three (a few 0.01°)
        turn = np.where(np.arange(len(data)) % 3 == 1, 1e-7, 0.0)
        data = dataclasses.replace(data, turn_var=turn)
        assert mekf.run_filter(p, data, use_mag).cost != pytest.approx(
            mekf.run_filter(p, dataclasses.replace(data, turn_var=None), use_mag).cost,
            rel=1e-9,
        )
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
