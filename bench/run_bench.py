#!/usr/bin/env python3
"""magcal benchmark: the speed and memory targets of issue 3, measured on one core.

    python bench/run_bench.py --out bench/results.json     # what `make bench` runs (~1-2 min)
    python bench/run_bench.py --show old.json new.json     # headline figures side by side

Four measurements, each in a fresh subprocess of this script (``--worker NAME``) with
OMP/OPENBLAS/MKL_NUM_THREADS=1 set before numpy is imported and the process pinned to one
CPU with ``os.sched_setaffinity``:

1. ``calibrate``: the full ML calibration (``pipeline.calibrate``: checks, initial estimate,
   ML optimisation, diagnostics) of a simulated 10-minute 100 Hz MEMS session, in a cold
   process as a user gets it. Imports and the simulation are timed but kept out of the
   total. Peak RSS (``ru_maxrss``) is read in the same process, which does nothing else.
2. ``imports``: how long ``import cvxpy`` takes once magcal is loaded (the ellipsoid SDP
   imports it lazily, so in a cold process it is paid inside the "ellipsoid" stage).
3. ``compare``: exact against finite-difference gradients on a shorter session, both ML
   optimisations from the same initial estimate θ₀ in one process.
4. ``scaling``: one cost+gradient and one cost-only evaluation at 6k, 60k and 600k samples.

Progress goes to stderr, the table to stdout, the machine-readable summary to ``--out``.
Targets are reported as pass/fail, never asserted: timing depends on the machine.
See bench/README.md for what each figure means.
"""

from __future__ import annotations

import argparse
import contextlib
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

# Issue 3 targets.
TARGET_CALIBRATION_S = 10.0
TARGET_PEAK_RSS_MB = 1024.0
TARGET_SPEEDUP = 20.0
TARGET_COST_REL_DIFF = 1e-6

#: Keys of ``result.extra["seconds"]`` in pipeline order; noise + ellipsoid + alignment is
#: the initial estimate (Algorithm 1 step 1), ml is step 2.
STAGES = ("checks", "noise", "ellipsoid", "alignment", "ml", "diagnostics")
INIT_STAGES = ("noise", "ellipsoid", "alignment")


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


#: A few seconds in total; only checks that the code runs (tests/unit/test_bench_smoke.py).
SMOKE_CONFIG = BenchConfig(
    calib_duration_s=15.0,
    calib_runs=1,
    compare_duration_s=15.0,
    compare_seeds=(1,),
    compare_max_iter=3,
    scaling_durations_s=(15.0, 30.0),
    scaling_reps=(2, 1),
)


def __getattr__(name: str):
    """``TAPE_DOUBLES_PER_SAMPLE``: the reverse-mode tape of host/csrc/mekf_likelihood.c, as
    the built kernel reports it. Looked up lazily: magcal imports numpy, which must not be
    loaded before a worker has set its single-thread environment."""
    if name == "TAPE_DOUBLES_PER_SAMPLE":
        from magcal.calib import native

        return native.TAPE_DOUBLES_PER_SAMPLE
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


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
    """(init, normalised θ₀ params, FilterData, θ₀) as ml.maximum_likelihood builds them."""
    from magcal.calib import initial, ml, params

    init = initial.initial_estimate(session)
    norm = ml.normalisation_for(init.params)
    p0 = init.params.scaled_magnetometer(norm.centre, norm.scale)
    data = ml.filter_data_for(session, init, p0, norm)
    return init, p0, data, params.pack(p0)


def work_calibrate(duration_s: float, seed: int, warm: bool) -> dict:
    """One full calibration in this (cold) process; with ``warm`` a second one afterwards."""
    t0 = time.perf_counter()
    from magcal.calib import pipeline

    import_s = time.perf_counter() - t0
    cvxpy_loaded = "cvxpy" in sys.modules
    t0 = time.perf_counter()
    session = _session(duration_s, seed)
    simulate_s = time.perf_counter() - t0
    rss_before_mb = _peak_rss_mb()
    _log(f"  {len(session)} samples simulated in {simulate_s:.2f} s; calibrating")

    cpu0 = _cpu_seconds()
    t0 = time.perf_counter()
    cal = pipeline.calibrate(session, "ml", gradient="exact")
    wall_s = time.perf_counter() - t0
    out = {
        "samples": len(session),
        "import_s": import_s,
        "cvxpy_imported_before_calibrate": cvxpy_loaded,
        "simulate_s": simulate_s,
        "wall_s": wall_s,
        "cpu_s": _cpu_seconds() - cpu0,
        "stages_s": {k: float(cal.result.extra["seconds"].get(k, 0.0)) for k in STAGES},
        "optimizer": _optimizer_summary(cal.result.extra["optimizer"]),
        "peak_rss_before_calibrate_mb": rss_before_mb,
        "peak_rss_mb": _peak_rss_mb(),
    }
    if warm:
        t0 = time.perf_counter()
        cal = pipeline.calibrate(session, "ml", gradient="exact")
        out["warm_wall_s"] = time.perf_counter() - t0
        out["warm_stages_s"] = {k: float(cal.result.extra["seconds"].get(k, 0.0)) for k in STAGES}
    return out


def _optimizer_summary(opt: dict) -> dict:
    keys = ("iterations", "cost_evaluations", "gradient_evaluations", "final_cost")
    out = {k: opt[k] for k in keys}
    out["stopping_rule"] = opt["stopping_rule"]
    out["seconds"] = float(opt["seconds"])
    return out


def work_imports() -> dict:
    """Import time of magcal's pipeline, then of cvxpy on top of it."""
    t0 = time.perf_counter()
    from magcal.calib import pipeline  # noqa: F401

    magcal_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    import cvxpy  # noqa: F401

    return {"magcal_pipeline_s": magcal_s, "cvxpy_s": time.perf_counter() - t0}


#: The ML runs of the comparison, as the pipeline runs them: the exact gradient evaluates
#: cost and gradient together at every trial point (about 2.4 filter passes); finite
#: differences (the paper's way) try points by cost alone, as a gradient there costs 35.
COMPARE_RUNS = ("exact", "numeric")


def work_compare(duration_s: float, seed: int, max_iter: int) -> dict:
    """Exact and numeric-gradient ML from one initial estimate, as the pipeline runs them
    (see :data:`COMPARE_RUNS`)."""
    import numpy as np

    from magcal.calib import cost, ml
    from magcal.calib.optimize import OptimizeOptions

    session = _session(duration_s, seed)
    # Import cvxpy first so that init_s is the initial estimate's computation only (in a
    # fresh process the ellipsoid fit would otherwise pay for the import).
    t0 = time.perf_counter()
    import cvxpy  # noqa: F401

    cvxpy_import_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    init, p0, data, theta0 = _ml_problem(session)
    init_s = time.perf_counter() - t0
    scales = ml.parameter_scales(p0, len(data))
    options = OptimizeOptions(max_iter=max_iter)
    runs: dict = {}
    thetas = {}
    objectives = {}
    for key in COMPARE_RUNS:
        gradient = key
        _log(f"  {key}: optimising ({len(session)} samples)")

        def progress(it, v, dec, key=key):
            if it % 25 == 0:
                _log(f"    {key} iteration {it}: cost {v:.6f}, decrement {dec:.2e}")

        with _instrument_ml(ml) as objective:
            t0, c0 = time.perf_counter(), time.process_time()
            est = ml.maximum_likelihood(session, init, gradient, options, progress)
            wall_s, cpu_s = time.perf_counter() - t0, time.process_time() - c0
        objectives.setdefault(gradient, objective)
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
            "final_cost_without_prior": float(cost.cost(est.theta, data)),
            "stopping_rule": r.stopping_rule,
            "converged": bool(r.converged),
            "theta0_identical": bool(np.array_equal(est.theta0, theta0)),
        }
        _log(f"  {key}: {wall_s:.2f} s, {r.iterations} iterations, '{r.stopping_rule}'")

    # How stationary each end point is, judged by the exact gradient of the objective the
    # optimiser minimised (V plus its prior), in scaled variables: the optimiser's gradient
    # rule compares this with OptimizeOptions.gradient_tol.
    fg_exact = objectives["exact"].get("fun_and_grad")
    fg_numeric = objectives["numeric"].get("fun_and_grad")
    for key, theta in thetas.items():
        g_max = None
        if fg_exact is not None:
            g_max = float(np.max(np.abs(fg_exact(theta)[1] * scales)))
        runs[key]["max_scaled_exact_gradient_at_end"] = g_max
    # The finite-difference gradient's own error at the exact optimum, same units: where
    # the true gradient is smaller than this, the numeric optimiser is steering by noise.
    # And the price of one gradient evaluation each way (median of a few), which is what
    # the speed-up would be if both needed the same number of evaluations.
    fd_error = t_exact = t_numeric = None
    if fg_exact is not None and fg_numeric is not None:
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
        "cvxpy_import_s": cvxpy_import_s,
        "max_iter": max_iter,
        "gradient_tol": options.gradient_tol,
        "runs": runs,
        "final_cost_abs_diff": abs(n["final_cost"] - e["final_cost"]),
        "final_cost_rel_diff": rel_diff(n),
        "max_param_diff_sigma": float(np.max(np.abs(thetas["exact"] - thetas["numeric"]) / scales)),
        "max_scaled_fd_gradient_error_at_optimum": fd_error,
        "gradient_evaluation_exact_s": t_exact,
        "gradient_evaluation_numeric_s": t_numeric,
        "speedup_per_gradient_evaluation": None if t_exact is None else t_numeric / t_exact,
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


class _InstrumentError(RuntimeError):
    """magcal.calib.ml no longer has what :func:`_instrument_ml` wraps."""


@contextlib.contextmanager
def _instrument_ml(ml_module):
    """Record the objective ``ml.maximum_likelihood`` builds (``fun_and_grad`` and the
    cost-only ``fun`` from ``penalised_cost_functions``), so that end points are judged by
    the very objective that was minimised, prior included, without restating how ml builds
    it. Raises _InstrumentError if the names are gone."""
    captured: dict = {}
    names = ("penalised_cost_functions", "minimize_bfgs")
    if not all(hasattr(ml_module, name) for name in names):
        raise _InstrumentError(f"magcal.calib.ml lacks {' or '.join(names)}")
    original_pcf, original_min = (getattr(ml_module, name) for name in names)

    def pcf(*args, **kwargs):
        fg, f = original_pcf(*args, **kwargs)
        captured["fun_and_grad"], captured["fun"] = fg, f
        return fg, f

    def minimize(fun_and_grad, *args, **kwargs):
        captured.setdefault("fun_and_grad", fun_and_grad)
        return original_min(fun_and_grad, *args, **kwargs)

    ml_module.penalised_cost_functions, ml_module.minimize_bfgs = pcf, minimize
    try:
        yield captured
    finally:
        ml_module.penalised_cost_functions, ml_module.minimize_bfgs = original_pcf, original_min


def work_scaling(durations_s: list[float], reps: list[int], seed: int) -> dict:
    """Median time of one cost+gradient and one cost evaluation at θ₀ per session size."""
    import tracemalloc

    import numpy as np

    from magcal.calib import cost, native

    rows = []
    for duration_s, n_rep in zip(durations_s, reps, strict=True):
        session = _session(duration_s, seed)
        _, _, data, theta0 = _ml_problem(session)
        n = len(data)
        _log(f"  {n} samples: {n_rep} repetitions")
        tape = native.new_tape(n)
        cost.cost_and_gradient(theta0, data, tape)  # warm-up: page in the tape and the data
        t_cg, t_c = [], []
        for _ in range(n_rep):
            t0 = time.perf_counter()
            cost.cost_and_gradient(theta0, data, tape)
            t_cg.append(time.perf_counter() - t0)
            t0 = time.perf_counter()
            cost.cost(theta0, data)
            t_c.append(time.perf_counter() - t0)
        # What one evaluation allocates on the Python/numpy side (the C kernel has no heap
        # allocations): with no tape passed in, this includes the tape itself.
        tracemalloc.start()
        cost.cost_and_gradient(theta0, data)
        cg_alloc = tracemalloc.get_traced_memory()[1]
        tracemalloc.reset_peak()
        cost.cost(theta0, data)
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


def run_all(config: BenchConfig, cpu: int | None) -> dict:
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
        _log(f"1/4 full calibration, cold process, run {i + 1}/{config.calib_runs}")
        r = run_worker(
            "calibrate",
            {"duration_s": config.calib_duration_s, "seed": SEED, "warm": False},
            cpu,
        )
        _log(f"  total {r['wall_s']:.2f} s, peak RSS {r['peak_rss_mb']:.0f} MB")
        runs.append(r)
    # In a process of its own, so that the cold runs' process times and memory stay clean.
    _log("1/4 full calibration twice in one process (for the warm figure)")
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
        "cvxpy_imported_before_calibrate": median["cvxpy_imported_before_calibrate"],
        "simulate_s": median["simulate_s"],
        "process_wall_s": median["process_wall_s"],
        "warm_wall_s": warm["warm_wall_s"],
        "warm_stages_s": warm["warm_stages_s"],
    }
    results["memory"] = {
        "peak_rss_mb": max(r["peak_rss_mb"] for r in runs),
        "peak_rss_before_calibrate_mb": max(r["peak_rss_before_calibrate_mb"] for r in runs),
    }

    _log("2/4 import times (fresh process)")
    results["imports"] = run_worker("imports", {}, cpu)
    results["imports"].pop("versions", None)

    per_seed = []
    for seed in config.compare_seeds:
        _log(
            f"3/4 exact vs numeric gradient, {config.compare_duration_s:g} s session, "
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

    _log("4/4 scaling of one cost(+gradient) evaluation")
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

    results["targets"] = targets(results)
    results["bench_wall_s"] = time.perf_counter() - started
    return results


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
    """Issue 3's targets, each {value, target, pass}. Reported, never asserted."""
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


# --------------------------------------------------------------------------------------
# Output


def _pf(ok: bool) -> str:
    return "PASS" if ok else "FAIL"


def _fmt(value, fmt: str) -> str:
    return "-" if value is None else fmt.format(value)


def _format_compare(cmp_: dict, tg: dict) -> list[str]:
    """Section 3: the first seed in detail, then one line per seed and the medians."""
    d = cmp_["per_seed"][0]
    out = [
        f"3. Exact vs numeric gradient, {cmp_['duration_s']:g} s sessions, seeds "
        + ", ".join(str(s) for s in cmp_["seeds"])
        + "; each pair from the same θ₀",
        f"   seed {d['seed']} in detail ({d['samples']:,} samples; shared init "
        f"{d['init_s']:.2f} s, after importing cvxpy):",
        f"   {'':<34}{'exact':>16}{'numeric':>16}",
    ]
    cols = [d["runs"][k] for k in COMPARE_RUNS]
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
        f"   {'speed-up, ML step, median':<34}{cmp_['speedup_ml_median']:8.1f} x  target >= "
        f"{TARGET_SPEEDUP:g} x  {_pf(tg['speedup_ml_median']['pass'])}",
        f"   {'  per gradient evaluation':<34}"
        f"{_fmt(cmp_['speedup_per_gradient_evaluation_median'], '{:8.1f}')} x",
        f"   {'final cost rel. difference, max':<34}{cmp_['final_cost_rel_diff_max']:8.1e}"
        f"    target <= {TARGET_COST_REL_DIFF:g}  {_pf(tg['final_cost_rel_diff_max']['pass'])}",
    ]
    return out


def format_table(res: dict) -> str:
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
        f"Python {m['python']}, numpy {m['numpy']}; preset '{PRESET}', seed {SEED}",
        "",
        f"1. Full ML calibration (pipeline.calibrate), {cal['samples']:,} samples, cold "
        f"process, median of {cal['runs']}",
        f"   {'total wall':<34}{cal['wall_s']:8.2f} s   target <= {TARGET_CALIBRATION_S:g} s"
        f"   {_pf(tg['calibration_wall_s']['pass'])}",
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
    for k in STAGES:
        out.append(f"   {'  ' + labels[k]:<34}{cal['stages_s'][k]:8.2f} s")
    opt = cal["optimizer"]
    out += [
        f"   {'  (init total)':<34}{cal['init_s']:8.2f} s",
        f"   optimiser: {opt['iterations']} iterations, {opt['gradient_evaluations']} "
        f"cost+gradient evaluations, stopped on '{opt['stopping_rule']}', "
        f"final cost {opt['final_cost']:.6f}",
        f"   not in the total: import magcal {cal['import_s']:.2f} s, simulation "
        f"{cal['simulate_s']:.2f} s; whole process {cal['process_wall_s']:.2f} s",
        f"   cvxpy import ({res['imports']['cvxpy_s']:.2f} s in a fresh process) is "
        + (
            "paid inside 'init: ellipsoid SDP'"
            if not cal["cvxpy_imported_before_calibrate"]
            else "paid before calibrate (in the import)"
        ),
    ]
    if cal["warm_wall_s"] is not None:
        out.append(
            f"   warm (second calibration, same process): {cal['warm_wall_s']:.2f} s, "
            f"ellipsoid {cal['warm_stages_s']['ellipsoid']:.2f} s"
        )
    out += [
        "",
        "2. Peak memory of the calibration process",
        f"   {'max RSS':<34}{mem['peak_rss_mb']:8.0f} MB  target <= {TARGET_PEAK_RSS_MB:g} MB"
        f"  {_pf(tg['peak_rss_mb']['pass'])}",
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


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", help="write the machine-readable results here (JSON)")
    ap.add_argument("--cpu", type=int, default=None, help="CPU to pin to (default: lowest)")
    ap.add_argument("--smoke", action="store_true", help="tiny sizes; only checks it runs")
    ap.add_argument("--show", nargs="+", metavar="JSON", help="print headline figures only")
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
    results = run_all(SMOKE_CONFIG if args.smoke else BenchConfig(), cpu)
    print(format_table(results))
    if args.out:
        Path(args.out).write_text(json.dumps(results, indent=1, sort_keys=False) + "\n")
        _log(f"results written to {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
