# SPDX-License-Identifier: Apache-2.0
"""Zhao et al.'s simulation settings and model, and the study's two new plots."""

from __future__ import annotations

import numpy as np
import pytest

from magcal.report.plots import plot_heading_error_comparison, plot_norm_series
from magcal_evaluation.study import zhao

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def test_the_printed_truth_is_consistent_with_the_printed_offsets():
    # (b − b_M)ᵀ A (b − b_M) = ‖b_HI‖² holds for the paper's numbers to their rounding: the
    # first column of Table 1 is the truth, and b_M, b_HI are read right.
    assert zhao.implied_hard_iron_norm() == pytest.approx(
        np.linalg.norm(zhao.HARD_IRON_G), rel=5e-4
    )
    # ... while the other two columns are not (they are estimates).
    d = zhao.PAPER_CKF_B_G - zhao.ZERO_BIAS_G
    assert np.sqrt(d @ zhao.PAPER_CKF_A @ d) != pytest.approx(
        np.linalg.norm(zhao.HARD_IRON_G), rel=5e-4
    )


def test_distortion_and_correction_invert_the_true_a():
    C = zhao.true_distortion()
    T = np.linalg.inv(C)
    np.testing.assert_allclose(T.T @ T, zhao.TRUE_A, atol=1e-12)
    Tz = zhao.correction_of(zhao.TRUE_A)
    np.testing.assert_allclose(Tz, Tz.T, atol=1e-15)
    np.testing.assert_allclose(Tz @ Tz, zhao.TRUE_A, atol=1e-12)
    np.testing.assert_allclose(Tz @ C, np.eye(3), atol=1e-12)


def test_attitudes_are_unit_quaternions_spread_over_all_angles():
    q = zhao.random_attitudes(np.random.default_rng(0), 5000)
    np.testing.assert_allclose(np.linalg.norm(q, axis=1), 1.0, atol=1e-12)
    angle = 2.0 * np.arccos(np.clip(q[:, 0], -1.0, 1.0))  # θ ∈ [0, 2π)
    assert angle.min() < 0.1 and angle.max() > 2.0 * np.pi - 0.1


def test_simulated_samples_follow_the_model_on_average():
    # E[(y − b)ᵀ A (y − b)] = B_m² + σ² tr A: the field term plus the noise's (the cross
    # term has zero mean). Checked to 5 standard errors.
    y = zhao.simulate_zhao(np.random.default_rng(1), 20000)
    d = y - zhao.TRUE_B_G
    q = np.einsum("ki,ij,kj->k", d, zhao.TRUE_A, d)
    expected = zhao.field_norm_g() ** 2 + zhao.NOISE_SIGMA_G**2 * np.trace(zhao.TRUE_A)
    assert abs(q.mean() - expected) < 5.0 * q.std() / np.sqrt(q.size)
    # Calibrated with the truth, the norm scatters about the field by the noise only.
    norms = zhao.calibrated_norms(y, zhao.TRUE_A, zhao.TRUE_B_G)
    assert abs(np.median(norms) - zhao.field_norm_g()) < 0.01
    raw = np.linalg.norm(y, axis=1)
    assert raw.std() > 5.0 * norms.std()


def test_same_seed_same_samples():
    a = zhao.simulate_zhao(np.random.default_rng(7), 50)
    b = zhao.simulate_zhao(np.random.default_rng(7), 50)
    c = zhao.simulate_zhao(np.random.default_rng(8), 50)
    assert np.array_equal(a, b) and not np.array_equal(a, c)


def test_norm_series_plot(tmp_path):
    rng = np.random.default_rng(2)
    path = plot_norm_series(
        {"raw": 1.0 + rng.random(100), "CKF": 0.49 + 0.01 * rng.standard_normal(100)},
        0.49,
        tmp_path / "n.png",
        unit="G",
    )
    assert path.read_bytes()[:8] == PNG_MAGIC
    with pytest.raises(ValueError, match="same number of samples"):
        plot_norm_series({"raw": np.ones(5), "CKF": np.ones(4)}, 1.0, tmp_path / "x.png", unit="G")
    with pytest.raises(ValueError, match="positive norm"):
        plot_norm_series({"raw": np.ones(5)}, 0.0, tmp_path / "x.png", unit="G")


def test_heading_error_comparison_plot(tmp_path):
    rng = np.random.default_rng(3)
    errors = {
        "table2": {"init": 50 + rng.random(20), "ml": 5 + rng.random(20), "ckf": np.array([])},
        "mems": {"init": 0.1 + rng.random(20), "ml": 0.02 + 0.01 * rng.random(20)},
    }
    path = plot_heading_error_comparison(errors, tmp_path / "c.png")
    assert path.read_bytes()[:8] == PNG_MAGIC
    with pytest.raises(ValueError, match="mems/ml has non-finite or non-positive"):
        plot_heading_error_comparison({"mems": {"ml": np.array([0.1, 0.0])}}, tmp_path / "x.png")
