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
  or ``timestamp``. Used when present: it is the raw field.
- ``vehicle_magnetometer`` (VehicleMagnetometer.msg): ``magnetometer_ga[3]``, the
  *calibrated* field in the body frame, with the ``device_id`` of its sensor. Without
  sensor_mag, its calibration ``CAL_MAGn_*`` (n: the ``CAL_MAGn_ID`` equal to that device id)
  is undone with the parameters in force (:func:`magcal.logs.correction.undo_px4`).
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
from magcal.logs.correction import PX4_RAW_FRAME, px4_calibration_index, px4_recorded, undo_px4
from magcal.logs.streams import (
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
]
RELATIVE_TIMESTAMP_INVALID = 0x7FFFFFFF
ARMING_STATE_ARMED = 2
NEEDS = "needs sensor_combined, and sensor_mag or vehicle_magnetometer"


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
            if pct != self._reported:
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
    raw = _datasets(ulog, "sensor_mag")
    calibrated = _datasets(ulog, "vehicle_magnetometer")
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
    mag_stream, notes = None, ()
    if compass - 1 in raw:
        mag_stream = _raw_mag(raw[compass - 1], compass)
    elif compass - 1 in calibrated:
        mag_stream, notes = _undone_mag(name, calibrated[compass - 1], compass, params)
    else:
        found = sorted({i + 1 for i in raw} | {i + 1 for i in calibrated})
        missing.append(
            f"no sensor_mag or vehicle_magnetometer for compass {compass} (found compasses "
            f"{instances_text(found)})"
        )
    if missing:
        raise LogImportError(f"{name} has {' and '.join(missing)}; {NEEDS}")
    assert imu_stream is not None and mag_stream is not None
    index = _calibration_slot(params, raw.get(compass - 1), compass)
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
        notes=notes,
    )


def _calibration_slot(params: ParamTimeline, data, compass: int) -> int:
    """CAL_MAGn index of the compass: by device id when known, else compass − 1."""
    if data is not None and "device_id" in data and len(data["device_id"]):
        n = px4_calibration_index(params.initial, int(data["device_id"][0]))
        if n is not None:
            return n
    return compass - 1


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


def _undone_mag(
    name: str, data: dict[str, np.ndarray], compass: int, params: ParamTimeline
) -> tuple[MagStream, tuple[str, ...]]:
    device = int(data["device_id"][0]) if "device_id" in data else None
    index = px4_calibration_index(params.initial, device) if device is not None else None
    if index is None:
        raise LogImportError(
            f"{name}: vehicle_magnetometer instance {compass - 1} (device id {device}) matches "
            "no CAL_MAGn_ID parameter, so its calibration cannot be undone; log the raw "
            "sensor_mag topic instead"
        )
    stamp = data["timestamp_sample"] if "timestamp_sample" in data else data["timestamp"]
    field = _vec(data, "magnetometer_ga")
    t, field = strictly_increasing(np.asarray(stamp, dtype=float) * 1e-6, field)
    undone = undo_px4(name, t, field, params, index)
    stream = MagStream(
        t=t[undone.keep],
        mag=undone.mag,
        instance=compass,
        unit=vehicle.MAG_UNIT[vehicle.PX4],
        frame=f"PX4 raw sensor frame: vehicle_magnetometer with CAL_MAG{index}_* undone (Rot0 = I)",
        source=f"vehicle_magnetometer[{compass - 1}]",
    )
    return stream, undone.notes
