# SPDX-License-Identifier: Apache-2.0
"""What every device command shares: the link arguments (``--port`` for a device running
magcal's firmware, ``--mavlink`` for an autopilot), opening a device session, and reading an
autopilot's compass parameters. Imports no command module, and loads the device and link
stacks only when a link is opened: the parsers are built from here for every command."""

from __future__ import annotations

import argparse
import contextlib
import math
from collections.abc import Iterator
from dataclasses import dataclass
from typing import TYPE_CHECKING

from magcal.errors import MagcalError

if TYPE_CHECKING:
    from magcal.device.client import DeviceClient, DeviceInfo, HelloResult, Scale


def add_link_arguments(p: argparse.ArgumentParser, required: bool = True) -> None:
    """``--port URL`` (a device running magcal's firmware) or ``--mavlink URL`` (an ArduPilot
    or PX4 autopilot), at most one, and exactly one when ``required`` (argparse says so when
    neither or both are given), and ``--compass N`` for the autopilot's compass."""
    link = p.add_mutually_exclusive_group(required=required)
    link.add_argument(
        "--port",
        metavar="URL",
        help="a device running magcal's firmware: a serial device or pseudo-terminal path, or "
        "socket://host:port (anything pyserial's serial_for_url accepts)",
    )
    link.add_argument(
        "--mavlink",
        metavar="URL",
        help="an ArduPilot or PX4 autopilot: udpin:0.0.0.0:14550 (listen), udpout:HOST:PORT, "
        "tcp:HOST:5760, or a serial device with its baud rate, /dev/ttyACM0,115200 (anything "
        "pymavlink's mavlink_connection accepts)",
    )
    p.add_argument(
        "--compass",
        type=compass_number,
        metavar="N",
        help="with --mavlink: the compass, 1-based as ArduPilot counts (COMPASS_OFS_X is 1, "
        "COMPASS_OFS2_X is 2); PX4's CAL_MAG{N-1}. Default 1 (info: all)",
    )


def compass_number(text: str) -> int:
    """An argparse type: a compass number 1, 2 or 3."""
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a compass number (1, 2 or 3)") from None
    if not 1 <= v <= 3:
        raise argparse.ArgumentTypeError(f"{text}: give 1, 2 or 3")
    return v


def check_link_options(args: argparse.Namespace, mavlink_only: tuple[str, ...] = ()) -> None:
    """Refuse options that belong to the other kind of link: ``--compass`` and the names in
    ``mavlink_only`` (attributes set to something other than None/False) need --mavlink."""
    if getattr(args, "mavlink", None):
        return
    used = ["--compass"] if getattr(args, "compass", None) is not None else []
    used += [
        "--" + name.replace("_", "-")
        for name in mavlink_only
        if getattr(args, name, None) not in (None, False)
    ]
    if used:
        raise MagcalError(
            f"{', '.join(used)} {'is' if len(used) == 1 else 'are'} for an autopilot: use "
            "--mavlink URL instead of --port"
        )


def finite(text: str) -> float:
    """An argparse type: a finite float (``nan`` and ``inf`` are no time or amount)."""
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    if not math.isfinite(v):
        raise argparse.ArgumentTypeError(f"{text} is not a finite number")
    return v


def positive(kind):
    """An argparse type: ``kind(text)`` (int or float) that must be finite and > 0."""

    def parse(text: str):
        v = finite(text) if kind is float else None
        if v is None:
            try:
                v = kind(text)
            except ValueError:
                raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
        if not v > 0:
            raise argparse.ArgumentTypeError(f"{text} must be positive")
        return v

    return parse


def scale_text(s: Scale) -> str:
    """An exact scale as the device gives it: "1/6842 gauss", "122 × 10^-6 standard_gravity"
    is written "122/1 × 10^-6 standard_gravity"."""
    exp = f" × 10^{s.exp10}" if s.exp10 else ""
    return f"{s.num}/{s.den}{exp} {s.unit.name.lower()}"


@dataclass(frozen=True)
class DeviceSession:
    """An open link with a negotiated protocol version and the device's description."""

    url: str
    client: DeviceClient
    hello: HelloResult
    info: DeviceInfo


@contextlib.contextmanager
def open_device(url: str) -> Iterator[DeviceSession]:
    """Open ``url``, say hello, read info; close the link on the way out, whatever happens."""
    from magcal.device.client import DeviceClient
    from magcal.link import LINK_OPEN_TIMEOUT_S, open_link

    if not url:
        raise MagcalError("no device given: pass --port URL")
    with open_link(url, LINK_OPEN_TIMEOUT_S) as link:
        client = DeviceClient(link)
        hello = client.hello()
        info = client.info()
        yield DeviceSession(url=url, client=client, hello=hello, info=info)


def compass_params(ap, compass: int, **kw):
    """The parameters in force of the autopilot's compass ``compass`` (1-based), with its unit
    and naming (:func:`magcal.autopilot.vehicle.read_compass_params`)."""
    from magcal.autopilot import vehicle

    return vehicle.read_compass_params(ap.read, ap.autopilot, compass, **kw)
