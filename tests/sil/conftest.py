"""The SIL device (build/sil/magcal-sil) as a process for the tests.

``sil_binary`` builds it once per session with ``make -s sil``; ``start_sil`` starts one
process (TCP protocol and feed on ephemeral loopback ports, a flash file of the test's) and
parses its start-up lines; every process started is stopped at teardown (SIGTERM, then
SIGKILL). Every wait has a timeout, and a timeout raises.
"""

from __future__ import annotations

import os
import re
import selectors
import signal
import subprocess
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest

from magcal.errors import MagcalError

REPO_ROOT = Path(__file__).resolve().parents[2]
SIL_BINARY = REPO_ROOT / "build" / "sil" / "magcal-sil"

MAKE_TIMEOUT_S = 300.0
# The process prints its three lines within milliseconds; the rest is margin for a loaded
# machine (2 shared cores, tests running in parallel).
STARTUP_TIMEOUT_S = 10.0
STOP_TIMEOUT_S = 5.0

_PROTO_RE = re.compile(r"^magcal-sil: protocol tcp 127\.0\.0\.1:(\d+)$")
_FEED_RE = re.compile(r"^magcal-sil: feed tcp 127\.0\.0\.1:(\d+)$")


class SilError(MagcalError):
    """The SIL process did not start or stop as documented."""


@dataclass
class SilProcess:
    proc: subprocess.Popen
    proto_port: int
    feed_port: int
    lines: list[str]

    def stop(self, timeout_s: float = STOP_TIMEOUT_S) -> int:
        """SIGTERM and wait; SIGKILL if it does not exit in time. Returns the exit status."""
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(timeout=timeout_s)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(timeout=timeout_s)
                raise SilError(f"magcal-sil did not exit within {timeout_s} s of SIGTERM") from None
        return self.proc.returncode

    def stderr_text(self) -> str:
        """What the process wrote to stderr (only once it has exited)."""
        if self.proc.poll() is None or self.proc.stderr is None:
            return ""
        return self.proc.stderr.read().decode(errors="replace")


def read_lines(proc: subprocess.Popen, count: int, timeout_s: float) -> list[str]:
    """The first ``count`` stdout lines of proc; SilError on timeout or early exit."""
    assert proc.stdout is not None
    fd = proc.stdout.fileno()
    os.set_blocking(fd, False)
    buf = b""
    deadline = time.monotonic() + timeout_s
    with selectors.DefaultSelector() as sel:
        sel.register(fd, selectors.EVENT_READ)
        while buf.count(b"\n") < count:
            left = deadline - time.monotonic()
            if left <= 0:
                raise SilError(
                    f"magcal-sil printed {buf!r} within {timeout_s} s; expected {count} lines"
                )
            if not sel.select(timeout=left):
                continue
            chunk = os.read(fd, 4096)
            if not chunk:
                raise SilError(f"magcal-sil exited after printing {buf!r}")
            buf += chunk
    return buf.decode().splitlines()[:count]


@pytest.fixture(scope="session")
def sil_binary() -> Path:
    """build/sil/magcal-sil, built (or brought up to date) with ``make -s sil``."""
    try:
        done = subprocess.run(
            ["make", "-s", "sil"],
            cwd=REPO_ROOT,
            capture_output=True,
            text=True,
            timeout=MAKE_TIMEOUT_S,
        )
    except subprocess.TimeoutExpired:
        pytest.fail(f"make -s sil did not finish within {MAKE_TIMEOUT_S} s")
    if done.returncode != 0:
        pytest.fail(f"make -s sil failed:\n{done.stdout}{done.stderr}")
    return SIL_BINARY


@pytest.fixture
def start_sil(sil_binary: Path) -> Iterator[Callable[..., SilProcess]]:
    """A factory: start_sil(flash_path, *extra_args) -> SilProcess, stopped at teardown."""
    started: list[SilProcess] = []

    def start(flash: Path, *extra: str) -> SilProcess:
        proc = subprocess.Popen(
            [str(sil_binary), "--flash", str(flash), "--tcp", "0", "--feed-tcp", "0", *extra],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
        )
        try:
            lines = read_lines(proc, 3, STARTUP_TIMEOUT_S)
            proto = _PROTO_RE.match(lines[0])
            feed = _FEED_RE.match(lines[1])
            if proto is None or feed is None or lines[2] != "magcal-sil: ready":
                raise SilError(f"unexpected start-up lines from magcal-sil: {lines}")
        except BaseException:
            proc.kill()
            proc.wait(timeout=STOP_TIMEOUT_S)
            raise
        sil = SilProcess(proc, int(proto.group(1)), int(feed.group(1)), lines)
        started.append(sil)
        return sil

    yield start
    for sil in started:
        if sil.proc.poll() is None:
            sil.proc.kill()
            sil.proc.wait(timeout=STOP_TIMEOUT_S)
        for stream in (sil.proc.stdout, sil.proc.stderr):
            if stream is not None:
                stream.close()
