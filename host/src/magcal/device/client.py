"""The host side of the device protocol (protocol/SPEC.md §2-§5) over a :class:`Link`.

``DeviceClient(link)`` sends requests and waits for their responses; stream messages that
arrive meanwhile are queued and read with :meth:`DeviceClient.read_stream` /
:meth:`DeviceClient.stream`. Every request gets a fresh seq (previous + 1 modulo 2^16); when
no response arrives within the time-out, the *same bytes* are sent again (the device answers
a retry from its cache without acting twice), at most ``request_retries`` times, and then the
last error is raised. A device's refusal (a status other than OK, or a nack) raises
:class:`DeviceError` with the status name. Line noise never raises: the Deframer drops bad
frames and counts them (``client.stats``).

:func:`flash_parameters` is SPEC §5's flash flow with a backup saved first and every step read
back; :func:`restore` writes a backup back.

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
import json
import logging
import math
import os
import random
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from datetime import datetime, timezone
from fractions import Fraction
from pathlib import Path
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
from magcal.link.base import Link, LinkClosedError, LinkError, LinkTimeoutError

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
BACKUP_FORMAT = "magcal-param-backup/1"


class DeviceError(MagcalError):
    """The device refused a request (status != OK, or a nack). ``status`` is the Status."""

    def __init__(self, message: str, status: Status | int, op: str = "") -> None:
        super().__init__(message)
        self.status = status
        self.op = op


class DeviceTimeoutError(DeviceError):
    """No response after every retry (status E_EMPTY: nothing was received)."""


class VersionMismatchError(DeviceError):
    """Host and device share no protocol version."""


class FlashError(MagcalError):
    """flash_parameters or restore stopped before writing, or a read-back did not match."""


class FlashInterruptedError(FlashError):
    """The flash flow was interrupted by a link failure. ``active`` says which complete set
    the device holds: "old", "new" or "unknown" (it could not be asked); ``step`` is the step
    that failed."""

    def __init__(self, message: str, active: str, step: str) -> None:
        super().__init__(message)
        self.active = active
        self.step = step


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
    Status.E_STATE: "the device was not in the state for this request: start the flow again",
    Status.E_SEQUENCE: "a sequence clash: send hello to start a new session",
    Status.E_UNKNOWN_MESSAGE: "the firmware does not know this request: update the firmware",
    Status.E_LENGTH: "the firmware expects another payload size: check versions",
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
            f = self._await(req.id, resp, seq, timeout_s, op)
            if f is not None:
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
    ) -> dict[str, Any] | None:
        """The response's fields, or None when the attempt timed out (the caller retries)."""
        deadline = time.monotonic() + timeout_s
        self._awaiting = (req_id, resp_id, seq, op)
        self._response = None
        self._nack = None
        try:
            while self._response is None:
                remaining = deadline - time.monotonic()
                if remaining <= 0 or not self._pump(remaining):
                    break
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


# ----------------------------------------------------------------------------- flash flow
Reconnect = Callable[[], DeviceClient]


@dataclass(frozen=True)
class FlashResult:
    """The outcome of a completed flash: the new set is active (read back bit-exact).

    active        : "new"
    crc32         : the set's CRC-32/ISO-HDLC
    backup_path   : where the previous set was saved
    recovered_from: the link failure the flow recovered from ("" when none)
    client        : the client to go on with (a reconnected one after a recovery)
    """

    active: str
    crc32: int
    backup_path: Path
    recovered_from: str = ""
    client: DeviceClient | None = field(default=None, compare=False, repr=False)


def _read_active(client: DeviceClient) -> ParamSet | None:
    """The active set, or None when the device has none (E_NO_PARAMS)."""
    try:
        return client.param_get(ParamWhich.ACTIVE)
    except DeviceError as exc:
        if exc.status == Status.E_NO_PARAMS and not isinstance(exc, DeviceTimeoutError):
            return None
        raise


def _write_backup(
    path: Path, old: ParamSet | None, info: DeviceInfo, url: str, overwrite: bool
) -> None:
    """Save the device's current set (atomically: temporary file, fsync, rename)."""
    if path.exists() and not overwrite:
        raise FlashError(
            f"flash: backup file {path} exists; nothing was written to the device: give "
            "another backup path (an earlier backup is worth keeping) or allow overwriting"
        )
    doc = {
        "format": BACKUP_FORMAT,
        "format_version": None if old is None else old.format_version,
        "blob": None if old is None else old.blob.hex(),
        "crc32": None if old is None else old.crc32,
        "device_uid": info.uid_hex,
        "fw_version": info.fw_version_str,
        "fw_build": f"{info.fw_build:08x}",
        "port": url,
        "time": datetime.now(timezone.utc).isoformat(timespec="seconds"),
    }
    tmp = path.with_name(path.name + ".tmp")
    try:
        with open(tmp, "w", encoding="utf-8") as fh:
            json.dump(doc, fh, indent=2)
            fh.write("\n")
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except OSError as exc:
        raise FlashError(
            f"flash: cannot save the backup to {path} ({exc.strerror or exc}); nothing was "
            "written to the device: choose a writable backup path"
        ) from exc


def read_backup(path: str | os.PathLike) -> dict[str, Any]:
    """A backup written by flash_parameters, checked (format, hex blob, CRC-32)."""
    p = Path(path)
    try:
        doc = json.loads(p.read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:
        raise FlashError(f"restore: cannot read backup {p} ({exc}); check the path") from exc
    if not isinstance(doc, dict) or doc.get("format") != BACKUP_FORMAT:
        raise FlashError(f"restore: {p} is not a {BACKUP_FORMAT} backup; check the file")
    if doc.get("blob") is not None:
        try:
            blob = bytes.fromhex(doc["blob"])
        except (TypeError, ValueError) as exc:
            raise FlashError(
                f"restore: backup {p} has a malformed blob; the file is damaged"
            ) from exc
        if crc32_iso_hdlc(blob) != doc.get("crc32"):
            raise FlashError(
                f"restore: backup {p}'s blob does not match its CRC-32; the file is damaged: "
                "do not write it"
            )
        doc["blob"] = blob
    return doc


def _hello_after_reset(client: DeviceClient, reconnect: Reconnect | None) -> DeviceClient:
    """hello until the restarted device answers (reconnecting when the link dropped)."""
    deadline = time.monotonic() + client.config.reset_recovery_timeout_s
    attempt = 0
    while True:
        attempt += 1
        try:
            client.hello()
            return client
        except (LinkError, DeviceTimeoutError) as exc:
            if time.monotonic() >= deadline:
                raise
            log.info("hello after reset on %s: attempt %d failed (%s)", client.url, attempt, exc)
            if isinstance(exc, LinkError) and reconnect is not None:
                client.close()
                try:
                    client = reconnect()
                except LinkError as exc2:
                    log.info("reconnect after reset failed (%s)", exc2)
                    if time.monotonic() >= deadline:
                        raise
                    time.sleep(0.1)
            elif isinstance(exc, LinkClosedError):
                raise


def _same(p: ParamSet | None, blob: bytes | None, format_version: int | None) -> bool:
    if p is None or blob is None:
        return p is None and blob is None
    return p.blob == blob and p.format_version == format_version


def flash_parameters(
    client: DeviceClient,
    blob: bytes,
    format_version: int,
    backup_path: str | os.PathLike,
    *,
    reconnect: Reconnect | None = None,
    overwrite_backup: bool = False,
) -> FlashResult:
    """Write a parameter set with SPEC §5's flow, every step checked:

    hello (when not done) and info (format version and size must match) -> param_get(active)
    -> backup file saved (before anything is written) -> param_set -> param_get(staged)
    compared bit for bit -> param_commit(crc32) -> reset -> hello -> param_get(active)
    compared bit for bit with ``blob``.

    reconnect : makes a new client on a fresh link (used after a reset that dropped the link,
        and after a link failure to find out what the device holds)

    Returns FlashResult(active="new"), also when a link failure was recovered from and the
    device was found to hold the new set. Raises FlashInterruptedError with ``active`` "old"
    or "unknown" when a link failure left the device without the new set (or nobody could
    ask it); DeviceError when the device refused a step (it then keeps its old set);
    FlashError when a read-back differs or before writing anything (backup, format checks).
    """
    blob = bytes(blob)
    crc = crc32_iso_hdlc(blob)
    path = Path(backup_path)
    commit_sent = False
    step = "hello"
    old: ParamSet | None = None
    try:
        if client.version is None:
            client.hello()
        step = "info"
        info = client.info()
        if info.params_format_version != format_version or info.params_size != len(blob):
            raise FlashError(
                f"flash on {client.url}: the device takes parameter format "
                f"{info.params_format_version} of {info.params_size} bytes; this set is format "
                f"{format_version} of {len(blob)} bytes; nothing was written: convert the "
                "calibration for this firmware"
            )
        step = "param_get(active)"
        old = _read_active(client)
        _write_backup(path, old, info, client.url, overwrite_backup)
        log.info("flash on %s: previous set saved to %s", client.url, path)
        step = "param_set"
        client.param_set(format_version, blob)
        step = "param_get(staged)"
        staged = client.param_get(ParamWhich.STAGED)
        if not _same(staged, blob, format_version) or staged.crc32 != crc:
            raise FlashError(
                f"flash on {client.url}: the staged set read back differs from the one sent "
                "(nothing committed; the device keeps its old set): check the link and retry"
            )
        step = "param_commit"
        commit_sent = True
        client.param_commit(crc)
        step = "reset"
        client.reset()
        step = "hello after reset"
        client = _hello_after_reset(client, reconnect)
        step = "param_get(active) after reset"
        active = _read_active(client)
    except (LinkError, DeviceTimeoutError) as exc:
        return _recover(client, exc, step, commit_sent, reconnect, old, blob, format_version, path)
    if _same(active, blob, format_version):
        log.info(
            "flash on %s: new set active (CRC-32 0x%08x), verified bit for bit", client.url, crc
        )
        return FlashResult("new", crc, path, "", client)
    which = (
        "its old set"
        if _same(active, old.blob if old else None, format_version if old else None)
        else "another set"
    )
    raise FlashError(
        f"flash on {client.url}: after commit and reset the device uses {which}, not the new "
        f"one (CRC-32 0x{crc:08x}); the commit did not take effect: run flash again, and "
        f"restore {path} if needed"
    )


def _recover(
    client: DeviceClient,
    exc: Exception,
    step: str,
    commit_sent: bool,
    reconnect: Reconnect | None,
    old: ParamSet | None,
    blob: bytes,
    format_version: int,
    path: Path,
) -> FlashResult:
    """After a link failure at ``step``: find which complete set the device holds."""
    url = client.url
    log.warning(
        "flash on %s: link failure at %s (%s); finding out what the device holds", url, step, exc
    )
    prefix = f"flash on {url}: link failure at {step} ({exc})"
    if reconnect is None:
        if not commit_sent:
            raise FlashInterruptedError(
                f"{prefix}; the commit was never sent, so the device holds its old complete "
                "set: reconnect and run flash again",
                "old",
                step,
            ) from exc
        raise FlashInterruptedError(
            f"{prefix}; the commit was sent, so the device holds either its old or the new "
            "complete set (a commit is atomic): reconnect, read the active set (magcal verify) "
            "and flash again if it is the old one",
            "unknown",
            step,
        ) from exc
    client.close()
    try:
        fresh = reconnect()
        fresh.hello()
        if commit_sent:
            # A committed set becomes active at the next reset: restart to find out.
            fresh.reset()
            fresh = _hello_after_reset(fresh, reconnect)
        active = _read_active(fresh)
    except (LinkError, DeviceError) as exc2:
        state = "unknown" if commit_sent else "old"
        holds = (
            "either its old or the new complete set"
            if commit_sent
            else "its old complete set (the commit was never sent)"
        )
        raise FlashInterruptedError(
            f"{prefix}; reconnecting failed too ({exc2}); the device holds {holds}: check the "
            "link, then read the active set (magcal verify) and flash again if needed",
            state,
            step,
        ) from exc
    if _same(active, blob, format_version):
        log.warning("flash on %s: recovered; the device holds the new set (verified)", url)
        return FlashResult("new", crc32_iso_hdlc(blob), path, f"{step}: {exc}", fresh)
    # Without a commit nothing was stored: whatever is active is the set from before.
    if not commit_sent or _same(
        active, old.blob if old else None, old.format_version if old else None
    ):
        fresh.close()
        raise FlashInterruptedError(
            f"{prefix}; reconnected: the device holds its old complete set (verified bit for "
            "bit): run flash again",
            "old",
            step,
        ) from exc
    fresh.close()
    raise FlashInterruptedError(
        f"{prefix}; reconnected: the device's active set is neither the old nor the new one: "
        f"restore {path} or flash again",
        "unknown",
        step,
    ) from exc


def restore(
    client: DeviceClient,
    backup_path: str | os.PathLike,
    *,
    new_backup_path: str | os.PathLike | None = None,
    reconnect: Reconnect | None = None,
    force: bool = False,
) -> FlashResult:
    """Write a backup back with :func:`flash_parameters` (the current set is backed up first,
    to ``new_backup_path``, default ``<backup>.before-restore-<time>.json``). Refuses a backup
    of another device (its uid) unless force."""
    p = Path(backup_path)
    doc = read_backup(p)
    if doc.get("blob") is None:
        raise FlashError(
            f"restore: backup {p} records that the device had no parameter set; there is "
            "nothing to write back (the protocol has no erase)"
        )
    if client.version is None:
        client.hello()
    info = client.info()
    if doc.get("device_uid") != info.uid_hex and not force:
        raise FlashError(
            f"restore: backup {p} is of device {doc.get('device_uid')}, this is device "
            f"{info.uid_hex}; nothing was written: use that device's backup (or force)"
        )
    if new_backup_path is None:
        stamp = datetime.now(timezone.utc).strftime("%Y%m%dT%H%M%S%fZ")
        new_backup_path = p.with_name(f"{p.stem}.before-restore-{stamp}.json")
    return flash_parameters(
        client, doc["blob"], int(doc["format_version"]), new_backup_path, reconnect=reconnect
    )
