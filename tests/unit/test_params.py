# SPDX-License-Identifier: Apache-2.0
import numpy as np
import pytest

from magcal.calib.likelihood import params


def random_params(rng):
    A = rng.normal(size=(3, 3))
    return params.ModelParams(
        D=np.eye(3) + 0.1 * rng.normal(size=(3, 3)),
        o=rng.normal(size=3),
        dip_rad=0.9,
        gyro_bias=0.01 * rng.normal(size=3),
        Sigma_gyr=1e-5 * (A @ A.T + np.eye(3)),
        Sigma_acc=1e-3 * np.diag([1.0, 2.0, 3.0]),
        Sigma_mag=1e-4 * (np.eye(3) + 0.3),
        time_offset_s=0.03,
    )


def test_pack_unpack_round_trip():
    p = random_params(np.random.default_rng(0))
    q = params.unpack(params.pack(p))
    for name in ("D", "o", "gyro_bias", "Sigma_gyr", "Sigma_acc", "Sigma_mag"):
        np.testing.assert_allclose(getattr(q, name), getattr(p, name), rtol=1e-12, atol=1e-18)
    assert q.dip_rad == p.dip_rad
    assert len(params.PARAM_NAMES) == params.N_PARAMS == 35
    assert q.time_offset_s == p.time_offset_s


def test_unpack_rejects_wrong_length():
    with pytest.raises(ValueError, match="shape"):
        params.unpack(np.zeros(34))


def test_cholesky_chain_rule_matches_finite_differences():
    rng = np.random.default_rng(1)
    c = rng.normal(size=6) * 0.5
    W = rng.normal(size=(3, 3))

    def f(c):  # any smooth function of Σ: tr(W Σ)
        return float(np.sum(W * params.chol_params_to_cov(c)))

    g = params.chol_params_grad(c, W)
    h = 1e-6
    fd = [(f(c + h * e) - f(c - h * e)) / (2 * h) for e in np.eye(6)]
    np.testing.assert_allclose(g, fd, rtol=1e-7, atol=1e-9)


def test_magnetometer_scaling_round_trip():
    p = random_params(np.random.default_rng(2))
    centre, scale = np.array([100.0, -50.0, 20.0]), 47.0
    q = p.scaled_magnetometer(centre, scale).unscaled_magnetometer(centre, scale)
    np.testing.assert_allclose(q.D, p.D)
    np.testing.assert_allclose(q.o, p.o)
    np.testing.assert_allclose(q.Sigma_mag, p.Sigma_mag)
