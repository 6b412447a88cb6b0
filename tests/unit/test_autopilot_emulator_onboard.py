# SPDX-License-Identifier: Apache-2.0
"""The emulator's on-board corrections and parameter rules, without the link.

Hand-computed numbers pin each reading of the sources; the random cases check that the
emulator's implementation and magcal.autopilot.mapping (written separately from the same
sources) agree to 1e-9.
"""

import math
import struct

import numpy as np
import pytest

from magcal.autopilot import mapping, rotations
from tests.autopilot_emulator import onboard
from tests.autopilot_emulator.params import (
    INT8,
    INT16,
    INT32,
    REAL32,
    ParamSpec,
    ParamStore,
    ap_set_float,
)


def _ap_params(**over):
    p = {"COMPASS_EXTERNAL": 1.0, "COMPASS_ORIENT": 0.0, "COMPASS_SCALE": 1.0}
    for a in "XYZ":
        p |= {f"COMPASS_OFS_{a}": 0.0, f"COMPASS_DIA_{a}": 1.0, f"COMPASS_ODI_{a}": 0.0}
    return p | over


def test_ardupilot_correct_hand_computed():
    # YAW_90 maps (x, y, z) to (-y, x, z); then + OFS, x SCALE, M x
    p = _ap_params(
        COMPASS_ORIENT=2.0, COMPASS_SCALE=1.2,
        COMPASS_OFS_X=10.0, COMPASS_OFS_Y=-20.0, COMPASS_OFS_Z=30.0,
        COMPASS_DIA_X=1.1, COMPASS_DIA_Y=0.9, COMPASS_DIA_Z=1.0,
        COMPASS_ODI_X=0.01, COMPASS_ODI_Y=0.02, COMPASS_ODI_Z=-0.03,
    )  # fmt: skip
    out = onboard.ardupilot_correct([100.0, 200.0, 300.0], p)
    # (-200, 100, 300) + OFS = (-190, 80, 330); x 1.2 = (-228, 96, 396); M x that:
    np.testing.assert_allclose(out[0], [-241.92, 72.24, 388.56], atol=1e-9)


def test_ardupilot_scale_outside_sanity_limits_and_zero_diagonals_are_unused():
    raw = np.array([[100.0, -50.0, 25.0]])
    for scale in (0.0, 0.84, 1.41, 3.0):
        p = _ap_params(COMPASS_SCALE=scale, COMPASS_DIA_X=0.0, COMPASS_DIA_Y=0.0, COMPASS_DIA_Z=0.0)
        np.testing.assert_allclose(onboard.ardupilot_correct(raw, p), raw, atol=1e-12)
    for scale in (0.85, 1.4):  # the bounds are included
        p = _ap_params(COMPASS_SCALE=scale)
        np.testing.assert_allclose(onboard.ardupilot_correct(raw, p), scale * raw, atol=1e-12)


def test_ardupilot_internal_compass_follows_board_orientation():
    p = _ap_params(COMPASS_EXTERNAL=0.0, COMPASS_ORIENT=4.0, AHRS_ORIENTATION=8.0)  # ROLL_180
    out = onboard.ardupilot_correct([1.0, 2.0, 3.0], p)
    np.testing.assert_allclose(out[0], [1.0, -2.0, -3.0], atol=1e-12)


def test_ardupilot_custom_rotation_uses_the_matrix_built_at_first_use():
    p = _ap_params(
        COMPASS_ORIENT=101.0, CUST_ROT1_ROLL=0.0, CUST_ROT1_PITCH=0.0, CUST_ROT1_YAW=90.0
    )
    np.testing.assert_allclose(onboard.ardupilot_correct([1.0, 0, 0], p)[0], [0, 1, 0], atol=1e-12)
    built = {1: np.eye(3)}  # built earlier from zero angles: the new YAW waits for a reboot
    np.testing.assert_allclose(
        onboard.ardupilot_correct([1.0, 0, 0], p, custom=built)[0], [1, 0, 0], atol=1e-12
    )


def _px4_params(index=0, **over):
    p = {f"CAL_MAG{index}_ROT": 0.0, "SENS_BOARD_ROT": 0.0}
    for a in "XYZ":
        p |= {f"CAL_MAG{index}_{a}OFF": 0.0, f"CAL_MAG{index}_{a}SCALE": 1.0}
        p |= {f"CAL_MAG{index}_{a}ODIAG": 0.0}
    return p | over


def test_px4_correct_hand_computed():
    p = _px4_params(
        CAL_MAG0_ROT=4.0,  # YAW_180: (x, y, z) -> (-x, -y, z)
        CAL_MAG0_XOFF=0.1, CAL_MAG0_YOFF=-0.2, CAL_MAG0_ZOFF=0.05,
        CAL_MAG0_XSCALE=1.1, CAL_MAG0_YSCALE=0.9, CAL_MAG0_ZSCALE=1.0,
        CAL_MAG0_XODIAG=0.01, CAL_MAG0_YODIAG=0.02, CAL_MAG0_ZODIAG=-0.03,
    )  # fmt: skip
    out = onboard.px4_correct([0.3, 0.1, -0.4], p)
    # raw - off = (0.2, 0.3, -0.45); S that = (0.214, 0.2855, -0.455); then YAW_180
    np.testing.assert_allclose(out[0], [-0.214, -0.2855, -0.455], atol=1e-12)


def test_px4_ignores_small_changes_until_reboot_and_rewrites_bad_rotations():
    p = _px4_params(CAL_MAG0_XOFF=0.2)
    cal = onboard.Px4MagCalibration.reset(0, True, p)
    assert cal.parameters_update(p) == {}
    np.testing.assert_allclose(cal.offset, [0.2, 0, 0])
    p["CAL_MAG0_XOFF"] = 0.205  # within PX4's 0.01 update threshold: not taken
    cal.parameters_update(p)
    np.testing.assert_allclose(cal.offset, [0.2, 0, 0])
    fresh = onboard.Px4MagCalibration.reset(0, True, p)  # a reboot takes it
    fresh.parameters_update(p)
    np.testing.assert_allclose(fresh.offset, [0.205, 0, 0])
    p["CAL_MAG0_ROT"] = float(onboard.PX4_ROTATION_MAX)
    assert cal.parameters_update(p) == {"CAL_MAG0_ROT": 0.0}
    internal = onboard.Px4MagCalibration.reset(1, False, _px4_params(1, CAL_MAG1_ROT=2.0))
    assert internal.parameters_update(_px4_params(1, CAL_MAG1_ROT=2.0)) == {"CAL_MAG1_ROT": -1.0}
    np.testing.assert_allclose(internal.rotation, np.eye(3))


def test_px4_rejects_non_positive_scales():
    p = _px4_params(CAL_MAG0_XSCALE=-1.0)
    cal = onboard.Px4MagCalibration.reset(0, True, p)
    cal.parameters_update(p)
    np.testing.assert_allclose(cal.scale, np.eye(3))


def _random_ap_params(rng, compass):
    k = onboard.ap_suffix(compass)
    p = {onboard.ap_external_name(compass): 1.0, "CUST_ROT_ENABLE": 1.0}
    orient = int(rng.choice([0, 2, 8, 17, 38, 101, 102]))
    p[f"COMPASS_ORIENT{k}"] = float(orient)
    for slot in (1, 2):
        for a in ("ROLL", "PITCH", "YAW"):
            p[f"CUST_ROT{slot}_{a}"] = rng.uniform(-180, 180)
    for a in "XYZ":
        p[f"COMPASS_OFS{k}_{a}"] = rng.uniform(-500, 500)
        p[f"COMPASS_DIA{k}_{a}"] = rng.uniform(0.8, 1.2)
        p[f"COMPASS_ODI{k}_{a}"] = rng.uniform(-0.1, 0.1)
    p[f"COMPASS_SCALE{k}"] = float(rng.choice([0.0, 0.9, 1.3, 2.0]))
    return p


@pytest.mark.parametrize("compass", [1, 2, 3])
def test_ardupilot_correction_agrees_with_magcal_mapping(compass):
    rng = np.random.default_rng(compass)
    for _ in range(20):
        p = _random_ap_params(rng, compass)
        raw = rng.uniform(-600, 600, (50, 3))
        ours = onboard.ardupilot_correct(raw, p, compass)
        theirs = mapping.ardupilot_correct(raw, p, compass)
        np.testing.assert_allclose(ours, theirs, rtol=0, atol=1e-9)


@pytest.mark.parametrize("index", [0, 1, 2])
def test_px4_correction_agrees_with_magcal_mapping(index):
    rng = np.random.default_rng(10 + index)
    for _ in range(20):
        p = _px4_params(index, CAL_MAG0_ROT=0.0)
        p[f"CAL_MAG{index}_ROT"] = float(rng.integers(0, 41))
        # changes from the boot state (zero, identity) beyond PX4's 0.01 update threshold,
        # which magcal's mapping does not model (see the next test)
        sign = rng.choice((-1.0, 1.0), (3, 3))
        for i, a in enumerate("XYZ"):
            p[f"CAL_MAG{index}_{a}OFF"] = sign[0, i] * rng.uniform(0.02, 0.5)
            p[f"CAL_MAG{index}_{a}SCALE"] = 1.0 + sign[1, i] * rng.uniform(0.02, 0.2)
            p[f"CAL_MAG{index}_{a}ODIAG"] = sign[2, i] * rng.uniform(0.01, 0.1)
        raw = rng.uniform(-0.6, 0.6, (50, 3))
        ours = onboard.px4_correct(raw, p, index, external=True)
        theirs = mapping.px4_correct(raw, p, index)
        np.testing.assert_allclose(ours, theirs, rtol=0, atol=1e-9)


def test_px4_never_applies_off_diagonals_within_its_threshold_of_zero():
    # Magnetometer::set_offdiagonal compares with the value in use, zero after Reset(): an
    # off-diagonal vector shorter than 0.01 is never taken, not even at boot
    p = _px4_params(CAL_MAG0_XODIAG=0.005, CAL_MAG0_YODIAG=-0.006, CAL_MAG0_ZODIAG=0.004)
    raw = np.array([[0.3, -0.2, 0.4]])
    np.testing.assert_allclose(onboard.px4_correct(raw, p, external=True), raw, atol=1e-15)
    assert np.abs(mapping.px4_correct(raw, p) - raw).max() > 1e-3  # the mapping applies it


def test_ardupilot_set_float_rounds_integers_and_stores_float32():
    assert ap_set_float(5.999, INT8) == 6.0
    assert ap_set_float(4.98, INT8) == 4.0  # +0.01 then truncation, as AP_Param::set_float
    assert ap_set_float(-3.995, INT8) == -4.0
    assert ap_set_float(40000.0, INT16) == 32767.0
    assert ap_set_float(300.0, INT8) == 127.0
    assert ap_set_float(97539.0, INT32) == 97539.0
    assert ap_set_float(0.1, REAL32) == float(np.float32(0.1))
    assert ap_set_float(math.nan, REAL32) is None
    assert ap_set_float(math.inf, INT32) is None


def test_param_store_encodings():
    specs = [ParamSpec("B_INT", INT32, -1), ParamSpec("A_FLOAT", REAL32, 0.5)]
    px4 = ParamStore("px4", specs)
    assert px4.visible_names() == ["A_FLOAT", "B_INT"]  # PX4 lists in name order
    assert px4.wire_value("B_INT") == (struct.pack("<i", -1), INT32)  # bytewise
    assert px4.set_from_wire("B_INT", struct.pack("<i", 396825)) == 396825.0
    assert px4.set_from_wire("NOPE", struct.pack("<f", 1.0)) is None
    ap = ParamStore("ardupilot", specs)
    assert ap.visible_names() == ["B_INT", "A_FLOAT"]  # ArduPilot: declaration order
    assert ap.wire_value("B_INT") == (struct.pack("<f", -1.0), INT32)  # a cast to float
    assert ap.set_from_wire("B_INT", struct.pack("<f", 7.0)) == 7.0


def test_ardupilot_enable_group_hides_custom_rotation_parameters():
    store = ParamStore(
        "ardupilot",
        [ParamSpec("CUST_ROT_ENABLE", INT8, 0), ParamSpec("CUST_ROT1_ROLL", REAL32, 0.0)],
    )
    assert store.visible_names() == ["CUST_ROT_ENABLE"]
    assert store.lookup("CUST_ROT1_ROLL") is None
    assert store.set_from_wire("CUST_ROT1_ROLL", struct.pack("<f", 5.0)) is None
    store.set_from_wire("CUST_ROT_ENABLE", struct.pack("<f", 1.0))
    assert store.visible_names() == ["CUST_ROT_ENABLE", "CUST_ROT1_ROLL"]


def test_enumerated_rotations_used_on_board_are_the_source_tables():
    # index 38 differs between the autopilots (ArduPilot 68.8/293.3 deg, PX4 68/293)
    assert (
        rotations.rotation_angle_deg(onboard.ap_enumerated_matrix(38), rotations.px4_matrix(38))
        > 0.5
    )
    np.testing.assert_allclose(onboard.ap_enumerated_matrix(99), np.eye(3))
