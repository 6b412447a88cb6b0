"""The ``magcal`` command line: thin wrappers around the library, nothing numerical here."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from magcal import __version__
from magcal.errors import MagcalError

EXIT_ERROR = 2
#: Exit status after Ctrl-C (128 + SIGINT, as a shell reports it).
EXIT_INTERRUPTED = 130


def _progress_printer(stream=None):
    """A BFGS progress line: rewritten in place on a terminal, every 10th otherwise."""
    stream = stream or sys.stderr
    tty = stream.isatty()

    def show(iteration: int, cost: float, decrement: float) -> None:
        line = f"ML iteration {iteration:4d}  cost {cost:.6f}  predicted decrease {decrement:.2e}"
        if tty:
            stream.write("\r" + line)
            stream.flush()
        elif iteration == 1 or iteration % 10 == 0:
            stream.write(line + "\n")

    def done() -> None:
        if tty:
            stream.write("\n")

    show.done = done  # type: ignore[attr-defined]
    return show


def _add_simulate(sub) -> None:
    p = sub.add_parser("simulate", help="write a simulated session CSV and its truth JSON")
    p.add_argument("--preset", default="mems", help="table2, mems, handheld, raw-counts")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--rate", type=float, dest="rate_hz", help="sample rate, Hz")
    p.add_argument("--duration", type=float, dest="duration_s", help="motion length, s")
    p.add_argument("--stationary", type=float, dest="stationary_s", help="rest first, s")
    p.add_argument("--motion", choices=["tumble", "yaw-only", "small"])
    p.add_argument("--max-rate", type=float, dest="max_rate_rad_s", help="rad/s")
    p.add_argument("--acc-rms", type=float, dest="translational_acc_rms", help="m/s²")
    p.add_argument("--bumps", type=int, dest="n_bumps", help="accelerometer outliers")
    p.add_argument("--gyro-sigma", type=float, dest="gyro_sigma", help="rad/s")
    p.add_argument("--acc-sigma", type=float, dest="acc_sigma", help="m/s²")
    p.add_argument("--mag-sigma", type=float, dest="mag_sigma", help="magnetometer units")
    p.add_argument("--field-scale", type=float, dest="field_scale", help="field, mag units")
    p.add_argument("--offset-scale", type=float, dest="offset_scale", help="mag units")
    p.add_argument("-o", "--output", required=True, help="session CSV to write")
    p.add_argument("--truth", help="truth JSON to write (default: OUTPUT with .truth.json)")
    p.set_defaults(run=_run_simulate)


def _run_simulate(args) -> int:
    from magcal.io.session import check_writable, write_session
    from magcal.sim.scenarios import TruthFormatError, preset, simulate, write_truth

    keys = (
        "rate_hz",
        "duration_s",
        "stationary_s",
        "motion",
        "max_rate_rad_s",
        "translational_acc_rms",
        "n_bumps",
        "gyro_sigma",
        "acc_sigma",
        "mag_sigma",
        "field_scale",
        "offset_scale",
    )
    overrides = {k: getattr(args, k) for k in keys if getattr(args, k) is not None}
    out = Path(args.output)
    truth_path = Path(args.truth) if args.truth else out.with_suffix(".truth.json")
    if truth_path.resolve() == out.resolve():
        raise MagcalError(
            f"simulate: --truth {truth_path} is the session file itself; give another name"
        )
    # Check both outputs first, so that a bad path never leaves a session without its truth.
    check_writable(out, "writing session")
    check_writable(truth_path, "writing truth", TruthFormatError)
    session, truth = simulate(preset(args.preset, **overrides), args.seed)
    write_session(out, session)
    write_truth(truth_path, truth)
    print(f"wrote {out} ({len(session)} samples) and {truth_path}")
    return 0


#: ``calibrate --method`` choices, as ``magcal.calib.calibrate.METHODS`` (not imported here: the
#: parser is built for every command, and the pipeline loads the numerical stack).
CALIBRATION_METHODS = ("ml", "init", "ckf", "two-step")


def _add_calibrate(sub) -> None:
    p = sub.add_parser("calibrate", help="calibrate a session (Kok & Schön Algorithm 1)")
    p.add_argument("session", help="session CSV (magcal-session: 1)")
    p.add_argument(
        "--method",
        default="ml",
        choices=CALIBRATION_METHODS,
        help="ml: maximum likelihood, Kok & Schön's Algorithm 1 (default); init: its initial "
        "estimate (step 1) only; ckf: Zhao et al.'s cubature Kalman filter, sample by sample; "
        "two-step: Alonso & Shuster's TWO-STEP. ckf and two-step fit the ellipsoid from the "
        "field norm alone and take the misalignment from init's alignment step",
    )
    p.add_argument("-o", "--output", help="result JSON to write")
    p.add_argument("--plot", metavar="DIR", help="write the paper's figures as PNG here")
    p.add_argument(
        "--force",
        action="store_true",
        help="calibrate even when the session cannot determine it (with a warning)",
    )
    p.add_argument(
        "--gradient",
        default="exact",
        choices=["exact", "numeric"],
        help="exact (reverse mode) or the paper's finite differences",
    )
    p.add_argument("--truth", help="truth JSON of a simulated session: also print errors")
    p.set_defaults(run=_run_calibrate)


def _print_summary(cal, out=None) -> None:
    out = out or sys.stdout
    r = cal.result
    x = r.extra
    with np.printoptions(precision=5, suppress=True):  # local: no global numpy state
        print(f"method      {r.method}", file=out)
        print(f"D           {np.array2string(r.D, prefix=' ' * 12)}", file=out)
        print(f"o           {r.o}", file=out)
        print(f"dip         {r.dip_deg:.3f}°", file=out)
        if r.gyro_bias is not None:
            print(f"gyro bias   {np.rad2deg(r.gyro_bias)} °/s", file=out)
        if "optimizer" in x:
            o = x["optimizer"]
            print(
                f"ML          {o['iterations']} iterations, {o['cost_evaluations']} cost and "
                f"{o['gradient_evaluations']} gradient evaluations, "
                f"final cost {o['final_cost']:.6f}, {o['seconds']:.2f} s, "
                f"stopped on '{o['stopping_rule']}' ({o['gradient']} gradient)",
                file=out,
            )
        s = x["innovations"]
        print(
            f"innovations normalised: mean {s['mean']:.3f}, std {s['std']:.3f}, "
            f"{100 * s['fraction_outside_3']:.2f} % outside ±3",
            file=out,
        )
        b, a = x["field_norm"]["before"], x["field_norm"]["after"]
        print(
            f"field norm  before {b['mean']:.4g} ± {b['std']:.3g} (raw units), "
            f"after {a['mean']:.5f} ± {a['std']:.5f}",
            file=out,
        )
        print(
            "time        " + ", ".join(f"{k} {v:.2f} s" for k, v in x["seconds"].items()), file=out
        )
        for w in r.warnings:
            print(f"warning: {w}", file=out)


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
            cal.filter_output.normalised,
            d / "innovations.png",
            title=f"Normalised innovations ({cal.result.method})",
        ),
    ]


def _run_calibrate(args) -> int:
    from magcal.calib.calibrate import calibrate
    from magcal.calib.diagnostics import observability
    from magcal.calib.initial import ellipsoid
    from magcal.io.result import check_result_writable, write_result
    from magcal.io.session import os_error_advice, read_session

    # Everything a typo can break is checked before calibrating: an ML run takes a while.
    if args.output:
        check_result_writable(args.output)
    if args.plot:
        _prepare_plot_dir(args.plot)
    # The observability checks refuse fewer samples; forced, the ellipsoid fit's minimum holds.
    min_samples = ellipsoid.MIN_SAMPLES if args.force else observability.MIN_SAMPLES
    session = read_session(args.session, min_samples=min_samples)
    truth = _read_matching_truth(args.truth, args.session, session) if args.truth else None
    progress = _progress_printer()
    try:
        cal = calibrate(
            session, args.method, force=args.force, gradient=args.gradient, progress=progress
        )
    finally:
        progress.done()
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


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="magcal", description="Magnetometer calibration with inertial sensors."
    )
    parser.add_argument("--version", action="version", version=f"magcal {__version__}")
    sub = parser.add_subparsers(dest="command", required=True)
    _add_simulate(sub)
    _add_calibrate(sub)
    _add_device_commands(sub)
    return parser


def _add_device_commands(sub) -> None:
    """Every module of :mod:`magcal.commands` that defines ``add_parser`` is a command; they
    are imported here, not at the top, so that simulate and calibrate do not load the serial
    or MAVLink stacks. A new command is a new module there, and nothing here changes."""
    import importlib
    import pkgutil

    import magcal.commands as commands

    for module in sorted(pkgutil.iter_modules(commands.__path__), key=lambda m: m.name):
        loaded = importlib.import_module(f"{commands.__name__}.{module.name}")
        add = getattr(loaded, "add_parser", None)
        if add is not None:
            add(sub)


def refusal(command: str, exc: BaseException | str) -> str:
    """The one-paragraph stderr message ``magcal <command>: ...`` for ``exc``.

    Line breaks are joined into one line, and the prefix is not doubled when the message
    already names the command ("simulate: unknown preset ...").
    """
    text = " ".join(line.strip() for line in str(exc).splitlines() if line.strip())
    text = text or type(exc).__name__
    if text.startswith(f"magcal {command}:"):
        return text
    if text.startswith(f"{command}:"):
        return f"magcal {text}"
    return f"magcal {command}: {text}"


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return args.run(args)
    except MagcalError as exc:
        print(refusal(args.command, exc), file=sys.stderr)
        return EXIT_ERROR
    except OSError as exc:
        # A safety net: the file functions raise MagcalError for the files they handle; any
        # other refusal by the system (a closed pipe, a full disk) is still a message.
        where = f" ({exc.filename})" if exc.filename else ""
        print(refusal(args.command, f"{exc.strerror or exc}{where}"), file=sys.stderr)
        return EXIT_ERROR
    except KeyboardInterrupt:
        print(f"magcal {args.command}: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
