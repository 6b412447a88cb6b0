# SPDX-License-Identifier: Apache-2.0
"""The host side of the device protocol (protocol/SPEC.md §2-§5) over a :class:`Link`.

``DeviceClient(link)`` sends requests and waits for their responses; stream messages that
arrive meanwhile are queued and read with :meth:`DeviceClient.read_stream` /
:meth:`DeviceClient.stream`. Every request gets a fresh seq (previous + 1 modulo 2^16); when
no response arrives within the time-out, the *same bytes* are sent again (the device answers
a retry from its cache without acting twice), at most ``request_retries`` times, and then the
last error is raised. A device's refusal (a status other than OK, or a nack) raises
:class:`DeviceError` with the status name. Line noise never raises: the Deframer drops bad
frames and counts them (``client.stats``).

SPEC §5's flash flow (a backup saved first, every step read back) and restore are in
:mod:`magcal.device.flash`.

Example::

    with open_link("socket://127.0.0.1:5760") as link:
        client = DeviceClient(link)
        client.hello()
        info = client.info()
        client.stream_start(StreamKind.RAW, count=100)
        samples = list(client.stream(100))
"""

from __future__ import annotations

import collections
import enum
import logging
import math
import random
import time
from collections.abc import Iterator
from dataclasses import dataclass
from fractions import Fraction
from typing import Any

import numpy as np

from magcal.device import generated as g
from magcal.device.framing import (
    Deframer,
    Frame,
    ProtocolError,
    crc32_iso_hdlc,
    encode_message,
    message_def,
    response_id,
    unpack_message,
)
from magcal.device.generated import MessageId, Status, Unit
from magcal.errors import MagcalError
from magcal.link.base import Link, LinkTimeoutError

log = logging.getLogger(__name__)

# The device answers within a millisecond; what delays a response is the link: streamed
# samples queued ahead of it (a few KB of UART buffer at 115 200 baud is ~0.3 s) and USB
# latency. 0.5 s covers that with margin yet notices a lost frame quickly.
REQUEST_TIMEOUT_S = 0.5
# Retries after the first attempt (same seq, same bytes): 4 attempts, 2 s before giving up.
# A frame is lost only to a bit error or a dropped byte; four losses in a row mean the link
# or the device is down, not noisy.
REQUEST_RETRIES = 3
# param_commit writes flash: a sector erase takes up to ~1 s on common MCUs (STM32F4 128 KB
# sectors: 1-2 s typical), so the commit gets its own time-out.
PARAM_COMMIT_TIMEOUT_S = 3.0
# After reset the firmware restarts (and a USB device re-enumerates): hello is retried this
# long before the device is declared gone.
RESET_RECOVERY_TIMEOUT_S = 5.0
# Stream messages kept while nobody reads them (oldest dropped first, counted); 65 536 samples
# are 11 minutes at 100 Hz.
STREAM_QUEUE_MAX = 65536
STREAM_TIMEOUT_S = 2.0  # default wait for the next stream message


class DeviceError(MagcalError):
    """The device refused a request (status != OK, or a nack). ``status`` is the Status."""

    def __init__(self, message: str, status: Status | int, op: str = "") -> None:
        super().__init__(message)
        self.status = status
        self.op = op


class DeviceTimeoutError(DeviceError):
    """No response after every retry (status E_EMPTY: nothing was received)."""


class _AttemptTimeoutError(DeviceTimeoutError):
    """One attempt of a request got no response in time (the request retries)."""


class VersionMismatchError(DeviceError):
    """Host and device share no protocol version."""


_ADVICE = {
    Status.E_ARG: "the request was malformed: check the magcal and firmware versions",
    Status.E_RANGE: "a value is outside the device's range",
    Status.E_SINGULAR: "the correction matrix is singular: calibrate again",
    Status.E_CONDITION: "the correction matrix is too badly conditioned: calibrate again",
    Status.E_VERSION: "the versions do not match: update magcal or the firmware",
    Status.E_EXPONENT: "the parameter set's exponents are out of range: convert it again",
    Status.E_NO_PARAMS: "the device has no parameter set: flash one (magcal flash)",
    Status.E_CRC: "the CRC did not match: retry the whole operation",
    Status.E_FLASH: "the device could not store the set: retry; replace the board if it persists",
    Status.E_OUTCOME_UNKNOWN: (
        "the device's flash failed after the commit point, so either the old or the new set is "
        "stored: reset the device and read the active set to find out"
    ),
    Status.E_STATE: "the device was not in the state for this request: start the flow again",
    Status.E_SEQUENCE: "a sequence clash: send hello to start a new session",
    Status.E_UNKNOWN_MESSAGE: "the firmware does not know this request: update the firmware",
    Status.E_LENGTH: "the firmware expects another payload size: check versions",
    # Mostly internal to the firmware (SPEC §6); advice in case a response carries them.
    Status.E_OVERFLOW: "a buffer on the device was full: slow down and retry",
    Status.E_EMPTY: "the device had nothing to send: retry",
    Status.E_FRAME: "the device could not decode the request: check the link and retry",
    Status.E_SENSOR: "a sensor read failed on the device: check the sensor's wiring and power",
    Status.E_NO_SPACE: "the device's buffer is too small for this request: update the firmware",
}


def _status_name(status: int) -> str:
    try:
        return Status(status).name
    except ValueError:
        return f"status {status}"


def _refusal(op: str, status: int, url: str) -> DeviceError:
    advice = _ADVICE.get(status, "see protocol/SPEC.md §6") if isinstance(status, int) else ""
    return DeviceError(
        f"{op} on {url}: device answered {_status_name(status)}; {advice}", status, op
    )


# ----------------------------------------------------------------------------- info, units
class StreamKind(enum.IntEnum):
    RAW = 0
    CORRECTED = 1


class ParamWhich(enum.IntEnum):
    ACTIVE = 0
    STAGED = 1


SENSOR_KINDS = ("mag", "acc", "gyr")  # index 0, 1, 2 of every per-sensor array
# Exact SI factor of each unit; DEG_PER_S is pi/180, kept as 1/180 with pi applied at the end.
UNIT_SI_FACTOR: dict[Unit, Fraction] = {
    Unit.TESLA: Fraction(1),
    Unit.GAUSS: Fraction(1, 10_000),
    Unit.METRE_PER_S2: Fraction(1),
    Unit.STANDARD_GRAVITY: Fraction(980_665, 100_000),
    Unit.RAD_PER_S: Fraction(1),
    Unit.DEG_PER_S: Fraction(1, 180),
}
_UNITS_WITH_PI = frozenset({Unit.DEG_PER_S})


@dataclass(frozen=True)
class Scale:
    """Exactly ``num / den * 10**exp10`` of ``unit`` (info_resp's fs_* and scale_*)."""

    num: int
    den: int
    exp10: int
    unit: Unit

    @property
    def si_rational(self) -> Fraction:
        """The value in SI units, exact, divided by pi when ``has_pi`` (deg/s)."""
        if self.unit not in UNIT_SI_FACTOR or self.den <= 0:
            raise MagcalError(
                f"scale {self.num}/{self.den}e{self.exp10} unit {self.unit!r} has no SI value: "
                "the device description is invalid; check the firmware's sensor table"
            )
        return Fraction(self.num, self.den) * Fraction(10) ** self.exp10 * UNIT_SI_FACTOR[self.unit]

    @property
    def has_pi(self) -> bool:
        return self.unit in _UNITS_WITH_PI

    @property
    def si(self) -> float:
        """The value in SI units as a float (rounded once; times pi at the end for deg/s)."""
        v = float(self.si_rational)
        return v * math.pi if self.has_pi else v

    def counts_to_si(self, counts: Any) -> np.ndarray:
        """counts (any shape, int16 values) -> float64 SI values, each rounded once from the
        exact rational (then times pi for deg/s)."""
        c = np.asarray(counts)
        if c.size and (c.min() < -32768 or c.max() > 32767):
            raise MagcalError("counts_to_si: counts must be int16 values (-32768 .. 32767)")
        return _si_table(self)[c.astype(np.int64) + 32768]


_SI_TABLES: dict[Scale, np.ndarray] = {}


def _si_table(scale: Scale) -> np.ndarray:
    """(65536,) float64, the SI value of every int16 count (cached per scale)."""
    table = _SI_TABLES.get(scale)
    if table is None:
        q = scale.si_rational
        table = np.array([float(c * q) for c in range(-32768, 32768)], dtype=np.float64)
        if scale.has_pi:
            table = table * math.pi  # pi once, at the end
        _SI_TABLES[scale] = table
    return table


@dataclass(frozen=True)
class SensorInfo:
    kind: str  # "mag", "acc" or "gyr"
    sensor_id: int
    name: str
    full_scale: Scale
    count_scale: Scale


@dataclass(frozen=True)
class DeviceInfo:
    """info_resp, parsed. sensors[0] magnetometer, [1] accelerometer, [2] gyroscope."""

    fw_version: tuple[int, int, int]
    fw_build: int
    protocol_version: int
    params_format_version: int
    params_size: int
    device_uid: tuple[int, int, int]
    sample_rate_mhz: int
    sensors: tuple[SensorInfo, SensorInfo, SensorInfo]

    @property
    def uid_hex(self) -> str:
        return "".join(f"{w:08x}" for w in self.device_uid)

    @property
    def fw_version_str(self) -> str:
        return ".".join(str(v) for v in self.fw_version)

    @property
    def sample_rate_hz(self) -> float:
        return self.sample_rate_mhz / 1000.0

    def sensor(self, kind: str) -> SensorInfo:
        return self.sensors[SENSOR_KINDS.index(kind)]

    @staticmethod
    def from_fields(f: dict[str, Any]) -> DeviceInfo:
        def scale(prefix: str, i: int) -> Scale:
            unit = f[prefix + "_unit"][i]
            if unit not in UNIT_SI_FACTOR or f[prefix + "_den"][i] == 0:
                raise DeviceError(
                    f"info: {SENSOR_KINDS[i]} {prefix} has unit code {unit} and denominator "
                    f"{f[prefix + '_den'][i]}, which have no SI value; fix the firmware's "
                    "sensor table (sensor_hal.h)",
                    Status.E_RANGE,
                    "info",
                )
            return Scale(
                int(f[prefix + "_num"][i]),
                int(f[prefix + "_den"][i]),
                int(f[prefix + "_exp10"][i]),
                Unit(unit),
            )

        names = (f["mag_name"], f["acc_name"], f["gyr_name"])
        sensors = tuple(
            SensorInfo(k, int(f["sensor_id"][i]), names[i], scale("fs", i), scale("scale", i))
            for i, k in enumerate(SENSOR_KINDS)
        )
        return DeviceInfo(
            fw_version=tuple(f["fw_version"]),
            fw_build=f["fw_build"],
            protocol_version=f["protocol_version"],
            params_format_version=f["params_format_version"],
            params_size=f["params_size"],
            device_uid=tuple(f["device_uid"]),
            sample_rate_mhz=f["sample_rate_mhz"],
            sensors=sensors,  # type: ignore[arg-type]
        )


@dataclass(frozen=True)
class HelloResult:
    version: int
    device_min_version: int
    device_max_version: int
    max_payload: int


@dataclass(frozen=True)
class ParamSet:
    which: ParamWhich
    format_version: int
    crc32: int
    blob: bytes


@dataclass(frozen=True)
class StreamStats:
    sent: int
    dropped: int


@dataclass(frozen=True)
class Sample:
    """A raw sample (kind 0): acquisition seq, device time (us), int16 counts per sensor."""

    seq: int
    t_us: int
    mag: tuple[int, int, int]
    acc: tuple[int, int, int]
    gyr: tuple[int, int, int]


@dataclass(frozen=True)
class Corrected:
    """A corrected sample (kind 1): raw mag counts and m_b[i] * 2**(out_exp - 31)."""

    seq: int
    t_us: int
    mag: tuple[int, int, int]
    out_exp: int
    m_b: tuple[int, int, int]


@dataclass(frozen=True)
class ClientConfig:
    """Time-outs and retries of a DeviceClient (defaults: the module's constants)."""

    request_timeout_s: float = REQUEST_TIMEOUT_S
    request_retries: int = REQUEST_RETRIES
    commit_timeout_s: float = PARAM_COMMIT_TIMEOUT_S
    reset_recovery_timeout_s: float = RESET_RECOVERY_TIMEOUT_S
    stream_queue_max: int = STREAM_QUEUE_MAX


@dataclass
class ClientStats:
    """What the client saw: retries, stale or unexpected frames, stream drops on the host."""

    requests: int = 0
    retries: int = 0
    stale_frames: int = 0
    stream_queue_dropped: int = 0
    bad_payloads: int = 0


# ----------------------------------------------------------------------------- client
class DeviceClient:
    """Requests, responses and streams over one link (see the module docstring)."""

    def __init__(
        self, link: Link, config: ClientConfig = ClientConfig(), first_seq: int | None = None
    ) -> None:
        self.link = link
        self.config = config
        self.deframer = Deframer()
        self.stats = ClientStats()
        self.version: int | None = None
        self._seq = random.randrange(1 << 16) if first_seq is None else first_seq & 0xFFFF
        self._stream_seq: int | None = None
        self._stream: collections.deque[Sample | Corrected] = collections.deque()

    @property
    def url(self) -> str:
        return getattr(self.link, "url", "?")

    def close(self) -> None:
        self.link.close()

    def __enter__(self) -> DeviceClient:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- requests
    def hello(
        self, min_version: int = g.PROTOCOL_MIN_VERSION, max_version: int = g.PROTOCOL_VERSION
    ) -> HelloResult:
        """Negotiate the protocol version (SPEC §2); VersionMismatchError when none is shared."""
        f = self._request(
            "hello", {"host_min_version": min_version, "host_max_version": max_version}, check=False
        )
        r = HelloResult(
            f["version"], f["device_min_version"], f["device_max_version"], f["max_payload"]
        )
        if f["status"] == Status.E_VERSION:
            raise VersionMismatchError(
                f"hello on {self.url}: no common protocol version: host speaks "
                f"[{min_version}, {max_version}], device [{r.device_min_version}, "
                f"{r.device_max_version}]; update magcal or the firmware",
                Status.E_VERSION,
                "hello",
            )
        if f["status"] != Status.OK:
            raise _refusal("hello", f["status"], self.url)
        if not min_version <= r.version <= max_version:
            raise VersionMismatchError(
                f"hello on {self.url}: device chose version {r.version}, outside the host's "
                f"[{min_version}, {max_version}]; update the firmware",
                Status.E_VERSION,
                "hello",
            )
        self.version = r.version
        return r

    def info(self) -> DeviceInfo:
        return DeviceInfo.from_fields(self._request("info", {}))

    def stream_start(
        self, kind: StreamKind | int = StreamKind.RAW, decimation: int = 1, count: int = 0
    ) -> None:
        """Start (or restart) a stream; its messages are read with read_stream/stream."""
        self._request("stream_start", {"kind": int(kind), "decimation": decimation, "count": count})

    def stream_stop(self) -> StreamStats:
        f = self._request("stream_stop", {})
        self._stream_seq = None
        return StreamStats(f["sent"], f["dropped"])

    def param_get(self, which: ParamWhich | int = ParamWhich.ACTIVE) -> ParamSet:
        """The active or staged set; DeviceError(E_NO_PARAMS) when that set does not exist."""
        f = self._request(
            "param_get", {"which": int(which)}, op=f"param_get({ParamWhich(which).name.lower()})"
        )
        blob = f["blob"]
        if crc32_iso_hdlc(blob) != f["crc32"]:
            raise DeviceError(
                f"param_get on {self.url}: the blob's CRC-32 0x{crc32_iso_hdlc(blob):08x} differs "
                f"from the device's 0x{f['crc32']:08x}; retry, then suspect the firmware",
                Status.E_CRC,
                "param_get",
            )
        return ParamSet(ParamWhich(f["which"]), f["format_version"], f["crc32"], blob)

    def param_set(self, format_version: int, blob: bytes) -> int:
        """Stage a set; returns the device's CRC-32 of it (checked against the host's)."""
        f = self._request("param_set", {"format_version": format_version, "blob": bytes(blob)})
        if f["crc32"] != crc32_iso_hdlc(blob):
            raise DeviceError(
                f"param_set on {self.url}: device staged a blob with CRC-32 0x{f['crc32']:08x}, "
                f"host sent 0x{crc32_iso_hdlc(blob):08x}; do not commit: run flash again",
                Status.E_CRC,
                "param_set",
            )
        return f["crc32"]

    def param_commit(self, crc32: int) -> None:
        self._request("param_commit", {"crc32": crc32}, timeout_s=self.config.commit_timeout_s)

    def reset(self) -> None:
        """Reset the device (it restarts after answering); then call hello again."""
        self._request("reset", {"magic": g.RESET_MAGIC})
        self.version = None
        self._stream_seq = None
        self._stream.clear()
        self.deframer.reset()

    # -- stream
    def read_stream(self, timeout_s: float = STREAM_TIMEOUT_S) -> Sample | Corrected:
        """The next stream message; DeviceTimeoutError when none arrives within timeout_s."""
        deadline = time.monotonic() + timeout_s
        while not self._stream:
            remaining = deadline - time.monotonic()
            if remaining <= 0 or not self._pump(remaining):
                if self._stream:
                    break
                raise DeviceTimeoutError(
                    f"stream on {self.url}: no sample within {timeout_s:.3g} s; check that a "
                    "stream was started and the device is acquiring",
                    Status.E_EMPTY,
                    "stream",
                )
        return self._stream.popleft()

    def stream(
        self, n: int | None = None, timeout_s: float = STREAM_TIMEOUT_S
    ) -> Iterator[Sample | Corrected]:
        """Yield n stream messages (forever when None), each within timeout_s."""
        k = 0
        while n is None or k < n:
            yield self.read_stream(timeout_s)
            k += 1

    # -- machinery
    def _next_seq(self) -> int:
        self._seq = (self._seq + 1) & 0xFFFF
        return self._seq

    def _request(
        self,
        name: str,
        fields: dict[str, Any],
        *,
        timeout_s: float | None = None,
        check: bool = True,
        op: str | None = None,
    ) -> dict[str, Any]:
        """Send a request and return its response's fields; same bytes on every retry."""
        op = op or name
        req = message_def(name)
        resp = response_id(name)
        seq = self._next_seq()
        # The leading delimiter flushes any line noise waiting in the device's receiver.
        wire = b"\x00" + encode_message(name, seq, fields)
        timeout_s = self.config.request_timeout_s if timeout_s is None else timeout_s
        attempts = 1 + self.config.request_retries
        self.stats.requests += 1
        if name == "stream_start":
            # Its messages carry this seq and may follow the response immediately.
            self._stream_seq = seq
            self._stream.clear()
        for attempt in range(1, attempts + 1):
            if attempt > 1:
                self.stats.retries += 1
                log.warning(
                    "%s on %s: no response within %.3g s; retry %d of %d (seq %d, same bytes)",
                    op,
                    self.url,
                    timeout_s,
                    attempt - 1,
                    attempts - 1,
                    seq,
                )
            self.link.write(wire)
            try:
                f = self._await(req.id, resp, seq, timeout_s, op)
            except _AttemptTimeoutError:
                continue
            if check and f["status"] != Status.OK:
                if name == "stream_start":
                    self._stream_seq = None
                raise _refusal(op, f["status"], self.url)
            return f
        if name == "stream_start":
            self._stream_seq = None
        raise DeviceTimeoutError(
            f"{op} on {self.url}: no response after {attempts} attempts of {timeout_s:.3g} s; "
            "check the device is powered, runs the magcal firmware, and the port (and baud rate)",
            Status.E_EMPTY,
            op,
        )

    def _await(
        self, req_id: int, resp_id: int, seq: int, timeout_s: float, op: str
    ) -> dict[str, Any]:
        """The response's fields; _AttemptTimeoutError when none came within timeout_s (the
        caller retries), the device's DeviceError on a nack."""
        deadline = time.monotonic() + timeout_s
        self._awaiting = (req_id, resp_id, seq, op)
        self._response = None
        self._nack = None
        try:
            while self._response is None:
                remaining = deadline - time.monotonic()
                if remaining <= 0 or not self._pump(remaining):
                    raise _AttemptTimeoutError(
                        f"{op} on {self.url}: no response within {timeout_s:.3g} s (seq {seq})",
                        Status.E_EMPTY,
                        op,
                    )
                if self._nack is not None:
                    raise self._nack
            return self._response
        finally:
            self._awaiting = None

    _awaiting: tuple[int, int, int, str] | None = None
    _response: dict[str, Any] | None = None
    _nack: DeviceError | None = None

    def _pump(self, timeout_s: float) -> bool:
        """Read once (up to timeout_s) and route what arrived; False on a time-out."""
        try:
            data = self.link.read(timeout_s)
        except LinkTimeoutError:
            return False
        for ev in self.deframer.feed(data):
            if isinstance(ev, Frame):
                self._route(ev)
        return True

    def _route(self, fr: Frame) -> None:
        if fr.id in (MessageId.SAMPLE, MessageId.CORRECTED):
            if fr.seq != self._stream_seq:
                self.stats.stale_frames += 1  # a stopped or replaced stream's message
                return
            try:
                _, f = unpack_message(fr.id, fr.payload)
            except ProtocolError as exc:
                self.stats.bad_payloads += 1
                log.warning("stream on %s: bad payload dropped (%s)", self.url, exc)
                return
            if fr.id == MessageId.SAMPLE:
                msg: Sample | Corrected = Sample(f["seq"], f["t_us"], f["mag"], f["acc"], f["gyr"])
            else:
                msg = Corrected(f["seq"], f["t_us"], f["mag"], f["out_exp"], f["m_b"])
            if len(self._stream) >= self.config.stream_queue_max:
                self._stream.popleft()
                self.stats.stream_queue_dropped += 1
            self._stream.append(msg)
            return
        aw = self._awaiting
        if aw is None or fr.seq != aw[2] or fr.id not in (aw[1], MessageId.NACK):
            self.stats.stale_frames += 1  # a late duplicate or an earlier request's answer
            return
        try:
            _, f = unpack_message(fr.id, fr.payload)
        except ProtocolError as exc:
            self.stats.bad_payloads += 1
            log.warning("%s on %s: bad response payload dropped (%s)", aw[3], self.url, exc)
            return
        if fr.id == MessageId.NACK:
            if f["request_id"] != aw[0]:
                self.stats.stale_frames += 1
                return
            # Raised by _await once the whole chunk is routed (later frames are kept).
            self._nack = DeviceError(
                f"{aw[3]} on {self.url}: device refused the frame with nack "
                f"{_status_name(f['status'])}; "
                + _ADVICE.get(f["status"], "check the magcal and firmware versions"),
                f["status"],
                aw[3],
            )
            return
        self._response = f
