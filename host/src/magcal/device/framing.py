# SPDX-License-Identifier: Apache-2.0
"""The device protocol's framing and message codec (protocol/SPEC.md), on bytes.

A frame on the wire is ``COBS(body) 0x00`` with ``body = id (u8) | seq (u16 LE) | payload |
crc (u16 LE)`` and crc the CRC-16/CCITT-FALSE of ``id | seq | payload``. Message layouts come
from the generated tables (:mod:`magcal.device.generated`, from protocol/schema.json).

Everything here is a pure function of bytes except :class:`Deframer`, which keeps the bytes
of a frame in progress between calls. Nothing blocks and nothing reads a port: the link layer
feeds received bytes to a Deframer and writes what :func:`encode_frame` returns.
"""

from __future__ import annotations

import binascii
import struct
from dataclasses import dataclass
from typing import Any

from magcal.device import generated as g
from magcal.device.generated import Message, MessageId, Status
from magcal.errors import MagcalError

CRC16_CCITT_FALSE_INIT = 0xFFFF
_STATUS_VALUES = frozenset(s.value for s in Status)


class ProtocolError(MagcalError):
    """A frame or a payload that does not follow the protocol; ``status`` says how."""

    def __init__(self, status: Status, message: str) -> None:
        super().__init__(message)
        self.status = status


def crc16_ccitt_false(data: bytes) -> int:
    """CRC-16/CCITT-FALSE (poly 0x1021, init 0xFFFF, no reflection, xorout 0); check 0x29B1."""
    return binascii.crc_hqx(data, CRC16_CCITT_FALSE_INIT)


def crc32_iso_hdlc(data: bytes) -> int:
    """CRC-32/ISO-HDLC (the zlib CRC-32), check 0xCBF43926: the parameter blob's CRC."""
    return binascii.crc32(data) & 0xFFFFFFFF


# ----------------------------------------------------------------------------- COBS
def cobs_encode(data: bytes) -> bytes:
    """Consistent Overhead Byte Stuffing: the result has no 0x00 and is at most
    ``len(data) + len(data) // 254 + 1`` bytes."""
    out = bytearray([0])
    code_at, code = 0, 1
    for b in data:
        if b == 0:
            out[code_at] = code
            code_at, code = len(out), 1
            out.append(0)
            continue
        out.append(b)
        code += 1
        if code == 0xFF:  # a full block of 254 bytes: no implied zero after it
            out[code_at] = code
            code_at, code = len(out), 1
            out.append(0)
    out[code_at] = code
    return bytes(out)


def _cobs_decode_lenient(data: bytes) -> tuple[bytes, bool]:
    """Decode as far as possible: (decoded bytes, whether the last block was cut short)."""
    out = bytearray()
    i, n = 0, len(data)
    while i < n:
        code = data[i]
        if code == 0:
            raise ProtocolError(Status.E_FRAME, "COBS decode: a 0x00 inside the encoded data")
        block = data[i + 1 : i + code]
        out += block
        if len(block) < code - 1:
            return bytes(out), True
        i += code
        if i < n and code != 0xFF:
            out.append(0)
    return bytes(out), False


def cobs_decode(data: bytes) -> bytes:
    """Inverse of :func:`cobs_encode`; raises ProtocolError(E_FRAME) on a malformed input."""
    out, truncated = _cobs_decode_lenient(data)
    if truncated:
        raise ProtocolError(Status.E_FRAME, "COBS decode: the last block is cut short")
    return out


# ----------------------------------------------------------------------------- frames
@dataclass(frozen=True)
class Frame:
    """A good frame: message id, request sequence and payload (not yet checked against the
    message catalogue)."""

    id: int
    seq: int
    payload: bytes


@dataclass(frozen=True)
class BadFrame:
    """A delimiter-terminated chunk that is not a good frame: status is E_FRAME (COBS or too
    short), E_CRC or E_OVERFLOW (longer than the receive buffer); raw is its encoded bytes
    (at most a buffer's worth)."""

    status: Status
    raw: bytes


def encode_frame(msg_id: int, seq: int, payload: bytes = b"") -> bytes:
    """The wire bytes of one frame, delimiter included."""
    if not 0 <= msg_id <= 0xFF or not 0 <= seq <= 0xFFFF:
        raise ProtocolError(
            Status.E_RANGE, f"encode frame: id {msg_id} or seq {seq} out of range (u8, u16)"
        )
    if len(payload) > g.FRAME_MAX_PAYLOAD:
        raise ProtocolError(
            Status.E_LENGTH,
            f"encode frame: payload of {len(payload)} bytes; the protocol allows at most "
            f"{g.FRAME_MAX_PAYLOAD}",
        )
    body = struct.pack(g.FRAME_HEADER_FORMAT, msg_id, seq) + bytes(payload)
    body += struct.pack("<H", crc16_ccitt_false(body))
    return cobs_encode(body) + b"\x00"


def _judge_body(body: bytes, truncated: bool, raw: bytes, max_body: int) -> Frame | BadFrame:
    if len(body) > max_body:
        return BadFrame(Status.E_OVERFLOW, raw)
    if truncated or len(body) < g.FRAME_MIN_BODY:
        return BadFrame(Status.E_FRAME, raw)
    (crc,) = struct.unpack_from("<H", body, len(body) - g.FRAME_CRC_SIZE)
    if crc16_ccitt_false(body[: -g.FRAME_CRC_SIZE]) != crc:
        return BadFrame(Status.E_CRC, raw)
    msg_id, seq = struct.unpack_from(g.FRAME_HEADER_FORMAT, body)
    return Frame(msg_id, seq, body[g.FRAME_HEADER_SIZE : -g.FRAME_CRC_SIZE])


def decode_frame(encoded: bytes, max_body: int = g.FRAME_MAX_BODY) -> Frame:
    """Decode one frame's encoded bytes (without the delimiter); raises ProtocolError with
    status E_FRAME, E_CRC or E_OVERFLOW."""
    if b"\x00" in encoded:
        raise ProtocolError(Status.E_FRAME, "decode frame: a 0x00 inside the encoded frame")
    body, truncated = _cobs_decode_lenient(encoded)
    result = _judge_body(body, truncated, encoded, max_body)
    if isinstance(result, BadFrame):
        raise ProtocolError(
            result.status, f"decode frame: {result.status.name} in a {len(encoded)}-byte frame"
        )
    return result


class Deframer:
    """Splits a received byte stream into frames at 0x00 delimiters.

    feed() never raises on line noise: every non-empty chunk ended by a delimiter gives one
    event, a Frame or a BadFrame, and the next frame starts after the delimiter, so one bad
    frame costs exactly that frame (resynchronisation). Empty chunks (0x00 0x00) are skipped.
    A chunk longer than the receive buffer (max_body bytes decoded) is dropped as it comes,
    keeping at most a few hundred bytes, and reported as E_OVERFLOW. The counters match the
    C decoder's (frame.h).
    """

    def __init__(self, max_body: int = g.FRAME_MAX_BODY) -> None:
        if max_body < g.FRAME_MIN_BODY:
            raise ProtocolError(
                Status.E_ARG, f"deframer: max_body {max_body} < {g.FRAME_MIN_BODY} (header + CRC)"
            )
        self.max_body = max_body
        # An encoded chunk longer than this decodes to more than max_body bytes (COBS
        # removes at most one byte in 255 plus one), so it can be dropped unseen.
        self._keep = 2 * (max_body + 2)
        self._buf = bytearray()
        self._overflowed = False
        self.n_ok = 0
        self.n_crc = 0
        self.n_malformed = 0
        self.n_overflow = 0

    def reset(self) -> None:
        """Drop the frame in progress (counters are kept)."""
        self._buf.clear()
        self._overflowed = False

    def feed(self, data: bytes) -> list[Frame | BadFrame]:
        events: list[Frame | BadFrame] = []
        start = 0
        while True:
            end = data.find(b"\x00", start)
            if end < 0:
                self._append(data[start:])
                return events
            self._append(data[start:end])
            event = self._finish()
            if event is not None:
                events.append(event)
            start = end + 1

    def _append(self, chunk: bytes) -> None:
        if self._overflowed:
            return
        self._buf += chunk
        if len(self._buf) > self._keep:
            self._overflowed = True
            del self._buf[self._keep :]

    def _finish(self) -> Frame | BadFrame | None:
        raw = bytes(self._buf)
        overflowed = self._overflowed
        self.reset()
        if not raw:
            return None
        if overflowed:
            event: Frame | BadFrame = BadFrame(Status.E_OVERFLOW, raw)
        else:
            body, truncated = _cobs_decode_lenient(raw)
            event = _judge_body(body, truncated, raw, self.max_body)
        if isinstance(event, Frame):
            self.n_ok += 1
        elif event.status == Status.E_CRC:
            self.n_crc += 1
        elif event.status == Status.E_OVERFLOW:
            self.n_overflow += 1
        else:
            self.n_malformed += 1
        return event


# ----------------------------------------------------------------------------- messages
def message_def(which: int | str) -> Message:
    """The catalogue entry of a message id or name; ProtocolError(E_UNKNOWN_MESSAGE)."""
    table = g.MESSAGES_BY_NAME if isinstance(which, str) else g.MESSAGES_BY_ID
    try:
        return table[which]
    except KeyError:
        shown = which if isinstance(which, str) else f"0x{which:02X}"
        raise ProtocolError(
            Status.E_UNKNOWN_MESSAGE,
            f"message {shown} is not in the catalogue (protocol/schema.json)",
        ) from None


def pack_message(which: int | str, fields: dict[str, Any]) -> bytes:
    """The payload of message ``which`` (id or name) with the given field values: ints,
    sequences of ints for arrays, str for char fields, bytes for a bytes field. Every field
    must be given; struct.error and out-of-range values raise ProtocolError(E_RANGE)."""
    m = message_def(which)
    names = {f.name for f in m.fields}
    if set(fields) != names:
        raise ProtocolError(
            Status.E_ARG,
            f"pack {m.name}: fields {sorted(fields)} given; it has exactly {sorted(names)}",
        )
    flat: list[Any] = []
    tail = b""
    for f in m.fields:
        v = fields[f.name]
        if f.type == "bytes":
            tail = bytes(v)
            if len(tail) > f.max:
                raise ProtocolError(
                    Status.E_RANGE,
                    f"pack {m.name}: {f.name} has {len(tail)} bytes; at most {f.max}",
                )
        elif f.type == "char":
            flat.append(v.encode("latin-1"))
            if len(flat[-1]) > f.count:
                raise ProtocolError(
                    Status.E_RANGE, f"pack {m.name}: {f.name} longer than {f.count} characters"
                )
        elif f.count > 1:
            if len(v) != f.count:
                raise ProtocolError(
                    Status.E_RANGE, f"pack {m.name}: {f.name} needs {f.count} values"
                )
            flat += [int(x) for x in v]
        else:
            flat.append(int(v))
    try:
        return struct.pack(m.struct_format, *flat) + tail
    except struct.error as exc:
        raise ProtocolError(Status.E_RANGE, f"pack {m.name}: {exc}") from None


def unpack_message(msg_id: int, payload: bytes) -> tuple[Message, dict[str, Any]]:
    """The catalogue entry and field values of a payload: ints, tuples for arrays, str for
    char fields (trailing NULs removed), bytes for a bytes field; a status field is a Status
    when the value is known. Raises ProtocolError E_UNKNOWN_MESSAGE or E_LENGTH."""
    m = message_def(msg_id)
    n = len(payload)
    if n < m.fixed_size or n > m.fixed_size + m.bytes_max:
        want = (
            f"{m.fixed_size}"
            if not m.bytes_max
            else f"{m.fixed_size} to {m.fixed_size + m.bytes_max}"
        )
        raise ProtocolError(
            Status.E_LENGTH, f"unpack {m.name}: payload of {n} bytes; it takes {want}"
        )
    flat = list(struct.unpack_from(m.struct_format, payload))
    out: dict[str, Any] = {}
    for f in m.fields:
        if f.type == "bytes":
            out[f.name] = bytes(payload[m.fixed_size :])
        elif f.type == "char":
            out[f.name] = flat.pop(0).decode("latin-1").rstrip("\x00")
        elif f.count > 1:
            out[f.name] = tuple(flat[: f.count])
            del flat[: f.count]
        else:
            v = flat.pop(0)
            if f.enum == "status" and v in _STATUS_VALUES:
                v = Status(v)
            out[f.name] = v
    return m, out


def encode_message(which: int | str, seq: int, fields: dict[str, Any]) -> bytes:
    """The wire bytes of a message: pack_message then encode_frame."""
    m = message_def(which)
    return encode_frame(m.id, seq, pack_message(m.id, fields))


def response_id(request: int | str) -> MessageId:
    """The id of the response to a request (id | 0x80); ProtocolError for a non-request."""
    m = message_def(request)
    if not m.response:
        raise ProtocolError(Status.E_ARG, f"{m.name} is not a request: it has no response")
    return MessageId(g.MESSAGES_BY_NAME[m.response].id)
