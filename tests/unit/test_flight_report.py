# SPDX-License-Identifier: Apache-2.0
"""The flight-log report's pure functions (magcal_evaluation.flight, flight_report): refusal
sentences, the magfit cache key, ArduPilot's correction and the scores built on it, the
consistency figures, the acceptance criteria and the tables. No log is run here."""

from __future__ import annotations

import numpy as np
import pytest

from magcal_evaluation import flight
from magcal_evaluation import flight_report as fr

SHA = "ab" * 32
FIELD_NED = np.array([231.6, 52.5, -527.8])  # mG, the flight logs' site


# ----------------------------------------------------------------------------- refusals
def test_first_sentence_strips_the_command_and_stops_at_the_first_full_stop():
    err = (
        "calibrate: checking what the session can determine\n"
        "magcal calibrate: This session cannot determine it: tilt 17°, eigenvalue 0.023 < 0.03: "
        "turned about the vertical. This is a flight: more text. Turn it by hand.\n"
    )
    assert flight.first_sentence(err) == (
        "This session cannot determine it: tilt 17°, eigenvalue 0.023 < 0.03: turned about "
        "the vertical."
    )


def test_first_sentence_without_a_full_stop_is_the_whole_message():
    err = "reading x: 100 %\nmagcal import: x.bin: no flight to import; pass --start and --end"
    assert flight.first_sentence(err) == "x.bin: no flight to import; pass --start and --end"


# ----------------------------------------------------------------------------- cache key
def test_cache_key_names_the_log_compass_and_options_and_changes_with_each():
    key = flight.magfit_cache_key(SHA, ("--elliptical", "--cmot"), 0, "2.4.50")
    assert key.startswith(SHA[:16] + "-mag0-elliptical-cmot-")
    assert flight.magfit_cache_key(SHA, ("--elliptical", "--cmot"), 0, "2.4.50") == key
    others = {
        flight.magfit_cache_key("cd" * 32, ("--elliptical", "--cmot"), 0, "2.4.50"),
        flight.magfit_cache_key(SHA, ("--elliptical",), 0, "2.4.50"),
        flight.magfit_cache_key(SHA, ("--elliptical", "--cmot"), 1, "2.4.50"),
        flight.magfit_cache_key(SHA, ("--elliptical", "--cmot"), 0, "2.4.51"),
    }
    assert key not in others and len(others) == 4
    assert "plain" in flight.magfit_cache_key(SHA, (), 0, "2.4.50")


def test_cache_key_refuses_what_is_not_a_sha256():
    with pytest.raises(ValueError, match="not a SHA-256"):
        flight.magfit_cache_key("f1_plain.bin", (), 0, "2.4.50")


def test_cache_key_is_not_fooled_by_options_that_slug_alike():
    a = flight.magfit_cache_key(SHA, ("--cmot",), 0, "v")
    b = flight.magfit_cache_key(SHA, ("cmot",), 0, "v")
    assert a != b


# ----------------------------------------------------------------------------- parameters
def test_read_param_file_reads_every_ardupilot_and_qgc_form(tmp_path):
    p = tmp_path / "p.parm"
    p.write_text(
        "# comment\nCOMPASS_OFS_X,7.5\nCOMPASS_DIA_X 1.02\n1 1 COMPASS_MOT_X 0.95 9\n"
        "COMPASS_ORIENT,101 # custom\nnot a line\n"
    )
    assert flight.read_param_file(p) == {
        "COMPASS_OFS_X": 7.5,
        "COMPASS_DIA_X": 1.02,
        "COMPASS_MOT_X": 0.95,
        "COMPASS_ORIENT": 101.0,
    }


def _params(n: int, ofs, dia=(1, 1, 1), odi=(0, 0, 0), mot=(0, 0, 0), motct=2, **more):
    k = "" if n == 1 else str(n)
    P = {"COMPASS_MOTCT": motct, **more}
    for ax, o, d, od, m in zip("XYZ", ofs, dia, odi, mot, strict=True):
        P[f"COMPASS_OFS{k}_{ax}"] = o
        P[f"COMPASS_DIA{k}_{ax}"] = d
        P[f"COMPASS_ODI{k}_{ax}"] = od
        P[f"COMPASS_MOT{k}_{ax}"] = m
    return P


def test_ap_correction_reads_compass_n_and_ardupilot_defaults():
    P = _params(2, (5, 13, -18), dia=(1.1, 0.9, 1.0), odi=(0.01, 0.02, 0.03), mot=(1, 2, 3))
    c = flight.ap_correction(P, 2)
    np.testing.assert_allclose(c.ofs, [5, 13, -18])
    np.testing.assert_allclose(c.M, [[1.1, 0.01, 0.02], [0.01, 0.9, 0.03], [0.02, 0.03, 1.0]])
    np.testing.assert_allclose(c.mot, [1, 2, 3])
    np.testing.assert_allclose(c.R, np.eye(3))
    # compass 1 has none of these: zero DIA means identity, as ArduPilot; no offsets
    c1 = flight.ap_correction(P, 1)
    np.testing.assert_allclose(c1.M, np.eye(3))
    np.testing.assert_allclose(c1.ofs, 0.0)


def test_ap_correction_scale_outside_its_range_is_ignored_and_motct_0_drops_the_motor():
    P = _params(1, (0, 0, 0), mot=(1, 1, 1), motct=0, COMPASS_SCALE=1.5)
    c = flight.ap_correction(P, 1)
    assert c.s == 1.0
    np.testing.assert_allclose(c.mot, 0.0)


def test_custom_rotation_is_read_from_cust_rot1():
    P = {"COMPASS_ORIENT": 101, "CUST_ROT1_ROLL": 0, "CUST_ROT1_PITCH": 0, "CUST_ROT1_YAW": 90}
    np.testing.assert_allclose(
        flight.orientation(P, 1), [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-12
    )


def test_apply_correction_undoes_a_known_offset_and_motor_field():
    truth = np.array([[200.0, 50.0, -500.0], [-100.0, 300.0, 400.0]])
    current = np.array([10.0, 30.0])
    mot = np.array([-0.9, 1.7, -0.5])  # the motors' field, mG/A
    y = truth + current[:, None] * mot - np.array([5.0, 13.0, -18.0])
    P = _params(1, (5, 13, -18), mot=tuple(-mot), motct=2)
    c = flight.apply_correction(flight.ap_correction(P, 1), y, np.eye(3), current)
    np.testing.assert_allclose(c, truth, atol=1e-9)


# ----------------------------------------------------------------------------- scores
def test_so3_against_itself_is_zero_and_an_offset_error_is_not():
    att = flight.random_attitudes(300)
    ref = flight.ap_correction(_params(2, (5, 13, -18)), 2)
    same = flight.so3_against(ref, ref, FIELD_NED, att)
    assert same["so3_rms"] < 1e-9 and same["so3_max"] < 1e-9
    off = flight.ap_correction(_params(2, (5, 13 + 10, -18)), 2)  # 10 mG off in y
    s = flight.so3_against(off, ref, FIELD_NED, att)
    # 10 mG across a ~240 mG horizontal field: at most ~2.4°, of the order of 1° RMS
    assert 0.5 < s["so3_rms"] < 2.4 and s["so3_max"] <= 2.5


def test_so3_against_sees_a_rotation_error():
    att = flight.random_attitudes(300)
    ref = flight.ap_correction({}, 1)
    turned = flight.ap_correction(
        {"COMPASS_ORIENT": 101, "CUST_ROT1_ROLL": 0, "CUST_ROT1_PITCH": 0, "CUST_ROT1_YAW": 2},
        1,
    )
    assert flight.so3_against(turned, ref, FIELD_NED, att)["so3_rms"] > 1.0


def test_motor_error_counts_no_compensation_as_zero():
    ref = flight.ap_correction(_params(2, (0, 0, 0), mot=(0.95, -1.677, 0.533)), 2)
    none = flight.ap_correction(_params(2, (0, 0, 0), motct=0), 2)
    assert flight.motor_error(none, ref) == pytest.approx(2.0, abs=1e-3)
    assert flight.motor_error(ref, ref) == 0.0
    thr = flight.ap_correction(_params(2, (0, 0, 0), motct=1), 2)
    assert flight.motor_error(thr, ref) is None


# ----------------------------------------------------------------------------- consistency
def test_forward_fill_holds_the_last_row():
    x = np.array([[np.nan, np.nan], [1, 2], [np.nan, np.nan], [3, 4]], float)
    out = flight.forward_fill(x)
    assert np.isnan(out[0]).all()
    np.testing.assert_array_equal(out[1:], [[1, 2], [1, 2], [3, 4]])


def test_dip_and_heading_difference_of_level_fields():
    down = np.tile([0.0, 0.0, 1.0], (2, 1))
    a = np.array([[1.0, 0.0, 1.0], [1.0, 0.0, 0.0]])
    np.testing.assert_allclose(flight.dip_deg(a, down), [45.0, 0.0])
    b = np.array([[1.0, 1.0, 5.0], [1.0, -1.0, 0.0]])  # 45° east of a, 45° west
    np.testing.assert_allclose(flight.heading_difference_deg(a, b, down), [45.0, -45.0])


def test_correction_figures_of_a_right_field_are_ideal():
    rng = np.random.default_rng(1)
    n = 200
    field_world = np.array([231.6, 52.5, -527.8])
    incl = np.degrees(np.arctan2(-field_world[2], np.hypot(*field_world[:2])))
    yaw = rng.uniform(-np.pi, np.pi, n)
    # level vehicle turning in yaw: body = Rz(yaw)ᵀ world
    c, s = np.cos(yaw), np.sin(yaw)
    body = np.column_stack(
        [
            c * field_world[0] + s * field_world[1],
            -s * field_world[0] + c * field_world[1],
            np.full(n, field_world[2]),
        ]
    )
    down = np.tile([0.0, 0.0, 1.0], (n, 1))
    second = body.copy()
    second[::2] = np.nan  # the second compass on every other row
    fig = flight.correction_figures(
        {1: body, 2: second}, down, float(np.linalg.norm(field_world)), -incl
    )
    one = fig["compasses"][1]
    assert one["strength_ratio"] == pytest.approx(1.0)
    assert one["strength_spread"] < 1e-12
    assert one["dip_error_deg"] == pytest.approx(0.0, abs=1e-9)
    assert fig["compasses"][2]["samples"] == n // 2
    assert fig["heading_vs_first_deg"][2]["rms"] == pytest.approx(0.0, abs=1e-9)


def test_compass_columns_and_session_params():
    meta = {"compasses": "1,2,3", "param.COMPASS_OFS2_X": "5", "param.BAD": "x", "date": "d"}
    assert flight.compass_columns(meta) == [(1, "mag"), (2, "mag2"), (3, "mag3")]
    assert flight.compass_columns({"compass": "2"}) == [(2, "mag")]
    assert flight.session_params(meta) == {"COMPASS_OFS2_X": 5.0}


# ----------------------------------------------------------------------------- criteria
def _row(so3, flight_rms, mot_err=0.0):
    return {
        "so3_rms": so3,
        "so3_max": 2 * so3,
        "flight_rms": flight_rms,
        "flight_p95": 0.6,
        "mot_err": mot_err,
    }


def _flight(magcal_score=None, refused=None, rot=None, magfit_best=0.24, compass2=None):
    scores = {
        "in force": _row(7.8, 7.0, 2.0),
        "ideal": _row(0.0, 0.30),
        "magfit": _row(5.6, 3.0, 2.0),
        "magfit --elliptical --cmot": _row(magfit_best, 0.33, 0.05),
    }
    if magcal_score:
        scores["magcal"] = magcal_score
    mc = {
        "seconds": {"import": 1.0, "calibrate": 3.0},
        "refused": refused,
        "refused_at": "calibrate" if refused else None,
    }
    return {
        "name": "f2_motor",
        "magcal": mc,
        "scores": scores,
        "truth_sim": {"ROT": rot},
        "compass2": compass2,
    }


def test_a_refusal_fails_every_criterion_that_applies_and_names_the_step():
    cs = flight.flight_criteria(_flight(refused="This session cannot determine it."))
    assert [c.passed for c in cs] == [False, None, False, False, False, False]
    assert all("calibrate refused" in c.measured for c in cs if c.passed is False)
    assert "does not apply" in cs[1].measured  # magfit's best 0.24° ≤ 0.31°


def test_a_good_result_passes_every_criterion():
    good = _row(0.20, 0.32, 0.05)
    cs = flight.flight_criteria(
        _flight(good, compass2={"so3_rms": 0.1, "so3_max": 0.3, "mot_err": 0.02})
    )
    assert [c.passed for c in cs] == [True, None, True, True, True, True]


def test_criteria_limits():
    # in flight: 1.1 × 0.30 + 0.05 = 0.38
    cs = flight.flight_criteria(_flight(_row(0.20, 0.39, 0.11)))
    by = {c.text: c.passed for c in cs}
    assert by["in-flight RMS ≤ 1.1× the truth's + 0.05°"] is False
    assert by["motor vector within 0.1 mG/A"] is False
    c2 = [c for c in cs if c.text.startswith("compass 2")][0]
    assert c2.passed is False and c2.measured == "not in the result"


def test_custom_rotation_allows_half_a_degree_and_the_magfit_ratio_applies_above_031():
    cs = flight.flight_criteria(_flight(_row(0.45, 0.30), rot=[-1.3, 1.7, 4.5], magfit_best=9.2))
    assert cs[0].text.endswith("(custom rotation)") and cs[0].passed is True
    # magfit's best is then its plain fit's 5.6°: 0.45 / 5.6
    assert cs[1].passed is True and cs[1].measured == "0.08× (0.450° / 5.600°, magfit)"
    cs = flight.flight_criteria(_flight(_row(0.45, 0.30), magfit_best=0.5))
    assert cs[0].passed is False and cs[1].passed is False  # 0.9× > 0.8×


def test_import_and_calibrate_time_limit():
    f = _flight(_row(0.2, 0.3))
    f["magcal"]["seconds"] = {"import": 4.0, "calibrate": 6.5, "flash": 1.0}
    t = flight.flight_criteria(f)[-1]
    assert t.passed is False and t.measured == "10.5 s"


def test_best_magfit_ignores_other_rows():
    scores = _flight()["scores"]
    assert flight.best_magfit(scores) == ("magfit --elliptical --cmot", 0.24)
    assert flight.best_magfit({"ideal": _row(0, 0.3)}) is None


def test_reallog_criterion_fails_on_a_traceback_or_a_crash():
    ok = {"name": "a", "steps": {"import": {"rc": 2, "traceback": False}}}
    tb = {"name": "b", "steps": {"import": {"rc": 1, "traceback": True}}}
    crash = {
        "name": "c",
        "steps": {
            "import": {"rc": 0, "traceback": False},
            "calibrate": {"rc": -11, "traceback": False},
        },
    }
    assert flight.reallog_criterion([ok]).passed is True
    c = flight.reallog_criterion([ok, tb, crash])
    assert c.passed is False and "b, c" in c.measured


# ----------------------------------------------------------------------------- tables
def test_outcome_line_of_a_refusal_and_a_failure():
    assert fr.outcome_line({"refused": "No flight.", "refused_at": "import"}) == (
        "import refused: No flight."
    )
    assert fr.outcome_line({"error": "calibrate exited with 1"}).startswith("**failed**")


def test_score_row_and_cell_escape_pipes():
    row = fr.score_row("magcal", _row(0.2, 0.3, None), "1.5", "a | b")
    assert row.startswith("| magcal | 0.200 | 0.40 | 0.300 | 0.60 | – | 1.5 | a / b |")
    assert fr.score_row("x", None, "–", "not run").count("|") == 9


def test_magfit_source_says_cached_or_measured():
    rec = {"seconds": 118.4, "cached": True, "measured_on": "2026-11-28 02:40 UTC"}
    assert fr.magfit_source(rec) == "fit 118 s (from the cache, measured 2026-11-28 02:40 UTC)"
    assert fr.magfit_source({"seconds": 30.0, "cached": False}) == "fit 30 s (measured now)"
    assert fr.magfit_source({"error": "exited with 1"}).startswith("fit failed")


def test_render_markdown_has_the_header_summary_and_refusal():
    f = _flight(refused="This session cannot determine it.")
    f.update(sha256=SHA, magfit={}, score_error=None)
    f["magcal"]["steps"] = {
        "import": {
            "argv": [str(flight.MAGCAL), "import", "f.bin", "-o", "s.csv"],
            "rc": 0,
            "seconds": 1.0,
        },
        "calibrate": {
            "argv": [str(flight.MAGCAL), "calibrate", "s.csv", "-o", "r.json"],
            "rc": 2,
            "seconds": 3.0,
        },
    }
    verdicts = flight.flight_criteria(f)
    meta = {
        "command": "python -m magcal_evaluation.flight_report",
        "date": "2026-11-28",
        "wall_s": 12.0,
        "cores": 2,
        "workers": 2,
        "python": "3.11",
        "pymavlink": "2.4.50",
        "commit": "abc1234",
        "flights": "F",
        "reallogs": "R",
        "cache": "C",
    }
    md = fr.render_markdown([f], [], verdicts, meta)
    assert md.startswith("# magcal on flight logs\n\nGenerated by `python -m")
    assert "| f2_motor | SO(3) RMS ≤ 0.25° | no calibration: calibrate refused | **FAIL** |" in md
    assert "calibrate refused: This session cannot determine it: nothing to score" in md
    assert "| calibrate | `magcal calibrate s.csv -o r.json` | 2 | 3.00 |" in md
