# SPDX-License-Identifier: Apache-2.0
"""Write PX4 ULog files (``.ulg``) from a :class:`~tests.loggen.scenario.BenchDay`.

The format (PX4's "ULog File Format" and pyulog's parser): a 16-byte header (``ULog``,
0x01 0x12 0x35, version 1, start time µs), then messages of ``uint16 size, uint8 type,
payload``: the definitions (``F`` formats ``name:type field;…``, ``I`` information,
``P`` initial parameters), then the data (``A`` subscribe a topic instance to a message id,
``D`` data ``uint16 id`` + the packed fields, ``P`` a parameter change). Topics follow PX4's
msg definitions: sensor_combined, sensor_mag (raw, gauss), vehicle_magnetometer (calibrated,
:func:`px4_corrected`), actuator_armed.
"""

from __future__ import annotations

import struct

import numpy as np

from magcal.autopilot import mapping, rotations
from tests.loggen.scenario import BenchDay
from tests.loggen.tlog import PX4_INT_PARAMS, PX4_PARAMS

MAGIC = b"ULog\x01\x12\x35"
#: Time from a magnetometer sample to its publication, µs.
MAG_PUBLISH_LATENCY_US = 300

TOPICS = {
    "sensor_combined": [
        ("uint64_t", "timestamp"),
        ("float[3]", "gyro_rad"),
        ("uint32_t", "gyro_integral_dt"),
        ("int32_t", "accelerometer_timestamp_relative"),
        ("float[3]", "accelerometer_m_s2"),
        ("uint32_t", "accelerometer_integral_dt"),
        ("uint8_t", "accelerometer_clipping"),
        ("uint8_t", "gyro_clipping"),
        ("uint8_t", "accel_calibration_count"),
        ("uint8_t", "gyro_calibration_count"),
    ],
    "sensor_mag": [
        ("uint64_t", "timestamp"),
        ("uint64_t", "timestamp_sample"),
        ("uint32_t", "device_id"),
        ("float", "x"),
        ("float", "y"),
        ("float", "z"),
        ("float", "temperature"),
        ("uint32_t", "error_count"),
    ],
    "vehicle_magnetometer": [
        ("uint64_t", "timestamp"),
        ("uint64_t", "timestamp_sample"),
        ("uint32_t", "device_id"),
        ("float[3]", "magnetometer_ga"),
        ("uint8_t", "calibration_count"),
    ],
    "actuator_armed": [
        ("uint64_t", "timestamp"),
        ("bool", "armed"),
        ("bool", "prearmed"),
        ("bool", "ready_to_arm"),
        ("bool", "lockdown"),
        ("bool", "manual_lockdown"),
        ("bool", "force_failsafe"),
        ("bool", "in_esc_calibration_mode"),
    ],
}
#: Integer parameters (written as int32_t), in addition to the CAL_MAG0 ones.
INT_PARAMS = PX4_INT_PARAMS | {"SENS_BOARD_ROT"}
_CODES = {
    "uint64_t": "Q",
    "uint32_t": "I",
    "int32_t": "i",
    "float": "f",
    "uint8_t": "B",
    "bool": "?",
}


def _struct(fields: list[tuple[str, str]]) -> struct.Struct:
    code = "<"
    for ftype, _ in fields:
        base, _, n = ftype.partition("[")
        code += (n.rstrip("]") if n else "") + _CODES[base]
    return struct.Struct(code)


def _message(kind: str, payload: bytes) -> bytes:
    return struct.pack("<HB", len(payload), ord(kind)) + payload


def _key_value(type_name: str, key: str, value: bytes) -> bytes:
    type_key = f"{type_name} {key}".encode()
    return bytes([len(type_key)]) + type_key + value


def _param(name: str, value: float) -> bytes:
    if name in INT_PARAMS:
        return _key_value("int32_t", name, struct.pack("<i", int(value)))
    return _key_value("float", name, struct.pack("<f", value))


def px4_corrected(raw: np.ndarray, params: dict[str, float]) -> np.ndarray:
    """PX4's Magnetometer::Correct for CAL_MAG0 (no power compensation) on raw (3,) gauss:
    ``L · Rot · S · (raw − off)``, Rot = CAL_MAG0_ROT or, when −1 (internal), SENS_BOARD_ROT;
    L from SENS_BOARD_X/Y/Z_OFF (roll, pitch, yaw degrees)."""
    p = dict(params)
    if p["CAL_MAG0_ROT"] < 0:
        p["CAL_MAG0_ROT"] = p["SENS_BOARD_ROT"]
    L = rotations.euler_deg_to_matrix(*(p.get(f"SENS_BOARD_{a}_OFF", 0.0) for a in "XYZ"))
    return L @ mapping.px4_correct(raw, p, 0)[0]


def write_ulog(
    path,
    day: BenchDay,
    params: dict[str, float] = PX4_PARAMS,
    changes: list[tuple[float, str, float]] = (),
    mag_every: int = 4,
    raw: bool = True,
    calibrated: bool = True,
    omit: tuple[str, ...] = (),
    unlogged: tuple[str, ...] = (),
) -> dict:
    """Write ``day`` as a ULog; raw field = ``day.mag`` / 1000 gauss.

    raw, calibrated : write sensor_mag, vehicle_magnetometer
    changes         : (time s, name, value) parameter changes mid-log
    omit            : topics not to write (e.g. "sensor_combined")
    unlogged        : parameters used by the correction but not written to the log

    Returns {"mag_index": day samples with a magnetometer record}.
    """
    dt_us = int(round((day.t[1] - day.t[0]) * 1e6))
    t_us = np.round(day.t * 1e6).astype(np.int64)
    out = [MAGIC + bytes([1]) + struct.pack("<Q", int(t_us[0]) - 100_000)]
    topics = [
        name
        for name in TOPICS
        if name not in omit
        and (name != "sensor_mag" or raw)
        and (name != "vehicle_magnetometer" or calibrated)
    ]
    for name in topics:
        fmt = ";".join(f"{ftype} {fname}" for ftype, fname in TOPICS[name]) + ";"
        out.append(_message("F", f"{name}:{fmt}".encode()))
    out.append(_message("I", _key_value("char[3]", "sys_name", b"PX4")))
    for pname, value in params.items():
        if pname not in unlogged:
            out.append(_message("P", _param(pname, value)))
    ids = {name: i for i, name in enumerate(topics)}
    for name, msg_id in ids.items():
        out.append(_message("A", struct.pack("<BH", 0, msg_id) + name.encode()))

    records: list[tuple[int, int, bytes]] = []

    def data(name: str, stamp: int, *values) -> None:
        payload = struct.pack("<H", ids[name]) + _struct(TOPICS[name]).pack(stamp, *values)
        records.append((stamp, len(records), _message("D", payload)))

    if "sensor_combined" in ids:
        # PX4 stamps the averages over [t − dt, t] at t: the simulator's gyr[k] is the mean
        # over [t_k, t_k+1], stamped t_k+1, with the accelerometer averaged over the same
        acc_mean = np.concatenate([0.5 * (day.acc[:-1] + day.acc[1:]), day.acc[-1:]])
        for k in range(day.t.size):
            stamp = int(t_us[k]) + dt_us
            data("sensor_combined", stamp, *day.gyr[k], dt_us, 0, *acc_mean[k], dt_us, 0, 0, 0, 0)
    mag_index = np.arange(0, day.t.size, mag_every)
    raw_gauss = day.mag / 1000.0
    device = int(params["CAL_MAG0_ID"])
    for k in mag_index:
        stamp = int(t_us[k]) + MAG_PUBLISH_LATENCY_US
        if "sensor_mag" in ids:
            data("sensor_mag", stamp, int(t_us[k]), device, *raw_gauss[k], 25.0, 0)
    if "vehicle_magnetometer" in ids:
        in_force = dict(params)
        pending = sorted(changes)
        for k in mag_index:
            while pending and pending[0][0] <= day.t[k]:
                in_force[pending[0][1]] = pending[0][2]
                pending.pop(0)
            corrected = px4_corrected(raw_gauss[k], in_force)
            stamp = int(t_us[k]) + MAG_PUBLISH_LATENCY_US
            data("vehicle_magnetometer", stamp, int(t_us[k]), device, *corrected, 0)
    if "actuator_armed" in ids:
        every_second = range(0, day.t.size, int(round(1e6 / dt_us)))
        edges = np.flatnonzero(np.diff(day.armed.astype(np.int8))) + 1
        for k in sorted(set(every_second) | set(edges.tolist())):
            data("actuator_armed", int(t_us[k]), bool(day.armed[k]), 0, 1, 0, 0, 0, 0)
    for time, pname, value in changes:
        stamp = int(round(time * 1e6))
        records.append((stamp, len(records), _message("P", _param(pname, value))))
    records.sort(key=lambda r: (r[0], r[1]))
    with open(path, "wb") as f:
        f.writelines(out)
        f.writelines(r[2] for r in records)
    return {"mag_index": mag_index}
