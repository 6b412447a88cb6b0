# SPDX-License-Identifier: Apache-2.0
"""``magcal import`` of PX4 ULog files written by tests/loggen (read back with pyulog)."""

from __future__ import annotations

import numpy as np
import pytest

from magcal.calib.calibrate import calibrate
from magcal.calib.diagnostics import quality
from magcal.logs import LogImportError, import_log, ulog
from magcal.logs.correction import MIXED_WINDOW_S
from tests.loggen.scenario import bench_day
from tests.loggen.tlog import PX4_PARAMS
from tests.loggen.ulog import write_ulog

CHANGE = (60.0, "CAL_MAG0_XOFF", 0.08)


@pytest.fixture(scope="module")
def day():
    return bench_day(seed=4)


@pytest.fixture(scope="module")
def logs(day, tmp_path_factory):
    d = tmp_path_factory.mktemp("ulog")
    write_ulog(d / "raw.ulg", day, changes=[CHANGE])
    write_ulog(d / "calibrated.ulg", day, changes=[CHANGE], raw=False)
    short = bench_day(seed=5, hand_s=6.0)
    write_ulog(d / "nosc.ulg", short, omit=("sensor_combined",))
    write_ulog(d / "short.ulg", short)
    return {p.stem: str(p) for p in d.iterdir()}


@pytest.fixture(scope="module")
def raw_result(logs):
    return import_log(logs["raw"])


def _index(day, t):
    k = np.searchsorted(day.t, t - 1e-7)
    assert np.allclose(day.t[k], t, rtol=0, atol=1e-9)
    return k


def test_sensor_mag_is_the_raw_field(day, raw_result):
    streams = raw_result.streams
    assert streams.autopilot == "px4" and streams.log_format == "ULog"
    assert streams.mag.source == "sensor_mag[0]" and streams.mag.unit == "gauss"
    k = _index(day, streams.mag.t)
    assert np.array_equal(streams.mag.mag, (day.mag[k] / 1000.0).astype(np.float32))
    # sensor_combined averages over [t − dt, t], stamped t: placed at the middle
    dt = day.t[1] - day.t[0]
    assert np.allclose(streams.imu.t, day.t + dt / 2, rtol=0, atol=1e-9)
    assert np.array_equal(streams.imu.gyr, day.gyr.astype(np.float32))
    # the parameters: initial, and the change with its time
    assert streams.params.initial["CAL_MAG0_ROT"] == 0.0
    assert streams.params.initial["CAL_MAG0_ID"] == PX4_PARAMS["CAL_MAG0_ID"]
    ((when, name, value),) = streams.params.changes
    assert name == "CAL_MAG0_XOFF" and value == pytest.approx(0.08)
    assert when == pytest.approx(CHANGE[0], abs=0.01)
    assert streams.armed is not None


def test_the_stretch_is_found_and_calibrates(day, raw_result):
    assert abs(raw_result.stretch.start_s - day.hand[0]) <= 1.0
    assert abs(raw_result.stretch.end_s - day.hand[1]) <= 1.0
    meta = raw_result.session.meta
    assert meta["mag_unit"] == "gauss" and meta["autopilot"] == "px4"
    assert meta["param.CAL_MAG0_XOFF"] == "0.05" and meta["param.CAL_MAG0_ID"] == "396825"
    assert meta["compass_external"] == "1"
    cal = calibrate(raw_result.session, "ml")
    s = day.sensor
    r = cal.result
    e = quality.calibration_heading_errors(s.D / 1000, s.o / 1000, s.m_n, r.D, r.o)
    assert quality.rms_deg(e) < 0.1  # measured 0.04° over seeds 0–2


def test_vehicle_magnetometer_is_undone_with_the_calibration_in_force(day, logs):
    streams = ulog.read(logs["calibrated"])
    assert streams.mag.source == "vehicle_magnetometer[0]"
    k = _index(day, streams.mag.t)
    # float32 in the log, float64 undo
    assert np.allclose(streams.mag.mag, day.mag[k] / 1000.0, rtol=0, atol=2e-6)
    every = np.arange(0, day.t.size, 4)
    dropped = np.setdiff1d(every, k)
    assert dropped.size == int(MIXED_WINDOW_S * 50)
    assert np.all((day.t[dropped] > CHANGE[0] - 0.01) & (day.t[dropped] <= CHANGE[0] + 0.51))
    assert any("changed 1 time(s)" in n for n in streams.notes)


def test_an_internal_magnetometer_with_a_level_adjustment_is_undone(day, tmp_path):
    """Internal (CAL_MAG0_ROT = −1): PX4 rotates it with the board, SENS_BOARD_ROT, and newer
    PX4 adds the level adjustment SENS_BOARD_X/Y/Z_OFF to every magnetometer's rotation."""
    params = dict(PX4_PARAMS, CAL_MAG0_ROT=-1.0, SENS_BOARD_ROT=4.0)
    params |= {"SENS_BOARD_X_OFF": 1.5, "SENS_BOARD_Y_OFF": -0.8, "SENS_BOARD_Z_OFF": 2.0}
    path = tmp_path / "internal.ulg"
    write_ulog(path, day, params=params, raw=False)
    streams = ulog.read(str(path))
    k = _index(day, streams.mag.t)
    assert np.allclose(streams.mag.mag, day.mag[k] / 1000.0, rtol=0, atol=2e-6)
    assert "SENS_BOARD_X_OFF" in streams.param_names and "SENS_BOARD_ROT" in streams.param_names
    assert import_log(str(path)).session.meta["compass_external"] == "0"
    # without SENS_BOARD_ROT in the log, an internal calibration cannot be undone
    write_ulog(path, day, params=params, raw=False, unlogged=("SENS_BOARD_ROT",))
    with pytest.raises(LogImportError, match=r"internal one \(CAL_MAG0_ROT = -1\)"):
        ulog.read(str(path))


def test_missing_topics_are_listed(logs):
    with pytest.raises(
        LogImportError,
        match=r"nosc.ulg has no sensor_combined for IMU 1 \(found IMUs none\); needs "
        "sensor_combined, and sensor_mag, vehicle_magnetometer or a magnetometer in "
        "sensor_combined",
    ):
        import_log(logs["nosc"])
    with pytest.raises(
        LogImportError,
        match=r"no sensor_mag, vehicle_magnetometer or sensor_combined magnetometer for "
        r"compass 2 \(found compasses 1\)",
    ):
        ulog.read(logs["short"], compass=2)
    with pytest.raises(LogImportError, match=r"no vehicle_imu instance 1 for IMU 2"):
        ulog.read(logs["short"], imu=2)
