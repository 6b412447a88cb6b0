# SPDX-License-Identifier: Apache-2.0
"""A lossy TCP proxy for the SIL tests: 127.0.0.1:port -> the device, with seeded line noise.

:class:`LossyProxy` forwards a client's connection to a TCP port (the SIL's protocol port) and
damages the bytes in both directions: bit flips, dropped bytes, duplicated bytes, pauses
(delayed bytes) and chunk splitting (a frame forwarded in several writes), each at a rate per
byte (per frame for splitting) given by :class:`Faults`, one set per direction.

Deterministic decisions. The proxy cuts each direction's clean byte stream into *units* at
the frame delimiter (the bytes up to and including each ``0x00``; protocol/SPEC.md §1) and
decides every fault of a unit from a random generator seeded with (seed, direction, the
unit's bytes, how often these bytes passed before). So the faults a frame suffers depend only
on the frames the two ends exchange, not on timing or on how TCP chunks the stream: a retry
(the same bytes again) gets fresh decisions, and a run that exchanges the same frames meets
the same faults. The delays are the one thing timing adds (their lengths are seeded too).
A unit is held until its delimiter arrives, at most one frame (247 bytes).

``lose_first`` names frames to lose on purpose, whatever the dice say: ("d2h", id) loses
the first frame with that message id from the device (a single bit flip, which the CRC-16
always catches), ("h2d", id) the first such request; e.g. the first ``param_commit_resp``,
so that the host must retry a commit the device has already acted on.

The log (:attr:`LossyProxy.units`, one :class:`Unit` per unit, both directions, in the order
forwarded) keeps each unit's clean bytes, its decoded frame, what was sent instead and
whether the receiver gets it intact: the bytes sent equal the clean ones (up to extra
``0x00`` delimiters, which are empty frames to a receiver) and the receiver's buffer was empty
when the unit began (the previous unit's last byte sent was a delimiter; otherwise the two
merge and both are lost). An intact unit is one frame the receiver decodes; any other is lost
to it (barring a CRC-16 collision, 2^-16 per damaged frame).

Every wait has a timeout: the threads poll a stop flag every POLL_S, sends time out after
SEND_TIMEOUT_S, :meth:`LossyProxy.close` joins the threads within JOIN_TIMEOUT_S and raises
if one is still running or a thread failed.
"""

from __future__ import annotations

import collections
import hashlib
import random
import select
import socket
import threading
import time
from dataclasses import dataclass, field

from magcal.device.framing import Frame, ProtocolError, decode_frame

POLL_S = 0.05
SEND_TIMEOUT_S = 5.0
CONNECT_TIMEOUT_S = 5.0
JOIN_TIMEOUT_S = 5.0
RECV_BYTES = 4096

DIRECTIONS = ("h2d", "d2h")  # host to device, device to host
FAULT_KINDS = ("flip", "drop", "duplicate", "delay", "split")


@dataclass(frozen=True)
class Faults:
    """Fault rates of one direction: per byte (flip, drop, duplicate, delay; at most one of
    flip, drop and duplicate per byte) and per unit (split)."""

    flip: float = 0.0
    drop: float = 0.0
    duplicate: float = 0.0
    delay: float = 0.0
    delay_s: tuple[float, float] = (0.002, 0.02)  # a delay's length, uniform, seconds
    split: float = 0.0  # a unit is forwarded in 2 to 4 writes
    split_pause_s: float = 0.001  # between those writes


@dataclass
class Unit:
    """One unit forwarded: its clean bytes, the frame they decode to (None for an empty unit,
    a lone delimiter), what was sent, whether the receiver gets the frame intact, whether the
    loss was forced (``lose_first``), and the faults applied (kind -> count)."""

    direction: str
    clean: bytes
    frame: Frame | None
    sent: bytes
    intact: bool
    forced: bool
    faults: dict[str, int] = field(default_factory=dict)


def _collapse_delimiters(data: bytes) -> bytes:
    """data with every run of 0x00 made one 0x00 (what a receiver makes of it)."""
    out = bytearray()
    for b in data:
        if b == 0 and out and out[-1] == 0:
            continue
        out.append(b)
    return bytes(out)


class LossyProxy:
    """See the module docstring. ``url`` is what ``open_link`` takes; use as a context
    manager or call :meth:`close`."""

    def __init__(
        self,
        target_port: int,
        faults: dict[str, Faults],
        seed: int,
        lose_first: frozenset[tuple[str, int]] = frozenset(),
    ) -> None:
        self.target_port = target_port
        self.faults = {d: faults.get(d, Faults()) for d in DIRECTIONS}
        self.seed = seed
        self._lose_first = set(lose_first)
        self.units: list[Unit] = []
        self.counts = {d: collections.Counter() for d in DIRECTIONS}
        self.errors: list[BaseException] = []
        self._seen: collections.Counter[tuple[str, bytes]] = collections.Counter()
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._socks: list[socket.socket] = []
        self._listener = socket.create_server(("127.0.0.1", 0))
        self._listener.settimeout(POLL_S)
        self.port = self._listener.getsockname()[1]
        self.url = f"socket://127.0.0.1:{self.port}"
        self._spawn(self._accept_loop, "lossy-proxy-accept")

    # -- what happened
    def frames(self, direction: str) -> list[Unit]:
        """The units of a direction that carry a frame, in order."""
        with self._lock:
            return [u for u in self.units if u.direction == direction and u.frame is not None]

    def total_faults(self, direction: str) -> collections.Counter:
        with self._lock:
            return collections.Counter(self.counts[direction])

    # -- threads
    def _spawn(self, fn, name: str, *args) -> None:
        t = threading.Thread(target=self._guard, args=(fn, *args), name=name, daemon=True)
        self._threads.append(t)
        t.start()

    def _guard(self, fn, *args) -> None:
        try:
            fn(*args)
        except BaseException as exc:  # kept for close() to raise
            if not self._stop.is_set():
                self.errors.append(exc)

    def _accept_loop(self) -> None:
        while not self._stop.is_set():
            try:
                host, _ = self._listener.accept()
            except TimeoutError:
                continue
            except OSError:
                return  # closed
            dev = socket.create_connection(("127.0.0.1", self.target_port), CONNECT_TIMEOUT_S)
            for s in (host, dev):
                s.settimeout(SEND_TIMEOUT_S)
                s.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            with self._lock:
                self._socks += [host, dev]
            self._spawn(self._pump, "lossy-proxy-h2d", host, dev, "h2d")
            self._spawn(self._pump, "lossy-proxy-d2h", dev, host, "d2h")

    def _pump(self, src: socket.socket, dst: socket.socket, direction: str) -> None:
        pending = bytearray()
        rx_clean = [True]  # the receiver's frame buffer is empty
        while not self._stop.is_set():
            ready, _, _ = select.select([src], [], [], POLL_S)
            if not ready:
                continue
            try:
                data = src.recv(RECV_BYTES)
            except OSError:
                data = b""
            if not data:
                break
            pending += data
            try:
                while (end := pending.find(0)) >= 0:
                    unit = bytes(pending[: end + 1])
                    del pending[: end + 1]
                    self._forward(unit, dst, direction, rx_clean)
            except OSError:
                break  # the receiver is gone: this connection is over (not a proxy failure)
        # The source closed: pass on what is left as it is, then the end of the stream.
        try:
            if pending:
                dst.sendall(bytes(pending))
            dst.shutdown(socket.SHUT_WR)
        except OSError:
            pass

    def _rng(self, direction: str, unit: bytes) -> random.Random:
        with self._lock:
            n = self._seen[(direction, unit)]
            self._seen[(direction, unit)] = n + 1
        key = f"{self.seed}/{direction}/{n}/".encode() + unit
        return random.Random(int.from_bytes(hashlib.blake2b(key, digest_size=8).digest(), "little"))

    def _forward(self, unit: bytes, dst: socket.socket, direction: str, rx_clean: list) -> None:
        try:
            frame: Frame | None = decode_frame(unit[:-1]) if len(unit) > 1 else None
        except ProtocolError:
            frame = None  # the two ends only send good frames; kept as an opaque unit
        forced = False
        if frame is not None:
            with self._lock:
                forced = (direction, frame.id) in self._lose_first
                self._lose_first.discard((direction, frame.id))
        rng = self._rng(direction, unit)
        f = self.faults[direction]
        counts: collections.Counter[str] = collections.Counter()
        pieces: list[tuple[float, bytearray]] = [(0.0, bytearray())]  # (pause before, bytes)
        if forced:
            b = unit[-2]
            pieces[0][1].extend(unit[:-2] + bytes([b ^ (0x02 if b == 0x01 else 0x01)]) + b"\0")
        else:
            for b in unit:
                if rng.random() < f.delay:
                    counts["delay"] += 1
                    pieces.append((rng.uniform(*f.delay_s), bytearray()))
                r = rng.random()
                out = pieces[-1][1]
                if r < f.drop:
                    counts["drop"] += 1
                elif r < f.drop + f.flip:
                    counts["flip"] += 1
                    out.append(b ^ (1 << rng.randrange(8)))
                elif r < f.drop + f.flip + f.duplicate:
                    counts["duplicate"] += 1
                    out += bytes([b, b])
                else:
                    out.append(b)
            if rng.random() < f.split:
                counts["split"] += 1
                split: list[tuple[float, bytearray]] = []
                for pause, data in pieces:
                    cuts = (
                        sorted(
                            rng.sample(range(1, len(data)), min(len(data) - 1, rng.randint(1, 3)))
                        )
                        if len(data) > 1
                        else []
                    )
                    bounds = [0, *cuts, len(data)]
                    for i in range(len(bounds) - 1):
                        split.append(
                            (pause if i == 0 else f.split_pause_s, data[bounds[i] : bounds[i + 1]])
                        )
                pieces = split
        sent = b"".join(bytes(d) for _, d in pieces)
        intact = rx_clean[0] and _collapse_delimiters(sent) == unit
        if sent:
            rx_clean[0] = sent[-1] == 0
        with self._lock:
            self.counts[direction].update(counts)
            if forced:
                self.counts[direction]["forced"] += 1
            self.units.append(Unit(direction, unit, frame, sent, intact, forced, dict(counts)))
        for pause, data in pieces:
            if pause > 0:
                time.sleep(pause)
            if data:
                dst.sendall(bytes(data))

    # -- stop
    def close(self) -> None:
        """Stop accepting and forwarding, close every socket, join the threads; raises when a
        thread failed or did not stop within JOIN_TIMEOUT_S."""
        self._stop.set()
        self._listener.close()
        with self._lock:
            socks = list(self._socks)
        for t in self._threads:
            t.join(JOIN_TIMEOUT_S)
        for s in socks:
            try:
                s.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass
            s.close()
        alive = [t.name for t in self._threads if t.is_alive()]
        if alive:
            raise RuntimeError(f"lossy proxy: threads {alive} did not stop in {JOIN_TIMEOUT_S} s")
        if self.errors:
            raise RuntimeError(f"lossy proxy: a thread failed: {self.errors[0]!r}") from (
                self.errors[0]
            )

    def __enter__(self) -> LossyProxy:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
