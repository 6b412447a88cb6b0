# SPDX-License-Identifier: Apache-2.0
"""From the study's run records to its summary: numbers, Markdown and figures.

:func:`summarise` is a pure function of the settings and the records (any order): the same
records give the same summary, whichever jobs, order or interruptions produced them. Only the
fields named ``seconds*`` are measured times. :func:`render_markdown` and
:func:`write_figures` turn it into ``summary.md`` and the PNGs.
"""

from __future__ import annotations

import math
from collections import Counter
from dataclasses import dataclass
from pathlib import Path

import numpy as np

import magcal_evaluation.study.zhao as zhao
from magcal.calib.diagnostics import quality
from magcal.report import plots
from magcal_evaluation.study.experiments import StudySettings, seeds

SUMMARY_FILE = "summary.md"
FIGURE8_FILE = "figure8.png"
ZHAO_FIGURE1_FILE = "zhao_figure1.png"
COMPARISON_FILE = "comparison.png"
#: Distinct failure reasons listed per table row; the rest are counted.
MAX_REASONS = 5
#: Seeds named per failure reason.
MAX_SEEDS_NAMED = 8
ZHAO_LABELS = {"ckf": "CKF", "two-step": "TWO-STEP"}


@dataclass(frozen=True)
class Reason:
    """One failure reason: its text, how many runs, and the first seeds."""

    text: str
    count: int
    seeds: tuple[int, ...]


@dataclass(frozen=True)
class Figure8Summary:
    """Kok & Schön Figure 8 over ``runs`` runs; medians over the runs that have the figure.

    ekf_*  : EKF heading RMSE against the true attitude, degrees (the paper's Figure 8)
    cal_*  : calibration-induced heading error (RMS over the SO(3) grid), degrees
    """

    runs: int
    failed: int
    forced: int
    ekf_init_median: float
    ekf_ml_median: float
    ekf_init_max: float
    ekf_ml_max: float
    ekf_ml_better: int
    ekf_compared: int
    cal_init_median: float
    cal_ml_median: float
    cal_floor_median: float
    seconds_median: float
    reasons: tuple[Reason, ...]


@dataclass(frozen=True)
class ComparisonRow:
    """One method on one scenario's seeds. Heading errors in degrees, over the runs that
    calibrated; ratio: median of per-run heading error / known-attitude floor."""

    scenario: str
    method: str
    runs: int
    ok: int
    exceptions: int
    refused: int
    heading_median: float
    heading_p90: float
    heading_max: float
    ratio_median: float
    floor_median: float
    seconds_median: float
    reasons: tuple[Reason, ...]


@dataclass(frozen=True)
class ZhaoMethod:
    """One estimator over the Zhao runs: mean and standard deviation of ``A`` (3×3) and
    ``b`` (gauss) over the runs it finished, and the largest error of the mean against the
    truth."""

    name: str
    ok: int
    failed: int
    A_mean: tuple[tuple[float, ...], ...]
    b_mean: tuple[float, ...]
    A_std: tuple[tuple[float, ...], ...]
    b_std: tuple[float, ...]
    A_mean_max_error: float
    b_mean_max_error: float
    seconds_median: float
    seconds_per_sample_median: float
    reasons: tuple[Reason, ...]


@dataclass(frozen=True)
class ZhaoSummary:
    runs: int
    samples: int
    methods: tuple[ZhaoMethod, ...]


@dataclass(frozen=True)
class StudySummary:
    """seconds_runs: the runs' own times added up (whatever the jobs and interruptions)."""

    settings: StudySettings
    runs: int
    failed: int
    seconds_runs: float
    figure8: Figure8Summary | None
    zhao: ZhaoSummary | None
    comparison: tuple[ComparisonRow, ...]


# --------------------------------------------------------------------------------------------
# Numbers


def _seed_of(record: dict) -> int:
    return int(record["params"]["seed"])


def _result(record: dict) -> dict:
    return record.get("result", {})


def _failed(record: dict) -> bool:
    return "crashed" in record or bool(_result(record).get("failed"))


def _reason_text(record: dict) -> str:
    if "crashed" in record:
        return f"run crashed: {record['crashed']}"
    return str(_result(record).get("reason", "failed (no reason given)"))


def _reasons(records: list[dict]) -> tuple[Reason, ...]:
    failed = sorted((r for r in records if _failed(r)), key=_seed_of)
    counts = Counter(_reason_text(r) for r in failed)
    out = []
    for text, count in sorted(counts.items(), key=lambda kv: (-kv[1], kv[0])):
        named = tuple(_seed_of(r) for r in failed if _reason_text(r) == text)[:MAX_SEEDS_NAMED]
        out.append(Reason(text, count, named))
    return tuple(out)


def _values(records: list[dict], key: str) -> np.ndarray:
    v = [_result(r).get(key) for r in records]
    return np.array([x for x in v if x is not None], dtype=float)


def _median(x: np.ndarray) -> float:
    return float(np.median(x)) if x.size else math.nan


def _max(x: np.ndarray) -> float:
    return float(np.max(x)) if x.size else math.nan


def summarise_figure8(records: list[dict]) -> Figure8Summary:
    done = [r for r in records if "result" in r]
    both = [
        _result(r)
        for r in done
        if _result(r).get("ekf_init_deg") is not None and _result(r).get("ekf_ml_deg") is not None
    ]
    ekf_i = np.array([r["ekf_init_deg"] for r in both])
    ekf_m = np.array([r["ekf_ml_deg"] for r in both])
    return Figure8Summary(
        runs=len(records),
        failed=sum(_failed(r) for r in records),
        forced=sum(bool(_result(r).get("forced")) for r in records),
        ekf_init_median=_median(ekf_i),
        ekf_ml_median=_median(ekf_m),
        ekf_init_max=_max(ekf_i),
        ekf_ml_max=_max(ekf_m),
        ekf_ml_better=int(np.sum(ekf_m < ekf_i)),
        ekf_compared=len(both),
        cal_init_median=_median(_values(done, "init_deg")),
        cal_ml_median=_median(_values(done, "ml_deg")),
        cal_floor_median=_median(_values(done, "floor_deg")),
        seconds_median=_median(np.array([r["seconds"] for r in records])),
        reasons=_reasons(records),
    )


def summarise_comparison(records: list[dict], settings: StudySettings) -> tuple[ComparisonRow, ...]:
    rows = []
    for scenario in settings.scenarios:
        for method in settings.methods:
            mine = [
                r
                for r in records
                if r["params"]["scenario"] == scenario and r["params"]["method"] == method
            ]
            ok = [r for r in mine if not _failed(r)]
            heading = _values(ok, "heading_deg")
            ratio = np.array(
                [_result(r)["heading_deg"] / _result(r)["floor_deg"] for r in ok], dtype=float
            )
            refused = sum(bool(_result(r).get("refused")) for r in mine if _failed(r))
            rows.append(
                ComparisonRow(
                    scenario=scenario,
                    method=method,
                    runs=len(mine),
                    ok=len(ok),
                    exceptions=len(mine) - len(ok) - refused,
                    refused=refused,
                    heading_median=_median(heading),
                    heading_p90=float(np.percentile(heading, 90)) if heading.size else math.nan,
                    heading_max=_max(heading),
                    ratio_median=_median(ratio),
                    floor_median=_median(_values(mine, "floor_deg")),
                    seconds_median=_median(_values(mine, "seconds")),
                    reasons=_reasons(mine),
                )
            )
    return tuple(rows)


def _matrix(a: np.ndarray) -> tuple:
    return (
        tuple(tuple(float(x) for x in row) for row in a)
        if a.ndim == 2
        else tuple(float(x) for x in a)
    )


def summarise_zhao(records: list[dict]) -> ZhaoSummary:
    names = [n for n in ZHAO_LABELS if any(n in _result(r) for r in records)]
    methods = []
    for name in names:
        parts = [_result(r).get(name) for r in records if "result" in r]
        ok = [p for p in parts if p is not None and not p.get("failed")]
        A = np.array([p["A"] for p in ok], dtype=float).reshape(-1, 3, 3)
        b = np.array([p["b"] for p in ok], dtype=float).reshape(-1, 3)
        nan33, nan3 = np.full((3, 3), math.nan), np.full(3, math.nan)
        A_mean = A.mean(axis=0) if len(ok) else nan33
        b_mean = b.mean(axis=0) if len(ok) else nan3
        secs = np.array([p["seconds"] for p in ok], dtype=float)
        per_sample = np.array(
            [
                p["seconds"] / _result(r)["samples"]
                for r in records
                for p in [_result(r).get(name)]
                if p is not None and not p.get("failed")
            ],
            dtype=float,
        )
        failed_runs = [r for r in records if "crashed" in r or _zhao_failed(r, name)]
        methods.append(
            ZhaoMethod(
                name=name,
                ok=len(ok),
                failed=len(records) - len(ok),
                A_mean=_matrix(A_mean),
                b_mean=_matrix(b_mean),
                A_std=_matrix(A.std(axis=0) if len(ok) else nan33),
                b_std=_matrix(b.std(axis=0) if len(ok) else nan3),
                A_mean_max_error=float(np.max(np.abs(A_mean - zhao.TRUE_A))),
                b_mean_max_error=float(np.max(np.abs(b_mean - zhao.TRUE_B_G))),
                seconds_median=_median(secs),
                seconds_per_sample_median=_median(per_sample),
                reasons=_zhao_reasons(failed_runs, name),
            )
        )
    samples = {int(_result(r)["samples"]) for r in records if "samples" in _result(r)}
    return ZhaoSummary(
        runs=len(records), samples=max(samples) if samples else 0, methods=tuple(methods)
    )


def _zhao_failed(record: dict, name: str) -> bool:
    part = _result(record).get(name)
    return part is None or bool(part.get("failed"))


def _zhao_reasons(records: list[dict], name: str) -> tuple[Reason, ...]:
    as_runs = []
    for r in records:
        if "crashed" in r:
            as_runs.append(r)
        else:
            part = _result(r).get(name) or {"reason": "no result"}
            as_runs.append({"params": r["params"], "result": {"failed": True, **part}})
    return _reasons(as_runs)


def summarise(settings: StudySettings, records: list[dict]) -> StudySummary:
    """The study's numbers from its records (any order; only this study's keys)."""
    by_experiment: dict[str, list[dict]] = {e: [] for e in settings.experiments}
    for r in sorted(records, key=lambda r: r["key"]):
        by_experiment.setdefault(r["experiment"], []).append(r)
    return StudySummary(
        settings=settings,
        runs=len(records),
        failed=sum(_failed(r) for r in records),
        seconds_runs=float(sum(r["seconds"] for r in records)),
        figure8=summarise_figure8(by_experiment["figure8"])
        if "figure8" in settings.experiments
        else None,
        zhao=summarise_zhao(by_experiment["zhao-table1"])
        if "zhao-table1" in settings.experiments
        else None,
        comparison=summarise_comparison(by_experiment["comparison"], settings)
        if "comparison" in settings.experiments
        else (),
    )


# --------------------------------------------------------------------------------------------
# Markdown


def _f(x: float, fmt: str = "{:.3g}") -> str:
    return "–" if x is None or not math.isfinite(x) else fmt.format(x)


def _seed_range(settings: StudySettings, experiment: str) -> str:
    s = seeds(settings, experiment)
    return f"{s[0]}..{s[-1]}" if len(s) > 1 else str(s[0])


def _reason_lines(prefix: str, reasons: tuple[Reason, ...]) -> list[str]:
    lines = []
    for r in reasons[:MAX_REASONS]:
        more = "…" if r.count > len(r.seeds) else ""
        text = " ".join(r.text.split())
        lines.append(
            f"- {prefix}{r.count} run(s), seeds {', '.join(map(str, r.seeds))}{more}: {text}"
        )
    if len(reasons) > MAX_REASONS:
        rest = sum(r.count for r in reasons[MAX_REASONS:])
        lines.append(
            f"- {prefix}{rest} more run(s) with {len(reasons) - MAX_REASONS} other reasons"
        )
    return lines


def _figure8_md(s: Figure8Summary, settings: StudySettings) -> list[str]:
    lines = [
        "## Kok & Schön (2016), Figure 8: Table 2 settings",
        "",
        f'{s.runs} runs (seeds {_seed_range(settings, "figure8")}), `preset("table2")`: 100 '
        "samples at rest and 300 of rotation, sensors drawn from Table 2. Heading RMSE of the "
        "calibration EKF run with each estimate against the true attitude (the paper's "
        "Figure 8), and the calibration-induced heading error (noise-free fields at "
        f"{quality.HEADING_GRID_SIZE} orientations, RMS).",
        "",
        f"![Figure 8]({FIGURE8_FILE})",
        "",
        "| estimate | EKF heading RMSE, median [°] | EKF heading RMSE, max [°] | "
        "calibration-induced heading error, median [°] |",
        "|---|---:|---:|---:|",
        f"| initial (Algorithm 1, step 1) | {_f(s.ekf_init_median)} | {_f(s.ekf_init_max)} | "
        f"{_f(s.cal_init_median)} |",
        f"| ML (Algorithm 1) | {_f(s.ekf_ml_median)} | {_f(s.ekf_ml_max)} | "
        f"{_f(s.cal_ml_median)} |",
        f"| known-attitude floor | – | – | {_f(s.cal_floor_median)} |",
        "",
        f"ML's EKF heading RMSE is below the initial estimate's in {s.ekf_ml_better} of "
        f"{s.ekf_compared} runs. Failed runs: {s.failed}; refused by the observability check "
        f"and then calibrated with force: {s.forced}. Median time per run "
        f"{_f(s.seconds_median, '{:.2f}')} s (simulation, calibration and both filters).",
    ]
    lines += [""] + _reason_lines("", s.reasons) if s.reasons else []
    return lines + [""]


def _matrix_cells(A: tuple, b: tuple) -> list[str]:
    """Four cells: the three rows of A and b as a column, for one Table 1 column."""
    rows = [" ".join(_f(x, "{:.3f}") for x in row) for row in A]
    return [f"{rows[i]} &#124; {_f(b[i], '{:.3f}')}" for i in range(3)]


def _zhao_md(s: ZhaoSummary, settings: StudySettings) -> list[str]:
    by_name = {m.name: m for m in s.methods}
    columns = [("true", zhao.TRUE_A, zhao.TRUE_B_G)]
    columns += [(f"{ZHAO_LABELS[m.name]} (ours)", m.A_mean, m.b_mean) for m in s.methods]
    paper = {
        "ckf": (zhao.PAPER_CKF_A, zhao.PAPER_CKF_B_G),
        "two-step": (zhao.PAPER_TWO_STEP_A, zhao.PAPER_TWO_STEP_B_G),
    }
    columns += [(f"{ZHAO_LABELS[n]} (paper)", *paper[n]) for n in by_name]
    cells = [_matrix_cells(np.asarray(A).tolist(), np.asarray(b).tolist()) for _, A, b in columns]
    lines = [
        "## Zhao et al., Table 1: CKF and TWO-STEP",
        "",
        f"{s.runs} runs (seeds {_seed_range(settings, 'zhao-table1')}) of the paper's "
        f"simulation, {s.samples} samples each (`magcal_evaluation.study.zhao`: σ = "
        f"{zhao.NOISE_SIGMA_G} G, field {zhao.field_norm_g():.3f} G, the true A and b of "
        "their Table 1; the sample count is ours, the paper gives none). magcal's CKF "
        "(`CubatureCalibrator`, sample by sample, started from the sphere of the first "
        "samples) and TWO-STEP, both given σ as the paper's filter is. Mean estimates, each "
        "row `A` row &#124; `b` component (gauss); the paper's columns are their Table 1 "
        "(its text lost the column heads: the order true, CKF, TWO-STEP is assumed):",
        "",
        "| | " + " | ".join(name for name, *_ in columns) + " |",
        "|---|" + "---|" * len(columns),
    ]
    for i in range(3):
        lines.append(f"| row {i + 1} | " + " | ".join(c[i] for c in cells) + " |")
    lines += [
        "",
        "| estimator | runs finished | failed | max \\|mean − true\\| of A | of b [G] | "
        "std over runs, A (max) | b (max) [G] | s per run (median) | µs per sample |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for m in s.methods:
        lines.append(
            f"| {ZHAO_LABELS[m.name]} | {m.ok} | {m.failed} | {_f(m.A_mean_max_error, '{:.4f}')} "
            f"| {_f(m.b_mean_max_error, '{:.4f}')} | {_f(float(np.max(m.A_std)), '{:.4f}')} | "
            f"{_f(float(np.max(m.b_std)), '{:.4f}')} | {_f(m.seconds_median, '{:.3f}')} | "
            f"{_f(1e6 * m.seconds_per_sample_median, '{:.1f}')} |"
        )
    for m in s.methods:
        lines += _reason_lines(f"{ZHAO_LABELS[m.name]}: ", m.reasons)
    lines += [
        "",
        f"![Zhao Figure 1]({ZHAO_FIGURE1_FILE})",
        "",
        "Field norm before and after calibration, first run (their Figure 1).",
        "",
    ]
    return lines


def _comparison_md(rows: tuple[ComparisonRow, ...], settings: StudySettings) -> list[str]:
    lines = [
        "## All methods on the same sessions",
        "",
        f"Each scenario (a preset of `magcal simulate`) with seeds "
        f"{_seed_range(settings, 'comparison')}; every method calibrates the same sessions "
        "through `calibrate(session, method)`. Heading error: the calibration-induced "
        f"heading error (noise-free fields at {quality.HEADING_GRID_SIZE} orientations "
        "covering SO(3), corrected with the estimate, RMS, degrees), over the runs that "
        "calibrated; / floor: median of the per-run ratio to the known-attitude fit. "
        "Refused: the observability checks refused the session (not forced). Time: the "
        "`calibrate` call alone.",
        "",
        f"![comparison]({COMPARISON_FILE})",
        "",
    ]
    for scenario in settings.scenarios:
        mine = [r for r in rows if r.scenario == scenario]
        floor = mine[0].floor_median if mine else math.nan
        lines += [
            f"### {scenario} (known-attitude floor, median: {_f(floor)}°)",
            "",
            "| method | runs | calibrated | exceptions | refused | heading error, median [°] "
            "| 90th percentile [°] | max [°] | / floor | s per run, median |",
            "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
        ]
        for r in mine:
            lines.append(
                f"| {r.method} | {r.runs} | {r.ok} | {r.exceptions} | {r.refused} | "
                f"{_f(r.heading_median)} | {_f(r.heading_p90)} | {_f(r.heading_max)} | "
                f"{_f(r.ratio_median, '{:.2f}')} | {_f(r.seconds_median, '{:.3f}')} |"
            )
        lines.append("")
        for r in mine:
            lines += _reason_lines(f"{r.method}: ", r.reasons)
        if any(r.reasons for r in mine):
            lines.append("")
    return lines


def render_markdown(summary: StudySummary, meta: dict) -> str:
    """``summary.md``. meta: command, date, wall_s (this invocation), runs_now, runs_before,
    jobs, cores, build, notes (list of str)."""
    st = summary.settings
    lines = [
        "# magcal study: the papers' experiments",
        "",
        f"Made by `{meta['command']}` on {meta['date']}; {meta['build']}. "
        f"{summary.runs} runs, {summary.failed} failed, {summary.seconds_runs:.0f} s of "
        f"runs in all (the runs' own times added up); this call ran {meta['runs_now']} of them "
        f"in {meta['wall_s']:.0f} s wall time with {meta['jobs']} jobs on {meta['cores']} cores"
        + (f", {meta['runs_before']} resumed from `runs.jsonl`" if meta["runs_before"] else "")
        + ".",
        "",
        f"Settings (`settings.json`): experiments {', '.join(st.experiments)}; runs {st.runs}"
        f" (Zhao: {st.zhao_runs}); first seed {st.seed}; methods "
        f"{', '.join(st.methods) or '–'}; scenarios {', '.join(st.scenarios) or '–'}. Every "
        "run's numbers are in `runs.jsonl`.",
        "",
    ]
    for note in meta.get("notes", []):
        lines.append(f"- Note: {note}")
    if meta.get("notes"):
        lines.append("")
    if summary.figure8 is not None:
        lines += _figure8_md(summary.figure8, st)
    if summary.zhao is not None:
        lines += _zhao_md(summary.zhao, st)
    if summary.comparison:
        lines += _comparison_md(summary.comparison, st)
    return "\n".join(lines).rstrip() + "\n"


# --------------------------------------------------------------------------------------------
# Figures


def write_figures(folder: Path, summary: StudySummary, records: list[dict]) -> list[Path]:
    """The study's PNGs in ``folder`` (those its experiments have data for)."""
    out = []
    st = summary.settings
    by_key = sorted(records, key=lambda r: r["key"])
    if summary.figure8 is not None and summary.figure8.ekf_compared:
        both = [
            _result(r)
            for r in by_key
            if r["experiment"] == "figure8"
            and _result(r).get("ekf_init_deg") is not None
            and _result(r).get("ekf_ml_deg") is not None
        ]
        out.append(
            plots.plot_heading_rmse_histograms(
                np.array([r["ekf_init_deg"] for r in both]),
                np.array([r["ekf_ml_deg"] for r in both]),
                folder / FIGURE8_FILE,
            )
        )
    if summary.zhao is not None:
        first = [
            _result(r)
            for r in by_key
            if r["experiment"] == "zhao-table1" and r["params"].get("traces")
        ]
        if first and "norm_raw" in first[0]:
            series = {"raw": np.array(first[0]["norm_raw"])}
            for name, label in ZHAO_LABELS.items():
                part = first[0].get(name) or {}
                if "norm" in part:
                    series[label] = np.array(part["norm"])
            out.append(
                plots.plot_norm_series(
                    series,
                    zhao.field_norm_g(),
                    folder / ZHAO_FIGURE1_FILE,
                    unit="G",
                    title="Field norm before and after calibration (Zhao et al. Figure 1; "
                    f"first run, seed {st.seed})",
                )
            )
    if summary.comparison:
        errors: dict[str, dict[str, np.ndarray]] = {}
        for scenario in st.scenarios:
            errors[scenario] = {}
            for method in st.methods:
                errors[scenario][method] = np.array(
                    [
                        _result(r)["heading_deg"]
                        for r in by_key
                        if r["experiment"] == "comparison"
                        and r["params"]["scenario"] == scenario
                        and r["params"]["method"] == method
                        and not _failed(r)
                    ],
                    dtype=float,
                )
        out.append(plots.plot_heading_error_comparison(errors, folder / COMPARISON_FILE))
    return out
