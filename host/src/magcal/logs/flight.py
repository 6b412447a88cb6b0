# SPDX-License-Identifier: Apache-2.0
"""A flight as a session: the armed, airborne stretch with a GNSS fix, every compass, GNSS
velocity, battery current and throttle.

**The stretch** (:func:`find_flight`). A sample is in flight when the vehicle was armed, in
the air and had a 3D GNSS fix:

- armed: the log's armed state (:attr:`LogStreams.armed`; armed throughout when the log does
  not say);
- in the air: the autopilot's land detector where the log records it
  (:attr:`LogStreams.airborne`: ArduPilot's NOT_LANDED / LAND_COMPLETE events, PX4's
  ``vehicle_land_detected``, MAVLink's EXTENDED_SYS_STATE); otherwise the GNSS altitude at
  least :data:`AIRBORNE_HEIGHT_M` above the ground, the 5th percentile of the altitude while
  armed with a fix;
- a fix: the latest GNSS solution at most :data:`GNSS_TIMEOUT_S` old (or three of the log's
  GNSS intervals, when it records them slowly), of fix type 3 (3D) or better.

The longest run of such samples is the flight imported.

**The rows** (:func:`flight_arrays`). As the hand-rotation session (:mod:`~magcal.logs.convert`)
every sample keeps its own time, and nothing measured is interpolated but the gyroscope's
mean rate:

- IMU rows at the log's IMU rate; above :data:`MAX_IMU_ROW_HZ` every k-th sample starts a
  row, k = ⌈rate / MAX_IMU_ROW_HZ⌉, and the row's accelerometer is the mean of its k samples;
- each compass's samples on rows at their own times (samples of several compasses stamped
  at the same time share a row: ArduPilot logs every MAG instance at one TimeUS);
- each GNSS solution on the nearest row within half a row period, or on a row of its own;
- the gyroscope of every row the exact mean of the IMU's piecewise-linear rate over the
  interval to the next row (:func:`~magcal.logs.convert.mean_rate`), so the rows turn the
  attitude through the angle the IMU measured, whatever was decimated;
- battery current and throttle held from their last sample (empty before the first).
"""

from __future__ import annotations

import datetime
import math
from dataclasses import dataclass

import numpy as np

from magcal.autopilot import vehicle
from magcal.io.session import Session, session_from_arrays
from magcal.logs.convert import Rows, mean_rate, param_text, session_meta
from magcal.logs.streams import GnssStream, LogStreams, MagStream, StepSignal
from magcal.logs.stretch import true_runs

#: Fix type from which a GNSS solution is used (GPS_FIX_TYPE_3D_FIX).
MIN_FIX_TYPE = 3
#: A GNSS solution older than this (or than this many of the log's GNSS intervals, if
#: longer) no longer counts as a fix, s.
GNSS_TIMEOUT_S = 2.0
GNSS_TIMEOUT_INTERVALS = 3.0
#: Without a land detector, in the air means this high above the ground, m.
AIRBORNE_HEIGHT_M = 3.0
#: Percentile of the armed GNSS altitude taken as the ground.
GROUND_PERCENTILE = 5.0
#: IMU rows faster than this are decimated, Hz.
MAX_IMU_ROW_HZ = 100.0
#: A flight shorter than this is not imported, s.
MIN_FLIGHT_S = 10.0


@dataclass(frozen=True)
class Flight:
    """The flight found in a log.

    start_s, end_s : the armed, airborne stretch with a 3D fix (log time, s)
    airborne_by    : what said the vehicle was in the air ("the land detector", "GNSS height")
    others         : how many other such stretches the log holds (shorter ones)
    """

    start_s: float
    end_s: float
    airborne_by: str
    others: int = 0

    @property
    def duration_s(self) -> float:
        return self.end_s - self.start_s


def describe(flight: Flight) -> str:
    """ "a flight of 343.4 s (58.13–401.52 s; in the air by the land detector)"."""
    more = f"; {flight.others} shorter one(s) left out" if flight.others else ""
    return (
        f"a flight of {flight.duration_s:.1f} s ({flight.start_s:.2f}–{flight.end_s:.2f} s log "
        f"time; armed, in the air by {flight.airborne_by}, with a 3D GNSS fix{more})"
    )


def fix_at(gnss: GnssStream, t: np.ndarray) -> np.ndarray:
    """(N,) bool: a GNSS solution of fix type ≥ MIN_FIX_TYPE at most GNSS_TIMEOUT_S old at each
    of ``t``."""
    i = np.searchsorted(gnss.t, t, side="right") - 1
    ok = i >= 0
    j = np.clip(i, 0, None)
    # a log that records the receiver slowly: three of its intervals
    timeout = GNSS_TIMEOUT_S
    if gnss.t.size > 1:
        timeout = max(timeout, GNSS_TIMEOUT_INTERVALS * float(np.median(np.diff(gnss.t))))
    return ok & (gnss.fix[j] >= MIN_FIX_TYPE) & (t - gnss.t[j] <= timeout)


def _armed(streams: LogStreams, t: np.ndarray) -> np.ndarray:
    if streams.armed is None:
        return np.ones(t.size, dtype=bool)
    return streams.armed.at(t) > 0.5


def _airborne(
    streams: LogStreams, t: np.ndarray, armed: np.ndarray, fix: np.ndarray
) -> tuple[np.ndarray, str]:
    if streams.airborne is not None:
        return streams.airborne.at(t) > 0.5, "the land detector"
    gnss = streams.gnss
    if gnss is None or not (armed & fix).any():
        return np.zeros(t.size, dtype=bool), "GNSS height"
    alt = np.interp(t, gnss.t, gnss.alt)
    ground = float(np.percentile(alt[armed & fix], GROUND_PERCENTILE))
    return alt > ground + AIRBORNE_HEIGHT_M, "GNSS height"


def in_flight(streams: LogStreams, t: np.ndarray) -> tuple[np.ndarray, str]:
    """(N,) bool: armed, in the air and with a 3D fix at each of ``t``; and what said it was
    in the air."""
    armed = _armed(streams, t)
    fix = fix_at(streams.gnss, t) if streams.gnss is not None else np.zeros(t.size, bool)
    airborne, by = _airborne(streams, t, armed, fix)
    return armed & airborne & fix, by


def find_flight(streams: LogStreams) -> tuple[Flight | None, str]:
    """The longest flight of the log (see the module docstring), or None and what is missing,
    as a clause for a refusal ("the vehicle never left the ground")."""
    t = streams.imu.t
    armed = _armed(streams, t)
    gnss = streams.gnss
    fix = fix_at(gnss, t) if gnss is not None else np.zeros(t.size, bool)
    airborne, by = _airborne(streams, t, armed, fix)
    if not armed.any():
        return None, "the vehicle was never armed"
    if streams.airborne is not None and not (armed & airborne).any():
        return None, "the vehicle never left the ground (the land detector never said otherwise)"
    if gnss is None:
        return None, "the log has no GNSS messages (a flight session needs GNSS velocity)"
    if not fix.any():
        return None, "the GNSS receiver never had a 3D fix"
    if not (armed & airborne).any():
        return None, (
            f"the vehicle never left the ground (armed, it never rose {AIRBORNE_HEIGHT_M:g} m "
            "above the ground by GNSS altitude, and the log records no land detector)"
        )
    runs = [(a, b) for a, b in true_runs(armed & airborne & fix) if t[b - 1] - t[a] > 0]
    if not runs:
        return None, "the GNSS receiver had no 3D fix while the vehicle was in the air"
    runs.sort(key=lambda r: t[r[1] - 1] - t[r[0]], reverse=True)
    a, b = runs[0]
    long_enough = [r for r in runs if t[r[1] - 1] - t[r[0]] >= MIN_FLIGHT_S]
    if not long_enough:
        return None, (
            f"the vehicle was in the air with a 3D GNSS fix for {t[b - 1] - t[a]:.1f} s at "
            f"most; a flight session needs {MIN_FLIGHT_S:g} s"
        )
    return Flight(float(t[a]), float(t[b - 1]), by, len(long_enough) - 1), ""


@dataclass(frozen=True)
class FlightArrays:
    """A flight session's columns over its rows (see the module docstring).

    t : (N,) s;  gyr : (N, 3) rad/s;  acc : (N, 3) m/s², NaN off IMU rows
    mags : compass number → (N, 3) its field, NaN off its rows, the first compass first
    vel : (N, 3) m/s north-east-down, NaN off GNSS rows
    current : (N,) A;  throttle : (N,) 0–1 (NaN before their first sample or when not logged)
    imu_rate_hz : the IMU's rate;  decimation : k, IMU samples per row
    """

    t: np.ndarray
    gyr: np.ndarray
    acc: np.ndarray
    mags: dict[int, np.ndarray]
    vel: np.ndarray
    current: np.ndarray
    throttle: np.ndarray
    imu_rate_hz: float
    decimation: int


def _held(signal: StepSignal | None, t: np.ndarray) -> np.ndarray:
    """The signal held from each sample on; NaN before its first or without one."""
    if signal is None or signal.t.size == 0:
        return np.full(t.size, np.nan)
    v = signal.at(t)
    v[t < signal.t[0]] = np.nan
    return v


def _usable(mag: MagStream) -> tuple[np.ndarray, np.ndarray]:
    """A compass's samples without those whose correction could not be undone."""
    if mag.suspect is None or not mag.suspect.any():
        return mag.t, mag.mag
    return mag.t[~mag.suspect], mag.mag[~mag.suspect]


def flight_arrays(streams: LogStreams, t0: float, t1: float) -> FlightArrays:
    """The rows of the flight session over [t0, t1] (inside the IMU's span)."""
    imu = streams.imu
    inside = np.flatnonzero((imu.t >= t0) & (imu.t <= t1))
    ti, ai = imu.t[inside], imu.acc[inside]
    rate = 1.0 / float(np.median(np.diff(imu.t)))
    k = max(1, math.ceil(rate / MAX_IMU_ROW_HZ - 1e-9))
    starts = np.arange(0, ti.size, k)
    t_imu = ti[starts]
    # the mean of each group of k samples (the last group may be shorter)
    acc_imu = np.add.reduceat(ai, starts, axis=0) / np.diff(np.append(starts, ti.size))[:, None]
    compasses = [streams.mag, *streams.other_mags]
    mag_data = []
    for m in compasses:
        tm, fm = _usable(m)
        sel = (tm >= t0) & (tm <= t1) & (tm >= imu.t[0]) & (tm <= imu.t[-1])
        mag_data.append((m.instance, tm[sel], fm[sel]))
    t = np.unique(np.concatenate([t_imu, *(tm for _, tm, _ in mag_data)]))
    gnss_t, gnss_v = np.zeros(0), np.zeros((0, 3))
    if streams.gnss is not None:
        g = streams.gnss
        # a solution with a horizontal velocity (telemetry's GPS_RAW_INT has no vertical one)
        horizontal = np.isfinite(g.vel[:, :2]).all(axis=1)
        sel = (g.t >= t0) & (g.t <= t1) & (g.fix >= MIN_FIX_TYPE) & horizontal
        gnss_t, gnss_v = g.t[sel], g.vel[sel]
    half_row = 0.5 * k / rate
    near = np.clip(np.searchsorted(t, gnss_t), 1, max(1, t.size - 1)) if t.size > 1 else None
    if near is not None and gnss_t.size:
        near = np.where(np.abs(t[near - 1] - gnss_t) <= np.abs(t[near] - gnss_t), near - 1, near)
        own = np.abs(t[near] - gnss_t) > half_row
        t = np.union1d(t, gnss_t[own])
    n = t.size
    gyr = np.empty((n, 3))
    if n > 1:
        gyr[:-1] = mean_rate(imu.t, imu.gyr, t[:-1], t[1:])
    gyr[-1] = [np.interp(t[-1], imu.t, imu.gyr[:, j]) for j in range(3)]
    acc = np.full((n, 3), np.nan)
    acc[np.searchsorted(t, t_imu)] = acc_imu
    mags = {}
    for instance, tm, fm in mag_data:
        field = np.full((n, 3), np.nan)
        field[np.searchsorted(t, tm)] = fm
        mags[instance] = field
    vel = np.full((n, 3), np.nan)
    if gnss_t.size:
        i = np.clip(np.searchsorted(t, gnss_t), 1, n - 1) if n > 1 else np.zeros(gnss_t.size, int)
        if n > 1:
            i = np.where(np.abs(t[i - 1] - gnss_t) <= np.abs(t[i] - gnss_t), i - 1, i)
        # two solutions nearest one row: the later one stays (rows hold one each)
        vel[i] = gnss_v
    return FlightArrays(
        t=t,
        gyr=gyr,
        acc=acc,
        mags=mags,
        vel=vel,
        current=_held(streams.current, t),
        throttle=_held(streams.throttle, t),
        imu_rate_hz=rate,
        decimation=k,
    )


def flight_columns(arrays: FlightArrays) -> dict[str, np.ndarray]:
    """The extra columns, in the order written: mag2_x … for every compass after the first
    (named by its number), vel_n/e/d, current, throttle."""
    out: dict[str, np.ndarray] = {}
    for instance, field in list(arrays.mags.items())[1:]:
        for j, axis in enumerate("xyz"):
            out[f"mag{instance}_{axis}"] = field[:, j]
    for j, axis in enumerate("ned"):
        out[f"vel_{axis}"] = arrays.vel[:, j]
    out["current"] = arrays.current
    out["throttle"] = arrays.throttle
    return out


def flight_meta(
    streams: LogStreams, arrays: FlightArrays, flight: Flight | None, t0: float, t1: float
) -> dict[str, str]:
    """The metadata a flight session adds to an imported session's (see docs/contracts.md):
    ``motion``, ``compasses``, ``location``, ``date``, ``flight_airborne_s``, the
    ``resampling`` of its rows, and ``param.NAME`` for every compass."""
    k = arrays.decimation
    if k > 1:
        imu = (
            f"IMU rows at {arrays.imu_rate_hz / k:.1f} Hz, every {k}th of the IMU's "
            f"{arrays.imu_rate_hz:.1f} Hz samples, the accelerometer the mean of the {k} "
            "samples from the row on"
        )
    else:
        imu = f"a row at each IMU sample ({arrays.imu_rate_hz:.1f} Hz)"
    meta = {
        "motion": "flight",
        "compasses": ",".join(str(c) for c in arrays.mags),
        "resampling": (
            f"{imu}; a row at each sample of each compass (compasses stamped at the same time "
            "share it); each GNSS solution on the nearest row within half a row period, or a "
            "row of its own; the gyroscope of each row the IMU's exact mean rate over the "
            "interval to the next row; current and throttle held from their last sample"
        ),
    }
    g = streams.gnss
    if g is not None:
        sel = (g.t >= t0) & (g.t <= t1) & (g.fix >= MIN_FIX_TYPE)
        if sel.any():
            lat, lon = float(np.median(g.lat[sel])), float(np.median(g.lon[sel]))
            alt_km = float(np.median(g.alt[sel])) / 1000.0
            meta["location"] = f"{lat:.7f},{lon:.7f},{alt_km:.4f}"
            utc = g.utc_s[sel]
            utc = utc[np.isfinite(utc)]
            if utc.size:
                day = datetime.datetime.fromtimestamp(float(np.median(utc)), datetime.UTC)
                meta["date"] = day.date().isoformat()
    t = streams.imu.t
    grid = t[(t >= t0) & (t <= t1)]
    airborne, _ = in_flight(streams, grid)
    steps = np.diff(grid)
    meta["flight_airborne_s"] = f"{float(np.sum(steps[airborne[:-1]])):.2f}"
    if flight is not None and flight.others:
        meta["flight_others"] = str(flight.others)
    in_force = streams.params.at(t1)
    names = [*streams.param_names, *streams.other_param_names]
    meta |= {
        vehicle.SESSION_PARAM_PREFIX + n: param_text(in_force[n])
        for n in dict.fromkeys(names)
        if n in in_force
    }
    changed = sorted(
        {n for when, n, _ in streams.params.changes if t0 <= when <= t1 and n in set(names)}
    )
    if changed:
        meta["params_changed"] = (
            f"{', '.join(changed)} changed within this range; the param. lines hold the values "
            "at its end"
        )
    return meta


def flight_session(
    streams: LogStreams, rows: Rows, sel: np.ndarray, flight: Flight | None
) -> Session:
    """The selected range as a flight session: the rows of :func:`flight_arrays`, the first
    compass in ``mag_*``, the others and the flight's signals in extra columns
    (:func:`flight_columns`), and the metadata of an imported session with
    :func:`flight_meta`'s."""
    t0, t1 = float(rows.t[sel][0]), float(rows.t[sel][-1])
    arrays = flight_arrays(streams, t0, t1)
    meta = session_meta(streams, rows, sel) | flight_meta(streams, arrays, flight, t0, t1)
    others = ", ".join(f"{m.instance} ({m.source})" for m in streams.other_mags)
    if others:
        meta["source"] += f"; other compasses {others}"
    first = arrays.mags[streams.mag.instance]
    return session_from_arrays(
        arrays.t, arrays.gyr, arrays.acc, first, meta, flight_columns(arrays)
    )
