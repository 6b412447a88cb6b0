# SPDX-License-Identifier: Apache-2.0
"""``magcal simulate -o SESSION.csv``: a simulated session and its truth (the sensor's errors,
the attitude), from a preset with optional overrides (:mod:`magcal.sim.scenarios`)."""

from __future__ import annotations

from pathlib import Path

from magcal.errors import MagcalError

#: What an override defaults to: each preset sets its own (magcal.sim.scenarios.PRESETS).
_PRESET_DEFAULT = " (default: the preset's)"


def add_parser(sub) -> None:
    p = sub.add_parser(
        "simulate",
        help="write a simulated session CSV and its truth JSON",
        description="Write a simulated calibration session and its truth: the sensor's errors "
        "and the attitude at every sample. A preset gives the sensor and the motion; the "
        "options below change one thing at a time, and the same seed gives the same sensor and "
        "motion. Calibrate the session with --truth to see how close a method comes.",
        epilog="examples:\n"
        "  magcal simulate -o session.csv\n"
        "  magcal simulate --preset handheld --seed 7 --mag-rate 25 -o handheld.csv\n"
        "  magcal simulate --motion yaw-only --duration 20 -o yaw.csv",
    )
    p.add_argument(
        "--preset",
        default="mems",
        metavar="NAME",
        help="the sensor and its motion. table2: the paper's Table 2, a normalised field and 3 s "
        "of fast rotation; mems: a MEMS unit turned slowly through all orientations for 60 s; "
        "handheld: a magnet a centimetre away, fast hand-held motion with a few knocks; "
        "raw-counts: hand-held, in raw units, a field of about 50 counts and offsets up to 100",
    )
    p.add_argument(
        "--seed",
        type=int,
        default=0,
        metavar="N",
        help="seed of the random draws: the sensor's errors, the motion and the noise each draw "
        "from their own stream, so changing the noise keeps the sensor and the motion",
    )
    p.add_argument(
        "--rate", type=float, dest="rate_hz", metavar="HZ", help="sample rate, Hz" + _PRESET_DEFAULT
    )
    p.add_argument(
        "--duration",
        type=float,
        dest="duration_s",
        metavar="S",
        help="length of the motion, s" + _PRESET_DEFAULT,
    )
    p.add_argument(
        "--stationary",
        type=float,
        dest="stationary_s",
        metavar="S",
        help="rest before the motion, s; 0: none" + _PRESET_DEFAULT,
    )
    p.add_argument(
        "--motion",
        choices=["tumble", "yaw-only", "small", "swing"],
        help="tumble: through all orientations; yaw-only: about the vertical only; small: a "
        "wobble of about 10° around one orientation; swing: the tumble with fast swings of "
        "±40° about the body's x axis on top (most of the rotation about one axis). yaw-only "
        "and small turn the sensor too little to determine a calibration: magcal calibrate "
        "refuses them (default: tumble)",
    )
    p.add_argument(
        "--max-rate",
        type=float,
        dest="max_rate_rad_s",
        metavar="RAD_S",
        help="bound on the angular rate, rad/s" + _PRESET_DEFAULT,
    )
    p.add_argument(
        "--acc-rms",
        type=float,
        dest="translational_acc_rms",
        metavar="M_S2",
        help="RMS of the acceleration besides gravity during the motion, m/s²; 0: pure rotation"
        + _PRESET_DEFAULT,
    )
    p.add_argument(
        "--bumps",
        type=int,
        dest="n_bumps",
        metavar="N",
        help="knocks on the accelerometer during the motion, 1-3 samples of 5-20 m/s² each"
        + _PRESET_DEFAULT,
    )
    noise = " (default: the sensor model's)"
    p.add_argument(
        "--gyro-sigma",
        type=float,
        dest="gyro_sigma",
        metavar="RAD_S",
        help="gyroscope noise, 1-σ per axis, rad/s; 0: noise-free" + noise,
    )
    p.add_argument(
        "--acc-sigma",
        type=float,
        dest="acc_sigma",
        metavar="M_S2",
        help="accelerometer noise, 1-σ per axis, m/s²" + noise,
    )
    p.add_argument(
        "--mag-sigma",
        type=float,
        dest="mag_sigma",
        metavar="UNITS",
        help="magnetometer noise, 1-σ per axis, magnetometer units" + noise,
    )
    p.add_argument(
        "--field-scale",
        type=float,
        dest="field_scale",
        metavar="UNITS",
        help="the field's magnitude in magnetometer units; with table2 it also scales the offset "
        "and the noise" + _PRESET_DEFAULT,
    )
    p.add_argument(
        "--offset-scale",
        type=float,
        dest="offset_scale",
        metavar="UNITS",
        help="size of the offset, magnetometer units; not used by table2 (default: the "
        "sensor model's)",
    )
    p.add_argument(
        "--mag-rate",
        type=float,
        dest="mag_rate_hz",
        metavar="HZ",
        help="magnetometer rate below --rate, Hz: a multi-rate session (magcal-session: 2)",
    )
    p.add_argument(
        "--mag-lag-s",
        type=float,
        dest="mag_lag_s",
        metavar="S",
        help="the magnetometer shows the field this long ago, s (truth: time_offset_s)",
    )
    p.add_argument("-o", "--output", required=True, help="session CSV to write")
    p.add_argument(
        "--truth",
        metavar="TRUTH.json",
        help="truth JSON to write (default: OUTPUT with .truth.json)",
    )
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
