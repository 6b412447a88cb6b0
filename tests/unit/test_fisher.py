# SPDX-License-Identifier: Apache-2.0
"""The Fisher information of V(θ) by forward sensitivities of the filter (mekf_fisher.c)
against the reverse-mode gradient and an independent construction from the textbook
filter's innovations and their covariances."""

import dataclasses

import numpy as np
import pytest

from magcal.calib.likelihood import mekf, params
from tests.synthetic import random_masks, synthetic_filter_problem, with_masks


def _away_from_truth(p, seed):
    """θ perturbed in every parameter, τ a few milliseconds: a point where nothing vanishes."""
    rng = np.random.default_rng(100 + seed)
    theta = params.pack(dataclasses.replace(p, time_offset_s=0.004))
    return (
        theta
        + rng.normal(size=theta.size)
        * np.r_[np.full(12, 0.02), 0.02, np.full(3, 0.005), np.full(18, 0.2), 0.002]
    )


def test_the_model_vector_of_theta_is_the_kernels_layout():
    """params.model_vector (complex-capable, for the Jacobian) and the kernel's own packing
    of the same parameters agree entry by entry."""
    p, _, _ = synthetic_filter_problem(n=20)
    theta = _away_from_truth(p, 0)
    packed = mekf._model_buffer(params.unpack(theta))
    np.testing.assert_allclose(params.model_vector(theta), packed, rtol=1e-14, atol=1e-16)


@pytest.mark.parametrize("masked", [False, True])
@pytest.mark.parametrize(("seed", "inflation"), [(0, "mixed"), (1, "none")])
def test_forward_derivatives_equal_the_reverse_gradient(seed, inflation, masked):
    p, data, _ = synthetic_filter_problem(n=300, seed=seed, inflation=inflation)
    if masked:
        data = with_masks(data, *random_masks(len(data), 10 + seed))
    theta = _away_from_truth(p, seed)
    J = params.model_jacobian(theta)
    cost, info, grad = mekf.fisher_information(params.unpack(theta), data, J.T)
    cost_r, grad_model = mekf.cost_and_model_gradient(params.unpack(theta), data)
    grad_r = np.concatenate([np.ravel(v) for v in vars(grad_model).values()]) @ J
    assert cost == cost_r
    assert np.linalg.norm(grad - grad_r) <= 1e-9 * np.linalg.norm(grad_r)
    assert np.allclose(info, info.T, rtol=0, atol=0)
    assert np.linalg.eigvalsh(info).min() >= -1e-9 * np.linalg.eigvalsh(info).max()


def test_information_equals_the_textbook_filters_sensitivities():
    """Σ_t ∂εᵀ S⁻¹ ∂ε + ½ tr(S⁻¹ ∂S S⁻¹ ∂S), with ∂ε and ∂S by central differences of the
    textbook 6×6 filter, per sample."""
    p, data, _ = synthetic_filter_problem(n=120, seed=4)
    data = with_masks(data, *random_masks(len(data), 7))
    theta = _away_from_truth(p, 4)
    J = params.model_jacobian(theta)
    _, info, _ = mekf.fisher_information(params.unpack(theta), data, J.T)

    steps = 1e-5 * np.maximum(1.0, np.abs(theta))

    def innovations(th):
        return mekf.reference_innovations(params.unpack(th), data)

    base = innovations(theta)
    d_eps, d_S = [], []
    for i in range(theta.size):
        e = np.zeros_like(theta)
        e[i] = steps[i]
        hi, lo = innovations(theta + e), innovations(theta - e)
        d_eps.append([(a[1] - b[1]) / (2 * steps[i]) for a, b in zip(hi, lo, strict=True)])
        d_S.append([(a[2] - b[2]) / (2 * steps[i]) for a, b in zip(hi, lo, strict=True)])
    expected = np.zeros_like(info)
    for t, (_, _, S) in enumerate(base):
        S_inv = np.linalg.inv(S)
        a = np.array([d_eps[i][t] for i in range(theta.size)])
        X = np.array([S_inv @ d_S[i][t] for i in range(theta.size)])
        expected += a @ S_inv @ a.T + 0.5 * np.einsum("iab,jba->ij", X, X)
    assert np.linalg.norm(info - expected) <= 1e-6 * np.linalg.norm(expected)


def test_directions_of_the_wrong_shape_are_refused():
    p, data, _ = synthetic_filter_problem(n=20)
    with pytest.raises(ValueError, match="directions: expected"):
        mekf.fisher_information(p, data, np.zeros((3, 45)))
    too_many = np.zeros((mekf.FISHER_MAX_DIRECTIONS + 1, mekf.MODEL_DOUBLES))
    with pytest.raises(ValueError, match="directions: expected"):
        mekf.fisher_information(p, data, too_many)


def test_a_broken_filter_gives_nan_and_zero_information():
    p, data, _ = synthetic_filter_problem(n=20)
    broken = dataclasses.replace(p, Sigma_mag=-np.eye(3))
    cost, info, grad = mekf.fisher_information(broken, data, np.eye(mekf.MODEL_DOUBLES)[:5])
    assert np.isnan(cost)
    assert not info.any() and not grad.any()
