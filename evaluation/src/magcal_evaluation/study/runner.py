# SPDX-License-Identifier: Apache-2.0
"""A resumable, parallel runner for independent seeded runs.

A study is a list of :class:`Task`\\ s, each with a unique key. :func:`run_tasks` runs the ones
that are not yet in the :class:`RunStore` on a process pool, appends each finished run to
``runs.jsonl`` as one JSON line (flushed and fsynced before the next is taken), and shows one
progress line on stderr. Interrupted (Ctrl-C), it lets the runs in progress finish and saves
them too; the next call with the same settings skips every saved key. A run's record depends
only on its task, never on the job count or the order, so an interrupted and resumed study
ends with the same records as an uninterrupted one (apart from the measured times).

Files in the study folder:

- ``settings.json``: what the study is (written once, atomically). Resuming with other
  settings is refused, so one folder never mixes two studies.
- ``runs.jsonl``: one finished run per line: ``{"key", "experiment", "params", "seconds",
  "result"}``, or ``"crashed"`` (the exception text) instead of ``"result"`` when the run
  itself raised. A torn last line (the machine stopped mid-write) is dropped and that run
  redone.
"""

from __future__ import annotations

import ctypes
import json
import math
import os
import signal
import sys
import time
from collections.abc import Callable, Iterable, Mapping
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass, field
from pathlib import Path
from typing import TextIO

import numpy as np

from magcal.errors import MagcalError
from magcal.ui import ProgressBar

SETTINGS_FILE = "settings.json"
RUNS_FILE = "runs.jsonl"
#: Without a terminal, a progress line is printed each time this share of the runs is done, %.
PROGRESS_LOG_STEP_PCT = 10.0
#: prctl(2) option: the signal a process gets when its parent dies (linux/prctl.h).
PR_SET_PDEATHSIG = 1


class StudyError(MagcalError):
    """A study folder cannot be used: other settings, a damaged runs file, a dead worker."""


@dataclass(frozen=True)
class Task:
    """One run: ``key`` is unique within the study; ``params`` (JSON values only) is all that
    the experiment's run function needs, so the record is a function of the task alone."""

    key: str
    experiment: str
    params: Mapping[str, object] = field(default_factory=dict)


def execute_guarded(run: Callable[[Task], dict], task: Task) -> dict:
    """``run(task)`` as a runs-file record: timed, and an exception becomes a counted crash
    (``"crashed"``) instead of stopping the study."""
    t0 = time.perf_counter()
    record: dict = {"key": task.key, "experiment": task.experiment, "params": dict(task.params)}
    try:
        record["result"] = run(task)
    except Exception as exc:  # one run's failure is a finding of the study, not its end
        record["crashed"] = f"{type(exc).__name__}: {exc}"
    record["seconds"] = time.perf_counter() - t0
    return record


def is_failure(record: dict) -> bool:
    """Whether a record counts as a failed run: it crashed, or its result says it failed."""
    return "crashed" in record or bool(record.get("result", {}).get("failed"))


# --------------------------------------------------------------------------------------------
# The study folder


def _json_text(value: object) -> str:
    # NaN and ±inf are not JSON: store them as null so that any reader can load the file.
    return json.dumps(_finite_or_none(value), sort_keys=True, ensure_ascii=False)


def _finite_or_none(value: object) -> object:
    if isinstance(value, np.ndarray | np.generic):
        value = value.tolist()  # numpy scalars and arrays as the plain values they hold
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: _finite_or_none(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_finite_or_none(v) for v in value]
    return value


def write_text_atomic(path: Path, text: str) -> None:
    """Write ``text`` to ``path`` so that a reader sees the old or the new file, never half."""
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "w", encoding="utf-8") as f:
        f.write(text)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)


class RunStore:
    """The runs saved in a study folder; :meth:`append` saves one more, durably."""

    def __init__(self, folder: Path, records: dict[str, dict]):
        self.folder = folder
        self.records = records
        self._file: TextIO | None = None

    @property
    def runs_path(self) -> Path:
        return self.folder / RUNS_FILE

    @classmethod
    def open(cls, folder: str | os.PathLike, settings: Mapping[str, object]) -> RunStore:
        """Open (or start) the study in ``folder`` with ``settings`` (JSON values).

        Raises :class:`StudyError` when the folder holds a study with other settings, or a
        runs file damaged anywhere but in its last line.
        """
        folder = Path(folder)
        try:
            folder.mkdir(parents=True, exist_ok=True)
        except FileExistsError:
            raise StudyError(f"study: {folder} is a file, not a folder: give a folder") from None
        except OSError as exc:
            raise StudyError(f"study: cannot create the folder {folder} ({exc})") from exc
        _check_or_write_settings(folder / SETTINGS_FILE, settings)
        return cls(folder, _read_runs(folder / RUNS_FILE))

    def append(self, record: dict) -> None:
        """Save ``record`` as one line, on disk (flushed and fsynced) before returning."""
        if self._file is None:
            self._file = open(self.runs_path, "a", encoding="utf-8")
        self._file.write(_json_text(record) + "\n")
        self._file.flush()
        os.fsync(self._file.fileno())
        self.records[record["key"]] = json.loads(_json_text(record))

    def close(self) -> None:
        if self._file is not None:
            self._file.close()
            self._file = None


def _check_or_write_settings(path: Path, settings: Mapping[str, object]) -> None:
    wanted = json.loads(_json_text(dict(settings)))
    if not path.exists():
        write_text_atomic(path, json.dumps(wanted, indent=1, sort_keys=True) + "\n")
        return
    try:
        saved = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:
        raise StudyError(
            f"study: cannot read {path} ({exc}): it is not a study's settings file; use an "
            "empty folder"
        ) from exc
    if saved == wanted:
        return
    keys = sorted(set(saved) | set(wanted))
    diffs = [
        f"{k} {json.dumps(saved.get(k))} there, {json.dumps(wanted.get(k))} now"
        for k in keys
        if saved.get(k) != wanted.get(k)
    ]
    raise StudyError(
        f"study: {path.parent} holds a study with other settings ({'; '.join(diffs)}). "
        "Resuming would mix two studies: rerun with the settings saved in "
        f"{path} to resume it, or give another folder for a new study"
    )


def _read_runs(path: Path) -> dict[str, dict]:
    """The saved records by key. A torn last line is cut off the file (its run is redone);
    a bad line before it is damage we do not guess about."""
    if not path.exists():
        return {}
    raw = path.read_bytes()
    lines = raw.split(b"\n")
    records: dict[str, dict] = {}
    good_end = 0  # byte offset just past the last complete, valid line
    offset = 0
    for number, line in enumerate(lines, start=1):
        end = offset + len(line) + 1
        complete = end <= len(raw)  # the line has its newline
        if line.strip():
            try:
                record = json.loads(line)
                if not isinstance(record, dict) or not isinstance(record.get("key"), str):
                    raise ValueError("not a run record")
            except (ValueError, UnicodeDecodeError) as exc:
                if complete and any(rest.strip() for rest in lines[number:]):
                    raise StudyError(
                        f"study: {path} line {number} is not a run record ({exc}): the file "
                        "was edited or damaged; delete that line to redo its run"
                    ) from None
                break  # the last line, torn by an interruption
            if not complete:
                break  # valid JSON but no newline: written partly; redo it to be safe
            records[record["key"]] = record
        if complete:
            good_end = end
        offset = end
    if good_end < len(raw):
        with open(path, "r+b") as f:
            f.truncate(good_end)
    return records


# --------------------------------------------------------------------------------------------
# Progress


class StudyProgress:
    """The study's progress on stderr through magcal's one progress display
    (:class:`magcal.ui.ProgressBar`): on a terminal a bar with runs done/total, the rate, the
    time left and the failures so far; in a log the line :meth:`line` (runs done/total,
    failures, elapsed, ETA) at every :data:`PROGRESS_LOG_STEP_PCT` per cent and at the end.
    Runs saved by an earlier, interrupted call count as done but not towards the rate."""

    def __init__(self, total: int, done: int, failed: int, stream: TextIO | None = None):
        self.total, self.done, self.failed = total, done, failed
        self._resumed = done
        self._t0 = time.monotonic()
        self._bar = ProgressBar(
            "study",
            total,
            stream,
            completed=done,
            unit="runs",
            log_step_pct=PROGRESS_LOG_STEP_PCT,
            log_line=lambda _done, _total: self.line(),
        )

    def line(self) -> str:
        elapsed = time.monotonic() - self._t0
        new = self.done - self._resumed
        left = self.total - self.done
        eta = "–" if new == 0 else _clock(elapsed / new * left)
        resumed = f" ({self._resumed} saved before)" if self._resumed else ""
        return (
            f"study: {self.done}/{self.total} runs{resumed}, {self.failed} failed, "
            f"{_clock(elapsed)} elapsed, ETA {eta}"
        )

    def update(self, record: dict | None = None) -> None:
        if record is not None:
            self.done += 1
            self.failed += is_failure(record)
        self._bar.update(self.done, note=f"{self.failed} failed")

    def message(self, text: str) -> None:
        """A line of its own, above the progress display."""
        self._bar.message(text)

    def finish(self) -> None:
        self._bar.close()


def _clock(seconds: float) -> str:
    s = int(round(seconds))
    return (
        f"{s // 3600}:{s // 60 % 60:02d}:{s % 60:02d}" if s >= 3600 else f"{s // 60}:{s % 60:02d}"
    )


# --------------------------------------------------------------------------------------------
# Running


def _init_worker(parent_pid: int) -> None:
    # Ctrl-C goes to the whole process group: the workers leave it to the parent, which
    # stops handing out runs and lets the ones in progress finish (and saves them).
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    _die_with_parent(parent_pid)


def _die_with_parent(parent_pid: int) -> None:
    """On Linux, have the kernel end this worker when the study process dies (killed rather
    than interrupted); otherwise a worker would wait for work forever."""
    if not sys.platform.startswith("linux"):
        return
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(PR_SET_PDEATHSIG, signal.SIGTERM)
    except (OSError, AttributeError):
        return
    if os.getppid() != parent_pid:  # it died before prctl took effect
        os._exit(1)


def run_tasks(
    tasks: Iterable[Task],
    store: RunStore,
    run: Callable[[Task], dict],
    *,
    jobs: int,
    progress: StudyProgress | None = None,
    on_record: Callable[[dict], None] | None = None,
) -> int:
    """Run every task whose key is not in ``store`` and save each record as it finishes.

    run       : the run function, ``Task -> dict`` of JSON values; a module-level function
                (it is sent to the worker processes)
    jobs      : worker processes; 1 runs in this process (no pool)
    on_record : called in this process after each record is saved (the tests interrupt
                through it)
    Returns the number of runs done by this call. On KeyboardInterrupt, the runs in progress
    are finished and saved, then the KeyboardInterrupt propagates.
    """
    pending = [t for t in tasks if t.key not in store.records]
    if progress is not None:
        progress.update()

    def finished(record: dict) -> None:
        store.append(record)
        if progress is not None:
            progress.update(record)
        if on_record is not None:
            on_record(record)

    if jobs <= 1 or len(pending) <= 1:
        for task in pending:
            finished(execute_guarded(run, task))
        return len(pending)

    done = 0
    with ProcessPoolExecutor(
        max_workers=jobs, initializer=_init_worker, initargs=(os.getpid(),)
    ) as pool:
        # Every future stays here until its record is saved, so none is lost on interrupt.
        outstanding: set[Future] = {pool.submit(execute_guarded, run, t) for t in pending}
        try:
            while outstanding:
                ready, _ = wait(outstanding, return_when=FIRST_COMPLETED)
                for fut in ready:
                    outstanding.discard(fut)
                    finished(fut.result())
                    done += 1
        except KeyboardInterrupt:
            unstarted = sum(f.cancel() for f in outstanding)
            running = [f for f in outstanding if not f.cancelled()]
            if progress is not None:
                progress.message(
                    f"study: interrupted; not starting {unstarted} runs, finishing the "
                    f"{len(running)} in progress (they are saved too)"
                )
            try:
                for fut in running:
                    record = fut.result()
                    store.append(record)
                    done += 1
                    if progress is not None:
                        progress.update(record)
            except (BrokenProcessPool, KeyboardInterrupt):
                pass  # a second Ctrl-C: stop waiting; what is saved stays saved
            raise
        except BrokenProcessPool as exc:
            raise StudyError(
                f"study: a worker process died ({exc}); the {len(store.records)} finished "
                f"runs are saved in {store.runs_path}. Rerun with --jobs 1 to see which run "
                "kills it"
            ) from exc
    return done
