# SPDX-License-Identifier: Apache-2.0
"""magcal_evaluation.world: the mirror of the SIL port's quantisation (the value of a count, round
half away from zero, saturation at the int16 limits), the exact round trip counts -> SI (the
client's conversion) -> counts, the physical feed lines (exact reprs), the feed socket, and
the true calibration in the device's format. tests/sil/test_sil_client.py checks the mirror
against the device itself.

Of WorldFeeder only the pause/resume hand-over is tested here (with a fake feed); its
feeding of the SIL device, paced and paused between steps, is exercised end to end by
tests/sil/test_demo_end_to_end.py (and tests/sil/test_cli_collect_verify.py)."""

from __future__ import annotations

import math
import socket
import threading
import time

import numpy as np
import pytest

from magcal.device import fixed_point
from magcal.device.client import DeviceClient, Scale
from magcal.device.generated import Unit
from magcal.sim.scenarios import preset, simulate
from magcal_evaluation.world import (
    FeedClient,
    WorldError,
    WorldFeeder,
    count_si,
    device_counts,
    make_world,
    physical_line,
)
from tests.fake_device import FakeDevice, MemoryLink

SCALES = {
    "LIS3MDL 4 G": Scale(1, 6842, 0, Unit.GAUSS),
    "AK8963 0.15 uT": Scale(15, 100, -6, Unit.TESLA),
    "LSM6DSO 4 g": Scale(122, 1, -6, Unit.STANDARD_GRAVITY),
    "MPU 2 g": Scale(1, 16384, 0, Unit.STANDARD_GRAVITY),
    "LSM6DSO 2000 dps": Scale(70, 1, -3, Unit.DEG_PER_S),
    "rad/s": Scale(1, 1000, 0, Unit.RAD_PER_S),
}
ALL_COUNTS = np.arange(-32768, 32768)


@pytest.fixture(scope="module")
def info():
    c = DeviceClient(MemoryLink(FakeDevice()), first_seq=1)
    c.hello()
    return c.info()


@pytest.fixture(scope="module")
def sim():
    return simulate(preset("mems", duration_s=4.0, stationary_s=0.5), seed=11)


def test_count_si_mirrors_the_port():
    # sensor_feed.c: num / den, times or divided by 10^|exp10|, times the unit's double.
    assert count_si(Scale(1, 6842, 0, Unit.GAUSS)) == 1.0 / 6842.0 * 1e-4
    assert count_si(Scale(122, 1, -6, Unit.STANDARD_GRAVITY)) == 122.0 / 1.0 / 1e6 * 9.80665
    assert count_si(Scale(175, 1, -4, Unit.DEG_PER_S)) == 175.0 / 1.0 / 1e4 * (math.pi / 180)
    assert count_si(Scale(2000, 1, 18, Unit.TESLA)) == 2e21
    for s in SCALES.values():  # a few ulp from the exact value the host converts with
        assert abs(count_si(s) / s.si - 1) < 1e-15
    for bad in (
        Scale(0, 1, 0, Unit.TESLA),
        Scale(1, 0, 0, Unit.TESLA),
        Scale(1, 1, 19, Unit.TESLA),
    ):
        with pytest.raises(WorldError, match="not a valid count scale"):
            count_si(bad)


@pytest.mark.parametrize("name", list(SCALES))
def test_every_count_round_trips_exactly(name):
    s = SCALES[name]
    si = s.counts_to_si(ALL_COUNTS)
    assert np.array_equal(device_counts(si, s), ALL_COUNTS)
    # Half an LSB either side still lands on the count (round to nearest).
    lsb = s.si
    assert np.array_equal(device_counts(si[1:-1] + 0.49 * lsb, s), ALL_COUNTS[1:-1])
    assert np.array_equal(device_counts(si[1:-1] - 0.49 * lsb, s), ALL_COUNTS[1:-1])


def test_device_counts_round_half_away_and_saturate():
    s = Scale(1, 1, 0, Unit.TESLA)  # 1 T per count: the quotient is the value, halves exact
    cases = [  # (value, count)
        (0.0, 0),
        (-0.0, 0),
        (0.4, 0),
        (0.49999999999999994, 0),  # the double below 1/2: q + 0.5 would round it up to 1
        (-0.49999999999999994, 0),
        (0.5, 1),
        (-0.5, -1),
        (1.5, 2),
        (2.5, 3),
        (-2.5, -3),
        (2.4999999999999996, 2),
        (32766.5, 32767),
        (32767.0, 32767),
        (32767.5, 32767),
        (32768.0, 32767),
        (1e300, 32767),
        (-32767.4, -32767),
        (-32767.5, -32768),
        (-32768.0, -32768),
        (-32768.5, -32768),
        (-1e300, -32768),
        (5e-324, 0),
    ]
    got = device_counts(np.array([v for v, _ in cases]), s)
    assert got.dtype == np.int16 and got.tolist() == [c for _, c in cases]
    tiny = Scale(1, 1000, -18, Unit.TESLA)  # 1e-21 T: the quotient overflows to inf
    assert device_counts(np.array([1e300, -1e300]), tiny).tolist() == [32767, -32768]
    # The SIL's sensors at and past their nominal full scale (int16 limits, not the range).
    assert device_counts(np.array([4e-4, 5e-4]), Scale(1, 6842, 0, Unit.GAUSS)).tolist() == [
        27368,
        32767,
    ]
    for bad in (np.nan, np.inf, -np.inf):
        with pytest.raises(WorldError, match="device_counts: non-finite value"):
            device_counts(np.array([0.0, bad]), s)


def test_world_counts_match_physics(info, sim):
    session, truth = sim
    w = make_world(session, truth, info)
    assert len(w) == len(session.t) and w.mag.dtype == np.int16
    assert np.array_equal(w.mag, device_counts(w.mag_t, info.sensor("mag").count_scale))
    assert np.all(np.diff(w.t_us) == 10_000)  # 100 Hz
    # The field is 50 uT in tesla, distorted: |D^-1 (y - o)| = 50 uT (noise-free).
    wi = make_world(session, truth, info, noise=False)
    s = truth.sensor
    m = (np.linalg.inv(s.D) @ (wi.mag_t / 50e-6 - s.o).T).T
    assert np.allclose(np.linalg.norm(m, axis=1), 1.0, atol=1e-12)
    # Counts back to SI with the client's exact conversion: within half an LSB.
    for kind, si in (("mag", w.mag_t), ("acc", w.acc_si), ("gyr", w.gyr_si)):
        sc = info.sensor(kind).count_scale
        back = sc.counts_to_si(getattr(w, kind))
        assert np.max(np.abs(back - si)) <= 0.5 * sc.si * (1 + 1e-9)
    # At rest, level-ish: the accelerometer reads about 1 g = 8197 counts of 122 ug0.
    assert (
        abs(np.linalg.norm(w.acc[0].astype(float)) - 9.80665 / info.sensor("acc").count_scale.si)
        < 200
    )


def test_true_params_correct_to_unit_norm(info, sim):
    session, truth = sim
    w = make_world(session, truth, info, noise=False)
    p = w.device_params()
    m = fixed_point.output_to_float(p, fixed_point.emulate(p, w.mag))
    # Quantisation of the counts (about 3400 counts for the field) limits the accuracy.
    assert np.allclose(np.linalg.norm(m, axis=1), 1.0, atol=2e-3)


def test_lines_format(info, sim):
    session, truth = sim
    w = make_world(session, truth, info, t0_us=5)
    lines = w.lines(0, 3)
    assert len(lines) == 3 and all(line.endswith("\n") for line in lines)
    f = lines[1].split()
    assert f[0] == "P" and int(f[1]) == 10_005 and len(f) == 11
    # The physical values, exactly (repr reads back as the same double), not counts.
    assert [float(x) for x in f[2:]] == [*w.mag_t[1], *w.acc_si[1], *w.gyr_si[1]]
    assert max(len(line) for line in w.lines()) < 512  # magcal-sil's line limit
    assert physical_line(7, [1e-5, -0.0, 5e-324], [1, 2, 3], [0.1, 1e300, -2.5]) == (
        "P 7 1e-05 -0.0 5e-324 1.0 2.0 3.0 0.1 1e+300 -2.5\n"
    )
    with pytest.raises(WorldError, match="non-finite value"):
        physical_line(7, [np.nan, 0, 0], [0, 0, 0], [0, 0, 0])
    with pytest.raises(WorldError, match="9 values needed"):
        physical_line(7, [0, 0], [0, 0, 0], [0, 0, 0])


def test_world_refuses_bad_times(info, sim):
    session, truth = sim
    with pytest.raises(WorldError, match="times must increase"):
        make_world(session, truth, info, t0_us=-20_000)


def test_feed_client_sends_lines(info, sim):
    session, truth = sim
    w = make_world(session, truth, info)
    srv = socket.create_server(("127.0.0.1", 0))
    got = bytearray()

    def run():
        conn, _ = srv.accept()
        with conn:
            while chunk := conn.recv(65536):
                got.extend(chunk)

    th = threading.Thread(target=run, daemon=True)
    th.start()
    with FeedClient("127.0.0.1", srv.getsockname()[1]) as feed:
        feed.send_world(w, 0, 50)
        feed.send_lines(w.lines(50, 53), pace_s=0.001)
    th.join(2)
    srv.close()
    assert got.decode() == "".join(w.lines(0, 53))


def test_feed_client_connect_error():
    s = socket.socket()
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()
    with pytest.raises(WorldError, match=f"feed: cannot connect to 127.0.0.1:{port}"):
        FeedClient("127.0.0.1", port, timeout_s=0.5)


class _SlowSecondSet(threading.Event):
    """An Event whose ``armed``-th set() from the feeder thread is delayed: the thread is
    preempted between deciding it is idle and saying so."""

    armed = 0

    def set(self) -> None:
        if threading.current_thread().name == "world-feeder" and self.armed:
            self.armed -= 1
            if self.armed == 0:
                time.sleep(0.1)
        super().set()


class _SlowFeed:
    """A feed socket whose every send takes 0.2 s; ``sending`` while one is in progress."""

    sending = False

    def send_lines(self, lines) -> None:
        self.sending = True
        time.sleep(0.2)
        self.sending = False


class _LongWorld:
    t_us = np.arange(0, 100_000_000, 10_000)

    def __len__(self) -> int:
        return len(self.t_us)

    def lines(self, a: int, b: int) -> list[str]:
        return ["x"] * (b - a)


def _wait_until(cond, timeout_s: float = 5.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not cond():
        if time.monotonic() > deadline:
            raise TimeoutError(f"condition not met within {timeout_s} s")
        time.sleep(0.001)


def test_feeder_pause_after_a_quick_resume_waits_for_the_send():
    # A resume() right after pause() returned must not let a set() of the idle flag from
    # before it land after it: the next pause() would then return mid-send.
    feed = _SlowFeed()
    with WorldFeeder(_LongWorld(), feed, speedup=1.0) as feeder:
        idle = _SlowSecondSet()
        idle.set()
        feeder._idle = idle
        feeder.resume()
        _wait_until(lambda: feed.sending)
        idle.armed = 2  # the thread's second set() after this point is delayed
        feeder.pause()
        assert not feed.sending
        feeder.resume()  # while a stale set() may be pending
        time.sleep(0.15)
        _wait_until(lambda: feed.sending)
        feeder.pause()
        assert not feed.sending, "pause() returned while a send was in progress"
