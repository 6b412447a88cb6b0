# SPDX-License-Identifier: Apache-2.0
"""The MAVLink client (magcal.link.mavlink) and the --mavlink command-line rules, against a
tiny fake vehicle on UDP loopback (heartbeats only) and without any vehicle."""

from __future__ import annotations

import socket
import threading

import numpy as np
import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from magcal import cli
from magcal.autopilot import vehicle
from magcal.autopilot.connection import open_autopilot
from magcal.io.result import CalibrationResult, write_result
from magcal.link import mavlink as ml
from tests.autopilot_emulator.emulator import free_udp_port

M = mavlink


class Heartbeats:
    """Sends heartbeats of the given (system, component, MAV_TYPE, MAV_AUTOPILOT) every 50 ms
    to 127.0.0.1:port until stopped."""

    def __init__(self, port: int, senders: list[tuple[int, int, int, int]]) -> None:
        self.port, self.senders = port, senders
        self.stop = threading.Event()
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.thread = threading.Thread(target=self._run, daemon=True)

    def _run(self) -> None:
        encoders = [M.MAVLink(None, srcSystem=s, srcComponent=c) for s, c, _, _ in self.senders]
        while not self.stop.wait(0.05):
            for enc, (_, _, kind, autopilot) in zip(encoders, self.senders, strict=True):
                msg = enc.heartbeat_encode(kind, autopilot, 0, 0, M.MAV_STATE_STANDBY)
                self.sock.sendto(msg.pack(enc), ("127.0.0.1", self.port))

    def __enter__(self):
        self.thread.start()
        return self

    def __exit__(self, *exc):
        self.stop.set()
        self.thread.join(2)
        self.sock.close()


GCS = (255, 190, M.MAV_TYPE_GCS, M.MAV_AUTOPILOT_INVALID)
GIMBAL = (1, 154, M.MAV_TYPE_GIMBAL, M.MAV_AUTOPILOT_INVALID)
PX4 = (1, 1, M.MAV_TYPE_QUADROTOR, M.MAV_AUTOPILOT_PX4)


def test_heartbeat_of_the_autopilot_is_picked_among_others():
    port = free_udp_port()
    with (
        ml.MavlinkClient.open(f"udpin:127.0.0.1:{port}") as client,
        Heartbeats(port, [GCS, GIMBAL, PX4]),
    ):
        hb = client.wait_heartbeat(5.0)
    assert (hb.system, hb.component, hb.autopilot) == (1, 1, M.MAV_AUTOPILOT_PX4)
    assert hb.vehicle_type == M.MAV_TYPE_QUADROTOR and hb.wire_version == 2


def test_no_autopilot_heartbeat_times_out_naming_what_was_heard():
    port = free_udp_port()
    with ml.MavlinkClient.open(f"udpin:127.0.0.1:{port}") as client, Heartbeats(port, [GCS]):
        with pytest.raises(ml.MavlinkTimeoutError, match="heard only system 255 component 190"):
            client.wait_heartbeat(0.5)


def test_an_autopilot_other_than_ardupilot_or_px4_is_refused():
    port = free_udp_port()
    generic = (1, 1, M.MAV_TYPE_QUADROTOR, M.MAV_AUTOPILOT_GENERIC)
    with (
        Heartbeats(port, [generic]),
        pytest.raises(vehicle.AutopilotError, match="works with ArduPilot .3. and PX4 .12. only"),
    ):
        with open_autopilot(f"udpin:127.0.0.1:{port}", heartbeat_timeout_s=5.0):
            pass


def test_a_parameter_nobody_answers_raises_after_the_tries():
    port = free_udp_port()
    with ml.MavlinkClient.open(f"udpin:127.0.0.1:{port}") as client, Heartbeats(port, [PX4]):
        client.wait_heartbeat(5.0)
        client._rtts.append(0.01)  # a known round trip: the shortest reply time-out
        with pytest.raises(ml.MavlinkTimeoutError, match="no answer for parameter X after 2"):
            client.param_read("X", tries=2)


@pytest.mark.parametrize(
    ("url", "match"),
    [("", "no MAVLink link given"), ("/dev/ttyNOPE0,57600", "no such device /dev/ttyNOPE0")],
)
def test_urls_that_are_no_link_are_refused(url, match):
    with pytest.raises(ml.MavlinkError, match=match):
        ml.check_mavlink_url(url)


def test_a_log_file_is_no_link(tmp_path):
    log = tmp_path / "flight.tlog"
    log.write_bytes(b"\0" * 10)
    with pytest.raises(ml.MavlinkError, match="is a file, not a link: a log is imported"):
        ml.check_mavlink_url(str(log))


# ------------------------------------------------------------------------------ command line
@pytest.mark.parametrize(
    ("argv", "match"),
    [
        (["collect", "-o", "x.csv"], "one of the arguments --port --mavlink is required"),
        (["info", "--port", "a", "--mavlink", "b"], "not allowed with argument"),
        (["verify", "--mavlink", "udpin:x:1", "--compass", "4"], "give 1, 2 or 3"),
    ],
)
def test_link_arguments_are_checked_by_the_parser(argv, match, capsys):
    with pytest.raises(SystemExit):
        cli.main(argv)
    assert match in capsys.readouterr().err


@pytest.mark.parametrize(
    ("argv", "match"),
    [
        (["info", "--port", "/dev/null", "--compass", "2"], "--compass is for an autopilot"),
        (
            ["flash", "r.json", "--port", "/dev/null", "--location", "1,2", "--reboot"],
            "--location, --reboot are for an autopilot",
        ),
        (["collect", "--port", "/dev/null", "-o", "x.csv", "--rate", "5"], "--rate is for an"),
    ],
)
def test_autopilot_options_need_mavlink(argv, match, capsys):
    assert cli.main(argv) == cli.EXIT_ERROR
    assert match in capsys.readouterr().err


def test_flash_without_a_field_strength_is_refused_before_any_link(tmp_path, capsys):
    path = tmp_path / "r.json"
    r = CalibrationResult("ml", np.eye(3), np.zeros(3), np.array([1.0, 0, 0]), 0.0)
    write_result(path, r)
    argv = ["flash", str(path), "--mavlink", "udpin:127.0.0.1:9"]
    assert cli.main(argv) == cli.EXIT_ERROR
    assert "give --location LAT,LON[,ALT_KM]" in capsys.readouterr().err
    assert cli.main([*argv, "--field", "485"]) == cli.EXIT_ERROR
    assert "with its unit" in capsys.readouterr().err


def test_old_ardupilot_that_refuses_message_intervals_gets_request_data_stream():
    from types import SimpleNamespace

    from magcal.autopilot.collect import start_stream

    calls = []
    client = SimpleNamespace(
        set_message_interval=lambda mid, us: calls.append(("interval", mid)) or M.MAV_RESULT_DENIED,
        request_data_stream=lambda sid, hz, start=True: calls.append(("stream", sid, hz)),
    )
    ap = SimpleNamespace(client=client, autopilot=vehicle.ARDUPILOT, url="x")
    assert start_stream(ap, "RAW_IMU", 50.0) == "REQUEST_DATA_STREAM"
    assert calls == [("interval", 27), ("stream", M.MAV_DATA_STREAM_RAW_SENSORS, 50)]
    px4 = SimpleNamespace(client=client, autopilot=vehicle.PX4, url="x")
    with pytest.raises(vehicle.AutopilotError, match="answered MAV_RESULT 2 to MAV_CMD_SET_MESS"):
        start_stream(px4, "SCALED_IMU", 50.0)
