# SPDX-License-Identifier: Apache-2.0
"""``magcal collect`` and ``magcal verify`` against the SIL device (build/sil/magcal-sil over
TCP), with a simulated tumbling session fed through the sensor feed faster than real time
(magcal_evaluation.world.WorldFeeder):

- collect with --duration: the session reads back with the device's identity and exact
  scales in its metadata, a plausible sample count, the samples equal to what was fed (within
  one count), acc in m/s^2 (|acc| ~ g), mag in uT (the world's 50 uT field once the true
  distortion is undone), no drops and consecutive device times;
- collect with --coverage: stops on the target;
- collect as a subprocess of host/magcal interrupted by SIGINT: exit 130 and the partial
  session written;
- verify fails with E_NO_PARAMS before a set is flashed, and after the world's true
  calibration is flashed reports a norm spread below 1 % and a small heading error.
"""

from __future__ import annotations

import math
import os
import queue
import re
import shutil
import signal
import subprocess
import threading
import time

import numpy as np
import pytest

from magcal import cli
from magcal.device import fixed_point
from magcal.device.client import DeviceClient
from magcal.device.flash import flash_parameters
from magcal.io.session import read_session
from magcal.link import LINK_OPEN_TIMEOUT_S, open_link
from magcal_evaluation.world import FeedClient, WorldFeeder, make_world, tumbling_session
from tests.sil.conftest import REPO_ROOT, SIL_BINARY

SUBPROCESS_TIMEOUT_S = 60.0
SPEEDUP = 10.0  # device seconds per wall-clock second
SIL_UID = "c0ffee"
FIELD_UT = 50.0

pytestmark = pytest.mark.skipif(
    not SIL_BINARY.exists()
    and not ((REPO_ROOT / "mk" / "sil.mk").exists() and shutil.which("make")),
    reason="the SIL executable build/sil/magcal-sil is missing and cannot be built",
)


def _client(url: str) -> DeviceClient:
    return DeviceClient(open_link(url, LINK_OPEN_TIMEOUT_S))


@pytest.fixture
def device(start_sil, tmp_path):
    """(sil, info, world, feeder): a running SIL, its info, a two-minute tumbling world and
    a paused feeder (resume it to feed at SPEEDUP); all stopped at teardown."""
    sil = start_sil(tmp_path / "flash.bin", "--uid", SIL_UID)
    client = _client(sil.url)
    try:
        client.hello()
        info = client.info()
    finally:
        client.close()
    session, truth = tumbling_session(120.0, seed=7, max_rate_rad_s=2.0)
    world = make_world(session, truth, info, t0_us=1_000_000)
    feed = FeedClient("127.0.0.1", sil.feed_port)
    feeder = WorldFeeder(world, feed, speedup=SPEEDUP)
    try:
        yield sil, info, world, feeder
    finally:
        feeder.close()
        feed.close()
        assert sil.stop() == 0


def _flash_truth(sil, world, tmp_path) -> None:
    """Flash the world's true calibration (counts in, unit-norm field out)."""
    clients = [_client(sil.url)]

    def reconnect() -> DeviceClient:
        clients.append(_client(sil.url))
        return clients[-1]

    try:
        clients[0].hello()
        result = flash_parameters(
            clients[0],
            fixed_point.encode(world.device_params()),
            fixed_point.FORMAT_VERSION,
            tmp_path / "backup.json",
            reconnect=reconnect,
        )
        assert result.active == "new"
    finally:
        for c in clients:
            c.close()


def _check_session(path, world, info):
    s = read_session(path)
    m = s.meta
    assert m["device_uid"] == info.uid_hex and SIL_UID in m["device_uid"]
    assert m["firmware"] == info.fw_version_str and m["protocol_version"] == "1"
    assert m["mag_unit"] == "uT" and m["mag_count_scale"].startswith("1/6842e0 gauss")
    assert m["acc_count_scale"].startswith("122/1e-6 standard_gravity")
    assert m["gyr_sensor"].startswith("LSM6DSO") and m["port"].startswith("socket://")
    assert int(m["samples"]) == len(s)
    # Every sample is one the world fed, at its time, in order; any sample missing is one the
    # device dropped (its link was full: a loaded machine) and collect counted it.
    k = world.indices(np.rint(s.t * 1e6).astype(np.int64))
    step = np.diff(k)
    assert np.all(step >= 1), "samples out of order or repeated"
    assert int(np.sum(step - 1)) == int(m["seq_gaps"]) <= int(m["dropped"]), "drops not counted"
    # Units: the values fed within one count of each sensor.
    mag_ut = world.mag_t[k] * 1e6
    assert np.max(np.abs(s.mag - mag_ut)) <= 100 / 6842 * 0.5 + 1e-9
    assert np.max(np.abs(s.acc - world.acc_si[k])) <= 122e-6 * 9.80665 * 0.5 + 1e-9
    assert np.allclose(np.median(np.linalg.norm(s.acc, axis=1)), 9.81, atol=0.3)
    # The mag field, the true distortion undone, is the world's 50 uT.
    sensor = world.truth.sensor
    field = np.linalg.solve(sensor.D, (s.mag / FIELD_UT - sensor.o).T).T * FIELD_UT
    assert np.allclose(np.linalg.norm(field, axis=1), FIELD_UT, rtol=0.03)
    return s


def test_collect_for_a_duration(device, tmp_path, capsys):
    sil, info, world, feeder = device
    out = tmp_path / "session.csv"
    feeder.resume()
    t0 = time.monotonic()
    args = ["collect", "--port", sil.url, "-o", str(out), "--duration", "3", "--coverage", "off"]
    code = cli.main(args)
    wall = time.monotonic() - t0
    feeder.pause()
    err = capsys.readouterr()
    assert code == 0, err.err
    assert 3.0 <= wall < 10.0
    s = _check_session(out, world, info)
    assert s.meta["stopped"] == "duration"
    # About 3 s at SPEEDUP x 100 Hz (a loaded machine feeds slower, never faster).
    assert 300 <= len(s) <= 3.3 * SPEEDUP * 100
    assert f"wrote {out}" in err.out
    lines = [x for x in err.err.splitlines() if "samples" in x]
    assert lines and re.search(r"\d+ samples +[\d.]+/s +dropped 0 +coverage +[\d.]+ %", lines[0])
    print(lines[-1])  # for the report: a real progress line


def test_collect_until_the_coverage_target(device, tmp_path, capsys):
    sil, info, world, feeder = device
    out = tmp_path / "session.csv"
    feeder.resume()
    code = cli.main(
        ["collect", "--port", sil.url, "-o", str(out), "--coverage", "80", "--duration", "60"]
    )
    feeder.pause()
    err = capsys.readouterr()
    assert code == 0, err.err
    s = _check_session(out, world, info)
    assert s.meta["stopped"] == "coverage"
    assert float(s.meta["coverage"].split()[0]) >= 80.0
    assert len(s) >= 200  # a calibration's minimum
    print(err.err.splitlines()[-1])


def _stderr_lines(proc: subprocess.Popen) -> queue.Queue:
    q: queue.Queue = queue.Queue()

    def pump() -> None:
        for line in proc.stderr:
            q.put(line)
        q.put(None)

    threading.Thread(target=pump, daemon=True).start()
    return q


def _default_sigint() -> None:
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def test_ctrl_c_writes_the_partial_session(device, tmp_path):
    sil, info, world, feeder = device
    out = tmp_path / "partial.csv"
    feeder.resume()
    # Only Ctrl-C may end this run, not the default coverage target (reached in about 7 s).
    argv = ["collect", "--port", sil.url, "-o", str(out), "--coverage", "off", "--duration", "600"]
    proc = subprocess.Popen(
        [str(REPO_ROOT / "host" / "magcal"), *argv],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env={**os.environ, "PYTHONUNBUFFERED": "1"},
        # SIGINT as a terminal delivers it: a shell runs a background job (`make test &`)
        # with SIGINT ignored, a child inherits that, and Python then keeps ignoring it.
        preexec_fn=_default_sigint,
    )
    try:
        lines = _stderr_lines(proc)
        deadline = time.monotonic() + SUBPROCESS_TIMEOUT_S
        seen = []
        while True:  # wait for a progress line with samples in it
            line = lines.get(timeout=max(0.1, deadline - time.monotonic()))
            assert line is not None, f"collect exited early: {''.join(seen)}"
            seen.append(line)
            match = re.match(r"\s*(\d+) samples", line)
            if match and int(match.group(1)) > 0:
                break
        proc.send_signal(signal.SIGINT)
        code = proc.wait(timeout=SUBPROCESS_TIMEOUT_S)
        stdout = proc.stdout.read()
        rest = []
        while (line := lines.get(timeout=SUBPROCESS_TIMEOUT_S)) is not None:
            rest.append(line)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(timeout=SUBPROCESS_TIMEOUT_S)
        feeder.pause()
    assert code == 130, "".join(seen + rest)
    assert f"wrote {out}" in stdout
    assert any("interrupted" in x and str(out) in x for x in rest)
    s = _check_session(out, world, info)
    assert s.meta["stopped"] == "interrupted" and len(s) > 0


def test_verify_before_and_after_flashing_the_true_calibration(device, tmp_path, capsys):
    sil, info, world, feeder = device
    # No set yet: a clear refusal, non-zero exit.
    assert cli.main(["verify", "--port", sil.url, "--samples", "50"]) == cli.EXIT_ERROR
    err = capsys.readouterr().err
    assert "E_NO_PARAMS" in err and "magcal flash" in err

    _flash_truth(sil, world, tmp_path)

    feeder.resume()
    code = cli.main(["verify", "--port", sil.url, "--samples", "400"])
    feeder.pause()
    captured = capsys.readouterr()
    assert code == 0, captured.err
    text = captured.out
    print(text)  # for the report
    m = re.search(r"std [\d.]+ \(([\d.]+) %\)", text)
    assert m and float(m.group(1)) < 1.0
    mean = float(re.search(r"norm +mean ([\d.]+)", text).group(1))
    assert math.isclose(mean, 1.0, abs_tol=0.02)
    assert "400 of 400 corrected samples equal the host's emulation" in text
    rms = float(re.search(r"heading +raw stream: RMS ([\d.]+)°", text).group(1))
    assert rms < 3.0
    dip = re.search(r"dip +([\d.]+)°", text)
    assert dip and abs(float(dip.group(1)) - world.truth.scenario.dip_deg) < 2.0


def test_verify_measures_a_collected_session(device, tmp_path, capsys):
    sil, info, world, feeder = device
    out = tmp_path / "session.csv"
    feeder.resume()
    assert cli.main(["collect", "--port", sil.url, "-o", str(out), "--duration", "2"]) == 0
    feeder.pause()
    _flash_truth(sil, world, tmp_path)
    capsys.readouterr()
    feeder.resume()
    code = cli.main(
        ["verify", "--port", sil.url, "--samples", "200", "--no-heading", "--session", str(out)]
    )
    feeder.pause()
    text = capsys.readouterr().out
    assert code == 0
    assert "heading    skipped (--no-heading)" in text
    rms = float(re.search(rf"heading +{re.escape(str(out))}: RMS ([\d.]+)°", text).group(1))
    assert rms < 3.0
