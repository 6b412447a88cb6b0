# SPDX-License-Identifier: Apache-2.0
"""Multi-rate sessions: the view at the magnetometer's rows, magnetometer glitches, and the
calibration of a session whose magnetometer is slower than its IMU."""

from __future__ import annotations

import numpy as np
import pytest

from magcal.calib import samples
from magcal.calib.calibrate import calibrate
from magcal.calib.diagnostics import quality, uncertainty
from magcal.calib.initial.sensor_levels import measure_sensor_levels
from magcal.io.session import session_from_arrays
from magcal.sim import preset, simulate


def thinned(session, every: int):
    """The session with the magnetometer kept at every ``every``-th row only."""
    mag = session.mag.copy()
    mag[np.arange(len(session)) % every != 0] = np.nan
    return session_from_arrays(session.t, session.gyr, session.acc, mag, session.meta)


def heading_rms_deg(truth, result) -> float:
    s = truth.sensor
    return quality.rms_deg(quality.calibration_heading_errors(s.D, s.o, s.m_n, result.D, result.o))


# ---------------------------------------------------------------------------------------------
# The view at the magnetometer's rows


def test_single_rate_session_is_its_own_view():
    s, _ = simulate(preset("mems", duration_s=5.0), 0)
    assert samples.at_magnetometer_rows(s) is s
    assert samples.drop_magnetometer_glitches(s)[0] is s


def test_view_gyroscope_is_the_rotation_between_magnetometer_rows():
    n = 13
    t = np.cumsum(np.r_[0.0, np.full(n - 1, 0.01)])
    t[5:] += 0.003  # an uneven step
    gyr = np.column_stack([np.arange(n, dtype=float), np.ones(n), -2.0 * np.arange(n)])
    acc = np.column_stack([t, 2 * t, np.full(n, 9.8)])
    acc[[3, 4]] = np.nan  # no accelerometer there
    mag = np.full((n, 3), np.nan)
    rows = [0, 4, 9]
    mag[rows] = [[1.0, 2.0, 3.0], [4.0, 5.0, 6.0], [7.0, 8.0, 9.0]]
    v = samples.at_magnetometer_rows(session_from_arrays(t, gyr, acc, mag))
    np.testing.assert_array_equal(v.t, t[rows])
    np.testing.assert_array_equal(v.mag, mag[rows])
    # Row r turns the attitude by gyr[r] (t[r+1] - t[r]); the view's row j by the sum of
    # those up to the next magnetometer row.
    for j, (a, b) in enumerate([(0, 4), (4, 9), (9, 12)]):
        angle = (gyr[a:b] * np.diff(t)[a:b, None]).sum(axis=0)
        np.testing.assert_allclose(v.gyr[j] * (t[b] - t[a]), angle, rtol=1e-12)
    # Accelerometer interpolated linearly across the rows that have it (row 4 has none).
    np.testing.assert_allclose(v.acc[1], [t[4], 2 * t[4], 9.8], rtol=1e-12)
    np.testing.assert_array_equal(v.acc[0], acc[0])
    assert not v.multi_rate


def test_levels_are_measured_per_stream_at_its_own_rate():
    s, truth = simulate(preset("mems", duration_s=20.0, stationary_s=3.0), 1)
    m = thinned(s, 4)
    multi = measure_sensor_levels(m)
    view = measure_sensor_levels(samples.at_magnetometer_rows(m))

    def ratio(measured, true):
        return float(np.trace(measured) / np.trace(true))

    # The gyroscope and accelerometer at the IMU's rate, the magnetometer at its own ...
    assert 0.8 < ratio(multi.noise.Sigma_gyr, truth.sensor.Sigma_gyr) < 1.25
    assert 0.8 < ratio(multi.noise.Sigma_mag, truth.sensor.Sigma_mag) < 1.25
    assert 0.8 < ratio(multi.noise.Sigma_acc, truth.sensor.Sigma_acc) < 1.25
    # ... while the gyroscope averaged over 4 rows has about a quarter of its variance.
    assert 0.15 < ratio(view.noise.Sigma_gyr, truth.sensor.Sigma_gyr) < 0.45
    assert multi.acc_used.shape == (len(m),)
    assert multi.acc_extra_var.shape == (len(m),)


# ---------------------------------------------------------------------------------------------
# Glitches


def smooth_field(k: int, rng) -> np.ndarray:
    u = np.linspace(0, 6 * np.pi, k)
    return np.column_stack([30 * np.cos(u), 30 * np.sin(u), 10 * np.sin(0.3 * u)]) + rng.normal(
        scale=0.2, size=(k, 3)
    )


def test_exact_repeats_of_a_resending_stream_are_not_samples():
    rng = np.random.default_rng(0)
    fresh = smooth_field(100, rng)
    mag = np.repeat(fresh, 4, axis=0)  # each reading sent four times
    rep = samples.repeated_samples(mag)
    assert rep.sum() == 300
    np.testing.assert_array_equal(mag[~rep], fresh)


def test_quantised_still_repeats_are_samples():
    # A quantised sensor: while still (the first 60 of 400 samples) it reads the same counts
    # often; while turning never. Those repeats are real samples and are kept ...
    rng = np.random.default_rng(1)
    mag = np.round(smooth_field(400, rng) * 10.0)
    mag[:60] = np.round(np.array([200.0, -50.0, 400.0]) + rng.normal(scale=0.3, size=(60, 3)))
    exact = np.r_[False, (mag[1:] == mag[:-1]).all(axis=1)]
    assert 5 < exact.sum() < 0.2 * 400
    assert not samples.repeated_samples(mag).any()
    # ... while a sensor still for most of the session repeats so often that they are not.
    still = np.round(np.array([200.0, -50.0, 400.0]) + rng.normal(scale=0.3, size=(400, 3)))
    rep = samples.repeated_samples(still)
    assert rep.sum() > 0.2 * 400
    np.testing.assert_array_equal(rep[1:], (still[1:] == still[:-1]).all(axis=1))


def test_isolated_jumps_are_found_and_steps_and_fast_motion_are_not():
    rng = np.random.default_rng(2)
    mag = smooth_field(600, rng)
    spikes = [50, 51, 300, 451]
    mag[50] += [15.0, 0, 0]
    mag[300] += [0, -8.0, 3.0]
    mag[451] += [4.0, 4.0, 4.0]
    mag[400:] += [20.0, 0.0, 0.0]  # a step (the surroundings changed): not a jump
    jumps = samples.isolated_jumps(mag)
    assert set(np.flatnonzero(jumps)) == {50, 300, 451}
    assert not jumps[398:403].any()
    # A smooth fast turn with noise only: nothing.
    assert not samples.isolated_jumps(smooth_field(600, np.random.default_rng(3))).any()
    del spikes


def test_glitches_become_rows_without_magnetometer_and_are_counted():
    s, truth = simulate(preset("mems", duration_s=30.0), 4)
    mag = s.mag.copy()
    mag[1000] += 5.0 * np.linalg.norm(mag[1000])  # a jump ...
    mag[1::2] = mag[0:-1:2]  # ... and every reading sent twice
    m = session_from_arrays(s.t, s.gyr, s.acc, mag, s.meta)
    cleaned, counts = samples.drop_magnetometer_glitches(m)
    assert counts.repeated == len(s) // 2
    assert counts.jumps == 1
    assert counts.used == len(s) - counts.repeated - 1
    assert not cleaned.has_mag[1000] and not cleaned.has_mag[1]
    r = calibrate(m, "init").result
    assert r.extra["magnetometer_samples"] == counts.as_dict()
    assert [w for w in r.warnings if w.startswith("magnetometer:")] == [
        f"magnetometer: {counts.used} samples used; left out: {counts.repeated} exact repeats "
        "of the previous value (re-sent, not new readings) and 1 isolated jump"
    ]
    assert heading_rms_deg(truth, r) < 0.5


def test_a_result_is_measured_on_the_samples_it_was_fitted_on():
    # Uncertainty and replay set the cost up on the session they are given: with every
    # reading sent twice, that must be the cost the estimate minimised (its minimum), not
    # one that counts the re-sent values as samples.
    s, _ = simulate(preset("mems", duration_s=20.0), 5)
    mag = s.mag.copy()
    mag[1::2] = mag[0:-1:2]
    m = session_from_arrays(s.t, s.gyr, s.acc, mag, s.meta)
    result = calibrate(m, "ml").result
    on_resent = uncertainty.calibration_uncertainty(result, m)
    on_cleaned = uncertainty.calibration_uncertainty(
        result, samples.drop_magnetometer_glitches(m)[0]
    )
    assert on_resent.newton_step_sigma < 1.0
    np.testing.assert_allclose(on_resent.theta_sigma, on_cleaned.theta_sigma, rtol=1e-12)


# ---------------------------------------------------------------------------------------------
# Calibration


@pytest.mark.parametrize("method", ["ml", "init", "ckf", "two-step"])
def test_multi_rate_session_calibrates_like_its_view(method):
    s, truth = simulate(preset("mems", duration_s=40.0), 3)
    m = thinned(s, 4)
    cal = calibrate(m, method)
    r = cal.result
    view = calibrate(samples.at_magnetometer_rows(m), method).result
    assert r.extra["magnetometer_samples"]["used"] == int(m.has_mag.sum())
    assert not r.warnings
    # The same motion and magnetometer samples: about as good as the single-rate session
    # at the magnetometer's rows (ML), the same for the per-sample methods.
    assert heading_rms_deg(truth, r) < 1.5 * heading_rms_deg(truth, view) + 0.02
    assert heading_rms_deg(truth, r) < 0.2
    assert cal.calibrated.shape == (len(m), 3)
    assert np.isnan(cal.calibrated[~m.has_mag]).all()
    assert np.isfinite(r.extra["innovations"]["std"])
    assert abs(r.extra["field_norm"]["after"]["mean"] - 1.0) < 0.01
    if method == "ml":
        # Every row propagated: the normalised innovations are white.
        assert 0.9 < r.extra["innovations"]["std"] < 1.1


# ---------------------------------------------------------------------------------------------
# Simulator


def test_simulated_magnetometer_rate_and_lag(tmp_path):
    import json
    import subprocess
    import sys

    from magcal.calib import frames
    from magcal.io.session import read_session

    base, truth = simulate(preset("mems", duration_s=10.0), 5)
    multi, _ = simulate(preset("mems", duration_s=10.0, mag_rate_hz=25.0), 5)
    # The IMU and the magnetometer samples it keeps are those of the single-rate session.
    np.testing.assert_array_equal(multi.gyr, base.gyr)
    np.testing.assert_array_equal(multi.acc, base.acc)
    np.testing.assert_array_equal(multi.mag[multi.has_mag], base.mag[multi.has_mag])
    steps = np.diff(multi.t[multi.has_mag])
    assert abs(float(np.mean(steps)) - 0.04) < 1e-3 and steps.max() < 0.041
    # A lag: the noise-free field at t shows the attitude at t - lag.
    lag = 0.05
    lagged, _ = simulate(preset("mems", duration_s=10.0, mag_sigma=0.0, mag_lag_s=lag), 5)
    s = truth.sensor
    k = np.arange(100, 1000)
    i = k - 5  # 0.05 s earlier at 100 Hz
    expected = frames.quat_to_matrix(truth.q_nb[i]).transpose(0, 2, 1) @ s.m_n @ s.D.T + s.o
    np.testing.assert_allclose(lagged.mag[k], expected, atol=1e-9)
    # The command line writes a version 2 session and records the lag.
    out = tmp_path / "s.csv"
    args = ["--preset", "mems", "--duration", "5", "--mag-rate", "20", "--mag-lag-s", "0.02"]
    subprocess.run([sys.executable, "-m", "magcal", "simulate", *args, "-o", str(out)], check=True)
    assert out.read_text(encoding="utf-8").startswith("# magcal-session: 2")
    assert read_session(out).has_mag.sum() == 20 * 7  # 5 s of motion plus 2 s of rest
    saved = json.loads(out.with_suffix(".truth.json").read_text(encoding="utf-8"))
    assert saved["time_offset_s"] == 0.02


def test_default_simulation_is_unchanged():
    # The magnetometer's rate and lag, at their defaults, change nothing: the values of the
    # simulator before they existed (recorded from it; rtol leaves room for another libm).
    a, _ = simulate(preset("table2"), 7)
    assert len(a) == 400 and not a.multi_rate
    np.testing.assert_allclose(
        a.mag[:2],
        [
            [0.4495557513181524, -0.20910783742089098, 1.3621437113506183],
            [0.3674526949297749, -0.1254865171437519, 1.3478163667595755],
        ],
        rtol=1e-12,
    )
    np.testing.assert_allclose(
        a.gyr[:2],
        [
            [0.0020553597630869076, 0.10739931471512498, -0.03859167629310061],
            [0.06936664467549705, 0.02436149772715195, 0.09892880421952129],
        ],
        rtol=1e-12,
    )
    assert a.mag.sum() == pytest.approx(410.58308430829607, rel=1e-12)
    assert a.acc.sum() == pytest.approx(-3384.4057203615193, rel=1e-12)
