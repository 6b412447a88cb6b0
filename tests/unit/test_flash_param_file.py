# SPDX-License-Identifier: Apache-2.0
"""``magcal flash RESULT --param-file OUT`` without a vehicle: the parameters from what the
result's session recorded, with the motor compensation (``motor``) and every compass
(``compasses``); scored against the known truth of the shared flight logs."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from magcal.autopilot import flash as F
from magcal.autopilot import mapping, rotations, vehicle, wmm
from magcal.autopilot import params as P
from magcal.cli import main
from magcal.io.result import (
    CalibrationResult,
    read_result,
    result_compasses,
    write_result,
)
from magcal.io.session import read_session

FLIGHTLOGS = Path("/work/shared/flightlogs")
SCORER = FLIGHTLOGS / "tools" / "score_flight.py"
#: Where the shared flights were flown (their truth's home), as a session's location.
HOME = "-35.363261,149.16523,0.584"
DATE = "2025-06-01"
F_MG = wmm.wmm_field(-35.363261, 149.16523, 0.584, wmm.dt.date.fromisoformat(DATE)).strength("mG")

needs_logs = pytest.mark.skipif(
    not SCORER.exists(), reason=f"{FLIGHTLOGS} is absent: the shared flight logs are not here"
)


def _euler(rpy_deg) -> np.ndarray:
    """R = Rz(yaw) Ry(pitch) Rx(roll), as the scorer builds it (scipy, independent of magcal)."""
    r, p, y = rpy_deg
    return Rotation.from_euler("ZYX", [y, p, r], degrees=True).as_matrix()


def _sym(d, od) -> np.ndarray:
    return np.array([[d[0], od[0], od[1]], [od[0], d[1], od[2]], [od[1], od[2], d[2]]], float)


def _truth_calibration(sim: dict, field: float, R_old: np.ndarray):
    """D, o, b of the simulated sensor in the session frame y = R_old·raw (mG) (the flight
    README's formula): raw = s·R_sᵀ(M⁻¹(B + MOT·I) − OFS)."""
    M_inv = np.linalg.inv(_sym(sim["DIA"], sim["ODI"]))
    R_s = np.eye(3) if sim.get("ROT") is None else _euler(sim["ROT"])
    K = sim.get("SCALING", 1.0) * R_old @ R_s.T
    return field * K @ M_inv, -K @ np.asarray(sim["OFS"]), K @ M_inv @ np.asarray(sim["MOT"])


def _result(D, o, meta, **extra) -> CalibrationResult:
    dip = 60.0
    return CalibrationResult(
        "ml",
        D,
        o,
        np.array([np.cos(np.radians(dip)), 0.0, -np.sin(np.radians(dip))]),
        dip,
        extra={"mag_unit": meta.get("mag_unit", "mG"), "session_meta": meta, **extra},
    )


def _motor(b, kept=True, source="current"):
    return {
        "input": source,
        "unit": "A" if source == "current" else "1",
        "vector": list(map(float, b)),
        "kept": kept,
        "statistic": 120.0,
        "threshold": 10.8,
    }


@pytest.fixture(scope="module")
def imported(tmp_path_factory):
    """Each shared flight's session metadata, as magcal import records it (compass 1)."""
    out = {}
    tmp = tmp_path_factory.mktemp("sessions")
    for name in ("f1_plain", "f2_motor", "f3_misaligned"):
        log = FLIGHTLOGS / f"{name}.bin"
        if not log.exists():
            continue
        path = tmp / f"{name}.csv"
        rc = main(["import", str(log), "-q", "--start", "100", "--end", "200", "-o", str(path)])
        assert rc == 0
        meta = dict(read_session(path).meta)
        # a flight session carries where and when it was flown
        meta |= {"location": HOME, "date": DATE}
        out[name] = meta
    return out


def _score(log: Path, parm: Path, tmp_path: Path) -> dict:
    out = tmp_path / "score.json"
    subprocess.run(
        [sys.executable, str(SCORER), str(log), str(parm), "--json", str(out)],
        check=True,
        capture_output=True,
        text=True,
    )
    (row,) = json.loads(out.read_text())["rows"]
    return row


@needs_logs
@pytest.mark.parametrize(
    ("name", "suffix"),
    [
        ("f1_plain", ".parm"),
        ("f2_motor", ".parm"),
        ("f2_motor", ".params"),
        ("f3_misaligned", ".param"),
        ("f3_misaligned", ".params"),
    ],
)
def test_a_result_built_from_the_truth_scores_zero(imported, tmp_path, capsys, name, suffix):
    meta = imported[name]
    truth = json.loads((FLIGHTLOGS / f"{name}.truth.json").read_text())
    recorded = vehicle.params_from_meta(meta)
    R_old = mapping.ardupilot_rotation(recorded, 1)
    D, o, b = _truth_calibration(truth["sim"], F_MG, R_old)
    extra = {"motor": _motor(b)} if np.any(truth["sim"]["MOT"]) else {}
    res = tmp_path / "r.json"
    write_result(res, _result(D, o, meta, **extra))
    parm = tmp_path / f"p{suffix}"
    rc = main(["flash", str(res), "--param-file", str(parm)])
    assert rc == 0, capsys.readouterr().err
    text = parm.read_text()
    assert f"from {res}" in text and "World Magnetic Model" in text
    row = _score(FLIGHTLOGS / f"{name}.bin", parm, tmp_path)
    assert row["so3_rms"] < 0.01
    assert row["mot_err"] is not None and row["mot_err"] <= 0.01
    written = P.read_param_file(parm).as_dict()
    if truth["sim"].get("ROT") is not None:
        assert written["COMPASS_ORIENT"] == 101
        assert written.get("CUST_ROT_ENABLE", recorded["CUST_ROT_ENABLE"]) == 1
        # ArduPilot shows CUST_ROT1_* only after a reboot with CUST_ROT_ENABLE = 1
        assert ("load it again" in text) == (recorded["CUST_ROT_ENABLE"] == 0)
    if extra:
        assert written.get("COMPASS_MOTCT", recorded.get("COMPASS_MOTCT")) == 2


def test_ardupilot_motor_vector_is_minus_the_interference_in_the_corrected_frame():
    rng = np.random.default_rng(3)
    M = _sym([0.95, 1.04, 1.01], [0.03, -0.02, 0.04])
    mot = np.array([-0.95, 1.677, -0.533])
    R_old = rotations.ardupilot_matrix(2)
    sim = {"DIA": np.diag(M), "ODI": [M[0, 1], M[0, 2], M[1, 2]], "OFS": [40.0, -80.0, 120.0]}
    sim |= {"MOT": mot, "ROT": [1.0, -2.0, 3.0]}
    D, o, b = _truth_calibration(sim, 500.0, R_old)
    out = mapping.to_ardupilot(np.linalg.inv(D), o, 500.0, R_old, motor_b=b)
    got = np.array([out.params[f"COMPASS_MOT_{a}"] for a in "XYZ"])
    assert np.allclose(got, -mot, atol=1e-9)
    assert out.params["COMPASS_MOTCT"] == 2
    # the corrected field with that compensation is the motor-free field, at any current
    raw = rng.normal(size=(20, 3)) * 300
    current = rng.uniform(0, 40, 20)
    y = raw @ R_old.T + current[:, None] * b
    want = 500.0 * (raw @ R_old.T - o) @ np.linalg.inv(D).T
    c = mapping.ardupilot_correct(y @ R_old, out.params) + current[:, None] * got
    assert np.abs(c - want).max() < 1e-6


def test_px4_compensation_is_minus_the_interference_per_kA_in_the_sensor_frame():
    b = np.array([0.002, -0.001, 0.0005])  # gauss per A
    D = 0.5 * np.eye(3)
    out = mapping.to_px4(np.linalg.inv(D), np.zeros(3), 0.5, motor_b=b, motor_input="current")
    comp = np.array([out.params[f"CAL_MAG0_{a}COMP"] for a in "XYZ"])
    assert np.allclose(comp, -b * 1000.0)  # G/kA
    assert out.params["CAL_MAG_COMP_TYP"] == 2
    thr = mapping.to_px4(np.linalg.inv(D), np.zeros(3), 0.5, motor_b=b, motor_input="throttle")
    assert thr.params["CAL_MAG_COMP_TYP"] == 1
    assert np.allclose([thr.params[f"CAL_MAG0_{a}COMP"] for a in "XYZ"], -b)


def _ap_meta(**extra) -> dict[str, str]:
    v = {}
    for k, orient, ext in (("", 0, 1), ("2", 0, 0)):
        v |= {
            f"COMPASS_{g}{k}_{a}": x
            for g, x in (("OFS", 10), ("DIA", 1), ("ODI", 0))
            for a in "XYZ"
        }
        v |= {f"COMPASS_ORIENT{k}": orient, f"COMPASS_DEV_ID{k}": 1000 + len(v)}
        v |= {f"COMPASS_SCALE{k}": 1}
        v[mapping.ap_external_name(int(k or 1))] = ext
    v |= {"COMPASS_OFFS_MAX": 1800, "CUST_ROT_ENABLE": 0, "AHRS_ORIENTATION": 0}
    v |= {"COMPASS_MOTCT": 0, "COMPASS_ORIENT3": 0}
    meta = {"autopilot": "ardupilot", "compass": "1", "mag_unit": "mG", "source": "test"}
    meta |= {f"param.{n}": str(x) for n, x in v.items()}
    return meta | extra


def _write(tmp_path, result) -> Path:
    path = tmp_path / "r.json"
    write_result(path, result)
    return path


def test_every_compass_is_written_with_its_own_names_and_compass_restricts(tmp_path, capsys):
    rng = np.random.default_rng(1)
    D1 = 480.0 * (np.eye(3) + 0.02 * rng.normal(size=(3, 3)))
    D2 = 500.0 * np.eye(3)
    b2 = [0.5, -1.0, 0.25]
    further = [
        {
            "compass": 2,
            "D": D2.tolist(),
            "o": [5.0, 13.0, -18.0],
            "D_inv": np.linalg.inv(D2).tolist(),
            "motor": _motor(b2),
            "warnings": [],
        }
    ]
    res = _write(tmp_path, _result(D1, [100.0, -50.0, 20.0], _ap_meta(), compasses=further))
    parm = tmp_path / "all.parm"
    assert main(["flash", str(res), "--param-file", str(parm), "--field", "500mG"]) == 0
    got = P.read_param_file(parm).as_dict()
    assert "COMPASS_OFS_X" in got and "COMPASS_OFS2_X" in got
    assert got["COMPASS_OFS2_X"] == pytest.approx(-5.0)
    assert got["COMPASS_MOT2_X"] == pytest.approx(-0.5, abs=1e-6)  # D2 = F·I: MOT2 = −b2
    assert got["COMPASS_MOTCT"] == 2
    assert "COMPASS_MOT_X" not in got  # compass 1 has no motor interference: left as it is
    assert "COMPASS_EXTERNAL" not in got and "COMPASS_ORIENT2" not in got  # nothing unchanged
    one = tmp_path / "two.params"
    assert (
        main(["flash", str(res), "--param-file", str(one), "--field", "500mG", "--compass", "2"])
        == 0
    )
    qgc = P.read_param_file(one)
    assert {e.name for e in qgc.entries} <= {n for n in got if "2" in n or n == "COMPASS_MOTCT"}
    types = {e.name: e.param_type for e in qgc.entries}
    assert types["COMPASS_MOTCT"] == P.INT8 and types["COMPASS_OFS2_X"] == P.REAL32
    # the round trip: the values read back are the values planned (float32)
    for e in qgc.entries:
        assert got[e.name] == e.value


def test_a_motor_interference_not_kept_leaves_the_compensation_as_it_is(tmp_path):
    D = 500.0 * np.eye(3)
    res = _write(tmp_path, _result(D, [1.0, 2.0, 3.0], _ap_meta(), motor=_motor([1, 2, 3], False)))
    parm = tmp_path / "p.parm"
    assert main(["flash", str(res), "--param-file", str(parm), "--field", "500mG"]) == 0
    assert not any("MOT" in n for n in P.read_param_file(parm).as_dict())


def test_the_field_comes_from_the_sessions_location_and_date(tmp_path, capsys):
    meta = _ap_meta(location=HOME, date=DATE + "T10:00:00Z")
    res = _write(tmp_path, _result(F_MG * np.eye(3), [0.0, 0.0, 0.0], meta))
    parm = tmp_path / "p.parm"
    assert main(["flash", str(res), "--param-file", str(parm)]) == 0
    assert f"on {DATE}" in parm.read_text()
    got = P.read_param_file(parm).as_dict()
    assert got["COMPASS_OFS_X"] == 0.0 and "COMPASS_DIA_X" not in got  # 1 already


def test_px4_param_file_uses_cal_mag_names_and_their_types(tmp_path):
    v = {
        f"CAL_MAG0_{a}{g}": x
        for g, x in (("OFF", 0.0), ("SCALE", 1.0), ("ODIAG", 0.0))
        for a in "XYZ"
    }
    v |= {"CAL_MAG0_ROT": 0, "CAL_MAG0_ID": 5, "SENS_BOARD_X_OFF": 0, "SENS_BOARD_Y_OFF": 0}
    v |= {"SENS_BOARD_Z_OFF": 0}
    meta = {"autopilot": "px4", "compass": "1", "mag_unit": "gauss", "source": "test"}
    meta |= {f"param.{n}": str(x) for n, x in v.items()}
    D = 0.5 * np.diag([1.1, 0.95, 1.0])
    res = _write(tmp_path, _result(D, [0.1, -0.05, 0.2], meta, motor=_motor([0.001, 0, 0])))
    out = tmp_path / "px4.params"
    assert main(["flash", str(res), "--param-file", str(out), "--field", "0.5gauss"]) == 0
    pf = P.read_param_file(out)
    types = {e.name: e.param_type for e in pf.entries}
    values = pf.as_dict()
    assert types["CAL_MAG_COMP_TYP"] == P.INT32 and values["CAL_MAG_COMP_TYP"] == 2
    assert values["CAL_MAG0_XCOMP"] == pytest.approx(-1.0)  # −0.001 G/A = −1 G/kA
    assert values["CAL_MAG0_XOFF"] == pytest.approx(0.1)


# ------------------------------------------------------------------------------ refusals
def test_refuses_a_result_whose_session_did_not_come_from_an_autopilot(tmp_path, capsys):
    res = _write(tmp_path, _result(np.eye(3), [0, 0, 0], {"source": "phone", "mag_unit": "uT"}))
    parm = tmp_path / "p.parm"
    assert main(["flash", str(res), "--param-file", str(parm), "--field", "50uT"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("magcal flash:") and len(err.strip().splitlines()) == 1
    assert "did not come from an autopilot" in err and "param.NAME" in err
    assert not parm.exists()


def test_refuses_a_session_without_a_further_compass_parameters(tmp_path, capsys):
    meta = {k: v for k, v in _ap_meta().items() if "2" not in k}
    further = [{"compass": 2, "D": np.eye(3).tolist(), "o": [0, 0, 0]}]
    res = _write(tmp_path, _result(500 * np.eye(3), [0, 0, 0], meta, compasses=further))
    with pytest.raises(Exception, match=r"compass 2: COMPASS_OFS2_X.*COMPASS_EXTERN2"):
        F.plan_param_file(
            result_compasses(read_result(res)), meta, wmm.parse_field("500mG"), where="r"
        )
    assert (
        main(["flash", str(res), "--param-file", str(tmp_path / "p.parm"), "--field", "500mG"]) == 2
    )
    assert "did not record the parameters in force" in capsys.readouterr().err


def test_refuses_motor_interferences_of_different_inputs(tmp_path, capsys):
    further = [
        {
            "compass": 2,
            "D": (500 * np.eye(3)).tolist(),
            "o": [0, 0, 0],
            "motor": _motor([1, 0, 0], source="throttle"),
        }
    ]
    res = _write(
        tmp_path,
        _result(500 * np.eye(3), [0, 0, 0], _ap_meta(), motor=_motor([1, 0, 0]), compasses=further),
    )
    assert (
        main(["flash", str(res), "--param-file", str(tmp_path / "p.parm"), "--field", "500mG"]) == 2
    )
    assert "one compensation type for every compass" in capsys.readouterr().err


def test_refuses_a_compass_the_result_does_not_calibrate_and_vehicle_options(tmp_path, capsys):
    res = _write(tmp_path, _result(500 * np.eye(3), [0, 0, 0], _ap_meta()))
    p = str(tmp_path / "p.parm")
    assert main(["flash", str(res), "--param-file", p, "--field", "500mG", "--compass", "3"]) == 2
    assert "not compass 3" in capsys.readouterr().err
    assert main(["flash", str(res), "--param-file", p, "--field", "500mG", "--reboot"]) == 2
    assert "--reboot needs a vehicle" in capsys.readouterr().err
    assert main(["flash", str(res), "--param-file", p]) == 2  # no location, no --field
    assert "has no location" in capsys.readouterr().err
    assert main(["flash", str(res)]) == 2
    assert "--param-file" in capsys.readouterr().err


def test_malformed_motor_and_compasses_keys_are_refused_by_name(tmp_path):
    bad = _result(np.eye(3), [0, 0, 0], _ap_meta(), motor={"input": "rpm", "vector": [0, 0, 0]})
    with pytest.raises(Exception, match=r"'motor.input' is 'rpm'"):
        result_compasses(bad)
    twice = _result(
        np.eye(3),
        [0, 0, 0],
        _ap_meta(),
        compasses=[{"compass": 1, "D": np.eye(3).tolist(), "o": [0, 0, 0]}],
    )
    with pytest.raises(Exception, match="compass 1 is calibrated twice"):
        result_compasses(twice)
    wrong = _result(
        np.eye(3),
        [0, 0, 0],
        _ap_meta(),
        compasses=[
            {
                "compass": 2,
                "D": np.eye(3).tolist(),
                "o": [0, 0, 0],
                "D_inv": (2 * np.eye(3)).tolist(),
            }
        ],
    )
    with pytest.raises(Exception, match=r"'compasses\[0\].D_inv' is not the inverse"):
        result_compasses(wrong)


# ------------------------------------------------------------------------------ MAVLink
def test_mavlink_flash_backs_up_writes_and_confirms_the_motor_compensation(tmp_path, capsys):
    from tests.autopilot_emulator import AutopilotEmulator

    with AutopilotEmulator(personality="ardupilot", seed=8, speedup=20.0, compasses=1) as emu:
        c = emu.truth.compass(1)
        params = emu.params
        R_old = rotations.ardupilot_matrix(int(params["COMPASS_ORIENT"]))
        meta = {
            f"param.{n}": repr(v) for n, v in params.items() if n.startswith(("COMPASS", "CUST"))
        }
        meta |= {"autopilot": "ardupilot", "compass": "1", "compass_external": "1"}
        b = np.array([0.4, -0.8, 0.2])  # mG/A in y
        result = CalibrationResult(
            "ml",
            R_old @ c.D,
            R_old @ c.o,
            emu.truth.m_n,
            emu.truth.dip_deg,
            extra={"mag_unit": "mG", "session_meta": meta, "motor": _motor(b)},
        )
        path = tmp_path / "r.json"
        write_result(path, result)
        field = f"{emu.field_strength:.9g}mG"
        assert main(["flash", str(path), "--mavlink", emu.url, "--field", field]) == 0
        after = emu.params
    (backup,) = sorted(tmp_path.glob("r.backup-*.params"))
    saved = P.read_param_file(backup).as_dict()
    assert saved["COMPASS_MOTCT"] == 0 and saved["COMPASS_MOT_X"] == 0.0  # old values first
    A = emu.field_strength * np.linalg.inv(R_old @ c.D)  # the rotation is enumerated here
    want = -A @ b
    got = np.array([after[f"COMPASS_MOT_{a}"] for a in "XYZ"])
    assert np.allclose(got, want, atol=1e-4) and after["COMPASS_MOTCT"] == 2
    assert "COMPASS_MOTCT = 2 confirmed" in capsys.readouterr().err


@needs_logs
def test_compass_2_of_a_flight_whose_calibration_in_force_is_right_changes_nothing(
    imported, tmp_path, capsys
):
    meta = imported["f2_motor"]
    if "param.COMPASS_OFS2_X" not in meta:
        pytest.skip("this import records the parameters of its own compass only")
    truth = json.loads((FLIGHTLOGS / "f2_motor.truth.json").read_text())
    recorded = vehicle.params_from_meta(meta)
    # compass 2: offsets (5, 13, −18) mG, no soft iron, COMPASS_MOT2 = −SIM_MAG_MOT in force
    sim2 = {"DIA": [1, 1, 1], "ODI": [0, 0, 0], "OFS": [5.0, 13.0, -18.0]}
    sim2 |= {"MOT": truth["sim"]["MOT"], "ROT": None}
    D2, o2, b2 = _truth_calibration(sim2, F_MG, mapping.ardupilot_rotation(recorded, 2))
    D1, o1, b1 = _truth_calibration(truth["sim"], F_MG, mapping.ardupilot_rotation(recorded, 1))
    further = [{"compass": 2, "D": D2.tolist(), "o": o2.tolist(), "motor": _motor(b2)}]
    res = tmp_path / "r.json"
    write_result(res, _result(D1, o1, meta, motor=_motor(b1), compasses=further))
    parm = tmp_path / "c2.parm"
    assert main(["flash", str(res), "--param-file", str(parm), "--compass", "2"]) == 0
    assert "already hold these values" in capsys.readouterr().out and not parm.exists()
    assert main(["flash", str(res), "--param-file", str(parm)]) == 0
    written = P.read_param_file(parm).as_dict()
    assert written and not any("2_" in n or n.endswith("2") for n in written)
