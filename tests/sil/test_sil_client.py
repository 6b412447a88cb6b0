"""The host's client library against the SIL device (build/sil/magcal-sil) end to end:
open_link("socket://..."), hello/info, a simulated session fed through the feed socket
(tests/sil/world.py) and streamed back raw (count, order, values), flash_parameters of the
simulator's true calibration, then the corrected stream within 1 LSB of fixed_point.emulate.

Uses the start_sil fixture of tests/sil/conftest.py (which builds the executable with make).
"""

from __future__ import annotations

import shutil

import numpy as np
import pytest

from magcal.device import fixed_point
from magcal.device.client import (
    ClientConfig,
    Corrected,
    DeviceClient,
    ParamWhich,
    Sample,
    StreamKind,
)
from magcal.device.flash import flash_parameters, read_backup
from magcal.device.generated import Unit
from magcal.link import open_link
from magcal.sim.scenarios import preset, simulate
from tests.sil.conftest import REPO_ROOT, SIL_BINARY
from tests.sil.world import FeedClient, make_world

LINK_OPEN_TIMEOUT_S = 5.0
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
