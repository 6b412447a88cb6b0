# SPDX-License-Identifier: Apache-2.0
"""An open autopilot: the MAVLink client, who the vehicle is, and its parameters.

``open_autopilot(url)`` opens the link, waits for the vehicle's HEARTBEAT, refuses anything
but ArduPilot and PX4, and gives an :class:`Autopilot` whose :meth:`Autopilot.read` and
:meth:`Autopilot.write` speak values (not wire floats: the autopilot's encoding of integers
is handled here, :mod:`magcal.autopilot.params`).
"""

from __future__ import annotations

import contextlib
import logging
from collections.abc import Iterator
from dataclasses import dataclass

from magcal.autopilot import params, vehicle
from magcal.link.mavlink import (
    HEARTBEAT_TIMEOUT_S,
    PARAM_READ_TRIES,
    Heartbeat,
    MavlinkClient,
    MavlinkError,
    MavlinkTimeoutError,
)

log = logging.getLogger(__name__)

#: How long to wait for AUTOPILOT_VERSION after asking (it is only shown, never needed).
VERSION_TIMEOUT_S = 1.0
MAV_CMD_REQUEST_MESSAGE = 512
MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN = 246
AUTOPILOT_VERSION_ID = 148
MAV_RESULT_ACCEPTED = 0


@dataclass
class Autopilot:
    """A vehicle on an open link. ``autopilot``: vehicle.ARDUPILOT or vehicle.PX4."""

    client: MavlinkClient
    heartbeat: Heartbeat
    autopilot: str

    @property
    def url(self) -> str:
        return self.client.url

    @property
    def name(self) -> str:
        return vehicle.AUTOPILOT_NAMES[self.autopilot]

    @property
    def encoding(self) -> str:
        return vehicle.ENCODING[self.autopilot]

    def describe(self) -> str:
        hb = self.heartbeat
        return (
            f"{self.name} {vehicle.vehicle_type_name(hb.vehicle_type).lower()}, system "
            f"{hb.system} component {hb.component}, MAVLink {hb.wire_version}"
        )

    def read(self, name: str, tries: int | None = None) -> params.ParamEntry:
        """The parameter's value as held. MavlinkTimeoutError when the vehicle never answered
        (no such parameter, or every reply lost): where a parameter may be hidden or absent,
        the caller catches it (:func:`magcal.autopilot.vehicle.read_optional`)."""
        pv = self.client.param_read(name, PARAM_READ_TRIES if tries is None else tries)
        value = params.decode(pv.wire_value, pv.param_type, self.encoding, name)
        return params.ParamEntry(name, value, pv.param_type)

    def write_once(self, name: str, value: float, param_type: int) -> params.ParamEntry | None:
        """One PARAM_SET of ``value``; the echoed value (decoded), None when no echo came."""
        wire = params.encode(value, param_type, self.encoding, name)
        pv = self.client.param_set(name, wire, param_type)
        if pv is None:
            return None
        return params.ParamEntry(
            name, params.decode(pv.wire_value, pv.param_type, self.encoding, name), pv.param_type
        )

    def firmware(self) -> str | None:
        """The firmware version from AUTOPILOT_VERSION ("4.5.7 official"), None when the
        vehicle does not answer within VERSION_TIMEOUT_S (it is shown, never needed)."""
        hb = self.heartbeat
        self.client.mav.command_long_send(
            hb.system,
            hb.component,
            MAV_CMD_REQUEST_MESSAGE,
            0,
            AUTOPILOT_VERSION_ID,
            0,
            0,
            0,
            0,
            0,
            0,
        )
        try:
            msg = self.client.recv(("AUTOPILOT_VERSION",), VERSION_TIMEOUT_S)
        except MavlinkTimeoutError:
            return None
        return vehicle.firmware_text(msg.flight_sw_version)

    def reboot(self, timeout_s: float = 3 * HEARTBEAT_TIMEOUT_S) -> None:
        """MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN (reboot the autopilot), then wait for its
        heartbeat again. MavlinkError when it refuses; MavlinkTimeoutError when it does not
        come back."""
        result = self.client.command_long(MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN, (1.0,))
        if result != MAV_RESULT_ACCEPTED:
            raise MavlinkError(
                f"{self.url}: the vehicle refused to reboot (MAV_RESULT {result}): is it armed? "
                "reboot it by hand"
            )
        self.client.wait_heartbeat(timeout_s)


@contextlib.contextmanager
def open_autopilot(
    url: str, heartbeat_timeout_s: float = HEARTBEAT_TIMEOUT_S
) -> Iterator[Autopilot]:
    """Open ``url``, identify the vehicle; the link is closed on the way out."""
    client = MavlinkClient.open(url)
    try:
        hb = client.wait_heartbeat(heartbeat_timeout_s)
        autopilot = vehicle.autopilot_of(hb.autopilot, f"--mavlink {url}")
        yield Autopilot(client, hb, autopilot)
    finally:
        client.close()
