# SPDX-License-Identifier: Apache-2.0
"""MAVLink telemetry logs (``.tlog``): what a ground station recorded from either autopilot.

A tlog is a sequence of MAVLink frames, each after the 8-byte big-endian µs (Unix) time the
ground station received it; pymavlink reads it (``mavutil.mavlink_connection`` on the
file). The vehicle is the source whose HEARTBEAT is not a ground station's (``autopilot`` not
MAV_AUTOPILOT_INVALID, ``type`` not MAV_TYPE_GCS), the one with the most IMU messages if
several; all its messages are read, wherever they are in the file, and its HEARTBEAT's
``autopilot`` field says which personality applies. Sample times are the vehicle's own
(``time_usec`` / ``time_boot_ms``, since boot), not the reception times, which carry the
link's latency; events that have no vehicle time (PARAM_VALUE, HEARTBEAT, VFR_HUD) are placed
on the vehicle's clock by the median offset between the two clocks.

- **ArduPilot** (GCS_Common.cpp ``send_raw_imu`` / ``send_scaled_imu``): RAW_IMU is IMU and
  compass 1, SCALED_IMU2 IMU and compass 2, SCALED_IMU3 the third; acceleration in mG
  (``accel · 1000 / GRAVITY_MSS``), rate in mrad/s, the **corrected** compass field in mG,
  all cast to int16 (truncated: the half unit is added back,
  :func:`~magcal.logs.streams.untruncate`). The correction is undone with the PARAM_VALUEs
  received (the ground station fetches them all when it connects, and each change comes back
  as PARAM_VALUE). Motor compensation is not in the stream: it is zero while disarmed, and
  armed data are not used.
- **PX4**: HIGHRES_IMU (``id`` = instance) carries the calibrated IMU in m/s² and rad/s as
  floats and is used when present, else SCALED_IMU*; the magnetometer comes from SCALED_IMU
  (compass 1), SCALED_IMU2, SCALED_IMU3, which PX4 fills with the **raw** ``sensor_mag``
  (mG, board frame); it is converted to gauss. PX4 sends integer parameters bytewise in
  PARAM_VALUE's float (MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_BYTEWISE); they are decoded so.

The armed state comes from the vehicle's HEARTBEAT (``base_mode`` bit
MAV_MODE_FLAG_SAFETY_ARMED) and the throttle from VFR_HUD.
"""

from __future__ import annotations

import dataclasses
import os
import struct
from collections.abc import Callable

import numpy as np
from pymavlink import mavutil

from magcal.autopilot import vehicle
from magcal.logs.correction import (
    PX4_RAW_FRAME,
    Undone,
    ardupilot_frame,
    ardupilot_recorded,
    flight_recorded_ardupilot,
    flight_recorded_px4,
    px4_recorded,
    undo_ardupilot,
)
from magcal.logs.streams import (
    GnssStream,
    ImuStream,
    LogImportError,
    LogStreams,
    MagStream,
    ParamTimeline,
    StepSignal,
    instances_text,
    strictly_increasing,
    untruncate,
)

Progress = Callable[[float], None]

MAV_AUTOPILOT_ARDUPILOTMEGA = 3
MAV_AUTOPILOT_PX4 = 12
MAV_AUTOPILOT_INVALID = 8
MAV_TYPE_GCS = 6
MAV_MODE_FLAG_SAFETY_ARMED = 128
#: HIGHRES_IMU fields_updated: bits 0–2 acceleration, 3–5 rate.
HIGHRES_ACC_GYRO = 0x3F
IMU_MESSAGES = ("RAW_IMU", "SCALED_IMU", "SCALED_IMU2", "SCALED_IMU3")
#: What a flight session takes besides the IMU and compasses.
FLIGHT_MESSAGES = ("GPS_RAW_INT", "BATTERY_STATUS", "SYS_STATUS", "EXTENDED_SYS_STATE")
#: MAVLink's "unknown" for GPS_RAW_INT vel and cog.
UINT16_UNKNOWN = 65535
#: A GPS_RAW_INT time_usec above this is UTC (Unix µs), below it time since boot.
UNIX_US_MIN = 1e15
#: MAV_LANDED_STATE: 1 on ground, 2 in air, 3 taking off, 4 landing (0 undefined).
LANDED_ON_GROUND, LANDED_IN_AIR = 1, (2, 3, 4)
#: Link latency allowed when telling a reboot from a delayed message, s.
LINK_LATENCY_S = 1.0
#: Progress is reported every this many messages.
PROGRESS_EVERY = 2000
#: MAV_PARAM_TYPE → struct code of the bytes in PARAM_VALUE's float (bytewise encoding).
_BYTEWISE = {1: "<B", 2: "<b", 3: "<H", 4: "<h", 5: "<I", 6: "<i"}
NEEDS_AP = "needs RAW_IMU (or SCALED_IMU2/3) and PARAM_VALUE messages"
NEEDS_PX4 = "needs HIGHRES_IMU or SCALED_IMU, and SCALED_IMU for the magnetometer"


def _instance_of(msg_type: str) -> int:
    """1-based instance of an IMU message: RAW_IMU/SCALED_IMU 1, SCALED_IMU2 2, ..."""
    return int(msg_type[-1]) if msg_type[-1].isdigit() else 1


def _boot_time_s(m) -> float:
    if hasattr(m, "time_usec"):
        return m.time_usec * 1e-6
    return m.time_boot_ms * 1e-3


def _param_value(m, autopilot: int) -> float:
    if autopilot == MAV_AUTOPILOT_PX4 and m.param_type in _BYTEWISE:
        raw = struct.pack("<f", m.param_value)
        code = _BYTEWISE[m.param_type]
        return float(struct.unpack(code, raw[: struct.calcsize(code)])[0])
    return float(m.param_value)


def _is_vehicle(heartbeat) -> bool:
    """Whether a HEARTBEAT comes from an autopilot: not a ground station's, and not
    MAV_AUTOPILOT_INVALID (a camera, a gimbal)."""
    return heartbeat.autopilot != MAV_AUTOPILOT_INVALID and heartbeat.type != MAV_TYPE_GCS


def _read_messages(path: str, progress: Progress | None) -> tuple[int, dict[str, list]]:
    """(autopilot, type → [(reception s, message)]) of the vehicle's messages, whatever
    order they arrived in.

    The vehicle is the source (system, component) whose HEARTBEAT is not a ground station's
    and not MAV_AUTOPILOT_INVALID (a camera, a gimbal); of several, the one that sent the
    most IMU messages. Its messages are kept from the start of the file, also those
    before its first HEARTBEAT (a ground station may fetch the parameters first)."""
    name = os.path.basename(path)
    wanted = ["HEARTBEAT", "PARAM_VALUE", "VFR_HUD", "HIGHRES_IMU", *IMU_MESSAGES, *FLIGHT_MESSAGES]
    try:
        # mavlogfile, not mavlink_connection: that one chooses the reader by the file's
        # suffix, and the format was recognised from the content
        conn = mavutil.mavlogfile(path, notimestamps=False, robust_parsing=True)
    except OSError:
        raise
    except Exception as exc:
        raise LogImportError(f"{name}: not a readable MAVLink telemetry log ({exc})") from exc
    by_source: dict[tuple[int, int], dict[str, list]] = {}
    count = 0
    try:
        while True:
            m = conn.recv_match(type=wanted)
            if m is None:
                break
            count += 1
            if progress is not None and count % PROGRESS_EVERY == 0:
                progress(conn.percent / 100.0)
            src = (m.get_srcSystem(), m.get_srcComponent())
            mine = by_source.setdefault(src, {k: [] for k in wanted})
            mine[m.get_type()].append((m._timestamp, m))
    finally:
        conn.close()
    if progress is not None:
        progress(1.0)
    vehicles = [
        (sum(len(seen[k]) for k in ("HIGHRES_IMU", *IMU_MESSAGES)), src)
        for src, seen in by_source.items()
        if any(_is_vehicle(m) for _, m in seen["HEARTBEAT"])
    ]
    if not vehicles:
        raise LogImportError(
            f"{name} has no HEARTBEAT from a vehicle (only ground stations, or no MAVLink at "
            "all); it cannot say which autopilot recorded the data"
        )
    src = max(vehicles)[1]
    seen = by_source[src]
    autopilot = next(m.autopilot for _, m in seen["HEARTBEAT"] if _is_vehicle(m))
    return autopilot, seen


def _params_note(samples: list) -> str:
    """ "" when every parameter the vehicle has arrived (each PARAM_VALUE index of
    0 … param_count − 1), else what is missing, for an error."""
    if not samples:
        return "the ground station never fetched the parameters while recording"
    total = max(int(m.param_count) for _, m in samples)
    got = {int(m.param_index) for _, m in samples if 0 <= m.param_index < total}
    if len(got) >= total:
        return ""
    return (
        f"the ground station received {len(got)} of the vehicle's {total} parameters while "
        "recording; fetch them all (refresh the parameter list) while the log records"
    )


def _clock_offset(seen: dict[str, list]) -> float:
    """Median of (reception time − vehicle time) over the timed messages, s."""
    d = [rx - _boot_time_s(m) for k in ("HIGHRES_IMU", *IMU_MESSAGES) for rx, m in seen[k]]
    return float(np.median(d)) if d else 0.0


def _in_order(name: str, samples: list) -> tuple[list, int]:
    """The samples whose vehicle time is later than every one before (a message delayed on
    the link, or a small clock step, goes back in time: it is dropped) and how many were
    dropped. A reboot, where the vehicle's clock restarted, is refused: the evidence is a
    clock after the step that is no later than the reception time that passed since the
    message before (plus :data:`LINK_LATENCY_S`)."""
    boot = np.array([_boot_time_s(m) for _, m in samples])
    rx = np.array([r for r, _ in samples])
    back = np.flatnonzero(np.diff(boot) < 0) + 1
    for k in back:
        if boot[k] <= rx[k] - rx[k - 1] + LINK_LATENCY_S:
            raise LogImportError(
                f"{name}: the vehicle rebooted during the recording (its clock restarted at "
                f"{boot[k]:.1f} s after {boot[k - 1]:.1f} s, {rx[k] - rx[k - 1]:.1f} s of "
                "reception time later); split the log at the reboot"
            )
    latest = np.maximum.accumulate(boot)
    keep = np.concatenate([[True], boot[1:] > latest[:-1]]) if boot.size else np.zeros(0, bool)
    return [x for x, k in zip(samples, keep, strict=True) if k], int((~keep).sum())


def _order_note(count: int, msg_type: str) -> tuple[str, ...]:
    if not count:
        return ()
    return (
        f"{count} {msg_type} message(s) carried a vehicle time earlier than one received "
        "before them (delayed on the link, or a clock step) and were dropped",
    )


def _imu_from_scaled(
    name: str, msg_type: str, samples: list, instance: int
) -> tuple[ImuStream, tuple[str, ...]]:
    samples, late = _in_order(name, samples)
    t = np.array([_boot_time_s(m) for _, m in samples])
    acc = vehicle.acc_mg_to_si(untruncate([(m.xacc, m.yacc, m.zacc) for _, m in samples]))
    gyr = vehicle.gyro_mrad_to_si(untruncate([(m.xgyro, m.ygyro, m.zgyro) for _, m in samples]))
    t, gyr, acc = strictly_increasing(t, gyr, acc)
    return ImuStream(t, gyr, acc, instance, msg_type), _order_note(late, msg_type)


def _imu_from_highres(
    name: str, samples: list, instance: int
) -> tuple[ImuStream | None, tuple[str, ...]]:
    mine = [(rx, m) for rx, m in samples if getattr(m, "id", 0) == instance - 1]
    if any(m.fields_updated for _, m in mine):
        mine = [
            (rx, m) for rx, m in mine if m.fields_updated & HIGHRES_ACC_GYRO == HIGHRES_ACC_GYRO
        ]
    if not mine:
        return None, ()
    mine, late = _in_order(name, mine)
    t = np.array([m.time_usec * 1e-6 for _, m in mine])
    acc = np.array([(m.xacc, m.yacc, m.zacc) for _, m in mine], float)
    gyr = np.array([(m.xgyro, m.ygyro, m.zgyro) for _, m in mine], float)
    t, gyr, acc = strictly_increasing(t, gyr, acc)
    stream = ImuStream(t, gyr, acc, instance, f"HIGHRES_IMU id {instance - 1}")
    return stream, _order_note(late, "HIGHRES_IMU")


def _imu_message(instance: int) -> str:
    return ("RAW_IMU", "SCALED_IMU2", "SCALED_IMU3")[instance - 1] if instance <= 3 else ""


def _mag_samples(seen: dict[str, list], msg_type: str) -> list:
    """Samples of ``msg_type`` whose magnetometer is not all zero (no such compass)."""
    return [(rx, m) for rx, m in seen.get(msg_type, []) if (m.xmag, m.ymag, m.zmag) != (0, 0, 0)]


def _fresh(t: np.ndarray, field: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
    """Drop a reading identical to the one before: the stream repeats the last compass
    reading until a new one arrives (a stream faster than the compass), and a repeat is no
    new measurement. At rest, with 1 mG steps and a few mG of noise, an exact repeat of all
    three components is rare, so little real data goes with them."""
    same = np.concatenate([[False], np.all(field[1:] == field[:-1], axis=1)])
    return t[~same], field[~same], int(same.sum())


def _stale_note(count: int, msg_type: str) -> tuple[str, ...]:
    if not count:
        return ()
    return (f"{count} {msg_type} magnetometer reading(s) repeating the one before were dropped",)


def read(path: str, compass: int = 1, imu: int = 1, progress: Progress | None = None) -> LogStreams:
    """Read a MAVLink ``.tlog``; compass and imu are 1-based (see the module docstring)."""
    name = os.path.basename(path)
    autopilot, seen = _read_messages(path, progress)
    offset = _clock_offset(seen)
    records = [
        (rx - offset, m.param_id, _param_value(m, autopilot)) for rx, m in seen["PARAM_VALUE"]
    ]
    params = ParamTimeline.from_records(records)
    armed, throttle = _armed_throttle(seen, offset)
    flight = {
        "gnss": _gnss(seen, offset),
        "current": _current(seen, offset),
        "airborne": _airborne(seen, offset),
    }
    if autopilot == MAV_AUTOPILOT_ARDUPILOTMEGA:
        streams = _ardupilot(path, name, seen, params, compass, imu, armed, throttle)
        return dataclasses.replace(streams, **flight)
    if autopilot == MAV_AUTOPILOT_PX4:
        streams = _px4(path, name, seen, params, compass, imu, armed, throttle)
        return dataclasses.replace(streams, **flight)
    raise LogImportError(
        f"{name}: the vehicle's HEARTBEAT names autopilot {autopilot}; magcal reads ArduPilot "
        f"({MAV_AUTOPILOT_ARDUPILOTMEGA}) and PX4 ({MAV_AUTOPILOT_PX4}) telemetry"
    )


def _gnss(seen: dict[str, list], offset: float) -> GnssStream | None:
    """GPS_RAW_INT: fix, position, horizontal velocity (vel along cog; vertical not in the
    message: left unknown) and UTC when time_usec is one; placed by reception time."""
    msgs = seen["GPS_RAW_INT"]
    if not msgs:
        return None
    t = np.array([rx - offset for rx, _ in msgs])
    fix = np.array([m.fix_type for _, m in msgs], dtype=int)
    lat = np.array([m.lat * 1e-7 for _, m in msgs])
    lon = np.array([m.lon * 1e-7 for _, m in msgs])
    alt = np.array([m.alt * 1e-3 for _, m in msgs])
    speed = np.array([np.nan if m.vel == UINT16_UNKNOWN else m.vel * 1e-2 for _, m in msgs])
    course = np.array([np.nan if m.cog == UINT16_UNKNOWN else m.cog * 1e-2 for _, m in msgs])
    course = np.deg2rad(course)
    vel = np.column_stack([speed * np.cos(course), speed * np.sin(course), np.full(t.size, np.nan)])
    stamp = np.array([float(m.time_usec) for _, m in msgs])
    utc = np.where(stamp > UNIX_US_MIN, stamp * 1e-6, np.nan)
    t, fix, lat, lon, alt, vel, utc = strictly_increasing(t, fix, lat, lon, alt, vel, utc)
    return GnssStream(t, fix, lat, lon, alt, vel, utc, "GPS_RAW_INT")


def _current(seen: dict[str, list], offset: float) -> StepSignal | None:
    """Battery current, A: BATTERY_STATUS id 0, else SYS_STATUS (cA; −1 unknown)."""
    for kind, pick in (
        ("BATTERY_STATUS", lambda m: getattr(m, "id", 0) == 0),
        ("SYS_STATUS", lambda m: True),
    ):
        msgs = [(rx, m) for rx, m in seen[kind] if pick(m) and m.current_battery >= 0]
        if msgs:
            t = np.array([rx - offset for rx, _ in msgs])
            return StepSignal(t, np.array([m.current_battery * 1e-2 for _, m in msgs]))
    return None


def _airborne(seen: dict[str, list], offset: float) -> StepSignal | None:
    """EXTENDED_SYS_STATE.landed_state: 1 in the air (taking off, flying, landing), 0 on the
    ground; None when the vehicle never said (undefined)."""
    msgs = [(rx, m) for rx, m in seen["EXTENDED_SYS_STATE"] if m.landed_state > 0]
    if not msgs:
        return None
    t = np.array([rx - offset for rx, _ in msgs])
    return StepSignal(t, np.array([float(m.landed_state in LANDED_IN_AIR) for _, m in msgs]))


def _armed_throttle(seen: dict[str, list], offset: float) -> tuple[StepSignal | None, ...]:
    hb = seen["HEARTBEAT"]
    armed = None
    if hb:
        t = np.array([rx - offset for rx, _ in hb])
        v = np.array([float(m.base_mode & MAV_MODE_FLAG_SAFETY_ARMED != 0) for _, m in hb])
        armed = StepSignal(t, v)
    hud = seen["VFR_HUD"]
    throttle = None
    if hud:
        t = np.array([rx - offset for rx, _ in hud])
        throttle = StepSignal(t, np.array([m.throttle / 100.0 for _, m in hud]))
    return armed, throttle


def _ardupilot(path, name, seen, params, compass, imu, armed, throttle) -> LogStreams:
    imu_type, mag_type = _imu_message(imu), _imu_message(compass)
    have_imu = [i for i in (1, 2, 3) if seen[_imu_message(i)]]
    have_mag = [i for i in (1, 2, 3) if _mag_samples(seen, _imu_message(i))]
    missing = []
    if not imu_type or not seen[imu_type]:
        missing.append(
            f"no {imu_type or 'message'} for IMU {imu} (found IMUs {instances_text(have_imu)})"
        )
    if not mag_type or not _mag_samples(seen, mag_type):
        missing.append(
            f"no magnetometer data for compass {compass} (found compasses "
            f"{instances_text(have_mag)})"
        )
    if not seen["PARAM_VALUE"]:
        missing.append("no PARAM_VALUE messages (the ground station never fetched parameters)")
    if missing:
        raise LogImportError(f"{name} (ArduPilot) has {' and '.join(missing)}; {NEEDS_AP}")
    imu_stream, imu_notes = _imu_from_scaled(name, imu_type, seen[imu_type], imu)
    params_note = _params_note(seen["PARAM_VALUE"])
    names = params.names()
    mag_stream, mag_notes, undone = _ap_mag(name, seen, params, compass, params_note)
    others, other_names, other_notes = [], [], []
    for k in have_mag:
        if k == compass:
            continue
        try:
            other, notes_k, undone_k = _ap_mag(name, seen, params, k, params_note)
        except LogImportError as exc:
            other_notes.append(f"compass {k} left out of the flight columns: {exc}")
            continue
        others.append(other)
        other_notes += notes_k
        other_names += flight_recorded_ardupilot(undone_k.param_compass, undone_k.naming, names)
    other_names += flight_recorded_ardupilot(undone.param_compass, undone.naming, names)
    return LogStreams(
        path=path,
        log_format="tlog",
        autopilot=vehicle.ARDUPILOT,
        imu=imu_stream,
        mag=mag_stream,
        params=params,
        param_names=ardupilot_recorded(undone.param_compass, undone.naming, params.names()),
        param_compass=undone.param_compass,
        naming=undone.naming,
        armed=armed,
        throttle=throttle,
        other_mags=tuple(others),
        other_param_names=tuple(dict.fromkeys(other_names)),
        notes=tuple(dict.fromkeys(imu_notes + mag_notes + tuple(other_notes))),
        meta=undone.meta,
    )


def _ap_mag(
    name: str, seen: dict[str, list], params: ParamTimeline, compass: int, params_note: str
) -> tuple[MagStream, tuple[str, ...], Undone]:
    """ArduPilot compass ``compass``'s samples (RAW_IMU, SCALED_IMU2/3) with the correction in
    force undone, the notes about them and how it was undone."""
    mag_type = _imu_message(compass)
    samples, late = _in_order(name, _mag_samples(seen, mag_type))
    t = np.array([_boot_time_s(m) for _, m in samples])
    t, field = strictly_increasing(t, np.array([(m.xmag, m.ymag, m.zmag) for _, m in samples]))
    t, field, stale = _fresh(t, field)
    field = untruncate(field)
    undone = undo_ardupilot(
        name,
        t,
        field,
        params,
        compass,
        params_complete=not params_note,
        params_note=params_note,
    )
    stream = MagStream(
        t=t[undone.keep],
        mag=undone.mag,
        instance=compass,
        unit=vehicle.MAG_UNIT[vehicle.ARDUPILOT],
        frame=ardupilot_frame(motor=False),
        source=mag_type,
    )
    notes = _order_note(late, mag_type) + _stale_note(stale, mag_type) + undone.notes
    return stream, notes, undone


def _px4(path, name, seen, params, compass, imu, armed, throttle) -> LogStreams:
    mag_type = ("SCALED_IMU", "SCALED_IMU2", "SCALED_IMU3")[compass - 1] if compass <= 3 else ""
    imu_stream, imu_notes = _imu_from_highres(name, seen["HIGHRES_IMU"], imu)
    scaled = ("SCALED_IMU", "SCALED_IMU2", "SCALED_IMU3")
    if imu_stream is None and imu <= 3 and seen[scaled[imu - 1]]:
        imu_stream, imu_notes = _imu_from_scaled(name, scaled[imu - 1], seen[scaled[imu - 1]], imu)
    have_mag = [i for i, k in enumerate(scaled, 1) if _mag_samples(seen, k)]
    missing = []
    if imu_stream is None:
        ids = sorted({getattr(m, "id", 0) + 1 for _, m in seen["HIGHRES_IMU"]})
        ids += [i for i, k in enumerate(scaled, 1) if seen[k] and i not in ids]
        missing.append(
            f"no HIGHRES_IMU or SCALED_IMU for IMU {imu} (found IMUs {instances_text(ids)})"
        )
    if not mag_type or not _mag_samples(seen, mag_type):
        missing.append(
            f"no SCALED_IMU magnetometer data for compass {compass} (found compasses "
            f"{instances_text(have_mag)})"
        )
    if missing:
        raise LogImportError(f"{name} (PX4) has {' and '.join(missing)}; {NEEDS_PX4}")
    assert imu_stream is not None
    mag_stream, mag_notes = _px4_mag(name, seen, compass)
    others, other_notes = [], []
    for k in have_mag:
        if k != compass:
            other, notes_k = _px4_mag(name, seen, k)
            others.append(other)
            other_notes += notes_k
    other_names = [n for k in have_mag for n in flight_recorded_px4(k - 1, params.names())]
    return LogStreams(
        path=path,
        log_format="tlog",
        autopilot=vehicle.PX4,
        imu=imu_stream,
        mag=mag_stream,
        params=params,
        param_names=px4_recorded(compass - 1, params.names()),
        param_compass=compass - 1,
        armed=armed,
        throttle=throttle,
        other_mags=tuple(others),
        other_param_names=tuple(dict.fromkeys(other_names)),
        notes=tuple(dict.fromkeys(imu_notes + mag_notes + tuple(other_notes))),
    )


def _px4_mag(name: str, seen: dict[str, list], compass: int) -> tuple[MagStream, tuple[str, ...]]:
    """PX4 compass ``compass``'s raw samples (SCALED_IMU, SCALED_IMU2/3: sensor_mag, mG)."""
    mag_type = ("SCALED_IMU", "SCALED_IMU2", "SCALED_IMU3")[compass - 1]
    samples, late = _in_order(name, _mag_samples(seen, mag_type))
    t = np.array([_boot_time_s(m) for _, m in samples])
    t, wire = strictly_increasing(t, np.array([(m.xmag, m.ymag, m.zmag) for _, m in samples]))
    t, wire, stale = _fresh(t, wire)
    field = vehicle.mag_wire_to_unit(untruncate(wire), vehicle.PX4)
    stream = MagStream(
        t=t,
        mag=field,
        instance=compass,
        unit=vehicle.MAG_UNIT[vehicle.PX4],
        frame=PX4_RAW_FRAME,
        source=mag_type,
    )
    return stream, _order_note(late, mag_type) + _stale_note(stale, mag_type)
