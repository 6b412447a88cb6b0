# SPDX-License-Identifier: Apache-2.0
"""The live CKF in ``magcal collect --mavlink`` against the autopilot emulator: the
progress shows the estimate's norm spread, says "ok to stop" once coverage and convergence
are both good enough, and the session records the final estimate as ``live_estimate``, as the
serial collect does (tests/unit/test_ckf_live.py). Both personalities: ArduPilot's field in
mG and PX4's in gauss, 10^4 apart, go through the same estimate.
"""

from __future__ import annotations

import io
import re
import sys

from magcal import cli
from magcal.autopilot import vehicle
from magcal.autopilot.collect import collect
from magcal.autopilot.connection import open_autopilot
from magcal.calib.norm_only import live as live_mod
from magcal.io.session import read_session
from tests.autopilot.test_mavlink_end_to_end import MAX_SAMPLES, SPEEDUP
from tests.autopilot_emulator import AutopilotEmulator

#: Wide enough that no progress line is cut here (cutting: tests/unit/test_ui.py).
WIDE_COLUMNS = 400
LIVE_ESTIMATE = re.compile(
    r"CKF norm spread (\d+\.\d+) %, uncertainty (\d+\.\d+) %, change over the last seconds "
    r"(\d+\.\d+) %, converged$"
)


class _Terminal(io.StringIO):
    """stderr as a terminal: the progress line is redrawn in place."""

    def isatty(self) -> bool:
        return True


def test_ardupilot_cli_progress_shows_the_norm_spread_then_ok_to_stop(
    tmp_path, monkeypatch, capsys
):
    terminal = _Terminal()
    monkeypatch.setattr(sys, "stderr", terminal)
    monkeypatch.setenv("COLUMNS", str(WIDE_COLUMNS))
    monkeypatch.delenv("CI", raising=False)
    monkeypatch.setenv("TERM", "xterm-256color")
    out = tmp_path / "live.csv"
    with AutopilotEmulator(personality="ardupilot", seed=0, speedup=SPEEDUP) as emu:
        argv = ["collect", "--mavlink", emu.url, "-o", str(out), "--max-samples", MAX_SAMPLES]
        assert cli.main(argv) == 0
    # each update redraws the line in place: control sequences removed, one update a line
    text = re.sub(r"\x1b\[[0-9;?]*[a-zA-Z]", "", terminal.getvalue())
    updates = [u for u in re.split(r"[\r\n]", text) if u]
    assert len(updates) > 5

    def first(pattern: str) -> int:
        return next(i for i, u in enumerate(updates) if re.search(pattern, u))

    # waiting for directions, then the spread with the coverage hint, then ok to stop alone
    waiting = first(r"  norm: waiting for more directions; ")
    spread = first(r"  norm spread \d+\.\d\d % \((settling|converged)\); \S")
    ok = first(r"  ok to stop: coverage \d+ %, norm spread \d+\.\d\d %$")
    assert waiting < spread < ok
    assert "ok to stop" in updates[-1]

    session = read_session(out)
    assert session.meta["stopped"] == "coverage"
    m = LIVE_ESTIMATE.match(session.meta["live_estimate"])
    assert m, session.meta["live_estimate"]
    spread_pct, std_pct, change_pct = map(float, m.groups())
    assert std_pct <= 100 * live_mod.MAX_NORM_STD and change_pct <= 100 * live_mod.MAX_NORM_CHANGE
    # the progress's last norm spread is the one recorded (2 decimals there, 3 here)
    shown = float(re.search(r"norm spread (\d+\.\d\d) %$", updates[-1]).group(1))
    assert abs(shown - spread_pct) <= 0.005 + 1e-9


def test_px4_collect_reports_the_live_state_and_records_it(tmp_path):
    progress = []
    with AutopilotEmulator(personality="px4", seed=1, speedup=SPEEDUP) as emu:
        with open_autopilot(emu.url) as ap:
            cp = vehicle.read_compass_params(ap.read, ap.autopilot, 1)
            r = collect(
                ap,
                cp,
                coverage_target=0.9,
                min_samples=500,
                max_samples=int(MAX_SAMPLES),
                progress=progress.append,
            )
    assert r.stopped == "coverage" and r.session.meta["mag_unit"] == "gauss"
    last = progress[-1]
    assert last.live is r.live and r.live.started and r.live.converged and r.live.ok_to_stop
    assert last.hint == r.live.text() and last.hint.startswith("ok to stop: coverage ")
    started = [p for p in progress if p.live is not None and p.live.started]
    assert started and all(p.hint.startswith(p.live.text()) for p in started)
    assert all(p.live is not None for p in progress)  # the estimate never failed
    # field directions seen in gauss, the spread relative: a few tenths of a percent at most
    assert 0.0 < r.live.norm_spread < 0.01
    assert r.session.meta["live_estimate"].startswith("CKF norm spread ")
    assert r.live.coverage == r.coverage.coverage >= 0.9
