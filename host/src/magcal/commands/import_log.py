# SPDX-License-Identifier: Apache-2.0
"""``magcal import LOG -o SESSION.csv``: a session from an ArduPilot or PX4 flight log.

Reads a DataFlash ``.bin``, a MAVLink ``.tlog`` or a PX4 ``.ulg``, undoes the autopilot's
compass correction, finds the stretch where the vehicle was turned by hand, or without one
the flight (or takes ``--start/--end``), and writes the session. Progress and the stretch
chosen go to stderr.
The log readers (pymavlink, pyulog) load when the command runs, not when the parser is built.
"""

from __future__ import annotations

import os
import sys

from magcal import ui
from magcal.commands.common import finite, positive

#: Progress lines when stderr is not a terminal: one per this many percent.
LOG_STEP_PCT = 25
#: Below this IMU rate the rotation between magnetometer samples rests on few gyro samples.
SLOW_IMU_HZ = 50.0


def add_parser(sub) -> None:
    p = sub.add_parser(
        "import",
        help="make a session from an ArduPilot .bin/.tlog or a PX4 .ulg flight log",
        description="Make a calibration session from a flight log: ArduPilot DataFlash .bin, "
        "MAVLink telemetry .tlog (ArduPilot or PX4) or PX4 .ulg. The autopilot's compass "
        "correction is undone with the parameters in force; the stretch where the vehicle was "
        "turned by hand is found from the gyroscope unless --start/--end give the range.",
        epilog="examples:\n"
        "  magcal import flight.bin -o session.csv\n"
        "  magcal import flight.tlog -o session.csv\n"
        "  magcal import log.ulg --compass 2 --start 120 --end 180 -o session.csv",
    )
    p.add_argument("log", help="the flight log (.bin, .tlog or .ulg)")
    p.add_argument("-o", "--output", required=True, help="session CSV to write")
    p.add_argument(
        "--compass",
        type=positive(int),
        default=1,
        metavar="N",
        help="magnetometer to import, 1 = the first (ArduPilot MAG instance 0, PX4 sensor_mag "
        "instance 0)",
    )
    p.add_argument(
        "--imu",
        type=positive(int),
        default=1,
        metavar="N",
        help="IMU to pair it with, 1 = the first",
    )
    p.add_argument("--start", type=finite, metavar="S", help="import from S seconds (log time)")
    p.add_argument("--end", type=finite, metavar="S", help="import up to S seconds (log time)")
    p.set_defaults(run=run)


def faster_imu_hint(streams) -> str:
    """How to log the IMU faster, for the log's autopilot and format."""
    from magcal.autopilot import vehicle

    if streams.log_format == "DataFlash":
        return "set the IMU_FAST bit of LOG_BITMASK"
    if streams.log_format == "tlog":
        rate = " (ArduPilot: SRn_RAW_SENS)" if streams.autopilot == vehicle.ARDUPILOT else ""
        return (
            f"telemetry carries it at the stream rate requested{rate}, and the autopilot's "
            "own log holds it faster"
        )
    return "choose SDLOG_PROFILE's high-rate sensor topics, or list them for the logger"


def flight_contents(session) -> str:
    """ "every compass (1,2,3), GNSS velocity, battery current and throttle": what a flight
    session holds (a signal the log lacks, or that is empty over the range, is not named)."""
    import numpy as np

    have = {name for name, v in session.extra.items() if not np.isnan(v).all()}
    parts = [f"every compass ({session.meta.get('compasses', '1')})"]
    parts += [
        what
        for what, column in (
            ("GNSS velocity", "vel_n"),
            ("battery current", "current"),
            ("throttle", "throttle"),
        )
        if column in have
    ]
    return ", ".join(parts[:-1]) + " and " + parts[-1] if len(parts) > 1 else parts[0]


def progress_printer(label: str, stream=None):
    """``show(fraction)`` of the log read, ``show.done()`` after it: a
    :class:`magcal.ui.ProgressBar` in percent; in a log ``label: 45 %`` every LOG_STEP_PCT %."""
    bar = ui.ProgressBar(
        label,
        100,
        stream,
        unit="%",
        log_step_pct=LOG_STEP_PCT,
        log_line=lambda done, total: f"{label}: {done} %",
    )

    def show(fraction: float) -> None:
        bar.update(int(100 * min(max(fraction, 0.0), 1.0)) if fraction == fraction else 0)

    show.done = bar.close  # type: ignore[attr-defined]
    return show


def run(args, out=None, err=None) -> int:
    from magcal.autopilot.vehicle import AUTOPILOT_NAMES
    from magcal.calib.diagnostics import observability
    from magcal.io.session import check_writable, write_session
    from magcal.logs import ImportOptions, import_log
    from magcal.logs.flight import describe as describe_flight
    from magcal.logs.stretch import describe

    out = out or sys.stdout
    err = err or sys.stderr
    check_writable(args.output, "writing session")
    options = ImportOptions(compass=args.compass, imu=args.imu, start_s=args.start, end_s=args.end)
    progress = progress_printer(f"reading {os.path.basename(args.log)}", err)
    try:
        result = import_log(args.log, options, progress)
    finally:
        progress.done()
    streams, rows = result.streams, result.rows
    who = AUTOPILOT_NAMES[streams.autopilot]
    print(
        f"{who} {streams.log_format} log: IMU {streams.imu.instance} at "
        f"{rows.imu_rate_hz:.1f} Hz, compass {streams.mag.instance} at {rows.mag_rate_hz:.1f} Hz "
        f"({streams.mag.unit}), {rows.t[0]:.1f}–{rows.t[-1]:.1f} s",
        file=err,
    )
    for note in streams.notes:
        print(f"note: {note}", file=err)
    if rows.imu_rate_hz < SLOW_IMU_HZ:
        print(
            f"note: the IMU is logged at only {rows.imu_rate_hz:.0f} Hz, so the rotation between "
            "magnetometer samples rests on few gyroscope samples; log the IMU faster for a better "
            f"calibration: {faster_imu_hint(streams)}",
            file=err,
        )
    for note in result.notes:
        print(f"note: {note}", file=err)
    if (
        result.flight is not None
        and result.stretch is None
        and args.start is None
        and args.end is None
    ):
        print(f"no hand rotation; found {describe_flight(result.flight)}", file=err)
        print(
            f"importing the flight, {result.start_s:.2f}–{result.end_s:.2f} s, with "
            f"{flight_contents(result.session)}; --start/--end choose another range",
            file=err,
        )
    elif result.stretch is None:
        kind = " (in flight: a flight session)" if result.flight is not None else ""
        print(
            f"range from --start/--end: {result.start_s:.2f}–{result.end_s:.2f} s{kind}",
            file=err,
        )
    else:
        print(f"found {describe(result.stretch)}", file=err)
        for other in result.others:
            print(f"  also {describe(other)}", file=err)
        print(
            f"importing {result.start_s:.2f}–{result.end_s:.2f} s (with rest around it); "
            "--start/--end choose another range",
            file=err,
        )
    session = result.session
    n_mag = int(session.has_mag.sum())
    if n_mag < observability.MIN_SAMPLES:
        print(
            f"warning: {n_mag} magnetometer samples; calibration needs at least "
            f"{observability.MIN_SAMPLES}: choose a longer range",
            file=err,
        )
    write_session(args.output, session)
    print(
        f"wrote {args.output} ({len(session)} rows: {int(session.has_acc.sum())} IMU and "
        f"{n_mag} magnetometer samples, {result.start_s:.2f}–{result.end_s:.2f} s log time)",
        file=out,
    )
    return 0
