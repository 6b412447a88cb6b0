# SPDX-License-Identifier: Apache-2.0
"""The ``magcal`` command line: builds the parser from the command modules, runs the command,
and turns its errors into exit codes. Nothing else lives here.

A command is a module with ``add_parser(subparsers)`` that sets ``run``: every module of
:mod:`magcal.commands` that has one, and every module another installed package registers in
the entry-point group ``magcal.commands``.
"""

from __future__ import annotations

import argparse
import importlib
import pkgutil
import re
import sys
import textwrap
import warnings
from importlib import metadata

from magcal import __version__
from magcal.errors import MagcalError
from magcal.ui import EXIT_ERROR, EXIT_INTERRUPTED, refusal

__all__ = ["EXIT_ERROR", "EXIT_INTERRUPTED", "build_parser", "main", "refusal"]

#: The entry-point group through which other packages add commands.
ENTRY_POINT_GROUP = "magcal.commands"
#: Commands listed first in ``--help``, in this order; the others follow by name.
FIRST_COMMANDS = ("simulate", "calibrate")

#: The loggers whose records -v shows: the serial and MAVLink links, the device protocol and
#: the autopilot's parameter and calibration traffic.
VERBOSE_LOGGERS = ("magcal.link", "magcal.device", "magcal.autopilot")

#: An option value that argparse would take for an option: a negative number, or a list of
#: numbers that starts with one ("-35.3,149.2").
_NEGATIVE_VALUE = re.compile(r"^-\.?\d")


class HelpFormatter(argparse.ArgumentDefaultsHelpFormatter):
    """How every command's ``--help`` is laid out.

    An option's default is shown, "(default: ml)", unless it says nothing (None, False: the
    option unset) or the help already tells it in its own words. The description and the
    epilog are wrapped paragraph by paragraph to the terminal's width, but an indented line,
    an example command line of the epilog, is kept as written (argparse's
    RawDescriptionHelpFormatter would keep every line break, and leave a long paragraph
    running past the terminal's edge). Lines never break at a hyphen, so that an option or a
    value (--max-samples, two-step, yaw-only) reads, and copies, whole."""

    def _get_help_string(self, action: argparse.Action) -> str | None:
        # "is", not "in": a default of 0 (== False) is a value worth showing.
        unset = any(action.default is v for v in (None, False, argparse.SUPPRESS))
        if unset or "default" in (action.help or "").lower():
            return action.help
        return super()._get_help_string(action)

    def _split_lines(self, text: str, width: int) -> list[str]:
        return textwrap.wrap(" ".join(text.split()), width, break_on_hyphens=False)

    def _fill_text(self, text: str, width: int, indent: str) -> str:
        lines: list[str] = []
        paragraph: list[str] = []
        for line in [*text.splitlines(), ""]:
            if line.strip() and not line[0].isspace():
                paragraph.extend(line.split())
                continue
            if paragraph:
                lines.append(
                    textwrap.fill(
                        " ".join(paragraph),
                        width,
                        initial_indent=indent,
                        subsequent_indent=indent,
                        break_on_hyphens=False,
                    )
                )
                paragraph = []
            lines.append(indent + line.rstrip() if line.strip() else "")
        return "\n".join(lines).rstrip("\n")


class Parser(argparse.ArgumentParser):
    """An ArgumentParser that takes ``--location -35.3,149.2`` (or any option value that starts
    with a minus and a digit) as the option's value, as ``--location=-35.3,149.2`` is taken;
    plain argparse reads such a value as an unknown option. Its subparsers are Parsers too,
    and so lay out their help with :class:`HelpFormatter` unless given another formatter."""

    def __init__(self, *args, formatter_class=HelpFormatter, **kwargs) -> None:
        super().__init__(*args, formatter_class=formatter_class, **kwargs)

    def parse_known_args(self, args=None, namespace=None):
        args = sys.argv[1:] if args is None else list(args)
        return super().parse_known_args(self._attach_negative_values(args), namespace)

    def _attach_negative_values(self, args: list[str]) -> list[str]:
        out: list[str] = []
        i = 0
        while i < len(args):
            arg = args[i]
            if arg == "--":
                return out + args[i:]
            nxt = args[i + 1] if i + 1 < len(args) else None
            option = self._value_option(arg)
            if option is not None and nxt is not None and _NEGATIVE_VALUE.match(nxt):
                out.append(f"{arg}={nxt}" if arg.startswith("--") else arg + nxt)
                i += 2
                continue
            out.append(arg)
            i += 1
        return out

    def _value_option(self, arg: str) -> argparse.Action | None:
        """The option ``arg`` names (also an unambiguous abbreviation) if it takes one value."""
        if not arg.startswith("-") or "=" in arg:
            return None
        actions = self._option_string_actions
        action = actions.get(arg)
        if action is None and arg.startswith("--") and self.allow_abbrev:
            matches = {a for name, a in actions.items() if name.startswith(arg)}
            action = matches.pop() if len(matches) == 1 else None
        return action if action is not None and action.nargs in (None, "?") else None


def build_parser() -> argparse.ArgumentParser:
    parser = Parser(prog="magcal", description="Magnetometer calibration with inertial sensors.")
    parser.add_argument("--version", action="version", version=f"magcal {__version__}")
    sub = parser.add_subparsers(dest="command", required=True)
    for module in _command_modules():
        module.add_parser(sub)
    for entry_point in metadata.entry_points(group=ENTRY_POINT_GROUP):
        _add_plugin(sub, entry_point)
    for command in sub.choices.values():
        _add_output_options(command)
    return parser


def _add_output_options(command: argparse.ArgumentParser) -> None:
    """-q and -v, on every command (after its name, where people type them)."""
    taken = command._option_string_actions
    group = command.add_argument_group("output")
    if "-q" not in taken and "--quiet" not in taken:
        group.add_argument(
            "-q",
            "--quiet",
            action="store_true",
            help="show no progress; results, warnings and errors still show",
        )
    if "-v" not in taken and "--verbose" not in taken:
        group.add_argument(
            "-v",
            "--verbose",
            action="store_true",
            help="also show what the links to the device and the autopilot log "
            "(magcal.link, magcal.device, magcal.autopilot)",
        )


def configure_output(args: argparse.Namespace) -> None:
    """Apply -q and -v: progress silenced; :data:`VERBOSE_LOGGERS` on stderr."""
    import logging

    from magcal import ui

    ui.set_quiet(getattr(args, "quiet", False))
    verbose = getattr(args, "verbose", False)
    for name in VERBOSE_LOGGERS:
        # Set afresh on every call: main() may run more than once in a process.
        log = logging.getLogger(name)
        for handler in [h for h in log.handlers if getattr(h, "magcal_verbose", False)]:
            log.removeHandler(handler)
        log.setLevel(logging.DEBUG if verbose else logging.NOTSET)
        if verbose:
            handler = logging.StreamHandler(sys.stderr)
            handler.setFormatter(logging.Formatter("magcal %(name)s: %(message)s"))
            handler.magcal_verbose = True  # type: ignore[attr-defined]
            log.addHandler(handler)


def _command_modules() -> list:
    """Every module of :mod:`magcal.commands` that defines ``add_parser``, FIRST_COMMANDS first.
    Imported here, not at the top: the commands load their own stacks lazily, and a new
    command is a new module there, with nothing to change here."""
    import magcal.commands as commands

    names = sorted(m.name for m in pkgutil.iter_modules(commands.__path__))
    first = {name: i for i, name in enumerate(FIRST_COMMANDS)}
    names.sort(key=lambda name: first.get(name, len(first)))
    modules = [importlib.import_module(f"{commands.__name__}.{name}") for name in names]
    return [m for m in modules if hasattr(m, "add_parser")]


def _add_plugin(sub, entry_point: metadata.EntryPoint) -> None:
    """The command of another package: ``entry_point`` names a module with ``add_parser``. A
    plugin that fails to load costs one warning on stderr, never the command line."""
    before = set(sub.choices)
    try:
        module = entry_point.load()
        module.add_parser(sub)
    except Exception as exc:  # any failure of foreign code: warn and carry on
        added = set(sub.choices) - before  # a command half made is no command
        for name in added:
            del sub.choices[name]
        sub._choices_actions[:] = [a for a in sub._choices_actions if a.dest not in added]
        print(
            f"magcal: warning: command {entry_point.name!r} from {entry_point.value} not "
            f"loaded: {' '.join(str(exc).split()) or type(exc).__name__}",
            file=sys.stderr,
        )


def quiet_libraries() -> None:
    """Keep the libraries' warnings off the terminal: whatever a library says in its own
    words; magcal's checks say what matters about a result in the product's. A numpy
    floating-point warning raised in magcal's own code still shows: the numerical core
    handles its non-finite trial points without one, so it would mean a fault."""
    warnings.filterwarnings("ignore", module=r"^(?!magcal)")


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    configure_output(args)
    try:
        with warnings.catch_warnings():
            quiet_libraries()
            return args.run(args)
    except MagcalError as exc:
        print(refusal(args.command, exc), file=sys.stderr)
        return EXIT_ERROR
    except OSError as exc:
        # A safety net: the file functions raise MagcalError for the files they handle; any
        # other refusal by the system (a closed pipe, a full disk) is still a message.
        where = f" ({exc.filename})" if exc.filename else ""
        print(refusal(args.command, f"{exc.strerror or exc}{where}"), file=sys.stderr)
        return EXIT_ERROR
    except KeyboardInterrupt:
        print(f"magcal {args.command}: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    finally:
        # -q and -v are the command's, not the process's: a program that calls main() and
        # then shows progress of its own (the tests, a plugin's host) gets it shown.
        configure_output(argparse.Namespace())
