# SPDX-License-Identifier: Apache-2.0
"""``magcal verify --port URL``: stream the device's corrected output and measure it.

Reports the spread of the corrected field's norm and, from a raw stream (or ``--session``), the
heading consistency (see :mod:`magcal.device.verify`). Exits 2 with a message when the device
has no active parameter set (E_NO_PARAMS), 1 when the device's output disagrees with the set
it reports or the norm spread exceeds ``--max-spread``.

``--mavlink URL [--compass N]``: the field the autopilot corrects with its parameters in force
(:mod:`magcal.autopilot.verify`): norm spread and heading consistency of its own stream, and
with ``--session`` the parameters in force applied to a session recorded by ``magcal collect
--mavlink``. Each half loads what it needs when it runs, not when the parser is built (this
one :mod:`magcal.autopilot` and pymavlink).
"""

from __future__ import annotations

import sys
from typing import TYPE_CHECKING

from magcal.commands.common import (
    add_link_arguments,
    check_link_options,
    compass_params,
    open_device,
    positive,
)
from magcal.ui import EXIT_FAILED

if TYPE_CHECKING:
    from magcal.device.verify import HeadingConsistency

DEFAULT_MAX_SPREAD_PCT = 2.0


def add_parser(sub) -> None:
    p = sub.add_parser(
        "verify",
        help="measure the device's corrected output (norm, heading)",
        description="Stream the device's corrected field and measure it: the spread of its norm "
        "and, from a raw stream or a recorded session, the heading consistency. Exits 1 when "
        "the spread exceeds --max-spread or the output disagrees with the parameter set the "
        "device reports. With --mavlink: the field the autopilot corrects with its parameters "
        "in force.",
        epilog="examples:\n"
        "  magcal verify --port /dev/ttyACM0\n"
        "  magcal verify --port /dev/ttyACM0 --samples 2000 --max-spread 1\n"
        "  magcal verify --mavlink udpin:0.0.0.0:14550 --session session.csv",
    )
    add_link_arguments(p)
    how_long = p.add_mutually_exclusive_group()
    how_long.add_argument(
        "--duration", type=positive(float), metavar="S", help="stream for S seconds"
    )
    how_long.add_argument(
        "--samples", type=positive(int), metavar="N", help="stream N samples (default 500)"
    )
    p.add_argument(
        "--session",
        metavar="SESSION.csv",
        help="also measure the heading consistency of the active set on this recorded session "
        "(magcal collect's file)",
    )
    p.add_argument(
        "--no-heading",
        action="store_true",
        help="skip the raw stream that measures the heading consistency",
    )
    p.add_argument(
        "--max-spread",
        type=positive(float),
        default=DEFAULT_MAX_SPREAD_PCT,
        metavar="PCT",
        help=f"fail when the norm's std/mean exceeds PCT %% (default {DEFAULT_MAX_SPREAD_PCT:g})",
    )
    p.add_argument(
        "--rate",
        type=positive(float),
        metavar="HZ",
        help="with --mavlink: the IMU message rate to ask for (default 50)",
    )
    p.set_defaults(run=run)


def heading_lines(h: HeadingConsistency, where: str) -> list[str]:
    return [
        f"heading    {where}: RMS {h.rms_deg:.2f}°, max {h.max_deg:.2f}° (tilt-compensated vs "
        f"gyro-propagated over {h.windows} windows of {h.window_s:g} s, {h.n} samples)",
        f"dip        {h.dip_mean_deg:.2f}° ± {h.dip_std_deg:.2f}°",
    ]


def run(args, out=None) -> int:
    from magcal.device.verify import verify
    from magcal.io.session import read_session

    check_link_options(args, ("rate",))
    if args.mavlink:
        if args.rate is None:
            from magcal.autopilot.verify import DEFAULT_RATE_HZ

            args.rate = DEFAULT_RATE_HZ
        return run_autopilot(args, out)
    out = out or sys.stdout
    session = read_session(args.session) if args.session else None
    with open_device(args.port) as dev:
        r = verify(
            dev.client,
            dev.info,
            n_samples=args.samples,
            duration_s=args.duration,
            heading=not args.no_heading,
            session=session,
        )
    n = r.norm
    lines = [
        f"device     {args.port}, uid {dev.info.uid_hex}, active set CRC-32 0x{r.crc32:08x}",
        f"norm       mean {n.mean:.5f}, std {n.std:.5f} ({100 * n.rel_std:.3f} %), "
        f"min {n.min:.5f}, max {n.max:.5f}, (max-min)/mean {100 * n.rel_range:.3f} % "
        f"over {n.n} corrected samples",
        f"device     {n.n - r.mismatches} of {n.n} corrected samples equal the host's "
        f"emulation of the active set (within 1 LSB); dropped {r.dropped}",
    ]
    if r.heading is not None:
        lines += heading_lines(r.heading, "raw stream")
    else:
        lines.append(f"heading    {r.heading_note}")
    if args.session:
        if r.session_heading is not None:
            lines += heading_lines(r.session_heading, args.session)
        else:
            lines.append(f"heading    {args.session}: not measurable (no sample with |acc| ≈ g)")
    for line in lines:
        print(line, file=out)
    status = 0
    if r.mismatches:
        print(
            f"magcal verify: {r.mismatches} corrected samples differ from the active set's "
            "correction: the device does not use the set it reports; reset it and verify again",
            file=sys.stderr,
        )
        status = EXIT_FAILED
    if 100 * n.rel_std > args.max_spread:
        print(
            f"magcal verify: the norm's spread {100 * n.rel_std:.2f} % exceeds "
            f"{args.max_spread:g} %: calibrate again (rotate through more orientations, away "
            "from magnetic objects) and flash the result",
            file=sys.stderr,
        )
        status = EXIT_FAILED
    return status


# ---------------------------------------------------------------- --mavlink: an autopilot


def run_autopilot(args, out=None) -> int:
    from magcal.autopilot import verify as apverify
    from magcal.autopilot.connection import open_autopilot
    from magcal.io.session import read_session

    out = out or sys.stdout
    session = read_session(args.session) if args.session else None
    compass = args.compass or 1
    with open_autopilot(args.mavlink) as ap:
        cp = compass_params(ap, compass)
        session_head = None
        if session is not None:
            session_head = apverify.heading_of_session(session, cp, args.session)
        r = apverify.verify(
            ap, cp, n_samples=args.samples, duration_s=args.duration, rate_hz=args.rate
        )
    n = r.norm
    who = (
        "corrected here with the parameters in force"
        if r.corrected_here
        else "corrected by the vehicle"
    )
    lines = [
        f"vehicle    {ap.describe()}, compass {compass}; stream {r.stream} ({who})",
        f"norm       mean {n.mean:.5g} {r.unit}, std {n.std:.4g} ({100 * n.rel_std:.3f} %), "
        f"min {n.min:.5g}, max {n.max:.5g}, (max-min)/mean {100 * n.rel_range:.3f} % "
        f"over {n.n} samples (missing {r.missing}, repeated timestamps {r.repeated})",
    ]
    if r.heading is not None:
        lines += heading_lines(r.heading, f"{r.stream} stream")
    else:
        lines.append("heading    not measurable: no sample with |acc| near g")
    if session is not None:
        if session_head is not None:
            lines += heading_lines(session_head, f"{args.session} (parameters in force)")
        else:
            lines.append(f"heading    {args.session}: not measurable (no sample with |acc| ≈ g)")
    for line in lines:
        print(line, file=out)
    max_spread = args.max_spread if args.max_spread is not None else DEFAULT_MAX_SPREAD_PCT
    if 100 * n.rel_std > max_spread:
        print(
            f"magcal verify: the norm's spread {100 * n.rel_std:.2f} % exceeds {max_spread:g} %: "
            "calibrate again (rotate through more orientations, away from magnetic objects) "
            "and flash the result",
            file=sys.stderr,
        )
        return EXIT_FAILED
    return 0
