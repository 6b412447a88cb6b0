# SPDX-License-Identifier: Apache-2.0
"""``magcal report RESULT.json SESSION.csv -o report.html [--validate OTHER.csv]``."""

from __future__ import annotations

import os

from magcal import ui
from magcal.errors import MagcalError

#: Bytes read to tell a session CSV from a result JSON when a file fails to parse.
SNIFF_BYTES = 64


def add_parser(sub) -> None:
    p = sub.add_parser(
        "report",
        help="write a self-contained HTML report: the calibration, its uncertainty, the "
        "figures, and a validation on another session",
        description="Write one self-contained HTML file about a calibration: the result with "
        "its uncertainty, naming any direction of the parameters the session cannot determine, "
        "and figures of the result applied to the session it was calibrated from. --validate "
        "also applies it to a second session, not used for the fit.",
        epilog="examples:\n"
        "  magcal report result.json session.csv -o report.html\n"
        "  magcal report result.json session.csv --validate other.csv -o report.html",
    )
    p.add_argument("result", help="result JSON (magcal-result/1) written by magcal calibrate")
    p.add_argument("session", help="the session CSV the result was calibrated from")
    p.add_argument("-o", "--output", required=True, help="HTML file to write")
    p.add_argument(
        "--validate",
        metavar="OTHER.csv",
        help="a second session, not used for the fit: norm, residuals and inclination on it",
    )
    p.set_defaults(run=run)


def _looks_like(path: str) -> str | None:
    """ "session" or "result" from a file's first bytes, None when unreadable or neither."""
    try:
        with open(path, "rb") as f:
            head = f.read(SNIFF_BYTES).lstrip(b"\xef\xbb\xbf").lstrip()
    except OSError:
        return None
    if head.startswith(b"# magcal-session"):
        return "session"
    if head.startswith(b"{"):
        return "result"
    return None


def _read_inputs(args):
    from magcal.calib.initial import ellipsoid
    from magcal.io.result import read_result
    from magcal.io.session import read_session

    if _looks_like(args.result) == "session":
        raise MagcalError(
            f"{args.result} is a session CSV, not a result JSON: the order is "
            "`magcal report RESULT.json SESSION.csv`"
        )
    for path, role in ((args.session, "session"), (args.validate, "validation session")):
        if path and _looks_like(path) == "result":
            raise MagcalError(
                f"the {role} {path} is a result JSON, not a session CSV: the order is "
                "`magcal report RESULT.json SESSION.csv [--validate OTHER.csv]`"
            )
    result = read_result(args.result)
    # The forced calibration minimum: any session that calibrate accepts can be reported on.
    session = read_session(args.session, min_samples=ellipsoid.MIN_SAMPLES)
    validation = (
        read_session(args.validate, min_samples=ellipsoid.MIN_SAMPLES) if args.validate else None
    )
    return result, session, validation


def _check_output(args) -> None:
    from magcal.report.contents import ReportError
    from magcal.report.html import check_report_writable

    out = os.path.realpath(args.output)
    for path in (args.result, args.session, args.validate):
        if path and os.path.realpath(path) == out:
            raise ReportError(
                f"writing report {args.output}: it is one of the inputs ({path}); give another name"
            )
    check_report_writable(args.output)


def progress_printer(stream=None):
    """``show(stage, done, total)`` for the report, ``show.done()`` after it: the Hessian's
    gradient passes as a :class:`magcal.ui.ProgressBar` (in a log, its first and last pass),
    then one line per later stage (the figures)."""
    state: dict[str, ui.ProgressBar | None] = {"bar": None}

    def show(stage: str, done: int, total: int) -> None:
        if stage == "hessian":
            if state["bar"] is None:
                state["bar"] = ui.ProgressBar(
                    "report: Hessian of the ML cost",
                    total,
                    stream,
                    log_step_pct=100,
                    log_line=lambda d, t: f"report: Hessian of the ML cost, gradient pass {d}/{t}",
                )
            state["bar"].update(done, total)
        else:
            close()
            ui.write_line(f"report: {stage}", stream)

    def close() -> None:
        if state["bar"] is not None:
            state["bar"].close()
            state["bar"] = None

    show.done = close  # type: ignore[attr-defined]
    return show


def run(args) -> int:
    from magcal.report.contents import build_report
    from magcal.report.html import render_html, write_report

    _check_output(args)
    result, session, validation = _read_inputs(args)
    progress = progress_printer()
    try:
        report = build_report(
            result,
            session,
            result_path=args.result,
            session_path=args.session,
            validation=validation,
            validation_path=args.validate,
            progress=progress,
        )
    finally:
        progress.done()
    write_report(args.output, render_html(report))
    unc = report.uncertainty
    if unc is None:
        state = "no uncertainty (see the report's notes)"
    elif unc.identifiable:
        state = "all parameters identifiable"
    else:
        # the directions can be many and long: the report lists them, the terminal counts
        n = len(unc.null_directions)
        state = f"NOT identifiable along {n} direction(s) of the parameters; the report lists them"
    print(f"wrote {args.output} ({state})")
    return 0
