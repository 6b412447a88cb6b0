# SPDX-License-Identifier: Apache-2.0
"""Autopilot parameter values on the wire and in files (pure functions, no I/O but files).

**Wire encoding.** PARAM_VALUE and PARAM_SET carry every value in a float32 field, with its
MAV_PARAM_TYPE. How an integer parameter travels differs (MAVLink common.xml,
MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_BYTEWISE / _C_CAST):

- ArduPilot casts: the float is the integer's value (``(float)value``);
- PX4 copies bytes: the float's four bytes are the int32's (``CAL_MAG0_ROT = 2`` travels as the
  float with bit pattern 0x00000002, a denormal), and PX4 refuses a PARAM_SET whose type differs
  from the parameter's ("param types mismatch", mavlink_parameters.cpp).

:func:`decode` / :func:`encode` convert between a parameter's value and its wire float;
:func:`confirmed` says whether an echoed value equals the one written (float32 equality for
REAL32, integer equality for the integer types). The float of an integer whose bytes are a
signalling NaN (0x7F800001–0x7FBFFFFF and the negative twins, beyond ±2.1e9) may be quietened
by a float conversion on the way; no compass parameter comes near.

**Files.** Two formats, chosen by suffix (:func:`write_param_file`, :func:`read_param_file`):

- ``.parm`` (Mission Planner and MAVProxy): one ``NAME,VALUE`` per line, ``#`` comments.
  Mission Planner writes ``NAME,VALUE``; MAVProxy (pymavlink ``mavparm.save``) writes
  ``NAME VALUE`` padded with spaces, and both read either (mavparm.load replaces ``,`` by a
  space). Values carry no type.
- ``.params`` (QGroundControl, ParameterManager::writeParametersToStream): ``#`` header lines
  ``# Onboard parameters for Vehicle N``, ``#``, ``# Stack: …``, ``# Vehicle: …``,
  ``# Version: …``, ``# Git Revision: …``, ``#``, ``# Vehicle-Id Component-Id Name Value
  Type``, then one tab-separated ``vehicle-id  component-id  NAME  VALUE  MAV_PARAM_TYPE`` per
  line. QGroundControl skips a parameter whose type differs from the vehicle's, so the type
  written is the one the vehicle reported.

Values are written with the fewest digits that give back the same float32 (the value the
vehicle holds), without an exponent: both formats are read by ``float()``-like parsers.
"""

from __future__ import annotations

import contextlib
import errno
import os
import re
import secrets
import struct
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from magcal.errors import MagcalError

# MAV_PARAM_TYPE (MAVLink common.xml)
UINT8, INT8, UINT16, INT16, UINT32, INT32, UINT64, INT64, REAL32, REAL64 = range(1, 11)
TYPE_NAMES = {
    UINT8: "UINT8",
    INT8: "INT8",
    UINT16: "UINT16",
    INT16: "INT16",
    UINT32: "UINT32",
    INT32: "INT32",
    REAL32: "REAL32",
}
#: struct formats of the integer types that fit the 4-byte wire field.
_INT_FORMATS = {UINT8: "<B", INT8: "<b", UINT16: "<H", INT16: "<h", UINT32: "<I", INT32: "<i"}
_INT_RANGES = {
    UINT8: (0, 2**8 - 1),
    INT8: (-(2**7), 2**7 - 1),
    UINT16: (0, 2**16 - 1),
    INT16: (-(2**15), 2**15 - 1),
    UINT32: (0, 2**32 - 1),
    INT32: (-(2**31), 2**31 - 1),
}

C_CAST, BYTEWISE = "c_cast", "bytewise"

PARM_SUFFIX, QGC_SUFFIX = ".parm", ".params"
QGC_HEADER_COLUMNS = "# Vehicle-Id Component-Id Name Value Type"
_NO_HARD_LINKS = {errno.EPERM, errno.ENOTSUP, errno.EOPNOTSUPP, errno.ENOSYS}


class ParamError(MagcalError):
    """A parameter value or a parameter file is unusable."""


def is_integer_type(param_type: int) -> bool:
    return param_type in _INT_FORMATS


def _check_type(param_type: int, name: str) -> None:
    if param_type != REAL32 and param_type not in _INT_FORMATS:
        raise ParamError(
            f"parameter {name}: MAV_PARAM_TYPE {param_type} does not fit the 4-byte wire value "
            "(only REAL32 and integers up to 32 bits do)"
        )


def held_value(value: float, param_type: int, name: str = "") -> float:
    """The value the vehicle will hold: the float32 nearest ``value`` for REAL32; for an
    integer type the integer itself (ParamError when ``value`` is not a whole number in its
    range)."""
    _check_type(param_type, name)
    if param_type == REAL32:
        return float(np.float32(value))
    lo, hi = _INT_RANGES[param_type]
    if value != int(value) or not lo <= value <= hi:
        raise ParamError(
            f"parameter {name} = {value!r} is not a whole number within "
            f"{TYPE_NAMES[param_type]} range [{lo}, {hi}]"
        )
    return float(int(value))


def encode(value: float, param_type: int, encoding: str, name: str = "") -> float:
    """The wire float32 (as a Python float) for ``value`` of ``param_type``."""
    held = held_value(value, param_type, name)
    if param_type == REAL32 or encoding == C_CAST:
        return held
    # A union on the wire: the integer's bytes, little-endian, in the float's place.
    return struct.unpack("<f", struct.pack("<I" if param_type == UINT32 else "<i", int(held)))[0]


def decode(wire: float, param_type: int, encoding: str, name: str = "") -> float:
    """The parameter's value from its wire float32 (``wire`` as a Python float)."""
    _check_type(param_type, name)
    if param_type == REAL32:
        return float(np.float32(wire))
    if encoding == C_CAST:
        return float(round(wire))
    raw = struct.pack("<f", wire)
    return float(struct.unpack("<i" if param_type != UINT32 else "<I", raw)[0])


def confirmed(wanted: float, got: float, param_type: int) -> bool:
    """Whether the vehicle's value ``got`` is the value ``wanted`` (both decoded): float32
    equality for REAL32, integer equality otherwise."""
    if param_type == REAL32:
        return bool(np.float32(wanted) == np.float32(got))
    return int(round(wanted)) == int(round(got))


def value_text(value: float, param_type: int | None) -> str:
    """The shortest text that reads back as the same float32 (integers as integers)."""
    if param_type is not None and is_integer_type(param_type):
        return str(int(value))
    return np.format_float_positional(np.float32(value), unique=True, trim="-")


# ------------------------------------------------------------------------------ files
@dataclass(frozen=True)
class ParamEntry:
    """One parameter of a file: name, value (as held), MAV_PARAM_TYPE (None: not known)."""

    name: str
    value: float
    param_type: int | None = None


@dataclass(frozen=True)
class ParamFile:
    """A parameter file's content: entries in file order, and the header facts (QGC).
    system_id : the vehicle's MAVLink system id (None: the file does not say; a .parm
    carries it only in magcal's own "magcal backup: ... system N" comment)."""

    entries: tuple[ParamEntry, ...]
    system_id: int | None = 1
    component_id: int = 1
    comments: tuple[str, ...] = field(default_factory=tuple)

    def as_dict(self) -> dict[str, float]:
        return {e.name: e.value for e in self.entries}


def file_format(path: str | os.PathLike) -> str:
    """``.parm`` or ``.params`` from the suffix; ParamError for any other."""
    suffix = Path(path).suffix.lower()
    if suffix in (PARM_SUFFIX, ".param"):
        return PARM_SUFFIX
    if suffix == QGC_SUFFIX:
        return QGC_SUFFIX
    raise ParamError(
        f"parameter file {path}: unknown suffix {suffix or '(none)'!r}: use .parm (Mission "
        "Planner, MAVProxy) or .params (QGroundControl)"
    )


def format_parm(pf: ParamFile) -> str:
    """Mission Planner text: ``# comment`` lines, then ``NAME,VALUE`` lines."""
    lines = [f"# {c}" if c else "#" for c in pf.comments]
    lines += [f"{e.name},{value_text(e.value, e.param_type)}" for e in pf.entries]
    return "\n".join(lines) + "\n"


def format_qgc(pf: ParamFile, stack: str = "", vehicle: str = "", version: str = "") -> str:
    """QGroundControl text (module docstring); entries without a type are written REAL32."""
    lines = [
        f"# Onboard parameters for Vehicle {pf.system_id or 1}",
        "#",
        f"# Stack: {stack}",
        f"# Vehicle: {vehicle}",
        f"# Version: {version}",
        "# Git Revision: ",
        "#",
    ]
    lines += [f"# {c}" if c else "#" for c in pf.comments]
    lines.append(QGC_HEADER_COLUMNS)
    for e in pf.entries:
        t = REAL32 if e.param_type is None else e.param_type
        lines.append(
            f"{pf.system_id or 1}\t{pf.component_id}\t{e.name}\t{value_text(e.value, t)}\t{t}"
        )
    return "\n".join(lines) + "\n"


def _parse_number(text: str, where: str) -> float:
    try:
        if text.lower().startswith(("0x", "-0x")):
            return float(int(text, 16))
        v = float(text)
    except ValueError:
        raise ParamError(f"{where}: {text!r} is not a number") from None
    if not np.isfinite(v):
        raise ParamError(f"{where}: {text!r} is not a finite number")
    return v


def parse_param_text(text: str, name: str = "parameter file", fmt: str | None = None) -> ParamFile:
    """Read ``.parm`` or ``.params`` text (format from ``fmt``, else guessed from the lines:
    five tab-separated fields make a QGC line). ParamError names the line of a bad one."""
    entries: list[ParamEntry] = []
    comments: list[str] = []
    system_id = component_id = None
    seen: dict[str, int] = {}
    for number, line in enumerate(text.splitlines(), start=1):
        body = line.split("#", 1)[0].strip()
        if line.strip().startswith("#"):
            comments.append(line.strip()[1:].strip())
        if not body:
            continue
        where = f"{name}: line {number}"
        fields = body.split("\t") if "\t" in body else body.replace(",", " ").split()
        fields = [f.strip() for f in fields if f.strip()]
        if len(fields) == 5 and fmt != PARM_SUFFIX:
            sysid, compid, pname, value, ptype = fields
            try:
                sysid_i, compid_i, type_i = int(sysid), int(compid), int(ptype)
            except ValueError:
                raise ParamError(
                    f"{where}: expected 'vehicle-id component-id NAME VALUE TYPE' with whole "
                    f"numbers for the ids and the type, found {body!r}"
                ) from None
            _check_type(type_i, pname)
            system_id = sysid_i if system_id is None else system_id
            component_id = compid_i if component_id is None else component_id
            v = _parse_number(value, where)
            entry = ParamEntry(pname, held_value(v, type_i, pname), type_i)
        elif len(fields) == 2 and fmt != QGC_SUFFIX:
            entry = ParamEntry(fields[0], _parse_number(fields[1], where))
        else:
            expected = "NAME,VALUE" if fmt == PARM_SUFFIX else "NAME,VALUE or 5 tab-separated"
            raise ParamError(f"{where}: expected {expected}, found {body!r}")
        if not entry.name.isascii() or len(entry.name) > 16 or not entry.name:
            raise ParamError(f"{where}: {entry.name!r} is not a parameter name (ASCII, ≤ 16)")
        if entry.name in seen:
            raise ParamError(
                f"{where}: parameter {entry.name} again (first on line {seen[entry.name]})"
            )
        seen[entry.name] = number
        entries.append(entry)
    if not entries:
        raise ParamError(f"{name}: no parameters in the file")
    if system_id is None:
        system_id = _backup_comment_system(comments)
    return ParamFile(tuple(entries), system_id, component_id or 1, tuple(comments))


_BACKUP_SYSTEM = re.compile(r"^magcal backup: .*? system (\d+),")


def _backup_comment_system(comments: list[str]) -> int | None:
    """The system id in magcal's backup comment ("magcal backup: PX4 system 3, ..."), the
    only place a .parm file records it; None when there is none."""
    for c in comments:
        m = _BACKUP_SYSTEM.match(c)
        if m:
            return int(m.group(1))
    return None


def read_param_file(path: str | os.PathLike) -> ParamFile:
    """Read a ``.parm`` or ``.params`` file (format from the suffix)."""
    fmt = file_format(path)
    try:
        text = Path(path).read_text(encoding="utf-8-sig")
    except OSError as exc:
        raise ParamError(f"reading parameter file {path}: {exc.strerror or exc}") from exc
    except UnicodeDecodeError as exc:
        raise ParamError(f"reading parameter file {path}: not UTF-8 text ({exc})") from exc
    return parse_param_text(text, str(path), fmt)


def render_param_file(path: str | os.PathLike, pf: ParamFile, **qgc_header: str) -> str:
    """The text of ``pf`` in the format ``path``'s suffix names."""
    if file_format(path) == PARM_SUFFIX:
        return format_parm(pf)
    return format_qgc(pf, **qgc_header)


def _fsync_dir(directory: Path) -> None:
    """fsync a directory, so that a name just linked or renamed into it survives a power
    loss (POSIX; where a directory cannot be opened, as on Windows, there is nothing to do)."""
    try:
        fd = os.open(directory, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError as exc:
        # some file systems refuse fsync on a directory (EINVAL): the file itself is synced
        if exc.errno not in (errno.EINVAL, errno.EBADF):
            raise
    finally:
        os.close(fd)


def write_new_file(path: str | os.PathLike, text: str, overwrite: bool = False) -> Path:
    """Write ``text`` to ``path`` atomically: a temporary file in the same directory, fsync,
    then a hard link (fails when ``path`` exists: a backup is never replaced) or, with
    ``overwrite``, a rename. ParamError when it cannot be written."""
    p = Path(path)
    tmp: Path | None = None
    try:
        name = p.with_name(f".{p.name}.{os.getpid()}-{secrets.token_hex(4)}.tmp")
        with open(name, "x", encoding="utf-8", newline="\n") as fh:
            tmp = name
            fh.write(text)
            fh.flush()
            os.fsync(fh.fileno())
        if overwrite:
            os.replace(tmp, p)
            tmp = None
            _fsync_dir(p.parent)
        else:
            try:
                os.link(tmp, p)
            except OSError as exc:
                if exc.errno not in _NO_HARD_LINKS:
                    raise
                with open(p, "x", encoding="utf-8", newline="\n") as dst:  # FAT: no hard links
                    dst.write(text)
                    dst.flush()
                    os.fsync(dst.fileno())
            _fsync_dir(p.parent)
    except FileExistsError as exc:
        raise ParamError(f"{p} exists; it is not replaced: give another path") from exc
    except OSError as exc:
        raise ParamError(f"cannot write {p} ({exc.strerror or exc}): choose another path") from exc
    finally:
        if tmp is not None:
            with contextlib.suppress(FileNotFoundError):
                os.unlink(tmp)
    return p
