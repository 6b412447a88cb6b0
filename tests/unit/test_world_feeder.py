"""tests/sil/world.py: quantisation to int16 counts, the exact round trip counts -> SI (the
client's conversion) -> counts, the feed lines, the feed socket, and the true calibration in
the device's format."""

from __future__ import annotations

import socket
import threading

import numpy as np
import pytest

from magcal.device import fixed_point
from magcal.device.client import DeviceClient, Scale
from magcal.device.generated import Unit
from magcal.sim.scenarios import preset, simulate
from tests.fake_device import FakeDevice, MemoryLink
from tests.sil.world import FeedClient, WorldError, make_world, quantise

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


@pytest.mark.parametrize("name", list(SCALES))
def test_every_count_round_trips_exactly(name):
    s = SCALES[name]
    si = s.counts_to_si(ALL_COUNTS)
    assert np.array_equal(quantise(si, s), ALL_COUNTS)
    # Half an LSB either side still lands on the count (round to nearest).
    lsb = s.si
    assert np.array_equal(quantise(si[1:-1] + 0.49 * lsb, s), ALL_COUNTS[1:-1])
    assert np.array_equal(quantise(si[1:-1] - 0.49 * lsb, s), ALL_COUNTS[1:-1])


def test_quantise_rounds_to_nearest_and_saturates():
    s = Scale(1, 1000, 0, Unit.TESLA)  # 1 mT per count
    v = np.array([0.0014, 0.0016, -0.0014, -0.0016, 0.0025, 1e3, -1e3, 32.7674, -32.7684])
    assert quantise(v, s).tolist() == [1, 2, -1, -2, 2, 32767, -32768, 32767, -32768]
    assert quantise(v, s).dtype == np.int16
    with pytest.raises(WorldError, match="quantise: non-finite value"):
        quantise(np.array([np.nan]), s)


def test_world_counts_match_physics(info, sim):
    session, truth = sim
    w = make_world(session, truth, info)
    assert len(w) == len(session.t) and w.mag.dtype == np.int16
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
    assert f[0] == "S" and int(f[1]) == 10_005 and len(f) == 11
    assert [int(x) for x in f[2:]] == [*w.mag[1], *w.acc[1], *w.gyr[1]]


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
