# SPDX-License-Identifier: Apache-2.0
"""magcal study: a tiny study writes its files; interrupted and resumed it gives the same
summary without redoing runs; other settings are refused; runs are deterministic per seed;
failures are counted; the Markdown tables hold the runs' numbers."""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import re
import shlex
import subprocess
import sys

import numpy as np
import pytest

from magcal import cli
from magcal.sim.scenarios import PRESETS, ScenarioConfig
from magcal_evaluation.study import experiments as ex
from magcal_evaluation.study.run import StudyError, StudySettingsError, make_settings, run_study
from magcal_evaluation.study.runner import RUNS_FILE, SETTINGS_FILE, Task
from magcal_evaluation.study.summary import SUMMARY_FILE

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"

#: The smallest study that still exercises every experiment this build can run.
TINY = {"runs": 2, "zhao_runs": 2, "scenarios": ("table2",)}


def tiny_settings(**overrides):
    return make_settings(**{**TINY, **overrides})[0]


def saved_records(folder) -> list[dict]:
    lines = (folder / RUNS_FILE).read_text(encoding="utf-8").splitlines()
    return [json.loads(line) for line in lines]


def timeless(value):
    """A summary as plain data without the measured times (``seconds*`` fields); NaN as a
    string so that equal summaries compare equal."""
    if dataclasses.is_dataclass(value):
        value = dataclasses.asdict(value)
    if isinstance(value, dict):
        return {k: timeless(v) for k, v in value.items() if not k.startswith("seconds")}
    if isinstance(value, list | tuple):
        return [timeless(v) for v in value]
    if isinstance(value, float) and math.isnan(value):
        return "nan"
    return value


def without_seconds(result: dict) -> dict:
    return {k: v for k, v in result.items() if k != "seconds"}


def table(markdown: str, heading: str) -> tuple[list[str], list[list[str]]]:
    """The first Markdown table after ``heading``: its column heads and its rows' cells."""
    after = markdown[markdown.index(heading) :]
    lines = [line for line in after.splitlines() if line.startswith("|")]
    start = after.splitlines().index(lines[0])
    rows = []
    for line in after.splitlines()[start:]:
        if not line.startswith("|"):
            break
        rows.append([c.strip() for c in line.strip("|").split("|")])
    return rows[0], rows[2:]


@pytest.fixture(scope="module")
def straight(tmp_path_factory):
    """The tiny study run once, uninterrupted, with 2 jobs."""
    folder = tmp_path_factory.mktemp("straight")
    settings = tiny_settings()
    outcome = run_study(folder, settings, jobs=2)
    return folder, settings, outcome


def test_tiny_study_writes_its_files(straight):
    folder, settings, outcome = straight
    n_tasks = len(ex.tasks(settings))
    assert outcome.runs_now == n_tasks and outcome.runs_before == 0
    records = saved_records(folder)
    assert sorted(r["key"] for r in records) == sorted(t.key for t in ex.tasks(settings))
    assert json.loads((folder / SETTINGS_FILE).read_text())["runs"] == 2
    pngs = [p for p in outcome.files if p.suffix == ".png"]
    assert {p.name for p in pngs} >= {"figure8.png", "comparison.png"}
    if "zhao-table1" in settings.experiments:
        assert "zhao_figure1.png" in {p.name for p in pngs}
    for p in pngs:
        assert p.read_bytes()[:8] == PNG_MAGIC
    text = (folder / SUMMARY_FILE).read_text(encoding="utf-8")
    assert "## Kok & Schön (2016), Figure 8" in text
    assert "## All methods on the same sessions" in text
    # Runs may fail (the CKF refuses some Table 2 sessions): each is counted, none is lost.
    assert outcome.summary.failed == sum("crashed" in r or r["result"]["failed"] for r in records)


def test_interrupted_then_resumed_equals_uninterrupted_and_redoes_nothing(
    straight, tmp_path, monkeypatch
):
    _, settings, reference = straight
    total = len(ex.tasks(settings))

    def interrupt_after_two(record, seen=[]):  # noqa: B006 - a counter local to this test
        seen.append(record["key"])
        if len(seen) == 2:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        run_study(tmp_path, settings, jobs=2, on_record=interrupt_after_two)
    first = saved_records(tmp_path)
    # The two seen, and those in progress when the interrupt came, are saved; not all.
    assert 2 <= len(first) < total

    calls = []
    for name, run in list(ex.RUNS.items()):

        def counted(params, run=run, name=name):
            calls.append((name, dict(params)))
            return run(params)

        monkeypatch.setitem(ex.RUNS, name, counted)
    resumed = run_study(tmp_path, settings, jobs=1)

    assert len(calls) == total - len(first) == resumed.runs_now
    assert resumed.runs_before == len(first)
    done_first = {(r["experiment"], json.dumps(r["params"], sort_keys=True)) for r in first}
    redone = [c for c in calls if (c[0], json.dumps(c[1], sort_keys=True)) in done_first]
    assert redone == []
    keys = [r["key"] for r in saved_records(tmp_path)]
    assert len(keys) == len(set(keys)) == total
    assert timeless(resumed.summary) == timeless(reference.summary)


def test_rerun_of_a_finished_study_runs_nothing(straight, tmp_path):
    folder, settings, reference = straight
    again = run_study(folder, settings, jobs=2)
    assert again.runs_now == 0 and again.runs_before == len(ex.tasks(settings))
    assert timeless(again.summary) == timeless(reference.summary)


def test_resume_with_other_settings_is_refused(straight):
    folder, settings, _ = straight
    before = (folder / RUNS_FILE).read_bytes()
    with pytest.raises(StudyError, match=r"other settings \(runs 2 there, 4 now\).*another folder"):
        run_study(folder, tiny_settings(runs=4), jobs=1)
    with pytest.raises(StudyError, match=r"seed 1 there, 7 now"):
        run_study(folder, tiny_settings(seed=7), jobs=1)
    assert (folder / RUNS_FILE).read_bytes() == before


def test_cli_refuses_other_settings_in_one_paragraph(straight, capsys):
    folder, *_ = straight
    argv = ["study", str(folder), "--runs", "5", "--scenarios", "table2", "--zhao-runs", "2"]
    assert cli.main(argv) == cli.EXIT_ERROR
    # Notes on what this build cannot run may come first; the refusal is one line.
    last = capsys.readouterr().err.splitlines()[-1]
    assert last.startswith("magcal study: ") and "runs 2 there, 5 now" in last
    assert "Traceback" not in last


@pytest.mark.parametrize(
    "task",
    [
        Task("figure8/seed=4", "figure8", {"seed": 4}),
        Task(
            "comparison/table2/ml/seed=4",
            "comparison",
            {"scenario": "table2", "method": "ml", "seed": 4},
        ),
    ],
    ids=["figure8", "comparison"],
)
def test_a_run_depends_only_on_its_task(task):
    a, b = ex.run_task(task), ex.run_task(task)
    assert without_seconds(a) == without_seconds(b)
    other = ex.run_task(dataclasses.replace(task, params={**task.params, "seed": 5}))
    assert without_seconds(other) != without_seconds(a)


def test_failures_are_counted_with_their_reason(tmp_path, monkeypatch):
    # A scenario the observability checks must refuse (yaw-only motion), and a run that
    # crashes outright: the study finishes and counts both, with reasons.
    monkeypatch.setitem(
        PRESETS, "yaw-only-test", ScenarioConfig(kind="mems", duration_s=10.0, motion="yaw-only")
    )
    real_figure8 = ex.RUNS["figure8"]

    def crash_on_seed_2(params):
        if params["seed"] == 2:
            raise FloatingPointError("simulated crash")
        return real_figure8(params)

    monkeypatch.setitem(ex.RUNS, "figure8", crash_on_seed_2)
    settings, _ = make_settings(
        runs=2, experiments=("figure8", "comparison"), scenarios=("yaw-only-test",)
    )
    outcome = run_study(tmp_path, settings, jobs=2)

    s = outcome.summary
    assert s.figure8.runs == 2 and s.figure8.failed == 1
    assert s.figure8.reasons[0].seeds == (2,)
    assert "FloatingPointError: simulated crash" in s.figure8.reasons[0].text
    for row in s.comparison:
        assert (row.runs, row.ok, row.refused, row.exceptions) == (2, 0, 2, 0)
        assert row.reasons[0].text.startswith("refused: ")
    assert s.failed == 1 + 2 * len(settings.methods)
    text = (tmp_path / SUMMARY_FILE).read_text(encoding="utf-8")
    assert "simulated crash" in text and "refused: " in text


def test_markdown_tables_hold_the_runs_numbers(straight):
    folder, settings, _ = straight
    text = (folder / SUMMARY_FILE).read_text(encoding="utf-8")
    records = saved_records(folder)

    head, rows = table(text, "### table2 ")
    assert head == [
        "method",
        "runs",
        "calibrated",
        "exceptions",
        "refused",
        "heading error, median [°]",
        "90th percentile [°]",
        "max [°]",
        "/ floor",
        "s per run, median",
    ]
    assert [r[0] for r in rows] == list(settings.methods)
    checked = 0
    for row in rows:
        mine = [
            r["result"]
            for r in records
            if r["experiment"] == "comparison" and r["params"]["method"] == row[0]
        ]
        ok = [r for r in mine if not r["failed"]]
        refused = sum(bool(r.get("refused")) for r in mine)
        counts = [len(mine), len(ok), len(mine) - len(ok) - refused, refused]
        assert row[1:5] == [str(n) for n in counts]
        assert row[9] == f"{np.median([r['seconds'] for r in mine]):.3f}"
        if not ok:
            assert row[5:9] == ["–"] * 4
            continue
        heading = np.array([r["heading_deg"] for r in ok])
        ratio = np.array([r["heading_deg"] / r["floor_deg"] for r in ok])
        assert row[5] == f"{np.median(heading):.3g}"
        assert row[7] == f"{heading.max():.3g}"
        assert row[8] == f"{np.median(ratio):.2f}"
        checked += 1
    assert checked >= 2  # init and ml at least

    head, rows = table(text, "## Kok & Schön (2016), Figure 8")
    fig8 = [r["result"] for r in records if r["experiment"] == "figure8"]
    assert [r[0] for r in rows] == [
        "initial (Algorithm 1, step 1)",
        "ML (Algorithm 1)",
        "known-attitude floor",
    ]
    assert rows[0][1] == f"{np.median([r['ekf_init_deg'] for r in fig8]):.3g}"
    assert rows[1][1] == f"{np.median([r['ekf_ml_deg'] for r in fig8]):.3g}"
    assert rows[1][3] == f"{np.median([r['ml_deg'] for r in fig8]):.3g}"
    assert rows[2][3] == f"{np.median([r['floor_deg'] for r in fig8]):.3g}"


def test_cli_runs_a_study(tmp_path, capsys):
    argv = ["study", str(tmp_path), "--runs", "1", "--experiments", "comparison"]
    argv += ["--scenarios", "table2", "--jobs", "1"]
    assert cli.main(argv) == 0
    out = capsys.readouterr().out
    assert f"wrote {tmp_path / SUMMARY_FILE}" in out
    assert re.search(r"\d+ runs \(\d+ now, 0 resumed\), \d+ failed", out)
    # The command the summary names resumes this study: nothing left to run.
    text = (tmp_path / SUMMARY_FILE).read_text(encoding="utf-8")
    command = re.search(r"Made by `magcal ([^`]*)`", text).group(1)
    assert cli.main(shlex.split(command)) == 0
    assert re.search(r"\d+ runs \(0 now, [1-9]\d* resumed\)", capsys.readouterr().out)


@pytest.mark.parametrize(
    ("kwargs", "pattern"),
    [
        ({"experiments": ("figure9",)}, r"unknown experiment\(s\) figure9; choose from"),
        ({"scenarios": ("moon",)}, r"unknown scenario\(s\) moon; choose from"),
        ({"runs": 0}, r"--runs and --zhao-runs must be ≥ 1"),
        ({"experiments": ()}, r"no experiment given"),
    ],
)
def test_bad_settings_are_refused(kwargs, pattern):
    with pytest.raises(StudySettingsError, match=pattern):
        make_settings(**kwargs)


def test_comparison_methods_follow_what_calibrate_accepts(monkeypatch):
    import magcal.calib.calibrate as pipeline

    monkeypatch.setattr(pipeline, "METHODS", ("ml", "init", "ckf"))
    settings, notes = make_settings(experiments=("comparison",))
    assert settings.methods == ("init", "ml", "ckf")
    assert any("two-step" in n for n in notes)


def test_zhao_table_holds_the_mean_estimates(straight):
    folder, settings, outcome = straight
    if "zhao-table1" not in settings.experiments:
        pytest.skip("this build has no CKF and TWO-STEP")
    from magcal_evaluation.study import zhao

    records = [r["result"] for r in saved_records(folder) if r["experiment"] == "zhao-table1"]
    text = (folder / SUMMARY_FILE).read_text(encoding="utf-8")
    head, rows = table(text, "## Zhao et al., Table 1")
    assert head == ["", "true", "CKF (ours)", "TWO-STEP (ours)", "CKF (paper)", "TWO-STEP (paper)"]
    for col, name in ((2, "ckf"), (3, "two-step")):
        A = np.mean([r[name]["A"] for r in records], axis=0)
        b = np.mean([r[name]["b"] for r in records], axis=0)
        for i in range(3):
            expected = " ".join(f"{x:.3f}" for x in A[i]) + f" &#124; {b[i]:.3f}"
            assert rows[i][col] == expected
        # Recovery on seeded data: at the paper's σ (10 % of the field) both estimators
        # shrink A by a few per cent (errors in variables); b is unbiased.
        assert np.max(np.abs(A - zhao.TRUE_A)) < 0.1
        assert np.max(np.abs(b - zhao.TRUE_B_G)) < 0.02
    for m in outcome.summary.zhao.methods:
        assert (m.ok, m.failed) == (settings.zhao_runs, 0)


def test_settings_without_the_comparison_record_no_methods():
    settings, notes = make_settings(experiments=("figure8",))
    assert settings.methods == () and settings.scenarios == ()
    assert not any(n.startswith("method(s)") for n in notes)


def test_jobs_default_to_the_cpus_this_process_may_use(monkeypatch):
    import os

    from magcal_evaluation.study import command as study_command

    monkeypatch.setattr(os, "cpu_count", lambda: 64)
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: {0, 3}, raising=False)
    args = cli.build_parser().parse_args(["study", "out"])
    assert args.jobs == 2  # the affinity mask (a container's or taskset's limit), not 64
    monkeypatch.delattr(os, "sched_getaffinity")
    assert study_command.available_cpus() == 64  # platforms without affinity masks


def test_the_command_module_loads_no_numerical_code():
    # magcal's command line loads it for every `magcal --help`; the experiments load when run.
    code = (
        "import sys, magcal_evaluation.study.command\n"
        "print(' '.join(m for m in ('numpy', 'scipy', 'matplotlib') if m in sys.modules))"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    assert done.stdout.split() == []


def test_study_is_registered_in_the_magcal_commands_entry_point_group():
    # magcal's command line adds every command of this group; the product has no study.
    from importlib.metadata import entry_points

    found = {ep.name: ep for ep in entry_points(group="magcal.commands")}
    assert found["study"].value == "magcal_evaluation.study.command"
    module = found["study"].load()
    sub = argparse.ArgumentParser().add_subparsers(dest="command")
    module.add_parser(sub)
    args = sub.choices["study"].parse_args(["out", "--runs", "3"])
    assert (args.outdir, args.runs, args.run) == ("out", 3, module.run)
