# SPDX-License-Identifier: Apache-2.0
"""Tests of magcal.autopilot: enumerated rotations and the parameter mapping."""

from __future__ import annotations

import numpy as np
import pytest

from magcal.autopilot import rotations as rot


# --- hand-transcribed Vector3::rotate() cases (ArduPilot libraries/AP_Math/vector3.cpp) ----
def _ap_roll_90(x, y, z):  # case ROTATION_ROLL_90: tmp = z; z = y; y = -tmp;
    return np.array([x, -z, y])


def _ap_pitch_180_yaw_90(x, y, z):  # z = -z; tmp = -x; x = -y; y = tmp;
    return np.array([-y, -x, -z])


def _ap_roll_270_pitch_90(x, y, z):  # tmp = z; z = -y; y = tmp; tmp = z; z = -x; x = tmp;
    y, z = z, -y
    x, z = z, -x
    return np.array([x, y, z])


def _ap_yaw_135(x, y, z):  # tmp = -H*(x + y); y = H*(x - y); x = tmp;
    h = np.sqrt(0.5)
    return np.array([-h * (x + y), h * (x - y), z])


#: ROTATION_ROLL_90_PITCH_68_YAW_293, explicit matrix in vector3.cpp / rotate_3f
AP_38 = np.array(
    [
        [0.14303897231223747, 0.36877648650320383, -0.91844638134308709],
        [-0.33213277779664740, -0.85628942146641884, -0.39554550256296522],
        [-0.93232380121551217, 0.36162457008209242, 0.0],
    ]
)
#: PX4 rotation.cpp rotate_3f ROTATION_ROLL_90_PITCH_68_YAW_293 (float, 6 digits)
PX4_38 = np.array(
    [
        [0.146371, 0.362280, -0.920505],
        [-0.344827, -0.853477, -0.390731],
        [-0.927184, 0.374607, 0.0],
    ]
)


@pytest.mark.parametrize(
    ("index", "func"),
    [(16, _ap_roll_90), (26, _ap_pitch_180_yaw_90), (30, _ap_roll_270_pitch_90), (3, _ap_yaw_135)],
)
def test_ardupilot_entries_match_vector3_rotate(index, func):
    v = np.array([0.3, -1.2, 2.5])
    assert np.allclose(rot.ardupilot_matrix(index) @ v, func(*v), atol=1e-12)


def test_roll_90_pitch_68_yaw_293_differs_between_autopilots():
    assert np.allclose(rot.ardupilot_matrix(38), AP_38, atol=1e-15)
    assert np.allclose(rot.px4_matrix(38), PX4_38, atol=1e-6)
    assert 0.5 < rot.rotation_angle_deg(rot.ardupilot_matrix(38), rot.px4_matrix(38)) < 1.5


def test_pitch_7_matches_quaternion():
    # quaternion.cpp from_rotation(ROTATION_PITCH_7): q1 = 0.99813479, q3 = 0.06104854
    q = np.array([0.99813479, 0.0, 0.06104854, 0.0])
    from magcal.calib import frames

    assert np.allclose(frames.quat_to_matrix(q), rot.ardupilot_matrix(41), atol=1e-7)


@pytest.mark.parametrize("mats", [rot.ARDUPILOT_MATRICES, rot.PX4_MATRICES])
def test_every_enumerated_rotation_is_proper(mats):
    for R in mats:
        assert np.allclose(R @ R.T, np.eye(3), atol=1e-12)
        assert np.isclose(np.linalg.det(R), 1.0)


def test_tables_sizes_and_common_entries():
    assert len(rot.ARDUPILOT_TABLE) == 44
    assert len(rot.PX4_TABLE) == 48
    for k in range(41):
        if k != 38:
            assert np.allclose(rot.ardupilot_matrix(k), rot.px4_matrix(k))


def test_euler_round_trip_and_gimbal_lock():
    rng = np.random.default_rng(1)
    for _ in range(50):
        r, p, y = rng.uniform(-180, 180), rng.uniform(-89, 89), rng.uniform(-180, 180)
        R = rot.euler_deg_to_matrix(r, p, y)
        assert np.allclose(rot.euler_deg_to_matrix(*rot.matrix_to_euler_deg(R)), R, atol=1e-12)
    for k in (24, 25, 28, 33):  # pitch ±90
        R = rot.ardupilot_matrix(k)
        assert np.allclose(rot.euler_deg_to_matrix(*rot.matrix_to_euler_deg(R)), R, atol=1e-12)


def test_nearest_finds_enumerated_and_angle():
    small = rot.euler_deg_to_matrix(2.0, 0.0, 0.0)
    n = rot.nearest(small @ rot.ardupilot_matrix(19), "ardupilot")
    assert n.index == 19
    assert n.angle_deg == pytest.approx(2.0)
    assert rot.nearest(rot.ardupilot_matrix(26), "ardupilot").index == 14  # duplicate → lower
    assert rot.nearest(rot.px4_matrix(45), "px4").index != 45  # beyond 40 unless allowed
    assert rot.nearest(rot.px4_matrix(45), "px4", max_index=47).index == 45
    with pytest.raises(ValueError, match="unknown autopilot"):
        rot.nearest(np.eye(3), "betaflight")


# --- mapping ---------------------------------------------------------------------------------
from magcal.autopilot import mapping  # noqa: E402
from magcal.autopilot.mapping import AutopilotMappingError  # noqa: E402


def _random_rotation(rng, max_deg=180.0):
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    ang = np.deg2rad(rng.uniform(0, max_deg))
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(ang) * K + (1 - np.cos(ang)) * K @ K


def _random_calibration(rng, F, misalign_deg=10.0):
    """D = F · (rotation × SPD near identity), o within a few tenths of F."""
    Q = _random_rotation(rng, misalign_deg)
    B = rng.normal(scale=0.08, size=(3, 3))
    spd = np.eye(3) + (B + B.T) / 2
    D = F * Q @ spd
    o = rng.normal(scale=0.3 * F, size=3)
    return np.linalg.inv(D), o


@pytest.mark.parametrize("seed", range(20))
@pytest.mark.parametrize("old_orient", [0, 6, 38])
def test_ardupilot_round_trip_custom(seed, old_orient):
    rng = np.random.default_rng(seed)
    F = 500.0
    D_inv, o = _random_calibration(rng, F)
    R_old = rot.ardupilot_matrix(old_orient)
    out = mapping.to_ardupilot(D_inv, o, F, R_old, compass=2)
    raw = rng.normal(scale=600, size=(50, 3))
    y = raw @ R_old.T
    ours = F * (y - o) @ D_inv.T
    assert out.params["COMPASS_ORIENT2"] == 101
    assert np.allclose(mapping.ardupilot_correct(raw, out.params, compass=2), ours, atol=1e-9 * F)
    assert out.heading_rms_deg == 0.0


@pytest.mark.parametrize("seed", range(10))
def test_ardupilot_round_trip_enumerated(seed):
    rng = np.random.default_rng(100 + seed)
    F = 480.0
    _, o = _random_calibration(rng, F)
    B = rng.normal(scale=0.05, size=(3, 3))
    P = np.eye(3) + (B + B.T) / 2
    R_old = rot.ardupilot_matrix(0)
    target = rot.ardupilot_matrix(int(rng.integers(0, 44)))
    D_inv = P @ target / F  # F·D⁻¹ = P' U' with U' enumerated
    out = mapping.to_ardupilot(D_inv, o, F, R_old)
    assert rot.ardupilot_matrix(int(out.params["COMPASS_ORIENT"])) == pytest.approx(target)
    raw = rng.normal(scale=600, size=(50, 3))
    ours = F * (raw @ R_old.T - o) @ D_inv.T
    assert np.allclose(mapping.ardupilot_correct(raw, out.params), ours, atol=1e-9 * F)


@pytest.mark.parametrize("seed", range(20))
@pytest.mark.parametrize("rot0", [None, 2, 38])
def test_px4_round_trip_custom(seed, rot0):
    rng = np.random.default_rng(200 + seed)
    F = 0.5
    D_inv, o = _random_calibration(rng, F)
    Rot0 = None if rot0 is None else rot.px4_matrix(rot0)
    out = mapping.to_px4(D_inv, o, F, Rot0, index=1, allow_custom=True)
    raw = rng.normal(scale=0.6, size=(50, 3))
    y = raw if Rot0 is None else raw @ Rot0.T
    ours = F * (y - o) @ D_inv.T
    assert out.params["CAL_MAG1_ROT"] == 100
    assert np.allclose(mapping.px4_correct(raw, out.params, index=1), ours, atol=1e-9 * F)


@pytest.mark.parametrize("seed", range(10))
def test_px4_round_trip_enumerated(seed):
    rng = np.random.default_rng(300 + seed)
    F = 0.45
    _, o = _random_calibration(rng, F)
    B = rng.normal(scale=0.05, size=(3, 3))
    P = np.eye(3) + (B + B.T) / 2
    target = rot.px4_matrix(int(rng.integers(0, 41)))
    D_inv = target @ P / F  # F·D⁻¹ = U P with U enumerated
    out = mapping.to_px4(D_inv, o, F)
    assert rot.px4_matrix(int(out.params["CAL_MAG0_ROT"])) == pytest.approx(target)
    raw = rng.normal(scale=0.6, size=(50, 3))
    ours = F * (raw - o) @ D_inv.T
    assert np.allclose(mapping.px4_correct(raw, out.params), ours, atol=1e-9 * F)


def test_polar_forms():
    rng = np.random.default_rng(5)
    A = rng.normal(size=(3, 3))
    U, P = mapping.polar_right(A)
    P2, U2 = mapping.polar_left(A)
    assert np.allclose(U @ P, A) and np.allclose(P2 @ U2, A)
    assert np.allclose(U, U2) and np.allclose(P, P.T) and np.allclose(P2, P2.T)


def test_ardupilot_offset_limit_refused():
    F = 500.0
    with pytest.raises(AutopilotMappingError, match=r"COMPASS_OFS_X = -2000 mG exceeds"):
        mapping.to_ardupilot(np.eye(3) / F, np.array([2000.0, 0, 0]), F, np.eye(3))


def test_ardupilot_diagonal_limit_refused():
    F = 500.0
    with pytest.raises(AutopilotMappingError, match=r"COMPASS_DIA_Z = .* outside 0.2–5.0"):
        mapping.to_ardupilot(np.diag([1, 1, 30.0]) / F, np.zeros(3), F, np.eye(3))


def test_ardupilot_offdiagonal_limit_refused():
    F = 500.0
    S = np.array([[2.0, 1.5, 0], [1.5, 2.0, 0], [0, 0, 1.0]])
    with pytest.raises(AutopilotMappingError, match=r"COMPASS_ODI_X = .* outside ±1.0"):
        mapping.to_ardupilot(S / F, np.zeros(3), F, np.eye(3))


def test_ardupilot_scale_used_when_diagonal_out_of_range():
    F = 500.0
    D_inv = np.diag([5.5, 5.2, 5.3]) / F
    out = mapping.to_ardupilot(D_inv, np.zeros(3), F, np.eye(3))
    assert out.params["COMPASS_SCALE"] == pytest.approx(1.4)
    raw = np.random.default_rng(0).normal(size=(10, 3))
    assert np.allclose(mapping.ardupilot_correct(raw, out.params), F * raw @ D_inv.T)


def test_px4_scale_limit_refused_and_offset_warning():
    F = 0.5
    with pytest.raises(AutopilotMappingError, match=r"CAL_MAG0_YSCALE = 4.000 outside 0.1–3.0"):
        mapping.to_px4(np.diag([1, 4.0, 1]) / F, np.zeros(3), F)
    out = mapping.to_px4(np.eye(3) / F, np.array([0, 0, 1.5]), F)
    assert any("ZOFF" in n for n in out.notes)


def test_reflection_refused():
    with pytest.raises(AutopilotMappingError, match="reflection"):
        mapping.to_px4(np.diag([1, 1, -1.0]), np.zeros(3), 1.0)


@pytest.mark.parametrize("autopilot", ["ardupilot", "px4"])
def test_unrepresentable_rotation_heading_error_grows(autopilot):
    F = 500.0 if autopilot == "ardupilot" else 0.5
    errors = []
    for angle in (1.0, 3.0, 10.0):
        D_inv = rot.euler_deg_to_matrix(0, 0, angle) / F
        if autopilot == "ardupilot":
            out = mapping.to_ardupilot(D_inv, np.zeros(3), F, np.eye(3), allow_custom=False)
        else:
            out = mapping.to_px4(D_inv, np.zeros(3), F, allow_custom=False)
        assert out.residual_angle_deg == pytest.approx(angle)
        assert any("not represented" in n for n in out.notes)
        errors.append(out.heading_rms_deg)
    assert 0 < errors[0] < errors[1] < errors[2]
    # a body-z misalignment of 10° is a 10° heading error when level, more or less when tilted
    assert 5.0 < errors[2] < 20.0


def test_internal_compass_keeps_rotation():
    F = 500.0
    D_inv = rot.euler_deg_to_matrix(3, 0, 0) / F
    out = mapping.to_ardupilot(D_inv, np.zeros(3), F, np.eye(3), external=False)
    assert "COMPASS_ORIENT" not in out.params
    assert out.residual_angle_deg == pytest.approx(3.0)
    assert out.heading_rms_deg > 0


@pytest.mark.parametrize("seed", range(10))
def test_uncorrect_inverts_the_onboard_correction(seed):
    """Undoing the correction in force gives back the raw field (the collect and import paths
    recover raw data this way), for both autopilots and with scale factors on and off."""
    rng = np.random.default_rng(400 + seed)
    D_inv, o = _random_calibration(rng, 500.0)
    ap = mapping.to_ardupilot(D_inv, o, 500.0, rot.ardupilot_matrix(6), compass=3).params
    ap["COMPASS_SCALE3"] = [0.0, 1.2, 3.0][seed % 3]  # 0 and 3.0 are ignored on board
    raw = rng.normal(scale=600, size=(40, 3))
    back = mapping.ardupilot_uncorrect(mapping.ardupilot_correct(raw, ap, 3), ap, 3)
    assert np.allclose(back, raw, rtol=0, atol=1e-9 * 600)
    D_inv, o = _random_calibration(rng, 0.5)
    px = mapping.to_px4(D_inv, o, 0.5, rot.px4_matrix(2), index=2, allow_custom=True).params
    raw = rng.normal(scale=0.6, size=(40, 3))
    back = mapping.px4_uncorrect(mapping.px4_correct(raw, px, 2), px, 2)
    assert np.allclose(back, raw, rtol=0, atol=1e-9 * 0.6)


def test_uncorrect_refuses_a_singular_scale_matrix():
    params = {f"COMPASS_{k}_{a}": 0.0 for k in ("OFS", "ODI") for a in "XYZ"}
    params |= {"COMPASS_DIA_X": 1.0, "COMPASS_DIA_Y": 1.0, "COMPASS_DIA_Z": 0.0}
    params |= {"COMPASS_ORIENT": 0, "COMPASS_SCALE": 0.0}
    with pytest.raises(mapping.AutopilotMappingError, match="singular"):
        mapping.ardupilot_uncorrect(np.ones((2, 3)), params)


# --- the same round trips against the emulator's independent formulas ---------------------------
# tests/autopilot_emulator/onboard.py transcribes each autopilot's on-board correction on its
# own (rotate_field + correct_field; Magnetometer Reset + ParametersUpdate + Correct), so these
# do not share magcal's mapping.ardupilot_correct / px4_correct. Float64 parameters must agree
# to 1e-9; parameters written to a .parm/.params file and read back (float32, as the vehicle
# holds them) to float32 precision.
from magcal.autopilot import flash as _flash  # noqa: E402
from magcal.autopilot import params as _params  # noqa: E402
from tests.autopilot_emulator import onboard  # noqa: E402

#: Float32 parameters: relative rounding 6e-8 on each, raw fields about 1.2 F.
FLOAT32_ATOL_PER_F = 1e-6  # measured: up to 1.6e-7 F (ArduPilot seed 400)


def _through_file(values: dict[str, float], path) -> dict[str, float]:
    entries = tuple(
        _params.ParamEntry(n, _params.held_value(v, t, n), t)
        for n, v in values.items()
        for t in [_flash._type_of(n, {})]
    )
    text = _params.render_param_file(path, _params.ParamFile(entries, 1, 1, ("round trip",)))
    path.write_text(text)
    return _params.read_param_file(path).as_dict()


@pytest.mark.parametrize("seed", range(10))
@pytest.mark.parametrize("suffix", [".parm", ".params"])
def test_ardupilot_round_trip_against_the_independent_formula(seed, suffix, tmp_path):
    rng = np.random.default_rng(400 + seed)
    F = 500.0
    D_inv, o = _random_calibration(rng, F)
    R_old = rot.ardupilot_matrix(6)
    out = mapping.to_ardupilot(D_inv, o, F, R_old, compass=2)
    values = out.params | {mapping.ap_external_name(2): 1.0}
    raw = rng.normal(scale=600, size=(50, 3))
    ours = F * (raw @ R_old.T - o) @ D_inv.T
    assert np.allclose(onboard.ardupilot_correct(raw, values, compass=2), ours, atol=1e-9 * F)
    held = _through_file(values, tmp_path / f"ap{suffix}")
    got = onboard.ardupilot_correct(raw, held, compass=2)
    assert np.allclose(got, ours, rtol=0, atol=FLOAT32_ATOL_PER_F * F)


@pytest.mark.parametrize("seed", range(10))
@pytest.mark.parametrize("suffix", [".parm", ".params"])
def test_px4_round_trip_against_the_independent_formula(seed, suffix, tmp_path):
    rng = np.random.default_rng(500 + seed)
    F = 0.45
    _, o = _random_calibration(rng, F)
    B = rng.normal(scale=0.05, size=(3, 3))
    P = np.eye(3) + (B + B.T) / 2
    target = rot.px4_matrix(int(rng.integers(0, 41)))
    D_inv = target @ P / F
    out = mapping.to_px4(D_inv, o, F)
    # vectors within PX4's 0.01 of their reset values would not be applied (flash notes it)
    assert mapping.px4_unapplied(out.params) == ()
    raw = rng.normal(scale=0.6, size=(50, 3))
    ours = F * (raw - o) @ D_inv.T
    assert np.allclose(onboard.px4_correct(raw, out.params), ours, atol=1e-9 * F)
    held = _through_file(out.params, tmp_path / f"px4{suffix}")
    got = onboard.px4_correct(raw, held)
    assert np.allclose(got, ours, rtol=0, atol=FLOAT32_ATOL_PER_F * F)
