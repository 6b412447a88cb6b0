# SPDX-License-Identifier: Apache-2.0
"""End to end in CI: the demo's flow against the SIL device, seeded and shorter.

magcal-sil starts on a fresh flash file; the world (a MEMS sensor with a random distortion in
a 50 uT field, seed 11) tumbles it, sped up, while the real command line (host/magcal) runs
collect, calibrate --method ml, flash and verify; then the device's own corrected output of
noise-free readings of the same motion is streamed (magcal_evaluation.demo, as ``make demo``).

After flashing:
- the heading error of the device's corrected output (each sample rotated to north with the
  attitude the world fed it with) is at most 0.5 deg RMS, and so is the calibration-induced
  heading error of the result over the SO(3) grid (the accuracy checks' metric);
- for every streamed sample, the device's fixed-point output equals the host's float64
  correction ``D_inv (y - o)`` of result.json (its unquantised D_inv and o), in the device's
  output LSBs, within 1 LSB, unrounded: the output's rounding (1/2 LSB) plus the parameter
  format's quantisation (Q1.30 D_inv, Q16.15 offset), which the default output exponent
  (fixed_point.default_out_exp) keeps within 1/2 LSB for every int16 input. The figure with
  the host value rounded to an LSB is printed too. (The device is bit-exact to
  fixed_point.emulate of the flashed set, which tests/sil/test_sil_client.py and magcal
  verify check.)
"""

from __future__ import annotations

import math
import shutil
import socket
import threading
import time

import numpy as np
import pytest

from magcal.device.client import DeviceClient
from magcal.io.result import read_result
from magcal.io.session import read_session
from magcal_evaluation.demo import DemoConfig, format_report, run_demo
from magcal_evaluation.sil import REPO_ROOT, SIL_BINARY
from magcal_evaluation.world import (
    FeedClient,
    WorldError,
    WorldFeeder,
    make_world,
    tumbling_session,
)
from tests.fake_device import FakeDevice, MemoryLink

SEED = 11
HEADING_BOUND_DEG = 0.5

needs_sil = pytest.mark.skipif(
    not SIL_BINARY.exists()
    and not ((REPO_ROOT / "mk" / "sil.mk").exists() and shutil.which("make")),
    reason="the SIL executable build/sil/magcal-sil is missing and cannot be built",
)


@needs_sil
def test_demo_end_to_end(sil_binary, tmp_path):
    cfg = DemoConfig(
        out_dir=tmp_path / "demo",
        seed=SEED,
        kind="mems",
        collect_s=30.0,  # device seconds: 3000 samples
        verify_s=2.0,
        check_s=5.0,
        speedup=6.0,
        sil_binary=sil_binary,
    )
    log: list[str] = []
    report = run_demo(cfg, log=log.append)
    print("\n".join(log))
    print(format_report(report))

    # Every step ran the real command line.
    assert report.steps == {
        "collect": "cli",
        "calibrate": "cli",
        "flash": "cli",
        "verify": "cli",
    }
    out = cfg.out_dir
    for name in ("session.csv", "result.json", "backup.json", "device.csv", "report.json"):
        assert (out / name).is_file(), name
    assert report.session_samples == len(read_session(out / "session.csv")) >= 3000

    # Calibration-induced heading error: from the grid, and from the device's own output.
    assert report.heading_grid_identity_deg > 10.0  # the distortion is real
    assert report.heading_grid_ml_deg <= HEADING_BOUND_DEG
    assert report.device_samples >= 0.9 * cfg.check_s * 100
    assert report.heading_device_corrected_deg <= HEADING_BOUND_DEG
    assert report.norm_spread_corrected_pct < 0.1 * report.norm_spread_raw_pct

    # The device's fixed-point output against the host's float correction, every sample,
    # recomputed here from the files the demo wrote.
    d = np.loadtxt(out / "device.csv", delimiter=",", dtype=np.int64)
    assert len(d) == report.device_samples
    raw, out_exp, got = d[:, 2:5], d[:, 5:6], d[:, 6:9]
    result = read_result(out / "result.json")
    y = raw.astype(np.float64) * report.session_unit_per_count  # the session's unit (uT)
    host = (y - result.o) @ np.asarray(result.D_inv, dtype=np.float64).T
    host_lsb = np.ldexp(host, (31 - out_exp).astype(np.int64))
    diff = np.abs(got - host_lsb)  # unrounded
    assert np.max(diff) <= 1.0, f"{int(np.sum(diff > 1))} samples beyond 1 LSB"
    assert report.max_lsb_diff == np.max(diff)
    assert report.max_lsb_diff_rounded == np.max(np.abs(got - np.rint(host_lsb))) <= 1


def _sink() -> tuple[socket.socket, list[bytes], threading.Thread]:
    """A loopback TCP server that keeps every byte it receives."""
    srv = socket.create_server(("127.0.0.1", 0))
    got: list[bytes] = []

    def serve() -> None:
        conn, _ = srv.accept()
        with conn:
            while chunk := conn.recv(65536):
                got.append(chunk)

    th = threading.Thread(target=serve, daemon=True)
    th.start()
    return srv, got, th


def test_world_feeder_paces_pauses_switches_and_runs_out():
    session, truth = tumbling_session(2.0, 4, stationary_s=0.0)
    client = DeviceClient(MemoryLink(FakeDevice()), first_seq=1)
    client.hello()
    info = client.info()
    world = make_world(session, truth, info)
    ideal = make_world(session, truth, info, noise=False)
    srv, got, th = _sink()
    with srv, FeedClient("127.0.0.1", srv.getsockname()[1]) as feed:
        feeder = WorldFeeder(world, feed, speedup=10.0)
        try:
            time.sleep(0.1)
            assert feeder.fed == 0  # starts paused
            feeder.resume()
            feeder.wait_fed(50, timeout_s=5.0)  # 0.5 device s at 10x: about 0.05 s
            feeder.pause()
            k = feeder.fed
            assert 50 <= k < len(world)
            time.sleep(0.1)
            assert feeder.fed == k  # paused: nothing more
            feeder.switch(ideal)
            feeder.speedup = math.inf
            feeder.resume()
            assert feeder.exhausted.wait(5.0)
            assert feeder.fed == len(world)
            with pytest.raises(WorldError, match="all .* samples were fed"):
                feeder.resume()
        finally:
            feeder.close()
    th.join(5.0)
    text = b"".join(got).decode()
    assert text == "".join(world.lines(0, k)) + "".join(ideal.lines(k, len(world)))
    # The truth in counts is what the device reads: k (D R m + o).
    D_c, o_c = world.calibration_counts()
    assert np.allclose(world.truth_counts().sensor.D, D_c)
    assert np.array_equal(world.indices(world.t_us[[3, 7]]), [3, 7])
    with pytest.raises(WorldError):
        world.indices([world.t_us[0] + 1])
