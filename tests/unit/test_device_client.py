# SPDX-License-Identifier: Apache-2.0
"""magcal.device.client, magcal.device.flash and magcal.link against the pure-Python fake
device (tests/fake_device.py): negotiation, exact unit conversion, seq and same-bytes retries,
refusals, stream routing, line noise, a lossy link, the flash flow interrupted at every byte,
restore, and real sockets and pseudo-terminals through open_link."""

from __future__ import annotations

import json
import math
import os
import threading
from fractions import Fraction

import numpy as np
import pytest

from magcal.device import fixed_point
from magcal.device.client import (
    ClientConfig,
    Corrected,
    DeviceClient,
    DeviceError,
    DeviceTimeoutError,
    ParamWhich,
    Sample,
    Scale,
    StreamKind,
    VersionMismatchError,
)
from magcal.device.flash import (
    FlashError,
    FlashInterruptedError,
    flash_parameters,
    read_backup,
    restore,
)
from magcal.device.framing import crc32_iso_hdlc, decode_frame, encode_frame, encode_message
from magcal.device.generated import MessageId, Status, Unit
from magcal.link import LinkClosedError, LinkError, LinkTimeoutError, open_link
from tests.fake_device import FakeDevice, LossyLink, MemoryLink, random_sample, serve_tcp

FAST = ClientConfig(request_timeout_s=0.02, request_retries=3, reset_recovery_timeout_s=0.5)


def blob_for(gain: float, offset=(10.0, -20.0, 5.0)) -> bytes:
    p = fixed_point.from_calibration(np.eye(3) * gain, np.array(offset))
    return fixed_point.encode(p)


OLD = blob_for(1.0 / 500)
NEW = blob_for(1.0 / 450, (3.0, 4.0, -7.5))


def client_for(dev: FakeDevice, config: ClientConfig = FAST, **kw) -> DeviceClient:
    return DeviceClient(MemoryLink(dev, **kw), config, first_seq=100)


class RecordingLink:
    """Records every write; drops the first n_drop_responses reads' data."""

    def __init__(self, inner, n_drop_responses: int = 0) -> None:
        self.inner, self.url = inner, inner.url
        self.writes: list[bytes] = []
        self.n_drop = n_drop_responses

    def write(self, data, timeout_s=None):
        self.writes.append(bytes(data))
        self.inner.write(data)

    def read(self, timeout_s, max_bytes=4096):
        data = self.inner.read(timeout_s, max_bytes)
        if self.n_drop:
            self.n_drop -= 1
            raise LinkTimeoutError("dropped", self.url)
        return data

    def close(self):
        self.inner.close()


class DeadLink:
    url = "dead://"

    def __init__(self):
        self.writes = []

    def write(self, data, timeout_s=None):
        self.writes.append(bytes(data))

    def read(self, timeout_s, max_bytes=4096):
        raise LinkTimeoutError("nothing", self.url)

    def close(self):
        pass


# ----------------------------------------------------------------------------- hello, info
def test_hello_negotiates_highest_common_version():
    dev = FakeDevice(min_version=1, max_version=3)
    c = client_for(dev)
    r = c.hello(1, 2)
    assert (r.version, r.device_min_version, r.device_max_version) == (2, 1, 3)
    assert c.version == 2


def test_hello_without_common_version_names_both_ranges():
    c = client_for(FakeDevice(min_version=2, max_version=4))
    with pytest.raises(VersionMismatchError, match=r"host speaks \[1, 1\], device \[2, 4\]"):
        c.hello(1, 1)


def test_info_parsed_and_counts_convert_exactly():
    c = client_for(FakeDevice())
    c.hello()
    info = c.info()
    assert info.uid_hex == "123456789abcdef00badf00d"
    assert info.fw_version_str == "1.2.3" and info.params_size == fixed_point.ENCODED_SIZE
    assert info.sample_rate_hz == 100.0
    mag, acc, gyr = (info.sensor(k).count_scale for k in ("mag", "acc", "gyr"))
    assert info.sensor("mag").name == "LIS3MDL" and mag.unit == Unit.GAUSS
    # 6842 counts are exactly 1 G = 1e-4 T; one accelerometer count 122 ug0.
    assert mag.si_rational * 6842 == Fraction(1, 10_000)
    assert mag.counts_to_si([6842])[0] == 1e-4
    assert acc.si_rational == Fraction(122, 10**6) * Fraction(980665, 100000)
    c_acc = np.array([-32768, -1, 0, 1, 12345, 32767])
    want = [float(int(k) * acc.si_rational) for k in c_acc]
    assert acc.counts_to_si(c_acc).tolist() == want  # each rounded once from the exact value
    # deg/s: rational first, pi once at the end.
    assert gyr.has_pi and gyr.si_rational == Fraction(7, 18000)
    assert gyr.counts_to_si([100])[0] == float(100 * Fraction(7, 18000)) * math.pi
    assert gyr.counts_to_si([100])[0] == pytest.approx(math.radians(7.0), rel=1e-15)
    with pytest.raises(Exception, match="int16 values"):
        gyr.counts_to_si([40000])


def test_info_with_invalid_unit_is_refused():
    sensors = list(FakeDevice().sensors)
    sensors[1] = (1, "X", (4, 1, 0, Unit.GAUSS), (1, 1, 0, Unit.INVALID))
    c = client_for(FakeDevice(sensors=tuple(sensors)))
    with pytest.raises(DeviceError, match="acc scale has unit code 0"):
        c.info()


def test_scale_without_si_value_raises():
    with pytest.raises(Exception, match="has no SI value"):
        _ = Scale(1, 0, 0, Unit.TESLA).si_rational


# ----------------------------------------------------------------------------- seq, retries
def test_seq_is_fresh_per_request_and_wraps():
    dev = FakeDevice()
    link = RecordingLink(MemoryLink(dev))
    c = DeviceClient(link, FAST, first_seq=0xFFFE)
    for _ in range(3):
        c.info()
    seqs = [decode_frame(w[1:-1]).seq for w in link.writes]  # after the leading 0x00
    assert seqs == [0xFFFF, 0, 1]
    assert dev.acted["info"] == 3 and c.stats.retries == 0


def test_lost_response_is_retried_with_the_same_bytes_and_not_acted_twice():
    dev = FakeDevice()
    link = RecordingLink(MemoryLink(dev), n_drop_responses=2)
    c = DeviceClient(link, FAST, first_seq=7)
    crc = c.param_set(fixed_point.FORMAT_VERSION, NEW)
    assert crc == crc32_iso_hdlc(NEW)
    assert len(link.writes) == 3 and len(set(link.writes)) == 1
    assert dev.acted["param_set"] == 1  # the retries were answered from the cache
    assert c.stats.retries == 2


def test_no_response_raises_after_bounded_retries(caplog):
    link = DeadLink()
    c = DeviceClient(link, FAST, first_seq=1)
    with pytest.raises(DeviceTimeoutError, match=r"info on dead://: no response after 4 attempts"):
        c.info()
    assert len(link.writes) == 4 and len(set(link.writes)) == 1
    assert sum("retry" in r.message for r in caplog.records) == 3


def test_stream_read_times_out():
    c = client_for(FakeDevice())
    with pytest.raises(DeviceTimeoutError, match="stream on memory://fake: no sample within"):
        c.read_stream(timeout_s=0.02)


# ----------------------------------------------------------------------------- refusals
def test_reused_seq_with_other_body_gets_nack_e_sequence():
    dev = FakeDevice()
    client_for(dev).info()  # seq 101 cached
    other = client_for(dev)  # starts at the same seq
    with pytest.raises(DeviceError, match="nack E_SEQUENCE") as ei:
        other.param_get(ParamWhich.ACTIVE)
    assert ei.value.status == Status.E_SEQUENCE


def test_unknown_message_gets_nack():
    from magcal.device.framing import unpack_message

    dev = FakeDevice()
    dev.receive(encode_frame(0x55, 3, b""))
    c = client_for(dev)
    # The nack is there (a client ignores it: not its request), naming the unknown id.
    frames = [decode_frame(x) for x in c.link.read(0.01).split(b"\x00") if x]
    assert [(f.id, f.seq) for f in frames] == [(MessageId.NACK, 3)]
    _, fields = unpack_message(MessageId.NACK, frames[0].payload)
    assert fields == {"status": Status.E_UNKNOWN_MESSAGE, "request_id": 0x55}
    assert dev.acted == {}


@pytest.mark.parametrize(
    "call, match",
    [
        (lambda c: c.param_get(ParamWhich.ACTIVE), r"param_get\(active\).*E_NO_PARAMS"),
        (lambda c: c.param_get(ParamWhich.STAGED), r"param_get\(staged\).*E_NO_PARAMS"),
        (lambda c: c.stream_start(StreamKind.CORRECTED), "stream_start.*E_NO_PARAMS"),
        (lambda c: c.stream_start(StreamKind.RAW, decimation=0), "stream_start.*E_RANGE"),
        (lambda c: c.param_commit(0x1234), "param_commit.*E_STATE"),
        (lambda c: c.param_set(2, NEW), "param_set.*E_VERSION"),
        (lambda c: c.param_set(1, NEW[:-1]), "param_set.*E_LENGTH"),
        (
            lambda c: c.param_set(1, NEW[:4] + bytes(36) + NEW[40:]),
            "param_set.*E_SINGULAR",
        ),
    ],
)
def test_refusals_raise_device_error_with_status_name(call, match):
    c = client_for(FakeDevice())
    c.hello()
    with pytest.raises(DeviceError, match=match):
        call(c)


def test_commit_with_wrong_crc_is_refused():
    c = client_for(FakeDevice())
    c.param_set(1, NEW)
    with pytest.raises(DeviceError, match="param_commit.*E_CRC"):
        c.param_commit(crc32_iso_hdlc(NEW) ^ 1)


# ----------------------------------------------------------------------------- streams
def test_stream_routed_while_responses_are_awaited():
    dev = FakeDevice(active_blob=OLD)
    c = client_for(dev, auto_samples=3)
    c.hello()
    c.stream_start(StreamKind.RAW, decimation=1, count=0)
    got = [c.read_stream() for _ in range(5)]
    assert c.param_get(ParamWhich.ACTIVE).blob == OLD  # samples keep arriving meanwhile
    got += [c.read_stream() for _ in range(20)]
    assert all(isinstance(s, Sample) for s in got)
    seqs = [s.seq for s in got]
    assert seqs == list(range(seqs[0], seqs[0] + 25))  # nothing lost while awaiting
    assert all(b.t_us > a.t_us for a, b in zip(got, got[1:], strict=False))
    stats = c.stream_stop()
    assert stats.sent >= 25 and stats.dropped == 0


def test_stream_with_decimation_and_count_then_corrected_matches_emulation():
    dev = FakeDevice(active_blob=OLD)
    c = client_for(dev, auto_samples=1)
    c.stream_start(StreamKind.RAW, decimation=3, count=4)
    got = list(c.stream(4))
    assert [b.seq - a.seq for a, b in zip(got, got[1:], strict=False)] == [3, 3, 3]
    with pytest.raises(DeviceTimeoutError, match="no sample"):
        c.read_stream(timeout_s=0.02)  # count reached: the stream ended
    c.stream_start(StreamKind.CORRECTED, count=10)
    cor = list(c.stream(10))
    assert all(isinstance(s, Corrected) for s in cor)
    raw = np.array([s.mag for s in cor])
    want = fixed_point.emulate(fixed_point.decode(OLD), raw)
    assert np.array_equal(np.array([s.m_b for s in cor]), want)


def test_old_stream_messages_are_dropped_after_restart():
    dev = FakeDevice()
    c = client_for(dev)
    c.stream_start(StreamKind.RAW)
    first = dev.stream.seq
    c.stream_start(StreamKind.RAW)  # replaces the stream: new seq
    assert dev.stream.seq == (first + 1) & 0xFFFF
    stale = {"seq": 0, "t_us": 1, "mag": (1, 2, 3), "acc": (0, 0, 0), "gyr": (0, 0, 0)}
    dev.outbox += encode_message("sample", first, stale)  # the old stream, still in flight
    dev.acquire(*random_sample(np.random.default_rng(2)), 2)
    s = c.read_stream()
    assert s.t_us == 2 and c.stats.stale_frames == 1


# ----------------------------------------------------------------------------- line noise
def test_garbage_and_bad_crc_are_counted_not_raised():
    dev = FakeDevice()
    c = client_for(dev)
    bad = bytearray(encode_frame(MessageId.INFO_RESP, 9, bytes(range(1, 130))))
    bad[5] ^= 0x80  # a payload byte: the CRC no longer matches
    dev.outbox += b"\x13\x37garbage\x00" + bytes(bad) + b"\xff" * 300 + b"\x00"
    assert c.info().uid_hex == "123456789abcdef00badf00d"
    assert (c.deframer.n_crc, c.deframer.n_malformed, c.deframer.n_overflow) == (1, 1, 1)


def test_lossy_link_requests_recover_by_retries_and_idempotency(tmp_path):
    dev = FakeDevice(active_blob=OLD)
    lossy = LossyLink(
        MemoryLink(dev, auto_samples=1),
        seed=4,
        bit_error=0.001,
        drop=0.001,
        duplicate=0.001,
        delay=0.001,
        delay_s=0.005,
    )
    cfg = ClientConfig(request_timeout_s=0.03, request_retries=8, reset_recovery_timeout_s=2.0)
    c = DeviceClient(lossy, cfg, first_seq=1)
    c.hello()
    for _ in range(30):
        assert c.info().params_size == fixed_point.ENCODED_SIZE
        assert c.param_get(ParamWhich.ACTIVE).blob == OLD
    r = flash_parameters(c, NEW, 1, tmp_path / "b.json")
    assert r.active == "new" and dev.flash == NEW and dev.active == NEW
    # Each write acted on once, whatever was lost or repeated on the way.
    assert dev.acted["param_set"] == 1 and dev.acted["param_commit"] == 1
    assert dev.acted["reset"] == 1
    c = r.client
    c.stream_start(StreamKind.RAW)
    got = [c.read_stream() for _ in range(200)]
    assert all(b.seq > a.seq for a, b in zip(got, got[1:], strict=False))  # order kept
    assert sum(lossy.faults.values()) > 50 and c.stats.retries > 0
    assert c.deframer.n_crc + c.deframer.n_malformed > 0


# ----------------------------------------------------------------------------- flash
def test_flash_happy_path_saves_backup_first(tmp_path):
    dev = FakeDevice(active_blob=OLD)
    c = client_for(dev)
    r = flash_parameters(c, NEW, 1, tmp_path / "b.json")
    assert (r.active, r.crc32, r.recovered_from) == ("new", crc32_iso_hdlc(NEW), "")
    assert dev.flash == NEW and dev.active == NEW and dev.resets == 1
    doc = json.loads((tmp_path / "b.json").read_text())
    assert bytes.fromhex(doc["blob"]) == OLD and doc["crc32"] == crc32_iso_hdlc(OLD)
    assert doc["device_uid"] == "123456789abcdef00badf00d" and doc["fw_version"] == "1.2.3"
    assert read_backup(tmp_path / "b.json")["blob"] == OLD


def test_flash_refuses_to_overwrite_backup_and_writes_nothing(tmp_path):
    (tmp_path / "b.json").write_text("{}")
    dev = FakeDevice(active_blob=OLD)
    with pytest.raises(FlashError, match="b.json exists; nothing was written"):
        flash_parameters(client_for(dev), NEW, 1, tmp_path / "b.json")
    assert dev.acted["param_set"] == 0


def test_flash_refuses_other_format(tmp_path):
    dev = FakeDevice(active_blob=OLD)
    with pytest.raises(FlashError, match="takes parameter format 1 of 52 bytes; this set is"):
        flash_parameters(client_for(dev), NEW + b"\x00", 1, tmp_path / "b.json")
    assert not (tmp_path / "b.json").exists()


def test_flash_failed_commit_keeps_old(tmp_path):
    dev = FakeDevice(active_blob=OLD, fail_commit=True)
    with pytest.raises(FlashError, match="param_commit.*E_FLASH.*keeps its old set") as info:
        flash_parameters(client_for(dev), NEW, 1, tmp_path / "b.json")
    assert dev.flash == OLD and info.value.active == "old" and info.value.commit_sent


def test_flash_detects_staged_mismatch(tmp_path):
    class Liar(FakeDevice):
        def _on_param_get(self, f):
            r = super()._on_param_get(f)
            if f["which"] == 1:
                r["blob"] = OLD
                r["crc32"] = crc32_iso_hdlc(OLD)
            return r

    dev = Liar(active_blob=OLD)
    with pytest.raises(FlashError, match="staged set read back differs"):
        flash_parameters(client_for(dev), NEW, 1, tmp_path / "b.json")
    assert dev.acted["param_commit"] == 0


def test_flash_detects_commit_without_effect(tmp_path):
    class Forgetful(FakeDevice):
        def _on_param_commit(self, f):
            return {"status": Status.OK}

    dev = Forgetful(active_blob=OLD)
    with pytest.raises(FlashError, match="uses its old set, not the new one"):
        flash_parameters(client_for(dev), NEW, 1, tmp_path / "b.json")


def _clean_flash_bytes(tmp_path) -> int:
    dev = FakeDevice(active_blob=OLD)
    link = LossyLink(MemoryLink(dev))
    flash_parameters(DeviceClient(link, FAST, first_seq=5), NEW, 1, tmp_path / "clean.json")
    return link.bytes_passed


@pytest.mark.parametrize("with_reconnect", [True, False])
def test_disconnect_at_every_byte_of_flash_leaves_old_or_new(tmp_path, with_reconnect):
    total = _clean_flash_bytes(tmp_path)
    assert total > 300
    outcomes = {"new": 0, "old": 0, "unknown": 0}
    for cut in range(total + 1):
        dev = FakeDevice(active_blob=OLD)
        link = LossyLink(MemoryLink(dev), disconnect_after=cut)

        def reconnect(dev=dev):
            dev.outbox.clear()  # what was in flight on the broken link is gone
            return DeviceClient(MemoryLink(dev), FAST, first_seq=900)

        path = tmp_path / f"b{cut}.json"
        kw = {"reconnect": reconnect} if with_reconnect else {}
        try:
            r = flash_parameters(DeviceClient(link, FAST, first_seq=5), NEW, 1, path, **kw)
            said = r.active
        except FlashInterruptedError as exc:
            said = exc.active
            assert exc.step and "link failure" in str(exc)
        # The device always holds a complete set, the old or the new one...
        assert dev.flash in (OLD, NEW)
        dev._reset()
        # ...and the client says which (or that it could not ask).
        if said != "unknown":
            assert dev.active == {"old": OLD, "new": NEW}[said], cut
        outcomes[said] += 1
    if with_reconnect:
        assert outcomes["unknown"] == 0 and outcomes["old"] > 0 and outcomes["new"] > 0
    else:
        assert outcomes["old"] > 0 and outcomes["unknown"] > 0


def test_flash_interrupted_without_reconnect_messages(tmp_path):
    dev = FakeDevice(active_blob=OLD)
    link = LossyLink(MemoryLink(dev), disconnect_after=40)
    with pytest.raises(FlashInterruptedError, match="commit was never sent.*old complete set"):
        flash_parameters(DeviceClient(link, FAST, first_seq=5), NEW, 1, tmp_path / "b.json")


# ----------------------------------------------------------------------------- restore
def test_restore_round_trip(tmp_path):
    dev = FakeDevice(active_blob=OLD)
    flash_parameters(client_for(dev), NEW, 1, tmp_path / "b.json")
    r = restore(client_for(dev), tmp_path / "b.json", new_backup_path=tmp_path / "c.json")
    assert r.active == "new" and dev.active == OLD
    assert read_backup(tmp_path / "c.json")["blob"] == NEW


def test_restore_refusals(tmp_path):
    dev = FakeDevice(active_blob=OLD)
    flash_parameters(client_for(dev), NEW, 1, tmp_path / "b.json")
    other = FakeDevice(active_blob=NEW, uid=(1, 2, 3))
    with pytest.raises(FlashError, match="is of device 123456789abcdef00badf00d, this is device"):
        restore(client_for(other), tmp_path / "b.json")
    flash_parameters(client_for(FakeDevice()), NEW, 1, tmp_path / "none.json")
    with pytest.raises(FlashError, match="had no parameter set; there is nothing to write back"):
        restore(client_for(dev), tmp_path / "none.json")
    doc = json.loads((tmp_path / "b.json").read_text())
    doc["blob"] = "ff" + doc["blob"][2:]
    (tmp_path / "d.json").write_text(json.dumps(doc))
    with pytest.raises(FlashError, match="does not match its CRC-32; the file is damaged"):
        restore(client_for(dev), tmp_path / "d.json")
    (tmp_path / "e.json").write_text("[]")
    with pytest.raises(FlashError, match="is not a magcal-param-backup/1 backup"):
        restore(client_for(dev), tmp_path / "e.json")


# ----------------------------------------------------------------------------- real links
def test_socket_url_to_fake_device(tmp_path):
    dev = FakeDevice(active_blob=OLD)
    port, stop, th = serve_tcp(dev)
    try:
        with open_link(f"socket://127.0.0.1:{port}", 2.0) as link:
            c = DeviceClient(link, ClientConfig(request_timeout_s=0.3))
            c.hello()
            assert c.info().uid_hex == "123456789abcdef00badf00d"
            r = flash_parameters(c, NEW, 1, tmp_path / "b.json")
            assert r.active == "new" and dev.active == NEW
    finally:
        stop.set()
        th.join(2)


def test_pseudo_terminal_path_to_fake_device():
    dev = FakeDevice()
    master, slave = os.openpty()
    name = os.ttyname(slave)
    stop = threading.Event()

    def run():
        import select

        while not stop.is_set():
            r, _, _ = select.select([master], [], [], 0.02)
            if r:
                dev.receive(os.read(master, 4096))
                out = dev.take_output()
                if out:
                    os.write(master, out)

    th = threading.Thread(target=run, daemon=True)
    th.start()
    try:
        with open_link(name, 1.0) as link:
            import tty

            tty.setraw(link._port.fileno())  # the SIL puts its pty in raw mode
            c = DeviceClient(link, ClientConfig(request_timeout_s=0.3))
            assert c.hello().version == 1
            assert c.info().sensor("gyr").name == "LSM6DSO"
    finally:
        stop.set()
        th.join(2)
        os.close(master)
        os.close(slave)


def test_open_link_errors_name_the_url():
    with pytest.raises(LinkError, match=r"open link socket://127.0.0.1:1: cannot open .*listening"):
        open_link("socket://127.0.0.1:1", 0.0)
    with pytest.raises(LinkError, match=r"open link /nonexistent/tty0: .*plugged in"):
        open_link("/nonexistent/tty0", 0.0)
    with pytest.raises(LinkError, match="MAVLink links .* are not supported yet"):
        open_link("mavlink://udp:1234", 0.0)
    with pytest.raises(LinkError, match="empty port URL"):
        open_link("", 0.0)


def test_link_read_timeout_and_closed():
    with open_link("loop://", 1.0) as link:
        link.write(b"ab")
        assert link.read(0.1) == b"ab"
        with pytest.raises(LinkTimeoutError, match=r"read from loop://: no byte within"):
            link.read(0.03)
    with pytest.raises(LinkClosedError, match="the link is closed; open it again"):
        link.read(0.01)
    with pytest.raises(LinkClosedError, match="the link is closed"):
        link.write(b"x")


def test_every_device_status_has_advice():
    # A status added to protocol/schema.json must come with advice for the user.
    from magcal.device import client as client_module
    from magcal.device.generated import Status

    missing = [s.name for s in Status if s != Status.OK and s not in client_module._ADVICE]
    assert missing == []
