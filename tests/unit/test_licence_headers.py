# SPDX-License-Identifier: Apache-2.0
"""Every C and Python source file in the repository states its licence: the line
``SPDX-License-Identifier: Apache-2.0`` within its first three lines (a shebang may come first;
the generated files get it from protocol/generate.py)."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parents[2]
SPDX = "SPDX-License-Identifier: Apache-2.0"
HEAD_LINES = 3
GIT_TIMEOUT_S = 30


def tracked_sources() -> list[str]:
    """The .c, .h and .py files git tracks, relative to the repository root."""
    if shutil.which("git") is None or not (REPO_ROOT / ".git").exists():
        pytest.skip("not a git checkout: the tracked files are unknown")
    out = subprocess.run(
        ["git", "ls-files", "-z", "--", "*.c", "*.h", "*.py"],
        cwd=REPO_ROOT,
        capture_output=True,
        check=True,
        timeout=GIT_TIMEOUT_S,
    ).stdout
    return [name for name in out.decode("utf-8").split("\0") if name]


def head(path: Path) -> str:
    with path.open(encoding="utf-8") as f:
        return "".join(f.readline() for _ in range(HEAD_LINES))


def test_every_source_file_states_its_licence():
    files = [name for name in tracked_sources() if (REPO_ROOT / name).is_file()]
    assert len(files) > 100, files  # the listing worked: the tree has hundreds
    missing = [name for name in files if SPDX not in head(REPO_ROOT / name)]
    assert not missing, (
        f"{len(missing)} source files lack '{SPDX}' in their first {HEAD_LINES} lines: "
        f"{missing}; add it as the first comment line (after a shebang)"
    )


def test_the_check_sees_a_missing_line(tmp_path):
    """head() reads only the first lines: an identifier further down does not count."""
    late = tmp_path / "late.py"
    late.write_text('"""Doc."""\n\nx = 1\n# ' + SPDX + "\n", encoding="utf-8")
    early = tmp_path / "early.py"
    early.write_text("#!/usr/bin/env python3\n# " + SPDX + '\n"""Doc."""\n', encoding="utf-8")
    assert SPDX not in head(late)
    assert SPDX in head(early)
