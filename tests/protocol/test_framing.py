# SPDX-License-Identifier: Apache-2.0
"""The host's framing and message codec (magcal.device.framing) against the golden vectors
(protocol/vectors/*.json), the CRC catalogue check value, COBS properties, and the deframer's
resynchronisation and error reporting."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from magcal.device import generated as g
from magcal.device.framing import (
    BadFrame,
    Deframer,
    Frame,
    ProtocolError,
    cobs_decode,
    cobs_encode,
    crc16_ccitt_false,
    crc32_iso_hdlc,
    decode_frame,
    encode_frame,
    encode_message,
    message_def,
    pack_message,
    response_id,
    unpack_message,
)
from magcal.device.generated import MessageId, Status

VECTORS = Path(__file__).resolve().parents[2] / "protocol" / "vectors"
MESSAGE_VECTORS = json.loads((VECTORS / "messages.json").read_text())["vectors"]
STREAM_VECTORS = json.loads((VECTORS / "frames.json").read_text())["vectors"]


def _json_values(m, fields: dict) -> dict:
    """Vector field values (lists, hex strings) as unpack_message gives them."""
    out = {}
    for f in m.fields:
        v = fields[f.name]
        if f.type == "bytes":
            v = bytes.fromhex(v)
        elif isinstance(v, list):
            v = tuple(v)
        out[f.name] = v
    return out


def _events_as_json(events) -> list[dict]:
    out = []
    for e in events:
        if isinstance(e, BadFrame):
            out.append({"status": e.status.name})
            continue
        d = {"status": "OK", "id": e.id, "seq": e.seq, "payload": e.payload.hex()}
        try:
            m, _ = unpack_message(e.id, e.payload)
        except ProtocolError as exc:
            d["message_status"] = exc.status.name
        else:
            d["message_status"] = "OK"
            d["message"] = m.name
        out.append(d)
    return out


# ----------------------------------------------------------------------------- CRCs, COBS
def test_crc_catalogue_check_values():
    assert crc16_ccitt_false(b"123456789") == 0x29B1
    assert crc32_iso_hdlc(b"123456789") == 0xCBF43926
    assert g.FRAME_CRC == "CRC-16/CCITT-FALSE"


@pytest.mark.parametrize(
    ("data", "encoded"),
    [  # examples from the COBS paper / Wikipedia
        (b"", b"\x01"),
        (b"\x00", b"\x01\x01"),
        (b"\x00\x00", b"\x01\x01\x01"),
        (b"\x11\x22\x00\x33", b"\x03\x11\x22\x02\x33"),
        (b"\x11\x22\x33\x44", b"\x05\x11\x22\x33\x44"),
        (b"\x11\x00\x00\x00", b"\x02\x11\x01\x01\x01"),
        (bytes(range(1, 255)), b"\xff" + bytes(range(1, 255)) + b"\x01"),
        (bytes(range(0, 255)), b"\x01\xff" + bytes(range(1, 255)) + b"\x01"),
    ],
)
def test_cobs_known_encodings(data, encoded):
    assert cobs_encode(data) == encoded
    assert cobs_decode(encoded) == data


def test_cobs_round_trip_random():
    rng = np.random.default_rng(5)
    for n in [0, 1, 253, 254, 255, 508, 1000]:
        for zeros in (0.0, 0.01, 0.5):
            data = rng.integers(1, 256, n, dtype=np.uint8)
            data[rng.random(n) < zeros] = 0
            raw = data.tobytes()
            enc = cobs_encode(raw)
            assert b"\x00" not in enc
            assert len(enc) <= n + n // 254 + 1
            assert cobs_decode(enc) == raw


@pytest.mark.parametrize("bad", [b"\x05\x11\x22", b"\x03\x11\x00\x22", b"\x00"])
def test_cobs_decode_rejects_malformed(bad):
    with pytest.raises(ProtocolError, match="COBS decode") as info:
        cobs_decode(bad)
    assert info.value.status == Status.E_FRAME


# ----------------------------------------------------------------------------- vectors
@pytest.mark.parametrize("vec", MESSAGE_VECTORS, ids=[v["name"] for v in MESSAGE_VECTORS])
def test_message_vector(vec):
    m = message_def(vec["message"])
    values = _json_values(m, vec["fields"])
    payload = bytes.fromhex(vec["payload"])
    wire = bytes.fromhex(vec["wire"])
    assert pack_message(vec["message"], values) == payload
    assert encode_message(vec["id"], vec["seq"], values) == wire
    assert encode_frame(vec["id"], vec["seq"], payload) == wire
    frame = decode_frame(wire[:-1])
    assert frame == Frame(vec["id"], vec["seq"], payload)
    got_m, got = unpack_message(frame.id, frame.payload)
    assert got_m is m
    assert got == values
    assert len(wire) <= g.FRAME_MAX_ENCODED


@pytest.mark.parametrize("vec", STREAM_VECTORS, ids=[v["name"] for v in STREAM_VECTORS])
def test_stream_vector(vec):
    wire = bytes.fromhex(vec["wire"])
    d = Deframer()
    assert _events_as_json(d.feed(wire)) == vec["events"]
    assert d.n_ok + d.n_crc + d.n_malformed + d.n_overflow == len(vec["events"])
    # Byte by byte and in uneven pieces: the same events.
    d1 = Deframer()
    one = [e for b in wire for e in d1.feed(bytes([b]))]
    assert _events_as_json(one) == vec["events"]
    d2, pieces, at, k = Deframer(), [], 0, 1
    while at < len(wire):
        pieces += d2.feed(wire[at : at + k])
        at, k = at + k, k * 3 % 17 + 1
    assert _events_as_json(pieces) == vec["events"]


def test_every_message_has_a_vector():
    assert {v["message"] for v in MESSAGE_VECTORS} == {m.name for m in g.MESSAGES}


def test_vectors_cover_every_frame_error():
    seen = {e["status"] for v in STREAM_VECTORS for e in v["events"]}
    seen |= {e.get("message_status") for v in STREAM_VECTORS for e in v["events"]}
    assert {"OK", "E_CRC", "E_FRAME", "E_OVERFLOW", "E_UNKNOWN_MESSAGE", "E_LENGTH"} <= seen


# ----------------------------------------------------------------------------- deframer
def test_deframer_survives_random_garbage_and_resynchronises():
    rng = np.random.default_rng(11)
    good = bytes.fromhex(MESSAGE_VECTORS[0]["wire"])
    d = Deframer()
    n_good = 0
    for _ in range(300):
        noise = rng.integers(0, 256, int(rng.integers(0, 400)), dtype=np.uint8).tobytes()
        events = d.feed(noise + b"\x00" + good)
        assert all(isinstance(e, Frame | BadFrame) for e in events)
        n_good += sum(1 for e in events if e == decode_frame(good[:-1]))
    assert n_good == 300  # the frame after each delimiter always decodes


def test_deframer_bounds_memory_on_endless_noise():
    d = Deframer()
    for _ in range(100):
        assert d.feed(b"\x55" * 10_000) == []
    assert len(d._buf) <= d._keep
    (event,) = d.feed(b"\x00")
    assert event.status == Status.E_OVERFLOW and d.n_overflow == 1


def test_deframer_small_buffer_and_reset():
    wire = bytes.fromhex(MESSAGE_VECTORS[0]["wire"])  # hello: 4-byte payload, body 9
    assert [e.status for e in Deframer(max_body=8).feed(wire)] == [Status.E_OVERFLOW]
    assert isinstance(Deframer(max_body=9).feed(wire)[0], Frame)
    d = Deframer()
    d.feed(wire[:4])
    d.reset()
    assert [type(e) for e in d.feed(wire)] == [Frame]
    with pytest.raises(ProtocolError, match="max_body 4"):
        Deframer(max_body=4)


# ----------------------------------------------------------------------------- errors
def test_encode_frame_refuses_bad_arguments():
    with pytest.raises(ProtocolError, match="at most 240") as info:
        encode_frame(0x7E, 0, bytes(g.FRAME_MAX_PAYLOAD + 1))
    assert info.value.status == Status.E_LENGTH
    with pytest.raises(ProtocolError, match="out of range"):
        encode_frame(0x100, 0)
    with pytest.raises(ProtocolError, match="out of range"):
        encode_frame(1, 0x10000)


def test_decode_frame_errors():
    wire = bytes.fromhex(MESSAGE_VECTORS[0]["wire"])[:-1]
    with pytest.raises(ProtocolError, match="E_CRC"):
        decode_frame(wire[:-1] + bytes([wire[-1] ^ 1]))
    with pytest.raises(ProtocolError, match="0x00 inside"):
        decode_frame(wire[:3] + b"\x00" + wire[3:])
    with pytest.raises(ProtocolError, match="E_FRAME"):
        decode_frame(b"\x03\x01\x02")
    with pytest.raises(ProtocolError, match="E_OVERFLOW"):
        decode_frame(wire, max_body=8)


def test_unpack_message_errors():
    with pytest.raises(ProtocolError, match="0x7E is not in the catalogue") as info:
        unpack_message(0x7E, b"")
    assert info.value.status == Status.E_UNKNOWN_MESSAGE
    with pytest.raises(ProtocolError, match="payload of 29 bytes; it takes 30") as info:
        unpack_message(MessageId.SAMPLE, bytes(29))
    assert info.value.status == Status.E_LENGTH
    with pytest.raises(ProtocolError, match="it takes 2 to 226"):
        unpack_message(MessageId.PARAM_SET, bytes(227))


def test_pack_message_errors():
    with pytest.raises(ProtocolError, match="fields .* given"):
        pack_message("hello", {"host_min_version": 1})
    with pytest.raises(ProtocolError, match="E_RANGE|format requires|out of range") as info:
        pack_message("hello", {"host_min_version": -1, "host_max_version": 1})
    assert info.value.status == Status.E_RANGE
    with pytest.raises(ProtocolError, match="blob has 225 bytes; at most 224"):
        pack_message("param_set", {"format_version": 1, "blob": bytes(225)})
    with pytest.raises(ProtocolError, match="needs 3 values"):
        pack_message(
            "sample", {"seq": 0, "t_us": 0, "mag": (1, 2), "acc": (0,) * 3, "gyr": (0,) * 3}
        )
    with pytest.raises(ProtocolError, match="not in the catalogue"):
        pack_message("no_such_message", {})


def test_status_field_becomes_status_enum():
    m, values = unpack_message(MessageId.NACK, bytes([0xF3, 0x7E]))
    assert values["status"] is Status.E_UNKNOWN_MESSAGE
    _, values = unpack_message(MessageId.NACK, bytes([0x80, 0x7E]))  # unknown: stays int
    assert values["status"] == -128 and not isinstance(values["status"], Status)


def test_requests_and_responses():
    assert response_id("param_set") == MessageId.PARAM_SET_RESP
    assert response_id(MessageId.HELLO) == MessageId.HELLO_RESP
    with pytest.raises(ProtocolError, match="sample is not a request"):
        response_id("sample")
    for m in g.MESSAGES:
        assert (m.id >= 0x80) == (m.direction == "from_device")


def test_sample_wire_overhead():
    """A sample is 30 payload bytes and 37 on the wire (header 3, CRC 2, COBS 1, delimiter 1)."""
    sample = next(v for v in MESSAGE_VECTORS if v["message"] == "sample")
    assert len(sample["payload"]) // 2 == 30
    assert len(sample["wire"]) // 2 == 37
