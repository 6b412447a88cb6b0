# SPDX-License-Identifier: Apache-2.0
"""The command line as a user runs it: files in, files out, exit codes and messages."""

import io
import json
import os
import re
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

import magcal.calib.calibrate
from magcal.cli import EXIT_ERROR, main, refusal
from magcal.commands import calibrate as calibrate_command
from magcal.errors import MagcalError
from magcal.io.result import REQUIRED_KEYS, read_result
from magcal.io.session import read_session, session_from_arrays, write_session

REPO = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def simulated(tmp_path_factory):
    d = tmp_path_factory.mktemp("sim")
    session = d / "s.csv"
    assert (
        main(
            ["simulate", "--preset", "mems", "--duration", "20", "--seed", "2", "-o", str(session)]
        )
        == 0
    )
    return session


@pytest.fixture
def no_calibration(monkeypatch):
    """Fail the test if the command gets as far as calibrating."""

    def calibrate(*args, **kwargs):
        raise AssertionError("calibrate() ran although the command should have stopped before")

    monkeypatch.setattr(magcal.calib.calibrate, "calibrate", calibrate)


def refused(capsys, argv: list[str], *patterns: str) -> str:
    """Run ``argv`` with -q, expect the refusal: exit 2, one line ``magcal <command>: ...`` on
    stderr (without -q, the steps a command had begun are on lines before it)."""
    assert main([*argv, "-q"]) == EXIT_ERROR
    err = capsys.readouterr().err
    command = argv[0]
    assert "Traceback" not in err
    assert err.endswith("\n") and err.count("\n") == 1, f"not one paragraph: {err!r}"
    assert err.startswith(f"magcal {command}: "), err
    assert not err.startswith(f"magcal {command}: {command}:"), f"doubled prefix: {err!r}"
    for pattern in patterns:
        assert re.search(pattern, err), f"{pattern!r} not in {err!r}"
    return err


def shortened(source: Path, path: Path, n: int) -> Path:
    """The first ``n`` samples of the session ``source``, written to ``path``."""
    s = read_session(source)
    write_session(path, session_from_arrays(s.t[:n], s.gyr[:n], s.acc[:n], s.mag[:n], s.meta))
    return path


# ---------------------------------------------------------------------------------------------
# Working runs


def test_simulate_writes_session_and_truth(simulated):
    assert simulated.read_text().startswith("# magcal-session: 1\n")
    truth = json.loads(simulated.with_suffix(".truth.json").read_text())
    assert truth["format"] == "magcal-truth/1"


def test_calibrate_writes_result_and_plots(simulated, tmp_path, capsys):
    out = tmp_path / "r.json"
    print_options = np.get_printoptions()
    code = main(
        [
            "calibrate",
            str(simulated),
            "-o",
            str(out),
            "--plot",
            str(tmp_path / "p"),
            "--truth",
            str(simulated.with_suffix(".truth.json")),
        ]
    )
    assert code == 0
    assert np.get_printoptions() == print_options  # the summary leaves numpy's state alone
    result = json.loads(out.read_text())
    assert set(REQUIRED_KEYS) <= set(result)
    back = read_result(out)  # the written file passes our own reader's checks
    assert back.method == "ml" and result["format"] == "magcal-result/1"
    assert back.D.shape == (3, 3) and back.gyro_bias is not None
    for name in ("ellipsoid_sphere.png", "field_norm.png", "innovations.png"):
        assert (tmp_path / "p" / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    text = capsys.readouterr().out
    assert "iterations" in text and "known-attitude floor" in text
    # A simulated gyroscope's gain is exact, and the summary says the test found so.
    assert "gyro gain" in text and "taken as exact" in text
    # The result is saved before anything is printed about it.
    assert text.index(f"wrote {out}") < text.index("method")


def test_result_is_written_before_the_summary(simulated, tmp_path, capsys, monkeypatch):
    def broken_summary(*args, **kwargs):
        raise MagcalError("calibrate: the summary failed")

    monkeypatch.setattr(calibrate_command, "_print_summary", broken_summary)
    out = tmp_path / "r.json"
    refused(capsys, ["calibrate", str(simulated), "--method", "init", "-o", str(out)], "summary")
    assert read_result(out).method == "init"  # the calibration is not lost


def test_unobservable_session_exits_non_zero_with_advice(tmp_path, capsys):
    session = tmp_path / "yaw.csv"
    argv = ["simulate", "--preset", "mems", "--duration", "20", "--motion", "yaw-only"]
    assert main([*argv, "-o", str(session)]) == 0
    capsys.readouterr()
    out = tmp_path / "r.json"
    refused(capsys, ["calibrate", str(session), "-o", str(out)], "yaw")
    assert not out.exists()
    assert main(["calibrate", str(session), "--method", "init", "--force", "-o", str(out)]) == 0
    assert read_result(out).warnings


# ---------------------------------------------------------------------------------------------
# Refusals: one line on stderr, exit 2, no traceback


def test_bad_session_names_the_line(tmp_path, capsys):
    bad = tmp_path / "bad.csv"
    bad.write_text(
        "# magcal-session: 1\nt,gyr_x,gyr_y,gyr_z,acc_x,acc_y,acc_z,mag_x,mag_y,mag_z\n"
        "0,0,0,0,0,0,9.8,1,0,0\n0.01,0,0,x,0,0,9.8,1,0,0\n"
    )
    refused(capsys, ["calibrate", str(bad)], "line 4")


def test_missing_session(tmp_path, capsys, no_calibration):
    refused(capsys, ["calibrate", str(tmp_path / "nope.csv")], r"nope\.csv: no such file")


@pytest.mark.parametrize("content", [None, b"\xff\xfe\x00binary"])
def test_unreadable_session(tmp_path, capsys, no_calibration, content):
    path = tmp_path / "s.csv"
    if content is None:
        path.mkdir()  # a directory where a file should be
        pattern = "it is a directory"
    else:
        path.write_bytes(content)
        pattern = "not UTF-8"
    refused(capsys, ["calibrate", str(path)], pattern)


def test_session_shorter_than_the_method_needs(simulated, tmp_path, capsys, no_calibration):
    # Contract: the reader rejects fewer samples than the method needs (observability minimum).
    short = shortened(simulated, tmp_path / "short.csv", 150)
    refused(capsys, ["calibrate", str(short)], "150 samples; calibration needs at least 200")


def test_forced_session_needs_the_ellipsoid_fits_minimum(simulated, tmp_path, capsys):
    tiny = shortened(simulated, tmp_path / "tiny.csv", 9)
    refused(capsys, ["calibrate", str(tiny), "--force"], "9 samples; calibration needs at least 10")
    short = shortened(simulated, tmp_path / "short.csv", 150)
    out = tmp_path / "r.json"
    assert main(["calibrate", str(short), "--force", "--method", "init", "-o", str(out)]) == 0
    assert any("forced" in w for w in read_result(out).warnings)


@pytest.mark.parametrize("where", ["missing", "file", "directory"])
def test_unwritable_output_is_refused_before_calibrating(
    simulated, tmp_path, capsys, no_calibration, where
):
    (tmp_path / "file").write_text("")
    out, pattern = {
        "missing": (tmp_path / "no" / "dir" / "r.json", r"directory .*dir does not exist"),
        "file": (tmp_path / "file" / "r.json", r"directory .*file is not a directory"),
        "directory": (tmp_path, "it is a directory"),
    }[where]
    refused(capsys, ["calibrate", str(simulated), "-o", str(out)], "writing result", pattern)


@pytest.mark.skipif(not hasattr(os, "geteuid") or os.geteuid() == 0, reason="root may write")
def test_read_only_output_directory_is_refused_before_calibrating(
    simulated, tmp_path, capsys, no_calibration
):
    d = tmp_path / "ro"
    d.mkdir()
    d.chmod(0o500)
    try:
        refused(capsys, ["calibrate", str(simulated), "-o", str(d / "r.json")], "cannot create")
    finally:
        d.chmod(0o700)


def test_plot_directory_that_is_a_file(simulated, tmp_path, capsys, no_calibration):
    (tmp_path / "p").write_text("")
    argv = ["calibrate", str(simulated), "--plot", str(tmp_path / "p")]
    refused(capsys, argv, "writing plots to .*p: it is a file, not a directory")


@pytest.mark.parametrize(
    ("content", "pattern"),
    [
        (None, r"reading truth .*nope\.truth\.json: no such file"),
        ("not json", "reading truth .*not JSON"),
        ('{"format": "magcal-result/1"}', "is this a truth file from `magcal simulate`"),
        (b"\xff\xfe", "not UTF-8"),
    ],
)
def test_bad_truth_is_refused_before_calibrating(
    simulated, tmp_path, capsys, no_calibration, content, pattern
):
    truth = tmp_path / "nope.truth.json"
    if isinstance(content, bytes):
        truth.write_bytes(content)
    elif content is not None:
        truth.write_text(content)
    refused(capsys, ["calibrate", str(simulated), "--truth", str(truth)], pattern)


def test_truth_of_another_session_names_both_files(simulated, tmp_path, capsys, no_calibration):
    other = tmp_path / "other.csv"
    argv = ["simulate", "--preset", "mems", "--duration", "5", "--seed", "3", "-o", str(other)]
    assert main(argv) == 0
    capsys.readouterr()
    truth = other.with_suffix(".truth.json")
    err = refused(
        capsys,
        ["calibrate", str(simulated), "--truth", str(truth)],
        r"has \d+ samples but the session .* has 2200",
        "another session",
    )
    assert str(truth) in err and str(simulated) in err


def test_unknown_preset(tmp_path, capsys):
    out = tmp_path / "s.csv"
    refused(capsys, ["simulate", "--preset", "nope", "-o", str(out)], "unknown preset 'nope'")
    assert not out.exists()


def test_simulate_into_a_missing_directory(tmp_path, capsys):
    out = tmp_path / "no" / "s.csv"
    refused(capsys, ["simulate", "-o", str(out)], r"writing session .*directory .*no does not")


def test_simulate_truth_over_its_own_session(tmp_path, capsys):
    out = tmp_path / "s.csv"
    refused(capsys, ["simulate", "-o", str(out), "--truth", str(out)], "session file itself")
    assert not out.exists()


def test_refusal_is_one_paragraph_without_a_doubled_prefix():
    assert refusal("simulate", MagcalError("simulate: bad")) == "magcal simulate: bad"
    assert refusal("simulate", MagcalError("magcal simulate: bad")) == "magcal simulate: bad"
    assert refusal("calibrate", MagcalError("simulate: x")) == "magcal calibrate: simulate: x"
    assert refusal("calibrate", MagcalError("a\n  b\n\nc")) == "magcal calibrate: a b c"
    assert refusal("calibrate", MagcalError()) == "magcal calibrate: MagcalError"


# ---------------------------------------------------------------------------------------------
# The launcher script


@pytest.mark.skipif(shutil.which("sh") is None, reason="needs a POSIX shell")
def test_launcher_refuses_without_a_virtual_environment(tmp_path):
    (tmp_path / "host").mkdir()
    launcher = tmp_path / "host" / "magcal"
    shutil.copy2(REPO / "host" / "magcal", launcher)
    run = subprocess.run([str(launcher), "--version"], capture_output=True, text=True)
    assert run.returncode == 2
    assert run.stderr == "magcal: no virtual environment: run `make setup` first\n"


@pytest.mark.skipif(
    not (REPO / ".venv" / "bin" / "python").exists(), reason="no .venv (run `make setup`)"
)
def test_launcher_runs_through_a_symlink(tmp_path):
    link = tmp_path / "magcal"
    link.symlink_to(REPO / "host" / "magcal")
    env = {**os.environ, "CDPATH": str(tmp_path)}
    run = subprocess.run([str(link), "--version"], capture_output=True, text=True, env=env)
    assert run.returncode == 0 and run.stdout.startswith("magcal ")


def test_every_command_takes_quiet_and_verbose():
    import argparse

    from magcal.cli import build_parser

    parser = build_parser()
    commands = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    for name, command in commands.choices.items():
        options = command._option_string_actions
        assert {"-q", "--quiet", "-v", "--verbose"} <= set(options), name


def test_verbose_shows_the_link_log_on_stderr(capsys):
    import logging

    from magcal.cli import build_parser, configure_output

    configure_output(build_parser().parse_args(["info", "--port", "/dev/null", "-v"]))
    logging.getLogger("magcal.link.serial_link").debug("opened /dev/ttyACM0")
    logging.getLogger("magcal.calib").debug("not a link")
    err = capsys.readouterr().err
    assert "magcal magcal.link.serial_link: opened /dev/ttyACM0" in err
    assert "not a link" not in err
    # Without -v the link's debug records stay off stderr.
    configure_output(build_parser().parse_args(["info", "--port", "/dev/null"]))
    logging.getLogger("magcal.link.serial_link").debug("opened /dev/ttyACM1")
    assert "ttyACM1" not in capsys.readouterr().err


def test_quiet_and_verbose_end_with_the_command(tmp_path, capsys):
    """-q and -v hold while main() runs; a display made after it shows again."""
    import logging

    from magcal import ui

    main(["info", "--port", str(tmp_path / "no-such-port"), "-q", "-v"])
    capsys.readouterr()
    stream = io.StringIO()
    with ui.StatusLine(stream) as status:
        status.update("shown", log=True)
    assert stream.getvalue() == "shown\n"
    assert logging.getLogger("magcal.link").level == logging.NOTSET
