# SPDX-License-Identifier: Apache-2.0
"""Byte links to a device, behind one URL factory.

``open_link(url, timeout_s)`` turns a ``--port`` URL into a :class:`Link`: a device or
pseudo-terminal path (``/dev/ttyACM0``, ``/dev/pts/5``, ``COM3``), ``socket://host:port`` or any
other URL pyserial's ``serial_for_url`` accepts (``rfc2217://``, ``loop://``, ...).
``--mavlink`` URLs (pymavlink's connection strings) carry messages, not our byte frames:
:class:`magcal.link.mavlink.MavlinkClient` opens them.
"""

from magcal.link.base import (
    LINK_OPEN_TIMEOUT_S,
    LINK_READ_POLL_S,
    Link,
    LinkClosedError,
    LinkError,
    LinkTimeoutError,
)
from magcal.link.serial_link import DEFAULT_BAUDRATE, SerialLink, open_link

__all__ = [
    "DEFAULT_BAUDRATE",
    "LINK_OPEN_TIMEOUT_S",
    "LINK_READ_POLL_S",
    "Link",
    "LinkClosedError",
    "LinkError",
    "LinkTimeoutError",
    "SerialLink",
    "open_link",
]
