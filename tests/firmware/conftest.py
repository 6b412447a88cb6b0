# SPDX-License-Identifier: Apache-2.0
"""The firmware library as a shared object, driven through ctypes.

``make test`` builds ``build/libmagcal_fw.so`` first; running pytest alone builds it here
with the same make rule (it is cheap and make skips it when up to date).
"""

from __future__ import annotations

import ctypes
import subprocess
from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parents[2]
FIRMWARE_LIB = REPO_ROOT / "build" / "libmagcal_fw.so"
MAKE_TIMEOUT_S = 300


@pytest.fixture(scope="session")
def fwlib() -> ctypes.CDLL:
    subprocess.run(
        ["make", "-s", "firmware-lib"], cwd=REPO_ROOT, check=True, timeout=MAKE_TIMEOUT_S
    )
    return ctypes.CDLL(str(FIRMWARE_LIB))
