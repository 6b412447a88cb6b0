# SPDX-License-Identifier: Apache-2.0
"""Write ArduPilot DataFlash ``.bin`` logs from a :class:`~tests.loggen.scenario.BenchDay`.

The format (as pymavlink's DFReader parses it): every message is ``0xA3 0x95 <type id>``
and a packed little-endian payload; ``FMT`` (type 128, ``BBnNZ``: Type, Length, Name[4],
Format[16], Columns[64]) defines each type before it is used. The IMU, MAG, PARM and ARM
definitions are ArduPilot's own (AP_InertialSensor/LogStructure.h,
AP_Compass/LogStructure.h, AP_Logger/LogStructure.h). The logged compass field is made the
way ArduPilot makes it (AP_Compass_Backend::correct_field, implemented here independently of
magcal.autopilot.mapping, against which a test checks it): ``mag + OFS``, times COMPASS_SCALE
when within [0.85, 1.4], times the DIA/ODI matrix, plus the motor offset ``MOT · throttle``;
computed in float32 and cast to ``int16_t`` (truncation), as AP_Compass_Logging.cpp does.
"""

from __future__ import annotations

import struct

import numpy as np

from tests.loggen.scenario import BenchDay

HEAD = b"\xa3\x95"
FMT_ID = 128
_IMU_COLS = "GyrX,GyrY,GyrZ,AccX,AccY,AccZ,EG,EA,T,GH,AH,GHz,AHz"
_MAG_COLS = "MagX,MagY,MagZ,OfsX,OfsY,OfsZ,MOX,MOY,MOZ,Health,S"
#: name → (id, format, columns) of the messages written (ArduPilot 4.x).
FORMATS = {
    "IMU": (131, "QBffffffIIfBBHH", f"TimeUS,I,{_IMU_COLS}"),
    "MAG": (132, "QBhhhhhhhhhBI", f"TimeUS,I,{_MAG_COLS}"),
    "PARM": (133, "QNff", "TimeUS,Name,Value,Default"),
    "ARM": (134, "QBIBB", "TimeUS,ArmState,ArmChecks,Forced,Method"),
}
#: Before ArduPilot 4.0: one message per instance (IMU, IMU2, MAG, MAG2), no I column.
LEGACY_FORMATS = {
    "IMU": (131, "QffffffIIfBBHH", f"TimeUS,{_IMU_COLS}"),
    "MAG": (132, "QhhhhhhhhhBI", f"TimeUS,{_MAG_COLS}"),
    "PARM": FORMATS["PARM"],
    "ARM": FORMATS["ARM"],
    "IMU2": (135, "QffffffIIfBBHH", f"TimeUS,{_IMU_COLS}"),
    "MAG2": (136, "QhhhhhhhhhBI", f"TimeUS,{_MAG_COLS}"),
}
#: ArduPilot 3.2 (2014): TimeMS (ms, uint32), PARM and EV without a time column, MAG
#: without Health and S, no FMTU.
ANCIENT_FORMATS = {
    "IMU": (131, "IffffffIIf", "TimeMS,GyrX,GyrY,GyrZ,AccX,AccY,AccZ,ErrG,ErrA,Temp"),
    "MAG": (132, "Ihhhhhhhhh", "TimeMS,MagX,MagY,MagZ,OfsX,OfsY,OfsZ,MOfsX,MOfsY,MOfsZ"),
    "PARM": (133, "Nf", "Name,Value"),
    "EV": (134, "B", "Id"),
}
#: DataFlash format characters → struct codes (the subset used here).
STRUCT = {"Q": "Q", "B": "B", "f": "f", "I": "I", "H": "H", "h": "h", "N": "16s", "n": "4s"}
#: Time from a compass sample's publication (S) to its log record (TimeUS), µs.
MAG_LOG_LATENCY_US = 700

#: Compass 1 parameters of the tests: offsets, soft iron, a scale within [0.85, 1.4], motor
#: compensation by throttle.
COMPASS_PARAMS = {
    "COMPASS_OFS_X": -40.5,
    "COMPASS_OFS_Y": 62.25,
    "COMPASS_OFS_Z": -15.0,
    "COMPASS_DIA_X": 1.03,
    "COMPASS_DIA_Y": 0.96,
    "COMPASS_DIA_Z": 1.01,
    "COMPASS_ODI_X": 0.02,
    "COMPASS_ODI_Y": -0.015,
    "COMPASS_ODI_Z": 0.01,
    "COMPASS_SCALE": 1.05,
    "COMPASS_ORIENT": 6.0,
    "COMPASS_EXTERNAL": 1.0,
    "COMPASS_MOTCT": 1.0,
    "COMPASS_MOT_X": 20.0,
    "COMPASS_MOT_Y": -10.0,
    "COMPASS_MOT_Z": 35.0,
    "COMPASS_DEV_ID": 97539.0,
    "AHRS_ORIENTATION": 0.0,
}


def _struct(fmt: str) -> struct.Struct:
    return struct.Struct("<" + "".join(STRUCT[c] for c in fmt))


def param_timeline(
    params: dict[str, float], changes: list[tuple[float, str, float]], t: np.ndarray
) -> list[dict[str, float]]:
    """The parameters in force at each time of ``t`` (N,): ``params`` then ``changes``."""
    out = []
    current = dict(params)
    pending = sorted(changes)
    k = 0
    for time in t:
        while k < len(pending) and pending[k][0] <= time:
            current[pending[k][1]] = pending[k][2]
            k += 1
        out.append(current)
        current = dict(current)
    return out


def ardupilot_corrected(
    y: np.ndarray, params: dict[str, float], throttle: float, compass: str = ""
) -> tuple[np.ndarray, np.ndarray]:
    """AP_Compass_Backend::correct_field on the rotated field ``y`` (3,) mG, in float32.

    Returns (corrected field, motor offset), both float32 (3,).
    """
    f32 = np.float32
    ofs = np.array([params[f"COMPASS_OFS{compass}_{a}"] for a in "XYZ"], dtype=f32)
    # a firmware without COMPASS_DIA/ODI (before their introduction) applies no matrix
    dia = np.array([params.get(f"COMPASS_DIA{compass}_{a}", 0.0) for a in "XYZ"], dtype=f32)
    odi = np.array([params.get(f"COMPASS_ODI{compass}_{a}", 0.0) for a in "XYZ"], dtype=f32)
    if np.all(dia == 0):
        dia = np.ones(3, dtype=f32)
    mag = np.asarray(y, dtype=f32) + ofs
    scale = f32(params.get(f"COMPASS_SCALE{compass}", 0.0))
    if f32(0.85) <= scale <= f32(1.4):
        mag = mag * scale
    M = np.array(
        [[dia[0], odi[0], odi[1]], [odi[0], dia[1], odi[2]], [odi[1], odi[2], dia[2]]], dtype=f32
    )
    mag = M @ mag
    motor = np.zeros(3, dtype=f32)
    if params.get("COMPASS_MOTCT", 0.0) == 1.0:
        mot = np.array([params[f"COMPASS_MOT{compass}_{a}"] for a in "XYZ"], dtype=f32)
        motor = mot * f32(throttle)
    return (mag + motor).astype(f32), motor


def _int16(v: np.ndarray) -> list[int]:
    """C's ``(int16_t)`` cast of a float: truncation towards zero."""
    return [int(x) for x in np.trunc(np.asarray(v, dtype=np.float64))]


def write_bin(
    path,
    day: BenchDay,
    params: dict[str, float] = COMPASS_PARAMS,
    changes: list[tuple[float, str, float]] = (),
    mag_every: int = 4,
    omit: tuple[str, ...] = (),
    legacy: bool = False,
    second_imu: bool = False,
    unlogged: list[tuple[float, str, float]] = (),
    ancient: bool = False,
) -> dict:
    """Write ``day`` as a DataFlash log; return what was logged, for the tests.

    params    : every parameter logged at the start (PARM at t[0] − 0.5 s)
    changes   : (time s, name, value): mid-log parameter changes (PARM when they happen)
    mag_every : one MAG sample per this many IMU samples
    omit      : message names not to write ("IMU", "MAG", "PARM", "ARM")
    legacy    : the pre-4.0 layout (IMU/IMU2, MAG/MAG2 without an instance column)
    second_imu: also log a second IMU (instance 1) with the gyro signs flipped
    unlogged  : parameter changes applied without a PARM record (as in-flight offset learning
                does): the MAG offsets logged show them
    ancient   : the ArduPilot 3.2 layout (ANCIENT_FORMATS): times in ms, untimed PARM and EV
                (placed in the file where they happened), the armed state as EV

    Returns {"mag_index": indices of day samples with a MAG record, "logged": (K, 3) int16
    field logged, "motor": (K, 3) motor offsets applied (float32), "params_at": the
    parameters in force at each MAG sample}.
    """
    formats = ANCIENT_FORMATS if ancient else LEGACY_FORMATS if legacy else FORMATS
    records: list[tuple[int, int, bytes]] = []  # (time µs, order, bytes)
    seq = iter(range(1 << 40))

    def add(time_us: int, name: str, *values) -> None:
        type_id, fmt, _ = formats[name]
        if not ancient:
            payload = _struct(fmt).pack(time_us, *values)
        elif fmt.startswith("I"):  # TimeMS
            payload = _struct(fmt).pack(time_us // 1000, *values)
        else:  # untimed, but written where it happened
            payload = _struct(fmt).pack(*values)
        records.append((time_us, next(seq), HEAD + bytes([type_id]) + payload))

    t_us = np.round(day.t * 1e6).astype(np.int64)
    start_us = int(t_us[0]) - 500_000
    header = b""
    fmt_struct = struct.Struct("<BB4s16s64s")
    for name, (type_id, fmt, cols) in formats.items():
        header += (
            HEAD
            + bytes([FMT_ID])
            + fmt_struct.pack(
                type_id, 3 + _struct(fmt).size, name.encode(), fmt.encode(), cols.encode()
            )
        )

    if "PARM" not in omit:
        for name, value in params.items():
            add(start_us, "PARM", name.encode(), value, *(() if ancient else (value,)))
        for time, name, value in changes:
            add(
                int(round(time * 1e6)),
                "PARM",
                name.encode(),
                value,
                *(() if ancient else (float("nan"),)),
            )
    if ancient and "ARM" not in omit:
        edges = np.flatnonzero(np.diff(day.armed.astype(np.int8))) + 1
        for i in edges:
            add(int(t_us[i]), "EV", 10 if day.armed[i] else 11)
    elif "ARM" not in omit:
        edges = np.flatnonzero(np.diff(day.armed.astype(np.int8))) + 1
        for i in edges:
            add(int(t_us[i]), "ARM", int(day.armed[i]), 0, 0, 0)
    if "IMU" not in omit:
        for k in range(day.t.size):
            g, a = day.gyr_point[k], day.acc[k]
            imu = (g[0], g[1], g[2], a[0], a[1], a[2], 0, 0, 25.0, 1, 1, 1000, 1000)
            if ancient:
                add(int(t_us[k]), "IMU", *imu[:9])
            elif legacy:
                add(int(t_us[k]), "IMU", *imu)
                add(int(t_us[k]), "IMU2", *imu)
            else:
                add(int(t_us[k]), "IMU", 0, *imu)
                if second_imu:
                    flipped = (-g[0], -g[1], -g[2]) + imu[3:]
                    add(int(t_us[k]), "IMU", 1, *flipped)

    mag_index = np.arange(0, day.t.size, mag_every)
    in_force = param_timeline(params, list(changes) + list(unlogged), day.t[mag_index])
    logged, motors = [], []
    for k, p in zip(mag_index, in_force, strict=True):
        field, motor = ardupilot_corrected(day.mag[k], p, day.throttle[k])
        f, m = _int16(field), _int16(motor)
        ofs = _int16([p[f"COMPASS_OFS_{a}"] for a in "XYZ"])
        logged.append(f)
        motors.append(motor)
        time_log = int(t_us[k]) + MAG_LOG_LATENCY_US
        sample_us = int(t_us[k]) & 0xFFFFFFFF
        if "MAG" in omit:
            continue
        if ancient:
            add(time_log, "MAG", *f, *ofs, *m)
        elif legacy:
            add(time_log, "MAG", *f, *ofs, *m, 1, sample_us)
            add(time_log, "MAG2", *f, *ofs, *m, 1, sample_us)
        else:
            add(time_log, "MAG", 0, *f, *ofs, *m, 1, sample_us)
    records.sort(key=lambda r: (r[0], r[1]))
    with open(path, "wb") as f:
        f.write(header)
        f.writelines(r[2] for r in records)
    return {
        "mag_index": mag_index,
        "logged": np.array(logged, dtype=float),
        "motor": np.array(motors, dtype=float),
        "params_at": in_force,
    }
