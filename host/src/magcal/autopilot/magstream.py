# SPDX-License-Identifier: Apache-2.0
"""Which magnetometer values in an autopilot's IMU stream are samples the vehicle measured.

An autopilot streams its IMU (``RAW_IMU``, ``SCALED_IMU``, ...) at the rate asked for and puts
into every message the latest compass reading it has; the compass itself updates at its own,
usually lower rate (ArduPilot's SITL compass at 10 Hz, a real one at 10–100 Hz). A value that
repeats is therefore no new measurement, and a value's time is that of the first message
carrying it. :class:`MagnetometerScreen` takes the stream row by row and decides:

- **new sample**: the value differs from the previous one (the streams carry no magnetometer
  time or counter; a change is the only evidence of a new reading). A quantised sensor held
  still can read the same counts twice: that reading is lost, which costs nothing, since a
  still sensor adds no information;
- **repeat**: the same value again; the row is an IMU-only row of the session;
- **fast turn**: the vehicle turned by more than :data:`MAX_TURN_RAD` (the gyroscope,
  integrated) between the previous value's row and this one's. Where within that interval
  the reading was taken is unknown, so its direction is uncertain by up to that turn, and an
  averaging driver blurs it: rejected (ArduPilot's calibration stand flips at up to 9 rad/s
  and gives readings with a field norm tens of percent off there);
- **frozen**: the value stayed while the vehicle turned by more than :data:`MAX_TURN_RAD`
  before the next one came: a reading that stopped updating, rejected.

The screen also integrates the gyroscope into the attitude relative to the first row
(``R_start_body``) at each accepted sample, for the coverage of orientations the vehicle
really took (:class:`magcal.device.coverage.AttitudeCoverage`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from magcal.calib import frames

#: A magnetometer value is rejected when the vehicle turned more than this (rad) between the
#: previous value's row and its own (fast turn), or while it stayed (frozen): a direction
#: uncertain by more than about 17°. Normal calibration motion (1–2 rad/s) with a 10 Hz
#: compass turns 0.1–0.2 rad between readings.
MAX_TURN_RAD = 0.3
#: A step between rows longer than this (s) is a gap in the stream (lost messages, a pause):
#: the attitude is not propagated across it.
MAX_PROPAGATION_STEP_S = 0.5


@dataclass(frozen=True)
class ScreenCounts:
    """What :class:`MagnetometerScreen` decided: rows seen, magnetometer values that were new
    (``changes``), accepted samples, and the rejected ones by reason."""

    rows: int
    changes: int
    accepted: int
    repeats: int
    fast_turn: int
    frozen: int

    def text(self) -> str:
        return (
            f"{self.accepted} magnetometer samples in {self.rows} IMU rows; "
            f"{self.repeats} rows repeated the previous value, {self.fast_turn} readings during "
            f"a fast turn and {self.frozen} frozen while turning were not used"
        )


class MagnetometerScreen:
    """Row-by-row decisions on a stream's magnetometer values (module docstring).

    Call :meth:`add` for every row in order (``row``: the caller's index of it), :meth:`finish`
    after the last. Accepted samples appear in ``rows`` (their row indices), ``values`` (as
    received) and ``attitudes`` (q_start_body at the row, :meth:`rotations` as matrices) once
    decided: a value is decided when the next new value arrives (its hold is then known) or
    at :meth:`finish`. A row costs a few microseconds (plain floats, no numpy), so that a
    live stream of thousands of messages a second keeps up.
    """

    def __init__(self, max_turn_rad: float = MAX_TURN_RAD) -> None:
        self.max_turn = float(max_turn_rad)
        self.rows: list[int] = []
        self.values: list[tuple[float, float, float]] = []
        self.attitudes: list[tuple[float, float, float, float]] = []
        self._n = 0  # rows seen
        self._q = (1.0, 0.0, 0.0, 0.0)
        self._t_prev: float | None = None
        self._w_prev = (0.0, 0.0, 0.0)
        self._last: tuple | None = None
        self._pending: tuple[int, tuple, tuple, float] | None = None
        self._turn = 0.0  # turn since the last new value's row, rad
        self._changes = self._repeats = self._fast = self._frozen = 0

    def add(self, row: int, t_s: float, gyr_rad_s: Sequence[float], value: tuple) -> None:
        """One row: its index, time (s, any origin, increasing; a step over
        MAX_PROPAGATION_STEP_S is a gap), gyroscope (3, rad/s) and magnetometer value."""
        w = (float(gyr_rad_s[0]), float(gyr_rad_s[1]), float(gyr_rad_s[2]))
        if self._t_prev is not None:
            dt = t_s - self._t_prev
            if 0.0 < dt <= MAX_PROPAGATION_STEP_S:
                wx, wy, wz = self._w_prev
                self._q = frames.quat_step(self._q, (wx * dt, wy * dt, wz * dt))
                self._turn += math.sqrt(wx * wx + wy * wy + wz * wz) * dt
        self._t_prev, self._w_prev = t_s, w
        self._n += 1
        value = tuple(value)
        if value == self._last:
            self._repeats += 1
            return
        self._changes += 1
        # the turn since the previous value's row is that value's hold and this one's turn
        # before (0 at the first row: nothing was integrated yet)
        self._decide(hold_turn=self._turn)
        self._last = value
        self._pending = (row, value, self._q, self._turn)
        self._turn = 0.0

    def finish(self) -> None:
        """Decide the last value (its hold so far)."""
        self._decide(hold_turn=self._turn)

    def _decide(self, hold_turn: float) -> None:
        if self._pending is None:
            return
        row, value, q, turn_before = self._pending
        self._pending = None
        if turn_before > self.max_turn:
            self._fast += 1
        elif hold_turn > self.max_turn:
            self._frozen += 1
        else:
            self.rows.append(row)
            self.values.append(value)
            self.attitudes.append(q)

    def rotations(self, start: int = 0, stop: int | None = None) -> np.ndarray:
        """(k, 3, 3) R_start_body of the accepted samples start..stop."""
        q = np.array(self.attitudes[start:stop], dtype=float).reshape(-1, 4)
        return frames.quat_to_matrix(q)

    def counts(self) -> ScreenCounts:
        return ScreenCounts(
            rows=self._n,
            changes=self._changes,
            accepted=len(self.rows),
            repeats=self._repeats,
            fast_turn=self._fast,
            frozen=self._frozen,
        )
