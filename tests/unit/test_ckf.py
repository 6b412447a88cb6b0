# SPDX-License-Identifier: Apache-2.0
"""Zhao et al.'s CKF (magcal.calib.norm_only.ckf): recovery on noise-free and noisy simulations, the
square-root update against the paper's covariance form, positive definiteness over 100k
samples, constant memory, invariance to the data's scale, the start, and the pipeline's
--method ckf (a full D, o through Algorithm 1's alignment)."""

from __future__ import annotations

import re

import numpy as np
import pytest

from magcal.calib.calibrate import calibrate
from magcal.calib.norm_only import ckf as ckf_mod
from magcal.calib.norm_only.ckf import CkfPrior, CubatureCalibrator, run_ckf
from magcal.errors import InsufficientDataError
from magcal.sim.scenarios import preset, simulate
from magcal_evaluation.accuracy import heading_rms_deg


def true_A(sensor) -> np.ndarray:
    d_inv = np.linalg.inv(sensor.D)
    return d_inv.T @ d_inv


def rel(a, b, scale) -> float:
    return float(np.linalg.norm(np.asarray(a) - b) / np.linalg.norm(scale))


@pytest.fixture(scope="module")
def noise_free():
    return [simulate(preset("mems", mag_sigma=0.0), seed) for seed in (1, 3)]


@pytest.fixture(scope="module")
def mems():
    return {seed: simulate(preset("mems"), seed) for seed in (1, 2)}


# ------------------------------------------------------------------------------- recovery


def test_noise_free_sessions_recover_the_ellipsoid(noise_free):
    for session, truth in noise_free:
        fit = run_ckf(session.mag)
        assert fit.order == "time" and fit.start_index > 200  # after the rest at the start
        e = fit.estimate
        A = true_A(truth.sensor)
        assert rel(e.A, A, A) < 1e-6
        assert rel(e.b, truth.sensor.o, np.linalg.norm(truth.sensor.D, 2)) < 1e-6
        # T from the eigendecomposition is the symmetric root: Tᵀ T = A, T = Tᵀ.
        np.testing.assert_allclose(e.T, e.T.T, atol=1e-12)
        np.testing.assert_allclose(e.T @ e.T, e.A, rtol=1e-10)


def test_pipeline_ckf_recovers_DDt_and_offset_like_init(noise_free):
    session, truth = noise_free[0]
    cal = calibrate(session, "ckf")
    D, o = truth.sensor.D, truth.sensor.o
    assert cal.result.method == "ckf"
    assert rel(cal.result.D @ cal.result.D.T, D @ D.T, D @ D.T) < 1e-6
    assert rel(cal.result.o, o, D) < 1e-6
    # The alignment step found the rotation a symmetric T cannot see: D itself, not only DDᵀ.
    assert rel(cal.result.D, D, D) < 1e-3
    assert abs(cal.result.dip_deg - np.rad2deg(truth.sensor.dip_rad)) < 0.05
    assert cal.result.gyro_bias is not None
    record = cal.result.extra["ckf"]
    assert record["order"] == "time" and len(record["state_std"]) == 9


def test_noisy_heading_error_is_comparable_to_init(mems):
    # MEMS, 1 min tumbling (the accuracy report's scenario). Measured on seeds 1-10: median
    # CKF 0.106°, init 0.085°, TWO-STEP 0.087°, ML 0.026°; CKF/init 0.93-1.93 per seed (the
    # worst, seed 6, 0.086° against 0.045°), 1.20 and 1.23 on the two seeds here.
    for session, truth in mems.values():
        h = {m: _heading(session, truth, m) for m in ("init", "ckf")}
        assert h["ckf"] < 1.6 * h["init"], h
        assert h["ckf"] < 0.2


def _heading(session, truth, method):
    cal = calibrate(session, method)
    return heading_rms_deg(truth, cal.result.D, cal.result.o)


# ----------------------------------------------------------------- the filter's numerics


def _paper_ckf(prior: CkfPrior, ys: np.ndarray):
    """Eq. 15–18 written plainly: Cholesky points and P − K P_zz Kᵀ, in the same normalised
    coordinates (centre b, scale det(A)^(-1/6)) and the same noise model."""
    scale = np.linalg.det(prior.A) ** (-1.0 / 6.0)
    A_n = prior.A * scale**2
    x = np.array([A_n[0, 0], A_n[1, 1], A_n[2, 2], A_n[0, 1], A_n[0, 2], A_n[1, 2], 0, 0, 0.0])
    P = np.diag(
        np.array(
            [ckf_mod.PRIOR_STD_A] * 3
            + [ckf_mod.PRIOR_STD_A_OFFDIAG] * 3
            + [ckf_mod.PRIOR_STD_B] * 3
        )
        ** 2
    )
    s2 = (prior.noise_std / scale) ** 2
    n = 9
    xi = np.sqrt(n) * np.hstack([np.eye(n), -np.eye(n)])  # (9, 18)
    for y in ys:
        u = (y - prior.b) / scale
        X = (np.linalg.cholesky(P) @ xi).T + x  # (18, 9)
        Z = np.empty(2 * n)
        for i, xp in enumerate(X):
            A = np.array([[xp[0], xp[3], xp[4]], [xp[3], xp[1], xp[5]], [xp[4], xp[5], xp[2]]])
            d = u - xp[6:]
            Z[i] = d @ A @ d - s2 * np.trace(A)
        z_hat = Z.mean()
        A = np.array([[x[0], x[3], x[4]], [x[3], x[1], x[5]], [x[4], x[5], x[2]]])
        d = u - x[6:]
        r = 4 * s2 * (A @ d) @ (A @ d) + 2 * s2**2 * np.trace(A @ A)
        P_zz = np.mean(Z * Z) - z_hat**2 + r
        P_xz = (X.T @ Z) / (2 * n) - x * z_hat
        K = P_xz / P_zz
        x = x + K * (1.0 - z_hat)
        P = P - np.outer(K, K) * P_zz
    return x, P


def test_square_root_update_agrees_with_the_papers_covariance_form(mems):
    session, truth = mems[1]
    prior = CkfPrior.sphere(truth.sensor.o + 0.1, 1.1, 0.005)
    ys = session.mag[300:700]
    f = CubatureCalibrator(prior)
    for y in ys:
        est = f.update(y)
    x_ref, P_ref = _paper_ckf(prior, ys)
    np.testing.assert_allclose(est.x, x_ref, rtol=1e-8, atol=1e-11)
    np.testing.assert_allclose(est.S @ est.S.T, P_ref, rtol=1e-6, atol=1e-12)


def test_covariance_stays_positive_definite_and_consistent_over_100k_samples():
    rng = np.random.default_rng(7)
    _, truth = simulate(preset("mems", duration_s=1.0), 11)
    s = truth.sensor
    u = rng.normal(size=(100_000, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    sigma = 0.005
    ys = u @ s.D.T + s.o + sigma * rng.normal(size=u.shape)
    f = CubatureCalibrator(CkfPrior.sphere(s.o + 0.05, 1.0, sigma))
    for chunk in np.split(ys, 10):
        f.update_many(chunk)
        P = f.estimate.P
        assert np.all(np.isfinite(P)) and np.allclose(P, P.T, rtol=0, atol=1e-15 * np.abs(P).max())
        assert np.linalg.eigvalsh(P)[0] > 0.0
    e = f.estimate
    assert e.samples == 100_000
    # The estimate is where the covariance says: normalised error squared within χ²₉'s 99.9 %.
    err = np.concatenate(
        [np.array([*np.diag(e.A - true_A(s)), *(e.A - true_A(s))[[0, 0, 1], [1, 2, 2]]]), e.b - s.o]
    )
    assert err @ np.linalg.solve(e.P, err) < 27.9


def _array_footprint(obj) -> dict:
    return {
        k: (v.shape, v.dtype) if isinstance(v, np.ndarray) else type(v).__name__
        for k, v in vars(obj).items()
    }


def test_the_incremental_filter_does_not_grow(mems):
    session, _ = mems[2]
    f = CubatureCalibrator()
    f.update_many(session.mag[:4000])
    assert f.started
    before = _array_footprint(f)
    for _ in range(2):
        f.update_many(session.mag)  # 12,400 more samples
    assert _array_footprint(f) == before
    assert f.samples_seen == 4000 + 2 * len(session)


def test_estimates_are_invariant_to_the_datas_unit_and_offset(mems):
    session, _ = mems[1]
    k, shift = 50.0, np.array([100.0, -30.0, 70.0])
    a = run_ckf(session.mag)
    b = run_ckf(k * session.mag + shift)
    assert a.start_index == b.start_index
    ea, eb = a.estimate, b.estimate
    np.testing.assert_allclose(eb.A * k**2, ea.A, rtol=1e-9)
    np.testing.assert_allclose(eb.b, k * ea.b + shift, rtol=1e-10)
    lam = np.concatenate([np.full(6, k**-2), np.full(3, k)])
    np.testing.assert_allclose(eb.P, ea.P * np.outer(lam, lam), rtol=1e-7)
    assert eb.noise_std == pytest.approx(k * ea.noise_std, rel=1e-12)


# ------------------------------------------------------------------------ start and errors


def test_no_estimate_before_the_start_then_one_per_sample(mems):
    session, _ = mems[1]
    f = CubatureCalibrator()
    assert f.update(session.mag[0]) is None
    with pytest.raises(InsufficientDataError, match="keep rotating the sensor"):
        f.estimate  # noqa: B018
    f.update_many(session.mag[1:200])  # at rest: the noise cloud is no start
    assert not f.started
    est = None
    for y in session.mag[200:]:
        est = f.update(y)
        if est is not None:
            break
    assert f.started and est.samples == f.updates
    # The reservoir (an even thinning of everything seen) went through the filter at once.
    assert 0 < est.samples <= ckf_mod.RESERVOIR_SAMPLES
    assert f.update(session.mag[-1]).samples == est.samples + 1


def test_a_prior_starts_at_once_and_bad_priors_are_refused():
    f = CubatureCalibrator(CkfPrior.sphere([1.0, 2.0, 3.0], 50.0, 0.2))
    assert f.started and f.update([51.0, 2.0, 3.0]) is not None
    with pytest.raises(ValueError, match="radius"):
        CkfPrior.sphere([0, 0, 0], 0.0, 0.1)
    with pytest.raises(ValueError, match="positive definite"):
        CkfPrior(-np.eye(3), np.zeros(3), 0.1)
    with pytest.raises(ValueError, match="noise_std"):
        CubatureCalibrator(noise_std=-1.0)


def test_a_short_session_runs_shuffled_with_a_warning():
    session, truth = simulate(preset("mems", duration_s=20), 2)  # no hemisphere in time
    cal = calibrate(session, "ckf")
    assert cal.result.extra["ckf"]["order"] == "shuffled"
    assert any("pseudo-random order" in w for w in cal.result.warnings)
    assert heading_rms_deg(truth, cal.result.D, cal.result.o) < 0.5


def test_readings_at_rest_are_refused_unless_forced():
    session, _ = simulate(preset("mems", duration_s=0.0, stationary_s=5.0), 1)
    with pytest.raises(InsufficientDataError, match="do not spread beyond .* at rest or barely"):
        run_ckf(session.mag)
    assert run_ckf(session.mag, force=True).order == "shuffled"


@pytest.mark.parametrize("seed", [1, 2, 3, 4])
def test_too_noisy_readings_are_refused_for_the_noise_not_the_motion(seed):
    # Zhao et al.'s Table 2: turned through all orientations, but σ ≈ 20 % of the field, so
    # no motion can spread the readings by 5 σ.
    session, truth = simulate(preset("table2"), seed)
    with pytest.raises(InsufficientDataError, match=r"noise \(σ ≈ \d+ % of the field\)") as e:
        run_ckf(session.mag)
    assert "at rest" not in str(e.value)
    sigma_percent = float(re.search(r"σ ≈ (\d+) %", str(e.value)).group(1))
    assert 10 <= sigma_percent <= 30  # the paper's σ_m, relative to its unit field
    assert run_ckf(session.mag, force=True).order == "shuffled"


def test_planar_readings_are_refused_unless_forced():
    session, _ = simulate(preset("mems", duration_s=20, motion="yaw-only"), 1)
    with pytest.raises(InsufficientDataError, match="close to a plane"):
        run_ckf(session.mag)
    e = run_ckf(session.mag, force=True).estimate
    assert np.all(np.isfinite(e.A)) and np.all(np.isfinite(e.b))
