# SPDX-License-Identifier: Apache-2.0
"""``magcal collect --port URL -o SESSION.csv``: record a calibration session from the device;
``--mavlink URL [--compass N]``: from an ArduPilot or PX4 autopilot
(:mod:`magcal.autopilot.collect`: the magnetometer in the autopilot's unit, mG or gauss, with
the on-board correction undone; the compass parameters in force in the metadata).

Stops at a coverage target of field directions (default 90 %), ``--duration`` or
``--max-samples``, whichever comes first, or Ctrl-C. Progress goes to stderr: one line
redrawn in place on a terminal (cut at its width; when the whole line does not fit, the
instruction comes first and the figures are cut), one line a second otherwise; it shows
the live estimate's norm spread and says when it is ok to stop. Whatever was collected is
written, also after Ctrl-C (exit 130) or an error mid-collection (exit 2, the file named).

``--view`` also shows the collection on a local page (:mod:`magcal.view`), opened in the
browser when there is one: the sphere of field directions with the cells still missing, the
same figures and instruction, and the readings before and after a fit once it has ended.

Each half loads what it needs when it runs, not when the parser is built (the device client
and the live estimate; the ``--mavlink`` half :mod:`magcal.autopilot` and pymavlink).
"""

from __future__ import annotations

import argparse
import sys
from typing import TYPE_CHECKING

from magcal.commands.common import (
    add_link_arguments,
    check_link_options,
    compass_params,
    open_device,
    positive,
)
from magcal.errors import MagcalError
from magcal.ui import EXIT_INTERRUPTED, StatusLine, print_wrapped, say

if TYPE_CHECKING:
    from magcal.device.collect import CollectProgress, CollectResult

DEFAULT_COVERAGE_PCT = 90.0
#: Progress lines per second when stderr is not a terminal (a log file).
LOG_LINES_PER_S = 1.0


def _coverage_arg(text: str) -> float | None:
    if text.strip().lower() in ("off", "none"):
        return None
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a percentage (or 'off')") from None
    if not 0.0 < v <= 100.0:
        raise argparse.ArgumentTypeError(f"{text} is outside (0, 100]")
    return v


def add_parser(sub) -> None:
    p = sub.add_parser(
        "collect",
        help="record a calibration session from the device",
        description="Record a calibration session from a device running magcal's firmware "
        "(--port) or from an ArduPilot or PX4 autopilot (--mavlink) while you turn it slowly "
        "through all orientations. Progress shows the field directions covered and says when "
        "it is enough to stop; it stops at the coverage target, --duration, "
        "--max-samples or Ctrl-C, and whatever was recorded is written.",
        epilog="examples:\n"
        "  magcal collect --port /dev/ttyACM0 -o session.csv\n"
        "  magcal collect --mavlink udpin:0.0.0.0:14550 --compass 2 --view -o session.csv\n"
        "  magcal collect --port /dev/ttyACM0 --duration 90 --coverage off -o session.csv",
    )
    add_link_arguments(p)
    p.add_argument("-o", "--output", required=True, help="session CSV to write")
    p.add_argument("--duration", type=positive(float), metavar="S", help="stop after S seconds")
    p.add_argument(
        "--coverage",
        type=_coverage_arg,
        default=DEFAULT_COVERAGE_PCT,
        metavar="PCT",
        help="stop once PCT %% of the field directions are covered (and the session is long "
        f"enough to calibrate); default {DEFAULT_COVERAGE_PCT:g}, 'off' to disable",
    )
    p.add_argument("--max-samples", type=positive(int), metavar="N", help="stop after N samples")
    p.add_argument(
        "--rate",
        type=positive(float),
        metavar="HZ",
        help="with --mavlink: the IMU message rate to ask for (default: 100 on a network link, "
        "what half a serial link's baud rate carries there)",
    )
    p.add_argument(
        "--view",
        action="store_true",
        help="also show the collection live on a local page (127.0.0.1, a free port, its "
        "address printed; opened in the browser when there is one): the sphere of field "
        "directions with the cells still missing, turnable with the mouse, what to do next, "
        "and the readings before and after a fit once collection ends",
    )
    p.set_defaults(run=run)


def progress_line(p: CollectProgress, columns: int | None = None) -> str:
    """The collect status: samples, rate, drops, coverage and the live estimate's hint.

    columns : the width the line will be cut at (None: never cut). When the whole line is
        wider and the report names its instruction, the instruction comes first, then the
        figures and the estimate's state: a narrow terminal cuts the figures, not what to do.
    """
    line = f"{p.figures()}  {p.hint}"
    if columns is None or len(line) <= columns or not p.instruction:
        return line
    parts = [p.instruction, " ".join(p.figures().split())]
    if p.live is not None and not p.live.ok_to_stop:
        parts.append(p.live.text())
    return "  ".join(parts)


def progress_printer(stream=None):
    """``show(progress)`` for the collection, ``show.done()`` after it (idempotent): a
    :class:`magcal.ui.StatusLine` redrawn in place on a terminal (cut at its width,
    :func:`progress_line`); in a log, LOG_LINES_PER_S whole lines of the collection's clock
    and always its last state."""
    status = StatusLine(stream, every_s=1.0 / LOG_LINES_PER_S, last=True)

    def show(p: CollectProgress) -> None:
        status.update(progress_line(p, status.columns()), p.elapsed_s)

    show.done = status.close  # type: ignore[attr-defined]
    return show


def write_collected(path: str, result: CollectResult, out) -> None:
    """Write the session and say what it holds."""
    from magcal.io.session import write_session

    write_session(path, result.session)
    print(
        f"wrote {path} ({result.samples} samples, {result.elapsed_s:.1f} s, dropped "
        f"{result.dropped}, coverage {100 * result.coverage.coverage:.1f} %)",
        file=out,
    )


def open_view(args, compass: str):
    """The live page for ``--view`` (None without it): served, its address said on stderr
    and opened in the browser when there is one."""
    if not getattr(args, "view", False):
        return None
    from magcal.view.collect import CollectView, open_in_browser

    view = CollectView([compass], title=f"magcal collect: {compass}")
    opened = open_in_browser(view.url)
    say(
        "collect",
        f"live view at {view.url}" + ("" if opened else " (open it in a browser on this machine)"),
    )
    return view


def reporter(progress, view):
    """The recorder's ``progress``: the terminal's printer, and the page's when there is one."""
    if view is None:
        return progress

    def report(p: CollectProgress) -> None:
        progress(p)
        view(p)

    return report


def collect_saving_partial(run_collect, path: str, progress) -> CollectResult:
    """``run_collect()``, the progress line ended however it stops. On a CollectError the
    samples received so far are written to ``path`` and the error names the file."""
    from magcal.device.collect import CollectError
    from magcal.io.session import write_session

    try:
        return run_collect()
    except CollectError as exc:
        progress.done()  # the message goes on its own line
        if exc.result.session is None:
            raise MagcalError(f"{exc}; no samples were received, nothing written") from exc
        write_session(path, exc.result.session)
        raise MagcalError(
            f"{exc}; the {exc.result.samples} samples collected were written to {path}"
        ) from exc
    finally:
        progress.done()


def finish_collect(
    args, result: CollectResult, min_samples: int, source: str, hint: str, out
) -> int:
    """Write a finished collection to ``args.output`` and return the exit code: interrupted
    (the partial session kept), too short, or below the coverage target (a warning).
    ``source`` and ``hint`` name the link and what to check when nothing arrived."""
    if result.session is None:
        raise MagcalError(f"collect {source}: no samples were received, nothing written; {hint}")
    write_collected(args.output, result, out)
    if result.interrupted:
        print(
            f"magcal collect: interrupted; the partial session is in {args.output}", file=sys.stderr
        )
        return EXIT_INTERRUPTED
    if result.samples < min_samples:
        raise MagcalError(
            f"collect: {args.output} has {result.samples} samples; calibration needs at least "
            f"{min_samples}: collect longer"
        )
    if args.coverage is not None and result.coverage.coverage < args.coverage / 100.0:
        print_wrapped(
            f"magcal collect: warning: coverage {100 * result.coverage.coverage:.1f} % is below "
            f"the target {args.coverage:g} % ({result.coverage.hint}); the calibration may be "
            "poorly determined: collect again with more rotation",
            sys.stderr,
        )
    return 0


def run(args, out=None) -> int:
    from magcal.calib.diagnostics import observability
    from magcal.device.collect import collect
    from magcal.io.session import check_writable

    check_link_options(args, ("rate",))
    if args.mavlink:
        return run_autopilot(args, out)
    out = out or sys.stdout
    if args.duration is None and args.coverage is None and args.max_samples is None:
        raise MagcalError("collect: --coverage off needs --duration or --max-samples")
    check_writable(args.output, "writing session")  # before collecting, not after
    min_samples = observability.MIN_SAMPLES
    progress = progress_printer()
    with open_device(args.port) as dev:
        info = dev.info
        say(
            "collect",
            f"device {args.port}: uid {info.uid_hex}, firmware {info.fw_version_str}, "
            f"{info.sample_rate_hz:g} Hz; recording: turn it slowly through all orientations",
        )
        view = open_view(args, f"magnetometer of device {info.uid_hex}")
        result = None
        try:
            result = collect_saving_partial(
                lambda: collect(
                    dev.client,
                    dev.info,
                    duration_s=args.duration,
                    coverage_target=None if args.coverage is None else args.coverage / 100.0,
                    max_samples=args.max_samples,
                    min_samples=min_samples,
                    progress=reporter(progress, view),
                ),
                args.output,
                progress,
            )
        finally:
            if view is not None:
                view.finish(result)
    return finish_collect(
        args, result, min_samples, f"on {args.port}", "check that the device is acquiring", out
    )


# ---------------------------------------------------------------- --mavlink: an autopilot


def run_autopilot(args, out=None) -> int:
    from magcal.autopilot.collect import collect as collect_from_autopilot
    from magcal.autopilot.connection import open_autopilot
    from magcal.calib.diagnostics import observability
    from magcal.io.session import check_writable

    out = out or sys.stdout
    if args.duration is None and args.coverage is None and args.max_samples is None:
        raise MagcalError("collect: --coverage off needs --duration or --max-samples")
    check_writable(args.output, "writing session")
    compass = args.compass or 1
    min_samples = observability.MIN_SAMPLES
    progress = progress_printer()
    with open_autopilot(args.mavlink) as ap:
        fw = ap.firmware()
        cp = compass_params(ap, compass)
        say(
            "collect",
            f"{ap.describe()}, firmware {fw or 'unknown'}; compass {compass} "
            f"({'external' if cp.external else 'internal'}), field in {cp.unit}",
        )
        view = open_view(args, f"compass {compass} ({'external' if cp.external else 'internal'})")
        result = None
        try:
            result = collect_saving_partial(
                lambda: collect_from_autopilot(
                    ap,
                    cp,
                    rate_hz=args.rate,
                    duration_s=args.duration,
                    coverage_target=None if args.coverage is None else args.coverage / 100.0,
                    max_samples=args.max_samples,
                    min_samples=min_samples,
                    progress=reporter(progress, view),
                    firmware=fw,
                ),
                args.output,
                progress,
            )
        finally:
            if view is not None:
                view.finish(result)
    if result.session is not None:
        meta = result.session.meta
        print(
            f"{meta['stream']} asked {meta['stream_request']}, arrived at "
            f"{meta['stream_rate_hz']} Hz, new magnetometer values at "
            f"{meta['magnetometer_rate_hz']} Hz; {result.screen.text()}",
            file=out,
        )
    return finish_collect(
        args,
        result,
        min_samples,
        f"on {args.mavlink}",
        "check that the vehicle streams its IMU",
        out,
    )
