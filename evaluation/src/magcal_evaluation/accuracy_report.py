#!/usr/bin/env python3
# SPDX-License-Identifier: Apache-2.0
"""The accuracy report: every accuracy check over seeded runs, `make accuracy`.

    python -m magcal_evaluation.accuracy_report --runs 20 --table2-runs 150 \\
        --out bench/accuracy.md --plots out/accuracy --figure8 bench/figure8.png

Runs every check of :mod:`magcal_evaluation.accuracy` over seeds 1..N (N = --runs, or
--table2-runs for Table 2) in --workers processes, prints one line per run to stderr, and
writes a Markdown report (the command, date, machine, per-scenario medians, pass/fail per
criterion, failed runs, timings), Figure 8 of the Table 2 runs (--figure8, by default
``figure8.png`` under --plots) and the raw per-run numbers (``runs.json`` under --plots).
Exits 1 when a check fails its bound (after writing).

A report needs at least 20 runs per check (:data:`MIN_RUNS`). Fewer, or the --quick
variants, are refused unless --exploratory is given; such a report is headed EXPLORATORY.
"""

from __future__ import annotations

import os

# One BLAS thread per worker process: the workers already use the cores, and oversubscribed
# BLAS threads only slow the small matrix products down. Set before numpy is imported.
for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import datetime  # noqa: E402
import json  # noqa: E402
import multiprocessing  # noqa: E402
import platform  # noqa: E402
import shlex  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

from magcal.calib.diagnostics import quality  # noqa: E402
from magcal.report.plots import plot_heading_rmse_histograms  # noqa: E402
from magcal_evaluation import REPO_ROOT, accuracy  # noqa: E402

#: Rough seconds per run, to start the long runs first so both workers finish together.
_COST_ESTIMATE_S = {
    "scale": 5.0,
    "mems-acc": 3.0,
    "small-noise": 2.0,
    "handheld": 1.5,
    "mems": 1.5,
    "table2": 0.5,
    "noise-free": 0.3,
}

#: Every check over at least this many seeded runs (Table 2 included).
MIN_RUNS = 20

GIT_TIMEOUT_S = 10.0


def _task(args: tuple[str, int, bool]) -> tuple[str, dict]:
    key, seed, quick = args
    return key, accuracy.run_check(key, seed, quick)


def _progress_line(i: int, total: int, key: str, run: dict) -> str:
    head = f"[{i:>4}/{total}] {key:<11} seed {run['seed']:>3}: "
    if run.get("error"):
        return head + f"FAILED {run['error'][:150]}"
    parts = []
    for name, fmt in (
        ("ratio", "ML/floor {:.2f}"),
        ("ratio_raw", "raw ML/floor {:.2f}"),
        ("ratio_unit", "unit {:.2f}"),
        ("ml_deg", "ML {:.3g}°"),
        ("sym_deg", "sym {:.3g}°"),
        ("rel_DDt", "rel DDᵀ {:.1e}"),
        ("rel_D", "rel D {:.1e}"),
        ("rel_o", "rel o {:.1e}"),
    ):
        if run.get(name) is not None:
            parts.append(fmt.format(run[name]))
    if run.get("forced"):
        parts.append("FORCED (observability refused)")
    if run.get("alignment_warning"):
        parts.append("alignment warning")
    return head + ", ".join(parts) + f" ({run['seconds']:.1f} s)"


def _git(*args: str) -> str | None:
    """``git *args`` in the repository: its stdout, or None if git is missing or fails. The
    same helper as in bench/run_bench.py (evaluation/ and bench/ import nothing from each other):
    keep the two identical."""
    try:
        proc = subprocess.run(
            ["git", *args],
            cwd=REPO_ROOT,
            capture_output=True,
            text=True,
            timeout=GIT_TIMEOUT_S,
            check=False,
        )
    except (OSError, subprocess.TimeoutExpired):
        return None
    return proc.stdout.strip() if proc.returncode == 0 else None


def _git_description() -> str:
    """The commit, and whether the code under host/ differs from it (as bench/ records)."""
    commit = _git("rev-parse", "--short", "HEAD")
    status = _git("status", "--porcelain", "--", "host")
    if commit is None or status is None:
        return "unknown commit"
    return commit + (" with uncommitted changes under host/" if status else "")


def run_record(module: str, argv: list[str] | None, workers: int, commit_at_start: str) -> dict:
    """What every report says of its run: the command that reproduces it, the date, the
    machine, and the code (``commit_at_start``, flagged when the tree changed meanwhile)."""
    now = _git_description()
    return {
        "command": f"python -m {module} "
        + " ".join(shlex.quote(a) for a in (sys.argv[1:] if argv is None else argv)),
        "date": datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC"),
        "cores": os.cpu_count(),
        "workers": workers,
        "python": platform.python_version(),
        "commit": commit_at_start
        + ("" if now == commit_at_start else f" (the tree changed to {now} during the run: rerun)"),
    }


def _f(x: float, fmt: str = "{:.3g}") -> str:
    return "–" if x is None or not np.isfinite(x) else fmt.format(x)


def _status(v: accuracy.Verdict) -> str:
    return "**pass**" if v.passed else "**FAIL**"


def render_markdown(verdicts: list[accuracy.Verdict], meta: dict) -> str:
    """The report; ``meta["exploratory"]`` (a reason, or None) heads it EXPLORATORY."""
    lines = ["# magcal accuracy report", ""]
    if meta.get("exploratory"):
        lines = [
            "# EXPLORATORY magcal accuracy report",
            "",
            f"**EXPLORATORY: {meta['exploratory']}. This is not a full accuracy report "
            f"(at least {MIN_RUNS} runs per check, full-size sessions): do not quote its "
            "verdicts as results.**",
            "",
        ]
    lines += [
        f"Generated by `{meta['command']}`",
        f"on {meta['date']} in {meta['wall_min']:.1f} min wall time; machine: "
        f"{meta['cores']} cores ({meta['workers']} worker processes), Python "
        f"{meta['python']}, magcal at {meta['commit']}.",
        "",
        "Every figure is a median over seeded simulations (seeds 1..N, fixed, never chosen "
        "by outcome). *Heading error*: the calibration-induced heading error — "
        f"noise-free fields at {quality.HEADING_GRID_SIZE} orientations covering SO(3), "
        "corrected with the estimate, rotated back with the true attitude, RMS of their "
        "heading, in degrees. *Floor*: the known-attitude least-squares fit of the same "
        "session. *Symmetric fit*: `(D̃D̃ᵀ)^½` and the ellipsoid's centre (no misalignment). "
        "Relative errors: `‖D̂ − D‖_F/‖D‖_F` and `‖ô − o‖/‖D‖₂` (see "
        "`magcal_evaluation.accuracy` for why the offset is divided by the field size).",
        "",
        "## Summary",
        "",
        "| check | runs | result | bound | failed runs (exception / beyond bound) | "
        "forced | s per run, median (max) | ML iterations, median (max); not converged |",
        "|---|---:|---|---|---:|---:|---:|---:|",
    ]
    for v in verdicts:
        iterations = (
            "–"
            if not np.isfinite(v.ml_iterations_median)
            else f"{v.ml_iterations_median:.0f} ({v.ml_iterations_max:.0f}); {v.ml_not_converged}"
        )
        lines.append(
            f"| {v.title} | {v.n_runs} | {_status(v)} | {v.bound} | {v.n_errors} / "
            f"{v.n_over_bound - v.n_errors} | {v.n_forced} | "
            f"{_f(v.seconds_median, '{:.2f}')} ({_f(v.seconds_max, '{:.2f}')}) | {iterations} |"
        )
    lines += [
        "",
        "`beyond bound` counts single runs beyond the check's bound (for the ratio checks: "
        "per-run ML/floor; Table 2: ML worse than init; hand-held: ML worse than the "
        "symmetric fit). Whether such runs fail the check depends on the check, as its "
        "criteria below say. Every check fails if any run raises or is refused by the "
        "observability check. Beyond that, the ratio, scale, noise-free and small-noise "
        "checks are judged on medians, so a run beyond the bound is "
        "counted but does not fail them. Table 2 is judged on medians (ML < init, Figure 8) "
        "and also needs the SDP's A positive definite in every run (and the library's "
        "algebraic fit never to return a non-positive-definite A). The hand-held check is "
        "per run: ML no worse than the symmetric fit, and an alignment warning, in every "
        "run. A time is one `calibrate()` call (the scale check: both scales). ML "
        "iterations: the ML step's, over its fits (not the second starting point's, on its "
        "own thread); not converged: runs whose ML stopped on a rule that certifies no "
        "optimum.",
        "",
        "## Heading errors (median RMS, degrees)",
        "",
        "| scenario | runs | floor | init | ML | symmetric fit | ML/floor: median of "
        "per-run ratios | ML/floor: ratio of medians | bound | result |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---|---|",
    ]
    for v in verdicts:
        if not np.isfinite(v.floor):
            continue
        lines.append(
            f"| {v.title} | {v.n_runs} | {_f(v.floor)} | {_f(v.init)} | {_f(v.ml)} | "
            f"{_f(v.sym)} | {_f(v.ratio_median, '{:.2f}')} | "
            f"{_f(v.ratio_of_medians, '{:.2f}')} | {v.bound} | {_status(v)} |"
        )
    lines += ["", "## Criteria", ""]
    for v in verdicts:
        lines += [f"### {v.title}: {_status(v)}", ""]
        lines += ["| criterion | measured | result |", "|---|---|---|"]
        for c in v.criteria:
            res = "info" if c.passed is None else ("pass" if c.passed else "**FAIL**")
            lines.append(f"| {c.text} | {c.measured} | {res} |")
        if v.n_runtime_warning_runs:
            lines.append(
                f"| runs with numpy RuntimeWarnings (overflow etc.) inside calibrate() | "
                f"{v.n_runtime_warning_runs}/{v.n_runs} | info |"
            )
        lines.append("")
        for e in v.errors:
            lines.append(f"- {e}")
        if v.errors:
            lines.append("")
    if meta.get("figure8"):
        lines += [
            "## Figure 8",
            "",
            f"`{meta['figure8']}`: heading RMSE of the calibration EKF run with the initial "
            "and the ML estimates against the true attitude, Table 2 runs (written by the "
            "command above).",
            "",
        ]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        prog=f"python -m {__spec__.name}", description=__doc__.splitlines()[0]
    )
    ap.add_argument("--runs", type=int, default=20, help="seeds per check (default 20)")
    ap.add_argument("--table2-runs", type=int, default=150, help="seeds for Table 2")
    ap.add_argument("--out", default="bench/accuracy.md", help="Markdown report path")
    ap.add_argument("--plots", default="out/accuracy", help="directory for runs.json")
    ap.add_argument(
        "--figure8",
        help="the Figure 8 plot of the Table 2 runs (default: figure8.png in --plots)",
    )
    ap.add_argument("--workers", type=int, default=2, help="processes (default 2)")
    ap.add_argument(
        "--checks",
        default=",".join(accuracy.CHECKS),
        help=f"comma-separated subset of {','.join(accuracy.CHECKS)}",
    )
    ap.add_argument("--quick", action="store_true", help="the quick variants (as the tests)")
    ap.add_argument(
        "--exploratory",
        action="store_true",
        help=f"allow fewer than {MIN_RUNS} runs or --quick; the report is headed EXPLORATORY",
    )
    args = ap.parse_args(argv)
    keys = [k.strip() for k in args.checks.split(",") if k.strip()]
    unknown = [k for k in keys if k not in accuracy.CHECKS]
    if unknown:
        ap.error(f"unknown check(s) {', '.join(unknown)}; known: {', '.join(accuracy.CHECKS)}")
    if args.runs < 1 or args.table2_runs < 1 or args.workers < 1:
        ap.error("--runs, --table2-runs and --workers must be at least 1")
    counts = []  # only of the checks that run
    if any(k != "table2" for k in keys):
        counts.append(("--runs", args.runs))
    if "table2" in keys:
        counts.append(("--table2-runs", args.table2_runs))
    reasons = [f"{name} {n}" for name, n in counts if n < MIN_RUNS]
    reasons += ["--quick"] if args.quick else []
    if reasons and not args.exploratory:
        ap.error(
            f"{', '.join(reasons)}: a report needs at least {MIN_RUNS} full-size runs per "
            "check; add --exploratory for a trial report (it is headed EXPLORATORY)"
        )
    exploratory = (
        "made with " + ", ".join(reasons + ["--exploratory"]) if args.exploratory else None
    )

    tasks = [
        (k, seed, args.quick)
        for k in keys
        for seed in range(1, (args.table2_runs if k == "table2" else args.runs) + 1)
    ]
    tasks.sort(key=lambda t: -_COST_ESTIMATE_S.get(t[0], 1.0))
    runs: dict[str, list[dict]] = {k: [] for k in keys}
    commit_at_start = _git_description()  # the code the workers import (forked below)
    t0 = time.perf_counter()
    with multiprocessing.get_context("fork").Pool(args.workers) as pool:
        for i, (key, run) in enumerate(pool.imap_unordered(_task, tasks), start=1):
            runs[key].append(run)
            print(_progress_line(i, len(tasks), key, run), file=sys.stderr, flush=True)
    wall = time.perf_counter() - t0

    verdicts = [accuracy.verdict(k, runs[k]) for k in keys]
    plots = Path(args.plots)
    plots.mkdir(parents=True, exist_ok=True)
    figure8 = None
    if "table2" in runs:
        t2 = [r for r in runs["table2"] if "ekf_ml_deg" in r and "ekf_init_deg" in r]
        if t2:
            figure8 = plot_heading_rmse_histograms(
                np.array([r["ekf_init_deg"] for r in t2]),
                np.array([r["ekf_ml_deg"] for r in t2]),
                Path(args.figure8) if args.figure8 else plots / "figure8.png",
            )
    with open(plots / "runs.json", "w", encoding="utf-8") as f:
        json.dump(runs, f, indent=1, default=float)
        f.write("\n")

    meta = {
        **run_record(__spec__.name, argv, args.workers, commit_at_start),
        "wall_min": wall / 60.0,
        "figure8": str(figure8) if figure8 else None,
        "exploratory": exploratory,
    }
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(render_markdown(verdicts, meta) + "\n", encoding="utf-8")

    for v in verdicts:
        print(v.describe(), file=sys.stderr)
    print(f"wrote {out} and {plots}/ in {wall / 60.0:.1f} min", file=sys.stderr)
    failed = [v.key for v in verdicts if not v.passed]
    if failed:
        print(f"checks failing their bound: {', '.join(failed)}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
