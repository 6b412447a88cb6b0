# SPDX-License-Identifier: Apache-2.0
"""``magcal import`` of ArduPilot DataFlash logs written by tests/loggen from the simulator."""

from __future__ import annotations

import numpy as np
import pytest

from magcal.autopilot import mapping, vehicle
from magcal.logs import ImportOptions, LogImportError, dataflash, import_log
from magcal.logs.correction import MIXED_WINDOW_S
from tests.loggen.dataflash import COMPASS_PARAMS, ardupilot_corrected, write_bin
from tests.loggen.scenario import bench_day


@pytest.fixture(scope="module")
def day():
    return bench_day(seed=0)


@pytest.fixture(scope="module")
def short_day():
    """A shorter day for the tests that only need a valid log."""
    return bench_day(seed=1, hand_s=12.0)


@pytest.fixture(scope="module")
def log(day, tmp_path_factory):
    path = tmp_path_factory.mktemp("bin") / "day.bin"
    return str(path), write_bin(path, day)


def _index(day, t: np.ndarray) -> np.ndarray:
    """Indices of the day's samples at times t (which are day times up to round-off)."""
    k = np.searchsorted(day.t, t - 1e-7)
    assert np.allclose(day.t[k], t, rtol=0, atol=1e-9)
    return k


def _bound(params: dict[str, float]) -> np.ndarray:
    """(3,) mG: how far the recovered field may be from the simulated one per axis.

    The log truncates the corrected field and the motor offset to whole mG; the importer adds
    back half a unit, so each is off by at most ½ (1 for a logged 0); through (M·s)⁻¹.
    """
    p = dict(params, COMPASS_ORIENT=0.0)
    Ms = mapping.ardupilot_correct(np.eye(3), p) - mapping.ardupilot_correct(np.zeros(3), p)
    return np.abs(np.linalg.inv(Ms.T)).sum(axis=1) * 1.5 + 1e-3


def test_the_generator_corrects_as_magcal_mapping_does():
    """Two implementations of ArduPilot's correct_field agree (float32 vs float64)."""
    rng = np.random.default_rng(7)
    p = dict(COMPASS_PARAMS, COMPASS_ORIENT=0.0, COMPASS_MOTCT=0.0)
    for y in rng.normal(0, 400, (20, 3)):
        ours, motor = ardupilot_corrected(y, p, throttle=0.7)
        assert np.all(motor == 0)
        assert np.allclose(ours, mapping.ardupilot_correct(y, p)[0], atol=2e-3)
    p["COMPASS_MOTCT"] = 1.0
    ours, motor = ardupilot_corrected(np.zeros(3), p, throttle=0.5)
    assert np.allclose(motor, [10.0, -5.0, 17.5])
    assert np.allclose(ours, mapping.ardupilot_correct(np.zeros(3), p)[0] + motor, atol=2e-3)


def test_the_raw_field_is_recovered(day, log):
    path, written = log
    streams = dataflash.read(path)
    k = _index(day, streams.mag.t)
    assert np.array_equal(k, written["mag_index"])  # every sample, none dropped
    err = np.abs(streams.mag.mag - day.mag[k])
    assert np.all(err <= _bound(COMPASS_PARAMS))
    # disarmed (no motor offset, which is constant while armed), the truncation error left
    # is zero-mean: std of a mean of uniform ±½ mG errors over ~2700 samples ≈ 0.006 mG
    rest = ~day.armed[k]
    assert np.all(np.abs(np.mean(streams.mag.mag[rest] - day.mag[k][rest], axis=0)) < 0.03)
    assert streams.mag.unit == "mG" and streams.autopilot == vehicle.ARDUPILOT


def test_the_imu_is_read_exactly(day, log):
    streams = dataflash.read(log[0])
    assert np.allclose(streams.imu.t, day.t, rtol=0, atol=1e-9)
    assert np.array_equal(streams.imu.gyr, day.gyr_point.astype(np.float32))
    assert np.array_equal(streams.imu.acc, day.acc.astype(np.float32))


def test_the_stretch_found_is_the_hand_rotation(day, log):
    result = import_log(log[0])
    s = result.stretch
    assert abs(s.start_s - day.hand[0]) <= 1.0 and abs(s.end_s - day.hand[1]) <= 1.0
    assert result.end_s < day.flight[0] - 1.0
    assert result.start_s == pytest.approx(s.start_s - 2.0, abs=0.05)
    session = result.session
    assert session.t[0] >= s.from_s and session.t[-1] <= s.to_s
    # 50 Hz magnetometer rows
    assert session.has_mag.sum() == pytest.approx((s.to_s - s.from_s) * 50, abs=2)


def test_start_and_end_override_the_detector(log):
    result = import_log(log[0], ImportOptions(start_s=20.0, end_s=30.0))
    assert result.stretch is None
    assert result.session.t[0] >= 20.0 and result.session.t[-1] <= 30.0
    assert result.session.has_mag.sum() == pytest.approx(500, abs=2)
    assert float(result.session.meta["log_start_s"]) == pytest.approx(20.0, abs=0.02)
    tail = import_log(log[0], ImportOptions(start_s=60.0))
    assert tail.session.t[-1] > 74.0
    with pytest.raises(LogImportError, match="--start 30 s is not before --end 20 s"):
        import_log(log[0], ImportOptions(start_s=30.0, end_s=20.0))
    with pytest.raises(LogImportError, match="no samples between 100 and 200 s"):
        import_log(log[0], ImportOptions(start_s=100.0, end_s=200.0))


def test_metadata_says_where_the_data_came_from(log):
    meta = import_log(log[0]).session.meta
    assert meta["mag_unit"] == "mG"
    assert meta["autopilot"] == "ardupilot" and meta["compass"] == "1" and meta["imu"] == "1"
    assert meta["log_file"] == "day.bin" and meta["log_format"] == "DataFlash"
    assert meta["source"].startswith("day.bin (ArduPilot DataFlash log), compass 1 (MAG[0])")
    # the compass parameters in force, as `magcal collect` records them (float32 texts)
    assert meta["param.COMPASS_OFS_X"] == "-40.5" and meta["param.COMPASS_DIA_Y"] == "0.96"
    assert meta["param.COMPASS_ORIENT"] == "6" and meta["param.COMPASS_DEV_ID"] == "97539"
    assert meta["compass_external"] == "1"
    assert not any(k.startswith("param.COMPASS_MOT") for k in meta)  # not part of the set
    assert "y = R_old·raw" in meta["mag_frame"]
    assert "50.0 Hz" in meta["resampling"] and "200.0 Hz" in meta["resampling"]
    assert "params_changed" not in meta


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        (
            {"compass": 2},
            r"day.bin has no MAG messages for compass 2 \(found compasses 1\); needs IMU, MAG "
            "and PARM messages",
        ),
        ({"imu": 3}, r"no IMU messages for IMU 3 \(found IMUs 1\)"),
    ],
)
def test_a_missing_instance_is_named(log, kwargs, message):
    with pytest.raises(LogImportError, match=message):
        dataflash.read(log[0], **kwargs)


@pytest.mark.parametrize(
    ("omit", "message"),
    [
        (("MAG",), r"has no MAG messages \(enable COMPASS in LOG_BITMASK\); needs IMU, MAG"),
        (("PARM",), "has no PARM messages; needs IMU, MAG and PARM"),
        (("IMU", "PARM"), r"has no IMU messages \(.*\) and no PARM messages; needs"),
    ],
)
def test_missing_messages_are_listed(short_day, tmp_path, omit, message):
    path = tmp_path / "day.bin"
    write_bin(path, short_day, omit=omit)
    with pytest.raises(LogImportError, match=message):
        import_log(str(path))


def test_a_parameter_change_mid_log_is_honoured(day, tmp_path):
    """An on-board calibration accepted at 30 s: each sample undone with its parameters."""
    changes = [(30.0, "COMPASS_OFS_X", -30.25), (30.0, "COMPASS_DIA_Y", 0.99)]
    path = tmp_path / "change.bin"
    written = write_bin(path, day, changes=changes)
    streams = dataflash.read(str(path))
    k = _index(day, streams.mag.t)
    dropped = np.setdiff1d(written["mag_index"], k)
    assert np.all((day.t[dropped] > 30.0) & (day.t[dropped] <= 30.0 + MIXED_WINDOW_S))
    assert dropped.size == int(MIXED_WINDOW_S * 50)
    after = dict(COMPASS_PARAMS, COMPASS_OFS_X=-30.25, COMPASS_DIA_Y=0.99)
    bound = np.maximum(_bound(COMPASS_PARAMS), _bound(after))
    assert np.all(np.abs(streams.mag.mag - day.mag[k]) <= bound)
    assert any("changed 2 time(s)" in n for n in streams.notes)
    meta = import_log(str(path)).session.meta
    assert "COMPASS_OFS_X" in meta["params_changed"]
    assert meta["param.COMPASS_OFS_X"] == "-30.25"


def test_offsets_changed_without_a_record_are_refused_where_they_apply(day, tmp_path):
    """In-flight learning changes the offsets in use without PARM: the logged OfsX shows it."""
    path = tmp_path / "learn.bin"
    write_bin(path, day, unlogged=[(62.0, "COMPASS_OFS_X", -10.0)])
    result = import_log(str(path))  # the hand rotation is before: fine
    assert result.end_s < 62.0
    with pytest.raises(LogImportError, match=r"from 62\.\d\d s on, compass 1 was corrected with "):
        import_log(str(path), ImportOptions(start_s=50.0, end_s=70.0))


def test_the_pre_4_0_layout_is_read(short_day, tmp_path):
    """IMU/IMU2 and MAG/MAG2 without an instance column."""
    path = tmp_path / "old.bin"
    write_bin(path, short_day, legacy=True, params=dict(COMPASS_PARAMS, **_second(COMPASS_PARAMS)))
    one = dataflash.read(str(path))
    two = dataflash.read(str(path), compass=2, imu=2)
    assert two.imu.source == "IMU2" and two.mag.source == "MAG2"  # the messages read
    assert np.array_equal(one.imu.gyr, two.imu.gyr)
    assert np.allclose(one.mag.mag, two.mag.mag)
    assert "COMPASS_OFS2_X" in two.param_names


def test_the_2014_layout_is_read_and_its_offsets_only_correction_undone(short_day, tmp_path):
    """TimeMS, PARM and EV without a time, MAG without Health and S, no FMTU; a firmware
    without COMPASS_DIA/ODI/SCALE (its correction was the offsets alone)."""
    params = {
        k: v
        for k, v in COMPASS_PARAMS.items()
        if not k.startswith(("COMPASS_DIA", "COMPASS_ODI", "COMPASS_SCALE"))
    }
    changes = [(short_day.t[0] + 4.0, "COMPASS_OFS_X", -30.0)]
    path = tmp_path / "2014.bin"
    written = write_bin(path, short_day, params=params, changes=changes, ancient=True)
    streams = dataflash.read(str(path))
    assert streams.imu.source == "IMU" and streams.mag.source == "MAG"
    ms = np.round(short_day.t * 1e6).astype(np.int64) // 1000
    assert np.allclose(streams.imu.t, ms * 1e-3, atol=1e-9)  # whole ms
    # the untimed change is placed where it was written: within one IMU period
    ((when, name, value),) = streams.params.changes
    assert name == "COMPASS_OFS_X" and value == -30.0
    assert abs(when - changes[0][0]) <= np.median(np.diff(short_day.t)) + 1e-3
    # the raw field, with the identity as the soft iron the firmware did not have
    k = np.searchsorted(short_day.t, streams.mag.t - 2e-3)
    assert np.array_equal(k, written["mag_index"][np.isin(written["mag_index"], k)])
    identity = dict(params, COMPASS_DIA_X=1.0, COMPASS_DIA_Y=1.0, COMPASS_DIA_Z=1.0)
    identity |= dict(COMPASS_ODI_X=0.0, COMPASS_ODI_Y=0.0, COMPASS_ODI_Z=0.0, COMPASS_SCALE=1.0)
    assert np.all(np.abs(streams.mag.mag - short_day.mag[k]) <= _bound(identity) + 1e-9)
    assert streams.armed is not None  # from EV
    session = import_log(str(path), ImportOptions(start_s=0.0, end_s=1e9)).session
    assert "COMPASS_DIA_X" in session.meta["onboard_soft_iron"]
    assert "param.COMPASS_DIA_X" not in session.meta  # nothing invented


def _second(params: dict[str, float]) -> dict[str, float]:
    """The same calibration for compass 2 (COMPASS_OFS2_X, …)."""
    out = {}
    for name, value in params.items():
        for stem in ("OFS", "DIA", "ODI"):
            if name.startswith(f"COMPASS_{stem}_"):
                out[name.replace(f"_{stem}_", f"_{stem}2_")] = value
    out["COMPASS_SCALE2"] = params["COMPASS_SCALE"]
    return out


def test_a_second_imu_is_chosen_with_imu(short_day, tmp_path):
    path = tmp_path / "two.bin"
    write_bin(path, short_day, second_imu=True)
    streams = dataflash.read(str(path), imu=2)
    assert np.array_equal(streams.imu.gyr, -short_day.gyr_point.astype(np.float32))
    with pytest.raises(LogImportError, match=r"no IMU messages for IMU 3 \(found IMUs 1, 2\)"):
        dataflash.read(str(path), imu=3)


def test_a_file_that_is_no_log(tmp_path):
    junk = tmp_path / "junk.bin"
    junk.write_bytes(b"not a log at all " * 64)
    with pytest.raises(LogImportError, match="not a log magcal can read .named like a DataFlash"):
        import_log(str(junk))
    empty = tmp_path / "empty.bin"
    empty.write_bytes(b"")
    with pytest.raises(LogImportError, match="empty"):
        import_log(str(empty))
    with pytest.raises(LogImportError, match="no such file"):
        import_log(str(tmp_path / "missing.bin"))
