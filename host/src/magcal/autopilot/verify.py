# SPDX-License-Identifier: Apache-2.0
"""Checking the field an ArduPilot or PX4 vehicle corrects with the parameters in force.

:func:`verify` streams the vehicle's own corrected field with its IMU and measures:

1. the **norm spread** of the corrected field (:func:`magcal.device.verify.norm_spread`; the
   autopilot's unit, and relative to the mean);
2. the **heading consistency** of the same samples
   (:func:`magcal.device.verify.heading_consistency`: tilt-compensated magnetic heading
   against gyro-propagated attitude over 1 s windows; its floor is about a degree, see there).

Which field: ArduPilot's RAW_IMU / SCALED_IMU2/3 (compass N's corrected field, body frame,
mG); PX4's HIGHRES_IMU for compass 1 (vehicle_magnetometer: the corrected field of the
selected magnetometer, gauss), and for compass 2 and 3, whose corrected field PX4 does not
stream, SCALED_IMU2/3's raw field corrected here with the parameters in force
(:func:`magcal.autopilot.vehicle.onboard_correction`: the same formula as the vehicle's).

With a session (:func:`heading_of_session`): the parameters in force applied to the session's
magnetometer as the vehicle would (the correction of the data the result was calibrated from)
and the heading consistency of that, as the serial ``verify --session`` does.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from magcal.autopilot import vehicle
from magcal.autopilot.collect import start_stream, stop_stream
from magcal.autopilot.connection import Autopilot
from magcal.device.verify import (
    DEFAULT_SAMPLES,
    VERIFY_STREAM_TIMEOUT_S,
    HeadingConsistency,
    NormSpread,
    VerifyError,
    heading_consistency,
    norm_spread,
)
from magcal.io.session import Session
from magcal.link.mavlink import MavlinkTimeoutError

DEFAULT_RATE_HZ = 50.0


@dataclass(frozen=True)
class AutopilotVerifyReport:
    """stream : the message measured; corrected_here : its field was corrected by magcal with
    the parameters in force (PX4 compass 2/3) rather than by the vehicle; norm in the
    autopilot's unit; heading : None when not measurable; repeated : samples skipped for a
    repeated timestamp; missing : samples missing by the time steps."""

    stream: str
    corrected_here: bool
    unit: str
    norm: NormSpread
    heading: HeadingConsistency | None
    samples: int
    missing: int
    repeated: int


def verify_stream(autopilot: str, compass: int) -> tuple[str, bool]:
    """(message, whether magcal corrects its field) for compass N (module docstring)."""
    if autopilot == vehicle.PX4 and compass == 1:
        return "HIGHRES_IMU", False
    return vehicle.collect_stream(autopilot, compass), autopilot == vehicle.PX4


def _fields(msg, stream: str, autopilot: str) -> tuple[list[float], list[float], list[float]]:
    """(acc m/s², gyro rad/s, mag in the autopilot's unit) of one message."""
    if stream == "HIGHRES_IMU":
        return (
            [msg.xacc, msg.yacc, msg.zacc],
            [msg.xgyro, msg.ygyro, msg.zgyro],
            [msg.xmag, msg.ymag, msg.zmag],
        )
    acc = vehicle.acc_mg_to_si(np.array([msg.xacc, msg.yacc, msg.zacc], dtype=float))
    gyr = vehicle.gyro_mrad_to_si(np.array([msg.xgyro, msg.ygyro, msg.zgyro], dtype=float))
    mag = vehicle.mag_wire_to_unit(np.array([msg.xmag, msg.ymag, msg.zmag], dtype=float), autopilot)
    return list(acc), list(gyr), list(mag)


def verify(
    ap: Autopilot,
    cp: vehicle.CompassParams,
    *,
    n_samples: int | None = None,
    duration_s: float | None = None,
    rate_hz: float = DEFAULT_RATE_HZ,
    clock: Callable[[], float] = time.monotonic,
) -> AutopilotVerifyReport:
    """Stream the corrected field and measure it (module docstring)."""
    if n_samples is None and duration_s is None:
        n_samples = DEFAULT_SAMPLES
    stream, here = verify_stream(ap.autopilot, cp.compass)
    base = vehicle.TIME_BASES[stream]
    ticks: list[int] = []
    host: list[float] = []
    acc: list[list[float]] = []
    gyr: list[list[float]] = []
    mag: list[list[float]] = []
    how = start_stream(ap, stream, rate_hz)
    try:
        start = clock()
        while (n_samples is None or len(ticks) < n_samples) and (
            duration_s is None or clock() - start < duration_s
        ):
            try:
                msg = ap.client.recv((stream,), VERIFY_STREAM_TIMEOUT_S)
            except MavlinkTimeoutError as exc:
                raise VerifyError(
                    f"verify on {ap.url}: no {stream} for {VERIFY_STREAM_TIMEOUT_S:g} s after "
                    f"{len(ticks)} samples: check the link"
                ) from exc
            a, g, m = _fields(msg, stream, ap.autopilot)
            ticks.append(int(getattr(msg, base.field)))
            host.append(clock())
            acc.append(a)
            gyr.append(g)
            mag.append(m)
    finally:
        stop_stream(ap, stream, how)
    if not ticks:
        raise VerifyError(f"verify on {ap.url}: no {stream} received")
    timeline = vehicle.unwrap_times(np.array(ticks), base, np.array(host))
    keep = timeline.keep
    m = np.array(mag)[keep]
    if here:
        m = vehicle.onboard_correction(m, cp)
    a = np.array(acc)[keep]
    g = np.array(gyr)[keep]
    head = heading_consistency(timeline.t[keep], a, g, m) if keep.sum() > 1 else None
    return AutopilotVerifyReport(
        stream,
        here,
        cp.unit,
        norm_spread(m),
        head,
        int(keep.sum()),
        timeline.missing,
        int((~keep).sum()),
    )


def heading_of_session(
    session: Session, cp: vehicle.CompassParams, where: str
) -> HeadingConsistency | None:
    """Heading consistency of the parameters in force applied to a session recorded by
    ``magcal collect --mavlink`` (it must be this autopilot's and compass's)."""
    meta = session.meta
    if meta.get("autopilot") != cp.autopilot or meta.get("compass") != str(cp.compass):
        raise VerifyError(
            f"verify: {where} was recorded from {meta.get('autopilot', 'an unknown autopilot')} "
            f"compass {meta.get('compass', '?')}, not {cp.autopilot} compass {cp.compass}: give "
            "the session of this vehicle's compass"
        )
    if meta.get("mag_unit") != cp.unit:
        raise VerifyError(
            f"verify: {where}'s mag_unit is {meta.get('mag_unit')!r}, not {cp.unit!r}: it was "
            "not recorded by magcal collect --mavlink"
        )
    recorded = vehicle.params_from_meta(meta)
    m = vehicle.onboard_correction(session.mag, cp, recorded or None)
    return heading_consistency(session.t, session.acc, session.gyr, m)
