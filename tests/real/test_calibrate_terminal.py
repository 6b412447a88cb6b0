# SPDX-License-Identifier: Apache-2.0
"""What ``magcal calibrate`` of a real recording shows a person, run as a person runs it
(host/magcal in a subprocess) on a committed 20 s excerpt of BROAD (evaluation/data/real/):

- under a pseudo-terminal: a progress display redrawn in place that names each step as it
  runs, the ML step's iterations, and warnings wrapped at the terminal's width;
- with stderr a pipe (a log): one line per step, nothing per iteration, at most 10 lines.
"""

from __future__ import annotations

import fcntl
import os
import re
import select
import struct
import subprocess
import termios
import time
from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parents[2]
MAGCAL = REPO_ROOT / "host" / "magcal"
SESSION = REPO_ROOT / "evaluation" / "data" / "real" / "sessions" / "broad21_fast_combined.csv"
TIMEOUT_S = 120.0
COLUMNS, ROWS = 90, 40
STAGES = (
    "calibrate: checking what the session can determine",
    "calibrate: ellipsoid fit (SDP)",
    "calibrate: ML, the paper's model (no time offset)",
    "calibrate: checking the result against its session",
)
MAX_PIPED_STDERR_LINES = 10
_CONTROL = re.compile(r"\x1b\[[0-9;?]*[a-zA-Z]")


def _env() -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if k not in ("CI", "COLUMNS", "LINES")}
    env["TERM"] = "xterm-256color"
    return env


def _run_in_a_terminal(argv: list[str]) -> tuple[int, str]:
    """(exit code, everything written to the terminal) of ``argv`` with a pseudo-terminal of
    COLUMNS x ROWS as its stdin, stdout and stderr."""
    master, slave = os.openpty()
    fcntl.ioctl(slave, termios.TIOCSWINSZ, struct.pack("HHHH", ROWS, COLUMNS, 0, 0))
    try:
        proc = subprocess.Popen(
            argv, stdin=slave, stdout=slave, stderr=slave, env=_env(), close_fds=True
        )
    finally:
        os.close(slave)
    written = b""
    deadline = time.monotonic() + TIMEOUT_S
    try:
        while time.monotonic() < deadline:
            if select.select([master], [], [], 0.2)[0]:
                try:
                    chunk = os.read(master, 65536)
                except OSError:  # EIO: every writer has closed the terminal
                    break
                if not chunk:
                    break
                written += chunk
            elif proc.poll() is not None:
                break
        code = proc.wait(max(1.0, deadline - time.monotonic()))
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        os.close(master)
    return code, written.decode("utf-8", errors="replace")


@pytest.fixture(scope="module")
def terminal(tmp_path_factory) -> str:
    out = tmp_path_factory.mktemp("tty") / "result.json"
    code, written = _run_in_a_terminal([str(MAGCAL), "calibrate", str(SESSION), "-o", str(out)])
    assert code == 0, written[-3000:]
    return written


def test_a_terminal_shows_each_step_by_name_redrawn_in_place(terminal):
    screen = _CONTROL.sub("", terminal)
    positions = [screen.find(stage) for stage in STAGES]
    assert all(p >= 0 for p in positions), screen[-3000:]
    assert positions == sorted(positions)  # in the order they run
    # the ML step's iterations are shown as they run, on the line the step is drawn on
    assert re.search(r"calibrate: ML, [^\r\n]*: iteration \d+, cost ", screen)
    # drawn in place (rich's Live: cursor up and erase line), not one line per update
    assert re.search(r"\x1b\[\d*A|\x1b\[2K", terminal)
    iterations = len(re.findall(r"iteration \d+, cost", screen))
    assert iterations > 5 and screen.count("\n") < iterations


def test_a_terminal_gets_its_warnings_wrapped_at_its_width(terminal):
    lines = re.split(r"\r?\n|\r", _CONTROL.sub("", terminal))
    warnings = [i for i, line in enumerate(lines) if line.startswith("warning: ")]
    assert warnings, "the excerpt has warnings (little tilt, a poorly determined rotation)"
    assert all(len(line) <= COLUMNS for line in lines)
    # a warning longer than the terminal continues on indented lines, words whole
    long = [i for i in warnings if lines[i + 1].startswith(" " * len("warning: "))]
    assert long


def test_a_pipe_gets_one_line_per_step_and_nothing_per_iteration(tmp_path):
    out = tmp_path / "result.json"
    env = _env()
    done = subprocess.run(
        [str(MAGCAL), "calibrate", str(SESSION), "-o", str(out)],
        capture_output=True,
        text=True,
        env=env,
        timeout=TIMEOUT_S,
        check=False,
    )
    assert done.returncode == 0, done.stderr
    lines = done.stderr.splitlines()
    assert len(lines) <= MAX_PIPED_STDERR_LINES, done.stderr
    assert all(stage in lines for stage in STAGES)
    assert "iteration" not in done.stderr and "\x1b" not in done.stderr and "\r" not in done.stderr
    # a log's warnings stay whole lines, for a reader or a grep
    assert any(len(w) > COLUMNS for w in done.stdout.splitlines() if w.startswith("warning: "))
