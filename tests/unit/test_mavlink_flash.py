# SPDX-License-Identifier: Apache-2.0
"""Planning, backing up and confirming an autopilot flash (magcal.autopilot.flash), on fakes."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from magcal.autopilot import flash as F
from magcal.autopilot import mapping, rotations, vehicle, wmm
from magcal.autopilot import params as P
from magcal.errors import MagcalError
from magcal.io.result import CalibrationResult

FIELD_MG = 500.0
FIELD = wmm.Field(FIELD_MG * 100.0, 60.0, 0.0, "test")


def _ap_in_force(orient=0, **extra):
    v = {
        f"COMPASS_{g}_{a}": x for g, x in (("OFS", 10.0), ("DIA", 1.0), ("ODI", 0.0)) for a in "XYZ"
    }
    v |= {"COMPASS_SCALE": 1.0, "COMPASS_ORIENT": float(orient), "COMPASS_EXTERNAL": 1.0}
    v |= {"COMPASS_OFFS_MAX": 1800.0, "CUST_ROT_ENABLE": 0.0, "AHRS_ORIENTATION": 0.0}
    v |= {"COMPASS_ORIENT2": 0.0, "COMPASS_ORIENT3": 0.0} | extra
    types = {
        n: (P.INT8 if "ORIENT" in n or n.endswith(("ENABLE", "EXTERNAL")) else P.REAL32) for n in v
    }
    return vehicle.CompassParams(vehicle.ARDUPILOT, 1, v, types, mapping.AP_NAMING_LEGACY, True)


def _calibration(rng, misalign_deg=2.0, offset=150.0):
    """A (3, 3) sensor-frame distortion D (mG per unit field) and o (mG)."""
    W = np.eye(3) + rng.uniform(-0.04, 0.04, (3, 3))
    W = (W + W.T) / 2
    axis = rng.normal(size=3)
    R_mis = rotations.euler_deg_to_matrix(*(misalign_deg * axis / np.linalg.norm(axis)))
    return FIELD_MG * W @ R_mis.T, rng.uniform(-offset, offset, 3)


def test_ardupilot_plan_reproduces_the_correction_with_a_custom_rotation():
    rng = np.random.default_rng(0)
    D_raw, o_raw = _calibration(rng)
    R_old = rotations.ardupilot_matrix(6)
    D, o = R_old @ D_raw, R_old @ o_raw  # the session frame y = R_old·raw
    cp = _ap_in_force(orient=6)
    plan = F.plan_flash(np.linalg.inv(D), o, cp, FIELD, recorded=dict(cp.values))
    names = [e.name for e in plan.writes]
    assert names[0] == "CUST_ROT_ENABLE" and names[-1] == "COMPASS_ORIENT"
    assert names.index("CUST_ROT1_YAW") < names.index("COMPASS_OFS_X")
    new = cp.values | {e.name: e.value for e in plan.writes}
    assert new["COMPASS_ORIENT"] == 101
    raw = rng.normal(size=(50, 3)) * 400
    want = FIELD_MG * (raw @ R_old.T - o) @ np.linalg.inv(D).T
    got = mapping.ardupilot_correct(raw, new)
    assert np.abs(got - want).max() < 1e-4 * FIELD_MG  # float32 parameters
    assert plan.reboot_reasons  # CUST_ROT_ENABLE 0 → 1 is 'reboot required' in ArduPilot


def test_ardupilot_external_compass_needs_the_recorded_rotation():
    rng = np.random.default_rng(1)
    D, o = _calibration(rng)
    with pytest.raises(MagcalError, match="pass --session SESSION.csv"):
        F.plan_flash(np.linalg.inv(D), o, _ap_in_force(), FIELD)


def test_offsets_beyond_compass_offs_max_are_refused():
    rng = np.random.default_rng(2)
    D, _ = _calibration(rng)
    cp = _ap_in_force(COMPASS_OFFS_MAX=500.0)
    with pytest.raises(mapping.AutopilotMappingError, match="exceeds COMPASS_OFFS_MAX 500 mG"):
        F.plan_flash(np.linalg.inv(D), np.array([900.0, 0, 0]), cp, FIELD, recorded=cp.values)


def test_a_custom_slot_in_use_elsewhere_is_not_taken():
    rng = np.random.default_rng(3)
    D, o = _calibration(rng)
    cp = _ap_in_force(AHRS_ORIENTATION=101.0)
    plan = F.plan_flash(np.linalg.inv(D), o, cp, FIELD, recorded=cp.values)
    written = {e.name: e.value for e in plan.writes}
    assert written["COMPASS_ORIENT"] == 102 and "CUST_ROT2_ROLL" in written
    assert not any(n.startswith("CUST_ROT1") for n in written)
    both = _ap_in_force(AHRS_ORIENTATION=101.0, COMPASS_ORIENT2=102.0)
    plan = F.plan_flash(np.linalg.inv(D), o, both, FIELD, recorded=both.values)
    assert plan.mapped.heading_rms_deg > 0.1  # left out, and its cost said
    assert any("not represented" in n for n in plan.mapped.notes)


def test_ardupilot_rotation_within_its_uncertainty_is_written_enumerated_without_a_warning():
    from magcal.commands.flash.autopilot import LEFT_OUT_WARN_DEG, _left_out

    rng = np.random.default_rng(6)
    D, o = _calibration(rng, misalign_deg=2.0)
    cp = _ap_in_force()
    sigma = np.array([2.0, 2.0, 2.0])
    plan = F.plan_flash(
        np.linalg.inv(D), o, cp, FIELD, recorded=cp.values, rotation_sigma_deg=sigma
    )
    assert plan.mapped.snapped and any("within its uncertainty" in n for n in plan.mapped.notes)
    new = {e.name: e.value for e in plan.writes + plan.unchanged}
    assert new["COMPASS_ORIENT"] == 0 and not any(n.startswith("CUST_ROT") for n in new)
    # costly enough that, were it not snapped, flash would exit 3 and ask for a custom rotation
    assert plan.mapped.heading_rms_deg >= LEFT_OUT_WARN_DEG
    assert _left_out(plan) == 0


def _px4_in_force(rot=0, z_off=0.0, external=True):
    v = {f"CAL_MAG0_{a}OFF": 0.0 for a in "XYZ"} | {f"CAL_MAG0_{a}SCALE": 1.0 for a in "XYZ"}
    v |= {f"CAL_MAG0_{a}ODIAG": 0.0 for a in "XYZ"} | {
        "CAL_MAG0_ROT": float(rot if external else -1)
    }
    v |= {"SENS_BOARD_X_OFF": 0.0, "SENS_BOARD_Y_OFF": 0.0, "SENS_BOARD_Z_OFF": z_off}
    types = {n: P.INT32 if n.endswith("_ROT") else P.REAL32 for n in v}
    return vehicle.CompassParams(vehicle.PX4, 1, v, types, "", external)


@pytest.mark.parametrize("z_off", [0.0, 90.0])
def test_px4_plan_reproduces_an_enumerated_mounting_through_the_level_trim(z_off):
    rng = np.random.default_rng(4)
    W = np.eye(3) + 0.03 * rng.normal(size=(3, 3))
    W = (W + W.T) / 2
    R = rotations.px4_matrix(10)
    A = R @ np.linalg.inv(W)  # the correction wanted: enumerated rotation × symmetric
    o = rng.uniform(-0.2, 0.2, 3)
    F_G = 0.5
    cp = _px4_in_force(z_off=z_off)
    plan = F.plan_flash(A / F_G, o, cp, wmm.Field(F_G * 1e5, 60.0, None, "t"), allow_custom=False)
    assert plan.mapped.residual_angle_deg < 1e-6
    new = (
        cp.values
        | {e.name: e.value for e in plan.writes}
        | {e.name: e.value for e in plan.unchanged}
    )
    y = rng.normal(size=(20, 3)) * 0.4
    got = vehicle.onboard_correction(
        y, vehicle.CompassParams(vehicle.PX4, 1, new, cp.types, "", True)
    )
    assert np.abs(got - (y - o) @ A.T).max() < 1e-6


def test_px4_refusals():
    D_inv, o = np.eye(3), np.zeros(3)
    with pytest.raises(MagcalError, match="internal .*SENS_BOARD_ROT"):
        F.plan_flash(D_inv, o, _px4_in_force(external=False), FIELD)
    with pytest.raises(MagcalError, match="no CAL_MAG0_ROLL/PITCH/YAW"):
        F.plan_flash(D_inv, o, _px4_in_force(), FIELD, allow_custom=True)


def test_px4_small_changes_written_one_by_one_need_a_reboot():
    cp = _px4_in_force()
    writes = (
        P.ParamEntry("CAL_MAG0_XSCALE", 1.005, P.REAL32),
        P.ParamEntry("CAL_MAG0_YSCALE", 1.02, P.REAL32),
        P.ParamEntry("CAL_MAG0_ZSCALE", 1.005, P.REAL32),
        P.ParamEntry("CAL_MAG0_XOFF", 0.2, P.REAL32),
    )
    reasons = F.px4_reboot_reasons(cp.values, writes, 0)
    assert len(reasons) == 1 and "CAL_MAG0_*SCALE" in reasons[0]
    assert F.px4_reboot_reasons(cp.values, writes[1:2] + writes[3:], 0) == []


def test_result_units_are_converted_or_refused():
    D = np.diag([50.0, 50.0, 50.0])
    r = CalibrationResult("ml", D, np.array([1.0, 2, 3]), np.array([1.0, 0, 0]), 0.0)
    r_uT = CalibrationResult(
        "ml", D, np.array([1.0, 2, 3]), np.array([1.0, 0, 0]), 0.0, extra={"mag_unit": "uT"}
    )
    D_inv, o, unit = F.result_in_unit(r_uT, "mG", None, "r.json")
    assert (
        unit == "uT"
        and D_inv == pytest.approx(np.eye(3) / 500.0)
        and o == pytest.approx([10, 20, 30])
    )
    with pytest.raises(MagcalError, match="unit of its D and o is unknown"):
        F.result_in_unit(r, "mG", None, "r.json")
    with pytest.raises(MagcalError, match="says its magnetometer unit is 'uT' but --mag-unit"):
        F.result_in_unit(r_uT, "mG", "gauss", "r.json")


def test_restore_order_hides_custom_rotations_last():
    entries = (
        P.ParamEntry("CUST_ROT_ENABLE", 0.0, P.INT8),
        P.ParamEntry("COMPASS_ORIENT", 6.0, P.INT8),
        P.ParamEntry("COMPASS_OFS_X", 1.0, P.REAL32),
    )
    order = [e.name for e in F.order_writes(vehicle.ARDUPILOT, entries, {})]
    assert order == ["COMPASS_OFS_X", "COMPASS_ORIENT", "CUST_ROT_ENABLE"]


# ------------------------------------------------------------------------------ fakes
class FakeAutopilot:
    """Parameters in a dict; ``lose(name, attempt)`` says whether an echo is lost; ``hidden``
    names never answer; ``clamp`` maps a name to the value the vehicle stores instead."""

    autopilot = vehicle.ARDUPILOT
    url = "fake:"
    name = "ArduPilot"
    heartbeat = SimpleNamespace(system=1, component=1, vehicle_type=2)

    def __init__(self, values, types, lose=lambda name, attempt: False, hidden=(), clamp=None):
        self.values, self.types, self.lose = dict(values), types, lose
        self.hidden, self.clamp = set(hidden), clamp or {}
        self.sets: list[str] = []

    def read(self, name, tries=None):
        if name in self.hidden or name not in self.values:
            return None
        return P.ParamEntry(name, self.values[name], self.types[name])

    def write_once(self, name, value, ptype):
        attempt = self.sets.count(name)
        self.sets.append(name)
        self.values[name] = self.clamp.get(name, value)
        if self.lose(name, attempt):
            return None
        return P.ParamEntry(name, self.values[name], ptype)


def _writes(n=5):
    return tuple(
        P.ParamEntry(f"COMPASS_OFS_{i}", float(np.float32(i + 0.1)), P.REAL32) for i in range(n)
    )


def test_lost_echoes_are_retried_until_confirmed():
    fake = FakeAutopilot({}, {}, lose=lambda name, attempt: attempt < 3)
    assert F.write_and_confirm(fake, _writes()) == ()
    assert len(fake.sets) == 5 * 4


def test_a_different_echo_is_reported_with_its_value():
    fake = FakeAutopilot({}, {}, clamp={"COMPASS_OFS_2": 7.0})
    (u,) = F.write_and_confirm(fake, _writes(), tries=3)
    assert (u.name, u.echoed, u.sent) == ("COMPASS_OFS_2", 7.0, True)
    assert fake.sets.count("COMPASS_OFS_2") == 3
    assert "vehicle echoed 7" in F.unconfirmed_text((u,))


def test_a_silent_link_is_given_up_and_the_rest_not_sent():
    fake = FakeAutopilot({}, {}, lose=lambda name, attempt: True)
    failed = F.write_and_confirm(fake, _writes(6), tries=2)
    assert [u.sent for u in failed] == [True, True, True, False, False, False]
    assert set(fake.sets) == {"COMPASS_OFS_0", "COMPASS_OFS_1", "COMPASS_OFS_2"}
    assert "hold their old values): COMPASS_OFS_3, COMPASS_OFS_4, COMPASS_OFS_5" in (
        F.unconfirmed_text(failed)
    )


def test_backup_saves_what_is_in_force_and_notes_hidden_custom_angles(tmp_path):
    cp = _ap_in_force(orient=6)
    fake = FakeAutopilot(cp.values, cp.types, hidden={"CUST_ROT1_ROLL"})
    path = tmp_path / "b.params"
    b = F.back_up(fake, ["CUST_ROT_ENABLE", "CUST_ROT1_ROLL", "COMPASS_ORIENT"], path, what="t")
    assert b.hidden == ("CUST_ROT1_ROLL",) and fake.sets == []  # nothing written
    saved = P.read_param_file(path)
    assert saved.as_dict() == {"CUST_ROT_ENABLE": 0.0, "COMPASS_ORIENT": 6.0}
    assert any("CUST_ROT1_ROLL (hidden while CUST_ROT_ENABLE = 0" in c for c in saved.comments)
    assert P.read_param_file(path.with_suffix(".parm")).as_dict() == saved.as_dict()
    with pytest.raises(MagcalError, match="no answer for COMPASS_OFS_Q while backing up"):
        F.back_up(fake, ["COMPASS_OFS_Q"], tmp_path / "c.params", what="t")
    assert not (tmp_path / "c.params").exists()


def test_px4_never_applied_vectors_are_noted_with_their_cost_and_are_no_reboot_reason():
    cp = _px4_in_force()
    F_G = 0.5
    S = np.array([[1.02, 0.004, 0.003], [0.004, 0.98, -0.005], [0.003, -0.005, 1.03]])
    o = np.array([0.003, -0.004, 0.002])  # norm 0.0054: never applied either
    plan = F.plan_flash(S / F_G, o, cp, wmm.Field(F_G * 1e5, 60.0, None, "t"), allow_custom=False)
    assert plan.never_applied == ("OFF", "ODIAG")
    assert plan.reboot_reasons == ()
    (note,) = [n for n in plan.mapped.notes if "never applies" in n]
    final = cp.values | {e.name: e.value for e in plan.writes + plan.unchanged}
    cost = mapping.px4_unapplied_heading_rms_deg(final, 0, F_G, 60.0)
    assert f"costs {cost:.2f}° RMS heading error" in note and cost > 0.1
    # verify's model of the vehicle: the same as with those vectors at their reset values
    cp_new = vehicle.CompassParams(vehicle.PX4, 1, final, cp.types, "", True)
    reset = final | {f"CAL_MAG0_{a}{g}": 0.0 for a in "XYZ" for g in ("OFF", "ODIAG")}
    cp_reset = vehicle.CompassParams(vehicle.PX4, 1, reset, cp.types, "", True)
    y = np.random.default_rng(9).normal(size=(20, 3)) * 0.4
    assert np.array_equal(
        vehicle.onboard_correction(y, cp_new), vehicle.onboard_correction(y, cp_reset)
    )
    # a vector beyond the threshold is applied, and a reboot reason only while it is not in use
    bigger = F.px4_reboot_reasons(cp.values, (P.ParamEntry("CAL_MAG0_XODIAG", 0.02, P.REAL32),), 0)
    assert bigger == []


@pytest.mark.parametrize("board", [0, 2])
def test_px4_internal_compass_keeps_the_board_rotation(board):
    """PX4 turns an internal compass (CAL_MAG0_ROT −1) with SENS_BOARD_ROT: the plan writes
    offsets and scales, never CAL_MAG0_ROT, and the vehicle's correction with them is the
    calibration when the sensor sits along the board."""
    rng = np.random.default_rng(5)
    W = np.eye(3) + 0.02 * rng.normal(size=(3, 3))
    W = (W + W.T) / 2
    R = rotations.px4_matrix(board)
    A = R @ np.linalg.inv(W)
    o = rng.uniform(-0.15, 0.15, 3)
    F_G = 0.5
    cp = _px4_in_force(external=False)
    cp.values["SENS_BOARD_ROT"] = float(board)
    cp.types["SENS_BOARD_ROT"] = P.INT32
    plan = F.plan_flash(A / F_G, o, cp, wmm.Field(F_G * 1e5, 60.0, None, "t"), allow_custom=True)
    names = {e.name for e in plan.writes} | {e.name for e in plan.unchanged}
    assert "CAL_MAG0_ROT" not in names and "CAL_MAG0_ROLL" not in names
    assert plan.mapped.residual_angle_deg < 1e-6
    new = cp.values | {e.name: e.value for e in plan.writes}
    y = rng.normal(size=(20, 3)) * 0.4
    got = vehicle.onboard_correction(
        y, vehicle.CompassParams(vehicle.PX4, 1, new, cp.types, "", False)
    )
    assert np.abs(got - (y - o) @ A.T).max() < 1e-6


def test_px4_internal_compass_misalignment_left_out_and_noted():
    cp = _px4_in_force(external=False)
    cp.values["SENS_BOARD_ROT"] = 0.0
    A = rotations.euler_deg_to_matrix(0.0, 0.0, 9.0)
    plan = F.plan_flash(A / 0.5, np.zeros(3), cp, wmm.Field(0.5e5, 60.0, None, "t"))
    assert abs(plan.mapped.residual_angle_deg - 9.0) < 1e-6
    assert plan.mapped.heading_rms_deg > 5.0
    assert any("SENS_BOARD_ROT only" in n for n in plan.mapped.notes)
    # within its uncertainty the board rotation is kept without a warning
    plan = F.plan_flash(
        A / 0.5,
        np.zeros(3),
        cp,
        wmm.Field(0.5e5, 60.0, None, "t"),
        rotation_sigma_deg=np.array([5.0, 5.0, 5.0]),
    )
    assert plan.mapped.snapped
