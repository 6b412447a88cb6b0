# SPDX-License-Identifier: Apache-2.0
"""From a session to a calibration result: Algorithm 1 with its checks and diagnostics.

This is the one entry point the command line and the report scripts call.

A multi-rate session (the magnetometer slower than the IMU, ``magcal-session: 2``) is
calibrated as it is: magnetometer glitches are dropped first (``samples.py``), everything
that works per magnetometer sample (checks, ellipsoid fits, the norm-only methods, the
initial estimate, the consistency checks) sees the session at the magnetometer's rows
(``samples.at_magnetometer_rows``), and the ML step and the result's filter use every row
with each stream's noise measured at its own rate.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from magcal.calib import samples
from magcal.calib.diagnostics import consistency, observability, quality, units
from magcal.calib.initial.ellipsoid import fit_ellipsoid_sdp
from magcal.calib.initial.estimate import InitialEstimate, initial_estimate, with_ellipsoid
from magcal.calib.initial.sensor_levels import measure_sensor_levels
from magcal.calib.likelihood import mekf
from magcal.calib.likelihood.ml import OPTIMIZERS, MLEstimate, maximum_likelihood
from magcal.calib.likelihood.optimize import OptimizeOptions
from magcal.calib.likelihood.params import ModelParams
from magcal.calib.likelihood.problem import LikelihoodProblem, Priors
from magcal.calib.norm_only import ckf, twostep
from magcal.errors import FieldChangedError, MagcalError
from magcal.io.result import CalibrationResult
from magcal.io.session import Session

METHODS = ("ml", "init", "ckf", "two-step")
#: Methods that fit the ellipsoid from the field norm alone, sample by sample (Zhao et al.'s
#: CKF) or in batch (Alonso & Shuster's TWO-STEP), instead of Algorithm 1's SDP; the
#: misalignment, the field's dip and the gyro bias then come from Algorithm 1's own steps
#: 1a and 1c, so the result is a full D, o like "init". Each returns (EllipsoidFit, the
#: result file's record of the run).
NORM_ONLY = {
    "ckf": ckf.calibration_ellipsoid,
    "two-step": twostep.calibration_ellipsoid,
}
#: The result's key for each norm-only method's record of its run.
NORM_ONLY_KEYS = {"ckf": "ckf", "two-step": "two_step"}

NOISY_ELLIPSOID_WARNING = (
    "the ellipsoid fit reached the edge of positive definiteness although the data cover "
    "all orientations: the magnetometer is very noisy for its field. The initial estimate "
    "was regularised towards a sphere; the ML step refines it, but check the result's "
    "normalised innovations and field norm"
)

#: Robust RMS of ‖y_a‖ − g (m/s²) above which the inclination from the accelerometer, and
#: with it the misalignment between magnetometer and inertial axes, cannot be trusted. A
#: random acceleration shows about 1/√3 of its size in the norm, so 0.3 m/s² here is
#: ≈0.5 m/s² of acceleration: the gravity direction off by ≈3° RMS.
MAX_TRUSTED_ACC_DEVIATION_RMS_M_S2 = 0.3


@dataclass(frozen=True)
class Calibration:
    """A result and what a person wants to look at next to it."""

    result: CalibrationResult
    init: InitialEstimate
    ml: MLEstimate | None
    filter_output: mekf.FilterOutput  # on every row of the session
    calibrated: np.ndarray  # (N, 3) D⁻¹(y − o), unit norm when good; NaN rows without a sample


def _filter_at(session: Session, init: InitialEstimate, p: ModelParams) -> mekf.FilterOutput:
    """The ML step's filter (normalised as from ``init``) at ``p``, starting from the
    attitude ``p`` gives."""
    return LikelihoodProblem.for_ml_step(session, init, at=p).run_filter_raw(p)


def _on_every_row(session: Session, init: InitialEstimate) -> InitialEstimate:
    """The initial estimate (made at the magnetometer's rows) for the filter on every row
    of a multi-rate session: the sensor levels and noise covariances measured per stream at
    its own rate; calibration and dip unchanged."""
    levels = measure_sensor_levels(session)
    params = dataclasses.replace(
        init.params,
        gyro_bias=levels.noise.gyro_bias,
        Sigma_gyr=levels.noise.Sigma_gyr,
        Sigma_acc=levels.Sigma_acc,
        Sigma_mag=levels.noise.Sigma_mag,
    )
    return dataclasses.replace(init, params=params, levels=levels)


def _other_starting_points(view: Session, init: InitialEstimate) -> list[tuple[str, ModelParams]]:
    """Where else the ML step starts from, to check that its optimum is the best the
    method's starting points reach: the initial estimate with its ellipsoid from TWO-STEP,
    the norm-only fit, in place of the SDP's (and the alignment and dip that go with it,
    from the initial estimate's own inertial attitude). None where TWO-STEP has no
    ellipsoid for the data."""
    try:
        fit, _ = twostep.calibration_ellipsoid(view.mag, force=True)
        p = with_ellipsoid(view, init, fit)
    except MagcalError:
        return []
    return [("the TWO-STEP fit", p)]


def _without_changed_field(
    session: Session, view: Session
) -> tuple[Session, Session, dict | None, list[str]]:
    """The session and its view without the magnetometer's readings where the field changed
    (``consistency.field_change``), what was left out for the result, and the warning; the
    same objects when the field was constant. Raises :class:`FieldChangedError` when the
    constant part is less than ``consistency.MIN_CONSTANT_FRACTION`` of the session."""
    try:
        change = consistency.field_change(view.t, view.mag)
    except MagcalError:  # no plain fit of these data: the checks that follow say why
        return session, view, None, []
    if not change.changed:
        return session, view, None, []
    margin = consistency.CHANGE_MARGIN_S
    spans = [
        (view.t[0] + a - margin, view.t[0] + b + margin)
        for a, b in consistency.merged_spans(change.changed)
    ]
    left_out = sum(int(((view.t >= a) & (view.t <= b)).sum()) for a, b in spans) / view.t.size
    if 1.0 - left_out < consistency.MIN_CONSTANT_FRACTION:
        raise FieldChangedError(
            f"{change.describe()}; the field was constant for only {100 * (1 - left_out):.0f} % "
            "of the magnetometer's samples, too little to tell which field the sensor is in "
            f"(at least {100 * consistency.MIN_CONSTANT_FRACTION:.0f} % needed to calibrate on "
            "the constant part): record again away from it; --force calibrates on all of it"
        )
    session = samples.without_magnetometer_between(session, spans)
    record = {
        "left_out_s": [[max(a - view.t[0], 0.0), b - view.t[0]] for a, b in spans],
        "left_out_fraction": left_out,
        **change.figures(),
    }
    warning = (
        f"{change.describe()}; calibrated without the magnetometer's readings there "
        f"({100 * left_out:.0f} % of them); --force calibrates on all of it"
    )
    return session, samples.at_magnetometer_rows(session), record, [warning]


def _alignment_warnings(session: Session, g: float) -> list[str]:
    dev = np.linalg.norm(session.acc, axis=1) - g
    # A robust spread (1.4826 × median |dev| equals the RMS for Gaussian deviations): a
    # few knocks must not raise this warning; they are handled as outliers.
    rms = float(1.4826 * np.median(np.abs(dev)))
    if rms > MAX_TRUSTED_ACC_DEVIATION_RMS_M_S2:
        return [
            "accelerations too large to trust the inclination (robust RMS of ‖acc‖ − g = "
            f"{rms:.2f} m/s², limit {MAX_TRUSTED_ACC_DEVIATION_RMS_M_S2} m/s²): the "
            "misalignment between magnetometer and inertial axes is poorly determined; "
            "rotate more slowly"
        ]
    return []


def calibrate(
    session: Session,
    method: str = "ml",
    *,
    force: bool = False,
    gradient: str = "exact",
    options: OptimizeOptions = OptimizeOptions(),
    progress: Callable[[int, float, float], None] | None = None,
    priors: Priors = Priors(),
    optimizer: str = OPTIMIZERS[0],
    stage: Callable[[str], None] | None = None,
    declared_units: units.SessionUnits = units.SessionUnits(),
    max_fit_residual: float = consistency.MAX_FIT_RESIDUAL,
) -> Calibration:
    """Calibrate a session with ``method``: "ml" (Algorithm 1), "init" (its step 1), "ckf"
    or "two-step" (the ellipsoid from the field norm alone, then step 1's alignment: see
    :data:`NORM_ONLY`). ``optimizer``: the ML step's (``likelihood.ml.OPTIMIZERS``).
    ``stage(text)`` is told as each step starts; ``progress`` at each ML iteration.
    ``declared_units``: the units the session's columns were given in (converted first; the
    others are checked against physics, ``diagnostics.units``). ``max_fit_residual``: the
    absolute gate on the corrected field's strength (``consistency.MAX_FIT_RESIDUAL``)."""

    def announce(text: str) -> None:
        if stage:
            stage(text)

    if method not in METHODS:
        raise MagcalError(f"unknown method {method!r}: choose one of {', '.join(METHODS)}")
    if not session.has_acc.any():
        raise MagcalError("the session has no accelerometer sample: record the accelerometer")
    session = units.checked_session(session, declared_units)
    seconds = {}
    session, mag_samples = samples.drop_magnetometer_glitches(session)
    # Everything that works per magnetometer sample sees this view (the session itself
    # when every row has every sensor).
    view = samples.at_magnetometer_rows(session)
    t0 = time.perf_counter()
    announce("checking what the session can determine")
    report = observability.check_observability(view.gyr, view.acc, view.mag, view.t)
    flight = session.meta.get("motion") == "flight"
    warnings = observability.raise_if_unobservable(report, force, flight)
    field_left_out = None
    if not force:  # forced, all of it is used, and the result's checks name the change
        session, view, field_left_out, cut = _without_changed_field(session, view)
        if cut:  # what is left must still determine the calibration
            report = observability.check_observability(view.gyr, view.acc, view.mag, view.t)
            warnings = observability.raise_if_unobservable(report, force, flight) + cut
    seconds["checks"] = time.perf_counter() - t0

    # Past the checks (or forced), a degenerate ellipsoid is fitted regardless, with a
    # warning. When the data do cover the sphere, degeneracy comes from noise, not from
    # too little rotation: say that instead of the fit's own advice to rotate more.
    t0 = time.perf_counter()
    method_record = None
    announce(f"ellipsoid fit ({'SDP' if method not in NORM_ONLY else method.upper()})")
    if method in NORM_ONLY:
        # These report degenerate data themselves; --force has already passed the checks.
        fit, method_record = NORM_ONLY[method](view.mag, force=force)
        seconds[method] = time.perf_counter() - t0
    else:
        fit = fit_ellipsoid_sdp(view.mag, force=True)
        seconds["ellipsoid"] = time.perf_counter() - t0
        if report.ok and fit.warnings:
            fit = dataclasses.replace(fit, warnings=(NOISY_ELLIPSOID_WARNING,))

    announce("the initial estimate: noise levels, alignment with the accelerometer, dip")
    init = initial_estimate(view, fit)
    seconds.update(init.seconds)
    warnings += list(init.warnings)
    warnings += _alignment_warnings(view, init.levels.g)
    if view is not session:
        init = _on_every_row(session, init)
    if mag_samples.warning():
        warnings.append(mag_samples.warning())

    extra: dict = {
        "initial": {
            "D": init.params.D,
            "o": init.params.o,
            "dip_deg": float(np.rad2deg(init.params.dip_rad)),
            "noise_source": init.levels.noise.source,
        },
        "observability": {
            "gravity_eigenvalues": report.gravity_eigenvalues,
            "mag_eig_ratio": report.mag_eig_ratio,
            "total_rotation_rad": report.total_rotation_rad,
        },
        "magnetometer_samples": mag_samples.as_dict(),
        "input_units": declared_units.as_dict(),
    }
    if field_left_out is not None:
        extra["field_left_out"] = field_left_out
    if method_record is not None:
        extra[NORM_ONLY_KEYS[method]] = method_record
    est = None
    if method == "ml":
        t0 = time.perf_counter()
        est = maximum_likelihood(
            session,
            init,
            gradient,
            options,
            progress,
            priors,
            optimizer,
            # Found on the second thread, beside the first fit.
            other_starts=lambda: _other_starting_points(view, init),
            stage=stage,
        )
        seconds["ml"] = time.perf_counter() - t0
        p = est.params
        r = est.report
        extra["priors"] = priors.as_dict()
        extra["time_offset_s"] = p.time_offset_s
        if est.time_offset_test is not None:
            extra["time_offset_test"] = est.time_offset_test.as_dict()
        extra["gyro_gain_error"] = p.gyro_gain_error
        if est.gyro_gain_test is not None:
            extra["gyro_gain_test"] = est.gyro_gain_test.as_dict()
        extra["optimizer"] = {
            "method": optimizer,
            "gradient": gradient,
            "iterations": r.iterations,
            "information_evaluations": r.information_evaluations,
            "cost_evaluations": r.cost_evaluations,
            "gradient_evaluations": r.gradient_evaluations,
            "final_cost": r.cost,
            "stopping_rule": r.stopping_rule,
            "hessian_resets": r.hessian_resets,
            "seconds": r.seconds,
        }
        extra["starting_points"] = [sp.as_dict() for sp in est.starting_points]
        different = est.different_optima()
        if different:
            best, worst = different
            warnings.append(
                f"the ML fits from {best.name} and from {worst.name} ended in clearly "
                f"different optima (negative log-likelihood {best.cost:.1f} against "
                f"{worst.cost:.1f}): the calibration goes on from the better one, {best.name}, "
                "but the session may admit more than one calibration; record again turning "
                "the sensor through every orientation, or check the result against a known "
                "heading"
            )
        if not r.converged:
            warnings.append(
                f"the ML optimisation stopped on '{r.stopping_rule}' before converging after "
                f"{r.iterations} iterations: the estimate may be improvable"
            )
    else:
        p = init.params

    t0 = time.perf_counter()
    announce("checking the result against its session")
    out = _filter_at(session, init, p)
    calibrated = np.linalg.solve(p.D, (session.mag - p.o).T).T
    view_rows = session.has_mag
    seconds["diagnostics"] = time.perf_counter() - t0
    extra["Sigma_gyr"] = p.Sigma_gyr
    extra["Sigma_acc"] = p.Sigma_acc
    extra["Sigma_mag"] = p.Sigma_mag
    # V(θ̂) of eq. (6) alone; the optimiser's final_cost also holds the gyro-noise prior.
    extra["negative_log_likelihood"] = out.cost
    extra["innovations"] = quality.innovation_stats(out.present_normalised()).as_dict()
    extra["field_norm"] = {
        "before": quality.norm_stats(view.mag),
        "after": quality.norm_stats(calibrated[view_rows]),
    }
    extra["seconds"] = seconds
    # D and o are in the session's magnetometer unit; saying which lets `magcal flash` turn
    # them into device counts without being told again.
    if session.meta.get("mag_unit"):
        extra["mag_unit"] = session.meta["mag_unit"]
    # The session's metadata travels with the result: flash --mavlink needs the compass
    # parameters that were in force while it was recorded (the frame D and o live in).
    if session.meta:
        extra["session_meta"] = {str(k): str(v) for k, v in session.meta.items()}

    # The same checks of the result against its own session for every method.
    t0 = time.perf_counter()
    checks = consistency.check(
        view.t,
        view.acc,
        view.mag,
        p.D,
        p.o,
        p.gyro_bias,
        None if method_record is None else np.asarray(method_record["A"]),
        session_fit=None if method in NORM_ONLY else fit,
        gyr=view.gyr,
        max_fit_residual=max_fit_residual,
    )
    seconds["consistency"] = time.perf_counter() - t0
    extra["consistency"] = checks.figures
    warnings += consistency.refusals_or_warnings(checks, method, force)

    result = CalibrationResult(
        method=method,
        D=p.D,
        o=p.o,
        m_n=p.m_n,
        dip_deg=float(np.rad2deg(p.dip_rad)),
        gyro_bias=p.gyro_bias,
        warnings=warnings,
        extra=extra,
    )
    return Calibration(result=result, init=init, ml=est, filter_output=out, calibrated=calibrated)
