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
import time
from collections.abc import Callable
from datetime import datetime, timezone

import numpy as np

from magcal.autopilot import vehicle
from magcal.autopilot.connection import Autopilot
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
from magcal.device.coverage import CoverageState
from magcal.errors import MagcalError
from magcal.io.session import session_from_arrays
from magcal.link.mavlink import MavlinkTimeoutError

log = logging.getLogger(__name__)

DEFAULT_RATE_HZ = 50.0
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


class _Recorder:
    """The messages received: timestamp ticks, IMU fields, the wire magnetometer, host times."""

    def __init__(self, stream: str) -> None:
        self.base = vehicle.TIME_BASES[stream]
        self.ticks: list[int] = []
        self.host: list[float] = []
        self.acc: list[tuple[int, int, int]] = []
        self.gyr: list[tuple[int, int, int]] = []
        self.mag: list[tuple[int, int, int]] = []
        self.gaps = 0
        self._step: int | None = None  # the nominal step, ticks

    def add(self, msg, host_s: float) -> None:
        tick = int(getattr(msg, self.base.field))
        if self.ticks:
            step = tick - self.ticks[-1]
            if step > 0 and self._step:
                self.gaps += max(0, round(step / self._step) - 1)
            if step > 0 and (self._step is None or step < self._step):
                self._step = step
        self.ticks.append(tick)
        self.host.append(host_s)
        self.acc.append((msg.xacc, msg.yacc, msg.zacc))
        self.gyr.append((msg.xgyro, msg.ygyro, msg.zgyro))
        self.mag.append((msg.xmag, msg.ymag, msg.zmag))

    def __len__(self) -> int:
        return len(self.ticks)


def collect(
    ap: Autopilot,
    cp: vehicle.CompassParams,
    *,
    rate_hz: float = DEFAULT_RATE_HZ,
    duration_s: float | None = None,
    coverage_target: float | None = None,
    max_samples: int | None = None,
    min_samples: int = 0,
    progress: Callable[[CollectProgress], None] | None = None,
    firmware: str | None = None,
    clock: Callable[[], float] = time.monotonic,
) -> CollectResult:
    """Record compass ``cp.compass``'s stream into a session (module docstring).

    rate_hz : the message rate asked for; duration_s, coverage_target (0..1, with at least
    min_samples), max_samples : stop conditions as for the serial collect; progress : called
    about every PROGRESS_INTERVAL_S. Raises CollectError with the partial result on a link
    error or when no message arrives for STALL_TIMEOUT_S."""
    rules = StopRules(duration_s, coverage_target, max_samples, min_samples)
    stream = vehicle.collect_stream(ap.autopilot, cp.compass)
    rec = _Recorder(stream)
    monitor = CollectMonitor(
        COVERAGE_MIN_EXTENT_UT * UNIT_PER_UT[ap.autopilot],
        rate_hz,
        coverage_target,
        lambda wire: vehicle.session_mag(wire.astype(float), cp),
    )

    def receive(wait_s: float) -> bool:
        rec.add(ap.client.recv((stream,), wait_s), clock())
        return True

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
    session = None
    if np.any(keep):
        meta = session_metadata(ap, cp, stream, firmware)
        meta.update(
            {
                "stream_request": f"{how}, {rate_hz:g} Hz",
                "collected_at": datetime.now(timezone.utc).isoformat(timespec="seconds"),
                "samples": str(int(np.count_nonzero(keep))),
                "dropped": str(timeline.missing),
                "repeated_timestamps_skipped": str(repeated),
                "time_wraps": str(timeline.wraps),
                "time_resets": str(timeline.resets),
                "coverage": f"{100 * state.coverage:.1f} % of {len(state.counts)} equal-area "
                "cells of field directions",
                "stopped": stopped,
            }
        )
        meta.update(live_metadata(live))
        mag = vehicle.session_mag(np.array(rec.mag, dtype=float)[keep], cp)
        session = session_from_arrays(
            timeline.t[keep],
            vehicle.gyro_mrad_to_si(np.array(rec.gyr, dtype=float)[keep]),
            vehicle.acc_mg_to_si(np.array(rec.acc, dtype=float)[keep]),
            mag,
            meta,
        )
    return CollectResult(
        session=session,
        samples=int(np.count_nonzero(keep)),
        stopped=stopped,
        dropped=timeline.missing,
        gaps=timeline.missing,
        device_dropped=-1,
        out_of_order=repeated,
        coverage=state,
        elapsed_s=elapsed,
        live=live,
    )


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
