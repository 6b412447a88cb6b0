# SPDX-License-Identifier: Apache-2.0
"""Session files (``magcal-session`` CSV): the in-memory form, reading and writing.

See ``docs/contracts.md`` for the format::

    # magcal-session: 1
    # source: ...
    t,gyr_x,gyr_y,gyr_z,acc_x,acc_y,acc_z,mag_x,mag_y,mag_z
    0,0.0012,-0.0031,0.0007,0.02,-0.11,9.80,21.3,-4.2,-38.9

Version 2 (multi-rate) has the same columns; a row's three ``acc_*`` cells may be empty
together (no accelerometer sample at that time), and so may its three ``mag_*`` cells (no
magnetometer sample). In memory such a vector is a row of NaN (``Session.has_acc``,
``Session.has_mag``). ``write_session`` writes version 1 whenever every row has both.

Reading is two-pass: a vectorised parse (``np.loadtxt``) handles valid files quickly; if it or
any check fails, a line-by-line re-scan finds the first bad line and names it. The re-scan is
the reference: whatever it accepts is a valid session, and the fast path accepts only files the
re-scan would accept, with bit-identical values.

Fields are plain (no CSV quoting). Whitespace-only lines are skipped. Metadata values are
stripped of surrounding whitespace.
"""

from __future__ import annotations

import math
import os
import re
import tempfile
from dataclasses import dataclass, field

import numpy as np

from magcal.errors import MagcalError, SessionFormatError

SESSION_VERSION = "1"
FIRST_LINE = "# magcal-session: 1"
#: The multi-rate form: rows may lack the accelerometer or the magnetometer.
MULTI_RATE_VERSION = "2"
FIRST_LINE_MULTI_RATE = "# magcal-session: 2"
SESSION_VERSIONS = (SESSION_VERSION, MULTI_RATE_VERSION)
TIME_COLUMN = "t"
VECTOR_COLUMNS = (
    ("gyr", ("gyr_x", "gyr_y", "gyr_z")),
    ("acc", ("acc_x", "acc_y", "acc_z")),
    ("mag", ("mag_x", "mag_y", "mag_z")),
)
#: The required columns, in the order ``write_session`` writes them.
COLUMNS = (TIME_COLUMN,) + tuple(name for _, names in VECTOR_COLUMNS for name in names)
#: Rows per chunk when a file with a problem is re-parsed to find the first bad line.
RESCAN_CHUNK_ROWS = 4096


class SessionFileError(SessionFormatError):
    """A session file cannot be opened, read or written (missing, a directory, no permission)."""


# --------------------------------------------------------------------------------------------
# File-system problems, shared by the readers and writers of magcal's files


def os_error_advice(exc: OSError, path: str | os.PathLike, writing: bool) -> str:
    """What went wrong with ``path`` and what to do, for an error message (no file name)."""
    directory = os.path.dirname(os.fspath(path)) or "."
    if isinstance(exc, FileNotFoundError):
        if writing:
            return f"directory {directory} does not exist: create it or write elsewhere"
        return "no such file: check the name and the directory"
    if isinstance(exc, IsADirectoryError):
        return "it is a directory: give a file name"
    if isinstance(exc, NotADirectoryError):
        return "part of the path is a file, not a directory: check the path"
    if isinstance(exc, PermissionError):
        if writing:
            return "permission denied: write to a directory you may write to"
        return "permission denied: make the file readable"
    return f"{exc.strerror or exc}: check the path and the disk"


def check_writable(
    path: str | os.PathLike, operation: str, error: type[MagcalError] = SessionFileError
) -> None:
    """Raise ``error`` unless a file can be written at ``path``.

    For commands that work long before they write: check first, so the work is not lost.
    operation : names it in the message, e.g. ``"writing result"``
    """
    name = os.fspath(path)
    directory = os.path.dirname(name) or "."
    if os.path.isdir(name):
        raise error(f"{operation} {name}: it is a directory: give a file name")
    if not os.path.isdir(directory):
        problem = "is not a directory" if os.path.exists(directory) else "does not exist"
        raise error(
            f"{operation} {name}: directory {directory} {problem}: create it or write elsewhere"
        )
    try:
        # Creating (and at once deleting) a file is the only reliable test: permissions,
        # ACLs and read-only file systems all show up here.
        with tempfile.TemporaryFile(dir=directory):
            pass
    except OSError as exc:
        raise error(
            f"{operation} {name}: cannot create files in directory {directory} "
            f"({exc.strerror or exc}): write elsewhere"
        ) from exc
    if os.path.exists(name) and not os.access(name, os.W_OK):
        raise error(f"{operation} {name}: the file exists and is read-only: write elsewhere")


@dataclass(frozen=True)
class Session:
    """One recording.

    t   : (N,) float, seconds, strictly increasing
    gyr : (N, 3) float, rad/s, body frame (every row)
    acc : (N, 3) float, m/s², specific force, body frame; a NaN row where the row has no
          accelerometer sample (:attr:`has_acc`)
    mag : (N, 3) float, raw magnetometer units (any unit); a NaN row where the row has no
          magnetometer sample (:attr:`has_mag`)
    meta: the ``# key: value`` metadata lines, without ``magcal-session``
    extra: columns beyond the ten, name → (N,) float, NaN where the cell is empty (written
          after the ten in this order; read only when :func:`read_session` is asked to)
    """

    t: np.ndarray
    gyr: np.ndarray
    acc: np.ndarray
    mag: np.ndarray
    meta: dict[str, str] = field(default_factory=dict)
    extra: dict[str, np.ndarray] = field(default_factory=dict)

    def __len__(self) -> int:
        return int(self.t.shape[0])

    @property
    def has_acc(self) -> np.ndarray:
        """(N,) bool: the row has an accelerometer sample."""
        return ~np.isnan(self.acc[:, 0])

    @property
    def has_mag(self) -> np.ndarray:
        """(N,) bool: the row has a magnetometer sample."""
        return ~np.isnan(self.mag[:, 0])

    @property
    def multi_rate(self) -> bool:
        """Some row lacks the accelerometer or the magnetometer (a version 2 session)."""
        return bool(np.isnan(self.acc[:, 0]).any() or np.isnan(self.mag[:, 0]).any())


def site_latitude_deg(meta: dict[str, str]) -> float | None:
    """The latitude, degrees north, in a session's ``location`` metadata ("LAT,LON" or
    "LAT,LON,ALT_KM", degrees north and east, as ``magcal flash --location`` takes it); None
    when there is none or it does not start with a latitude."""
    text = meta.get("location", "")
    try:
        lat = float(text.split(",")[0])
    except ValueError:
        return None
    return lat if -90.0 <= lat <= 90.0 else None


# --------------------------------------------------------------------------------------------
# Building and validating in memory


def session_from_arrays(
    t: np.ndarray,
    gyr: np.ndarray,
    acc: np.ndarray,
    mag: np.ndarray,
    meta: dict[str, str] | None = None,
    extra: dict[str, np.ndarray] | None = None,
) -> Session:
    """Validate arrays and wrap them in a :class:`Session` (float64 copies).

    t   : (N,) seconds, finite, strictly increasing, N ≥ 1
    gyr : (N, 3) rad/s;  acc : (N, 3) m/s²;  mag : (N, 3) raw magnetometer units
    meta: ``key -> value`` strings (keys without ``:``, no newlines anywhere)
    extra: more columns, name → (N,) float, NaN for an empty cell, finite otherwise; names
          are not those of the ten columns, and hold no ``,`` or blank

    ``acc`` and ``mag`` may have all-NaN rows (no such sample at that row: a multi-rate
    session); every other value must be finite, and at least one row must have the
    magnetometer. Raises :class:`SessionFormatError` naming the array and the (0-based)
    sample index.
    """
    t = np.array(t, dtype=np.float64)
    if t.ndim != 1:
        raise SessionFormatError(f"building a session: t must have shape (N,), got {t.shape}")
    n = t.shape[0]
    if n == 0:
        raise SessionFormatError("building a session: it has no samples; record some data")
    arrays = {"t": t}
    for name, value in (("gyr", gyr), ("acc", acc), ("mag", mag)):
        a = np.array(value, dtype=np.float64)
        if a.shape != (n, 3):
            raise SessionFormatError(
                f"building a session: {name} must have shape ({n}, 3) like t, got {a.shape}"
            )
        arrays[name] = a
    for name, a in arrays.items():
        bad = ~np.isfinite(a)
        if name in ("acc", "mag"):
            absent = np.isnan(a).all(axis=1)
            bad[absent] = False
        if bad.any():
            index = int(np.argwhere(bad)[0][0])
            raise SessionFormatError(
                f"building a session: {name} at sample {index} is not finite ({a[index]}); "
                "remove or repair that sample (a sample without this sensor is all NaN)"
            )
    if np.isnan(arrays["mag"][:, 0]).all():
        raise SessionFormatError(
            "building a session: no sample has a magnetometer reading; record the magnetometer"
        )
    steps = np.diff(t)
    if (steps <= 0).any():
        index = int(np.flatnonzero(steps <= 0)[0]) + 1
        raise SessionFormatError(
            f"building a session: t must be strictly increasing, but sample {index} has "
            f"t = {float(t[index])!r} after t = {float(t[index - 1])!r}"
        )
    meta = dict(meta or {})
    _check_meta(meta, "building a session")
    columns = _check_extra(extra or {}, n)
    return Session(
        t=t, gyr=arrays["gyr"], acc=arrays["acc"], mag=arrays["mag"], meta=meta, extra=columns
    )


def _check_extra(extra: dict[str, np.ndarray], n: int) -> dict[str, np.ndarray]:
    """float64 copies of the extra columns, checked (see :func:`session_from_arrays`)."""
    out = {}
    for name, value in extra.items():
        if not isinstance(name, str) or not name or name in COLUMNS or re.search(r"[,\s#]", name):
            raise SessionFormatError(
                f"building a session: extra column name {name!r} must be non-empty, without "
                "',', blanks or '#', and not one of the ten required columns"
            )
        a = np.array(value, dtype=np.float64)
        if a.shape != (n,):
            raise SessionFormatError(
                f"building a session: extra column {name} must have shape ({n},) like t, got "
                f"{a.shape}"
            )
        if np.isinf(a).any():
            index = int(np.flatnonzero(np.isinf(a))[0])
            raise SessionFormatError(
                f"building a session: extra column {name} at sample {index} is infinite; an "
                "empty cell is NaN"
            )
        out[name] = a
    return out


def _breaks_line(text: str) -> bool:
    """True if ``text`` holds anything the reader's ``str.splitlines`` splits at.

    That is more than \\n and \\r: also \\v, \\f, \\x1c-\\x1e, \\x85, \\u2028 and \\u2029. The
    sentinel makes a lone separator (``"\\x85".splitlines() == [""]``) count too.
    """
    return len((text + "x").splitlines()) != 1


def _check_meta(meta: dict[str, str], operation: str) -> None:
    for key, value in meta.items():
        if not isinstance(key, str) or not isinstance(value, str):
            raise SessionFormatError(f"{operation}: metadata {key!r} must map str to str")
        if not key.strip() or ":" in key or _breaks_line(key):
            raise SessionFormatError(
                f"{operation}: metadata key {key!r} must be non-empty without ':' or newlines"
            )
        if _breaks_line(value):
            raise SessionFormatError(
                f"{operation}: metadata {key!r} has a newline in its value (\\x85, \\u2028 "
                "and the other line separators count too): put it on one line"
            )
        try:
            (key + value).encode("utf-8")
        except UnicodeEncodeError:
            raise SessionFormatError(
                f"{operation}: metadata {key!r} is not valid Unicode text (a lone surrogate?)"
            ) from None
        if key.strip() == "magcal-session":
            raise SessionFormatError(f"{operation}: metadata key 'magcal-session' is reserved")


# --------------------------------------------------------------------------------------------
# Writing


def _multi_rate_rows(data: np.ndarray) -> list[str]:
    """Version 2 rows of ``data`` (N, 10 + extra columns): a NaN is an empty cell (a vector
    without a sample: three of them)."""
    rows = []
    for values in data.tolist():
        cells = ["" if math.isnan(v) else repr(v) for v in values]
        rows.append(",".join(cells) + "\n")
    return rows


def write_session(path: str | os.PathLike, session: Session) -> None:
    """Write ``session`` as a ``magcal-session`` CSV file: version 1 when every row has the
    accelerometer and the magnetometer (so readers of version 1 read it), version 2 (empty
    cells where a row lacks one) otherwise.

    Values are written with ``repr`` (shortest text that round-trips float64 exactly), so
    ``read_session(path)`` gives back bit-identical arrays.

    Extra columns (:attr:`Session.extra`) follow the ten; a session with an empty extra cell
    is written as version 2 (version 1 rows are plain numbers).
    """
    # Validate first so that we never write a file our own reader rejects.
    s = session_from_arrays(
        session.t, session.gyr, session.acc, session.mag, session.meta, session.extra
    )
    data = np.column_stack([s.t, s.gyr, s.acc, s.mag, *s.extra.values()])
    multi_rate = s.multi_rate or any(np.isnan(v).any() for v in s.extra.values())
    columns = COLUMNS + tuple(s.extra)
    row_format = ",".join(["%r"] * len(columns))  # %r of a Python float is its repr
    try:
        with open(path, "w", encoding="utf-8", newline="\n") as f:
            f.write((FIRST_LINE_MULTI_RATE if multi_rate else FIRST_LINE) + "\n")
            for key, value in s.meta.items():
                f.write(f"# {key.strip()}: {value}\n")
            f.write(",".join(columns) + "\n")
            # .tolist() gives Python floats, whose repr is plain (numpy 2 scalars print
            # np.float64).
            if multi_rate:
                f.writelines(_multi_rate_rows(data))
            else:
                f.writelines(row_format % tuple(row) + "\n" for row in data.tolist())
    except OSError as exc:
        raise SessionFileError(
            f"writing session {os.fspath(path)}: {os_error_advice(exc, path, writing=True)}"
        ) from exc


# --------------------------------------------------------------------------------------------
# Reading


def read_session(path: str | os.PathLike, min_samples: int = 0, extra: bool = False) -> Session:
    """Read a ``magcal-session`` CSV file, version 1 or 2 (multi-rate).

    path        : the file
    min_samples : reject sessions with fewer samples (the calling method's minimum)
    extra       : also read the columns beyond the ten into :attr:`Session.extra` (numbers,
                  an empty cell NaN); otherwise they are not parsed

    Columns may come in any order; extra columns are ignored (not even parsed). Raises
    :class:`SessionFormatError` whose message names the file, the 1-based line number and the
    problem (bad first line, missing columns, wrong field count, non-numeric or non-finite
    value, a partly empty vector, non-increasing time, no magnetometer sample, too few
    samples). Version 2 rows without an accelerometer or magnetometer sample have NaN there.
    """
    name = os.fspath(path)
    try:
        # utf-8-sig: tolerate the byte-order mark some Windows tools write.
        with open(path, encoding="utf-8-sig") as f:
            lines = f.read().splitlines()
    except UnicodeDecodeError as exc:
        raise SessionFormatError(f"reading session {name}: not UTF-8 text ({exc})") from exc
    except OSError as exc:
        raise SessionFileError(
            f"reading session {name}: {os_error_advice(exc, path, writing=False)}"
        ) from exc

    meta, header_index, version = _read_preamble(name, lines)
    columns = [c.strip() for c in lines[header_index].split(",")]
    usecols = _required_indices(name, header_index + 1, columns)
    first = header_index + 1  # index into `lines` of the first data row
    last = len(lines)
    while last > first and not lines[last - 1].strip():
        last -= 1  # trailing blank lines are harmless; keep them off the fast path

    data = _parse(name, lines, first, last, columns, usecols, version == MULTI_RATE_VERSION)

    n = data.shape[0]
    if n == 0:
        raise SessionFormatError(f"reading session {name}: it has no samples; record some data")
    if np.isnan(data[:, 7]).all():
        raise _error(
            name,
            header_index,
            "no row after this header has a magnetometer sample (all mag_* cells are empty); "
            "a session needs the magnetometer",
        )
    if n < min_samples:
        raise SessionFormatError(
            f"reading session {name}: session has {n} samples; calibration needs at least "
            f"{min_samples}: record longer"
        )
    more = _parse_extra(name, lines, first, last, columns, usecols) if extra else {}
    return Session(
        t=data[:, 0].copy(),
        gyr=data[:, 1:4].copy(),
        acc=data[:, 4:7].copy(),
        mag=data[:, 7:10].copy(),
        meta=meta,
        extra=more,
    )


def _parse_extra(
    name: str, lines: list[str], first: int, last: int, columns: list[str], usecols: list[int]
) -> dict[str, np.ndarray]:
    """The columns beyond the ten (rows already checked by :func:`_parse`): name → (N,)
    float, an empty cell NaN; a cell that is neither empty nor a finite number is refused."""
    wanted = [k for k in range(len(columns)) if k not in set(usecols)]
    if not wanted:
        return {}
    rows = [lines[i].split(",") for i in range(first, last) if lines[i].strip()]
    where = [i for i in range(first, last) if lines[i].strip()]
    out = {}
    for k in wanted:
        values = np.empty(len(rows))
        for r, fields in enumerate(rows):
            text = fields[k].strip()
            if not text:
                values[r] = math.nan
                continue
            try:
                if "_" in text:  # as the ten columns: Python's float() accepts "1_000"
                    raise ValueError
                values[r] = float(text)
            except ValueError:
                problem = f"column {columns[k]}: {text!r} is not a number"
                raise _error(name, where[r], problem) from None
            if not math.isfinite(values[r]):
                problem = f"column {columns[k]}: value {text!r} is not finite"
                raise _error(name, where[r], problem)
        out[columns[k]] = values
    return out


def _error(name: str, line_index: int, problem: str) -> SessionFormatError:
    """An error about ``lines[line_index]`` (reported 1-based, as an editor shows it)."""
    return SessionFormatError(f"reading session {name}: line {line_index + 1}: {problem}")


def _read_preamble(name: str, lines: list[str]) -> tuple[dict[str, str], int, str]:
    """Check the first line, collect ``# key: value`` metadata; return (meta, header index,
    version)."""
    if not lines:
        raise SessionFormatError(
            f"reading session {name}: the file is empty; expected first line {FIRST_LINE!r}"
        )
    first = lines[0].strip()
    key, _, version = first.lstrip("#").partition(":")
    if not first.startswith("#") or key.strip() != "magcal-session":
        raise _error(name, 0, _not_a_session(lines[0]))
    version = version.strip()
    if version not in SESSION_VERSIONS:
        raise _error(
            name,
            0,
            f"unsupported session version {version!r}; this reader knows versions "
            f"{' and '.join(SESSION_VERSIONS)}: upgrade magcal",
        )
    meta: dict[str, str] = {}
    for i in range(1, len(lines)):
        text = lines[i].strip()
        if not text:
            continue
        if not text.startswith("#"):
            return meta, i, version
        key, sep, value = text[1:].partition(":")
        if key.strip() == "magcal-session":
            raise _error(
                name,
                i,
                "a second 'magcal-session' line; the version goes on the first line only "
                "(are two files joined together?)",
            )
        # Comment lines without "key:" carry no metadata; they are allowed and ignored.
        if sep and key.strip():
            meta[key.strip()] = value.strip()
    raise SessionFormatError(
        f"reading session {name}: no header line after the metadata; expected {','.join(COLUMNS)!r}"
    )


def _not_a_session(first_line: str) -> str:
    """What a file whose first line is not ``magcal-session`` lacks, and how to add it."""
    layout = (
        "then one row per sample: t in seconds, the gyroscope in rad/s, the accelerometer in "
        f"m/s² ({FIRST_LINE_MULTI_RATE!r} instead when some rows lack the accelerometer or the "
        "magnetometer)"
    )
    header = {c.strip() for c in first_line.split(",")}
    if all(c in header for c in COLUMNS):
        return (
            f"expected {FIRST_LINE!r}, found the column header {first_line[:60]!r}: add the "
            f"line {FIRST_LINE!r} above it, as the file's first line; the header follows it, "
            + layout
        )
    return (
        f"expected {FIRST_LINE!r}, found {first_line[:60]!r}: not a magcal session. A CSV file "
        f"of samples becomes one with the line {FIRST_LINE!r} first, then the header line "
        f"{','.join(COLUMNS)!r} (the columns in any order), " + layout
    )


def _required_indices(name: str, header_line: int, columns: list[str]) -> list[int]:
    """Positions of the required columns in the header, in ``COLUMNS`` order."""
    missing = [c for c in COLUMNS if c not in columns]
    if missing:
        raise SessionFormatError(
            f"reading session {name}: line {header_line}: header lacks column(s) "
            f"{', '.join(missing)} (found: {', '.join(columns)}); the header must name "
            f"{','.join(COLUMNS)}"
        )
    duplicated = [c for c in COLUMNS if columns.count(c) > 1]
    if duplicated:
        raise SessionFormatError(
            f"reading session {name}: line {header_line}: header repeats column(s) "
            f"{', '.join(duplicated)}"
        )
    return [columns.index(c) for c in COLUMNS]


def _parse(
    name: str,
    lines: list[str],
    first: int,
    last: int,
    columns: list[str],
    usecols: list[int],
    multi_rate: bool = False,
) -> np.ndarray:
    """Parse the data rows ``lines[first:last]`` into an (N, 10) array in ``COLUMNS`` order;
    ``multi_rate`` (version 2): empty acc/mag vectors are NaN rows."""
    data = _parse_fast(lines[first:last], len(columns), usecols, -math.inf, multi_rate)
    if data is not None:
        return data
    # Something is wrong, or merely unusual (a blank line). Re-parse in chunks so that only the
    # chunk holding the first problem is scanned line by line: an error near the end of a
    # 600k-row file is then found in about the time of one fast parse.
    parts = [np.empty((0, len(COLUMNS)))]
    previous_t, previous_line = -math.inf, first
    for start in range(first, last, RESCAN_CHUNK_ROWS):
        stop = min(start + RESCAN_CHUNK_ROWS, last)
        part = _parse_fast(lines[start:stop], len(columns), usecols, previous_t, multi_rate)
        if part is None:
            part, previous_line = _parse_slow(
                name, lines, start, stop, columns, usecols, previous_t, previous_line, multi_rate
            )
        elif len(part):
            previous_line = stop - 1  # a chunk that passed has no blank lines
        if len(part):
            previous_t = float(part[-1, 0])
        parts.append(part)
    return np.concatenate(parts)


#: An empty cell after a separator, for the version 2 fast path (the rows joined with a
#: trailing newline). Blank cells and an empty first cell fail ``loadtxt`` and fall to the
#: slow path, which judges them; a simple pattern keeps the fast path fast.
_EMPTY_CELL = re.compile(r",(?=,|\n)")


def _parse_fast(
    rows: list[str], n_fields: int, usecols: list[int], previous_t: float, multi_rate: bool = False
) -> np.ndarray | None:
    """Vectorised parse of data rows; ``None`` if anything at all is off.

    previous_t : the time of the sample before ``rows[0]`` (``-inf`` if none), s
    multi_rate : version 2: an all-empty acc or mag vector becomes a NaN row
    """
    if not rows:
        return np.empty((0, len(COLUMNS)))
    # loadtxt ignores fields outside usecols, so count the fields of every row ourselves.
    # This also sends blank lines (0 commas) to the slow path, which skips them.
    commas = n_fields - 1
    if any(row.count(",") != commas for row in rows):
        return None
    if multi_rate:
        text = "\n".join(rows)
        # Spelled-out values (nan, inf) must not pass as empty cells: the slow path judges.
        if "n" in text or "N" in text:
            return None
        rows = _EMPTY_CELL.sub(",nan", text + "\n")[:-1].split("\n")
    try:
        data = np.loadtxt(rows, delimiter=",", comments=None, usecols=usecols, ndmin=2)
    except ValueError:
        return None
    if data.shape != (len(rows), len(COLUMNS)):
        return None
    finite = np.isfinite(data)
    if multi_rate:
        for sl in (slice(4, 7), slice(7, 10)):
            absent = np.isnan(data[:, sl])
            whole = absent.all(axis=1)
            if (absent.any(axis=1) != whole).any():
                return None  # a partly empty vector: the slow path names the line
            finite[whole, sl] = True
    if not finite.all():
        return None
    if data[0, 0] <= previous_t or (np.diff(data[:, 0]) <= 0).any():
        return None
    return data


def _parse_slow(
    name: str,
    lines: list[str],
    first: int,
    last: int,
    columns: list[str],
    usecols: list[int],
    previous_t: float,
    previous_line: int,
    multi_rate: bool = False,
) -> tuple[np.ndarray, int]:
    """Line-by-line parse that raises on the first bad line (the reference semantics).

    previous_t, previous_line : time and line index of the sample before ``lines[first]``
    multi_rate : version 2: the three cells of acc or mag may be empty together (NaN)
    Returns the (n, 10) data and the line index of its last sample.
    """
    out: list[list[float]] = []
    for i in range(first, last):
        line = lines[i]
        if not line.strip():
            continue
        fields = line.split(",")
        if len(fields) != len(columns):
            raise _error(
                name,
                i,
                f"has {len(fields)} fields but the header has {len(columns)}; "
                "the row is truncated or has extra separators",
            )
        values = []
        empty = [False] * len(COLUMNS)
        if multi_rate:
            for start in (4, 7):
                cells = [fields[usecols[j]].strip() == "" for j in range(start, start + 3)]
                if all(cells):
                    empty[start : start + 3] = [True] * 3
                elif any(cells):
                    names = COLUMNS[start : start + 3]
                    blank = ", ".join(c for c, e in zip(names, cells, strict=True) if e)
                    raise _error(
                        name,
                        i,
                        f"{blank} empty but not all of {', '.join(names)}: a vector is "
                        "either complete or empty (no sample at that time)",
                    )
        for j, k in enumerate(usecols):
            if empty[j]:
                values.append(math.nan)
                continue
            text = fields[k]
            # Python's float() accepts "1_000"; numpy's parser (the fast path) does not.
            try:
                if "_" in text:
                    raise ValueError
                value = float(text)
            except ValueError:
                raise _error(
                    name, i, f"column {columns[k]}: {text.strip()!r} is not a number"
                ) from None
            if not math.isfinite(value):
                raise _error(
                    name,
                    i,
                    f"column {columns[k]}: value {text.strip()!r} is not finite; "
                    "remove or repair that sample",
                )
            values.append(value)
        t = values[0]
        if t <= previous_t:
            raise _error(
                name,
                i,
                f"time t = {t!r} s is not after t = {previous_t!r} s on line "
                f"{previous_line + 1}; t must be strictly increasing",
            )
        previous_t, previous_line = t, i
        out.append(values)
    return np.array(out, dtype=np.float64).reshape(-1, len(COLUMNS)), previous_line
