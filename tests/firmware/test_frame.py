# SPDX-License-Identifier: Apache-2.0
"""The C frame codec (frame.h, messages.h) through the shared library: the golden vectors,
and agreement with the host's Deframer on random byte streams."""

from __future__ import annotations

import ctypes
import json
from pathlib import Path

import numpy as np
import pytest

from magcal.device import generated as g
from magcal.device.framing import BadFrame, Deframer, encode_frame
from magcal.device.generated import Status

VECTORS = Path(__file__).resolve().parents[2] / "protocol" / "vectors"
MESSAGE_VECTORS = json.loads((VECTORS / "messages.json").read_text())["vectors"]
STREAM_VECTORS = json.loads((VECTORS / "frames.json").read_text())["vectors"]
MSG_T_BYTES = 1024  # room for mc_msg_t (its size is not exported; it is a few hundred bytes)


class FrameT(ctypes.Structure):
    _fields_ = [
        ("id", ctypes.c_uint8),
        ("seq", ctypes.c_uint16),
        ("payload", ctypes.POINTER(ctypes.c_uint8)),
        ("payload_len", ctypes.c_size_t),
    ]


class DecoderT(ctypes.Structure):
    """mc_frame_decoder_t, field for field."""

    _fields_ = [
        ("buf", ctypes.POINTER(ctypes.c_uint8)),
        ("cap", ctypes.c_size_t),
        ("len", ctypes.c_size_t),
        ("code", ctypes.c_uint8),
        ("left", ctypes.c_uint8),
        ("discarding", ctypes.c_uint8),
        ("n_ok", ctypes.c_uint32),
        ("n_crc", ctypes.c_uint32),
        ("n_malformed", ctypes.c_uint32),
        ("n_overflow", ctypes.c_uint32),
    ]


@pytest.fixture(scope="module")
def fw(fwlib):
    fwlib.mc_frame_decoder_init.argtypes = [
        ctypes.POINTER(DecoderT),
        ctypes.POINTER(ctypes.c_uint8),
        ctypes.c_size_t,
    ]
    fwlib.mc_frame_decoder_init.restype = ctypes.c_int
    fwlib.mc_frame_decoder_push.argtypes = [
        ctypes.POINTER(DecoderT),
        ctypes.c_uint8,
        ctypes.POINTER(FrameT),
    ]
    fwlib.mc_frame_decoder_push.restype = ctypes.c_int
    fwlib.mc_frame_encode.argtypes = [
        ctypes.c_uint8,
        ctypes.c_uint16,
        ctypes.c_char_p,
        ctypes.c_size_t,
        ctypes.c_char_p,
        ctypes.c_size_t,
        ctypes.POINTER(ctypes.c_size_t),
    ]
    fwlib.mc_frame_encode.restype = ctypes.c_int
    fwlib.mc_msg_unpack.argtypes = [
        ctypes.c_uint8,
        ctypes.POINTER(ctypes.c_uint8),
        ctypes.c_size_t,
        ctypes.c_char_p,
    ]
    fwlib.mc_msg_unpack.restype = ctypes.c_int
    return fwlib


class CDecoder:
    def __init__(self, fw, cap: int = g.FRAME_MAX_BODY) -> None:
        self.fw = fw
        self.buf = (ctypes.c_uint8 * cap)()
        self.d = DecoderT()
        assert fw.mc_frame_decoder_init(ctypes.byref(self.d), self.buf, cap) == Status.OK

    def feed(self, data: bytes) -> list[dict]:
        events = []
        f = FrameT()
        msg = ctypes.create_string_buffer(MSG_T_BYTES)
        for b in data:
            st = self.fw.mc_frame_decoder_push(ctypes.byref(self.d), b, ctypes.byref(f))
            if st == Status.E_EMPTY:
                continue
            if st != Status.OK:
                events.append({"status": Status(st).name})
                continue
            payload = bytes(f.payload[: f.payload_len]) if f.payload_len else b""
            ms = self.fw.mc_msg_unpack(f.id, f.payload, f.payload_len, msg)
            events.append(
                {
                    "status": "OK",
                    "id": f.id,
                    "seq": f.seq,
                    "payload": payload.hex(),
                    "message_status": Status(ms).name,
                }
            )
        return events


def _strip_names(events: list[dict]) -> list[dict]:
    return [{k: v for k, v in e.items() if k != "message"} for e in events]


@pytest.mark.parametrize("vec", STREAM_VECTORS, ids=[v["name"] for v in STREAM_VECTORS])
def test_c_decoder_stream_vectors(fw, vec):
    dec = CDecoder(fw)
    assert dec.feed(bytes.fromhex(vec["wire"])) == _strip_names(vec["events"])
    d = dec.d
    assert d.n_ok + d.n_crc + d.n_malformed + d.n_overflow == len(vec["events"])


@pytest.mark.parametrize("vec", MESSAGE_VECTORS, ids=[v["name"] for v in MESSAGE_VECTORS])
def test_c_encoder_message_vectors(fw, vec):
    payload = bytes.fromhex(vec["payload"])
    out = ctypes.create_string_buffer(g.FRAME_MAX_ENCODED)
    n = ctypes.c_size_t(0)
    st = fw.mc_frame_encode(
        vec["id"], vec["seq"], payload, len(payload), out, len(out), ctypes.byref(n)
    )
    assert st == Status.OK
    assert out.raw[: n.value].hex() == vec["wire"]


def test_c_encoder_refuses_too_small_buffer(fw):
    vec = MESSAGE_VECTORS[0]
    payload = bytes.fromhex(vec["payload"])
    out = ctypes.create_string_buffer(len(vec["wire"]) // 2 - 1)
    n = ctypes.c_size_t(7)
    st = fw.mc_frame_encode(1, 1, payload, len(payload), out, len(out), ctypes.byref(n))
    assert st == Status.E_NO_SPACE and n.value == 0


@pytest.mark.parametrize("cap", [g.FRAME_MIN_BODY, 40, g.FRAME_MAX_BODY])
def test_c_decoder_agrees_with_host_deframer_on_random_streams(fw, cap):
    rng = np.random.default_rng(cap)
    dec, host = CDecoder(fw, cap), Deframer(max_body=cap)
    n_ok = 0
    for _ in range(150):
        parts = []
        for _ in range(int(rng.integers(1, 6))):
            kind = rng.integers(0, 3)
            if kind == 0:
                parts.append(rng.integers(0, 256, int(rng.integers(0, 80)), np.uint8).tobytes())
            else:
                n = int(rng.integers(0, 60))
                wire = bytearray(
                    encode_frame(
                        int(rng.integers(0, 256)), 7, bytes(rng.integers(0, 256, n, np.uint8))
                    )
                )
                if kind == 2:
                    wire[int(rng.integers(0, len(wire)))] ^= 1 << int(rng.integers(0, 8))
                parts.append(bytes(wire))
        data = b"".join(parts)
        c_events = dec.feed(data)
        h_events = host.feed(data)
        assert len(c_events) == len(h_events)
        for c, h in zip(c_events, h_events, strict=True):
            if isinstance(h, BadFrame):
                assert c == {"status": h.status.name}
            else:
                assert (c["id"], c["seq"], c["payload"]) == (h.id, h.seq, h.payload.hex())
                n_ok += 1
    assert n_ok > (20 if cap == g.FRAME_MAX_BODY else 0)
    assert dec.d.n_overflow > 0
    assert (dec.d.n_ok, dec.d.n_crc, dec.d.n_malformed, dec.d.n_overflow) == (
        host.n_ok,
        host.n_crc,
        host.n_malformed,
        host.n_overflow,
    )
