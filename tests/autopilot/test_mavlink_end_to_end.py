# SPDX-License-Identifier: Apache-2.0
"""End to end over MAVLink with the autopilot emulator, through the real CLI:
collect → calibrate → flash → the emulator's own corrected field; backups, dry runs, restores
and a lossy parameter link.

The emulator starts each vehicle with an older, imperfect calibration (heading errors of
many degrees) and hides the true compass errors; ``emu.heading_error_deg()`` is the RMS
heading error of the field it corrects on board with the parameters then in use.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from magcal import cli
from magcal.autopilot import flash as apflash
from magcal.autopilot import params as ap_params
from magcal.io.result import CalibrationResult, write_result
from magcal.io.session import read_session
from tests.autopilot_emulator import AutopilotEmulator
from tests.autopilot_emulator.world import PATH_S

#: Simulated seconds per wall-clock second: a 90 % coverage session takes a few seconds.
SPEEDUP = 20.0
#: A bound on every collection here, samples (IMU messages at 100 Hz): twice the emulated
#: path, after which the vehicle holds still and coverage can only creep up by gyroscope
#: drift. A collection that misses its coverage target then ends, and the test goes on (or
#: fails) instead of waiting for ever.
MAX_SAMPLES = str(int(2 * PATH_S * 100))
HEADING_BOUND_DEG = 0.5
UNIT = {"ardupilot": "mG", "px4": "gauss"}


def _field_arg(emu: AutopilotEmulator) -> str:
    return f"{emu.field_strength:.9g}{UNIT[emu.personality]}"


def _collect_and_calibrate(emu, tmp_path):
    session = tmp_path / f"{emu.personality}.csv"
    result = tmp_path / f"{emu.personality}.json"
    argv = ["collect", "--mavlink", emu.url, "-o", str(session), "--max-samples", MAX_SAMPLES]
    assert cli.main(argv) == 0
    assert cli.main(["calibrate", str(session), "-o", str(result), "--method", "ml"]) == 0
    return session, result


def _backup_paths(tmp_path, stem: str):
    return sorted(tmp_path.glob(f"{stem}.backup-*.params"))


def test_ardupilot_collect_calibrate_flash_verify_restore(tmp_path, capsys):
    with AutopilotEmulator(personality="ardupilot", seed=0, speedup=SPEEDUP) as emu:
        before = emu.heading_error_deg()
        old = emu.params
        session, result = _collect_and_calibrate(emu, tmp_path)

        meta = read_session(session).meta
        assert meta["mag_unit"] == "mG" and meta["autopilot"] == "ardupilot"
        assert float(meta["param.COMPASS_OFS_X"]) == pytest.approx(old["COMPASS_OFS_X"], rel=1e-6)

        common = ["--mavlink", emu.url, "--field", _field_arg(emu)]
        dry = tmp_path / "dry.parm"
        from_session = [*common, "--session", str(session)]
        assert (
            cli.main(["flash", str(result), *from_session, "--dry-run", "--param-file", str(dry)])
            == 0
        )
        assert emu.params == old  # a dry run reads, never writes
        planned = ap_params.read_param_file(dry).as_dict()
        assert "CUST_ROT1_YAW" in planned  # the hidden 3° misalignment needs a custom rotation

        capsys.readouterr()
        # Without --session: the result carries the session's metadata (the parameters in
        # force while it was recorded).
        assert cli.main(["flash", str(result), *common]) == 0
        after = emu.heading_error_deg()
        out = capsys.readouterr().out
        assert "confirmed" in out
        assert after <= HEADING_BOUND_DEG, f"heading error {before:.2f}° → {after:.3f}°"
        assert before > 5.0  # the calibration in force at start was poor: the test means something

        now = emu.params
        for name, value in planned.items():  # the dry run's file is what was written
            assert np.float32(now[name]) == np.float32(value), name
        (backup,) = _backup_paths(tmp_path, "ardupilot")
        saved = ap_params.read_param_file(backup)
        assert {e.name for e in saved.entries} >= {
            n for n in planned if not n.startswith("CUST_ROT1")
        }
        for e in saved.entries:  # the values in force before the first PARAM_SET
            assert np.float32(e.value) == np.float32(old[e.name]), e.name
        twin = ap_params.read_param_file(backup.with_suffix(".parm")).as_dict()
        assert {n: np.float32(v) for n, v in twin.items()} == {
            n: np.float32(v) for n, v in saved.as_dict().items()
        }

        assert cli.main(["verify", "--mavlink", emu.url, "--samples", "300"]) == 0
        assert "corrected by the vehicle" in capsys.readouterr().out

        assert cli.main(["flash", "--restore", str(backup), "--mavlink", emu.url, "--reboot"]) == 0
        restored = emu.params
        for name in saved.as_dict():
            assert np.float32(restored[name]) == np.float32(old[name]), name
        assert "CUST_ROT1_YAW" not in restored  # hidden again with CUST_ROT_ENABLE = 0
        assert emu.heading_error_deg() == pytest.approx(before, rel=1e-6)


def test_px4_collect_calibrate_flash(tmp_path, capsys):
    with AutopilotEmulator(personality="px4", seed=1, speedup=SPEEDUP) as emu:
        before = emu.heading_error_deg()
        old = emu.params
        session, result = _collect_and_calibrate(emu, tmp_path)
        assert read_session(session).meta["mag_unit"] == "gauss"
        export = tmp_path / "px4.params"
        argv = ["flash", str(result), "--mavlink", emu.url, "--field", _field_arg(emu)]
        assert cli.main([*argv, "--param-file", str(export), "--reboot"]) == 0
        after = emu.heading_error_deg()
        assert after <= HEADING_BOUND_DEG, f"heading error {before:.2f}° → {after:.3f}°"
        assert before > 5.0
        exported = ap_params.read_param_file(export)
        assert {e.name: e.param_type for e in exported.entries}["CAL_MAG0_ROT"] == ap_params.INT32
        for e in exported.entries:
            assert np.float32(emu.params[e.name]) == np.float32(e.value), e.name
        (backup,) = _backup_paths(tmp_path, "px4")
        for e in ap_params.read_param_file(backup).entries:
            assert np.float32(e.value) == np.float32(old[e.name]), e.name


# ------------------------------------------------------------------------------ lossy link
def _truth_result(emu, tmp_path) -> str:
    """A result made from the emulator's hidden truth (no collect needed), in the frame an
    ArduPilot session has (y = R_old·raw), with the session's parameters in its extra."""
    c = emu.truth.compass(1)
    params = emu.params
    orient = int(params["COMPASS_ORIENT"])
    from magcal.autopilot import rotations

    R_old = rotations.ardupilot_matrix(orient)
    D = R_old @ c.D
    o = R_old @ c.o
    meta = {f"param.{n}": repr(v) for n, v in params.items() if n.startswith(("COMPASS", "CUST"))}
    meta |= {"autopilot": "ardupilot", "compass": "1", "compass_external": "1"}
    result = CalibrationResult(
        method="ml",
        D=D,
        o=o,
        m_n=emu.truth.m_n,
        dip_deg=emu.truth.dip_deg,
        extra={"mag_unit": "mG", "session_meta": meta},
    )
    path = tmp_path / "truth.json"
    write_result(path, result)
    return str(path)


def test_flash_confirms_every_value_over_a_lossy_link(tmp_path, capsys):
    with AutopilotEmulator(
        personality="ardupilot", seed=2, speedup=SPEEDUP, param_value_loss=0.3
    ) as emu:
        result = _truth_result(emu, tmp_path)
        argv = ["flash", result, "--mavlink", emu.url, "--field", _field_arg(emu)]
        assert cli.main(argv) == 0
        assert "all 14 parameters written and confirmed" in capsys.readouterr().out
        assert emu.stats.get("PARAM_VALUE_DROPPED", 0) > 0  # the loss did happen
        assert emu.heading_error_deg() <= HEADING_BOUND_DEG


def test_flash_without_echoes_fails_naming_backup_and_each_value_is_old_or_new(
    tmp_path, capsys, monkeypatch
):
    with AutopilotEmulator(personality="ardupilot", seed=3, speedup=SPEEDUP) as emu:
        result = _truth_result(emu, tmp_path)
        old = emu.params
        dry = tmp_path / "plan.parm"
        argv = ["flash", result, "--mavlink", emu.url, "--field", _field_arg(emu)]
        assert cli.main([*argv, "--dry-run", "--param-file", str(dry)]) == 0
        planned = ap_params.read_param_file(dry).as_dict()
        real_back_up = apflash.back_up

        def back_up_then_lose_every_echo(*args, **kwargs):
            backup = real_back_up(*args, **kwargs)
            emu.param_value_loss = 1.0  # from now on no PARAM_VALUE reaches magcal
            return backup

        monkeypatch.setattr(apflash, "back_up", back_up_then_lose_every_echo)
        capsys.readouterr()
        assert cli.main(argv) == cli.EXIT_ERROR
        err = capsys.readouterr().err
        (backup,) = _backup_paths(tmp_path, "truth")
        assert "not confirmed" in err and str(backup) in err
        assert "hold their old values" in err  # the link was given up: the rest not sent
        now = emu.params
        changed = 0
        for name, new in planned.items():
            if name not in old:
                # CUST_ROT1_*, hidden while CUST_ROT_ENABLE was 0 (stored 0, the emulator's
                # default): now visible (the enable arrived) with that value or the new one
                assert name not in now or np.float32(now[name]) in (0.0, np.float32(new)), name
                continue
            is_old = np.float32(now[name]) == np.float32(old[name])
            is_new = np.float32(now[name]) == np.float32(new)
            assert is_old or is_new, name
            changed += int(not is_old)
        assert changed > 0  # PARAM_SET still arrived: some values are new, unconfirmed
        saved = ap_params.read_param_file(backup).as_dict()
        assert all(np.float32(v) == np.float32(old[n]) for n, v in saved.items())
        json.loads(open(result).read())  # the result file is untouched


def test_ctrl_c_during_collect_writes_the_partial_session(tmp_path, monkeypatch):
    import magcal.commands.collect as collect_command

    def interrupting_printer():
        pressed = []

        def show(p):  # Ctrl-C once, after 300 samples
            if p.samples >= 300 and not pressed:
                pressed.append(p.samples)
                raise KeyboardInterrupt

        show.done = lambda: None
        return show

    monkeypatch.setattr(collect_command, "progress_printer", interrupting_printer)
    out = tmp_path / "partial.csv"
    with AutopilotEmulator(personality="px4", seed=4, speedup=SPEEDUP) as emu:
        argv = ["collect", "--mavlink", emu.url, "-o", str(out), "--max-samples", MAX_SAMPLES]
        assert cli.main(argv) == cli.EXIT_INTERRUPTED
    session = read_session(out)
    assert len(session) >= 300 and session.meta["stopped"] == "interrupted"
    assert np.all(np.diff(session.t) > 0)
