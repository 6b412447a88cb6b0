# SPDX-License-Identifier: Apache-2.0
"""The firmware on its Cortex-M4 target under QEMU.

Plain ``pytest tests`` skips these tests when ``qemu-system-arm`` or the image
(build/cortex-m4/magcal-target.elf) is missing, naming the make target that provides it;
``make test-target`` builds the image, sets MAGCAL_REQUIRE_TARGET=1 and so fails instead.
"""

from __future__ import annotations

import os
import shutil

import pytest

from tests.target.qemu import QEMU, TARGET_ELF, QemuTarget

REQUIRE_ENV = "MAGCAL_REQUIRE_TARGET"


def _missing() -> str | None:
    if shutil.which(QEMU) is None:
        return f"{QEMU} not found: run `make deps-target`"
    if not TARGET_ELF.is_file():
        return f"{TARGET_ELF.relative_to(TARGET_ELF.parents[2])} not built: run `make target-elf`"
    return None


def require_target() -> None:
    """Skip (or, with MAGCAL_REQUIRE_TARGET=1, fail) when QEMU or the image is missing."""
    missing = _missing()
    if missing is not None:
        if os.environ.get(REQUIRE_ENV) == "1":
            pytest.fail(f"{REQUIRE_ENV}=1 and {missing}")
        pytest.skip(missing)


@pytest.fixture(scope="module")
def target():
    """One QEMU target for a test module: booted, its UART open, shut down afterwards."""
    require_target()
    with QemuTarget() as t:
        yield t


@pytest.fixture
def target_factory():
    """A function that starts a fresh QemuTarget (not yet read from); every one it started
    is shut down after the test."""
    require_target()
    started: list[QemuTarget] = []

    def start() -> QemuTarget:
        t = QemuTarget()
        started.append(t)
        return t.start()

    yield start
    for t in started:
        t.close()
