# SPDX-License-Identifier: Apache-2.0
"""The host's client library against the SIL device (build/sil/magcal-sil) end to end:
open_link("socket://..."), hello/info, a simulated session fed through the feed socket as
physical values (magcal_evaluation.world, P lines) and streamed back raw as the counts the device
made of them (count, order, values exactly as world.device_counts predicts), flash_parameters
of the simulator's true calibration, then the corrected stream within 1 LSB of
fixed_point.emulate. And the device's quantisation at the edges: values at half counts,
past the full scale and at +-1e300 (saturation at the int16 limits), non-finite values
refused and skipped.

Uses the start_sil fixture of tests/sil/conftest.py (which builds the executable with make).
"""

from __future__ import annotations

import re
import shutil

import numpy as np
import pytest

from magcal.device import fixed_point
from magcal.device.client import (
    SENSOR_KINDS,
    ClientConfig,
    Corrected,
    DeviceClient,
    ParamWhich,
    Sample,
    StreamKind,
)
from magcal.device.flash import flash_parameters, read_backup
from magcal.device.generated import Unit
from magcal.link import LINK_OPEN_TIMEOUT_S, open_link
from magcal.sim.scenarios import preset, simulate
from magcal_evaluation.sil import REPO_ROOT, SIL_BINARY
from magcal_evaluation.world import FeedClient, count_si, device_counts, make_world, physical_line

SIL_STREAM_TIMEOUT_S = 10.0  # a loaded machine (2 shared cores) may be slow to feed
N_RAW = 150
N_CORRECTED = 150

pytestmark = pytest.mark.skipif(
    not SIL_BINARY.exists()
    and not ((REPO_ROOT / "mk" / "sil.mk").exists() and shutil.which("make")),
    reason="the SIL executable build/sil/magcal-sil is missing and cannot be built "
    "(no mk/sil.mk or no make)",
)


def _client(sil) -> DeviceClient:
    link = open_link(f"socket://127.0.0.1:{sil.proto_port}", LINK_OPEN_TIMEOUT_S)
    return DeviceClient(link, ClientConfig())


def test_client_streams_flashes_and_corrects(start_sil, tmp_path):
    sil = start_sil(tmp_path / "flash.bin")
    client = _client(sil)
    try:
        hello = client.hello()
        assert hello.version == 1
        info = client.info()
        mag = info.sensor("mag").count_scale
        assert mag.unit in (Unit.GAUSS, Unit.TESLA) and mag.si > 0
        assert info.params_format_version == fixed_point.FORMAT_VERSION
        assert info.params_size == fixed_point.ENCODED_SIZE

        session, truth = simulate(preset("mems", duration_s=3.0, stationary_s=0.5), seed=5)
        world = make_world(session, truth, info, t0_us=1_000_000)
        assert len(world) >= N_RAW + N_CORRECTED

        # Raw stream: every fed sample comes back, in order, with its counts and time.
        client.stream_start(StreamKind.RAW)
        with FeedClient("127.0.0.1", sil.feed_port) as feed:
            feed.send_world(world, 0, N_RAW)
            raw = list(client.stream(N_RAW, SIL_STREAM_TIMEOUT_S))
            stats = client.stream_stop()
            assert all(isinstance(s, Sample) for s in raw)
            seqs = [s.seq for s in raw]
            assert seqs == list(range(seqs[0], seqs[0] + N_RAW))
            assert [s.t_us for s in raw] == world.t_us[:N_RAW].tolist()
            assert np.array_equal(np.array([s.mag for s in raw]), world.mag[:N_RAW])
            assert np.array_equal(np.array([s.acc for s in raw]), world.acc[:N_RAW])
            assert np.array_equal(np.array([s.gyr for s in raw]), world.gyr[:N_RAW])
            assert (stats.sent, stats.dropped) == (N_RAW, 0)

            # Flash the true calibration with the full flow (backup, read-backs, reset).
            params = world.device_params()
            blob = fixed_point.encode(params)

            def reconnect() -> DeviceClient:
                return _client(sil)

            backup = tmp_path / "backup.json"
            result = flash_parameters(
                client, blob, fixed_point.FORMAT_VERSION, backup, reconnect=reconnect
            )
            assert result.active == "new" and result.recovered_from == ""
            client = result.client
            assert read_backup(backup)["blob"] is None  # a fresh flash file: no set before
            assert client.param_get(ParamWhich.ACTIVE).blob == blob

            # Corrected stream: the device's output within 1 LSB of the emulation.
            client.stream_start(StreamKind.CORRECTED)
            feed.send_world(world, N_RAW, N_RAW + N_CORRECTED)
            cor = list(client.stream(N_CORRECTED, SIL_STREAM_TIMEOUT_S))
            client.stream_stop()
        assert all(isinstance(s, Corrected) for s in cor)
        assert [s.t_us for s in cor] == world.t_us[N_RAW : N_RAW + N_CORRECTED].tolist()
        raw_mag = np.array([s.mag for s in cor])
        assert np.array_equal(raw_mag, world.mag[N_RAW : N_RAW + N_CORRECTED])
        assert all(s.out_exp == params.out_exp for s in cor)
        want = fixed_point.emulate(params, raw_mag).astype(np.int64)
        got = np.array([s.m_b for s in cor], dtype=np.int64)
        assert np.max(np.abs(got - want)) <= 1
        # And the true calibration makes the field unit norm (noise and quantisation aside).
        m = fixed_point.output_to_float(params, got)
        assert np.allclose(np.linalg.norm(m, axis=1), 1.0, atol=0.05)
    finally:
        client.close()
    assert sil.stop() == 0


def _edge_rows(lsb: list[float], rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """(N, 9) physical values at the edges of the quantisation, and (M,) the indices of the
    rows that must saturate (each value at +32767 or -32768)."""
    lsb9 = np.repeat(np.asarray(lsb), 3)
    rows = [
        rng.uniform(-32767.9, 32766.9, (40, 9)) * lsb9,  # anywhere in the register range
        (rng.integers(-32768, 32767, (20, 9)) + 0.5) * lsb9,  # at half counts: ties
        (rng.integers(-32767, 32767, (10, 9)) - 0.5) * lsb9,
        (rng.integers(-32768, 32767, (10, 9)) + 0.4999) * lsb9,  # just either side
        (rng.integers(-32768, 32767, (10, 9)) + 0.5001) * lsb9,
        np.zeros((1, 9)),
        np.full((1, 9), -0.0),
        np.full((1, 9), 5e-324),
    ]
    n_in = sum(len(r) for r in rows)
    sat = [
        np.full((1, 9), 1e300),
        np.full((1, 9), -1e300),
        np.full((1, 9), 32767.5) * lsb9,
        np.full((1, 9), -32768.5) * lsb9,
        np.full((1, 9), 40000.0) * lsb9,
        # 5 G, 5 g and 20 rad/s: past the nominal full scale and the register limits
        np.array([[5e-4, -5e-4, 5e-4, 49.03325, -49.03325, 49.03325, 20.0, -20.0, 20.0]]),
    ]
    all_rows = np.vstack(rows + sat)
    return all_rows, np.arange(n_in, len(all_rows))


def test_device_quantises_physical_lines(start_sil, tmp_path):
    sil = start_sil(tmp_path / "flash.bin")
    client = _client(sil)
    try:
        client.hello()
        info = client.info()
        scales = [info.sensor(kind).count_scale for kind in SENSOR_KINDS]
        rows, sat = _edge_rows([count_si(s) for s in scales], np.random.default_rng(7))
        # The nominal full scale (+-4 G, +-4 g, +-500 dps) is inside the register range or at
        # its edge: 27368, 32787 -> 32767 and 28571 counts.
        nominal = np.array([[4e-4, -4e-4, 0.0, 39.2266, -39.2266, 0.0, 500 * np.pi / 180, 0, 0]])
        rows = np.vstack([rows, nominal])
        want = np.concatenate(
            [device_counts(rows[:, 3 * k : 3 * k + 3], scales[k]) for k in range(3)], axis=1
        )
        t_us = 1_000 + 10_000 * np.arange(len(rows))
        lines = [physical_line(t, r[:3], r[3:6], r[6:]) for t, r in zip(t_us, rows, strict=True)]
        # Two refused lines in between: skipped, the device goes on.
        refused = [
            f"P {t_us[5] + 1} nan 0 0 0 0 0 0 0 0\n",
            f"P {t_us[5] + 2} 0 0 0 -inf 0 0 0 0 0\n",
        ]
        lines[6:6] = refused

        client.stream_start(StreamKind.RAW)
        with FeedClient("127.0.0.1", sil.feed_port) as feed:
            feed.send_lines(lines)
            raw = list(client.stream(len(rows), SIL_STREAM_TIMEOUT_S))
            stats = client.stream_stop()
        assert (stats.sent, stats.dropped) == (len(rows), 0)
        assert [s.t_us for s in raw] == t_us.tolist()
        got = np.array([[*s.mag, *s.acc, *s.gyr] for s in raw])
        # The device's counts are exactly the mirror's prediction, row by row...
        assert np.array_equal(got, want)
        # ...which saturates at the int16 limits as documented, never wrapping.
        assert np.all(np.isin(got[sat], (32767, -32768)))
        assert np.array_equal(np.sign(got[sat]), np.sign(rows[sat]))
        assert got[-1].tolist() == [27368, -27368, 0, 32767, -32768, 0, 28571, 0, 0]
        # In range, the counts are the nearest ones (half counts away from zero).
        q = rows[: sat[0]] / np.repeat([count_si(s) for s in scales], 3)
        assert np.all(np.abs(got[: sat[0]] - q) <= 0.5)
        ties = np.abs(np.abs(q - np.trunc(q)) - 0.5) == 0
        assert ties.sum() > 50
        assert np.array_equal(np.abs(got[: sat[0]][ties]), np.abs(np.trunc(q[ties])) + 1)
    finally:
        client.close()
    assert sil.stop() == 0
    err = sil.stderr_text()
    for n, value in ((7, "nan"), (8, "-inf")):
        assert re.search(
            rf"feed line {n}: status -2 \(a value out of range, not finite, or a time before "
            rf"the clock\), skipped: P \d+ .*{re.escape(value)}",
            err,
        ), err
