# SPDX-License-Identifier: Apache-2.0
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

**Layouts.** Every log defines its messages (FMT: name, format, column names), and since
about 2017 their units and multipliers (FMTU, with UNIT and MULT): fields are found by
name, and where FMTU gives a unit the value is scaled by its multiplier (the IMU must then
be in rad/s and m/s², the compass in gauss: anything else is refused as an unknown kind of
log). Older logs say no units; theirs are the ones ArduPilot has always logged (rad/s, m/s²,
mG). Time is the column FMTU marks as seconds, else ``TimeUS`` (µs), else ``TimeMS`` (ms,
logs before 2015). Messages without a time column (PARM, EV before 2015) are placed at the
time of the IMU message before them in the file. Firmware without COMPASS_DIA/ODI (older
ArduPilot, as in logs of 2014) corrected the compass with its offsets alone: the log holds
every parameter, so their absence means that, and the session says so
(``onboard_soft_iron``).

The file is indexed by pymavlink's ``DFReader_binary`` (which finds every message of a type
without parsing the others, with its C indexer when built); the few types needed are then
decoded with numpy from that index, not one Python object per message, so a 100 MB log
takes seconds. DFReader's clock pass is skipped: it reads the whole log message by message,
without progress, when no GPS has a fix (a calibration indoors), and magcal uses the
messages' own times. What the C indexer prints about bytes that are no message is kept off
the terminal, and the bytes are counted: a file that is mostly such bytes is not a DataFlash
log.
"""

from __future__ import annotations

import contextlib
import os
import sys
from collections.abc import Callable, Iterator

import numpy as np
from pymavlink import DFReader

from magcal.autopilot import vehicle
from magcal.logs.convert import IMU_GAP_FACTOR
from magcal.logs.correction import (
    Undone,
    ardupilot_frame,
    ardupilot_recorded,
    flight_recorded_ardupilot,
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
#: FMTU multiplier ids (AP_Logger/LogStructure.h); a log's MULT messages override them.
_MULTIPLIERS = {
    "-": 0.0,
    "?": None,
    "2": 1e2,
    "1": 1.0,
    "0": 1.0,
    "A": 1e-1,
    "B": 1e-2,
    "C": 1e-3,
    "D": 1e-4,
    "E": 1e-5,
    "F": 1e-6,
    "G": 1e-7,
    "I": 1e-9,
    "!": 3.6,
    "/": 3600.0,
}
#: Time columns by name, for logs without FMTU: (column, s per count).
TIME_COLUMNS = (("TimeUS", 1e-6), ("TimeMS", 1e-3))
#: An IMU gap shorter than this is no logging pause, s.
PAUSE_MIN_S = 1.0
#: Bytes after the last message that are no damage (a log written in 256-byte pages, and
#: DFReader's own allowance).
TRAILER_BYTES = 528
PAUSE_CAUSE = "a logging pause: nothing at all was logged"
#: Above this fraction of skipped bytes the file is not a DataFlash log.
BAD_FRACTION = 0.5
#: EV ids (AP_Logger LogEvent): ARMED = 10, DISARMED = 11, LAND_COMPLETE = 18,
#: NOT_LANDED = 28.
EV_ARMED, EV_DISARMED, EV_LAND_COMPLETE, EV_NOT_LANDED = 10, 11, 18, 28
#: GPS time: the GPS epoch (1980-01-06) in Unix seconds, a week, and GPS − UTC (leap
#: seconds since 2017; only the date is taken from it).
GPS_EPOCH_UNIX_S, WEEK_S, GPS_UTC_LEAP_S = 315964800.0, 604800.0, 18.0
#: A MAG sample is published at most this long before it is logged; beyond, S is not used.
MAX_PUBLISH_LAG_US = 1_000_000
NEEDS = "needs IMU, MAG and PARM messages"


class _Index(DFReader.DFReader_binary):
    """DFReader's index of a binary log, without its clock pass (see the module docstring)."""

    def init_clock(self) -> None:
        self.clock = None


def _decode(df: _Index, name: str) -> dict[str, np.ndarray] | None:
    """Every message ``name`` as column arrays (multipliers of c/C/e/E/L applied), or None.

    The key ``OFFSET`` holds each message's byte offset in the file (its place in the log,
    for messages without a time column)."""
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
            f"{os.path.basename(df.filehandle.name)}: message {name} is defined with {size} "
            f"bytes but its format {fmt.format!r} has {dtype.itemsize}: the log is damaged or "
            "of an unknown kind"
        )
    data = df.data_map
    end = len(data)
    offsets = [o for o in df.offsets[mtype] if o + 3 + size <= end]
    body = b"".join(data[o + 3 : o + 3 + size] for o in offsets)
    rec = np.frombuffer(body, dtype=dtype)
    out = {"OFFSET": np.asarray(offsets, dtype=np.int64)}
    for col, code in zip(fmt.columns, fmt.format, strict=False):
        mult = DFReader.FORMAT_TO_STRUCT[code][1]
        v = rec[col]
        out[col] = v * mult if mult is not None else v
    return out


def _text(values: np.ndarray) -> list[str]:
    """Fixed-width byte strings (DataFlash n/N/Z) as text."""
    return [bytes(v).split(b"\0", 1)[0].decode("ascii", "replace") for v in values]


def _units(df: _Index) -> dict[str, dict[str, tuple[str, float | None]]]:
    """message → column → (unit id, multiplier) from the FMTU messages (with MULT's
    multipliers where the log defines them); empty for logs without FMTU (before ~2017)."""
    fmtu = _decode(df, "FMTU")
    if fmtu is None or "FmtType" not in fmtu:
        return {}
    mults = dict(_MULTIPLIERS)
    mult = _decode(df, "MULT")
    if mult is not None and "Id" in mult and "Mult" in mult:
        for i, m in zip(mult["Id"], mult["Mult"], strict=True):
            # MULT holds a float32 (1e-6 as 9.99999997e-07): its shortest decimal is the
            # multiplier meant, and keeps µs times exact (an IMU and a MAG message of the
            # same TimeUS then have the same time)
            mults[chr(int(i))] = float(str(np.float32(m)))
    out: dict[str, dict[str, tuple[str, float | None]]] = {}
    for ftype, unit_ids, mult_ids in zip(
        fmtu["FmtType"], _text(fmtu["UnitIds"]), _text(fmtu["MultIds"]), strict=True
    ):
        fmt = df.formats.get(int(ftype))
        if fmt is None:
            continue
        out[fmt.name] = {
            col: (u, mults.get(m))
            for col, u, m in zip(fmt.columns, unit_ids, mult_ids, strict=False)
        }
    return out


def _time_column(
    cols: dict[str, np.ndarray], units: dict[str, tuple[str, float | None]]
) -> np.ndarray | None:
    """The message's time in s: the column FMTU gives unit ``s``, else TimeUS (µs since
    boot) or TimeMS (ms, before 2015); None for an untimed message (PARM, EV, MSG before
    2015)."""
    for col, (unit, mult) in units.items():
        if unit == "s" and col in cols and mult:
            return np.asarray(cols[col], dtype=float) * mult
    for col, scale in TIME_COLUMNS:
        if col in cols:
            return np.asarray(cols[col], dtype=float) * scale
    return None


def _si(
    name: str,
    cols: dict[str, np.ndarray],
    units: dict[str, tuple[str, float | None]],
    names: tuple[str, ...],
    unit: str,
    scale: float,
    source: str,
) -> np.ndarray:
    """(N, 3) columns ``names`` in the unit ``scale`` × SI: the FMTU multiplier when the log
    declares one (the unit id must be ``unit``), else the historical unit (scale 1)."""
    v = np.column_stack([np.asarray(cols[n], dtype=float) for n in names])
    declared = units.get(names[0])
    if declared is None or declared[0] in ("-", "?", "\0", ""):
        return v
    uid, mult = declared
    if uid != unit:
        raise LogImportError(
            f"{name}: its FMTU gives {source} {names[0]} the unit {uid!r}, not {unit!r} as "
            "ArduPilot has always logged it; the log is of an unknown kind"
        )
    if mult is None or mult == 0:
        return v  # '-' or '?': no multiplier
    return v * (mult / scale)


def _placed(offsets: np.ndarray, ref_offsets: np.ndarray, ref_t: np.ndarray) -> np.ndarray:
    """Times for untimed messages: that of the last timed message before each in the file
    (the first one's for those before any)."""
    i = np.searchsorted(ref_offsets, offsets, side="right") - 1
    return ref_t[np.clip(i, 0, ref_t.size - 1)]


class _Clock:
    """Times of the log's messages, untimed ones placed by their position in the file."""

    def __init__(self, units: dict[str, dict[str, tuple[str, float | None]]]) -> None:
        self.units = units
        self.ref_offsets = np.zeros(0, dtype=np.int64)
        self.ref_t = np.zeros(0)

    def reference(self, cols: dict[str, np.ndarray], name: str) -> None:
        """Use the timed message ``name`` (the IMU: the most frequent) to place the others."""
        t = _time_column(cols, self.units.get(name, {}))
        if t is not None and t.size and self.ref_t.size == 0:
            self.ref_offsets, self.ref_t = cols["OFFSET"], t

    def times(self, cols: dict[str, np.ndarray], name: str) -> np.ndarray:
        t = _time_column(cols, self.units.get(name, {}))
        if t is not None:
            return t
        if self.ref_t.size == 0:
            return np.zeros(cols["OFFSET"].size)
        return _placed(cols["OFFSET"], self.ref_offsets, self.ref_t)


def _instances(df: _Index, base: str) -> dict[int, tuple[str, dict[str, np.ndarray]]]:
    """1-based instance → (message name, columns), from ``base`` with an ``I`` column
    (ArduPilot 4.0 on) or BASE, BASE2, BASE3 (before)."""
    out: dict[int, tuple[str, dict[str, np.ndarray]]] = {}
    cols = _decode(df, base)
    if cols is not None and "I" in cols:
        for i in np.unique(cols["I"]):
            sel = cols["I"] == i
            out[int(i) + 1] = (base, {k: v[sel] for k, v in cols.items()})
        return out
    if cols is not None:
        out[1] = (base, cols)
    for k in (2, 3):
        more = _decode(df, f"{base}{k}")
        if more is not None:
            out[k] = (f"{base}{k}", more)
    return out


def _params(df: _Index, clock: _Clock) -> ParamTimeline | None:
    """PARM records; without a time column (before 2015) each is placed at the time of the
    IMU message before it in the file."""
    cols = _decode(df, "PARM")
    if cols is None:
        return None
    names = _text(cols["Name"])
    t = clock.times(cols, "PARM")
    values = np.asarray(cols["Value"], dtype=float)
    return ParamTimeline.from_records(list(zip(t.tolist(), names, values.tolist(), strict=True)))


def _armed(df: _Index, clock: _Clock) -> StepSignal | None:
    arm = _decode(df, "ARM")
    if arm is not None and "ArmState" in arm:
        t = clock.times(arm, "ARM")
        state = (np.asarray(arm["ArmState"]) != 0).astype(float)
        return StepSignal(t, state, before=1.0 - state[0])
    ev = _decode(df, "EV")
    if ev is not None and "Id" in ev:
        sel = np.isin(ev["Id"], (EV_ARMED, EV_DISARMED))
        if sel.any():
            t = clock.times(ev, "EV")[sel]
            state = (ev["Id"][sel] == EV_ARMED).astype(float)
            return StepSignal(t, state, before=1.0 - state[0])
    return None


def _airborne(df: _Index, clock: _Clock) -> StepSignal | None:
    """The land detector's state from EV (NOT_LANDED: in the air; LAND_COMPLETE, DISARMED:
    on the ground); None when the log has no NOT_LANDED event (the detector never said)."""
    ev = _decode(df, "EV")
    if ev is None or "Id" not in ev or not (ev["Id"] == EV_NOT_LANDED).any():
        return None
    sel = np.isin(ev["Id"], (EV_NOT_LANDED, EV_LAND_COMPLETE, EV_DISARMED))
    t = clock.times(ev, "EV")[sel]
    return StepSignal(t, (ev["Id"][sel] == EV_NOT_LANDED).astype(float), before=0.0)


def _first_instance(cols: dict[str, np.ndarray], column: str) -> dict[str, np.ndarray]:
    """The rows of instance 0 of a message with an instance column (all rows without)."""
    if column not in cols:
        return cols
    sel = cols[column] == 0
    return {k: v[sel] for k, v in cols.items()}


def _gnss(name: str, df: _Index, clock: _Clock) -> GnssStream | None:
    """The first GNSS receiver (GPS instance 0; GPS before ArduPilot 4.0): fix, position,
    velocity (Spd along GCrs, VZ down) and GPS time (GWk/GMS; Week/TimeMS before 2015, when
    the log time was T)."""
    cols = _decode(df, "GPS")
    if cols is None or not {"Status", "Lat", "Lng", "Alt", "Spd", "GCrs"} <= set(cols):
        return None
    cols = _first_instance(cols, "I")
    if "GMS" in cols:
        t = clock.times(cols, "GPS")
        week, week_ms = cols.get("GWk"), cols["GMS"]
    elif "T" in cols and "Week" in cols and "TimeMS" in cols:
        t = np.asarray(cols["T"], dtype=float) * 1e-3
        week, week_ms = cols["Week"], cols["TimeMS"]
    else:
        return None
    if t.size == 0:
        return None
    speed = np.asarray(cols["Spd"], dtype=float)
    course = np.deg2rad(np.asarray(cols["GCrs"], dtype=float))
    down = np.asarray(cols["VZ"], dtype=float) if "VZ" in cols else np.full(t.size, np.nan)
    vel = np.column_stack([speed * np.cos(course), speed * np.sin(course), down])
    utc = np.full(t.size, np.nan)
    if week is not None:
        week = np.asarray(week, dtype=float)
        ok = week > 0
        utc[ok] = (
            GPS_EPOCH_UNIX_S + week[ok] * WEEK_S + np.asarray(week_ms, float)[ok] * 1e-3
        ) - GPS_UTC_LEAP_S
    fix = np.asarray(cols["Status"], dtype=int)
    lat, lon = np.asarray(cols["Lat"], float), np.asarray(cols["Lng"], float)
    alt = np.asarray(cols["Alt"], float)
    t, fix, lat, lon, alt, vel, utc = strictly_increasing(t, fix, lat, lon, alt, vel, utc)
    return GnssStream(t, fix, lat, lon, alt, vel, utc, "GPS[0]" if "I" in cols else "GPS")


def _current(df: _Index, clock: _Clock) -> StepSignal | None:
    """Battery 0's current, A: BAT.Curr (ArduPilot 3.6 on), else CURR.Curr (centiamperes)."""
    bat = _decode(df, "BAT")
    if bat is not None and "Curr" in bat:
        bat = _first_instance(bat, "Inst" if "Inst" in bat else "Instance")
        t = clock.times(bat, "BAT")
        return StepSignal(t, np.asarray(bat["Curr"], dtype=float)) if t.size else None
    curr = _decode(df, "CURR")
    if curr is not None and "Curr" in curr:
        t = clock.times(curr, "CURR")
        return StepSignal(t, np.asarray(curr["Curr"], dtype=float) / 100.0) if t.size else None
    return None


def _throttle(df: _Index, clock: _Clock) -> StepSignal | None:
    """The throttle output, 0–1: CTUN.ThO (Copter 0–1; Plane percent), or CTUN.ThrOut of
    older firmware (Copter 0–1000)."""
    cols = _decode(df, "CTUN")
    if cols is None:
        return None
    for column, scales in (("ThO", (1.0, 100.0)), ("ThrOut", (100.0, 1000.0))):
        if column in cols:
            v = np.asarray(cols[column], dtype=float)
            t = clock.times(cols, "CTUN")
            if not t.size:
                return None
            # the larger scale when the values exceed the smaller one's full range
            scale = scales[1] if np.nanmax(np.abs(v)) > 1.5 * scales[0] else scales[0]
            return StepSignal(t, np.clip(v / scale, 0.0, 1.0))
    return None


def _mag_sample_times(cols: dict[str, np.ndarray], t_log: np.ndarray) -> np.ndarray:
    """s: time of each MAG sample: S (publish time, uint32 µs) unwrapped against the log
    time when it is plausible, else the log time (and always for logs without S)."""
    if "S" not in cols:
        return t_log
    time_us = np.round(t_log * 1e6).astype(np.int64)
    s = np.asarray(cols["S"], dtype=np.int64)
    lag = (time_us - s) % (1 << 32)
    ok = (s != 0) & (lag <= MAX_PUBLISH_LAG_US)
    return np.where(ok, time_us - lag, time_us) * 1e-6


def _pauses(df: _Index, clock: _Clock, t_imu: np.ndarray) -> tuple[tuple[float, float, str], ...]:
    """Where the IMU is missing for long and no other timed message was logged either:
    logging stopped (ArduPilot pauses its log while disarmed unless LOG_DISARMED is set)."""
    dt = np.diff(t_imu)
    if dt.size == 0:
        return ()
    long = np.flatnonzero(dt > max(PAUSE_MIN_S, IMU_GAP_FACTOR * float(np.median(dt))))
    if long.size == 0:
        return ()
    others = []
    for name in ("GPS", "BARO", "ATT", "CTUN", "NTUN", "CURR", "RCIN", "PM"):
        cols = _decode(df, name)
        if cols is not None:
            t = _time_column(cols, clock.units.get(name, {}))
            if t is not None:
                others.append(t)
    seen = np.sort(np.concatenate(others)) if others else np.zeros(0)
    out = []
    for g in long:
        a, b = float(t_imu[g]), float(t_imu[g + 1])
        inside = np.searchsorted(seen, b, "left") - np.searchsorted(seen, a, "right")
        if inside == 0:
            out.append((a, b, PAUSE_CAUSE))
    return tuple(out)


def _flush_python_output() -> None:
    # Python's buffered text must reach the file descriptor it was written for, before
    # descriptors 1 and 2 are moved
    for s in (sys.stdout, sys.stderr):
        with contextlib.suppress(Exception):
            s.flush()


class _NativeOutput:
    """Inside :func:`_quiet_native_output`: a way through for the progress bar."""

    def __init__(self, saved: dict[int, int], null: int) -> None:
        self._saved = saved
        self._null = null

    def through(self, fn: Callable[..., None]) -> Callable[..., None]:
        """``fn`` with the real stdout and stderr back while it runs (a progress bar)."""

        def call(*args) -> None:
            _flush_python_output()
            for fd, copy in self._saved.items():
                os.dup2(copy, fd)
            try:
                fn(*args)
                _flush_python_output()
            finally:
                for fd in self._saved:
                    os.dup2(self._null, fd)

        return call


@contextlib.contextmanager
def _quiet_native_output() -> Iterator[_NativeOutput]:
    """Discard what native code prints on the process's stdout and stderr (file descriptors
    1 and 2, which ``contextlib.redirect_stderr`` does not reach)."""
    _flush_python_output()
    saved = {fd: os.dup(fd) for fd in (1, 2)}
    null = os.open(os.devnull, os.O_WRONLY)
    try:
        for fd in saved:
            os.dup2(null, fd)
        yield _NativeOutput(saved, null)
    finally:
        _flush_python_output()
        for fd, copy in saved.items():
            os.dup2(copy, fd)
            os.close(copy)
        os.close(null)


def _open(path: str, progress: Progress | None) -> tuple[_Index, int]:
    """DFReader's index of the file, and how many of its bytes are not DataFlash messages
    (what its C indexer prints about them is discarded)."""
    with _quiet_native_output() as native:

        def indexed(pct: float) -> None:
            if progress is not None:
                progress(min(1.0, pct / 100.0))

        try:
            df = _Index(path, progress_callback=native.through(indexed))
        except OSError:
            raise  # the CLI reports file-system errors with the path
        except Exception as exc:  # DFReader raises bare Exception on unknown formats
            raise LogImportError(
                f"{os.path.basename(path)}: not a readable DataFlash log ({exc}); is it an "
                "ArduPilot .bin file?"
            ) from exc
    covered = sum(
        len(offsets) * df.formats[t].len
        for t, offsets in enumerate(df.offsets)
        if offsets and t in df.formats
    )
    return df, max(0, df.data_len - covered)


def read(path: str, compass: int = 1, imu: int = 1, progress: Progress | None = None) -> LogStreams:
    """Read an ArduPilot DataFlash ``.bin`` log, of any ArduPilot version (see the module
    docstring).

    compass, imu : 1-based instance numbers (MAG ``I`` + 1 or MAG, MAG2, MAG3; IMU likewise)
    progress     : called with the fraction of the file indexed (0–1)
    """
    name = os.path.basename(path)
    df, skipped = _open(path, progress)
    try:
        size = max(1, df.data_len)
        if not df.name_to_id or skipped > BAD_FRACTION * size:
            raise LogImportError(
                f"{name}: not a DataFlash log: {100 * skipped / size:.0f} % of its bytes are not "
                "DataFlash messages (an ArduPilot .bin starts with FMT messages and holds "
                "nothing else)"
            )
        clock = _Clock(_units(df))
        imus = _instances(df, "IMU")
        mags = _instances(df, "MAG")
        if imus:
            ref_name, ref = imus[min(imus)]
            clock.reference(ref, ref_name)
        params = _params(df, clock)
        armed = _armed(df, clock)
        airborne = _airborne(df, clock)
        gnss = _gnss(name, df, clock)
        current, throttle = _current(df, clock), _throttle(df, clock)
        t_imu_all = clock.times(imus[imu][1], imus[imu][0]) if imu in imus else np.zeros(0)
        pauses = _pauses(df, clock, np.sort(t_imu_all))
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
    units = clock.units
    notes = []
    if skipped > TRAILER_BYTES:
        notes.append(f"{skipped} byte(s) of the log that are not DataFlash messages were skipped")

    imu_name, icol = imus[imu]
    u = units.get(imu_name, {})
    t_imu, gyr, acc = strictly_increasing(
        t_imu_all,
        _si(name, icol, u, ("GyrX", "GyrY", "GyrZ"), "E", 1.0, imu_name),
        _si(name, icol, u, ("AccX", "AccY", "AccZ"), "o", 1.0, imu_name),
    )
    imu_stream = ImuStream(t_imu, gyr, acc, imu, f"IMU[{imu - 1}]" if "I" in icol else imu_name)

    mag_stream, mag_notes, undone = _mag_stream(name, mags, compass, units, clock, params)
    notes += mag_notes
    others, other_names = [], []
    for k in sorted(mags):
        if k == compass:
            continue
        try:
            other, other_notes, other_undone = _mag_stream(name, mags, k, units, clock, params)
        except LogImportError as exc:
            notes.append(f"compass {k} left out of the flight columns: {exc}")
            continue
        others.append(other)
        notes += other_notes
        other_names += flight_recorded_ardupilot(
            other_undone.param_compass, other_undone.naming, params.names()
        )
    other_names += flight_recorded_ardupilot(undone.param_compass, undone.naming, params.names())
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
        throttle=throttle,
        other_mags=tuple(others),
        other_param_names=tuple(dict.fromkeys(other_names)),
        gnss=gnss,
        current=current,
        airborne=airborne,
        notes=tuple(notes),
        known_gaps=pauses,
        meta=undone.meta,
    )


def _mag_stream(
    name: str,
    mags: dict[int, tuple[str, dict[str, np.ndarray]]],
    compass: int,
    units: dict[str, dict[str, tuple[str, float | None]]],
    clock: _Clock,
    params: ParamTimeline,
) -> tuple[MagStream, list[str], Undone]:
    """Compass ``compass``'s samples with the correction in force undone, the notes about
    them and how it was undone."""
    notes = []
    mag_name, mcol = mags[compass]
    u = units.get(mag_name, {})
    keep = np.ones(mcol["MagX"].shape[0], dtype=bool)
    if "Health" in mcol:
        unhealthy = mcol["Health"] == 0
        keep &= ~unhealthy
        if unhealthy.all():
            raise LogImportError(
                f"{name}: all {unhealthy.size} {mag_name} samples of compass {compass} are marked "
                "unhealthy (Health = 0: the autopilot was not reading that compass)"
                + (
                    f"; choose another with --compass (found compasses {instances_text(mags)})"
                    if len(mags) > 1
                    else "; the log has no other compass"
                )
            )
        if unhealthy.any():
            notes.append(
                f"{int(unhealthy.sum())} MAG sample(s) of compass {compass} marked unhealthy "
                "were dropped"
            )
    t_mag = _mag_sample_times(mcol, clock.times(mcol, mag_name))
    field = untruncate(_si(name, mcol, u, ("MagX", "MagY", "MagZ"), "G", 1e-3, mag_name))
    motor = None
    for names in (("MOX", "MOY", "MOZ"), ("MOfsX", "MOfsY", "MOfsZ")):
        if all(n in mcol for n in names):
            motor = untruncate(_si(name, mcol, u, names, "G", 1e-3, mag_name))
    offsets = None
    if "OfsX" in mcol:
        offsets = _si(name, mcol, u, ("OfsX", "OfsY", "OfsZ"), "G", 1e-3, mag_name)
    # The field of one sensor reading is logged at every compass read until the next
    # arrives: the same S twice is the same sample.
    arrays = [field] + [a for a in (motor, offsets) if a is not None]
    t_mag, *arrays = strictly_increasing(t_mag[keep], *(a[keep] for a in arrays))
    field = arrays.pop(0)
    motor = arrays.pop(0) if motor is not None else None
    offsets = arrays.pop(0) if offsets is not None else None
    undone = undo_ardupilot(
        name, t_mag, field, params, compass, motor, offsets, params_complete=True
    )
    stream = MagStream(
        t=t_mag[undone.keep],
        mag=undone.mag,
        instance=compass,
        unit=vehicle.MAG_UNIT[vehicle.ARDUPILOT],
        frame=ardupilot_frame(motor is not None),
        source=mag_name if "I" not in mcol else f"MAG[{compass - 1}]",
        suspect=undone.suspect,
        suspect_reason=undone.suspect_reason,
    )
    return stream, notes + list(undone.notes), undone
