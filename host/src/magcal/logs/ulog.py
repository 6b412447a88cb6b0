# SPDX-License-Identifier: Apache-2.0
"""PX4 ULog files (``.ulg``), read with pyulog.

Topics (PX4 ``msg/*.msg``, read with the code search tool):

- ``sensor_combined`` (SensorCombined.msg): ``timestamp`` µs, ``gyro_rad[3]`` "average
  angular rate measured in the FRD body frame … over the last gyro sampling period"
  (``gyro_integral_dt`` µs), ``accelerometer_m_s2[3]`` likewise over
  ``accelerometer_integral_dt``, at ``timestamp + accelerometer_timestamp_relative``
  (``RELATIVE_TIMESTAMP_INVALID`` = 0x7fffffff marks a missing accelerometer). Each average
  is placed at the middle of its period. It is the primary IMU (``--imu 1``); other IMUs come
  from ``vehicle_imu`` instances (``delta_angle``/``delta_velocity`` over their ``_dt``), when
  logged.
- ``sensor_mag`` (SensorMag.msg): ``x, y, z`` "magnetic field in the FRD board frame … in
  Gauss", uncalibrated, one instance per magnetometer, at ``timestamp_sample`` (newer PX4)
  or ``timestamp``: the raw field.
- ``vehicle_magnetometer`` (VehicleMagnetometer.msg): ``magnetometer_ga[3]``, the
  *calibrated* field in the body frame, with (newer PX4) the ``device_id`` of its sensor.
- ``sensor_combined.magnetometer_ga[3]`` (PX4 before 1.7, at ``timestamp +
  magnetometer_timestamp_relative``): the calibrated field of the primary magnetometer.

**Which source.** Loggers often record the raw sensor_mag slowly (1 Hz) and the calibrated
field at the sensor's rate: the source with the most samples per second is used, the raw one
when it has at least :data:`RAW_RATE_SHARE` of the best rate. A calibrated field has its
calibration ``CAL_MAGn_*`` undone with the parameters in force
(:func:`magcal.logs.correction.undo_px4`); n is the ``CAL_MAGn_ID`` equal to its device id,
or where the topic names none, the slot whose undone field agrees with the raw sensor_mag
samples logged beside it (content), or the only calibrated slot.
- ``actuator_armed.armed`` or ``vehicle_status.arming_state`` (2 = armed): the armed state.

Parameters: the file's initial parameters, then its parameter changes (pyulog's
``changed_parameters``, placed at the time of the last data before them).
"""

from __future__ import annotations

import io
import os
from collections.abc import Callable

import numpy as np

from magcal.autopilot import vehicle
from magcal.logs.correction import (
    PX4_RAW_FRAME,
    flight_recorded_px4,
    px4_calibration_index,
    px4_recorded,
    undo_px4,
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
)

Progress = Callable[[float], None]

TOPICS = [
    "sensor_combined",
    "vehicle_imu",
    "sensor_mag",
    "vehicle_magnetometer",
    "actuator_armed",
    "vehicle_status",
    "vehicle_gps_position",
    "sensor_gps",
    "battery_status",
    "vehicle_land_detected",
    "actuator_controls_0",
    "vehicle_thrust_setpoint",
]
RELATIVE_TIMESTAMP_INVALID = 0x7FFFFFFF
ARMING_STATE_ARMED = 2
NEEDS = (
    "needs sensor_combined, and sensor_mag, vehicle_magnetometer or a magnetometer in "
    "sensor_combined"
)
#: The raw sensor_mag is used when its rate is at least this share of the best source's.
RAW_RATE_SHARE = 0.5
#: Matching a calibrated source to raw samples: time apart, s, and median distance, gauss.
MATCH_DT_S = 0.05
MATCH_GAUSS = 0.02
#: The first PX4 release whose sensor_mag is the raw field (see _sensor_mag_is_raw).
SENSOR_MAG_RAW_FROM = (1, 12)


class _ProgressFile(io.RawIOBase):
    """A read-only file that reports the fraction read (pyulog takes a file object)."""

    def __init__(self, path: str, progress: Progress | None) -> None:
        self._f = open(path, "rb")  # closed by close()
        self._size = max(1, os.fstat(self._f.fileno()).st_size)
        self._progress = progress
        self._reported = -1

    def readable(self) -> bool:
        return True

    def seekable(self) -> bool:
        return True

    def read(self, n: int = -1) -> bytes:
        data = self._f.read(n)
        if self._progress is not None:
            pct = int(100 * self._f.tell() / self._size)
            # pyulog seeks back (appended data, the index): the fraction read never shrinks
            if pct > self._reported:
                self._reported = pct
                self._progress(pct / 100.0)
        return data

    def seek(self, offset: int, whence: int = 0) -> int:
        return self._f.seek(offset, whence)

    def tell(self) -> int:
        return self._f.tell()

    def close(self) -> None:
        self._f.close()
        super().close()


def _datasets(ulog, name: str) -> dict[int, dict[str, np.ndarray]]:
    """multi_id → field arrays of topic ``name``."""
    return {d.multi_id: d.data for d in ulog.data_list if d.name == name}


def _vec(data: dict[str, np.ndarray], base: str) -> np.ndarray:
    return np.column_stack([np.asarray(data[f"{base}[{i}]"], dtype=float) for i in range(3)])


def _imu_combined(data: dict[str, np.ndarray]) -> ImuStream:
    stamp = np.asarray(data["timestamp"], dtype=np.int64)
    t_gyr = stamp.astype(float)
    if "gyro_integral_dt" in data:
        t_gyr = t_gyr - 0.5 * np.asarray(data["gyro_integral_dt"], dtype=float)
    gyr = _vec(data, "gyro_rad")
    acc = _vec(data, "accelerometer_m_s2")
    t_acc = stamp.astype(float)
    valid = np.ones(stamp.size, dtype=bool)
    if "accelerometer_timestamp_relative" in data:
        rel = np.asarray(data["accelerometer_timestamp_relative"], dtype=np.int64)
        valid = rel != RELATIVE_TIMESTAMP_INVALID
        t_acc = t_acc + np.where(valid, rel, 0)
    if "accelerometer_integral_dt" in data:
        t_acc = t_acc - 0.5 * np.asarray(data["accelerometer_integral_dt"], dtype=float)
    t_gyr, gyr = strictly_increasing(t_gyr * 1e-6, gyr)
    t_acc, acc = strictly_increasing(t_acc[valid] * 1e-6, acc[valid])
    acc = np.column_stack([np.interp(t_gyr, t_acc, acc[:, j]) for j in range(3)])
    return ImuStream(t_gyr, gyr, acc, 1, "sensor_combined")


def _imu_vehicle_imu(data: dict[str, np.ndarray], instance: int) -> ImuStream:
    stamp = np.asarray(data.get("timestamp_sample", data["timestamp"]), dtype=float)
    dt_a = np.asarray(data["delta_angle_dt"], dtype=float)
    dt_v = np.asarray(data["delta_velocity_dt"], dtype=float)
    ok = (dt_a > 0) & (dt_v > 0)
    gyr = _vec(data, "delta_angle")[ok] / (dt_a[ok, None] * 1e-6)
    acc = _vec(data, "delta_velocity")[ok] / (dt_v[ok, None] * 1e-6)
    t = (stamp[ok] - 0.5 * dt_a[ok]) * 1e-6
    t, gyr, acc = strictly_increasing(t, gyr, acc)
    return ImuStream(t, gyr, acc, instance, f"vehicle_imu[{instance - 1}]")


def _params(ulog) -> ParamTimeline:
    initial = {k: float(v) for k, v in ulog.initial_parameters.items()}
    changes = []
    current = dict(initial)
    for stamp, name, value in ulog.changed_parameters:
        value = float(value)
        if current.get(name) != value:
            changes.append((stamp * 1e-6, name, value))
        current[name] = value
    return ParamTimeline(initial, tuple(sorted(changes, key=lambda c: c[0])))


def _armed(ulog) -> StepSignal | None:
    armed = _datasets(ulog, "actuator_armed").get(0)
    if armed is not None and "armed" in armed:
        t = np.asarray(armed["timestamp"], dtype=float) * 1e-6
        return StepSignal(t, (np.asarray(armed["armed"]) != 0).astype(float))
    status = _datasets(ulog, "vehicle_status").get(0)
    if status is not None and "arming_state" in status:
        t = np.asarray(status["timestamp"], dtype=float) * 1e-6
        return StepSignal(t, (np.asarray(status["arming_state"]) == ARMING_STATE_ARMED) * 1.0)
    return None


def _gnss(ulog) -> GnssStream | None:
    """vehicle_gps_position (the receiver chosen), else sensor_gps instance 0: fix, position
    (lat/lon in 1e-7 degrees and alt in mm before PX4 1.14, latitude_deg/longitude_deg and
    altitude_msl_m after), NED velocity (NaN where vel_ned_valid is false) and UTC."""
    data = _datasets(ulog, "vehicle_gps_position").get(0)
    source = "vehicle_gps_position"
    if data is None:
        data, source = _datasets(ulog, "sensor_gps").get(0), "sensor_gps"
    if data is None or "fix_type" not in data:
        return None
    t = np.asarray(data.get("timestamp_sample", data["timestamp"]), dtype=float) * 1e-6
    if "latitude_deg" in data:
        lat, lon = (np.asarray(data[k], float) for k in ("latitude_deg", "longitude_deg"))
        alt = np.asarray(data["altitude_msl_m"], float)
    else:
        lat, lon = (np.asarray(data[k], float) * 1e-7 for k in ("lat", "lon"))
        alt = np.asarray(data["alt"], float) * 1e-3
    vel = np.column_stack([np.asarray(data[f"vel_{a}_m_s"], float) for a in "ned"])
    if "vel_ned_valid" in data:
        vel[np.asarray(data["vel_ned_valid"]) == 0] = np.nan
    utc = np.asarray(data.get("time_utc_usec", np.zeros(t.size)), dtype=float)
    utc = np.where(utc > 0, utc * 1e-6, np.nan)
    fix = np.asarray(data["fix_type"], dtype=int)
    t, fix, lat, lon, alt, vel, utc = strictly_increasing(t, fix, lat, lon, alt, vel, utc)
    return GnssStream(t, fix, lat, lon, alt, vel, utc, source)


def _current(ulog) -> StepSignal | None:
    """battery_status instance 0's current_a (A; negative: unknown)."""
    data = _datasets(ulog, "battery_status").get(0)
    if data is None or "current_a" not in data:
        return None
    t = np.asarray(data["timestamp"], dtype=float) * 1e-6
    current = np.asarray(data["current_a"], dtype=float)
    ok = current >= 0
    return StepSignal(t[ok], current[ok]) if ok.any() else None


def _airborne(ulog) -> StepSignal | None:
    """vehicle_land_detected.landed: 0 in the air."""
    data = _datasets(ulog, "vehicle_land_detected").get(0)
    if data is None or "landed" not in data:
        return None
    t = np.asarray(data["timestamp"], dtype=float) * 1e-6
    return StepSignal(t, (np.asarray(data["landed"]) == 0).astype(float))


def _throttle(ulog) -> StepSignal | None:
    """The collective thrust, 0–1: −vehicle_thrust_setpoint.xyz[2] (PX4 1.14 on), else
    actuator_controls_0.control[3]."""
    data = _datasets(ulog, "vehicle_thrust_setpoint").get(0)
    if data is not None and "xyz[2]" in data:
        value = -np.asarray(data["xyz[2]"], dtype=float)
    else:
        data = _datasets(ulog, "actuator_controls_0").get(0)
        if data is None or "control[3]" not in data:
            return None
        value = np.asarray(data["control[3]"], dtype=float)
    t = np.asarray(data["timestamp"], dtype=float) * 1e-6
    ok = np.isfinite(value)
    return StepSignal(t[ok], np.clip(value[ok], 0.0, 1.0)) if ok.any() else None


def read(path: str, compass: int = 1, imu: int = 1, progress: Progress | None = None) -> LogStreams:
    """Read a PX4 ``.ulg``; compass = sensor_mag instance + 1, imu 1 = sensor_combined."""
    from pyulog import ULog

    name = os.path.basename(path)
    f = _ProgressFile(path, progress)
    try:
        ulog = ULog(f, message_name_filter_list=TOPICS, disable_str_exceptions=True)
    except OSError:
        raise
    except Exception as exc:  # pyulog raises its own and struct/Value errors
        raise LogImportError(f"{name}: not a readable ULog file ({exc})") from exc
    finally:
        f.close()

    combined = _datasets(ulog, "sensor_combined")
    vimu = _datasets(ulog, "vehicle_imu")
    params = _params(ulog)
    missing = []
    imu_stream = None
    if imu == 1 and 0 in combined:
        imu_stream = _imu_combined(combined[0])
    elif imu > 1 and imu - 1 in vimu:
        imu_stream = _imu_vehicle_imu(vimu[imu - 1], imu)
    else:
        found = ([1] if combined else []) + [i + 1 for i in vimu if i + 1 > 1]
        where = "sensor_combined" if imu == 1 else f"vehicle_imu instance {imu - 1}"
        missing.append(f"no {where} for IMU {imu} (found IMUs {instances_text(found)})")
    try:
        chosen = _choose_mag(name, ulog, params, compass)
    except _NoMag as exc:
        chosen = None
        missing.append(str(exc))
    if missing:
        raise LogImportError(f"{name} has {' and '.join(missing)}; {NEEDS}")
    assert imu_stream is not None and chosen is not None
    mag_stream, notes, index = chosen
    others, other_names = [], list(flight_recorded_px4(index, params.names()))
    instances = set(_datasets(ulog, "sensor_mag")) | set(_datasets(ulog, "vehicle_magnetometer"))
    for k in sorted(i + 1 for i in instances):
        if k == compass:
            continue
        try:
            other, other_notes, other_index = _choose_mag(name, ulog, params, k)
        except (_NoMag, LogImportError) as exc:
            notes += (f"compass {k} left out of the flight columns: {exc}",)
            continue
        others.append(other)
        notes += other_notes
        other_names += flight_recorded_px4(other_index, params.names())
    return LogStreams(
        path=path,
        log_format="ULog",
        autopilot=vehicle.PX4,
        imu=imu_stream,
        mag=mag_stream,
        params=params,
        param_names=px4_recorded(index, params.names()),
        param_compass=index,
        armed=_armed(ulog),
        throttle=_throttle(ulog),
        other_mags=tuple(others),
        other_param_names=tuple(dict.fromkeys(other_names)),
        gnss=_gnss(ulog),
        current=_current(ulog),
        airborne=_airborne(ulog),
        notes=notes,
        known_gaps=_dropouts(ulog),
        gap_cause="nothing was logged",
    )


def _raw_mag(data: dict[str, np.ndarray], compass: int) -> MagStream:
    stamp = data["timestamp_sample"] if "timestamp_sample" in data else data["timestamp"]
    field = np.column_stack([np.asarray(data[a], dtype=float) for a in "xyz"])
    t, field = strictly_increasing(np.asarray(stamp, dtype=float) * 1e-6, field)
    return MagStream(
        t=t,
        mag=field,
        instance=compass,
        unit=vehicle.MAG_UNIT[vehicle.PX4],
        frame=PX4_RAW_FRAME,
        source=f"sensor_mag[{compass - 1}]",
    )


class _NoMag(Exception):
    """No magnetometer source for the compass asked for (text: what was found)."""


def _rate_hz(t: np.ndarray) -> float:
    return (t.size - 1) / (t[-1] - t[0]) if t.size > 1 and t[-1] > t[0] else 0.0


def _calibrated(
    data: dict[str, np.ndarray], field: str, stamp_relative: str | None
) -> tuple[np.ndarray, np.ndarray]:
    """(t s, field gauss) of a calibrated field, sorted, repeats dropped."""
    stamp = np.asarray(data.get("timestamp_sample", data["timestamp"]), dtype=np.int64)
    valid = np.ones(stamp.size, dtype=bool)
    if stamp_relative and stamp_relative in data:
        rel = np.asarray(data[stamp_relative], dtype=np.int64)
        valid = rel != RELATIVE_TIMESTAMP_INVALID
        stamp = stamp + np.where(valid, rel, 0)
    v = _vec(data, field)
    valid &= np.all(np.isfinite(v), axis=1)
    t, v = strictly_increasing(stamp[valid] * 1e-6, v[valid])
    # sensor_combined repeats the last magnetometer sample until a new one arrives
    fresh = np.concatenate([[True], np.any(v[1:] != v[:-1], axis=1)]) if t.size else t > 0
    return t[fresh], v[fresh]


def _device_slot(params: ParamTimeline, data: dict[str, np.ndarray]) -> int | None:
    """The CAL_MAGn slot whose CAL_MAGn_ID is the device id a topic names, or None (it
    names none, or no slot has it)."""
    if "device_id" not in data or not len(data["device_id"]):
        return None
    return px4_calibration_index(params.initial, int(data["device_id"][0]))


def _slots(params: ParamTimeline) -> list[int]:
    """CAL_MAGn slots that hold a magnetometer (CAL_MAGn_ID ≠ 0)."""
    return [n for n in range(8) if params.initial.get(f"CAL_MAG{n}_ID", 0) not in (0, None)]


def _version(ulog) -> tuple[int, int] | None:
    """(major, minor) of the PX4 release that wrote the log (ULog info ver_sw_release,
    0xAABBCCTT), or None when the log does not say."""
    v = ulog.msg_info_dict.get("ver_sw_release")
    if not isinstance(v, int) or v <= 0:
        return None
    return (v >> 24) & 0xFF, (v >> 16) & 0xFF


def _sensor_mag_is_raw(ulog) -> bool:
    """Whether sensor_mag holds the raw field. Before PX4 1.12 the driver
    (PX4Magnetometer) applied CAL_MAGn's offsets and scales before publishing it, and the
    sensors module only rotated it: in the logs at hand sensor_mag equals
    vehicle_magnetometer up to a rotation under 1.11.2, and equals it with CAL_MAGn undone
    (within 0.01 gauss) under 1.12.3 and later. Unknown versions: raw."""
    version = _version(ulog)
    return version is None or version >= SENSOR_MAG_RAW_FROM


def _unrotated(params: ParamTimeline, slot: int) -> ParamTimeline:
    """The parameters with CAL_MAG``slot``'s rotation and the board level adjustment set to
    none: undoing with them undoes the offsets and scales alone."""
    fixed = {f"CAL_MAG{slot}_ROT": 0.0} | {f"SENS_BOARD_{a}_OFF": 0.0 for a in "XYZ"}
    changes = tuple(c for c in params.changes if c[1] not in fixed)
    return ParamTimeline(params.initial | fixed, changes)


def _slot_by_content(
    t: np.ndarray, field: np.ndarray, params: ParamTimeline, raws: dict, raw_is_raw: bool
) -> int | None:
    """The CAL_MAGn slot of a calibrated field that names no device, from the sensor_mag
    instances logged beside it (at most MATCH_DT_S apart): the one whose field norm agrees
    within MATCH_GAUSS (norms do not depend on the rotations), with the calibrated field
    undone by the slot of that instance's device when sensor_mag is raw, as it is."""
    best = None
    for data in raws.values():
        n = _device_slot(params, data)
        if n is None:
            continue
        raw = _raw_mag(data, 1)
        ours = field
        if raw_is_raw:
            try:
                ours = undo_px4("", t, field, params, n, params_complete=True).mag
            except LogImportError:
                continue
        i = np.clip(np.searchsorted(t, raw.t), 1, max(1, t.size - 1))
        near = np.where(np.abs(t[i - 1] - raw.t) < np.abs(t[i] - raw.t), i - 1, i)
        close = np.abs(t[near] - raw.t) <= MATCH_DT_S
        if close.sum() < 3:
            continue
        diff = np.linalg.norm(ours[near[close]], axis=1) - np.linalg.norm(raw.mag[close], axis=1)
        err = float(np.median(np.abs(diff)))
        if best is None or err < best[0]:
            best = (err, n)
    return best[1] if best is not None and best[0] <= MATCH_GAUSS else None


def _choose_mag(
    name: str, ulog, params: ParamTimeline, compass: int
) -> tuple[MagStream, tuple[str, ...], int]:
    """The compass's magnetometer stream, its notes and its CAL_MAGn slot (see the module
    docstring, "Which source")."""
    raw_sets = _datasets(ulog, "sensor_mag")
    vmag_sets = _datasets(ulog, "vehicle_magnetometer")
    combined = _datasets(ulog, "sensor_combined").get(0)
    i = compass - 1
    raw_is_raw = _sensor_mag_is_raw(ulog)
    raw = _raw_mag(raw_sets[i], compass) if i in raw_sets else None
    calibrated = []  # (t, field, source, CAL_MAGn slot of the device it names or None)
    if i in vmag_sets:
        t, f = _calibrated(vmag_sets[i], "magnetometer_ga", None)
        calibrated.append((t, f, f"vehicle_magnetometer[{i}]", _device_slot(params, vmag_sets[i])))
    if compass == 1 and combined is not None and "magnetometer_ga[0]" in combined:
        t, f = _calibrated(combined, "magnetometer_ga", "magnetometer_timestamp_relative")
        calibrated.append((t, f, "sensor_combined.magnetometer_ga", None))
    calibrated = [c for c in calibrated if c[0].size >= 2]
    if raw is None and not calibrated:
        found = sorted({k + 1 for k in raw_sets} | {k + 1 for k in vmag_sets})
        if combined is not None and "magnetometer_ga[0]" in combined:
            found = sorted(set(found) | {1})
        raise _NoMag(
            f"no sensor_mag, vehicle_magnetometer or sensor_combined magnetometer for compass "
            f"{compass} (found compasses {instances_text(found)})"
        )
    raw_rate = _rate_hz(raw.t) if raw is not None else 0.0
    best = max(calibrated, key=lambda c: _rate_hz(c[0]), default=None)
    best_rate = _rate_hz(best[0]) if best is not None else 0.0
    if raw is not None and raw_rate >= RAW_RATE_SHARE * best_rate:
        slot = _device_slot(params, raw_sets[i])
        if slot is None:  # no device named, or none in CAL_MAGn_ID: the instance's own
            slot = i
        if raw_is_raw:
            return raw, (), slot
        return _undone(
            name,
            raw.t,
            raw.mag,
            _unrotated(params, slot),
            slot,
            compass,
            raw.source,
            (
                "PX4 before 1.12 applied CAL_MAGn's offsets and scales in the driver: they "
                f"were undone on sensor_mag[{i}]",
            ),
        )
    assert best is not None
    t, field, source, slot = best
    notes: list[str] = []
    if slot is None and raw_sets:
        slot = _slot_by_content(t, field, params, raw_sets, raw_is_raw)
        if slot is not None:
            notes.append(
                f"{source} names no device; its calibration is CAL_MAG{slot}_* (its field's "
                "norm agrees with that magnetometer's sensor_mag samples)"
            )
    prime = params.initial.get("CAL_MAG_PRIME")
    if slot is None and prime:
        slot = px4_calibration_index(params.initial, int(prime))
        if slot is not None:
            notes.append(
                f"{source} names no device; CAL_MAG_PRIME says the primary magnetometer, "
                f"calibrated by CAL_MAG{slot}_*"
            )
    slots = _slots(params)
    if slot is None and len(slots) == 1:
        slot = slots[0]
    if slot is None:
        raise LogImportError(
            f"{name}: the magnetometer is logged fast only calibrated ({source}, "
            f"{_rate_hz(t):.0f} Hz), which names no device, and no CAL_MAGn_* set could be "
            "shown to be its calibration, so it cannot be undone; log sensor_mag at the "
            "sensor's rate"
        )
    if raw is not None:
        notes.append(
            f"sensor_mag[{i}] is logged at {raw_rate:.1f} Hz only; {source} "
            f"({_rate_hz(t):.1f} Hz) was used with CAL_MAG{slot}_* undone"
        )
    return _undone(name, t, field, params, slot, compass, source, tuple(notes))


def _undone(
    name: str,
    t: np.ndarray,
    field: np.ndarray,
    params: ParamTimeline,
    slot: int,
    compass: int,
    source: str,
    notes: tuple[str, ...],
) -> tuple[MagStream, tuple[str, ...], int]:
    undone = undo_px4(name, t, field, params, slot, params_complete=True)
    stream = MagStream(
        t=t[undone.keep],
        mag=undone.mag,
        instance=compass,
        unit=vehicle.MAG_UNIT[vehicle.PX4],
        frame=f"PX4 raw sensor frame: {source} with CAL_MAG{slot}_* undone (Rot0 = I)",
        source=source,
    )
    return stream, notes + undone.notes, slot


def _dropouts(ulog) -> tuple[tuple[float, float, str], ...]:
    """The logger's dropouts (ULog 'O' messages: data lost because its buffer was full), as
    known gaps: from the last data before each, for its duration."""
    out = []
    for d in getattr(ulog, "dropouts", []) or []:
        t0 = d.timestamp * 1e-6
        out.append((t0, t0 + d.duration * 1e-3, f"the logger dropped {d.duration} ms of data"))
    return tuple(out)
