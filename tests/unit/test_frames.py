# SPDX-License-Identifier: Apache-2.0
import numpy as np
import pytest

from magcal.calib import frames


def test_quaternion_product_matches_matrix_product():
    q = frames.so3_grid(20)
    R = frames.quat_to_matrix(q)
    prod = frames.quat_to_matrix(frames.quat_multiply(q[:10], q[10:]))
    np.testing.assert_allclose(prod, R[:10] @ R[10:], atol=1e-14)


def test_matrix_quaternion_round_trip_all_branches():
    q = np.vstack([frames.so3_grid(50), [[0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]])
    R = frames.quat_to_matrix(q)
    np.testing.assert_allclose(frames.quat_to_matrix(frames.matrix_to_quat(R)), R, atol=1e-14)


def test_rotvec_round_trip_and_small_angles():
    for v in ([0.1, -0.2, 0.3], [1e-12, 0, 0], [0, 0, 3.0]):
        np.testing.assert_allclose(frames.quat_to_rotvec(frames.rotvec_to_quat(v)), v, atol=1e-15)


def test_integration_convention_body_rate():
    # A body rate about body z turns q_nb about its own z: the body x axis, seen in n,
    # turns from north towards west/east by the angle.
    q = frames.quat_multiply([1.0, 0, 0, 0], frames.quat_exp(0.5 * np.array([0, 0, 0.3])))
    x_n = frames.quat_to_matrix(q) @ [1.0, 0, 0]
    assert frames.heading_of(x_n) == pytest.approx(0.3)


def test_scalar_gyroscope_step_matches_the_vectorised_integration():
    rng = np.random.default_rng(3)
    rates = rng.normal(0.0, 2.0, (300, 3))
    rates[:5] = 1e-12  # the small-angle branch
    dt = np.full(300, 0.01)
    q = (1.0, 0.0, 0.0, 0.0)
    for phi in rates * dt[:, None]:
        q = frames.quat_step(q, tuple(phi))
    expected = frames.integrate_rates(rates, dt)[-1]
    np.testing.assert_allclose(
        frames.quat_to_matrix(np.array(q)), frames.quat_to_matrix(expected), atol=1e-12
    )
    assert abs(np.linalg.norm(q) - 1.0) < 1e-15


def test_triad_recovers_attitude():
    m_n = frames.field_direction(np.deg2rad(65))
    for q in frames.so3_grid(7):
        R_bn = frames.quat_to_matrix(q).T
        up_b = R_bn @ [0, 0, 1.0]
        q_est = frames.triad(9.81 * up_b, 3.0 * R_bn @ m_n, m_n)
        np.testing.assert_allclose(
            frames.quat_to_matrix(q_est), frames.quat_to_matrix(q), atol=1e-12
        )


def test_heading_error_between():
    q = frames.so3_grid(5)
    dz = frames.rotvec_to_quat([0, 0, 0.05])  # a heading error applied in n
    np.testing.assert_allclose(frames.heading_error_between(frames.quat_multiply(dz, q), q), 0.05)


def test_so3_grid_covers_rotations():
    R = frames.quat_to_matrix(frames.so3_grid(500))
    # Each body axis should point every way: the scatter of its n-frame direction is ≈ I/3.
    for k in range(3):
        d = R[:, :, k]
        np.testing.assert_allclose(d.T @ d / len(d), np.eye(3) / 3, atol=0.02)
