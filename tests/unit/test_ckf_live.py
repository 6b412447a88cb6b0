# SPDX-License-Identifier: Apache-2.0
"""The live CKF while collecting (magcal.calib.norm_only.live and its use in magcal.device.collect):
"ok to stop" on a good session and not on a partial or a too noisy one, block means at high
rates, and collect's progress line with the estimate (and without it should it fail)."""

from __future__ import annotations

import numpy as np
import pytest

from magcal.calib.norm_only import live as live_mod
from magcal.calib.norm_only.live import LiveCalibration, LiveState
from magcal.device import collect as col
from magcal.device.coverage import CoverageTracker
from magcal.sim.scenarios import preset, simulate
from tests.unit.test_collect import FakeClient, _info, _samples

#: Readings per call, as collect feeds them (0.25 s at 100 Hz).
CHUNK = 25


def replay(mag: np.ndarray, rate_hz: float = 100.0) -> list[LiveState]:
    """The states a recorder would show, with coverage measured as collect does."""
    live = LiveCalibration(rate_hz)
    tracker = CoverageTracker(min_extent=0.2 * float(np.ptp(mag, axis=0).max()))
    states = []
    for i in range(0, mag.shape[0], CHUNK):
        live.add(mag[i : i + CHUNK])
        tracker.add(mag[i : i + CHUNK])
        states.append(live.state(tracker.state().coverage))
    return states


@pytest.fixture(scope="module")
def handheld():
    session, _ = simulate(preset("handheld"), 2)
    return session


def test_ok_to_stop_appears_on_a_good_session(handheld):
    states = replay(handheld.mag)
    ok = [s for s in states if s.ok_to_stop]
    assert ok, states[-1]
    first = ok[0]
    assert first.converged and first.coverage >= live_mod.OK_COVERAGE
    assert first.norm_std <= live_mod.MAX_NORM_STD and first.norm_change <= live_mod.MAX_NORM_CHANGE
    assert first.text().startswith("ok to stop: coverage ")
    # The spread is the sensor's noise (0.5 % of the field in this simulation), not more.
    assert 0.003 < first.norm_spread < 0.008
    # Converged before coverage was complete: the display then says so, without "ok".
    early = [s for s in states if s.converged and not s.ok_to_stop]
    assert early and early[0].text().endswith("(converged)")


def test_no_ok_to_stop_on_the_first_part_of_that_session(handheld):
    states = replay(handheld.mag[:2000])
    assert states[-1].started and states[-1].coverage < live_mod.OK_COVERAGE
    assert not any(s.ok_to_stop for s in states)
    assert "norm spread" in states[-1].text()


def test_no_convergence_with_too_noisy_readings_however_covered():
    session, _ = simulate(preset("mems", mag_sigma=0.05), 1)  # 5 % of the field
    states = replay(session.mag)
    assert max(s.coverage for s in states) >= live_mod.OK_COVERAGE
    assert not any(s.converged or s.ok_to_stop for s in states)
    assert states[-1].norm_std > live_mod.MAX_NORM_STD
    assert states[-1].text().endswith("(settling)")


def test_nothing_before_the_start():
    session, _ = simulate(preset("mems", duration_s=5, motion="small"), 1)
    states = replay(session.mag)
    assert not any(s.started for s in states)
    assert states[-1].text() == "norm: waiting for more directions"
    assert states[-1].norm_spread is None and not states[-1].ok_to_stop


def test_a_fast_stream_is_filtered_as_block_means_however_it_is_cut(handheld):
    mag = np.repeat(handheld.mag[:3000], 10, axis=0)  # a 1 kHz stream of the same motion
    one = LiveCalibration(1000.0)
    assert one.block == 10 and one.ckf_rate_hz == pytest.approx(100.0)
    one.add(mag)
    pieces = LiveCalibration(1000.0)
    for i in range(0, mag.shape[0], 7):
        pieces.add(mag[i : i + 7])
    assert one.readings == pieces.readings == mag.shape[0]
    assert one.ckf.updates == pieces.ckf.updates and one.ckf.started
    # (equal but for the rounding of sums in another order)
    np.testing.assert_allclose(one.ckf.estimate.x, pieces.ckf.estimate.x, rtol=1e-9, atol=1e-12)
    # Block means of a repeated stream are the 100 Hz stream itself.
    direct = LiveCalibration(100.0)
    direct.add(handheld.mag[:3000])
    np.testing.assert_allclose(one.ckf.estimate.x, direct.ckf.estimate.x, rtol=1e-9, atol=1e-12)


# --------------------------------------------------------------------- in magcal collect


def _collect(client, **kw):
    return col.collect(client, _info(), clock=client.clock, **kw)


def test_collect_shows_the_live_estimate_and_records_it():
    progress = []
    client = FakeClient(_samples())
    r = _collect(client, coverage_target=0.9, min_samples=500, progress=progress.append)
    assert r.stopped == "coverage"
    last = progress[-1]
    assert last.live is r.live and r.live.started
    assert "norm spread" in last.hint
    started = [p for p in progress if p.live is not None and p.live.started]
    assert started and all(p.hint.startswith(p.live.text()) for p in started)
    waiting = [p for p in progress if p.live is not None and not p.live.started]
    assert waiting and all(
        p.hint.startswith("norm: waiting for more directions; ") for p in waiting
    )
    assert r.session.meta["live_estimate"].startswith("CKF norm spread ")


def test_a_failing_live_estimate_does_not_stop_the_collection(monkeypatch, caplog):
    def broken(self, mag):
        raise ValueError("broken on purpose")

    monkeypatch.setattr(LiveCalibration, "add", broken)
    progress = []
    client = FakeClient(_samples(300))
    r = _collect(client, max_samples=300, progress=progress.append)
    assert r.stopped == "samples" and len(r.session) == 300
    assert r.live is None and "live_estimate" not in r.session.meta
    assert all(p.live is None for p in progress)
    assert progress[-1].hint == r.coverage.hint
    assert "live estimate failed" in caplog.text
