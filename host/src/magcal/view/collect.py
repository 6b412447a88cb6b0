# SPDX-License-Identifier: Apache-2.0
"""The live page of one ``magcal collect``: :class:`CollectView` takes the recorder's
progress reports (call it as the recorder's ``progress``, beside the terminal's printer) and,
once collection has ended, the result (:meth:`CollectView.finish`)."""

from __future__ import annotations

import os
import sys
import webbrowser
from typing import Any

from magcal.device.collect import CollectProgress, CollectResult
from magcal.view.model import CompassView, result_spheres
from magcal.view.server import ViewServer


def open_in_browser(url: str) -> bool:
    """Open ``url`` in the person's graphical browser, if there is one; never fails.

    Not on a Linux machine without a display (ssh, CI), and not in a text browser
    (webbrowser's fallback: lynx, w3m), which would take over the terminal that shows the
    progress. True when a browser was asked to open it."""
    if sys.platform.startswith("linux") and not (
        os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")
    ):
        return False
    try:
        browser = webbrowser.get()
        if type(browser) is webbrowser.GenericBrowser:  # a text browser, in this terminal
            return False
        return bool(browser.open(url, new=2))
    except (webbrowser.Error, OSError):
        return False


class CollectView:
    """The page (:class:`magcal.view.server.ViewServer`) with one panel per compass.

    compasses : the panels' names, in order ("magnetometer", "compass 2 (external)");
        a report goes to the first unless ``progress(report, compass=name)`` names another
    """

    def __init__(self, compasses: list[str], *, title: str) -> None:
        self.title = title
        self.panels = {name: CompassView(name) for name in compasses}
        self._first = compasses[0]
        self.server = ViewServer()
        self.url = self.server.url
        self.server.publish(self._state())

    def __call__(self, progress: CollectProgress, compass: str | None = None) -> None:
        self.panels[compass or self._first].add(progress)
        self.server.publish(self._state())

    def finish(self, result: CollectResult | None) -> None:
        """The last state: collection ended, with the readings before and after a fit;
        then the server stops, once the open pages have it."""
        extra: dict[str, Any] = {"done": True, "stopped": "error"}
        if result is not None:
            extra["stopped"] = result.stopped
            if result.session is not None:
                extra["result"] = result_spheres(result.session.mag)
        self.server.publish(self._state(**extra))
        self.server.close()

    def close(self) -> None:
        """Stop serving at once (idempotent)."""
        self.server.close(0.0)

    def _state(self, **extra: Any) -> dict[str, Any]:
        state: dict[str, Any] = {
            "title": self.title,
            "done": False,
            "compasses": [p.snapshot() for p in self.panels.values()],
            "result": None,
        }
        state.update(extra)
        return state
