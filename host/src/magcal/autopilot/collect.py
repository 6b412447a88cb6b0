# SPDX-License-Identifier: Apache-2.0
"""Recording a calibration session from an ArduPilot or PX4 vehicle over MAVLink.

:func:`collect` asks for compass N's IMU stream (:func:`magcal.autopilot.vehicle.collect_stream`)
with MAV_CMD_SET_MESSAGE_INTERVAL (checked by its COMMAND_ACK; an ArduPilot that refuses or
does not answer gets the deprecated REQUEST_DATA_STREAM for its raw-sensor group instead),
reads it until a stop condition, and gives the vehicle its default rate back.

Each message carries the accelerometer, gyroscope and magnetometer of one moment, so there is
nothing to pair: a message is a sample. The session holds (see :mod:`magcal.autopilot.vehicle`):

- ``t`` s from the message timestamps (time_usec or time_boot_ms), unwrapped and re-based
  after a clock restart (:func:`~magcal.autopilot.vehicle.unwrap_times`); a repeated
  timestamp drops the sample;
- ``acc`` m/s², ``gyr`` rad/s (body frame, as the autopilot calibrated them);
- ``mag`` in the autopilot's unit (``# mag_unit: mG`` for ArduPilot, ``gauss`` for PX4) and
  frame (``# mag_frame:``): ArduPilot's corrected field with the correction in force undone,
  PX4's raw field;
- metadata: source, autopilot, vehicle, firmware, compass, stream, the compass parameters in
  force (``param.NAME: value``), counts.

Progress, coverage and the live estimate are those of the serial path
(:class:`magcal.device.collect.CollectMonitor`: the coverage of field directions, the live CKF
on the magnetometer in session units, its norm spread and "ok to stop" in the progress hint,
its final state as the ``live_estimate`` metadata), and so are the stop rules and the result
(:class:`magcal.device.collect.CollectResult`: on Ctrl-C ``interrupted``; on an error
:class:`~magcal.device.collect.CollectError` with the partial result).
"""

from __future__ import annotations

import logging
import statistics
import time
from collections import deque
from collections.abc import Callable
from datetime import datetime, timezone

import numpy as np

from magcal.autopilot import vehicle
from magcal.autopilot.connection import Autopilot
from magcal.autopilot.magstream import MAX_PROPAGATION_STEP_S, MagnetometerScreen
from magcal.calib.norm_only.live import LiveState
from magcal.device.collect import (
    COVERAGE_MIN_EXTENT_UT,
    STALL_TIMEOUT_S,
    CollectError,
    CollectMonitor,
    CollectProgress,
    CollectResult,
    StopRules,
    final_report,
    live_metadata,
    record_stream,
)
from magcal.device.coverage import AttitudeCoverage, CoverageState
from magcal.errors import MagcalError
from magcal.io.session import session_from_arrays
from magcal.link.mavlink import MavlinkTimeoutError

log = logging.getLogger(__name__)

#: The IMU message rate asked for on a network link (UDP, TCP), Hz: a magnetometer value's
#: time is that of the first message carrying it, so the faster the stream, the closer.
NETWORK_RATE_HZ = 100.0
#: ... and never less than this, Hz.
MIN_RATE_HZ = 10.0
#: A MAVLink 2 RAW_IMU on the wire: 12 bytes of framing and 29 of payload.
IMU_MESSAGE_BYTES = 41
MAV_RESULT_ACCEPTED = 0
MAV_DATA_STREAM_RAW_SENSORS = 1
#: Session magnetometer units per µT (for the coverage tracker's minimum extent).
UNIT_PER_UT = {vehicle.ARDUPILOT: 10.0, vehicle.PX4: 0.01}


def start_stream(ap: Autopilot, message: str, rate_hz: float) -> str:
    """Ask for ``message`` at ``rate_hz``; returns how ("SET_MESSAGE_INTERVAL" or
    "REQUEST_DATA_STREAM"). AutopilotError when the vehicle refuses."""
    msg_id = vehicle.MESSAGE_IDS[message]
    try:
        result = ap.client.set_message_interval(msg_id, 1e6 / rate_hz)
    except MavlinkTimeoutError:
        result = None
    if result == MAV_RESULT_ACCEPTED:
        return "SET_MESSAGE_INTERVAL"
    if ap.autopilot == vehicle.ARDUPILOT:
        # older ArduPilot: the stream groups of REQUEST_DATA_STREAM (RAW_IMU, SCALED_IMU2/3)
        ap.client.request_data_stream(MAV_DATA_STREAM_RAW_SENSORS, max(1, round(rate_hz)))
        return "REQUEST_DATA_STREAM"
    said = "did not answer" if result is None else f"answered MAV_RESULT {result}"
    raise vehicle.AutopilotError(
        f"{ap.url}: the vehicle {said} to MAV_CMD_SET_MESSAGE_INTERVAL for {message}: it cannot "
        "stream that message (PX4: is the MAVLink instance's mode 'Normal' or 'Onboard'?)"
    )


def stop_stream(ap: Autopilot, message: str, how: str) -> None:
    """Give the vehicle its default rate of ``message`` back (best effort, logged)."""
    try:
        if how == "REQUEST_DATA_STREAM":
            ap.client.request_data_stream(MAV_DATA_STREAM_RAW_SENSORS, 0, start=False)
        else:
            ap.client.set_message_interval(vehicle.MESSAGE_IDS[message], 0)
    except (MagcalError, OSError, KeyboardInterrupt) as exc:
        # also a second Ctrl-C: what was collected is still written
        log.warning("%s: could not restore the default rate of %s (%r)", ap.url, message, exc)


#: Recent time steps whose median is a stream's nominal step.
NOMINAL_STEP_WINDOW = 256


class _Recorder:
    """The messages received (timestamp ticks, IMU fields, the wire magnetometer, host times)
    and the magnetometer screen over them (:mod:`magcal.autopilot.magstream`). Its length
    and ``mag`` are the accepted magnetometer samples: what the coverage, the live estimate
    and the stop rules count."""

    def __init__(self, stream: str) -> None:
        self.base = vehicle.TIME_BASES[stream]
        self.ticks: list[int] = []
        self.host: list[float] = []
        self.acc: list[tuple[int, int, int]] = []
        self.gyr: list[tuple[int, int, int]] = []
        self.wire_mag: list[tuple[int, int, int]] = []
        self.screen = MagnetometerScreen()
        self.gaps = 0
        # The nominal step (ticks): the median of the recent ones, since a millisecond time
        # stamp of a 100 Hz stream jitters by a tick or two either way.
        self._steps: deque[int] = deque(maxlen=NOMINAL_STEP_WINDOW)
        self._t = 0.0  # the screen's running time, s

    @property
    def mag(self) -> list[tuple[float, float, float]]:
        return self.screen.values

    def add(self, msg, host_s: float) -> None:
        tick = int(getattr(msg, self.base.field))
        if self.ticks:
            step = vehicle.tick_step(self.ticks[-1], tick, self.base)
            if step > 0:
                if self._steps:
                    # per message: statistics' median of a few hundred ints costs a third of numpy's
                    nominal = float(statistics.median(self._steps))
                    if step > vehicle.GAP_STEPS * nominal:
                        self.gaps += max(0, round(step / nominal) - 1)
                self._steps.append(step)
            if step == 0:  # a repeated time stamp: dropped from the session, not screened
                self._append(msg, tick, host_s)
                return
            dt = step * self.base.tick_s
            # a reset or a long pause: no propagation across it
            self._t += dt if 0 < dt <= vehicle.MAX_WRAP_STEP_S else 2 * MAX_PROPAGATION_STEP_S
        self._append(msg, tick, host_s)
        # mrad/s to rad/s without numpy's per-call cost on every row
        per_rad = vehicle.GYRO_MRAD_PER_RAD
        gyr = tuple(w / per_rad for w in self.gyr[-1])
        self.screen.add(len(self.ticks) - 1, self._t, gyr, self.wire_mag[-1])

    def _append(self, msg, tick: int, host_s: float) -> None:
        self.ticks.append(tick)
        self.host.append(host_s)
        self.acc.append((msg.xacc, msg.yacc, msg.zacc))
        self.gyr.append((msg.xgyro, msg.ygyro, msg.zgyro))
        self.wire_mag.append((msg.xmag, msg.ymag, msg.zmag))

    def __len__(self) -> int:
        return len(self.screen.values)


class _AttitudeMonitor(CollectMonitor):
    """The recorders' monitor with the coverage of orientations the vehicle really took
    (:class:`magcal.device.coverage.AttitudeCoverage`, from the screen's attitude at each
    accepted sample) in place of the raw field directions'."""

    def __init__(self, rec: _Recorder, min_extent: float, *args) -> None:
        super().__init__(min_extent, *args)
        self.tracker = AttitudeCoverage(min_extent)  # type: ignore[assignment]
        self._rec = rec

    def _track(self, readings: np.ndarray, start: int, stop: int) -> None:
        self.tracker.add(readings, self._rec.screen.rotations(start, stop))


def link_rate_hz(url: str) -> float:
    """The IMU message rate to ask for on ``url``: NETWORK_RATE_HZ on a network link; on a
    serial link (``DEVICE,BAUD``) what half its bandwidth carries of a MAVLink 2 RAW_IMU
    (IMU_MESSAGE_BYTES, 10 bits a byte), at most NETWORK_RATE_HZ and at least MIN_RATE_HZ."""
    parts = url.split(",")
    if len(parts) > 1 and parts[-1].strip().isdigit():
        carried = 0.5 * int(parts[-1]) / (10 * IMU_MESSAGE_BYTES)
        return float(max(MIN_RATE_HZ, min(NETWORK_RATE_HZ, round(carried))))
    return NETWORK_RATE_HZ


def collect(
    ap: Autopilot,
    cp: vehicle.CompassParams,
    *,
    rate_hz: float | None = None,
    duration_s: float | None = None,
    coverage_target: float | None = None,
    max_samples: int | None = None,
    min_samples: int = 0,
    progress: Callable[[CollectProgress], None] | None = None,
    firmware: str | None = None,
    clock: Callable[[], float] = time.monotonic,
) -> CollectResult:
    """Record compass ``cp.compass``'s stream into a session (module docstring).

    rate_hz : the message rate asked for (None: :func:`link_rate_hz`); duration_s,
    coverage_target (0..1, with at least min_samples), max_samples : stop conditions as for
    the serial collect (samples: accepted magnetometer samples); progress : called about
    every PROGRESS_INTERVAL_S. Raises CollectError with the partial result on a link
    error or when no message arrives for STALL_TIMEOUT_S."""
    rules = StopRules(duration_s, coverage_target, max_samples, min_samples)
    if rate_hz is None:
        rate_hz = link_rate_hz(ap.url)
    stream = vehicle.collect_stream(ap.autopilot, cp.compass)
    rec = _Recorder(stream)
    monitor = _AttitudeMonitor(
        rec,
        COVERAGE_MIN_EXTENT_UT * UNIT_PER_UT[ap.autopilot],
        None,  # the live estimate on every magnetometer sample (the compass's own rate)
        coverage_target,
        lambda wire: vehicle.session_mag(wire.astype(float), cp),
    )

    def receive(wait_s: float) -> bool:
        # A sample is a new magnetometer value (the IMU rows between are not): the rate shown
        # is the samples'.
        before = len(rec)
        rec.add(ap.client.recv((stream,), wait_s), clock())
        return len(rec) > before

    def stalled() -> MavlinkTimeoutError:
        return MavlinkTimeoutError(
            f"collect on {ap.url}: no {stream} for {STALL_TIMEOUT_S:g} s; check that the "
            "vehicle streams it (link bandwidth, compass present)"
        )

    how = start_stream(ap, stream, rate_hz)
    start = clock()
    stopped, error = record_stream(
        rec,
        receive,
        monitor,
        rules,
        start_s=start,
        timeout_error=MavlinkTimeoutError,
        stall_error=stalled,
        progress=progress,
        clock=clock,
    )
    stop_stream(ap, stream, how)
    rec.screen.finish()
    elapsed = clock() - start
    state, live = final_report(rec, monitor, elapsed, progress)
    result = _result(ap, cp, rec, stream, how, rate_hz, firmware, stopped, state, elapsed, live)
    if error is not None:
        raise CollectError(
            f"collect on {ap.url}: stopped by an error after {len(rec)} samples: {error}", result
        ) from error
    return result


def _result(
    ap: Autopilot,
    cp: vehicle.CompassParams,
    rec: _Recorder,
    stream: str,
    how: str,
    rate_hz: float,
    firmware: str | None,
    stopped: str,
    state: CoverageState,
    elapsed: float,
    live: LiveState | None,
) -> CollectResult:
    timeline = vehicle.unwrap_times(np.array(rec.ticks), rec.base, np.array(rec.host))
    keep = timeline.keep
    repeated = int(np.count_nonzero(~keep))
    counts = rec.screen.counts()
    rows = np.array(rec.screen.rows, dtype=np.int64)
    # The recorder screens exactly the rows unwrap_times keeps (both drop a row whose
    # vehicle.tick_step from the one before is 0), so the accepted rows need no filtering.
    assert keep[rows].all()
    session = None
    if rows.size:
        mag = np.full((len(rec.ticks), 3), np.nan)
        mag[rows] = vehicle.session_mag(np.array(rec.mag, dtype=float), cp)
        t = timeline.t[keep]
        meta = session_metadata(ap, cp, stream, firmware)
        meta.update(
            {
                "stream_request": f"{how}, {rate_hz:g} Hz",
                "stream_rate_hz": f"{_rate(t, t.size):.1f}",
                "magnetometer_rate_hz": f"{_rate(t, counts.changes):.1f}",
                "collected_at": datetime.now(timezone.utc).isoformat(timespec="seconds"),
                "samples": str(int(rows.size)),
                "imu_rows": str(int(t.size)),
                "magnetometer_repeats": str(counts.repeats),
                "magnetometer_fast_turn": str(counts.fast_turn),
                "magnetometer_frozen": str(counts.frozen),
                "dropped": str(timeline.missing),
                "repeated_timestamps_skipped": str(repeated),
                "time_wraps": str(timeline.wraps),
                "time_resets": str(timeline.resets),
                "coverage": f"{100 * state.coverage:.1f} % of {len(state.counts)} equal-area "
                "cells of field directions at the orientations taken (gyroscope)",
                "stopped": stopped,
            }
        )
        meta.update(live_metadata(live))
        session = session_from_arrays(
            t,
            vehicle.gyro_mrad_to_si(np.array(rec.gyr, dtype=float)[keep]),
            vehicle.acc_mg_to_si(np.array(rec.acc, dtype=float)[keep]),
            mag[keep],
            meta,
        )
    return CollectResult(
        session=session,
        samples=int(rows.size),
        stopped=stopped,
        dropped=timeline.missing,
        gaps=timeline.missing,
        device_dropped=-1,
        out_of_order=repeated,
        coverage=state,
        elapsed_s=elapsed,
        live=live,
        screen=counts,
    )


def _rate(t: np.ndarray, count: int) -> float:
    """count events per second over the times t (s); 0 without a span."""
    span = float(t[-1] - t[0]) if t.size > 1 else 0.0
    return count / span if span > 0 else 0.0


def session_metadata(
    ap: Autopilot, cp: vehicle.CompassParams, stream: str, firmware: str | None
) -> dict[str, str]:
    """Who recorded what: the vehicle, the compass, units, frame and the parameters in force."""
    hb = ap.heartbeat
    fw = firmware or "unknown"
    meta = {
        "source": f"magcal collect over MAVLink, {ap.name} {fw}, {ap.url}",
        "autopilot": ap.autopilot,
        "vehicle": vehicle.vehicle_type_name(hb.vehicle_type).lower(),
        "firmware": fw,
        "mavlink_system": str(hb.system),
        "mavlink_component": str(hb.component),
        "compass": str(cp.compass),
        "compass_external": "1" if cp.external else "0",
        "stream": stream,
        "t_unit": f"s ({vehicle.TIME_BASES[stream].field} of {stream}, unwrapped)",
        "gyr_unit": "rad/s",
        "acc_unit": "m/s^2",
        "mag_unit": cp.unit,
        "mag_frame": vehicle.mag_frame_text(cp),
    }
    if cp.naming:
        meta["param_naming"] = cp.naming
    meta.update(cp.session_meta())
    return meta
