# SPDX-License-Identifier: Apache-2.0
"""Simulators run in their own process groups and are always stopped: at the end of their
``with`` block, and at interpreter exit for any left running (a test that failed, Ctrl-C)."""

from __future__ import annotations

import atexit
import os
import signal
import subprocess
import time
from pathlib import Path

_running: set[int] = set()


def missing(path: Path, what: str, env_var: str) -> str | None:
    """None when the simulator at ``path`` is there, else why not (a test's skip message)."""
    if path.exists():
        return None
    return f"{what} not found at {path} (set {env_var} or put it beside the checkout)"


def start(*args, **kwargs) -> subprocess.Popen:
    """``subprocess.Popen`` in a new process group, registered for :func:`stop_all`."""
    proc = subprocess.Popen(*args, start_new_session=True, **kwargs)
    _running.add(proc.pid)
    return proc


def stop(proc: subprocess.Popen, term_wait_s: float = 3.0) -> None:
    """Stop ``proc``'s process group: SIGTERM, then SIGKILL after ``term_wait_s``."""
    if proc.poll() is not None:
        _running.discard(proc.pid)
        return
    for sig, wait in ((signal.SIGTERM, term_wait_s), (signal.SIGKILL, 3.0)):
        try:
            os.killpg(proc.pid, sig)
        except ProcessLookupError:
            break
        deadline = time.monotonic() + wait
        while time.monotonic() < deadline:
            try:
                if os.waitpid(proc.pid, os.WNOHANG)[0]:
                    _running.discard(proc.pid)
                    return
            except ChildProcessError:
                _running.discard(proc.pid)
                return
            time.sleep(0.05)
    _running.discard(proc.pid)


@atexit.register
def stop_all() -> None:
    for pid in list(_running):
        try:
            os.killpg(pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
        _running.discard(pid)
