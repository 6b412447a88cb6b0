# SPDX-License-Identifier: Apache-2.0
"""Samples with some measurements absent (FilterData.has_acc, has_mag): the C kernel against
the textbook filter, its exact gradient against finite differences, and the all-present
masks against no masks."""

import dataclasses

import numpy as np
import pytest
import scipy.linalg

from magcal.calib import frames
from magcal.calib.likelihood import _mekf, mekf
from tests.synthetic import random_masks, synthetic_filter_problem, with_masks


def kernel_cost_grad(p, data, use_mag, masks):
    n = len(data)
    tape, grad = mekf.new_tape(n), np.empty(mekf.MODEL_DOUBLES)
    args = (mekf._model_buffer(p), *mekf._data_args(data), use_mag)
    return _mekf.cost_grad(*args, tape, grad, *masks), grad


def kernel_outputs(p, data, use_mag, masks):
    n = len(data)
    q, innov, normed = np.empty((n, 4)), np.empty((n, 6)), np.empty((n, 6))
    args = (mekf._model_buffer(p), *mekf._data_args(data), use_mag)
    return _mekf.cost(*args, q, innov, normed, *masks), q, innov, normed


@pytest.mark.parametrize("use_mag", [True, False])
def test_all_present_masks_are_bit_identical_to_no_masks(filter_problem, use_mag):
    p, data, _ = filter_problem
    n = len(data)
    none = (None, None)
    c0, g0 = kernel_cost_grad(p, data, use_mag, none)
    out0 = kernel_outputs(p, data, use_mag, none)
    for ones in (np.ones(n, dtype=bool), np.ones(n, dtype=np.uint8)):
        c1, g1 = kernel_cost_grad(p, data, use_mag, (ones, ones))
        assert c1 == c0
        assert np.array_equal(g1, g0)
        out1 = kernel_outputs(p, data, use_mag, (ones, ones))
        assert out1[0] == out0[0] == c0
        for a, b in zip(out1[1:], out0[1:], strict=True):
            assert np.array_equal(a, b)
    # And through the wrappers, with the FilterData's default (all True) masks.
    assert data.has_acc.all() and data.has_mag.all()
    assert mekf.filter_pass(p, data, use_mag) == out0[0]


@pytest.mark.parametrize("use_mag", [True, False])
@pytest.mark.parametrize(("seed", "inflation"), [(0, "mixed"), (1, "none"), (2, "all")])
def test_kernel_matches_reference_with_random_masks(seed, inflation, use_mag):
    p, data, _ = synthetic_filter_problem(n=300, seed=seed, inflation=inflation)
    has_acc, has_mag = random_masks(len(data), seed)
    assert (~has_acc & ~has_mag).sum() > 10  # some samples are pure time updates
    data = with_masks(data, has_acc, has_mag)
    ref = mekf.run_filter_reference(p, data, use_mag)
    nat = mekf.run_filter(p, data, use_mag)
    assert nat.cost == pytest.approx(ref.cost, rel=1e-9)
    np.testing.assert_allclose(
        frames.quat_to_matrix(nat.q_filt), frames.quat_to_matrix(ref.q_filt), atol=1e-9
    )
    # Absent measurements are NaN in both (the magnetometer's 0 without use_mag).
    absent = np.c_[np.repeat(~has_acc[:, None], 3, 1), np.repeat(~has_mag[:, None], 3, 1)]
    if not use_mag:
        absent[:, 3:] = False
    for got, want in ((nat.innovations, ref.innovations), (nat.normalised, ref.normalised)):
        np.testing.assert_array_equal(np.isnan(got), absent)
        np.testing.assert_allclose(got, want, rtol=1e-9, atol=1e-9)
    if not use_mag:
        assert np.all(nat.innovations[:, 3:] == 0.0)
    # The cost and gradient kernel agrees with the forward pass.
    c, _ = kernel_cost_grad(p, data, use_mag, mekf._optional_args(data))
    assert c == pytest.approx(nat.cost, rel=1e-14)


def test_absent_values_are_not_read():
    p, data, _ = synthetic_filter_problem(n=200, seed=4)
    has_acc, has_mag = random_masks(len(data), 4)
    blank = with_masks(data, has_acc, has_mag)
    kept = with_masks(data, has_acc, has_mag, blank=False)
    assert np.isnan(blank.acc).any() and np.isnan(blank.mag).any()
    c_blank, g_blank = mekf.cost_and_model_gradient(p, blank)
    c_kept, g_kept = mekf.cost_and_model_gradient(p, kept)
    assert np.isfinite(c_blank) and c_blank == c_kept
    for name, value in vars(g_blank).items():
        assert np.array_equal(value, getattr(g_kept, name)), name


def hand_built_half_rate_magnetometer(p, data):
    """The textbook filter written out for one pattern: even samples update with the
    accelerometer and the magnetometer (6 rows), odd samples with the accelerometer alone
    (3 rows). Returns the cost and the filtered attitudes."""
    g_n = frames.gravity_n(data.g)
    q, P, cost = data.q0.copy(), data.P0.copy(), 0.0
    q_filt = np.empty((len(data), 4))
    for t in range(len(data)):
        if t > 0:
            dt = data.dt[t]
            q = frames.quat_multiply(q, frames.quat_exp(0.5 * dt * (data.gyr[t - 1] - p.gyro_bias)))
            R = frames.quat_to_matrix(q)
            P = P + dt**2 * R @ p.Sigma_gyr @ R.T
        Rt = frames.quat_to_matrix(q).T
        Sa = p.Sigma_acc + data.acc_extra_var[t] * np.eye(3)
        eps_a = data.acc[t] + Rt @ g_n
        H_a = -Rt @ frames.skew(g_n)
        if t % 2 == 0:
            eps = np.r_[eps_a, data.mag[t] - p.D @ Rt @ p.m_n - p.o]
            H = np.vstack([H_a, p.D @ Rt @ frames.skew(p.m_n)])
            noise = scipy.linalg.block_diag(Sa, p.Sigma_mag)
        else:
            eps, H, noise = eps_a, H_a, Sa
        S = H @ P @ H.T + noise
        cost += 0.5 * (eps @ np.linalg.solve(S, eps) + np.linalg.slogdet(S)[1])
        K = P @ H.T @ np.linalg.inv(S)
        P = (np.eye(3) - K @ H) @ P
        P = 0.5 * (P + P.T)
        q = frames.quat_normalize(frames.quat_multiply(frames.quat_exp(0.5 * K @ eps), q))
        q_filt[t] = q
    return cost, q_filt


def test_magnetometer_at_every_other_sample_matches_hand_built_filter():
    p, data, _ = synthetic_filter_problem(n=400, seed=5, inflation="mixed")
    has_mag = np.arange(len(data)) % 2 == 0
    masked = with_masks(data, np.ones(len(data), dtype=bool), has_mag)
    cost, q_filt = hand_built_half_rate_magnetometer(p, data)
    out = mekf.run_filter(p, masked)
    assert out.cost == pytest.approx(cost, rel=1e-9)
    np.testing.assert_allclose(
        frames.quat_to_matrix(out.q_filt), frames.quat_to_matrix(q_filt), atol=1e-9
    )
    # Dropping those samples' magnetometer changes the result (the mask is not ignored).
    assert abs(mekf.filter_pass(p, data, True) - out.cost) > 1.0


def test_absent_accelerometer_is_the_limit_of_an_infinitely_inflated_one():
    """Σa,t = Σa + c I with c → ∞ removes the accelerometer's information and innovation
    term; only its ½ log det grows, by 3/2 log c per sample (plus O(1/c))."""
    p, data, _ = synthetic_filter_problem(n=300, seed=6, inflation="mixed")
    has_acc = np.random.default_rng(6).random(len(data)) > 0.3
    big = 1e8
    extra = np.where(has_acc, data.acc_extra_var, big)
    inflated = dataclasses.replace(data, acc_extra_var=extra)
    masked = with_masks(data, has_acc, np.ones(len(data), dtype=bool))
    c_inflated, g_inflated = mekf.cost_and_model_gradient(p, inflated)
    c_masked, g_masked = mekf.cost_and_model_gradient(p, masked)
    n_dropped = int((~has_acc).sum())
    assert c_masked == pytest.approx(c_inflated - 1.5 * n_dropped * np.log(big), abs=1e-5)
    for name in ("D", "o", "m", "gyro_bias", "Sigma_gyr", "Sigma_mag"):
        np.testing.assert_allclose(
            getattr(g_masked, name), getattr(g_inflated, name), rtol=1e-5, atol=1e-5
        )


def test_samples_without_measurements_are_pure_time_updates():
    p, data, _ = synthetic_filter_problem(n=200, seed=7)
    none = np.ones(len(data), dtype=bool)
    none[50:80] = False
    masked = with_masks(data, none, none)
    out = mekf.run_filter(p, masked)
    assert np.isnan(out.innovations[50:80]).all() and np.isnan(out.normalised[50:80]).all()
    assert np.isfinite(out.innovations[:50]).all() and np.isfinite(out.innovations[80:]).all()
    # The attitude over the gap is the gyroscope's integration from the last update.
    q = out.q_filt[49]
    for t in range(50, 80):
        q = frames.quat_multiply(
            q, frames.quat_exp(0.5 * data.dt[t] * (data.gyr[t - 1] - p.gyro_bias))
        )
        np.testing.assert_allclose(out.q_filt[t], q, atol=1e-12)
    # Every sample without measurements: the cost is 0 and the gradient is zero.
    nothing = np.zeros(len(data), dtype=bool)
    all_none = with_masks(data, nothing, nothing)
    c, g = mekf.cost_and_model_gradient(p, all_none)
    assert c == 0.0
    assert all(np.all(v == 0.0) for v in vars(g).values())


def test_make_filter_data_masks():
    p, data, _ = synthetic_filter_problem(n=100)
    t = np.cumsum(np.r_[0.0, data.dt[1:]])
    full = mekf.make_filter_data(t, data.gyr, data.acc, data.mag, data.q0)
    assert full.has_acc.dtype == bool and full.has_acc.all() and full.has_mag.all()
    has_acc = np.arange(100) % 3 > 0
    acc = data.acc.copy()
    acc[~has_acc] = np.nan
    masked = mekf.make_filter_data(t, data.gyr, acc, data.mag, data.q0, has_acc=has_acc)
    # g from the samples with the accelerometer only (NaN elsewhere is not read).
    assert masked.g == pytest.approx(np.median(np.linalg.norm(data.acc[has_acc], axis=1)))
    assert np.array_equal(masked.has_acc, has_acc) and masked.has_mag.all()
    with pytest.raises(ValueError, match=r"has_mag: expected \(100,\) bool"):
        mekf.make_filter_data(t, data.gyr, data.acc, data.mag, data.q0, has_mag=np.ones(99, bool))
    with pytest.raises(ValueError, match=r"has_acc: expected \(100,\) bool"):
        mekf.make_filter_data(t, data.gyr, data.acc, data.mag, data.q0, has_acc=np.ones(100))
