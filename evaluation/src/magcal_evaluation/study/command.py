# SPDX-License-Identifier: Apache-2.0
"""``magcal study OUTDIR``: the papers' experiments, resumable (see
:mod:`magcal_evaluation.study`).

magcal's command line finds this module through the entry-point group ``magcal.commands``
(evaluation/pyproject.toml) and calls :func:`add_parser`."""

from __future__ import annotations

import argparse
import os
import shlex
import sys

from magcal.commands.common import positive


def _names(text: str) -> tuple[str, ...]:
    names = tuple(n.strip() for n in text.split(",") if n.strip())
    if not names:
        raise argparse.ArgumentTypeError("give at least one name")
    return names


def _non_negative_int(text: str) -> int:
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not an integer") from None
    if v < 0:
        raise argparse.ArgumentTypeError(f"{text} must be ≥ 0")
    return v


def available_cpus() -> int:
    """CPUs this process may run on: its affinity mask where the platform has one (Linux;
    a container's or ``taskset``'s limit, unlike ``os.cpu_count()``, the machine's), else
    the machine's count."""
    try:
        return max(len(os.sched_getaffinity(0)), 1)
    except (AttributeError, OSError):
        return os.cpu_count() or 1


def add_parser(sub) -> None:
    p = sub.add_parser(
        "study",
        help="the papers' experiments (Kok & Schön Figure 8, Zhao Table 1, every method "
        "compared): PNGs and summary.md; interrupt and rerun to resume",
        description="Rerun the papers' experiments on seeded simulations: Kok & Schön's "
        "Figure 8 (the EKF's heading error with the initial and the ML estimates, Table 2 "
        "settings), Zhao et al.'s Table 1 and Figure 1 (their cubature Kalman filter against "
        "TWO-STEP), and init, ML, CKF and TWO-STEP compared on the same scenarios (heading "
        "error, time per run, refusals with their reasons). Writes summary.md and PNG figures "
        "to OUTDIR. Every finished run is appended to OUTDIR/runs.jsonl: interrupt with Ctrl-C "
        "and run the same command again to resume. A run depends only on its experiment, "
        "scenario, method and seed, so neither --jobs nor an interruption changes a figure.",
        epilog="examples:\n"
        "  magcal study out/study\n"
        "  magcal study out/quick --runs 10 --zhao-runs 5 --scenarios table2,mems\n"
        "  magcal study out/figure8 --experiments figure8 --runs 50 --jobs 1",
    )
    p.add_argument("outdir", help="study folder (created; rerun with it to resume)")
    p.add_argument(
        "--runs",
        type=positive(int),
        default=150,
        metavar="N",
        help="runs of Figure 8 and per scenario and method of the comparison (default 150)",
    )
    p.add_argument(
        "--zhao-runs",
        type=positive(int),
        default=50,
        metavar="N",
        help="runs of Zhao Table 1 (default 50)",
    )
    p.add_argument(
        "--experiments",
        type=_names,
        metavar="LIST",
        help="comma-separated subset of figure8,zhao-table1,comparison (default: every one "
        "this build can run)",
    )
    p.add_argument(
        "--scenarios",
        type=_names,
        metavar="LIST",
        help="the comparison's scenarios, presets of `magcal simulate` (default "
        "table2,mems,handheld,raw-counts)",
    )
    p.add_argument(
        "--seed",
        type=_non_negative_int,
        default=1,
        metavar="N",
        help="first seed; run i uses seed + i",
    )
    p.add_argument(
        "--jobs",
        type=positive(int),
        default=available_cpus(),
        metavar="N",
        help="worker processes (default: every CPU this process may use)",
    )
    p.set_defaults(run=run)


def _command(args, settings) -> str:
    """The command that resumes this study (every setting spelled out)."""
    parts = [
        "magcal study",
        shlex.quote(str(args.outdir)),
        f"--runs {settings.runs}",
        f"--zhao-runs {settings.zhao_runs}",
        f"--experiments {','.join(settings.experiments)}",
    ]
    if settings.scenarios:  # none without the comparison
        parts.append(f"--scenarios {','.join(settings.scenarios)}")
    parts += [f"--seed {settings.seed}", f"--jobs {args.jobs}"]
    return " ".join(parts)


def run(args, out=None) -> int:
    # Imported here, not at the top: the CLI imports every command module at start-up, and
    # the study's modules (simulation, calibration, plots) take a second to load.
    from magcal_evaluation.study.experiments import DEFAULT_SCENARIOS
    from magcal_evaluation.study.run import make_settings, run_study

    out = out or sys.stdout
    settings, notes = make_settings(
        runs=args.runs,
        zhao_runs=args.zhao_runs,
        seed=args.seed,
        experiments=args.experiments,
        scenarios=args.scenarios or DEFAULT_SCENARIOS,
    )
    for note in notes:
        print(f"magcal study: {note}", file=sys.stderr)
    outcome = run_study(
        args.outdir, settings, jobs=args.jobs, notes=notes, command=_command(args, settings)
    )
    for path in outcome.files:
        print(f"wrote {path}", file=out)
    print(
        f"{outcome.summary.runs} runs ({outcome.runs_now} now, {outcome.runs_before} resumed), "
        f"{outcome.summary.failed} failed, {outcome.wall_s:.0f} s",
        file=out,
    )
    return 0
