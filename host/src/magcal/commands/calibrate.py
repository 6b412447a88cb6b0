# SPDX-License-Identifier: Apache-2.0
"""``magcal calibrate SESSION.csv``: calibrate a recorded or simulated session
(:func:`magcal.calib.calibrate.calibrate`), print a summary, and optionally write the result,
the paper's figures, and the errors against a simulation's truth."""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

from magcal import ui
from magcal.errors import MagcalError

#: ``calibrate --method`` choices, as ``magcal.calib.calibrate.METHODS`` (not imported here: the
#: parser is built for every command, and the pipeline loads the numerical stack).
CALIBRATION_METHODS = ("ml", "init", "ckf", "two-step")
#: The ML step's optimisers (magcal.calib.likelihood.ml.OPTIMIZERS), the default first.
ML_OPTIMIZERS = ("trust-region", "bfgs")
#: The units a session's columns may be given in, the session format's first (the keys of
#: TIME_UNITS, GYRO_UNITS and ACC_UNITS of magcal.calib.diagnostics.units).
TIME_UNITS = ("s", "ms", "us")
GYRO_UNITS = ("rad/s", "deg/s")
ACC_UNITS = ("m/s2", "g", "mg")


def add_parser(sub) -> None:
    p = sub.add_parser(
        "calibrate",
        help="calibrate a session (Kok & Schön Algorithm 1)",
        description="Calibrate a recorded or simulated session: estimate the magnetometer's "
        "distortion D and offset o (soft and hard iron, scale, misalignment to the IMU), the "
        "field's dip and the gyroscope's bias, and check the result against the session. "
        "Prints a summary and writes the result that magcal flash and magcal report read.",
        epilog="examples:\n"
        "  magcal calibrate session.csv -o result.json\n"
        "  magcal calibrate session.csv -o result.json --truth session.truth.json --plot plots\n"
        "  magcal calibrate log.csv --time-unit ms --gyro-unit deg/s --acc-unit g -o result.json",
    )
    p.add_argument("session", help="session CSV (magcal-session: 1 or 2)")
    p.add_argument(
        "--method",
        default="ml",
        choices=CALIBRATION_METHODS,
        help="ml: maximum likelihood, Kok & Schön's Algorithm 1; init: its initial "
        "estimate (step 1) only; ckf: Zhao et al.'s cubature Kalman filter, sample by sample; "
        "two-step: Alonso & Shuster's TWO-STEP. ckf and two-step fit the ellipsoid from the "
        "field norm alone and take the misalignment from init's alignment step",
    )
    p.add_argument("-o", "--output", help="result JSON to write")
    p.add_argument("--plot", metavar="DIR", help="write the paper's figures as PNG here")
    p.add_argument(
        "--force",
        action="store_true",
        help="calibrate even when the session cannot determine it, and write a result its own "
        "session contradicts (a gyroscope bias or D no sensor has, a field norm or dip worse "
        "than a plain ellipsoid fit's, a field that changed during the recording), each with "
        "a warning",
    )
    p.add_argument(
        "--max-fit-residual",
        type=_percent,
        default=DEFAULT_MAX_FIT_RESIDUAL_PERCENT,
        metavar="PERCENT",
        help="the absolute gate: refuse a result whose corrected field's strength departs "
        "from constant by more than this, RMS beyond the magnetometer's noise, in %% of the "
        "field (like ArduPilot's COMPASS_CAL_FIT, in any unit). The default is twice what "
        "calibrations of clean real recordings leave",
    )
    p.add_argument(
        "--gradient",
        default="exact",
        choices=["exact", "numeric"],
        help="exact (reverse mode) or the paper's finite differences",
    )
    p.add_argument(
        "--optimizer",
        default=None,
        choices=ML_OPTIMIZERS,
        help="the ML step's optimiser: trust-region (the default; bfgs with --gradient "
        "numeric, as the trust region needs the exact gradient), a trust region on the "
        "likelihood's Fisher information refined by BFGS updates, which converges in tens of "
        "iterations where BFGS takes hundreds on real hand-held recordings; or bfgs, damped "
        "BFGS from the identity (the paper's), cheaper per iteration on long simulated "
        "sessions",
    )
    p.add_argument(
        "--gyro-bias-prior",
        type=angle_rate_prior,
        default=DEFAULT_GYRO_BIAS_PRIOR,
        metavar="WIDTH",
        help="1-σ width of the prior on each axis of the gyroscope bias, centred on 0, e.g. "
        "2deg/s or 0.03rad/s (a bare number is °/s); 'none' for no prior. Default "
        f"{DEFAULT_GYRO_BIAS_PRIOR}: MEMS offsets are a few °/s",
    )
    p.add_argument(
        "--misalignment-prior",
        type=angle_prior,
        default="none",
        metavar="WIDTH",
        help="1-σ width of a prior on the rotation between the magnetometer's and the IMU's "
        "axes, centred on the nearest axis permutation, e.g. 5deg or 0.1rad (a bare number is "
        "degrees); default none. For a magnetometer mounted along the IMU's axes: data that "
        "cannot tell then fall back to aligned axes",
    )
    units_note = (
        "; without it the column must be in {0}, and a session that looks like another unit "
        "is refused, naming it (told from {1})"
    )
    p.add_argument(
        "--time-unit",
        choices=TIME_UNITS,
        default=None,
        help="the unit of the session's t column (us: microseconds), converted to seconds "
        "before calibrating"
        + units_note.format(
            "seconds", "its step and from the gyroscope's turn against the accelerometer's"
        ),
    )
    p.add_argument(
        "--gyro-unit",
        choices=GYRO_UNITS,
        default=None,
        help="the unit of the session's gyroscope columns, converted to rad/s before "
        "calibrating" + units_note.format("rad/s", "its turn against the accelerometer's"),
    )
    p.add_argument(
        "--acc-unit",
        choices=ACC_UNITS,
        default=None,
        help="the unit of the session's accelerometer columns (g: 9.80665 m/s²), converted "
        "to m/s² before calibrating" + units_note.format("m/s²", "its reading at rest"),
    )
    p.add_argument(
        "--truth",
        metavar="TRUTH.json",
        help="the truth magcal simulate wrote with the session: also print the heading errors "
        "the calibration leaves",
    )
    p.set_defaults(run=run)


#: --max-fit-residual's default, % (MAX_FIT_RESIDUAL of magcal.calib.diagnostics.consistency;
#: not imported here, the parser loads no numerical code).
DEFAULT_MAX_FIT_RESIDUAL_PERCENT = 8.0


def _percent(text: str) -> float:
    """A positive percentage: "8" or "8%"."""
    try:
        value = float(text.strip().removesuffix("%"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a percentage (e.g. 8 or 8%)") from None
    if not value > 0.0:
        raise argparse.ArgumentTypeError(f"{text!r}: the limit must be above 0 %")
    return value


#: --gyro-bias-prior's default, as the command line writes it (GYRO_BIAS_PRIOR_DEG_S of
#: magcal.calib.likelihood.problem; not imported here, the parser loads no numerical code).
DEFAULT_GYRO_BIAS_PRIOR = "5deg/s"
_RATE_UNITS = {"deg/s": math.pi / 180.0, "°/s": math.pi / 180.0, "rad/s": 1.0}
_ANGLE_UNITS = {"deg": math.pi / 180.0, "°": math.pi / 180.0, "rad": 1.0}


def _width(text: str, units: dict[str, float], bare: str) -> float | None:
    """A prior width in SI units (rad or rad/s) from "2deg/s", "0.1rad", "5" (``bare``'s unit)
    or "none" (no prior)."""
    import argparse

    t = text.strip().replace(" ", "")
    if t.lower() == "none":
        return None
    unit = next((u for u in sorted(units, key=len, reverse=True) if t.endswith(u)), None)
    number = t[: -len(unit)] if unit else t
    try:
        value = float(number)
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"{text!r}: give a width like 5{bare}, a number in {', '.join(units)}, or none"
        ) from None
    if not math.isfinite(value) or value <= 0.0:
        raise argparse.ArgumentTypeError(f"{text!r}: a width must be a positive number, or none")
    return value * units[unit or bare]


def angle_rate_prior(text: str) -> float | None:
    """An argparse type: a gyroscope-bias prior width, rad/s (None: no prior)."""
    return _width(text, _RATE_UNITS, "deg/s")


def angle_prior(text: str) -> float | None:
    """An argparse type: a misalignment prior width, rad (None: no prior)."""
    return _width(text, _ANGLE_UNITS, "deg")


def summary_rows(cal) -> list[tuple[str, str]]:
    """The result at a glance, as label-value rows: method, D, o, dip, gyroscope bias, the
    optimizer's account, the innovations, the field norm before and after, the time taken."""
    import numpy as np

    r = cal.result
    x = r.extra
    indent = " " * (ui.LABEL_WIDTH + 1)
    with np.printoptions(precision=5, suppress=True):  # local: no global numpy state
        rows = [
            ("method", r.method),
            ("D", np.array2string(r.D, prefix=indent)),
            ("o", f"{r.o}"),
            ("dip", f"{r.dip_deg:.3f}°"),
        ]
        if r.gyro_bias is not None:
            rows.append(("gyro bias", f"{np.rad2deg(r.gyro_bias)} °/s"))
        if "time_offset_s" in r.extra:
            rows.append(
                ("time offset", f"{1e3 * r.extra['time_offset_s']:.1f} ms (magnetometer delay)")
            )
        test = x.get("gyro_gain_test")
        if test is not None:
            verdict = (
                f"allowed for, {100 * test['gain_error']:g} % per entry"
                if test["kept"]
                else "taken as exact"
            )
            rows.append(
                (
                    "gyro gain",
                    f"{verdict} (likelihood-ratio statistic {test['statistic']:.1f}, "
                    f"threshold {test['threshold']:.2f})",
                )
            )
    if "optimizer" in x:
        o = x["optimizer"]
        rows.append(
            (
                "ML",
                f"{o['iterations']} iterations, {o['cost_evaluations']} cost and "
                f"{o['gradient_evaluations']} gradient evaluations, "
                f"final cost {o['final_cost']:.6f}, {o['seconds']:.2f} s, "
                f"stopped on '{o['stopping_rule']}' ({o['gradient']} gradient)",
            )
        )
    s = x["innovations"]
    rows.append(
        (
            "innovations",
            f"normalised: mean {s['mean']:.3f}, std {s['std']:.3f}, "
            f"{100 * s['fraction_outside_3']:.2f} % outside ±3",
        )
    )
    b, a = x["field_norm"]["before"], x["field_norm"]["after"]
    rows.append(
        (
            "field norm",
            f"before {b['mean']:.4g} ± {b['std']:.3g} (raw units), "
            f"after {a['mean']:.5f} ± {a['std']:.5f}",
        )
    )
    rows.append(("time", ", ".join(f"{k} {v:.2f} s" for k, v in x["seconds"].items())))
    return rows


def _print_summary(cal, out=None) -> None:
    out = out or sys.stdout
    ui.print_table(summary_rows(cal), out)
    for w in cal.result.warnings:
        ui.print_wrapped(f"warning: {w}", out)


class CalibrationProgress:
    """What ``magcal calibrate`` shows while it works: the step under way and, in the ML
    step, its iteration, cost and predicted decrease.

    On a terminal: one status line redrawn in place (:class:`magcal.ui.StatusLine`). In a
    log: one line per step as it starts, nothing per iteration. ``quiet``: nothing.
    Pass :meth:`stage` and the object itself to :func:`magcal.calib.calibrate.calibrate`;
    :meth:`done` (idempotent) after it."""

    def __init__(self, stream=None, *, quiet: bool = False) -> None:
        self._status = None if quiet else ui.StatusLine(stream, last=False)
        self._stage = ""

    def stage(self, text: str) -> None:
        self._stage = text
        if self._status is not None:
            self._status.update(f"calibrate: {text}", log=True)

    def __call__(self, iteration: int, cost: float, decrement: float) -> None:
        if self._status is not None and self._status.live:
            self._status.update(
                f"calibrate: {self._stage}: iteration {iteration}, cost {cost:.3f}, "
                f"predicted decrease {decrement:.1e}"
            )

    def done(self) -> None:
        if self._status is not None:
            self._status.close()


def _read_matching_truth(truth_path: str, session_path: str, session):
    """The truth file of ``session``; refuses one whose length shows it is another session's."""
    from magcal.sim.scenarios import read_truth

    truth = read_truth(truth_path)
    n_truth, n_session = int(truth.q_nb.shape[0]), len(session)
    if n_truth != n_session:
        raise MagcalError(
            f"comparing with the truth: {truth_path} has {n_truth} samples but the session "
            f"{session_path} has {n_session}, so it is the truth of another session: pass the "
            f"truth file that `magcal simulate` wrote with {session_path}"
        )
    return truth


def _print_truth_comparison(cal, truth, session, out=None) -> None:
    out = out or sys.stdout
    from magcal.calib.diagnostics import quality

    st = truth.sensor
    floor = quality.known_attitude_fit(session.mag, truth.q_nb, st.m_n)
    rows = [
        ("known-attitude floor", floor),
        ("initial estimate", (cal.init.params.D, cal.init.params.o)),
    ]
    # init's result is the initial estimate; ckf and two-step replace its ellipsoid step, so
    # their "initial estimate" is their own result.
    if cal.ml is not None:
        rows.append(("ML estimate", (cal.result.D, cal.result.o)))
    elif cal.result.method != "init":
        rows[1] = (f"{cal.result.method} estimate", (cal.result.D, cal.result.o))
    print("calibration-induced heading error against the truth (RMS over SO(3)):", file=out)
    for name, (D, o) in rows:
        e = quality.calibration_heading_errors(st.D, st.o, st.m_n, D, o)
        print(f"  {name:22s} {quality.rms_deg(e):.4f}°", file=out)


def _prepare_plot_dir(directory: str) -> None:
    """Create the ``--plot`` directory and check that files can be written there."""
    from magcal.io.session import check_writable, os_error_advice

    try:
        Path(directory).mkdir(parents=True, exist_ok=True)
    except FileExistsError:
        raise MagcalError(
            f"writing plots to {directory}: it is a file, not a directory: give a directory"
        ) from None
    except OSError as exc:
        raise MagcalError(
            f"writing plots to {directory}: cannot create the directory "
            f"({os_error_advice(exc, directory, writing=True)})"
        ) from exc
    check_writable(Path(directory) / "ellipsoid_sphere.png", "writing plot", MagcalError)


def _write_plots(cal, session, directory: str) -> list[Path]:
    import numpy as np

    from magcal.report import plots

    d = Path(directory)
    return [
        plots.plot_ellipsoid_sphere(session.mag, cal.calibrated, d / "ellipsoid_sphere.png"),
        plots.plot_norms(
            session.t,
            np.linalg.norm(session.mag, axis=1),
            np.linalg.norm(cal.calibrated, axis=1),
            d / "field_norm.png",
        ),
        plots.plot_innovation_histogram(
            cal.filter_output.present_normalised(),
            d / "innovations.png",
            title=f"Normalised innovations ({cal.result.method})",
        ),
    ]


def run(args) -> int:
    from magcal.calib.calibrate import calibrate
    from magcal.calib.diagnostics import observability, units
    from magcal.calib.initial import ellipsoid
    from magcal.calib.likelihood.problem import Priors
    from magcal.io.result import check_result_writable, write_result
    from magcal.io.session import os_error_advice, read_session

    # Everything a typo can break is checked before calibrating: an ML run takes a while.
    declared = units.SessionUnits(t=args.time_unit, gyr=args.gyro_unit, acc=args.acc_unit)
    if args.optimizer is None:
        args.optimizer = ML_OPTIMIZERS[0] if args.gradient == "exact" else "bfgs"
    if args.optimizer == "trust-region" and args.gradient != "exact":
        raise MagcalError(
            "--optimizer trust-region needs the exact gradient (its curvature comes from the "
            "same pass): drop --gradient numeric, or use --optimizer bfgs"
        )
    if args.output:
        check_result_writable(args.output)
    if args.plot:
        _prepare_plot_dir(args.plot)
    # The observability checks refuse fewer samples; forced, the ellipsoid fit's minimum holds.
    min_samples = ellipsoid.MIN_SAMPLES if args.force else observability.MIN_SAMPLES
    session = read_session(args.session, min_samples=min_samples)
    truth = _read_matching_truth(args.truth, args.session, session) if args.truth else None
    progress = CalibrationProgress(quiet=getattr(args, "quiet", False))
    try:
        cal = calibrate(
            session,
            args.method,
            force=args.force,
            gradient=args.gradient,
            optimizer=args.optimizer,
            progress=progress,
            stage=progress.stage,
            priors=Priors(
                gyro_bias_rad_s=args.gyro_bias_prior, misalignment_rad=args.misalignment_prior
            ),
            declared_units=declared,
            max_fit_residual=args.max_fit_residual / 100.0,
        )
    finally:
        progress.done()
    # What the calibration saw: the plots' time axis in seconds.
    session = units.convert(session, declared)
    # Save the result first: nothing printed or plotted below may lose it.
    if args.output:
        write_result(args.output, cal.result)
        print(f"wrote {args.output}")
    _print_summary(cal)
    if truth is not None:
        _print_truth_comparison(cal, truth, session)
    if args.plot:
        try:
            for path in _write_plots(cal, session, args.plot):
                print(f"wrote {path}")
        except OSError as exc:
            raise MagcalError(
                f"writing plots to {args.plot}: {os_error_advice(exc, args.plot, writing=True)}"
            ) from exc
    return 0
