# SPDX-License-Identifier: Apache-2.0
"""magcal on real recordings with an optical reference attitude: the heading metric, the
plain-fit baseline, the known-attitude floor, every method, the acceptance criteria.

Pure functions on arrays (plus the reading of a data folder); the report that runs them is
:mod:`magcal_evaluation.real_report` (``make real``).

The data folder (default :data:`DEFAULT_DATA_DIR`, the checkout's sibling ``shared/realdata``)
holds ``cases.json`` (the cases, in order, with their ``source``), ``sessions/CASE.csv`` (the
magcal session a calibration is made from) and ``truth/CASE.npz`` (what it is scored on: for
each trial ``i`` the times ``t_i`` (s), the raw magnetometer ``mag_i`` (the session's unit),
the reference attitude ``quat_wxyz_i`` (body → world, world x east, y north, z up), the
scored samples ``valid_i``; and ``declination_deg``, the field's heading in the world frame).

**The metric** (:func:`heading_errors_rad`). A calibration ``(D, o)`` corrects a sample to
``m = D⁻¹(y − o)`` in the body axes; the reference attitude rotates it into the world; its
heading ``atan2(east, north) − declination``, wrapped to (−180°, 180°], is the error. The RMS
over a trial's scored samples, and the median over a case's trials, in degrees
(:func:`case_heading_deg`).

**The plain fit** (:func:`plain_fit`): the ellipsoid of the magnetometer data alone and its
symmetric ``D = (D̃D̃ᵀ)^½`` (:func:`magcal.calib.initial.ellipsoid.symmetric_fit`: no rotation
between magnetometer and body axes), what a calibrator that ignores the other sensors gives.
The ellipsoid is magcal's algebraic fit
(:func:`magcal.calib.initial.ellipsoid.fit_ellipsoid_algebraic`: least squares of the
quadric's algebraic residual in centred, scaled coordinates, no positive-definiteness
constraint). It fails (None) when the quadric is no ellipsoid, as on a recording whose field
changes with position. magcal's own SDP fit (``fit_ellipsoid_sdp``) would instead return the
best ellipsoid there is; :func:`plain_fit_sdp` gives that variant for comparison.

**The known-attitude floor** (:func:`known_attitude_floor`): least squares of ``y`` on
``D R(t)ᵀ m + o`` with the reference ``R(t)`` (body → world), solving ``D`` (9), ``o`` (3)
and the unit field ``m`` in the world frame (its heading and dip). It is fitted on every
sample of the recording that has a reference attitude, scored on the scored ones, and its
heading error is taken from its own field heading: the floor solves the world frame's north
along with the rest. What remains is the field's inhomogeneity and the reference's error.

Frames: :func:`magcal.calib.diagnostics.quality.known_attitude_fit` solves ``D, o`` for a
*given* field ``m_n`` and attitude ``q_nb``; it only forms ``R(q_nb)ᵀ m_n``, so any world
frame serves as long as the attitude and the field are expressed in the same one. Here it is
called with the reference's world frame (east, north, up) directly, and the field direction
is solved around it (:func:`known_attitude_floor`). magcal's navigation frame (x magnetic
north, y west, z up) is that world frame turned about the vertical:
``v_n = Rz(90° − ψ_m) v_world`` with ``ψ_m`` the field's heading (east of north), which the
metric never needs, since it compares headings in the world frame.

**Stability** (:func:`stability`): ML calibrated again with the session's magnetometer
moved by ``k ·`` :data:`STABILITY_STEP` of the field's magnitude on every axis (k = 1 …
:data:`STABILITY_MAX_K`; far below any magnetometer's resolution), each scored as the
unmoved run is. The calibration is stable when every run gives the same heading error
within :data:`STABILITY_MAX_SPREAD_DEG`, or every run refuses for the same reason (the
refusal's class and message with its figures left out: :func:`refusal_kind`).
"""

from __future__ import annotations

import dataclasses
import functools
import json
import math
import re
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import scipy.linalg
import scipy.optimize
from scipy.spatial.transform import Rotation, Slerp

from magcal.calib import frames
from magcal.calib.calibrate import METHODS, calibrate
from magcal.calib.diagnostics import quality
from magcal.calib.diagnostics.uncertainty import misalignment_deg
from magcal.calib.initial.ellipsoid import (
    fit_ellipsoid_algebraic,
    fit_ellipsoid_sdp,
    symmetric_fit,
)
from magcal.calib.samples import drop_magnetometer_glitches
from magcal.errors import MagcalError
from magcal.io.session import Session, read_session, session_from_arrays
from magcal_evaluation import REPO_ROOT

#: The data folder in a checkout: ``shared/realdata`` beside the repository.
DEFAULT_DATA_DIR = REPO_ROOT.parent / "shared" / "realdata"

#: The acceptance criteria (:func:`criteria`). ML no worse than the plain fit on any case ...
ML_PER_CASE_MAX_RATIO_TO_PLAIN = 1.03
#: ... and better by this factor in the median over cases.
ML_MEDIAN_MAX_RATIO_TO_PLAIN = 0.92
#: On the recordings of this source (reference on the recording itself), the median
#: ML/floor ...
FLOOR_SOURCE = "BROAD"
ML_MEDIAN_MAX_RATIO_TO_FLOOR = 1.25
#: A recording whose field changes with position, and the clean part of the same recording:
#: refused with a message about the field, or calibrated within this factor of the clean part.
CHANGING_FIELD_CASE = "fiumarg_rec11_full"
CLEAN_PART_CASE = "fiumarg_rec11_undist"
CHANGING_FIELD_MAX_RATIO_TO_CLEAN = 1.1
#: What a refusal of a changing field says (case-insensitive).
CHANGING_FIELD_MESSAGE = re.compile(
    r"field.*(chang|vari|inhomogen|position|disturb)|(chang|vari|inhomogen|disturb).*field",
    re.IGNORECASE | re.DOTALL,
)
#: No method may be worse than this factor of the plain fit without refusing.
ANY_METHOD_MAX_RATIO_TO_PLAIN = 2.0
#: Stability (:func:`stability`): the magnetometer is moved by k times this fraction of the
#: field's magnitude, k = 1 … STABILITY_MAX_K, ...
STABILITY_STEP = 2e-6
STABILITY_MAX_K = 5
#: ... and the heading errors of the runs (k = 0 … STABILITY_MAX_K) may differ by at most
#: this much, degrees (max − min): a change of the data that small must not change the
#: calibration's heading more than its last figure shown.
STABILITY_MAX_SPREAD_DEG = 0.05
#: The figures a refusal's message quotes (signed integers, decimals, exponents, nan, inf),
#: left out when refusals are compared by kind (:func:`refusal_kind`).
_FIGURE = re.compile(r"[-+−±]?(?:\d+(?:[.,]\d+)*(?:[eE][-+]?\d+)?|\b(?:nan|inf)\b)", re.I)

#: Span of the rotations compared to find the IMU's axes in the reference's body frame, s,
#: and the smallest gyroscope rotation over it that counts, rad.
IMU_ALIGNMENT_WINDOW_S = 0.1
IMU_ALIGNMENT_MIN_TURN_RAD = 0.05
#: Span of the windows over which the gyroscope's rotation is compared with the reference's
#: to read the gyroscope's bias, s: short enough that the integrated rate is the rotation
#: vector at hand-held rates (a turn of a few degrees), and a few of the reference's frames.
REFERENCE_BIAS_WINDOW_S = 0.03

#: The magnetometer's delay behind the reference (:func:`reference_delay`) is looked for
#: on this grid of delays, s, up to this far either way (hand-held recordings show tens of
#: ms), the best refined by a parabola through its neighbours.
REFERENCE_DELAY_STEP_S = 0.002
REFERENCE_DELAY_MAX_S = 0.1

#: Known-attitude floor: the alternating least squares that start the Levenberg–Marquardt
#: fit (each one cheap; a few bring it close).
FLOOR_ALTERNATIONS = 5
FLOOR_TOLERANCE = 1e-12


class RealDataError(MagcalError):
    """The data folder is missing or incomplete."""


# ----------------------------------------------------------------------------- reading


@dataclass(frozen=True, eq=False)
class Trial:
    """One scored recording.

    t     : (N,) s;  mag : (N, 3) raw magnetometer, the session's unit
    q_wb  : (N, 4) reference attitude, body → world (x east, y north, z up), scalar first;
            NaN where the reference has no attitude
    valid : (N,) bool, the samples the metric scores
    """

    name: str
    t: np.ndarray
    mag: np.ndarray
    q_wb: np.ndarray
    valid: np.ndarray


@dataclass(frozen=True, eq=False)
class Case:
    """A session to calibrate and the trials it is scored on."""

    name: str
    info: dict
    session: Session
    trials: tuple[Trial, ...]
    declination_deg: float
    #: which session was calibrated: :data:`FORM_SESSION` or :data:`FORM_RAW`
    form: str = "session"

    @property
    def source(self) -> str:
        return str(self.info.get("source", ""))


def case_names(data_dir: str | Path) -> list[str]:
    """The cases of ``data_dir/cases.json``, in its order. Raises :class:`RealDataError` when
    the folder or the file is missing."""
    data_dir = Path(data_dir)
    index = data_dir / "cases.json"
    if not data_dir.is_dir():
        raise RealDataError(
            f"real recordings: no folder {data_dir}; put the real-data set there (cases.json, "
            "sessions/, truth/) or name another with --data"
        )
    if not index.is_file():
        raise RealDataError(
            f"real recordings: {data_dir} has no cases.json; is it the real-data set?"
        )
    return list(json.loads(index.read_text(encoding="utf-8")))


def load_truth(path: str | Path) -> tuple[tuple[Trial, ...], float]:
    """The trials and the declination (degrees) of a ``truth/CASE.npz``."""
    with np.load(path) as z:
        names = [str(n) for n in z["trial_names"]]
        trials = tuple(
            Trial(
                name=name,
                t=np.asarray(z[f"t_{i}"], dtype=float),
                mag=np.asarray(z[f"mag_{i}"], dtype=float),
                q_wb=np.asarray(z[f"quat_wxyz_{i}"], dtype=float),
                valid=np.asarray(z[f"valid_{i}"], dtype=bool),
            )
            for i, name in enumerate(names)
        )
        declination = float(np.ravel(z["declination_deg"])[0])
    return trials, declination


#: The forms a case's session comes in: the single-rate ``sessions/CASE.csv``, or the
#: multi-rate session built from the streams at their own rates in ``raw/CASE.npz``.
FORM_SESSION = "session"
FORM_RAW = "multi-rate"


def multi_rate_session(raw_path: str | Path, meta: dict[str, str]) -> Session:
    """The multi-rate session (``magcal-session: 2``) of a ``raw/CASE.npz``: the streams
    ``acc_t, acc``, ``gyr_t, gyr``, ``mag_t, mag`` at their own times.

    Rows at the union of the three streams' times from the first gyroscope sample on; each
    row's gyroscope is the latest gyroscope sample (held, as the filter propagates with it
    until the next row), the accelerometer only at its own rows, the magnetometer only at
    its own. Nothing is interpolated.
    """
    with np.load(raw_path) as z:
        streams = {k: np.asarray(z[k], dtype=float) for k in z.files}
    t_g = streams["gyr_t"]
    t = np.unique(np.concatenate([t_g, streams["acc_t"], streams["mag_t"]]))
    t = t[t >= t_g[0]]
    gyr = streams["gyr"][np.searchsorted(t_g, t, side="right") - 1]

    def at_own_rows(name: str) -> np.ndarray:
        out = np.full((t.size, 3), np.nan)
        own_t, values = streams[f"{name}_t"], streams[name]
        keep = own_t >= t[0]
        out[np.searchsorted(t, own_t[keep])] = values[keep]
        return out

    source = meta.get("source", "")
    meta = {**meta, "source": f"{source}; multi-rate, from the streams at their own rates"}
    return session_from_arrays(t, gyr, at_own_rows("acc"), at_own_rows("mag"), meta)


def load_case(data_dir: str | Path, name: str) -> Case:
    """The case; its session is the multi-rate one of ``raw/CASE.npz`` when there is one
    (:func:`multi_rate_session`), else ``sessions/CASE.csv``."""
    data_dir = Path(data_dir)
    info = json.loads((data_dir / "cases.json").read_text(encoding="utf-8"))[name]
    for sub, ext in (("sessions", "csv"), ("truth", "npz")):
        if not (data_dir / sub / f"{name}.{ext}").is_file():
            raise RealDataError(f"real recordings: {data_dir / sub / f'{name}.{ext}'} missing")
    session = read_session(data_dir / "sessions" / f"{name}.csv")
    form = FORM_SESSION
    raw = data_dir / "raw" / f"{name}.npz"
    if raw.is_file():
        session, form = multi_rate_session(raw, session.meta), FORM_RAW
    trials, declination = load_truth(data_dir / "truth" / f"{name}.npz")
    return Case(name, info, session, trials, declination, form)


def scored_on_own_recording(case: Case) -> bool:
    """True when the case is scored on the recording it is calibrated from (one trial with
    the session's magnetometer samples): only then is a known-attitude floor a bound on what
    a calibration of the session can do."""
    if len(case.trials) != 1:
        return False
    trial = case.trials[0]
    return trial.mag.shape == case.session.mag.shape and bool(
        np.allclose(trial.mag, case.session.mag, rtol=1e-6, atol=1e-9 * np.abs(trial.mag).max())
    )


# ----------------------------------------------------------------------------- the metric


def heading_errors_rad(
    D: np.ndarray, o: np.ndarray, mag: np.ndarray, q_wb: np.ndarray, declination_deg: float
) -> np.ndarray:
    """(N,) rad: ``atan2(east, north) − declination`` of ``R(q_wb) D⁻¹(y − o)``, wrapped.

    D : (3, 3), raw units per unit field;  o : (3,) raw units;  mag : (N, 3) raw units
    q_wb : (N, 4) body → world (x east, y north, z up);  declination_deg : the field's heading
    """
    m_b = np.linalg.solve(np.asarray(D, dtype=float), (np.asarray(mag) - o).T).T
    m_w = np.einsum("kij,kj->ki", frames.quat_to_matrix(q_wb), m_b)
    return frames.wrap_angle(np.arctan2(m_w[:, 0], m_w[:, 1]) - math.radians(declination_deg))


def _rotations(q_wb: np.ndarray) -> Rotation:
    """scipy rotations of scalar-first quaternions (N, 4)."""
    return Rotation.from_quat(q_wb[:, [1, 2, 3, 0]])


def reference_at(trial: Trial, delay_s: float) -> tuple[np.ndarray, np.ndarray]:
    """The reference attitude at the times the magnetometer measured, t − delay_s (s; the
    magnetometer lags by delay_s), by spherical interpolation: (N, 4) and the (N,) mask of
    the samples it exists for (within the reference's span, a reference there)."""
    if delay_s == 0.0:
        return trial.q_wb, np.all(np.isfinite(trial.q_wb), axis=1)
    have = np.all(np.isfinite(trial.q_wb), axis=1)
    t = trial.t[have]
    slerp = Slerp(t, _rotations(trial.q_wb[have]))
    at = trial.t - delay_s
    ok = have & (at >= t[0]) & (at <= t[-1])
    q = np.full_like(trial.q_wb, np.nan)
    q[ok] = slerp(at[ok]).as_quat()[:, [3, 0, 1, 2]]
    return q, ok


def trial_heading_deg(
    D: np.ndarray, o: np.ndarray, trial: Trial, declination_deg: float, delay_s: float = 0.0
) -> float:
    """RMS heading error (degrees) over the trial's scored samples; with ``delay_s`` against
    the reference at the time the magnetometer measured (:func:`reference_at`)."""
    q, ok = reference_at(trial, delay_s)
    v = trial.valid & ok
    return quality.rms_deg(heading_errors_rad(D, o, trial.mag[v], q[v], declination_deg))


def case_heading_deg(
    D: np.ndarray,
    o: np.ndarray,
    case: Case,
    declination_deg: float | None = None,
    delay_s: float = 0.0,
) -> float:
    """Median over the case's trials of :func:`trial_heading_deg` (declination: the case's
    unless given)."""
    decl = case.declination_deg if declination_deg is None else declination_deg
    return float(np.median([trial_heading_deg(D, o, tr, decl, delay_s) for tr in case.trials]))


# ----------------------------------------------------------------------------- references


def plain_fit(mag: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """The plain fit: (D (3, 3) symmetric, o (3,)) in raw units, or None when the algebraic
    ellipsoid fit of ``mag`` (N, 3) is no ellipsoid. See the module's docstring. NaN rows
    (no magnetometer sample in a multi-rate session) are left out."""
    try:
        fit = fit_ellipsoid_algebraic(mag[~np.isnan(mag[:, 0])])
    except MagcalError:
        return None
    if fit is None:
        return None
    return symmetric_fit(fit), fit.o


def plain_fit_sdp(mag: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """The same with magcal's SDP ellipsoid (positive definite by construction), or None
    when it raises."""
    try:
        fit = fit_ellipsoid_sdp(mag[~np.isnan(mag[:, 0])])
    except MagcalError:
        return None
    return symmetric_fit(fit), fit.o


@dataclass(frozen=True, eq=False)
class FloorFit:
    """The known-attitude fit. D (3, 3), o (3,): raw units; m_w (3,): unit field in the world
    frame; heading_deg: its heading east of north; dip_deg: positive down."""

    D: np.ndarray
    o: np.ndarray
    m_w: np.ndarray
    heading_deg: float
    dip_deg: float


def _field_of(heading: float, dip: float) -> np.ndarray:
    """Unit field (east, north, up) of a heading east of north and a dip (down), rad."""
    return np.array(
        [math.sin(heading) * math.cos(dip), math.cos(heading) * math.cos(dip), -math.sin(dip)]
    )


def known_attitude_floor(mag: np.ndarray, q_wb: np.ndarray) -> FloorFit:
    """Least squares of ``mag`` (N, 3) on ``D R(q_wb)ᵀ m + o`` over D, o and the unit ``m``.

    The model is linear in (D, o) for a given m (``quality.known_attitude_fit``) and linear
    in m for a given D: a few alternations from the bilinear solution (``D ⊗ m`` unknown as
    27 coefficients, its best rank-one factor) start a Levenberg–Marquardt fit of all 14
    unknowns, m as a heading and a dip.
    """
    mag = np.asarray(mag, dtype=float)
    R_bw = np.transpose(frames.quat_to_matrix(q_wb), (0, 2, 1))
    coef, _ = _bilinear_fit(mag, R_bw)
    products = coef[:9].T.reshape(9, 3)  # rows (i, j), columns k
    m = np.linalg.svd(products)[2][0]
    if m[2] > 0.0:  # the sign is D's and m's together; take the field pointing down
        m = -m
    for _ in range(FLOOR_ALTERNATIONS):
        D, o = quality.known_attitude_fit(mag, q_wb, m)
        A = np.einsum("ij,kjl->kil", D, R_bw).reshape(-1, 3)
        m, *_ = np.linalg.lstsq(A, (mag - o).ravel(), rcond=None)
        m /= np.linalg.norm(m)
    D, o = quality.known_attitude_fit(mag, q_wb, m)

    def unpack(p: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        return p[:9].reshape(3, 3), p[9:12], _field_of(p[12], p[13])

    def residual(p: np.ndarray) -> np.ndarray:
        D_, o_, m_ = unpack(p)
        return ((R_bw @ m_) @ D_.T + o_ - mag).ravel()

    p0 = np.concatenate([D.ravel(), o, [math.atan2(m[0], m[1]), math.asin(-m[2])]])
    sol = scipy.optimize.least_squares(
        residual, p0, method="lm", xtol=FLOOR_TOLERANCE, ftol=FLOOR_TOLERANCE
    )
    D, o, m = unpack(sol.x)
    return FloorFit(
        D=D,
        o=o,
        m_w=m,
        heading_deg=math.degrees(math.atan2(m[0], m[1])),
        dip_deg=math.degrees(math.asin(-m[2])),
    )


def _bilinear_fit(mag: np.ndarray, R_bw: np.ndarray) -> tuple[np.ndarray, float]:
    """The known-attitude model with ``D ⊗ m`` as 27 free coefficients, linear:
    ``y_i = Σ_jk D_ij m_k (R_bw)_jk + o_i``. Its coefficients (10, 3) (the 9 products of
    row i in column i, then o) and the RMS residual of ``mag`` (N, 3) on it; R_bw (N, 3, 3)."""
    n = mag.shape[0]
    X = np.hstack([R_bw.reshape(n, 9), np.ones((n, 1))])
    coef, *_ = np.linalg.lstsq(X, mag, rcond=None)
    return coef, float(np.sqrt(np.mean(np.sum((X @ coef - mag) ** 2, axis=1))))


def _bilinear_residual(mag: np.ndarray, q_wb: np.ndarray) -> float:
    """RMS residual of ``mag`` (N, 3) on :func:`_bilinear_fit` (:func:`known_attitude_floor`'s
    start) with the attitudes ``q_wb``: linear, so cheap to scan."""
    return _bilinear_fit(mag, np.transpose(frames.quat_to_matrix(q_wb), (0, 2, 1)))[1]


def _best_delay(residual_at) -> float | None:
    """s: the delay on the grid of :data:`REFERENCE_DELAY_STEP_S` within
    ±:data:`REFERENCE_DELAY_MAX_S` where ``residual_at(delay)`` is smallest, refined by a
    parabola through its neighbours; None when that is at the grid's edge."""
    k_max = int(round(REFERENCE_DELAY_MAX_S / REFERENCE_DELAY_STEP_S))
    delays = REFERENCE_DELAY_STEP_S * np.arange(-k_max, k_max + 1)
    residuals = [residual_at(float(d)) for d in delays]
    k = int(np.argmin(residuals))
    if k in (0, len(delays) - 1):
        return None
    a, b, c = residuals[k - 1 : k + 2]
    curvature = a - 2.0 * b + c
    shift = 0.5 * (a - c) / curvature if curvature > 0.0 else 0.0
    return float(delays[k] + REFERENCE_DELAY_STEP_S * shift)


def reference_delay(trial: Trial, rows: np.ndarray | None = None) -> float | None:
    """s: the magnetometer's delay behind the reference attitude, as the reference itself
    shows it: the delay at which the known-attitude model explains the magnetometer best
    (smallest residual against the reference at ``t − delay``, :func:`reference_at`;
    :func:`_best_delay`), over the trial's samples or the ``rows`` (N,) bool of them
    (:func:`measured_rows`). It is independent of any calibration, and it measures the
    magnetometer against the reference's clock, not the gyroscope's. None when no delay
    within the grid is best."""
    have = np.all(np.isfinite(trial.q_wb), axis=1)
    if rows is not None:
        have &= rows
    # The same samples at every delay, so that the residuals compare.
    keep = have & _within(trial.t, trial.t[have], REFERENCE_DELAY_MAX_S)

    def residual_at(delay: float) -> float:
        q, _ = reference_at(trial, delay)
        return _bilinear_residual(trial.mag[keep], q[keep])

    return _best_delay(residual_at)


def gyroscope_delay(case: Case, C: np.ndarray) -> float | None:
    """s: the gyroscope's delay behind the reference attitude: the delay at which the
    reference's rate (from consecutive attitudes, turned to the IMU's axes by ``C``,
    :class:`ImuAxes`) matches the gyroscope's best (the median of
    ``|ω_gyro − ω_reference|`` after the median difference, the bias, is taken out;
    :func:`_best_delay`). With :func:`reference_delay` it gives the magnetometer's delay
    behind the gyroscope, which ML's time offset estimates. None unless the case is scored on
    its own recording, or when no delay within the grid is best."""
    if not scored_on_own_recording(case):
        return None
    trial, session = case.trials[0], case.session
    have = np.all(np.isfinite(trial.q_wb), axis=1)
    keep = have & _within(trial.t, trial.t[have], REFERENCE_DELAY_MAX_S)
    steps = np.flatnonzero(keep[:-1] & keep[1:])
    # The gyroscope's mean over a step against the reference's rotation over it.
    gyro = 0.5 * (session.gyr[steps] + session.gyr[steps + 1])
    dt = trial.t[steps + 1] - trial.t[steps]

    def residual_at(delay: float) -> float:
        q, _ = reference_at(trial, delay)
        turn = (_rotations(q[steps]).inv() * _rotations(q[steps + 1])).as_rotvec()
        diff = gyro - (turn / dt[:, None]) @ np.asarray(C)
        diff -= np.median(diff, axis=0)
        return float(np.median(np.linalg.norm(diff, axis=1)))

    return _best_delay(residual_at)


def _within(t: np.ndarray, t_reference: np.ndarray, margin_s: float) -> np.ndarray:
    """(N,) bool: the times at least ``margin_s`` inside the reference's span."""
    return (t >= t_reference[0] + margin_s) & (t <= t_reference[-1] - margin_s)


def case_floor(case: Case, delay_s: float = 0.0, rows: np.ndarray | None = None) -> FloorFit | None:
    """The floor of a case scored on its own recording (fitted on the samples that have a
    reference attitude, or the ``rows`` (N,) bool of them; with ``delay_s``, the reference
    at the magnetometer's times), else None."""
    if not scored_on_own_recording(case):
        return None
    trial = case.trials[0]
    q, have = reference_at(trial, delay_s)
    if rows is not None:
        have = have & rows
    return known_attitude_floor(trial.mag[have], q[have])


def measured_rows(case: Case) -> np.ndarray:
    """(N,) bool: the session's rows where the magnetometer measured, as a calibration takes
    them (:func:`magcal.calib.samples.drop_magnetometer_glitches`): a stream that repeats
    its last value until the next reading has no new measurement in the repeats, and they
    show the field later than it was measured (BROAD: 29 % of the rows)."""
    return drop_magnetometer_glitches(case.session)[0].has_mag


# ----------------------------------------------------------------------------- methods


@dataclass
class MethodRun:
    """One method on one case. heading_deg: the metric (NaN when refused); refused: the
    refusal's message or None; the rest describes the estimate (None when refused)."""

    method: str
    heading_deg: float = math.nan
    refused: str | None = None
    #: the refusal's kind (:func:`refusal_kind`) or None
    refusal_kind: str | None = None
    gyro_bias_deg_s: list[float] | None = None
    misalignment_deg: float | None = None
    misalignment_vec_deg: list[float] | None = None
    time_offset_s: float | None = None
    D: list[list[float]] | None = None
    o: list[float] | None = None
    seconds: float = 0.0
    warnings: list[str] = field(default_factory=list)


def run_method(case: Case, method: str, *, force: bool = False) -> MethodRun:
    """``calibrate(case.session, method, force=force)`` scored on the case."""
    t0 = time.perf_counter()
    try:
        cal = calibrate(case.session, method, force=force)
    except MagcalError as exc:
        return MethodRun(
            method,
            refused=str(exc),
            refusal_kind=refusal_kind(exc),
            seconds=time.perf_counter() - t0,
        )
    seconds = time.perf_counter() - t0
    res = cal.result
    mis = misalignment_deg(res.D)
    offset = res.extra.get("time_offset_s")
    return MethodRun(
        method=method,
        heading_deg=case_heading_deg(res.D, res.o, case),
        gyro_bias_deg_s=None
        if res.gyro_bias is None
        else [float(x) for x in np.rad2deg(res.gyro_bias)],
        misalignment_deg=float(np.linalg.norm(mis)),
        misalignment_vec_deg=[float(x) for x in mis],
        time_offset_s=None if offset is None else float(offset),
        D=res.D.tolist(),
        o=res.o.tolist(),
        seconds=seconds,
        warnings=list(res.warnings),
    )


def refusal_kind(exc: BaseException) -> str:
    """What a refusal says, without its figures: the exception's class and its message with
    every number replaced by "#", so that refusals for the same reason compare equal
    whatever the figures they quote."""
    return f"{type(exc).__name__}: {_FIGURE.sub('#', str(exc))}"


def field_magnitude(session: Session) -> float:
    """The field's magnitude in the session's unit: the median norm of the magnetometer's
    readings about their mean, over the rows that have a magnetometer sample."""
    mag = session.mag[session.has_mag]
    return float(np.median(np.linalg.norm(mag - mag.mean(axis=0), axis=1)))


def stability_verdict(runs: list[dict]) -> tuple[float | None, bool]:
    """(spread, stable) of :func:`stability`'s runs (each with ``heading_deg`` or
    ``refused``, the refusal's kind): the spread max − min of the heading errors, degrees,
    where every run gives one (else None); stable when that is at most
    :data:`STABILITY_MAX_SPREAD_DEG`, or when every run refuses with the same kind."""
    kinds = {run["refused"] for run in runs}
    if kinds == {None}:
        headings = [run["heading_deg"] for run in runs]
        spread = max(headings) - min(headings)
        return spread, bool(math.isfinite(spread) and spread <= STABILITY_MAX_SPREAD_DEG)
    return None, len(kinds) == 1 and None not in kinds


def stability(case: Case, ml_run: dict) -> dict:
    """ML's heading error with the session's magnetometer moved by ``k · STABILITY_STEP ·
    field`` on every axis (field: :func:`field_magnitude`), k = 0 … :data:`STABILITY_MAX_K`:
    k = 0 is ``ml_run`` (the unforced ML run of :func:`evaluate_case`, a :class:`MethodRun`
    dict), the others calibrated as it was (unforced) and scored on the case's unmoved
    trials. Rows without a magnetometer sample stay without one (NaN). JSON-ready: the
    field, the runs (``k``, ``heading_deg`` or None, ``refused``: the refusal's kind or
    None), the spread (degrees, :func:`stability_verdict`) and ``stable``."""
    field_size = field_magnitude(case.session)
    runs = [{"k": 0, **_stability_entry(ml_run)}]
    for k in range(1, STABILITY_MAX_K + 1):
        moved = dataclasses.replace(
            case.session, mag=case.session.mag + k * STABILITY_STEP * field_size
        )
        run = run_method(dataclasses.replace(case, session=moved), "ml")
        runs.append({"k": k, **_stability_entry(run.__dict__)})
    spread, stable = stability_verdict(runs)
    return {"field": field_size, "runs": runs, "spread_deg": spread, "stable": stable}


def _stability_entry(run: dict) -> dict:
    if run["refused"] is not None:
        return {"heading_deg": None, "refused": run["refusal_kind"]}
    return {"heading_deg": float(run["heading_deg"]), "refused": None}


def evaluate_case(case: Case, methods: tuple[str, ...] = METHODS) -> dict:
    """Everything the report shows of one case, JSON-ready: ``plain``, ``plain_sdp`` and
    ``floor`` (degrees or None), the floor's field heading and dip, per method its
    :class:`MethodRun` as a dict, plus ``forced`` (the run with force=True) when refused,
    and ``stability`` (:func:`stability`; None without ML)."""
    t0 = time.perf_counter()
    mag = case.session.mag[case.session.has_mag]
    plain = plain_fit(mag)
    sdp = plain_fit_sdp(mag)
    floor = case_floor(case)
    out: dict = {
        "case": case.name,
        "source": case.source,
        "samples": len(case.session),
        "form": case.form,
        "mag_samples": int(case.session.has_mag.sum()),
        "trials": len(case.trials),
        "plain": None if plain is None else case_heading_deg(*plain, case),
        "plain_sdp": None if sdp is None else case_heading_deg(*sdp, case),
        "floor": None
        if floor is None
        else case_heading_deg(floor.D, floor.o, case, floor.heading_deg),
        "floor_field_heading_deg": None if floor is None else floor.heading_deg,
        "floor_dip_deg": None if floor is None else floor.dip_deg,
        "methods": {},
    }
    for method in methods:
        run = run_method(case, method)
        entry = dict(run.__dict__)
        if run.refused is not None:
            entry["forced"] = dict(run_method(case, method, force=True).__dict__)
        out["methods"][method] = entry
    ml = out["methods"].get("ml", {})
    out["stability"] = stability(case, ml) if ml else None
    ml_result = ml.get("forced", ml)
    axes = imu_axes(case)  # once for the two sections that use it: two delay scans
    for key, score in (
        ("at_magnetometer_time", _at_magnetometer_time),
        ("imu_frame", functools.partial(_in_imu_frame, axes=axes)),
        ("other_recordings", _on_other_recordings),
        ("reference_delay", functools.partial(_at_reference_delay, axes=axes)),
        ("trial_by_trial", _trial_by_trial),
    ):
        out[key] = score(case, plain, floor, ml_result)
        if out[key] is not None:
            out[key]["ml_forced"] = "forced" in ml
    out["seconds"] = time.perf_counter() - t0
    return out


def _window_rotations(
    case: Case, window_s: float, gyro_delay_s: float = 0.0
) -> tuple[np.ndarray, ...] | None:
    """Over consecutive windows of ``window_s`` that have a reference at both ends: the
    reference's rotation (rotation vector of R(t)ᵀ R(t + T), reference body axes, with the
    reference at ``t − gyro_delay_s``: the motion the gyroscope's samples measured), the
    gyroscope's integrated rate (IMU axes), both (K, 3) rad, and the windows' spans (K,) s.
    None unless the case is scored on its own recording."""
    if not scored_on_own_recording(case):
        return None
    trial, session = case.trials[0], case.session
    q_wb, have = reference_at(trial, gyro_delay_s)
    step = max(1, int(round(window_s / np.median(np.diff(session.t)))))
    rotations = _rotations(np.where(have[:, None], q_wb, [1.0, 0.0, 0.0, 0.0]))
    # Trapezoids: a gyroscope sample is the rate at its time, not over the step after it.
    rate_dt = 0.5 * (session.gyr[:-1] + session.gyr[1:]) * np.diff(session.t)[:, None]
    starts = np.arange(0, len(session.t) - step, step)
    starts = starts[have[starts] & have[starts + step]]
    reference = (rotations[starts].inv() * rotations[starts + step]).as_rotvec()
    turned_by = np.vstack([np.zeros(3), np.cumsum(rate_dt, axis=0)])  # ∫ω dt from the start
    gyro = turned_by[starts + step] - turned_by[starts]
    return reference, gyro, session.t[starts + step] - session.t[starts]


@dataclass(frozen=True)
class ImuAxes:
    """How the IMU sits against the reference (:func:`imu_axes`).

    C            : (3, 3), ``v_reference = C v_imu``: the IMU's axes in the reference's body
                   frame (markers, a rig)
    gyro_delay_s : s, the gyroscope's delay behind the reference's clock
                   (:func:`gyroscope_delay`; None where no delay within the grid is best)
    """

    C: np.ndarray
    gyro_delay_s: float | None


def imu_axes(case: Case) -> ImuAxes | None:
    """The IMU's axes in the reference's body frame, from the rotations over
    :data:`IMU_ALIGNMENT_WINDOW_S` windows: the reference's against the gyroscope's
    integrated rate, by least squares (Wahba), with the reference at the gyroscope's delay;
    and that delay. Where the motion turns more one way than another, a delay of a few ms
    left in turns C by tenths of a degree (BROAD: 0.4–0.7°), so C is read twice: at no
    delay, which gives the delay, then at the delay, which gives C and the delay again.
    None unless the case is scored on its own recording."""
    C = _aligned_windows(case, 0.0)
    if C is None:
        return None
    delay = gyroscope_delay(case, C)
    at_delay = _aligned_windows(case, delay) if delay else None
    if at_delay is None:
        return ImuAxes(C, delay)
    return ImuAxes(at_delay, gyroscope_delay(case, at_delay))


def _aligned_windows(case: Case, gyro_delay_s: float) -> np.ndarray | None:
    """:attr:`ImuAxes.C` from the windows with the reference at ``gyro_delay_s`` (None
    without three windows that turn)."""
    windows = _window_rotations(case, IMU_ALIGNMENT_WINDOW_S, gyro_delay_s)
    if windows is None:
        return None
    reference, gyro, _ = windows
    turned = np.linalg.norm(gyro, axis=1) > IMU_ALIGNMENT_MIN_TURN_RAD
    if turned.sum() < 3:
        return None
    C, _ = Rotation.align_vectors(reference[turned], gyro[turned])
    return C.as_matrix()


def reference_gyro_bias(case: Case, C: np.ndarray, gyro_delay_s: float = 0.0) -> np.ndarray | None:
    """(3,) rad/s in the IMU's axes: the gyroscope's rate minus the reference's (turned to the
    IMU's axes by ``C``, at the gyroscope's delay ``gyro_delay_s``: :class:`ImuAxes`),
    median over :data:`REFERENCE_BIAS_WINDOW_S` windows (robust to the reference's dropouts
    and glitches): the bias an estimate can be checked against. None unless the case is
    scored on its own recording."""
    windows = _window_rotations(case, REFERENCE_BIAS_WINDOW_S, gyro_delay_s)
    if windows is None or len(windows[2]) == 0:
        return None
    reference, gyro, span = windows
    return np.median((gyro - reference @ np.asarray(C)) / span[:, None], axis=0)


def in_imu_frame(case: Case, C: np.ndarray) -> Case:
    """The case with its reference attitudes turned to the IMU's axes: R_imu = R_reference C."""
    qc = frames.matrix_to_quat(C)
    trials = tuple(
        dataclasses.replace(tr, q_wb=frames.quat_multiply(tr.q_wb, qc)) for tr in case.trials
    )
    return dataclasses.replace(case, trials=trials)


def _in_imu_frame(
    case: Case, plain, floor: FloorFit | None, ml_run: dict, *, axes: ImuAxes | None
) -> dict | None:
    """The plain fit, the floor and ML (forced, if it refused) scored with the reference
    attitude turned to the IMU's axes (``axes``: :func:`imu_axes`): the body frame an
    inertial calibration aligns the magnetometer to (None where there is no such rotation).
    The floor turns with the attitude: with R_imu = R_reference C its fit is D C, field and
    offset unchanged, so it is not refitted."""
    if axes is None or ml_run.get("D") is None:
        return None
    C = axes.C
    imu = in_imu_frame(case, C)
    if floor is not None:
        floor = dataclasses.replace(floor, D=floor.D @ C)
    north = None if floor is None else floor.heading_deg
    bias = reference_gyro_bias(case, C, axes.gyro_delay_s or 0.0)
    return {
        "rotation_deg": [float(x) for x in np.rad2deg(Rotation.from_matrix(C).as_rotvec())],
        "reference_gyro_bias_deg_s": None if bias is None else [float(x) for x in np.rad2deg(bias)],
        "plain": None if plain is None else case_heading_deg(*plain, imu, north),
        "floor": None if floor is None else case_heading_deg(floor.D, floor.o, imu, north),
        "ml": case_heading_deg(np.array(ml_run["D"]), np.array(ml_run["o"]), imu, north),
    }


def _at_magnetometer_time(
    case: Case, plain, same_time: FloorFit | None, ml_run: dict
) -> dict | None:
    """The plain fit, the floor and ML (forced, if it refused) scored against the reference
    at the times the magnetometer measured, by the ML's time offset: what a fusion filter
    that knows the delay gets from each calibration (None without an ML time offset)."""
    if not ml_run.get("time_offset_s") or ml_run.get("D") is None:
        return None
    delay = float(ml_run["time_offset_s"])
    floor = case_floor(case, delay)
    return {
        "delay_s": delay,
        # The rotation part of the floor's D, fitted at the same time and at t − τ: a
        # magnetometer lag during steady turns looks like a fixed rotation to a fit without τ.
        "floor_rotation_deg": None
        if floor is None
        else [[float(x) for x in misalignment_deg(f.D)] for f in (same_time, floor)],
        "plain": None if plain is None else case_heading_deg(*plain, case, delay_s=delay),
        "floor": None
        if floor is None
        else case_heading_deg(floor.D, floor.o, case, floor.heading_deg, delay),
        "ml": case_heading_deg(np.array(ml_run["D"]), np.array(ml_run["o"]), case, delay_s=delay),
    }


def _at_reference_delay(
    case: Case, _plain, floor: FloorFit | None, ml_run: dict, *, axes: ImuAxes | None
) -> dict | None:
    """For a case scored on its own recording: the magnetometer's delay behind the reference
    (:func:`reference_delay`) and the known-attitude fit there, the calibration of the
    magnetometer as it is, with the lag left out of D; both on the rows where the
    magnetometer measured (:func:`measured_rows`), as a calibration sees them. Scored as
    every method is (at t, the case's declination), the fit is the floor of a calibration
    that carries the lag in a time offset instead of in D; scored at its own time and north,
    what such a calibration gives a fusion filter that knows the delay. The same fit with
    the reference turned to the IMU's axes (``imu_fit``, where they are found: ``axes``,
    :func:`imu_axes`) calibrates the magnetometer against the IMU with the attitude
    known exactly: the best an inertial calibration can find, scored as its result is, in
    the reference's axes. None without a floor, a delay or an ML result."""
    if floor is None or ml_run.get("D") is None:
        return None
    measured = measured_rows(case)
    delay = reference_delay(case.trials[0], measured)
    if delay is None:
        return None
    fit = case_floor(case, delay, measured)
    gyro_delay = None if axes is None else axes.gyro_delay_s
    imu_fit = None if axes is None else case_floor(in_imu_frame(case, axes.C), delay, measured)
    D_ml, o_ml = np.array(ml_run["D"]), np.array(ml_run["o"])
    return {
        "delay_s": delay,
        "gyroscope_delay_s": gyro_delay,
        "fit": case_heading_deg(fit.D, fit.o, case),
        "imu_fit": None if imu_fit is None else case_heading_deg(imu_fit.D, imu_fit.o, case),
        "imu_fit_rotation_deg": None
        if imu_fit is None
        else [float(x) for x in misalignment_deg(imu_fit.D)],
        "fit_at_delay": case_heading_deg(fit.D, fit.o, case, fit.heading_deg, delay),
        "fit_rotation_deg": [float(x) for x in misalignment_deg(fit.D)],
        "floor_rotation_deg": [float(x) for x in misalignment_deg(floor.D)],
        "ml": case_heading_deg(D_ml, o_ml, case),
        "floor": case_heading_deg(floor.D, floor.o, case, floor.heading_deg),
    }


def _trial_by_trial(case: Case, plain, _floor, ml_run: dict) -> dict | None:
    """For a case scored on several recordings: ML's and the plain fit's heading on each
    (degrees, in the trials' order). The case's figure is the median over trials of each
    method on its own; where the trials fall into groups of easy and hard recordings, the
    two medians can come from different trials, and the pairs say how the two compare
    recording by recording. None for a single trial, no plain fit or no ML result."""
    if len(case.trials) < 2 or plain is None or ml_run.get("D") is None:
        return None
    D_ml, o_ml = np.array(ml_run["D"]), np.array(ml_run["o"])
    return {
        "names": [tr.name for tr in case.trials],
        "ml": [trial_heading_deg(D_ml, o_ml, tr, case.declination_deg) for tr in case.trials],
        "plain": [trial_heading_deg(*plain, tr, case.declination_deg) for tr in case.trials],
    }


def scored_recordings_fit(case: Case) -> FloorFit:
    """The known-attitude fit (:func:`known_attitude_floor`) on every scored sample of every
    trial: the (D, o) that the scored recordings themselves show, which no calibration from
    another recording can be given."""
    scored = [
        (tr.mag[keep], tr.q_wb[keep])
        for tr in case.trials
        for keep in [tr.valid & np.all(np.isfinite(tr.q_wb), axis=1)]
    ]
    return known_attitude_floor(
        np.vstack([m for m, _ in scored]), np.vstack([q for _, q in scored])
    )


def _on_other_recordings(case: Case, plain, _floor, ml_run: dict) -> dict | None:
    """For a case scored on other recordings: the fit on the scored recordings
    (:func:`scored_recordings_fit`), its rotation and how far its offset is from ML's, and
    the headings of ML without its rotation (the symmetric factor P of D = P U), of the
    plain fit turned by the scored recordings' own rotation, and of ML's D and the plain
    fit's D each given the scored recordings' own offset, and of the fit's D given the
    offset of the calibration recording (ML's, and the plain fit's): what the D those
    recordings show is worth with the offset a calibration recording can give. None for a
    case scored on its own recording (it has the floor instead), or without an ML result."""
    if scored_on_own_recording(case) or ml_run.get("D") is None:
        return None
    fit = scored_recordings_fit(case)
    D_ml, o_ml = np.array(ml_run["D"]), np.array(ml_run["o"])
    _, P_ml = scipy.linalg.polar(D_ml, side="left")  # D = P U: (U, P)
    U_fit, _ = scipy.linalg.polar(fit.D, side="left")
    return {
        "fit": case_heading_deg(fit.D, fit.o, case),
        "fit_rotation_deg": [float(x) for x in misalignment_deg(fit.D)],
        "offset_change": float(np.linalg.norm(fit.o - o_ml)),
        "field_norm": float(np.cbrt(abs(np.linalg.det(D_ml)))),
        "ml_without_rotation": case_heading_deg(P_ml, o_ml, case),
        "plain_with_fit_rotation": None
        if plain is None
        else case_heading_deg(plain[0] @ U_fit, plain[1], case),
        "ml_with_fit_offset": case_heading_deg(D_ml, fit.o, case),
        "plain_with_fit_offset": None if plain is None else case_heading_deg(plain[0], fit.o, case),
        "fit_with_ml_offset": case_heading_deg(fit.D, o_ml, case),
        "fit_with_plain_offset": None if plain is None else case_heading_deg(fit.D, plain[1], case),
        "ml_plain_offset_gap": None if plain is None else float(np.linalg.norm(o_ml - plain[1])),
    }


# ----------------------------------------------------------------------------- criteria


@dataclass(frozen=True)
class Criterion:
    """One acceptance criterion: its text, what was measured, and pass (True), fail (False)
    or not applicable (None: the cases it needs are not in the data)."""

    text: str
    measured: str
    passed: bool | None


def ratio(a: float | None, b: float | None) -> float | None:
    if a is None or b is None or not (math.isfinite(a) and math.isfinite(b)) or b <= 0.0:
        return None
    return a / b


@dataclass(frozen=True)
class RightCalibration:
    """What the calibration a case's own data show to be right scores (heading, degrees):
    where the case is scored on its own recording, the known-attitude fit at the
    magnetometer's delay (``reference_delay``'s fit); where it is scored on other recordings,
    the D those recordings show with the calibration recording's offset, ML's
    (``other_recordings``' fit_with_ml_offset). ``kind`` says which."""

    case: str
    kind: str
    plain: float
    ml: float | None
    right: float

    @property
    def better(self) -> float:
        """The better of ML (None where it refused) and the right calibration."""
        return self.right if self.ml is None else min(self.ml, self.right)


def right_calibrations(results: list[dict]) -> list[RightCalibration]:
    """:class:`RightCalibration` of every case with a plain fit and one of those sections."""
    out = []
    for r in results:
        if r.get("plain") is None or "ml" not in r.get("methods", {}):
            continue
        ml_run = r["methods"]["ml"]
        ml = None if ml_run["refused"] is not None else ml_run["heading_deg"]
        delay, other = r.get("reference_delay"), r.get("other_recordings")
        if delay:
            out.append(
                RightCalibration(r["case"], "fit at the delay", r["plain"], ml, delay["fit"])
            )
        elif other and other.get("fit_with_ml_offset") is not None:
            out.append(
                RightCalibration(
                    r["case"],
                    "the scored recordings' D, ML's offset",
                    r["plain"],
                    ml,
                    other["fit_with_ml_offset"],
                )
            )
    return out


def criteria(results: list[dict]) -> list[Criterion]:
    """The acceptance criteria on :func:`evaluate_case` results (ML: method "ml")."""
    by_name = {r["case"]: r for r in results}
    out = []

    with_plain = [r for r in results if r["plain"] is not None and "ml" in r["methods"]]
    per_case = []
    for r in with_plain:
        ml = r["methods"]["ml"]
        q = ratio(ml["heading_deg"], r["plain"])
        per_case.append((r["case"], q, ml["refused"] is not None))
    bad = [
        f"{name} {'refused' if refused else f'{q:.2f}'}"
        for name, q, refused in per_case
        if refused or q is None or q > ML_PER_CASE_MAX_RATIO_TO_PLAIN
    ]
    worst = max((q for _, q, _ in per_case if q is not None), default=None)
    out.append(
        Criterion(
            f"ML ≤ {ML_PER_CASE_MAX_RATIO_TO_PLAIN} × plain fit on every case with a plain fit "
            "(a refusal fails it)",
            f"worst {worst:.2f}; beyond: {', '.join(bad) or 'none'}"
            if worst is not None
            else "no case",
            None if not per_case else not bad,
        )
    )

    qs = [q for _, q, _ in per_case if q is not None]
    med = float(np.median(qs)) if qs else None
    out.append(
        Criterion(
            f"median over cases of ML/plain ≤ {ML_MEDIAN_MAX_RATIO_TO_PLAIN}",
            f"{med:.2f} over {len(qs)} cases" if med is not None else "no case",
            None if med is None else med <= ML_MEDIAN_MAX_RATIO_TO_PLAIN,
        )
    )

    floor_q = [
        ratio(r["methods"]["ml"]["heading_deg"], r["floor"])
        for r in results
        if r["source"] == FLOOR_SOURCE and r["floor"] is not None and "ml" in r["methods"]
    ]
    refused_floor = any(q is None for q in floor_q)
    fq = [q for q in floor_q if q is not None]
    med_f = float(np.median(fq)) if fq else None
    out.append(
        Criterion(
            f"{FLOOR_SOURCE} cases: median ML/floor ≤ {ML_MEDIAN_MAX_RATIO_TO_FLOOR}",
            (f"{med_f:.2f} over {len(fq)} cases" if med_f is not None else "no case")
            + (" (ML refused some)" if refused_floor else ""),
            None
            if med_f is None
            else (med_f <= ML_MEDIAN_MAX_RATIO_TO_FLOOR and not refused_floor),
        )
    )

    full, clean = by_name.get(CHANGING_FIELD_CASE), by_name.get(CLEAN_PART_CASE)
    text = (
        f"{CHANGING_FIELD_CASE} (the field changes with position): ML refuses it with a "
        f"message about the field, or calibrates it within {CHANGING_FIELD_MAX_RATIO_TO_CLEAN}"
        f" × ML on {CLEAN_PART_CASE}"
    )
    if full is None or clean is None or "ml" not in full["methods"]:
        out.append(Criterion(text, "cases not in the data", None))
    else:
        ml_full, ml_clean = full["methods"]["ml"], clean["methods"]["ml"]
        if ml_full["refused"] is not None:
            ok = bool(CHANGING_FIELD_MESSAGE.search(ml_full["refused"]))
            measured = f"refused: {ml_full['refused'][:160]}"
        else:
            q = ratio(ml_full["heading_deg"], ml_clean["heading_deg"])
            ok = q is not None and q <= CHANGING_FIELD_MAX_RATIO_TO_CLEAN
            measured = (
                f"calibrated: {ml_full['heading_deg']:.2f}° against "
                f"{ml_clean['heading_deg']:.2f}° on the clean part"
                + (f" ({q:.2f}×)" if q is not None else " (clean part refused)")
            )
        out.append(Criterion(text, measured, ok))

    worse = []
    for r in with_plain:
        for method, m in r["methods"].items():
            q = ratio(m["heading_deg"], r["plain"])
            if m["refused"] is None and (q is None or q > ANY_METHOD_MAX_RATIO_TO_PLAIN):
                worse.append(f"{r['case']} {method} {'–' if q is None else f'{q:.1f}'}")
    out.append(
        Criterion(
            f"no method worse than {ANY_METHOD_MAX_RATIO_TO_PLAIN:g} × plain fit without "
            "refusing (cases with a plain fit)",
            ", ".join(worse) or "none",
            None if not with_plain else not worse,
        )
    )

    stable = [r for r in results if r.get("stability")]
    unstable = [
        f"{r['case']} ({_instability(r['stability'])})"
        for r in stable
        if not r["stability"]["stable"]
    ]
    spreads = [r["stability"]["spread_deg"] for r in stable]
    worst = max((s for s in spreads if s is not None), default=None)
    out.append(
        Criterion(
            f"ML stable under k·{scientific(STABILITY_STEP)} shifts of the magnetometer on "
            f"every case (k = 0…"
            f"{STABILITY_MAX_K}: the same heading error within {STABILITY_MAX_SPREAD_DEG}°, "
            "or the same refusal)",
            (
                "no case"
                if not stable
                else (f"largest spread {worst:.3f}°" if worst is not None else "all refused")
                + f"; unstable: {', '.join(unstable) or 'none'}"
            ),
            None if not stable else not unstable,
        )
    )
    return out


def scientific(x: float) -> str:
    """``x`` as "2·10⁻⁶" (one significant figure's mantissa as ``{:g}`` gives it)."""
    mantissa, exponent = f"{x:e}".split("e")
    superscript = str(int(exponent)).translate(str.maketrans("-0123456789", "⁻⁰¹²³⁴⁵⁶⁷⁸⁹"))
    return f"{float(mantissa):g}·10{superscript}"


def _instability(section: dict) -> str:
    """Why a :func:`stability` section is not stable, in a few words."""
    if section["spread_deg"] is not None:
        return f"spread {section['spread_deg']:.3f}°"
    refused = [run["k"] for run in section["runs"] if run["refused"] is not None]
    if len(refused) < len(section["runs"]):
        return f"refused at k = {', '.join(map(str, refused))} only"
    return "refused for different reasons"
