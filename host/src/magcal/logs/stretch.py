# SPDX-License-Identifier: Apache-2.0
"""Find the stretch of a flight log where the vehicle was turned by hand.

A log holds much that is no use for a calibration: the vehicle on the ground, taxiing,
flying. What a calibration needs is the part where someone picked the vehicle up and turned
it through all orientations. :func:`find_hand_rotation` finds it from the inertial data
alone (plus the armed state and throttle when the log has them):

1. **Rotating.** The angular rate ``‖ω‖`` (raw gyroscope; a bias of a degree or two per
   second is far below the threshold) averaged over ``smooth_s`` must be at least
   ``min_rate_rad_s``. Turning a vehicle by hand runs at 0.5–3 rad/s; a vehicle at rest
   or being carried reads a few hundredths.
2. **Not flying.** Samples while armed or above ``max_throttle`` are out (a vehicle can
   rotate in flight, and its motors disturb the compass); so are samples where the specific
   force's norm departs from g by more than ``max_acc_rms_m_s2`` RMS over ``smooth_s``: a
   hand moves a vehicle with about 1 m/s² (some 0.6 m/s² along gravity), a vehicle in a
   turn, a climb or a launch with several. Samples the caller marks unusable (IMU data
   lost, a correction that cannot be undone) count as flight too.
3. **Stretches.** Runs of rotating, not-flying samples, joined across pauses shorter than
   ``max_gap_s`` (a person changes grip) in which the vehicle did not fly; runs shorter than
   ``min_duration_s`` are dropped.
4. **Choice.** Each stretch is scored by how much of the sphere the gravity direction
   covered in the body frame (the accelerometer direction averaged over a quarter second,
   in 100 equal-area cells, :mod:`magcal.device.coverage`): a calibration needs the vehicle
   tilted every way, and flight, even when armed state and throttle are missing, keeps the
   specific force near the body's vertical. Stretches below ``min_tilt_coverage`` are not a
   hand rotation (a flight, a turn on a table) and are dropped. The best is the one with the
   most coverage; stretches within ``coverage_tie`` of it count as equal and the longest
   wins.
5. **Margin.** The chosen stretch is widened by ``margin_s`` on both sides as far as the
   vehicle was not flying, so that the calibration also sees the rest before and after (it
   measures the gyroscope bias there).

The function is pure (arrays in, a list out) and does not read files.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from magcal.device import coverage

STANDARD_GRAVITY_M_S2 = 9.80665


@dataclass(frozen=True)
class StretchConfig:
    """Thresholds of :func:`find_hand_rotation` (see the module docstring)."""

    smooth_s: float = 1.0
    min_rate_rad_s: float = 0.3
    max_acc_rms_m_s2: float = 2.5
    max_throttle: float = 0.05
    max_gap_s: float = 3.0
    min_duration_s: float = 5.0
    gravity_smooth_s: float = 0.25
    coverage_tie: float = 0.05
    min_tilt_coverage: float = 0.1
    margin_s: float = 2.0


@dataclass(frozen=True)
class Stretch:
    """One stretch of hand rotation.

    start_s, end_s   : the rotation itself (log time, s)
    from_s, to_s     : with the margin of rest around it: what to import
    tilt_coverage    : fraction of gravity directions seen in the body frame (0–1)
    mean_rate_rad_s  : mean ‖ω‖ over the stretch
    """

    start_s: float
    end_s: float
    from_s: float
    to_s: float
    tilt_coverage: float
    mean_rate_rad_s: float

    @property
    def duration_s(self) -> float:
        return self.end_s - self.start_s


def _moving_average(x: np.ndarray, w: int) -> np.ndarray:
    """Centred moving average over ``w`` samples along axis 0 (shorter at the ends)."""
    n = x.shape[0]
    w = max(1, min(int(w), n))
    c = np.cumsum(np.concatenate([np.zeros((1,) + x.shape[1:]), x]), axis=0)
    lo = np.clip(np.arange(n) - w // 2, 0, n)
    hi = np.clip(np.arange(n) - w // 2 + w, 0, n)
    count = (hi - lo).reshape((n,) + (1,) * (x.ndim - 1))
    return (c[hi] - c[lo]) / count


def true_runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """[start, stop) index ranges where ``mask`` is true."""
    d = np.diff(np.concatenate([[0], mask.astype(np.int8), [0]]))
    return list(zip(np.flatnonzero(d == 1).tolist(), np.flatnonzero(d == -1).tolist(), strict=True))


def find_hand_rotation(
    t: np.ndarray,
    gyr: np.ndarray,
    acc: np.ndarray,
    armed: np.ndarray | None = None,
    throttle: np.ndarray | None = None,
    unusable: np.ndarray | None = None,
    config: StretchConfig = StretchConfig(),
) -> list[Stretch]:
    """Stretches of hand rotation, best first (empty when there is none).

    t        : (N,) s, strictly increasing
    gyr      : (N, 3) rad/s;  acc : (N, 3) m/s², specific force
    armed    : (N,) bool or None (unknown: not used)
    throttle : (N,) 0–1 or None (unknown: not used)
    unusable : (N,) bool or None: samples that must not be imported (lost IMU data, a
               correction that cannot be undone); treated like flight
    """
    t = np.asarray(t, dtype=float)
    n = t.size
    if n < 2:
        return []
    dt = float(np.median(np.diff(t)))
    w = max(1, int(round(config.smooth_s / dt)))
    rate = _moving_average(np.linalg.norm(gyr, axis=1), w)
    dev = np.linalg.norm(acc, axis=1) - STANDARD_GRAVITY_M_S2
    flying = np.sqrt(_moving_average(dev * dev, w)) > config.max_acc_rms_m_s2
    if armed is not None:
        flying |= np.asarray(armed, dtype=bool)
    if throttle is not None:
        flying |= np.asarray(throttle, dtype=float) > config.max_throttle
    if unusable is not None:
        flying |= np.asarray(unusable, dtype=bool)
    rotating = (rate >= config.min_rate_rad_s) & ~flying

    runs: list[list[int]] = []
    for a, b in true_runs(rotating):
        # Join to the previous run across a short pause in which the vehicle did not fly.
        if (
            runs
            and t[a] - t[runs[-1][1] - 1] <= config.max_gap_s
            and not flying[runs[-1][1] : a].any()
        ):
            runs[-1][1] = b
        else:
            runs.append([a, b])

    cells = coverage.make_cells()
    up = _moving_average(acc, max(1, int(round(config.gravity_smooth_s / dt))))
    norm = np.linalg.norm(up, axis=1, keepdims=True)
    up = up / np.where(norm > 0, norm, 1.0)
    stretches = []
    for a, b in runs:
        if t[b - 1] - t[a] < config.min_duration_s:
            continue
        counts = coverage.cell_counts(cells, up[a:b])
        tilt = coverage.coverage_fraction(counts)
        if tilt < config.min_tilt_coverage:
            continue
        lo, hi = _widen(t, flying, a, b, config.margin_s)
        stretches.append(
            Stretch(
                start_s=float(t[a]),
                end_s=float(t[b - 1]),
                from_s=float(t[lo]),
                to_s=float(t[hi - 1]),
                tilt_coverage=tilt,
                mean_rate_rad_s=float(np.mean(rate[a:b])),
            )
        )
    if not stretches:
        return []
    best = max(s.tilt_coverage for s in stretches)
    return sorted(
        stretches,
        key=lambda s: (s.tilt_coverage >= best - config.coverage_tie, s.duration_s),
        reverse=True,
    )


def _widen(t: np.ndarray, flying: np.ndarray, a: int, b: int, margin_s: float) -> tuple[int, int]:
    """[a, b) widened by up to margin_s on each side, not into flight."""
    lo = int(np.searchsorted(t, t[a] - margin_s, side="left"))
    fly_before = np.flatnonzero(flying[lo:a])
    if fly_before.size:
        lo = lo + int(fly_before[-1]) + 1
    hi = int(np.searchsorted(t, t[b - 1] + margin_s, side="right"))
    fly_after = np.flatnonzero(flying[b:hi])
    if fly_after.size:
        hi = b + int(fly_after[0])
    return lo, hi


def describe(stretch: Stretch) -> str:
    """One line for the user: where, how long, how much tilt."""
    return (
        f"hand rotation {stretch.start_s:.1f}–{stretch.end_s:.1f} s ({stretch.duration_s:.1f} s, "
        f"mean rate {stretch.mean_rate_rad_s:.2f} rad/s, gravity seen from "
        f"{100 * stretch.tilt_coverage:.0f} % of directions)"
    )


def explain_none(
    t: np.ndarray,
    gyr: np.ndarray,
    acc: np.ndarray,
    armed: np.ndarray | None = None,
    throttle: np.ndarray | None = None,
    unusable: np.ndarray | None = None,
    config: StretchConfig = StretchConfig(),
) -> str:
    """Why :func:`find_hand_rotation` found nothing (same arguments), for the error message."""
    if np.asarray(t).size < 2:
        return "the log has fewer than two samples"
    untilted = dataclasses.replace(config, min_tilt_coverage=0.0)
    rotations = find_hand_rotation(t, gyr, acc, armed, throttle, unusable, untilted)
    if rotations:
        r = max(rotations, key=lambda s: s.tilt_coverage)
        return (
            f"the vehicle turned at {r.start_s:.1f}–{r.end_s:.1f} s but the gravity direction "
            f"covered only {100 * r.tilt_coverage:.0f} % of directions in its frame (a hand "
            f"rotation covers more than {100 * config.min_tilt_coverage:.0f} %: a flight or a "
            "turn on a table is not enough)"
        )
    dt = float(np.median(np.diff(t)))
    rate = _moving_average(np.linalg.norm(gyr, axis=1), max(1, int(round(config.smooth_s / dt))))
    fast = rate >= config.min_rate_rad_s
    longest = max((t[b - 1] - t[a] for a, b in true_runs(fast)), default=0.0)
    text = (
        f"the angular rate (averaged over {config.smooth_s:g} s) exceeded "
        f"{config.min_rate_rad_s:g} rad/s for at most {longest:.1f} s at a time "
        f"(needs {config.min_duration_s:g} s while disarmed)"
    )
    if longest >= config.min_duration_s:
        text += "; the long ones were while armed, under throttle, or accelerating"
    return text
