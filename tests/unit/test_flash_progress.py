# SPDX-License-Identifier: Apache-2.0
"""``magcal flash --mavlink``'s parameter writes as a person sees them: on a terminal a
progress bar of the parameters written with the last one named, a parameter not confirmed on
a line of its own; in a log each parameter's line, as before."""

from __future__ import annotations

import io
import re

import pytest

from magcal.commands.flash.autopilot import WriteProgress

_ANSI = re.compile(r"\x1b\[[0-9;?]*[a-zA-Z]")
WRITES = (
    "1/3 COMPASS_OFS_X = 12.5 confirmed",
    "2/3 COMPASS_OFS_Y: NOT confirmed after 3 tries",
    "3/3 COMPASS_OFS_Z = -4 confirmed",
)


class _Terminal(io.StringIO):
    def isatty(self) -> bool:
        return True


@pytest.fixture(autouse=True)
def _a_person_watches(monkeypatch):
    monkeypatch.delenv("CI", raising=False)
    monkeypatch.setenv("TERM", "xterm-256color")
    monkeypatch.setenv("COLUMNS", "120")


def _write(stream) -> str:
    progress = WriteProgress(len(WRITES), stream)
    for text in WRITES:
        progress(text)
    progress.close()
    progress.close()
    return stream.getvalue()


def test_a_log_gets_each_parameters_line():
    assert _write(io.StringIO()).splitlines() == [f"magcal flash: {t}" for t in WRITES]


def test_a_terminal_gets_a_bar_and_the_failures_on_their_own_lines():
    written = _write(_Terminal())
    screen = [s for s in re.split(r"[\r\n]", _ANSI.sub("", written)) if s.strip()]
    assert "magcal flash: 2/3 COMPASS_OFS_Y: NOT confirmed after 3 tries" in screen
    bars = [s for s in screen if s.startswith("flash: writing parameters")]
    assert bars and "3/3" in bars[-1] and "COMPASS_OFS_Z = -4 confirmed" in bars[-1]
    assert not any(s.startswith("magcal flash: 1/3") for s in screen)  # the bar, not lines
