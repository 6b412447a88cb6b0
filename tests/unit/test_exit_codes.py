# SPDX-License-Identifier: Apache-2.0
"""docs/contracts.md's table of exit statuses is the one magcal.ui defines: every EXIT_*
constant has a row, and every row but 0 is a constant."""

from __future__ import annotations

import re
from pathlib import Path

from magcal import ui

CONTRACTS = Path(__file__).resolve().parents[2] / "docs" / "contracts.md"


def documented_statuses() -> set[int]:
    text = CONTRACTS.read_text(encoding="utf-8")
    table = text.split("Exit status", 1)[1].split("\n\n", 2)[1]
    return {int(m) for m in re.findall(r"^\| (\d+) \|", table, re.M)}


def test_contracts_document_every_exit_status():
    constants = {v for k, v in vars(ui).items() if k.startswith("EXIT_")}
    assert len(constants) == len([k for k in vars(ui) if k.startswith("EXIT_")]), "one per value"
    assert documented_statuses() == {0} | constants


def test_the_table_is_read():
    assert {0, 2, 130} <= documented_statuses()
