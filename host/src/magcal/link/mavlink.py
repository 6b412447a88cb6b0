# SPDX-License-Identifier: Apache-2.0
"""A small MAVLink client for ArduPilot and PX4, on top of pymavlink.

:class:`MavlinkClient` is the only place magcal talks MAVLink. It opens anything
``pymavlink.mavutil.mavlink_connection`` accepts (``udpin:0.0.0.0:14550``,
``udpout:192.168.4.1:14550``, ``tcp:127.0.0.1:5760``, a serial device with its baud rate
``/dev/ttyACM0,115200`` or ``COM5,57600``), waits for the vehicle's HEARTBEAT, and offers
the few exchanges magcal needs, each with a time-out and a bounded number of tries:

- :meth:`MavlinkClient.wait_heartbeat`: the first heartbeat of an autopilot (ground stations'
  heartbeats and ``MAV_AUTOPILOT_INVALID`` components such as gimbals are skipped); it fixes
  the target system and component for everything that follows;
- :meth:`MavlinkClient.command_long`: a COMMAND_LONG answered by a COMMAND_ACK;
- :meth:`MavlinkClient.param_read` / :meth:`MavlinkClient.param_set`: PARAM_REQUEST_READ or
  PARAM_SET answered by a PARAM_VALUE of the same name (the raw wire float; decoding it is
  :mod:`magcal.autopilot.params`' job);
- :meth:`MavlinkClient.recv`: the next message of some types from the vehicle.

Time-outs: a parameter or command reply is awaited for an adaptive time, ``RTT_FACTOR`` times
the longest of the last round trips, within [``REPLY_TIMEOUT_MIN_S``, ``REPLY_TIMEOUT_MAX_S``]
(``REPLY_TIMEOUT_FIRST_S`` before any reply). A lost reply on a radio link then costs about
one round trip, not a fixed second, and a slow link still gets its time. Every wait raises
:class:`MavlinkTimeoutError` when nothing came; nothing returns ``None``.
"""

from __future__ import annotations

import logging
import os
import time
from collections import deque
from collections.abc import Callable, Collection
from dataclasses import dataclass
from typing import Any

from magcal.errors import MagcalError

log = logging.getLogger(__name__)

#: How long to wait for the vehicle's first heartbeat (autopilots send one a second).
HEARTBEAT_TIMEOUT_S = 5.0
REPLY_TIMEOUT_FIRST_S = 1.0
REPLY_TIMEOUT_MIN_S = 0.15
REPLY_TIMEOUT_MAX_S = 2.0
#: The reply time-out is this many times the longest recent round trip.
RTT_FACTOR = 4.0
#: Round trips remembered for the adaptive time-out.
RTT_HISTORY = 8
#: Tries of one parameter read (PARAM_REQUEST_READ) before giving up on it.
PARAM_READ_TRIES = 10
COMMAND_TRIES = 3
#: Our own MAVLink identity: a ground station (255) and MAV_COMP_ID_MISSIONPLANNER (190).
GCS_SYSTEM_ID = 255
GCS_COMPONENT_ID = 190
PARAM_ID_LEN = 16

_MAV_AUTOPILOT_INVALID = 8
_MAV_TYPE_GCS = 6


class MavlinkError(MagcalError):
    """A MAVLink link cannot be opened, or the vehicle did not answer as expected."""


class MavlinkTimeoutError(MavlinkError):
    """Nothing (of what was awaited) arrived within the time-out."""


@dataclass(frozen=True)
class Heartbeat:
    """The vehicle's identity from its HEARTBEAT.

    system, component : its MAVLink ids; autopilot : MAV_AUTOPILOT; vehicle_type : MAV_TYPE;
    wire_version : 1 or 2 (the MAVLink version of the packet)
    """

    system: int
    component: int
    autopilot: int
    vehicle_type: int
    base_mode: int
    custom_mode: int
    system_status: int
    wire_version: int


@dataclass(frozen=True)
class ParamValue:
    """One PARAM_VALUE: the name, the raw wire float, MAV_PARAM_TYPE, index and count."""

    name: str
    wire_value: float
    param_type: int
    index: int
    count: int


def check_mavlink_url(url: str) -> None:
    """Refuse what mavlink_connection would treat as something other than a live link.

    A regular file would be opened as a log to replay (``magcal import`` reads logs), and a
    path that does not exist would fail deep inside pyserial; both get a clear message.
    """
    if not url or not url.strip():
        raise MavlinkError("no MAVLink link given: pass --mavlink URL (e.g. udpin:0.0.0.0:14550)")
    device = url.split(",")[0]
    if os.path.isfile(device):
        raise MavlinkError(
            f"--mavlink {url}: {device} is a file, not a link: a log is imported with "
            "magcal import, a live vehicle is reached with udpin:, tcp: or a serial device"
        )
    if device.startswith("/") and not os.path.exists(device):
        raise MavlinkError(
            f"--mavlink {url}: no such device {device}: give a serial device with its baud rate "
            "(/dev/ttyACM0,115200) or a network link (udpin:0.0.0.0:14550, tcp:host:5760)"
        )


class MavlinkClient:
    """A MAVLink connection to one vehicle (see the module docstring).

    conn : a pymavlink ``mavfile`` (what ``mavutil.mavlink_connection`` returns)
    url : the connection string, for messages
    clock : a monotonic clock, s
    """

    def __init__(self, conn: Any, url: str, clock: Callable[[], float] = time.monotonic) -> None:
        self.conn = conn
        self.url = url
        self.clock = clock
        self.heartbeat: Heartbeat | None = None
        self._rtts: deque[float] = deque(maxlen=RTT_HISTORY)
        self._closed = False

    # ------------------------------------------------------------------ opening, closing
    @classmethod
    def open(cls, url: str) -> MavlinkClient:
        """Open ``url`` with pymavlink (no heartbeat awaited yet)."""
        check_mavlink_url(url)
        from pymavlink import mavutil

        try:
            conn = mavutil.mavlink_connection(
                url,
                source_system=GCS_SYSTEM_ID,
                source_component=GCS_COMPONENT_ID,
                autoreconnect=False,
            )
        except Exception as exc:  # pymavlink raises socket, serial and value errors alike
            raise MavlinkError(
                f"--mavlink {url}: cannot open the link ({exc}): check the connection string "
                "(udpin:ADDR:PORT listens, udpout:ADDR:PORT and tcp:ADDR:PORT connect, "
                "/dev/ttyACM0,115200 is a serial device with its baud rate)"
            ) from exc
        return cls(conn, url)

    def close(self) -> None:
        if not self._closed:
            self._closed = True
            try:
                self.conn.close()
            except OSError as exc:
                log.warning("closing %s: %s", self.url, exc)

    def __enter__(self) -> MavlinkClient:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    @property
    def mav(self) -> Any:
        """pymavlink's encoder (``conn.mav``), for ``*_send`` calls."""
        return self.conn.mav

    # ------------------------------------------------------------------ receiving
    def _recv_any(self, timeout_s: float) -> Any | None:
        """The next message of any type (None when none within timeout_s)."""
        msg = self.conn.recv_match(blocking=True, timeout=max(timeout_s, 0.0))
        return msg

    def _from_vehicle(self, msg: Any) -> bool:
        hb = self.heartbeat
        if hb is None:
            return True
        return msg.get_srcSystem() == hb.system and msg.get_srcComponent() == hb.component

    def recv(self, types: Collection[str], timeout_s: float) -> Any:
        """The next message of one of ``types`` from the vehicle; MavlinkTimeoutError when
        none arrives within ``timeout_s``."""
        wanted = set(types)
        deadline = self.clock() + timeout_s
        while True:
            remaining = deadline - self.clock()
            if remaining <= 0:
                break
            msg = self._recv_any(remaining)
            if msg is None:
                continue
            if msg.get_type() in wanted and self._from_vehicle(msg):
                return msg
        raise MavlinkTimeoutError(
            f"{self.url}: no {'/'.join(sorted(wanted))} from the vehicle within {timeout_s:.1f} s"
        )

    def poll(self, types: Collection[str]) -> Any | None:
        """A message of ``types`` already received (no waiting), or None."""
        wanted = set(types)
        while True:
            msg = self.conn.recv_match(blocking=False)
            if msg is None:
                return None
            if msg.get_type() in wanted and self._from_vehicle(msg):
                return msg

    def wait_heartbeat(self, timeout_s: float = HEARTBEAT_TIMEOUT_S) -> Heartbeat:
        """The first autopilot HEARTBEAT (see the module docstring); fixes the target."""
        deadline = self.clock() + timeout_s
        others: set[str] = set()
        while self.clock() < deadline:
            msg = self._recv_any(deadline - self.clock())
            if msg is None or msg.get_type() != "HEARTBEAT":
                continue
            if msg.type == _MAV_TYPE_GCS or msg.autopilot == _MAV_AUTOPILOT_INVALID:
                others.add(f"system {msg.get_srcSystem()} component {msg.get_srcComponent()}")
                continue
            wire = 2 if bytes(msg.get_msgbuf()[:1]) == b"\xfd" else 1
            self.heartbeat = Heartbeat(
                system=msg.get_srcSystem(),
                component=msg.get_srcComponent(),
                autopilot=msg.autopilot,
                vehicle_type=msg.type,
                base_mode=msg.base_mode,
                custom_mode=msg.custom_mode,
                system_status=msg.system_status,
                wire_version=wire,
            )
            self.conn.target_system = self.heartbeat.system
            self.conn.target_component = self.heartbeat.component
            return self.heartbeat
        seen = f" (heard only {', '.join(sorted(others))}, not an autopilot)" if others else ""
        raise MavlinkTimeoutError(
            f"--mavlink {self.url}: no autopilot HEARTBEAT within {timeout_s:g} s{seen}: check "
            "that the vehicle is powered and the link's address, port or baud rate (with "
            "udpin: the vehicle must send to this port)"
        )

    def _target(self) -> Heartbeat:
        if self.heartbeat is None:
            raise MavlinkError(f"{self.url}: no vehicle yet (wait_heartbeat first)")
        return self.heartbeat

    # ------------------------------------------------------------------ request / reply
    def reply_timeout_s(self) -> float:
        """How long to await one reply now (module docstring)."""
        if not self._rtts:
            return REPLY_TIMEOUT_FIRST_S
        return min(REPLY_TIMEOUT_MAX_S, max(REPLY_TIMEOUT_MIN_S, RTT_FACTOR * max(self._rtts)))

    def _exchange(
        self, send: Callable[[], None], match: Callable[[Any], bool], types: Collection[str]
    ) -> Any | None:
        """Send once and await a matching reply for reply_timeout_s; None when none came."""
        timeout = self.reply_timeout_s()
        start = self.clock()
        send()
        deadline = start + timeout
        while True:
            remaining = deadline - self.clock()
            if remaining <= 0:
                return None
            msg = self._recv_any(remaining)
            if msg is None or msg.get_type() not in types or not self._from_vehicle(msg):
                continue
            if match(msg):
                self._rtts.append(self.clock() - start)
                return msg

    def command_long(
        self, command: int, params: tuple[float, ...], tries: int = COMMAND_TRIES
    ) -> int:
        """Send COMMAND_LONG (up to 7 params) and return the COMMAND_ACK's MAV_RESULT.

        Re-sent with an incremented ``confirmation`` when no ack comes; MavlinkTimeoutError
        after ``tries`` sends without an ack."""
        hb = self._target()
        p = tuple(params) + (0.0,) * (7 - len(params))
        for attempt in range(tries):

            def send(attempt=attempt) -> None:
                self.mav.command_long_send(hb.system, hb.component, command, attempt, *p)

            ack = self._exchange(send, lambda m: m.command == command, ("COMMAND_ACK",))
            if ack is not None:
                return int(ack.result)
            log.info("%s: no COMMAND_ACK for command %d (try %d)", self.url, command, attempt + 1)
        raise MavlinkTimeoutError(
            f"{self.url}: the vehicle did not acknowledge command {command} after {tries} tries"
        )

    def param_read(self, name: str, tries: int = PARAM_READ_TRIES) -> ParamValue:
        """The vehicle's PARAM_VALUE for ``name`` (PARAM_REQUEST_READ by name).

        MavlinkTimeoutError after ``tries`` requests without an answer: the parameter does not
        exist on this vehicle, or every answer was lost."""
        hb = self._target()
        raw = _param_id_bytes(name)
        for attempt in range(tries):
            reply = self._exchange(
                lambda: self.mav.param_request_read_send(hb.system, hb.component, raw, -1),
                lambda m: _param_name(m.param_id) == name,
                ("PARAM_VALUE",),
            )
            if reply is not None:
                return _param_value(reply)
            log.info("%s: no PARAM_VALUE for %s (try %d)", self.url, name, attempt + 1)
        raise MavlinkTimeoutError(
            f"{self.url}: no answer for parameter {name} after {tries} requests"
        )

    def param_set(self, name: str, wire_value: float, param_type: int) -> ParamValue | None:
        """Send PARAM_SET once and return the PARAM_VALUE echo of ``name`` (None when none
        came within the reply time-out). The caller compares the echoed value and retries."""
        hb = self._target()
        raw = _param_id_bytes(name)
        reply = self._exchange(
            lambda: self.mav.param_set_send(hb.system, hb.component, raw, wire_value, param_type),
            lambda m: _param_name(m.param_id) == name,
            ("PARAM_VALUE",),
        )
        return None if reply is None else _param_value(reply)

    def set_message_interval(self, message_id: int, interval_us: float) -> int:
        """MAV_CMD_SET_MESSAGE_INTERVAL (511): the MAV_RESULT (interval -1 stops the message,
        0 restores the vehicle's default rate)."""
        return self.command_long(511, (float(message_id), float(interval_us)))

    def request_data_stream(self, stream_id: int, rate_hz: int, start: bool = True) -> None:
        """REQUEST_DATA_STREAM (deprecated; older ArduPilot), sent once, no reply expected."""
        hb = self._target()
        self.mav.request_data_stream_send(hb.system, hb.component, stream_id, rate_hz, int(start))


def _param_id_bytes(name: str) -> bytes:
    raw = name.encode("ascii")
    if len(raw) > PARAM_ID_LEN:
        raise MavlinkError(f"parameter name {name!r} is longer than {PARAM_ID_LEN} characters")
    return raw


def _param_name(param_id: Any) -> str:
    """PARAM_VALUE's param_id as text (pymavlink gives str or bytes, NUL-padded or not)."""
    if isinstance(param_id, (bytes, bytearray)):
        param_id = param_id.decode("ascii", errors="replace")
    return str(param_id).split("\x00", 1)[0]


def _param_value(msg: Any) -> ParamValue:
    return ParamValue(
        name=_param_name(msg.param_id),
        wire_value=float(msg.param_value),
        param_type=int(msg.param_type),
        index=int(msg.param_index),
        count=int(msg.param_count),
    )
