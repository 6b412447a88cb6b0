# SPDX-License-Identifier: Apache-2.0
"""Parameter values on the MAVLink wire and in .parm / .params files (magcal.autopilot.params)."""

from __future__ import annotations

import struct

import numpy as np
import pytest

from magcal.autopilot import params as P


@pytest.mark.parametrize("value", [0, 2, 38, 100, -1, 2**31 - 1, -(2**31)])
def test_px4_int32_travels_bytewise_and_comes_back(value):
    wire = P.encode(value, P.INT32, P.BYTEWISE)
    assert struct.pack("<f", wire) == struct.pack("<i", value)  # the int's bytes, not its value
    assert P.decode(wire, P.INT32, P.BYTEWISE) == value


def test_ardupilot_integers_travel_as_their_value():
    assert P.encode(101, P.INT8, P.C_CAST) == 101.0
    assert P.decode(101.0, P.INT8, P.C_CAST) == 101


def test_real32_is_held_as_float32_and_confirmed_by_float32_equality():
    v = 0.1
    held = P.held_value(v, P.REAL32)
    assert held == float(np.float32(0.1)) and held != 0.1
    assert P.confirmed(v, held, P.REAL32)
    assert not P.confirmed(v, np.nextafter(np.float32(held), np.float32(1)), P.REAL32)
    assert P.confirmed(3, 3.0, P.INT8) and not P.confirmed(3, 4.0, P.INT8)


@pytest.mark.parametrize(
    ("value", "ptype", "match"),
    [(1.5, P.INT8, "not a whole number"), (200, P.INT8, "INT8 range"), (1, 10, "4-byte")],
)
def test_values_the_type_cannot_hold_are_refused(value, ptype, match):
    with pytest.raises(P.ParamError, match=match):
        P.held_value(value, ptype, "X")


def _pf():
    entries = (
        P.ParamEntry("COMPASS_OFS_X", P.held_value(-339.0064, P.REAL32), P.REAL32),
        P.ParamEntry("COMPASS_DIA_Y", P.held_value(1.0 / 3.0, P.REAL32), P.REAL32),
        P.ParamEntry("COMPASS_ODI_Z", P.held_value(-3.4679e-4, P.REAL32), P.REAL32),
        P.ParamEntry("COMPASS_ORIENT", 101.0, P.INT8),
        P.ParamEntry("CAL_MAG0_ROT", -1.0, P.INT32),
    )
    return P.ParamFile(entries, system_id=7, component_id=1, comments=("a comment",))


def test_mission_planner_parm_round_trips_to_the_same_float32(tmp_path):
    path = tmp_path / "x.parm"
    path.write_text(P.format_parm(_pf()))
    text = path.read_text()
    assert "COMPASS_ORIENT,101\n" in text and text.startswith("# a comment\n")
    values = [line.split(",")[1] for line in text.splitlines() if not line.startswith("#")]
    assert values[2] == "-0.00034679" and not any("e" in v.lower() for v in values)  # no exponent
    back = P.read_param_file(path)
    for a, b in zip(_pf().entries, back.entries, strict=True):
        assert a.name == b.name and np.float32(a.value) == np.float32(b.value)
        assert b.param_type is None  # a .parm has no types


def test_mavproxy_style_spaces_and_trailing_comments_are_read():
    pf = P.parse_param_text("COMPASS_OFS_X    12.500000\nCOMPASS_ORIENT 6  # yaw 270\n", "m.parm")
    assert pf.as_dict() == {"COMPASS_OFS_X": 12.5, "COMPASS_ORIENT": 6.0}


def test_qgroundcontrol_params_have_its_header_tabs_and_types(tmp_path):
    path = tmp_path / "x.params"
    path.write_text(P.format_qgc(_pf(), stack="PX4", vehicle="QUADROTOR"))
    lines = path.read_text().splitlines()
    assert lines[0] == "# Onboard parameters for Vehicle 7"
    assert "# Stack: PX4" in lines and "# Vehicle: QUADROTOR" in lines
    assert P.QGC_HEADER_COLUMNS in lines
    data = [line for line in lines if not line.startswith("#")]
    assert data[-1] == "7\t1\tCAL_MAG0_ROT\t-1\t6"
    back = P.read_param_file(path)
    assert (back.system_id, back.component_id) == (7, 1)
    assert [(e.name, e.value, e.param_type) for e in back.entries] == [
        (e.name, e.value, e.param_type) for e in _pf().entries
    ]


@pytest.mark.parametrize(
    ("text", "match"),
    [
        ("COMPASS_OFS_X,abc\n", "line 1: 'abc' is not a number"),
        ("# ok\nCOMPASS_OFS_X,1\nCOMPASS_OFS_X,2\n", "line 3: parameter COMPASS_OFS_X again"),
        ("A,1,2\n", "line 1: expected NAME,VALUE"),
        ("# only comments\n", "no parameters"),
        ("COMPASS_OFS_X,nan\n", "not a finite number"),
    ],
)
def test_bad_parameter_files_name_the_line(text, match):
    with pytest.raises(P.ParamError, match=match):
        P.parse_param_text(text, "f.parm", P.PARM_SUFFIX)


def test_qgc_line_with_a_bad_type_is_refused():
    with pytest.raises(P.ParamError, match="line 1"):
        P.parse_param_text("1\t1\tX\t1\tnine\n", "f.params", P.QGC_SUFFIX)


def test_unknown_suffix_is_refused():
    with pytest.raises(P.ParamError, match="unknown suffix '.txt'"):
        P.file_format("backup.txt")


def test_new_files_are_never_replaced(tmp_path):
    path = tmp_path / "b.params"
    P.write_new_file(path, "one\n")
    with pytest.raises(P.ParamError, match="exists"):
        P.write_new_file(path, "two\n")
    assert path.read_text() == "one\n"
    P.write_new_file(path, "three\n", overwrite=True)
    assert path.read_text() == "three\n"
    assert [p.name for p in tmp_path.iterdir()] == ["b.params"]  # no temporary left behind


def test_a_parm_file_says_its_system_only_in_magcals_backup_comment():
    plain = P.parse_param_text("COMPASS_OFS_X,12.5\n", "m.parm", fmt=P.PARM_SUFFIX)
    assert plain.system_id is None  # Mission Planner's format carries no system id
    ours = P.parse_param_text(P.format_parm(_pf_with_backup_comment(3)), "b.parm")
    assert ours.system_id == 3
    qgc = P.parse_param_text(P.format_qgc(_pf()), "b.params")
    assert qgc.system_id == 7


def _pf_with_backup_comment(system: int) -> P.ParamFile:
    comment = f"magcal backup: PX4 system {system}, before magcal flash r.json, read now"
    return P.ParamFile(_pf().entries, system_id=system, comments=(comment,))


def test_new_files_and_their_directory_are_synced(tmp_path, monkeypatch):
    import os
    import stat

    synced: list[bool] = []  # one entry per fsync: whether it was a directory
    real_fsync = os.fsync

    def fsync(fd):
        synced.append(stat.S_ISDIR(os.fstat(fd).st_mode))
        real_fsync(fd)

    monkeypatch.setattr(os, "fsync", fsync)
    P.write_new_file(tmp_path / "a.params", "one\n")
    assert synced == [False, True]  # the file's data, then the directory entry (the link)
    synced.clear()
    P.write_new_file(tmp_path / "a.params", "two\n", overwrite=True)
    assert synced == [False, True]  # the same for the rename
