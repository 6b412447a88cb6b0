# SPDX-License-Identifier: Apache-2.0
"""The SIL device (``build/sil/magcal-sil``) as a child process: build, start, stop.

``magcal-sil`` (firmware/port/posix/sil_main.c) is the firmware's protocol endpoint as a
native process; the demo (``make demo``) and the tests talk to it like to a board::

    with start_sil(flash_path) as sil:           # TCP protocol and feed, ephemeral ports
        url = sil.url                            # "socket://127.0.0.1:PORT" for --port
        FeedClient("127.0.0.1", sil.feed_port)   # magcal_evaluation.world: the sensors
    # stopped here: SIGTERM, then SIGKILL if it does not exit in time

On start the process prints three lines (each flushed)::

    magcal-sil: protocol tcp 127.0.0.1:PORT      (or: magcal-sil: protocol pty /dev/pts/N)
    magcal-sil: feed tcp 127.0.0.1:PORT
    magcal-sil: ready

:func:`start_sil` parses them with a timeout. Every wait here has a timeout, and a timeout
raises :class:`SilError` (the process is killed first when it was being started).

Its stderr (one line per refused feed line, and its errors) goes to an unnamed temporary
file, not a pipe: a pipe nobody reads while it runs fills up (64 KB) and would block the
device in fprintf. :meth:`SilProcess.stderr_text` reads it at any time.
"""

from __future__ import annotations

import os
import re
import selectors
import signal
import subprocess
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import IO

from magcal.errors import MagcalError
from magcal_evaluation import REPO_ROOT

#: Where ``make sil`` puts the executable in that checkout.
SIL_BINARY = REPO_ROOT / "build" / "sil" / "magcal-sil"
#: The environment variable naming another magcal-sil executable, used instead of SIL_BINARY
#: when no binary is passed (a build elsewhere, or an installed evaluation package).
SIL_BINARY_ENV = "MAGCAL_SIL_BINARY"

MAKE_TIMEOUT_S = 300.0
# The process prints its three lines within milliseconds; the rest is margin for a loaded
# machine (2 shared cores, tests running in parallel).
STARTUP_TIMEOUT_S = 10.0
STOP_TIMEOUT_S = 5.0

_PROTO_TCP_RE = re.compile(r"^magcal-sil: protocol tcp 127\.0\.0\.1:(\d+)$")
_PROTO_PTY_RE = re.compile(r"^magcal-sil: protocol pty (\S+)$")
_FEED_RE = re.compile(r"^magcal-sil: feed tcp 127\.0\.0\.1:(\d+)$")
_READY = "magcal-sil: ready"


class SilError(MagcalError):
    """The SIL process could not be built, did not start or stop as documented."""


@dataclass
class SilProcess:
    """A running magcal-sil.

    proto_port : the protocol's TCP port (0 when it serves a pty: see ``pty``)
    feed_port : the sensor feed's TCP port
    lines : the start-up lines, as printed
    pty : the pseudo-terminal path with ``--pty``, else ""
    stderr_file : the file its stderr goes to (see :meth:`stderr_text`)
    """

    proc: subprocess.Popen
    proto_port: int
    feed_port: int
    lines: list[str]
    stderr_file: IO[bytes]
    pty: str = ""

    @property
    def url(self) -> str:
        """What ``--port`` takes for this device: ``socket://127.0.0.1:PORT`` or the pty."""
        return self.pty if self.pty else f"socket://127.0.0.1:{self.proto_port}"

    def stop(self, timeout_s: float = STOP_TIMEOUT_S) -> int:
        """SIGTERM and wait; SIGKILL if it does not exit in time (then SilError). Returns the
        exit status (0 for a clean exit on SIGTERM)."""
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(timeout=timeout_s)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(timeout=timeout_s)
                raise SilError(f"magcal-sil did not exit within {timeout_s} s of SIGTERM") from None
        return self.proc.returncode

    def kill(self, timeout_s: float = STOP_TIMEOUT_S) -> None:
        """SIGKILL if still running, wait, and close the pipes (idempotent)."""
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait(timeout=timeout_s)
        self.close_pipes()

    def close_pipes(self) -> None:
        """Close its stdout pipe and the stderr file (stderr_text then raises SilError)."""
        for stream in (self.proc.stdout, self.stderr_file):
            if stream is not None and not stream.closed:
                stream.close()

    def stderr_text(self) -> str:
        """What the process has written to stderr so far (also while it runs)."""
        return _read_file(self.stderr_file)

    def __enter__(self) -> SilProcess:
        return self

    def __exit__(self, *exc: object) -> None:
        try:
            if self.proc.poll() is None:
                self.stop()
        finally:
            self.kill()


def _read_file(f: IO[bytes]) -> str:
    """All of f from its start (f's position is not used: the child writes through its own
    file descriptor); SilError when it was closed."""
    if f.closed:
        raise SilError("magcal-sil's stderr is no longer available (the process was killed)")
    return os.pread(f.fileno(), os.fstat(f.fileno()).st_size, 0).decode(errors="replace")


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


def default_binary() -> Path:
    """The magcal-sil to start when none is given: ``$MAGCAL_SIL_BINARY`` when set, else the
    checkout's build/sil/magcal-sil (:data:`SIL_BINARY`)."""
    named = os.environ.get(SIL_BINARY_ENV, "").strip()
    return Path(named) if named else SIL_BINARY


def build_sil(repo_root: Path = REPO_ROOT, timeout_s: float = MAKE_TIMEOUT_S) -> Path:
    """``make -s sil`` in repo_root (builds or brings build/sil/magcal-sil up to date).
    Returns the executable's path; SilError when repo_root is not a magcal checkout, when make
    fails or takes longer than timeout_s."""
    if not (Path(repo_root) / "mk" / "sil.mk").is_file():
        raise SilError(
            f"building magcal-sil: {repo_root} is not a magcal checkout (no mk/sil.mk): install "
            f"the evaluation editable from a checkout (make setup), or build magcal-sil there "
            f"and name it in ${SIL_BINARY_ENV}"
        )
    try:
        done = subprocess.run(
            ["make", "-s", "sil"], cwd=repo_root, capture_output=True, text=True, timeout=timeout_s
        )
    except subprocess.TimeoutExpired:
        raise SilError(f"make -s sil did not finish within {timeout_s} s") from None
    except OSError as exc:
        raise SilError(f"cannot run make ({exc}); install make and a C compiler") from exc
    if done.returncode != 0:
        raise SilError(f"make -s sil failed:\n{done.stdout}{done.stderr}")
    return repo_root / "build" / "sil" / "magcal-sil"


def start_sil(
    flash: Path | str,
    *extra: str,
    binary: Path | str | None = None,
    pty: bool = False,
    timeout_s: float = STARTUP_TIMEOUT_S,
) -> SilProcess:
    """Start magcal-sil on the flash file ``flash`` and parse its start-up lines.

    The protocol is served on an ephemeral TCP port (or a pty with ``pty=True``), the feed on
    an ephemeral TCP port; ``extra`` are further arguments (e.g. ``"--uid", "c0ffee"``);
    ``binary`` is the executable (default: :func:`default_binary`). SilError (after killing
    the process) when the lines are not as documented within timeout_s; stop it with
    :meth:`SilProcess.stop` or use it as a context manager.
    """
    binary = default_binary() if binary is None else Path(binary)
    if not binary.exists():
        raise SilError(
            f"{binary} does not exist: run `make sil` first (or name the executable in "
            f"${SIL_BINARY_ENV})"
        )
    proto_args = ["--pty"] if pty else ["--tcp", "0"]
    err = tempfile.TemporaryFile(prefix="magcal-sil-stderr-")
    try:
        proc = subprocess.Popen(
            [str(binary), "--flash", str(flash), *proto_args, "--feed-tcp", "0", *extra],
            stdout=subprocess.PIPE,
            stderr=err,
        )
    except BaseException:
        err.close()
        raise
    try:
        lines = read_lines(proc, 3, timeout_s)
        proto = (_PROTO_PTY_RE if pty else _PROTO_TCP_RE).match(lines[0])
        feed = _FEED_RE.match(lines[1])
        if proto is None or feed is None or lines[2] != _READY:
            raise SilError(f"unexpected start-up lines from magcal-sil: {lines}")
    except SilError as exc:
        _kill_started(proc)
        said = _read_file(err).strip()
        err.close()
        raise SilError(f"{exc}; its stderr: {said}" if said else str(exc)) from exc
    except BaseException:
        _kill_started(proc)
        err.close()
        raise
    if pty:
        return SilProcess(proc, 0, int(feed.group(1)), lines, err, pty=proto.group(1))
    return SilProcess(proc, int(proto.group(1)), int(feed.group(1)), lines, err)


def _kill_started(proc: subprocess.Popen) -> None:
    proc.kill()
    proc.wait(timeout=STOP_TIMEOUT_S)
    if proc.stdout is not None:
        proc.stdout.close()
