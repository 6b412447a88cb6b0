# SPDX-License-Identifier: Apache-2.0
"""What magcal knows about an ArduPilot or PX4 vehicle (magcal.autopilot.vehicle): identity,
compass numbering, stream units, the session's frame, time stamps, reading parameters."""

from __future__ import annotations

import numpy as np
import pytest

from magcal.autopilot import mapping, rotations, vehicle
from magcal.autopilot import params as P
from magcal.link.mavlink import MavlinkTimeoutError


def test_only_ardupilot_and_px4_are_accepted():
    assert vehicle.autopilot_of(3, "x") == vehicle.ARDUPILOT
    assert vehicle.autopilot_of(12, "x") == vehicle.PX4
    with pytest.raises(vehicle.AutopilotError, match=r"MAV_AUTOPILOT 0 \(MAV_AUTOPILOT_GENERIC\)"):
        vehicle.autopilot_of(0, "--mavlink udpin:x")


def test_firmware_version_text():
    assert vehicle.firmware_text((4 << 24) | (5 << 16) | (7 << 8) | 255) == "4.5.7 official"
    assert vehicle.firmware_text((1 << 24) | (15 << 16) | (0 << 8) | 64) == "1.15.0 alpha"


def test_compass_numbers_map_to_streams_and_px4_slots():
    assert vehicle.collect_stream(vehicle.ARDUPILOT, 1) == "RAW_IMU"
    assert vehicle.collect_stream(vehicle.ARDUPILOT, 3) == "SCALED_IMU3"
    assert vehicle.collect_stream(vehicle.PX4, 1) == "SCALED_IMU"
    assert vehicle.collect_stream(vehicle.PX4, 2) == "SCALED_IMU2"
    assert vehicle.px4_index(2) == 1 and vehicle.px4_required(1)[0] == "CAL_MAG1_XOFF"
    with pytest.raises(vehicle.AutopilotError, match="--compass 4: give 1, 2 or 3"):
        vehicle.collect_stream(vehicle.PX4, 4)


def test_stream_units():
    g = vehicle.acc_mg_to_si(np.array([0, 0, -1000]))
    assert g[2] == pytest.approx(-9.80665)
    assert vehicle.gyro_mrad_to_si(np.array([1000, 0, 0]))[0] == 1.0
    assert vehicle.mag_wire_to_unit(np.array([485.0, 0, 0]), vehicle.PX4)[0] == pytest.approx(0.485)
    assert vehicle.mag_wire_to_unit(np.array([485.0, 0, 0]), vehicle.ARDUPILOT)[0] == 485.0


# ------------------------------------------------------------------------------ time stamps
US = vehicle.TIME_BASES["RAW_IMU"]
MS = vehicle.TIME_BASES["SCALED_IMU"]


def test_a_32_bit_microsecond_wrap_continues_the_time():
    ticks = np.array([2**32 - 20_000, 2**32 - 10_000, 0, 10_000])
    tl = vehicle.unwrap_times(ticks, US, np.arange(4) * 0.01)
    assert tl.wraps == 1 and tl.resets == 0
    assert tl.t == pytest.approx([0.0, 0.01, 0.02, 0.03])


def test_a_clock_restart_continues_by_the_host_interval_and_repeats_are_dropped():
    ticks = np.array([5_000_000_000, 5_000_020_000, 5_000_020_000, 1_000, 21_000])
    host = np.array([0.0, 0.02, 0.021, 0.5, 0.52])
    tl = vehicle.unwrap_times(ticks, US, host)
    assert tl.resets == 1 and tl.wraps == 0
    assert list(tl.keep) == [True, True, False, True, True]
    assert tl.t[tl.keep] == pytest.approx([0.0, 0.02, 0.5, 0.52])
    assert np.all(np.diff(tl.t[tl.keep]) > 0)


def test_missing_samples_are_counted_from_the_steps():
    ticks = np.array([0, 20, 40, 100, 120, 140])  # ms: 40 → 100 misses two 20 ms samples
    assert vehicle.unwrap_times(ticks, MS, np.zeros(6)).missing == 2


# ------------------------------------------------------------------------------ frames
def _ap_params(rng, orient=6, external=1):
    p = {
        f"COMPASS_OFS_{a}": float(v) for a, v in zip("XYZ", rng.uniform(-200, 200, 3), strict=True)
    }
    p |= {
        f"COMPASS_DIA_{a}": float(v) for a, v in zip("XYZ", rng.uniform(0.9, 1.1, 3), strict=True)
    }
    p |= {
        f"COMPASS_ODI_{a}": float(v)
        for a, v in zip("XYZ", rng.uniform(-0.05, 0.05, 3), strict=True)
    }
    return p | {"COMPASS_SCALE": 1.1, "COMPASS_ORIENT": float(orient), "COMPASS_EXTERNAL": external}


def _cp(autopilot, values, external=True):
    types = {n: P.REAL32 for n in values}
    naming = mapping.AP_NAMING_LEGACY if autopilot == vehicle.ARDUPILOT else ""
    return vehicle.CompassParams(autopilot, 1, values, types, naming, external)


def test_ardupilot_session_holds_the_field_after_the_rotation_in_force():
    rng = np.random.default_rng(1)
    values = _ap_params(rng)
    raw = rng.normal(size=(20, 3)) * 300
    corrected = mapping.ardupilot_correct(raw, values)
    y = vehicle.session_mag(corrected, _cp(vehicle.ARDUPILOT, values))
    assert y == pytest.approx(raw @ rotations.ardupilot_matrix(6).T, abs=1e-9)
    # and the vehicle's correction of that y with the same parameters is what it streamed
    again = vehicle.onboard_correction(y, _cp(vehicle.ARDUPILOT, values), recorded=values)
    assert again == pytest.approx(corrected, abs=1e-9)


def test_ardupilot_internal_compass_is_not_turned_by_its_parameters():
    rng = np.random.default_rng(2)
    values = _ap_params(rng, orient=4, external=0)
    cp = _cp(vehicle.ARDUPILOT, values, external=False)
    y = rng.normal(size=(5, 3)) * 300
    streamed = mapping.ardupilot_correct_field(y, values)
    assert vehicle.session_mag(streamed, cp) == pytest.approx(y, abs=1e-9)
    assert vehicle.onboard_correction(y, cp) == pytest.approx(streamed, abs=1e-9)


def test_px4_session_is_raw_gauss_and_the_onboard_correction_includes_the_level_trim():
    values = {f"CAL_MAG0_{a}OFF": 0.1 for a in "XYZ"}
    values |= {f"CAL_MAG0_{a}SCALE": 1.0 for a in "XYZ"} | {
        f"CAL_MAG0_{a}ODIAG": 0.0 for a in "XYZ"
    }
    values |= {"CAL_MAG0_ROT": 0.0, "SENS_BOARD_X_OFF": 0.0, "SENS_BOARD_Y_OFF": 0.0}
    values |= {"SENS_BOARD_Z_OFF": 90.0}
    cp = _cp(vehicle.PX4, values)
    y = vehicle.session_mag(np.array([[600.0, 100.0, 100.0]]), cp)
    assert y == pytest.approx(np.array([[0.6, 0.1, 0.1]]))
    assert vehicle.onboard_correction(y, cp) == pytest.approx(
        np.array([[0.0, 0.5, 0.0]]), abs=1e-12
    )


# ------------------------------------------------------------------------------ reading
def _reader(values: dict[str, float], types: dict[str, int] | None = None):
    asked: list[str] = []

    def read(name, tries):
        asked.append(name)
        if name not in values:
            raise MavlinkTimeoutError(f"no answer for parameter {name}")
        return P.ParamEntry(name, values[name], (types or {}).get(name, P.REAL32))

    return read, asked


def test_ardupilot_naming_is_detected_and_custom_angles_read_when_enabled():
    rng = np.random.default_rng(3)
    values = _ap_params(rng, orient=101)
    values |= {"CUST_ROT_ENABLE": 1.0, "CUST_ROT1_ROLL": 1.0, "CUST_ROT1_PITCH": 2.0}
    values |= {"CUST_ROT1_YAW": 3.0, "COMPASS_DEV_ID": 97539.0}
    read, asked = _reader(values)
    cp = vehicle.read_compass_params(read, vehicle.ARDUPILOT, 1)
    assert cp.naming == mapping.AP_NAMING_LEGACY and cp.external
    assert cp.values["CUST_ROT1_YAW"] == 3.0
    per_instance = {k.replace("COMPASS_", "COMPASS1_"): v for k, v in values.items()}
    read, _ = _reader(per_instance)
    with pytest.raises(vehicle.AutopilotError, match="COMPASS1_EXTERN"):
        vehicle.read_compass_params(read, vehicle.ARDUPILOT, 1)  # detected, then one missing


def test_missing_compass_parameters_are_listed():
    read, _ = _reader({"COMPASS_OFS_X": 0.0})
    with pytest.raises(
        vehicle.AutopilotError, match=r"COMPASS_OFS_Y, COMPASS_OFS_Z, .*nothing was"
    ):
        vehicle.read_compass_params(read, vehicle.ARDUPILOT, 1)


def test_session_metadata_round_trips_the_parameters():
    cp = _cp(vehicle.ARDUPILOT, {"COMPASS_OFS_X": float(np.float32(-339.0064))})
    assert vehicle.params_from_meta(cp.session_meta()) == pytest.approx(cp.values, rel=1e-7)
    with pytest.raises(vehicle.AutopilotError, match="param.X: 'abc' is not a number"):
        vehicle.params_from_meta({"param.X": "abc"})


@pytest.mark.parametrize("autopilot", [vehicle.ARDUPILOT, vehicle.PX4])
def test_a_compass_with_device_id_zero_is_refused_naming_the_present_ones(autopilot):
    rng = np.random.default_rng(5)
    if autopilot == vehicle.ARDUPILOT:
        ap1 = _ap_params(rng)
        values = dict(ap1)
        for k in (2, 3):
            values |= {
                n.replace("COMPASS_OFS_", f"COMPASS_OFS{k}_")
                .replace("COMPASS_DIA_", f"COMPASS_DIA{k}_")
                .replace("COMPASS_ODI_", f"COMPASS_ODI{k}_")
                .replace("COMPASS_SCALE", f"COMPASS_SCALE{k}")
                .replace("COMPASS_ORIENT", f"COMPASS_ORIENT{k}"): 0.0
                for n in ap1
                if n != "COMPASS_EXTERNAL"
            }
            values[f"COMPASS_EXTERN{k}"] = 0.0
        values |= {"COMPASS_DEV_ID": 97539.0, "COMPASS_DEV_ID2": 0.0, "COMPASS_DEV_ID3": 131874.0}
    else:
        values = {"SENS_BOARD_X_OFF": 0.0, "SENS_BOARD_Y_OFF": 0.0, "SENS_BOARD_Z_OFF": 0.0}
        for i, dev in enumerate((396825.0, 0.0, 2261002.0)):
            values |= {n: 0.0 for n in vehicle.px4_required(i)[:10]}
            values[f"CAL_MAG{i}_ID"] = dev
    read, _ = _reader(values)
    name = "COMPASS_DEV_ID2" if autopilot == vehicle.ARDUPILOT else "CAL_MAG1_ID"
    with pytest.raises(
        vehicle.AutopilotError,
        match=rf"compass 2 is absent \({name} = 0\); this vehicle has compasses 1 and 3",
    ):
        vehicle.read_compass_params(read, autopilot, 2)
    assert vehicle.read_compass_params(read, autopilot, 3).compass == 3
