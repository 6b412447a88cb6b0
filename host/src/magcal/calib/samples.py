# SPDX-License-Identifier: Apache-2.0
"""Multi-rate sessions: the magnetometer's own samples, glitches removed, and a view at them.

A multi-rate session (``magcal-session: 2``) has the IMU at its rate and the magnetometer at
its own, lower one: rows without a magnetometer sample have NaN there (``Session.has_mag``).
Two functions here serve every calibration method, in this order:

* :func:`drop_magnetometer_glitches`: a re-sent value (an exact repeat of the previous
  magnetometer sample in a stream that repeats often) and an isolated jump are not samples:
  their rows become rows without the magnetometer;
* :func:`at_magnetometer_rows`: the session seen at the magnetometer's rows only, a
  single-rate session, for everything that works per magnetometer sample (the ellipsoid
  fits, the norm-only methods, the initial estimate, the sensor-level checks and the
  consistency checks). The maximum-likelihood step instead uses every row: it propagates
  with every IMU row and updates each sensor where it measured (``likelihood/problem.py``).

A session whose rows all have both sensors and whose magnetometer has no glitches passes
through both unchanged (the same object).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from magcal.io.session import Session

#: Exact repeats of the previous magnetometer sample are re-sent values, not samples, when
#: more than this fraction of the stream's samples repeat (:func:`repeated_samples`).
REPEATED_FRACTION = 0.2
#: Neighbours on each side whose component-wise median an isolated jump is measured against.
JUMP_NEIGHBOURS = 2
#: A magnetometer sample is an isolated jump when its distance from the median of its
#: neighbours exceeds this many robust sigmas of all such distances (1.4826 × their median
#: absolute deviation above their median; for smooth motion the distance is the path's
#: curvature plus noise) ...
JUMP_ROBUST_SIGMAS = 10.0
#: ... and exceeds this multiple of the neighbours' own spread about that median (their
#: largest distance from it): a step in the field (a change of the surroundings) or a fast
#: turn moves the neighbours apart too, an isolated spike does not.
JUMP_OVER_SPREAD = 2.0


@dataclass(frozen=True)
class MagnetometerSamples:
    """What :func:`drop_magnetometer_glitches` did: magnetometer samples used, exact repeats
    of the previous sample and isolated jumps dropped."""

    used: int
    repeated: int
    jumps: int

    def as_dict(self) -> dict:
        return {"used": self.used, "repeated": self.repeated, "jumps": self.jumps}

    def warning(self) -> str | None:
        """One line for the result's warnings when samples were dropped, else None."""
        if not self.repeated and not self.jumps:
            return None
        left_out = []
        if self.repeated:
            left_out.append(
                f"{self.repeated} exact repeats of the previous value (re-sent, not new readings)"
            )
        if self.jumps:
            left_out.append(f"{self.jumps} isolated jump{'s' if self.jumps > 1 else ''}")
        return f"magnetometer: {self.used} samples used; left out: {' and '.join(left_out)}"


def repeated_samples(mag: np.ndarray) -> np.ndarray:
    """(K,) bool over magnetometer samples (K, 3): the sample is a re-sent one, not new.

    A sample equal to the previous one exactly is re-sent when such repeats are common in
    the stream (more than :data:`REPEATED_FRACTION` of its samples): a stream re-sending its
    latest reading (an autopilot's telemetry faster than its compass) repeats at least every
    other sample, moving or not. A quantised sensor held still can also read the same counts
    twice, but only while still, a small part of a calibration's motion: those repeats are
    real samples and are kept. (A still, coarsely quantised sensor that repeats more often
    loses them; the next reading that differs is used, so little is lost.) A real stream
    with noise above its resolution (a phone at 25 Hz) never repeats all three axes.
    """
    rep = np.zeros(mag.shape[0], dtype=bool)
    rep[1:] = (mag[1:] == mag[:-1]).all(axis=1)
    if rep.sum() <= REPEATED_FRACTION * mag.shape[0]:
        rep[:] = False
    return rep


def isolated_jumps(mag: np.ndarray) -> np.ndarray:
    """(K,) bool over magnetometer samples (K, 3): isolated jumps (see
    :data:`JUMP_ROBUST_SIGMAS`, :data:`JUMP_OVER_SPREAD`). The first and last
    :data:`JUMP_NEIGHBOURS` samples are never flagged (too few neighbours)."""
    k = mag.shape[0]
    h = JUMP_NEIGHBOURS
    jumps = np.zeros(k, dtype=bool)
    if k < 2 * h + 5:
        return jumps
    offsets = [o for o in range(-h, h + 1) if o != 0]
    centre = mag[h : k - h]
    neighbours = np.stack([mag[h + o : k - h + o] for o in offsets], axis=1)  # (M, 2h, 3)
    median = np.median(neighbours, axis=1)
    distance = np.linalg.norm(centre - median, axis=1)
    spread = np.linalg.norm(neighbours - median[:, None, :], axis=2).max(axis=1)
    level = float(np.median(distance))
    sigma = 1.4826 * float(np.median(np.abs(distance - level)))
    if sigma <= 0.0:
        return jumps
    jumps[h : k - h] = (distance > level + JUMP_ROBUST_SIGMAS * sigma) & (
        distance > JUMP_OVER_SPREAD * spread
    )
    return jumps


def drop_magnetometer_glitches(session: Session) -> tuple[Session, MagnetometerSamples]:
    """The session with re-sent values (:func:`repeated_samples`), then isolated jumps
    (:func:`isolated_jumps`, among the remaining samples), turned into rows without the
    magnetometer, and the counts. The same object when nothing was dropped."""
    rows = np.flatnonzero(session.has_mag)
    repeated = repeated_samples(session.mag[rows])
    kept = rows[~repeated]
    jumps = isolated_jumps(session.mag[kept])
    counts = MagnetometerSamples(
        used=int(kept.size - jumps.sum()), repeated=int(repeated.sum()), jumps=int(jumps.sum())
    )
    if not repeated.any() and not jumps.any():
        return session, counts
    mag = session.mag.copy()
    mag[rows[repeated]] = np.nan
    mag[kept[jumps]] = np.nan
    return Session(
        t=session.t, gyr=session.gyr, acc=session.acc, mag=mag, meta=session.meta
    ), counts


def without_magnetometer_between(session: Session, spans_s: list[tuple[float, float]]) -> Session:
    """The session with the magnetometer's readings inside each span (start, end), s on the
    session's clock, ends included, turned into rows without the magnetometer: the IMU rows
    stay, so a filter propagates through the span with the gyroscope."""
    drop = np.zeros(session.t.size, dtype=bool)
    for start, end in spans_s:
        drop |= (session.t >= start) & (session.t <= end)
    if not (drop & session.has_mag).any():
        return session
    mag = session.mag.copy()
    mag[drop] = np.nan
    return Session(t=session.t, gyr=session.gyr, acc=session.acc, mag=mag, meta=session.meta)


def at_magnetometer_rows(session: Session) -> Session:
    """The session at its magnetometer rows: a single-rate session (every row has all three).

    gyroscope : the mean rate from that row to the next magnetometer row, i.e. the rotation
                between the two samples divided by their interval, summed exactly as the
                filter propagates (row r turns the attitude by ``gyr[r] (t[r+1] − t[r])``),
                so a filter on the view turns through the same angles as on every row. The
                last magnetometer row takes the rows after it (its own rate if none).
    accelerometer : linearly interpolated at the row's time from the rows that have it
                (the nearest one beyond the ends).
    magnetometer : the samples themselves, never interpolated.

    A session whose rows all have both sensors is returned as it is.
    """
    has_mag = session.has_mag
    if has_mag.all() and session.has_acc.all():
        return session
    t, gyr = session.t, session.gyr
    rows = np.flatnonzero(has_mag)
    # Rotation up to each row: cum[r] = Σ_{s<r} gyr[s] (t[s+1] − t[s]).
    cum = np.zeros((t.size, 3))
    cum[1:] = np.cumsum(gyr[:-1] * np.diff(t)[:, None], axis=0)
    ends = np.append(rows[1:], t.size - 1)
    mean = np.empty((rows.size, 3))
    span = t[ends] - t[rows]
    moving = span > 0
    mean[moving] = (cum[ends[moving]] - cum[rows[moving]]) / span[moving, None]
    mean[~moving] = gyr[rows[~moving]]
    has_acc = session.has_acc
    t_acc, acc = t[has_acc], session.acc[has_acc]
    acc_at = np.column_stack([np.interp(t[rows], t_acc, acc[:, j]) for j in range(3)])
    return Session(
        t=t[rows].copy(), gyr=mean, acc=acc_at, mag=session.mag[rows].copy(), meta=session.meta
    )
