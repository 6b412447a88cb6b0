# SPDX-License-Identifier: Apache-2.0
"""The report's uncertainty: the Hessian of the ML cost, its inverse, and what they say.

Toy problems with a known answer pin the numerics; simulated sessions pin the statistics (the
reported σ against the spread of ML estimates over 20 sessions)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import scipy.linalg

from magcal.calib import frames
from magcal.calib.calibrate import calibrate
from magcal.calib.diagnostics import replay, uncertainty
from magcal.io.result import CalibrationResult
from magcal.sim.scenarios import preset, simulate


def linear_gaussian(seed=0, n_obs=200, n_par=5):
    """y = A θ + e, e ~ N(0, R): V(θ) = ½ (y − Aθ)ᵀ R⁻¹ (y − Aθ), Cov(θ̂) = (Aᵀ R⁻¹ A)⁻¹."""
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(n_obs, n_par)) * np.array([1.0, 10.0, 0.1, 3.0, 1e3])[:n_par]
    r = rng.uniform(0.5, 2.0, size=n_obs) ** 2
    theta_true = rng.normal(size=n_par)
    y = A @ theta_true + rng.normal(size=n_obs) * np.sqrt(r)

    def gradient(theta):
        return -A.T @ ((y - A @ theta) / r)

    theta_hat = np.linalg.solve(A.T @ (A / r[:, None]), A.T @ (y / r))
    return gradient, theta_hat, np.linalg.inv(A.T @ (A / r[:, None])), A, r


def test_hessian_inverse_equals_the_known_covariance_of_a_linear_gaussian_problem():
    gradient, theta_hat, cov_true, _, _ = linear_gaussian()
    scales = np.sqrt(np.diag(cov_true)) * 3.0  # rough scales, as problem.parameter_scales are
    calls = []
    H = uncertainty.central_difference_hessian(
        gradient, theta_hat, 1e-2 * scales, progress=lambda done, total: calls.append((done, total))
    )
    hc = uncertainty.covariance_from_hessian(H, scales)
    assert hc.identifiable
    np.testing.assert_allclose(hc.cov, cov_true, rtol=1e-8, atol=1e-12 * np.abs(cov_true).max())
    assert calls[-1] == (10, 10) and len(calls) == 10


def test_linear_gaussian_monte_carlo_spread_matches_the_inverse_hessian():
    """The same toy, many noise draws: the ML estimates scatter as H⁻¹ says."""
    _, _, cov_true, A, r = linear_gaussian(seed=1)
    rng = np.random.default_rng(2)
    normal = A.T @ (A / r[:, None])
    estimates = []
    for _ in range(2000):
        y = rng.normal(size=A.shape[0]) * np.sqrt(r)  # θ_true = 0
        estimates.append(np.linalg.solve(normal, A.T @ (y / r)))
    spread = np.std(estimates, axis=0)
    H = uncertainty.central_difference_hessian(
        lambda th: -A.T @ ((0.0 - A @ th) / r), np.zeros(A.shape[1]), np.full(A.shape[1], 1e-3)
    )
    scales = 3.0 * np.sqrt(np.diag(cov_true))
    sigma = np.sqrt(np.diag(uncertainty.covariance_from_hessian(H, scales).cov))
    np.testing.assert_allclose(spread, sigma, rtol=0.06)  # 2000 draws: ±1.6 % (1σ)
    np.testing.assert_allclose(sigma, np.sqrt(np.diag(cov_true)), rtol=1e-8)


def test_a_direction_without_curvature_is_reported_and_makes_its_quantities_unbounded():
    rng = np.random.default_rng(3)
    A = rng.normal(size=(50, 3))
    A = np.column_stack([A, A[:, 1]])  # θ1 and θ3 enter only as θ1 + θ3
    H = A.T @ A
    hc = uncertainty.covariance_from_hessian(H, np.ones(4))
    assert not hc.identifiable
    assert hc.null_directions.shape == (1, 4)
    text = uncertainty.direction_text(hc.null_directions[0], ["a", "b", "c", "d"])
    assert text in ("0.71·b − 0.71·d", "0.71·d − 0.71·b")
    B = np.array([[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 1.0], [0.0, 1.0, 0.0, 0.0]])
    value, sigma = uncertainty.propagate(lambda th: B @ th, np.zeros(4), hc)
    assert np.isfinite(sigma[:2]).all() and sigma[2] == np.inf  # θ1 + θ3 is determined
    # θ0 and θ1 + θ3 get the inverse on the determined subspace: here the exact answer.
    reduced = np.linalg.inv(np.column_stack([A[:, 0], A[:, 1], A[:, 2]]).T @ A[:, :3])
    np.testing.assert_allclose(sigma[0], np.sqrt(reduced[0, 0]), rtol=1e-9)
    np.testing.assert_allclose(sigma[1], np.sqrt(reduced[1, 1]), rtol=1e-9)


def test_the_marginal_covariance_of_a_definite_hessian_is_its_inverse_block():
    rng = np.random.default_rng(5)
    M = rng.normal(size=(5, 5))
    H = M @ M.T + 5 * np.eye(5)
    keep = np.array([True, False, True, True, False])
    hc = uncertainty.marginal_covariance(H, np.ones(5), keep)
    assert hc.identifiable
    np.testing.assert_allclose(hc.cov[np.ix_(keep, keep)], np.linalg.inv(H)[np.ix_(keep, keep)])
    assert not hc.cov[~keep].any() and not hc.cov[:, ~keep].any()
    everything = uncertainty.marginal_covariance(H, np.ones(5), np.ones(5, dtype=bool))
    np.testing.assert_allclose(everything.cov, np.linalg.inv(H))


def test_a_noise_model_direction_without_resolved_curvature_leaves_the_calibration_bounded():
    """Calibration coordinates a, b; noise-model coordinates c, d. d barely curves (below the
    identifiability threshold) and couples to b at 1e-4: the whole Hessian's null direction
    then touches b by more than rounding and calls b unbounded; marginalising the noise
    model keeps b's σ within the few per cent d's unresolved curvature can move it."""
    H = np.array(
        [
            [2.0, 0.3, 0.2, 0.0],
            [0.3, 1.0, 0.1, 1e-4],
            [0.2, 0.1, 1.0, 0.0],
            [0.0, 1e-4, 0.0, 1e-7],
        ]
    )
    calibration = np.array([True, True, False, False])
    whole = uncertainty.covariance_from_hessian(H, np.ones(4))
    _, sigma_whole = uncertainty.propagate(lambda th: th[:2], np.zeros(4), whole)
    assert sigma_whole[1] == np.inf
    hc = uncertainty.marginal_covariance(H, np.ones(4), calibration)
    assert hc.identifiable
    _, sigma = uncertainty.propagate(lambda th: th[:2], np.zeros(4), hc)
    exact = np.sqrt(np.diag(np.linalg.inv(H))[:2])
    np.testing.assert_allclose(sigma, exact, rtol=0.1)
    noise = uncertainty.marginal_covariance(H, np.ones(4), ~calibration)
    assert not noise.identifiable
    text = uncertainty.direction_text(noise.null_directions[0], ["a", "b", "c", "d"])
    assert text.startswith("1.00·d")


def test_a_block_is_judged_against_the_whole_hessians_curvature():
    """A noise model that curves 1e-6 as much as the calibration is below what the finite
    differences resolve, however well conditioned it is on its own."""
    H = np.diag([2.0, 1.0, 1e-6, 2e-6])
    calibration = np.array([True, True, False, False])
    noise = uncertainty.marginal_covariance(H, np.ones(4), ~calibration)
    assert noise.null_directions.shape == (2, 4)
    assert uncertainty.marginal_covariance(H, np.ones(4), calibration).identifiable


def test_a_direction_the_calibration_leaves_free_stays_unbounded_when_the_noise_is_marginalised():
    rng = np.random.default_rng(6)
    A = rng.normal(size=(60, 4))
    A = np.column_stack([A[:, :3], A[:, 1], A[:, 3]])  # θ1 and θ3 enter only as θ1 + θ3
    H = A.T @ A
    calibration = np.array([True, True, True, True, False])
    hc = uncertainty.marginal_covariance(H, np.ones(5), calibration)
    assert hc.null_directions.shape == (1, 5)
    text = uncertainty.direction_text(hc.null_directions[0], list("abcde"))
    assert text in ("0.71·b − 0.71·d", "0.71·d − 0.71·b")
    _, sigma = uncertainty.propagate(lambda th: th[[0, 1]], np.zeros(5), hc)
    assert np.isfinite(sigma[0]) and sigma[1] == np.inf


def test_propagate_is_the_delta_method_on_a_linear_map():
    rng = np.random.default_rng(4)
    M = rng.normal(size=(6, 6))
    H = M @ M.T + 6 * np.eye(6)
    hc = uncertainty.covariance_from_hessian(H, np.ones(6))
    B = rng.normal(size=(3, 6))
    value, sigma = uncertainty.propagate(lambda th: B @ th + 1.0, np.zeros(6), hc)
    np.testing.assert_allclose(value, 1.0)
    np.testing.assert_allclose(sigma, np.sqrt(np.diag(B @ np.linalg.inv(H) @ B.T)), rtol=1e-8)


def test_a_non_finite_gradient_is_an_error_naming_the_coordinate():
    def gradient(x):
        return np.array([np.nan if x[1] > 0.5 else 0.0, 0.0])

    with pytest.raises(Exception, match="coordinate 1"):
        uncertainty.central_difference_hessian(gradient, np.array([0.0, 0.45]), np.full(2, 0.1))


# --------------------------------------------------------------------------------------------
# On simulated sessions


@pytest.fixture(scope="module")
def mems():
    session, truth = simulate(preset("mems", duration_s=30), seed=11)
    return session, truth, calibrate(session, "ml")


def test_sigma_is_finite_and_positive_for_every_quantity_and_the_estimate_is_the_minimum(mems):
    session, _, cal = mems
    u = uncertainty.calibration_uncertainty(cal.result, session)
    assert u.identifiable and u.null_directions == []
    for name, _ in uncertainty.QUANTITIES:
        sigma = u.sigma[name]
        if name == "m_n":
            sigma = sigma[[0, 2]]  # m_n's y component is 0 for every dip
        if name == "time_offset_s" and not cal.result.extra["time_offset_test"]["kept"]:
            assert sigma == 0.0  # held at 0: not a parameter of this estimate
            continue
        assert np.isfinite(sigma).all() and (sigma > 0).all(), name
    np.testing.assert_allclose(u.values["D"], cal.result.D, rtol=1e-12)
    np.testing.assert_allclose(u.values["D_inv"], cal.result.D_inv, rtol=1e-12)
    np.testing.assert_allclose(u.values["o"], cal.result.o, rtol=1e-12, atol=1e-12)
    assert u.values["dip_deg"] == pytest.approx(cal.result.dip_deg, abs=1e-12)
    assert u.newton_step_sigma < 0.1  # ML converged: the point is the cost's minimum
    assert u.at_minimum and not u.negative_curvature
    assert u.notes == []


def test_an_init_result_is_far_from_the_ml_minimum_and_says_whose_curvature_it_is(mems):
    session, _, _ = mems
    init = calibrate(session, "init")
    u = uncertainty.calibration_uncertainty(init.result, session)
    assert u.newton_step_sigma > 1.0
    assert any("not ml" in note for note in u.notes)


# The forced ML search tries points where the filter breaks down; it rejects them without a
# floating-point warning (a warning there would reach the terminal).
@pytest.mark.filterwarnings("error::RuntimeWarning")
def test_yaw_only_motion_is_not_identifiable_along_the_vertical_axis_column():
    session, _ = simulate(preset("mems", duration_s=20, motion="yaw-only"), seed=2)
    cal = calibrate(session, "ml", force=True)
    u = uncertainty.calibration_uncertainty(cal.result, session)
    assert not u.identifiable
    # Rotating about the vertical never turns the magnetometer's vertical sensitivity (D's
    # column for body z, which points up) against the field: it trades with o and the dip.
    assert any("D22" in d or "D02" in d or "D12" in d for d in u.null_directions)
    assert np.isinf(u.sigma["o"][2])


def misalignment_deg(D):
    U, _ = scipy.linalg.polar(D, side="left")
    return np.rad2deg(frames.quat_to_rotvec(frames.matrix_to_quat(U.T)))


def test_reported_sigma_matches_the_monte_carlo_spread_of_ml_estimates():
    """20 simulated sessions (30 s MEMS tumbling): the errors of the ML estimates divided by
    the reported σ must have an RMS near 1 (within a factor of 2) for every quantity group.
    Each session has its own sensor, so errors, not raw estimates, are compared."""
    groups = {"D": [], "o": [], "dip_deg": [], "misalignment_deg": [], "gyro_bias": []}
    for seed in range(20):
        session, truth = simulate(preset("mems", duration_s=30), seed=seed)
        cal = calibrate(session, "ml")
        u = uncertainty.calibration_uncertainty(cal.result, session)
        st = truth.sensor
        true = {
            "D": st.D,
            "o": st.o,
            "dip_deg": np.rad2deg(st.dip_rad),
            "misalignment_deg": misalignment_deg(st.D),
            "gyro_bias": st.gyro_bias,
        }
        for name, z in groups.items():
            z.append(np.ravel((u.values[name] - true[name]) / u.sigma[name]))
    for name, z in groups.items():
        rms = float(np.sqrt(np.mean(np.concatenate(z) ** 2)))
        assert 0.5 < rms < 2.0, f"{name}: RMS of (estimate − truth)/σ = {rms:.2f}"


# --------------------------------------------------------------------------------------------
# What the filter needs from a result


def test_a_result_without_noise_covariances_or_gyro_bias_has_no_model(mems):
    _, _, cal = mems
    r = cal.result
    extra = {k: v for k, v in r.extra.items() if k != "Sigma_mag"}
    no_cov = dataclasses.replace(r, method="ckf", extra=extra)
    with pytest.raises(replay.ModelUnavailableError, match="Sigma_mag"):
        replay.model_params_from_result(no_cov)
    no_bias = CalibrationResult(
        method="two-step", D=r.D, o=r.o, m_n=r.m_n, dip_deg=r.dip_deg, extra=r.extra
    )
    with pytest.raises(replay.ModelUnavailableError, match="gyroscope bias"):
        replay.model_params_from_result(no_bias)
    bad = dataclasses.replace(r, extra={**r.extra, "Sigma_acc": [[1, 0, 0], [0, -1, 0], [0, 0, 1]]})
    with pytest.raises(replay.ModelUnavailableError, match="not positive definite"):
        replay.model_params_from_result(bad)


def test_inclination_gives_the_dip_at_every_orientation_and_skips_accelerated_samples():
    dip = np.deg2rad(64.0)
    q = frames.so3_grid(500)
    R_nb = frames.quat_to_matrix(q)
    field_b = np.einsum("kji,j->ki", R_nb, frames.field_direction(dip))
    acc = np.einsum("kji,j->ki", R_nb, [0.0, 0.0, 9.81])  # specific force at rest: up · g
    acc[:50] *= 1.2  # 2 m/s² off gravity: not a measurement of "up"
    dips, used = replay.inclination_dip_deg(acc, 3.0 * field_b)
    assert used.sum() == 450 and not used[:50].any()
    np.testing.assert_allclose(dips, 64.0, atol=1e-9)


def test_misalignment_is_the_rotation_of_the_polar_decomposition():
    angles = np.array([3.0, -2.0, 5.0])
    U = frames.quat_to_matrix(frames.rotvec_to_quat(np.deg2rad(angles))).T  # body → mag axes
    P = np.array([[1.2, 0.1, -0.05], [0.1, 0.9, 0.02], [-0.05, 0.02, 1.05]])  # soft iron, SPD
    np.testing.assert_allclose(uncertainty.misalignment_deg(40.0 * P @ U), angles, atol=1e-9)
    mirrored = P @ U @ np.diag([1.0, 1.0, -1.0])
    assert np.isnan(uncertainty.misalignment_deg(mirrored)).all()
