# SPDX-License-Identifier: Apache-2.0
"""Write MAVLink telemetry logs (``.tlog``) from a :class:`~tests.loggen.scenario.BenchDay`.

A tlog is what a ground station records: each MAVLink frame (packed by pymavlink's
encoder) after the 8-byte big-endian µs Unix time of its reception. Two personalities:

- ArduPilot: RAW_IMU (IMU and compass 1) as GCS_Common.cpp ``send_raw_imu`` fills it —
  ``accel · 1000 / GRAVITY_MSS`` mG, ``gyro · 1000`` mrad/s and the corrected field
  (:func:`tests.loggen.dataflash.ardupilot_corrected`), each cast to int16 — plus
  PARAM_VALUE (the values as floats) when the ground station connects and on each change;
- PX4: HIGHRES_IMU (float SI units, ``id`` 0) and SCALED_IMU whose magnetometer is the raw
  field in mG; PARAM_VALUE with integer parameters encoded bytewise.

Both send HEARTBEAT (armed bit) at 1 Hz and VFR_HUD (throttle %) at 4 Hz; a ground
station's own HEARTBEAT (system 255) is mixed in, as real tlogs hold it.
"""

from __future__ import annotations

import struct

import numpy as np
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from magcal.autopilot import mapping
from tests.loggen.dataflash import COMPASS_PARAMS, ardupilot_corrected, param_timeline
from tests.loggen.scenario import BenchDay

GRAVITY_MSS = 9.80665
UNIX_T0_S = 1_700_000_000.0
#: PX4 calibration of the tests (raw gauss → corrected); CAL_MAG0_ROT is an INT32 parameter.
PX4_PARAMS = {
    "CAL_MAG0_ID": 396825.0,
    "CAL_MAG0_XOFF": 0.05,
    "CAL_MAG0_YOFF": -0.1,
    "CAL_MAG0_ZOFF": 0.12,
    "CAL_MAG0_XSCALE": 1.02,
    "CAL_MAG0_YSCALE": 0.97,
    "CAL_MAG0_ZSCALE": 1.01,
    "CAL_MAG0_XODIAG": 0.01,
    "CAL_MAG0_YODIAG": -0.02,
    "CAL_MAG0_ZODIAG": 0.005,
    "CAL_MAG0_ROT": 0.0,
    "CAL_MAG0_PRIO": 50.0,
}
PX4_INT_PARAMS = {"CAL_MAG0_ID", "CAL_MAG0_ROT", "CAL_MAG0_PRIO"}
MAV_PARAM_TYPE_INT32 = 6
MAV_PARAM_TYPE_REAL32 = 9


def _int16(v) -> list[int]:
    return [int(x) for x in np.trunc(np.asarray(v, dtype=np.float64))]


class _Log:
    """Frames with reception times, written in time order."""

    def __init__(self, seed: int) -> None:
        self.rng = np.random.default_rng(seed)
        self.frames: list[tuple[float, int, bytes]] = []
        self.vehicle = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
        self.gcs = mavlink.MAVLink(None, srcSystem=255, srcComponent=190)

    def add(self, boot_s: float, msg, sender=None) -> None:
        # Reception: 5–25 ms after the vehicle's time (link latency).
        rx = UNIX_T0_S + boot_s + self.rng.uniform(0.005, 0.025)
        buf = msg.pack(sender or self.vehicle)
        self.frames.append((rx, len(self.frames), buf))

    def write(self, path) -> None:
        with open(path, "wb") as f:
            for rx, _, buf in sorted(self.frames):
                f.write(struct.pack(">Q", int(round(rx * 1e6))) + buf)


def _heartbeats(log: _Log, day: BenchDay, autopilot: int) -> None:
    for k in range(0, day.t.size, int(round(1.0 / (day.t[1] - day.t[0])))):
        base = 1 | (mavlink.MAV_MODE_FLAG_SAFETY_ARMED if day.armed[k] else 0)
        log.add(day.t[k], mavlink.MAVLink_heartbeat_message(2, autopilot, base, 0, 4, 3))
        log.add(
            day.t[k] + 0.3,
            mavlink.MAVLink_heartbeat_message(
                mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0, 3
            ),
            sender=log.gcs,
        )
    for k in range(0, day.t.size, int(round(0.25 / (day.t[1] - day.t[0])))):
        hud = mavlink.MAVLink_vfr_hud_message(0.0, 0.0, 0, int(100 * day.throttle[k]), 0.0, 0.0)
        log.add(day.t[k], hud)


def _params(log: _Log, at_s: float, params: dict[str, float], encode) -> None:
    for i, (name, value) in enumerate(params.items()):
        value, ptype = encode(name, value)
        msg = mavlink.MAVLink_param_value_message(name.encode(), value, ptype, len(params), i)
        log.add(at_s, msg)


def write_ardupilot_tlog(
    path,
    day: BenchDay,
    params: dict[str, float] = COMPASS_PARAMS,
    changes: list[tuple[float, str, float]] = (),
    every: int = 4,
    omit: tuple[str, ...] = (),
    seed: int = 0,
    mag_hold: int = 1,
) -> dict:
    """ArduPilot telemetry (see the module docstring); RAW_IMU every ``every`` samples.

    mag_hold : the compass updates once per this many RAW_IMU messages; in between the
               stream repeats its last reading (as a stream faster than the compass does)

    Returns {"index": day samples sent, "params_at": parameters in force at each}.
    """
    log = _Log(seed)
    _heartbeats(log, day, mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA)
    if "PARAM_VALUE" not in omit:
        _params(log, day.t[0] + 0.5, params, lambda n, v: (v, MAV_PARAM_TYPE_REAL32))
        for time, name, value in changes:
            msg = mavlink.MAVLink_param_value_message(
                name.encode(), value, MAV_PARAM_TYPE_REAL32, len(params), 0
            )
            log.add(time, msg)
    index = np.arange(0, day.t.size, every)
    in_force = param_timeline(params, list(changes), day.t[index])
    for n, (k, p) in enumerate(zip(index, in_force, strict=True)):
        if n % mag_hold == 0:
            field, _ = ardupilot_corrected(day.mag[k], p, day.throttle[k])
        acc = _int16(np.float32(day.acc[k]) * np.float32(1000.0) / np.float32(GRAVITY_MSS))
        gyr = _int16(np.float32(day.gyr_point[k]) * np.float32(1000.0))
        if "RAW_IMU" not in omit:
            msg = mavlink.MAVLink_raw_imu_message(
                int(round(day.t[k] * 1e6)), *acc, *gyr, *_int16(field), 0, 2500
            )
            log.add(day.t[k], msg)
    log.write(path)
    return {"index": index, "params_at": in_force}


def _px4_encode(name: str, value: float) -> tuple[float, int]:
    if name in PX4_INT_PARAMS:
        bits = struct.unpack("<f", struct.pack("<i", int(value)))[0]
        return bits, MAV_PARAM_TYPE_INT32
    return value, MAV_PARAM_TYPE_REAL32


def write_px4_tlog(
    path,
    day: BenchDay,
    params: dict[str, float] = PX4_PARAMS,
    highres_every: int = 2,
    mag_every: int = 4,
    seed: int = 0,
) -> dict:
    """PX4 telemetry (see the module docstring). The raw field is ``day.mag`` / 1000 gauss.

    Returns {"mag_index": day samples with a SCALED_IMU, "imu_index": with a HIGHRES_IMU}.
    """
    log = _Log(seed)
    _heartbeats(log, day, mavlink.MAV_AUTOPILOT_PX4)
    _params(log, day.t[0] + 0.5, params, _px4_encode)
    imu_index = np.arange(0, day.t.size, highres_every)
    raw_gauss = day.mag / 1000.0
    corrected = mapping.px4_correct(raw_gauss, params, 0)
    for k in imu_index:
        a, g, m = day.acc[k], day.gyr_point[k], corrected[k]
        msg = mavlink.MAVLink_highres_imu_message(
            int(round(day.t[k] * 1e6)), *a, *g, *m, 1013.0, 0.0, 0.0, 25.0, 0x1FF, 0
        )
        log.add(day.t[k], msg)
    mag_index = np.arange(0, day.t.size, mag_every)
    for k in mag_index:
        acc = _int16(day.acc[k] * 1000.0 / GRAVITY_MSS)
        gyr = _int16(day.gyr_point[k] * 1000.0)
        msg = mavlink.MAVLink_scaled_imu_message(
            int(round(day.t[k] * 1e3)), *acc, *gyr, *_int16(raw_gauss[k] * 1000.0), 2500
        )
        log.add(day.t[k], msg)
    log.write(path)
    return {"mag_index": mag_index, "imu_index": imu_index}
