# SPDX-License-Identifier: Apache-2.0
"""The simulator: sensor sampling, trajectories, measurements, truth files."""

import json
import time

import numpy as np
import pytest

from magcal.calib import frames
from magcal.errors import MagcalError
from magcal.sim import (
    PRESETS,
    TruthFormatError,
    make_trajectory,
    preset,
    read_truth,
    sample_handheld_magnet,
    sample_mems,
    sample_table2,
    simulate,
    write_truth,
)
from magcal.sim.model import compose_d, noise_factor
from magcal.sim.trajectory import orientation_spread

DEG = np.pi / 180.0
NOISE_FREE = {"gyro_sigma": 0.0, "acc_sigma": 0.0, "mag_sigma": 0.0}


def _integrate(q0, omega, dt):
    """The paper's dynamics with a perfect gyroscope, one sample at a time."""
    q = np.empty((omega.shape[0], 4))
    q[0] = q0
    for k in range(omega.shape[0] - 1):
        q[k + 1] = frames.quat_multiply(q[k], frames.quat_exp(0.5 * dt * omega[k]))
    return q


def _r_bn(q_nb):
    return np.transpose(frames.quat_to_matrix(q_nb), (0, 2, 1))


# --- determinism, shapes ---------------------------------------------------------------


@pytest.mark.parametrize("name", sorted(PRESETS))
def test_presets_are_deterministic_and_well_formed(name):
    cfg = preset(name, duration_s=min(PRESETS[name].duration_s, 5.0))
    s1, t1 = simulate(cfg, 11)
    s2, t2 = simulate(cfg, 11)
    s3, _ = simulate(cfg, 12)
    for a in ("t", "gyr", "acc", "mag"):
        np.testing.assert_array_equal(getattr(s1, a), getattr(s2, a))
    np.testing.assert_array_equal(t1.q_nb, t2.q_nb)
    assert not np.array_equal(s1.mag, s3.mag)
    n = len(s1)
    assert n == round((cfg.stationary_s + cfg.duration_s) * cfg.rate_hz)
    assert s1.gyr.shape == s1.acc.shape == s1.mag.shape == (n, 3)
    assert np.all(np.diff(s1.t) > 0)
    np.testing.assert_allclose(np.diff(s1.t), 1.0 / cfg.rate_hz)
    assert t1.q_nb.shape == (n, 4)
    np.testing.assert_allclose(np.linalg.norm(t1.q_nb, axis=1), 1.0, atol=1e-12)
    assert "seed 11" in s1.meta["source"]


def test_table2_preset_is_100_stationary_then_300_rotating_samples():
    session, truth = simulate(preset("table2"), 0)
    traj = truth.trajectory
    assert len(session) == 400 and traj.n_stationary == 100
    assert np.all(traj.omega_b[:100] == 0.0)
    assert np.all(np.linalg.norm(traj.omega_b[101:], axis=1) > 0.0)
    assert np.all(traj.acc_n == 0.0)


def test_same_seed_keeps_the_sensor_when_motion_or_noise_changes():
    _, a = simulate(preset("mems", duration_s=5.0), 3)
    _, b = simulate(preset("mems", duration_s=8.0, motion="yaw-only", gyro_sigma=0.0), 3)
    np.testing.assert_array_equal(a.sensor.D, b.sensor.D)
    np.testing.assert_array_equal(a.sensor.o, b.sensor.o)


# --- sensor parameters -------------------------------------------------------------------


def test_table2_sampling_follows_the_paper():
    rng = np.random.default_rng(0)
    diag, zeta, eta, euler, o, bias, var = [], [], [], [], [], [], []
    for _ in range(300):
        s = sample_table2(rng)
        D = s.D
        # Rows of D_skew and D_rot have unit norm, so row norms of D are D11, D22, D33.
        d = np.linalg.norm(D, axis=1)
        diag.append(d)
        M = D / d[:, None]  # D_skew D_rot: row0·row1 = sin ζ, row0·row2 = -sin η
        zeta.append(np.arcsin(M[0] @ M[1]))
        eta.append(-np.arcsin(M[0] @ M[2]))
        # Mᵀ = D_rotᵀ D_skewᵀ is a QR factorisation (D_skew lower triangular, diagonal > 0).
        Q, Rt = np.linalg.qr(M.T)
        Q = Q * np.sign(np.diag(Rt))
        D_rot = Q.T
        assert np.allclose(D_rot @ D_rot.T, np.eye(3)) and np.linalg.det(D_rot) > 0
        euler.append(
            [
                np.arctan2(D_rot[1, 0], D_rot[0, 0]),
                -np.arcsin(D_rot[2, 0]),
                np.arctan2(D_rot[2, 1], D_rot[2, 2]),
            ]
        )
        o.append(s.o)
        bias.append(s.gyro_bias)
        var.append([np.diag(s.Sigma_gyr), np.diag(s.Sigma_acc), np.diag(s.Sigma_mag)])
        for S in (s.Sigma_gyr, s.Sigma_acc, s.Sigma_mag):
            assert np.all(S == np.diag(np.diag(S)))
        assert s.dip_rad == pytest.approx(71.6 * DEG)
    diag, zeta, eta, euler = map(np.asarray, (diag, zeta, eta, euler))
    o, bias, var = map(np.asarray, (o, bias, var))

    def spans(x, lo, hi):
        width = hi - lo
        return (
            x.min() >= lo
            and x.max() <= hi
            and x.min() < lo + 0.05 * width
            and (x.max() > hi - 0.05 * width)
        )

    assert spans(diag, 0.5, 1.5)
    assert spans(zeta, -30 * DEG, 30 * DEG) and spans(eta, -30 * DEG, 30 * DEG)
    assert spans(euler, -10 * DEG, 10 * DEG)
    assert spans(o, -1.0, 1.0)
    assert spans(bias, -1.0 * DEG, 1.0 * DEG)  # U(-1, 1) read as deg/s
    assert spans(var[:, 0], 1e-3, 1e-2)
    assert spans(var[:, 1], 1e-3, 1e-1) and spans(var[:, 2], 1e-3, 1e-1)


def test_compose_d_matches_paper_eq_31_32():
    z, e, r = 0.1, -0.2, 0.3
    skew = np.array(
        [
            [1, 0, 0],
            [np.sin(z), np.cos(z), 0],
            [-np.sin(e), np.cos(e) * np.sin(r), np.cos(e) * np.cos(r)],
        ]
    )
    expected = np.diag([0.7, 1.1, 1.3]) @ skew @ frames.euler_zyx_to_matrix(0.05, -0.04, 0.03)
    np.testing.assert_allclose(compose_d([0.7, 1.1, 1.3], [z, e, r], [0.05, -0.04, 0.03]), expected)


def test_mems_and_magnet_sensors_have_the_documented_sizes():
    rng = np.random.default_rng(1)
    for _ in range(50):
        m = sample_mems(rng, scale=50.0, offset_scale=100.0)
        assert 0.8 * 50 < m.field_norm < 1.2 * 50
        assert np.all(np.abs(m.o) <= 100.0)
        sig = np.sqrt(np.diag(m.Sigma_mag))
        assert np.all((sig > 0.8 * 0.005 * 50) & (sig < 1.2 * 0.005 * 50))
        assert np.all(np.sqrt(np.diag(m.Sigma_gyr)) < 1.2 * 0.005)
        assert 0.5 * DEG <= np.linalg.norm(m.gyro_bias) <= 1.5 * DEG
        h = sample_handheld_magnet(rng, scale=2.0)
        assert 3.0 * 2.0 <= np.linalg.norm(h.o) <= 6.0 * 2.0
    with pytest.raises(MagcalError, match="scale must be a positive"):
        sample_mems(rng, scale=0.0)


def test_noise_factor_handles_zero_and_rejects_indefinite():
    np.testing.assert_array_equal(noise_factor(np.zeros((3, 3))), np.zeros((3, 3)))
    S = np.array([[4.0, 1.0, 0.0], [1.0, 3.0, 0.5], [0.0, 0.5, 2.0]])
    L = noise_factor(S)
    np.testing.assert_allclose(L @ L.T, S)
    with pytest.raises(MagcalError, match="not positive semi-definite"):
        noise_factor(np.diag([1.0, -1.0, 1.0]))


# --- trajectories ------------------------------------------------------------------------


@pytest.mark.parametrize("motion", ["tumble", "yaw-only", "small"])
def test_perfect_gyro_integrates_to_the_true_attitude(motion):
    rng = np.random.default_rng(5)
    traj = make_trajectory(rng, 100.0, 1.0, 19.0, motion=motion, max_rate_rad_s=2.0)
    q = _integrate(traj.q_nb[0], traj.omega_b, 0.01)
    assert np.max(np.abs(q - traj.q_nb)) < 1e-12
    assert np.all(np.sum(traj.q_nb[:-1] * traj.q_nb[1:], axis=1) >= 0.0)  # sign-continuous


@pytest.mark.parametrize(
    ("motion", "max_rate"), [("tumble", 1.5), ("tumble", 6.0), ("yaw-only", 1.5), ("small", 0.5)]
)
def test_angular_rate_respects_the_limit_and_starts_from_rest(motion, max_rate):
    traj = make_trajectory(
        np.random.default_rng(2), 100.0, 0.5, 30.0, motion=motion, max_rate_rad_s=max_rate
    )
    w = np.linalg.norm(traj.omega_b, axis=1)
    assert w.max() <= max_rate * (1 + 1e-9)
    assert np.all(w[:50] == 0.0) and w[50] < 1e-3 * max_rate  # smooth start
    assert w[50:].mean() > 0.2 * max_rate
    # Smooth: angular acceleration of order max_rate² / step, not impulses.
    dw = np.linalg.norm(np.diff(traj.omega_b, axis=0), axis=1) * 100.0
    assert dw.max() < 2.0 * max_rate**2 / 0.35


def test_tumble_covers_all_orientations():
    _, truth = simulate(preset("mems"), 4)
    q = truth.q_nb[truth.trajectory.n_stationary :]
    assert orientation_spread(q) > 0.2  # 1/3 for a uniform cover
    R_bn = _r_bn(q)
    up_b = R_bn[:, :, 2]  # R_bn e_z: where "up" is in the body
    octants = {tuple(s) for s in (up_b > 0).astype(int)}
    assert len(octants) == 8
    m_b = R_bn @ truth.sensor.m_n
    assert np.linalg.eigvalsh(m_b.T @ m_b / len(m_b))[0] > 0.2


def test_table2_rotation_visits_diverse_orientations():
    for seed in range(5):
        _, truth = simulate(preset("table2"), seed)
        assert orientation_spread(truth.q_nb[100:]) > 0.05


def test_yaw_only_keeps_z_vertical_and_turns():
    traj = make_trajectory(np.random.default_rng(3), 100.0, 0.0, 30.0, motion="yaw-only")
    R_nb = frames.quat_to_matrix(traj.q_nb)
    np.testing.assert_allclose(R_nb[:, :, 2], np.tile([0.0, 0.0, 1.0], (len(traj), 1)), atol=1e-12)
    np.testing.assert_allclose(traj.omega_b[:, :2], 0.0, atol=1e-12)
    yaw = frames.heading_of(R_nb[:, :, 0])
    assert np.ptp(np.unwrap(yaw)) > np.pi
    assert orientation_spread(traj.q_nb) < 1e-12


def test_small_motion_stays_within_its_amplitude():
    traj = make_trajectory(
        np.random.default_rng(4), 100.0, 1.0, 30.0, motion="small", small_amplitude_rad=10 * DEG
    )
    angle = np.linalg.norm(
        frames.quat_to_rotvec(frames.quat_multiply(frames.quat_conjugate(traj.q_nb[0]), traj.q_nb)),
        axis=1,
    )
    assert 5 * DEG < angle.max() <= 11 * DEG


@pytest.mark.parametrize("rms", [0.3, 1.0])
def test_translational_acceleration_has_the_requested_rms(rms):
    traj = make_trajectory(
        np.random.default_rng(6), 100.0, 2.0, 30.0, max_rate_rad_s=2.0, acc_rms_m_s2=rms
    )
    a = traj.acc_n
    assert np.all(a[:200] == 0.0)
    got = np.sqrt(np.mean(np.sum(a[200:] ** 2, axis=1)))
    assert abs(got - rms) < 0.1 * rms
    assert np.all(np.abs(a[200:].mean(axis=0)) < 0.05 * rms)
    assert np.max(np.linalg.norm(np.diff(a, axis=0), axis=1)) < 0.2 * rms  # smooth


def test_bumps_count_size_and_place():
    traj = make_trajectory(np.random.default_rng(7), 100.0, 1.0, 20.0, n_bumps=7)
    norm = np.linalg.norm(traj.acc_n, axis=1)
    on = norm > 0
    starts = np.flatnonzero(on & ~np.concatenate([[False], on[:-1]]))
    assert len(starts) == 7
    np.testing.assert_array_equal(starts, traj.bumps[:, 0])
    assert np.all((traj.bumps[:, 1] >= 1) & (traj.bumps[:, 1] <= 3))
    assert np.all(starts >= traj.n_stationary)
    assert np.all((norm[on] >= 5.0) & (norm[on] <= 20.0))
    assert on.sum() == traj.bumps[:, 1].sum()
    with pytest.raises(MagcalError, match="bumps do not fit"):
        make_trajectory(np.random.default_rng(7), 100.0, 0.0, 0.1, n_bumps=3)


def test_trajectory_rejects_bad_settings():
    rng = np.random.default_rng(0)
    with pytest.raises(MagcalError, match="unknown motion"):
        make_trajectory(rng, 100.0, 1.0, 1.0, motion="spin")
    with pytest.raises(MagcalError, match="max_rate_rad_s must be positive"):
        make_trajectory(rng, 100.0, 1.0, 1.0, max_rate_rad_s=0.0)
    with pytest.raises(MagcalError, match="at least 2"):
        make_trajectory(rng, 100.0, 0.0, 0.0)


# --- measurements ------------------------------------------------------------------------


def test_noise_free_measurements_follow_the_model():
    cfg = preset("handheld", duration_s=10.0, n_bumps=3, **NOISE_FREE)
    session, truth = simulate(cfg, 8)
    traj, s = truth.trajectory, truth.sensor
    R_bn = _r_bn(truth.q_nb)
    g_n = np.array([0.0, 0.0, -9.81])
    expected_acc = np.einsum("kij,kj->ki", R_bn, traj.acc_n - g_n)  # R_bn (a_n - g_n)
    np.testing.assert_allclose(session.acc, expected_acc, atol=1e-12)
    np.testing.assert_allclose(session.gyr, traj.omega_b + s.gyro_bias, atol=1e-15)
    np.testing.assert_allclose(session.mag, (R_bn @ s.m_n) @ s.D.T + s.o, atol=1e-12)


def test_accelerometer_reads_plus_g_along_up_at_rest():
    session, truth = simulate(preset("mems", duration_s=1.0, **NOISE_FREE), 0)
    up_b = _r_bn(truth.q_nb[:1])[0] @ np.array([0.0, 0.0, 1.0])
    np.testing.assert_allclose(session.acc[0], 9.81 * up_b, atol=1e-12)


@pytest.mark.parametrize("name", ["raw-counts", "table2", "handheld"])
def test_noise_free_magnetometer_lies_on_the_ellipsoid(name):
    session, truth = simulate(preset(name, duration_s=3.0, **NOISE_FREE), 9)
    s = truth.sensor
    m_b = np.linalg.solve(s.D, (session.mag - s.o).T).T
    np.testing.assert_allclose(np.linalg.norm(m_b, axis=1), 1.0, atol=1e-12)
    np.testing.assert_allclose(m_b, _r_bn(truth.q_nb) @ s.m_n, atol=1e-12)


def test_noise_has_the_sensor_covariances():
    session, truth = simulate(preset("mems", stationary_s=0.0, duration_s=300.0), 10)
    ideal, _ = simulate(preset("mems", stationary_s=0.0, duration_s=300.0, **NOISE_FREE), 10)
    s = truth.sensor
    for name, Sigma in (("gyr", s.Sigma_gyr), ("acc", s.Sigma_acc), ("mag", s.Sigma_mag)):
        e = getattr(session, name) - getattr(ideal, name)
        np.testing.assert_allclose(np.cov(e.T), Sigma, rtol=0.05, atol=0.02 * Sigma.max())


def test_noise_overrides_set_isotropic_covariances():
    _, truth = simulate(preset("raw-counts", duration_s=1.0, gyro_sigma=0.01, mag_sigma=0.5), 0)
    np.testing.assert_allclose(truth.sensor.Sigma_gyr, 1e-4 * np.eye(3))
    np.testing.assert_allclose(truth.sensor.Sigma_mag, 0.25 * np.eye(3))
    with pytest.raises(MagcalError, match="sigma must be ≥ 0"):
        simulate(preset("mems", duration_s=1.0, acc_sigma=-1.0), 0)


# --- configuration and truth files -------------------------------------------------------


def test_preset_rejects_unknown_names_and_settings():
    with pytest.raises(MagcalError, match="unknown preset 'nope'"):
        preset("nope")
    with pytest.raises(MagcalError, match="unknown scenario setting.*durration_s"):
        preset("mems", durration_s=1.0)
    with pytest.raises(MagcalError, match="unknown kind"):
        simulate(preset("mems", kind="brick", duration_s=1.0), 0)
    with pytest.raises(MagcalError, match="seed must be a non-negative integer"):
        simulate(preset("mems", duration_s=1.0), -1)
    with pytest.raises(MagcalError, match="offset_scale is not used"):
        simulate(preset("table2", offset_scale=3.0), 0)


def test_truth_round_trip(tmp_path):
    cfg = preset("handheld", duration_s=2.0)
    _, truth = simulate(cfg, 21)
    path = tmp_path / "truth.json"
    write_truth(path, truth)
    d = json.loads(path.read_text())
    assert d["format"] == "magcal-truth/1" and d["seed"] == 21
    assert len(d["q_nb"]) == len(truth.t) and len(d["q_nb"][0]) == 4
    assert d["scenario"]["kind"] == "handheld" and len(d["bumps"]) == 5
    np.testing.assert_allclose(np.array(d["D_inv"]) @ np.array(d["D"]), np.eye(3), atol=1e-12)
    back = read_truth(path)
    for a in ("D", "o", "gyro_bias", "Sigma_gyr", "Sigma_acc", "Sigma_mag"):
        np.testing.assert_array_equal(getattr(back.sensor, a), getattr(truth.sensor, a))
    assert back.sensor.dip_rad == pytest.approx(truth.sensor.dip_rad, abs=1e-15)
    np.testing.assert_array_equal(back.t, truth.t)
    np.testing.assert_array_equal(back.q_nb, truth.q_nb)
    assert back.scenario == cfg and back.seed == 21 and back.trajectory is None


def test_read_truth_rejects_bad_files(tmp_path):
    p = tmp_path / "t.json"
    p.write_text('{"format": "magcal-result/1"}')
    with pytest.raises(TruthFormatError, match="expected 'magcal-truth/1'"):
        read_truth(p)
    p.write_text("not json")
    with pytest.raises(TruthFormatError, match="not JSON"):
        read_truth(p)
    _, truth = simulate(preset("mems", duration_s=1.0), 0)
    write_truth(p, truth)
    d = json.loads(p.read_text())
    del d["o"]
    p.write_text(json.dumps(d))
    with pytest.raises(TruthFormatError, match="missing key 'o'"):
        read_truth(p)
    d["o"] = [1.0, 2.0]
    p.write_text(json.dumps(d))
    with pytest.raises(TruthFormatError, match="'o' has shape"):
        read_truth(p)


def test_600k_samples_simulate_quickly():
    t0 = time.perf_counter()
    session, _ = simulate(preset("handheld", duration_s=6000.0, n_bumps=50), 1)
    assert len(session) == 600_000
    assert time.perf_counter() - t0 < 20.0  # a per-sample Python loop would take minutes
