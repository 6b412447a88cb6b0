# SPDX-License-Identifier: Apache-2.0
"""bench/run_bench.py runs end to end on tiny sessions (structure only, never timing)."""

import importlib.util
import json
import sys
from pathlib import Path

import numpy as np
import pytest

from magcal.calib.likelihood import mekf

BENCH_DIR = Path(__file__).resolve().parents[2] / "bench"


@pytest.fixture(scope="module")
def bench():
    # As when run as a script: bench/ on sys.path, so that run_bench finds bench/report.py.
    sys.path.insert(0, str(BENCH_DIR))
    spec = importlib.util.spec_from_file_location("run_bench", BENCH_DIR / "run_bench.py")
    module = importlib.util.module_from_spec(spec)
    # dataclasses resolve string annotations through sys.modules, so register it first.
    sys.modules[spec.name] = module
    try:
        spec.loader.exec_module(module)
        yield module
    finally:
        sys.modules.pop(spec.name, None)
        sys.modules.pop("report", None)
        sys.path.remove(str(BENCH_DIR))


TINY_CASE = "tiny_case"


@pytest.fixture(scope="module")
def tiny_realdata(tmp_path_factory):
    """A real-data set of one short simulated case, laid out as ``make real`` reads it
    (cases.json, sessions/CASE.csv, truth/CASE.npz)."""
    from magcal.io.session import write_session
    from magcal.sim.scenarios import preset, simulate

    root = tmp_path_factory.mktemp("realdata")
    session, _ = simulate(preset("mems", duration_s=15.0), 2)
    (root / "sessions").mkdir()
    (root / "truth").mkdir()
    write_session(root / "sessions" / f"{TINY_CASE}.csv", session)
    n = len(session)
    np.savez(
        root / "truth" / f"{TINY_CASE}.npz",
        trial_names=np.array([TINY_CASE]),
        t_0=session.t,
        mag_0=session.mag,
        quat_wxyz_0=np.tile([1.0, 0.0, 0.0, 0.0], (n, 1)),
        valid_0=np.ones(n, dtype=bool),
        declination_deg=np.array([0.0]),
    )
    (root / "cases.json").write_text(json.dumps({TINY_CASE: {"source": "simulated"}}))
    return root


@pytest.fixture(scope="module")
def smoke_results(bench, tmp_path_factory, tiny_realdata):
    out = tmp_path_factory.mktemp("bench") / "results.json"
    try:
        assert bench.main(["--smoke", "--realdata", str(tiny_realdata), "--out", str(out)]) == 0
    except SystemExit as exc:  # a failed worker: report its message, not pytest internals
        pytest.fail(str(exc))
    return out, json.loads(out.read_text())


def test_smoke_run_writes_every_section(smoke_results, bench):
    _, res = smoke_results
    assert res["format"] == bench.RESULTS_FORMAT
    assert res["machine"]["cpu_count"] >= 1
    assert res["machine"]["numpy"]
    cal = res["calibration"]
    assert cal["samples"] > 1000
    assert cal["runs"] == bench.SMOKE_CONFIG.calib_runs
    # The stages as the pipeline recorded them, in its order, which STAGES documents.
    assert list(cal["stages_s"]) == list(bench.STAGES)
    assert list(cal["warm_stages_s"]) == list(bench.STAGES)
    assert cal["wall_s"] > 0 and cal["warm_wall_s"] > 0
    assert cal["optimizer"]["iterations"] >= 1
    assert res["memory"]["peak_rss_mb"] >= res["memory"]["peak_rss_before_calibrate_mb"] > 0
    imports = res["imports"]
    assert imports["total_s"] >= imports["numpy_s"] > 0
    assert set(imports["loaded"]) == set(bench.HEAVY_PACKAGES)
    assert isinstance(cal["imported_during_calibrate"], list)


def test_smoke_compare_starts_every_run_from_the_same_theta0(smoke_results, bench):
    _, res = smoke_results
    cmp_ = res["exact_vs_numeric"]
    assert cmp_["seeds"] == list(bench.SMOKE_CONFIG.compare_seeds)
    (one,) = cmp_["per_seed"]
    assert set(one["runs"]) == set(bench.COMPARE_RUNS)
    for run in one["runs"].values():
        assert run["theta0_identical"]
        assert run["iterations"] <= one["max_iter"]
        assert run["max_scaled_exact_gradient_at_end"] >= 0.0
    assert one["max_scaled_fd_gradient_error_at_optimum"] >= 0.0
    assert one["speedup_per_gradient_evaluation"] > 0.0
    assert cmp_["speedup_ml_median"] == one["speedup_ml"] > 0.0
    assert cmp_["final_cost_rel_diff_max"] == one["final_cost_rel_diff"] >= 0.0


def test_smoke_scaling_rows_and_tape_size(smoke_results, bench):
    _, res = smoke_results
    rows = res["scaling"]["rows"]
    assert len(rows) == len(bench.SMOKE_CONFIG.scaling_durations_s)
    assert rows[0]["samples"] < rows[1]["samples"]
    for r in rows:
        tape_bytes = 8 * mekf.TAPE_DOUBLES_PER_SAMPLE * r["samples"]
        assert r["tape_mb"] == pytest.approx(tape_bytes / 1e6)
        assert r["repetitions"] == len(r["cost_grad_all_s"])
    assert res["scaling"]["loglog_slope_cost_grad"] is not None


def test_smoke_targets_are_reported_not_asserted(smoke_results):
    _, res = smoke_results
    assert set(res["targets"]) == {
        "calibration_wall_s",
        "peak_rss_mb",
        "speedup_ml_median",
        "final_cost_rel_diff_max",
    }
    for row in res["targets"].values():
        assert isinstance(row["pass"], bool)


def test_smoke_optimizers_side_by_side_in_process_and_cold(smoke_results, bench):
    _, res = smoke_results
    opt = res["optimizers"]
    assert opt["real_skipped"] is None
    assert [c["case"] for c in opt["real"]] == [TINY_CASE]
    for case in (opt["simulated"], *opt["real"]):
        assert list(case["runs"]) == list(bench.OPTIMIZERS)
        for run in case["runs"].values():
            assert "error" not in run
            assert run["iterations"] >= 1 and run["ml_s"] > 0
        b, t = case["runs"]["bfgs"], case["runs"]["trust-region"]
        assert b["information_evaluations"] == 0 < t["information_evaluations"]
        assert case["final_cost_diff"] == pytest.approx(t["final_cost"] - b["final_cost"])
    summary = opt["real_summary"]
    assert summary["cases"] == 1
    assert summary["bfgs"]["median_iterations"] == opt["real"][0]["runs"]["bfgs"]["iterations"]
    # The cold command lines: the case's CSV and the simulated session, each optimiser.
    cli = opt["cli"]
    assert list(cli["calibrate"]) == [TINY_CASE, "simulated"]
    for per_session in cli["calibrate"].values():
        for name in bench.OPTIMIZERS:
            assert per_session[name]["exit_codes"] == [0] * cli["reps"]
            assert per_session[name]["median_s"] > 0
    assert cli["help"]["exit_codes"] == [0] * cli["reps"]


def test_missing_realdata_is_skipped_with_the_reason(bench, tmp_path):
    names, skipped = bench.real_case_names(tmp_path / "absent", None)
    assert names == []
    assert skipped.startswith(f"no {tmp_path / 'absent' / 'cases.json'}")
    names, skipped = bench.real_case_names(None, None)
    assert names == [] and "skipped" in skipped


def test_table_and_show_print_the_results(smoke_results, bench, capsys):
    path, res = smoke_results
    table = bench.format_table(res)
    for heading in (
        "1. Full ML calibration",
        "2. Peak memory",
        "3. Exact vs numeric",
        "4. One",
        "7. The ML step's optimisers",
    ):
        assert heading in table
    assert bench.main(["--show", str(path), str(path)]) == 0
    shown = capsys.readouterr().out
    assert "calibration wall (s)" in shown and "peak RSS (MB)" in shown


def test_failing_worker_stops_the_benchmark_with_its_name(bench):
    with pytest.raises(SystemExit, match="worker 'no-such-worker' failed"):
        bench.run_worker("no-such-worker", {}, None)
