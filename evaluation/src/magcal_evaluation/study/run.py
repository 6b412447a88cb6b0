# SPDX-License-Identifier: Apache-2.0
"""Running (or resuming) a study in its folder: the tasks of
:mod:`magcal_evaluation.study.experiments` through :mod:`magcal_evaluation.study.runner`, then
``summary.md`` and the figures of :mod:`magcal_evaluation.study.summary`."""

from __future__ import annotations

import datetime
import os
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TextIO

from magcal_evaluation.study.experiments import (
    EXPERIMENTS,
    STUDY_METHODS,
    StudySettings,
    StudySettingsError,
    describe_build,
    make_settings,
    run_task,
    tasks,
)
from magcal_evaluation.study.runner import (
    RunStore,
    StudyError,
    StudyProgress,
    run_tasks,
    write_text_atomic,
)
from magcal_evaluation.study.summary import (
    SUMMARY_FILE,
    StudySummary,
    render_markdown,
    summarise,
    write_figures,
)

__all__ = [
    "EXPERIMENTS",
    "STUDY_METHODS",
    "StudyError",
    "StudyOutcome",
    "StudySettings",
    "StudySettingsError",
    "make_settings",
    "run_study",
]


@dataclass(frozen=True)
class StudyOutcome:
    """summary: the numbers; files: what was written; runs_now / runs_before: runs done by
    this call / found saved; wall_s: this call's wall time."""

    summary: StudySummary
    files: list[Path]
    runs_now: int
    runs_before: int
    wall_s: float


def run_study(
    folder: str | os.PathLike,
    settings: StudySettings,
    *,
    jobs: int,
    notes: list[str] | None = None,
    command: str = "magcal study",
    stream: TextIO | None = None,
    on_record: Callable[[dict], None] | None = None,
) -> StudyOutcome:
    """Run (or resume) the study in ``folder`` and write its summary and figures there.

    jobs      : worker processes (1: in this process)
    notes     : lines for the summary (what this build cannot run, from make_settings)
    command   : the command line to name in the summary
    on_record : called after each run is saved (tests interrupt through it)
    Raises StudyError for a folder holding other settings; on Ctrl-C the finished runs are
    saved and KeyboardInterrupt propagates.
    """
    folder = Path(folder)
    stream = stream or sys.stderr
    store = RunStore.open(folder, settings.as_json())
    todo = tasks(settings)
    keys = {t.key for t in todo}
    saved = [r for k, r in store.records.items() if k in keys]
    progress = StudyProgress(
        len(todo),
        len(saved),
        sum("crashed" in r or r["result"].get("failed", False) for r in saved),
        stream,
    )
    t0 = time.perf_counter()
    try:
        runs_now = run_tasks(
            todo, store, run_task, jobs=jobs, progress=progress, on_record=on_record
        )
    except KeyboardInterrupt:
        have = sum(k in store.records for k in keys)
        progress.message(
            f"study: {have} of {len(todo)} runs are saved in {store.runs_path}; run the same "
            "command again to resume"
        )
        raise
    finally:
        progress.finish()
        store.close()
    wall_s = time.perf_counter() - t0

    records = [store.records[k] for k in sorted(keys)]
    summary = summarise(settings, records)
    files = write_figures(folder, summary, records)
    meta = {
        "command": command,
        "date": datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC"),
        "build": describe_build(),
        "wall_s": wall_s,
        "runs_now": runs_now,
        "runs_before": len(saved),
        "jobs": jobs,
        "cores": os.cpu_count(),
        "notes": list(notes or []),
    }
    write_text_atomic(folder / SUMMARY_FILE, render_markdown(summary, meta))
    files.append(folder / SUMMARY_FILE)
    return StudyOutcome(summary, files, runs_now, len(saved), wall_s)
