"""Import autopilot flight logs as magcal sessions (``magcal import LOG -o session.csv``).

- :mod:`~magcal.logs.dataflash`: ArduPilot DataFlash ``.bin`` (IMU, MAG, PARM);
- :mod:`~magcal.logs.tlog`: MAVLink telemetry ``.tlog`` from either autopilot;
- :mod:`~magcal.logs.ulog`: PX4 ``.ulg`` (pyulog);
- :mod:`~magcal.logs.correction`: the on-board compass correction undone with the
  parameters in force at each sample;
- :mod:`~magcal.logs.stretch`: where the vehicle was turned by hand (pure function);
- :mod:`~magcal.logs.convert`: pairing magnetometer and IMU samples, the session and its
  metadata.

:func:`import_log` runs them in that order.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from magcal.io.session import Session, os_error_advice
from magcal.logs.convert import Rows, cut, pair, to_session
from magcal.logs.streams import LogImportError, LogStreams
from magcal.logs.stretch import Stretch, StretchConfig, explain_none, find_hand_rotation

__all__ = ["ImportOptions", "ImportResult", "LogImportError", "import_log", "read_log"]

Progress = Callable[[float], None]

ULOG_MAGIC = b"ULog\x01\x12\x35"
DATAFLASH_MAGIC = b"\xa3\x95"
#: MAVLink 1 and 2 start-of-frame bytes, after a tlog's 8-byte timestamp.
MAVLINK_STX = (0xFE, 0xFD)
FORMATS = ("dataflash", "tlog", "ulog")


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
    """

    session: Session
    streams: LogStreams
    rows: Rows
    start_s: float
    end_s: float
    stretch: Stretch | None
    others: tuple[Stretch, ...]


def sniff_format(path: str) -> str:
    """ "dataflash", "tlog" or "ulog", from the first bytes (the extension when unclear)."""
    name = os.path.basename(path)
    try:
        with open(path, "rb") as f:
            head = f.read(16)
    except OSError as exc:
        raise LogImportError(
            f"reading log {path}: {os_error_advice(exc, path, writing=False)}"
        ) from exc
    if head.startswith(ULOG_MAGIC):
        return "ulog"
    if head.startswith(DATAFLASH_MAGIC):
        return "dataflash"
    if len(head) > 8 and head[8] in MAVLINK_STX:
        return "tlog"
    ext = os.path.splitext(name)[1].lower()
    by_ext = {".bin": "dataflash", ".tlog": "tlog", ".ulg": "ulog"}
    if ext in by_ext and head:
        return by_ext[ext]
    raise LogImportError(
        f"{name}: not a log magcal can read ({'empty' if not head else 'unknown content'}); "
        "give an ArduPilot DataFlash .bin, a MAVLink .tlog or a PX4 .ulg file"
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
    if options.start_s is not None or options.end_s is not None:
        start = -np.inf if options.start_s is None else options.start_s
        end = np.inf if options.end_s is None else options.end_s
        if start >= end:
            raise LogImportError(f"--start {start:g} s is not before --end {end:g} s")
        sel = cut(rows, start, end, streams)
        stretch, others = None, ()
    else:
        armed = streams.armed.at(rows.t) > 0.5 if streams.armed is not None else None
        throttle = streams.throttle.at(rows.t) if streams.throttle is not None else None
        inputs = (rows.t, rows.gyr, rows.acc, armed, throttle, rows.gap | rows.suspect)
        found = find_hand_rotation(*inputs, config=options.stretch)
        if not found:
            raise LogImportError(
                f"{os.path.basename(path)}: no stretch where the vehicle was turned by hand: "
                f"{explain_none(*inputs, config=options.stretch)}; pass --start and --end "
                "(log time, s) to choose the range"
            )
        stretch, others = found[0], tuple(found[1:])
        sel = cut(rows, stretch.from_s, stretch.to_s, streams)
    session = to_session(streams, rows, sel)
    return ImportResult(
        session=session,
        streams=streams,
        rows=rows,
        start_s=float(session.t[0]),
        end_s=float(session.t[-1]),
        stretch=stretch,
        others=others,
    )
