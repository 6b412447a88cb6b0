# SPDX-License-Identifier: Apache-2.0
"""The MAP priors: the misalignment measure and its gradient, the priors in the problem's
cost, their effect on an estimate, and the command line's widths."""

from __future__ import annotations

import argparse

import numpy as np
import pytest

from magcal.calib import frames
from magcal.calib.calibrate import calibrate
from magcal.calib.likelihood import params
from magcal.calib.likelihood.problem import (
    NO_PRIORS,
    LikelihoodProblem,
    Priors,
    misalignment_penalty,
    misalignment_vector,
)
from magcal.commands.calibrate import angle_prior, angle_rate_prior
from magcal.sim.scenarios import preset, simulate


def _spd(rng):
    A = rng.normal(size=(3, 3))
    return np.eye(3) + 0.1 * (A + A.T)


@pytest.mark.parametrize("seed", range(4))
def test_misalignment_vector_is_the_rotation_against_the_reference_to_first_order(seed):
    rng = np.random.default_rng(seed)
    U0 = frames.axis_permutation_rotations()[seed * 5]
    phi = np.deg2rad(rng.uniform(-2.0, 2.0, 3))
    D = _spd(rng) @ frames.quat_to_matrix(frames.rotvec_to_quat(phi)) @ U0
    # Error O(φ²): 2° is 0.035 rad, so agreement to a few 1e-3 relative to |φ|.
    assert np.allclose(misalignment_vector(D, U0), phi, atol=2e-3 * np.linalg.norm(phi) + 1e-4)
    assert np.allclose(
        frames.nearest_rotation(D),
        frames.quat_to_matrix(frames.rotvec_to_quat(phi)) @ U0,
        atol=1e-9,
    )
    assert np.allclose(frames.nearest_axis_permutation(frames.nearest_rotation(D)), U0)


def test_misalignment_penalty_gradient_matches_central_differences():
    rng = np.random.default_rng(7)
    U0 = frames.axis_permutation_rotations()[3]
    D = _spd(rng) @ frames.quat_to_matrix(frames.rotvec_to_quat([0.05, -0.1, 0.08])) @ U0
    sigma = np.deg2rad(5.0)
    value, grad = misalignment_penalty(D.ravel(), U0, sigma)
    phi = misalignment_vector(D, U0)
    assert value == pytest.approx(0.5 * phi @ phi / sigma**2, rel=1e-12)
    h = 1e-6
    fd = np.array(
        [
            (
                misalignment_penalty(D.ravel() + h * e, U0, sigma)[0]
                - misalignment_penalty(D.ravel() - h * e, U0, sigma)[0]
            )
            / (2 * h)
            for e in np.eye(9)
        ]
    )
    np.testing.assert_allclose(grad, fd, rtol=1e-6, atol=1e-6 * np.abs(fd).max())


@pytest.fixture(scope="module")
def short_session():
    return simulate(preset("mems", duration_s=20.0), 3)


def test_the_priors_gradient_matches_central_differences(short_session):
    session, _ = short_session
    init = calibrate(session, "init").init
    priors = Priors(gyro_bias_rad_s=np.deg2rad(2.0), misalignment_rad=np.deg2rad(3.0))
    problem = LikelihoodProblem.for_ml_step(session, init, priors=priors)
    theta = problem.theta0 + 1e-3 * np.random.default_rng(0).standard_normal(params.N_PARAMS)
    value, grad = problem.prior(theta)
    h = 1e-7
    fd = np.array(
        [
            (problem.prior(theta + h * e)[0] - problem.prior(theta - h * e)[0]) / (2 * h)
            for e in np.eye(params.N_PARAMS)
        ]
    )
    np.testing.assert_allclose(grad, fd, rtol=1e-5, atol=1e-6)
    unpriored = LikelihoodProblem.for_ml_step(session, init, priors=NO_PRIORS)
    assert problem.prior(theta)[0] > unpriored.prior(theta)[0]


def test_a_tight_bias_prior_pulls_the_estimate_to_zero(short_session):
    session, truth = short_session
    free = calibrate(session, "ml", priors=NO_PRIORS).result
    # The MAP bias is the free one shrunk by the likelihood's curvature over it plus the
    # prior's precision: 0.001 °/s outweighs 20 s of data about 300 to 1 (0.01 °/s, 3 to 1).
    tight = calibrate(session, "ml", priors=Priors(gyro_bias_rad_s=np.deg2rad(0.001))).result
    assert np.linalg.norm(free.gyro_bias - truth.sensor.gyro_bias) < 0.2 * np.linalg.norm(
        truth.sensor.gyro_bias
    )
    assert np.linalg.norm(tight.gyro_bias) < 0.1 * np.linalg.norm(free.gyro_bias)
    assert tight.extra["priors"] == {
        "gyro_bias_deg_s": pytest.approx(0.001),
        "misalignment_deg": None,
        "time_offset_s": pytest.approx(0.1),
        "noise_coupling": pytest.approx(10.0),
    }
    assert Priors.from_dict(tight.extra["priors"]) == Priors(
        gyro_bias_rad_s=pytest.approx(np.deg2rad(0.001)), misalignment_rad=None
    )


def test_prior_widths_on_the_command_line():
    assert angle_rate_prior("2deg/s") == pytest.approx(np.deg2rad(2.0))
    assert angle_rate_prior("0.03 rad/s") == pytest.approx(0.03)
    assert angle_rate_prior("3") == pytest.approx(np.deg2rad(3.0))
    assert angle_rate_prior("None") is None
    assert angle_prior("5deg") == pytest.approx(np.deg2rad(5.0))
    assert angle_prior("0.1rad") == pytest.approx(0.1)
    for bad in ("-2deg/s", "0", "fast", "nan"):
        with pytest.raises(argparse.ArgumentTypeError, match="width"):
            angle_rate_prior(bad)


def test_the_priors_curvature_and_the_information_step_of_the_problem(short_session):
    """The priors' Hessian against central differences of their gradient, and the problem's
    (cost, gradient, information) against its cost and reverse-mode gradient."""
    session, _ = short_session
    init = calibrate(session, "init").init
    priors = Priors(gyro_bias_rad_s=np.deg2rad(2.0), misalignment_rad=np.deg2rad(3.0))
    problem = LikelihoodProblem.for_ml_step(session, init, priors=priors)
    theta = problem.theta0 + 1e-3 * np.random.default_rng(1).standard_normal(params.N_PARAMS)
    h = 1e-6
    fd = np.array(
        [
            (problem.prior(theta + h * e)[1] - problem.prior(theta - h * e)[1]) / (2 * h)
            for e in np.eye(params.N_PARAMS)
        ]
    ).T
    curvature = problem.prior_curvature(theta)
    np.testing.assert_allclose(curvature, fd, rtol=1e-5, atol=1e-6 * np.abs(fd).max())
    value, grad, info = problem.cost_gradient_and_information(theta)
    value_r, grad_r = problem.cost_and_gradient(theta)
    assert value == pytest.approx(value_r, rel=1e-12)
    np.testing.assert_allclose(grad, grad_r, rtol=1e-8, atol=1e-9 * np.abs(grad_r).max())
    assert np.linalg.eigvalsh(info - curvature).min() >= -1e-9 * np.abs(info).max()
