# SPDX-License-Identifier: Apache-2.0
"""Links over pyserial: device and pseudo-terminal paths, ``socket://``, other pyserial URLs."""

from __future__ import annotations

import logging
import time

import serial

from magcal.link.base import (
    LINK_OPEN_TIMEOUT_S,
    LINK_READ_POLL_S,
    LINK_WRITE_TIMEOUT_S,
    Link,
    LinkClosedError,
    LinkError,
    LinkTimeoutError,
)

log = logging.getLogger(__name__)

DEFAULT_BAUDRATE = 115_200  # the firmware's UART; ignored by USB CDC, pseudo-terminals, sockets
OPEN_RETRY_INTERVAL_S = 0.1  # between attempts to open a port that is not there (yet)
# Schemes handled elsewhere (not by pyserial); --mavlink will add its opener here.
_NOT_YET = {
    "mavlink": "MAVLink links (--mavlink) are not supported yet: use --port with a serial "
    "device, pseudo-terminal or socket:// URL",
}


def _advice(url: str) -> str:
    if url.startswith("socket://"):
        return "check that the device or SIL is running and listening at that host and port"
    if "://" in url:
        return "check the URL (anything pyserial's serial_for_url accepts) and that the peer runs"
    return (
        "check the device is plugged in, the path is right (ls /dev/tty* /dev/pts/*), "
        "no other program holds the port, and you may open it (group dialout)"
    )


class SerialLink:
    """A :class:`~magcal.link.base.Link` over a pyserial port object (already open)."""

    def __init__(self, port: serial.SerialBase, url: str) -> None:
        self._port: serial.SerialBase | None = port
        self.url = url

    # -- Link
    def read(self, timeout_s: float, max_bytes: int = 4096) -> bytes:
        """At least one byte (up to max_bytes) within timeout_s, or LinkTimeoutError."""
        port = self._open_port("read")
        deadline = time.monotonic() + timeout_s
        while True:
            try:
                waiting = port.in_waiting
                data = port.read(max(1, min(max_bytes, waiting)))
            except (serial.SerialException, OSError) as exc:
                self.close()
                raise LinkClosedError(
                    f"read from {self.url}: the link failed ({exc}); {_advice(self.url)}",
                    self.url,
                ) from exc
            if data:
                return data
            if time.monotonic() >= deadline:
                raise LinkTimeoutError(
                    f"read from {self.url}: no byte within {timeout_s:.3g} s; "
                    "check the device is running and the port settings",
                    self.url,
                )

    def write(self, data: bytes, timeout_s: float | None = None) -> None:
        """Write all of data within timeout_s (default: the write time-out set at open)."""
        port = self._open_port("write")
        try:
            if timeout_s is not None and port.write_timeout != timeout_s:
                port.write_timeout = timeout_s
            n = port.write(data)
            port.flush()
        except serial.SerialTimeoutException as exc:
            raise LinkTimeoutError(
                f"write to {self.url}: {len(data)} bytes not written within "
                f"{port.write_timeout:.3g} s; check flow control and that the device reads",
                self.url,
            ) from exc
        except (serial.SerialException, OSError) as exc:
            self.close()
            raise LinkClosedError(
                f"write to {self.url}: the link failed ({exc}); {_advice(self.url)}", self.url
            ) from exc
        if n is not None and n != len(data):
            raise LinkTimeoutError(
                f"write to {self.url}: {n} of {len(data)} bytes written; check flow control",
                self.url,
            )

    def close(self) -> None:
        port, self._port = self._port, None
        if port is not None:
            try:
                port.close()
            except (serial.SerialException, OSError) as exc:  # closing is best effort
                log.debug("close %s: %s", self.url, exc)

    def __enter__(self) -> SerialLink:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _open_port(self, op: str) -> serial.SerialBase:
        if self._port is None:
            raise LinkClosedError(f"{op} {self.url}: the link is closed; open it again", self.url)
        return self._port


def open_link(
    url: str,
    timeout_s: float = LINK_OPEN_TIMEOUT_S,
    *,
    baudrate: int = DEFAULT_BAUDRATE,
    write_timeout_s: float = LINK_WRITE_TIMEOUT_S,
) -> Link:
    """Open the ``--port`` URL: a device or pseudo-terminal path, ``socket://host:port``, or
    any other pyserial URL. An open that fails is retried every OPEN_RETRY_INTERVAL_S until
    ``timeout_s`` has passed (a port that appears late, a SIL that is still starting).

    Raises LinkError naming the URL and what to check.
    """
    if not isinstance(url, str) or not url.strip():
        raise LinkError(f"open link: empty port URL {url!r}; give --port PATH or socket://H:P")
    scheme = url.split("://", 1)[0].lower() if "://" in url else ""
    if scheme in _NOT_YET:
        raise LinkError(f"open link {url}: {_NOT_YET[scheme]}", url)
    try:
        port = serial.serial_for_url(
            url,
            baudrate=baudrate,
            timeout=LINK_READ_POLL_S,
            write_timeout=write_timeout_s,
            do_not_open=True,
        )
    except (ValueError, serial.SerialException) as exc:
        raise LinkError(f"open link {url}: {exc}; {_advice(url)}", url) from exc
    # A port that is not there yet (USB re-enumerating after a reset, a SIL still starting)
    # is retried until timeout_s; pyserial's socket handler bounds each connect itself (5 s).
    deadline = time.monotonic() + timeout_s
    attempt = 0
    while True:
        attempt += 1
        try:
            port.open()
            break
        except (serial.SerialException, OSError, ValueError) as exc:
            if time.monotonic() + OPEN_RETRY_INTERVAL_S > deadline:
                raise LinkError(
                    f"open link {url}: cannot open after {attempt} attempt(s) in "
                    f"{timeout_s:.3g} s ({exc}); {_advice(url)}",
                    url,
                ) from exc
            log.info("open link %s: attempt %d failed (%s); retrying", url, attempt, exc)
            time.sleep(OPEN_RETRY_INTERVAL_S)
    log.debug("opened link %s", url)
    return SerialLink(port, url)
