# SPDX-License-Identifier: Apache-2.0
"""``magcal collect --mavlink ... --view`` against the autopilot emulator: the page's
WebSocket gets the compass's panel with the progress's figures while collecting, and the
before/after of the fit when collection ends, as for a device (tests/browser runs the page
itself in Chromium against the SIL device)."""

from __future__ import annotations

import json
import threading

from websockets.exceptions import ConnectionClosed
from websockets.sync.client import connect

from magcal import cli
from magcal.view import collect as view_collect
from tests.autopilot.test_mavlink_end_to_end import MAX_SAMPLES, SPEEDUP
from tests.autopilot_emulator import AutopilotEmulator

TIMEOUT_S = 30.0


def test_the_page_follows_a_mavlink_collection(tmp_path, monkeypatch, capsys):
    states: list[dict] = []
    readers: list[threading.Thread] = []

    def page(url: str) -> bool:
        """Instead of a browser: a page's WebSocket, reading every state until the end."""
        port = url.rstrip("/").rsplit(":", 1)[1]
        ws = connect(f"ws://127.0.0.1:{port}/ws", origin=url.rstrip("/"), open_timeout=TIMEOUT_S)

        def read() -> None:
            with ws:
                try:
                    while True:
                        states.append(json.loads(ws.recv(timeout=TIMEOUT_S)))
                except (ConnectionClosed, TimeoutError):
                    pass

        readers.append(threading.Thread(target=read, daemon=True))
        readers[-1].start()
        return True

    monkeypatch.setattr(view_collect, "open_in_browser", page)
    out = tmp_path / "s.csv"
    with AutopilotEmulator(personality="ardupilot", seed=0, speedup=SPEEDUP) as emu:
        argv = ["collect", "--mavlink", emu.url, "-o", str(out), "--view"]
        assert cli.main([*argv, "--max-samples", MAX_SAMPLES]) == 0
    readers[0].join(TIMEOUT_S)
    err = capsys.readouterr().err
    assert "magcal collect: live view at http://127.0.0.1:" in err
    live = [s for s in states if not s["done"] and s["compasses"][0]["samples"]]
    assert live, "no state with samples reached the page"
    panel = live[-1]["compasses"][0]
    assert panel["name"].startswith("compass 1 (") and panel["cells"] and panel["points"]
    last = states[-1]
    assert last["done"] and last["stopped"] in ("coverage", "samples")
    assert float(last["result"].get("after_spread_pct", 100)) < 1.0, last["result"].get("error")
    written = read_coverage(out)
    assert last["compasses"][0]["coverage_pct"] == written


def read_coverage(path) -> str:
    from magcal.io.session import read_session

    return read_session(path).meta["coverage"].split()[0]
