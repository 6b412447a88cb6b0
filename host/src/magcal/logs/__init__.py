# SPDX-License-Identifier: Apache-2.0
"""Import autopilot flight logs as magcal sessions (``magcal import LOG -o session.csv``).

- :mod:`~magcal.logs.dataflash`: ArduPilot DataFlash ``.bin`` (IMU, MAG, PARM);
- :mod:`~magcal.logs.tlog`: MAVLink telemetry ``.tlog`` from either autopilot;
- :mod:`~magcal.logs.ulog`: PX4 ``.ulg`` (pyulog);
- :mod:`~magcal.logs.correction`: the on-board compass correction undone with the
  parameters in force at each sample;
- :mod:`~magcal.logs.stretch`: where the vehicle was turned by hand (pure function);
- :mod:`~magcal.logs.convert`: pairing magnetometer and IMU samples, the session and its
  metadata;
- :mod:`~magcal.logs.flight`: a log without a hand rotation: its flight (armed, in the air,
  with GNSS) as a session with every compass, GNSS velocity, current and throttle.

:func:`import_log` runs them in that order, after :func:`sniff_format` has recognised the
format from the file's content (never from its name alone). A hand rotation is preferred to
a flight when the log holds both.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from magcal.io.session import Session, os_error_advice
from magcal.logs.convert import Rows, cut, pair, to_session
from magcal.logs.flight import Flight, find_flight, flight_session, in_flight
from magcal.logs.streams import LogImportError, LogStreams
from magcal.logs.stretch import Stretch, StretchConfig, explain_none, find_hand_rotation

__all__ = ["ImportOptions", "ImportResult", "LogImportError", "import_log", "read_log"]

Progress = Callable[[float], None]

ULOG_MAGIC = b"ULog\x01\x12\x35"
DATAFLASH_MAGIC = b"\xa3\x95"
#: The message type of FMT, with which every DataFlash log begins.
DATAFLASH_FMT = b"\x80"
#: Bytes read to recognise a format.
SNIFF_BYTES = 4096
#: tlog records that must parse in a row (one is enough in a file shorter than SNIFF_BYTES).
SNIFF_FRAMES = 2
#: MAVLink 1 and 2 start-of-frame bytes, after a tlog's 8-byte timestamp.
MAVLINK1_STX, MAVLINK2_STX = 0xFE, 0xFD
FORMATS = ("dataflash", "tlog", "ulog")
#: A --start/--end range in flight for more than this share of its time is a flight session.
FLIGHT_RANGE_SHARE = 0.5


@dataclass(frozen=True)
class ImportOptions:
    """What to import.

    compass, imu   : 1-based instance numbers
    start_s, end_s : log-time range (s) to import instead of the detected stretch; either
                     may be None (from the first / to the last sample)
    stretch        : the detector's thresholds
    """

    compass: int = 1
    imu: int = 1
    start_s: float | None = None
    end_s: float | None = None
    stretch: StretchConfig = StretchConfig()


@dataclass(frozen=True)
class ImportResult:
    """An imported session and how it was chosen.

    stretch : the detected hand rotation (None when --start/--end chose the range)
    others  : the other candidate stretches, best first
    flight  : the flight imported (a flight session), None for a hand rotation; with
              --start/--end a range mostly in flight gives a flight session whose flight
              is the range
    notes   : remarks on the range (e.g. gaps left out)
    """

    session: Session
    streams: LogStreams
    rows: Rows
    start_s: float
    end_s: float
    stretch: Stretch | None
    others: tuple[Stretch, ...]
    notes: tuple[str, ...] = ()
    flight: Flight | None = None


def _mavlink_frames(data: bytes) -> int:
    """How many consecutive tlog records (8-byte time, then a MAVLink 1 or 2 frame) parse
    from the start of ``data``, up to :data:`SNIFF_FRAMES`."""
    n = i = 0
    while n < SNIFF_FRAMES and i + 10 <= len(data):
        stx, length = data[i + 8], data[i + 9]
        if stx == MAVLINK1_STX:
            size = 6 + length + 2
        elif stx == MAVLINK2_STX:
            signed = data[i + 10] & 0x01 if i + 10 < len(data) else 0
            size = 10 + length + 2 + (13 if signed else 0)
        else:
            break
        if i + 8 + size > len(data):
            break
        n += 1
        i += 8 + size
    return n


def sniff_format(path: str) -> str:
    """ "dataflash", "tlog" or "ulog", from the file's content (never its name alone): the
    ULog magic; DataFlash messages, which start with an FMT message; consecutive
    time-stamped MAVLink frames. Anything else is refused."""
    name = os.path.basename(path)
    try:
        with open(path, "rb") as f:
            head = f.read(SNIFF_BYTES)
    except OSError as exc:
        raise LogImportError(
            f"reading log {path}: {os_error_advice(exc, path, writing=False)}"
        ) from exc
    if head.startswith(ULOG_MAGIC):
        return "ulog"
    if head.startswith(DATAFLASH_MAGIC + DATAFLASH_FMT):
        return "dataflash"
    frames = _mavlink_frames(head)
    if frames >= SNIFF_FRAMES or (frames >= 1 and len(head) < SNIFF_BYTES):
        return "tlog"
    what = "it is empty" if not head else "its content is none of these"
    claimed = {".bin": "a DataFlash log", ".tlog": "a telemetry log", ".ulg": "a ULog"}.get(
        os.path.splitext(name)[1].lower()
    )
    if head and claimed:
        what = f"named like {claimed}, but its first bytes are not those of one"
    raise LogImportError(
        f"{name}: not a log magcal can read ({what}); give an ArduPilot DataFlash .bin "
        "(starts with FMT messages), a MAVLink .tlog (time-stamped MAVLink frames) or a PX4 "
        ".ulg (starts with the ULog magic)"
    )


def read_log(
    path: str, compass: int = 1, imu: int = 1, progress: Progress | None = None
) -> LogStreams:
    """The streams of ``path``, whatever its format (see :func:`sniff_format`)."""
    kind = sniff_format(path)
    if kind == "dataflash":
        from magcal.logs import dataflash as reader
    elif kind == "tlog":
        from magcal.logs import tlog as reader
    else:
        from magcal.logs import ulog as reader
    return reader.read(path, compass=compass, imu=imu, progress=progress)


def import_log(
    path: str, options: ImportOptions = ImportOptions(), progress: Progress | None = None
) -> ImportResult:
    """Read ``path``, pair its sensors, choose the range and build the session."""
    streams = read_log(path, options.compass, options.imu, progress)
    rows = pair(streams.imu, streams.mag)
    flight = None
    if options.start_s is not None or options.end_s is not None:
        start = -np.inf if options.start_s is None else options.start_s
        end = np.inf if options.end_s is None else options.end_s
        if start >= end:
            raise LogImportError(f"--start {start:g} s is not before --end {end:g} s")
        sel, notes = cut(rows, start, end, streams)
        stretch, others = None, ()
        t = streams.imu.t
        t = t[(t >= rows.t[sel][0]) & (t <= rows.t[sel][-1])]
        flying, by = in_flight(streams, t)
        if flying.mean() > FLIGHT_RANGE_SHARE:
            flight = Flight(float(rows.t[sel][0]), float(rows.t[sel][-1]), by)
    else:
        armed = streams.armed.at(rows.t) > 0.5 if streams.armed is not None else None
        throttle = streams.throttle.at(rows.t) if streams.throttle is not None else None
        inputs = (rows.t, rows.gyr, rows.acc, armed, throttle, rows.gap | rows.suspect)
        found = find_hand_rotation(*inputs, config=options.stretch)
        if found:
            stretch, others = found[0], tuple(found[1:])
            sel, notes = cut(rows, stretch.from_s, stretch.to_s, streams)
        else:
            flight, missing = find_flight(streams)
            if flight is None:
                raise LogImportError(
                    f"{os.path.basename(path)}: no stretch where the vehicle was turned by "
                    f"hand: {explain_none(*inputs, config=options.stretch)}; and no flight to "
                    f"import: {missing}; pass --start and --end (log time, s) to choose the "
                    "range"
                )
            stretch, others = None, ()
            sel, notes = cut(rows, flight.start_s, flight.end_s, streams)
    if flight is not None:
        session = flight_session(streams, rows, sel, flight)
    else:
        session = to_session(streams, rows, sel)
    return ImportResult(
        session=session,
        streams=streams,
        rows=rows,
        start_s=float(session.t[0]),
        end_s=float(session.t[-1]),
        stretch=stretch,
        others=others,
        notes=notes,
        flight=flight,
    )
