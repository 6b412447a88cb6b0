# SPDX-License-Identifier: Apache-2.0
"""Are the session's columns in the units the calibration assumes? Checked against physics.

A session file carries no units in its columns: ``t`` must be in seconds, the gyroscope in
rad/s and the accelerometer in m/s² (``docs/contracts.md``). A file written in other units
reads without error and would calibrate to something wrong, so each unit is checked against
what the sensors must show whatever the motion:

* **time step** — the median positive step of ``t`` must give a sample rate some inertial
  sensor has (:data:`MIN_SAMPLE_RATE_HZ` … :data:`MAX_SAMPLE_RATE_HZ`). A step that only
  makes sense in milliseconds or microseconds names that unit.
* **accelerometer** — at rest it reads g. The median norm over the quietest samples names
  the unit it is in: m/s² (≈ 9.81), g (≈ 1) or mg (≈ 1000).
* **gyroscope** — a direction fixed in the world, seen in the body, turns as the gyroscope
  says: ``v_{t+T} = Exp(−ω T) v_t`` to first order (``magcal.calib.frames``: ``q_nb`` steps by
  ``exp_q(½ ω T)`` and ``v_b = R(q_nb)ᵀ v_n``). Gravity is such a direction. Carried back by
  the gyroscope's turn, ``R(q_nb) a_b``, the accelerometer must then read the same vector
  throughout. This is tested on pairs of short stretches a second apart between which the
  accelerometer's averaged direction turned by :data:`TURN_MIN_DEG` or more: the gyroscope
  read in rad/s and in °/s (and, where the time step allows it, with ``t`` in milliseconds)
  is tried, and the reading whose carried directions agree best is taken. A session whose
  gravity direction hardly turns (turned about the vertical only) cannot tell; the check
  then says nothing.

The accelerometer's *sign* cannot be checked this way: a negated accelerometer turns with
the gyroscope just as gravity does, and against the magnetometer it looks like a field whose
dip has the other sign (the world turned half a turn about north). The alignment's dip
warning names it (``magcal.calib.initial.alignment``).

A unit given on the command line (``--time-unit``, ``--gyro-unit``, ``--acc-unit``) is
applied by :func:`convert` and not checked: the person has said what the column holds.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

import numpy as np

from magcal.calib.frames import GRAVITY_M_S2, integrate_rates, quat_to_matrix
from magcal.errors import MagcalError
from magcal.io.session import Session

# --------------------------------------------------------------------------------------------
# The units a session's columns may be given in, as factors to the contract's unit.

#: ``t``: factor to seconds.
TIME_UNITS = {"s": 1.0, "ms": 1e-3, "us": 1e-6}
#: Gyroscope: factor to rad/s.
GYRO_UNITS = {"rad/s": 1.0, "deg/s": math.pi / 180.0}
#: Accelerometer: factor to m/s² (standard gravity for g).
STANDARD_GRAVITY_M_S2 = 9.80665
ACC_UNITS = {"m/s2": 1.0, "g": STANDARD_GRAVITY_M_S2, "mg": 1e-3 * STANDARD_GRAVITY_M_S2}
#: How the units are spoken of in messages.
_SPOKEN = {
    "s": "seconds",
    "ms": "milliseconds",
    "us": "microseconds",
    "rad/s": "rad/s",
    "deg/s": "°/s",
    "m/s2": "m/s²",
    "g": "g",
    "mg": "mg",
}

# --------------------------------------------------------------------------------------------
# Time step

#: Plausible sample rates of a session in seconds, Hz. No inertial sensor used to calibrate
#: a magnetometer is read slower than 1 Hz (magcal's own collection asks an autopilot for 10
#: Hz or more; integrating the gyroscope over a second's hand turn is already meaningless)
#: and none faster than 50 kHz (MEMS gyroscopes output at most 32 kHz). A step outside is
#: refused. With 1 Hz, ``t`` in milliseconds is told from the step alone up to 1 kHz; above
#: that the gyroscope check tells it (``TIME_UNITS`` readings tried there).
MIN_SAMPLE_RATE_HZ = 1.0
MAX_SAMPLE_RATE_HZ = 50_000.0

# --------------------------------------------------------------------------------------------
# Accelerometer

#: Relative tolerance of the accelerometer's norm at rest against g in a unit. The units are
#: a factor 9.8 or 1000 apart, so 25 % is far from any confusion and far wider than a real
#: accelerometer's scale error (1–3 %) plus what hand motion leaves in the quietest samples.
ACC_NORM_TOLERANCE = 0.25
#: Fraction of the accelerometer's samples taken as the quietest: those with the smallest
#: gyroscope rate (turning is what a hand does most; the ordering needs no unit).
QUIET_FRACTION = 0.25

# --------------------------------------------------------------------------------------------
# Gyroscope against the accelerometer's turn

#: The accelerometer is averaged over stretches of this length, s (in the time reading
#: tried), TURN_SPAN_S apart: hand accelerations (≈ 1 m/s², zero-mean over a fraction of a
#: second) then move its direction by a few degrees, not by tens. The average is taken in
#: the frame the gyroscope's turn carries the body to, so the turn within a stretch does not
#: blur it for the reading that is right.
TURN_AVERAGE_S = 0.25
TURN_SPAN_S = 1.0
#: A new pair of stretches starts every TURN_STRIDE_S, s, so MIN_TURN_WINDOWS pairs cover
#: two seconds of turning at least; at most MAX_TURN_WINDOWS pairs (a longer stride on long
#: sessions: the medians are stable long before).
TURN_STRIDE_S = 0.1
MIN_TURN_WINDOWS = 20
MAX_TURN_WINDOWS = 4000
#: Smallest turn of the accelerometer's averaged direction between the two stretches,
#: degrees. The right reading misses it by a few degrees (hand accelerations left after the
#: average, a gyroscope bias of a few °/s over the span); a reading without turn misses it
#: by all of it.
TURN_MIN_DEG = 20.0
#: A stretch is used only if every accelerometer sample in it is within this fraction of
#: the session's median norm (any unit): a shake or knock of g or more swamps gravity's
#: direction in the average.
TURN_QUIET_FRACTION = 0.5
#: A reading other than the contract's is taken only when it fits clearly better: the
#: contract's reading misses by at least CLEAR_RATIO times as much and by CLEAR_MARGIN_DEG
#: more, and the other reading misses by less than MAX_FIT_FRACTION of the accelerometer's
#: turn (a gyroscope unrelated to the accelerometer, e.g. with its axes mixed up, or
#: accelerations that swamp gravity, fit no reading and are left to the checks of the result).
CLEAR_RATIO = 3.0
CLEAR_MARGIN_DEG = 10.0
MAX_FIT_FRACTION = 0.5


class UnitsError(MagcalError):
    """A session's column looks like it is in another unit than the session format's (``t``
    in milliseconds, the gyroscope in °/s, the accelerometer in g)."""


@dataclass(frozen=True)
class SessionUnits:
    """The units a session's columns are in, as given on the command line; None: the session
    format's (s, rad/s, m/s²), checked by :func:`check_units`."""

    t: str | None = None
    gyr: str | None = None
    acc: str | None = None

    def __post_init__(self) -> None:
        for name, value, table in (
            ("time", self.t, TIME_UNITS),
            ("gyroscope", self.gyr, GYRO_UNITS),
            ("accelerometer", self.acc, ACC_UNITS),
        ):
            if value is not None and value not in table:
                raise MagcalError(
                    f"unknown {name} unit {value!r}: choose one of {', '.join(table)}"
                )

    def as_dict(self) -> dict[str, str]:
        """The units the columns were read in (the result's ``input_units``)."""
        return {"t": self.t or "s", "gyr": self.gyr or "rad/s", "acc": self.acc or "m/s2"}


@dataclass(frozen=True, eq=False)
class TurnReading:
    """One reading of the gyroscope tried against the accelerometer's turn.

    gyr_unit, time_unit : keys of GYRO_UNITS, TIME_UNITS
    windows     : int, pairs of stretches used (TURN_SPAN_S apart with t in ``time_unit``)
    residual_deg: float, median angle, degrees, between the pair's mean accelerometer
                  directions carried back by this reading's turn (NaN: fewer than
                  MIN_TURN_WINDOWS pairs)
    contract_residual_deg : float, degrees, the same for the contract's reading (rad/s, t in
                  seconds) on these pairs
    turn_deg    : float, degrees, median turn of the accelerometer's mean direction between
                  the pair's stretches (in the body frame)
    """

    gyr_unit: str
    time_unit: str
    windows: int
    residual_deg: float
    contract_residual_deg: float
    turn_deg: float


@dataclass(frozen=True, eq=False)
class UnitsReport:
    """The figures the units were judged on, and the refusal (``message``; "" when none).

    median_step        : float, median positive step of ``t``, the file's time unit
    acc_norm_at_rest   : float, median accelerometer norm over the quietest samples, the
                         file's accelerometer unit (NaN: no accelerometer sample)
    readings           : tuple of TurnReading, the gyroscope readings tried (empty when the
                         check was skipped)
    gyro_check         : str, "done", or why it was skipped
    message            : str, the refusal, one paragraph ("" when the units look right)
    problems           : list of str, each wrong unit's part of it
    """

    median_step: float
    acc_norm_at_rest: float
    readings: tuple[TurnReading, ...] = ()
    gyro_check: str = ""
    message: str = ""
    problems: list[str] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return not self.message


# --------------------------------------------------------------------------------------------
# The checks


def median_step(t: np.ndarray) -> float:
    """Median of the positive steps of ``t`` (N,), in its own unit (NaN: none)."""
    dt = np.diff(np.asarray(t, dtype=float))
    dt = dt[np.isfinite(dt) & (dt > 0.0)]
    return float(np.median(dt)) if dt.size else float("nan")


def _plausible_rate(rate_hz: float) -> bool:
    return MIN_SAMPLE_RATE_HZ <= rate_hz <= MAX_SAMPLE_RATE_HZ


def _fmt_rate(rate_hz: float) -> str:
    if rate_hz >= 1000.0:
        return f"{rate_hz / 1000.0:.3g} kHz"
    return f"{rate_hz:.3g} Hz"


def time_step_problem(step: float) -> str:
    """Why a median step ``step`` (the file's unit) cannot be seconds ("" when it can)."""
    if not np.isfinite(step):
        return ""
    rate = 1.0 / step
    if _plausible_rate(rate):
        return ""
    for unit in ("ms", "us"):
        rate_u = 1.0 / (step * TIME_UNITS[unit])
        if _plausible_rate(rate_u):
            return (
                f"t looks like {_SPOKEN[unit]}, not seconds: its median step is {step:.6g}, "
                f"i.e. {_fmt_rate(rate)} in seconds but {_fmt_rate(rate_u)} in "
                f"{_SPOKEN[unit]}: write t in seconds (divide it by "
                f"{1.0 / TIME_UNITS[unit]:.0f}) or pass --time-unit {unit}"
            )
    slow = rate < MIN_SAMPLE_RATE_HZ
    return (
        f"t's median step is {step:.6g} s, i.e. a sample rate of {rate:.3g} Hz, "
        f"{'slower' if slow else 'faster'} than any inertial sensor is read "
        f"({MIN_SAMPLE_RATE_HZ:g} Hz to {MAX_SAMPLE_RATE_HZ / 1000:g} kHz): write t in seconds"
    )


def acc_norm_at_rest(gyr: np.ndarray, acc: np.ndarray) -> float:
    """Median accelerometer norm over the QUIET_FRACTION of its samples with the smallest
    gyroscope rate, in the accelerometer's own unit.

    gyr : (N, 3) float, any rate unit (only its ordering is used)
    acc : (N, 3) float, any unit; NaN rows (no sample) are skipped
    """
    acc = np.asarray(acc, dtype=float)
    rate = np.linalg.norm(np.asarray(gyr, dtype=float), axis=1)
    ok = np.all(np.isfinite(acc), axis=1) & np.isfinite(rate)
    if not ok.any():
        return float("nan")
    norm, rate = np.linalg.norm(acc[ok], axis=1), rate[ok]
    quiet = rate <= np.quantile(rate, QUIET_FRACTION)
    return float(np.median(norm[quiet]))


def acc_unit_problem(norm: float) -> str:
    """Why an accelerometer whose norm at rest is ``norm`` cannot be in m/s² ("" when it can).

    m/s² is accepted within a factor 2 of g: a scale that wrong is a fault the calibration's
    own checks report, not a unit. Outside, the unit within ACC_NORM_TOLERANCE is named."""
    if not np.isfinite(norm) or 0.5 * GRAVITY_M_S2 <= norm <= 2.0 * GRAVITY_M_S2:
        return ""
    for unit in ("g", "mg"):
        at_rest = STANDARD_GRAVITY_M_S2 / ACC_UNITS[unit]
        if abs(norm / at_rest - 1.0) <= ACC_NORM_TOLERANCE:
            factor = ACC_UNITS[unit]
            return (
                f"the accelerometer looks like {_SPOKEN[unit]}, not m/s²: at rest it reads "
                f"{norm:.4g} (the median norm of its quietest samples), where m/s² would read "
                f"{GRAVITY_M_S2} and {_SPOKEN[unit]} {at_rest:.4g}: write it in m/s² "
                f"(multiply by {factor:.6g}) or pass --acc-unit {unit}"
            )
    return (
        f"the accelerometer reads {norm:.4g} at rest (the median norm of its quietest "
        f"samples), where m/s² would read {GRAVITY_M_S2}, g 1 and mg 1000: it is in no unit "
        "of acceleration (raw counts?); write it in m/s² using the sensor's scale"
    )


def _cumsum0(x: np.ndarray) -> np.ndarray:
    """Cumulative sum along axis 0 with a leading zero: sums of rows [i, j) are c[j] − c[i]."""
    return np.concatenate([np.zeros((1,) + x.shape[1:]), np.cumsum(x, axis=0)])


@dataclass(frozen=True, eq=False)
class _Pairs:
    """Pairs of averaging stretches, as row ranges [a0, a1) and [b0, b1) (each (K,) int)."""

    a0: np.ndarray
    a1: np.ndarray
    b0: np.ndarray
    b1: np.ndarray

    def angles_deg(self, v: np.ndarray) -> np.ndarray:
        """Angle between the means of v (N, 3) (zero rows: no sample) over each pair, deg."""
        c = _cumsum0(v)
        a, b = c[self.a1] - c[self.a0], c[self.b1] - c[self.b0]
        cos = np.einsum("ij,ij->i", a, b) / (np.linalg.norm(a, axis=1) * np.linalg.norm(b, axis=1))
        return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))

    def select(self, keep: np.ndarray) -> _Pairs:
        return _Pairs(self.a0[keep], self.a1[keep], self.b0[keep], self.b1[keep])


def _stretch_pairs(t: np.ndarray, has_acc: np.ndarray, quiet: np.ndarray, seconds: float) -> _Pairs:
    """Pairs of TURN_AVERAGE_S stretches TURN_SPAN_S apart, starting every TURN_STRIDE_S,
    with ``t`` read in units of ``seconds`` s; both stretches hold an accelerometer sample and
    only ``quiet`` ones (N,) bool."""
    avg, span = TURN_AVERAGE_S / seconds, TURN_SPAN_S / seconds
    last = t[-1] - span - avg
    if not last > t[0]:
        empty = np.zeros(0, dtype=int)
        return _Pairs(empty, empty, empty, empty)
    stride = max(TURN_STRIDE_S / seconds, (last - t[0]) / MAX_TURN_WINDOWS)
    s = np.arange(t[0], last, stride)
    a0, a1 = np.searchsorted(t, s), np.searchsorted(t, s + avg)
    b0, b1 = np.searchsorted(t, s + span), np.searchsorted(t, s + span + avg)
    n = _cumsum0(has_acc.astype(float))
    loud = _cumsum0((has_acc & ~quiet).astype(float))
    keep = (n[a1] > n[a0]) & (n[b1] > n[b0]) & (loud[a1] == loud[a0]) & (loud[b1] == loud[b0])
    return _Pairs(a0[keep], a1[keep], b0[keep], b1[keep])


def gyro_turn_readings(
    t: np.ndarray,
    gyr: np.ndarray,
    acc: np.ndarray,
    time_units: tuple[str, ...] = ("s",),
    gyro_units: tuple[str, ...] = tuple(GYRO_UNITS),
) -> tuple[TurnReading, ...]:
    """Each reading (gyroscope unit × time unit) of the gyroscope against the accelerometer's
    turn: see the module docstring.

    t   : (N,) float, increasing, the file's time unit
    gyr : (N, 3) float, finite, the file's gyroscope unit; row k held over [t_k, t_{k+1})
    acc : (N, 3) float, any unit; NaN rows: no accelerometer sample
    Returns one :class:`TurnReading` per pair, residual NaN where fewer than
    MIN_TURN_WINDOWS pairs of stretches turned by TURN_MIN_DEG.

    For a pair of stretches, the accelerometer's samples are carried to one frame by the
    gyroscope's turn, ``R(q_k) a_k`` with ``q_k`` the gyroscope integrated from the first
    row (:func:`magcal.calib.frames.integrate_rates`): gravity is then the same vector
    throughout, if the reading is right. The residual is the angle between the two
    stretches' means; the turn is the same angle without the gyroscope (the body frame).
    """
    t = np.asarray(t, dtype=float)
    gyr = np.asarray(gyr, dtype=float)
    acc = np.asarray(acc, dtype=float)
    has_acc = np.all(np.isfinite(acc), axis=1)
    a = np.where(has_acc[:, None], acc, 0.0)
    norm = np.linalg.norm(a, axis=1)
    quiet = np.abs(norm / np.median(norm[has_acc]) - 1.0) <= TURN_QUIET_FRACTION
    dt = np.diff(t)
    # One integration per scale factor: the turn between two rows is exact whatever the
    # attitude reached since the start (a prefix product of quaternions).
    carried: dict[float, np.ndarray] = {}

    def in_start_frame(scale: float) -> np.ndarray:
        if scale not in carried:
            q = integrate_rates(scale * gyr[:-1], dt)
            carried[scale] = np.einsum("kij,kj->ki", quat_to_matrix(q), a)
        return carried[scale]

    out = []
    for time_unit in time_units:
        f_t = TIME_UNITS[time_unit]
        pairs = _stretch_pairs(t, has_acc, quiet, f_t)
        turn = pairs.angles_deg(a)
        pairs = pairs.select(turn >= TURN_MIN_DEG)
        turn = turn[turn >= TURN_MIN_DEG]
        nan = float("nan")
        miss = dict.fromkeys(gyro_units, nan)
        contract = typical_turn = nan
        if turn.size >= MIN_TURN_WINDOWS:
            typical_turn = float(np.median(turn))
            contract = float(np.median(pairs.angles_deg(in_start_frame(1.0))))
            for u in gyro_units:
                miss[u] = float(np.median(pairs.angles_deg(in_start_frame(GYRO_UNITS[u] * f_t))))
        out += [
            TurnReading(
                gyr_unit=u,
                time_unit=time_unit,
                windows=int(turn.size),
                residual_deg=miss[u],
                contract_residual_deg=contract,
                turn_deg=typical_turn,
            )
            for u in gyro_units
        ]
    return tuple(out)


def _clearly_better(r: TurnReading) -> bool:
    """The reading fits clearly better than the contract's on its stretches."""
    if not np.isfinite(r.residual_deg):
        return False
    return (
        r.contract_residual_deg >= CLEAR_RATIO * r.residual_deg
        and r.contract_residual_deg - r.residual_deg >= CLEAR_MARGIN_DEG
        and r.residual_deg <= MAX_FIT_FRACTION * r.turn_deg
    )


def gyro_unit_problem(readings: tuple[TurnReading, ...]) -> str:
    """Why the readings say the gyroscope or t is not in the contract's unit ("" when they
    do not)."""
    tried = [r for r in readings if np.isfinite(r.residual_deg)]
    if not tried:
        return ""
    best = min(tried, key=lambda r: r.residual_deg)
    if (best.gyr_unit, best.time_unit) == ("rad/s", "s") or not _clearly_better(best):
        return ""
    looks, fix = [], []
    if best.gyr_unit != "rad/s":
        looks.append(f"the gyroscope looks like {_SPOKEN[best.gyr_unit]}, not rad/s")
        fix.append(
            f"write the gyroscope in rad/s (multiply by {GYRO_UNITS[best.gyr_unit]:.6g}) or "
            f"pass --gyro-unit {best.gyr_unit}"
        )
    if best.time_unit != "s":
        looks.append(f"t looks like {_SPOKEN[best.time_unit]}, not seconds")
        fix.append(
            f"write t in seconds (divide by {1.0 / TIME_UNITS[best.time_unit]:.0f}) or pass "
            f"--time-unit {best.time_unit}"
        )
    read_as = [f"in {_SPOKEN[best.gyr_unit]}"]
    if best.time_unit != "s":
        read_as.append(f"with t in {_SPOKEN[best.time_unit]}")
    return (
        f"{' and '.join(looks)}: where the accelerometer's direction turned (a median "
        f"{best.turn_deg:.0f}° between stretches {TURN_SPAN_S:g} s apart, {best.windows} "
        f"times), the gyroscope's turn read in rad/s with t in seconds misses it by a median "
        f"{best.contract_residual_deg:.1f}°, read {' '.join(read_as)} by "
        f"{best.residual_deg:.1f}°: {'; '.join(fix)}"
    )


def check_units(
    t: np.ndarray,
    gyr: np.ndarray,
    acc: np.ndarray,
    declared: SessionUnits = SessionUnits(),
) -> UnitsReport:
    """Check a session's units against physics (module docstring).

    t   : (N,) float, increasing, seconds if right
    gyr : (N, 3) float, rad/s if right
    acc : (N, 3) float, m/s² if right; NaN rows: no accelerometer sample
    declared : the units given on the command line; those given are not checked (the
          arrays are then already converted, see :func:`convert`)

    Returns the figures and, when a unit looks wrong, the refusal's one-paragraph message.
    """
    t = np.asarray(t, dtype=float)
    gyr = np.asarray(gyr, dtype=float)
    acc = np.asarray(acc, dtype=float)
    step = median_step(t)
    norm = acc_norm_at_rest(gyr, acc)
    problems = []
    if declared.t is None and (p := time_step_problem(step)):
        problems.append(p)
    if declared.acc is None and (p := acc_unit_problem(norm)):
        problems.append(p)
    readings: tuple[TurnReading, ...] = ()
    gyro_check = "done"
    if declared.gyr is not None and declared.t is not None:
        gyro_check = "skipped: both units given"
    elif problems:
        gyro_check = "skipped: another unit is wrong"
    elif not (np.all(np.isfinite(gyr)) and np.all(np.isfinite(t))) or len(t) < 2:
        gyro_check = "skipped: non-finite values"
    else:
        # t in milliseconds is tried where the step allows it (a rate the sensors have).
        time_units = ("s",)
        if declared.t is None and np.isfinite(step) and _plausible_rate(1.0 / (step * 1e-3)):
            time_units = ("s", "ms")
        gyro_units = ("rad/s",) if declared.gyr is not None else tuple(GYRO_UNITS)
        readings = gyro_turn_readings(t, gyr, acc, time_units, gyro_units)
        if not any(np.isfinite(r.residual_deg) for r in readings):
            gyro_check = (
                f"skipped: fewer than {MIN_TURN_WINDOWS} pairs of stretches between which the "
                f"accelerometer's direction turned by {TURN_MIN_DEG:.0f}°"
            )
        elif p := gyro_unit_problem(readings):
            problems.append(p)
    message = ""
    if problems:
        message = (
            "The session's units are not the session format's (t in seconds, the gyroscope "
            "in rad/s, the accelerometer in m/s²): " + "; ".join(problems) + "."
        )
    return UnitsReport(
        median_step=step,
        acc_norm_at_rest=norm,
        readings=readings,
        gyro_check=gyro_check,
        message=message,
        problems=problems,
    )


# --------------------------------------------------------------------------------------------
# On a session


def convert(session: Session, declared: SessionUnits) -> Session:
    """``session`` with the columns given in ``declared`` units converted to the session
    format's (s, rad/s, m/s²); the session itself when none was given."""
    changes = {}
    if declared.t is not None and declared.t != "s":
        changes["t"] = session.t * TIME_UNITS[declared.t]
    if declared.gyr is not None and declared.gyr != "rad/s":
        changes["gyr"] = session.gyr * GYRO_UNITS[declared.gyr]
    if declared.acc is not None and declared.acc != "m/s2":
        changes["acc"] = session.acc * ACC_UNITS[declared.acc]
    return dataclasses.replace(session, **changes) if changes else session


def checked_session(session: Session, declared: SessionUnits = SessionUnits()) -> Session:
    """The session in the format's units: the ``declared`` units converted, the others
    checked (:func:`check_units`). Raises :class:`UnitsError` with the report's message when
    a unit looks wrong."""
    session = convert(session, declared)
    report = check_units(session.t, session.gyr, session.acc, declared)
    if not report.ok:
        raise UnitsError(report.message)
    return session
