# SPDX-License-Identifier: Apache-2.0
"""The SIL device (build/sil/magcal-sil) end to end over TCP loopback: start-up lines, hello,
info with the documented sensor scales, retries and nacks, parameter set/get/commit, reset,
a restart of the process with the same flash file, raw and corrected streams fed over the
feed socket, a client reconnecting, and clean exits.

The protocol helper is deliberately minimal and local (raw frames with
magcal.device.framing); the host's client library is tested on its own.
"""

from __future__ import annotations

import socket
import struct
import subprocess
import time
from typing import Any

import pytest

from magcal.device import framing
from magcal.device.generated import MessageId, Status
from magcal_evaluation.sil import SIL_BINARY, STOP_TIMEOUT_S, SilProcess

RESPONSE_TIMEOUT_S = 5.0
STREAM_TIMEOUT_S = 10.0
CONNECT_TIMEOUT_S = 5.0
RECV_CHUNK_TIMEOUT_S = 0.1
PARAMS_FORMAT_VERSION = 1
PARAMS_STRUCT = "<Hbb9i3i"  # params.h: version, E_d, E_m, d_inv[9] Q1.30, offset[3] Q16.15


def params_blob(d_inv_exp: int, out_exp: int, d_inv: list[int], offset: list[int]) -> bytes:
    return struct.pack(PARAMS_STRUCT, PARAMS_FORMAT_VERSION, d_inv_exp, out_exp, *d_inv, *offset)


# D^-1 = I (mantissa 2^29 with E_d = 1), offset (100, -200, 300) counts, E_m = 16: the
# corrected output is exactly (y - o) * 2^(31 - 16) (correction.h).
IDENTITY_OFFSET = (100, -200, 300)
IDENTITY_BLOB = params_blob(
    1, 16, [1 << 29, 0, 0, 0, 1 << 29, 0, 0, 0, 1 << 29], [o << 15 for o in IDENTITY_OFFSET]
)


class RawDevice:
    """Requests and stream messages over one TCP connection, every wait bounded."""

    def __init__(self, port: int) -> None:
        self.sock = socket.create_connection(("127.0.0.1", port), timeout=CONNECT_TIMEOUT_S)
        self.sock.settimeout(RECV_CHUNK_TIMEOUT_S)
        self.deframer = framing.Deframer()
        self.frames: list[framing.Frame] = []
        self.seq = 0

    def close(self) -> None:
        self.sock.close()

    def _receive(self, deadline: float, what: str) -> None:
        if time.monotonic() > deadline:
            raise TimeoutError(f"SIL device: no {what} in time")
        try:
            data = self.sock.recv(65536)
        except TimeoutError:
            return
        if not data:
            raise ConnectionError(f"SIL device closed the connection while waiting for {what}")
        for event in self.deframer.feed(data):
            assert isinstance(event, framing.Frame), f"bad frame from the device: {event}"
            self.frames.append(event)

    def send(self, name: str, fields: dict[str, Any], seq: int | None = None) -> int:
        if seq is None:
            self.seq = (self.seq + 1) & 0xFFFF
            seq = self.seq
        self.sock.sendall(framing.encode_message(name, seq, fields))
        return seq

    def wait_answer(self, request: str, seq: int) -> tuple[int, dict[str, Any]]:
        """The response (or nack) to ``request`` with ``seq``: (id, fields)."""
        want = {int(framing.response_id(request)), int(MessageId.NACK)}
        deadline = time.monotonic() + RESPONSE_TIMEOUT_S
        while True:
            for i, f in enumerate(self.frames):
                if f.id in want and f.seq == seq:
                    del self.frames[i]
                    return f.id, framing.unpack_message(f.id, f.payload)[1]
            self._receive(deadline, f"answer to {request} seq {seq}")

    def request(self, name: str, fields: dict[str, Any] | None = None) -> dict[str, Any]:
        seq = self.send(name, fields or {})
        msg_id, out = self.wait_answer(name, seq)
        assert msg_id == framing.response_id(name), f"{name}: nack {out}"
        return out

    def stream(self, msg_id: int, n: int) -> list[tuple[int, dict[str, Any]]]:
        """The next n stream messages of id msg_id: (header seq, fields)."""
        got: list[tuple[int, dict[str, Any]]] = []
        deadline = time.monotonic() + STREAM_TIMEOUT_S
        while True:
            keep = []
            for f in self.frames:
                if f.id == msg_id and len(got) < n:
                    got.append((f.seq, framing.unpack_message(f.id, f.payload)[1]))
                else:
                    keep.append(f)
            self.frames = keep
            if len(got) == n:
                return got
            self._receive(deadline, f"{n} stream messages ({len(got)} so far)")


def connect(sil: SilProcess) -> RawDevice:
    dev = RawDevice(sil.proto_port)
    out = dev.request("hello", {"host_min_version": 1, "host_max_version": 1})
    assert out["status"] == Status.OK and out["version"] == 1
    return dev


def feed(sil: SilProcess, lines: list[str]) -> None:
    with socket.create_connection(("127.0.0.1", sil.feed_port), timeout=CONNECT_TIMEOUT_S) as s:
        s.sendall("".join(line + "\n" for line in lines).encode())


def sample_line(t_us: int, k: int) -> tuple[str, list[int]]:
    counts = [((k * 7919 + 1000 * i) % 65536) - 32768 for i in range(9)]
    return f"S {t_us} " + " ".join(str(c) for c in counts), counts


@pytest.fixture
def flash(tmp_path):
    return tmp_path / "flash.bin"


def test_startup_lines_and_clean_exit(start_sil, flash):
    sil = start_sil(flash)
    assert sil.lines[2] == "magcal-sil: ready"
    assert 0 < sil.proto_port < 65536 and 0 < sil.feed_port < 65536
    assert flash.stat().st_size == 2 * 2048
    assert sil.stop() == 0


def test_sigint_exits_zero(start_sil, flash):
    sil = start_sil(flash)
    sil.proc.send_signal(2)
    assert sil.proc.wait(timeout=STOP_TIMEOUT_S) == 0


def test_errors_exit_nonzero_with_one_line(sil_binary, tmp_path):
    cases = [
        ([], 2),
        (["--flash", str(tmp_path / "f.bin"), "--tcp", "x"], 2),
        (["--flash", str(tmp_path / "f.bin"), "--uid", "0x" + "1" * 25], 2),
        (["--flash", str(tmp_path / "missing-dir" / "f.bin"), "--tcp", "0"], 1),
    ]
    for args, status in cases:
        done = subprocess.run(
            [str(SIL_BINARY), *args], capture_output=True, text=True, timeout=STOP_TIMEOUT_S
        )
        assert done.returncode == status, (args, done.stderr)
        assert done.stderr.count("\n") == 1 and done.stderr.startswith("magcal-sil: ")
    wrong_size = tmp_path / "wrong.bin"
    wrong_size.write_bytes(b"\xff" * 100)
    done = subprocess.run(
        [str(SIL_BINARY), "--flash", str(wrong_size), "--tcp", "0"],
        capture_output=True,
        text=True,
        timeout=STOP_TIMEOUT_S,
    )
    assert done.returncode == 1 and "another size" in done.stderr


def test_hello_info_and_nacks(start_sil, flash):
    sil = start_sil(flash, "--uid", "0x0102030405060708090A0B0C")
    dev = connect(sil)
    out = dev.request("hello", {"host_min_version": 2, "host_max_version": 7})
    assert out["status"] == Status.E_VERSION and out["version"] == 0
    info = dev.request("info")
    assert info["status"] == Status.OK
    assert info["params_format_version"] == 1 and info["params_size"] == 52
    assert info["device_uid"] == (0x090A0B0C, 0x05060708, 0x01020304)
    assert info["sample_rate_mhz"] == 100000
    assert (info["mag_name"], info["acc_name"], info["gyr_name"]) == (
        "LIS3MDL",
        "LSM6DSO",
        "LSM6DSO",
    )
    # LIS3MDL 1/6842 G, LSM6DSO 0.122 mg and 17.5 mdps per count.
    assert info["scale_num"] == (1, 122, 175)
    assert info["scale_den"] == (6842, 1, 1)
    assert info["scale_exp10"] == (0, -6, -4)
    assert info["scale_unit"] == (2, 4, 6)
    assert info["fs_num"] == (4, 4, 500)

    # Unknown id and wrong length: nack with the frame's seq.
    dev.sock.sendall(framing.encode_frame(0x55, 900))
    assert dev.wait_answer("info", 900) == (
        MessageId.NACK,
        {"status": Status.E_UNKNOWN_MESSAGE, "request_id": 0x55},
    )
    dev.sock.sendall(framing.encode_frame(MessageId.INFO, 901, b"\x00"))
    assert dev.wait_answer("info", 901)[1]["status"] == Status.E_LENGTH
    # Retry: same seq and bytes, the same answer; another request on that seq: E_SEQUENCE.
    seq = dev.send("param_get", {"which": 0})
    first = dev.wait_answer("param_get", seq)
    assert first[1]["status"] == Status.E_NO_PARAMS
    dev.send("param_get", {"which": 0}, seq=seq)
    assert dev.wait_answer("param_get", seq) == first
    dev.send("param_get", {"which": 1}, seq=seq)
    assert dev.wait_answer("param_get", seq)[1] == {
        "status": Status.E_SEQUENCE,
        "request_id": MessageId.PARAM_GET,
    }
    dev.close()


def test_params_commit_reset_and_restart(start_sil, flash):
    crc = framing.crc32_iso_hdlc(IDENTITY_BLOB)
    sil = start_sil(flash)
    dev = connect(sil)
    assert dev.request("param_get", {"which": 0})["status"] == Status.E_NO_PARAMS
    assert dev.request("stream_start", {"kind": 1, "decimation": 1, "count": 0}) == {
        "status": Status.E_NO_PARAMS
    }
    bad = dev.request("param_set", {"format_version": 1, "blob": IDENTITY_BLOB[:-1]})
    assert bad["status"] == Status.E_LENGTH
    out = dev.request("param_set", {"format_version": 1, "blob": IDENTITY_BLOB})
    assert out == {"status": Status.OK, "crc32": crc}
    staged = dev.request("param_get", {"which": 1})
    assert staged["blob"] == IDENTITY_BLOB and staged["crc32"] == crc
    assert dev.request("param_commit", {"crc32": crc ^ 1})["status"] == Status.E_CRC
    assert dev.request("param_commit", {"crc32": crc})["status"] == Status.OK
    assert dev.request("param_get", {"which": 0})["status"] == Status.E_NO_PARAMS
    assert dev.request("reset", {"magic": 1})["status"] == Status.E_ARG
    assert dev.request("reset", {"magic": 0x54455352})["status"] == Status.OK

    # After the reset (same port, same connection): no staged set, the committed one active.
    dev.request("hello", {"host_min_version": 1, "host_max_version": 1})
    assert dev.request("param_get", {"which": 1})["status"] == Status.E_NO_PARAMS
    active = dev.request("param_get", {"which": 0})
    assert active["status"] == Status.OK and active["blob"] == IDENTITY_BLOB
    dev.close()
    assert sil.stop() == 0

    # A new process on the same flash file: the set is still active, and in use.
    sil = start_sil(flash)
    dev = connect(sil)
    active = dev.request("param_get", {"which": 0})
    assert active["blob"] == IDENTITY_BLOB and active["crc32"] == crc
    assert dev.request("stream_start", {"kind": 1, "decimation": 1, "count": 3}) == {
        "status": Status.OK
    }
    lines, counts = zip(*(sample_line(1000 * (k + 1), k) for k in range(3)), strict=True)
    feed(sil, list(lines))
    for k, (_, m) in enumerate(dev.stream(MessageId.CORRECTED, 3)):
        assert m["seq"] == k and m["mag"] == tuple(counts[k][:3]) and m["out_exp"] == 16
        assert m["m_b"] == tuple(
            (y - o) << 15 for y, o in zip(counts[k][:3], IDENTITY_OFFSET, strict=True)
        )
    stop = dev.request("stream_stop")
    assert (stop["sent"], stop["dropped"]) == (3, 0)
    dev.close()


def test_raw_stream_round_trip_and_reconnect(start_sil, flash):
    sil = start_sil(flash)
    dev = connect(sil)
    start_seq = dev.send("stream_start", {"kind": 0, "decimation": 1, "count": 0})
    assert dev.wait_answer("stream_start", start_seq)[1] == {"status": Status.OK}
    n = 200
    sent = [sample_line(10_000 * (k + 1), k) for k in range(n)]
    feed(sil, ["T 5000", "E 6000", *(line for line, _ in sent), "bogus line"])
    got = dev.stream(MessageId.SAMPLE, n)
    for k, (header_seq, m) in enumerate(got):
        counts = sent[k][1]
        assert header_seq == start_seq
        assert m["seq"] == k  # consecutive: nothing dropped, the failed read takes no number
        assert m["t_us"] == 10_000 * (k + 1)
        assert (m["mag"], m["acc"], m["gyr"]) == (
            tuple(counts[:3]),
            tuple(counts[3:6]),
            tuple(counts[6:]),
        )
    stop = dev.request("stream_stop")
    assert (stop["sent"], stop["dropped"]) == (n, 0)

    # Decimation and count over a second feed connection (the clock goes on).
    assert dev.request("stream_start", {"kind": 0, "decimation": 4, "count": 5}) == {
        "status": Status.OK
    }
    feed(sil, [sample_line(3_000_000 + 1000 * k, k)[0] for k in range(30)])
    got = dev.stream(MessageId.SAMPLE, 5)
    assert [m["seq"] for _, m in got] == [n + 4 * k for k in range(5)]
    assert dev.request("stream_stop")["sent"] == 5
    dev.close()

    # The client reconnects: served again, the state kept.
    dev = connect(sil)
    assert dev.request("info")["status"] == Status.OK
    dev.close()
    assert sil.stop() == 0


def test_full_link_drops_stream_messages_and_keeps_responses(start_sil, flash):
    sil = start_sil(flash)
    dev = RawDevice.__new__(RawDevice)
    sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)  # a slow, small link
    sock.settimeout(CONNECT_TIMEOUT_S)
    sock.connect(("127.0.0.1", sil.proto_port))
    sock.settimeout(RECV_CHUNK_TIMEOUT_S)
    dev.sock, dev.deframer, dev.frames, dev.seq = sock, framing.Deframer(), [], 0
    assert dev.request("stream_start", {"kind": 0, "decimation": 1, "count": 0}) == {
        "status": Status.OK
    }
    n = 50_000  # about 1.8 MB of sample messages, far more than the link buffers hold
    with socket.create_connection(("127.0.0.1", sil.feed_port), timeout=CONNECT_TIMEOUT_S) as f:
        f.sendall("".join(f"S {k + 1} {k % 1000} 0 0 0 0 0 0 0 0\n" for k in range(n)).encode())
        # Feed lines are handled in order: once a marker sample (t_us > n) arrives, every
        # line fed before it was handled. A marker may itself be dropped: feed another.
        markers = 0
        deadline = time.monotonic() + STREAM_TIMEOUT_S

        def marker_seen() -> bool:
            return any(
                fr.id == MessageId.SAMPLE and struct.unpack_from("<Q", fr.payload, 4)[0] > n
                for fr in dev.frames
            )

        while not marker_seen():
            f.sendall(f"S {n + 1 + markers} 0 0 0 0 0 0 0 0 0\n".encode())
            markers += 1
            pause = time.monotonic() + 0.2
            while time.monotonic() < pause:
                dev._receive(deadline, "a marker sample")
    stop = dev.request("stream_stop")
    samples = [
        framing.unpack_message(fr.id, fr.payload)[1]
        for fr in dev.frames
        if fr.id == MessageId.SAMPLE
    ]
    assert stop["status"] == Status.OK
    assert stop["dropped"] > 0
    assert stop["sent"] == len(samples)
    assert stop["sent"] + stop["dropped"] == n + markers
    seqs = [m["seq"] for m in samples]
    assert seqs == sorted(set(seqs))  # increasing; the gaps are the drops
    dev.close()
