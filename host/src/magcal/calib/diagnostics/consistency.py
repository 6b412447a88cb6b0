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
  Stretches differing by more than :data:`FIELD_CHANGE_LIMIT` are a change; weighted by their
  share of the session it refuses the result from :data:`FIELD_CHANGE_REFUSE_IMPACT`, naming
  them; a smaller one is a warning. No stretch is chosen to calibrate on instead: which of two
  fields the sensor will meet in use is not in the data.

Where the limits come from: simulated sessions of every preset (``magcal simulate --preset
mems|handheld|table2|raw-counts``, also with ``--acc-rms 2``; ten seeds each, every method)
never reach them with a good calibration, with the margins given at each constant.

:func:`check` measures the figures, :func:`refusals_or_warnings` turns the failed ones into a
:class:`ResultContradictedError` (or, forced, into warnings).
"""

from __future__ import annotations

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
#: The changed stretches refuse the result when their change, weighted by their share of the
#: session (Σ duration × |change| / session duration), reaches this fraction of the field:
#: that much bends the fit by more than a magnetometer's noise (a 2 % error in the field
#: norm turns a heading by up to about 1°). A short change (a knock, the end of a recording
#: set down near something: 17 % over 4 % of a session is 0.7 %) is a warning naming it.
FIELD_CHANGE_REFUSE_IMPACT = 0.02

_DIRECTIONS = fibonacci_sphere(FIELD_DIRECTIONS)


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
    warnings : changes of the field too short to refuse; a field norm far less constant
               than the uncorrected one where the plain fit's is as bad
    figures  : every figure measured, for the result's ``extra["consistency"]``
    """

    refusals: list[str] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)
    figures: dict = field(default_factory=dict)


def _finite(x: float) -> float | None:
    """``x``, or None for NaN and infinity: the figures go into a JSON result."""
    return float(x) if np.isfinite(x) else None


def _norm_spread(calibrated: np.ndarray) -> float:
    n = np.linalg.norm(calibrated, axis=1)
    return float(np.std(n) / np.mean(n))


def _dip_spread_deg(acc: np.ndarray, calibrated: np.ndarray) -> tuple[float, int]:
    """1.4826 × median absolute deviation of the per-sample dip (equals the standard deviation
    for Gaussian scatter; a few knocks do not move it), and the number of samples used."""
    dip, _ = inclination_dip_deg(acc, calibrated)
    if dip.size == 0:
        return float("nan"), 0
    return float(1.4826 * np.median(np.abs(dip - np.median(dip)))), int(dip.size)


def turn_misses_deg(
    t: np.ndarray, gyr: np.ndarray, gyro_bias: np.ndarray, *corrections: np.ndarray
) -> tuple[list[float], int]:
    """For each correction of the magnetometer (N, 3): the median angle, degrees, between the
    corrected field's direction at t + :data:`TURN_WINDOW_S` and its direction at t carried
    there by the gyroscope's rotation; and the pairs they are over. The rotation is
    integrated once for all of them.

    gyr : (N, 3) rad/s, each row's rate held until the next row (the session's convention).
    """
    if t.size < 2:
        return [float("nan")] * len(corrections), 0
    later = np.searchsorted(t, t + TURN_WINDOW_S)
    pairs = np.flatnonzero(later < t.size)
    if pairs.size == 0:
        return [float("nan")] * len(corrections), 0
    R = frames.quat_to_matrix(frames.integrate_rates(gyr[:-1] - gyro_bias, np.diff(t)))
    misses = []
    for calibrated in corrections:
        u = calibrated / np.linalg.norm(calibrated, axis=1, keepdims=True)
        # The field in the frame the gyroscope's integration starts from: constant if all
        # agree.
        w = np.einsum("kij,kj->ki", R, u)
        cosines = np.clip(np.sum(w[pairs] * w[later[pairs]], axis=1), -1.0, 1.0)
        misses.append(float(np.rad2deg(np.median(np.arccos(cosines)))))
    return misses, int(pairs.size)


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


def _field_change(
    t: np.ndarray, mag: np.ndarray, plain_cal: np.ndarray
) -> tuple[list[str], list[str], dict]:
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
    figures: dict = {
        "stretch_s": FIELD_STRETCH_S,
        # null where a stretch shares no direction with the others (JSON has no NaN)
        "levels": [[s.start_s, s.end_s, _finite(s.level)] for s in stretches],
    }
    if not changed:
        return [], [], figures
    duration = float(t[-1] - t[0])
    changed_s = sum(s.end_s - s.start_s for s in changed)
    impact = sum((s.end_s - s.start_s) * abs(s.level) for s in changed) / duration
    figures["changed_fraction"] = changed_s / duration
    figures["impact"] = impact
    worst = max(changed, key=lambda s: abs(s.level))
    text = (
        f"the magnetic field changed during the recording: its strength differed by up to "
        f"{100 * worst.level:+.0f} % (limit ±{100 * FIELD_CHANGE_LIMIT:.0f} %) from the rest "
        f"at the same sensor orientations {_spans(changed)} ({100 * changed_s / duration:.0f} % "
        f"of the session, {100 * impact:.1f} % of the field on average; limit "
        f"{100 * FIELD_CHANGE_REFUSE_IMPACT:.0f} %): steel or a magnet nearby that does not "
        "move with the sensor"
    )
    if impact >= FIELD_CHANGE_REFUSE_IMPACT:
        return [f"{text}; record again away from it"], [], figures
    return [], [f"{text}; the calibration used all of it"], figures


def _spans(stretches: list[FieldStretch]) -> str:
    """'between 30 s and 45 s and between 55 s and 62 s' for consecutive stretches merged."""
    spans: list[list[float]] = []
    for s in stretches:
        if spans and s.start_s - spans[-1][1] <= FIELD_STRETCH_S / 2:
            spans[-1][1] = s.end_s
        else:
            spans.append([s.start_s, s.end_s])
    return " and ".join(f"between {a:.0f} s and {b:.0f} s" for a, b in spans)


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
    """
    mag = np.asarray(mag, dtype=float)
    D = np.asarray(D, dtype=float)
    o = np.asarray(o, dtype=float)
    refusals: list[str] = []
    figures: dict = {}

    if gyro_bias is not None:
        bias = float(np.rad2deg(np.max(np.abs(gyro_bias))))
        figures["gyro_bias_max_deg_s"] = _finite(bias)
        if not np.isfinite(bias) or bias > MAX_GYRO_BIAS_DEG_S:
            refusals.append(
                f"its gyroscope bias of {bias:.1f} °/s is beyond any MEMS gyroscope's (limit "
                f"{MAX_GYRO_BIAS_DEG_S:.0f} °/s per axis)"
            )
    if ellipsoid_A is not None:
        eig = np.linalg.eigvalsh(0.5 * (ellipsoid_A + np.asarray(ellipsoid_A).T))
        figures["ellipsoid_A_min_eigenvalue"] = _finite(eig[0])
        if not np.all(np.isfinite(eig)) or eig[0] <= 0.0:
            refusals.append(
                "its fitted ellipsoid is not one (the matrix A is not positive definite, "
                f"smallest eigenvalue {eig[0]:.3g})"
            )
    if not (np.all(np.isfinite(D)) and np.all(np.isfinite(o))):
        refusals.append("its D or o is not finite")
        return Checks(refusals, [], figures)
    singular = np.linalg.svd(D, compute_uv=False)
    condition = float(singular[0] / singular[-1]) if singular[-1] > 0 else float("inf")
    figures["D_condition"] = _finite(condition)
    if condition > MAX_D_CONDITION:
        refusals.append(
            f"its D stretches one axis {condition:.3g}× against another (condition number; "
            f"limit {MAX_D_CONDITION:.0f}): no magnetometer's soft iron does"
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
        refusals.append(
            f"its corrected field norm varies by {100 * spread['result']:.2f} % (std/mean), "
            f"against {100 * spread['raw']:.2f} % uncorrected and {100 * spread['plain_fit']:.2f} "
            f"% for a plain ellipsoid fit (limit {100 * limit:.2f} %)"
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
        refusals.append(
            f"its dip angle against the accelerometer scatters by {dip_result:.2f}° from sample "
            f"to sample, against {dip_plain:.2f}° for a plain ellipsoid fit (limit "
            f"{DIP_SPREAD_MAX_RATIO}× and +{DIP_SPREAD_MARGIN_DEG}°): its alignment with the "
            "accelerometer is wrong"
        )

    if gyr is not None:
        bias = np.zeros(3) if gyro_bias is None else np.asarray(gyro_bias, dtype=float)
        (miss_plain, miss_result), n_pairs = turn_misses_deg(t, gyr, bias, plain_cal, calibrated)
        figures["turn_miss_deg"] = {
            "plain_fit": _finite(miss_plain),
            "result": _finite(miss_result),
            "pairs": n_pairs,
            "window_s": TURN_WINDOW_S,
        }
        if n_pairs >= MIN_TURN_PAIRS and not (
            miss_result <= TURN_MAX_RATIO * miss_plain + TURN_MARGIN_DEG
        ):
            refusals.append(
                f"its corrected field turns against the gyroscope: carried {TURN_WINDOW_S:g} s "
                f"by the measured rotation it misses itself by {miss_result:.2f}° (median), "
                f"against {miss_plain:.2f}° for a plain ellipsoid fit (limit {TURN_MAX_RATIO}× "
                f"+ {TURN_MARGIN_DEG}°): its axes are turned against the gyroscope's"
            )

    field_refusals, warnings, figures["field_stretches"] = _field_change(t, mag, plain_cal)
    worse = NORM_WORSE_THAN_RAW * spread["raw"] + NORM_SPREAD_MARGIN
    if spread["result"] > worse and spread["result"] <= limit:
        warnings.append(
            f"the corrected field norm varies by {100 * spread['result']:.1f} % (std/mean), "
            f"{spread['result'] / spread['raw']:.0f}× the uncorrected field's "
            f"{100 * spread['raw']:.2f} %: this correction makes the field far less constant "
            "than none (a plain ellipsoid fit of this session is as bad: "
            f"{100 * spread['plain_fit']:.1f} %); the session does not determine a calibration"
        )
    return Checks(refusals + field_refusals, warnings, figures)


def refusals_or_warnings(checks: Checks, method: str, force: bool) -> list[str]:
    """The warnings a result carries; raises :class:`ResultContradictedError` naming every
    failed check unless ``force``, which turns them into warnings."""
    if not checks.refusals:
        return list(checks.warnings)
    what = "; ".join(checks.refusals)
    if not force:
        raise ResultContradictedError(
            f"the {method} result contradicts its own session, so it was not written: {what}. "
            "Record again, turning the sensor slowly through all orientations away from steel "
            "and magnets, or try another --method; --force writes it anyway with this as a "
            "warning"
        )
    return [f"forced: the result contradicts its own session: {what}", *checks.warnings]
