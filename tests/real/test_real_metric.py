# SPDX-License-Identifier: Apache-2.0
"""The real-data metric, the plain fit and the known-attitude floor on synthetic data with a
known attitude (:mod:`magcal_evaluation.real`)."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from magcal.calib import frames
from magcal.calib.diagnostics.uncertainty import misalignment_deg
from magcal.io.session import session_from_arrays
from magcal_evaluation import real

DECLINATION_DEG = 23.0
DIP_DEG = 60.0
FIELD_UT = 48.0


def _field_w() -> np.ndarray:
    return real._field_of(math.radians(DECLINATION_DEG), math.radians(DIP_DEG))


def _simulate(D, o, q_wb, noise_ut=0.0, seed=0):
    """y = D R(q_wb)ᵀ m_w + o (+ noise), (N, 3) µT."""
    R_bw = np.transpose(frames.quat_to_matrix(q_wb), (0, 2, 1))
    y = (R_bw @ _field_w()) @ np.asarray(D).T + o
    return y + noise_ut * np.random.default_rng(seed).standard_normal(y.shape)


def _distortion(seed: int, symmetric: bool) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    A = np.eye(3) + 0.15 * rng.standard_normal((3, 3))
    if symmetric:
        A = 0.5 * (A + A.T)
    return FIELD_UT * A, 30.0 * rng.standard_normal(3)


def _level_attitudes(n: int) -> np.ndarray:
    """Level attitudes (body z up) at yaws spread over the circle."""
    yaw = np.linspace(0.0, 2.0 * np.pi, n, endpoint=False)
    return np.column_stack([np.cos(yaw / 2), np.zeros(n), np.zeros(n), np.sin(yaw / 2)])


def _trial(mag, q_wb) -> real.Trial:
    n = mag.shape[0]
    return real.Trial("synthetic", np.arange(n) * 0.01, mag, q_wb, np.ones(n, bool))


def test_true_calibration_gives_zero_heading_error():
    q = frames.so3_grid(500)
    D, o = _distortion(1, symmetric=False)
    y = _simulate(D, o, q)
    err = real.heading_errors_rad(D, o, y, q, DECLINATION_DEG)
    assert np.max(np.abs(err)) < 1e-9
    assert real.trial_heading_deg(D, o, _trial(y, q), DECLINATION_DEG) < 1e-7


@pytest.mark.parametrize("alpha_deg", [3.0, -10.0, 170.0])
def test_a_rotation_of_D_about_the_vertical_shifts_the_heading_by_its_angle(alpha_deg):
    # Level attitudes: a rotation of the body axes about body z (= up) by α turns the
    # corrected field by −α about the vertical, i.e. its heading (east of north) by +α.
    q = _level_attitudes(72)
    D, o = _distortion(2, symmetric=False)
    y = _simulate(D, o, q)
    a = math.radians(alpha_deg)
    U = np.array([[math.cos(a), -math.sin(a), 0.0], [math.sin(a), math.cos(a), 0.0], [0, 0, 1]])
    err = real.heading_errors_rad(D @ U, o, y, q, DECLINATION_DEG)
    np.testing.assert_allclose(err, a, atol=1e-9)
    assert real.trial_heading_deg(D @ U, o, _trial(y, q), DECLINATION_DEG) == pytest.approx(
        abs(alpha_deg), abs=1e-7
    )


def test_the_error_is_wrapped_and_the_median_is_over_trials():
    q = _level_attitudes(36)
    D, o = _distortion(3, symmetric=False)
    y = _simulate(D, o, q)
    # A declination off by 350° is an error of 10°, not 350°.
    assert real.trial_heading_deg(D, o, _trial(y, q), DECLINATION_DEG - 350.0) == pytest.approx(
        10.0, abs=1e-7
    )
    trials = tuple(_trial(y, q) for _ in range(3))
    case = real.Case("c", {}, None, trials, DECLINATION_DEG + 5.0)
    assert real.case_heading_deg(D, o, case) == pytest.approx(5.0, abs=1e-7)


def test_invalid_samples_are_not_scored():
    q = frames.so3_grid(200)
    D, o = _distortion(4, symmetric=False)
    y = _simulate(D, o, q)
    y[::2] += 100.0  # garbage where the reference is not scored
    valid = np.zeros(200, bool)
    valid[1::2] = True
    trial = real.Trial("t", np.arange(200.0), y, q, valid)
    assert real.trial_heading_deg(D, o, trial, DECLINATION_DEG) < 1e-7


def test_plain_fit_recovers_a_symmetric_distortion():
    q = frames.so3_grid(800)
    D, o = _distortion(5, symmetric=True)
    y = _simulate(D, o, q)
    D_fit, o_fit = real.plain_fit(y)
    np.testing.assert_allclose(D_fit, D, rtol=0, atol=1e-6 * FIELD_UT)
    np.testing.assert_allclose(o_fit, o, rtol=0, atol=1e-6 * FIELD_UT)


def test_plain_fit_cannot_see_a_misalignment():
    # D = P U: the plain fit finds P and misses the rotation U, so it is worse than the
    # floor by about U's angle.
    q = frames.so3_grid(800)
    P, o = _distortion(6, symmetric=True)
    U = frames.quat_to_matrix(frames.rotvec_to_quat(np.deg2rad([0.0, 0.0, 4.0])))
    y = _simulate(P @ U, o, q)
    D_fit, _ = real.plain_fit(y)
    np.testing.assert_allclose(D_fit, P, atol=1e-6 * FIELD_UT)
    assert real.trial_heading_deg(D_fit, o, _trial(y, q), DECLINATION_DEG) > 2.0


@pytest.mark.parametrize("noise_ut", [0.0, 0.3])
def test_known_attitude_floor_recovers_the_truth(noise_ut):
    q = frames.so3_grid(1500)
    D, o = _distortion(7, symmetric=False)
    y = _simulate(D, o, q, noise_ut=noise_ut, seed=7)
    fit = real.known_attitude_floor(y, q)
    tol = 1e-6 if noise_ut == 0.0 else 0.02  # relative; 0.3 µT noise on a 48 µT field
    np.testing.assert_allclose(fit.D, D, atol=tol * FIELD_UT)
    np.testing.assert_allclose(fit.o, o, atol=tol * FIELD_UT)
    np.testing.assert_allclose(fit.m_w, _field_w(), atol=tol)
    assert fit.heading_deg == pytest.approx(DECLINATION_DEG, abs=100 * tol)
    assert fit.dip_deg == pytest.approx(DIP_DEG, abs=100 * tol)
    # ... and the plain fit of the same data is no better than the floor.
    D_p, o_p = real.plain_fit(y)
    trial = _trial(y, q)
    floor = real.trial_heading_deg(fit.D, fit.o, trial, fit.heading_deg)
    assert floor <= real.trial_heading_deg(D_p, o_p, trial, DECLINATION_DEG) + 1e-9


def test_missing_data_folder_is_named(tmp_path):
    missing = tmp_path / "realdata"
    with pytest.raises(real.RealDataError, match=str(missing)):
        real.case_names(missing)


def test_multi_rate_session_from_raw_streams(tmp_path):
    from magcal_evaluation.real import multi_rate_session

    gyr_t = np.array([0.10, 0.20, 0.30, 0.40])
    acc_t = np.array([0.05, 0.15, 0.25, 0.35])
    mag_t = np.array([0.12, 0.30, 0.38])
    gyr = np.arange(12, dtype=float).reshape(4, 3)
    acc = 10.0 + np.arange(12, dtype=float).reshape(4, 3)
    mag = 100.0 + np.arange(9, dtype=float).reshape(3, 3)
    path = tmp_path / "c.npz"
    np.savez(path, gyr_t=gyr_t, gyr=gyr, acc_t=acc_t, acc=acc, mag_t=mag_t, mag=mag)
    s = multi_rate_session(path, {"source": "x"})
    # Rows at every stream's times from the first gyroscope sample on (0.30 is shared).
    np.testing.assert_array_equal(s.t, [0.10, 0.12, 0.15, 0.20, 0.25, 0.30, 0.35, 0.38, 0.40])
    # The gyroscope held from its latest sample; the others only at their own rows.
    np.testing.assert_array_equal(
        s.gyr[[0, 1, 2, 3, 4, 5, 6, 7, 8]], gyr[[0, 0, 0, 1, 1, 2, 2, 2, 3]]
    )
    np.testing.assert_array_equal(s.has_acc, [0, 0, 1, 0, 1, 0, 1, 0, 0])
    np.testing.assert_array_equal(s.acc[s.has_acc], acc[1:])
    np.testing.assert_array_equal(s.has_mag, [0, 1, 0, 0, 0, 1, 0, 1, 0])
    np.testing.assert_array_equal(s.mag[s.has_mag], mag)
    assert "multi-rate" in s.meta["source"]


def test_a_lagging_magnetometer_is_scored_at_its_own_time():
    # A steady yaw at 2 rad/s; the magnetometer shows the field 20 ms late.
    t = np.arange(0.0, 6.0, 0.005)
    yaw = 2.0 * t
    q = np.column_stack([np.cos(yaw / 2), np.zeros_like(t), np.zeros_like(t), np.sin(yaw / 2)])
    delay = 0.02
    late = 2.0 * (t - delay)
    q_late = np.column_stack(
        [np.cos(late / 2), np.zeros_like(t), np.zeros_like(t), np.sin(late / 2)]
    )
    D, o = _distortion(3, symmetric=False)
    trial = real.Trial("lagging", t, _simulate(D, o, q_late), q, np.ones(t.size, bool))
    same_time = real.trial_heading_deg(D, o, trial, DECLINATION_DEG)
    assert same_time == pytest.approx(math.degrees(2.0 * delay), rel=1e-3)  # 2.29°
    assert real.trial_heading_deg(D, o, trial, DECLINATION_DEG, delay_s=delay) < 1e-6
    # Samples whose earlier time falls before the reference starts are not scored.
    _, ok = real.reference_at(trial, delay)
    assert not ok[: int(round(delay / 0.005))].any() and ok[int(round(delay / 0.005)) :].all()


def _rig(gyro_bias_deg_s=(0.0, 0.0, 0.0), mag_delay_s=0.0, gyro_delay_s=0.0):
    """A case scored on its own recording whose reference body frame is the IMU's turned by a
    known rotation C (v_ref = C v_imu); the gyroscope measures in the IMU's axes, with a bias;
    the magnetometer and the gyroscope show the motion late by their delays. Returns the case,
    C and the IMU's own attitudes."""
    t = np.arange(0.0, 20.0, 0.01)

    def rate_imu(at):
        return np.column_stack([np.sin(0.7 * at), np.cos(0.4 * at), 0.5 * np.sin(1.1 * at + 1.0)])

    # Attitudes on a fine grid, so that a delay of a fraction of a step can be looked up.
    fine = np.arange(-0.2, 20.2, 0.001)
    q_fine = frames.integrate_rates(rate_imu(fine[:-1] + 0.0005), np.diff(fine))
    C = frames.quat_to_matrix(frames.rotvec_to_quat(np.deg2rad([1.0, -2.0, 3.0])))
    # R_imu = R_ref C, so R_ref = R_imu Cᵀ.
    q_ref_fine = frames.quat_multiply(q_fine, frames.quat_conjugate(frames.matrix_to_quat(C)))

    def at(times):
        return q_ref_fine[np.rint((times - fine[0]) / 0.001).astype(int)]

    q_ref, q_imu = at(t), frames.quat_multiply(at(t), frames.matrix_to_quat(C))
    D, o = _distortion(4, symmetric=False)
    mag = _simulate(D, o, at(t - mag_delay_s))
    gyr = rate_imu(t - gyro_delay_s) + np.deg2rad(gyro_bias_deg_s)
    session = session_from_arrays(t, gyr, np.zeros_like(mag) + [0, 0, 9.8], mag)
    case = real.Case(
        "rig", {}, session, (real.Trial("rig", t, mag, q_ref, np.ones(t.size, bool)),), 0.0
    )
    return case, C, q_imu


def _angle_deg(A: np.ndarray, B: np.ndarray) -> float:
    return float(np.rad2deg(np.linalg.norm(frames.quat_to_rotvec(frames.matrix_to_quat(A.T @ B)))))


def test_the_imu_axes_are_found_in_the_reference_frame():
    case, C, q_imu = _rig()
    found = real.imu_axes(case).C
    assert _angle_deg(found, C) < 0.05
    # In the IMU's frame the attitudes are the IMU's own.
    turned = real.in_imu_frame(case, found)
    np.testing.assert_allclose(
        frames.quat_to_matrix(turned.trials[0].q_wb), frames.quat_to_matrix(q_imu), atol=1e-3
    )


def test_the_imu_axes_are_found_past_the_gyroscopes_delay():
    # The windows compared at the same times would turn C by the rig's delayed motion.
    case, C, _ = _rig(gyro_delay_s=0.02)
    assert _angle_deg(real._aligned_windows(case, 0.0), C) > 0.1
    axes = real.imu_axes(case)
    assert _angle_deg(axes.C, C) < 0.05
    assert 1e3 * axes.gyro_delay_s == pytest.approx(20.0, abs=0.3)


def test_the_gyroscope_bias_is_read_against_the_reference():
    bias = np.array([0.3, -0.5, 2.0])
    case, C, _ = _rig(bias)
    np.testing.assert_allclose(np.rad2deg(real.reference_gyro_bias(case, C)), bias, atol=0.01)
    # Read in the wrong axes, the reference's rate leaks into the bias.
    assert np.abs(np.rad2deg(real.reference_gyro_bias(case, np.eye(3))) - bias).max() > 0.05


def test_the_rotation_the_scored_recordings_show():
    # A phone scored on two other recordings, with the calibration's own D = P U.
    P, o = _distortion(8, symmetric=True)
    U = frames.quat_to_matrix(frames.rotvec_to_quat(np.deg2rad([0.5, -2.0, 1.0])))
    D = P @ U
    trials = tuple(
        _trial(_simulate(D, o, q), q) for q in (frames.so3_grid(600), frames.so3_grid(700))
    )
    q_cal = frames.so3_grid(900)
    mag = _simulate(D, o, q_cal)
    t = np.arange(len(q_cal)) * 0.01
    session = session_from_arrays(t, np.zeros_like(mag), np.zeros_like(mag) + [0, 0, 9.8], mag)
    case = real.Case("phone", {}, session, trials, DECLINATION_DEG)
    ml_run = {"D": D.tolist(), "o": o.tolist()}
    got = real._on_other_recordings(case, (P, o), None, ml_run)
    np.testing.assert_allclose(got["fit_rotation_deg"], misalignment_deg(D), atol=1e-6)
    assert got["offset_change"] < 1e-6 * FIELD_UT
    assert got["fit"] < 1e-6
    # The plain fit turned by the scored recordings' rotation is the truth; without it, and
    # ML without its rotation, miss by about the rotation's angle.
    assert got["plain_with_fit_rotation"] < 1e-6
    plain = real.case_heading_deg(P, o, case)
    assert plain > 1.0 and got["ml_without_rotation"] == pytest.approx(plain)
    # Given the scored recordings' offset, a calibration whose offset is off (a day when the
    # hard iron moved) scores as its D does: exact for the true D, the plain fit's miss.
    shifted = {"D": D.tolist(), "o": (o + [0.1 * FIELD_UT, 0.0, 0.0]).tolist()}
    moved = real._on_other_recordings(case, (P, o + [0.1 * FIELD_UT, 0.0, 0.0]), None, shifted)
    assert real.case_heading_deg(D, np.array(shifted["o"]), case) > 1.0
    assert moved["ml_with_fit_offset"] < 1e-6
    assert moved["plain_with_fit_offset"] == pytest.approx(plain)
    # A case scored on its own recording has its floor instead.
    own = real.Case("own", {}, session, (_trial(mag, q_cal),), DECLINATION_DEG)
    assert real._on_other_recordings(own, (P, o), None, ml_run) is None


@pytest.mark.parametrize("mag_delay_ms, gyro_delay_ms", [(0.0, 0.0), (23.0, 7.0), (-12.0, 3.0)])
def test_the_delays_are_read_against_the_reference(mag_delay_ms, gyro_delay_ms):
    case, C, _ = _rig((0.5, -1.0, 2.0), mag_delay_ms * 1e-3, gyro_delay_ms * 1e-3)
    assert 1e3 * real.reference_delay(case.trials[0]) == pytest.approx(mag_delay_ms, abs=0.3)
    assert 1e3 * real.gyroscope_delay(case, C) == pytest.approx(gyro_delay_ms, abs=0.3)


def test_the_delay_is_read_on_the_magnetometers_own_samples():
    # A magnetometer read at half the rows, its value repeated in between: a repeat shows
    # the field one row later than it was measured, and is no measurement.
    case, _, _ = _rig(mag_delay_s=0.02)
    mag = case.session.mag.copy()
    mag[1::2] = mag[0:-1:2]
    trial = dataclasses.replace(case.trials[0], mag=mag)
    case = dataclasses.replace(
        case, session=dataclasses.replace(case.session, mag=mag), trials=(trial,)
    )
    measured = real.measured_rows(case)
    assert measured.sum() == len(mag) // 2
    assert 1e3 * real.reference_delay(trial, measured) == pytest.approx(20.0, abs=0.3)
    assert 1e3 * real.reference_delay(trial) > 21.0
    D, o = _distortion(4, symmetric=False)
    got = real._at_reference_delay(
        case, None, real.case_floor(case), {"D": D, "o": o}, axes=real.imu_axes(case)
    )
    assert 1e3 * got["delay_s"] == pytest.approx(20.0, abs=0.3)


def test_a_delay_beyond_the_search_is_not_reported():
    case, _, _ = _rig(mag_delay_s=1.5 * real.REFERENCE_DELAY_MAX_S)
    assert real.reference_delay(case.trials[0]) is None


def test_the_fit_at_the_magnetometers_delay_is_the_magnetometer_as_it_is():
    case, _, _ = _rig(mag_delay_s=0.03)
    floor, axes = real.case_floor(case), real.imu_axes(case)
    D, o = _distortion(4, symmetric=False)
    ml_run = {"D": D.tolist(), "o": o.tolist()}
    got = real._at_reference_delay(case, None, floor, ml_run, axes=axes)
    assert got["delay_s"] == pytest.approx(0.03, abs=3e-4)
    # The fit there has D's own rotation and no error at its own time; scored at t it is
    # charged for the lag as the true D is, while the floor takes part of the lag into D.
    np.testing.assert_allclose(got["fit_rotation_deg"], misalignment_deg(D), atol=0.05)
    assert got["fit_at_delay"] < 0.02
    assert got["fit"] == pytest.approx(got["ml"], rel=0.02) and got["ml"] > 1.0
    assert got["floor"] < got["fit"]
    assert np.linalg.norm(np.subtract(got["floor_rotation_deg"], misalignment_deg(D))) > 0.2
    # In the IMU's axes (the reference's turned by C) the fit is the magnetometer against the
    # IMU, D C, which ML would find, scored in the reference's axes as ML's result is: C's
    # 3.7° move its score away from the fit's.
    C = axes.C
    np.testing.assert_allclose(got["imu_fit_rotation_deg"], misalignment_deg(D @ C), atol=0.05)
    assert got["imu_fit"] == pytest.approx(real.case_heading_deg(D @ C, o, case), rel=0.01)
    assert abs(got["imu_fit"] - got["fit"]) > 1.0
    # Without a floor (a case scored on other recordings) there is nothing to compare.
    assert real._at_reference_delay(case, None, None, ml_run, axes=axes) is None


def test_trial_by_trial_pairs_each_recording():
    P, o = _distortion(8, symmetric=True)
    U = frames.quat_to_matrix(frames.rotvec_to_quat(np.deg2rad([0.5, -2.0, 1.0])))
    D = P @ U
    qs = (frames.so3_grid(600), frames.so3_grid(700), _level_attitudes(300))
    trials = tuple(_trial(_simulate(D, o, q, noise_ut=0.5, seed=k), q) for k, q in enumerate(qs))
    session = session_from_arrays(
        np.arange(10) * 0.01, np.zeros((10, 3)), np.zeros((10, 3)), np.ones((10, 3))
    )
    case = real.Case("phone", {}, session, trials, DECLINATION_DEG)
    got = real._trial_by_trial(case, (P, o), None, {"D": D.tolist(), "o": o.tolist()})
    assert got["names"] == ["synthetic"] * 3
    for k, tr in enumerate(trials):
        assert got["ml"][k] == pytest.approx(real.trial_heading_deg(D, o, tr, DECLINATION_DEG))
        assert got["plain"][k] == pytest.approx(real.trial_heading_deg(P, o, tr, DECLINATION_DEG))
    assert max(got["ml"]) < min(got["plain"])  # the plain fit misses the rotation
    one = dataclasses.replace(case, trials=trials[:1])
    assert real._trial_by_trial(one, (P, o), None, {"D": D.tolist(), "o": o.tolist()}) is None


def test_the_right_calibration_is_taken_from_the_section_each_case_has():
    def result(case, plain, ml, refused=None, **sections):
        methods = {"ml": {"heading_deg": ml, "refused": refused}}
        return {"case": case, "plain": plain, "methods": methods, **sections}

    results = [
        result("own", 6.0, 5.5, reference_delay={"fit": 5.0}),
        result("other", 7.0, 8.0, other_recordings={"fit_with_ml_offset": 7.5}),
        result("refused", 7.0, 9.0, refused="no", reference_delay={"fit": 6.5}),
        result("no plain", None, 3.0, reference_delay={"fit": 2.0}),
        result("no section", 5.0, 4.0),
    ]
    got = real.right_calibrations(results)
    assert [(c.case, c.right, c.ml) for c in got] == [
        ("own", 5.0, 5.5),
        ("other", 7.5, 8.0),
        ("refused", 6.5, None),
    ]
    assert got[0].kind != got[1].kind
    assert [c.better for c in got] == [5.0, 7.5, 6.5]
