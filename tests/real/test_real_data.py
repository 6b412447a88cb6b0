# SPDX-License-Identifier: Apache-2.0
"""The real-data report on real recordings: end to end on the committed excerpt
(``evaluation/data/real``, always present), and the plain fit and floor against the figures
the full set's README gives (``../shared/realdata`` beside the checkout, when present).
The full report is ``make real``."""

from __future__ import annotations

import math
import re

import pytest

from magcal.calib.calibrate import METHODS
from magcal.errors import MagcalError
from magcal_evaluation import REPO_ROOT, real, real_report

EXCERPT = REPO_ROOT / "evaluation" / "data" / "real"

#: A sane bound on any reference's heading error on these recordings, degrees (an
#: uncalibrated magnetometer with this hard iron is off by tens of degrees).
SANE_HEADING_DEG = 15.0


@pytest.fixture(scope="module")
def excerpt_results() -> dict[str, dict]:
    return {
        name: real.evaluate_case(real.load_case(EXCERPT, name)) for name in real.case_names(EXCERPT)
    }


def test_excerpt_is_small_and_documented():
    size = sum(p.stat().st_size for p in EXCERPT.rglob("*") if p.is_file())
    assert size < 2_000_000
    text = (EXCERPT / "README.md").read_text(encoding="utf-8")
    assert "CC BY 4.0" in text and "Laidig" in text and "real_excerpt" in text


def test_excerpt_is_scored_on_its_own_recording():
    for name in real.case_names(EXCERPT):
        case = real.load_case(EXCERPT, name)
        assert real.scored_on_own_recording(case)
        assert case.trials[0].valid.sum() > 0.9 * len(case.session)


def test_references_are_ordered_and_sane(excerpt_results):
    for name, r in excerpt_results.items():
        assert r["plain"] is not None, name
        assert 0.0 < r["floor"] <= r["plain"] <= SANE_HEADING_DEG, name
        assert r["plain_sdp"] is not None and r["plain_sdp"] <= SANE_HEADING_DEG, name
        # A magnetometer calibrated by its maker, in a room: a dip between 60° and 75°.
        assert 60.0 < r["floor_dip_deg"] < 75.0, name


def test_every_method_runs_end_to_end(excerpt_results):
    for name, r in excerpt_results.items():
        assert set(r["methods"]) == set(METHODS)
        for method, m in r["methods"].items():
            if m["refused"] is not None:
                assert "forced" in m, (name, method)
                continue
            assert math.isfinite(m["heading_deg"]), (name, method)
            assert len(m["gyro_bias_deg_s"]) == 3
            assert m["misalignment_deg"] == pytest.approx(
                math.sqrt(sum(x * x for x in m["misalignment_vec_deg"]))
            )
            assert m["seconds"] > 0.0


def test_report_writes_markdown_and_exits_1_on_a_failed_criterion(tmp_path, excerpt_results):
    out = tmp_path / "real.md"
    code = real_report.main(
        [
            "--data",
            str(EXCERPT),
            "--out",
            str(out),
            "--raw",
            str(tmp_path / "real.json"),
            "--workers",
            "1",
        ]
    )
    text = out.read_text(encoding="utf-8")
    assert "| case | plain | floor | ml | init | ckf | two-step |" in text
    own = [r for r in excerpt_results.values() if r.get("reference_delay")]
    assert own, "the excerpt has cases scored on their own recording"
    for r in own:
        assert f"| {r['case']} | {1e3 * r['reference_delay']['delay_s']:.1f} |" in text
    for name in excerpt_results:
        assert f"| {name} |" in text
    assert "## Stability under tiny shifts of the magnetometer" in text
    assert "| case | k = 0 | k = 1 | k = 2 | k = 3 | k = 4 | k = 5 | spread ° | verdict |" in text
    for name in excerpt_results:
        assert re.search(rf"^\| {name} \|( [0-9.]+ \|| refused \|){{6}} ", text, re.M), name
    verdicts = real.criteria(list(excerpt_results.values()))
    assert code == (1 if any(c.passed is False for c in verdicts) else 0)
    assert (tmp_path / "real.json").is_file()


def test_ml_is_stable_under_tiny_shifts_of_the_magnetometer(excerpt_results):
    for name, r in excerpt_results.items():
        s = r["stability"]
        assert [run["k"] for run in s["runs"]] == list(range(real.STABILITY_MAX_K + 1))
        ml = r["methods"]["ml"]
        assert s["runs"][0]["heading_deg"] == (None if ml["refused"] else ml["heading_deg"])
        assert s["stable"], (name, s)
    assert _criterion(excerpt_results, "stable under").passed


def test_refusals_compare_by_kind_not_by_figures():
    def kind(message: str, error: type[Exception] = MagcalError) -> str:
        return real.refusal_kind(error(message))

    assert kind("refused because X (figure 7.1)") == kind("refused because X (figure 7.2)")
    assert kind("up to +37 % (limit ±8 %)") == kind("up to -1.5e-3 % (limit ±8 %)")
    assert kind("refused because X (figure 7.1)") != kind("refused because Y (figure 7.1)")
    assert kind("figure 7.1") != kind("figure 7.1", real.RealDataError)


@pytest.mark.parametrize(
    "runs, spread, stable",
    [
        ([5.0, 5.01, 5.05], 0.05, True),
        ([5.0, 5.06, 5.0], 0.06, False),
        (["A", "A", "A"], None, True),
        (["A", "B", "A"], None, False),
        ([5.0, "A", 5.0], None, False),
    ],
)
def test_stability_verdict(runs, spread, stable):
    runs = [
        {"refused": x, "heading_deg": None}
        if isinstance(x, str)
        else {"refused": None, "heading_deg": x}
        for x in runs
    ]
    got_spread, got_stable = real.stability_verdict(runs)
    assert got_stable is stable
    assert got_spread == (None if spread is None else pytest.approx(spread))


def test_report_refuses_a_missing_folder(tmp_path, capsys):
    code = real_report.main(["--data", str(tmp_path / "nothing"), "--out", str(tmp_path / "x.md")])
    assert code == 2
    assert str(tmp_path / "nothing") in capsys.readouterr().err
    assert not (tmp_path / "x.md").exists()


# The acceptance criteria on the excerpt. Where the product does not meet one there yet, the
# test is a strict xfail naming the figure measured (python -m magcal_evaluation.real_report
# --data evaluation/data/real): it fails as soon as the criterion is met, so it cannot go stale.

ML_VS_PLAIN_NOT_MET = {
    "broad21_fast_combined": "ML 4.81° against the plain fit's 4.60° (1.05×; bound 1.03×)",
}


@pytest.mark.parametrize(
    "name",
    [
        pytest.param(n, marks=pytest.mark.xfail(strict=True, reason=ML_VS_PLAIN_NOT_MET[n]))
        if n in ML_VS_PLAIN_NOT_MET
        else n
        for n in ("broad36_magnet5cm", "broad21_fast_combined")
    ],
)
def test_ml_no_worse_than_the_plain_fit(excerpt_results, name):
    r = excerpt_results[name]
    assert r["methods"]["ml"]["refused"] is None
    assert r["methods"]["ml"]["heading_deg"] <= real.ML_PER_CASE_MAX_RATIO_TO_PLAIN * r["plain"]


def _criterion(results: dict, pattern: str) -> real.Criterion:
    (c,) = [c for c in real.criteria(list(results.values())) if re.search(pattern, c.text)]
    return c


def test_ml_median_better_than_the_plain_fit(excerpt_results):
    assert _criterion(excerpt_results, "median over cases of ML/plain").passed


@pytest.mark.xfail(
    strict=True, reason="median ML/floor 1.38 on the excerpt (1.16 and 1.60; bound 1.25)"
)
def test_ml_median_near_the_floor(excerpt_results):
    assert _criterion(excerpt_results, "median ML/floor").passed


@pytest.mark.xfail(
    strict=True,
    reason="two-step 11.0× the plain fit on broad21_fast_combined's excerpt (bound 2×)",
)
def test_no_method_far_worse_than_the_plain_fit_without_refusing(excerpt_results):
    assert _criterion(excerpt_results, "no method worse").passed


def test_changing_field_criterion_needs_its_cases(excerpt_results):
    assert _criterion(excerpt_results, "changes with position").passed is None


# ------------------------------------------------------------------ the full set's README

#: The README's figures (median heading RMS, degrees; None: "fit fails", or no floor).
README_PLAIN_FLOOR = {
    "broad35_magnet4cm": (6.71, 4.96),
    "broad36_magnet5cm": (7.75, 5.59),
    "broad21_fast_combined": (9.63, 6.98),
    "broad08_fast_rotation_breaks": (9.64, 8.77),
    "tyrex_iphone4s_d2": (7.11, None),
    "tyrex_iphone4s_d3": (10.86, None),
    "tyrex_iphone5_d3": (6.45, None),
    "tyrex_iphone5_d4": (6.83, None),
    "fiumarg_rec11_undist": (5.14, 1.85),
    "fiumarg_rec11_full": (None, 3.84),
}
#: The floor is one well-posed least-squares problem solved to convergence: it reproduces
#: the README's two decimals, up to their rounding.
FLOOR_TOLERANCE_DEG = 0.006
#: The README does not say how its algebraic ellipsoid fit is normalised; algebraic fits that
#: differ only in that agree to a few per cent on these recordings (magcal's SDP fit differs
#: from its algebraic one by up to 7 %).
PLAIN_RELATIVE_TOLERANCE = 0.05
NOT_REPRODUCED = {
    ("fiumarg_rec11_undist", "plain"): "the plain fit gives 4.23°, the README 5.14°",
    ("fiumarg_rec11_full", "floor"): (
        "the floor fitted on every sample with a reference gives 9.88°, the README 3.84°"
    ),
}

needs_full_set = pytest.mark.skipif(
    not (real.DEFAULT_DATA_DIR / "cases.json").is_file(),
    reason=f"the full real-data set is not at {real.DEFAULT_DATA_DIR} (make real uses it)",
)


def _params(kind: str):
    for name, figures in README_PLAIN_FLOOR.items():
        marks = [needs_full_set]
        if (name, kind) in NOT_REPRODUCED:
            marks.append(pytest.mark.xfail(strict=True, reason=NOT_REPRODUCED[name, kind]))
        yield pytest.param(name, figures[0 if kind == "plain" else 1], marks=marks, id=name)


@pytest.mark.parametrize("name, expected", list(_params("plain")))
def test_plain_fit_reproduces_the_readme(name, expected):
    case = real.load_case(real.DEFAULT_DATA_DIR, name)
    fit = real.plain_fit(case.session.mag)
    if expected is None:
        assert fit is None
    else:
        assert real.case_heading_deg(*fit, case) == pytest.approx(
            expected, rel=PLAIN_RELATIVE_TOLERANCE
        )


@pytest.mark.parametrize("name, expected", list(_params("floor")))
def test_floor_reproduces_the_readme(name, expected):
    case = real.load_case(real.DEFAULT_DATA_DIR, name)
    fit = real.case_floor(case)
    if expected is None:
        assert fit is None
    else:
        got = real.case_heading_deg(fit.D, fit.o, case, fit.heading_deg)
        assert got == pytest.approx(expected, abs=FLOOR_TOLERANCE_DEG)
