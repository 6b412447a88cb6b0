# SPDX-License-Identifier: Apache-2.0
"""Tests of the ellipsoid fit (Algorithm 1, step 1b)."""

from __future__ import annotations

import types

import clarabel
import cvxpy as cp
import numpy as np
import pytest
import scipy.sparse

from magcal.calib.initial import ellipsoid
from magcal.calib.initial.ellipsoid import (
    EllipsoidFit,
    fit_ellipsoid_algebraic,
    fit_ellipsoid_sdp,
    symmetric_fit,
)
from magcal.errors import CalibrationError, InsufficientDataError


def _unit_vectors(rng: np.random.Generator, n: int) -> np.ndarray:
    u = rng.normal(size=(n, 3))
    return u / np.linalg.norm(u, axis=1, keepdims=True)


def _random_D(rng: np.random.Generator) -> np.ndarray:
    """A well-conditioned calibration matrix: scale, skew and rotation (any handedness)."""
    return np.diag(rng.uniform(0.7, 1.4, 3)) + 0.15 * rng.normal(size=(3, 3))


def _ellipsoid_data(rng, n, D, o, noise=0.0):
    return _unit_vectors(rng, n) @ D.T + o + noise * rng.normal(size=(n, 3))


def _rel(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.max(np.abs(a - b)) / np.max(np.abs(b)))


@pytest.mark.parametrize("seed", range(5))
def test_noise_free_recovers_DDt_and_offset(seed):
    rng = np.random.default_rng(seed)
    D = _random_D(rng)
    o = rng.normal(size=3) * 2.0
    y = _ellipsoid_data(rng, 3000, D, o)
    fit = fit_ellipsoid_sdp(y)
    assert isinstance(fit, EllipsoidFit)
    assert fit.method == "sdp"
    # The acceptance criterion: D̃D̃ᵀ = DDᵀ and o = o to 1e-6 relative.
    assert _rel(fit.D_tilde @ fit.D_tilde.T, D @ D.T) < 1e-6
    assert np.max(np.abs(fit.o - o)) < 1e-6 * np.linalg.norm(o)
    # D̃ is the lower-triangular Cholesky factor.
    assert np.allclose(fit.D_tilde, np.tril(fit.D_tilde))
    assert np.all(np.diag(fit.D_tilde) > 0)
    # D = D̃ U with U orthogonal.
    U = np.linalg.solve(fit.D_tilde, D)
    assert np.allclose(U @ U.T, np.eye(3), atol=1e-6)
    assert fit.radius_rms < 1e-6


def test_quadric_coefficients_describe_the_data():
    rng = np.random.default_rng(10)
    D = _random_D(rng)
    o = np.array([30.0, -12.0, 5.0])
    y = _ellipsoid_data(rng, 2000, D, o)
    fit = fit_ellipsoid_sdp(y)
    assert np.trace(fit.A) == pytest.approx(1.0)
    assert np.allclose(fit.A, fit.A.T)
    assert np.all(np.linalg.eigvalsh(fit.A) > 0)
    resid = np.einsum("ni,ij,nj->n", y, fit.A, y) + y @ fit.b + fit.c
    assert np.max(np.abs(resid)) < 1e-8 * abs(fit.c)
    # eq. 20 up to scale: A ∝ D⁻ᵀD⁻¹, b = −2Ao, and the corrected formulas of docs/algorithm.md.
    Dinv = np.linalg.inv(D)
    A_true = Dinv.T @ Dinv
    assert _rel(fit.A, A_true / np.trace(A_true)) < 1e-6
    assert _rel(fit.b, -2.0 * fit.A @ o) < 1e-6
    Ainv_b = np.linalg.solve(fit.A, fit.b)
    beta = 0.25 * fit.b @ Ainv_b - fit.c
    assert _rel(beta * np.linalg.inv(fit.A), D @ D.T) < 1e-6
    assert np.allclose(-0.5 * Ainv_b, o, rtol=1e-6)


def test_scale_and_offset_invariance():
    rng = np.random.default_rng(3)
    D = _random_D(rng)
    o = rng.normal(size=3)
    y = _ellipsoid_data(rng, 4000, D, o, noise=0.02)
    f1 = fit_ellipsoid_sdp(y)
    f2 = fit_ellipsoid_sdp(y * 50.0 + 100.0)
    assert np.allclose(f2.o, 50.0 * f1.o + 100.0, rtol=1e-6, atol=1e-6)
    assert np.allclose(f2.D_tilde, 50.0 * f1.D_tilde, rtol=1e-6, atol=1e-6)
    assert f2.radius_rms == pytest.approx(f1.radius_rms, rel=1e-6)


def test_noisy_data_are_close():
    rng = np.random.default_rng(4)
    D = _random_D(rng) * 48.0  # µT-like
    o = np.array([120.0, -40.0, 300.0])  # offsets several times the field
    y = _ellipsoid_data(rng, 20000, D, o, noise=0.5)
    fit = fit_ellipsoid_sdp(y)
    assert _rel(fit.D_tilde @ fit.D_tilde.T, D @ D.T) < 0.01
    assert np.linalg.norm(fit.o - o) < 0.01 * np.linalg.norm(D, 2)
    # With D = D̃U (U orthogonal) and y = Dû + o + e, e ~ N(0, σ²I): D̃⁻¹(y − o) = v + D̃⁻¹e
    # with v = Uû on the unit sphere, so to first order ‖D̃⁻¹(y − o)‖ − 1 = vᵀD̃⁻¹e, whose
    # mean square over uniform v is σ² tr((DDᵀ)⁻¹)/3. The neglected terms: second order,
    # (σ/|D|)² ≈ 1e-4 against an RMS of 1e-2; the RMS of 20,000 samples, ≈ 0.5 % relative
    # (1/√(2N)); the fit's own error, smaller still. Seeds 4-13 agree to 1.3 %.
    predicted = 0.5 * np.sqrt(np.trace(np.linalg.inv(D @ D.T)) / 3.0)
    assert fit.radius_rms == pytest.approx(predicted, rel=0.03)


def test_600k_samples_are_fitted():
    # Correctness at the size of a long session; its speed is measured by bench/, not here.
    rng = np.random.default_rng(5)
    D = _random_D(rng)
    o = rng.normal(size=3)
    fit = fit_ellipsoid_sdp(_ellipsoid_data(rng, 600_000, D, o, noise=0.01))
    assert _rel(fit.D_tilde @ fit.D_tilde.T, D @ D.T) < 1e-2


def test_planar_data_raise():
    rng = np.random.default_rng(6)
    u = rng.normal(size=(2000, 2))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    y = np.column_stack([u, np.zeros(len(u))]) @ _random_D(rng).T + 5.0
    with pytest.raises(InsufficientDataError, match="rotate"):
        fit_ellipsoid_sdp(y)


def test_force_on_degenerate_data_gives_a_regularised_fit_with_a_warning():
    rng = np.random.default_rng(6)
    u = rng.normal(size=(2000, 2))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    y = 40.0 * np.column_stack([u, np.zeros(len(u))]) + [5.0, -3.0, 7.0]
    fit = fit_ellipsoid_sdp(y, force=True)
    assert fit.warnings and "Forced" in fit.warnings[0] and "plane" in fit.warnings[0]
    # Among all quadrics through the circle, the sphere centred in its plane.
    assert np.allclose(fit.o, [5.0, -3.0, 7.0], atol=0.1)
    assert np.allclose(fit.D_tilde @ fit.D_tilde.T, 1600.0 * np.eye(3), rtol=0.1, atol=16.0)
    assert fit.radius_rms < 0.01
    # A patch (small wobble) gives a sane, if uncertain, ellipsoid.
    v = _unit_vectors(rng, 20000)
    v = v[v[:, 2] > np.cos(np.radians(15.0))]
    y = 40.0 * v + 0.4 * rng.normal(size=v.shape)
    with pytest.raises(InsufficientDataError):
        fit_ellipsoid_sdp(y)
    fit = fit_ellipsoid_sdp(y, force=True)
    assert fit.warnings and fit.a_eig_ratio > 0.01


def test_force_changes_nothing_on_good_data():
    rng = np.random.default_rng(12)
    y = _ellipsoid_data(rng, 3000, _random_D(rng), rng.normal(size=3), noise=0.01)
    a, b = fit_ellipsoid_sdp(y), fit_ellipsoid_sdp(y, force=True)
    assert b.warnings == () and np.array_equal(a.D_tilde, b.D_tilde)


def test_line_data_raise():
    t = np.linspace(-1.0, 1.0, 500)
    y = np.outer(t, [1.0, 2.0, 3.0]) + 0.001 * np.random.default_rng(0).normal(size=(500, 3))
    with pytest.raises(InsufficientDataError, match="rotat"):
        fit_ellipsoid_sdp(y)


def test_bad_input_raises():
    with pytest.raises(InsufficientDataError, match="at least"):
        fit_ellipsoid_sdp(np.ones((5, 3)))
    with pytest.raises(InsufficientDataError, match="identical"):
        fit_ellipsoid_sdp(np.ones((100, 3)))
    y = _ellipsoid_data(np.random.default_rng(0), 100, np.eye(3), np.zeros(3))
    y[3, 1] = np.nan
    with pytest.raises(CalibrationError, match="NaN"):
        fit_ellipsoid_sdp(y)
    with pytest.raises(ValueError, match="shape"):
        fit_ellipsoid_sdp(np.ones((100, 2)))


class _FakeSolver:
    """Stands in for clarabel.DefaultSolver: its solve() ends with ``status``."""

    status = "Solved"

    def __init__(self, *args):
        pass

    def solve(self):
        return types.SimpleNamespace(status=self.status, x=[1.0, 1.0, 1.0] + [0.0] * 7)


def test_solver_failure_raises(monkeypatch):
    def fail(*args):
        raise Exception("simulated failure")  # how clarabel refuses its input

    monkeypatch.setattr(clarabel, "DefaultSolver", fail)
    y = _hyperboloid(np.random.default_rng(0), 300)  # A ⪰ 0 binds: the solver runs
    with pytest.raises(CalibrationError, match=r"CLARABEL failed \(simulated failure\)"):
        fit_ellipsoid_sdp(y)


@pytest.mark.parametrize(
    ("status", "pattern"),
    [
        ("PrimalInfeasible", "CLARABEL ended with status 'PrimalInfeasible'.*rotate"),
        ("MaxIterations", "CLARABEL ended with status 'MaxIterations'"),
        ("NumericalError", r"CLARABEL failed \(NumericalError\).*upgrade clarabel"),
        ("InsufficientProgress", r"CLARABEL failed \(InsufficientProgress\)"),
    ],
)
def test_solver_bad_status_raises(monkeypatch, status, pattern):
    monkeypatch.setattr(clarabel, "DefaultSolver", type("S", (_FakeSolver,), {"status": status}))
    y = _hyperboloid(np.random.default_rng(0), 300)
    with pytest.raises(CalibrationError, match=pattern):
        fit_ellipsoid_sdp(y)


def test_inactive_constraint_gives_the_polished_sdp_solution_without_the_solver(monkeypatch):
    # Noisy data all round an ellipsoid: A ⪰ 0 is inactive, so the optimum is the
    # trace-constrained least squares, exactly what polishing the solver's solution gives.
    rng = np.random.default_rng(4)
    y = _ellipsoid_data(rng, 3000, _random_D(rng), rng.normal(size=3), noise=0.05)
    z, mu, s = ellipsoid._normalise(y)
    g = ellipsoid._gram(z, off_diag_weight=2.0)
    polished = ellipsoid._polish(g, ellipsoid._solve_sdp(ellipsoid._gram_factor(g)))
    expected, _ = ellipsoid._finish(polished, y, mu, s, "sdp")

    def no_solver(*args):
        raise AssertionError("the interior-point solver ran")

    monkeypatch.setattr(clarabel, "DefaultSolver", no_solver)
    fit = fit_ellipsoid_sdp(y)
    assert np.array_equal(fit.o, expected.o) and np.array_equal(fit.D_tilde, expected.D_tilde)


def test_csc_matrix_is_scipy_csc_matrix():
    # What the solver is handed is what scipy.sparse would hand it, entry for entry.
    rng = np.random.default_rng(5)
    for shape in [(10, 10), (7, 10), (1, 3), (4, 1)]:
        a = rng.normal(size=shape) * (rng.uniform(size=shape) < 0.4)
        ours, theirs = ellipsoid._CscMatrix.from_dense(a), scipy.sparse.csc_matrix(a)
        assert ours.shape == theirs.shape and ours.nnz == theirs.nnz
        for name in ("data", "indices", "indptr"):
            assert np.array_equal(getattr(ours, name), getattr(theirs, name)), name


def _cvxpy_sdp(r: np.ndarray, ridge: float = 0.0) -> np.ndarray:
    """The SDP of ``ellipsoid._solve_sdp`` as cvxpy states it from the matrices: a second,
    independent formulation (cvxpy builds its own conic form) to agree with."""
    A = cp.Variable((3, 3), symmetric=True)
    b = cp.Variable(3)
    c = cp.Variable(1)
    xi = cp.hstack([A[0, 0], A[1, 1], A[2, 2], A[0, 1], A[0, 2], A[1, 2], b, c])
    objective = 0.5 * cp.sum_squares(r @ xi)
    if ridge > 0.0:
        towards_sphere = cp.sum_squares(A - np.eye(3) / 3.0)
        objective += 0.5 * ridge * (towards_sphere + ellipsoid.FORCED_RIDGE_B * cp.sum_squares(b))
    problem = cp.Problem(cp.Minimize(objective), [cp.trace(A) == 1, A >> 0])
    problem.solve(solver=cp.CLARABEL)
    assert problem.status == cp.OPTIMAL
    Av = A.value
    return np.concatenate(
        [[Av[0, 0], Av[1, 1], Av[2, 2], Av[0, 1], Av[0, 2], Av[1, 2]], b.value, c.value]
    )


def _hyperboloid(rng, n: int) -> np.ndarray:
    """Noisy samples of a hyperboloid of one sheet: the best quadric has an indefinite A, so
    the SDP's PSD constraint is active (A is singular at the optimum)."""
    angle, h = rng.uniform(0.0, 2.0 * np.pi, n), rng.uniform(-1.0, 1.0, n)
    radius = np.sqrt(1.0 + h**2)
    u = np.column_stack([radius * np.cos(angle), radius * np.sin(angle), h])
    return u @ np.diag([30.0, 25.0, 20.0]) + [3.0, 1.0, -2.0] + 0.6 * rng.normal(size=(n, 3))


@pytest.mark.parametrize("case", ["ellipsoid", "PSD active", "ridge"])
def test_sdp_agrees_with_cvxpy(case):
    rng = np.random.default_rng(2)
    if case == "PSD active":
        y = _hyperboloid(rng, 3000)
    else:
        y = _ellipsoid_data(rng, 3000, _random_D(rng), rng.normal(size=3), noise=0.05)
    z, _, _ = ellipsoid._normalise(y)
    g = ellipsoid._gram(z, off_diag_weight=2.0)
    r = ellipsoid._gram_factor(g)
    ridge = ellipsoid.FORCED_RIDGE * float(np.trace(g)) / 10.0 if case == "ridge" else 0.0
    xi, reference = ellipsoid._solve_sdp(r, ridge), _cvxpy_sdp(r, ridge)
    A, _, _ = ellipsoid._unpack(xi)
    if case == "PSD active":
        assert np.linalg.eigvalsh(A)[0] < 1e-6
    # Both to Clarabel's tolerances (relative gap 1e-8): the solutions agree to about 1e-7
    # (seen: 1e-12 to 3e-7 on simulated, real and degenerate data), their costs closer still.
    assert _rel(xi, reference) < 1e-5
    p, q = ellipsoid._sdp_objective(r, ridge)
    cost, cost_ref = (0.5 * x @ p @ x + q @ x for x in (xi, reference))
    assert cost == pytest.approx(cost_ref, rel=1e-7, abs=1e-12)


def test_algebraic_agrees_on_good_data():
    rng = np.random.default_rng(7)
    D = _random_D(rng)
    o = rng.normal(size=3)
    y = _ellipsoid_data(rng, 3000, D, o)
    alg = fit_ellipsoid_algebraic(y)
    sdp = fit_ellipsoid_sdp(y)
    assert alg is not None and alg.method == "algebraic"
    assert np.allclose(alg.D_tilde, sdp.D_tilde, atol=1e-8)
    assert np.allclose(alg.o, sdp.o, atol=1e-8)


def test_sdp_keeps_A_positive_definite_where_algebraic_does_not():
    # A ±40° cap of the sphere with noise: the algebraic fit's A is indefinite (seeded case).
    rng = np.random.default_rng(1)
    u = _unit_vectors(rng, 6000)
    u = u[u[:, 2] > np.cos(np.radians(40.0))]
    y = u * 50.0 + [10.0, 20.0, 30.0] + 2.0 * rng.normal(size=u.shape)
    assert fit_ellipsoid_algebraic(y) is None
    fit = fit_ellipsoid_sdp(y)
    assert np.all(np.linalg.eigvalsh(fit.A) > 0)


def test_symmetric_fit():
    rng = np.random.default_rng(8)
    D = _random_D(rng)
    fit = fit_ellipsoid_sdp(_ellipsoid_data(rng, 2000, D, np.zeros(3)))
    D_sym = symmetric_fit(fit)
    assert np.allclose(D_sym, D_sym.T)
    assert np.all(np.linalg.eigvalsh(D_sym) > 0)
    assert np.allclose(D_sym @ D_sym, D @ D.T, atol=1e-6)
    # For a symmetric positive definite D the symmetric fit is D itself.
    S = D @ D.T
    lam, v = np.linalg.eigh(S)
    D_spd = (v * np.sqrt(lam)) @ v.T
    fit = fit_ellipsoid_sdp(_ellipsoid_data(rng, 2000, D_spd, np.ones(3)))
    assert np.allclose(symmetric_fit(fit), D_spd, atol=1e-6)
