# SPDX-License-Identifier: Apache-2.0
"""``magcal calibrate --method ckf|two-step`` as a user runs it: a valid magcal-result/1,
the usual refusal (exit 2) on a session that cannot determine the calibration and a result
with a warning under --force, and --method's help naming all four methods."""

from __future__ import annotations

import json

import pytest

from magcal.calib import calibrate
from magcal.calib.likelihood import ml
from magcal.cli import EXIT_ERROR, main
from magcal.commands import calibrate as calibrate_command
from magcal.io.result import REQUIRED_KEYS, read_result

METHOD_KEYS = {"ckf": "ckf", "two-step": "two_step"}


@pytest.fixture(scope="module")
def sessions(tmp_path_factory):
    d = tmp_path_factory.mktemp("sim")
    good, yaw = d / "good.csv", d / "yaw.csv"
    assert main(["simulate", "--preset", "mems", "--seed", "1", "-o", str(good)]) == 0
    argv = ["simulate", "--preset", "mems", "--duration", "20", "--motion", "yaw-only"]
    assert main([*argv, "-o", str(yaw)]) == 0
    return good, yaw


@pytest.mark.parametrize("method", ["ckf", "two-step"])
def test_calibrate_writes_a_result(sessions, tmp_path, capsys, method):
    good, _ = sessions
    out = tmp_path / "r.json"
    truth = good.with_suffix(".truth.json")
    assert (
        main(["calibrate", str(good), "--method", method, "-o", str(out), "--truth", str(truth)])
        == 0
    )
    data = json.loads(out.read_text())
    assert set(REQUIRED_KEYS) <= set(data) and data["method"] == method
    result = read_result(out)  # passes the reader's checks (D_inv, m_n against dip, ...)
    assert result.method == method and result.gyro_bias is not None
    assert METHOD_KEYS[method] in result.extra and "field_norm" in result.extra
    assert result.extra["field_norm"]["after"]["std"] < 0.01
    text = capsys.readouterr().out
    assert f"method      {method}" in text and "known-attitude floor" in text


@pytest.mark.parametrize("method", ["ckf", "two-step"])
def test_unobservable_session_is_refused_unless_forced(sessions, tmp_path, capsys, method):
    _, yaw = sessions
    out = tmp_path / "r.json"
    assert main(["calibrate", str(yaw), "--method", method, "-q", "-o", str(out)]) == EXIT_ERROR
    err = capsys.readouterr().err
    assert err.startswith("magcal calibrate: ") and "yaw" in err and err.count("\n") == 1
    assert not out.exists()
    assert main(["calibrate", str(yaw), "--method", method, "--force", "-o", str(out)]) == 0
    assert read_result(out).warnings


def test_method_help_lists_every_method(capsys):
    assert calibrate_command.CALIBRATION_METHODS == calibrate.METHODS
    assert calibrate_command.ML_OPTIMIZERS == ml.OPTIMIZERS
    with pytest.raises(SystemExit):
        main(["calibrate", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "{ml,init,ckf,two-step}" in text
    for phrase in ("ml: maximum likelihood", "init: its initial", "ckf: Zhao", "two-step: Alonso"):
        assert phrase in text


def test_trust_region_with_numeric_gradients_is_refused_before_reading(tmp_path, capsys):
    out = tmp_path / "r.json"
    argv = ["calibrate", str(tmp_path / "absent.csv"), "--optimizer", "trust-region"]
    assert main([*argv, "--gradient", "numeric", "-o", str(out)]) == EXIT_ERROR
    err = capsys.readouterr().err
    assert "needs the exact gradient" in err and err.count("\n") == 1
    assert not out.exists()
