# SPDX-License-Identifier: Apache-2.0
"""Checks of a finished calibration against its own session: a result the data contradict is
refused, whatever method produced it.

Every method's result (``ml``, ``init``, ``ckf``, ``two-step``) goes through the same checks,
each a figure measured on the session and a named limit:

* **gyroscope bias** (°/s, largest axis) above :data:`MAX_GYRO_BIAS_DEG_S`: not a MEMS
  gyroscope's offset, but the estimator absorbing something else into it;
* **D** not finite, or its condition number (largest over smallest singular value: how far
  the correction stretches one axis against another) above :data:`MAX_D_CONDITION`; for the
  norm-only methods also their ellipsoid matrix ``A`` not positive definite;
* **field-norm spread** (std/mean of ‖D⁻¹(y − o)‖) worse than the raw field's and far worse
  than the plain fit's (the symmetric ellipsoid fit of the magnetometer alone), by
  :data:`NORM_SPREAD_MAX_RATIO` and :data:`NORM_SPREAD_MARGIN`;
* **dip spread** (robust spread of the per-sample dip from the angle between the corrected
  field and the accelerometer's "up", :func:`magcal.calib.diagnostics.replay.inclination_dip_deg`)
  clearly worse than the plain fit's: :data:`DIP_SPREAD_MAX_RATIO` and
  :data:`DIP_SPREAD_MARGIN_DEG`. The plain fit has no misalignment, so for a magnetometer
  aligned with the IMU its dip spread is the baseline a correct result matches, and for a
  misaligned one a correct result beats it;
* **turn against the gyroscope**: the corrected field, carried over :data:`TURN_WINDOW_S` by
  the rotation the gyroscope measured, should meet itself again; the median angle it misses
  by is compared with the plain fit's (:data:`TURN_MAX_RATIO`, :data:`TURN_MARGIN_DEG`). A
  correction whose axes are turned against the gyroscope's fails it however well it fits
  the field's norm and dip. For the methods that fit without the gyroscope (init, ckf,
  two-step) these are held-out data;
* **a field that changes during the recording** (steel or a magnet that does not move with the
  sensor): the session is cut into stretches of :data:`FIELD_STRETCH_S`; each stretch's field
  norm (plain fit) is compared with the other stretches' *at the same field directions*, so an
  ellipsoid that fits some orientations worse than others does not look like a change.
  Stretches differing by more than :data:`FIELD_CHANGE_LIMIT` are a change
  (:func:`field_change`). ``calibrate`` leaves their magnetometer readings out before fitting
  when the constant part is at least :data:`MIN_CONSTANT_FRACTION` of the session and refuses
  the session otherwise; a change still found in the data a result was fitted to refuses it.

Where the limits come from: simulated sessions of every preset (``magcal simulate --preset
mems|handheld|table2|raw-counts``, also with ``--acc-rms 2``; ten seeds each, every method)
never reach them with a good calibration, with the margins given at each constant.

:func:`check` measures the figures, :func:`refusals_or_warnings` turns the failed ones into a
:class:`ResultContradictedError` (or, forced, into warnings).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np

from magcal.calib import frames
from magcal.calib.diagnostics.replay import inclination_dip_deg
from magcal.calib.initial.ellipsoid import EllipsoidFit, fit_ellipsoid_sdp, symmetric_fit
from magcal.calib.norm_only.live import fibonacci_sphere
from magcal.errors import ResultContradictedError

#: Largest gyroscope bias accepted, °/s on any axis. Datasheet zero-rate offsets of MEMS
#: gyroscopes are ±1–5 °/s for most parts and ±20–25 °/s for the widest (MPU-6050 ±20 °/s,
#: L3GD20H ±25 °/s at its widest range); an iPhone 5 in real recordings shows ≈7 °/s on two
#: separate sessions. Beyond 25 °/s the figure is not a gyroscope's offset.
MAX_GYRO_BIAS_DEG_S = 25.0
#: Largest condition number of D. Soft iron and the sensor's own scale errors stretch an axis
#: by tens of percent, not 10× against another (simulated MEMS and hand-held presets: ≤ 2.7;
#: the real recordings' plain fits: ≤ 1.3); beyond 10 the ellipsoid has collapsed along a
#: direction the data do not pin down.
MAX_D_CONDITION = 10.0
#: The corrected field-norm spread may exceed max(raw spread, this × the plain fit's) by at
#: most :data:`NORM_SPREAD_MARGIN`: a correction that makes the field less constant than no
#: correction at all and far less than a plain fit does contradicts the data. The ML fit
#: weighs the norm against the inertial sensors, so it need not match the plain fit's spread:
#: on the noisy, short table2 sessions its spread reaches 1.33× the plain fit's and exceeds the
#: raw field's (their noise is larger than their distortion); on every other preset it equals
#: the plain fit's (ratio 1.00).
NORM_SPREAD_MAX_RATIO = 2.0
#: ... plus this, as a fraction of the field: a spread 1 % above a tiny one changes a heading
#: by well under a degree and contradicts nothing.
NORM_SPREAD_MARGIN = 0.01
#: A result whose field-norm spread exceeds this × the uncorrected field's (plus the margin)
#: carries a warning even where the plain fit is as bad (a degenerate session, forced): the
#: correction then makes the field far less constant than no correction at all.
NORM_WORSE_THAN_RAW = 3.0
#: Largest ratio of the result's dip spread to the plain fit's. Good simulated results stay
#: at ≤ 1.02 (the largest: hand-held accelerations of 2 m/s², which blur both alike); results
#: with heading errors of 80–100° reach 1.4–2.
DIP_SPREAD_MAX_RATIO = 1.25
#: ... and the result's spread must also exceed the plain fit's by this much, degrees: a
#: quarter more of a spread of a few tenths of a degree is noise, not a contradiction.
DIP_SPREAD_MARGIN_DEG = 0.5
#: Largest residual of the corrected field's strength beyond the magnetometer's own noise
#: (:func:`fit_residual`), as a fraction of the field: the absolute gate, like ArduPilot's
#: COMPASS_CAL_FIT (an RMS residual in mG, default 16 mG: ≈3 % of a 500 mG field, noise
#: included) but in any unit. What is compared with it is the residual's lower bound
#: (:data:`FIT_RESIDUAL_SIGMAS`). Every method's calibration of the clean real recordings of
#: ../shared/realdata leaves 0–2.1 %, and 3.8 % where a magnet sits on the board and a short
#: change of the field is left in (broad35_magnet4cm, as calibrated before such changes were
#: left out); recordings beside steel calibrated as if the field were constant leave 5–47 %
#: (fiumarg_rec11_full, forced). Twice the largest clean figure.
MAX_FIT_RESIDUAL = 0.08
#: The residual is refused when it exceeds the limit by more than this many sampling errors
#: (in the squared residual): a short, noisy session (the paper's Table 2: 400 samples with
#: a noise of 20 % of the field) must not be refused for its noise estimate's scatter.
FIT_RESIDUAL_SIGMAS = 3.0

#: Fewest samples where the accelerometer reads gravity alone for the dip check.
MIN_DIP_SAMPLES = 50

#: Span over which the corrected field is carried by the gyroscope's rotation, s: long enough
#: to turn by tens of degrees when the sensor is being turned, short enough that a few °/s of
#: gyroscope bias move it by a few degrees at most (the same for the result and the plain fit).
TURN_WINDOW_S = 1.0
#: Largest ratio of the result's median miss to the plain fit's. Good results on simulated
#: presets stay at ≤ 1 (the plain fit lacks the misalignment); on real recordings correct
#: results reach 0.9–1.0, while results with twice the plain fit's heading error reach 2–3.
TURN_MAX_RATIO = 1.5
#: ... and the result's miss must exceed the plain fit's by this much, degrees.
TURN_MARGIN_DEG = 0.5
#: A result whose corrected field, turned by more than this (degrees), would follow the
#: gyroscope's rotation clearly better (:data:`TURN_MAX_RATIO`, :data:`TURN_MARGIN_DEG`) has
#: its axes turned against the gyroscope's, whatever the plain fit's alignment: the plain fit
#: is no baseline where the sensor itself is misaligned, or where most of the turning is
#: about one axis and a rotation about it shows little. Correct results on the real
#: recordings of ../shared/realdata would be turned by at most 6.5° (init, whose alignment
#: the accelerations blur; ML ≤ 2.8°, a lagging magnetometer included), simulated ones by
#: < 0.1°; a result turned 24° about the axis of fast swings is found turned by 24.0°.
TURN_ROTATION_LIMIT_DEG = 10.0
#: Gauss–Newton steps of :func:`turn_to_gyroscope` (it converges in 2-4).
_TURN_FIT_STEPS = 10
#: Fewest window pairs for the turn check.
MIN_TURN_PAIRS = 50

#: Length of the stretches whose fields are compared, s: long enough to hold a few
#: orientations, short enough to name where a change happened.
FIELD_STRETCH_S = 5.0
#: Field directions (a Fibonacci sphere, ≈14° apart) at which stretches are compared.
FIELD_DIRECTIONS = 200
#: Samples per block when each is assigned its nearest direction.
_CELL_BLOCK = 4096
#: Fewest samples of a stretch, and of the others, in one direction for it to be compared.
FIELD_MIN_CELL_SAMPLES = 5
#: A stretch whose field norm differs from the constant part's by more than this fraction is
#: a change. Stretches of undisturbed real recordings stay within 4.2 % (phones with lagging
#: magnetometers); steel bars beside the sensor move it by 10–45 %.
FIELD_CHANGE_LIMIT = 0.08
#: A session whose field changed is calibrated without the changed stretches' magnetometer
#: readings when the constant part is at least this share of the session's magnetometer
#: samples, and refused otherwise: with the constant field seen twice as long as every change
#: together, which field the sensor is calibrated in is not a coin toss. The stretches are
#: left out, not the session cut to its longest constant stretch: the filter propagates
#: through them with the gyroscope, and a short knock halfway through costs nothing else.
MIN_CONSTANT_FRACTION = 2.0 / 3.0
#: Left out around a change on each side, s: a change that begins or ends inside a stretch
#: changes the stretch's median only when it fills most of it, so up to half a stretch of it
#: next to the changed stretches goes unseen.
CHANGE_MARGIN_S = FIELD_STRETCH_S / 2

_DIRECTIONS = fibonacci_sphere(FIELD_DIRECTIONS)

#: What to do about each kind of contradiction, in the refusal after the figures.
ADVICE_ORIENTATIONS = (
    "record again turning the sensor slowly through all orientations, each face up in turn, "
    "or try another --method"
)
ADVICE_GYROSCOPE = (
    "check the gyroscope's unit (--gyro-unit) and begin the recording with a few seconds "
    "of the sensor held still"
)
ADVICE_AXES = (
    "record again turning the sensor about more than one axis, slowly enough that the "
    "accelerometer reads mostly gravity, or try another --method"
)
ADVICE_STEEL = "record again away from steel and magnets that do not move with the sensor"


@dataclass(frozen=True)
class FieldStretch:
    """One stretch of the session: start and end (s from the session's start) and its field
    norm relative to the constant part's (NaN when it shares no directions with the rest)."""

    start_s: float
    end_s: float
    level: float


@dataclass(frozen=True)
class Checks:
    """The figures of :func:`check` and the ones that contradict the result.

    refusals : one sentence per failed check, naming the figure and its limit
    advice   : what to do about them, each once
    warnings : changes of the field too short to refuse; a field norm far less constant
               than the uncorrected one where the plain fit's is as bad
    figures  : every figure measured, for the result's ``extra["consistency"]``
    """

    refusals: list[str] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)
    figures: dict = field(default_factory=dict)
    advice: list[str] = field(default_factory=list)


def _finite(x: float) -> float | None:
    """``x``, or None for NaN and infinity: the figures go into a JSON result."""
    return float(x) if np.isfinite(x) else None


def _norm_spread(calibrated: np.ndarray) -> float:
    n = np.linalg.norm(calibrated, axis=1)
    return float(np.std(n) / np.mean(n))


@dataclass(frozen=True)
class FitResidual:
    """The corrected field's strength against a constant (:func:`fit_residual`), fractions of
    the field: ``total`` RMS, the magnetometer's white ``noise`` in it, the RMS ``beyond``
    the noise, and its ``lower`` bound (:data:`FIT_RESIDUAL_SIGMAS` sampling errors off)."""

    total: float
    noise: float
    beyond: float
    lower: float

    def as_dict(self) -> dict:
        return {k: _finite(v) for k, v in dataclasses.asdict(self).items()}


def fit_residual(calibrated: np.ndarray) -> FitResidual:
    """How far the corrected field's strength is from constant, beyond the noise.

    calibrated : (N, 3) the corrected magnetometer, in time order
    The relative residual r = ‖c‖/mean − 1 holds the sensor's white noise, which changes from
    one sample to the next, and the fit's error, which changes with the orientation, slowly
    against the sample rate. Half the mean squared step estimates the noise's variance, so
    beyond² = mean((r − r̄)² − Δr²/2). Its sampling error is the one it has when r is white
    noise alone (the terms' variance and their covariance with the next, which shares a
    sample): a fit's error concentrated in part of the session (a field that changed) must
    not widen the bound that decides whether there is one.
    """
    n = np.linalg.norm(calibrated, axis=1)
    if n.size < 3:
        return FitResidual(*[float("nan")] * 4)
    r = n / np.mean(n) - 1.0
    r -= np.mean(r)
    step2 = 0.5 * np.diff(r) ** 2
    excess = r[:-1] ** 2 - step2
    beyond2 = float(np.mean(excess))
    d = excess - beyond2
    variance = float(np.mean(d * d) + 2.0 * np.mean(d[:-1] * d[1:]))
    error = float(np.sqrt(max(variance, 0.0) / excess.size))
    return FitResidual(
        total=float(np.sqrt(np.mean(r**2))),
        noise=float(np.sqrt(np.mean(step2))),
        beyond=float(np.sqrt(max(beyond2, 0.0))),
        lower=float(np.sqrt(max(beyond2 - FIT_RESIDUAL_SIGMAS * error, 0.0))),
    )


def _dip_spread_deg(acc: np.ndarray, calibrated: np.ndarray) -> tuple[float, int]:
    """1.4826 × median absolute deviation of the per-sample dip (equals the standard deviation
    for Gaussian scatter; a few knocks do not move it), and the number of samples used."""
    dip, _ = inclination_dip_deg(acc, calibrated)
    if dip.size == 0:
        return float("nan"), 0
    return float(1.4826 * np.median(np.abs(dip - np.median(dip)))), int(dip.size)


def turn_windows(
    t: np.ndarray, gyr: np.ndarray, gyro_bias: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The pairs of samples :data:`TURN_WINDOW_S` apart that the turn checks compare: the
    first sample of each pair (K,), the second (K,), and the rotation the gyroscope measured
    from the first to the second, M = R_aᵀ R_b (K, 3, 3), which carries the field seen at the
    second back to the first. K is 0 for a session shorter than the window.

    gyr : (N, 3) rad/s, each row's rate held until the next row (the session's convention).
    """
    none = np.zeros(0, dtype=int)
    if t.size < 2:
        return none, none, np.zeros((0, 3, 3))
    later = np.searchsorted(t, t + TURN_WINDOW_S)
    pairs = np.flatnonzero(later < t.size)
    R = frames.quat_to_matrix(frames.integrate_rates(gyr[:-1] - gyro_bias, np.diff(t)))
    return pairs, later[pairs], np.swapaxes(R[pairs], 1, 2) @ R[later[pairs]]


def _median_miss_deg(windows, calibrated: np.ndarray, Q: np.ndarray | None = None) -> float:
    """The median angle, degrees, between the corrected field (turned by Q when given) at the
    first sample of each window and its direction at the second carried back by the
    gyroscope's rotation: constant if all agree."""
    first, second, M = windows
    if first.size == 0:
        return float("nan")
    u = calibrated / np.linalg.norm(calibrated, axis=1, keepdims=True)
    if Q is not None:
        u = u @ Q.T
    cosines = np.sum(u[first] * (M @ u[second][:, :, None])[:, :, 0], axis=1)
    return float(np.rad2deg(np.median(np.arccos(np.clip(cosines, -1.0, 1.0)))))


def turn_misses_deg(
    t: np.ndarray, gyr: np.ndarray, gyro_bias: np.ndarray, *corrections: np.ndarray
) -> tuple[list[float], int]:
    """For each correction of the magnetometer (N, 3): the median angle, degrees, between the
    corrected field's direction at t + :data:`TURN_WINDOW_S` and its direction at t carried
    there by the gyroscope's rotation; and the pairs they are over. The rotation is
    integrated once for all of them (:func:`turn_windows`).
    """
    windows = turn_windows(t, gyr, gyro_bias)
    return [_median_miss_deg(windows, c) for c in corrections], int(windows[0].size)


def turn_to_gyroscope(windows, calibrated: np.ndarray) -> tuple[np.ndarray, float, float]:
    """The rotation Q (3, 3) that, applied to the corrected field, makes it follow the
    gyroscope's rotation best over the pairs of :func:`turn_windows` (least squares of the
    chords Q u_a − M Q u_b), the median miss (degrees, as :func:`turn_misses_deg`) with Q
    applied, and Q's angle (degrees). Q is the identity and the miss NaN without pairs.
    """
    first, second, M = windows
    if first.size == 0:
        return np.eye(3), float("nan"), 0.0
    u = calibrated / np.linalg.norm(calibrated, axis=1, keepdims=True)
    ua, ub = u[first], u[second]
    Q = np.eye(3)
    for _ in range(_TURN_FIT_STEPS):
        qa, qb = ua @ Q.T, ub @ Q.T
        chord = qa - (M @ qb[:, :, None])[:, :, 0]
        # Q → exp([φ]×) Q moves Q u by −[Q u]× φ.
        J = M @ frames.skew(qb) - frames.skew(qa)
        step = -np.linalg.solve(
            np.einsum("kji,kjl->il", J, J, optimize=True),
            np.einsum("kji,kj->i", J, chord, optimize=True),
        )
        Q = frames.rotvec_to_matrix(step) @ Q
        if np.linalg.norm(step) < 1e-6:
            break
    angle = float(np.rad2deg(np.arccos(np.clip(0.5 * (np.trace(Q) - 1.0), -1.0, 1.0))))
    return Q, _median_miss_deg(windows, calibrated, Q), angle


def field_stretches(t: np.ndarray, calibrated: np.ndarray) -> list[FieldStretch]:
    """The session cut into stretches of :data:`FIELD_STRETCH_S` and each one's field level.

    t          : (N,) s
    calibrated : (N, 3) a correction of the magnetometer (the plain fit), any scale
    A stretch's level is the sample-weighted mean, over the field directions it shares with
    the other stretches, of its median norm over the median of all stretches' medians in that
    direction, minus 1; the levels are then taken relative to the constant part's
    (:func:`_constant_level`).
    """
    t = np.asarray(t, dtype=float)
    norm = np.linalg.norm(calibrated, axis=1)
    unit = calibrated / norm[:, None]
    # The nearest direction of each sample, in blocks: a whole session's N × directions
    # products would cost more memory than the calibration itself.
    cell = np.concatenate(
        [
            np.argmax(unit[i : i + _CELL_BLOCK] @ _DIRECTIONS.T, axis=1)
            for i in range(0, unit.shape[0], _CELL_BLOCK)
        ]
    )
    index = np.floor((t - t[0]) / FIELD_STRETCH_S).astype(int)
    n_stretch = int(index.max()) + 1
    if n_stretch < 2:
        return []
    # Median norm of each stretch in each direction (NaN where it has too few samples).
    med = np.full((n_stretch, FIELD_DIRECTIONS), np.nan)
    count = np.zeros((n_stretch, FIELD_DIRECTIONS), dtype=int)
    groups, first, sizes, ranked = _sorted_groups(index * FIELD_DIRECTIONS + cell, norm)
    count.flat[groups] = sizes
    # The median as np.median takes it: the mean of the two middle values (the same one
    # twice for an odd count, which halves back exactly).
    middle = 0.5 * (ranked[first + (sizes - 1) // 2] + ranked[first + sizes // 2])
    middle[np.isnan(ranked[first + sizes - 1])] = np.nan  # np.median's NaN in, NaN out
    enough = sizes >= FIELD_MIN_CELL_SAMPLES
    med.flat[groups[enough]] = middle[enough]
    shared = np.isfinite(med).sum(axis=0) >= 2  # directions seen in two stretches or more
    reference = np.full(FIELD_DIRECTIONS, np.nan)
    reference[shared] = np.nanmedian(med[:, shared], axis=0)
    levels = np.full(n_stretch, np.nan)
    for j in range(n_stretch):
        use = shared & np.isfinite(med[j])
        if use.any():
            levels[j] = np.average(med[j, use] / reference[use] - 1.0, weights=count[j, use])
    levels -= _constant_level(levels)
    # Each stretch's first and last sample in the session's order.
    order = np.argsort(index, kind="stable")
    present, start, size = np.unique(index[order], return_index=True, return_counts=True)
    return [
        FieldStretch(float(t[order[a]] - t[0]), float(t[order[a + n - 1]] - t[0]), float(levels[j]))
        for j, a, n in zip(present, start, size, strict=True)
    ]


def _sorted_groups(
    key: np.ndarray, values: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``values`` (N,) grouped by the integer ``key`` (N,) and sorted within each group:
    (the distinct keys, each group's first position in the sorted values, its size, the
    sorted values). NaN values sort last in their group, as ``np.sort`` puts them."""
    order = np.lexsort((values, key))
    groups, first, sizes = np.unique(key[order], return_index=True, return_counts=True)
    return groups, first, sizes, values[order]


def _plain_correction(
    mag: np.ndarray, rows: np.ndarray | slice = slice(None), fit: EllipsoidFit | None = None
) -> np.ndarray:
    """(N, 3) the magnetometer corrected by the plain fit (symmetric D) of ``mag[rows]``;
    ``fit`` is the SDP fit of those rows when the caller has it already."""
    if fit is None:
        fit = fit_ellipsoid_sdp(mag[rows], force=True)
    return np.linalg.solve(symmetric_fit(fit), (mag - fit.o).T).T


def _changed(stretches: list[FieldStretch]) -> list[FieldStretch]:
    return [s for s in stretches if np.isfinite(s.level) and abs(s.level) > FIELD_CHANGE_LIMIT]


def _constant_level(levels: np.ndarray) -> float:
    """The median level of the constant part: the most stretches whose levels agree within
    :data:`FIELD_CHANGE_LIMIT` (on a tie, the group holding the earliest stretch). With half a
    session in another field, the median of all levels would sit between the two fields."""
    finite = np.flatnonzero(np.isfinite(levels))
    if finite.size == 0:
        return 0.0
    best: np.ndarray | None = None
    for i in finite:  # a window [level_i, level_i + limit] over the stretches' levels
        group = finite[
            (levels[finite] >= levels[i]) & (levels[finite] <= levels[i] + FIELD_CHANGE_LIMIT)
        ]
        if (
            best is None
            or group.size > best.size
            or (group.size == best.size and group.min() < best.min())
        ):
            best = group
    return float(np.median(levels[best]))


@dataclass(frozen=True)
class FieldChange:
    """Where the field changed during a session (:func:`field_change`).

    stretches  : every stretch with its level, relative to the constant part's
    changed    : the stretches beyond :data:`FIELD_CHANGE_LIMIT`
    duration_s : the session's duration
    """

    stretches: list[FieldStretch]
    changed: list[FieldStretch]
    duration_s: float

    @property
    def changed_fraction(self) -> float:
        """The changed stretches' share of the session."""
        return sum(s.end_s - s.start_s for s in self.changed) / self.duration_s

    @property
    def impact(self) -> float:
        """Σ duration × |change| / session duration: a fraction of the field."""
        return sum((s.end_s - s.start_s) * abs(s.level) for s in self.changed) / self.duration_s

    def describe(self) -> str:
        """The change in one clause: its size, where, its share and impact, the likely cause."""
        worst = max(self.changed, key=lambda s: abs(s.level))
        return (
            f"the magnetic field changed during the recording: its strength differed by up to "
            f"{100 * worst.level:+.0f} % (limit ±{100 * FIELD_CHANGE_LIMIT:.0f} %) from the rest "
            f"at the same sensor orientations {_spans(self.changed)} "
            f"({100 * self.changed_fraction:.0f} % of the session, {100 * self.impact:.1f} % of "
            "the field on average): steel or a magnet nearby that does not move with the sensor"
        )

    def figures(self) -> dict:
        figures: dict = {
            "stretch_s": FIELD_STRETCH_S,
            # null where a stretch shares no direction with the others (JSON has no NaN)
            "levels": [[s.start_s, s.end_s, _finite(s.level)] for s in self.stretches],
        }
        if self.changed:
            figures["changed_fraction"] = self.changed_fraction
            figures["impact"] = self.impact
        return figures


def field_change(
    t: np.ndarray, mag: np.ndarray, plain_cal: np.ndarray | None = None
) -> FieldChange:
    """The stretches of a single-rate session ``t`` (N,) s, ``mag`` (N, 3) and those where
    the field changed, measured on the plain fit's correction ``plain_cal`` (fitted here when
    None)."""
    if plain_cal is None:
        plain_cal = _plain_correction(mag)
    stretches = field_stretches(t, plain_cal)
    changed = _changed(stretches)
    if changed:
        # The plain fit of the whole session bends towards the changed field and blurs the
        # contrast; refitted on the unchanged stretches, it shows the change in full.
        rel = t - t[0]
        keep = np.ones(len(t), dtype=bool)
        for s in changed:
            keep &= ~((rel >= s.start_s) & (rel <= s.end_s))
        if keep.sum() >= 0.5 * len(t):
            stretches = field_stretches(t, _plain_correction(mag, keep))
            changed = _changed(stretches)
    return FieldChange(stretches, changed, float(t[-1] - t[0]) if t.size else 0.0)


def _field_change_checked(
    t: np.ndarray, mag: np.ndarray, plain_cal: np.ndarray
) -> tuple[list[str], dict]:
    """A change in the data a result was fitted to is a refusal: ``calibrate`` has already
    left out the stretches of a change it could (``without_changed_field``), so what is left
    bends the fit. Forced, it is a warning that the calibration used all of it."""
    change = field_change(t, mag, plain_cal)
    if not change.changed:
        return [], change.figures()
    return [change.describe()], change.figures()


def merged_spans(stretches: list[FieldStretch]) -> list[tuple[float, float]]:
    """(start, end) s of runs of consecutive stretches, merged."""
    spans: list[list[float]] = []
    for s in stretches:
        if spans and s.start_s - spans[-1][1] <= FIELD_STRETCH_S / 2:
            spans[-1][1] = s.end_s
        else:
            spans.append([s.start_s, s.end_s])
    return [(a, b) for a, b in spans]


def _spans(stretches: list[FieldStretch]) -> str:
    """'between 30 s and 45 s and between 55 s and 62 s' for consecutive stretches merged."""
    return " and ".join(f"between {a:.0f} s and {b:.0f} s" for a, b in merged_spans(stretches))


def check(
    t: np.ndarray,
    acc: np.ndarray,
    mag: np.ndarray,
    D: np.ndarray,
    o: np.ndarray,
    gyro_bias: np.ndarray | None,
    ellipsoid_A: np.ndarray | None = None,
    session_fit: EllipsoidFit | None = None,
    gyr: np.ndarray | None = None,
    max_fit_residual: float = MAX_FIT_RESIDUAL,
) -> Checks:
    """Measure a result against its session.

    t, acc, mag : (N,) s, (N, 3) m/s², (N, 3) magnetometer units: the session
    gyr         : (N, 3) rad/s, each row's rate held until the next row, for the turn check
                  (skipped without it), with ``gyro_bias`` removed (zero when None)
    D, o        : (3, 3), (3,) the result's correction, magnetometer units
    gyro_bias   : (3,) rad/s, or None for a result without one
    ellipsoid_A : (3, 3) a norm-only method's fitted ellipsoid matrix, or None
    session_fit : the SDP ellipsoid fit of the whole session's magnetometer, when the caller
                  has it (the plain fit is its symmetric part); fitted here otherwise
    max_fit_residual : the absolute gate (:data:`MAX_FIT_RESIDUAL`), a fraction of the field
    """
    mag = np.asarray(mag, dtype=float)
    D = np.asarray(D, dtype=float)
    o = np.asarray(o, dtype=float)
    refusals: list[str] = []
    advice: list[str] = []
    figures: dict = {}

    def refuse(text: str, what_to_do: str) -> None:
        refusals.append(text)
        if what_to_do not in advice:
            advice.append(what_to_do)

    if gyro_bias is not None:
        bias = float(np.rad2deg(np.max(np.abs(gyro_bias))))
        figures["gyro_bias_max_deg_s"] = _finite(bias)
        if not np.isfinite(bias) or bias > MAX_GYRO_BIAS_DEG_S:
            refuse(
                f"its gyroscope bias of {bias:.1f} °/s is beyond any MEMS gyroscope's (limit "
                f"{MAX_GYRO_BIAS_DEG_S:.0f} °/s per axis)",
                ADVICE_GYROSCOPE,
            )
    if ellipsoid_A is not None:
        eig = np.linalg.eigvalsh(0.5 * (ellipsoid_A + np.asarray(ellipsoid_A).T))
        figures["ellipsoid_A_min_eigenvalue"] = _finite(eig[0])
        if not np.all(np.isfinite(eig)) or eig[0] <= 0.0:
            refuse(
                "its fitted ellipsoid is not one (the matrix A is not positive definite, "
                f"smallest eigenvalue {eig[0]:.3g})",
                ADVICE_ORIENTATIONS,
            )
    if not (np.all(np.isfinite(D)) and np.all(np.isfinite(o))):
        refuse("its D or o is not finite", ADVICE_ORIENTATIONS)
        return Checks(refusals, [], figures, advice)
    singular = np.linalg.svd(D, compute_uv=False)
    condition = float(singular[0] / singular[-1]) if singular[-1] > 0 else float("inf")
    figures["D_condition"] = _finite(condition)
    if condition > MAX_D_CONDITION:
        refuse(
            f"its D stretches one axis {condition:.3g}× against another (condition number; "
            f"limit {MAX_D_CONDITION:.0f}): no magnetometer's soft iron does",
            ADVICE_ORIENTATIONS,
        )

    plain_cal = _plain_correction(mag, fit=session_fit)
    calibrated = np.linalg.solve(D, (mag - o).T).T if condition < np.inf else plain_cal

    spread = {
        "raw": _norm_spread(mag),
        "plain_fit": _norm_spread(plain_cal),
        "result": _norm_spread(calibrated),
    }
    figures["field_norm_spread"] = {k: _finite(v) for k, v in spread.items()}
    limit = max(spread["raw"], NORM_SPREAD_MAX_RATIO * spread["plain_fit"]) + NORM_SPREAD_MARGIN
    if not spread["result"] <= limit:
        refuse(
            f"its corrected field norm varies by {100 * spread['result']:.2f} % (std/mean), "
            f"against {100 * spread['raw']:.2f} % uncorrected and {100 * spread['plain_fit']:.2f} "
            f"% for a plain ellipsoid fit (limit {100 * limit:.2f} %)",
            ADVICE_ORIENTATIONS,
        )

    residual = fit_residual(calibrated)
    figures["fit_residual"] = {**residual.as_dict(), "limit": max_fit_residual}
    if residual.lower > max_fit_residual:
        refuse(
            f"its corrected field's strength is not constant: it departs from its mean by "
            f"{100 * residual.beyond:.1f} % of the field (RMS beyond the magnetometer's noise of "
            f"{100 * residual.noise:.1f} %; at least {100 * residual.lower:.1f} % allowing for "
            f"sampling; limit {100 * max_fit_residual:g} %, --max-fit-residual): the model of "
            "a constant field distorted by the sensor does not fit these data, as when steel or "
            "a magnet nearby does not move with the sensor",
            ADVICE_STEEL,
        )

    dip_plain, n_dip = _dip_spread_deg(acc, plain_cal)
    dip_result, _ = _dip_spread_deg(acc, calibrated)
    figures["dip_spread_deg"] = {
        "plain_fit": _finite(dip_plain),
        "result": _finite(dip_result),
        "samples": n_dip,
    }
    if n_dip >= MIN_DIP_SAMPLES and not (
        dip_result <= DIP_SPREAD_MAX_RATIO * dip_plain
        or dip_result <= dip_plain + DIP_SPREAD_MARGIN_DEG
    ):
        refuse(
            f"its dip angle against the accelerometer scatters by {dip_result:.2f}° from sample "
            f"to sample, against {dip_plain:.2f}° for a plain ellipsoid fit (limit "
            f"{DIP_SPREAD_MAX_RATIO}× and +{DIP_SPREAD_MARGIN_DEG}°): its alignment with the "
            "accelerometer is wrong",
            ADVICE_AXES,
        )

    if gyr is not None:
        bias = np.zeros(3) if gyro_bias is None else np.asarray(gyro_bias, dtype=float)
        windows = turn_windows(t, gyr, bias)
        miss_plain = _median_miss_deg(windows, plain_cal)
        miss_result = _median_miss_deg(windows, calibrated)
        n_pairs = int(windows[0].size)
        figures["turn_miss_deg"] = {
            "plain_fit": _finite(miss_plain),
            "result": _finite(miss_result),
            "pairs": n_pairs,
            "window_s": TURN_WINDOW_S,
        }
        Q, miss_turned, angle = turn_to_gyroscope(windows, calibrated)
        figures["turn_miss_deg"]["result_turned"] = _finite(miss_turned)
        figures["turn_miss_deg"]["turn_deg"] = _finite(angle)
        if (
            n_pairs >= MIN_TURN_PAIRS
            and angle > TURN_ROTATION_LIMIT_DEG
            and not miss_result <= TURN_MAX_RATIO * miss_turned + TURN_MARGIN_DEG
        ):
            axis = frames.quat_to_rotvec(frames.matrix_to_quat(Q))
            axis = axis / np.linalg.norm(axis)
            refuse(
                f"its axes are turned against the gyroscope's: turned by {angle:.0f}° about its "
                f"({axis[0]:+.2f}, {axis[1]:+.2f}, {axis[2]:+.2f}) axis, its corrected field "
                f"would follow the measured rotation far better (carried {TURN_WINDOW_S:g} s it "
                f"misses itself by {miss_turned:.2f}° instead of {miss_result:.2f}°, median; limit "
                f"{TURN_ROTATION_LIMIT_DEG:.0f}° of turn and {TURN_MAX_RATIO}× + "
                f"{TURN_MARGIN_DEG}°)",
                ADVICE_AXES,
            )
        elif n_pairs >= MIN_TURN_PAIRS and not (
            miss_result <= TURN_MAX_RATIO * miss_plain + TURN_MARGIN_DEG
        ):
            refuse(
                f"its corrected field turns against the gyroscope: carried {TURN_WINDOW_S:g} s "
                f"by the measured rotation it misses itself by {miss_result:.2f}° (median), "
                f"against {miss_plain:.2f}° for a plain ellipsoid fit (limit {TURN_MAX_RATIO}× "
                f"+ {TURN_MARGIN_DEG}°): its axes are turned against the gyroscope's",
                ADVICE_AXES,
            )

    field_refusals, figures["field_stretches"] = _field_change_checked(t, mag, plain_cal)
    warnings: list[str] = []
    worse = NORM_WORSE_THAN_RAW * spread["raw"] + NORM_SPREAD_MARGIN
    if spread["result"] > worse and spread["result"] <= limit:
        warnings.append(
            f"the corrected field norm varies by {100 * spread['result']:.1f} % (std/mean), "
            f"{spread['result'] / spread['raw']:.0f}× the uncorrected field's "
            f"{100 * spread['raw']:.2f} %: this correction makes the field far less constant "
            "than none (a plain ellipsoid fit of this session is as bad: "
            f"{100 * spread['plain_fit']:.1f} %); the session does not determine a calibration"
        )
    if field_refusals and ADVICE_STEEL not in advice:
        advice.append(ADVICE_STEEL)
    return Checks(refusals + field_refusals, warnings, figures, advice)


def refusals_or_warnings(checks: Checks, method: str, force: bool) -> list[str]:
    """The warnings a result carries; raises :class:`ResultContradictedError` naming every
    failed check unless ``force``, which turns them into warnings."""
    if not checks.refusals:
        return list(checks.warnings)
    what = "; ".join(checks.refusals)
    if not force:
        advice = "; ".join(checks.advice or [ADVICE_ORIENTATIONS])
        raise ResultContradictedError(
            f"the {method} result contradicts its own session, so it was not written: {what}. "
            f"To do: {advice}; --force writes it anyway with this as a warning"
        )
    return [f"forced: the result contradicts its own session: {what}", *checks.warnings]
