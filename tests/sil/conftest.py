# SPDX-License-Identifier: Apache-2.0
"""The SIL device (build/sil/magcal-sil) as a process for the tests, on magcal_evaluation.sil.

``sil_binary`` builds it once per session with ``make -s sil``; ``start_sil`` starts one
process (TCP protocol and feed on ephemeral loopback ports, a flash file of the test's) and
parses its start-up lines; every process started is stopped at teardown (SIGKILL if still
running). Every wait has a timeout, and a timeout raises.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

from magcal_evaluation import sil as _sil
from magcal_evaluation.sil import (  # noqa: F401  (re-exported for the tests)
    MAKE_TIMEOUT_S,
    REPO_ROOT,
    SIL_BINARY,
    STARTUP_TIMEOUT_S,
    STOP_TIMEOUT_S,
    SilError,
    SilProcess,
    read_lines,
)


@pytest.fixture(scope="session")
def sil_binary() -> Path:
    """build/sil/magcal-sil, built (or brought up to date) with ``make -s sil``."""
    try:
        return _sil.build_sil(REPO_ROOT, MAKE_TIMEOUT_S)
    except SilError as exc:
        pytest.fail(str(exc))


@pytest.fixture
def start_sil(sil_binary: Path) -> Iterator[Callable[..., SilProcess]]:
    """A factory: start_sil(flash_path, *extra_args) -> SilProcess, stopped at teardown."""
    started: list[SilProcess] = []

    def start(flash: Path, *extra: str) -> SilProcess:
        sil = _sil.start_sil(flash, *extra, binary=sil_binary, timeout_s=STARTUP_TIMEOUT_S)
        started.append(sil)
        return sil

    yield start
    for sil in started:
        sil.kill(STOP_TIMEOUT_S)
