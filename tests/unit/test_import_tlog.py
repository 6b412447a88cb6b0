# SPDX-License-Identifier: Apache-2.0
"""``magcal import`` of MAVLink telemetry logs (ArduPilot and PX4 personalities)."""

from __future__ import annotations

import numpy as np
import pytest

from magcal.autopilot import mapping
from magcal.calib.calibrate import calibrate
from magcal.calib.diagnostics import quality
from magcal.logs import ImportOptions, LogImportError, import_log, tlog
from tests.loggen.dataflash import COMPASS_PARAMS
from tests.loggen.scenario import bench_day
from tests.loggen.tlog import GRAVITY_MSS, PX4_PARAMS, write_ardupilot_tlog, write_px4_tlog


@pytest.fixture(scope="module")
def day():
    return bench_day(seed=2)


@pytest.fixture(scope="module")
def ap_log(day, tmp_path_factory):
    path = tmp_path_factory.mktemp("tlog") / "ap.tlog"
    changes = [(30.0, "COMPASS_OFS_Y", 70.0)]
    return str(path), write_ardupilot_tlog(path, day, changes=changes)


@pytest.fixture(scope="module")
def ap_result(ap_log):
    return import_log(ap_log[0])


@pytest.fixture(scope="module")
def px4_log(day, tmp_path_factory):
    path = tmp_path_factory.mktemp("tlog") / "px4.tlog"
    return str(path), write_px4_tlog(path, day, highres_every=4)


@pytest.fixture(scope="module")
def px4_result(px4_log):
    return import_log(px4_log[0])


@pytest.fixture(scope="module")
def short_logs(tmp_path_factory):
    """Short ArduPilot and PX4 tlogs for the error paths (each read costs a full parse)."""
    short = bench_day(seed=3, hand_s=6.0)
    d = tmp_path_factory.mktemp("short")
    write_ardupilot_tlog(d / "ap.tlog", short)
    write_ardupilot_tlog(d / "noparams.tlog", short, omit=("PARAM_VALUE",))
    write_px4_tlog(d / "px4.tlog", short, highres_every=4)
    return {name: str(d / f"{name}.tlog") for name in ("ap", "noparams", "px4")}


def _index(day, t):
    k = np.searchsorted(day.t, t - 1e-7)
    assert np.allclose(day.t[k], t, rtol=0, atol=1e-9)
    return k


def _heading_rms_deg(day, result, unit_scale=1.0):
    s = day.sensor
    return quality.rms_deg(
        quality.calibration_heading_errors(
            s.D * unit_scale, s.o * unit_scale, s.m_n, result.D, result.o
        )
    )


def test_ardupilot_telemetry_is_undone_with_the_parameters_received(day, ap_log, ap_result):
    streams = ap_result.streams
    assert streams.autopilot == "ardupilot" and streams.log_format == "tlog"
    assert streams.imu.source == "RAW_IMU" and streams.mag.source == "RAW_IMU"
    k = _index(day, streams.mag.t)
    # the GCS heartbeat of system 255 did not make it the vehicle; nothing but the first
    # sample (before the vehicle's first heartbeat arrived), the samples right after the
    # parameter change and exact repeats of the reading before (stale) are missing
    (stale,) = [int(n.split()[0]) for n in streams.notes if "repeating the one before" in n]
    assert 0 < stale < 10  # at rest, 1 mG steps, 2.5 mG noise: a few exact repeats
    assert k.size >= ap_log[1]["index"].size - 1 - 25 - stale
    assert any("changed 1 time(s)" in n for n in streams.notes)
    rest = ~day.armed[k]  # armed: motor compensation, not in the stream
    after = dict(COMPASS_PARAMS, COMPASS_OFS_Y=70.0, COMPASS_ORIENT=0.0)
    Ms = mapping.ardupilot_correct(np.eye(3), after) - mapping.ardupilot_correct(np.zeros(3), after)
    bound = np.abs(np.linalg.inv(Ms.T)).sum(axis=1) * 1.0 + 1e-3
    assert np.all(np.abs(streams.mag.mag[rest] - day.mag[k][rest]) <= bound)
    # acc mG and gyro mrad/s int16, the half unit added back (a whole unit for a logged 0)
    j = _index(day, streams.imu.t)
    half = np.where(streams.imu.acc == 0, 1.0, 0.5)
    assert np.all(np.abs(streams.imu.acc - day.acc[j]) <= half * 1e-3 * GRAVITY_MSS + 1e-5)
    half = np.where(streams.imu.gyr == 0, 1.0, 0.5)
    assert np.all(np.abs(streams.imu.gyr - day.gyr_point[j]) <= half * 1e-3 + 1e-6)
    assert streams.armed is not None and streams.throttle is not None


def test_ardupilot_telemetry_imports_and_calibrates(day, ap_result):
    result = ap_result
    assert abs(result.stretch.start_s - day.hand[0]) <= 1.0
    assert abs(result.stretch.end_s - day.hand[1]) <= 1.0
    meta = result.session.meta
    assert meta["log_format"] == "tlog" and meta["mag_unit"] == "mG"
    assert meta["param.COMPASS_OFS_Y"] == "70"
    assert "COMPASS_OFS_Y" in meta["params_changed"]
    cal = calibrate(result.session, "ml")
    # measured 0.064° (seed 2); 1 mG and 1 mrad/s resolution, 50 Hz
    assert _heading_rms_deg(day, cal.result) < 0.1


def test_a_stream_faster_than_the_compass_repeats_no_reading(tmp_path):
    short = bench_day(seed=3, hand_s=6.0)
    path = tmp_path / "held.tlog"
    sent = write_ardupilot_tlog(path, short, mag_hold=3)["index"]
    streams = tlog.read(str(path))
    k = _index(short, streams.mag.t)
    # only the messages that carried a new compass reading remain (the very first came
    # before the vehicle's first heartbeat: it is the vehicle's all the same)
    assert np.array_equal(k, sent[::3])
    assert streams.imu.t.size == sent.size  # the IMU is not held


def test_ardupilot_telemetry_without_parameters_or_compass(short_logs):
    with pytest.raises(
        LogImportError,
        match=r"ap.tlog \(ArduPilot\) has no magnetometer data for compass 2 \(found compasses "
        r"1\); needs RAW_IMU",
    ):
        tlog.read(short_logs["ap"], compass=2)
    with pytest.raises(LogImportError, match="no PARAM_VALUE messages"):
        import_log(short_logs["noparams"])


def test_px4_telemetry_gives_the_raw_field_in_gauss(day, px4_result):
    streams = px4_result.streams
    assert streams.autopilot == "px4" and streams.mag.unit == "gauss"
    assert streams.imu.source == "HIGHRES_IMU id 0"
    k = _index(day, streams.mag.t)
    # SCALED_IMU carries whole mG (truncated, half added back; a whole one for a logged 0)
    half = np.where(streams.mag.mag == 0, 1.0, 0.5)
    assert np.all(np.abs(streams.mag.mag - day.mag[k] / 1000.0) <= half * 1e-3 + 1e-9)
    j = _index(day, streams.imu.t)
    assert np.allclose(streams.imu.gyr, day.gyr_point[j].astype(np.float32), rtol=0, atol=0)
    # integer parameters arrive bytewise in PARAM_VALUE's float
    p = streams.params.initial
    assert p["CAL_MAG0_ID"] == 396825.0 and p["CAL_MAG0_ROT"] == 0.0 and p["CAL_MAG0_PRIO"] == 50
    assert p["CAL_MAG0_XOFF"] == pytest.approx(PX4_PARAMS["CAL_MAG0_XOFF"])
    assert "CAL_MAG0_XSCALE" in streams.param_names


def test_px4_telemetry_imports_and_calibrates(day, px4_result):
    result = px4_result
    assert abs(result.stretch.start_s - day.hand[0]) <= 1.0
    cal = calibrate(result.session, "ml")
    assert result.session.meta["mag_unit"] == "gauss"
    # measured 0.043° (seed 2)
    assert _heading_rms_deg(day, cal.result, 1e-3) < 0.1


def test_px4_telemetry_without_the_compass(short_logs):
    with pytest.raises(
        LogImportError,
        match=r"\(PX4\) has no SCALED_IMU magnetometer data for compass 3 \(found compasses 1\)",
    ):
        tlog.read(short_logs["px4"], compass=3)
    with pytest.raises(LogImportError, match=r"no HIGHRES_IMU or SCALED_IMU for IMU 2"):
        tlog.read(short_logs["px4"], imu=2)


def test_a_tlog_without_a_vehicle(tmp_path):
    from pymavlink.dialects.v20 import ardupilotmega as mavlink

    gcs = mavlink.MAVLink(None, srcSystem=255, srcComponent=190)
    hb = mavlink.MAVLink_heartbeat_message(6, 8, 0, 0, 0, 3).pack(gcs)
    path = tmp_path / "gcs.tlog"
    stamps = [(1_700_000_000_000_000 + i).to_bytes(8, "big") for i in range(5)]
    path.write_bytes(b"".join(stamp + hb for stamp in stamps))
    with pytest.raises(LogImportError, match="has no HEARTBEAT from a vehicle"):
        import_log(str(path))


class _Msg:
    """A stand-in for a pymavlink message: what tlog's clock and parameter checks read."""

    def __init__(self, **fields):
        self.__dict__.update(fields)


def _timed(pairs):
    """[(reception s, message with time_boot_ms)] from (reception s, vehicle s) pairs."""
    return [(rx, _Msg(time_boot_ms=int(round(boot * 1e3)))) for rx, boot in pairs]


def test_a_clock_step_is_a_reboot_only_with_evidence():
    # one message delayed on the link: its vehicle time goes back 1 s, it is dropped
    delayed = _timed([(0.0, 610.0), (0.25, 610.25), (0.5, 611.5), (0.8, 610.5), (1.0, 612.0)])
    kept, dropped = tlog._in_order("x.tlog", delayed)
    assert dropped == 1 and [m.time_boot_ms for _, m in kept] == [610000, 610250, 611500, 612000]
    # a reboot: the clock restarts near zero, sooner than the reception time that passed
    rebooted = _timed([(0.0, 610.0), (0.25, 610.25), (20.0, 12.0), (20.25, 12.25)])
    with pytest.raises(LogImportError, match="rebooted during the recording"):
        tlog._in_order("x.tlog", rebooted)


def test_parameters_are_complete_only_when_every_index_arrived():
    every = [(0.0, _Msg(param_index=i, param_count=3)) for i in range(3)]
    assert tlog._params_note(every) == ""
    assert "received 2 of the vehicle's 3" in tlog._params_note(every[:2])
    assert "never fetched" in tlog._params_note([])


def test_firmware_without_soft_iron_parameters_is_not_told_to_log_them(tmp_path):
    short = bench_day(seed=4, hand_s=8.0)
    params = {
        k: v for k, v in COMPASS_PARAMS.items() if not k.startswith(("COMPASS_DIA", "COMPASS_ODI"))
    }
    path = tmp_path / "old.tlog"
    write_ardupilot_tlog(path, short, params=params)
    result = import_log(str(path), ImportOptions(start_s=0.0, end_s=1e9))
    assert "COMPASS_DIA_X" in result.session.meta["onboard_soft_iron"]
