# SPDX-License-Identifier: Apache-2.0
"""A result its own session contradicts is refused: each check of
``magcal.calib.diagnostics.consistency`` on constructed data, the refusal through
``calibrate`` and ``magcal calibrate`` (exit 2, nothing written; ``--force`` writes it with the
refusal as a warning), and good simulated sessions of every preset pass."""

from __future__ import annotations

import dataclasses
import json
import re

import numpy as np
import pytest

from magcal.calib import frames
from magcal.calib.calibrate import calibrate
from magcal.calib.diagnostics import consistency
from magcal.cli import EXIT_ERROR, main
from magcal.errors import FieldChangedError, MagcalError, ResultContradictedError
from magcal.io.result import read_result
from magcal.io.session import write_session
from magcal.sim.scenarios import preset, simulate
from magcal_evaluation.accuracy import heading_rms_deg


@pytest.fixture(scope="module")
def mems():
    return simulate(preset("mems"), 1)


@pytest.fixture(scope="module")
def handheld():
    """Fast hand-held motion: every 5 s of it visits most field directions, so a change of the
    field shows at the same directions (a slow tumble's halves see different ones)."""
    return simulate(preset("handheld"), 1)


def _check(session, D, o, bias=None, A=None):
    return consistency.check(session.t, session.acc, session.mag, D, o, bias, A, gyr=session.gyr)


def _refuse(checks):
    consistency.refusals_or_warnings(checks, "ml", force=False)


def test_the_true_calibration_passes(mems):
    session, truth = mems
    st = truth.sensor
    checks = _check(session, st.D, st.o, st.gyro_bias)
    assert checks.refusals == [] and checks.warnings == []
    assert checks.figures["D_condition"] < 2.0


def test_a_gyroscope_bias_of_40_deg_s_is_refused(mems):
    session, truth = mems
    st = truth.sensor
    checks = _check(session, st.D, st.o, np.deg2rad([40.0, 0.0, 0.0]))
    with pytest.raises(ResultContradictedError, match=r"gyroscope bias of 40\.0 °/s.*limit 25"):
        _refuse(checks)
    # Just inside the limit, nothing to say about the bias itself (the field, carried by a
    # gyroscope 24 °/s off, no longer turns as it should: the turn check says that).
    refusals = _check(session, st.D, st.o, np.deg2rad([0.0, -24.0, 0.0])).refusals
    assert not any("gyroscope bias" in r for r in refusals)


def test_a_d_with_condition_1e5_is_refused(mems):
    session, truth = mems
    st = truth.sensor
    u, s, vt = np.linalg.svd(st.D)
    D = u @ np.diag([s[0], s[0], s[0] * 1e-5]) @ vt
    checks = _check(session, D, st.o)
    assert checks.figures["D_condition"] == pytest.approx(1e5, rel=1e-6)
    with pytest.raises(ResultContradictedError, match=r"stretches one axis 1e\+05×.*limit 10"):
        _refuse(checks)


def test_a_non_finite_d_and_an_ellipsoid_that_is_not_one_are_refused(mems):
    session, truth = mems
    st = truth.sensor
    with pytest.raises(ResultContradictedError, match="not finite"):
        _refuse(_check(session, np.full((3, 3), np.nan), st.o))
    A = np.diag([1.0, 1.0, -0.1])
    with pytest.raises(ResultContradictedError, match="not positive definite"):
        _refuse(_check(session, st.D, st.o, A=A))


def test_a_worse_field_norm_than_raw_and_plain_fit_is_refused(handheld):
    session, truth = handheld
    st = truth.sensor
    # The offset moved by most of the field: the norm swings with orientation.
    o = st.o + 0.8 * st.D[:, 0]
    checks = _check(session, st.D, o)
    spread = checks.figures["field_norm_spread"]
    assert spread["result"] > max(spread["raw"], 2 * spread["plain_fit"])
    with pytest.raises(ResultContradictedError, match=r"corrected field norm varies by .* %"):
        _refuse(checks)


def test_a_wrong_alignment_with_the_accelerometer_is_refused(mems):
    session, truth = mems
    st = truth.sensor
    c, s = np.cos(np.deg2rad(20.0)), np.sin(np.deg2rad(20.0))
    turned = st.D @ np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])
    checks = _check(session, turned, st.o)
    assert checks.figures["field_norm_spread"]["result"] == pytest.approx(
        checks.figures["field_norm_spread"]["plain_fit"], rel=0.05
    )  # the same ellipsoid: only the dip can tell
    with pytest.raises(ResultContradictedError, match=r"dip angle .* scatters by"):
        _refuse(checks)


def test_axes_turned_against_the_gyroscope_are_refused(mems):
    session, truth = mems
    st = truth.sensor
    checks = _check(session, st.D, st.o, st.gyro_bias)
    assert checks.figures["turn_miss_deg"]["result"] < checks.figures["turn_miss_deg"]["plain_fit"]
    # Turned by 10° about the body's z axis: no change of the ellipsoid, and none of the dip
    # at rest, but the field no longer turns as the gyroscope says.
    c, s = np.cos(np.deg2rad(10.0)), np.sin(np.deg2rad(10.0))
    turned = st.D @ np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    checks = _check(session, turned, st.o, st.gyro_bias)
    miss = checks.figures["turn_miss_deg"]
    assert miss["result"] > 1.5 * miss["plain_fit"] + 0.5
    assert miss["turn_deg"] == pytest.approx(10.0, abs=0.05)
    with pytest.raises(ResultContradictedError, match=r"axes are turned against the gyroscope"):
        _refuse(checks)


def test_the_turn_miss_of_a_rotation_the_gyroscope_measured_is_zero():
    t = np.arange(0.0, 5.0, 0.01)
    rate = np.tile([0.3, -0.5, 0.8], (t.size, 1))
    R = frames.quat_to_matrix(frames.integrate_rates(rate[:-1], np.diff(t)))
    field = np.einsum("kji,j->ki", R, [0.4, 0.0, -0.9])  # Rᵀ m: the field in the body frame
    (miss,), pairs = consistency.turn_misses_deg(t, rate, np.zeros(3), field)
    assert miss < 1e-6 and pairs == np.sum(t + consistency.TURN_WINDOW_S <= t[-1] + 1e-9)


def _field_jump(session, o, factor):
    """The session with the field (not the offset) scaled by ``factor`` from halfway on."""
    mag = session.mag.copy()
    half = session.t >= session.t[0] + 0.5 * (session.t[-1] - session.t[0])
    mag[half] = o + factor * (mag[half] - o)
    return dataclasses.replace(session, mag=mag)


def test_a_field_that_jumps_20_percent_halfway_is_refused_naming_the_stretch(handheld):
    session, truth = handheld
    jumped = _field_jump(session, truth.sensor.o, 1.2)
    with pytest.raises(
        FieldChangedError,
        match=r"field changed during the recording.* between 30 s and 60 s.*constant for only "
        r"46 %.*away from it.*--force",
    ):
        calibrate(jumped, "init")
    forced = calibrate(jumped, "init", force=True).result
    assert any("forced" in w and "field changed" in w for w in forced.warnings)
    assert forced.extra["consistency"]["field_stretches"]["impact"] > 0.02
    assert "field_left_out" not in forced.extra


def _changed_between(session, o, start_s, end_s, factor=1.2):
    mag = session.mag.copy()
    rel = session.t - session.t[0]
    inside = (rel >= start_s) & (rel < end_s)
    mag[inside] = o + factor * (mag[inside] - o)
    return dataclasses.replace(session, mag=mag)


@pytest.mark.parametrize(("start_s", "end_s"), [(57.0, 60.0), (20.0, 32.0), (18.0, 31.0)])
def test_a_change_over_a_third_or_less_is_left_out(handheld, start_s, end_s):
    """At the end (a sensor set down by steel) or in the middle (carried past it): calibrated
    without the changed stretches' magnetometer readings, as well as without the change."""
    session, truth = handheld
    changed = _changed_between(session, truth.sensor.o, start_s, end_s)
    clean = calibrate(session, "ml").result
    result = calibrate(changed, "ml").result
    left_out = result.extra["field_left_out"]
    assert any("calibrated without the magnetometer's readings there" in w for w in result.warnings)
    spans = left_out["left_out_s"]
    # The stretches of 5 s that hold the change with their margins, and nothing else.
    assert spans[0][0] <= start_s and spans[-1][1] >= end_s - 0.1
    assert sum(b - a for a, b in spans) <= (end_s - start_s) + 2 * (
        consistency.FIELD_STRETCH_S + consistency.CHANGE_MARGIN_S
    )
    assert np.allclose(result.D, clean.D, rtol=0, atol=2e-3 * np.abs(clean.D).max())
    assert np.allclose(result.o, clean.o, rtol=0, atol=2e-3 * np.abs(clean.D).max())
    # Forced, all of it is used, and the result's check names the change.
    forced = calibrate(changed, "init", force=True).result
    assert "field_left_out" not in forced.extra
    assert any("field changed" in w for w in forced.warnings)


@pytest.mark.parametrize(
    ("name", "overrides", "methods"),
    [
        ("mems", {}, ("ml", "init", "ckf", "two-step")),
        ("handheld", {}, ("ml", "init", "ckf", "two-step")),
        ("raw-counts", {}, ("ml", "init")),
        ("mems", {"translational_acc_rms": 2.0}, ("ml", "init")),
        # Noisy and 4 s long: the ML result is good, the ellipsoid-only ones often are not.
        ("table2", {}, ("ml",)),
    ],
)
def test_good_simulated_sessions_are_not_refused(name, overrides, methods):
    for seed in (0, 1):
        session, _ = simulate(preset(name, **overrides), seed)
        for method in methods:
            result = calibrate(session, method).result
            assert "consistency" in result.extra
            assert not any("changed" in w for w in result.warnings)


def test_cli_refuses_with_exit_2_and_writes_nothing_unless_forced(handheld, tmp_path, capsys):
    session, truth = handheld
    path = tmp_path / "jump.csv"
    write_session(path, _field_jump(session, truth.sensor.o, 1.2))
    out = tmp_path / "r.json"
    assert main(["calibrate", str(path), "--method", "init", "-q", "-o", str(out)]) == EXIT_ERROR
    err = capsys.readouterr().err
    assert err.startswith("magcal calibrate: ") and err.count("\n") == 1
    assert "field changed" in err and "--force" in err
    assert not out.exists()
    assert main(["calibrate", str(path), "--method", "init", "--force", "-o", str(out)]) == 0
    warnings = read_result(out).warnings
    assert any("forced: the result contradicts its own session" in w for w in warnings)


def test_a_stretch_that_shares_no_direction_is_left_out_and_the_figures_are_json():
    rng = np.random.default_rng(0)
    t = np.arange(2000) * 0.01  # 20 s: four stretches
    field = rng.normal(size=(2000, 3))
    field[:, 2] = np.abs(field[:, 2]) + 0.5  # the first three stretches: the upper half only
    field[1500:] = [0.0, 0.0, -1.0]  # the last: one direction nobody else saw
    field /= np.linalg.norm(field, axis=1)[:, None]
    acc = np.tile([0.0, 0.0, 9.81], (2000, 1))
    checks = consistency.check(t, acc, 50.0 * field, 50.0 * np.eye(3), np.zeros(3), None)
    levels = checks.figures["field_stretches"]["levels"]
    assert [row[2] is None for row in levels] == [False, False, False, True]
    json.dumps(checks.figures, allow_nan=False)


def test_the_fit_residual_sees_a_fit_error_through_noise():
    rng = np.random.default_rng(4)
    u = rng.normal(size=(20000, 3))
    u /= np.linalg.norm(u, axis=1)[:, None]
    # Slow motion: the fit's error changes little from one sample to the next.
    u = np.cumsum(u, axis=0)
    u /= np.linalg.norm(u, axis=1)[:, None]
    noise = 0.2 * rng.normal(size=(20000, 3))  # 20 % of the field per axis
    alone = consistency.fit_residual(u + noise)
    # The noise relative to the mean strength, which the noise itself raises by ≈ 4 %.
    assert alone.noise == pytest.approx(0.2 / 1.04, rel=0.03) and alone.lower < 0.01
    bent = u * (1.0 + 0.1 * np.sqrt(2) * np.sin(np.arange(20000) / 300.0))[:, None]
    figure = consistency.fit_residual(bent + 0.01 * rng.normal(size=(20000, 3)))
    assert figure.beyond == pytest.approx(0.1, rel=0.05) and figure.lower > 0.09


def _not_an_ellipsoid(session, o, D, amplitude):
    """The field's strength scaled by 1 + amplitude·uₓu_yu_z of its direction u: a distortion
    no ellipsoid has (RMS amplitude/√105 over the sphere), the direction unchanged."""
    m = np.linalg.solve(D, (session.mag - o).T).T
    u = m / np.linalg.norm(m, axis=1)[:, None]
    scale = 1.0 + amplitude * u[:, 0] * u[:, 1] * u[:, 2]
    return dataclasses.replace(session, mag=o + (scale[:, None] * m) @ D.T)


def test_a_field_no_ellipsoid_fits_is_refused_by_the_absolute_gate(handheld, tmp_path, capsys):
    session, truth = handheld
    bent = _not_an_ellipsoid(session, truth.sensor.o, truth.sensor.D, 1.2)  # 11.7 % RMS
    path = tmp_path / "bent.csv"
    write_session(path, bent)
    out = tmp_path / "r.json"
    assert main(["calibrate", str(path), "-q", "-o", str(out)]) == EXIT_ERROR
    err = capsys.readouterr().err
    assert re.search(
        r"strength is not constant: it departs from its mean by 1\d\.\d % of the "
        r"field .*limit 8 %",
        err,
    ), err
    assert not out.exists()
    # The limit is the user's to move.
    assert main(["calibrate", str(path), "-q", "--max-fit-residual", "15", "-o", str(out)]) == 0
    figure = read_result(out).extra["consistency"]["fit_residual"]
    assert 0.08 < figure["lower"] < 0.15 and figure["limit"] == 0.15
    # A distortion of a third of that passes the default gate.
    write_session(path, _not_an_ellipsoid(session, truth.sensor.o, truth.sensor.D, 0.4))
    assert main(["calibrate", str(path), "-q", "-o", str(out)]) == 0


def test_the_command_line_default_is_the_gate():
    from magcal.commands.calibrate import DEFAULT_MAX_FIT_RESIDUAL_PERCENT

    assert DEFAULT_MAX_FIT_RESIDUAL_PERCENT / 100 == consistency.MAX_FIT_RESIDUAL


@pytest.fixture(scope="module")
def swing():
    """Fast swings about the body's x axis on a tumble, with 3.9 m/s² of accelerations:
    most of the turning is about one axis, and the accelerometer's gravity is blurred."""
    return simulate(preset("handheld", motion="swing", translational_acc_rms=3.9), 5)


def test_a_correction_turned_about_the_swing_axis_is_refused(swing):
    session, truth = swing
    st = truth.sensor
    turned = st.D @ frames.rotvec_to_matrix(np.deg2rad([24.0, 0.0, 0.0])).T
    checks = _check(session, turned, st.o, st.gyro_bias)
    with pytest.raises(
        ResultContradictedError,
        match=r"turned by 24° about its \(-1\.00, [+-]0\.00, [+-]0\.00\).*To do: record again "
        r"turning the sensor about more than one axis.*--force",
    ):
        _refuse(checks)
    # Against the plain fit, itself misaligned, the turned correction's miss looks small.
    figures = checks.figures["turn_miss_deg"]
    limit = consistency.TURN_MAX_RATIO * figures["plain_fit"] + consistency.TURN_MARGIN_DEG
    assert figures["result"] < limit
    assert _check(session, st.D, st.o, st.gyro_bias).refusals == []


@pytest.mark.parametrize("method", ["ml", "init", "ckf", "two-step"])
def test_every_method_on_a_swinging_session_is_right_or_refused(swing, method):
    session, truth = swing
    try:
        result = calibrate(session, method).result
    except MagcalError:
        return
    error = heading_rms_deg(truth, result.D, result.o)
    assert error < 10.0, f"{method}: {error:.1f}° written"


def _field_stretch_medians_by_masks(t, calibrated):
    """The medians and counts of ``consistency.field_stretches``, one mask per stretch and
    direction (the plain way, O(N × cells)): the reference its grouped version must equal."""
    norm = np.linalg.norm(calibrated, axis=1)
    cell = np.argmax((calibrated / norm[:, None]) @ consistency._DIRECTIONS.T, axis=1)
    index = np.floor((t - t[0]) / consistency.FIELD_STRETCH_S).astype(int)
    med = np.full((index.max() + 1, consistency.FIELD_DIRECTIONS), np.nan)
    count = np.zeros(med.shape, dtype=int)
    for j in range(index.max() + 1):
        for c in np.unique(cell[index == j]):
            values = norm[(index == j) & (cell == c)]
            count[j, c] = values.size
            if values.size >= consistency.FIELD_MIN_CELL_SAMPLES:
                med[j, c] = np.median(values)
    return med, count


def test_field_stretches_group_the_samples_as_masks_do(handheld):
    session, _ = handheld
    rng = np.random.default_rng(2)
    cal = session.mag - session.mag.mean(axis=0)
    cal[rng.integers(0, len(cal), 5)] = np.nan  # NaN in, NaN out, as np.median
    med, count = _field_stretch_medians_by_masks(session.t, cal)
    norm = np.linalg.norm(cal, axis=1)
    cell = np.argmax((cal / norm[:, None]) @ consistency._DIRECTIONS.T, axis=1)
    index = np.floor((session.t - session.t[0]) / consistency.FIELD_STRETCH_S).astype(int)
    groups, first, sizes, ranked = consistency._sorted_groups(
        index * consistency.FIELD_DIRECTIONS + cell, norm
    )
    np.testing.assert_array_equal(count.flat[groups], sizes)
    assert count.sum() == sizes.sum() == len(norm)
    middle = 0.5 * (ranked[first + (sizes - 1) // 2] + ranked[first + sizes // 2])
    middle[np.isnan(ranked[first + sizes - 1])] = np.nan
    enough = sizes >= consistency.FIELD_MIN_CELL_SAMPLES
    np.testing.assert_array_equal(middle[enough], med.flat[groups[enough]])
    # The stretches' spans and levels on clean data, against the same masks.
    clean = session.mag - session.mag.mean(axis=0)
    stretches = consistency.field_stretches(session.t, clean)
    index = np.floor((session.t - session.t[0]) / consistency.FIELD_STRETCH_S).astype(int)
    spans = [
        (session.t[index == j][0] - session.t[0], session.t[index == j][-1] - session.t[0])
        for j in range(index.max() + 1)
    ]
    assert [(s.start_s, s.end_s) for s in stretches] == spans


def test_what_is_left_after_a_change_must_still_determine_the_calibration(handheld, monkeypatch):
    """Were the part left after a change to turn about the vertical only, the session is
    refused for that, not calibrated from it."""
    from magcal.calib import calibrate as pipeline

    yaw, _ = simulate(preset("handheld", motion="yaw-only", duration_s=60.0), 1)

    def left(session, view):
        return yaw, yaw, {"left_out_s": [[0.0, 5.0]]}, ["the magnetic field changed …"]

    monkeypatch.setattr(pipeline, "_without_changed_field", left)
    with pytest.raises(MagcalError, match="cannot determine the magnetometer calibration"):
        calibrate(handheld[0], "init")
