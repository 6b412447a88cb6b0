# SPDX-License-Identifier: Apache-2.0
"""``magcal collect --view`` in a real browser: Debian's Chromium, headless, driven over its
DevTools protocol (a WebSocket, with the websockets client the product's server uses).

The SIL device (build/sil/magcal-sil) is fed a tumbling world; ``host/magcal collect --port
... --view`` runs as a person runs it, its stderr a pipe (whole progress lines). Chromium opens
the address the command prints; the page must show a panel whose sample count grows while
collection runs (it receives the device's samples live), end with the collection, and show
the coverage figure of the terminal's last progress line. A screenshot of the page mid-way
and at the end is taken; with MAGCAL_UPDATE_SCREENSHOTS=1 (``make screenshots``) the last
one is written to docs/img/collect-view.png, which README.md shows.

Chromium comes from ``make deps-browser``; without it plain ``pytest`` skips, naming that
target, and under ``make test`` (MAGCAL_REQUIRE_BROWSER=1) or in CI a missing Chromium fails.
"""

from __future__ import annotations

import base64
import contextlib
import json
import os
import queue
import re
import shutil
import subprocess
import threading
import time
import urllib.request
from pathlib import Path

import numpy as np
import pytest
from matplotlib import image as mpimg
from websockets.sync.client import connect

from magcal.device.client import DeviceClient
from magcal.link import LINK_OPEN_TIMEOUT_S, open_link
from magcal_evaluation.world import FeedClient, WorldFeeder, make_world, tumbling_session
from tests.browser.test_report_browser import CHROMIUM_FLAGS, chromium
from tests.sil.conftest import REPO_ROOT, SIL_BINARY, sil_binary, start_sil  # noqa: F401

SPEEDUP = 5.0  # device seconds per wall-clock second
DURATION_S = 10.0  # wall-clock seconds of collection
STEP_TIMEOUT_S = 30.0  # each wait below: Chromium's start, the page's load, the collection
POLL_S = 0.2
WINDOW = (1280, 1100)
SCREENSHOT = REPO_ROOT / "docs" / "img" / "collect-view.png"
UPDATE_ENV = "MAGCAL_UPDATE_SCREENSHOTS"
#: The page's figures, read from its DOM.
PROBE = """JSON.stringify({
  status: document.getElementById("status").getAttribute("data-status"),
  panels: Array.from(document.querySelectorAll(".panel")).map(function (p) {
    return {name: p.getAttribute("data-compass"), samples: p.getAttribute("data-samples"),
            coverage: p.getAttribute("data-coverage"),
            instruction: p.querySelector(".instruction").textContent};
  }),
  result: !document.getElementById("result").hidden
})"""

pytestmark = pytest.mark.skipif(
    not SIL_BINARY.exists()
    and not ((REPO_ROOT / "mk" / "sil.mk").exists() and shutil.which("make")),
    reason="the SIL executable build/sil/magcal-sil is missing and cannot be built",
)


class DevTools:
    """One page of a headless Chromium, over the DevTools protocol."""

    def __init__(self, binary: str, profile: Path) -> None:
        w, h = WINDOW
        self.proc = subprocess.Popen(
            [
                binary,
                *CHROMIUM_FLAGS,
                f"--user-data-dir={profile}",
                f"--window-size={w},{h}",
                "--remote-debugging-port=0",
                "about:blank",
            ],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
        port_file = profile / "DevToolsActivePort"
        deadline = time.monotonic() + STEP_TIMEOUT_S
        while not (port_file.exists() and port_file.read_text().count("\n") >= 1):
            if time.monotonic() > deadline or self.proc.poll() is not None:
                self.close()
                pytest.fail(f"Chromium gave no DevTools port in {STEP_TIMEOUT_S:g} s")
            time.sleep(POLL_S)
        port = int(port_file.read_text().split()[0])
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/json/list", timeout=10) as r:
            pages = [t for t in json.load(r) if t["type"] == "page"]
        self._stack = contextlib.ExitStack()
        self.ws = self._stack.enter_context(
            connect(pages[0]["webSocketDebuggerUrl"], max_size=None, open_timeout=10)
        )
        self._id = 0

    def call(self, method: str, **params):
        self._id += 1
        self.ws.send(json.dumps({"id": self._id, "method": method, "params": params}))
        deadline = time.monotonic() + STEP_TIMEOUT_S
        while True:
            reply = json.loads(self.ws.recv(timeout=max(0.1, deadline - time.monotonic())))
            if reply.get("id") == self._id:
                if "error" in reply:
                    raise AssertionError(f"DevTools {method}: {reply['error']}")
                return reply["result"]

    def probe(self) -> dict:
        """The page's figures; empty ones while it is still loading."""
        result = self.call("Runtime.evaluate", expression=PROBE, returnByValue=True)
        if "exceptionDetails" in result:
            return {"status": None, "panels": [], "result": False}
        return json.loads(result["result"]["value"])

    def screenshot(self, path: Path) -> np.ndarray:
        """The whole page (beyond the window's height) as PNG."""
        size = self.call("Page.getLayoutMetrics")["cssContentSize"]
        clip = {"x": 0, "y": 0, "width": WINDOW[0], "height": size["height"], "scale": 1}
        data = self.call(
            "Page.captureScreenshot", format="png", clip=clip, captureBeyondViewport=True
        )["data"]
        path.write_bytes(base64.b64decode(data))
        return mpimg.imread(path)

    def close(self) -> None:
        if getattr(self, "_stack", None) is not None:
            self._stack.close()
        self.proc.kill()
        self.proc.wait(10)


@pytest.fixture
def browser(tmp_path):
    tools = DevTools(chromium(), tmp_path / "profile")
    try:
        yield tools
    finally:
        tools.close()


@pytest.fixture
def device(start_sil, tmp_path):  # noqa: F811  (the fixture imported above)
    """(sil, feeder): a running SIL device and a paused feeder of a tumbling world."""
    sil = start_sil(tmp_path / "flash.bin", "--uid", "c0ffee")
    client = DeviceClient(open_link(sil.url, LINK_OPEN_TIMEOUT_S))
    try:
        client.hello()
        info = client.info()
    finally:
        client.close()
    session, truth = tumbling_session(120.0, seed=3, max_rate_rad_s=1.5)
    world = make_world(session, truth, info, t0_us=1_000_000)
    feed = FeedClient("127.0.0.1", sil.feed_port)
    feeder = WorldFeeder(world, feed, speedup=SPEEDUP)
    try:
        yield sil, feeder
    finally:
        feeder.close()
        feed.close()
        assert sil.stop() == 0


def _lines(stream) -> queue.Queue:
    q: queue.Queue = queue.Queue()

    def pump() -> None:
        for line in stream:
            q.put(line.rstrip("\n"))
        q.put(None)

    threading.Thread(target=pump, daemon=True).start()
    return q


def _wait(predicate, what: str):
    deadline = time.monotonic() + STEP_TIMEOUT_S
    while time.monotonic() < deadline:
        value = predicate()
        if value:
            return value
        time.sleep(POLL_S)
    pytest.fail(f"waited {STEP_TIMEOUT_S:g} s for {what}")


def test_the_live_page_follows_the_collection(browser, device, tmp_path):
    sil, feeder = device
    out = tmp_path / "session.csv"
    env = {k: v for k, v in os.environ.items() if k not in ("DISPLAY", "WAYLAND_DISPLAY")}
    env.pop("CI", None)  # whole progress lines anyway: stderr is a pipe
    argv = ["collect", "--port", sil.url, "-o", str(out), "--view"]
    argv += ["--coverage", "off", "--duration", f"{DURATION_S:g}"]
    feeder.resume()
    proc = subprocess.Popen(
        [str(REPO_ROOT / "host" / "magcal"), *argv],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=env,
    )
    try:
        stderr = _lines(proc.stderr)
        seen: list[str] = []

        def address() -> str | None:
            while not stderr.empty():
                line = stderr.get()
                if line is None:
                    pytest.fail(
                        "collect ended before printing the view's address:\n" + "\n".join(seen)
                    )
                seen.append(line)
                m = re.search(r"live view at (http://127\.0\.0\.1:\d+/)", line)
                if m:
                    return m.group(1)
            return None

        url = _wait(address, "the view's address on stderr")
        browser.call("Page.enable")
        browser.call("Page.navigate", url=url)

        def samples() -> int:
            panels = browser.probe()["panels"]
            return int(panels[0]["samples"] or 0) if panels else 0

        first = _wait(samples, "the first samples on the page")
        _wait(lambda: samples() > first, "more samples on the page")
        mid = browser.screenshot(tmp_path / "collect-view-mid.png")
        page = _wait(
            lambda: (p := browser.probe())["status"] == "done" and p["result"] and p,
            "the page to show the end of collection",
        )
        final = browser.screenshot(tmp_path / "collect-view.png")
        stdout = proc.stdout.read()
        assert proc.wait(STEP_TIMEOUT_S) == 0
    finally:
        feeder.pause()
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    while (line := stderr.get(timeout=STEP_TIMEOUT_S)) is not None:
        seen.append(line)
    progress = [line for line in seen if re.search(r"\d samples .* coverage", line)]
    assert progress, "\n".join(seen)
    terminal = re.search(r"coverage\s+(\d+\.\d) %", progress[-1]).group(1)
    written = re.search(r"coverage (\d+\.\d) %", stdout).group(1)
    panel = page["panels"][0]
    assert panel["coverage"] == terminal == written
    assert int(panel["samples"]) == int(progress[-1].split()[0])
    assert panel["name"].startswith("magnetometer of device 00c0ffee")
    assert panel["instruction"]
    # drawn: the sphere's cells are coloured (covered green, missing red), the rest of the
    # page is grey text on white; a page whose drawing failed is nearly colourless
    for image in (mid, final):
        rgb = image[..., :3]
        coloured = rgb.max(axis=-1) - rgb.min(axis=-1) > 0.15
        assert coloured.mean() > 0.02
    green = final[..., 1] > np.maximum(final[..., 0], final[..., 2]) + 0.1
    assert green.mean() > 0.01  # by the end, many cells are covered
    if os.environ.get(UPDATE_ENV) == "1":
        SCREENSHOT.parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(tmp_path / "collect-view.png", SCREENSHOT)
