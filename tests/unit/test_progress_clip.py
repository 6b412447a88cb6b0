"""collect's progress line on a terminal is clipped to the terminal's width, so that it can be
rewritten in place (a wrapped line leaves its first part behind on every update); in a log
(not a terminal) every line is written whole, one per second as before.
"""

from __future__ import annotations

import fcntl
import io
import os
import struct
import termios

import pytest

from magcal.commands import common
from magcal.commands.collect import progress_printer
from magcal.commands.common import CLIPPED_MARK, clip_line, terminal_columns
from magcal.device.collect import CollectProgress

HINT = "norm spread 0.41 % (settling); point the sensor's -x+y axis along the field"


def _progress(samples: int, elapsed_s: float, hint: str = HINT) -> CollectProgress:
    return CollectProgress(samples, elapsed_s, 1000.0, 0, 0.5, hint)


class _Terminal(io.StringIO):
    def isatty(self) -> bool:
        return True


def _updates(text: str) -> list[str]:
    """The lines a \\r-rewriting printer wrote, without the erase-to-end-of-line."""
    assert text.startswith("\r")
    return [u.removesuffix("\x1b[K") for u in text[1:].split("\r")]


def test_clip_line_leaves_the_last_column_free_and_marks_the_cut():
    line = "x" * 50
    assert clip_line(line, 51) == line  # fits in 50 of 51 columns
    assert clip_line(line, 50) == "x" * (49 - len(CLIPPED_MARK)) + CLIPPED_MARK
    assert len(clip_line(line, 50)) == 49
    assert clip_line(line, 4) == "xxx"  # too narrow for the mark: cut only
    assert clip_line(line, 1) == "x" and clip_line(line, 0) == "x"
    assert clip_line("", 10) == ""


@pytest.mark.parametrize("columns", [40, 80, 132])
def test_a_terminal_gets_each_update_within_its_width(monkeypatch, columns):
    monkeypatch.setenv("COLUMNS", str(columns))
    stream = _Terminal()
    show = progress_printer(stream)
    for i in range(5):
        show(_progress(100 * i, 0.25 * i))
    show.done()
    text = stream.getvalue()
    assert text.endswith("\n") and text.count("\n") == 1
    updates = _updates(text[:-1])
    assert len(updates) == 5
    full = [
        f"{100 * i:7d} samples  {1000.0:6.1f}/s  dropped 0  coverage  50.0 %  {HINT}"
        for i in range(5)
    ]
    for update, line in zip(updates, full, strict=True):
        assert len(update) <= columns - 1
        if len(line) <= columns - 1:
            assert update == line
        else:
            assert update.endswith(CLIPPED_MARK) and line.startswith(update[: -len(CLIPPED_MARK)])
    assert len(full[0]) > 80  # the 40 and 80 columns cases do clip


def test_a_log_gets_whole_lines_once_a_second(monkeypatch):
    monkeypatch.setenv("COLUMNS", "40")
    stream = io.StringIO()  # not a terminal
    show = progress_printer(stream)
    for i in range(9):
        show(_progress(100 * i, 0.25 * i))
    show.done()
    lines = stream.getvalue().splitlines()
    assert "\r" not in stream.getvalue() and "\x1b" not in stream.getvalue()
    assert [line.split()[0] for line in lines] == ["0", "400", "800"]  # at 0, 1 and 2 s
    assert all(line.endswith(HINT) for line in lines)


def test_terminal_columns_asks_the_stream_own_terminal(monkeypatch):
    monkeypatch.delenv("COLUMNS", raising=False)
    master, slave = os.openpty()
    try:
        fcntl.ioctl(slave, termios.TIOCSWINSZ, struct.pack("HHHH", 24, 57, 0, 0))
        with open(slave, "w", closefd=False) as tty:
            assert terminal_columns(tty) == 57
            show = progress_printer(tty)
            show(_progress(1, 0.0))
            tty.flush()
            written = os.read(master, 4096).decode()
        assert len(_updates(written.replace("\r\n", "\n"))[0]) == 56
    finally:
        os.close(master)
        os.close(slave)


def test_terminal_columns_prefers_columns_then_falls_back_to_shutil(monkeypatch):
    monkeypatch.setenv("COLUMNS", "77")
    assert terminal_columns(io.StringIO()) == 77
    monkeypatch.delenv("COLUMNS")
    monkeypatch.setattr(common.shutil, "get_terminal_size", lambda: os.terminal_size((91, 30)))
    assert terminal_columns(io.StringIO()) == 91  # no fileno: not a terminal of its own


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
