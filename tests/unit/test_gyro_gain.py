# SPDX-License-Identifier: Apache-2.0
"""The ML step's test of the gyroscope's gain error, on simulated sessions with an exact
gyroscope and with one whose gain matrix is off the identity."""

import dataclasses

import numpy as np
import pytest

from magcal.calib.calibrate import calibrate
from magcal.calib.diagnostics import replay
from magcal.calib.likelihood.problem import GYRO_GAIN_ERROR
from magcal.sim.scenarios import preset, simulate


def _session(seed: int, gain_error: float):
    """A simulated MEMS session whose gyroscope reads ``G ω`` with G's entries off the
    identity by ``gain_error`` (1 σ)."""
    session, _ = simulate(preset("mems", duration_s=30), seed=seed)
    G = np.eye(3) + gain_error * np.random.default_rng(seed).standard_normal((3, 3))
    return dataclasses.replace(session, gyr=session.gyr @ G.T)


@pytest.mark.parametrize("seed", [1, 2])
def test_an_exact_gyroscope_gain_is_kept_exact(seed):
    result = calibrate(_session(seed, 0.0), "ml").result
    test = result.extra["gyro_gain_test"]
    assert not test["kept"] and test["statistic"] < test["threshold"]
    assert result.extra["gyro_gain_error"] == 0.0


@pytest.mark.parametrize("seed", [1, 2])
def test_a_gyroscope_gain_off_by_two_percent_is_allowed_for(seed):
    session = _session(seed, 0.02)
    result = calibrate(session, "ml").result
    test = result.extra["gyro_gain_test"]
    assert test["kept"] and test["statistic"] > test["threshold"]
    assert result.extra["gyro_gain_error"] == GYRO_GAIN_ERROR
    # A result carries the filter it was fitted with: replayed on its session (set up
    # afresh, which moves the cost by a fraction of a nat), the cost is the one the
    # estimate reached; with the gain taken as exact it is not.
    p = replay.model_params_from_result(result)
    assert p.gyro_gain_error == GYRO_GAIN_ERROR
    nll = result.extra["negative_log_likelihood"]
    allowed_for = replay.run_filter_at(session, p).cost
    exact = replay.run_filter_at(session, dataclasses.replace(p, gyro_gain_error=0.0)).cost
    assert abs(allowed_for - nll) < test["threshold"] / 2 < exact - nll
