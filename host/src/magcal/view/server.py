# SPDX-License-Identifier: Apache-2.0
"""The live page's server: 127.0.0.1 only, a free port the system picks, one WebSocket.

:class:`ViewServer` serves the page's files (``static/``, read from the installed package)
over plain HTTP and, on ``/ws``, sends the page the whole state as JSON each time it changes
(:meth:`ViewServer.publish`): a page opened late, or reloaded, gets everything at once, and a
slow page skips states instead of queueing them. The server runs on threads of its own
(websockets' synchronous server: one to accept, one per connection), so the recorder's loop
never waits for a page.

Only pages of this server may open the WebSocket: its Origin must be the server's own address
(a page of another site that the browser shows meanwhile may not read the collection).
"""

from __future__ import annotations

import json
import logging
import threading
import time
from importlib import resources
from typing import Any

from magcal.errors import MagcalError

log = logging.getLogger(__name__)

HOST = "127.0.0.1"
#: The page's files and their types.
STATIC_FILES = {
    "/": ("index.html", "text/html; charset=utf-8"),
    "/index.html": ("index.html", "text/html; charset=utf-8"),
    "/view.js": ("view.js", "text/javascript; charset=utf-8"),
    "/view.css": ("view.css", "text/css; charset=utf-8"),
}
WEBSOCKET_PATH = "/ws"
#: A connection waits this long at most for a new state before checking whether the server
#: is closing, s.
WAIT_STATE_S = 0.5
#: How long :meth:`ViewServer.close` waits for the open pages to have the last state, s.
FINAL_STATE_TIMEOUT_S = 5.0
#: How long the server's threads may take to stop, s.
SHUTDOWN_TIMEOUT_S = 5.0


class ViewError(MagcalError):
    """The live page could not be served."""


class ViewServer:
    """The page on ``url`` (see the module docstring). ``publish(state)`` a new state (a
    JSON-ready dictionary); ``close()`` once the last state is published. A context manager.
    """

    def __init__(self) -> None:
        from websockets.sync.server import serve

        self._files = {path: _read_static(name) for path, (name, _) in STATIC_FILES.items()}
        self._cond = threading.Condition()
        self._state = b"{}"
        self._version = 0
        self._closing = False
        self._sent: dict[int, int] = {}  # connection id -> version sent
        try:
            self._server = serve(
                self._connection, HOST, 0, process_request=self._request, logger=log
            )
        except OSError as exc:
            raise ViewError(f"collect --view: cannot listen on {HOST} ({exc})") from exc
        self.port = int(self._server.socket.getsockname()[1])
        self.url = f"http://{HOST}:{self.port}/"
        self._origin = f"http://{HOST}:{self.port}"
        self._thread = threading.Thread(
            target=self._server.serve_forever, name="magcal-view", daemon=True
        )
        self._thread.start()

    # ------------------------------------------------------------------ the recorder's side
    def publish(self, state: dict[str, Any]) -> None:
        """Send ``state`` to every open page (and to every page opened later)."""
        data = json.dumps(state, separators=(",", ":")).encode()
        with self._cond:
            self._state = data
            self._version += 1
            self._cond.notify_all()

    def close(self, final_timeout_s: float = FINAL_STATE_TIMEOUT_S) -> None:
        """Stop serving, once every open page has the last state (at most
        ``final_timeout_s``). Idempotent."""
        deadline = time.monotonic() + final_timeout_s
        with self._cond:
            if self._closing:
                return
            self._cond.wait_for(
                lambda: all(v == self._version for v in self._sent.values()),
                timeout=max(0.0, deadline - time.monotonic()),
            )
            self._closing = True
            self._cond.notify_all()
        self._server.shutdown()
        self._thread.join(SHUTDOWN_TIMEOUT_S)

    def __enter__(self) -> ViewServer:
        return self

    def __exit__(self, *exc) -> None:
        self.close(0.0 if exc[0] is not None else FINAL_STATE_TIMEOUT_S)

    # ------------------------------------------------------------------ the page's side
    def _request(self, connection, request):
        """Files over plain HTTP; the WebSocket handshake only from this server's pages."""
        path = request.path.split("?", 1)[0]
        if path == WEBSOCKET_PATH:
            if request.headers.get("Origin") != self._origin:
                return connection.respond(403, "only this server's page may connect\n")
            return None  # go on with the handshake
        if path not in self._files:
            return connection.respond(404, "not found\n")
        response = connection.respond(200, "")
        del response.headers["Content-Type"]
        del response.headers["Content-Length"]
        body = self._files[path]
        response.headers["Content-Type"] = STATIC_FILES[path][1]
        response.headers["Content-Length"] = str(len(body))
        response.headers["Cache-Control"] = "no-store"
        response.body = body
        return response

    def _connection(self, websocket) -> None:
        """Send the state each time it changes, until the server closes or the page goes."""
        from websockets.exceptions import ConnectionClosed

        key = id(websocket)
        sent = 0
        try:
            while True:
                with self._cond:
                    self._sent[key] = sent
                    self._cond.notify_all()
                    self._cond.wait_for(
                        lambda sent=sent: self._version != sent or self._closing,
                        timeout=WAIT_STATE_S,
                    )
                    if self._closing:
                        break
                    if self._version == sent:
                        continue
                    data, version = self._state, self._version
                websocket.send(data.decode())
                sent = version
        except ConnectionClosed:
            pass
        finally:
            with self._cond:
                self._sent.pop(key, None)
                self._cond.notify_all()


def _read_static(name: str) -> bytes:
    try:
        return resources.files("magcal.view").joinpath("static", name).read_bytes()
    except OSError as exc:
        raise ViewError(
            f"collect --view: the page's file {name} is missing from the installed package "
            f"({exc}): reinstall magcal"
        ) from exc
