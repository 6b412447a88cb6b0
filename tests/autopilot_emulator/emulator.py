# SPDX-License-Identifier: Apache-2.0
"""The emulator: a thread that speaks MAVLink 2 over UDP loopback as ArduPilot or PX4 would.

Link: the emulator sends from an ephemeral port on 127.0.0.1 to ``127.0.0.1:PORT`` (as SITL
sends to a ground station); the client listens with ``udpin:127.0.0.1:PORT`` (``emu.url``) and
answers to the address the packets came from. System id 1, component id 1
(MAV_COMP_ID_AUTOPILOT1); messages addressed to another system or component are ignored.

Clock: simulated time runs ``speedup`` times faster than the wall clock from :meth:`start`
(sample k of the world is at ``k / SIM_RATE_HZ`` s). Every message carries the time of the
sample it was made from (``time_usec``/``time_boot_ms``), so rates and time stamps are exact
in simulated time even when the emulator lags behind the wall clock (it then catches up with
bursts of at most :data:`MAX_MESSAGES_PER_TICK` messages between reads of the socket).

Messages sent (see the package docstring for units and frames): HEARTBEAT (1 Hz),
PARAM_VALUE, COMMAND_ACK, STATUSTEXT (PX4 parameter errors), AUTOPILOT_VERSION and
MESSAGE_INTERVAL on request, and the streams of :data:`STREAMS`, all off until requested
with MAV_CMD_SET_MESSAGE_INTERVAL (or, ArduPilot only, REQUEST_DATA_STREAM).
"""

from __future__ import annotations

import math
import select
import socket
import struct
import threading
import time
import zlib
from collections.abc import Callable

import numpy as np
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from tests.autopilot_emulator import personalities
from tests.autopilot_emulator.params import ParamStore
from tests.autopilot_emulator.world import (
    PATH_S,
    SIM_RATE_HZ,
    heading_errors_rad,
    make_world,
    rms_deg,
)

GRAVITY_MSS = 9.80665  # ArduPilot GRAVITY_MSS, PX4 CONSTANTS_ONE_G
SYSTEM_ID = 1
COMPONENT_ID = mavlink.MAV_COMP_ID_AUTOPILOT1
HOST = "127.0.0.1"
HEARTBEAT_INTERVAL_US = 1_000_000
LOOP_TICK_S = 0.002
MAX_MESSAGES_PER_TICK = 200
PARAMS_PER_TICK = 10
STOP_TIMEOUT_S = 5.0
SOCKET_BUFFER_BYTES = 1 << 20
IMU_TEMPERATURE_CDEG = 2500

M = mavlink
#: Streamed messages per personality (message id → name).
STREAMS = {
    "ardupilot": {
        M.MAVLINK_MSG_ID_RAW_IMU: "RAW_IMU",
        M.MAVLINK_MSG_ID_SCALED_IMU2: "SCALED_IMU2",
        M.MAVLINK_MSG_ID_SCALED_IMU3: "SCALED_IMU3",
        M.MAVLINK_MSG_ID_ATTITUDE: "ATTITUDE",
    },
    "px4": {
        M.MAVLINK_MSG_ID_SCALED_IMU: "SCALED_IMU",
        M.MAVLINK_MSG_ID_SCALED_IMU2: "SCALED_IMU2",
        M.MAVLINK_MSG_ID_SCALED_IMU3: "SCALED_IMU3",
        M.MAVLINK_MSG_ID_HIGHRES_IMU: "HIGHRES_IMU",
        M.MAVLINK_MSG_ID_ATTITUDE: "ATTITUDE",
    },
}
#: (major, minor, patch) reported in AUTOPILOT_VERSION.
VERSIONS = {"ardupilot": (4, 5, 7), "px4": (1, 15, 4)}
#: ArduPilot REQUEST_DATA_STREAM groups (GCS_Common.cpp): stream id → messages.
AP_DATA_STREAMS = {
    M.MAV_DATA_STREAM_RAW_SENSORS: (
        M.MAVLINK_MSG_ID_RAW_IMU,
        M.MAVLINK_MSG_ID_SCALED_IMU2,
        M.MAVLINK_MSG_ID_SCALED_IMU3,
    ),
    M.MAV_DATA_STREAM_EXTRA1: (M.MAVLINK_MSG_ID_ATTITUDE,),
}


class EmulatorError(RuntimeError):
    """The emulator's thread failed or did not stop."""


def free_udp_port(host: str = HOST) -> int:
    """A UDP port that was free a moment ago (bind to port 0 and release it)."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind((host, 0))
        return int(s.getsockname()[1])


def _i16(values: np.ndarray) -> list[int]:
    """C's float → int16_t conversion as the autopilots' message packing does it: truncation
    toward zero (clipped to the range, where C would be undefined)."""
    return [max(-32768, min(32767, int(v))) for v in np.asarray(values, dtype=float).tolist()]


def _raw_payload(msg: mavlink.MAVLink_message) -> bytes:
    """A received message's payload bytes as sent (PARAM_SET's float field may hold an
    int32's bytes, which a Python float cannot always carry). From the frame: pymavlink's
    get_payload() is offset by the MAVLink 1 header length for MAVLink 2 frames."""
    buf = bytes(msg.get_msgbuf())
    header = 10 if buf[0] == mavlink.PROTOCOL_MARKER_V2 else 6
    return buf[header : header + buf[1]]


def _attitude_ned(R_nb: np.ndarray) -> tuple[float, float, float]:
    """(roll, pitch, yaw) rad of the body (FRD) relative to NED from magcal's R_nb (n = x north,
    y west, z up): ``R_ned_b = diag(1, −1, −1) R_nb``, Euler 3-2-1."""
    R = np.diag([1.0, -1.0, -1.0]) @ R_nb
    roll = math.atan2(R[2, 1], R[2, 2])
    pitch = -math.asin(max(-1.0, min(1.0, R[2, 0])))
    yaw = math.atan2(R[1, 0], R[0, 0])
    return roll, pitch, yaw


class AutopilotEmulator:
    """An emulated ArduPilot or PX4 autopilot on UDP loopback; see the package docstring.

    personality      : "ardupilot" or "px4"
    seed             : seeds the compass errors, the motion, the noise and the PARAM_VALUE loss
    port             : UDP port the client listens on (default: a free one)
    speedup          : simulated seconds per wall-clock second
    param_value_loss : fraction of PARAM_VALUE messages dropped (seeded), for lossy-link tests
    compasses        : 1–3 compasses present (parameters of all three are listed)
    motion           : "tumble", "yaw-only" or "small" (magcal.sim.trajectory)
    misalignment_deg : hidden compass-to-IMU misalignment of the external compass (default:
                       ArduPilot 3°, PX4 0° since PX4 cannot represent one)
    path_s           : length of the simulated path, s; the vehicle then holds still
    mag_noise        : magnetometer noise σ in raw units (default ArduPilot SIM_MAG_RND 2 mG,
                       PX4 0.002 G); 0 gives exact fields (up to the int16 truncation)
    system_id        : its MAVLink system id (SYSID_THISMAV / MAV_SYS_ID; the parameter is
                       not changed)
    """

    def __init__(
        self,
        personality: str = "ardupilot",
        seed: int = 0,
        port: int | None = None,
        speedup: float = 1.0,
        param_value_loss: float = 0.0,
        compasses: int = 1,
        motion: str = "tumble",
        *,
        misalignment_deg: float | None = None,
        path_s: float = PATH_S,
        mag_noise: float | None = None,
        system_id: int = SYSTEM_ID,
    ) -> None:
        if personality not in STREAMS:
            raise ValueError(f"unknown personality {personality!r}: use 'ardupilot' or 'px4'")
        if not speedup > 0 or not math.isfinite(speedup):
            raise ValueError(f"speedup must be a positive finite number, got {speedup!r}")
        if not 0.0 <= param_value_loss <= 1.0:
            raise ValueError(f"param_value_loss must be in [0, 1], got {param_value_loss!r}")
        rng = np.random.default_rng(seed)
        self._ap = personalities.make_personality(personality, rng, compasses, misalignment_deg)
        self._world = make_world(rng, motion, path_s=path_s)
        self._loss_rng = np.random.default_rng([seed, 0x10557])
        self.personality = personality
        self.port = free_udp_port() if port is None else int(port)
        self.speedup = float(speedup)
        self.param_value_loss = float(param_value_loss)
        self._store = ParamStore(personality, self._ap.specs)
        if mag_noise is not None:
            if personality == "ardupilot":
                self._store.force("SIM_MAG_RND", mag_noise)
            else:
                self._ap.mag_noise_sigma = float(mag_noise)
        self._lock = threading.RLock()  # parameters, on-board state, compass models
        with self._lock:
            self._ap.reboot(self._store)
            self._refresh_models()
        self.system_id = int(system_id)
        self._mav = mavlink.MAVLink(None, srcSystem=self.system_id, srcComponent=COMPONENT_ID)
        self._mav.robust_parsing = True
        self._intervals_us: dict[int, int] = {mid: 0 for mid in STREAMS[personality]}
        self._intervals_us[M.MAVLINK_MSG_ID_HEARTBEAT] = HEARTBEAT_INTERVAL_US
        self._next_due_us: dict[int, int] = {mid: 0 for mid in self._intervals_us}
        self._param_queue: list[tuple[str, int]] = []
        self._sock: socket.socket | None = None
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._error: BaseException | None = None
        self._wall0 = 0.0
        self._stats: dict[str, int] = {}
        self.gcs_heartbeats = 0
        #: Called with the parameter's name (in the emulator's thread) when a PARAM_SET
        #: arrives, before it is stored: tests check what the client did before writing.
        self.param_set_hook: Callable[[str], None] | None = None

    # -- public interface -------------------------------------------------------------------
    @property
    def url(self) -> str:
        """What the client passes to mavutil.mavlink_connection."""
        return f"udpin:{HOST}:{self.port}"

    @property
    def params(self) -> dict[str, float]:
        """Visible parameters now stored, name → value (integers exact, floats as float32)."""
        with self._lock:
            snap = self._store.snapshot()
            return {n: snap[n] for n in self._store.visible_names()}

    @property
    def truth(self) -> personalities.EmulatorTruth:
        with self._lock:
            return self._ap.truth(self._store.snapshot(), self._world.dip_deg, self._world.m_n)

    @property
    def field_strength(self) -> float:
        """Local field magnitude in the personality's unit: ArduPilot mG, PX4 gauss."""
        return self._ap.field_strength

    @property
    def unit(self) -> str:
        return self._ap.unit

    @property
    def sim_time_s(self) -> float:
        """Simulated seconds since start() (0 before)."""
        if self._thread is None:
            return 0.0
        return (time.monotonic() - self._wall0) * self.speedup

    @property
    def stats(self) -> dict[str, int]:
        """Counters: messages sent per type, PARAM_VALUE_DROPPED, PARAM_SET_RECEIVED."""
        with self._lock:
            return dict(self._stats)

    def heading_error_deg(self, compass: int = 1) -> float:
        """RMS heading error (deg) of the field the autopilot corrects on board with the
        calibration now in use, over the path's attitudes: noise-free raw fields, corrected
        as on board, rotated into n with the true attitude, heading from magnetic north."""
        idx = self._world.heading_attitudes()
        with self._lock:
            A, c, _ = self._models[compass - 1]
            raw = self._world.m_b[idx] @ A.T + c
            corrected = self._ap.correct(raw, self._store.snapshot(), compass)
        return rms_deg(heading_errors_rad(self._world.R_nb[idx], corrected))

    def apply_params(self, values: dict[str, float]) -> dict[str, float]:
        """Set parameters as if PARAM_SETs had arrived (same storage rules and on-board
        effects, nothing sent): a back door for tests. Values are what a client means
        (PX4 INT32 parameters as plain numbers). Returns name → stored value; raises KeyError
        for a name the autopilot would ignore."""
        out = {}
        with self._lock:
            for name, value in values.items():
                lookup = self._store.lookup(name)
                if lookup is None:
                    raise KeyError(f"{self.personality} has no parameter {name!r} now")
                if self.personality == "px4" and lookup[1] == M.MAV_PARAM_TYPE_INT32:
                    wire = struct.pack("<i", int(value))
                else:
                    wire = struct.pack("<f", value)
                stored = self._store.set_from_wire(name, wire)
                if stored is None:
                    raise KeyError(f"{self.personality} ignores {name} = {value!r}")
                out[name] = stored
                self._ap.after_params_changed(self._store)
            self._refresh_models()
        return out

    def reboot(self) -> None:
        """What a reboot does to the compass state (custom rotations rebuilt, PX4 calibration
        reset and re-read); the simulated clock and the link go on."""
        with self._lock:
            self._ap.reboot(self._store)
            self._refresh_models()

    def start(self) -> AutopilotEmulator:
        if self._thread is not None:
            raise EmulatorError("the emulator is already started")
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, SOCKET_BUFFER_BYTES)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, SOCKET_BUFFER_BYTES)
        sock.bind((HOST, 0))
        sock.setblocking(False)
        self._sock = sock
        self._wall0 = time.monotonic()
        self._thread = threading.Thread(target=self._run, name="autopilot-emulator", daemon=True)
        self._thread.start()
        return self

    def stop(self, timeout_s: float = STOP_TIMEOUT_S) -> None:
        """Stop the thread and close the socket; raises EmulatorError if the thread failed
        or does not stop in time."""
        thread = self._thread
        self._stop.set()
        if thread is not None:
            thread.join(timeout_s)
            if thread.is_alive():
                raise EmulatorError(f"the emulator thread did not stop within {timeout_s} s")
        if self._sock is not None:
            self._sock.close()
            self._sock = None
        self.check()

    def check(self) -> None:
        """Raise the thread's failure, if any."""
        if self._error is not None:
            raise EmulatorError(f"the emulator thread failed: {self._error!r}") from self._error

    def __enter__(self) -> AutopilotEmulator:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # -- thread -----------------------------------------------------------------------------
    def _run(self) -> None:
        try:
            while not self._stop.is_set():
                readable, _, _ = select.select([self._sock], [], [], LOOP_TICK_S)
                if readable:
                    self._receive()
                self._send_queued_params()
                self._send_due(int(self.sim_time_s * 1e6))
        except BaseException as exc:  # kept for check()/stop()
            self._error = exc

    def _receive(self) -> None:
        for _ in range(100):  # bounded: go back to sending between bursts
            try:
                data = self._sock.recv(65535)
            except (BlockingIOError, InterruptedError):
                return
            except OSError:  # ICMP port unreachable from an earlier send: nobody listens yet
                continue
            for msg in self._mav.parse_buffer(data) or []:
                self._handle(msg)

    def _count(self, name: str, n: int = 1) -> None:
        with self._lock:
            self._stats[name] = self._stats.get(name, 0) + n

    def _send(self, msg: mavlink.MAVLink_message) -> None:
        self._send_bytes(msg.pack(self._mav), msg.get_type())

    def _send_bytes(self, buf: bytes, name: str) -> None:
        try:
            self._sock.sendto(buf, (HOST, self.port))
        except OSError:  # loopback with no listener yet (ECONNREFUSED) or a full buffer
            self._count("SEND_FAILED")
            return
        self._count(name)

    # -- incoming -----------------------------------------------------------------------------
    def _for_us(self, msg: mavlink.MAVLink_message) -> bool:
        ts = getattr(msg, "target_system", 0)
        tc = getattr(msg, "target_component", 0)
        return ts in (0, self.system_id) and tc in (0, COMPONENT_ID)

    def _handle(self, msg: mavlink.MAVLink_message) -> None:
        kind = msg.get_type()
        if kind == "HEARTBEAT":
            self.gcs_heartbeats += 1
            return
        if kind == "BAD_DATA" or not self._for_us(msg):
            return
        if kind == "PARAM_REQUEST_LIST":
            self._on_param_request_list()
        elif kind == "PARAM_REQUEST_READ":
            self._on_param_request_read(msg)
        elif kind == "PARAM_SET":
            self._on_param_set(msg)
        elif kind == "COMMAND_LONG":
            self._on_command_long(msg)
        elif kind == "REQUEST_DATA_STREAM" and self.personality == "ardupilot":
            self._on_request_data_stream(msg)

    @staticmethod
    def _param_name(raw: bytes | str) -> str:
        if isinstance(raw, str):
            raw = raw.encode("latin-1", errors="replace")
        return raw.split(b"\0", 1)[0].decode("ascii", errors="replace")

    def _on_param_request_list(self) -> None:
        names = self._store.visible_names()
        queue: list[tuple[str, int]] = []
        if self.personality == "px4":
            queue.append(("_HASH_CHECK", -1))
        queue += [(n, i) for i, n in enumerate(names)]
        self._param_queue = queue

    def _send_queued_params(self) -> None:
        for _ in range(min(PARAMS_PER_TICK, len(self._param_queue))):
            name, index = self._param_queue.pop(0)
            if name == "_HASH_CHECK":
                names = self._store.visible_names()
                crc = 0  # like param_hash_check(): a CRC32 over the names and values
                for n in names:
                    crc = zlib.crc32(n.encode() + self._store.wire_value(n)[0], crc)
                self._send_param_value(
                    name, struct.pack("<I", crc), M.MAV_PARAM_TYPE_UINT32, len(names), -1
                )
            else:
                self._send_param(name, index)

    def _on_param_request_read(self, msg: mavlink.MAVLink_message) -> None:
        if msg.param_index >= 0:
            name = self._store.by_index(msg.param_index)
            if name is None:
                if self.personality == "px4":
                    self._statustext(f"[pm] unknown param ID: {msg.param_index}")
                return
            self._send_param(name, msg.param_index)
            return
        name = self._param_name(
            msg._param_id_raw if hasattr(msg, "_param_id_raw") else msg.param_id
        )
        if self._store.lookup(name) is None:
            return  # both autopilots stay silent
        # ArduPilot echoes the request's index (-1); PX4 always sends the parameter's index
        self._send_param(name, -1 if self.personality == "ardupilot" else None)

    def _on_param_set(self, msg: mavlink.MAVLink_message) -> None:
        name = self._param_name(
            msg._param_id_raw if hasattr(msg, "_param_id_raw") else msg.param_id
        )
        self._count("PARAM_SET_RECEIVED")  # stats' other counts are of messages sent
        if self.param_set_hook is not None:
            self.param_set_hook(name)
        value_bytes = (_raw_payload(msg) + bytes(4))[:4]  # MAVLink 2 trims trailing zeros
        with self._lock:
            stored = self._store.set_from_wire(name, value_bytes)
            if stored is None:
                if self.personality == "px4":
                    self._statustext(f"[pm] unknown param: {name}")
                return
            before = self._store.snapshot()
            self._ap.after_params_changed(self._store)
            self._refresh_models()
            after = self._store.snapshot()
        # ArduPilot: send_parameter_value with index -1; PX4: send_param with its index
        self._send_param(name, -1 if self.personality == "ardupilot" else None, before[name])
        for other, value in after.items():
            # rewritten by the autopilot itself and announced: PX4's CAL_MAGn_ROT reset,
            # ArduPilot's CUST_ROT_ENABLE (set_and_save_ifchanged); ArduPilot's all-zero
            # COMPASS_DIA → 1 is a plain set(), not announced
            if value != before[other] and not other.startswith("COMPASS_DIA"):
                self._send_param(other, -1 if self.personality == "ardupilot" else None)

    def _send_param(self, name: str, index: int | None, value: float | None = None) -> None:
        with self._lock:
            value_bytes, mav_type = self._store.wire_value(name)
            if value is not None:
                if self.personality == "px4" and mav_type == M.MAV_PARAM_TYPE_INT32:
                    value_bytes = struct.pack("<i", int(value))
                else:
                    value_bytes = struct.pack("<f", value)
            names = self._store.visible_names()
        if index is None:
            index = names.index(name)
        self._send_param_value(name, value_bytes, mav_type, len(names), index)

    def _send_param_value(
        self, name: str, value_bytes: bytes, mav_type: int, count: int, index: int
    ) -> None:
        if self.param_value_loss > 0 and self._loss_rng.random() < self.param_value_loss:
            self._count("PARAM_VALUE_DROPPED")
            return
        name16 = name.encode("ascii")[:16].ljust(16, b"\0")
        msg = self._mav.param_value_encode(name16, 0.0, mav_type, count, index & 0xFFFF)
        # the float field's 4 bytes as the autopilot has them (PX4 INT32 bytewise)
        payload = value_bytes + struct.pack("<HH16sB", count, index & 0xFFFF, name16, mav_type)
        self._send_bytes(msg._pack(self._mav, msg.crc_extra, payload), "PARAM_VALUE")

    def _statustext(self, text: str, severity: int = M.MAV_SEVERITY_INFO) -> None:
        self._send(self._mav.statustext_encode(severity, text.encode("ascii")[:50]))

    def _on_command_long(self, msg: mavlink.MAVLink_message) -> None:
        """Answer with COMMAND_ACK first; a requested message follows the ACK (as ArduPilot
        queues it)."""
        cmd = msg.command
        result = M.MAV_RESULT_ACCEPTED
        reply: mavlink.MAVLink_message | None = None
        if cmd == M.MAV_CMD_SET_MESSAGE_INTERVAL:
            result = self._set_interval(int(msg.param1), msg.param2)
        elif cmd == M.MAV_CMD_GET_MESSAGE_INTERVAL:
            mid = int(msg.param1)
            if mid in self._intervals_us:
                interval = self._intervals_us[mid]
                reply = self._mav.message_interval_encode(mid, interval if interval > 0 else -1)
            else:
                result = M.MAV_RESULT_FAILED
        elif cmd == M.MAV_CMD_REQUEST_MESSAGE:
            reply = self._requested(int(msg.param1))
            if reply is None:
                result = M.MAV_RESULT_FAILED
        elif cmd == M.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES:
            reply = self._autopilot_version()
        elif cmd == M.MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN and int(msg.param1) == 1:
            self.reboot()
        else:
            result = M.MAV_RESULT_UNSUPPORTED
        self._send(
            self._mav.command_ack_encode(
                cmd, result, 0, 0, msg.get_srcSystem(), msg.get_srcComponent()
            )
        )
        if reply is not None:
            self._send(reply)

    def _set_interval(self, mid: int, interval_us: float) -> int:
        if mid not in self._intervals_us:
            return M.MAV_RESULT_FAILED
        if interval_us < 0:
            self._intervals_us[mid] = 0  # off
        elif interval_us == 0:  # default: heartbeat 1 Hz, data streams off
            self._intervals_us[mid] = HEARTBEAT_INTERVAL_US if mid == 0 else 0
        else:
            sample_us = int(round(1e6 / SIM_RATE_HZ))
            self._intervals_us[mid] = max(sample_us, int(round(interval_us)))
            self._next_due_us[mid] = int(self.sim_time_s * 1e6)
        return M.MAV_RESULT_ACCEPTED

    def _on_request_data_stream(self, msg: mavlink.MAVLink_message) -> None:
        if msg.start_stop == 1 and msg.req_message_rate > 0:
            interval = 1e6 / msg.req_message_rate
        elif msg.start_stop in (0, 1):
            interval = -1.0
        else:
            return
        groups = (
            AP_DATA_STREAMS.values()
            if msg.req_stream_id == M.MAV_DATA_STREAM_ALL
            else (
                [AP_DATA_STREAMS[msg.req_stream_id]] if msg.req_stream_id in AP_DATA_STREAMS else []
            )
        )
        for group in groups:
            for mid in group:
                self._set_interval(mid, interval)

    def _requested(self, mid: int) -> mavlink.MAVLink_message | None:
        if mid == M.MAVLINK_MSG_ID_AUTOPILOT_VERSION:
            return self._autopilot_version()
        if mid == M.MAVLINK_MSG_ID_HEARTBEAT:
            return self._heartbeat()
        if mid in STREAMS[self.personality]:
            return self._stream_message(mid, int(self.sim_time_s * SIM_RATE_HZ))
        return None

    def _autopilot_version(self) -> mavlink.MAVLink_message:
        major, minor, patch = VERSIONS[self.personality]
        sw = (major << 24) | (minor << 16) | (patch << 8) | M.FIRMWARE_VERSION_TYPE_OFFICIAL
        caps = M.MAV_PROTOCOL_CAPABILITY_MAVLINK2 | M.MAV_PROTOCOL_CAPABILITY_SET_ATTITUDE_TARGET
        caps |= (
            M.MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_BYTEWISE
            if self.personality == "px4"
            else M.MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_C_CAST
        )
        return self._mav.autopilot_version_encode(
            caps, sw, 0, 0, 0, [0] * 8, [0] * 8, [0] * 8, 0, 0, 0x4D41474341_4C0001
        )

    # -- streams ------------------------------------------------------------------------------
    def _heartbeat(self) -> mavlink.MAVLink_message:
        if self.personality == "px4":
            base, custom = 81, 65536  # custom mode enabled, manual input; PX4 MANUAL
        else:
            base, custom = 81, 0  # custom mode enabled, manual input, stabilize; STABILIZE
        return self._mav.heartbeat_encode(
            M.MAV_TYPE_QUADROTOR, self._ap.autopilot, base, custom, M.MAV_STATE_STANDBY
        )

    def _send_due(self, now_us: int) -> None:
        """Send what is due up to now_us, earliest first across all streams (so that a lag
        delays every stream alike), at most MAX_MESSAGES_PER_TICK."""
        for _ in range(MAX_MESSAGES_PER_TICK):
            due, mid = min(
                ((d, m) for m, d in self._next_due_us.items() if self._intervals_us[m] > 0),
                default=(now_us + 1, -1),
            )
            if due > now_us:
                return
            if mid == M.MAVLINK_MSG_ID_HEARTBEAT:
                self._send(self._heartbeat())
            else:
                # the latest sample at or before the due time
                self._send(self._stream_message(mid, due * int(SIM_RATE_HZ) // 1_000_000))
            self._next_due_us[mid] = due + self._intervals_us[mid]

    def _refresh_models(self) -> None:
        """Recompute each compass's model and its raw and corrected fields over the path
        (after any change of the parameters or the on-board state; caller holds the lock)."""
        params = self._store.snapshot()
        self._models, self._raw, self._corrected = [], [], []
        for n in range(1, personalities.MAX_COMPASSES + 1):
            A, c = self._ap.compass_model(params, n)
            sigma = self._ap.noise_sigma(params)
            raw = self._world.m_b @ A.T + c + sigma * self._world.mag_noise[n - 1]
            self._models.append((A, c, sigma))
            self._raw.append(raw)
            self._corrected.append(self._ap.correct(raw, params, n))

    def _fields(self, n: int, k: int) -> tuple[np.ndarray, np.ndarray]:
        """(raw sensor-frame field, field corrected on board) (3,) each of compass n at
        sample k, raw units, with noise."""
        with self._lock:
            if k < len(self._world):
                return self._raw[n - 1][k], self._corrected[n - 1][k]
            A, c, sigma = self._models[n - 1]  # holding still after the path
            noise = self._world.mag_noise[n - 1, k % len(self._world)]
            raw = A @ self._world.field_body(k) + c + sigma * noise
            return raw, self._ap.correct(raw, self._store.snapshot(), n)[0]

    def _stream_message(self, mid: int, k: int) -> mavlink.MAVLink_message:
        t_us = k * 1_000_000 // int(SIM_RATE_HZ)
        t_ms = t_us // 1000
        if mid == M.MAVLINK_MSG_ID_ATTITUDE:
            roll, pitch, yaw = _attitude_ned(self._world.attitude(k))
            _, gyro = self._world.imu(k, 0)
            return self._mav.attitude_encode(t_ms, roll, pitch, yaw, *gyro)
        if mid == M.MAVLINK_MSG_ID_HIGHRES_IMU:  # PX4 only
            acc, gyro = self._world.imu(k, 0)
            _, mag = self._fields(1, k)
            return self._mav.highres_imu_encode(
                t_us, *acc, *gyro, *mag, 1013.25, 0.0, 0.0, 25.0, 0x1FF, 0
            )
        instance = {
            M.MAVLINK_MSG_ID_RAW_IMU: 0,
            M.MAVLINK_MSG_ID_SCALED_IMU: 0,
            M.MAVLINK_MSG_ID_SCALED_IMU2: 1,
            M.MAVLINK_MSG_ID_SCALED_IMU3: 2,
        }[mid]
        acc, gyro = self._world.imu(k, instance)
        n = instance + 1
        if n > self._ap.compasses:
            mag_mG = np.zeros(3)
        elif self.personality == "px4":  # sensor_mag: raw sensor frame, gauss × 1000
            mag_mG = self._fields(n, k)[0] * 1000.0
        else:  # compass.get_field(): corrected, body frame, mG
            mag_mG = self._fields(n, k)[1]
        a = _i16(acc * 1000.0 / GRAVITY_MSS)
        g = _i16(gyro * 1000.0)
        m = _i16(mag_mG)
        if mid == M.MAVLINK_MSG_ID_RAW_IMU:
            return self._mav.raw_imu_encode(t_us, *a, *g, *m, 0, IMU_TEMPERATURE_CDEG)
        encode = {
            M.MAVLINK_MSG_ID_SCALED_IMU: self._mav.scaled_imu_encode,
            M.MAVLINK_MSG_ID_SCALED_IMU2: self._mav.scaled_imu2_encode,
            M.MAVLINK_MSG_ID_SCALED_IMU3: self._mav.scaled_imu3_encode,
        }[mid]
        return encode(t_ms, *a, *g, *m, IMU_TEMPERATURE_CDEG)
