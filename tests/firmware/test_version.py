# SPDX-License-Identifier: Apache-2.0
"""firmware/include/magcal/version.h gives the host package's version (host/pyproject.toml):
one version for a release of both sides."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parents[2]
VERSION_H = REPO_ROOT / "firmware" / "include" / "magcal" / "version.h"
PYPROJECT = REPO_ROOT / "host" / "pyproject.toml"


def header_macros() -> dict[str, str]:
    text = VERSION_H.read_text(encoding="utf-8")
    return dict(re.findall(r"^#define (MAGCAL_VERSION_\w+) (.+?)\s*$", text, re.M))


def host_version() -> str:
    tomllib = pytest.importorskip("tomllib", reason="tomllib needs Python 3.11")
    with PYPROJECT.open("rb") as f:
        return tomllib.load(f)["project"]["version"]


def test_header_version_is_the_host_package_version():
    m = header_macros()
    numbers = [m[f"MAGCAL_VERSION_{part}"] for part in ("MAJOR", "MINOR", "PATCH")]
    for n in numbers:
        assert re.fullmatch(r"0|[1-9][0-9]*", n), f"{n!r}: a plain decimal integer, for #if"
    assert m["MAGCAL_VERSION_STRING"] == '"' + ".".join(numbers) + '"'
    assert ".".join(numbers) == host_version()


def test_the_check_reads_every_macro():
    assert set(header_macros()) == {
        "MAGCAL_VERSION_MAJOR",
        "MAGCAL_VERSION_MINOR",
        "MAGCAL_VERSION_PATCH",
        "MAGCAL_VERSION_STRING",
    }
