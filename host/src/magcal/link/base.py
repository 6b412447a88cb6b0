# SPDX-License-Identifier: Apache-2.0
"""The Link protocol: a byte stream with a timed read, a write and a close.

A link knows nothing about frames: :class:`magcal.device.client.DeviceClient` writes whole
frames and feeds whatever :meth:`Link.read` returns to a resynchronising Deframer.

Contract of every implementation:

- ``read(timeout_s)`` returns at least one byte, or raises :class:`LinkTimeoutError` when none
  arrived within ``timeout_s`` (it never returns ``b""`` or ``None``), or
  :class:`LinkClosedError` when the other end is gone.
- ``write(data, timeout_s)`` writes all of ``data`` or raises (LinkTimeoutError when the bytes
  could not be written within ``timeout_s``, LinkClosedError).
- ``close()`` is idempotent; afterwards read and write raise LinkClosedError.
- A link is a context manager that closes itself.
"""

from __future__ import annotations

from typing import Protocol, runtime_checkable

from magcal.errors import MagcalError

LINK_OPEN_TIMEOUT_S = 5.0  # opening a port or connecting a socket
LINK_WRITE_TIMEOUT_S = 2.0  # a whole frame (<= 247 bytes) takes 21 ms at 115 200 baud
# A read waits in slices of this length, so a long wait stays responsive (and a port's
# pyserial timeout is set once, not reconfigured with termios on every read).
LINK_READ_POLL_S = 0.02


class LinkError(MagcalError):
    """A link cannot be opened, read or written. The message names the URL and what to check."""

    def __init__(self, message: str, url: str = "") -> None:
        super().__init__(message)
        self.url = url


class LinkTimeoutError(LinkError):
    """Nothing arrived (read) or the bytes could not leave (write) within the time-out."""


class LinkClosedError(LinkError):
    """The link was closed here or by the other end (disconnected device, closed socket)."""


@runtime_checkable
class Link(Protocol):
    """A byte stream to a device (see the module docstring for the contract)."""

    url: str

    def read(self, timeout_s: float, max_bytes: int = 4096) -> bytes: ...

    def write(self, data: bytes, timeout_s: float | None = None) -> None: ...

    def close(self) -> None: ...

    def __enter__(self) -> Link: ...

    def __exit__(self, *exc: object) -> None: ...
