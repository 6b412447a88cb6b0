# SPDX-License-Identifier: Apache-2.0
"""From a log's streams to a magcal session: pair the sensors in time, cut, describe.

**Pairing.** A session row holds one gyroscope, accelerometer and magnetometer vector at one
time. Logs sample the magnetometer more slowly than the IMU (ArduPilot logs MAG at its
compass-read rate, 10–100 Hz, and IMU at the loop rate, 50–400 Hz+; PX4 sensor_mag at
50–100 Hz, sensor_combined at 200+ Hz). The rows are placed at the **magnetometer's own
sample times**, and the IMU is brought to them:

- the magnetometer is never interpolated: each row's field is one real reading, with its own
  noise. Interpolating it onto the IMU's faster clock would invent readings whose errors are
  correlated, which the maximum-likelihood fit would count as independent evidence, and would
  bend the field's path between readings while the vehicle turns;
- the gyroscope of row k is the **mean rate over [t_k, t_k+1]**, the integral of the
  piecewise-linear IMU rate divided by the interval, because that is how the calibration's
  filter uses it (``q_{k+1} = q_k ⊙ exp(½ (t_{k+1} − t_k) ω_k)``): the row then turns the
  attitude through the angle the IMU measured, whatever the ratio of the rates (sampling
  the rate at t_k only would lose most of a fast turn's detail at 10 Hz);
- the accelerometer is linearly interpolated at t_k.

The last magnetometer sample only closes the previous interval and is not a row; samples
outside the IMU's time span are dropped. IMU data missing for longer than
``max(IMU_GAP_MIN_S, IMU_GAP_FACTOR × its median interval)`` (telemetry loss) makes the rows
across the gap unusable: they are marked, the detector avoids them, and an explicit range
over them keeps its longest stretch between the gaps.

**The session.** Those rows choose the range (the hand-rotation detector works on them);
the session written keeps every sample of the range at its own rate, a multi-rate session
(``magcal-session: 2``, :func:`multirate_arrays`): a row at each IMU sample (gyroscope and
accelerometer) and one at each magnetometer sample (its field; the accelerometer empty), the
gyroscope of every row the mean rate over the interval to the next row, as above. Nothing
the IMU measured between two magnetometer samples is averaged away.
"""

from __future__ import annotations

import os
from dataclasses import dataclass

import numpy as np

from magcal.autopilot import mapping, params, vehicle
from magcal.io.session import Session, session_from_arrays
from magcal.logs.streams import ImuStream, LogImportError, LogStreams, MagStream
from magcal.logs.stretch import true_runs

IMU_GAP_MIN_S = 0.1
IMU_GAP_FACTOR = 10.0
#: Gaps named in one message at most.
MAX_GAPS_LISTED = 3
#: A stretch between gaps shorter than this many rows is not worth importing.
MIN_STRETCH_ROWS = 2


@dataclass(frozen=True)
class Rows:
    """Paired samples at the magnetometer's times.

    t              : (K,) s;  gyr : (K, 3) rad/s, mean over [t_k, t_k+1];  acc : (K, 3) m/s²
    mag            : (K, 3) raw magnetometer units
    gap            : (K,) bool, the row's interval holds an IMU gap
    gaps           : (start s, end s) of each IMU gap (the last sample before, the first after)
    suspect        : (K,) bool, the field's correction could not be undone (see MagStream)
    imu_rate_hz, mag_rate_hz : median sample rates
    """

    t: np.ndarray
    gyr: np.ndarray
    acc: np.ndarray
    mag: np.ndarray
    gap: np.ndarray
    suspect: np.ndarray
    imu_rate_hz: float
    mag_rate_hz: float
    gaps: tuple[tuple[float, float], ...] = ()


def mean_rate(t: np.ndarray, gyr: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Mean of the piecewise-linear rate through (t, gyr) over each [a_k, b_k].

    t : (N,) s, increasing;  gyr : (N, 3);  a, b : (K,) with t[0] ≤ a < b ≤ t[-1]
    returns (K, 3): (G(b) − G(a)) / (b − a) with G the exact integral of the interpolant.
    """
    dt = np.diff(t)
    cum = np.concatenate([np.zeros((1, 3)), np.cumsum(0.5 * (gyr[1:] + gyr[:-1]) * dt[:, None], 0)])

    def integral(x: np.ndarray) -> np.ndarray:
        i = np.clip(np.searchsorted(t, x, side="right") - 1, 0, t.size - 2)
        u = (x - t[i])[:, None]
        slope = (gyr[i + 1] - gyr[i]) / dt[i][:, None]
        return cum[i] + gyr[i] * u + 0.5 * slope * u * u

    return (integral(b) - integral(a)) / (b - a)[:, None]


def pair(imu: ImuStream, mag: MagStream) -> Rows:
    """Rows at the magnetometer's sample times (see the module docstring)."""
    if imu.t.size < 2 or mag.t.size < 2:
        raise LogImportError(
            f"too few samples to pair: {imu.t.size} IMU and {mag.t.size} magnetometer samples"
        )
    inside = (mag.t >= imu.t[0]) & (mag.t <= imu.t[-1])
    t_m = mag.t[inside]
    field = mag.mag[inside]
    suspect = mag.suspect[inside] if mag.suspect is not None else np.zeros(t_m.size, bool)
    if t_m.size < 2:
        raise LogImportError(
            f"the magnetometer ({mag.source}, {mag.t[0]:.1f}–{mag.t[-1]:.1f} s) and the IMU "
            f"({imu.source}, {imu.t[0]:.1f}–{imu.t[-1]:.1f} s) hardly overlap in time"
        )
    a, b = t_m[:-1], t_m[1:]
    gyr = mean_rate(imu.t, imu.gyr, a, b)
    acc = np.column_stack([np.interp(a, imu.t, imu.acc[:, j]) for j in range(3)])
    imu_dt = np.diff(imu.t)
    limit = max(IMU_GAP_MIN_S, IMU_GAP_FACTOR * float(np.median(imu_dt)))
    gap = np.zeros(a.size, dtype=bool)
    gaps = []
    for g in np.flatnonzero(imu_dt > limit):
        gap |= (a < imu.t[g + 1]) & (b > imu.t[g])
        gaps.append((float(imu.t[g]), float(imu.t[g + 1])))
    return Rows(
        t=a,
        gyr=gyr,
        acc=acc,
        mag=field[:-1],
        gap=gap,
        suspect=suspect[:-1],
        imu_rate_hz=1.0 / float(np.median(imu_dt)),
        mag_rate_hz=1.0 / float(np.median(np.diff(t_m))),
        gaps=tuple(gaps),
    )


def _range_problem(rows: Rows, sel: np.ndarray, what: np.ndarray) -> tuple[float, float] | None:
    hit = np.flatnonzero(sel & what)
    if hit.size == 0:
        return None
    return float(rows.t[hit[0]]), float(rows.t[hit[-1]])


def describe_gap(gap: tuple[float, float], streams: LogStreams) -> str:
    """ "251.42–879.34 s (627.9 s without IMU data: a logging pause)"."""
    a, b = gap
    known = [c for g0, g1, c in streams.known_gaps if g0 <= b + 1e-6 and a <= g1 + 1e-6]
    cause = known[0] if known else streams.gap_cause
    return f"{a:.2f}–{b:.2f} s ({b - a:.2f} s without IMU data: {cause})"


def cut(
    rows: Rows, start_s: float, end_s: float, streams: LogStreams
) -> tuple[np.ndarray, tuple[str, ...]]:
    """(K,) bool: the rows in [start_s, end_s], and notes. A range across IMU gaps keeps its
    longest stretch between them (said in a note); ranges with unusable rows are refused."""
    name = os.path.basename(streams.path)
    sel = (rows.t >= start_s) & (rows.t <= end_s)
    if not sel.any():
        raise LogImportError(
            f"{name}: no samples between {start_s:g} and {end_s:g} s; the paired data span "
            f"{rows.t[0]:.1f}–{rows.t[-1]:.1f} s (log time)"
        )
    notes: tuple[str, ...] = ()
    if (sel & rows.gap).any():
        # the last row's interval reaches the next row's time, which may be past end_s
        last = int(np.flatnonzero(sel)[-1])
        reach = max(end_s, float(rows.t[min(last + 1, rows.t.size - 1)]))
        inside = [g for g in rows.gaps if g[1] > start_s and g[0] < reach]
        runs = true_runs(sel & ~rows.gap)
        a, b = max(runs, key=lambda r: r[1] - r[0], default=(0, 0))
        listed = "; ".join(describe_gap(g, streams) for g in inside[:MAX_GAPS_LISTED])
        more = f" and {len(inside) - MAX_GAPS_LISTED} more" if len(inside) > MAX_GAPS_LISTED else ""
        if b - a < MIN_STRETCH_ROWS:
            raise LogImportError(
                f"{name}: IMU data are missing at {listed}{more}, and no stretch between the "
                "gaps in this range is long enough to import; choose another range with "
                "--start/--end"
            )
        sel = np.zeros_like(sel)
        sel[a:b] = True
        notes = (
            f"IMU data are missing at {listed}{more}; the longest stretch between the gaps, "
            f"{rows.t[a]:.2f}–{rows.t[b - 1]:.2f} s, was imported",
        )
    bad = _range_problem(rows, sel, rows.suspect)
    if bad is not None:
        raise LogImportError(
            f"{name}: from {bad[0]:.2f} s on, {streams.mag.suspect_reason}; choose a range "
            "before it with --start/--end"
        )
    return sel, notes


def param_text(value: float) -> str:
    """A parameter for the metadata: integers exactly (device ids exceed float32's 2**24),
    others as the shortest text of their float32 (what the autopilot holds)."""
    if float(value).is_integer() and abs(value) < 2**53:
        return str(int(value))
    return params.value_text(value, None)


def compass_external(streams: LogStreams, in_force: dict[str, float]) -> str | None:
    """ "1" external, "0" internal, None unknown: ArduPilot COMPASS_EXTERNn ≠ 0, PX4
    CAL_MAGn_ROT ≥ 0 (−1 marks an internal magnetometer)."""
    if streams.autopilot == vehicle.ARDUPILOT:
        name = mapping.ap_external_name(streams.param_compass, streams.naming or "legacy")
        value = in_force.get(name)
        return None if value is None else ("1" if value != 0 else "0")
    value = in_force.get(f"CAL_MAG{streams.param_compass}_ROT")
    return None if value is None else ("1" if value >= 0 else "0")


def session_meta(streams: LogStreams, rows: Rows, sel: np.ndarray) -> dict[str, str]:
    """The session's metadata: the contract's ``source`` and ``mag_unit``, and the keys
    ``magcal collect`` writes over MAVLink (``autopilot``, ``compass``, ``compass_external``,
    ``mag_frame``, ``param.NAME`` for each compass parameter in force at the end of the
    range), so that ``flash`` and ``verify`` treat an imported session like a collected one;
    plus where in which log it came from."""
    name = os.path.basename(streams.path)
    t0, t1 = float(rows.t[sel][0]), float(rows.t[sel][-1])
    in_force = streams.params.at(t1)
    recorded = {n: in_force[n] for n in streams.param_names if n in in_force}
    changed = sorted(
        {n for when, n, _ in streams.params.changes if t0 <= when <= t1 and n in recorded}
    )
    meta = {
        "source": (
            f"{name} ({vehicle.AUTOPILOT_NAMES[streams.autopilot]} {streams.log_format} log), "
            f"compass {streams.mag.instance} ({streams.mag.source}), IMU "
            f"{streams.imu.instance} ({streams.imu.source}), {t0:.3f}–{t1:.3f} s"
        ),
        "autopilot": streams.autopilot,
        "compass": str(streams.mag.instance),
        "imu": str(streams.imu.instance),
        "log_file": name,
        "log_format": streams.log_format,
        "log_start_s": f"{t0:.6f}",
        "log_end_s": f"{t1:.6f}",
        "gyr_unit": "rad/s",
        "acc_unit": "m/s^2",
        "mag_unit": streams.mag.unit,
        "mag_frame": streams.mag.frame,
        "resampling": (
            f"every sample at its own rate: a row at each IMU sample ({rows.imu_rate_hz:.1f} Hz) "
            f"and at each magnetometer sample ({rows.mag_rate_hz:.1f} Hz); the gyroscope of "
            "each row is the IMU's mean rate over the interval to the next row"
        ),
    }
    meta |= streams.meta
    external = compass_external(streams, in_force)
    if external is not None:
        meta["compass_external"] = external
    if streams.naming and streams.naming != mapping.AP_NAMING_LEGACY:
        meta["param_naming"] = streams.naming
    if changed:
        meta["params_changed"] = (
            f"{', '.join(changed)} changed within this range; the param. lines hold the values "
            "at its end"
        )
    meta |= {vehicle.SESSION_PARAM_PREFIX + n: param_text(v) for n, v in recorded.items()}
    return meta


def multirate_arrays(
    imu: ImuStream, mag: MagStream, t0: float, t1: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(t, gyr, acc, mag) of the multi-rate session over [t0, t1] (inside the IMU's span):
    a row at every IMU and every magnetometer sample time (one row where both coincide);
    ``acc`` NaN on rows without an IMU sample, ``mag`` NaN on rows without a magnetometer
    sample; ``gyr`` of row k the mean rate of the IMU's piecewise-linear rate over
    [t_k, t_k+1] (:func:`mean_rate`), of the last row its rate at that time."""
    in_imu = (imu.t >= t0) & (imu.t <= t1)
    in_mag = (mag.t >= t0) & (mag.t <= t1)
    t = np.union1d(imu.t[in_imu], mag.t[in_mag])
    gyr = np.empty((t.size, 3))
    if t.size > 1:
        gyr[:-1] = mean_rate(imu.t, imu.gyr, t[:-1], t[1:])
    gyr[-1] = [np.interp(t[-1], imu.t, imu.gyr[:, j]) for j in range(3)]
    acc = np.full((t.size, 3), np.nan)
    acc[np.searchsorted(t, imu.t[in_imu])] = imu.acc[in_imu]
    field = np.full((t.size, 3), np.nan)
    field[np.searchsorted(t, mag.t[in_mag])] = mag.mag[in_mag]
    return t, gyr, acc, field


def to_session(streams: LogStreams, rows: Rows, sel: np.ndarray) -> Session:
    """The selected range as a multi-rate :class:`~magcal.io.session.Session` (see the
    module docstring) with metadata."""
    t0, t1 = float(rows.t[sel][0]), float(rows.t[sel][-1])
    t, gyr, acc, mag = multirate_arrays(streams.imu, streams.mag, t0, t1)
    return session_from_arrays(t, gyr, acc, mag, session_meta(streams, rows, sel))
