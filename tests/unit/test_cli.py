"""The command line as a user runs it: files in, files out, exit codes and messages."""

import json

import pytest

from magcal.cli import EXIT_ERROR, main
from magcal.io.result import REQUIRED_KEYS


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


def test_simulate_writes_session_and_truth(simulated):
    assert simulated.read_text().startswith("# magcal-session: 1\n")
    truth = json.loads(simulated.with_suffix(".truth.json").read_text())
    assert truth["format"] == "magcal-truth/1"


def test_calibrate_writes_result_and_plots(simulated, tmp_path, capsys):
    out = tmp_path / "r.json"
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
    result = json.loads(out.read_text())
    assert set(REQUIRED_KEYS) <= set(result)
    assert result["format"] == "magcal-result/1" and result["method"] == "ml"
    for name in ("ellipsoid_sphere.png", "field_norm.png", "innovations.png"):
        assert (tmp_path / "p" / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    text = capsys.readouterr().out
    assert "iterations" in text and "known-attitude floor" in text


def test_unobservable_session_exits_non_zero_with_advice(tmp_path, capsys):
    session = tmp_path / "yaw.csv"
    main(
        [
            "simulate",
            "--preset",
            "mems",
            "--duration",
            "20",
            "--motion",
            "yaw-only",
            "-o",
            str(session),
        ]
    )
    out = tmp_path / "r.json"
    assert main(["calibrate", str(session), "-o", str(out)]) == EXIT_ERROR
    err = capsys.readouterr().err
    assert "magcal calibrate:" in err and "yaw" in err
    assert not out.exists()
    assert main(["calibrate", str(session), "--method", "init", "--force", "-o", str(out)]) == 0
    assert json.loads(out.read_text())["warnings"]


def test_bad_session_names_the_line(tmp_path, capsys):
    bad = tmp_path / "bad.csv"
    bad.write_text(
        "# magcal-session: 1\nt,gyr_x,gyr_y,gyr_z,acc_x,acc_y,acc_z,mag_x,mag_y,mag_z\n"
        "0,0,0,0,0,0,9.8,1,0,0\n0.01,0,0,x,0,0,9.8,1,0,0\n"
    )
    assert main(["calibrate", str(bad)]) == EXIT_ERROR
    assert "line 4" in capsys.readouterr().err
