# SPDX-License-Identifier: Apache-2.0
"""A pure-Python magcal device (protocol/SPEC.md, device side) and test links.

FakeDevice is a byte-in/byte-out state machine: ``receive(data)`` feeds it what the host
wrote and queues its answers in ``outbox``; ``acquire(mag, acc, gyr, t_us)`` is one acquired
sample (sent when a stream runs). It keeps the idempotency cache of SPEC §3, a staged set, a
"flash" that survives reset (and reconnects), and counts what it acted on (``acted``), so a
test can check that a retry was not acted on twice.

Links (all follow magcal.link.base's contract):

- MemoryLink(device): synchronous, in memory; read() returns the device's output (and, when
  ``auto_samples`` is set, lets the device acquire that many samples first).
- LossyLink(inner, ...): injects bit errors, dropped, duplicated and delayed bytes in both
  directions (seeded), and a disconnect after a given number of bytes.
- serve_tcp(device): the device behind a TCP socket in a thread (for open_link socket://).
"""

from __future__ import annotations

import collections
import random
import socket
import struct
import threading
import time
from dataclasses import dataclass

import numpy as np

from magcal.device import fixed_point
from magcal.device import generated as g
from magcal.device.framing import (
    Deframer,
    Frame,
    ProtocolError,
    crc16_ccitt_false,
    crc32_iso_hdlc,
    encode_frame,
    pack_message,
    unpack_message,
)
from magcal.device.generated import MessageId, Status, Unit
from magcal.link.base import LinkClosedError, LinkTimeoutError

# (id, name, full scale (num, den, exp10, unit), count scale) per sensor, like sensor_hal.h's
# examples: LIS3MDL +-4 G, LSM6DSO +-4 g and +-2000 dps.
DEFAULT_SENSORS = (
    (0x3D, "LIS3MDL", (4, 1, 0, Unit.GAUSS), (1, 6842, 0, Unit.GAUSS)),
    (0x6C, "LSM6DSO", (4, 1, 0, Unit.STANDARD_GRAVITY), (122, 1, -6, Unit.STANDARD_GRAVITY)),
    (0x6C, "LSM6DSO", (2000, 1, 0, Unit.DEG_PER_S), (70, 1, -3, Unit.DEG_PER_S)),
)


@dataclass
class Stream:
    seq: int
    kind: int
    decimation: int
    count: int
    sent: int = 0
    dropped: int = 0
    phase: int = 0


class FakeDevice:
    """The device side of the protocol (see the module docstring)."""

    def __init__(
        self,
        *,
        active_blob: bytes | None = None,
        uid: tuple[int, int, int] = (0x12345678, 0x9ABCDEF0, 0x0BADF00D),
        min_version: int = 1,
        max_version: int = 1,
        sensors=DEFAULT_SENSORS,
        fail_commit: bool = False,
        commit_answer: tuple[Status, bool] | None = None,
    ) -> None:
        self.flash = active_blob  # what storage holds (survives reset)
        self.active = active_blob  # what is in use (loaded at reset)
        self.staged: bytes | None = None
        self.uid = uid
        self.min_version, self.max_version = min_version, max_version
        self.sensors = sensors
        self.fail_commit = fail_commit
        # (status, stored): a good commit answers status, having stored the staged set or not
        # (E_OUTCOME_UNKNOWN after either: SPEC §5's "either set may be the stored one").
        self.commit_answer = commit_answer
        self.deframer = Deframer()
        self.outbox = bytearray()
        self.cache: tuple[int, int, int, bytes] | None = None  # seq, id, crc, response
        self.stream: Stream | None = None
        self.acq_seq = 0
        self.acted: collections.Counter[str] = collections.Counter()
        self.resets = 0
        self.params: fixed_point.DeviceParams | None = None
        self._load()

    # -- wire
    def receive(self, data: bytes) -> None:
        for ev in self.deframer.feed(bytes(data)):
            if isinstance(ev, Frame):
                self._handle(ev)

    def take_output(self, max_bytes: int | None = None) -> bytes:
        n = len(self.outbox) if max_bytes is None else min(max_bytes, len(self.outbox))
        out = bytes(self.outbox[:n])
        del self.outbox[:n]
        return out

    def _send(self, msg_id: int, seq: int, payload: bytes) -> bytes:
        wire = encode_frame(msg_id, seq, payload)
        self.outbox += wire
        return wire

    # -- acquisition
    def acquire(self, mag, acc, gyr, t_us: int) -> None:
        """One acquired sample (int16 counts); sent when a stream runs."""
        seq = self.acq_seq
        self.acq_seq = (self.acq_seq + 1) & 0xFFFFFFFF
        s = self.stream
        if s is None:
            return
        s.phase += 1
        if s.phase < s.decimation:
            return
        s.phase = 0
        if s.kind == 0:
            payload = pack_message(
                "sample", {"seq": seq, "t_us": t_us, "mag": mag, "acc": acc, "gyr": gyr}
            )
            self._send(MessageId.SAMPLE, s.seq, payload)
        else:
            m_b = fixed_point.emulate(self.params, np.array([mag]))[0]
            payload = pack_message(
                "corrected",
                {
                    "seq": seq,
                    "t_us": t_us,
                    "mag": mag,
                    "out_exp": self.params.out_exp,
                    "m_b": [int(v) for v in m_b],
                },
            )
            self._send(MessageId.CORRECTED, s.seq, payload)
        s.sent += 1
        if s.count and s.sent >= s.count:
            self.stream = None

    # -- requests
    def _load(self) -> None:
        self.active = self.flash
        self.params = None if self.flash is None else fixed_point.decode(self.flash)

    def _handle(self, fr: Frame) -> None:
        self._current_seq = fr.seq  # stream messages carry the start request's seq
        body = struct.pack("<BH", fr.id, fr.seq) + fr.payload
        crc = crc16_ccitt_false(body)
        if fr.id == MessageId.HELLO:
            self.cache = None
        elif self.cache is not None and self.cache[0] == fr.seq:
            if self.cache[1] == fr.id and self.cache[2] == crc:
                self.outbox += self.cache[3]  # a retry: answer again, do not act
                return
            self._send(
                MessageId.NACK, fr.seq, pack_message("nack", _nack(Status.E_SEQUENCE, fr.id))
            )
            return
        try:
            m, f = unpack_message(fr.id, fr.payload)
        except ProtocolError as exc:
            self._send(MessageId.NACK, fr.seq, pack_message("nack", _nack(exc.status, fr.id)))
            return
        if m.direction != "to_device":
            self._send(
                MessageId.NACK, fr.seq, pack_message("nack", _nack(Status.E_UNKNOWN_MESSAGE, fr.id))
            )
            return
        self.acted[m.name] += 1
        resp = getattr(self, "_on_" + m.name)(f)
        wire = self._send(fr.id | 0x80, fr.seq, pack_message(fr.id | 0x80, resp))
        if fr.id != MessageId.HELLO:
            self.cache = (fr.seq, fr.id, crc, wire)
        if fr.id == MessageId.RESET and resp["status"] == Status.OK:
            self._reset()

    def _reset(self) -> None:
        self.resets += 1
        self.stream = None
        self.staged = None
        self.cache = None
        self.deframer.reset()
        self._load()

    def _on_hello(self, f):
        lo = max(f["host_min_version"], self.min_version)
        hi = min(f["host_max_version"], self.max_version)
        ok = lo <= hi
        return {
            "status": Status.OK if ok else Status.E_VERSION,
            "version": hi if ok else 0,
            "device_min_version": self.min_version,
            "device_max_version": self.max_version,
            "max_payload": g.FRAME_MAX_PAYLOAD,
        }

    def _on_info(self, f):
        def col(i, j):
            return [s[i][j] for s in self.sensors]

        return {
            "status": Status.OK,
            "fw_version": (1, 2, 3),
            "fw_build": 0xDEADBEEF,
            "protocol_version": self.max_version,
            "params_format_version": fixed_point.FORMAT_VERSION,
            "params_size": fixed_point.ENCODED_SIZE,
            "device_uid": self.uid,
            "sample_rate_mhz": 100_000,
            "sensor_id": [s[0] for s in self.sensors],
            "mag_name": self.sensors[0][1],
            "acc_name": self.sensors[1][1],
            "gyr_name": self.sensors[2][1],
            "fs_num": col(2, 0),
            "fs_den": col(2, 1),
            "fs_exp10": col(2, 2),
            "fs_unit": [int(u) for u in col(2, 3)],
            "scale_num": col(3, 0),
            "scale_den": col(3, 1),
            "scale_exp10": col(3, 2),
            "scale_unit": [int(u) for u in col(3, 3)],
        }

    def _on_stream_start(self, f):
        if f["kind"] not in (0, 1) or f["decimation"] < 1:
            return {"status": Status.E_RANGE}
        if f["kind"] == 1 and self.params is None:
            return {"status": Status.E_NO_PARAMS}
        self.stream = Stream(self._current_seq, f["kind"], f["decimation"], f["count"])
        return {"status": Status.OK}

    def _on_stream_stop(self, f):
        s, self.stream = self.stream, None
        return {"status": Status.OK, "sent": s.sent if s else 0, "dropped": s.dropped if s else 0}

    def _on_param_get(self, f):
        if f["which"] not in (0, 1):
            return {
                "status": Status.E_RANGE,
                "which": f["which"],
                "format_version": 0,
                "crc32": 0,
                "blob": b"",
            }
        blob = self.active if f["which"] == 0 else self.staged
        if blob is None:
            return {
                "status": Status.E_NO_PARAMS,
                "which": f["which"],
                "format_version": 0,
                "crc32": 0,
                "blob": b"",
            }
        return {
            "status": Status.OK,
            "which": f["which"],
            "format_version": fixed_point.FORMAT_VERSION,
            "crc32": crc32_iso_hdlc(blob),
            "blob": blob,
        }

    def _on_param_set(self, f):
        if f["format_version"] != fixed_point.FORMAT_VERSION:
            return {"status": Status.E_VERSION, "crc32": 0}
        try:
            fixed_point.validate(fixed_point.decode(f["blob"]))
        except fixed_point.FixedPointError as exc:
            return {"status": exc.status, "crc32": 0}
        self.staged = f["blob"]
        return {"status": Status.OK, "crc32": crc32_iso_hdlc(f["blob"])}

    def _on_param_commit(self, f):
        if self.staged is None:
            return {"status": Status.E_STATE}
        if crc32_iso_hdlc(self.staged) != f["crc32"]:
            return {"status": Status.E_CRC}
        if self.fail_commit:
            return {"status": Status.E_FLASH}
        if self.commit_answer is not None:
            status, stored = self.commit_answer
            if stored:
                self.flash = self.staged
            return {"status": status}
        self.flash = self.staged  # atomic, as storage.h's two-slot commit
        return {"status": Status.OK}

    def _on_reset(self, f):
        return {"status": Status.OK if f["magic"] == g.RESET_MAGIC else Status.E_ARG}

    _current_seq = 0


def _nack(status: Status, request_id: int) -> dict:
    return {"status": status, "request_id": request_id}


def random_sample(rng: np.random.Generator):
    """(mag, acc, gyr) int16 counts."""
    v = rng.integers(-2000, 2000, size=9)
    return tuple(int(x) for x in v[:3]), tuple(int(x) for x in v[3:6]), tuple(int(x) for x in v[6:])


# ----------------------------------------------------------------------------- links
class MemoryLink:
    """A synchronous in-memory link to a FakeDevice. With auto_samples, every read lets the
    device acquire that many random samples first (10 ms apart)."""

    def __init__(
        self, device: FakeDevice, url: str = "memory://fake", auto_samples: int = 0, seed: int = 0
    ):
        self.device = device
        self.url = url
        self.closed = False
        self.auto_samples = auto_samples
        self._rng = np.random.default_rng(seed)
        self._t_us = 0

    def read(self, timeout_s: float, max_bytes: int = 4096) -> bytes:
        if self.closed:
            raise LinkClosedError(f"read {self.url}: closed", self.url)
        # Acquire auto_samples samples per read; more (up to 100) while nothing is sent
        # (decimation), as the time a real read waits would let the device acquire.
        for k in range(100 if self.auto_samples else 0):
            if k >= self.auto_samples and self.device.outbox:
                break
            self._t_us += 10_000
            self.device.acquire(*random_sample(self._rng), self._t_us)
        data = self.device.take_output(max_bytes)
        if data:
            return data
        time.sleep(timeout_s)
        raise LinkTimeoutError(f"read {self.url}: no byte within {timeout_s} s", self.url)

    def write(self, data: bytes, timeout_s: float | None = None) -> None:
        if self.closed:
            raise LinkClosedError(f"write {self.url}: closed", self.url)
        self.device.receive(data)

    def close(self) -> None:
        self.closed = True

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


class LossyLink:
    """Wraps a link and damages the bytes both ways (seeded): per byte, with the given
    probabilities, a bit flip, a drop, a duplicate, or a delay (the byte and all after it wait
    delay_s); after disconnect_after bytes in total (both directions) the link is gone."""

    def __init__(
        self,
        inner,
        *,
        seed: int = 0,
        bit_error: float = 0.0,
        drop: float = 0.0,
        duplicate: float = 0.0,
        delay: float = 0.0,
        delay_s: float = 0.01,
        disconnect_after: int | None = None,
    ) -> None:
        self.inner = inner
        self.url = getattr(inner, "url", "lossy://")
        self.rng = random.Random(seed)
        self.bit_error, self.drop, self.duplicate, self.delay = bit_error, drop, duplicate, delay
        self.delay_s = delay_s
        self.disconnect_after = disconnect_after
        self.bytes_passed = 0
        self.closed = False
        self.faults = collections.Counter()
        self._held: collections.deque[tuple[float, bytes]] = collections.deque()

    def _damage(self, data: bytes) -> bytes:
        out = bytearray()
        for b in data:
            r = self.rng.random()
            if r < self.bit_error:
                out.append(b ^ (1 << self.rng.randrange(8)))
                self.faults["bit_error"] += 1
            elif r < self.bit_error + self.drop:
                self.faults["drop"] += 1
            elif r < self.bit_error + self.drop + self.duplicate:
                out += bytes([b, b])
                self.faults["duplicate"] += 1
            else:
                out.append(b)
        return bytes(out)

    def _budget(self, data: bytes) -> bytes:
        """Cut data at the disconnect point (then the link is gone)."""
        if self.disconnect_after is None:
            self.bytes_passed += len(data)
            return data
        left = self.disconnect_after - self.bytes_passed
        if left < len(data):
            self.closed = True
            data = data[: max(left, 0)]
        self.bytes_passed += len(data)
        return data

    def write(self, data: bytes, timeout_s: float | None = None) -> None:
        if self.closed:
            raise LinkClosedError(f"write {self.url}: disconnected", self.url)
        part = self._budget(data)
        if part:
            self.inner.write(self._damage(part))
        if self.closed:
            raise LinkClosedError(f"write {self.url}: disconnected mid-write", self.url)

    def read(self, timeout_s: float, max_bytes: int = 4096) -> bytes:
        deadline = time.monotonic() + timeout_s
        while True:
            if self.closed:
                raise LinkClosedError(f"read {self.url}: disconnected", self.url)
            now = time.monotonic()
            if self._held and self._held[0][0] <= now:
                return self._deliver(self._held.popleft()[1])
            wait = deadline - now
            if self._held:
                wait = min(wait, self._held[0][0] - now)
            try:
                data = self.inner.read(max(wait, 0.0), max_bytes)
            except LinkTimeoutError:
                if self._held and self._held[0][0] <= time.monotonic():
                    continue
                if time.monotonic() >= deadline:
                    raise
                continue
            data = self._damage(data)
            if not data:
                continue
            if self._held or (self.delay and self.rng.random() < self.delay * len(data)):
                # Held back; later bytes queue behind it (a delay never reorders a stream).
                self.faults["delay"] += 1
                self._held.append((time.monotonic() + self.delay_s, data))
                continue
            return self._deliver(data)

    def _deliver(self, data: bytes) -> bytes:
        part = self._budget(data)
        if not part:
            raise LinkClosedError(f"read {self.url}: disconnected", self.url)
        return part

    def close(self) -> None:
        self.closed = True
        self.inner.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def serve_tcp(device: FakeDevice) -> tuple[int, threading.Event, threading.Thread]:
    """Serve device on 127.0.0.1:<port> (one connection at a time) until stop is set."""
    srv = socket.create_server(("127.0.0.1", 0))
    srv.settimeout(0.05)
    port = srv.getsockname()[1]
    stop = threading.Event()
    lock = threading.Lock()

    def run() -> None:
        with srv:
            while not stop.is_set():
                try:
                    conn, _ = srv.accept()
                except TimeoutError:
                    continue
                conn.settimeout(0.01)
                with conn:
                    while not stop.is_set():
                        try:
                            data = conn.recv(4096)
                            if not data:
                                break
                            with lock:
                                device.receive(data)
                        except TimeoutError:
                            pass
                        with lock:
                            out = device.take_output()
                        if out:
                            conn.sendall(out)

    th = threading.Thread(target=run, daemon=True)
    th.start()
    return port, stop, th
