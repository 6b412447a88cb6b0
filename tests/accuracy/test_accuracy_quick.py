# SPDX-License-Identifier: Apache-2.0
"""Quick versions of the accuracy checks (the full report is ``make accuracy``).

Each check runs a few fixed seeds (1..n, never chosen by outcome) through the same functions
as the accuracy report (:mod:`magcal_evaluation.accuracy`) and asserts the same bound on the
median. Sessions are shorter only where the check does not fix their length (noise-free,
small noise, scale, hand-held); the MEMS checks keep their full minute.
"""

from __future__ import annotations

import numpy as np
import pytest

from magcal.calib import calibrate
from magcal.calib.initial.ellipsoid import fit_ellipsoid_algebraic
from magcal.sim.scenarios import preset, simulate
from magcal_evaluation import accuracy

#: Seeds per check in the quick version (seeds 1..n).
QUICK_SEEDS = {
    "noise-free": 3,
    "small-noise": 3,
    # The ratio checks use the report's full 20 seeds (≈0.7 s a run): a median of 5 is
    # too noisy to hold to the check's bound either way.
    "mems": 20,
    "mems-acc": 20,
    "table2": 50,  # a third of the full 150: the runs are 400 samples
    "scale": 3,
    "handheld": 3,
}


#: Checks whose bound the library does not meet (the README's "Known limit"). Strict: the
#: test fails as soon as the bound is met, so this list cannot go stale.
NOT_MET_YET = {
    "mems-acc": (
        "with smooth 0.2-2 Hz translational accelerations of 0.3 m/s² the "
        "ML misalignment sits at about 2× the known-attitude floor (20 seeds 2.01×; bound 2×), "
        "below the scenario's Cramér-Rao bound of 2.29× (make cramer-rao)"
    ),
}


def test_every_check_has_a_quick_version():
    assert set(QUICK_SEEDS) == set(accuracy.CHECKS)


@pytest.mark.parametrize(
    "key",
    [
        pytest.param(k, marks=pytest.mark.xfail(strict=True, reason=NOT_MET_YET[k]))
        if k in NOT_MET_YET
        else k
        for k in QUICK_SEEDS
    ],
)
def test_quick_check_meets_its_bound(key):
    runs = [accuracy.run_check(key, seed, quick=True) for seed in range(1, QUICK_SEEDS[key] + 1)]
    v = accuracy.verdict(key, runs)
    assert v.n_runs == QUICK_SEEDS[key]
    assert v.passed, v.describe()


# --------------------------------------------------------------------------- the measures


def test_heading_error_of_the_true_calibration_is_zero_and_of_a_tilt_is_not():
    _, truth = simulate(preset("mems", duration_s=5.0), 1)
    s = truth.sensor
    assert accuracy.heading_rms_deg(truth, s.D, s.o) < 1e-9
    # A 1° rotation about the body z axis folded into D shows up as about a degree.
    c, n = np.cos(np.deg2rad(1.0)), np.sin(np.deg2rad(1.0))
    rz = np.array([[c, -n, 0.0], [n, c, 0.0], [0.0, 0.0, 1.0]])
    assert 0.3 < accuracy.heading_rms_deg(truth, s.D @ rz, s.o) < 3.0


def test_relative_errors_do_not_depend_on_the_unit():
    rng = np.random.default_rng(0)
    D, o = np.eye(3) + 0.1 * rng.standard_normal((3, 3)), rng.standard_normal(3)
    dD, do = 1e-3 * rng.standard_normal((3, 3)), 1e-3 * rng.standard_normal(3)
    for k in (1.0, 50.0):
        assert accuracy.rel_error_matrix(k * (D + dD), k * D) == pytest.approx(
            np.linalg.norm(dD) / np.linalg.norm(D)
        )
        assert accuracy.rel_error_offset(k * (o + do), k * o, k * D) == pytest.approx(
            np.linalg.norm(do) / np.linalg.norm(D, 2)
        )


def test_algebraic_eigenvalues_agree_with_the_library_fit():
    # Whenever the library's algebraic fit returns an ellipsoid, its A is positive definite.
    for seed in range(1, 6):
        session, _ = simulate(preset("table2"), seed)
        if fit_ellipsoid_algebraic(session.mag) is not None:
            assert accuracy.algebraic_a_eigenvalues(session.mag)[0] > 0.0


def test_algebraic_eigenvalues_see_a_hyperboloid():
    # Points on x² + y² − z² = 1: the best quadric is that hyperboloid, A indefinite.
    rng = np.random.default_rng(1)
    u, h = rng.uniform(0.0, 2 * np.pi, 500), rng.uniform(-1.0, 1.0, 500)
    r = np.sqrt(1.0 + h * h)
    mag = np.column_stack([r * np.cos(u), r * np.sin(u), h])
    eig = accuracy.algebraic_a_eigenvalues(mag)
    assert eig[0] < 0.0 < eig[-1]


def test_alignment_warning_is_recognised():
    session, _ = simulate(preset("mems", duration_s=30.0, translational_acc_rms=3.0), 1)
    texts = calibrate.calibrate(session, "init").result.warnings
    assert any(accuracy.is_alignment_warning(t) for t in texts), texts
    assert not accuracy.is_alignment_warning(
        "no stationary stretch found: gyro bias and noise levels start from conservative priors"
    )


# --------------------------------------------------------------------------- the verdicts


def _ratio_run(seed, floor, ml, error=None):
    run = {"seed": seed, "error": error, "forced": False, "refused": False, "seconds": 1.0}
    if error is None:
        run.update(floor_deg=floor, init_deg=5 * ml, ml_deg=ml, sym_deg=10 * ml, ratio=ml / floor)
    return run


def test_ratio_verdict_fails_beyond_the_bound_and_on_any_error():
    good = [_ratio_run(s, 1.0, 1.1) for s in range(1, 6)]
    assert accuracy.verdict("mems", good).passed
    bad = [_ratio_run(s, 1.0, 1.1 if s < 3 else 1.4) for s in range(1, 6)]
    v = accuracy.verdict("mems", bad)
    assert not v.passed and v.n_over_bound == 3
    broken = good[:4] + [_ratio_run(5, 1.0, 0.0, error="CalibrationError: diverged")]
    v = accuracy.verdict("mems", broken)
    assert not v.passed and v.n_errors == 1 and "diverged" in v.describe()


def test_ratio_verdict_uses_both_the_median_ratio_and_the_ratio_of_medians():
    # Per-run ratios 1, 1, 2, 2, 1 (median 1.0); medians ML 5, floor 3 (ratio 1.67 > 1.3).
    floors, mls = [1.0, 2.0, 3.0, 4.0, 5.0], [1.0, 2.0, 6.0, 8.0, 5.0]
    runs = [_ratio_run(s, f, m) for s, (f, m) in enumerate(zip(floors, mls, strict=True), 1)]
    v = accuracy.verdict("mems", runs)
    assert v.ratio_median == pytest.approx(1.0)
    assert v.ratio_of_medians == pytest.approx(5.0 / 3.0)
    assert not v.passed


def test_a_refusal_of_a_good_result_fails_the_check_and_of_a_wrong_one_does_not():
    wrong = {
        "seed": 1,
        "contradicted": "D is badly conditioned",
        "ml_deg": 107.0,
        "floor_deg": 13.0,
    }
    good = {"seed": 2, "contradicted": "D is badly conditioned", "ml_deg": 0.05, "floor_deg": 0.04}
    clean = {"seed": 3, "contradicted": None, "ml_deg": 0.05, "floor_deg": 0.04}
    assert accuracy._refusals_are_right([wrong, clean]).passed
    assert not accuracy._refusals_are_right([wrong, good, clean]).passed
