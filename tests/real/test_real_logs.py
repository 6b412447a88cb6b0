# SPDX-License-Identifier: Apache-2.0
"""``magcal import`` on real autopilot logs: every one is imported or refused in one true
paragraph, never a traceback or a flood of lines.

The committed set (``tests/data/reallogs``, always present) and the full set
(``../shared/reallogs`` beside the checkout, 23 logs from ArduPilot 3.x to PX4 1.15, when
present: its logs without a stated licence cannot be committed). Each log is imported twice:
as a user would (the hand-rotation detector chooses) and over its whole length
(``--start/--end``, which also exercises the pairing and the gaps).
"""

from __future__ import annotations

import re
import shutil
from pathlib import Path

import numpy as np
import pytest
from pymavlink import mavutil

from magcal.cli import main
from magcal.logs import (
    ImportOptions,
    LogImportError,
    dataflash,
    import_log,
    read_log,
    sniff_format,
    tlog,
    ulog,
)

REPO_ROOT = Path(__file__).resolve().parents[2]
COMMITTED = REPO_ROOT / "tests" / "data" / "reallogs"
#: The full set: ``shared/reallogs`` beside the checkout (as ``make real`` finds realdata).
FULL_SET = REPO_ROOT.parent / "shared" / "reallogs"
LOG_SUFFIXES = {".bin", ".tlog", ".ulg"}
#: The acceptance bound on what one import prints, lines (stdout and stderr together).
MAX_LINES = 20
EXIT_OK, EXIT_REFUSED = 0, 2


def _logs(folder: Path) -> list[Path]:
    return sorted(p for p in folder.rglob("*") if p.suffix.lower() in LOG_SUFFIXES)


def _full_set() -> list[Path]:
    return _logs(FULL_SET) if FULL_SET.is_dir() else []


needs_full_set = pytest.mark.skipif(
    not _full_set(),
    reason=f"the full set of real logs is not at {FULL_SET} (the committed ones still run)",
)


def _run(capfd, *argv: str) -> tuple[int, str]:
    code = main(["import", *argv])
    out, err = capfd.readouterr()
    return code, out + err


def _check_output(path: Path, code: int, text: str) -> None:
    lines = text.splitlines()
    assert code in (EXIT_OK, EXIT_REFUSED), (path.name, code, text[-2000:])
    assert "Traceback" not in text, (path.name, text[-2000:])
    assert len(lines) <= MAX_LINES, (path.name, len(lines), lines[:30])
    assert "Warning:" not in text and "RuntimeWarning" not in text, (path.name, text)
    assert "bad header" not in text, path.name
    if code == EXIT_REFUSED:
        refusal = [ln for ln in lines if ln.startswith("magcal import:")]
        assert len(refusal) == 1, (path.name, lines)  # one paragraph, one line
        assert path.name in refusal[0] or "error: argument" in refusal[0], refusal
    if "IMU_FAST" in text:
        assert sniff_format(str(path)) == "dataflash", path.name  # ArduPilot's bitmask only


def _import_both_ways(capfd, tmp_path: Path, path: Path) -> None:
    out = str(tmp_path / f"{path.name}.csv")
    code, text = _run(capfd, str(path), "-o", out)
    _check_output(path, code, text)
    code, text = _run(capfd, str(path), "-o", out, "--start", "0", "--end", "1e12")
    _check_output(path, code, text)
    if code == EXIT_OK:
        assert Path(out).stat().st_size > 0


@pytest.mark.parametrize("name", [p.name for p in _logs(COMMITTED)])
def test_a_committed_log_is_imported_or_refused_in_one_paragraph(name, capfd, tmp_path):
    _import_both_ways(capfd, tmp_path, COMMITTED / name)


@needs_full_set
def test_every_log_of_the_full_set_is_imported_or_refused_in_one_paragraph(capfd, tmp_path):
    logs = _full_set()
    assert len(logs) >= 20
    for path in logs:
        _import_both_ways(capfd, tmp_path, path)


def test_files_that_are_no_log_are_refused_in_one_paragraph(capfd, tmp_path):
    renamed = tmp_path / "telemetry.bin"  # a tlog named like a DataFlash log: read as a tlog
    shutil.copy(COMMITTED / "ardusub_small.tlog", renamed)
    assert sniff_format(str(renamed)) == "tlog"
    code, text = _run(capfd, str(renamed), "-o", str(tmp_path / "a.csv"))
    _check_output(renamed, code, text)
    assert "DataFlash" not in text  # read as telemetry: nothing about DataFlash
    noise = tmp_path / "noise.bin"
    noise.write_bytes(np.random.default_rng(0).integers(0, 256, 100_000, np.uint8).tobytes())
    code, text = _run(capfd, str(noise), "-o", str(tmp_path / "b.csv"))
    _check_output(noise, code, text)
    assert code == EXIT_REFUSED and "not a log magcal can read" in text
    # DataFlash's magic followed by noise: its indexer's complaints stay off the terminal
    fake = tmp_path / "fake.bin"
    fake.write_bytes(b"\xa3\x95\x80" + noise.read_bytes())
    code, text = _run(capfd, str(fake), "-o", str(tmp_path / "c.csv"))
    _check_output(fake, code, text)
    assert code == EXIT_REFUSED and re.search("not a (readable )?DataFlash log", text)


def test_bad_option_values_are_refused(capfd, tmp_path):
    log = str(COMMITTED / "ardusub_small.BIN")
    for bad in ("nan", "inf", "-inf", "soon"):
        with pytest.raises(SystemExit) as stop:
            main(["import", log, "-o", str(tmp_path / "a.csv"), "--start", bad])
        assert stop.value.code == EXIT_REFUSED
        assert "--start" in capfd.readouterr().err


def test_telemetry_keeps_every_parameter_whatever_its_arrival_order():
    path = str(COMMITTED / "ardusub_small.tlog")
    conn = mavutil.mavlogfile(path, notimestamps=False, robust_parsing=True)
    sent, count = set(), 0
    while (m := conn.recv_match(type="PARAM_VALUE")) is not None:
        sent.add(m.param_id)
        count = max(count, m.param_count)
    conn.close()
    streams = tlog.read(path)
    assert streams.params.names() == sent and len(sent) >= count - 1  # (one index re-sent)
    assert "COMPASS_OFS_X" in streams.params.names()


def test_px4_uses_the_fast_calibrated_magnetometer_over_a_slow_raw_one():
    streams = ulog.read(str(COMMITTED / "sample_log_small.ulg"))
    assert streams.mag.source == "vehicle_magnetometer[0]"
    assert np.median(np.diff(streams.mag.t)) < 0.1  # not the 1 Hz sensor_mag
    assert any("sensor_mag[0] is logged at 1.0 Hz only" in n for n in streams.notes)


def test_px4_reads_the_magnetometer_inside_sensor_combined():
    streams = ulog.read(str(COMMITTED / "sample_appended_multiple.ulg"))
    assert streams.mag.source == "sensor_combined.magnetometer_ga"
    norm = np.linalg.norm(streams.mag.mag, axis=1)
    assert 0.1 < np.median(norm) < 1.0  # gauss: the Earth's field with a vehicle's hard iron


def test_progress_never_runs_backwards(tmp_path):
    seen: list[float] = []
    read_log(str(COMMITTED / "sample_appended_multiple.ulg"), progress=seen.append)
    from magcal.commands.import_log import progress_printer

    shown = []

    class Stream:
        def write(self, text):
            shown.extend(int(w) for w in text.split() if w.isdigit())

        def flush(self):
            pass

        def isatty(self):
            return False

    show = progress_printer("x", Stream())
    for f in seen:
        show(f)
    show.done()
    assert shown == sorted(shown)


@needs_full_set
def test_old_dataflash_layouts_are_read_with_their_units():
    for path in _logs(FULL_SET / "ardupilot"):
        try:
            streams = dataflash.read(str(path))
        except LogImportError as exc:  # a log without a (working) compass
            assert "MAG" in str(exc), (path.name, exc)
            continue
        # gyroscope rad/s, accelerometer m/s², field mG: g and the Earth's field
        acc = np.median(np.linalg.norm(streams.imu.acc, axis=1))
        assert 7.0 < acc < 12.5, (path.name, acc)  # m/s², not g or mG
        assert np.all(np.diff(streams.imu.t) > 0) and np.all(np.diff(streams.mag.t) > 0)
        params = streams.params.names()
        if "COMPASS_DIA_X" not in params:
            meta = import_log(str(path), ImportOptions(start_s=0, end_s=1e12)).session.meta
            assert "onboard_soft_iron" in meta, path.name


def test_import_calibrate_report_on_a_real_log_that_cannot_determine_a_calibration(capfd, tmp_path):
    """A log without a hand rotation, forced through: every step says what is wrong in lines
    a terminal shows, the forced result says the field got less constant than raw."""
    session, result = str(tmp_path / "s.csv"), str(tmp_path / "r.json")
    log = str(COMMITTED / "ardusub_small.BIN")
    assert main(["import", log, "-o", session, "--start", "0", "--end", "1e12"]) == EXIT_OK
    capfd.readouterr()
    assert main(["calibrate", session, "--force", "-o", result]) == EXIT_OK
    text = "".join(capfd.readouterr())
    assert "Warning:" not in text and "RuntimeWarning" not in text
    assert "far less constant than none" in text
    assert main(["report", result, session, "-o", str(tmp_path / "r.html")]) == EXIT_OK
    text = "".join(capfd.readouterr())
    assert "Traceback" not in text
    assert max(len(line) for line in text.splitlines()) <= 300, text
