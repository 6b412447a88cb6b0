# SPDX-License-Identifier: Apache-2.0
"""Session CSV files: round trip, tolerated variations, and every error path."""

from __future__ import annotations

import os

import numpy as np
import pytest

import magcal.io.session as session_module
from magcal.errors import MagcalError, SessionFormatError
from magcal.io.session import (
    COLUMNS,
    Session,
    SessionFileError,
    check_writable,
    read_session,
    session_from_arrays,
    write_session,
)

HEADER = "t,gyr_x,gyr_y,gyr_z,acc_x,acc_y,acc_z,mag_x,mag_y,mag_z"


def make_session(n: int = 50, seed: int = 0, meta: dict[str, str] | None = None) -> Session:
    rng = np.random.default_rng(seed)
    t = 12.5 + 0.01 * np.arange(n) + 1e-4 * rng.random(n)
    return session_from_arrays(
        t,
        rng.normal(scale=0.3, size=(n, 3)),
        rng.normal(scale=9.81, size=(n, 3)),
        rng.normal(scale=40.0, size=(n, 3)),
        meta if meta is not None else {"source": "unit test", "mag_unit": "uT"},
    )


def write_text(tmp_path, text: str, name: str = "s.csv"):
    path = tmp_path / name
    path.write_text(text, encoding="utf-8")
    return path


def good_rows(n: int = 3) -> list[str]:
    return [f"{0.01 * i!r},0,0,0,0,0,9.81,20,0,-40" for i in range(n)]


def session_text(rows: list[str], header: str = HEADER, meta: str = "# source: x\n") -> str:
    return "# magcal-session: 1\n" + meta + header + "\n" + "\n".join(rows) + "\n"


# ---------------------------------------------------------------------------------------------
# Round trip and accepted variations


def test_round_trip_is_bit_exact(tmp_path):
    s = make_session(200)
    # Values that are hard to print: tiny, huge, negative zero, many significant digits.
    s.mag[0] = [1e-300, -0.0, 0.1 + 0.2]
    s.acc[1] = [1.7976931348623157e308, 5e-324, 1 / 3]
    path = tmp_path / "s.csv"
    write_session(path, s)
    r = read_session(path)
    for name in ("t", "gyr", "acc", "mag"):
        a, b = getattr(s, name), getattr(r, name)
        assert a.shape == b.shape
        assert a.tobytes() == b.tobytes(), name  # bit-identical, including the sign of zero
    assert r.meta == {"source": "unit test", "mag_unit": "uT"}
    assert len(r) == 200


def test_written_file_follows_the_contract(tmp_path):
    path = tmp_path / "s.csv"
    write_session(path, make_session(3, meta={"source": "dev 7"}))
    lines = path.read_text().splitlines()
    assert lines[0] == "# magcal-session: 1"
    assert lines[1] == "# source: dev 7"
    assert lines[2] == HEADER
    assert len(lines) == 6
    assert all(len(row.split(",")) == 10 for row in lines[3:])
    assert COLUMNS == tuple(HEADER.split(","))


def test_columns_in_any_order_and_extra_columns_ignored(tmp_path):
    header = "note,mag_z,mag_y,mag_x,t,acc_z,acc_y,acc_x,gyr_z,gyr_y,gyr_x,temp"
    rows = [
        "hello,-40,2,20,0.5,9.8,0.2,0.1,0.03,0.02,0.01,25.5",
        "not a number,-41,3,21,0.6,9.7,0.3,0.2,0.06,0.05,0.04,nan",
    ]
    s = read_session(write_text(tmp_path, session_text(rows, header)))
    np.testing.assert_array_equal(s.t, [0.5, 0.6])
    np.testing.assert_array_equal(s.gyr, [[0.01, 0.02, 0.03], [0.04, 0.05, 0.06]])
    np.testing.assert_array_equal(s.acc, [[0.1, 0.2, 9.8], [0.2, 0.3, 9.7]])
    np.testing.assert_array_equal(s.mag, [[20, 2, -40], [21, 3, -41]])


def test_metadata_parsing(tmp_path):
    meta = "# source: Xsens MTi-100: serial 42\n#mag_unit:uT   \n# a free comment without a key\n\n"
    s = read_session(write_text(tmp_path, session_text(good_rows(), meta=meta)))
    # Only the first ':' separates key from value; values are stripped.
    assert s.meta == {"source": "Xsens MTi-100: serial 42", "mag_unit": "uT"}


def test_tolerates_bom_crlf_blank_lines_and_spaces(tmp_path):
    rows = good_rows(4)
    rows[2] = " " + rows[2].replace(",", " , ")
    text = session_text(rows[:2] + [""] + rows[2:]) + "\n\n"
    path = tmp_path / "s.csv"
    path.write_bytes(b"\xef\xbb\xbf" + text.replace("\n", "\r\n").encode())
    s = read_session(path)
    np.testing.assert_array_equal(s.t, [0.0, 0.01, 0.02, 0.03])


def test_metadata_with_unusual_characters_round_trips(tmp_path):
    # Everything that is not a line separator survives: tabs, NUL, other scripts, emoji.
    meta = {"source": "a\tb\x00c ÅÄÖ ☃ 🧲", "note": "", "x_y-z.1": "1: 2: 3"}
    path = tmp_path / "s.csv"
    write_session(path, make_session(3, meta=meta))
    assert read_session(path).meta == meta


# Every character str.splitlines() splits at: the reader sees a new line there.
LINE_SEPARATORS = ["\n", "\r", "\v", "\f", "\x1c", "\x1d", "\x1e", "\x85", "\u2028", "\u2029"]


@pytest.mark.parametrize("sep", LINE_SEPARATORS)
def test_write_rejects_every_line_separator_in_metadata(tmp_path, sep):
    path = tmp_path / "s.csv"
    for meta in ({"source": f"one{sep}# two: 2"}, {"source": sep}, {f"so{sep}urce": "x"}):
        with pytest.raises(SessionFormatError, match="newline"):
            write_session(path, Session(*arrays(), meta=meta))  # bypasses validation
        assert not path.exists()
    # Without the check the file would read back differently (or not at all):
    text = f"# magcal-session: 1\n# source: one{sep}# two: 2\n{HEADER}\n" + "\n".join(good_rows())
    assert read_session(write_text(tmp_path, text, "raw.csv")).meta != {
        "source": f"one{sep}# two: 2"
    }


def test_write_rejects_unencodable_metadata(tmp_path):
    path = tmp_path / "s.csv"
    with pytest.raises(SessionFormatError, match="not valid Unicode"):
        write_session(path, Session(*arrays(), meta={"source": "\ud800"}))
    assert not path.exists()


def test_second_version_line_is_rejected_not_kept_as_metadata(tmp_path):
    text = session_text(good_rows(), meta="# source: x\n# magcal-session: 1\n")
    with pytest.raises(SessionFormatError, match="line 3: a second 'magcal-session' line"):
        read_session(write_text(tmp_path, text))


def test_time_need_not_start_at_zero(tmp_path):
    rows = [f"{1e6 + i},0,0,0,0,0,9.81,1,0,0" for i in range(3)]
    assert read_session(write_text(tmp_path, session_text(rows))).t[0] == 1e6


def test_min_samples_met(tmp_path):
    assert len(read_session(write_text(tmp_path, session_text(good_rows(5))), 5)) == 5


def test_errors_are_magcal_errors():
    assert issubclass(SessionFormatError, MagcalError)


def _without_the_slow_path(monkeypatch):
    """Valid files are read by the vectorised parse alone: the line-by-line re-scan fails."""
    monkeypatch.setattr(session_module, "_parse_slow", lambda *a, **k: pytest.fail("re-scan"))


def test_reads_60k_rows_back_exactly(tmp_path, monkeypatch):
    # A ten-minute 100 Hz session, by the fast path; its reading time is not a test bound
    # (it depends on how busy the host is).
    _without_the_slow_path(monkeypatch)
    path = tmp_path / "big.csv"
    s = make_session(60_000)
    write_session(path, s)
    r = read_session(path)
    assert r.mag.tobytes() == s.mag.tobytes()
    assert r.t.tobytes() == s.t.tobytes()


# ---------------------------------------------------------------------------------------------
# Error paths of read_session: each names the file, the line and the problem


def test_error_names_the_file(tmp_path):
    path = write_text(tmp_path, "t,x\n", name="named.csv")
    with pytest.raises(SessionFormatError, match=r"named\.csv"):
        read_session(path)


def test_missing_file(tmp_path):
    path = tmp_path / "nope.csv"
    with pytest.raises(SessionFileError, match=r"reading session .*nope\.csv: no such file"):
        read_session(path)


def test_directory_instead_of_file(tmp_path):
    with pytest.raises(SessionFileError, match="it is a directory: give a file name"):
        read_session(tmp_path)


def test_write_into_missing_directory(tmp_path):
    path = tmp_path / "no" / "s.csv"
    with pytest.raises(
        SessionFileError, match=r"writing session .*: directory .*no does not exist"
    ):
        write_session(path, make_session(3))


def test_file_errors_are_session_format_errors():
    assert issubclass(SessionFileError, SessionFormatError)


def test_check_writable(tmp_path):
    check_writable(tmp_path / "new.json", "writing result")  # a fresh file in a directory
    assert list(tmp_path.iterdir()) == []  # the probe leaves nothing behind
    with pytest.raises(SessionFileError, match=r"writing result .*: directory .*no does not exist"):
        check_writable(tmp_path / "no" / "r.json", "writing result")
    (tmp_path / "file").write_text("")
    with pytest.raises(SessionFileError, match=r"directory .*file is not a directory"):
        check_writable(tmp_path / "file" / "r.json", "writing result")
    with pytest.raises(SessionFileError, match="it is a directory"):
        check_writable(tmp_path, "writing result")


@pytest.mark.skipif(not hasattr(os, "geteuid") or os.geteuid() == 0, reason="root may write")
def test_check_writable_read_only_directory(tmp_path):
    d = tmp_path / "ro"
    d.mkdir()
    d.chmod(0o500)
    try:
        with pytest.raises(SessionFileError, match="cannot create files in directory"):
            check_writable(d / "r.json", "writing result")
    finally:
        d.chmod(0o700)


def test_empty_file(tmp_path):
    with pytest.raises(SessionFormatError, match="file is empty"):
        read_session(write_text(tmp_path, ""))


def test_missing_first_line(tmp_path):
    with pytest.raises(SessionFormatError, match=r"line 1: expected '# magcal-session: 1'"):
        read_session(write_text(tmp_path, HEADER + "\n" + "\n".join(good_rows()) + "\n"))


def test_wrong_version(tmp_path):
    text = session_text(good_rows()).replace("magcal-session: 1", "magcal-session: 3")
    with pytest.raises(SessionFormatError, match=r"line 1: unsupported session version '3'"):
        read_session(write_text(tmp_path, text))


def test_no_header(tmp_path):
    with pytest.raises(SessionFormatError, match="no header line"):
        read_session(write_text(tmp_path, "# magcal-session: 1\n# source: x\n"))


def test_missing_columns_are_named(tmp_path):
    header = "t,gyr_x,gyr_y,gyr_z,acc_x,acc_y,acc_z,mag_x"
    rows = ["0,0,0,0,0,0,9.8,1", "1,0,0,0,0,0,9.8,1"]
    with pytest.raises(SessionFormatError, match=r"line 3: header lacks column\(s\) mag_y, mag_z"):
        read_session(write_text(tmp_path, session_text(rows, header)))


def test_duplicated_column(tmp_path):
    header = HEADER + ",mag_x"
    rows = [r + ",5" for r in good_rows()]
    with pytest.raises(SessionFormatError, match=r"line 3: header repeats column\(s\) mag_x"):
        read_session(write_text(tmp_path, session_text(rows, header)))


def test_non_numeric_value(tmp_path):
    rows = good_rows(5)
    rows[3] = "0.03,0,0,0,0,abc,9.81,20,0,-40"
    # first data row is line 4, so rows[3] is line 7
    with pytest.raises(SessionFormatError, match=r"line 7: column acc_y: 'abc' is not a number"):
        read_session(write_text(tmp_path, session_text(rows)))


def test_empty_value(tmp_path):
    rows = good_rows(3)
    rows[1] = "0.01,0,0,0,0,0,9.81,20,,-40"
    with pytest.raises(SessionFormatError, match=r"line 5: column mag_y: '' is not a number"):
        read_session(write_text(tmp_path, session_text(rows)))


def test_underscore_number_is_rejected(tmp_path):
    rows = good_rows(3)
    rows[2] = "0.02,0,0,0,0,0,9.81,2_0,0,-40"
    with pytest.raises(SessionFormatError, match=r"line 6: column mag_x: '2_0' is not a number"):
        read_session(write_text(tmp_path, session_text(rows)))


@pytest.mark.parametrize("bad", ["nan", "inf", "-Infinity", "1e999"])
def test_non_finite_value(tmp_path, bad):
    rows = good_rows(4)
    rows[2] = f"0.02,0,{bad},0,0,0,9.81,20,0,-40"
    with pytest.raises(SessionFormatError, match=r"line 6: column gyr_y: value .* is not finite"):
        read_session(write_text(tmp_path, session_text(rows)))


def test_non_increasing_time_names_both_times(tmp_path):
    rows = good_rows(4)
    rows[2] = "0.005,0,0,0,0,0,9.81,20,0,-40"
    pattern = r"line 6: time t = 0\.005 s is not after t = 0\.01 s on line 5"
    with pytest.raises(SessionFormatError, match=pattern):
        read_session(write_text(tmp_path, session_text(rows)))


def test_repeated_time(tmp_path):
    rows = good_rows(3) + ["0.02,0,0,0,0,0,9.81,20,0,-40"]
    with pytest.raises(SessionFormatError, match=r"line 7: time t = 0\.02 s is not after"):
        read_session(write_text(tmp_path, session_text(rows)))


def test_time_after_blank_line_names_the_right_lines(tmp_path):
    rows = good_rows(2) + ["", "0.0,0,0,0,0,0,9.81,20,0,-40"]
    with pytest.raises(SessionFormatError, match=r"line 7: time .* on line 5"):
        read_session(write_text(tmp_path, session_text(rows)))


@pytest.mark.parametrize(
    ("row", "count"),
    [("0.02,0,0,0,0,0,9.81,20,0", 9), ("0.02,0,0,0,0,0,9.81,20,0,-40,7", 11)],
)
def test_wrong_number_of_fields(tmp_path, row, count):
    rows = good_rows(2) + [row] + good_rows(4)[3:]
    with pytest.raises(
        SessionFormatError, match=rf"line 6: has {count} fields but the header has 10"
    ):
        read_session(write_text(tmp_path, session_text(rows)))


def test_wrong_number_of_fields_in_an_extra_column(tmp_path):
    # The missing field is one the reader ignores; the row is still malformed.
    rows = [r + ",x" for r in good_rows(3)]
    rows[1] = rows[1][:-2]
    with pytest.raises(SessionFormatError, match="line 5: has 10 fields but the header has 11"):
        read_session(write_text(tmp_path, session_text(rows, HEADER + ",note")))


def test_first_bad_line_is_reported(tmp_path):
    rows = good_rows(6)
    rows[4] = "0.04,0,0,0,0,0,9.81,20,0,nan"
    rows[2] = "0.02,0,0,0,0,0,9.81,oops,0,-40"
    with pytest.raises(SessionFormatError, match="line 6: column mag_x: 'oops'"):
        read_session(write_text(tmp_path, session_text(rows)))


def test_error_deep_in_a_large_file(tmp_path):
    path = tmp_path / "big.csv"
    write_session(path, make_session(5_000))
    lines = path.read_text().splitlines()
    fields = lines[4_000].split(",")
    fields[8] = "12x"
    lines[4_000] = ",".join(fields)
    path.write_text("\n".join(lines) + "\n")
    with pytest.raises(SessionFormatError, match=r"line 4001: column mag_y: '12x'"):
        read_session(path)


def test_no_samples(tmp_path):
    with pytest.raises(SessionFormatError, match="no samples"):
        read_session(write_text(tmp_path, session_text([])))


def test_too_few_samples(tmp_path):
    path = write_text(tmp_path, session_text(good_rows(210)))
    pattern = "session has 210 samples; calibration needs at least 500: record longer"
    with pytest.raises(SessionFormatError, match=pattern):
        read_session(path, min_samples=500)


def test_not_utf8(tmp_path):
    path = tmp_path / "s.csv"
    path.write_bytes(b"# magcal-session: 1\n\xff\xfe\n")
    with pytest.raises(SessionFormatError, match="not UTF-8"):
        read_session(path)


# ---------------------------------------------------------------------------------------------
# session_from_arrays and write_session validation


def arrays(n: int = 5):
    t = np.arange(n, dtype=float)
    return t, np.zeros((n, 3)), np.zeros((n, 3)), np.ones((n, 3))


def test_from_arrays_copies_as_float64():
    t, g, a, _ = arrays()
    m_int = np.ones((5, 3), dtype=int)
    s = session_from_arrays(t, g, a, m_int)
    assert s.mag.dtype == np.float64
    t[0] = -5.0
    assert s.t[0] == 0.0
    assert s.meta == {}


def test_from_arrays_bad_t_shape():
    _, g, a, m = arrays()
    with pytest.raises(SessionFormatError, match=r"t must have shape \(N,\)"):
        session_from_arrays(np.zeros((5, 1)), g, a, m)


def test_from_arrays_empty():
    with pytest.raises(SessionFormatError, match="no samples"):
        session_from_arrays(np.zeros(0), np.zeros((0, 3)), np.zeros((0, 3)), np.zeros((0, 3)))


@pytest.mark.parametrize("which", [1, 2, 3])
def test_from_arrays_bad_vector_shape(which):
    args = list(arrays())
    args[which] = np.zeros((4, 3))
    name = ["t", "gyr", "acc", "mag"][which]
    with pytest.raises(SessionFormatError, match=rf"{name} must have shape \(5, 3\) like t"):
        session_from_arrays(*args)


@pytest.mark.parametrize(("which", "name"), [(0, "t"), (1, "gyr"), (2, "acc"), (3, "mag")])
def test_from_arrays_non_finite_names_sample(which, name):
    args = [x.copy() for x in arrays()]
    if which == 0:
        args[0][3] = np.nan
    else:
        args[which][3, 1] = np.inf
    with pytest.raises(SessionFormatError, match=rf"{name} at sample 3 is not finite"):
        session_from_arrays(*args)


def test_from_arrays_non_increasing_names_sample():
    t, g, a, m = arrays()
    t[2] = 1.0
    with pytest.raises(SessionFormatError, match=r"sample 2 has t = 1\.0 after t = 1\.0"):
        session_from_arrays(t, g, a, m)


@pytest.mark.parametrize(
    ("meta", "pattern"),
    [
        ({"a:b": "x"}, "must be non-empty without ':'"),
        ({"": "x"}, "must be non-empty"),
        ({"source": "two\nlines"}, "newline in its value"),
        ({"magcal-session": "2"}, "reserved"),
        ({"source": 3}, "must map str to str"),
    ],
)
def test_from_arrays_bad_meta(meta, pattern):
    with pytest.raises(SessionFormatError, match=pattern):
        session_from_arrays(*arrays(), meta=meta)


def test_write_rejects_invalid_session(tmp_path):
    t, g, a, m = arrays()
    m[1, 0] = np.nan
    bad = Session(t=t, gyr=g, acc=a, mag=m)  # bypasses validation
    path = tmp_path / "s.csv"
    with pytest.raises(SessionFormatError, match="mag at sample 1 is not finite"):
        write_session(path, bad)
    assert not path.exists()


# ---------------------------------------------------------------------------------------------
# The chunked re-scan (used when the fast parse fails) must agree with a plain scan.


@pytest.fixture
def small_chunks(monkeypatch):
    import magcal.io.session as session_module

    monkeypatch.setattr(session_module, "RESCAN_CHUNK_ROWS", 3)


def test_rescan_with_blank_lines_reads_all_rows(tmp_path, small_chunks):
    rows = good_rows(10)
    rows.insert(4, "")  # forces the re-scan; the file is still valid
    s = read_session(write_text(tmp_path, session_text(rows)))
    np.testing.assert_array_equal(s.t, [0.01 * i for i in range(10)])


@pytest.mark.parametrize("bad_row", [3, 4, 5, 6])
def test_rescan_detects_time_going_back_at_chunk_boundaries(tmp_path, small_chunks, bad_row):
    rows = good_rows(9)
    rows[bad_row] = "0.0,0,0,0,0,0,9.81,20,0,-40"
    line = bad_row + 4
    with pytest.raises(SessionFormatError, match=rf"line {line}: time .* on line {line - 1}"):
        read_session(write_text(tmp_path, session_text(rows)))


def test_rescan_names_the_right_previous_line_across_a_blank(tmp_path, small_chunks):
    rows = good_rows(3) + ["", "0.0,0,0,0,0,0,9.81,20,0,-40"] + good_rows(8)[5:]
    with pytest.raises(SessionFormatError, match=r"line 8: time t = 0\.0 s .* on line 6"):
        read_session(write_text(tmp_path, session_text(rows)))


# ---------------------------------------------------------------------------------------------
# Version 2: multi-rate sessions (rows without the accelerometer or the magnetometer)


def make_multi_rate_session(n: int = 300, every: int = 4, seed: int = 3) -> Session:
    """An IMU at every row, the magnetometer at every ``every``-th, one row without acc."""
    rng = np.random.default_rng(seed)
    t = 0.005 * np.arange(n) + 1e-5 * rng.random(n)
    acc = rng.normal(scale=9.81, size=(n, 3))
    mag = rng.normal(scale=40.0, size=(n, 3))
    mag[np.arange(n) % every != 0] = np.nan
    acc[every] = np.nan  # a magnetometer row between IMU samples
    return session_from_arrays(t, rng.normal(scale=0.3, size=(n, 3)), acc, mag, {"source": "x"})


def test_multi_rate_round_trip_is_bit_exact(tmp_path):
    s = make_multi_rate_session()
    s.mag[0] = [1e-300, -0.0, 0.1 + 0.2]
    path = tmp_path / "s.csv"
    write_session(path, s)
    text = path.read_text(encoding="utf-8")
    assert text.startswith("# magcal-session: 2\n")
    assert ",,," in text  # empty mag cells
    back = read_session(path)
    for name in ("t", "gyr", "acc", "mag"):
        a, b = getattr(s, name), getattr(back, name)
        np.testing.assert_array_equal(np.isnan(a), np.isnan(b))
        assert a[~np.isnan(a)].tobytes() == b[~np.isnan(b)].tobytes()
    np.testing.assert_array_equal(back.has_mag, np.arange(len(s)) % 4 == 0)
    assert not back.has_acc[4] and back.has_acc.sum() == len(s) - 1
    assert back.multi_rate


def test_single_rate_session_is_written_as_version_1(tmp_path):
    s = make_session(20)
    path = tmp_path / "s.csv"
    write_session(path, s)
    assert path.read_text(encoding="utf-8").startswith("# magcal-session: 1\n")
    back = read_session(path)
    assert back.has_acc.all() and back.has_mag.all() and not back.multi_rate


def test_version_1_refuses_empty_cells(tmp_path):
    rows = good_rows(3)
    rows[1] = "0.01,0,0,0,,,,20,0,-40"
    with pytest.raises(SessionFormatError, match=r"line 5: column acc_x: '' is not a number"):
        read_session(write_text(tmp_path, session_text(rows)))


def v2_text(rows: list[str]) -> str:
    return "# magcal-session: 2\n# source: x\n" + HEADER + "\n" + "\n".join(rows) + "\n"


@pytest.mark.parametrize("pad", ["", " "])
def test_version_2_reads_empty_vectors_slow_and_fast(tmp_path, pad):
    rows = good_rows(6)
    rows[1] = f"0.01,0,0,0,{pad},{pad},{pad},20,0,-40"
    rows[2] = f"0.02,0,0,0,0,0,9.81,{pad},{pad},{pad}"
    rows[3] = "0.03 ,0,0,0,0,0,9.81,,,"  # blank after a number
    s = read_session(write_text(tmp_path, v2_text(rows)))
    np.testing.assert_array_equal(s.has_acc, [True, False, True, True, True, True])
    np.testing.assert_array_equal(s.has_mag, [True, True, False, False, True, True])
    assert s.acc[0, 2] == 9.81 and s.t[3] == 0.03


@pytest.mark.parametrize(
    "cells, message",
    [
        (",0,9.81,20,0,-40", r"line 5: acc_x empty but not all of acc_x, acc_y, acc_z"),
        ("0,0,9.81,20,,-40", r"line 5: mag_y empty but not all of mag_x, mag_y, mag_z"),
        ("0,0,9.81,,0,", r"line 5: mag_x, mag_z empty but not all"),
        ("0,0,9.81,nan,nan,nan", r"line 5: column mag_x: value 'nan' is not finite"),
    ],
)
def test_version_2_errors_name_the_line(tmp_path, cells, message):
    rows = good_rows(5000)  # long enough for the chunked re-scan
    rows[1] = f"0.01,0,0,0,{cells}"
    with pytest.raises(SessionFormatError, match=message):
        read_session(write_text(tmp_path, v2_text(rows)))


def test_version_2_empty_gyroscope_is_an_error(tmp_path):
    rows = good_rows(3)
    rows[2] = "0.02,,,,0,0,9.81,20,0,-40"
    with pytest.raises(SessionFormatError, match=r"line 6: column gyr_x: '' is not a number"):
        read_session(write_text(tmp_path, v2_text(rows)))


def test_version_2_without_magnetometer_is_an_error(tmp_path):
    rows = [f"{0.01 * i!r},0,0,0,0,0,9.81,,," for i in range(4)]
    with pytest.raises(SessionFormatError, match=r"line 3: no row .* has a magnetometer sample"):
        read_session(write_text(tmp_path, v2_text(rows)))


def test_session_from_arrays_checks_nan_rows():
    n = 5
    t, v = np.arange(n, dtype=float), np.ones((n, 3))
    mag = v.copy()
    mag[2] = np.nan
    assert session_from_arrays(t, v, v, mag).has_mag.sum() == 4
    mag[2, 0] = 1.0  # partly NaN
    with pytest.raises(SessionFormatError, match="mag at sample 2 is not finite"):
        session_from_arrays(t, v, v, mag)
    with pytest.raises(SessionFormatError, match="no sample has a magnetometer"):
        session_from_arrays(t, v, v, np.full((n, 3), np.nan))
    gyr = v.copy()
    gyr[1] = np.nan
    with pytest.raises(SessionFormatError, match="gyr at sample 1 is not finite"):
        session_from_arrays(t, gyr, v, v)


def test_version_2_large_file_fast_path_is_exact(tmp_path, monkeypatch):
    _without_the_slow_path(monkeypatch)
    s = make_multi_rate_session(n=20000, every=7)
    path = tmp_path / "s.csv"
    write_session(path, s)
    back = read_session(path)
    np.testing.assert_array_equal(np.nan_to_num(back.mag, nan=7.5), np.nan_to_num(s.mag, nan=7.5))
    np.testing.assert_array_equal(np.nan_to_num(back.acc, nan=7.5), np.nan_to_num(s.acc, nan=7.5))
