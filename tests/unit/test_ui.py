# SPDX-License-Identifier: Apache-2.0
"""The command line's one way of showing progress (magcal.ui, on rich): on a terminal, lines
redrawn in place that never wrap; in a log (not a terminal, TERM=dumb, CI), whole plain lines,
rate-limited as each command asks, the last state always written."""

from __future__ import annotations

import fcntl
import io
import os
import re
import select
import struct
import termios

import pytest

from magcal import ui
from magcal.commands.calibrate import CalibrationProgress
from magcal.commands.collect import progress_printer
from magcal.commands.import_log import progress_printer as import_printer
from magcal.commands.report import progress_printer as report_printer
from magcal.device.collect import CollectProgress

HINT = "norm spread 0.41 % (settling); point the sensor's -x+y axis along the field"
_ANSI = re.compile(r"\x1b\[[0-9;?]*[a-zA-Z]")


def _progress(samples: int, elapsed_s: float, hint: str = HINT) -> CollectProgress:
    return CollectProgress(samples, elapsed_s, 1000.0, 0, 0.5, hint)


def _line(samples: int, hint: str = HINT) -> str:
    return f"{samples:7d} samples  {1000.0:6.1f}/s  dropped 0  coverage  50.0 %  {hint}"


class _Terminal(io.StringIO):
    def isatty(self) -> bool:
        return True


def _screen_lines(text: str) -> list[str]:
    """What a terminal shows line by line: control sequences removed, split at \\r and \\n."""
    return [part for part in re.split(r"[\r\n]", _ANSI.sub("", text)) if part]


@pytest.fixture(autouse=True)
def _a_person_watches(monkeypatch):
    monkeypatch.delenv("CI", raising=False)
    monkeypatch.setenv("TERM", "xterm-256color")


@pytest.mark.parametrize("columns", [40, 80, 132])
def test_the_collect_line_on_a_terminal_never_wraps(monkeypatch, columns):
    monkeypatch.setenv("COLUMNS", str(columns))
    stream = _Terminal()
    show = progress_printer(stream)
    for i in range(5):
        show(_progress(100 * i, 0.25 * i))
    show.done()
    show.done()
    text = stream.getvalue()
    assert _ANSI.sub("", text).endswith("\n")
    shown = _screen_lines(text)
    assert all(len(line) <= columns for line in shown)
    # each state, and the last once more as the display stops
    assert [line.split()[0] for line in shown] == ["0", "100", "200", "300", "400", "400"]
    full = _line(400)
    assert len(full) > 80  # the 40 and 80 columns cases do cut
    if len(full) <= columns:
        assert full in shown
    else:
        assert all(line.endswith("…") for line in shown)


def test_the_collect_line_fits_the_streams_own_terminal(monkeypatch):
    monkeypatch.delenv("COLUMNS", raising=False)
    master, slave = os.openpty()
    try:
        fcntl.ioctl(slave, termios.TIOCSWINSZ, struct.pack("HHHH", 24, 57, 0, 0))
        with open(slave, "w", closefd=False) as tty:
            assert ui.terminal_columns(tty) == 57
            show = progress_printer(tty)
            show(_progress(1, 0.0))
            show.done()
            tty.flush()
            written = b""
            while select.select([master], [], [], 0.2)[0]:  # all of it, not the first chunk
                written += os.read(master, 8192)
        written = written.decode()
        shown = _screen_lines(written)
        assert shown and all(len(line) <= 57 for line in shown)
        assert shown[-1].endswith("…")
    finally:
        os.close(master)
        os.close(slave)


def test_terminal_columns_prefers_columns_then_the_streams_terminal(monkeypatch):
    monkeypatch.setenv("COLUMNS", "77")
    assert ui.terminal_columns(io.StringIO()) == 77
    monkeypatch.delenv("COLUMNS")
    assert ui.terminal_columns(io.StringIO()) is None  # no terminal of its own: rich asks


def test_a_log_gets_whole_lines_once_a_second(monkeypatch):
    monkeypatch.setenv("COLUMNS", "40")
    stream = io.StringIO()  # not a terminal
    show = progress_printer(stream)
    for i in range(9):
        show(_progress(100 * i, 0.25 * i))
    show.done()
    lines = stream.getvalue().splitlines()
    assert "\r" not in stream.getvalue() and "\x1b" not in stream.getvalue()
    assert lines == [_line(0), _line(400), _line(800)]  # at 0, 1 and 2 s, whole


@pytest.mark.parametrize("env", [{"CI": "true"}, {"TERM": "dumb"}])
def test_a_ci_log_or_a_dumb_terminal_gets_plain_lines(monkeypatch, env):
    for key, value in env.items():
        monkeypatch.setenv(key, value)
    stream = _Terminal()
    assert not ui.is_live(stream)
    show = progress_printer(stream)
    for i in range(5):
        show(_progress(100 * i, 0.25 * i))
    show.done()
    assert stream.getvalue().splitlines() == [_line(0), _line(400)]


def test_a_log_gets_the_last_update_even_within_the_second():
    """The last state is the one that may say "ok to stop": done() writes it if the
    once-a-second rule held it back, and nothing twice."""
    stream = io.StringIO()
    show = progress_printer(stream)
    show(_progress(0, 0.0))
    show(_progress(50, 0.5, "ok to stop: coverage 92 %, norm spread 0.4 %"))
    show.done()
    show.done()
    lines = stream.getvalue().splitlines()
    assert [line.split()[0] for line in lines] == ["0", "50"]
    assert lines[-1].endswith("ok to stop: coverage 92 %, norm spread 0.4 %")


def _calibrate(progress: CalibrationProgress) -> None:
    """Two steps, the second with three ML iterations, as calibrate reports them."""
    progress.stage("ellipsoid fit (SDP)")
    progress.stage("ML, the paper's model (no time offset)")
    for k in range(1, 4):
        progress(k, 1.0 / k, 1e-3)
    progress.done()


def test_calibrate_logs_one_line_per_step_and_nothing_per_iteration():
    stream = io.StringIO()
    _calibrate(CalibrationProgress(stream))
    assert stream.getvalue().splitlines() == [
        "calibrate: ellipsoid fit (SDP)",
        "calibrate: ML, the paper's model (no time offset)",
    ]


def test_calibrate_quiet_shows_nothing(monkeypatch):
    for stream in (io.StringIO(), _Terminal()):
        _calibrate(CalibrationProgress(stream, quiet=True))
        assert stream.getvalue() == ""


def test_calibrate_on_a_terminal_is_one_line_with_the_step(monkeypatch):
    monkeypatch.setenv("COLUMNS", "200")
    stream = _Terminal()
    _calibrate(CalibrationProgress(stream))
    shown = _screen_lines(stream.getvalue())
    assert shown[-1] == (
        "calibrate: ML, the paper's model (no time offset): iteration 3, cost 0.333, "
        "predicted decrease 1.0e-03"
    )


def test_import_logs_every_quarter():
    stream = io.StringIO()
    show = import_printer("reading flight.bin", stream)
    for k in range(0, 101, 5):
        show(k / 100)
    show.done()
    assert stream.getvalue().splitlines() == [
        f"reading flight.bin: {p} %" for p in (0, 25, 50, 75, 100)
    ]


def test_report_logs_the_first_and_last_pass_then_the_figures():
    stream = io.StringIO()
    show = report_printer(stream)
    for k in range(1, 69):
        show("hessian", k, 68)
    show("drawing the figures", 0, 1)
    show.done()
    assert stream.getvalue().splitlines() == [
        "report: Hessian of the ML cost, gradient pass 1/68",
        "report: Hessian of the ML cost, gradient pass 68/68",
        "report: drawing the figures",
    ]


def test_a_progress_bar_on_a_terminal_shows_count_and_rate(monkeypatch):
    """A study runner's use: N runs, some resumed, a note, a message above the bar."""
    monkeypatch.setenv("COLUMNS", "100")
    stream = _Terminal()
    with ui.ProgressBar("study", 10, stream, completed=4, unit="runs") as bar:
        for _ in range(6):
            bar.advance(note="1 failed")
        bar.message("interrupted: finishing 2 runs in progress")
    shown = _screen_lines(stream.getvalue())
    assert all(len(line) <= 100 for line in shown)
    assert "interrupted: finishing 2 runs in progress" in shown
    assert shown[-1].startswith("study") and "10/10" in shown[-1] and "1 failed" in shown[-1]


def test_a_progress_bar_in_a_log_counts_resumed_work():
    stream = io.StringIO()
    with ui.ProgressBar("study", 8, stream, completed=2, log_step_pct=50) as bar:
        for _ in range(6):
            bar.advance()
    assert stream.getvalue().splitlines() == ["study: 3/8", "study: 4/8", "study: 8/8"]


def test_a_table_is_plain_lines_in_a_log_and_a_table_on_a_terminal(monkeypatch):
    d = "[[1 0]\n" + " " * 13 + "[0 1]]"  # as np.array2string(..., prefix=12 spaces)
    rows = [("method", "ml"), ("D", d), ("gyro bias", "[0 0] °/s")]
    log = io.StringIO()
    ui.print_table(rows, log)
    assert log.getvalue() == (
        "method      ml\nD           [[1 0]\n             [0 1]]\ngyro bias   [0 0] °/s\n"
    )
    monkeypatch.setenv("COLUMNS", "60")
    terminal = _Terminal()
    ui.print_table(rows, terminal)
    shown = _screen_lines(terminal.getvalue())
    assert [line.split()[0] for line in shown] == ["method", "D", "[0", "gyro"]
    assert shown[2].strip() == "[0 1]]"
    assert shown[2].index("[0") == shown[1].index("[[") + 1  # in its column, not the log's


def test_refusal_is_one_paragraph_naming_the_command():
    assert ui.refusal("flash", "flash: no\n  link") == "magcal flash: no link"
    assert ui.refusal("flash", ValueError()) == "magcal flash: ValueError"
