# SPDX-License-Identifier: Apache-2.0
"""What flash, collect and info do around the writes, on the autopilot emulator through the
real CLI: an absent compass is refused, the backup exists before the first PARAM_SET, a dry
run sends none, an interrupted write accounts for every parameter and names the backup, and
the .parm twin restores on a vehicle of any system id.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from magcal import cli
from magcal.autopilot import params as ap_params
from magcal.autopilot import rotations
from magcal.autopilot.connection import Autopilot
from magcal.io.result import CalibrationResult, write_result
from magcal.link.mavlink import MavlinkError
from tests.autopilot_emulator import AutopilotEmulator

SPEEDUP = 20.0
UNIT = {"ardupilot": "mG", "px4": "gauss"}


def _field_arg(emu: AutopilotEmulator) -> str:
    return f"{emu.field_strength:.9g}{UNIT[emu.personality]}"


def _truth_result(emu: AutopilotEmulator, tmp_path: Path, compass: int = 1) -> str:
    """An ArduPilot result from the emulator's hidden truth for ``compass``, in the frame
    the session would have (y = R_old·raw for an external compass, with the parameters in
    force as the session's metadata; the raw frame for an internal one)."""
    c = emu.truth.compass(compass)
    extra: dict[str, object] = {"mag_unit": UNIT[emu.personality]}
    D, o = c.D, c.o
    if c.external:
        params = emu.params
        k = "" if compass == 1 else str(compass)
        R_old = rotations.ardupilot_matrix(int(params[f"COMPASS_ORIENT{k}"]))
        D, o = R_old @ D, R_old @ o
        meta = {
            f"param.{n}": repr(v) for n, v in params.items() if n.startswith(("COMPASS", "CUST"))
        }
        meta |= {"autopilot": "ardupilot", "compass": str(compass), "compass_external": "1"}
        extra["session_meta"] = meta
    result = CalibrationResult(
        method="ml", D=D, o=o, m_n=emu.truth.m_n, dip_deg=emu.truth.dip_deg, extra=extra
    )
    path = tmp_path / f"truth{compass}.json"
    write_result(path, result)
    return str(path)


def _backups(tmp_path: Path, stem: str = "truth1") -> list[Path]:
    return sorted(tmp_path.glob(f"{stem}.backup-*.params"))


# ------------------------------------------------------------------------------ absent compass
def test_collect_from_an_absent_compass_is_refused(tmp_path, capsys):
    out = tmp_path / "s.csv"
    with AutopilotEmulator(personality="ardupilot", seed=5, speedup=SPEEDUP, compasses=1) as emu:
        argv = [
            "collect",
            "--mavlink",
            emu.url,
            "--compass",
            "2",
            "--duration",
            "4",
            "-o",
            str(out),
        ]
        assert cli.main(argv) == cli.EXIT_ERROR
    err = capsys.readouterr().err
    assert "compass 2 is absent (COMPASS_DEV_ID2 = 0); this vehicle has compass 1" in err
    assert not out.exists()


@pytest.mark.parametrize("personality", ["ardupilot", "px4"])
def test_flash_to_an_absent_compass_is_refused(personality, tmp_path, capsys):
    with AutopilotEmulator(personality=personality, seed=6, speedup=SPEEDUP, compasses=1) as emu:
        result = CalibrationResult(
            method="ml",
            D=np.eye(3),
            o=np.zeros(3),
            m_n=emu.truth.m_n,
            dip_deg=emu.truth.dip_deg,
            extra={"mag_unit": UNIT[personality]},
        )
        write_result(tmp_path / "r.json", result)
        argv = ["flash", str(tmp_path / "r.json"), "--mavlink", emu.url, "--compass", "2"]
        assert cli.main([*argv, "--field", _field_arg(emu)]) == cli.EXIT_ERROR
        assert emu.stats.get("PARAM_SET_RECEIVED", 0) == 0
    err = capsys.readouterr().err
    assert "compass 2 is absent" in err and "this vehicle has compass 1" in err


# ------------------------------------------------------------------------------ backup first
def test_the_backup_holds_the_old_values_at_the_first_param_set(tmp_path):
    with AutopilotEmulator(personality="ardupilot", seed=7, speedup=SPEEDUP) as emu:
        result = _truth_result(emu, tmp_path)
        old = emu.params
        seen: list[tuple[str, dict[str, float] | None, dict[str, float] | None]] = []

        def at_param_set(name: str) -> None:
            if seen:
                return
            files = _backups(tmp_path)
            read = [ap_params.read_param_file(p).as_dict() for p in files] if files else []
            twin = files[0].with_suffix(".parm") if files else None
            seen.append(
                (
                    name,
                    read[0] if read else None,
                    ap_params.read_param_file(twin).as_dict() if twin and twin.exists() else None,
                )
            )

        emu.param_set_hook = at_param_set
        argv = ["flash", result, "--mavlink", emu.url, "--field", _field_arg(emu)]
        assert cli.main(argv) == 0
        assert emu.stats["PARAM_SET_RECEIVED"] >= 1
    (first, saved, twin) = seen[0]
    assert saved is not None and twin is not None, f"no backup when {first} was set"
    assert "COMPASS_OFS_X" in saved and "COMPASS_ORIENT" in saved
    for values in (saved, twin):
        for name, value in values.items():
            assert np.float32(value) == np.float32(old[name]), name


def test_a_dry_run_sends_no_param_set(tmp_path):
    with AutopilotEmulator(personality="ardupilot", seed=8, speedup=SPEEDUP) as emu:
        result = _truth_result(emu, tmp_path)
        argv = ["flash", result, "--mavlink", emu.url, "--field", _field_arg(emu)]
        assert cli.main([*argv, "--dry-run"]) == 0
        assert emu.stats.get("PARAM_SET_RECEIVED", 0) == 0
        assert cli.main(argv) == 0  # the counter counts: a real flash sends them
        assert emu.stats["PARAM_SET_RECEIVED"] >= 10


# ------------------------------------------------------------------------------ interrupted
@pytest.mark.parametrize(
    ("cause", "code"),
    [
        (KeyboardInterrupt, cli.EXIT_INTERRUPTED),
        (lambda: MavlinkError("udp: link lost"), cli.EXIT_ERROR),
        (lambda: OSError(5, "Input/output error"), cli.EXIT_ERROR),
    ],
)
def test_an_interrupted_flash_names_the_backup_and_what_each_parameter_holds(
    cause, code, tmp_path, capsys, monkeypatch
):
    real_write_once = Autopilot.write_once
    calls: list[str] = []

    def write_once(self, name, value, param_type):
        calls.append(name)
        if len(calls) == 3:
            raise cause()
        return real_write_once(self, name, value, param_type)

    monkeypatch.setattr(Autopilot, "write_once", write_once)
    with AutopilotEmulator(personality="ardupilot", seed=9, speedup=SPEEDUP) as emu:
        result = _truth_result(emu, tmp_path)
        old = emu.params
        argv = ["flash", result, "--mavlink", emu.url, "--field", _field_arg(emu)]
        assert cli.main(argv) == code
        now = emu.params
    err = capsys.readouterr().err
    (backup,) = _backups(tmp_path)
    assert str(backup) in err and "--restore" in err
    first, second, third = calls
    assert f"2 confirmed with their new values: {first} = " in err and second in err
    assert f"{third} was being written: it holds its old value" in err
    assert "not sent (old values): " in err
    # the third PARAM_SET never went out: its old value (a hidden CUST_ROTn_* is stored 0)
    assert np.float32(now[third]) == np.float32(old.get(third, 0.0))
    assert np.float32(now[first]) != np.float32(old[first])  # confirmed new


# ------------------------------------------------------------------------------ info, compass 2
@pytest.mark.parametrize(
    ("personality", "device"),
    [("ardupilot", "device id 131874"), ("px4", "device id 2260994")],
)
def test_info_lists_each_compass_and_says_which_are_absent(personality, device, capsys):
    with AutopilotEmulator(personality=personality, seed=10, speedup=SPEEDUP, compasses=2) as emu:
        assert cli.main(["info", "--mavlink", emu.url]) == 0
    out = capsys.readouterr().out
    name = {"ardupilot": "ArduPilot", "px4": "PX4"}[personality]
    assert out.startswith(f"autopilot  {name} ")
    lines = {line[:9]: line for line in out.splitlines() if line.startswith("compass ")}
    assert device in lines["compass 2"]
    assert "compass 3 is absent" in lines["compass 3"]
    assert "this vehicle has compasses 1 and 2" in lines["compass 3"]
    own = "COMPASS_OFS2_X" if personality == "ardupilot" else "CAL_MAG1_XOFF"
    assert f"  {own} " in out


def test_flash_dry_run_of_compass_2_plans_its_own_parameters(tmp_path, capsys):
    with AutopilotEmulator(personality="ardupilot", seed=11, speedup=SPEEDUP, compasses=3) as emu:
        result = _truth_result(emu, tmp_path, compass=2)
        plan = tmp_path / "plan2.parm"
        argv = ["flash", result, "--mavlink", emu.url, "--compass", "2", "--dry-run"]
        assert cli.main([*argv, "--field", _field_arg(emu), "--param-file", str(plan)]) == 0
        assert emu.stats.get("PARAM_SET_RECEIVED", 0) == 0
    planned = ap_params.read_param_file(plan).as_dict()
    assert {"COMPASS_OFS2_X", "COMPASS_DIA2_Y", "COMPASS_ODI2_Z"} <= set(planned)
    assert not any(n.startswith(("COMPASS_OFS_", "COMPASS_DIA_", "COMPASS_OFS3")) for n in planned)
    truth = emu.truth.compass(2)
    assert np.allclose([planned[f"COMPASS_OFS2_{a}"] for a in "XYZ"], -truth.o, atol=1.0)


# ------------------------------------------------------------------------------ restore .parm
def test_the_parm_twin_restores_on_a_vehicle_of_another_system_id(tmp_path, capsys):
    with AutopilotEmulator(personality="ardupilot", seed=12, speedup=SPEEDUP, system_id=3) as emu:
        result = _truth_result(emu, tmp_path)
        old = emu.params
        assert cli.main(["flash", result, "--mavlink", emu.url, "--field", _field_arg(emu)]) == 0
        (backup,) = _backups(tmp_path)
        assert "-sys3-" in backup.name
        twin = backup.with_suffix(".parm")
        assert ap_params.read_param_file(twin).system_id == 3  # from magcal's comment
        assert cli.main(["flash", "--restore", str(twin), "--mavlink", emu.url]) == 0
        now = emu.params
        for name, value in ap_params.read_param_file(twin).as_dict().items():
            assert np.float32(now[name]) == np.float32(old[name]) == np.float32(value), name
        # a .parm from elsewhere (Mission Planner's) says no system: not refused for it
        plain = tmp_path / "mp.parm"
        plain.write_text(f"COMPASS_OFS_X,{old['COMPASS_OFS_X'] + 1.0}\n")
        assert cli.main(["flash", "--restore", str(plain), "--mavlink", emu.url]) == 0
        assert np.float32(emu.params["COMPASS_OFS_X"]) == np.float32(old["COMPASS_OFS_X"] + 1.0)
    # and a file that names another system is still refused without --force
    with AutopilotEmulator(personality="ardupilot", seed=12, speedup=SPEEDUP, system_id=4) as emu:
        capsys.readouterr()
        assert cli.main(["flash", "--restore", str(twin), "--mavlink", emu.url]) == cli.EXIT_ERROR
    assert "saved from system 3, this vehicle is system 4" in capsys.readouterr().err


# ------------------------------------------------------------------------------ PX4 threshold
def _px4_result(emu, tmp_path, odiag, name) -> str:
    """A PX4 result whose mapping is CAL_MAG0_ROT in force, scale diag(1.02, 0.98, 1.01) with
    the off-diagonals ``odiag``, and the true offsets."""
    F = emu.field_strength
    R = rotations.px4_matrix(int(emu.params["CAL_MAG0_ROT"]))
    x, y, z = odiag
    S = np.array([[1.02, x, y], [x, 0.98, z], [y, z, 1.01]])
    result = CalibrationResult(
        method="ml",
        D=F * np.linalg.inv(R @ S),
        o=emu.truth.compass(1).o,
        m_n=emu.truth.m_n,
        dip_deg=emu.truth.dip_deg,
        extra={"mag_unit": "gauss"},
    )
    path = tmp_path / f"{name}.json"
    write_result(path, result)
    return str(path)


def test_px4_off_diagonals_within_its_threshold_are_reported_never_applied(tmp_path, capsys):
    tiny = (0.004, 0.003, -0.005)  # norm 0.0071 ≤ 0.01
    with AutopilotEmulator(personality="px4", seed=13, speedup=SPEEDUP) as emu:
        field = ["--field", _field_arg(emu)]
        assert (
            cli.main(
                [
                    "flash",
                    _px4_result(emu, tmp_path, (0, 0, 0), "zero"),
                    "--mavlink",
                    emu.url,
                    *field,
                ]
            )
            == 0
        )
        emu.reboot()  # every value of that first flash in use
        without = emu.heading_error_deg()
        capsys.readouterr()
        small = _px4_result(emu, tmp_path, tiny, "tiny")
        assert cli.main(["flash", small, "--mavlink", emu.url, *field, "--reboot"]) == 0
        assert np.allclose([emu.params[f"CAL_MAG0_{a}ODIAG"] for a in "XYZ"], tiny, atol=1e-6)
        # the vehicle keeps the reset off-diagonals: the same correction as without them
        assert emu.heading_error_deg() == pytest.approx(without, abs=1e-9)
        emu.reboot()
        assert emu.heading_error_deg() == pytest.approx(without, abs=1e-9)
    captured = capsys.readouterr()
    assert "never applies such a small change" in captured.err
    assert "CAL_MAG0_X/Y/ZODIAG = (0.004, 0.003, -0.005)" in captured.err
    assert "reboot" not in captured.out  # a reboot would not help: not asked for, not done
