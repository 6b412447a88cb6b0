"""What every device command shares: the link arguments and opening a device session."""

from __future__ import annotations

import argparse
import contextlib
from collections.abc import Iterator
from dataclasses import dataclass

from magcal.device.client import DeviceClient, DeviceInfo, HelloResult, Scale
from magcal.errors import MagcalError
from magcal.link import LINK_OPEN_TIMEOUT_S, open_link


def add_link_arguments(p: argparse.ArgumentParser) -> None:
    """``--port URL`` (required for now; ``--mavlink`` comes with the autopilot issue)."""
    p.add_argument(
        "--port",
        required=True,
        metavar="URL",
        help="the device: a serial device or pseudo-terminal path, or socket://host:port "
        "(anything pyserial's serial_for_url accepts)",
    )


def positive(kind):
    """An argparse type: ``kind(text)`` (int or float) that must be > 0."""

    def parse(text: str):
        try:
            v = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
        if v <= 0:
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
    if not url:
        raise MagcalError("no device given: pass --port URL")
    with open_link(url, LINK_OPEN_TIMEOUT_S) as link:
        client = DeviceClient(link)
        hello = client.hello()
        info = client.info()
        yield DeviceSession(url=url, client=client, hello=hello, info=info)
