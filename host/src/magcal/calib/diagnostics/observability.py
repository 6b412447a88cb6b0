# SPDX-License-Identifier: Apache-2.0
"""Can this session determine the calibration? Checks before fitting, with reasons.

Three things must hold for Kok & Schön's method (and for any ellipsoid fit):

* the magnetometer data must cover a good part of the ellipsoid, or the 9 + 3 parameters of
  ``D`` and ``o`` are not determined (a small patch, or a circle from yaw-only motion, fits
  many ellipsoids);
* the gravity direction must change in the body frame (tilt, not only yaw), or the rotation
  between the magnetometer and the inertial axes (Section 6.2) is not determined: with a
  constant vertical in the body frame, only the vertical component of the field is used;
* the session must be long enough to average the noise.

The figures are cheap (one pass over the data) and need no fit.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from magcal.errors import InsufficientDataError

#: Fewest samples and shortest duration, s. The paper's Monte Carlo sessions (Table 2) have
#: 100 stationary + 300 rotating samples and calibrate; a person needs a few seconds at least
#: to turn a sensor through all orientations. Coverage is judged by the tests below.
MIN_SAMPLES = 200
MIN_DURATION_S = 2.0
#: Second-largest eigenvalue of the scatter ``mean(u uᵀ)`` of the accelerometer directions
#: ``u`` (trace 1). For tilts of RMS θ (rad) about the less-excited horizontal axis it is
#: about θ²: 0.03 ≈ 10° RMS. Yaw-only motion gives ~0; tumbling gives ~1/3.
MIN_GRAVITY_SPREAD = 0.03
#: Below this the tilt is reported as marginal (≈ 18° RMS about the weaker axis).
WARN_GRAVITY_SPREAD = 0.1
#: Smallest eigenvalue of the gravity-direction scatter below which the tilt is about one
#: horizontal axis only (still solvable with yaw, but weaker): a warning.
WARN_GRAVITY_SINGLE_AXIS = 0.01
#: Ratio of the smallest to the largest eigenvalue of the magnetometer covariance. A
#: sphere covered evenly gives 1 (an ellipsoid of axis ratio k: about 1/k²); a cap of
#: ±30° about 0.02; yaw only (a circle) 0. 0.03 refuses caps smaller than about ±35° and
#: yaw with less than ~15° of tilt, while accepting tumbling with axis ratios up to ~3.
MIN_MAG_EIG_RATIO = 0.03
#: Below this the coverage is reported as marginal.
WARN_MAG_EIG_RATIO = 0.1
#: Moving-average length applied to the accelerometer before taking its direction, s: hand
#: accelerations (≈1 m/s² RMS, zero-mean over a fraction of a second) would otherwise look
#: like tilt, while the gravity direction changes little over a quarter second.
GRAVITY_SMOOTH_S = 0.25
#: Accumulated rotation angle ∫‖ω‖dt, rad: covering all orientations takes more than one
#: full turn. (Raw gyro: a bias adds to it, which is harmless at this threshold.)
MIN_TOTAL_ROTATION_RAD = 2.0 * np.pi

_ADVICE = (
    "Rotate the sensor slowly through all orientations: tilt it nose up and down and roll it "
    "over onto each side, not only yaw (turning it flat on a table is not enough), for half a "
    "minute or so, away from iron and electronics; then calibrate again, or pass --force to "
    "accept a poor calibration."
)


@dataclass(frozen=True, eq=False)
class ObservabilityReport:
    """Whether a session can determine the calibration, with the reasons and figures.

    ok        : bool, no problems
    problems  : list of str, reasons to refuse (empty when ok)
    warnings  : list of str, marginal conditions that do not refuse
    message   : str, one paragraph for the user: the problems and what to do ("" when ok)
    n_samples : int
    duration_s: float, s
    gravity_eigenvalues : (3,) float, ascending, of the scatter ``mean(u uᵀ)`` of the unit
                accelerometer directions (after a GRAVITY_SMOOTH_S moving average; trace 1):
                ~(0, 0, 1) for yaw only, ~⅓ each for tumbling
    tilt_spread_deg : float, deg, 95th percentile of the angle between the accelerometer
                direction and its mean direction
    mag_eigenvalues : (3,) float, ascending, of the magnetometer covariance about the data
                mean, normalised to trace 1
    mag_eig_ratio : float, smallest / largest of ``mag_eigenvalues``
    total_rotation_rad : float, rad, ``Σ ‖ω_t‖ Δt`` (raw gyro)
    """

    ok: bool
    problems: list[str]
    warnings: list[str]
    message: str
    n_samples: int
    duration_s: float
    gravity_eigenvalues: np.ndarray = field(default_factory=lambda: np.full(3, np.nan))
    tilt_spread_deg: float = float("nan")
    mag_eigenvalues: np.ndarray = field(default_factory=lambda: np.full(3, np.nan))
    mag_eig_ratio: float = float("nan")
    total_rotation_rad: float = float("nan")


def _moving_average(x: np.ndarray, w: int) -> np.ndarray:
    """Centred-window moving average of x (n, 3) over w samples (shorter at the ends)."""
    if w <= 1 or x.shape[0] < 2:
        return x
    c = np.concatenate([np.zeros((1, 3)), np.cumsum(x - x.mean(axis=0), axis=0)])
    i = np.arange(x.shape[0])
    lo = np.clip(i - w // 2, 0, x.shape[0])
    hi = np.clip(i - w // 2 + w, 0, x.shape[0])
    return (c[hi] - c[lo]) / (hi - lo)[:, None] + x.mean(axis=0)


def _gravity_figures(acc: np.ndarray) -> tuple[np.ndarray, float]:
    norm = np.linalg.norm(acc, axis=1)
    u = acc[norm > 0.0] / norm[norm > 0.0, None]
    if u.shape[0] == 0:
        return np.full(3, np.nan), float("nan")
    scatter = u.T @ u / u.shape[0]
    eig = np.linalg.eigvalsh(0.5 * (scatter + scatter.T))
    mean = u.mean(axis=0)
    mean_norm = np.linalg.norm(mean)
    if mean_norm == 0.0:
        return eig, 180.0
    cosang = np.clip(u @ (mean / mean_norm), -1.0, 1.0)
    return eig, float(np.degrees(np.percentile(np.arccos(cosang), 95.0)))


def _mag_figures(mag: np.ndarray) -> tuple[np.ndarray, float]:
    if mag.shape[0] < 2:
        return np.full(3, np.nan), float("nan")
    cov = np.cov(mag, rowvar=False)
    tr = float(np.trace(cov))
    if not tr > 0.0:
        return np.zeros(3), 0.0
    eig = np.linalg.eigvalsh(0.5 * (cov + cov.T)) / tr
    eig = np.clip(eig, 0.0, None)
    return eig, float(eig[0] / eig[-1])


def check_observability(
    gyr: np.ndarray,
    acc: np.ndarray,
    mag: np.ndarray,
    t: np.ndarray,
) -> ObservabilityReport:
    """Check that a session can determine the calibration.

    gyr : (N, 3) float, rad/s
    acc : (N, 3) float, m/s²
    mag : (N, 3) float, raw magnetometer units
    t   : (N,) float, s, increasing

    Refuses (``ok=False``) a session that is too short, has non-finite values, whose gravity
    direction barely changes in the body frame (yaw-only motion), whose magnetometer data
    cover only a small part of the ellipsoid (too little rotation), or that has less than a
    full turn of accumulated rotation. Thresholds: the module's ``MIN_*`` constants.
    """
    t = np.asarray(t, dtype=float)
    n = int(t.shape[0])
    gyr = np.asarray(gyr, dtype=float)
    acc = np.asarray(acc, dtype=float)
    mag = np.asarray(mag, dtype=float)
    for name, x in (("gyr", gyr), ("acc", acc), ("mag", mag)):
        if x.shape != (n, 3):
            raise ValueError(f"{name} must have shape ({n}, 3), got {x.shape}")

    problems: list[str] = []
    warnings: list[str] = []
    duration = float(t[-1] - t[0]) if n > 1 else 0.0
    if n < MIN_SAMPLES or duration < MIN_DURATION_S:
        problems.append(
            f"the session is too short ({n} samples over {duration:.1f} s; the calibration "
            f"needs at least {MIN_SAMPLES} samples over {MIN_DURATION_S:.0f} s)"
        )
    finite = np.all(np.isfinite(gyr), axis=1) & np.all(np.isfinite(acc), axis=1)
    finite &= np.all(np.isfinite(mag), axis=1) & np.isfinite(t)
    if not np.all(finite):
        problems.append(f"{int(np.sum(~finite))} samples contain NaN or infinite values")
        gyr, acc, mag, t = gyr[finite], acc[finite], mag[finite], t[finite]

    if n > 1 and t.shape[0] > 1:
        dt = float(np.median(np.diff(t)))
        w = round(GRAVITY_SMOOTH_S / dt) if dt > 0.0 else 1
    else:
        w = 1
    g_eig, tilt = _gravity_figures(_moving_average(acc, w))
    m_eig, m_ratio = _mag_figures(mag)
    total_rot = float(np.sum(np.linalg.norm(gyr[:-1], axis=1) * np.diff(t))) if n > 1 else 0.0

    if np.isfinite(g_eig[1]):
        if g_eig[1] < MIN_GRAVITY_SPREAD:
            problems.append(
                "the gravity direction barely changes in the sensor frame (tilt spread "
                f"{tilt:.0f}°, eigenvalue {g_eig[1]:.3f} < {MIN_GRAVITY_SPREAD}): the sensor "
                "was only turned about the vertical (yaw) or hardly tilted, so the rotation "
                "between the magnetometer and the inertial axes cannot be found"
            )
        elif g_eig[1] < WARN_GRAVITY_SPREAD:
            warnings.append(
                f"the sensor was tilted little (tilt spread {tilt:.0f}°); the misalignment "
                "estimate may be inaccurate"
            )
        elif g_eig[0] < WARN_GRAVITY_SINGLE_AXIS:
            warnings.append(
                "the sensor was tilted about one horizontal axis only; roll it as well as "
                "pitching it for a better calibration"
            )
    if np.isfinite(m_ratio):
        if m_ratio < MIN_MAG_EIG_RATIO:
            problems.append(
                "the magnetometer data cover only a small part of the ellipsoid (eigenvalue "
                f"ratio {m_ratio:.3f} < {MIN_MAG_EIG_RATIO}): the sensor was rotated too "
                "little, so its scale, offset and skew are not determined"
            )
        elif m_ratio < WARN_MAG_EIG_RATIO:
            warnings.append(
                f"the magnetometer data cover the ellipsoid only partly (eigenvalue ratio "
                f"{m_ratio:.3f}); the calibration may be inaccurate"
            )
    if total_rot < MIN_TOTAL_ROTATION_RAD:
        problems.append(
            f"the sensor turned through only {np.degrees(total_rot):.0f}° in total (at least "
            f"{np.degrees(MIN_TOTAL_ROTATION_RAD):.0f}° are needed)"
        )

    message = ""
    if problems:
        message = (
            "This session cannot determine the magnetometer calibration: "
            + "; ".join(problems)
            + ". "
            + _ADVICE
        )
    return ObservabilityReport(
        ok=not problems,
        problems=problems,
        warnings=warnings,
        message=message,
        n_samples=n,
        duration_s=duration,
        gravity_eigenvalues=g_eig,
        tilt_spread_deg=tilt,
        mag_eigenvalues=m_eig,
        mag_eig_ratio=m_ratio,
        total_rotation_rad=total_rot,
    )


#: What to do when a flight (``motion: flight``, ``magcal import`` of a flight log) does
#: not determine the calibration: a vehicle in flight cannot be tumbled, but it can be
#: turned by hand on the ground and that stretch of a log imported.
_FLIGHT_ADVICE = (
    "This is a flight: a flight's small tilts leave the calibration undetermined with the "
    "hand-rotation model. Turn the vehicle by hand through all orientations (nose up and "
    "down, on each side) before a flight and import that stretch of the log (magcal import "
    "finds it, or give --start and --end), or record it with magcal collect --mavlink. "
    "--force calibrates the flight anyway, but this model has neither the motors' "
    "interference nor the flight's accelerations: with the motors' current moving the "
    "field, such a result can be tens of degrees off."
)


def raise_if_unobservable(
    report: ObservabilityReport, force: bool, flight: bool = False
) -> list[str]:
    """Refuse an unobservable session, or (with ``force``) turn the refusal into warnings.

    Returns the warnings to carry into the result: the report's warnings, plus, with
    ``force``, one naming the failed checks. Raises :class:`InsufficientDataError` with
    ``report.message`` when the report is not ok and ``force`` is False; for a ``flight``
    the advice is what a flight allows.
    """
    if report.ok:
        return list(report.warnings)
    if not force:
        message = report.message
        if flight:
            message = message.replace(_ADVICE, _FLIGHT_ADVICE)
        raise InsufficientDataError(message)
    forced = "calibrated despite failed observability checks (forced): " + "; ".join(
        report.problems
    )
    return [forced, *report.warnings]
