# SPDX-License-Identifier: Apache-2.0
"""What the command line shows a person: exit codes, refusals, messages on stderr, progress and
result tables.

One implementation for every command, on ``rich``: on a terminal a progress bar with rate and
time left (:class:`ProgressBar`), a status line rewritten in place and cut to the terminal's
width, never wrapped (:class:`StatusLine`), and tables (:func:`print_table`). When the output is
not a terminal a person watches (not a terminal, ``TERM=dumb``, or a CI log: ``CI`` set) the
same things are plain whole lines, written no more often than the caller asks, so that logs stay
readable and tests deterministic (:func:`is_live`).

This module is a leaf: it imports nothing from :mod:`magcal.commands` or :mod:`magcal.cli`, so
any command, and any tool beside the product (a study runner), can use it. ``rich`` is imported
only when something is drawn on a terminal.
"""

from __future__ import annotations

import os
import sys
import time
from collections.abc import Callable, Sequence
from typing import TextIO

#: The check ran and the outcome is not good enough (verify's norm spread, a mismatch).
EXIT_FAILED = 1
#: A refusal or an error: one paragraph on stderr (:func:`refusal`).
EXIT_ERROR = 2
#: A flash to an autopilot wrote the calibration (every value confirmed, in force) but left
#: out a misalignment costing at least 0.5° of heading: no custom rotation (the firmware has
#: none, or --no-custom-rotation) and no enumerated one within its uncertainty. A warning on
#: stderr names the cost.
EXIT_MISALIGNMENT_LEFT_OUT = 3
#: Exit status after Ctrl-C (128 + SIGINT, as a shell reports it).
EXIT_INTERRUPTED = 130

#: Redraws a second of a live progress display on a terminal.
REFRESH_PER_S = 10

#: Set by ``-q`` (:func:`set_quiet`): progress displays show nothing; messages, warnings,
#: results and errors still do.
_quiet = False


def set_quiet(quiet: bool) -> None:
    """Silence (or restore) every progress display made from now on."""
    global _quiet
    _quiet = bool(quiet)


def refusal(command: str, exc: BaseException | str) -> str:
    """The one-paragraph stderr message ``magcal <command>: ...`` for ``exc``.

    Line breaks are joined into one line, and the prefix is not doubled when the message
    already names the command ("simulate: unknown preset ...").
    """
    text = " ".join(line.strip() for line in str(exc).splitlines() if line.strip())
    text = text or type(exc).__name__
    if text.startswith(f"magcal {command}:"):
        return text
    if text.startswith(f"{command}:"):
        return f"magcal {text}"
    return f"magcal {command}: {text}"


def say(command: str, text: str, stream: TextIO | None = None) -> None:
    """``magcal <command>: text`` on stderr (or ``stream``), flushed at once."""
    print(f"magcal {command}: {text}", file=stream or sys.stderr, flush=True)


def is_live(stream: TextIO) -> bool:
    """True when ``stream`` is a terminal a person watches: it is a terminal, ``TERM`` is not
    ``dumb``, and ``CI`` is not set (a CI runner may give a terminal to a log)."""
    isatty = getattr(stream, "isatty", None)
    try:
        tty = bool(isatty and isatty())
    except ValueError:  # closed
        tty = False
    return tty and os.environ.get("TERM") != "dumb" and not os.environ.get("CI")


def terminal_columns(stream: TextIO) -> int | None:
    """The width of the terminal ``stream`` writes to: ``COLUMNS`` when set, else the stream's
    own terminal; None when neither says (rich then asks the standard streams)."""
    if os.environ.get("COLUMNS", "").isdigit() and int(os.environ["COLUMNS"]) > 0:
        return int(os.environ["COLUMNS"])
    try:
        columns = os.get_terminal_size(stream.fileno()).columns
    except (AttributeError, ValueError, OSError):  # no fileno, closed, or not a terminal
        return None
    return columns if columns > 0 else None  # 0: a pseudo-terminal whose size was never set


def _console(stream: TextIO):
    from rich.console import Console

    return Console(
        file=stream,
        force_terminal=True,
        width=terminal_columns(stream),
        highlight=False,
        markup=False,
        emoji=False,
    )


def print_wrapped(text: str, stream: TextIO | None = None, *, indent: int | None = None) -> None:
    """``text`` (a warning, a note) on stdout or ``stream``: on a terminal wrapped at its width
    between words, the continuation lines indented by ``indent`` spaces (default: to the
    text after its first ": ", so "warning: ..." reads as one block); in a log one whole line,
    which a reader or a grep takes whole."""
    stream = stream or sys.stdout
    if not is_live(stream):
        print(text, file=stream, flush=True)
        return
    import textwrap

    width = terminal_columns(stream) or _console(stream).width
    if indent is None:
        head = text.find(": ")
        indent = head + 2 if 0 <= head < width // 3 else 2
    lines = textwrap.wrap(
        text,
        width=max(width, indent + 20),
        subsequent_indent=" " * indent,
        break_long_words=False,
        break_on_hyphens=False,
    )
    print("\n".join(lines), file=stream, flush=True)


def write_line(text: str, stream: TextIO | None = None) -> None:
    """``text`` as a whole line on stderr (or ``stream``), flushed at once."""
    stream = stream or sys.stderr
    stream.write(text + "\n")
    stream.flush()


class _Display:
    """What :class:`StatusLine` and :class:`ProgressBar` share: the stream, whether it is live,
    the rich display drawn on it (None until the first update, and always in a log), messages
    above it, closing, and use as a context manager."""

    def __init__(self, stream: TextIO | None) -> None:
        self.stream = stream or sys.stderr
        self.live = is_live(self.stream)
        self.quiet = _quiet
        self._display = None  # rich Live or Progress, both with .console and .stop()

    def message(self, text: str) -> None:
        """``text`` on a line of its own, above the live display on a terminal."""
        if self._display is not None:
            self._display.console.print(text, soft_wrap=True)
        else:
            write_line(text, self.stream)

    def close(self) -> None:
        if self._display is not None:
            self._display.stop()
            self._display = None
        self._closed()

    def _closed(self) -> None:
        """What a subclass writes once the display is gone."""

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class StatusLine(_Display):
    """One line of status whose total is not known (an optimizer's iterations, a recording).

    On a terminal: the text, redrawn in place, cut with "…" at the terminal's width (a wrapped
    line could not be redrawn). Otherwise whole lines: by default one per
    ``every_s`` seconds of the caller's clock (``update(text, t_s)``; the first always), or
    as the caller says (``update(text, log=...)``); with ``last=True`` the last text, if held
    back, is written by :meth:`close` (the last state may be the one that matters: "ok to
    stop"). Use it as a context manager, or call :meth:`close` (idempotent).
    """

    def __init__(
        self, stream: TextIO | None = None, *, every_s: float = 1.0, last: bool = True
    ) -> None:
        super().__init__(stream)
        self._every_s = every_s
        self._last = last
        self._next_s: float | None = None
        self._held: str | None = None
        self._console = None

    def update(self, text: str, t_s: float | None = None, *, log: bool | None = None) -> None:
        """Show ``text``. In a log it is written when ``log`` is True, or, ``log`` not given,
        when ``t_s`` (s, the caller's clock; now when None) is ``every_s`` past the last."""
        if self.quiet:
            return
        if self.live:
            self._show(text)
            return
        if log is None:
            now = time.monotonic() if t_s is None else t_s
            log = self._next_s is None or now >= self._next_s
            if log:
                self._next_s = now + self._every_s
        if log:
            self._held = None
            write_line(text, self.stream)
        elif self._last:
            self._held = text

    def columns(self) -> int | None:
        """The width a line is cut at: the terminal's on a terminal; None in a log, where
        lines are written whole."""
        if not self.live:
            return None
        width = terminal_columns(self.stream)
        if width is not None:
            return width
        if self._console is None:
            self._console = _console(self.stream)
        return self._console.width

    def _show(self, text: str) -> None:
        from rich.live import Live

        if self._display is None:
            if self._console is None:
                self._console = _console(self.stream)
            # Drawn at each update, not by a timer: every state the caller reports is shown
            # (callers report a few times a second), and the output is deterministic.
            self._display = Live(
                _status_renderable(text),
                console=self._console,
                auto_refresh=False,
                redirect_stdout=False,
                redirect_stderr=False,
            )
            self._display.start(refresh=True)
        else:
            width = terminal_columns(self.stream)
            if width is not None:  # follow a resized terminal
                self._console.width = width
            self._display.update(_status_renderable(text), refresh=True)

    def _closed(self) -> None:
        if self._held is not None:
            write_line(self._held, self.stream)
            self._held = None


def _status_renderable(text: str):
    """``text`` on one line: cut with "…" at the terminal's width, never wrapped."""
    from rich.text import Text

    return Text(text, no_wrap=True, overflow="ellipsis", end="")


class ProgressBar(_Display):
    """Work of known size: ``completed`` of ``total`` (runs, gradient passes, percent).

    On a terminal: the label, a bar, completed/total (a percentage when ``unit`` is "%"), the
    rate (``unit`` per second), the time left, and an optional note (``update(..., note="2
    failed")``). Otherwise one whole
    line, ``log_line(completed, total)`` (default "label: completed/total"), at the first
    update, each time the percentage crosses a multiple of ``log_step_pct``, and at the end.
    ``completed`` may start above zero (work resumed): the rate counts only what is done here.
    Use it as a context manager, or call :meth:`close` (idempotent).
    """

    def __init__(
        self,
        label: str,
        total: int,
        stream: TextIO | None = None,
        *,
        completed: int = 0,
        unit: str = "",
        log_step_pct: float = 25.0,
        log_line: Callable[[int, int], str] | None = None,
    ) -> None:
        super().__init__(stream)
        self.label = label
        self.total = total
        self.completed = completed
        self._unit = unit
        self._step = log_step_pct
        self._log_line = log_line or (lambda done, total: f"{label}: {done}/{total}")
        self._logged_step: int | None = None
        self._task = None

    def update(self, completed: int, total: int | None = None, *, note: str | None = None) -> None:
        if total is not None:
            self.total = total
        self.completed = completed
        if self.quiet:
            return
        if self.live:
            self._draw(note)
            return
        step = self._step_of(completed)
        if self._logged_step is None or step != self._logged_step:
            self._logged_step = step
            write_line(self._log_line(completed, self.total), self.stream)

    def advance(self, by: int = 1, *, note: str | None = None) -> None:
        self.update(self.completed + by, note=note)

    def _step_of(self, completed: int) -> int:
        if self.total <= 0:
            return 0
        pct = 100.0 * min(max(completed / self.total, 0.0), 1.0)
        return int(pct // self._step) if self._step > 0 else int(pct)

    def _draw(self, note: str | None) -> None:
        if self._display is None:
            self._display = _rich_progress(_console(self.stream), self._unit)
            self._display.start()
            self._task = self._display.add_task(
                self.label, total=self.total, completed=self.completed, note=note or ""
            )
            return
        fields = {} if note is None else {"note": note}
        self._display.update(self._task, completed=self.completed, total=self.total, **fields)


def _rich_progress(console, unit: str):
    from rich.progress import (
        BarColumn,
        MofNCompleteColumn,
        Progress,
        ProgressColumn,
        TaskProgressColumn,
        TextColumn,
        TimeRemainingColumn,
    )
    from rich.table import Column
    from rich.text import Text

    class RateColumn(ProgressColumn):
        """The task's recent rate, in ``unit`` per second."""

        def render(self, task) -> Text:
            speed = task.speed
            return Text("" if speed is None else f"{speed:.3g} {unit}/s".replace(" /s", "/s"))

    def fixed() -> Column:
        return Column(no_wrap=True)

    # One line at any width: the label gives way first (cut with "…"), the figures never wrap.
    return Progress(
        TextColumn(
            "{task.description}", table_column=Column(no_wrap=True, overflow="ellipsis", ratio=1)
        ),
        BarColumn(bar_width=20, table_column=fixed()),
        (TaskProgressColumn if unit == "%" else MofNCompleteColumn)(table_column=fixed()),
        RateColumn(table_column=fixed()),
        TimeRemainingColumn(table_column=fixed()),
        TextColumn("{task.fields[note]}", table_column=fixed()),
        console=console,
        refresh_per_second=REFRESH_PER_S,
        redirect_stdout=False,
        redirect_stderr=False,
    )


#: Width of the label column of a plain table (:func:`print_table`).
LABEL_WIDTH = 11


def print_table(
    rows: Sequence[tuple[str, str]], out: TextIO | None = None, *, title: str | None = None
) -> None:
    """Label-value rows: a table on a terminal; plain ``label value`` lines otherwise, the
    labels padded to LABEL_WIDTH. A value of several lines has its continuation lines indented
    for the plain layout (LABEL_WIDTH + 1 spaces); the table removes that indent."""
    out = out or sys.stdout
    if not is_live(out):
        for label, value in rows:
            print(f"{label:<{LABEL_WIDTH}} {value}", file=out)
        return
    from rich.table import Table

    indent = " " * (LABEL_WIDTH + 1)
    table = Table(title=title, show_header=False, box=None, pad_edge=False)
    table.add_column(style="bold", no_wrap=True)
    table.add_column()
    for label, value in rows:
        lines = value.split("\n")
        lines[1:] = [line.removeprefix(indent) for line in lines[1:]]
        table.add_row(label, "\n".join(lines))
    _console(out).print(table)
