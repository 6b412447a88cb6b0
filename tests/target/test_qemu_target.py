# SPDX-License-Identifier: Apache-2.0
"""The cross-built firmware (library + firmware/port/mps2-an386) on QEMU's mps2-an386.

Boot: the banner names the firmware, the library revision and the board; the self-test
checks the library's CRC check values and the SysTick time source on the Cortex-M4; the
protocol line says the RAM flash was formatted, and a 0x00 delimiter ends the text.

Session, through magcal.device.client over the UART's pty: hello and info (the sensors'
exact scales), a raw stream equal count for count to what the synthetic sensors are
documented to produce (synthetic_sensors.h), a parameter set built with
fixed_point.from_calibration written, read back bit-exact from the staged set, committed,
then reset: a real reboot of the emulated MCU (the boot lines appear again, flash=kept) after
which the set is active and a corrected stream equals fixed_point.emulate on the raw counts
it carries. Throughput and boot time are measured and printed (pytest -s shows them).

Every wait has a time-out (the client's, QemuTarget's); QEMU is shut down by the fixtures.
"""

from __future__ import annotations

import math
import re
import statistics
import time
import zlib

import numpy as np
import pytest

from magcal.device import fixed_point
from magcal.device.client import (
    ClientConfig,
    Corrected,
    DeviceClient,
    DeviceError,
    ParamWhich,
    Sample,
    StreamKind,
)
from magcal.device.generated import Status, Unit
from magcal.link import open_link

BOOT_LINE_TIMEOUT_S = 10.0
LINK_OPEN_TIMEOUT_S = 5.0
STREAM_TIMEOUT_S = 3.0  # for each stream message (they come every 10 ms)
# Bounds for boot_us, microseconds: the self-test waits 20 ms on SysTick, and
# on QEMU the whole boot takes milliseconds of guest time (seconds would mean a runaway clock).
SELFTEST_WAIT_US = 20_000
BOOT_US_MAX = 5_000_000
# QEMU's pty backend notices that the host opened the pty only on its next one-second poll;
# until then the firmware's output reaches the host but the host's bytes wait, so the first
# request after QEMU starts may take about a second: the client retries it.
# A reset reboots the MCU; its response comes before the reboot, the next hello after it.
CLIENT_CONFIG = ClientConfig(request_timeout_s=0.5, request_retries=6)

N_RAW = 150
N_CORRECTED = 150
THROUGHPUT_S = 5.0

BANNER_RE = re.compile(
    r"magcal-target fw=(?P<fw>\d+\.\d+\.\d+) lib=(?P<lib>\S+) "
    r"board=mps2-an386 cpu=cortex-m4"
)
SELFTEST_RE = re.compile(
    r"selftest crc16=(?P<crc16>[0-9A-F]{4}) crc32=(?P<crc32>[0-9A-F]{8}) "
    r"time=(?P<time>\w+) boot_us=(?P<boot_us>\d+) result=(?P<result>PASS|FAIL)"
)

# ---------------------------------------------------------------- the synthetic sensors
# synthetic_sensors.h, exactly: a board lying level, yawing one turn per 256 samples.
PERIOD_US = 10_000
SIN_Q15 = [round(32767 * math.sin(2 * math.pi * i / 256)) for i in range(65)]
MAG_H_X, MAG_H_Y, MAG_V = 1368, 1231, 3079
MAG_O = (412, -237, 158)
ACC = (0, 0, 8197)
GYR = (0, 0, 8036)
TARGET_UID = (0x36383341, 0x0000004E, 0x4D505332)


def _sin256(i: int) -> int:
    i %= 256
    if i < 64:
        return SIN_Q15[i]
    if i < 128:
        return SIN_Q15[128 - i]
    return -_sin256(i - 128)


def _q15(a: int, x: int) -> int:
    return (a * x + 16384) >> 15


def synthetic_mag(k: int) -> tuple[int, int, int]:
    """The magnetometer counts of sample k (k = the acquisition seq on this port)."""
    s, c = _sin256(k), _sin256(k + 64)
    return (MAG_O[0] + _q15(MAG_H_X, c), MAG_O[1] - _q15(MAG_H_Y, s), MAG_O[2] - MAG_V)


def true_calibration() -> tuple[np.ndarray, np.ndarray]:
    """D_inv, o (counts) that make the synthetic field unit norm: a rotation (10 degrees
    about (1, 1, 1)) times the inverse soft iron and 1/|B|, so D_inv is full."""
    f = math.hypot(MAG_H_X, MAG_V)
    axis = np.ones(3) / math.sqrt(3.0)
    a = math.radians(10.0)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    r = np.eye(3) + math.sin(a) * k + (1 - math.cos(a)) * (k @ k)
    d_inv = r @ np.diag([1 / f, MAG_H_X / (MAG_H_Y * f), 1 / f])
    return d_inv, np.array(MAG_O, dtype=np.float64)


# ---------------------------------------------------------------- helpers
class TapLink:
    """A Link that keeps a copy of every byte read, to see the boot text after a reboot."""

    def __init__(self, link) -> None:
        self.link = link
        self.url = link.url
        self.received = bytearray()

    def read(self, timeout_s: float, max_bytes: int = 4096) -> bytes:
        data = self.link.read(timeout_s, max_bytes)
        self.received += data
        return data

    def write(self, data: bytes, timeout_s: float | None = None) -> None:
        self.link.write(data, timeout_s)

    def close(self) -> None:
        self.link.close()


def _stream(client: DeviceClient, kind: StreamKind, n: int) -> tuple[list, tuple[int, int]]:
    client.stream_start(kind)
    try:
        msgs = list(client.stream(n, STREAM_TIMEOUT_S))
    finally:
        stats = client.stream_stop()
    return msgs, (stats.sent, stats.dropped)


def _assert_consecutive(msgs: list) -> None:
    seqs = [m.seq for m in msgs]
    assert seqs == list(range(seqs[0], seqs[0] + len(seqs))), "seq gap: a sample was dropped"
    t = np.array([m.t_us for m in msgs], dtype=np.int64)
    assert np.all(np.diff(t) == PERIOD_US), "samples not 10 ms apart"
    assert all(m.t_us % PERIOD_US == 0 for m in msgs)


# ---------------------------------------------------------------- boot
@pytest.fixture(scope="module")
def boot(target):
    """The three lines the firmware prints at boot (banner, self-test, protocol), then the
    0x00 that starts the protocol."""
    lines = [target.read_line(BOOT_LINE_TIMEOUT_S) for _ in range(3)]
    assert target.read_exact(1, BOOT_LINE_TIMEOUT_S) == b"\x00"
    print(f"QEMU boot (start until the UART was open): {target.boot_s:.3f} s")
    return lines


def test_banner_names_firmware_library_and_board(boot):
    match = BANNER_RE.fullmatch(boot[0])
    assert match, f"unexpected banner {boot[0]!r}"
    assert match["lib"] != "unknown"


def test_selftest_crc_check_values_and_time_source(boot):
    match = SELFTEST_RE.fullmatch(boot[1])
    assert match, f"unexpected self-test line {boot[1]!r}"
    # The catalogue check values for "123456789" (crc.h), computed on the Cortex-M4.
    assert match["crc16"] == "29B1"
    assert match["crc32"] == "CBF43926"
    assert match["time"] == "ok"
    assert SELFTEST_WAIT_US <= int(match["boot_us"]) <= BOOT_US_MAX
    assert match["result"] == "PASS"


def test_protocol_starts_on_a_freshly_formatted_flash(boot):
    # A new QEMU has zeroed RAM: the RAM flash's header is invalid and it is formatted.
    assert boot[2] == "protocol flash=erased boots=1"


# ---------------------------------------------------------------- protocol session
@pytest.fixture(scope="module")
def client(target, boot):
    """A DeviceClient on the target's pty (the boot text already read)."""
    tap = TapLink(open_link(target.pty, LINK_OPEN_TIMEOUT_S))
    c = DeviceClient(tap, CLIENT_CONFIG)
    try:
        yield c
    finally:
        c.close()


def test_hello_and_info(client, boot):
    hello = client.hello()
    assert hello.version == 1
    info = client.info()
    assert info.fw_version_str == BANNER_RE.fullmatch(boot[0])["fw"]
    assert info.fw_build != 0  # the commit id, from mk/target.mk
    assert info.device_uid == TARGET_UID
    assert info.sample_rate_mhz == 100_000
    assert info.params_format_version == fixed_point.FORMAT_VERSION
    assert info.params_size == fixed_point.ENCODED_SIZE
    mag, acc, gyr = info.sensors
    assert (mag.name, mag.sensor_id, acc.name, acc.sensor_id, gyr.name, gyr.sensor_id) == (
        "LIS3MDL",
        0x3D,
        "LSM6DSO",
        0x6C,
        "LSM6DSO",
        0x6C,
    )
    # The datasheet scales, exactly (sil_main.c's table).
    scales = [
        (s.count_scale.num, s.count_scale.den, s.count_scale.exp10, s.count_scale.unit)
        for s in info.sensors
    ]
    assert scales == [
        (1, 6842, 0, Unit.GAUSS),
        (122, 1, -6, Unit.STANDARD_GRAVITY),
        (175, 1, -4, Unit.DEG_PER_S),
    ]
    ranges = [
        (s.full_scale.num, s.full_scale.den, s.full_scale.exp10, s.full_scale.unit)
        for s in info.sensors
    ]
    assert ranges == [
        (4, 1, 0, Unit.GAUSS),
        (4, 1, 0, Unit.STANDARD_GRAVITY),
        (500, 1, 0, Unit.DEG_PER_S),
    ]


def test_raw_stream_is_the_documented_synthetic_motion(client):
    client.hello()
    msgs, (sent, dropped) = _stream(client, StreamKind.RAW, N_RAW)
    assert all(isinstance(m, Sample) for m in msgs)
    _assert_consecutive(msgs)
    for m in msgs:
        assert m.mag == synthetic_mag(m.seq), f"sample {m.seq}"
        assert m.acc == ACC and m.gyr == GYR
    assert sent >= N_RAW and dropped == 0
    # In SI units: 1 g up, 140.625 deg/s of yaw, a 0.49 G field (hard and soft iron aside).
    info = client.info()
    assert info.sensor("acc").count_scale.counts_to_si(ACC[2]) == pytest.approx(9.80665, 1e-3)
    assert info.sensor("gyr").count_scale.counts_to_si(GYR[2]) == pytest.approx(
        math.radians(140.625), 1e-3
    )


def test_parameter_write_readback_commit_reboot_and_corrected_stream(client):
    client.hello()
    before, _ = _stream(client, StreamKind.RAW, 5)

    # A fresh flash: no active set, so no corrected stream either.
    with pytest.raises(DeviceError) as exc:
        client.param_get(ParamWhich.ACTIVE)
    assert exc.value.status == Status.E_NO_PARAMS
    with pytest.raises(DeviceError) as exc:
        client.stream_start(StreamKind.CORRECTED)
    assert exc.value.status == Status.E_NO_PARAMS

    d_inv, o = true_calibration()
    params = fixed_point.from_calibration(d_inv, o)
    assert all(v != 0 for v in params.d_inv)  # a full matrix: every entry exercised
    blob = fixed_point.encode(params)
    crc = client.param_set(fixed_point.FORMAT_VERSION, blob)
    assert crc == zlib.crc32(blob)
    staged = client.param_get(ParamWhich.STAGED)
    assert (staged.blob, staged.crc32, staged.format_version) == (
        blob,
        crc,
        fixed_point.FORMAT_VERSION,
    )
    client.param_commit(crc)
    # Committed, not yet active: the set becomes active at the next reset (SPEC §5).
    with pytest.raises(DeviceError) as exc:
        client.param_get(ParamWhich.ACTIVE)
    assert exc.value.status == Status.E_NO_PARAMS

    tap: TapLink = client.link
    mark = len(tap.received)
    t0 = time.monotonic()
    client.reset()
    client.hello()
    reboot_s = time.monotonic() - t0
    # A real reboot: the boot lines again, and the RAM flash kept across it.
    after = bytes(tap.received[mark:])
    assert b"magcal-target fw=" in after
    assert b"protocol flash=kept boots=2\r\n\x00" in after
    print(f"reset request until hello answered after the reboot: {reboot_s * 1000:.1f} ms")

    active = client.param_get(ParamWhich.ACTIVE)
    assert (active.blob, active.crc32, active.format_version) == (
        blob,
        crc,
        fixed_point.FORMAT_VERSION,
    )
    with pytest.raises(DeviceError) as exc:  # a reset clears the staged set
        client.param_get(ParamWhich.STAGED)
    assert exc.value.status == Status.E_NO_PARAMS

    cor, (sent, dropped) = _stream(client, StreamKind.CORRECTED, N_CORRECTED)
    assert all(isinstance(m, Corrected) for m in cor)
    _assert_consecutive(cor)
    assert cor[0].seq < before[-1].seq  # the numbers (and the clock) started again
    assert cor[0].t_us < before[-1].t_us
    assert sent >= N_CORRECTED and dropped == 0
    raw = np.array([m.mag for m in cor])
    assert [tuple(r) for r in raw.tolist()] == [synthetic_mag(m.seq) for m in cor]
    assert all(m.out_exp == params.out_exp for m in cor)
    got = np.array([m.m_b for m in cor], dtype=np.int64)
    want = fixed_point.emulate(params, raw).astype(np.int64)
    assert np.array_equal(got, want), "the device's correction differs from the emulation"
    # And the calibration removes the hard and soft iron: a unit field.
    m = fixed_point.output_to_float(params, got)
    assert np.allclose(np.linalg.norm(m, axis=1), 1.0, atol=2e-3)


def test_stream_throughput_and_drops(client):
    """The raw stream over the emulated UART for THROUGHPUT_S seconds of host time."""
    client.hello()
    client.stream_start(StreamKind.RAW)
    msgs = []
    t0 = time.monotonic()
    try:
        while time.monotonic() - t0 < THROUGHPUT_S:
            msgs.append(client.read_stream(STREAM_TIMEOUT_S))
    finally:
        stats = client.stream_stop()
    wall_s = time.monotonic() - t0
    _assert_consecutive(msgs)
    device_s = (msgs[-1].t_us - msgs[0].t_us) / 1e6
    print(
        f"raw stream: {len(msgs)} samples in {wall_s:.2f} s host time "
        f"({len(msgs) / wall_s:.1f}/s), {device_s:.2f} s device time; "
        f"device sent {stats.sent}, dropped {stats.dropped}"
    )
    assert stats.dropped == 0
    assert stats.sent >= len(msgs)
    # QEMU's clock is the host's: about 100 samples per host second (loose for a busy host).
    assert len(msgs) / wall_s > 50.0


def test_boot_to_first_response(target_factory):
    """A fresh QEMU answers its first hello (within the client's retries) and every one after
    it; the times are printed, not asserted (they depend on how busy the host is)."""
    t0 = time.monotonic()
    t = target_factory()
    c = DeviceClient(open_link(t.pty, LINK_OPEN_TIMEOUT_S), CLIENT_CONFIG)
    try:
        first = c.hello()
        first_s = time.monotonic() - t0
        latencies = []
        for _ in range(20):
            t1 = time.monotonic()
            # Every later hello answers the same: the device did not restart meanwhile.
            assert c.hello() == first
            latencies.append(time.monotonic() - t1)
    finally:
        c.close()
    print(
        f"QEMU start until the first response: {first_s:.3f} s (QEMU named its pty and "
        f"the CPU ran after {t.boot_s:.3f} s); hello round trip after that: median "
        f"{statistics.median(latencies) * 1000:.1f} ms, max {max(latencies) * 1000:.1f} ms"
    )
    assert first.version == 1
