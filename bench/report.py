# SPDX-License-Identifier: Apache-2.0
"""Text output of bench/run_bench.py: the table of one run and the headline figures of
several results files side by side (``--show``).

Everything printed is read from the results dictionary (the JSON ``--out`` writes): the
preset, seed, stage order, comparison runs and target bounds are the ones the run recorded,
so an older file prints as it was measured. No numpy here: run_bench imports this module
before its workers set their single-thread environment.
"""

from __future__ import annotations

import json
from pathlib import Path


def _pf(ok: bool) -> str:
    return "PASS" if ok else "FAIL"


def _fmt(value, fmt: str) -> str:
    return "-" if value is None else fmt.format(value)


def _target(row: dict, unit: str = "") -> str:
    """A row of ``results["targets"]`` as "target <= 10 s  PASS"."""
    return f"target {row['target']}{unit}  {_pf(row['pass'])}"


def _format_compare(cmp_: dict, tg: dict) -> list[str]:
    """Section 3: the first seed in detail, then one line per seed and the medians."""
    d = cmp_["per_seed"][0]
    out = [
        f"3. Exact vs numeric gradient, {cmp_['duration_s']:g} s sessions, seeds "
        + ", ".join(str(s) for s in cmp_["seeds"])
        + "; each pair from the same θ₀",
        f"   seed {d['seed']} in detail ({d['samples']:,} samples; shared init "
        f"{d['init_s']:.2f} s, its imports excluded):",
        f"   {'':<34}" + "".join(f"{k:>16}" for k in d["runs"]),
    ]
    cols = list(d["runs"].values())
    for label, key, fmt in (
        ("ML wall (s)", "wall_s", "{:.2f}"),
        ("ML CPU time (s)", "cpu_s", "{:.2f}"),
        ("iterations", "iterations", "{}"),
        ("cost evaluations", "cost_evaluations", "{}"),
        ("gradient evaluations", "gradient_evaluations", "{}"),
        ("final cost (with prior)", "final_cost", "{:.6f}"),
        ("final V(θ) (no prior)", "final_cost_without_prior", "{:.6f}"),
        ("stopping rule", "stopping_rule", "{}"),
        ("max |exact grad| at end (scaled)", "max_scaled_exact_gradient_at_end", "{:.2e}"),
    ):
        cells = ["-" if c is None else _fmt(c[key], fmt) for c in cols]
        out.append(f"   {label:<34}" + "".join(f"{c:>16}" for c in cells))
    t_e, t_n = d["gradient_evaluation_exact_s"], d["gradient_evaluation_numeric_s"]
    out += [
        f"   {'one gradient evaluation':<34}{_fmt(t_e and 1e3 * t_e, '{:.1f} ms'):>16}"
        f"{_fmt(t_n and 1e3 * t_n, '{:.1f} ms'):>16}   "
        f"ratio {_fmt(d['speedup_per_gradient_evaluation'], '{:.1f}')} x",
        f"   {'final cost difference':<34}{d['final_cost_abs_diff']:.2e} nats, relative "
        f"{d['final_cost_rel_diff']:.2e}",
        f"   {'max parameter difference':<34}{d['max_param_diff_sigma']:.2e} σ "
        "(each parameter's rough 1-σ uncertainty)",
        f"   {'finite-difference gradient error':<34}"
        + _fmt(d["max_scaled_fd_gradient_error_at_optimum"], "{:.2e}")
        + f" (scaled, at the exact optimum; gradient rule < {d['gradient_tol']:g})",
        f"   {'speed-up, ML step':<34}{d['speedup_ml']:.1f} x (CPU time {d['speedup_ml_cpu']:.1f}"
        f" x; incl. shared init {d['speedup_with_init']:.1f} x)",
        f"   {'seed':>6}{'samples':>9}{'speed-up':>10}{'per eval':>10}"
        f"{'iters e/n':>11}{'evals e/n':>11}{'rules e/n':>19}{'cost rel diff':>15}",
    ]
    for r in cmp_["per_seed"]:
        e, n = r["runs"]["exact"], r["runs"]["numeric"]
        out.append(
            f"   {r['seed']:>6}{r['samples']:>9,}{r['speedup_ml']:>9.1f}x"
            f"{_fmt(r['speedup_per_gradient_evaluation'], '{:.1f}x'):>10}"
            f"{e['iterations']:>6}/{n['iterations']:<4}"
            f"{e['gradient_evaluations']:>6}/{n['gradient_evaluations']:<4}"
            f"{e['stopping_rule'] + '/' + n['stopping_rule']:>19}"
            f"{r['final_cost_rel_diff']:>15.2e}"
        )
    out += [
        f"   {'speed-up, ML step, median':<34}{cmp_['speedup_ml_median']:8.1f} x  "
        + _target(tg["speedup_ml_median"], " x"),
        f"   {'  per gradient evaluation':<34}"
        f"{_fmt(cmp_['speedup_per_gradient_evaluation_median'], '{:8.1f}')} x",
        f"   {'final cost rel. difference, max':<34}{cmp_['final_cost_rel_diff_max']:8.1e}    "
        + _target(tg["final_cost_rel_diff_max"]),
    ]
    return out


def _format_imports(imp: dict, cal: dict) -> list[str]:
    """The cold imports (section 1's last lines); none for results measured before they were
    broken down."""
    if "numpy_s" not in imp:
        return []
    loaded = [name for name, present in imp["loaded"].items() if present]
    absent = [name for name, present in imp["loaded"].items() if not present]
    during = cal["imported_during_calibrate"]
    return [
        f"   imports in a fresh process: numpy {imp['numpy_s']:.2f} s, "
        # Results measured when the pipeline still imported scipy time it on its own.
        + (f"scipy {imp['scipy_s']:.2f} s, " if "scipy_s" in imp else "")
        + f"clarabel {imp['clarabel_s']:.2f} s, the rest of the "
        f"pipeline {imp['magcal_pipeline_s']:.2f} s (total {imp['total_s']:.2f} s)",
        f"   the pipeline loads {', '.join(loaded) or 'none of them'}"
        + (f"; not {', '.join(absent)}" if absent else "")
        + "; first imported inside calibrate: "
        + (", ".join(during) if during else "nothing"),
    ]


def _optimizer_row(label: str, c: dict, names: list[str]) -> str:
    """One case of section 7: per optimiser iterations, Fisher-information and gradient
    evaluations, the stopping rule and the ML step's seconds; the final costs' difference."""
    cells = []
    for name in names:
        r = c["runs"][name]
        if "error" in r:
            cells.append(f"{'failed (' + r['error'].split(':')[0] + ')':>37}")
            continue
        rule = r["stopping_rule"] + ("*" if r["forced"] else "")
        cells.append(
            f"{r['iterations']:>6}{r['information_evaluations']:>5}"
            f"{r['gradient_evaluations']:>6}{rule:>13}{r['ml_s']:>7.2f}"
        )
    diff = c["final_cost_diff"]
    return (
        f"   {label:<29}{c['samples']:>8,}"
        + "".join(f"  {cell}" for cell in cells)
        + f"{_fmt(diff, '{:+.2e}'):>10}"
    )


def _format_optimizers(opt: dict) -> list[str]:
    """Section 7: both optimisers per case, their medians over the real recordings, the cold
    command lines."""
    names = list(opt["simulated"]["runs"])
    columns = f"{'iters':>6}{'info':>5}{'grads':>6}{'rule':>13}{'ML s':>7}"
    out = [
        "",
        "7. The ML step's optimisers, calibrate(session, 'ml', optimizer=...) in one process",
        f"   {'':<37}" + "".join(f"  {name:^37}" for name in names).rstrip(),
        f"   {'case':<29}{'samples':>8}" + "".join(f"  {columns}" for _ in names) + "     Δcost",
        _optimizer_row(opt["simulated"]["case"], opt["simulated"], names),
    ]
    for c in opt["real"]:
        out.append(
            _optimizer_row(c["case"] + ("" if c["form"] == "session" else " (mr)"), c, names)
        )
    if opt["real_skipped"]:
        out.append(f"   real recordings: {opt['real_skipped']}")
    summary = opt.get("real_summary")
    if summary:
        for name in names:
            s = summary[name]
            failed = f", failed on {', '.join(s['failed'])}" if s["failed"] else ""
            out.append(
                f"   {name + ', real, median':<29}{s['median_iterations']:>8g} iterations, "
                f"{s['median_information_evaluations']:g} information and "
                f"{s['median_gradient_evaluations']:g} gradient evaluations, ML "
                f"{s['median_ml_s']:.2f} s (total {s['total_ml_s']:.1f} s); "
                f"{s['converged']}/{s['finished']} converged{failed}"
            )
        out.append(
            f"   Δcost = trust-region − bfgs final cost (nats), real: "
            f"{_fmt(summary['final_cost_diff_min'], '{:+.2e}')} to "
            f"{_fmt(summary['final_cost_diff_max'], '{:+.2e}')}; * forced past refusing checks, "
            "(mr) multi-rate session"
        )
    cli = opt["cli"]
    out.append(f"   cold whole process, host/magcal, 1 thread, median of {cli['reps']}:")
    for r in cli["calibrate"].values():
        cells = ", ".join(
            f"{name} {r[name]['median_s']:.2f} s"
            + ("" if set(r[name]["exit_codes"]) == {0} else f" (exit {r[name]['exit_codes']})")
            for name in names
        )
        out.append(f"   {'  calibrate ' + r['session']:<44}{cells}")
    out.append(f"   {'  --help':<44}{cli['help']['median_s']:.2f} s")
    return out


def format_table(res: dict) -> str:
    """The table ``run_bench.py`` prints: one section per measurement."""
    m, cal, mem = res["machine"], res["calibration"], res["memory"]
    cmp_, scal, tg = res["exact_vs_numeric"], res["scaling"], res["targets"]
    commit = (res["git"]["commit"] or "unknown")[:10]
    modified = res["git"].get("host_modified") or []
    dirty = f" + uncommitted changes to {', '.join(modified)}" if modified else ""
    pin = f"pinned to CPU {m['pinned_cpu']}" if m["pinned_cpu"] is not None else "not pinned"
    load = m["loadavg_at_start"]
    load_txt = f", load {load[0]:.2f} at start" if load else ""
    out = [
        f"magcal benchmark, {res['date']}, commit {commit}{dirty}",
        f"machine: {m['cpu_model']}, {m['cpu_count']} cores ({pin}, 1 thread){load_txt}",
        f"Python {m['python']}, numpy {m['numpy']}; preset '{res['config']['preset']}', "
        f"seed {res['config']['seed']}",
        "",
        f"1. Full ML calibration (pipeline.calibrate), {cal['samples']:,} samples, cold "
        f"process, median of {cal['runs']}",
        f"   {'total wall':<34}{cal['wall_s']:8.2f} s   " + _target(tg["calibration_wall_s"], " s"),
        f"   {'  all runs':<34}{', '.join(f'{w:.2f}' for w in cal['wall_all_s']):>8} s",
        f"   {'  CPU time (user+sys)':<34}{cal['cpu_s']:8.2f} s",
    ]
    labels = {
        "checks": "observability checks",
        "noise": "init: stationary, bias, noise",
        "ellipsoid": "init: ellipsoid SDP",
        "alignment": "init: alignment (R_D, m_z)",
        "ml": "ML optimisation",
        "diagnostics": "diagnostics",
    }
    for k, seconds in cal["stages_s"].items():  # in the pipeline's order (run_bench.STAGES)
        out.append(f"   {'  ' + labels.get(k, k):<34}{seconds:8.2f} s")
    opt = cal["optimizer"]
    out += [
        f"   {'  (init total)':<34}{cal['init_s']:8.2f} s",
        f"   optimiser: {opt['iterations']} iterations, {opt['gradient_evaluations']} "
        f"cost+gradient evaluations, stopped on '{opt['stopping_rule']}', "
        f"final cost {opt['final_cost']:.6f}",
        f"   not in the total: import magcal {cal['import_s']:.2f} s, simulation "
        f"{cal['simulate_s']:.2f} s; whole process {cal['process_wall_s']:.2f} s",
    ]
    out += _format_imports(res["imports"], cal)
    if cal["warm_wall_s"] is not None:
        out.append(
            f"   warm (second calibration, same process): {cal['warm_wall_s']:.2f} s, "
            f"ellipsoid {cal['warm_stages_s']['ellipsoid']:.2f} s"
        )
    out += [
        "",
        "2. Peak memory of the calibration process",
        f"   {'max RSS':<34}{mem['peak_rss_mb']:8.0f} MB  " + _target(tg["peak_rss_mb"], " MB"),
        f"   {'  of which before calibrate':<34}{mem['peak_rss_before_calibrate_mb']:8.0f} MB",
        "",
    ]
    out += _format_compare(cmp_, tg)
    out += [
        "",
        "4. One evaluation at θ₀ (median), time per sample, memory",
        f"   {'samples':>9}{'cost+grad':>12}{'cost':>10}{'ratio':>7}{'cg ns/smp':>11}"
        f"{'c ns/smp':>10}{'tape':>10}{'alloc/eval':>12}{'data':>9}",
    ]
    for r in scal["rows"]:
        out.append(
            f"   {r['samples']:>9,}{r['cost_grad_s'] * 1e3:>9.1f} ms{r['cost_s'] * 1e3:>7.1f} ms"
            f"{r['grad_over_cost']:>7.2f}{r['cost_grad_ns_per_sample']:>11.0f}"
            f"{r['cost_ns_per_sample']:>10.0f}{r['tape_mb']:>7.1f} MB"
            f"{r['cost_grad_alloc_mb']:>9.1f} MB{r['data_mb']:>6.1f} MB"
        )
    if scal["loglog_slope_cost_grad"] is not None:
        out.append(
            f"   log-log slope of cost+gradient time vs samples: "
            f"{scal['loglog_slope_cost_grad']:.3f} (1 = linear)"
        )
    ckf = res.get("ckf")  # results of builds without the CKF section have none
    if ckf is not None:
        out += [
            "",
            f"5. CKF (Zhao et al.), time per sample on {ckf['samples']:,} samples, median",
            f"   {'filter step (update_many)':<34}{ckf['step_us_per_sample']:8.1f} µs",
            f"   {'update() with estimate + P':<34}{ckf['update_us_per_sample']:8.1f} µs",
            f"   {'live, as collect runs it':<34}{ckf['live_us_per_sample']:8.1f} µs per reading",
            f"   {'whole session, --method ckf filter':<34}{ckf['run_ckf_s']:8.2f} s "
            f"({ckf['run_ckf_order']} order); TWO-STEP {ckf['two_step_s']:.2f} s",
            f"   {'filter state':<34}{ckf['filter_state_bytes']:8d} bytes, whatever the samples",
        ]
    logs = res.get("log_import")  # results of builds without it have none
    if logs is not None and logs.get("logs"):
        out += ["", "6. magcal import of the largest real flight log of each format, median"]
        for kind, r in logs["logs"].items():
            out.append(
                f"   {kind:<10}{r['file']:<32}{r['size_mb']:6.1f} MB {r['seconds']:7.2f} s "
                f"{r['mb_per_s']:7.1f} MB/s"
            )
    if res.get("optimizers") is not None:  # results of builds without it have none
        out += _format_optimizers(res["optimizers"])
    out += ["", f"benchmark took {res['bench_wall_s']:.0f} s"]
    return "\n".join(out)


#: Headline figures for ``--show``: (label, path into the results, format).
HEADLINE = (
    ("commit", ("git", "commit"), "{:.10}"),
    ("date", ("date",), "{:.10}"),
    ("cores", ("machine", "cpu_count"), "{}"),
    ("calibration wall (s)", ("calibration", "wall_s"), "{:.2f}"),
    ("  init (s)", ("calibration", "init_s"), "{:.2f}"),
    ("  ML (s)", ("calibration", "stages_s", "ml"), "{:.2f}"),
    ("  iterations", ("calibration", "optimizer", "iterations"), "{}"),
    ("peak RSS (MB)", ("memory", "peak_rss_mb"), "{:.0f}"),
    ("numeric/exact speed-up", ("exact_vs_numeric", "speedup_ml_median"), "{:.1f}"),
    (
        "  per gradient eval.",
        ("exact_vs_numeric", "speedup_per_gradient_evaluation_median"),
        "{:.1f}",
    ),
    ("final cost rel. diff", ("exact_vs_numeric", "final_cost_rel_diff_max"), "{:.1e}"),
    ("cost+grad slope", ("scaling", "loglog_slope_cost_grad"), "{:.3f}"),
    ("CKF step (µs/sample)", ("ckf", "step_us_per_sample"), "{:.1f}"),
    ("log import (MB/s)", ("log_import", "largest", "mb_per_s"), "{:.1f}"),
    ("ML iters, real, bfgs", ("optimizers", "real_summary", "bfgs", "median_iterations"), "{}"),
    (
        "  trust-region",
        ("optimizers", "real_summary", "trust-region", "median_iterations"),
        "{}",
    ),
    (
        "cold calibrate broad35",
        ("optimizers", "cli", "calibrate", "broad35_magnet4cm", "bfgs", "median_s"),
        "{:.2f}",
    ),
    (
        "  trust-region",
        ("optimizers", "cli", "calibrate", "broad35_magnet4cm", "trust-region", "median_s"),
        "{:.2f}",
    ),
    ("magcal --help (s)", ("optimizers", "cli", "help", "median_s"), "{:.2f}"),
)


def _get(d: dict, path: tuple[str, ...]):
    for key in path:
        if not isinstance(d, dict) or key not in d:
            return None
        d = d[key]
    return d


def format_headlines(files: list[str]) -> str:
    """One column per results file, for comparing runs over time."""
    docs = [json.loads(Path(f).read_text()) for f in files]
    lines = [f"{'':<26}" + "".join(f"{Path(f).name[:16]:>18}" for f in files)]
    for label, path, fmt in HEADLINE:
        cells = []
        for d in docs:
            v = _get(d, path)
            cells.append("-" if v is None else fmt.format(v))
        lines.append(f"{label:<26}" + "".join(f"{c:>18}" for c in cells))
    for d_i, d in enumerate(docs):
        for r in _get(d, ("scaling", "rows")) or []:
            lines.append(
                f"file {d_i + 1}: {r['samples']:>9,} samples  cost+grad "
                f"{r['cost_grad_s'] * 1e3:8.1f} ms  ({r['cost_grad_ns_per_sample']:.0f} ns/sample)"
            )
    return "\n".join(lines)
