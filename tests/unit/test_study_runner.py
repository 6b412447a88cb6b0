# SPDX-License-Identifier: Apache-2.0
"""The study runner's folder: settings checked, runs saved one per line, a torn last line
redone, damage elsewhere refused, progress on one line."""

from __future__ import annotations

import io
import json

import numpy as np
import pytest

from magcal_evaluation.study.runner import (
    RUNS_FILE,
    SETTINGS_FILE,
    RunStore,
    StudyError,
    StudyProgress,
    Task,
    execute_guarded,
    run_tasks,
)

SETTINGS = {"format": "test/1", "runs": 3}


def square(task: Task) -> dict:
    x = task.params["x"]
    if x < 0:
        raise ValueError(f"negative {x}")
    return {"square": x * x, "failed": False}


def tasks(n: int) -> list[Task]:
    return [Task(f"sq/{i}", "sq", {"x": i}) for i in range(n)]


def test_saved_runs_are_skipped_and_each_line_is_one_run(tmp_path):
    store = RunStore.open(tmp_path, SETTINGS)
    assert run_tasks(tasks(3), store, square, jobs=1) == 3
    store.close()
    store = RunStore.open(tmp_path, SETTINGS)
    assert set(store.records) == {"sq/0", "sq/1", "sq/2"}
    assert run_tasks(tasks(5), store, square, jobs=2) == 2
    store.close()
    lines = (tmp_path / RUNS_FILE).read_text().splitlines()
    assert sorted(json.loads(x)["key"] for x in lines) == [f"sq/{i}" for i in range(5)]
    assert {json.loads(x)["result"]["square"] for x in lines} == {0, 1, 4, 9, 16}


def test_a_torn_last_line_is_dropped_and_its_run_redone(tmp_path):
    store = RunStore.open(tmp_path, SETTINGS)
    run_tasks(tasks(2), store, square, jobs=1)
    store.close()
    path = tmp_path / RUNS_FILE
    with open(path, "a", encoding="utf-8") as f:
        f.write('{"key": "sq/2", "experiment": "sq", "res')  # the write cut short
    store = RunStore.open(tmp_path, SETTINGS)
    assert set(store.records) == {"sq/0", "sq/1"}
    assert path.read_text().endswith("}\n")  # cut back to the last whole line
    assert run_tasks(tasks(3), store, square, jobs=1) == 1
    store.close()
    assert len(path.read_text().splitlines()) == 3


def test_a_damaged_line_before_the_end_is_refused(tmp_path):
    store = RunStore.open(tmp_path, SETTINGS)
    run_tasks(tasks(3), store, square, jobs=1)
    store.close()
    path = tmp_path / RUNS_FILE
    lines = path.read_text().splitlines()
    lines[1] = "not json"
    path.write_text("\n".join(lines) + "\n")
    with pytest.raises(StudyError, match=r"runs.jsonl line 2 is not a run record.*delete"):
        RunStore.open(tmp_path, SETTINGS)


def test_other_settings_are_refused_and_named(tmp_path):
    RunStore.open(tmp_path, SETTINGS).close()
    with pytest.raises(StudyError, match=r"other settings \(runs 3 there, 4 now\)"):
        RunStore.open(tmp_path, {**SETTINGS, "runs": 4})
    with pytest.raises(StudyError, match=r"extra null there, 1 now"):
        RunStore.open(tmp_path, {**SETTINGS, "extra": 1})
    assert json.loads((tmp_path / SETTINGS_FILE).read_text()) == SETTINGS


def test_a_folder_that_is_a_file_is_refused(tmp_path):
    (tmp_path / "f").write_text("x")
    with pytest.raises(StudyError, match="is a file, not a folder"):
        RunStore.open(tmp_path / "f", SETTINGS)


def test_a_raising_run_is_a_counted_crash_in_a_worker_too(tmp_path):
    store = RunStore.open(tmp_path, SETTINGS)
    progress = StudyProgress(4, 0, 0, io.StringIO())
    run_tasks([Task("neg", "sq", {"x": -2}), *tasks(3)], store, square, jobs=2, progress=progress)
    store.close()
    assert store.records["neg"]["crashed"] == "ValueError: negative -2"
    assert "result" not in store.records["neg"]
    assert progress.failed == 1 and progress.done == 4


def test_non_finite_numbers_and_numpy_values_are_saved_as_json(tmp_path):
    store = RunStore.open(tmp_path, SETTINGS)
    store.append(
        {"key": "k", "result": {"a": float("nan"), "b": np.float64(2.5), "c": np.arange(2)}}
    )
    store.close()
    line = (tmp_path / RUNS_FILE).read_text()
    assert json.loads(line)["result"] == {"a": None, "b": 2.5, "c": [0, 1]}


def test_execute_guarded_times_and_keeps_the_task():
    rec = execute_guarded(square, Task("k", "sq", {"x": 3}))
    assert rec["key"] == "k" and rec["params"] == {"x": 3} and rec["result"]["square"] == 9
    assert rec["seconds"] >= 0.0


def test_progress_line_counts_and_estimates():
    stream = io.StringIO()
    p = StudyProgress(10, 4, 1, stream)
    assert p.line().startswith("study: 4/10 runs (4 saved before), 1 failed, 0:00 elapsed, ETA –")
    p.update({"key": "a", "crashed": "x"})
    assert "5/10 runs" in p.line() and "2 failed" in p.line()
    assert "ETA 0:00" in p.line()  # one new run took ~0 s, so the rest takes ~0 s


def test_progress_in_a_log_is_whole_lines_at_each_step_and_the_end():
    stream = io.StringIO()
    p = StudyProgress(20, 0, 0, stream)
    p.update()
    for i in range(20):
        p.update({"key": str(i), "crashed": "x"} if i == 3 else {"key": str(i), "result": {}})
    p.finish()
    lines = stream.getvalue().splitlines()
    # The first state, then one line per PROGRESS_LOG_STEP_PCT (10 %: every 2 runs of 20).
    assert lines[0].startswith("study: 0/20 runs, 0 failed")
    assert lines[-1].startswith("study: 20/20 runs, 1 failed")
    assert len(lines) == 11
    assert all("\r" not in line and "\x1b" not in line for line in lines)
