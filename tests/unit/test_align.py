# SPDX-License-Identifier: Apache-2.0
"""Tests of the misalignment step (Algorithm 1, step 1c)."""

from __future__ import annotations

import numpy as np
import pytest

from magcal.calib.frames import (
    field_direction,
    gravity_n,
    quat_multiply,
    quat_normalize,
    quat_to_matrix,
    rotvec_to_matrix,
    rotvec_to_quat,
)
from magcal.calib.initial import alignment
from magcal.calib.initial.alignment import (
    Alignment,
    acceleration_weights,
    estimate_alignment,
    estimate_alignment_from_vertical,
    vertical_from_accelerometer,
)
from magcal.errors import CalibrationError, InsufficientDataError


def _random_rotation(rng: np.random.Generator) -> np.ndarray:
    return quat_to_matrix(quat_normalize(rng.normal(size=4)))


def _scenario(rng, n=5000, dip=1.0, det_sign=1.0):
    """Random attitudes, a lower-triangular D̃ and D = D̃ U; noise-free magnetometer data."""
    q_nb = quat_normalize(rng.normal(size=(n, 4)))
    R_bn = np.swapaxes(quat_to_matrix(q_nb), -1, -2)
    m_b = R_bn @ field_direction(dip)
    L = np.tril(0.2 * rng.normal(size=(3, 3)))
    D_tilde = L + np.diag(rng.uniform(0.8, 1.3, 3) - np.diag(L))
    U = _random_rotation(rng)
    if det_sign < 0:
        U = U @ np.diag([1.0, 1.0, -1.0])
    D = D_tilde @ U
    o = rng.normal(size=3)
    mag = m_b @ D.T + o
    return q_nb, mag, o, D_tilde, D, U


@pytest.mark.parametrize("seed", range(6))
@pytest.mark.parametrize("dip_deg", [0.0, 0.02, -0.02, 4.0, -4.0])
def test_dip_sign_judged_against_its_noise(seed, dip_deg):
    """A dip within its noise of 0° is not called negative; a clearly negative one is."""
    rng = np.random.default_rng(100 + seed)
    q_nb, mag, o, D_tilde, _D, _U = _scenario(rng, n=3000, dip=np.radians(dip_deg))
    mag = mag + 0.02 * rng.normal(size=mag.shape)
    al = estimate_alignment(mag, o, D_tilde, q_nb)
    # 2 % noise on 3000 samples: m_z has a standard error of ≈ 0.02/√3000 (0.02° of dip), so
    # ±0.02° is within the noise and ±4° is 200 standard errors away.
    negative = any("negative" in w for w in al.warnings)
    assert negative == (dip_deg < -1.0)


@pytest.mark.parametrize("seed", range(4))
@pytest.mark.parametrize("dip_deg", [65.0, 0.0, -40.0, 85.0])
def test_true_attitude_recovers_D(seed, dip_deg):
    rng = np.random.default_rng(seed)
    dip = np.radians(dip_deg)
    q_nb, mag, o, D_tilde, D, U = _scenario(rng, dip=dip)
    al = estimate_alignment(mag, o, D_tilde, q_nb)
    assert isinstance(al, Alignment)
    # Acceptance: D̃ R_D = D_true to 1e-6.
    assert np.max(np.abs(al.D0 - D)) < 1e-6 * np.max(np.abs(D))
    assert np.allclose(al.R_D, U, atol=1e-6)
    assert np.allclose(al.R_D @ al.R_D.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(al.R_D) == pytest.approx(1.0)
    assert al.dip_rad == pytest.approx(dip, abs=1e-6)
    assert al.m_z == pytest.approx(-np.sin(dip), abs=1e-6)
    assert np.allclose(al.m_n, field_direction(dip), atol=1e-6)
    assert al.residual_rms < 1e-6
    assert al.hessian_min_eig > alignment.MIN_HESSIAN_EIG
    if dip_deg < 0:
        assert any("negative" in w for w in al.warnings)
    else:
        assert al.warnings == ()


def test_noisy_inputs_close():
    rng = np.random.default_rng(11)
    dip = np.radians(70.0)
    q_nb, mag, o, D_tilde, D, _ = _scenario(rng, n=20000, dip=dip)
    mag = mag + 0.01 * rng.normal(size=mag.shape)
    # Inclination errors of ~1° from an inertial-only filter.
    q_est = quat_multiply(rotvec_to_quat(0.017 * rng.normal(size=(len(q_nb), 3))), q_nb)
    al = estimate_alignment(mag, o, D_tilde, q_est)
    assert np.max(np.abs(al.D0 - D)) < 0.01
    assert al.dip_rad == pytest.approx(dip, abs=np.radians(0.5))
    assert 0.01 < al.residual_rms < 0.05


def test_vertical_from_accelerometer_matches_attitude():
    rng = np.random.default_rng(2)
    q_nb, mag, o, D_tilde, D, _ = _scenario(rng, n=3000)
    R_bn = np.swapaxes(quat_to_matrix(q_nb), -1, -2)
    acc = -(R_bn @ gravity_n())
    v_b = vertical_from_accelerometer(acc)
    assert np.allclose(v_b, quat_to_matrix(q_nb)[:, 2, :], atol=1e-12)
    al = estimate_alignment_from_vertical(mag, o, D_tilde, v_b)
    assert np.max(np.abs(al.D0 - D)) < 1e-6
    with pytest.raises(CalibrationError, match="zero"):
        vertical_from_accelerometer(np.zeros((3, 3)))


def test_unnormalised_quaternions_accepted():
    rng = np.random.default_rng(3)
    q_nb, mag, o, D_tilde, D, _ = _scenario(rng, n=2000)
    al = estimate_alignment(mag, o, D_tilde, 3.0 * q_nb)
    assert np.max(np.abs(al.D0 - D)) < 1e-6


def test_reflection_resolved_by_expected_dip_sign():
    rng = np.random.default_rng(4)
    dip = np.radians(60.0)
    q_nb, mag, o, D_tilde, D, _ = _scenario(rng, dip=dip, det_sign=-1.0)
    # Restricted to SO(3), the best fit is −D with the dip of the wrong sign (the cost is
    # invariant under (R_D, m_z) → (−R_D, −m_z)) ...
    al = estimate_alignment(mag, o, D_tilde, q_nb)
    assert np.allclose(al.D0, -D, atol=1e-6)
    assert al.dip_rad == pytest.approx(-dip, abs=1e-6)
    assert any("mirrored" in w for w in al.warnings)
    # ... and a known hemisphere picks the reflection.
    al = estimate_alignment(mag, o, D_tilde, q_nb, expected_dip_sign=+1)
    assert np.allclose(al.D0, D, atol=1e-6)
    assert np.linalg.det(al.R_D) == pytest.approx(-1.0)
    assert al.dip_rad == pytest.approx(dip, abs=1e-6)
    assert any("mirrored" in w for w in al.warnings)


def test_expected_dip_sign_consistent_no_warning():
    rng = np.random.default_rng(5)
    q_nb, mag, o, D_tilde, D, _ = _scenario(rng, dip=np.radians(-30.0))
    al = estimate_alignment(mag, o, D_tilde, q_nb, expected_dip_sign=-1)
    assert np.max(np.abs(al.D0 - D)) < 1e-6
    assert al.warnings == ()


def test_yaw_only_warns():
    rng = np.random.default_rng(6)
    n = 3000
    yaw = rotvec_to_quat(np.outer(rng.uniform(-np.pi, np.pi, n), [0.0, 0.0, 1.0]))
    q_nb = quat_multiply(yaw, rotvec_to_quat([0.3, -0.2, 0.0]))
    R_bn = np.swapaxes(quat_to_matrix(q_nb), -1, -2)
    D = np.diag([1.1, 0.9, 1.0])
    mag = (R_bn @ field_direction(1.0)) @ D.T
    al = estimate_alignment(mag, np.zeros(3), D, q_nb)
    assert al.hessian_min_eig < alignment.MIN_HESSIAN_EIG
    assert any("poorly determined" in w for w in al.warnings)


def test_acceleration_weights():
    g = 9.81
    acc = np.array([[0.0, 0.0, g], [0.0, 0.0, g + 0.5], [g - 0.5, 0.0, 0.0], [0, 0, g + 5.0]])
    w = acceleration_weights(acc)
    assert w == pytest.approx([1.0, 0.5, 0.5, 1.0 / 101.0])
    assert acceleration_weights(acc, g=g + 0.5)[1] == pytest.approx(1.0)
    with pytest.raises(ValueError, match="shape"):
        acceleration_weights(np.ones(3))


def test_weights_reduce_effect_of_accelerated_samples():
    rng = np.random.default_rng(7)
    n = 10000
    dip = np.radians(65.0)
    q_nb, mag, o, D_tilde, D, _ = _scenario(rng, n=n, dip=dip)
    R_bn = np.swapaxes(quat_to_matrix(q_nb), -1, -2)
    acc = -(R_bn @ gravity_n())
    # A third of the samples are accelerated: the (acc-aided) attitude tilts ~10° and the
    # accelerometer norm is off by 3 m/s².
    bad = rng.random(n) < 0.33
    tilt = np.zeros((n, 3))
    tilt[bad, 0] = np.radians(10.0)
    q_bad = quat_multiply(rotvec_to_quat(tilt), q_nb)
    acc[bad] *= (9.81 + 3.0) / 9.81
    w = acceleration_weights(acc)
    plain = estimate_alignment(mag, o, D_tilde, q_bad)
    weighted = estimate_alignment(mag, o, D_tilde, q_bad, weights=w)
    err_plain = np.max(np.abs(plain.D0 - D))
    err_weighted = np.max(np.abs(weighted.D0 - D))
    assert err_weighted < 0.2 * err_plain
    assert abs(weighted.dip_rad - dip) < abs(plain.dip_rad - dip)


def test_bad_input_raises():
    rng = np.random.default_rng(8)
    q_nb, mag, o, D_tilde, _, _ = _scenario(rng, n=100)
    with pytest.raises(InsufficientDataError, match="at least"):
        estimate_alignment(mag[:5], o, D_tilde, q_nb[:5])
    with pytest.raises(InsufficientDataError, match="weights"):
        estimate_alignment(mag, o, D_tilde, q_nb, weights=np.zeros(100))
    with pytest.raises(ValueError, match="shape"):
        estimate_alignment(mag, o, D_tilde, q_nb[:, :3])
    with pytest.raises(ValueError, match="shape"):
        estimate_alignment(mag, o, D_tilde, q_nb, weights=np.ones(99))


def test_jacobian_matches_finite_differences():
    rng = np.random.default_rng(9)
    L = rng.normal(size=(9, 9))
    R = _random_rotation(rng)
    J = alignment._jacobian(L, R)
    h = 1e-6
    fd = np.empty((9, 3))
    for k in range(3):
        e = np.zeros(3)
        e[k] = h
        plus = L @ (rotvec_to_matrix(e) @ R).ravel()
        minus = L @ (rotvec_to_matrix(-e) @ R).ravel()
        fd[:, k] = (plus - minus) / (2 * h)
    assert np.allclose(J, fd, atol=1e-8)


def test_60k_samples_are_aligned():
    # Correctness at the size of a 10-minute session; its speed is measured by bench/.
    rng = np.random.default_rng(10)
    q_nb, mag, o, D_tilde, D, _ = _scenario(rng, n=60000)
    al = estimate_alignment(mag, o, D_tilde, q_nb)
    assert np.max(np.abs(al.D0 - D)) < 1e-6
