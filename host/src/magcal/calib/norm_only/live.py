# SPDX-License-Identifier: Apache-2.0
"""Live calibration while a session is being recorded: is it good enough to stop?

:class:`LiveCalibration` runs Zhao et al.'s CKF (:mod:`magcal.calib.norm_only.ckf`) on the
magnetometer stream and, when asked with the coverage of field directions the recorder
measures, says how good the current estimate is (:class:`LiveState`). It knows nothing about
links or devices: the serial ``collect`` (``magcal.device.collect``) feeds it, and a MAVLink
recorder can feed it the same way (``add`` the readings, ``state(coverage)`` for the display).

What is shown and how "converged" is decided:

* **Norm spread**: std / mean of ``‖T (y − b)‖`` over the last :data:`WINDOW_S` of readings
  with the current estimate (the calibrated field norm should be constant). It cannot go
  below the sensor's noise (σ / field); a much larger value means a poor fit or a disturbed
  field.
* **Uncertainty**: the largest, over :data:`N_DIRECTIONS` directions covering the sphere, of
  the calibrated norm's standard deviation that the filter's covariance ``P`` implies at the
  estimated ellipsoid in that direction. Directions never visited keep a large ``P``, so
  this also says when part of the sphere is still missing.
* **Stability**: the largest change, over the same directions, of the calibrated norm
  between the estimate of :data:`STABILITY_S` ago and now (the covariance alone can be
  optimistic while the filter is still moving).
* **Converged**: uncertainty ≤ :data:`MAX_NORM_STD` and change ≤ :data:`MAX_NORM_CHANGE`
  (0.3 % of the field each: a field-size error of 0.3 % in one direction tilts the corrected
  field by at most about 0.2°).
* **OK to stop**: converged and the coverage at least ``ok_coverage`` (default
  :data:`OK_COVERAGE`).

Cost: at high sample rates the CKF runs on block means of about :data:`CKF_RATE_HZ` (a 1 kHz
stream is averaged over blocks of 10; averaging reduces the noise the filter sees, which it
measures itself, and a block of 10 ms bends the path of a 3 rad/s rotation by 4e-5 of the
field). Every sample costs one addition; each block mean one CKF update (tens of µs);
:meth:`LiveCalibration.state` a fixed amount of work (call it a few times a second).
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

import numpy as np

from magcal.calib.norm_only.ckf import CkfEstimate, CubatureCalibrator

#: The CKF runs on block means of the stream at about this rate, Hz.
CKF_RATE_HZ = 100.0
#: The norm spread is taken over this much of the most recent stream, s.
WINDOW_S = 3.0
#: The estimate's change is measured over this long, s ...
STABILITY_S = 3.0
#: ... from snapshots taken this often, s.
SNAPSHOT_S = 1.0
#: Converged: the worst direction's 1σ of the calibrated norm from P at most this (fraction
#: of the field) ...
MAX_NORM_STD = 0.003
#: ... and the calibrated norm changed by at most this in every direction over STABILITY_S.
MAX_NORM_CHANGE = 0.003
#: Coverage of field directions at which, converged, the user may stop (collect's default
#: target).
OK_COVERAGE = 0.9
#: Directions at which uncertainty and change are evaluated (a Fibonacci sphere).
N_DIRECTIONS = 100


def fibonacci_sphere(n: int) -> np.ndarray:
    """(n, 3) unit vectors spread evenly over the sphere (golden-angle spiral)."""
    k = np.arange(n) + 0.5
    z = 1.0 - 2.0 * k / n
    phi = math.pi * (3.0 - math.sqrt(5.0)) * k
    r = np.sqrt(1.0 - z * z)
    return np.column_stack([r * np.cos(phi), r * np.sin(phi), z])


_DIRECTIONS = fibonacci_sphere(N_DIRECTIONS)


@dataclass(frozen=True)
class LiveState:
    """The live estimate as a recorder displays it.

    readings     : magnetometer readings given so far
    started      : the filter has started (its first readings spanned enough directions)
    norm_spread  : std/mean of the calibrated norm over the last WINDOW_S (None before the
                   start)
    norm_std     : worst direction's 1σ of the calibrated norm from the covariance (fraction
                   of the field; None before the start)
    norm_change  : largest change of the calibrated norm over STABILITY_S (None until the
                   filter has run that long)
    converged    : norm_std ≤ MAX_NORM_STD and norm_change ≤ MAX_NORM_CHANGE
    coverage     : the coverage of field directions given to :meth:`LiveCalibration.state`
    ok_to_stop   : converged and coverage ≥ the calibration's ``ok_coverage``
    """

    readings: int
    started: bool
    norm_spread: float | None
    norm_std: float | None
    norm_change: float | None
    converged: bool
    coverage: float
    ok_to_stop: bool

    def text(self) -> str:
        """A short phrase for a progress line (kept short: the line is rewritten in place)."""
        if not self.started:
            return "norm: waiting for more directions"
        spread = f"norm spread {100 * self.norm_spread:.2f} %"
        if self.ok_to_stop:
            return f"ok to stop: coverage {100 * self.coverage:.0f} %, {spread}"
        return f"{spread} ({'converged' if self.converged else 'settling'})"


class LiveCalibration:
    """The CKF on a magnetometer stream (see the module docstring).

    sample_rate_hz : the stream's rate (sets the block length for :data:`CKF_RATE_HZ`);
                     None or ≤ 0 runs the filter on every reading
    ok_coverage    : coverage (0..1) needed, with convergence, for "ok to stop"
    """

    def __init__(
        self,
        sample_rate_hz: float | None,
        *,
        ok_coverage: float = OK_COVERAGE,
        ckf_rate_hz: float = CKF_RATE_HZ,
    ) -> None:
        rate = float(sample_rate_hz) if sample_rate_hz and sample_rate_hz > 0 else ckf_rate_hz
        self.block = max(1, round(rate / ckf_rate_hz))
        self.ckf_rate_hz = rate / self.block
        self.ok_coverage = float(ok_coverage)
        self.ckf = CubatureCalibrator()
        self.readings = 0
        self._sum = np.zeros(3)
        self._in_block = 0
        self._window = np.empty((max(2, math.ceil(WINDOW_S * self.ckf_rate_hz)), 3))
        self._n_window = 0
        self._snapshot_every = max(1, round(SNAPSHOT_S * self.ckf_rate_hz))
        self._snapshots: deque[CkfEstimate] = deque(maxlen=round(STABILITY_S / SNAPSHOT_S) + 1)
        self._next_snapshot = 0

    def add(self, mag: np.ndarray) -> None:
        """Readings (3,) or (N, 3), any fixed unit, in stream order."""
        y = np.asarray(mag, dtype=float).reshape(-1, 3)
        if y.shape[0] == 0:
            return
        self.readings += y.shape[0]
        # Complete the open block, then whole blocks at once, then keep the remainder.
        first = min(self.block - self._in_block, y.shape[0])
        self._sum += y[:first].sum(axis=0)
        self._in_block += first
        means = []
        if self._in_block == self.block:
            means.append(self._sum / self.block)
            self._sum = np.zeros(3)
            self._in_block = 0
        rest = y[first:]
        whole = rest.shape[0] // self.block * self.block
        if whole:
            means.extend(rest[:whole].reshape(-1, self.block, 3).mean(axis=1))
        if rest.shape[0] > whole:
            self._sum = rest[whole:].sum(axis=0)
            self._in_block = rest.shape[0] - whole
        if means:
            self._feed(np.array(means))

    def _feed(self, means: np.ndarray) -> None:
        """Block means into the filter, with a snapshot every SNAPSHOT_S of stream."""
        i = 0
        while i < means.shape[0]:
            if not self.ckf.started:
                self.ckf.update_many(means[i : i + 1])  # before the start: a reservoir add
                i += 1
                if self.ckf.started:
                    self._next_snapshot = self.ckf.updates
            else:
                k = max(0, self._next_snapshot - self.ckf.updates)
                chunk = means[i : i + k]
                self.ckf.update_many(chunk)
                i += chunk.shape[0]
            if self.ckf.started and self.ckf.updates >= self._next_snapshot:
                self._snapshots.append(self.ckf.estimate)
                self._next_snapshot = self.ckf.updates + self._snapshot_every
        for m in means[-self._window.shape[0] :]:
            self._window[self._n_window % self._window.shape[0]] = m
            self._n_window += 1

    def state(self, coverage: float) -> LiveState:
        """The estimate's state now, with the recorder's coverage (0..1)."""
        if not self.ckf.started:
            return LiveState(self.readings, False, None, None, None, False, coverage, False)
        est = self.ckf.estimate
        n = min(self._n_window, self._window.shape[0])
        norms = est.norms(self._window[:n])
        spread = float(np.std(norms) / np.mean(norms)) if n > 1 else 0.0
        points = est.points(_DIRECTIONS)
        norm_std = float(np.max(est.norm_std(points)))
        change = None
        if len(self._snapshots) == self._snapshots.maxlen:
            raw = est.centre + est.scale * points
            change = float(np.max(np.abs(self._snapshots[0].norms(raw) - 1.0)))
        converged = norm_std <= MAX_NORM_STD and change is not None and change <= MAX_NORM_CHANGE
        ok = converged and coverage >= self.ok_coverage
        return LiveState(self.readings, True, spread, norm_std, change, converged, coverage, ok)
