# SPDX-License-Identifier: Apache-2.0
"""Every command explains itself in ``magcal COMMAND --help``: a description, examples that
are real command lines, a help text for every argument, the defaults that mean something, and
lines that fit the terminal."""

from __future__ import annotations

import argparse
import importlib.metadata
import shlex

import pytest

from magcal import cli
from magcal.cli import main

#: The product's commands, as test_cli_commands.EXPECTED (plugins are not the product's text).
PRODUCT_COMMANDS = [
    "simulate",
    "calibrate",
    "collect",
    "flash",
    "import",
    "info",
    "report",
    "verify",
]


@pytest.fixture
def commands(monkeypatch) -> dict[str, argparse.ArgumentParser]:
    """The product's commands by name, without the installed packages' plugins."""
    monkeypatch.setattr(importlib.metadata, "entry_points", lambda **kw: [])
    (sub,) = [a for a in cli.build_parser()._actions if a.dest == "command"]
    return dict(sub.choices)


def _help(monkeypatch, capsys, argv: list[str], columns: int = 100) -> str:
    monkeypatch.setenv("COLUMNS", str(columns))
    with pytest.raises(SystemExit) as exc:
        main(argv)
    assert exc.value.code == 0
    return capsys.readouterr().out


def _examples(parser: argparse.ArgumentParser) -> list[str]:
    return [line.strip() for line in parser.epilog.splitlines() if line.startswith("  magcal ")]


def test_every_product_command_is_covered(commands):
    assert list(commands) == PRODUCT_COMMANDS


@pytest.mark.parametrize("name", PRODUCT_COMMANDS)
def test_a_command_has_a_description_and_examples(commands, name):
    parser = commands[name]
    assert parser.description and parser.description.strip()
    assert parser.epilog and f"magcal {name}" in parser.epilog
    assert 1 <= len(_examples(parser)) <= 3


@pytest.mark.parametrize("name", PRODUCT_COMMANDS)
def test_every_argument_has_a_help_text(commands, name):
    no_help = [
        action.option_strings or [action.dest]
        for action in commands[name]._actions
        if not isinstance(action, argparse._HelpAction) and not (action.help or "").strip()
    ]
    assert no_help == []


@pytest.mark.parametrize("name", PRODUCT_COMMANDS)
def test_the_examples_are_command_lines_magcal_takes(commands, name, monkeypatch):
    parser = cli.build_parser()
    for example in _examples(commands[name]):
        argv = shlex.split(example)
        assert argv[:2] == ["magcal", name]
        args = parser.parse_args(argv[1:])  # a typo in an example exits here
        assert args.command == name


@pytest.mark.parametrize("name", PRODUCT_COMMANDS)
def test_help_fits_100_columns_and_shows_no_empty_default(commands, name, monkeypatch, capsys):
    text = _help(monkeypatch, capsys, [name, "--help"])
    assert [line for line in text.splitlines() if len(line) > 100] == []
    assert "(default: None)" not in text and "(default: False)" not in text
    assert "examples:\n  magcal " in text  # the epilog's lines kept, not run together


def test_calibrate_help_shows_the_defaults_and_both_session_versions(monkeypatch, capsys):
    text = " ".join(_help(monkeypatch, capsys, ["calibrate", "--help"]).split())
    method = text[text.index("--method {") : text.index("-o OUTPUT, --output")]
    assert method.endswith("(default: ml) ")
    assert (
        "--gradient {exact,numeric} exact (reverse mode) or the paper's finite differences "
        "(default: exact)" in text
    )
    assert "session CSV (magcal-session: 1 or 2)" in text


def test_simulate_help_shows_a_default_of_zero(monkeypatch, capsys):
    text = " ".join(_help(monkeypatch, capsys, ["simulate", "--help"]).split())
    assert "(default: 0)" in text and "(default: mems)" in text


def test_a_help_that_tells_its_default_gets_no_second_one(monkeypatch, capsys):
    text = " ".join(_help(monkeypatch, capsys, ["collect", "--help"]).split())
    assert "default 90, 'off' to disable --max-samples" in text


def test_a_narrow_terminal_wraps_the_description_and_keeps_the_examples(monkeypatch, capsys):
    text = _help(monkeypatch, capsys, ["flash", "--help"], columns=60)
    assert max(len(line) for line in text.split("examples:")[0].splitlines()) <= 60
    assert "\n  magcal flash result.json --port /dev/ttyACM0\n" in text


@pytest.mark.parametrize("columns", [60, 80, 100])
def test_lines_do_not_break_at_a_hyphen(monkeypatch, capsys, columns):
    # so that an option or a value reads (and copies) whole: two-step, --gyro-bias-prior
    text = _help(monkeypatch, capsys, ["calibrate", "--help"], columns=columns)
    assert [line for line in text.splitlines() if line.rstrip().endswith("-")] == []


def test_a_plugin_command_gets_the_same_layout(monkeypatch, capsys):
    import sys
    import types

    m = types.ModuleType("fake_magcal_plugin_hello")

    def add_parser(sub):
        p = sub.add_parser("hello", help="say hello", epilog="example:\n  magcal hello --to you")
        p.add_argument("--to", default="world", help="whom to greet")
        p.set_defaults(run=lambda args: 0)

    m.add_parser = add_parser
    monkeypatch.setitem(sys.modules, m.__name__, m)
    ep = importlib.metadata.EntryPoint(name="hello", value=m.__name__, group=cli.ENTRY_POINT_GROUP)
    monkeypatch.setattr(importlib.metadata, "entry_points", lambda **kw: [ep])
    text = _help(monkeypatch, capsys, ["hello", "--help"])
    assert "whom to greet (default: world)" in text
    assert "example:\n  magcal hello --to you" in text
