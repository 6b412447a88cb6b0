# SPDX-License-Identifier: Apache-2.0
"""``magcal collect --view`` without a browser: the server's files, its Origin check and the
states it pushes; the panel built from progress reports; the before/after of a fit; the
browser left alone where there is no display. (tests/browser drives the page in Chromium.)"""

from __future__ import annotations

import json
import urllib.error
import urllib.request

import numpy as np
import pytest
from websockets.exceptions import InvalidStatus
from websockets.sync.client import connect

from magcal.commands.collect import progress_line
from magcal.device.collect import CollectProgress
from magcal.device.coverage import CoverageTracker
from magcal.view import collect as view_collect
from magcal.view.model import MAX_POINTS, CompassView, result_spheres
from magcal.view.server import ViewServer

TIMEOUT_S = 10.0


def _sphere(n: int, seed: int = 0) -> np.ndarray:
    u = np.random.default_rng(seed).normal(size=(n, 3))
    return u / np.linalg.norm(u, axis=1, keepdims=True)


def _report(readings: np.ndarray, tracker: CoverageTracker, samples: int) -> CollectProgress:
    tracker.add(readings)
    state = tracker.state(force=True)
    return CollectProgress(
        samples, 1.0, 100.0, 0, state.coverage, state.hint, None, state.hint, state, readings
    )


@pytest.fixture
def server():
    s = ViewServer()
    try:
        yield s
    finally:
        s.close(0.0)


def test_the_server_listens_on_loopback_and_serves_the_page(server):
    assert server.url.startswith("http://127.0.0.1:") and server.port > 0
    with urllib.request.urlopen(server.url, timeout=TIMEOUT_S) as r:
        assert r.headers["Content-Type"].startswith("text/html")
        assert b'<script src="view.js">' in r.read()
    with urllib.request.urlopen(server.url + "view.js", timeout=TIMEOUT_S) as r:
        assert b"new WebSocket" in r.read()
    with pytest.raises(urllib.error.HTTPError, match="404"):
        urllib.request.urlopen(server.url + "../etc/passwd", timeout=TIMEOUT_S)


def test_only_the_servers_own_page_may_open_the_websocket(server):
    ws_url = f"ws://127.0.0.1:{server.port}/ws"
    with pytest.raises(InvalidStatus, match="403"):
        with connect(ws_url, origin="http://evil.example", open_timeout=TIMEOUT_S):
            pass
    with connect(ws_url, origin=f"http://127.0.0.1:{server.port}", open_timeout=TIMEOUT_S) as ws:
        server.publish({"n": 1})
        assert json.loads(ws.recv(timeout=TIMEOUT_S)) == {"n": 1}
        server.publish({"n": 2})
        assert json.loads(ws.recv(timeout=TIMEOUT_S)) == {"n": 2}


def test_a_page_opened_late_gets_the_last_state_and_close_waits_for_it(server):
    server.publish({"n": 1})
    server.publish({"n": 2, "done": True})
    origin = f"http://127.0.0.1:{server.port}"
    with connect(f"ws://127.0.0.1:{server.port}/ws", origin=origin) as ws:
        assert json.loads(ws.recv(timeout=TIMEOUT_S)) == {"n": 2, "done": True}
        server.close(TIMEOUT_S)  # the page has the last state: returns at once


def test_the_panel_shows_the_terminals_figures_and_keeps_a_bounded_sample():
    tracker = CoverageTracker(min_extent=10.0)
    panel = CompassView("magnetometer")
    centre = np.array([30.0, -10.0, 5.0])
    half = _sphere(4000)
    half = half[half[:, 2] > 0]  # the upper half only: the largest hole is round -z
    for k in range(0, len(half), 500):
        p = _report(centre + 50.0 * half[k : k + 500], tracker, k + 500)
        panel.add(p)
    snap = panel.snapshot()
    assert snap["coverage_pct"] == p.coverage_percent() == f"{100 * p.coverage:.1f}"
    assert snap["figures"] == " ".join(p.figures().split())
    assert f"coverage {snap['coverage_pct']:>5} %" in progress_line(p)
    assert len(snap["counts"]) == sum(snap["cells"]["band_counts"]) == len(p.coverage_state.counts)
    assert snap["face"] == "-z" and snap["target"][2] < -0.9
    assert snap["instruction"] == p.instruction == "point the sensor's -z axis along the field"
    points = np.array(snap["points"])
    assert 0 < len(points) <= MAX_POINTS
    assert np.allclose(np.linalg.norm(points, axis=1), 1.0, atol=0.01)  # directions
    assert (points[:, 2] > -0.05).all()  # about the tracker's centre, not the origin


def test_many_reports_keep_at_most_max_points():
    tracker = CoverageTracker(min_extent=10.0)
    panel = CompassView("m")
    for k in range(8):
        panel.add(_report(50.0 * _sphere(1000, seed=k), tracker, 1000 * (k + 1)))
    assert MAX_POINTS // 2 <= len(panel.snapshot()["points"]) <= MAX_POINTS


def test_the_result_puts_an_ellipsoid_back_on_the_unit_sphere():
    D = np.array([[1.2, 0.1, 0.0], [0.0, 0.9, 0.05], [0.0, 0.0, 1.05]])
    mag = 48.0 * _sphere(3000) @ D.T + np.array([20.0, -35.0, 12.0])
    r = result_spheres(mag)
    assert float(r["after_spread_pct"]) < 0.1 < float(r["before_spread_pct"])
    after = np.array(r["after"])
    assert np.allclose(np.linalg.norm(after, axis=1), 1.0, atol=0.01)
    assert len(r["before"]) <= MAX_POINTS and "error" not in r


def test_the_result_leaves_out_rows_without_a_reading():
    mag = 50.0 * _sphere(2000)
    mag[::3] = np.nan  # a MAVLink session's IMU rows between magnetometer values
    r = result_spheres(mag)
    assert np.isfinite(np.array(r["before"])).all() and np.isfinite(np.array(r["after"])).all()
    assert float(r["after_spread_pct"]) < 0.1
    assert result_spheres(np.full((5, 3), np.nan)) == {
        "before": [],
        "error": "no magnetometer readings",
    }


def test_the_result_of_a_flat_recording_says_why_there_is_no_after():
    u = _sphere(2000)
    u[:, 2] = 0.0  # yaw only: a circle
    r = result_spheres(50.0 * u + 1e-3 * _sphere(2000, seed=1))
    assert "after" not in r and r["error"] and len(r["before"]) > 0


def test_the_narrow_collect_line_puts_the_instruction_first():
    tracker = CoverageTracker(min_extent=10.0)
    p = _report(50.0 * _sphere(300), tracker, 300)
    wide = progress_line(p, 400)
    assert wide == progress_line(p) and wide.split()[0] == "300"
    narrow = progress_line(p, 60)
    assert narrow.startswith(p.instruction) and "coverage" in narrow


def test_no_browser_is_opened_without_a_display(monkeypatch):
    monkeypatch.setattr(view_collect.sys, "platform", "linux")
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    opened = []
    monkeypatch.setattr(view_collect.webbrowser, "get", lambda: opened.append(1))
    assert view_collect.open_in_browser("http://127.0.0.1:1/") is False and not opened


def test_a_text_browser_is_not_started_in_the_terminal(monkeypatch):
    monkeypatch.setenv("DISPLAY", ":0")
    text_browser = view_collect.webbrowser.GenericBrowser("lynx")
    monkeypatch.setattr(text_browser, "open", lambda *a, **k: pytest.fail("lynx started"))
    monkeypatch.setattr(view_collect.webbrowser, "get", lambda: text_browser)
    assert view_collect.open_in_browser("http://127.0.0.1:1/") is False
