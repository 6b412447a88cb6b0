#!/usr/bin/env python3
# SPDX-License-Identifier: Apache-2.0
"""magcal benchmark: speed and memory against the product's targets, measured on one core.

    python bench/run_bench.py --out bench/results.json     # what `make bench` runs (~35 s)
    python bench/run_bench.py --show old.json new.json     # headline figures side by side

Seven measurements, each in a fresh subprocess of this script (``--worker NAME``) with
OMP/OPENBLAS/MKL_NUM_THREADS=1 set before numpy is imported and the process pinned to one
CPU with ``os.sched_setaffinity``:

1. ``calibrate``: the full ML calibration (``calibrate.calibrate``: checks, initial estimate,
   ML optimisation, diagnostics) of a simulated 10-minute 100 Hz MEMS session, in a cold
   process as a user gets it. Imports and the simulation are timed but kept out of the
   total. Peak RSS (``ru_maxrss``) is read in the same process, which does nothing else.
2. ``imports``: what a cold process pays before it can calibrate: ``import numpy``, the
   scipy modules the pipeline uses, ``import clarabel`` (the ellipsoid SDP's solver), then
   the rest of ``magcal.calib.calibrate``; and which of the heavy libraries that loads.
3. ``compare``: exact against finite-difference gradients on a shorter session, both ML
   optimisations from the same initial estimate θ₀ in one process.
4. ``scaling``: one cost+gradient and one cost-only evaluation at 6k, 60k and 600k samples.
5. ``ckf``: Zhao et al.'s cubature Kalman filter (``magcal.calib.norm_only.ckf``), time per
   sample: the filter step alone, ``update`` returning the estimate and covariance, the live
   estimate as ``magcal collect`` runs it, and a whole session through ``--method ckf``'s filter and
   through TWO-STEP for comparison.
6. ``log_import``: ``magcal import``'s reading of a flight log (format detection, the
   reader, undoing the on-board correction, pairing, the session of the whole log, not
   written), in MB of log per second: the largest log of each format in the real logs beside
   the checkout (``../shared/reallogs``), else in the committed ones (tests/data/reallogs).
7. ``optimizers``: the ML step's two optimisers (``calibrate(session, "ml",
   optimizer=...)``, bfgs and trust-region) side by side on a simulated 10-minute session and
   on every real recording of ``--realdata`` (``../shared/realdata`` beside the checkout; the
   sessions as ``make real`` builds them), then the cold whole-process wall time of
   ``host/magcal calibrate SESSION -o OUT --optimizer ...`` on one real recording and on the
   simulated session, and of ``magcal --help``.

Progress goes to stderr, the table (formatted by bench/report.py) to stdout, the
machine-readable summary to ``--out``.
Targets are reported as pass/fail, never asserted: timing depends on the machine.
See bench/README.md for what each figure means.
"""

from __future__ import annotations

import argparse
import datetime
import importlib.metadata
import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from dataclasses import asdict, dataclass
from pathlib import Path

# bench/report.py, found because Python puts a script's own directory first on sys.path.
from report import format_headlines, format_table

RESULTS_FORMAT = "magcal-bench/1"
REPO_ROOT = Path(__file__).resolve().parent.parent

#: Environment that keeps numpy's BLAS and any OpenMP pool to one thread. It must be in the
#: environment before numpy is imported, so the workers get it from their parent.
SINGLE_THREAD_ENV = {"OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}

#: One worker must finish within this; a hung worker fails the benchmark rather than `make`.
WORKER_TIMEOUT_S = 900.0
GIT_TIMEOUT_S = 10.0

PRESET = "mems"
SEED = 1
GRADIENT_TIMING_REPS = 5

# The targets: a 10-minute 100 Hz session calibrated within 10 s and 1 GB, exact gradients at
# least 20× faster than finite differences, to the same optimum.
TARGET_CALIBRATION_S = 10.0
TARGET_PEAK_RSS_MB = 1024.0
TARGET_SPEEDUP = 20.0
TARGET_COST_REL_DIFF = 1e-6

#: Keys of ``result.extra["seconds"]`` in the order ``calibrate.calibrate`` writes them: the
#: observability checks; the initial estimate (Algorithm 1 step 1), whose ellipsoid fit the
#: pipeline runs first (to judge it) and ``initial_estimate`` then adds noise and alignment;
#: ml (step 2); diagnostics.
STAGES = ("checks", "ellipsoid", "noise", "alignment", "ml", "diagnostics", "consistency")
INIT_STAGES = ("ellipsoid", "noise", "alignment")


@dataclass(frozen=True)
class BenchConfig:
    """Sizes and repetitions. Durations are of the motion, s; the preset adds 2 s of rest
    at 100 Hz, so 600 s gives 60,200 samples."""

    calib_duration_s: float = 600.0
    calib_runs: int = 5
    compare_duration_s: float = 60.0
    compare_seeds: tuple[int, ...] = (1, 2, 3)
    compare_max_iter: int = 500
    scaling_durations_s: tuple[float, ...] = (60.0, 600.0, 6000.0)
    scaling_reps: tuple[int, ...] = (9, 5, 3)
    ckf_duration_s: float = 120.0
    ckf_reps: int = 3
    log_import_reps: int = 3
    optimizers_sim_duration_s: float = 600.0
    #: the first this many cases of the real-data set's cases.json; None: all of them
    optimizers_real_cases: int | None = None
    #: the real recording the cold command line calibrates; None: the set's first case
    cli_real_case: str | None = "broad35_magnet4cm"
    cli_reps: int = 3


#: A few seconds in total; only checks that the code runs (tests/unit/test_bench_smoke.py).
SMOKE_CONFIG = BenchConfig(
    calib_duration_s=15.0,
    calib_runs=1,
    compare_duration_s=15.0,
    compare_seeds=(1,),
    compare_max_iter=3,
    scaling_durations_s=(15.0, 30.0),
    scaling_reps=(2, 1),
    ckf_duration_s=15.0,
    ckf_reps=1,
    log_import_reps=1,
    optimizers_sim_duration_s=15.0,
    optimizers_real_cases=1,
    cli_real_case=None,
    cli_reps=1,
)
#: Real flight logs for the import throughput: the full set beside the checkout, else the
#: committed ones.
REAL_LOG_DIRS = (
    Path(__file__).resolve().parents[1].parent / "shared" / "reallogs",
    Path(__file__).resolve().parents[1] / "tests" / "data" / "reallogs",
)


#: The real-data set of ``make real`` (cases.json, sessions/, truth/, raw/), beside the
#: checkout unless ``--realdata`` names another.
DEFAULT_REALDATA_DIR = REPO_ROOT.parent / "shared" / "realdata"
#: The ML step's optimisers compared by section 7, in the order shown.
OPTIMIZERS = ("bfgs", "trust-region")
#: The command line as a user runs it from a checkout.
MAGCAL_SCRIPT = REPO_ROOT / "host" / "magcal"


def _log(msg: str) -> None:
    print(f"[bench] {msg}", file=sys.stderr, flush=True)


# --------------------------------------------------------------------------------------
# Workers: run in a fresh, single-threaded, pinned process. numpy and magcal are imported
# inside them only, after the environment is set.


def _peak_rss_mb() -> float:
    import resource

    # ru_maxrss is in KiB on Linux (bytes on macOS).
    scale = 1.0 / 1024.0 if sys.platform != "darwin" else 1.0 / (1024.0 * 1024.0)
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * scale


def _cpu_seconds() -> float:
    import resource

    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def _session(duration_s: float, seed: int):
    from magcal.sim.scenarios import preset, simulate

    session, _ = simulate(preset(PRESET, duration_s=float(duration_s)), seed)
    return session


def _ml_problem(session):
    """(init, the likelihood problem ml.maximum_likelihood minimises, from the one builder)."""
    from magcal.calib.initial import estimate
    from magcal.calib.likelihood.problem import LikelihoodProblem

    init = estimate.initial_estimate(session)
    return init, LikelihoodProblem.for_ml_step(session, init)


def work_calibrate(duration_s: float, seed: int, warm: bool) -> dict:
    """One full calibration in this (cold) process; with ``warm`` a second one afterwards."""
    t0 = time.perf_counter()
    from magcal.calib import calibrate

    import_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    session = _session(duration_s, seed)
    simulate_s = time.perf_counter() - t0
    rss_before_mb = _peak_rss_mb()
    _log(f"  {len(session)} samples simulated in {simulate_s:.2f} s; calibrating")

    packages_before = _top_level_packages()
    cpu0 = _cpu_seconds()
    t0 = time.perf_counter()
    cal = calibrate.calibrate(session, "ml", gradient="exact")
    wall_s = time.perf_counter() - t0
    out = {
        "samples": len(session),
        "import_s": import_s,
        # A package first imported inside calibrate is paid inside wall_s.
        "imported_during_calibrate": sorted(_top_level_packages() - packages_before),
        "simulate_s": simulate_s,
        "wall_s": wall_s,
        "cpu_s": _cpu_seconds() - cpu0,
        "stages_s": _stage_seconds(cal),
        "optimizer": _optimizer_summary(cal.result.extra["optimizer"]),
        "peak_rss_before_calibrate_mb": rss_before_mb,
        "peak_rss_mb": _peak_rss_mb(),
    }
    if warm:
        t0 = time.perf_counter()
        cal = calibrate.calibrate(session, "ml", gradient="exact")
        out["warm_wall_s"] = time.perf_counter() - t0
        out["warm_stages_s"] = _stage_seconds(cal)
    return out


def _stage_seconds(cal) -> dict:
    """The pipeline's own stage times, s, in the order it recorded them (:data:`STAGES`, as
    the smoke test checks)."""
    return {k: float(v) for k, v in cal.result.extra["seconds"].items()}


def _optimizer_summary(opt: dict) -> dict:
    keys = ("iterations", "cost_evaluations", "gradient_evaluations", "final_cost")
    out = {k: opt[k] for k in keys}
    out["stopping_rule"] = opt["stopping_rule"]
    out["seconds"] = float(opt["seconds"])
    return out


def _top_level_packages() -> set[str]:
    return {name.partition(".")[0] for name in sys.modules}


#: The heavy libraries whose presence after importing the pipeline ``imports`` records.
HEAVY_PACKAGES = ("numpy", "scipy", "clarabel", "cvxpy", "matplotlib")


def work_imports() -> dict:
    """Import times in a cold process, each on top of the ones before: numpy, clarabel,
    then the rest of ``magcal.calib.calibrate`` (magcal's own modules and whatever else they
    load); which of :data:`HEAVY_PACKAGES` and scipy's modules the pipeline has loaded."""
    import importlib

    out: dict = {}
    for key, modules in (
        ("numpy_s", ("numpy",)),
        ("clarabel_s", ("clarabel",)),
        ("magcal_pipeline_s", ("magcal.calib.calibrate",)),
    ):
        t0 = time.perf_counter()
        for name in modules:
            importlib.import_module(name)
        out[key] = time.perf_counter() - t0
    out["total_s"] = sum(out.values())
    loaded = _top_level_packages()
    out["loaded"] = {name: name in loaded for name in HEAVY_PACKAGES}
    out["scipy_modules_loaded"] = sorted(
        name for name in sys.modules if name.startswith("scipy.") and name.count(".") == 1
    )
    return out


#: The ML runs of the comparison, as the pipeline runs them: the exact gradient evaluates
#: cost and gradient together at every trial point (about 2.4 filter passes); finite
#: differences (the paper's way) try points by cost alone, as a gradient there costs 35.
COMPARE_RUNS = ("exact", "numeric")


def work_compare(duration_s: float, seed: int, max_iter: int) -> dict:
    """Exact and numeric-gradient ML from one initial estimate, as the pipeline runs them
    (see :data:`COMPARE_RUNS`)."""
    import numpy as np

    # The initial estimate's modules (the ellipsoid fit's clarabel among them) are imported
    # here, before init_s is timed, so that it is the computation only.
    from magcal.calib.initial import estimate  # noqa: F401
    from magcal.calib.likelihood import ml
    from magcal.calib.likelihood.optimize import OptimizeOptions

    session = _session(duration_s, seed)
    t0 = time.perf_counter()
    init, problem = _ml_problem(session)
    init_s = time.perf_counter() - t0
    scales = problem.scales
    options = OptimizeOptions(max_iter=max_iter)
    runs: dict = {}
    thetas = {}
    for key in COMPARE_RUNS:
        gradient = key
        _log(f"  {key}: optimising ({len(session)} samples)")

        def progress(it, v, dec, key=key):
            if it % 25 == 0:
                _log(f"    {key} iteration {it}: cost {v:.6f}, decrement {dec:.2e}")

        t0, c0 = time.perf_counter(), time.process_time()
        est = ml.maximum_likelihood(session, init, gradient, options, progress, optimizer="bfgs")
        wall_s, cpu_s = time.perf_counter() - t0, time.process_time() - c0
        r = est.report
        thetas[key] = est.theta
        runs[key] = {
            "wall_s": wall_s,
            "cpu_s": cpu_s,
            "iterations": r.iterations,
            "cost_evaluations": r.cost_evaluations,
            "gradient_evaluations": r.gradient_evaluations,
            "seconds_per_gradient_evaluation": wall_s / max(r.gradient_evaluations, 1),
            "final_cost": float(r.cost),
            "final_cost_without_prior": float(problem.negative_log_likelihood(est.theta)),
            "stopping_rule": r.stopping_rule,
            "converged": bool(r.converged),
            "theta0_identical": bool(np.array_equal(est.theta0, problem.theta0)),
        }
        _log(f"  {key}: {wall_s:.2f} s, {r.iterations} iterations, '{r.stopping_rule}'")

    # How stationary each end point is, judged by the exact gradient of the objective the
    # optimiser minimised (V plus its prior, from the same builder), in scaled variables:
    # the optimiser's gradient rule compares this with OptimizeOptions.gradient_tol.
    fg_exact, fg_numeric = problem.cost_and_gradient, problem.cost_and_numeric_gradient
    for key, theta in thetas.items():
        runs[key]["max_scaled_exact_gradient_at_end"] = float(
            np.max(np.abs(fg_exact(theta)[1] * scales))
        )
    # The finite-difference gradient's own error at the exact optimum, same units: where
    # the true gradient is smaller than this, the numeric optimiser is steering by noise.
    # And the price of one gradient evaluation each way (median of a few), which is what
    # the speed-up would be if both needed the same number of evaluations.
    g_e = fg_exact(thetas["exact"])[1]
    g_n = fg_numeric(thetas["exact"])[1]
    fd_error = float(np.max(np.abs((g_n - g_e) * scales)))
    t_exact = _median_seconds(lambda: fg_exact(thetas["exact"]), GRADIENT_TIMING_REPS)
    t_numeric = _median_seconds(lambda: fg_numeric(thetas["exact"]), GRADIENT_TIMING_REPS)

    e, n = runs["exact"], runs["numeric"]

    def rel_diff(run):
        return abs(run["final_cost"] - e["final_cost"]) / max(abs(e["final_cost"]), 1e-300)

    out = {
        "samples": len(session),
        "init_s": init_s,
        "max_iter": max_iter,
        "gradient_tol": options.gradient_tol,
        "runs": runs,
        "final_cost_abs_diff": abs(n["final_cost"] - e["final_cost"]),
        "final_cost_rel_diff": rel_diff(n),
        "max_param_diff_sigma": float(np.max(np.abs(thetas["exact"] - thetas["numeric"]) / scales)),
        "max_scaled_fd_gradient_error_at_optimum": fd_error,
        "gradient_evaluation_exact_s": t_exact,
        "gradient_evaluation_numeric_s": t_numeric,
        "speedup_per_gradient_evaluation": t_numeric / t_exact,
        "speedup_ml": n["wall_s"] / e["wall_s"],
        "speedup_ml_cpu": n["cpu_s"] / e["cpu_s"],
        "speedup_with_init": (init_s + n["wall_s"]) / (init_s + e["wall_s"]),
    }
    return out


def _median_seconds(fn, reps: int) -> float:
    times = []
    for _ in range(reps):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def work_scaling(durations_s: list[float], reps: list[int], seed: int) -> dict:
    """Median time of one cost+gradient and one cost evaluation at θ₀ per session size."""
    import tracemalloc

    import numpy as np

    from magcal.calib.likelihood import mekf
    from magcal.calib.likelihood.problem import (
        negative_log_likelihood,
        negative_log_likelihood_and_gradient,
    )

    rows = []
    for duration_s, n_rep in zip(durations_s, reps, strict=True):
        session = _session(duration_s, seed)
        _, problem = _ml_problem(session)
        data, theta0 = problem.data, problem.theta0
        n = len(data)
        _log(f"  {n} samples: {n_rep} repetitions")
        tape = mekf.new_tape(n)
        negative_log_likelihood_and_gradient(
            theta0, data, tape
        )  # warm-up: page in the tape and the data
        t_cg, t_c = [], []
        for _ in range(n_rep):
            t0 = time.perf_counter()
            negative_log_likelihood_and_gradient(theta0, data, tape)
            t_cg.append(time.perf_counter() - t0)
            t0 = time.perf_counter()
            negative_log_likelihood(theta0, data)
            t_c.append(time.perf_counter() - t0)
        # What one evaluation allocates on the Python/numpy side (the C kernel has no heap
        # allocations): with no tape passed in, this includes the tape itself.
        tracemalloc.start()
        negative_log_likelihood_and_gradient(theta0, data)
        cg_alloc = tracemalloc.get_traced_memory()[1]
        tracemalloc.reset_peak()
        negative_log_likelihood(theta0, data)
        c_alloc = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
        fields = (data.dt, data.gyr, data.acc, data.mag, data.acc_extra_var)
        cg_s, c_s = statistics.median(t_cg), statistics.median(t_c)
        rows.append(
            {
                "samples": n,
                "repetitions": n_rep,
                "cost_grad_s": cg_s,
                "cost_grad_all_s": t_cg,
                "cost_s": c_s,
                "cost_all_s": t_c,
                "cost_grad_ns_per_sample": 1e9 * cg_s / n,
                "cost_ns_per_sample": 1e9 * c_s / n,
                "grad_over_cost": cg_s / c_s,
                "tape_mb": tape.nbytes / 1e6,
                "data_mb": sum(f.nbytes for f in fields) / 1e6,
                "cost_grad_alloc_mb": cg_alloc / 1e6,
                "cost_alloc_mb": c_alloc / 1e6,
            }
        )
    first, last = rows[0], rows[-1]
    slope = None
    if last["samples"] != first["samples"]:
        slope = float(
            np.log(last["cost_grad_s"] / first["cost_grad_s"])
            / np.log(last["samples"] / first["samples"])
        )
    return {"rows": rows, "loglog_slope_cost_grad": slope, "peak_rss_mb": _peak_rss_mb()}


#: Readings per ``LiveCalibration.add`` in the live figure: what collect feeds every 0.25 s at
#: 100 Hz (it asks for the state as often).
LIVE_CHUNK = 25


def work_ckf(duration_s: float, seed: int, reps: int) -> dict:
    """The CKF's cost per sample on one session (median of ``reps`` passes each).

    - ``step``: ``CubatureCalibrator.update_many`` from a prior: the filter step alone;
    - ``update``: ``update(y)`` per sample, which also returns the estimate and covariance;
    - ``live``: ``LiveCalibration`` fed as collect feeds it, with its state every
      LIVE_CHUNK readings (per reading);
    - ``run_ckf_s``: a whole session as ``--method ckf`` filters it (start included);
      ``two_step_s``: TWO-STEP on the same readings.
    """
    from magcal.calib.norm_only import ckf, live, twostep

    session = _session(duration_s, seed)
    mag = session.mag
    n = len(mag)
    prior = ckf.CkfPrior.from_readings(mag)

    def step():
        ckf.CubatureCalibrator(prior).update_many(mag)

    def update():
        f = ckf.CubatureCalibrator(prior)
        for y in mag:
            f.update(y)

    def live_feed():
        lc = live.LiveCalibration(100.0)
        for i in range(0, n, LIVE_CHUNK):
            lc.add(mag[i : i + LIVE_CHUNK])
            lc.state(0.5)

    out: dict = {"samples": n}
    for key, fn in (("step", step), ("update", update), ("live", live_feed)):
        _log(f"  {key}: {reps} pass(es) over {n} samples")
        seconds = _median_seconds(fn, reps)
        out[f"{key}_us_per_sample"] = 1e6 * seconds / n
    t0 = time.perf_counter()
    fit = ckf.run_ckf(mag)
    out["run_ckf_s"] = time.perf_counter() - t0
    out["run_ckf_order"] = fit.order
    out["run_ckf_start_sample"] = fit.start_index
    t0 = time.perf_counter()
    twostep.two_step(mag)
    out["two_step_s"] = time.perf_counter() - t0
    f = ckf.CubatureCalibrator(prior)
    f.update_many(mag[:10])
    out["filter_state_bytes"] = sum(v.nbytes for v in vars(f).values() if hasattr(v, "nbytes"))
    return out


def _largest_logs() -> dict[str, str]:
    """format → path of the largest log of that format in the first folder of
    :data:`REAL_LOG_DIRS` that has any."""
    from magcal.logs import LogImportError, sniff_format

    for folder in REAL_LOG_DIRS:
        if not folder.is_dir():
            continue
        best: dict[str, Path] = {}
        for p in folder.rglob("*"):
            if p.suffix.lower() not in (".bin", ".tlog", ".ulg"):
                continue
            try:
                kind = sniff_format(str(p))
            except LogImportError:
                continue
            if kind not in best or p.stat().st_size > best[kind].stat().st_size:
                best[kind] = p
        if best:
            return {k: str(v) for k, v in sorted(best.items())}
    return {}


def work_log_import(reps: int) -> dict:
    """MB/s of importing the largest real log of each format (median of ``reps``), the whole
    log as the session (``--start/--end`` over all of it: no stretch detection)."""
    from magcal.logs import ImportOptions, LogImportError, import_log

    everything = ImportOptions(start_s=-1e12, end_s=1e12)
    out: dict = {"logs": {}}
    for kind, path in _largest_logs().items():
        size_mb = os.path.getsize(path) / 1e6
        _log(f"  {kind}: {os.path.basename(path)} ({size_mb:.1f} MB), {reps} pass(es)")

        def once(path=path):
            try:
                import_log(path, everything)
            except LogImportError:
                pass  # refused after reading (a gap, no compass): still read in full

        seconds = _median_seconds(once, reps)
        out["logs"][kind] = {
            "file": os.path.basename(path),
            "size_mb": size_mb,
            "seconds": seconds,
            "mb_per_s": size_mb / seconds,
        }
    if out["logs"]:
        largest = max(out["logs"].values(), key=lambda r: r["size_mb"])
        out["largest"] = largest
    return out


def _optimizer_run(session, optimizer: str) -> dict:
    """``calibrate(session, "ml", optimizer=optimizer)``; refused by its checks, again with
    ``force`` (as ``make real`` scores a refused case). An error is recorded, not raised."""
    from magcal.calib import calibrate
    from magcal.calib.likelihood.optimize import CONVERGED_RULES
    from magcal.errors import MagcalError

    forced = False
    t0 = time.perf_counter()
    try:
        try:
            cal = calibrate.calibrate(session, "ml", optimizer=optimizer)
        except MagcalError:
            forced = True
            cal = calibrate.calibrate(session, "ml", optimizer=optimizer, force=True)
    except Exception as exc:  # noqa: BLE001 -- a benchmark records a failing run and goes on
        return {
            "forced": forced,
            "error": f"{type(exc).__name__}: {exc}",
            "wall_s": time.perf_counter() - t0,
        }
    wall_s = time.perf_counter() - t0
    opt = cal.result.extra["optimizer"]
    return {
        "forced": forced,
        "iterations": opt["iterations"],
        "information_evaluations": opt["information_evaluations"],
        "gradient_evaluations": opt["gradient_evaluations"],
        "cost_evaluations": opt["cost_evaluations"],
        "stopping_rule": opt["stopping_rule"],
        "converged": opt["stopping_rule"] in CONVERGED_RULES,
        "final_cost": float(opt["final_cost"]),
        "negative_log_likelihood": float(cal.result.extra["negative_log_likelihood"]),
        # The fits from the other starting points (on a second thread), not in iterations.
        "check_iterations": sum(p["iterations"] for p in cal.result.extra["starting_points"][1:]),
        "optimizer_s": float(opt["seconds"]),
        "ml_s": float(cal.result.extra["seconds"]["ml"]),
        "wall_s": wall_s,
    }


def _optimizer_case(name: str, session, **info) -> dict:
    """Every optimiser of :data:`OPTIMIZERS` on one session, and the final costs' difference
    (trust-region − bfgs, nats; negative: trust-region found the lower optimum)."""
    runs = {}
    for optimizer in OPTIMIZERS:
        r = runs[optimizer] = _optimizer_run(session, optimizer)
        if "error" in r:
            _log(f"  {name}, {optimizer}: failed: {r['error']}")
        else:
            _log(
                f"  {name}, {optimizer}: {r['iterations']} iterations, stopped on "
                f"'{r['stopping_rule']}', ML {r['ml_s']:.2f} s"
            )
    b, t = runs["bfgs"], runs["trust-region"]
    both = "error" not in b and "error" not in t
    return {
        "case": name,
        "samples": len(session),
        "mag_samples": int(session.has_mag.sum()),
        **info,
        "runs": runs,
        "final_cost_diff": t["final_cost"] - b["final_cost"] if both else None,
    }


def work_optimizers(
    sim_duration_s: float,
    seed: int,
    sim_csv: str,
    realdata: str | None,
    real_cases: list[str],
) -> dict:
    """Section 7's in-process part: the optimisers on the simulated session (written to
    ``sim_csv`` too, for the command line) and on each case of ``real_cases`` in
    ``realdata``, its session as ``make real`` builds it (``real.load_case``: multi-rate from
    raw/CASE.npz where there is one)."""
    from magcal.io.session import write_session

    session = _session(sim_duration_s, seed)
    write_session(sim_csv, session)
    out: dict = {
        "simulated": _optimizer_case(
            f"simulated {sim_duration_s:g} s", session, form="simulated", preset=PRESET
        ),
        "real": [],
    }
    if real_cases:
        from magcal_evaluation import real

        for name in real_cases:
            case = real.load_case(realdata, name)
            out["real"].append(
                _optimizer_case(name, case.session, form=case.form, source=case.source)
            )
    return out


def _worker_main(name: str, params: dict, result_file: str) -> None:
    # Normally inherited from the parent; set again in case a worker is run by hand. Still
    # before any numpy import: the workers import it lazily.
    os.environ.update(SINGLE_THREAD_ENV)
    cpu = params.pop("cpu", None)
    if cpu is not None and hasattr(os, "sched_setaffinity"):
        os.sched_setaffinity(0, {int(cpu)})
    workers = {
        "calibrate": work_calibrate,
        "imports": work_imports,
        "compare": work_compare,
        "scaling": work_scaling,
        "ckf": work_ckf,
        "log_import": work_log_import,
        "optimizers": work_optimizers,
    }
    out = workers[name](**params)
    out["versions"] = {
        "python": platform.python_version(),
        "numpy": sys.modules["numpy"].__version__ if "numpy" in sys.modules else None,
    }
    Path(result_file).write_text(json.dumps(out))


# --------------------------------------------------------------------------------------
# Parent: spawns the workers, assembles the results, prints and writes them.


def run_worker(name: str, params: dict, cpu: int | None) -> dict:
    """Run one worker in a fresh pinned, single-threaded subprocess; its result plus the
    wall time of the whole process (interpreter start to exit) as ``process_wall_s``."""
    with tempfile.TemporaryDirectory(prefix="magcal-bench-") as tmp:
        result_file = os.path.join(tmp, "result.json")
        cmd = [
            sys.executable,
            str(Path(__file__).resolve()),
            "--worker",
            name,
            "--params",
            json.dumps({**params, "cpu": cpu}),
            "--result-file",
            result_file,
        ]
        env = {**os.environ, **SINGLE_THREAD_ENV}
        t0 = time.perf_counter()
        try:
            proc = subprocess.run(cmd, env=env, timeout=WORKER_TIMEOUT_S, check=False)
        except subprocess.TimeoutExpired as exc:
            raise SystemExit(
                f"bench: worker '{name}' took longer than {WORKER_TIMEOUT_S:.0f} s: check "
                "the machine's load, or run it by hand to see where it hangs"
            ) from exc
        process_wall_s = time.perf_counter() - t0
        if proc.returncode != 0:
            raise SystemExit(
                f"bench: worker '{name}' failed with exit code {proc.returncode} (its "
                "traceback is above): fix the error and run the benchmark again"
            )
        out = json.loads(Path(result_file).read_text())
    out["process_wall_s"] = process_wall_s
    return out


def _git(*args: str) -> str | None:
    """``git *args`` in the repository: its stdout, or None if git is missing or fails. The
    same helper as in magcal_evaluation.accuracy_report (bench/ imports the evaluation's
    real-data loader in a worker only, never its reports): keep the two identical."""
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


def _cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown"


def machine_info(cpu: int | None) -> dict:
    try:
        numpy_version = importlib.metadata.version("numpy")
    except importlib.metadata.PackageNotFoundError:
        numpy_version = None
    return {
        "cpu_count": os.cpu_count(),
        "cpu_model": _cpu_model(),
        "pinned_cpu": cpu,
        "loadavg_at_start": list(os.getloadavg()) if hasattr(os, "getloadavg") else None,
        "platform": platform.platform(),
        "python": platform.python_version(),
        "numpy": numpy_version,
    }


def _default_cpu() -> int | None:
    if not hasattr(os, "sched_getaffinity"):
        return None
    return min(os.sched_getaffinity(0))


def _median_run(runs: list[dict]) -> dict:
    """The run with the median total wall time (the lower one of an even count)."""
    ordered = sorted(runs, key=lambda r: r["wall_s"])
    return ordered[(len(ordered) - 1) // 2]


def run_all(config: BenchConfig, cpu: int | None, realdata: Path | None = None) -> dict:
    """Every measurement; returns the results dictionary written to ``--out``."""
    started = time.perf_counter()
    results: dict = {
        "format": RESULTS_FORMAT,
        "date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        "git": {
            "commit": _git("rev-parse", "HEAD"),
            # Uncommitted changes to the measured code: the figures are then not the commit's.
            "host_modified": [
                line[3:]
                for line in (_git("status", "--porcelain", "--", "host") or "").splitlines()
            ],
        },
        "machine": machine_info(cpu),
        "config": {**asdict(config), "preset": PRESET, "seed": SEED},
    }

    runs = []
    for i in range(config.calib_runs):
        _log(f"1/7 full calibration, cold process, run {i + 1}/{config.calib_runs}")
        r = run_worker(
            "calibrate",
            {"duration_s": config.calib_duration_s, "seed": SEED, "warm": False},
            cpu,
        )
        _log(f"  total {r['wall_s']:.2f} s, peak RSS {r['peak_rss_mb']:.0f} MB")
        runs.append(r)
    # In a process of its own, so that the cold runs' process times and memory stay clean.
    _log("1/7 full calibration twice in one process (for the warm figure)")
    warm = run_worker(
        "calibrate", {"duration_s": config.calib_duration_s, "seed": SEED, "warm": True}, cpu
    )
    results["machine"]["numpy"] = runs[0]["versions"]["numpy"] or results["machine"]["numpy"]
    median = _median_run(runs)
    results["calibration"] = {
        "samples": median["samples"],
        "runs": len(runs),
        "wall_s": median["wall_s"],
        "wall_all_s": [r["wall_s"] for r in runs],
        "cpu_s": median["cpu_s"],
        "stages_s": median["stages_s"],
        "init_s": sum(median["stages_s"][k] for k in INIT_STAGES),
        "optimizer": median["optimizer"],
        "import_s": median["import_s"],
        "imported_during_calibrate": median["imported_during_calibrate"],
        "simulate_s": median["simulate_s"],
        "process_wall_s": median["process_wall_s"],
        "warm_wall_s": warm["warm_wall_s"],
        "warm_stages_s": warm["warm_stages_s"],
    }
    results["memory"] = {
        "peak_rss_mb": max(r["peak_rss_mb"] for r in runs),
        "peak_rss_before_calibrate_mb": max(r["peak_rss_before_calibrate_mb"] for r in runs),
    }

    _log("2/7 import times (fresh process)")
    results["imports"] = run_worker("imports", {}, cpu)
    results["imports"].pop("versions", None)

    per_seed = []
    for seed in config.compare_seeds:
        _log(
            f"3/7 exact vs numeric gradient, {config.compare_duration_s:g} s session, "
            f"seed {seed} ({len(per_seed) + 1}/{len(config.compare_seeds)})"
        )
        r = run_worker(
            "compare",
            {
                "duration_s": config.compare_duration_s,
                "seed": seed,
                "max_iter": config.compare_max_iter,
            },
            cpu,
        )
        r.pop("versions", None)
        _log(f"  speed-up {r['speedup_ml']:.1f}x, final costs {r['final_cost_rel_diff']:.1e} apart")
        per_seed.append({"seed": seed, **r})
    results["exact_vs_numeric"] = compare_summary(per_seed, config.compare_duration_s)

    _log("4/7 scaling of one cost(+gradient) evaluation")
    scal = run_worker(
        "scaling",
        {
            "durations_s": list(config.scaling_durations_s),
            "reps": list(config.scaling_reps),
            "seed": SEED,
        },
        cpu,
    )
    scal.pop("versions", None)
    results["scaling"] = scal

    _log("5/7 CKF time per sample")
    ckf = run_worker(
        "ckf",
        {"duration_s": config.ckf_duration_s, "seed": SEED, "reps": config.ckf_reps},
        cpu,
    )
    ckf.pop("versions", None)
    results["ckf"] = ckf

    _log("6/7 flight-log import throughput")
    logs = run_worker("log_import", {"reps": config.log_import_reps}, cpu)
    logs.pop("versions", None)
    results["log_import"] = logs

    _log("7/7 the ML step's optimisers, bfgs and trust-region")
    results["optimizers"] = run_optimizers(config, realdata, cpu)

    results["targets"] = targets(results)
    results["bench_wall_s"] = time.perf_counter() - started
    return results


def run_optimizers(config: BenchConfig, realdata: Path | None, cpu: int | None) -> dict:
    """Section 7: the in-process comparison (a worker), then the cold command lines. Not
    pinned to ``cpu``: the ML step fits its second starting point on a second thread, so
    these run on the machine's cores as a user's calibration does."""
    del cpu
    names, skipped = real_case_names(realdata, config.optimizers_real_cases)
    if skipped:
        _log(f"  {skipped}")
    out: dict = {
        "realdata": None if realdata is None else str(realdata),
        "real_skipped": skipped,
    }
    with tempfile.TemporaryDirectory(prefix="magcal-bench-sim-") as tmp:
        sim_csv = os.path.join(tmp, "simulated.csv")
        r = run_worker(
            "optimizers",
            {
                "sim_duration_s": config.optimizers_sim_duration_s,
                "seed": SEED,
                "sim_csv": sim_csv,
                "realdata": None if realdata is None else str(realdata),
                "real_cases": names,
            },
            None,
        )
        out["simulated"] = r["simulated"]
        out["real"] = r["real"]
        out["real_summary"] = optimizer_summary(r["real"]) if r["real"] else None
        sessions = {}
        cli_case = config.cli_real_case or (names[0] if names else None)
        if cli_case in names:
            sessions[cli_case] = str(realdata / "sessions" / f"{cli_case}.csv")
        elif not skipped:
            _log(f"  {cli_case}: not among the real recordings; its cold calibrate is skipped")
        sessions["simulated"] = sim_csv
        out["cli"] = cli_timings(sessions, config.cli_reps, None)
    return out


def real_case_names(realdata: Path | None, limit: int | None) -> tuple[list[str], str | None]:
    """The cases of ``realdata/cases.json`` (the first ``limit``), or none and why."""
    if realdata is None:
        return [], "no real-data folder given: the real recordings are skipped"
    index = realdata / "cases.json"
    if not index.is_file():
        return [], f"no {index}: the real recordings are skipped (--realdata names the set)"
    names = list(json.loads(index.read_text(encoding="utf-8")))
    return (names if limit is None else names[:limit]), None


def _pinned(cpu: int | None):
    """A ``preexec_fn`` that pins the child to ``cpu`` (None when not pinning)."""
    if cpu is None or not hasattr(os, "sched_setaffinity"):
        return None
    return lambda: os.sched_setaffinity(0, {cpu})


def _cold_run(args: list[str], cpu: int | None) -> tuple[float, int]:
    """Wall time of ``host/magcal *args`` as a whole process, s, and its exit status."""
    env = {**os.environ, **SINGLE_THREAD_ENV}
    t0 = time.perf_counter()
    try:
        proc = subprocess.run(
            [str(MAGCAL_SCRIPT), *args],
            env=env,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.PIPE,
            text=True,
            timeout=WORKER_TIMEOUT_S,
            preexec_fn=_pinned(cpu),
            check=False,
        )
    except subprocess.TimeoutExpired as exc:
        raise SystemExit(
            f"bench: magcal {' '.join(args)} took longer than {WORKER_TIMEOUT_S:.0f} s: "
            "run it by hand to see where it hangs"
        ) from exc
    seconds = time.perf_counter() - t0
    if proc.returncode != 0:
        _log(f"  magcal {' '.join(args)}: exit {proc.returncode}: {proc.stderr[-300:]!r}")
    return seconds, proc.returncode


def cli_timings(sessions: dict[str, str], reps: int, cpu: int | None) -> dict:
    """Cold ``magcal calibrate SESSION -o OUT --optimizer ...`` per session and optimiser
    (the optimisers alternating, so that a change in the machine's load falls on both), and
    ``magcal --help``; each the median of ``reps`` whole processes."""
    out: dict = {"reps": reps, "calibrate": {}}
    with tempfile.TemporaryDirectory(prefix="magcal-bench-cli-") as tmp:
        for label, path in sessions.items():
            _log(f"  magcal calibrate {os.path.basename(path)}, {reps} run(s) per optimiser")
            runs: dict = {o: {"all_s": [], "exit_codes": []} for o in OPTIMIZERS}
            for _ in range(reps):
                for optimizer in OPTIMIZERS:
                    result = os.path.join(tmp, f"result-{optimizer}.json")
                    args = ["calibrate", path, "-o", result, "--optimizer", optimizer]
                    seconds, code = _cold_run(args, cpu)
                    runs[optimizer]["all_s"].append(seconds)
                    runs[optimizer]["exit_codes"].append(code)
            for r in runs.values():
                r["median_s"] = statistics.median(r["all_s"])
            out["calibrate"][label] = {"session": os.path.basename(path), **runs}
    _log(f"  magcal --help, {reps} run(s)")
    helps = [_cold_run(["--help"], cpu) for _ in range(reps)]
    out["help"] = {
        "median_s": statistics.median(t for t, _ in helps),
        "all_s": [t for t, _ in helps],
        "exit_codes": [c for _, c in helps],
    }
    return out


def optimizer_summary(cases: list[dict]) -> dict:
    """Per optimiser over the real recordings: medians of iterations, evaluations and ML
    seconds over the runs that finished, how many converged, which failed; and the range
    of the final costs' differences (trust-region − bfgs, nats)."""
    out: dict = {"cases": len(cases)}
    for optimizer in OPTIMIZERS:
        done = [c["runs"][optimizer] for c in cases if "error" not in c["runs"][optimizer]]

        def med(key, done=done):
            return statistics.median(r[key] for r in done) if done else None

        out[optimizer] = {
            "finished": len(done),
            "converged": sum(r["converged"] for r in done),
            "failed": [c["case"] for c in cases if "error" in c["runs"][optimizer]],
            "median_iterations": med("iterations"),
            "median_information_evaluations": med("information_evaluations"),
            "median_gradient_evaluations": med("gradient_evaluations"),
            "median_ml_s": med("ml_s"),
            "total_ml_s": sum(r["ml_s"] for r in done),
        }
    diffs = [c["final_cost_diff"] for c in cases if c["final_cost_diff"] is not None]
    out["final_cost_diff_min"] = min(diffs) if diffs else None
    out["final_cost_diff_max"] = max(diffs) if diffs else None
    return out


def compare_summary(per_seed: list[dict], duration_s: float) -> dict:
    """The comparison over seeds: the speed-ups vary with how many iterations each
    optimiser happens to need, so the target is judged on the median speed-up and the
    worst cost difference."""

    def values(key):
        return [r[key] for r in per_seed if r[key] is not None]

    def median_or_none(key):
        v = values(key)
        return statistics.median(v) if v else None

    return {
        "duration_s": duration_s,
        "seeds": [r["seed"] for r in per_seed],
        "speedup_ml_median": statistics.median(values("speedup_ml")),
        "speedup_ml_min": min(values("speedup_ml")),
        "speedup_ml_max": max(values("speedup_ml")),
        "speedup_per_gradient_evaluation_median": median_or_none("speedup_per_gradient_evaluation"),
        "final_cost_rel_diff_max": max(values("final_cost_rel_diff")),
        "per_seed": per_seed,
    }


def targets(results: dict) -> dict:
    """The speed and memory targets, each {value, target, pass}. Reported, never asserted."""
    cal, cmp_ = results["calibration"], results["exact_vs_numeric"]

    def row(value, target, ok):
        return {"value": value, "target": target, "pass": bool(ok)}

    return {
        "calibration_wall_s": row(
            cal["wall_s"], f"<= {TARGET_CALIBRATION_S:g}", cal["wall_s"] <= TARGET_CALIBRATION_S
        ),
        "peak_rss_mb": row(
            results["memory"]["peak_rss_mb"],
            f"<= {TARGET_PEAK_RSS_MB:g}",
            results["memory"]["peak_rss_mb"] <= TARGET_PEAK_RSS_MB,
        ),
        "speedup_ml_median": row(
            cmp_["speedup_ml_median"],
            f">= {TARGET_SPEEDUP:g}",
            cmp_["speedup_ml_median"] >= TARGET_SPEEDUP,
        ),
        "final_cost_rel_diff_max": row(
            cmp_["final_cost_rel_diff_max"],
            f"<= {TARGET_COST_REL_DIFF:g}",
            cmp_["final_cost_rel_diff_max"] <= TARGET_COST_REL_DIFF,
        ),
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", help="write the machine-readable results here (JSON)")
    ap.add_argument("--cpu", type=int, default=None, help="CPU to pin to (default: lowest)")
    ap.add_argument("--smoke", action="store_true", help="tiny sizes; only checks it runs")
    ap.add_argument("--show", nargs="+", metavar="JSON", help="print headline figures only")
    ap.add_argument(
        "--realdata",
        type=Path,
        default=DEFAULT_REALDATA_DIR,
        metavar="DIR",
        help="the real-data set (cases.json, sessions/, truth/, raw/) for the optimisers' "
        "comparison (default: ../shared/realdata beside the checkout; skipped when absent)",
    )
    ap.add_argument("--worker", help=argparse.SUPPRESS)
    ap.add_argument("--params", default="{}", help=argparse.SUPPRESS)
    ap.add_argument("--result-file", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)

    if args.worker:
        _worker_main(args.worker, json.loads(args.params), args.result_file)
        return 0
    if args.show:
        print(format_headlines(args.show))
        return 0
    cpu = args.cpu if args.cpu is not None else _default_cpu()
    results = run_all(SMOKE_CONFIG if args.smoke else BenchConfig(), cpu, args.realdata)
    print(format_table(results))
    if args.out:
        Path(args.out).write_text(json.dumps(results, indent=1, sort_keys=False) + "\n")
        _log(f"results written to {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
