#!/usr/bin/env python3
# SPDX-License-Identifier: Apache-2.0
"""The real-recordings report: every calibration method on real data, `make real`.

    python -m magcal_evaluation.real_report --data ../shared/realdata --out bench/real.md

Calibrates each case of the data folder (see :mod:`magcal_evaluation.real`) with every
method, scores it with the reference attitude against the plain fit and the known-attitude
floor, and writes a Markdown report (the command, date, machine, commit, the heading table,
the acceptance criteria, ML's stability under tiny shifts of the magnetometer, the estimates
per method) and every case's figures as JSON (--raw).
A refused method is shown "refused", and its forced result (force=True) is scored too. One
process per case, --workers at a time. Exits 1 when a criterion fails (after writing).
"""

from __future__ import annotations

import os

# One BLAS thread per worker process (as the accuracy report). Set before numpy is imported.
for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import json  # noqa: E402
import math  # noqa: E402
import multiprocessing  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
import warnings  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

from magcal.calib.calibrate import METHODS  # noqa: E402
from magcal.ui import ProgressBar  # noqa: E402
from magcal_evaluation import real  # noqa: E402
from magcal_evaluation.accuracy_report import _git_description, run_record  # noqa: E402


def _task(args: tuple[str, str]) -> dict:
    data_dir, name = args
    with warnings.catch_warnings():
        # numpy's overflow warnings inside a method are the method's business; the report
        # shows what it estimates.
        warnings.simplefilter("ignore", RuntimeWarning)
        try:
            return real.evaluate_case(real.load_case(data_dir, name))
        except Exception as exc:  # one broken case must not hide the others' figures
            return {"case": name, "error": f"{type(exc).__name__}: {exc}"}


def _f(x: float | None, fmt: str = "{:.2f}") -> str:
    return "–" if x is None or not math.isfinite(x) else fmt.format(x)


def _cell(r: dict, method: str) -> str:
    """heading (×plain, ×floor), or "refused" (forced: heading)."""
    m = r["methods"].get(method)
    if m is None:
        return "–"
    if m["refused"] is not None:
        forced = m.get("forced") or {}
        if forced.get("refused") is not None:
            return "refused (forced: raises)"
        return f"refused (forced {_f(forced.get('heading_deg'))})"
    ratios = [
        _f(real.ratio(m["heading_deg"], r[ref]), "{:.2f}×" + label)
        for ref, label in (("plain", "p"), ("floor", "f"))
        if r[ref] is not None
    ]
    return f"{_f(m['heading_deg'])} ({', '.join(ratios)})" if ratios else _f(m["heading_deg"])


def _with_plain_ratio(x: float | None, plain: float | None) -> str:
    """A heading with its ratio to the plain fit's: "7.94 (1.15×p)"."""
    return f"{_f(x)} ({_f(real.ratio(x, plain), '{:.2f}×p')})"


def _form(r: dict) -> str:
    if r.get("form") == real.FORM_RAW:
        return "multi-rate, from raw/"
    return "sessions/ (single-rate)"


def _vec(v, digits: int = 2) -> str:
    """A 3-vector as "(+x, +y, +z)", or "–"."""
    return "–" if v is None else "(" + ", ".join(f"{x:+.{digits}f}" for x in v) + ")"


def _detail_row(r: dict, method: str, m: dict, forced: bool) -> str:
    bias = m.get("gyro_bias_deg_s")
    bias_txt = "–" if bias is None else f"{np.linalg.norm(bias):.3f} {_vec(bias, 3)}"
    mis = m.get("misalignment_vec_deg")
    mis_txt = "–" if mis is None else f"{_f(m['misalignment_deg'], '{:.1f}')} {_vec(mis, 1)}"
    offset = m.get("time_offset_s")
    refused = m.get("refused")
    if refused:
        status = ("forced run raises: " if forced else "refused: ") + refused[:140].replace(
            "|", "/"
        )
    else:
        status = "forced" if forced else "no"
    return (
        f"| {r['case']} | {method}{' (forced)' if forced else ''} | {_f(m['heading_deg'])} | "
        f"{bias_txt} | {mis_txt} | {'–' if offset is None else f'{offset * 1e3:.1f} ms'} | "
        f"{status} | {m['seconds']:.2f} |"
    )


def _rescored_ml_cell(a: dict) -> str:
    """ML's heading in a rescored table, with its ratios to that table's plain fit and floor."""
    ratios = [f"{a['ml'] / a[ref]:.2f}×{ref[0]}" for ref in ("plain", "floor") if a.get(ref)]
    cell = _f(a["ml"]) + (f" ({', '.join(ratios)})" if ratios else "")
    return f"refused (forced {cell})" if a.get("ml_forced") else cell


def _stability_row(r: dict) -> str:
    """case | the heading per k (or "refused") | spread | verdict."""
    a = r["stability"]
    cells = [
        "refused" if run["refused"] is not None else f"{run['heading_deg']:.3f}"
        for run in a["runs"]
    ]
    if a["stable"]:
        verdict = "stable" if a["spread_deg"] is not None else "stable (the same refusal)"
    else:
        verdict = "**unstable**"
    return f"| {r['case']} | {' | '.join(cells)} | {_f(a['spread_deg'], '{:.3f}')} | {verdict} |"


def _section_rows(results: list[dict], key: str):
    """(case result, its ``key`` section, ML's run: the forced one where ML refused) for
    every case that has the section."""
    for r in results:
        section = r.get(key)
        if section:
            yield r, section, r["methods"]["ml"].get("forced", r["methods"]["ml"])


def render_markdown(results: list[dict], verdicts: list[real.Criterion], meta: dict) -> str:
    lines = [
        "# magcal on real recordings",
        "",
        f"Generated by `{meta['command']}`",
        f"on {meta['date']} in {meta['wall_s']:.0f} s wall time; machine: {meta['cores']} cores "
        f"({meta['workers']} worker processes), Python {meta['python']}, magcal at "
        f"{meta['commit']}. Data: `{meta['data']}` (see its README.md).",
        "",
        "Each case is a session calibrated by every method and scored with an optical reference "
        "attitude: every scored sample corrected, `m = D⁻¹(y − o)`, rotated into the world with "
        "the reference, heading `atan2(east, north) − declination`, wrapped; RMS per trial and "
        "median over the case's trials, in degrees. *Plain*: the symmetric ellipsoid fit of the "
        'magnetometer alone (magcal\'s algebraic fit; "fails" when it is no ellipsoid). '
        "*Floor*: the least-squares fit of `y = D R(t)ᵀ m + o` with the reference attitude, "
        "solving D, o and the field (its heading is the floor's north), where the case is "
        "scored on its own recording. Cells: heading (ratio to plain ×p, to floor ×f); "
        '"refused": the method refused the session, with the forced result (force=True) in '
        "brackets. A case with the streams at their own rates (`raw/CASE.npz`) is calibrated "
        "as a multi-rate session built from them (rows at every stream's times, the gyroscope "
        "held, nothing interpolated: `magcal_evaluation.real.multi_rate_session`), the others "
        "from `sessions/CASE.csv`; the References table says which (*session*).",
        "",
        "## Heading error (median RMS, degrees)",
        "",
        "| case | plain | floor | " + " | ".join(METHODS) + " |",
        "|---|---:|---:|" + "---:|" * len(METHODS),
    ]
    for r in results:
        if "error" in r:
            lines.append(f"| {r['case']} | error: {r['error'][:200]} |")
            continue
        plain = "fit fails" if r["plain"] is None else _f(r["plain"])
        lines.append(
            f"| {r['case']} | {plain} | {_f(r['floor'])} | "
            + " | ".join(_cell(r, m) for m in METHODS)
            + " |"
        )
    good = [r for r in results if "error" not in r]
    lines += [
        "",
        "## Summary",
        "",
        "| criterion | measured | result |",
        "|---|---|---|",
    ]
    for c in verdicts:
        res = "n/a" if c.passed is None else ("pass" if c.passed else "**FAIL**")
        lines.append(f"| {c.text} | {c.measured} | {res} |")
    shifts = range(real.STABILITY_MAX_K + 1)
    lines += [
        "",
        "## Stability under tiny shifts of the magnetometer",
        "",
        "ML's heading error (degrees) with every magnetometer reading of the session moved by "
        f"k·{real.scientific(real.STABILITY_STEP)} of the field's magnitude on each axis, far "
        "below any sensor's resolution (k = 0 is the run of the heading table), each run "
        "calibrated and scored as that table's: stable when the spread (max − min) is at most "
        f"{real.STABILITY_MAX_SPREAD_DEG}° or every run refuses for the same reason "
        "(`magcal_evaluation.real.stability`, `make real`).",
        "",
        "| case | " + " | ".join(f"k = {k}" for k in shifts) + " | spread ° | verdict |",
        "|---|" + "---:|" * len(shifts) + "---:|---|",
    ]
    lines += [_stability_row(r) for r in good if r.get("stability")]
    lines += [
        "",
        "## Scored at the magnetometer's own time",
        "",
        "The same calibrations scored against the reference attitude at the time the "
        "magnetometer measured, `t − τ` with the ML's time offset τ (the reference "
        "interpolated spherically; the floor refitted there): the heading error a fusion "
        "filter that knows the delay gets. Where the magnetometer lags, the table above "
        "charges every calibration for the lag, and the least-squares fits (plain, floor) "
        "partly absorb it into D; the one with τ does not. The last column is the rotation "
        "part of the floor's D (as the estimates table gives ML's), fitted at the same time "
        "and at `t − τ`: where the recording turns more one way than the other, the lag "
        "looks like a fixed rotation to a fit without τ, and that rotation belongs to the "
        "recording's motion, not to the sensor. Cases where ML kept no time offset are left "
        "out.",
        "",
        "| case | τ ms | plain | floor | ml | floor's rotation ° (at t → at t − τ) |",
        "|---|---:|---:|---:|---:|---|",
    ]
    for r, a, _ in _section_rows(good, "at_magnetometer_time"):
        ml = _rescored_ml_cell(a)
        turns = a.get("floor_rotation_deg")
        turn_txt = "–" if not turns else " → ".join(_vec(v) for v in turns)
        lines.append(
            f"| {r['case']} | {1e3 * a['delay_s']:.1f} | {_f(a['plain'])} | {_f(a['floor'])} "
            f"| {ml} | {turn_txt} |"
        )
    lines += [
        "",
        "## The magnetometer's delay as the reference shows it",
        "",
        "The reference measures the magnetometer's delay too, independently of any "
        "calibration: the delay behind the reference's clock at which the known-attitude "
        "model explains the magnetometer best (`magcal_evaluation.real.reference_delay`; "
        "on the rows where the magnetometer measured, as the calibration takes them: a "
        "stream's repeats of its last value are no new measurement), "
        "and the gyroscope's, where the reference's rate matches the gyroscope's best "
        "(`magcal_evaluation.real.gyroscope_delay`). Their difference is the magnetometer's "
        "delay behind the gyroscope, which ML's time offset τ estimates; ML holds each "
        "gyroscope sample over the step that follows it, which puts its attitude half a "
        "step late, so τ comes out about half a step shorter than that difference. "
        "*Fit at the delay*: the known-attitude fit at the magnetometer's delay, "
        "the magnetometer as it is, with no lag in D; its rotation stands beside the "
        "floor's, which takes the lag in as a rotation. Scored as every method is (at t, the "
        "case's declination), it is the best a calibration can do that carries the lag in a "
        "time offset rather than in D, and ML's ratio to it (×d) says how close ML comes; "
        "scored at its own time and north it is what a fusion filter that knows the delay "
        "could get. *In the IMU's axes*: the same fit with the reference turned to the IMU's "
        "axes (as in the section below), the magnetometer calibrated against the IMU with the "
        "attitude known exactly and the lag left out: the best an inertial calibration can "
        "find. Scored as every method is, in the reference's axes, it carries the IMU's "
        "mounting in the reference's frame as ML's result does; ML's ratio to it is ×i. Cases "
        "scored on other recordings are left out.",
        "",
        "| case | magnetometer's delay ms | gyroscope's delay ms | ML's τ ms | floor | fit at "
        "the delay | fit at the delay, in the IMU's axes | ml | fit at the delay, at its own "
        "time | its rotation ° | floor's rotation ° |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|---|---|",
    ]
    for r, a, ml_run in _section_rows(good, "reference_delay"):
        tau = ml_run.get("time_offset_s")
        gyro = a.get("gyroscope_delay_s")
        imu_fit = a.get("imu_fit")
        vs_imu = "" if imu_fit is None else f"{a['ml'] / imu_fit:.2f}×i, "
        ml = f"{_f(a['ml'])} ({a['ml'] / a['fit']:.2f}×d, {vs_imu}{a['ml'] / a['floor']:.2f}×f)"
        if a.get("ml_forced"):
            ml = f"refused (forced {ml})"
        imu_txt = "–" if imu_fit is None else f"{_f(imu_fit)} ({imu_fit / a['floor']:.2f}×f)"
        lines.append(
            f"| {r['case']} | {1e3 * a['delay_s']:.1f} | "
            f"{'–' if gyro is None else f'{1e3 * gyro:.1f}'} | "
            f"{'–' if tau is None else f'{1e3 * tau:.1f}'} | {_f(a['floor'])} | "
            f"{_f(a['fit'])} ({a['fit'] / a['floor']:.2f}×f) | {imu_txt} | {ml} | "
            f"{_f(a['fit_at_delay'])} | {_vec(a['fit_rotation_deg'])} | "
            f"{_vec(a['floor_rotation_deg'])} |"
        )
    lines += [
        "",
        "## Scored in the IMU's frame",
        "",
        "The reference attitude is that of the optical markers' body frame. An inertial "
        "calibration aligns the magnetometer to the IMU's axes, which sit in that frame turned "
        "by the rotation given here (from the gyroscope's rotations over 0.1 s against the "
        "reference's at the gyroscope's delay, least squares: "
        "`magcal_evaluation.real.imu_axes`). "
        "Here the reference is turned to the IMU's axes before scoring, the floor turned "
        "with it (the same fit: its D times the rotation), and all three share the floor's "
        "north. The gyroscope's bias as the reference "
        "shows it (its rate minus the reference's over 30 ms at the gyroscope's delay, median: "
        "`magcal_evaluation.real.reference_gyro_bias`) stands beside ML's estimate. Cases "
        "scored on other recordings are left out.",
        "",
        "| case | IMU in the reference frame, ° | plain | floor | ml | gyro bias °/s: "
        "reference | gyro bias °/s: ml |",
        "|---|---|---:|---:|---:|---|---|",
    ]
    for r, a, ml_run in _section_rows(good, "imu_frame"):
        ml = _rescored_ml_cell(a)
        angle = float(np.linalg.norm(a["rotation_deg"]))
        lines.append(
            f"| {r['case']} | {angle:.2f} {_vec(a['rotation_deg'])} | {_f(a['plain'])} | "
            f"{_f(a['floor'])} | {ml} | {_vec(a.get('reference_gyro_bias_deg_s'), 3)} | "
            f"{_vec(ml_run.get('gyro_bias_deg_s'), 3)} |"
        )
    lines += [
        "",
        "## Scored on other recordings",
        "",
        "A phone's calibration recording is scored on its other recordings, made on other "
        "days. *Fit there*: the known-attitude fit on those scored recordings themselves "
        "(`magcal_evaluation.real.scored_recordings_fit`), which no calibration recording can "
        "give; its rotation is the magnetometer's rotation as the scored recordings show it, "
        "beside ML's (the rotation part of D, as in the estimates table). *Offset moved*: "
        "that fit's offset minus ML's, as a fraction of the field. The last columns take the "
        "rotation out of ML's D (its symmetric factor P of D = P U) and put the scored "
        "recordings' own rotation into the plain fit's D: where the plain fit turned by the "
        "right rotation scores worse than the plain fit, its missing rotation offsets its "
        "other errors on those days (the offset moved), and a calibration that finds the "
        "rotation loses there unless it also knows those days' offset, which its own "
        "recording does not show. The last two columns give ML's D and the plain fit's D "
        "those days' own offset (the fit's): what each D is worth once the offset is right.",
        "",
        "| case | fit there | its rotation ° | ml | ml's rotation ° | offset moved | "
        "ml without its rotation | plain | plain with the fit's rotation | "
        "ml's D, the fit's offset | plain's D, the fit's offset |",
        "|---|---:|---|---:|---|---:|---:|---:|---:|---:|---:|",
    ]
    for r, a, ml_run in _section_rows(good, "other_recordings"):
        forced = " (forced)" if a.get("ml_forced") else ""
        lines.append(
            f"| {r['case']} | {_f(a['fit'])} | {_vec(a['fit_rotation_deg'])} | "
            f"{_f(ml_run['heading_deg'])}{forced} | {_vec(ml_run['misalignment_vec_deg'])} | "
            f"{100 * a['offset_change'] / a['field_norm']:.1f} % | "
            f"{_f(a['ml_without_rotation'])} | {_f(r['plain'])} | "
            f"{_f(a['plain_with_fit_rotation'])} | {_f(a['ml_with_fit_offset'])} | "
            f"{_f(a['plain_with_fit_offset'])} |"
        )
    lines += [
        "",
        "The calibration recording gives one offset, which ML and the plain fit agree on "
        "(their gap, as a fraction of the field). The last two columns score the D the "
        "scored recordings themselves show (the fit's) with that offset: what a "
        "calibration whose D is exactly right scores on those days. Where that is worse "
        "than the plain fit, the plain fit's lead comes from its D's errors offsetting the "
        "moved offset, which no calibration recording shows, and no calibration that finds "
        "the right D can be as good as the plain fit there.",
        "",
        "| case | plain | ml | ML's offset − the plain fit's | the fit's D, ML's offset | "
        "the fit's D, the plain fit's offset |",
        "|---|---:|---:|---:|---:|---:|",
    ]
    for r, a, ml_run in _section_rows(good, "other_recordings"):
        gap = a.get("ml_plain_offset_gap")
        gap_txt = "–" if gap is None else f"{100 * gap / a['field_norm']:.2f} %"
        lines.append(
            f"| {r['case']} | {_f(r['plain'])} | "
            f"{_with_plain_ratio(ml_run['heading_deg'], r['plain'])} | {gap_txt} | "
            f"{_with_plain_ratio(a['fit_with_ml_offset'], r['plain'])} | "
            f"{_with_plain_ratio(a.get('fit_with_plain_offset'), r['plain'])} |"
        )
    rights = real.right_calibrations(good)
    if rights:
        lines += [
            "",
            "## What a right calibration scores",
            "",
            "Each case's heading error with the calibration its own data show to be right: "
            "where it is scored on its own recording, the known-attitude fit at the "
            "magnetometer's delay (from the section on the magnetometer's delay); where it is "
            "scored on other recordings, the D those recordings show with the calibration "
            "recording's offset, ML's (from the section on other recordings). It is no lower "
            "bound: a calibration can score better by "
            "being wrong in a way the recording's motion or the scored days' offset rewards, "
            "as ML does where its ratio is below the right one's. The medians say what being "
            "right earns across the cases, against the median the acceptance asks of ML "
            f"(≤ {real.ML_MEDIAN_MAX_RATIO_TO_PLAIN}), and what the better of ML and the "
            "right calibration earns, case by case.",
            "",
            "| case | right calibration | plain | right | ml | better of the two |",
            "|---|---|---:|---:|---:|---:|",
        ]
        for c in rights:
            lines.append(
                f"| {c.case} | {c.kind} | {_f(c.plain)} | "
                f"{_with_plain_ratio(c.right, c.plain)} | "
                f"{'refused' if c.ml is None else _with_plain_ratio(c.ml, c.plain)} | "
                f"{_with_plain_ratio(c.better, c.plain)} |"
            )
        right_q = [c.right / c.plain for c in rights]
        ml_q = [c.ml / c.plain for c in rights if c.ml is not None]
        better_q = [c.better / c.plain for c in rights]
        lines.append(
            f"| median over {len(rights)} cases of the ratio to plain | | | "
            f"{np.median(right_q):.3f}×p | {np.median(ml_q):.3f}×p | "
            f"{np.median(better_q):.3f}×p |"
        )
    lines += [
        "",
        "## Trial by trial",
        "",
        "A case scored on several recordings takes each method's median over them; the "
        "ratios above divide one median by the other. Where a case's recordings fall into "
        "easy and hard groups, the two medians can come from different recordings. Here ML "
        "and the plain fit are compared recording by recording: on how many ML's heading "
        "error is the smaller, and the ratio ML/plain per recording (median, and the range).",
        "",
        "| case | recordings | ML better on | ML/plain per recording: median (range) | "
        "median ml | median plain | ratio of the medians |",
        "|---|---:|---:|---|---:|---:|---:|",
    ]
    for r, a, _ in _section_rows(good, "trial_by_trial"):
        ml, plain = np.array(a["ml"]), np.array(a["plain"])
        q = ml / plain
        lines.append(
            f"| {r['case']} | {len(q)} | {int((q < 1.0).sum())} | {np.median(q):.2f} "
            f"({q.min():.2f}–{q.max():.2f}) | {np.median(ml):.2f} | {np.median(plain):.2f} | "
            f"{np.median(ml) / np.median(plain):.2f} |"
        )
    lines += [
        "",
        "## Estimates per method",
        "",
        "Gyroscope bias: the result's, norm (vector), °/s (init and the norm-only methods "
        "take it from the session's rest periods, zero without any). "
        "Misalignment: the rotation of the magnetometer axes against the body axes, the "
        "rotation part of D by polar decomposition "
        "(`magcal.calib.diagnostics.uncertainty.misalignment_deg`): angle (rotation vector), "
        "degrees. Time offset: the magnetometer's delay against the inertial sensors, when the "
        'result has one (`time_offset_s`), else "–". Time: one `calibrate()` call, s.',
        "",
        "| case | method | heading ° | gyro bias °/s | misalignment ° | time offset | "
        "refused | time s |",
        "|---|---|---:|---|---|---:|---|---:|",
    ]
    for r in good:
        for method, m in r["methods"].items():
            lines.append(_detail_row(r, method, m, forced=False))
            if m.get("forced"):
                lines.append(_detail_row(r, method, m["forced"], forced=True))
    lines += [
        "",
        "## References",
        "",
        "| case | source | session | rows (magnetometer) | trials | plain (algebraic) | "
        "plain (SDP ellipsoid) | floor | floor's field heading ° | floor's dip ° |",
        "|---|---|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in good:
        lines.append(
            f"| {r['case']} | {r['source']} | {_form(r)} | {r['samples']} "
            f"({r.get('mag_samples', r['samples'])}) | {r['trials']} | "
            f"{'fit fails' if r['plain'] is None else _f(r['plain'])} | {_f(r['plain_sdp'])} | "
            f"{_f(r['floor'])} | {_f(r['floor_field_heading_deg'])} | {_f(r['floor_dip_deg'])} |"
        )
    lines += [
        "",
        "The plain fit is magcal's algebraic ellipsoid fit; its SDP fit (positive definite by "
        "construction) is shown beside it. Where a case is scored on other recordings (a "
        "phone's calibration recording scored on its other recordings) there is no floor.",
    ]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        prog=f"python -m {__spec__.name}", description=__doc__.splitlines()[0]
    )
    ap.add_argument(
        "--data",
        default=str(real.DEFAULT_DATA_DIR),
        help="the real-data folder (default: shared/realdata beside the checkout)",
    )
    ap.add_argument("--out", default="bench/real.md", help="Markdown report path")
    ap.add_argument(
        "--raw",
        default="out/real.json",
        help="the figures of every case as JSON (default %(default)s)",
    )
    ap.add_argument("--workers", type=int, default=2, help="processes (default 2)")
    ap.add_argument("--cases", default="", help="comma-separated subset of the cases")
    args = ap.parse_args(argv)
    if args.workers < 1:
        ap.error("--workers must be at least 1")
    try:
        names = real.case_names(args.data)
    except real.RealDataError as exc:
        print(f"magcal_evaluation.real_report: {exc}", file=sys.stderr)
        return 2
    if args.cases:
        wanted = [c.strip() for c in args.cases.split(",") if c.strip()]
        unknown = [c for c in wanted if c not in names]
        if unknown:
            ap.error(f"unknown case(s) {', '.join(unknown)}; known: {', '.join(names)}")
        names = wanted

    commit_at_start = _git_description()
    t0 = time.perf_counter()
    by_name: dict[str, dict] = {}
    with (
        multiprocessing.get_context("fork").Pool(args.workers) as pool,
        ProgressBar("real recordings", len(names), unit="cases", log_step_pct=10.0) as bar,
    ):
        failed = 0
        for r in pool.imap_unordered(_task, [(args.data, n) for n in names]):
            by_name[r["case"]] = r
            failed += "error" in r
            bar.advance(note=f"{failed} failed" if failed else None)
    wall = time.perf_counter() - t0
    results = [by_name[n] for n in names]
    verdicts = real.criteria([r for r in results if "error" not in r])

    meta = {
        **run_record(__spec__.name, argv, args.workers, commit_at_start),
        "wall_s": wall,
        "data": args.data,
    }
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(render_markdown(results, verdicts, meta) + "\n", encoding="utf-8")
    raw = Path(args.raw)
    raw.parent.mkdir(parents=True, exist_ok=True)
    with open(raw, "w", encoding="utf-8") as f:
        json.dump({"meta": meta, "cases": results}, f, indent=1, default=float)
        f.write("\n")

    for c in verdicts:
        res = "n/a" if c.passed is None else ("pass" if c.passed else "FAIL")
        print(f"{res:>4}  {c.text}: {c.measured}", file=sys.stderr)
    print(f"wrote {out} and {raw} in {wall:.0f} s", file=sys.stderr)
    errors = [r["case"] for r in results if "error" in r]
    if errors:
        print(f"cases that raised: {', '.join(errors)}", file=sys.stderr)
    if errors or any(c.passed is False for c in verdicts):
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
