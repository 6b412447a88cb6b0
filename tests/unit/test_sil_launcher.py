# SPDX-License-Identifier: Apache-2.0
"""magcal_evaluation.sil finds the SIL device without the product's help: an argument, else
$MAGCAL_SIL_BINARY, else the checkout the evaluation package runs from."""

from __future__ import annotations

import pytest

from magcal_evaluation import sil


def test_the_checkout_is_the_one_the_package_runs_from():
    assert (sil.REPO_ROOT / "mk" / "sil.mk").is_file()
    assert sil.SIL_BINARY == sil.REPO_ROOT / "build" / "sil" / "magcal-sil"


def test_the_binary_comes_from_the_environment_else_the_checkout(monkeypatch, tmp_path):
    monkeypatch.delenv(sil.SIL_BINARY_ENV, raising=False)
    assert sil.default_binary() == sil.SIL_BINARY
    elsewhere = tmp_path / "magcal-sil"
    monkeypatch.setenv(sil.SIL_BINARY_ENV, str(elsewhere))
    assert sil.default_binary() == elsewhere
    with pytest.raises(sil.SilError, match=r"magcal-sil does not exist: run `make sil` first"):
        sil.start_sil(tmp_path / "flash.bin")
    # An argument wins over the environment.
    with pytest.raises(sil.SilError, match=r"other does not exist.*\$MAGCAL_SIL_BINARY"):
        sil.start_sil(tmp_path / "flash.bin", binary=tmp_path / "other")


def test_build_refuses_a_folder_that_is_not_a_checkout(tmp_path):
    with pytest.raises(sil.SilError, match=r"is not a magcal checkout \(no mk/sil.mk\)"):
        sil.build_sil(tmp_path)
