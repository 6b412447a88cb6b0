# SPDX-License-Identifier: Apache-2.0
"""What a flight-log reader hands on: time series in SI units, parameters over time.

Every reader (:mod:`~magcal.logs.dataflash`, :mod:`~magcal.logs.tlog`,
:mod:`~magcal.logs.ulog`) turns its format into a :class:`LogStreams`; everything after that
(the hand-rotation detector, pairing the magnetometer with the IMU, the session file) is the
same for all of them. Times are the autopilot's own clock (seconds since boot), so that
``--start/--end`` mean the same thing as the times a log viewer shows.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from magcal.errors import MagcalError


class LogImportError(MagcalError):
    """A flight log cannot be imported: unreadable, or without the messages magcal needs."""


@dataclass(frozen=True)
class ImuStream:
    """One IMU's samples, body frame.

    t        : (N,) float, s, strictly increasing (autopilot boot time)
    gyr      : (N, 3) float, rad/s
    acc      : (N, 3) float, m/s², specific force (about +9.81 on the up axis at rest)
    instance : 1-based IMU number, as ``--imu`` counts
    source   : the messages or topic read, e.g. "IMU[0]", "sensor_combined"
    """

    t: np.ndarray
    gyr: np.ndarray
    acc: np.ndarray
    instance: int
    source: str


@dataclass(frozen=True)
class MagStream:
    """One magnetometer's raw samples (the on-board correction undone).

    t        : (M,) float, s, strictly increasing
    mag      : (M, 3) float, in ``unit``, in the frame ``frame`` describes
    instance : 1-based compass number, as ``--compass`` counts
    unit     : "mG" (ArduPilot) or "gauss" (PX4)
    frame    : one line saying which rotation, if any, the vector has been through
    source   : the messages or topic read
    suspect  : (M,) bool or None: samples that must not be imported (the correction could
               not be undone there), ``suspect_reason`` says why
    """

    t: np.ndarray
    mag: np.ndarray
    instance: int
    unit: str
    frame: str
    source: str
    suspect: np.ndarray | None = None
    suspect_reason: str = ""


@dataclass(frozen=True)
class GnssStream:
    """The GNSS receiver's solutions.

    t        : (K,) float, s, strictly increasing (autopilot boot time)
    fix      : (K,) int, fix type as MAVLink's GPS_FIX_TYPE counts it (3 = 3D fix; above:
               better, DGPS and RTK); below 3 the position is not used
    lat, lon : (K,) float, degrees north and east;  alt : (K,) float, m above mean sea level
    vel      : (K, 3) float, m/s, north-east-down
    utc_s    : (K,) float, UTC as seconds since 1970 (NaN where the receiver gave no time)
    source   : the messages or topic read
    """

    t: np.ndarray
    fix: np.ndarray
    lat: np.ndarray
    lon: np.ndarray
    alt: np.ndarray
    vel: np.ndarray
    utc_s: np.ndarray
    source: str


@dataclass(frozen=True)
class StepSignal:
    """A value that holds from each time on until the next one (armed state, throttle).

    t      : (K,) float, s, non-decreasing
    value  : (K,) float
    before : the value before t[0]; None: the first value (a periodic report of a state
             says what it was; an event log of changes, like ArduPilot's ARM, does not)
    """

    t: np.ndarray
    value: np.ndarray
    before: float | None = None

    def at(self, times: np.ndarray) -> np.ndarray:
        """The value in force at each of ``times`` (N,)."""
        i = np.searchsorted(self.t, np.asarray(times, dtype=float), side="right") - 1
        out = self.value[np.clip(i, 0, None)].astype(float)
        if self.before is not None:
            out[i < 0] = self.before
        return out


@dataclass(frozen=True)
class ParamTimeline:
    """Autopilot parameters and when they changed.

    initial : name → value in force from the start of the log
    changes : (time s, name, value), sorted by time; only real changes (a value repeated
              is not one)
    """

    initial: dict[str, float]
    changes: tuple[tuple[float, str, float], ...] = ()

    @staticmethod
    def from_records(records: list[tuple[float, str, float]]) -> ParamTimeline:
        """Build from every (time, name, value) record in log order: the first record of a
        name is its value from the start (the autopilot logs all parameters when a log
        opens, or the ground station fetches them when it connects); a later different value
        is a change."""
        initial: dict[str, float] = {}
        current: dict[str, float] = {}
        changes: list[tuple[float, str, float]] = []
        for t, name, value in sorted(records, key=lambda r: r[0]):
            value = float(value)
            if name not in current:
                initial[name] = value
            elif current[name] != value and not (np.isnan(current[name]) and np.isnan(value)):
                changes.append((float(t), name, value))
            current[name] = value
        return ParamTimeline(initial, tuple(changes))

    def at(self, t: float) -> dict[str, float]:
        """name → value in force at time ``t`` (s)."""
        out = dict(self.initial)
        for when, name, value in self.changes:
            if when > t:
                break
            out[name] = value
        return out

    def change_times(self, names: set[str] | frozenset[str]) -> np.ndarray:
        """(K,) times at which any of ``names`` changed."""
        return np.array([when for when, name, _ in self.changes if name in names], dtype=float)

    def names(self) -> set[str]:
        """Every parameter name the log holds."""
        return set(self.initial) | {name for _, name, _ in self.changes}


@dataclass(frozen=True)
class LogStreams:
    """Everything the importer needs from one log.

    path       : the log file
    log_format : "DataFlash", "tlog" or "ULog"
    autopilot  : magcal.autopilot.vehicle.ARDUPILOT or .PX4 ("ardupilot", "px4")
    imu, mag   : the chosen IMU and magnetometer
    params     : the autopilot parameters over time (compass ones at least, when logged)
    param_names: the names of the parameters that describe the chosen compass's on-board
                 correction (recorded in the session for a later ``flash``)
    param_compass: which parameter set that is (ArduPilot: the 1-based n of COMPASS_OFSn_X;
                 PX4: the n of CAL_MAGn_*)
    naming     : ArduPilot's parameter naming (magcal.autopilot.mapping.AP_NAMING_*); PX4 ""
    armed      : 1.0 while armed (motors may spin), else 0.0; None when the log does not say
    throttle   : 0..1; None when the log does not say
    other_mags : every other compass of the log, in compass order, each with its on-board
                 correction undone as ``mag``'s (a compass whose correction cannot be undone is
                 left out, with a note)
    other_param_names: the parameters of those compasses' corrections (and shared ones, such
                 as the motor-compensation type), recorded in a flight session
    gnss       : the GNSS solutions; None when the log has none
    current    : battery current, A; None when the log does not say
    airborne   : 1.0 while the autopilot's land detector says the vehicle is in the air;
                 None when the log does not say
    notes      : remarks for the user (e.g. samples dropped and why)
    known_gaps : (start s, end s, cause) of stretches whose cause the log tells (a logging
                 pause, a logger dropout); an IMU gap overlapping one has that cause
    gap_cause  : what other IMU gaps are, as far as the format tells ("lost messages")
    meta       : more session metadata the reader knows (e.g. a correction assumed)
    """

    path: str
    log_format: str
    autopilot: str
    imu: ImuStream
    mag: MagStream
    params: ParamTimeline
    param_names: tuple[str, ...] = ()
    param_compass: int = 1
    naming: str = ""
    armed: StepSignal | None = None
    throttle: StepSignal | None = None
    other_mags: tuple[MagStream, ...] = ()
    other_param_names: tuple[str, ...] = ()
    gnss: GnssStream | None = None
    current: StepSignal | None = None
    airborne: StepSignal | None = None
    notes: tuple[str, ...] = field(default_factory=tuple)
    known_gaps: tuple[tuple[float, float, str], ...] = ()
    gap_cause: str = "lost messages"
    meta: dict[str, str] = field(default_factory=dict)


def strictly_increasing(t: np.ndarray, *arrays: np.ndarray) -> tuple[np.ndarray, ...]:
    """Sort by time and drop repeated times (a sample logged twice, a message re-sent).

    t : (N,) s; arrays : (N, ...) each. Returns (t, *arrays) with t strictly increasing; of
    samples with equal times the first is kept.
    """
    order = np.argsort(t, kind="stable")
    t = np.asarray(t, dtype=float)[order]
    keep = np.concatenate([[True], np.diff(t) > 0]) if t.size else np.zeros(0, dtype=bool)
    return (t[keep],) + tuple(np.asarray(a)[order][keep] for a in arrays)


def untruncate(v: np.ndarray) -> np.ndarray:
    """The mean value behind C's cast of a float to an integer (truncation towards zero).

    ArduPilot logs and streams its compass field as ``(int16_t)field``, so a logged n ≠ 0
    came from (n, n + 1) or (n − 1, n): its mean is n ± ½. Left as it is, the truncation
    pulls every component half a unit towards zero, a bias that moves the fitted ellipsoid:
    in three simulated DataFlash logs (500 mG field, 2.5 mG noise) it raised the
    known-attitude heading-error floor from 0.024–0.042° to 0.043–0.10°; with the half unit
    added back the floor is that of the unrounded data. A logged 0 came from (−1, 1): its
    mean is 0.
    """
    v = np.asarray(v, dtype=float)
    return v + 0.5 * np.sign(v)


def instances_text(instances: list[int] | set[int]) -> str:
    """ "1, 2" or "none" for an error message."""
    return ", ".join(str(i) for i in sorted(instances)) or "none"
