# SPDX-License-Identifier: Apache-2.0
"""Recording a calibration session from the device's raw stream.

:func:`collect` starts a raw stream, converts each sample's counts to SI units with the
device's exact count scales, tracks the coverage of field directions
(:mod:`magcal.device.coverage`) and stops at a coverage target, a duration, a sample count or
Ctrl-C (:class:`StopRules`; the loop, :func:`record_stream`, and what it watches,
:class:`CollectMonitor`, serve the MAVLink recorder :mod:`magcal.autopilot.collect` too). It
returns a :class:`CollectResult` holding a :class:`~magcal.io.session.Session`:

- ``t`` seconds of the device clock (``t_us / 1e6``; t_us is a 64-bit microsecond counter that
  never wraps), ``gyr`` rad/s, ``acc`` m/s², ``mag`` µT (``# mag_unit: uT``). Each value is
  the exact rational count scale (for µT: times 10^6) rounded once to a float64;
- metadata (``# key: value``, see ``docs/contracts.md``): source, device_uid,
  firmware, firmware_build, protocol_version, port, each sensor's name and exact count scale,
  units, samples, dropped, device_dropped, coverage, stopped (why it stopped).

Live estimate: the magnetometer stream also runs through a
:class:`~magcal.calib.norm_only.live.LiveCalibration` (Zhao et al.'s CKF on block means of
about 100 Hz;
:class:`CollectMonitor` runs it with the coverage for both recorders, serial and MAVLink),
whose state goes with every progress report: the calibrated field's norm spread and, once
the estimate has converged and the coverage reached the target (90 % without one), "ok to
stop" (:meth:`~magcal.calib.norm_only.live.LiveState.text`, shown before the coverage hint).
It never stops the collection by itself and never loses a sample: should it fail, collection goes on
without it (logged).

Dropped samples: the stream's seq is the acquisition counter (+1 per sample modulo 2^32), so
every sample lost on the way (the device's transmit queue, the link, the host's queue) shows
as a seq gap. The device's own count (stream_stop's ``dropped``) also includes samples lost
after the last one received, which no gap shows; the session's ``dropped`` is therefore
``max(gaps, device_dropped)`` (both are recorded).

Nothing collected is lost: on Ctrl-C the stream is stopped and the result is returned with
``interrupted=True``; on any other error :class:`CollectError` is raised carrying the partial
result, which the caller writes.
"""

from __future__ import annotations

import logging
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from datetime import datetime, timezone
from typing import Any, Protocol

import numpy as np

from magcal.calib.norm_only.live import OK_COVERAGE, LiveCalibration, LiveState
from magcal.device.client import (
    DeviceClient,
    DeviceInfo,
    DeviceTimeoutError,
    Sample,
    Scale,
    SensorInfo,
    StreamKind,
)
from magcal.device.coverage import CoverageState, CoverageTracker
from magcal.device.generated import Status
from magcal.errors import MagcalError
from magcal.io.session import Session, session_from_arrays

log = logging.getLogger(__name__)

#: How often collect reports progress and refreshes the coverage, s.
PROGRESS_INTERVAL_S = 0.25
#: No sample for this long ends the collection with an error (the device stopped acquiring).
STALL_TIMEOUT_S = 5.0
#: Readings must span this much (µT) along some axis before they give field directions:
#: about a quarter turn in the weakest Earth field (~25 µT).
COVERAGE_MIN_EXTENT_UT = 10.0
#: Samples for which the rate shown is averaged (2 s at 100 Hz).
RATE_WINDOW_SAMPLES = 200
SEQ_MODULUS = 1 << 32
UT_PER_T_EXP10 = 6  # µT = T * 10^6

SI_UNIT_TEXT = {"mag": "T", "acc": "m/s^2", "gyr": "rad/s"}


class CollectError(MagcalError):
    """collect stopped on an error; ``result`` holds what was collected (may be empty)."""

    def __init__(self, message: str, result: CollectResult) -> None:
        super().__init__(message)
        self.result = result


@dataclass(frozen=True)
class CollectProgress:
    """What collect reports while it runs."""

    samples: int
    elapsed_s: float
    rate_hz: float  # samples per second over the last RATE_WINDOW_SAMPLES
    dropped: int  # seq gaps so far
    coverage: float  # 0..1
    hint: str  # what to do next: the live estimate's state, then the coverage hint
    live: LiveState | None = None  # None before the first report or if the estimate failed
    #: The one thing to do next, without figures: "ok to stop: ..." once it is, else the
    #: coverage hint (:func:`instruction`); "" when the reporter did not say.
    instruction: str = ""
    #: The coverage behind ``coverage``: cell counts, centre, hint (None: not given).
    coverage_state: CoverageState | None = None
    #: The magnetometer readings (K, 3) in session units added since the previous report
    #: (None: not given), for a display of the field directions.
    readings: np.ndarray | None = None

    def coverage_percent(self) -> str:
        """The coverage figure as every display shows it: "87.0" (percent, one decimal)."""
        return f"{100 * self.coverage:.1f}"

    def figures(self) -> str:
        """Samples, rate, drops and coverage, as the progress line shows them."""
        return (
            f"{self.samples:7d} samples  {self.rate_hz:6.1f}/s  dropped {self.dropped}  "
            f"coverage {self.coverage_percent():>5} %"
        )


@dataclass(frozen=True)
class CollectResult:
    """session : the samples in SI units (None when there were none);
    stopped : "coverage", "duration", "samples", "interrupted" or "error";
    dropped : max(seq gaps, device_dropped); gaps : samples missing between received seqs;
    device_dropped : stream_stop's count (-1 when the stream could not be stopped);
    out_of_order : samples skipped because their time did not increase;
    live : the live estimate's last state (None if it failed);
    screen : the MAVLink recorder's magnetometer decisions
        (:class:`magcal.autopilot.magstream.ScreenCounts`; None from the device)."""

    session: Session | None
    samples: int
    stopped: str
    dropped: int
    gaps: int
    device_dropped: int
    out_of_order: int
    coverage: CoverageState
    elapsed_s: float
    live: LiveState | None = None
    screen: Any = None

    @property
    def interrupted(self) -> bool:
        return self.stopped == "interrupted"


def scale_text(s: Scale) -> str:
    """The exact count scale as text: "1/6842e0 gauss" (num/den × 10^exp10 unit)."""
    return f"{s.num}/{s.den}e{s.exp10} {s.unit.name.lower()}"


def scale_in(s: Scale, exp10_shift: int) -> Scale:
    """The same scale in units 10^-exp10_shift times the SI unit (exact): for µT,
    ``scale_in(s, UT_PER_T_EXP10)``."""
    return Scale(s.num, s.den, s.exp10 + exp10_shift, s.unit)


def session_metadata(info: DeviceInfo, url: str, protocol_version: int | None) -> dict[str, str]:
    """The device's identity and exact scales as session metadata (one line each)."""
    fw = f"{info.fw_version_str} (build {info.fw_build:08x})"
    meta = {
        "source": f"magcal collect, magcal firmware {fw}, device uid {info.uid_hex}, {url}",
        "device_uid": info.uid_hex,
        "firmware": info.fw_version_str,
        "firmware_build": f"{info.fw_build:08x}",
        "protocol_version": str(protocol_version if protocol_version is not None else "?"),
        "port": url,
        "sample_rate_hz": f"{info.sample_rate_hz:g}",
        "t_unit": "s (device clock t_us / 1e6)",
        "gyr_unit": "rad/s",
        "acc_unit": "m/s^2",
        "mag_unit": "uT",
    }
    for s in info.sensors:
        meta[f"{s.kind}_sensor"] = f"{s.name} (id 0x{s.sensor_id:02x})"
        meta[f"{s.kind}_count_scale"] = (
            f"{scale_text(s.count_scale)} = {s.count_scale.si!r} {SI_UNIT_TEXT[s.kind]}"
        )
    return meta


def counts_to_session_units(sensor: SensorInfo, counts: np.ndarray) -> np.ndarray:
    """Counts (N, 3) -> session units: µT for the magnetometer, SI for the others, each value
    the exact rational rounded once."""
    scale = sensor.count_scale
    if sensor.kind == "mag":
        scale = scale_in(scale, UT_PER_T_EXP10)
    return scale.counts_to_si(np.asarray(counts, dtype=np.int64).reshape(-1, 3))


def seq_gap(prev: int, seq: int) -> int:
    """Stream messages missing between two received seqs (the acquisition counter: +1 per
    sample modulo 2^32, so the uint32 wrap is no gap); 0 for a repeated or older seq (a
    duplicate on the link), which is no gap either."""
    gap = (seq - prev - 1) % SEQ_MODULUS
    return 0 if gap >= SEQ_MODULUS // 2 else gap


class _Recorder:
    """The samples received so far, and the seq bookkeeping."""

    def __init__(self) -> None:
        self.seq: list[int] = []
        self.t_us: list[int] = []
        self.mag: list[tuple[int, int, int]] = []
        self.acc: list[tuple[int, int, int]] = []
        self.gyr: list[tuple[int, int, int]] = []
        self.gaps = 0
        self.out_of_order = 0

    def add(self, s: Sample) -> None:
        if self.seq:
            self.gaps += seq_gap(self.seq[-1], s.seq)
            if s.t_us <= self.t_us[-1]:
                # A session's time must increase; keep the file readable (counted).
                self.out_of_order += 1
                return
        self.seq.append(s.seq)
        self.t_us.append(s.t_us)
        self.mag.append(s.mag)
        self.acc.append(s.acc)
        self.gyr.append(s.gyr)

    def __len__(self) -> int:
        return len(self.seq)


class GuardedLiveCalibration:
    """The live estimate as a recorder runs it: a failure of the estimate must not end a
    collection, so it is logged and the estimate switched off. For every recorder (the
    MAVLink one too): ``add`` the readings, ``state(coverage)`` for :func:`progress_hint`."""

    def __init__(self, sample_rate_hz: float, ok_coverage: float) -> None:
        self.calibration: LiveCalibration | None = LiveCalibration(
            sample_rate_hz, ok_coverage=ok_coverage
        )

    def add(self, mag: np.ndarray) -> None:
        if self.calibration is not None:
            try:
                self.calibration.add(mag)
            except (ValueError, ArithmeticError, MagcalError) as exc:
                self._fail(exc)

    def state(self, coverage: float) -> LiveState | None:
        if self.calibration is not None:
            try:
                return self.calibration.state(coverage)
            except (ValueError, ArithmeticError, MagcalError) as exc:
                self._fail(exc)
        return None

    def _fail(self, exc: BaseException) -> None:
        log.warning("collect: the live estimate failed (%s); collecting without it", exc)
        self.calibration = None


def live_summary(live: LiveState) -> str:
    """The live estimate at the end, for the session's metadata."""
    change = "n/a" if live.norm_change is None else f"{100 * live.norm_change:.3f} %"
    return (
        f"CKF norm spread {100 * live.norm_spread:.3f} %, uncertainty "
        f"{100 * live.norm_std:.3f} %, change over the last seconds {change}, "
        f"{'converged' if live.converged else 'not converged'}"
    )


def live_metadata(live: LiveState | None) -> dict[str, str]:
    """``{"live_estimate": ...}`` for the session's metadata once the estimate has started,
    else nothing."""
    return {"live_estimate": live_summary(live)} if live is not None and live.started else {}


def progress_hint(coverage: CoverageState, live: LiveState | None) -> str:
    """The progress line's advice: "ok to stop: ..." alone once it is, else the live
    estimate's state followed by the coverage hint."""
    if live is None:
        return coverage.hint
    if live.ok_to_stop:
        return live.text()
    return f"{live.text()}; {coverage.hint}"


def instruction(coverage: CoverageState, live: LiveState | None) -> str:
    """The one thing to do next, without the estimate's figures: the live estimate's
    "ok to stop: ..." once it is, else the coverage hint."""
    if live is not None and live.ok_to_stop:
        return live.text()
    return coverage.hint


class RecordedStream(Protocol):
    """What :func:`record_stream` needs of a recorder: the samples so far (``len``), the
    messages found missing (``gaps``) and the magnetometer readings as received (``mag``)."""

    gaps: int
    mag: list[tuple[int, int, int]]

    def __len__(self) -> int: ...


class CollectMonitor:
    """What every recorder (serial, MAVLink) watches while it collects, and reports as
    :class:`CollectProgress`: the coverage of field directions, the live estimate and the
    receive rate.

    min_extent : the coverage tracker's minimum extent, in session units
    sample_rate_hz : the stream's nominal rate (the live estimate's block length)
    coverage_target : the collection's coverage target (0..1), None without one: the
        coverage the live estimate needs for "ok to stop" (OK_COVERAGE without a target)
    to_session_units : magnetometer readings as received (N, 3) -> session units (N, 3)
    """

    def __init__(
        self,
        min_extent: float,
        sample_rate_hz: float,
        coverage_target: float | None,
        to_session_units: Callable[[np.ndarray], np.ndarray],
    ) -> None:
        self.tracker = CoverageTracker(min_extent=min_extent)
        self.live = GuardedLiveCalibration(sample_rate_hz, coverage_target or OK_COVERAGE)
        self._to_session_units = to_session_units
        self._fed = 0
        self._times: deque[float] = deque(maxlen=RATE_WINDOW_SAMPLES)
        self._unreported: list[np.ndarray] = []

    def received(self, host_s: float) -> None:
        """A sample arrived at host time ``host_s`` (s), for the rate shown."""
        self._times.append(host_s)

    def feed(self, mag: list[tuple[int, int, int]], force: bool = False) -> CoverageState:
        """The readings of ``mag`` (all received so far, in order) not yet seen, in session
        units, to the coverage tracker and the live estimate; the coverage now (``force``:
        refreshed whatever the tracker's schedule)."""
        if len(mag) > self._fed:
            readings = self._to_session_units(np.array(mag[self._fed :]))
            self._track(readings, self._fed, len(mag))
            self.live.add(readings)
            self._unreported.append(readings)
            self._fed = len(mag)
        return self.tracker.state(force=force)

    def _track(self, readings: np.ndarray, start: int, stop: int) -> None:
        """Readings ``start:stop`` of the recording (K, 3), session units, to the coverage."""
        self.tracker.add(readings)

    def progress(
        self,
        rec: RecordedStream,
        elapsed_s: float,
        coverage: CoverageState,
        live: LiveState | None = None,
    ) -> CollectProgress:
        """The report for ``coverage`` and the live estimate's state (``live``: one already
        taken, else taken now)."""
        t = self._times
        span = t[-1] - t[0] if len(t) > 1 else 0.0
        rate = (len(t) - 1) / span if span > 0 else 0.0
        if live is None:
            live = self.live.state(coverage.coverage)
        readings = np.concatenate(self._unreported) if self._unreported else np.empty((0, 3))
        self._unreported = []
        return CollectProgress(
            len(rec),
            elapsed_s,
            rate,
            rec.gaps,
            coverage.coverage,
            progress_hint(coverage, live),
            live,
            instruction(coverage, live),
            coverage,
            readings,
        )


@dataclass(frozen=True)
class StopRules:
    """When a collection stops, whichever comes first (at least one must be given).

    duration_s : after this long (host clock), s
    coverage_target : once this fraction (0..1) of field directions is covered and at least
        ``min_samples`` samples were recorded
    max_samples : after this many samples
    """

    duration_s: float | None = None
    coverage_target: float | None = None
    max_samples: int | None = None
    min_samples: int = 0

    def __post_init__(self) -> None:
        if self.duration_s is None and self.coverage_target is None and self.max_samples is None:
            raise MagcalError("collect: give a stop condition (duration, coverage or sample count)")


def record_stream(
    rec: RecordedStream,
    receive: Callable[[float], bool],
    monitor: CollectMonitor,
    rules: StopRules,
    *,
    start_s: float,
    timeout_error: type[Exception],
    stall_error: Callable[[], Exception],
    progress: Callable[[CollectProgress], None] | None,
    clock: Callable[[], float],
    begin: Callable[[], None] | None = None,
) -> tuple[str, BaseException | None]:
    """The collection loop of every recorder: ``receive(wait_s)`` until a stop rule, with a
    progress report about every PROGRESS_INTERVAL_S.

    rec : the recorder that ``receive`` adds to
    receive : waits at most wait_s (s) for one message and records it: True when it was a
        sample; raises ``timeout_error`` when none arrived
    start_s : the collection's start (``clock``), from which duration and elapsed count
    stall_error : the error raised when no sample arrived for STALL_TIMEOUT_S
    begin : called first, inside the loop's error handling (starts the stream)

    Returns why it stopped ("duration", "samples", "coverage", "interrupted" or "error") and
    the error for "error" (a MagcalError or OSError; any other is raised). The caller stops
    the stream and then makes the :func:`final_report`.
    """
    last_sample = start_s
    next_report = start_s
    try:
        if begin is not None:
            begin()
        while True:
            now = clock()
            if rules.duration_s is not None and now - start_s >= rules.duration_s:
                return "duration", None
            # Waits only while no sample is queued: wake up for the next report or the end.
            wait = min(PROGRESS_INTERVAL_S, next_report - now)
            if rules.duration_s is not None:
                wait = min(wait, start_s + rules.duration_s - now)
            try:
                sample = receive(max(0.001, wait))
            except timeout_error:
                sample = False
                if clock() - last_sample > STALL_TIMEOUT_S:
                    raise stall_error() from None
            if sample:
                last_sample = clock()
                monitor.received(last_sample)
                if rules.max_samples is not None and len(rec) >= rules.max_samples:
                    return "samples", None
            now = clock()
            if now >= next_report:
                next_report = now + PROGRESS_INTERVAL_S
                state = monitor.feed(rec.mag)
                if progress is not None:
                    progress(monitor.progress(rec, now - start_s, state))
                if (
                    rules.coverage_target is not None
                    and state.coverage >= rules.coverage_target
                    and len(rec) >= rules.min_samples
                ):
                    return "coverage", None
    except KeyboardInterrupt:
        return "interrupted", None
    except (MagcalError, OSError) as exc:
        return "error", exc


def final_report(
    rec: RecordedStream,
    monitor: CollectMonitor,
    elapsed_s: float,
    progress: Callable[[CollectProgress], None] | None,
) -> tuple[CoverageState, LiveState | None]:
    """After the stream was stopped: every reading to the coverage and the live estimate, the
    last progress report (when there were samples); the final coverage and live state."""
    state = monitor.feed(rec.mag, force=True)
    live = monitor.live.state(state.coverage)
    if progress is not None and len(rec):
        progress(monitor.progress(rec, elapsed_s, state, live))
    return state, live


def collect(
    client: DeviceClient,
    info: DeviceInfo,
    *,
    duration_s: float | None = None,
    coverage_target: float | None = None,
    max_samples: int | None = None,
    min_samples: int = 0,
    progress: Callable[[CollectProgress], None] | None = None,
    clock: Callable[[], float] = time.monotonic,
) -> CollectResult:
    """Record the raw stream into a session until a stop condition (see the module docstring).

    duration_s : stop after this long (host clock), s
    coverage_target : stop once this fraction (0..1) of field directions is covered and at
        least ``min_samples`` samples were recorded
    max_samples : stop after this many samples
    progress : called about every PROGRESS_INTERVAL_S with a :class:`CollectProgress`

    Returns a CollectResult (``interrupted`` after Ctrl-C). Raises CollectError with the
    partial result on a device or link error, or when no sample arrives for STALL_TIMEOUT_S.
    """
    rules = StopRules(duration_s, coverage_target, max_samples, min_samples)
    rec = _Recorder()
    mag_sensor = info.sensor("mag")
    monitor = CollectMonitor(
        COVERAGE_MIN_EXTENT_UT,
        info.sample_rate_hz,
        coverage_target,
        lambda counts: counts_to_session_units(mag_sensor, counts),
    )

    def receive(wait_s: float) -> bool:
        msg = client.read_stream(wait_s)
        if isinstance(msg, Sample):
            rec.add(msg)
            return True
        return False

    def stalled() -> DeviceTimeoutError:
        return DeviceTimeoutError(
            f"collect on {client.url}: no sample for {STALL_TIMEOUT_S:g} s; check that the "
            "device is acquiring (sensors connected, firmware running)",
            Status.E_EMPTY,
            "collect",
        )

    start = clock()
    stopped, error = record_stream(
        rec,
        receive,
        monitor,
        rules,
        start_s=start,
        timeout_error=DeviceTimeoutError,
        stall_error=stalled,
        progress=progress,
        clock=clock,
        # inside the loop's handling: a Ctrl-C during the start still stops the stream
        begin=lambda: client.stream_start(StreamKind.RAW),
    )
    # Stopped on the way out whatever happened, also after a Ctrl-C during stream_start.
    device_dropped = _stop_stream(client, rec, max_samples)
    elapsed = clock() - start
    state, live = final_report(rec, monitor, elapsed, progress)
    result = _result(rec, info, client, stopped, device_dropped, state, elapsed, live)
    if error is not None:
        raise CollectError(
            f"collect on {client.url}: stopped by an error after {len(rec)} samples: {error}",
            result,
        ) from error
    return result


def _stop_stream(client: DeviceClient, rec: _Recorder, max_samples: int | None) -> int:
    """Stop the stream (best effort) and keep the samples already queued, up to max_samples
    in all; the device's dropped count, or -1 when it could not be asked."""
    try:
        return client.stream_stop().dropped
    except (MagcalError, OSError, KeyboardInterrupt) as exc:
        log.warning("collect on %s: could not stop the stream (%s)", client.url, exc)
        return -1
    finally:
        # Also when the stop failed: the samples queued are the session's too.
        _drain_queued(client, rec, max_samples)


def _drain_queued(client: DeviceClient, rec: _Recorder, max_samples: int | None) -> None:
    """Add the samples the client has queued (those that arrived before the stop's response)
    without waiting, until the session has max_samples; the rest are read and discarded, so
    no message of this stream is left for the client's next user."""
    while True:
        try:
            msg = client.read_stream(0.0)
        except DeviceTimeoutError:
            return
        if isinstance(msg, Sample) and (max_samples is None or len(rec) < max_samples):
            rec.add(msg)


def _result(
    rec: _Recorder,
    info: DeviceInfo,
    client: DeviceClient,
    stopped: str,
    device_dropped: int,
    state: CoverageState,
    elapsed: float,
    live: LiveState | None,
) -> CollectResult:
    dropped = max(rec.gaps, device_dropped)
    session = None
    if len(rec):
        meta = session_metadata(info, client.url, client.version)
        meta.update(
            {
                "collected_at": datetime.now(timezone.utc).isoformat(timespec="seconds"),
                "samples": str(len(rec)),
                "dropped": str(dropped),
                "seq_gaps": str(rec.gaps),
                "device_dropped": str(device_dropped) if device_dropped >= 0 else "unknown",
                "coverage": f"{100 * state.coverage:.1f} % of {len(state.counts)} equal-area "
                "cells of field directions",
                "stopped": stopped,
            }
        )
        if rec.out_of_order:
            meta["out_of_order_skipped"] = str(rec.out_of_order)
        meta.update(live_metadata(live))
        t = np.array(rec.t_us, dtype=np.int64)
        session = session_from_arrays(
            t.astype(np.float64) / 1e6,
            counts_to_session_units(info.sensor("gyr"), np.array(rec.gyr)),
            counts_to_session_units(info.sensor("acc"), np.array(rec.acc)),
            counts_to_session_units(info.sensor("mag"), np.array(rec.mag)),
            meta,
        )
    return CollectResult(
        session=session,
        samples=len(rec),
        stopped=stopped,
        dropped=dropped,
        gaps=rec.gaps,
        device_dropped=device_dropped,
        out_of_order=rec.out_of_order,
        coverage=state,
        elapsed_s=elapsed,
        live=live,
    )
