# SPDX-License-Identifier: Apache-2.0
"""The committed generated files are exactly what protocol/generate.py makes of
protocol/schema.json (nothing is generated at run time), and the schema is in its canonical
layout."""

from __future__ import annotations

import importlib.util
import json
import subprocess
import sys
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parents[2]
GENERATOR = REPO_ROOT / "protocol" / "generate.py"
GENERATE_TIMEOUT_S = 60


def _generator_module():
    spec = importlib.util.spec_from_file_location("protocol_generate", GENERATOR)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_regenerating_gives_the_committed_files(tmp_path):
    subprocess.run(
        [sys.executable, str(GENERATOR), "--out", str(tmp_path)],
        check=True,
        timeout=GENERATE_TIMEOUT_S,
    )
    produced = sorted(p.relative_to(tmp_path) for p in tmp_path.rglob("*") if p.is_file())
    assert len(produced) == 7
    stale = [
        str(rel)
        for rel in produced
        if (REPO_ROOT / rel).read_bytes() != (tmp_path / rel).read_bytes()
    ]
    assert not stale, f"out of date with protocol/schema.json: {stale}: run make generate"


def test_schema_is_in_canonical_layout():
    gen = _generator_module()
    text = (REPO_ROOT / "protocol" / "schema.json").read_text(encoding="utf-8")
    assert gen.format_schema(json.loads(text)) == text


def test_generator_is_deterministic(tmp_path):
    """Two runs with different hash seeds write identical bytes."""
    for seed in ("1", "2"):
        subprocess.run(
            [sys.executable, str(GENERATOR), "--out", str(tmp_path / seed)],
            check=True,
            timeout=GENERATE_TIMEOUT_S,
            env={"PYTHONHASHSEED": seed, "PATH": "/usr/bin:/bin"},
        )
    for path in (tmp_path / "1").rglob("*"):
        if path.is_file():
            twin = tmp_path / "2" / path.relative_to(tmp_path / "1")
            assert path.read_bytes() == twin.read_bytes(), path


def test_status_header_keeps_names_and_values():
    """status.h's table is the schema's: MC_<name> = <value> for every entry."""
    schema = json.loads((REPO_ROOT / "protocol" / "schema.json").read_text(encoding="utf-8"))
    header = (REPO_ROOT / "firmware" / "include" / "magcal" / "status.h").read_text()
    for entry in schema["status"]:
        assert f"MC_{entry['name']} = {entry['value']}" in header
