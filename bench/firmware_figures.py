#!/usr/bin/env python3
# SPDX-License-Identifier: Apache-2.0
"""Firmware figures: the library's size on a Cortex-M4 and the cost of one correction.

    python3 bench/firmware_figures.py --out bench/firmware.json

(a) ``.text``/``.data``/``.bss`` of every object of ``build/cortex-m4/libmagcal.a`` (``make
    cross``: ``arm-none-eabi-gcc -mcpu=cortex-m4 -mthumb -mfloat-abi=soft -Os``), with the
    symbols the library needs from outside (libgcc helpers such as ``__aeabi_ldivmod`` or
    libc functions such as ``memcpy``).
(b) The Cortex-M4 instructions of ``mc_correction_apply`` from ``arm-none-eabi-objdump -dr``
    of ``correction.o``: its own body plus the static functions of the same object it calls
    (each once; literal-pool words are not instructions), and every call it makes to a symbol
    outside that object, which must be none.
(c) Host instructions per ``mc_correction_apply`` call, from ``valgrind --tool=callgrind
    --toggle-collect=mc_correction_apply`` on ``bench/correction_driver.c`` (built with
    ``gcc -O2`` like the ctypes library): instructions counted inside the function and its
    callees, divided by the number of calls. Callgrind counts instructions, not time, so the
    figure is the same on a loaded machine.

Each figure whose tool is missing (run ``make deps-target`` for the Arm toolchain) or whose
code is not there yet is reported as such instead of failing. Prints a Markdown table and
writes the figures as JSON. Exit status 1 only when a tool that is present fails.
"""

from __future__ import annotations

import argparse
import datetime
import json
import re
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

FORMAT = "magcal-firmware-figures/1"
REPO_ROOT = Path(__file__).resolve().parent.parent
CROSS_DIR = REPO_ROOT / "build" / "cortex-m4"
CROSS_LIB = CROSS_DIR / "libmagcal.a"
CORRECTION_SRC = REPO_ROOT / "firmware" / "src" / "correction.c"
CORRECTION_OBJ = CROSS_DIR / "lib" / "correction.o"
DRIVER_SRC = REPO_ROOT / "bench" / "correction_driver.c"
DRIVER_BIN = REPO_ROOT / "build" / "bench" / "correction_driver"
FUNCTION = "mc_correction_apply"

ARM_PREFIX = "arm-none-eabi-"
HOST_CFLAGS = ["-std=c99", "-Wall", "-Wextra", "-Wpedantic", "-Werror", "-O2"]
DRIVER_CALLS = 100_000

MAKE_TIMEOUT_S = 300.0
TOOL_TIMEOUT_S = 120.0
VALGRIND_TIMEOUT_S = 600.0

# objdump -dr lines: a function label, an instruction, a relocation.
_LABEL_RE = re.compile(r"^[0-9a-f]+ <(?P<name>[^>]+)>:$")
_INSN_RE = re.compile(r"^\s+[0-9a-f]+:\t(?P<mnemonic>\S+)")
_RELOC_RE = re.compile(r"^\s+[0-9a-f]+: (?P<type>R_ARM_\w+)\s+(?P<sym>\S+)$")
# Relocations of a branch to another function: bl (call) and b.w (tail call).
_CALL_RELOCS = {"R_ARM_THM_CALL", "R_ARM_THM_JUMP24", "R_ARM_THM_JUMP19", "R_ARM_CALL"}


class FigureError(Exception):
    """A tool that is present failed; the message names the command."""


def run(cmd: list[str], timeout_s: float = TOOL_TIMEOUT_S) -> str:
    try:
        proc = subprocess.run(
            cmd, cwd=REPO_ROOT, capture_output=True, text=True, timeout=timeout_s, check=False
        )
    except subprocess.TimeoutExpired as exc:
        raise FigureError(f"{' '.join(cmd)} did not finish within {timeout_s} s") from exc
    if proc.returncode != 0:
        raise FigureError(f"{' '.join(cmd)} failed (exit {proc.returncode}):\n{proc.stderr}")
    return proc.stdout


def first_line(cmd: list[str]) -> str:
    return run(cmd).splitlines()[0].strip()


# ---------------------------------------------------------------- (a) library size
def library_size() -> dict:
    if shutil.which(ARM_PREFIX + "gcc") is None:
        return {"status": "no toolchain: arm-none-eabi-gcc not found, run `make deps-target`"}
    run(["make", "-s", "--no-print-directory", "cross"], timeout_s=MAKE_TIMEOUT_S)
    members = run([ARM_PREFIX + "ar", "t", str(CROSS_LIB)]).split()
    objects = [CROSS_DIR / "lib" / m for m in members]
    rows = []
    for line in run([ARM_PREFIX + "size", *map(str, objects)]).splitlines()[1:]:
        text, data, bss, _dec, _hex, name = line.split(maxsplit=5)
        rows.append({"object": Path(name).name, "text": int(text), "data": int(data),
                     "bss": int(bss)})  # fmt: skip
    total = {k: sum(r[k] for r in rows) for k in ("text", "data", "bss")}
    # Symbols the library uses but does not define: libgcc and libc functions.
    defined, undefined = set(), set()
    for line in run([ARM_PREFIX + "nm", "-g", str(CROSS_LIB)]).splitlines():
        parts = line.split()
        if len(parts) == 2 and parts[0] == "U":
            undefined.add(parts[1])
        elif len(parts) == 3:
            defined.add(parts[2])
    return {
        "status": "ok",
        "compiler": first_line([ARM_PREFIX + "gcc", "--version"]),
        "flags": "-mcpu=cortex-m4 -mthumb -mfloat-abi=soft -Os -ffunction-sections "
        "-fdata-sections (make cross)",
        "objects": rows,
        "total": total,
        "external_symbols": sorted(undefined - defined),
    }


# ---------------------------------------------------------------- (b) Cortex-M4 instructions
def parse_objdump(text: str) -> dict[str, dict]:
    """Function name -> {"insns": [mnemonic, ...], "calls": [symbol, ...]}."""
    functions: dict[str, dict] = {}
    current = None
    for line in text.splitlines():
        if m := _LABEL_RE.match(line):
            current = functions.setdefault(m["name"], {"insns": [], "calls": []})
        elif current is None:
            continue
        elif m := _RELOC_RE.match(line):
            if m["type"] in _CALL_RELOCS:
                current["calls"].append(m["sym"])
        elif m := _INSN_RE.match(line):
            if not m["mnemonic"].startswith("."):  # .word/.short: literal pool data
                current["insns"].append(m["mnemonic"])
    return functions


def correction_instructions(lib: dict) -> dict:
    if lib["status"] != "ok":
        return {"status": lib["status"]}
    if not CORRECTION_SRC.is_file() or not CORRECTION_OBJ.is_file():
        return {"status": f"not built yet: {CORRECTION_SRC.relative_to(REPO_ROOT)} missing"}
    functions = parse_objdump(
        run([ARM_PREFIX + "objdump", "-dr", "--no-show-raw-insn", str(CORRECTION_OBJ)])
    )
    if FUNCTION not in functions:
        return {"status": f"not built yet: {FUNCTION} not in {CORRECTION_OBJ.name}"}
    # The function and the functions of the same object it reaches, each counted once.
    counted: dict[str, int] = {}
    external: list[dict] = []
    todo = [FUNCTION]
    while todo:
        name = todo.pop()
        if name in counted:
            continue
        counted[name] = len(functions[name]["insns"])
        for callee in functions[name]["calls"]:
            if callee in functions:
                todo.append(callee)
            else:
                external.append({"caller": name, "callee": callee})
    indirect = sorted(
        {name for name in counted for insn in functions[name]["insns"] if insn.startswith("blx")}
    )
    return {
        "status": "ok",
        "function": FUNCTION,
        "instructions": sum(counted.values()),
        "per_function": counted,
        "external_calls": external,
        "indirect_calls_in": indirect,
        "note": "static count from the disassembly (not executed instructions); "
        "correct_one's loop body runs once per axis",
    }


# ---------------------------------------------------------------- (c) host instructions
def host_instructions(calls: int) -> dict:
    if not CORRECTION_SRC.is_file():
        return {"status": f"not built yet: {CORRECTION_SRC.relative_to(REPO_ROOT)} missing"}
    for tool in ("gcc", "valgrind"):
        if shutil.which(tool) is None:
            return {"status": f"no {tool}: install it (Debian package {tool})"}
    DRIVER_BIN.parent.mkdir(parents=True, exist_ok=True)
    sources = sorted(str(p) for p in (REPO_ROOT / "firmware" / "src").glob("*.c"))
    run(["gcc", *HOST_CFLAGS, "-I", "firmware/include", str(DRIVER_SRC), *sources,
         "-o", str(DRIVER_BIN)])  # fmt: skip
    with tempfile.TemporaryDirectory(prefix="magcal-callgrind-") as tmp:
        out = Path(tmp) / "callgrind.out"
        run(["valgrind", "--tool=callgrind", f"--callgrind-out-file={out}",
             f"--toggle-collect={FUNCTION}", str(DRIVER_BIN), str(calls)],
            timeout_s=VALGRIND_TIMEOUT_S)  # fmt: skip
        summary = re.search(r"^summary: (\d+)$", out.read_text(), re.MULTILINE)
    if summary is None:
        raise FigureError(f"callgrind wrote no summary line to {out}")
    total = int(summary[1])
    return {
        "status": "ok",
        "compiler": first_line(["gcc", "--version"]),
        "flags": " ".join(HOST_CFLAGS),
        "valgrind": first_line(["valgrind", "--version"]),
        "calls": calls,
        "instructions_total": total,
        "instructions_per_call": total / calls,
    }


# ---------------------------------------------------------------- report
def markdown(fig: dict) -> str:
    lines = ["| figure | value |", "|---|---|"]
    lib = fig["library"]
    if lib["status"] == "ok":
        t = lib["total"]
        lines.append(f"| libmagcal, Cortex-M4 -Os: code (.text incl. rodata) | {t['text']} bytes |")
        lines.append(f"| libmagcal, Cortex-M4: RAM (.data + .bss) | {t['data'] + t['bss']} bytes |")
        ext = ", ".join(lib["external_symbols"]) or "none"
        lines.append(f"| libmagcal: symbols from libc/libgcc | {ext} |")
    else:
        lines.append(f"| libmagcal, Cortex-M4 | {lib['status']} |")
    cm4 = fig["correction_cortex_m4"]
    if cm4["status"] == "ok":
        parts = " + ".join(f"{n} {k}" for k, n in cm4["per_function"].items())
        lines.append(
            f"| {FUNCTION}, Cortex-M4 instructions (static) | {cm4['instructions']} ({parts}) |"
        )
        calls = ", ".join(f"{c['caller']} -> {c['callee']}" for c in cm4["external_calls"])
        lines.append(f"| {FUNCTION}: calls outside correction.o | {calls or 'none'} |")
    else:
        lines.append(f"| {FUNCTION}, Cortex-M4 | {cm4['status']} |")
    host = fig["correction_host"]
    if host["status"] == "ok":
        lines.append(
            f"| {FUNCTION}, host instructions per call (callgrind, gcc -O2, "
            f"{host['calls']} calls) | {host['instructions_per_call']:.1f} |"
        )
    else:
        lines.append(f"| {FUNCTION}, host | {host['status']} |")
    return "\n".join(lines)


def git_revision() -> str:
    try:
        return run(["git", "describe", "--always", "--dirty"]).strip()
    except (FigureError, OSError):
        return "unknown"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, help="write the figures as JSON here")
    ap.add_argument("--calls", type=int, default=DRIVER_CALLS, help="corrections under callgrind")
    args = ap.parse_args(argv)
    try:
        lib = library_size()
        fig = {
            "format": FORMAT,
            "date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
            "revision": git_revision(),
            "library": lib,
            "correction_cortex_m4": correction_instructions(lib),
            "correction_host": host_instructions(args.calls),
        }
    except FigureError as exc:
        print(f"firmware_figures: {exc}", file=sys.stderr)
        return 1
    print(markdown(fig))
    if args.out is not None:
        args.out.write_text(json.dumps(fig, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
