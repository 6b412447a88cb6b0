# SPDX-License-Identifier: Apache-2.0
"""``magcal simulate -o SESSION.csv``: a simulated session and its truth (the sensor's errors,
the attitude), from a preset with optional overrides (:mod:`magcal.sim.scenarios`)."""

from __future__ import annotations

from pathlib import Path

from magcal.errors import MagcalError


def add_parser(sub) -> None:
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
    p.add_argument(
        "--mag-rate",
        type=float,
        dest="mag_rate_hz",
        help="magnetometer rate below --rate, Hz: a multi-rate session (magcal-session: 2)",
    )
    p.add_argument(
        "--mag-lag-s",
        type=float,
        dest="mag_lag_s",
        help="the magnetometer shows the field this long ago, s (truth: time_offset_s)",
    )
    p.add_argument("-o", "--output", required=True, help="session CSV to write")
    p.add_argument("--truth", help="truth JSON to write (default: OUTPUT with .truth.json)")
    p.set_defaults(run=run)


def run(args) -> int:
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
        "mag_rate_hz",
        "mag_lag_s",
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
