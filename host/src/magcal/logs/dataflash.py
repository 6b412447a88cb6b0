"""ArduPilot DataFlash logs (``.bin``): IMU, MAG, PARM (and ARM/EV for the armed state).

Message definitions, as in ArduPilot's sources (read with the code search tool):

- ``IMU`` (libraries/AP_InertialSensor/LogStructure.h): ``QBffffffIIfBBHH``,
  ``TimeUS,I,GyrX,GyrY,GyrZ,AccX,AccY,AccZ,EG,EA,T,GH,AH,GHz,AHz``, units ``s#EEEooo…``:
  TimeUS µs since boot, I the 0-based instance, gyro rad/s, accelerometer m/s², both in the
  body frame (after AHRS_ORIENTATION and the IMU calibration). Before ArduPilot 4.0 the
  instances were separate messages IMU, IMU2, IMU3 without ``I``; both are read.
- ``MAG`` (libraries/AP_Compass/LogStructure.h, AP_Compass_Logging.cpp):
  ``QBhhhhhhhhhBI``, ``TimeUS,I,MagX,MagY,MagZ,OfsX,OfsY,OfsZ,MOX,MOY,MOZ,Health,S``: the
  **corrected** field ``get_field(i)`` in mG (units ``G`` with multiplier ``C`` = 1e-3), the
  offsets and motor offsets in use, each cast to ``int16_t``; ``S`` is the µs time (uint32,
  wraps after 71 minutes) at which the field was published. ``I`` counts compasses in
  priority order. The int16 casts truncate; the importer adds back the half unit they remove
  on average (:func:`~magcal.logs.streams.untruncate`). Older logs name the motor offsets
  MOfsX/Y/Z, and have MAG2, MAG3.
- ``PARM``: ``TimeUS,Name,Value[,Default]``, every parameter when the log opens and each
  change as it happens.
- ``ARM`` (``ArmState``) or ``EV`` (Id 10 armed, 11 disarmed): the armed state.

The file is indexed by pymavlink's ``DFReader_binary`` (which finds every message of a type
without parsing the others, with its C indexer when built); the few types needed are then
decoded with numpy from that index, not one Python object per message, so a 100 MB log
takes seconds. DFReader's clock pass is skipped: it reads the whole log message by message,
without progress, when no GPS has a fix (a calibration indoors), and magcal uses TimeUS.
"""

from __future__ import annotations

import os
from collections.abc import Callable

import numpy as np
from pymavlink import DFReader

from magcal.autopilot import vehicle
from magcal.logs.correction import ardupilot_frame, ardupilot_recorded, undo_ardupilot
from magcal.logs.streams import (
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

#: ``struct`` codes of DFReader's FORMAT_TO_STRUCT → numpy (little-endian, packed).
_NUMPY = {
    "b": "i1",
    "B": "u1",
    "h": "<i2",
    "H": "<u2",
    "i": "<i4",
    "I": "<u4",
    "q": "<i8",
    "Q": "<u8",
    "f": "<f4",
    "d": "<f8",
    "e": "<f2",
    "4s": "S4",
    "16s": "S16",
    "64s": "S64",
}
#: EV ids (AP_Logger LogEvent): ARMED = 10, DISARMED = 11.
EV_ARMED, EV_DISARMED = 10, 11
#: A MAG sample is published at most this long before it is logged; beyond, S is not used.
MAX_PUBLISH_LAG_US = 1_000_000
NEEDS = "needs IMU, MAG and PARM messages"


class _Index(DFReader.DFReader_binary):
    """DFReader's index of a binary log, without its clock pass (see the module docstring)."""

    def init_clock(self) -> None:
        self.clock = None


def _decode(df: _Index, name: str) -> dict[str, np.ndarray] | None:
    """Every message ``name`` as column arrays (multipliers of c/C/e/E/L applied), or None."""
    mtype = df.name_to_id.get(name)
    if mtype is None or not df.offsets[mtype]:
        return None
    fmt = df.formats[mtype]
    fields = []
    for col, code in zip(fmt.columns, fmt.format, strict=False):
        struct_code = DFReader.FORMAT_TO_STRUCT[code][0]
        fields.append((col, _NUMPY[struct_code]))
    dtype = np.dtype(fields)
    size = fmt.len - 3
    if dtype.itemsize != size:
        raise LogImportError(
            f"{df.filehandle.name}: message {name} is defined with {size} bytes but its format "
            f"{fmt.format!r} has {dtype.itemsize}: the log is damaged or of an unknown kind"
        )
    data = df.data_map
    end = len(data)
    body = b"".join(data[o + 3 : o + 3 + size] for o in df.offsets[mtype] if o + 3 + size <= end)
    rec = np.frombuffer(body, dtype=dtype)
    out = {}
    for col, code in zip(fmt.columns, fmt.format, strict=False):
        mult = DFReader.FORMAT_TO_STRUCT[code][1]
        v = rec[col]
        out[col] = v * mult if mult is not None else v
    return out


def _instances(df: _Index, base: str) -> dict[int, dict[str, np.ndarray]]:
    """1-based instance → columns, from ``base`` with an ``I`` column or BASE, BASE2, BASE3."""
    out: dict[int, dict[str, np.ndarray]] = {}
    cols = _decode(df, base)
    if cols is not None and "I" in cols:
        for i in np.unique(cols["I"]):
            sel = cols["I"] == i
            out[int(i) + 1] = {k: v[sel] for k, v in cols.items()}
        return out
    if cols is not None:
        out[1] = cols
    for k in (2, 3):
        more = _decode(df, f"{base}{k}")
        if more is not None:
            out[k] = more
    return out


def _vec(cols: dict[str, np.ndarray], *names: str) -> np.ndarray:
    return np.column_stack([np.asarray(cols[n], dtype=float) for n in names])


def _params(df: _Index) -> ParamTimeline | None:
    cols = _decode(df, "PARM")
    if cols is None:
        return None
    names = [bytes(n).split(b"\0", 1)[0].decode("ascii", "replace") for n in cols["Name"]]
    t = np.asarray(cols["TimeUS"], dtype=float) * 1e-6
    values = np.asarray(cols["Value"], dtype=float)
    return ParamTimeline.from_records(list(zip(t.tolist(), names, values.tolist(), strict=True)))


def _armed(df: _Index) -> StepSignal | None:
    arm = _decode(df, "ARM")
    if arm is not None and "ArmState" in arm:
        t = np.asarray(arm["TimeUS"], dtype=float) * 1e-6
        state = (np.asarray(arm["ArmState"]) != 0).astype(float)
        return StepSignal(t, state, before=1.0 - state[0])
    ev = _decode(df, "EV")
    if ev is not None and "Id" in ev:
        sel = np.isin(ev["Id"], (EV_ARMED, EV_DISARMED))
        if sel.any():
            t = np.asarray(ev["TimeUS"][sel], dtype=float) * 1e-6
            state = (ev["Id"][sel] == EV_ARMED).astype(float)
            return StepSignal(t, state, before=1.0 - state[0])
    return None


def _mag_sample_times(cols: dict[str, np.ndarray]) -> np.ndarray:
    """µs time of each MAG sample: S (publish time, uint32 µs) unwrapped against TimeUS when
    it is plausible, else TimeUS."""
    time_us = np.asarray(cols["TimeUS"], dtype=np.int64)
    if "S" not in cols:
        return time_us
    s = np.asarray(cols["S"], dtype=np.int64)
    lag = (time_us - s) % (1 << 32)
    ok = (s != 0) & (lag <= MAX_PUBLISH_LAG_US)
    return np.where(ok, time_us - lag, time_us)


def read(path: str, compass: int = 1, imu: int = 1, progress: Progress | None = None) -> LogStreams:
    """Read an ArduPilot DataFlash ``.bin`` log.

    compass, imu : 1-based instance numbers (MAG ``I`` + 1, IMU ``I`` + 1)
    progress     : called with the fraction of the file indexed (0–1)
    """
    name = os.path.basename(path)

    def indexed(pct: float) -> None:
        if progress is not None:
            progress(min(1.0, pct / 100.0))

    try:
        df = _Index(path, progress_callback=indexed)
    except OSError:
        raise  # the CLI reports file-system errors with the path
    except Exception as exc:  # DFReader raises bare Exception on unknown formats
        raise LogImportError(
            f"{name}: not a readable DataFlash log ({exc}); is it an ArduPilot .bin file?"
        ) from exc
    try:
        if not df.name_to_id:
            raise LogImportError(f"{name}: no DataFlash messages found; is it an ArduPilot .bin?")
        imus = _instances(df, "IMU")
        mags = _instances(df, "MAG")
        params = _params(df)
        armed = _armed(df)
    finally:
        df.close()

    missing = []
    if imu not in imus:
        missing.append(
            f"no IMU messages for IMU {imu} (found IMUs {instances_text(imus)})"
            if imus
            else "no IMU messages (enable IMU in LOG_BITMASK)"
        )
    if compass not in mags:
        missing.append(
            f"no MAG messages for compass {compass} (found compasses {instances_text(mags)})"
            if mags
            else "no MAG messages (enable COMPASS in LOG_BITMASK)"
        )
    if params is None:
        missing.append("no PARM messages")
    if missing:
        raise LogImportError(f"{name} has {' and '.join(missing)}; {NEEDS}")
    assert params is not None

    icol = imus[imu]
    t_imu, gyr, acc = strictly_increasing(
        np.asarray(icol["TimeUS"], dtype=float) * 1e-6,
        _vec(icol, "GyrX", "GyrY", "GyrZ"),
        _vec(icol, "AccX", "AccY", "AccZ"),
    )
    imu_stream = ImuStream(t_imu, gyr, acc, imu, f"IMU[{imu - 1}]")

    mcol = mags[compass]
    keep = np.ones(mcol["TimeUS"].shape[0], dtype=bool)
    notes = []
    if "Health" in mcol:
        unhealthy = mcol["Health"] == 0
        keep &= ~unhealthy
        if unhealthy.any():
            notes.append(f"{int(unhealthy.sum())} MAG sample(s) marked unhealthy were dropped")
    t_us = _mag_sample_times(mcol)
    field = untruncate(_vec(mcol, "MagX", "MagY", "MagZ"))
    motor = None
    for names in (("MOX", "MOY", "MOZ"), ("MOfsX", "MOfsY", "MOfsZ")):
        if all(n in mcol for n in names):
            motor = untruncate(_vec(mcol, *names))
    offsets = _vec(mcol, "OfsX", "OfsY", "OfsZ") if "OfsX" in mcol else None
    # The field of one sensor reading is logged at every compass read until the next
    # arrives: the same S twice is the same sample.
    arrays = [field] + [a for a in (motor, offsets) if a is not None]
    t_mag, *arrays = strictly_increasing(t_us[keep] * 1e-6, *(a[keep] for a in arrays))
    field = arrays.pop(0)
    motor = arrays.pop(0) if motor is not None else None
    offsets = arrays.pop(0) if offsets is not None else None
    undone = undo_ardupilot(name, t_mag, field, params, compass, motor, offsets)
    mag_stream = MagStream(
        t=t_mag[undone.keep],
        mag=undone.mag,
        instance=compass,
        unit=vehicle.MAG_UNIT[vehicle.ARDUPILOT],
        frame=ardupilot_frame(motor is not None),
        source=f"MAG[{compass - 1}]",
        suspect=undone.suspect,
        suspect_reason=undone.suspect_reason,
    )
    return LogStreams(
        path=path,
        log_format="DataFlash",
        autopilot=vehicle.ARDUPILOT,
        imu=imu_stream,
        mag=mag_stream,
        params=params,
        param_names=ardupilot_recorded(undone.param_compass, undone.naming, params.names()),
        param_compass=undone.param_compass,
        naming=undone.naming,
        armed=armed,
        notes=tuple(notes) + undone.notes,
    )
