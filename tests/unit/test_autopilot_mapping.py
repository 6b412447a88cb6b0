"""Tests of magcal.autopilot: enumerated rotations and the parameter mapping (issue 6)."""

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
