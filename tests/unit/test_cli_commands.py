# SPDX-License-Identifier: Apache-2.0
"""How the command line finds its commands (every module of magcal.commands with add_parser,
and every module other packages register in the entry-point group ``magcal.commands``), and
option values that start with a minus and a digit (a southern latitude, a negative time)."""

from __future__ import annotations

import importlib.metadata
import subprocess
import sys
import types

import pytest

from magcal import cli
from magcal.cli import EXIT_ERROR, main

EXPECTED = ["simulate", "calibrate", "collect", "flash", "import", "info", "report", "verify"]


def _subcommands() -> list[str]:
    parser = cli.build_parser()
    (sub,) = [a for a in parser._actions if a.dest == "command"]
    return list(sub.choices)


def _plugin(monkeypatch, name: str, module: types.ModuleType | None, value: str | None = None):
    """Register ``module`` (None: a module that does not exist) as entry point ``name``."""
    value = value or f"fake_magcal_plugin_{name}"
    if module is not None:
        monkeypatch.setitem(sys.modules, value, module)
    ep = importlib.metadata.EntryPoint(name=name, value=value, group=cli.ENTRY_POINT_GROUP)
    return ep


def _entry_points(monkeypatch, *eps):
    def entry_points(**kw):
        assert kw == {"group": cli.ENTRY_POINT_GROUP}
        return list(eps)

    monkeypatch.setattr(importlib.metadata, "entry_points", entry_points)


def _hello_module() -> types.ModuleType:
    m = types.ModuleType("fake_magcal_plugin_hello")

    def add_parser(sub):
        p = sub.add_parser("hello", help="say hello")
        p.add_argument("--to", default="world")
        p.set_defaults(run=lambda args: print(f"hello {args.to}") or 0)

    m.add_parser = add_parser
    return m


def test_the_product_commands_come_from_their_modules(monkeypatch):
    _entry_points(monkeypatch)
    names = _subcommands()
    assert [n for n in names if n != "study"] == EXPECTED


def test_a_plugin_command_is_listed_and_runs(monkeypatch, capsys):
    _entry_points(monkeypatch, _plugin(monkeypatch, "hello", _hello_module()))
    assert "hello" in _subcommands()
    assert main(["hello", "--to", "magcal"]) == 0
    captured = capsys.readouterr()
    assert captured.out == "hello magcal\n" and captured.err == ""


def test_a_broken_plugin_costs_one_warning_and_nothing_else(monkeypatch, capsys, tmp_path):
    def half_made(sub):
        sub.add_parser("half", help="never finished")
        raise RuntimeError("the plugin's own bug\nsecond line")

    broken = types.ModuleType("fake_magcal_plugin_half")
    broken.add_parser = half_made
    _entry_points(
        monkeypatch,
        _plugin(monkeypatch, "missing", None, value="no_such_magcal_plugin_module"),
        _plugin(monkeypatch, "half", broken),
        _plugin(monkeypatch, "hello", _hello_module()),
    )
    names = _subcommands()
    warnings = capsys.readouterr().err.splitlines()
    assert len(warnings) == 2
    assert warnings[0].startswith("magcal: warning: command 'missing' from ")
    assert "no_such_magcal_plugin_module" in warnings[0]
    assert warnings[1].endswith("not loaded: the plugin's own bug second line")
    assert "half" not in names and "hello" in names
    assert [n for n in names if n not in ("study", "hello")] == EXPECTED
    out = tmp_path / "s.csv"
    assert main(["simulate", "-o", str(out), "--duration", "5", "--stationary", "1"]) == 0
    assert out.exists()
    with pytest.raises(SystemExit):
        main(["half"])


def test_a_plugin_cannot_replace_a_product_command(monkeypatch, capsys):
    m = types.ModuleType("fake_magcal_plugin_info")
    m.add_parser = lambda sub: sub.add_parser("info", help="an impostor")
    _entry_points(monkeypatch, _plugin(monkeypatch, "info", m))
    assert _subcommands().count("info") == 1
    assert "command 'info' from fake_magcal_plugin_info not loaded" in capsys.readouterr().err


# ----------------------------------------------------------------------- start-up imports
#: Libraries that only running a command may load: every parser is built for `magcal --help`.
HEAVY = ("numpy", "scipy", "matplotlib", "cvxpy", "clarabel", "pymavlink", "pyulog", "serial")


def _loaded_after(argvs: list[list[str]], modules: tuple[str, ...] = HEAVY) -> list[str]:
    """The ``modules`` a fresh interpreter holds after ``magcal ARGV`` for each of ``argvs``
    (the product's commands only: no entry points; their output dropped)."""
    code = "\n".join(
        [
            "import contextlib, importlib.metadata, io, sys",
            "importlib.metadata.entry_points = lambda **kw: []",
            "from magcal.cli import main",
            f"for argv in {argvs!r}:",
            "    with contextlib.redirect_stdout(io.StringIO()):",
            "        try:",
            "            assert main(argv) == 0, argv",
            "        except SystemExit as exc:",  # --help
            "            assert exc.code == 0, argv",
            f"print(' '.join(m for m in {modules!r} if m in sys.modules))",
        ]
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    return done.stdout.split()


def test_help_loads_no_library_a_command_needs():
    loaded = _loaded_after([["--help"]] + [[name, "--help"] for name in EXPECTED])
    assert loaded == []


def test_calibrate_loads_neither_cvxpy_nor_matplotlib_without_plots(tmp_path):
    session = tmp_path / "s.csv"
    argv = ["simulate", "--duration", "20", "--seed", "1", "-o", str(session)]
    assert main(argv) == 0
    loaded = _loaded_after([["calibrate", str(session), "--method", "init"]])
    assert "numpy" in loaded and "clarabel" in loaded  # it did calibrate
    assert "cvxpy" not in loaded and "matplotlib" not in loaded


def test_calibrate_loads_no_scipy(tmp_path):
    # scipy's import alone takes a good part of a cold calibration's time budget; the whole
    # default pipeline runs on numpy (and the ellipsoid fit's solver, where A ⪰ 0 binds).
    session = tmp_path / "s.csv"
    argv = ["simulate", "--duration", "20", "--seed", "1", "-o", str(session)]
    assert main(argv) == 0
    out = tmp_path / "out.json"
    loaded = _loaded_after([["calibrate", str(session), "-o", str(out)]], ("numpy", "scipy"))
    assert out.exists() and loaded == ["numpy"]


# ----------------------------------------------------------------------- negative values
@pytest.fixture
def flash_args(monkeypatch):
    """The arguments ``flash --mavlink`` would run with (no link is opened)."""
    from magcal.commands.flash import autopilot

    seen = []
    monkeypatch.setattr(autopilot, "run", lambda args: seen.append(args) or 0)
    return seen


@pytest.mark.parametrize(
    "location",
    [
        ["--location", "-35.3,149.2"],
        ["--location=-35.3,149.2"],
        ["--loc", "-35.3,149.2"],  # an abbreviation, as argparse allows
    ],
)
def test_a_southern_location_is_a_value(flash_args, location):
    argv = ["flash", "r.json", "--mavlink", "udpin:127.0.0.1:9", *location]
    assert main(argv) == 0
    assert flash_args[0].location == "-35.3,149.2"


def test_negative_values_everywhere_a_value_is_taken(flash_args):
    argv = ["flash", "--location", "-.5,-70.1,-0.2", "--mavlink", "udpin:127.0.0.1:9", "r.json"]
    assert main(argv) == 0
    a = flash_args[0]
    assert (a.location, a.result, a.mavlink) == ("-.5,-70.1,-0.2", "r.json", "udpin:127.0.0.1:9")


def test_import_takes_negative_times(monkeypatch):
    from magcal.commands import import_log

    seen = []
    monkeypatch.setattr(import_log, "run", lambda args: seen.append(args) or 0)
    assert main(["import", "log.bin", "-o", "s.csv", "--start", "-12.5", "--end", "-1"]) == 0
    assert (seen[0].start, seen[0].end) == (-12.5, -1.0)


def test_a_southern_location_with_a_device_port_is_refused_by_magcal_not_argparse(capsys):
    argv = ["flash", "r.json", "--port", "/dev/null", "--location", "-35.3,149.2"]
    assert main(argv) == EXIT_ERROR
    assert "--location is for an autopilot" in capsys.readouterr().err


def test_an_unknown_option_or_a_missing_value_is_still_refused(capsys):
    with pytest.raises(SystemExit):
        main(["flash", "r.json", "--mavlink", "u", "--locationx", "-35.3,149.2"])
    assert "unrecognized arguments: --locationx -35.3,149.2" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["flash", "r.json", "--mavlink", "u", "--location"])
    assert "argument --location: expected one argument" in capsys.readouterr().err
