# SPDX-License-Identifier: Apache-2.0
"""magcal_evaluation.cramer_rao: the augmented MEKF is the calibration MEKF when the
acceleration process is off (against the C kernel, with and without knocks), the Fisher
information from per-sample scores agrees with the kernel's Hessian, and unknown
accelerations raise the bound above the known-attitude floor's neighbourhood."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from magcal.calib.calibrate import calibrate
from magcal.calib.diagnostics import uncertainty
from magcal.calib.likelihood import params
from magcal.calib.likelihood.problem import (
    LikelihoodProblem,
    negative_log_likelihood,
    negative_log_likelihood_and_gradient,
)
from magcal.errors import MagcalError
from magcal.sim.scenarios import preset, simulate
from magcal_evaluation import accuracy
from magcal_evaluation import cramer_rao as cr

OFF = cr.AccelerationProcess(rms_m_s2=0.0, f0_hz=1.0, zeta=0.7)


def _problem(config, seed):
    """(session, truth, filter data, θ_true normalised, prior precision, normalisation)."""
    session, truth = simulate(config, seed)
    init = calibrate(session, "init", force=True).init  # short sessions: fast tests
    problem = LikelihoodProblem.for_ml_step(session, init)
    norm = problem.norm
    theta = params.pack(truth.sensor.scaled_magnetometer(norm.centre, norm.scale))
    return session, truth, problem.data, theta, problem.prior_precision, norm


@pytest.fixture(scope="module")
def short_acc():
    return _problem(preset("mems", duration_s=8.0, translational_acc_rms=0.3, n_bumps=3), 7)


def test_with_the_process_off_it_is_the_calibration_filter(short_acc):
    _, _, data, theta, _, _ = short_acc
    assert np.any(data.acc_extra_var > 0.0)  # the knocks' inflation is exercised too
    other = theta + 0.01 * np.random.default_rng(0).standard_normal(theta.size)
    costs = cr.per_sample_costs(np.stack([theta, other]), data, OFF)
    for row, th in zip(costs, (theta, other), strict=True):
        assert row.sum() == pytest.approx(negative_log_likelihood(th, data), rel=1e-12)


def test_accelerations_change_the_costs(short_acc):
    _, _, data, theta, _, _ = short_acc
    on = dataclasses.replace(OFF, rms_m_s2=0.17)
    assert cr.per_sample_costs(theta, data, on).sum() < cr.per_sample_costs(theta, data, OFF).sum()


def test_outer_product_information_agrees_with_the_hessian():
    _, truth, data, theta, precision, norm = _problem(preset("mems", duration_s=20.0), 3)
    info = cr.fisher_information(theta, data, OFF) + np.diag(precision)

    def gradient(th):
        return negative_log_likelihood_and_gradient(th, data)[1] + precision * (th - theta)

    hess = uncertainty.central_difference_hessian(gradient, theta, np.full(theta.size, 1e-5))
    s = truth.sensor
    J = cr.heading_error_jacobian(s.D, s.o, s.m_n, norm.centre, norm.scale)
    by_scores = cr.heading_bound_deg(info, J)
    by_hessian = cr.heading_bound_deg(hess, J)  # the gradient holds the prior
    assert by_scores == pytest.approx(by_hessian, rel=0.05)


def test_unknown_accelerations_raise_the_bound(short_acc):
    session, truth, data, theta, precision, norm = short_acc
    s = truth.sensor
    J = cr.heading_error_jacobian(s.D, s.o, s.m_n, norm.centre, norm.scale)
    known = cr.heading_bound_deg(cr.fisher_information(theta, data, OFF) + np.diag(precision), J)
    on = dataclasses.replace(OFF, rms_m_s2=0.3 / np.sqrt(3.0))
    unknown = cr.heading_bound_deg(cr.fisher_information(theta, data, on) + np.diag(precision), J)
    assert unknown > 1.3 * known
    floor = accuracy.floor_heading_rms_deg(session, truth)
    assert known > 0.5 * floor


def test_uneven_sampling_is_refused(short_acc):
    _, _, data, theta, _, _ = short_acc
    dt = data.dt.copy()
    dt[5] *= 1.5
    with pytest.raises(MagcalError, match="sample interval varies"):
        cr.per_sample_costs(theta, dataclasses.replace(data, dt=dt), OFF)
