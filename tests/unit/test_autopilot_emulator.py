# SPDX-License-Identifier: Apache-2.0
"""The autopilot emulator over its UDP link, with plain pymavlink as the client.

Rates are counted in simulated time (the messages' time fields); absences are checked
against later messages on the same ordered loopback link (heartbeats, other replies), never
against the wall clock. Timeouts are generous and only bound a failure.
"""

import struct
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import scipy.linalg
from pymavlink import mavutil

from magcal.autopilot import mapping, rotations
from tests.autopilot_emulator import AutopilotEmulator, EmulatorError
from tests.autopilot_emulator.emulator import _attitude_ned, free_udp_port
from tests.autopilot_emulator.world import heading_errors_rad, rms_deg

TIMEOUT_S = 20.0
PATH_S = 30.0  # short paths keep construction fast
SPEEDUP = 10.0
M = mavutil.mavlink
REPO = Path(__file__).resolve().parents[2]


@pytest.fixture(params=["ardupilot", "px4"])
def personality(request):
    return request.param


def _emulator(personality, **kw):
    kw.setdefault("path_s", PATH_S)
    kw.setdefault("speedup", SPEEDUP)
    return AutopilotEmulator(personality, **kw)


def _connect(emu):
    link = mavutil.mavlink_connection(emu.url, source_system=255, source_component=190)
    hb = link.recv_match(type="HEARTBEAT", blocking=True, timeout=TIMEOUT_S)
    assert hb is not None, "no HEARTBEAT from the emulator"
    return link, hb


def _recv(link, kinds, timeout=TIMEOUT_S):
    msg = link.recv_match(type=kinds, blocking=True, timeout=timeout)
    assert msg is not None, f"nothing of {kinds} within {timeout} s"
    return msg


def _recv_until_heartbeats(link, kinds, heartbeats=2):
    """Messages of ``kinds`` that arrive before ``heartbeats`` more heartbeats (≥ 1 s of
    simulated time each): on the ordered link, what has not come by then was never sent."""
    out, seen = [], 0
    while seen < heartbeats:
        msg = _recv(link, [*kinds, "HEARTBEAT"])
        if msg.get_type() == "HEARTBEAT":
            seen += 1
        else:
            out.append(msg)
    return out


def _param_value(msg, personality):
    """A PARAM_VALUE's value as the autopilot means it (PX4 INT32: bytewise)."""
    if personality == "px4" and msg.param_type == M.MAV_PARAM_TYPE_INT32:
        return float(struct.unpack("<i", struct.pack("<f", msg.param_value))[0])
    return float(msg.param_value)


def _command(link, cmd, *params):
    link.mav.command_long_send(1, 1, cmd, 0, *(list(params) + [0] * (7 - len(params))))
    while True:
        ack = _recv(link, ["COMMAND_ACK"])
        if ack.command == cmd:
            return ack


def test_heartbeat_identifies_the_autopilot(personality):
    with _emulator(personality) as emu:
        link, hb = _connect(emu)
        link.mav.heartbeat_send(M.MAV_TYPE_GCS, M.MAV_AUTOPILOT_INVALID, 0, 0, 0)
        hb2 = _recv(link, ["HEARTBEAT"])  # the GCS heartbeat is taken without fuss
        link.close()
        emu.check()
    expected = {"ardupilot": M.MAV_AUTOPILOT_ARDUPILOTMEGA, "px4": M.MAV_AUTOPILOT_PX4}
    assert hb.autopilot == hb2.autopilot == expected[personality]
    assert hb.type == M.MAV_TYPE_QUADROTOR
    assert (hb.get_srcSystem(), hb.get_srcComponent()) == (1, M.MAV_COMP_ID_AUTOPILOT1)
    assert emu.gcs_heartbeats >= 1


def test_param_list_has_every_parameter_with_its_type_and_value(personality):
    with _emulator(personality, compasses=2) as emu:
        link, _ = _connect(emu)
        link.mav.param_request_list_send(1, 1)
        got = {}
        for msg in _recv_until_heartbeats(link, ["PARAM_VALUE"]):
            got[msg.param_id] = msg
        expected = emu.params
        link.close()
    if personality == "px4":
        hash_check = got.pop("_HASH_CHECK")
        assert hash_check.param_index == 65535
    assert set(got) == set(expected)
    count = len(expected)
    assert sorted(m.param_index for m in got.values()) == list(range(count))
    assert {m.param_count for m in got.values()} == {count}
    for name, msg in got.items():
        assert _param_value(msg, personality) == expected[name], name
    if personality == "ardupilot":
        assert got["COMPASS_ORIENT"].param_type == M.MAV_PARAM_TYPE_INT8
        assert got["COMPASS_OFFS_MAX"].param_type == M.MAV_PARAM_TYPE_INT16
        assert got["COMPASS_DEV_ID"].param_type == M.MAV_PARAM_TYPE_INT32
        assert got["COMPASS_OFS_X"].param_type == M.MAV_PARAM_TYPE_REAL32
        assert got["COMPASS_DEV_ID"].param_value == 97539.0  # a float cast, not bytewise
        assert "CUST_ROT1_ROLL" not in got  # hidden while CUST_ROT_ENABLE = 0
        assert "SIM_MAG1_OFS_X" in got and "COMPASS_OFS2_X" in got
    else:
        assert got["CAL_MAG0_ROT"].param_type == M.MAV_PARAM_TYPE_INT32
        assert got["CAL_MAG0_XOFF"].param_type == M.MAV_PARAM_TYPE_REAL32
        assert expected["CAL_MAG1_ROT"] == -1.0  # internal compass
        assert [m.param_index for m in sorted(got.values(), key=lambda m: m.param_id)] == list(
            range(count)
        )  # name order


def test_param_read_by_name_and_index_and_unknown_names(personality):
    name = "COMPASS_OFS_Y" if personality == "ardupilot" else "CAL_MAG0_YOFF"
    with _emulator(personality) as emu:
        link, _ = _connect(emu)
        index = (
            list(emu.params).index(name)
            if personality == "ardupilot"
            else sorted(emu.params).index(name)
        )
        link.mav.param_request_read_send(1, 1, b"NO_SUCH_PARAM", -1)
        link.mav.param_request_read_send(1, 1, name.encode(), -1)
        by_name = _recv(link, ["PARAM_VALUE"])
        link.mav.param_request_read_send(1, 1, b"", index)
        by_index = _recv(link, ["PARAM_VALUE"])
        link.mav.param_request_read_send(1, 1, b"", 10_000)
        link.mav.param_request_read_send(1, 1, name.encode(), -1)
        after_bad_index = _recv(link, ["PARAM_VALUE", "STATUSTEXT"])
        value = emu.params[name]
        link.close()
    assert by_name.param_id == by_index.param_id == name  # no answer to the unknown name
    assert by_name.param_value == by_index.param_value == pytest.approx(value, abs=0)
    assert by_index.param_index == index
    assert by_name.param_index == (65535 if personality == "ardupilot" else index)
    if personality == "px4":
        assert after_bad_index.get_type() == "STATUSTEXT"
        assert "unknown param ID: 10000" in after_bad_index.text
    else:
        assert after_bad_index.get_type() == "PARAM_VALUE"  # ArduPilot: silence


def test_ardupilot_param_set_round_trip_and_rules():
    with _emulator("ardupilot") as emu:
        link, _ = _connect(emu)
        sets = [
            ("COMPASS_OFS_X", 123.456, M.MAV_PARAM_TYPE_REAL32),
            ("COMPASS_ORIENT", 5.999, M.MAV_PARAM_TYPE_INT8),  # +0.01, truncated: 6
            ("COMPASS_OFFS_MAX", 40000.0, M.MAV_PARAM_TYPE_INT16),  # constrained
            ("NO_SUCH_PARAM", 1.0, M.MAV_PARAM_TYPE_REAL32),  # ignored, no answer
            ("COMPASS_DEV_ID", 97539.0, M.MAV_PARAM_TYPE_INT32),
        ]
        replies = []
        for name, value, kind in sets:
            link.mav.param_set_send(1, 1, name.encode(), value, kind)
            if name != "NO_SUCH_PARAM":
                replies.append(_recv(link, ["PARAM_VALUE"]))
        params = emu.params
        link.close()
    assert [r.param_id for r in replies] == [
        "COMPASS_OFS_X", "COMPASS_ORIENT", "COMPASS_OFFS_MAX", "COMPASS_DEV_ID"
    ]  # fmt: skip
    assert replies[0].param_value == float(np.float32(123.456)) == params["COMPASS_OFS_X"]
    assert replies[1].param_value == 6.0 == params["COMPASS_ORIENT"]
    assert replies[2].param_value == 32767.0
    assert all(r.param_index == 65535 for r in replies)  # send_parameter_value: index -1


def test_px4_param_set_is_bytewise_and_invalid_rotation_is_rewritten():
    with _emulator("px4") as emu:
        link, _ = _connect(emu)
        as_float = struct.unpack("<f", struct.pack("<i", 2))[0]
        link.mav.param_set_send(1, 1, b"CAL_MAG0_ROT", as_float, M.MAV_PARAM_TYPE_INT32)
        rot = _recv(link, ["PARAM_VALUE"])
        link.mav.param_set_send(1, 1, b"CAL_MAG0_XOFF", 0.125, M.MAV_PARAM_TYPE_REAL32)
        off = _recv(link, ["PARAM_VALUE"])
        bad = struct.unpack("<f", struct.pack("<i", 99))[0]
        link.mav.param_set_send(1, 1, b"CAL_MAG0_ROT", bad, M.MAV_PARAM_TYPE_INT32)
        echo, rewrite = _recv(link, ["PARAM_VALUE"]), _recv(link, ["PARAM_VALUE"])
        link.mav.param_set_send(1, 1, b"NO_SUCH_PARAM", 1.0, M.MAV_PARAM_TYPE_REAL32)
        unknown = _recv(link, ["STATUSTEXT"])
        params = emu.params
        link.close()
    assert _param_value(rot, "px4") == 2.0 and rot.param_type == M.MAV_PARAM_TYPE_INT32
    assert off.param_value == 0.125 == params["CAL_MAG0_XOFF"]
    assert _param_value(echo, "px4") == 99.0  # the value set goes out first ...
    assert _param_value(rewrite, "px4") == 0.0 == params["CAL_MAG0_ROT"]  # ... then the reset
    assert unknown.text == "[pm] unknown param: NO_SUCH_PARAM"


def test_param_value_loss_fraction_is_seeded():
    received = []
    for _ in range(2):
        with _emulator("ardupilot", seed=5, param_value_loss=0.3) as emu:
            link, _ = _connect(emu)
            link.mav.param_request_list_send(1, 1)
            names = {m.param_id for m in _recv_until_heartbeats(link, ["PARAM_VALUE"])}
            stats, total = emu.stats, len(emu.params)
            link.close()
        received.append(names)
        assert len(names) == stats["PARAM_VALUE"]  # nothing lost on loopback
        assert len(names) + stats["PARAM_VALUE_DROPPED"] == total
        assert 0.15 < stats["PARAM_VALUE_DROPPED"] / total < 0.45
    assert received[0] == received[1]  # the same seed drops the same messages


def test_set_message_interval_sets_the_rate_in_simulated_time(personality):
    mid, kind, time_field, per_s = {
        "ardupilot": (M.MAVLINK_MSG_ID_RAW_IMU, "RAW_IMU", "time_usec", 1e6),
        "px4": (M.MAVLINK_MSG_ID_SCALED_IMU, "SCALED_IMU", "time_boot_ms", 1e3),
    }[personality]
    counts = []
    with _emulator(personality) as emu:
        link, _ = _connect(emu)
        for hz in (50, 10):
            ack = _command(link, M.MAV_CMD_SET_MESSAGE_INTERVAL, mid, 1e6 / hz)
            assert ack.result == M.MAV_RESULT_ACCEPTED
            times = []
            while not times or times[-1] - times[0] < 2.0:
                times.append(getattr(_recv(link, [kind]), time_field) / per_s)
            counts.append((len(times) - 1) / (times[-1] - times[0]))
        link.mav.command_long_send(1, 1, M.MAV_CMD_GET_MESSAGE_INTERVAL, 0, mid, 0, 0, 0, 0, 0, 0)
        interval = _recv(link, ["MESSAGE_INTERVAL"])
        ack = _command(link, M.MAV_CMD_SET_MESSAGE_INTERVAL, mid, -1)
        after_off = _recv_until_heartbeats(link, [kind])
        unknown = _command(link, M.MAV_CMD_SET_MESSAGE_INTERVAL, 9999, 1e5)
        link.close()
    assert counts == [pytest.approx(50.0, rel=1e-6), pytest.approx(10.0, rel=1e-6)]
    assert (interval.message_id, interval.interval_us) == (mid, 100_000)
    assert ack.result == M.MAV_RESULT_ACCEPTED and after_off == []
    assert unknown.result == M.MAV_RESULT_FAILED


def test_ardupilot_request_data_stream_starts_the_raw_sensor_group():
    with _emulator("ardupilot", compasses=3) as emu:
        link, _ = _connect(emu)
        link.mav.request_data_stream_send(1, 1, M.MAV_DATA_STREAM_RAW_SENSORS, 20, 1)
        times = {"RAW_IMU": [], "SCALED_IMU2": [], "SCALED_IMU3": []}
        while min(len(t) for t in times.values()) < 21:
            msg = _recv(link, list(times))
            stamp = msg.time_usec * 1e-6 if msg.get_type() == "RAW_IMU" else msg.time_boot_ms * 1e-3
            times[msg.get_type()].append(stamp)
        link.mav.request_data_stream_send(1, 1, M.MAV_DATA_STREAM_ALL, 0, 0)
        _recv(link, ["HEARTBEAT"])  # anything in flight before the stop has arrived
        after_stop = _recv_until_heartbeats(link, list(times))
        link.close()
    for t in times.values():
        assert np.diff(t[:21]) == pytest.approx(np.full(20, 0.05), abs=1e-9)
    assert after_stop == []


def test_attitude_is_relative_to_ned():
    # body FRD level, nose north: R_nb maps x→north, y (right)→east = −west, z (down)→−up
    assert _attitude_ned(np.diag([1.0, -1.0, -1.0])) == pytest.approx((0.0, 0.0, 0.0))
    east = np.array([[0.0, -1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])  # nose east
    assert _attitude_ned(east) == pytest.approx((0.0, 0.0, np.pi / 2))
    nose_up = np.array([[0.0, 0.0, 1.0], [0.0, -1.0, 0.0], [1.0, 0.0, 0.0]])  # x up, z north
    assert _attitude_ned(nose_up) == pytest.approx((0.0, np.pi / 2, 0.0))


def test_the_vehicle_holds_still_after_the_path():
    emu = _emulator("px4", path_s=3.0, mag_noise=0.0)
    n = len(emu._world)
    late = [emu._stream_message(M.MAVLINK_MSG_ID_HIGHRES_IMU, k) for k in (n + 10, 5 * n + 3)]
    last = emu._stream_message(M.MAVLINK_MSG_ID_HIGHRES_IMU, n - 1)
    for msg in late:
        assert np.linalg.norm([msg.xgyro, msg.ygyro, msg.zgyro]) < 0.05  # bias + noise
        assert np.linalg.norm([msg.xacc, msg.yacc, msg.zacc]) == pytest.approx(9.81, abs=0.1)
        np.testing.assert_allclose(
            [msg.xmag, msg.ymag, msg.zmag], [last.xmag, last.ymag, last.zmag], rtol=1e-6
        )


def test_streams_carry_the_field_where_each_autopilot_corrects_it(personality):
    """Noise-free compass: ArduPilot's RAW_IMU and PX4's HIGHRES_IMU carry the field
    corrected with the parameters in force; PX4's SCALED_IMU the raw sensor field ×1000."""
    with _emulator(personality, mag_noise=0.0) as emu:
        link, _ = _connect(emu)
        truth = emu.truth.compass(1)
        params = emu.params
        world = emu._world
        ids = (
            [M.MAVLINK_MSG_ID_RAW_IMU]
            if personality == "ardupilot"
            else [M.MAVLINK_MSG_ID_SCALED_IMU, M.MAVLINK_MSG_ID_HIGHRES_IMU]
        )
        for mid in ids:
            _command(link, M.MAV_CMD_SET_MESSAGE_INTERVAL, mid, 1e5)
        kinds = ["RAW_IMU"] if personality == "ardupilot" else ["SCALED_IMU", "HIGHRES_IMU"]
        msgs = [_recv(link, kinds) for _ in range(20)]
        link.close()
    for msg in msgs:
        if msg.get_type() == "SCALED_IMU":
            k = round(msg.time_boot_ms * 1e-3 * world.rate_hz)
        else:
            k = round(msg.time_usec * 1e-6 * world.rate_hz)
        raw = truth.D @ world.field_body(k) + truth.o
        mag = np.array([msg.xmag, msg.ymag, msg.zmag], dtype=float)
        if msg.get_type() == "RAW_IMU":
            expected = mapping.ardupilot_correct(raw, params)[0]
            np.testing.assert_array_equal(mag, np.trunc(expected))  # int16 cast: truncation
        elif msg.get_type() == "SCALED_IMU":
            np.testing.assert_array_equal(mag, np.trunc(raw * 1000.0))
        else:
            expected = mapping.px4_correct(raw, params)[0]
            np.testing.assert_allclose(mag, expected, rtol=1e-6)  # float32 field
            np.testing.assert_allclose(
                [msg.xacc, msg.yacc, msg.zacc], world.imu(k, 0)[0], rtol=1e-6, atol=1e-6
            )


def _exact_ardupilot(emu):
    """Parameters that invert compass 1's truth: ``F D⁻¹ = P U`` (left polar) ⇒ custom
    rotation U, ``M = P``, ``OFS = −U o``."""
    t = emu.truth.compass(1)
    U, P = scipy.linalg.polar(emu.field_strength * np.linalg.inv(t.D), side="left")
    roll, pitch, yaw = rotations.matrix_to_euler_deg(U)
    ofs = -U @ t.o
    values = {"CUST_ROT_ENABLE": 1, "CUST_ROT1_ROLL": roll, "CUST_ROT1_PITCH": pitch}
    values |= {"CUST_ROT1_YAW": yaw, "COMPASS_SCALE": 1.0}
    values |= {f"COMPASS_OFS_{a}": ofs[i] for i, a in enumerate("XYZ")}
    values |= {f"COMPASS_DIA_{a}": P[i, i] for i, a in enumerate("XYZ")}
    values |= {"COMPASS_ODI_X": P[0, 1], "COMPASS_ODI_Y": P[0, 2], "COMPASS_ODI_Z": P[1, 2]}
    return values, U, P, ofs


def test_truth_is_sitl_formula_and_exact_parameters_give_zero_heading_error():
    with _emulator("ardupilot", seed=3) as emu:  # no start(): nothing on the link needed
        before = emu.heading_error_deg(1)
        values, U, P, ofs = _exact_ardupilot(emu)
        p, t = emu.params, emu.truth.compass(1)
        # the same, independently, from the SITL parameters and the hidden misalignment
        s = p["SIM_MAG1_SCALING"]
        E = np.array(
            [
                [p["SIM_MAG1_DIA_X"], p["SIM_MAG1_ODI_X"], p["SIM_MAG1_ODI_Y"]],
                [p["SIM_MAG1_ODI_X"], p["SIM_MAG1_DIA_Y"], p["SIM_MAG1_ODI_Z"]],
                [p["SIM_MAG1_ODI_Y"], p["SIM_MAG1_ODI_Z"], p["SIM_MAG1_DIA_Z"]],
            ]
        )
        np.testing.assert_allclose(P, E / s, atol=1e-9)
        np.testing.assert_allclose(U, t.R_sensor_to_body, atol=1e-9)
        np.testing.assert_allclose(ofs, s * np.array([p[f"SIM_MAG1_OFS_{a}"] for a in "XYZ"]),
                                   atol=1e-6)  # fmt: skip
        assert rotations.rotation_angle_deg(t.R_sensor_to_body, rotations.ardupilot_matrix(
            int(p["SIM_MAG1_ORIENT"]))) == pytest.approx(3.0, abs=1e-9)  # fmt: skip
        # ArduPilot builds the custom matrix at first use: angles before COMPASS_ORIENT
        emu.apply_params(values)
        emu.apply_params({"COMPASS_ORIENT": 101})
        after = emu.heading_error_deg(1)
        emu.apply_params({"CUST_ROT1_YAW": values["CUST_ROT1_YAW"] + 10.0})
        stale = emu.heading_error_deg(1)  # RebootRequired: still the old matrix
        emu.reboot()
        rebooted = emu.heading_error_deg(1)
    assert before > 2.0
    assert after < 1e-3  # float32 parameters: about 1e-5 deg
    assert stale == after
    assert rebooted > 3.0


def test_px4_exact_parameters_give_zero_heading_error():
    with _emulator("px4", seed=4, compasses=2) as emu:
        before = [emu.heading_error_deg(n) for n in (1, 2)]
        for n in (1, 2):
            t = emu.truth.compass(n)
            U, P = scipy.linalg.polar(emu.field_strength * np.linalg.inv(t.D), side="right")
            near = rotations.nearest(U, "px4")
            assert near.angle_deg < 1e-6  # PX4's default: no misalignment
            i = n - 1
            values = {f"CAL_MAG{i}_ROT": near.index if n == 1 else -1}
            values |= {f"CAL_MAG{i}_{a}OFF": t.o[j] for j, a in enumerate("XYZ")}
            values |= {f"CAL_MAG{i}_{a}SCALE": P[j, j] for j, a in enumerate("XYZ")}
            values |= {f"CAL_MAG{i}_XODIAG": P[0, 1], f"CAL_MAG{i}_YODIAG": P[0, 2]}
            values |= {f"CAL_MAG{i}_ZODIAG": P[1, 2]}
            emu.apply_params(values)
        emu.reboot()  # changes within PX4's 0.01 threshold need a reboot to take effect
        after = [emu.heading_error_deg(n) for n in (1, 2)]
    assert min(before) > 2.0
    assert max(after) < 1e-3


def test_heading_error_is_the_rms_over_the_path_of_the_corrected_field():
    with _emulator("ardupilot", seed=2) as emu:
        world, t, p = emu._world, emu.truth.compass(1), emu.params
        idx = world.heading_attitudes()
        corrected = mapping.ardupilot_correct(world.m_b[idx] @ t.D.T + t.o, p)
        expected = rms_deg(heading_errors_rad(world.R_nb[idx], corrected))
        assert emu.heading_error_deg(1) == pytest.approx(expected, rel=1e-12)


def test_request_message_autopilot_version_and_reboot_command(personality):
    with _emulator(personality) as emu:
        link, _ = _connect(emu)
        ack = _command(link, M.MAV_CMD_REQUEST_MESSAGE, M.MAVLINK_MSG_ID_AUTOPILOT_VERSION)
        version = _recv(link, ["AUTOPILOT_VERSION"])
        reboot = _command(link, M.MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN, 1)
        other = _command(link, M.MAV_CMD_DO_START_MAG_CAL)
        link.close()
    assert ack.result == reboot.result == M.MAV_RESULT_ACCEPTED
    assert other.result == M.MAV_RESULT_UNSUPPORTED
    bytewise = M.MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_BYTEWISE
    assert bool(version.capabilities & bytewise) == (personality == "px4")


def test_stop_is_clean_and_bad_arguments_are_refused():
    emu = _emulator("px4").start()
    with pytest.raises(EmulatorError, match="already started"):
        emu.start()
    emu.stop()
    emu.stop()  # idempotent
    with pytest.raises(ValueError, match="personality"):
        AutopilotEmulator("inav")
    with pytest.raises(ValueError, match="speedup"):
        AutopilotEmulator("px4", speedup=0)
    with pytest.raises(ValueError, match="param_value_loss"):
        AutopilotEmulator("px4", param_value_loss=1.5)
    with pytest.raises(KeyError, match="CUST_ROT1_ROLL"):
        _emulator("ardupilot").apply_params({"CUST_ROT1_ROLL": 1.0})  # hidden: not enabled


def test_command_line_runs_an_emulator():
    port = free_udp_port()
    link = mavutil.mavlink_connection(f"udpin:127.0.0.1:{port}", source_system=255)
    proc = subprocess.Popen(
        [sys.executable, "-m", "tests.autopilot_emulator", "--personality", "px4",
         "--port", str(port), "--seed", "1", "--duration", "30"],
        cwd=REPO, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
    )  # fmt: skip
    try:
        hb = link.recv_match(type="HEARTBEAT", blocking=True, timeout=TIMEOUT_S)
    finally:
        proc.terminate()
        proc.wait(timeout=TIMEOUT_S)
        link.close()
    assert hb is not None and hb.autopilot == M.MAV_AUTOPILOT_PX4
