# SPDX-License-Identifier: Apache-2.0
"""``magcal import`` on the command line, and on to ``magcal calibrate``."""

from __future__ import annotations

import io
import json
import sys

import numpy as np
import pytest

from magcal.autopilot import flash, vehicle, wmm
from magcal.calib import frames
from magcal.calib.diagnostics import quality
from magcal.cli import main
from magcal.io.session import read_session
from tests.loggen.dataflash import write_bin
from tests.loggen.scenario import bench_day


@pytest.fixture(scope="module")
def day():
    return bench_day(seed=0)


@pytest.fixture(scope="module")
def log(day, tmp_path_factory):
    path = tmp_path_factory.mktemp("cli") / "flight.bin"
    write_bin(path, day)
    return str(path)


@pytest.fixture(scope="module")
def imported(log, tmp_path_factory):
    """`magcal import` then `magcal calibrate`: (session path, result path, import stderr)."""
    d = tmp_path_factory.mktemp("imported")
    session_path, result_path = d / "s.csv", d / "r.json"
    capture = pytest.MonkeyPatch()
    err = io.StringIO()
    capture.setattr(sys, "stderr", err)
    try:
        assert main(["import", log, "-o", str(session_path)]) == 0
        import_err = err.getvalue()
        assert main(["calibrate", str(session_path), "-o", str(result_path)]) == 0
    finally:
        capture.undo()
    return session_path, result_path, import_err


def test_import_reports_progress_and_the_stretch(imported):
    err = imported[2]
    assert "reading flight.bin: 100 %" in err
    assert "ArduPilot DataFlash log: IMU 1 at 200.0 Hz, compass 1 at 50.0 Hz (mG)" in err
    assert "found hand rotation" in err and "importing" in err


def test_import_then_calibrate_recovers_the_simulated_calibration(day, imported):
    session_path, result_path, _ = imported
    result = json.loads(result_path.read_text())
    D, o = np.array(result["D"]), np.array(result["o"])
    s = day.sensor
    ml = quality.rms_deg(quality.calibration_heading_errors(s.D, s.o, s.m_n, D, o))
    # the best any estimate can do with these data: least squares with the true attitude
    session = read_session(session_path)
    assert session.has_acc.sum() > 3 * session.has_mag.sum()  # every IMU sample kept
    t = session.t[session.has_mag]
    k = np.searchsorted(day.t, t - 1e-7)
    D0, o0 = quality.known_attitude_fit(session.mag[session.has_mag], day.q_nb[k], s.m_n)
    floor = quality.rms_deg(quality.calibration_heading_errors(s.D, s.o, s.m_n, D0, o0))
    # measured (seed 0): floor 0.024°, ML 0.040° on the multi-rate session (0.031° on rows
    # at the magnetometer's samples); the README's MEMS ratio is 1.16
    assert ml < 0.1 and ml < 2.0 * floor
    assert np.allclose(o, s.o, atol=1.0)  # mG


def test_the_session_maps_onto_ardupilot_parameters_like_a_collected_one(day, imported):
    """flash reads the compass parameters in force from the session (param.NAME lines, as
    `magcal collect` writes them): the plan it makes from the imported session's calibration,
    applied by the autopilot's own correction, gives the true field direction."""
    session_path, result_path, _ = imported
    session = read_session(session_path)
    result = json.loads(result_path.read_text())
    recorded = vehicle.params_from_meta(session.meta)
    assert recorded["COMPASS_ORIENT"] == 6 and recorded["COMPASS_OFS_X"] == -40.5
    assert session.meta["autopilot"] == vehicle.ARDUPILOT and session.meta["compass"] == "1"
    assert session.meta["compass_external"] == "1"
    values = dict(recorded, CUST_ROT_ENABLE=0.0)
    cp = vehicle.CompassParams(vehicle.ARDUPILOT, 1, values, {}, naming="legacy")
    field = wmm.Field(50_000.0, None, None, "test")  # 500 mG
    plan = flash.plan_flash(
        np.array(result["D_inv"]), np.array(result["o"]), cp, field, recorded=recorded
    )
    new = dict(values) | {e.name: e.value for e in plan.writes}
    assert new["COMPASS_ORIENT"] == 101  # ORIENT 6 (yaw 270°) and a few degrees more
    after = vehicle.CompassParams(vehicle.ARDUPILOT, 1, new, {}, naming="legacy")
    # noise-free readings at the session's true attitudes
    k = np.searchsorted(day.t, session.t - 1e-7)
    m_b = np.einsum("kji,j->ki", frames.quat_to_matrix(day.q_nb[k]), day.sensor.m_n)
    B = vehicle.onboard_correction(m_b @ day.sensor.D.T + day.sensor.o, after, recorded)
    cos = np.sum(B * m_b, axis=1) / np.linalg.norm(B, axis=1)
    angle = np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))
    assert np.sqrt(np.mean(angle**2)) < 0.05  # measured 0.014°
    assert np.linalg.norm(B, axis=1).mean() == pytest.approx(500.0, rel=1e-3)


def test_start_and_end_on_the_command_line(log, tmp_path, capsys):
    out = tmp_path / "s.csv"
    assert main(["import", log, "-o", str(out), "--start", "10", "--end", "20"]) == 0
    assert "range from --start/--end: 10.00–20.00 s" in capsys.readouterr().err
    session = read_session(out)
    assert session.t[0] >= 10.0 and session.t[-1] <= 20.0
    assert session.has_mag.sum() == 501  # 50 Hz, both ends included
    assert session.has_acc.sum() > 3 * 501  # and every IMU sample between


def test_a_missing_compass_is_one_paragraph_and_exit_2(log, tmp_path, capsys):
    out = tmp_path / "s.csv"
    assert main(["import", log, "-o", str(out), "--compass", "2"]) == 2
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert err == (
        "magcal import: flight.bin has no MAG messages for compass 2 (found compasses 1); "
        "needs IMU, MAG and PARM messages"
    )
    assert not out.exists()


def test_an_unwritable_output_is_refused_before_reading(log, tmp_path, capsys):
    assert main(["import", log, "-o", str(tmp_path / "no" / "s.csv")]) == 2
    err = capsys.readouterr().err
    assert "writing session" in err and "does not exist" in err
    assert "reading flight.bin" not in err


def test_a_short_range_warns(log, tmp_path, capsys):
    assert main(["import", log, "-o", str(tmp_path / "s.csv"), "--start", "10", "--end", "12"]) == 0
    err = capsys.readouterr().err
    assert "warning: 101 magnetometer samples; calibration needs at least 200" in err


def test_a_slowly_logged_imu_gets_a_note(tmp_path, capsys):
    path = tmp_path / "slow.bin"
    write_bin(path, bench_day(seed=1, rate_hz=40.0, hand_s=8.0), mag_every=4)
    assert main(["import", str(path), "-o", str(tmp_path / "s.csv")]) == 0
    err = capsys.readouterr().err
    assert "IMU 1 at 40.0 Hz, compass 1 at 10.0 Hz" in err
    assert "note: the IMU is logged at only 40 Hz" in err
