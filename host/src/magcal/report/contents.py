# SPDX-License-Identifier: Apache-2.0
"""What the calibration report shows, computed: the uncertainty, the figures, the validation.

:func:`build_report` applies a result to the session it was calibrated from (and optionally to
a second session, not used for the fit), checks that they belong together, and returns a
:class:`Report` of numbers and PNG figures; ``html.py`` formats it.
"""

from __future__ import annotations

import math
import tempfile
from collections.abc import Callable
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

from magcal.calib import samples
from magcal.calib.diagnostics import quality, replay, uncertainty
from magcal.calib.diagnostics.uncertainty import CalibrationUncertainty
from magcal.errors import CalibrationError, MagcalError
from magcal.io.result import CalibrationResult, apply_correction
from magcal.io.session import Session
from magcal.report import plots

#: The raw field norm a result records (``field_norm.before``) must equal the session's to
#: this relative tolerance, or the result was calibrated from another session. Both are
#: computed from the same CSV numbers, so only the summation order can differ.
SAME_SESSION_RTOL = 1e-9


class ReportError(MagcalError):
    """A report cannot be made: mismatched inputs, an unwritable output."""


@dataclass(frozen=True)
class Figure:
    """A PNG with its title and caption; ``wide`` figures span the page's width."""

    title: str
    caption: str
    png: bytes
    wide: bool = False


@dataclass(frozen=True)
class SessionEvaluation:
    """The result applied to one session (the fit session or a validation session).

    norm_before, norm_after : {"mean", "std"} of ‖y‖ (raw units) and ‖D⁻¹(y − o)‖
    innovations             : statistics of the ML filter's normalised innovations, or None
                              when the result lacks the filter's noise covariances
    dip_raw, dip_calibrated : {"mean", "std", "count"} of the per-sample dip angle (°), or
                              None when no sample has an accelerometer norm close to gravity
    """

    label: str
    path: str
    n_samples: int
    duration_s: float
    rate_hz: float
    meta: dict[str, str]
    norm_before: dict
    norm_after: dict
    innovations: quality.InnovationStats | None
    dip_raw: dict | None
    dip_calibrated: dict | None
    figures: list[Figure]
    notes: list[str] = field(default_factory=list)

    @property
    def spread_before(self) -> float:
        """std/mean of the raw field norm."""
        return self.norm_before["std"] / self.norm_before["mean"]

    @property
    def spread_after(self) -> float:
        return self.norm_after["std"] / self.norm_after["mean"]


@dataclass(frozen=True)
class Report:
    result: CalibrationResult
    result_path: str
    fit: SessionEvaluation
    uncertainty: CalibrationUncertainty | None
    validation: SessionEvaluation | None
    notes: list[str] = field(default_factory=list)
    created: str = ""


# --------------------------------------------------------------------------------------------
# Consistency of the inputs


def _unit_text(unit: str | None) -> str:
    return repr(unit) if unit else "not stated"


def check_units(result: CalibrationResult, session: Session, session_path: str) -> str | None:
    """Raise :class:`ReportError` when the session's ``mag_unit`` differs from the result's;
    a note when either does not state it."""
    unit_result = result.extra.get("mag_unit")
    unit_session = session.meta.get("mag_unit")
    if unit_result and unit_session and unit_result != unit_session:
        raise ReportError(
            f"the result's magnetometer unit is {unit_result!r} but the session "
            f"{session_path} is in {unit_session!r}: D and o do not apply to it; pass a "
            "session recorded in the result's unit"
        )
    if not (unit_result and unit_session):
        return (
            f"magnetometer units could not be compared for {session_path} (result: "
            f"{_unit_text(unit_result)}, session: {_unit_text(unit_session)})"
        )
    return None


def _recorded_norm(result: CalibrationResult) -> dict | None:
    before = result.extra.get("field_norm", {})
    before = before.get("before") if isinstance(before, dict) else None
    if not isinstance(before, dict):
        return None
    values = [before.get("mean"), before.get("std")]
    if not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in values):
        return None
    return {"mean": float(values[0]), "std": float(values[1])}


def _raw_norm(session: Session) -> dict:
    """The raw field norm as the calibration records it: over the magnetometer's samples
    that it used (a multi-rate session's rows without one, and its glitches, left out)."""
    used, _ = samples.drop_magnetometer_glitches(session)
    return quality.norm_stats(used.mag[used.has_mag])


def is_fit_session(result: CalibrationResult, session: Session) -> bool | None:
    """Whether ``session`` is the one the result was calibrated from, by the raw field norm
    the result records; None when it records none."""
    recorded = _recorded_norm(result)
    if recorded is None:
        return None
    got = _raw_norm(session)
    return all(
        math.isclose(got[k], recorded[k], rel_tol=SAME_SESSION_RTOL, abs_tol=0.0)
        for k in ("mean", "std")
    )


def check_fit_session(
    result: CalibrationResult, session: Session, result_path: str, session_path: str
) -> str | None:
    """Raise :class:`ReportError` when the result was calibrated from another session; a
    note when the result records nothing to check it by."""
    same = is_fit_session(result, session)
    if same is None:
        return (
            f"the result {result_path} records no raw field norm (field_norm.before), so it "
            f"could not be checked that it was calibrated from {session_path}"
        )
    if not same:
        recorded = _recorded_norm(result)
        got = _raw_norm(session)
        raise ReportError(
            f"the result {result_path} was not calibrated from the session {session_path}: "
            f"the result records a raw field norm of {recorded['mean']:.6g} ± "
            f"{recorded['std']:.6g}, this session has {got['mean']:.6g} ± {got['std']:.6g}. "
            "Pass the session it was calibrated from; give another session with --validate"
        )
    return None


# --------------------------------------------------------------------------------------------
# Computing the report


def _png(draw: Callable[[Path], Path]) -> bytes:
    with tempfile.TemporaryDirectory(prefix="magcal-report-") as tmp:
        return Path(draw(Path(tmp) / "figure.png")).read_bytes()


def _dip_stats(values: np.ndarray) -> dict:
    return {"mean": float(values.mean()), "std": float(values.std()), "count": int(values.size)}


def evaluate_session(
    result: CalibrationResult, session: Session, path: str, label: str
) -> SessionEvaluation:
    """Apply ``result`` to ``session``: norms, the ML filter's normalised innovations,
    per-sample dip angles, and their figures. The filter runs on every row; the rest is per
    magnetometer sample (a multi-rate session at its magnetometer's rows, glitches left out,
    as the calibration sees it)."""
    full = session
    session = samples.at_magnetometer_rows(samples.drop_magnetometer_glitches(full)[0])
    calibrated = apply_correction(result, session.mag)
    notes = []
    figures = [
        Figure(
            "Ellipsoid and sphere",
            "Raw magnetometer data (red, centred and scaled) and the calibrated field (blue), "
            "which should lie on the unit sphere.",
            _png(lambda p: plots.plot_ellipsoid_sphere(session.mag, calibrated, p)),
        )
    ]
    innovations = None
    try:
        model = replay.model_params_from_result(result)
    except replay.ModelUnavailableError:
        model = None  # build_report notes it once for the whole page
    if model is not None:
        out = replay.run_filter_at(full, model)
        normalised = out.present_normalised()
        if np.isfinite(normalised).all():
            innovations = quality.innovation_stats(normalised)
            figures.append(
                Figure(
                    "Normalised innovations",
                    "One-step prediction errors of the ML filter (accelerometer and "
                    "magnetometer, whitened by their predicted covariance) with the result's "
                    "parameters; a model that fits gives N(0, 1).",
                    _png(
                        lambda p: plots.plot_innovation_histogram(
                            normalised, p, title=f"Normalised innovations, {label}"
                        )
                    ),
                )
            )
        else:
            notes.append(
                f"no innovations: the ML filter with the result's parameters broke down on "
                f"the {label} (non-finite covariances)"
            )
    figures.append(
        Figure(
            "Field norm",
            "The field's magnitude over time before (red, divided by its mean) and after "
            "(blue) calibration; after calibration it should be 1 at every orientation.",
            _png(
                lambda p: plots.plot_norms(
                    session.t,
                    np.linalg.norm(session.mag, axis=1),
                    np.linalg.norm(calibrated, axis=1),
                    p,
                )
            ),
            wide=True,
        )
    )
    dip_raw = dip_cal = None
    raw_dip, used = replay.inclination_dip_deg(session.acc, session.mag)
    if used.any():
        cal_dip, _ = replay.inclination_dip_deg(session.acc, calibrated)
        dip_raw, dip_cal = _dip_stats(raw_dip), _dip_stats(cal_dip)
        figures.append(
            Figure(
                "Inclination consistency",
                "The dip angle between the field and the accelerometer's up at each sample "
                f"whose acceleration norm is within {replay.INCLINATION_ACC_TOL_M_S2} m/s² "
                "of gravity. It does not depend on the heading: a calibration that fits "
                "gives the same angle at every orientation.",
                _png(
                    lambda p: plots.plot_dip_angles(
                        raw_dip, cal_dip, result.dip_deg, p, title=f"Dip angle per sample, {label}"
                    )
                ),
                wide=True,
            )
        )
    else:
        notes.append(
            f"no inclination check on the {label}: no sample has an accelerometer norm within "
            f"{replay.INCLINATION_ACC_TOL_M_S2} m/s² of gravity"
        )
    duration = float(session.t[-1] - session.t[0])
    return SessionEvaluation(
        label=label,
        path=path,
        n_samples=len(session),
        duration_s=duration,
        rate_hz=(len(session) - 1) / duration if duration > 0 else float("nan"),
        meta=dict(session.meta),
        norm_before=quality.norm_stats(session.mag),
        norm_after=quality.norm_stats(calibrated),
        innovations=innovations,
        dip_raw=dip_raw,
        dip_calibrated=dip_cal,
        figures=figures,
        notes=notes,
    )


def build_report(
    result: CalibrationResult,
    session: Session,
    *,
    result_path: str,
    session_path: str,
    validation: Session | None = None,
    validation_path: str | None = None,
    progress: Callable[[str, int, int], None] | None = None,
) -> Report:
    """Everything the page shows. ``progress(stage, done, total)`` is called during the
    Hessian ("hessian", gradient passes done of total) and once before the figures
    ("drawing the figures", 0, 1).

    Raises :class:`ReportError` when the result was not calibrated from ``session`` or a
    session's magnetometer unit differs from the result's.
    """
    notes = []
    for note in (
        check_units(result, session, session_path),
        check_fit_session(result, session, result_path, session_path),
    ):
        if note:
            notes.append(note)
    if validation is not None:
        note = check_units(result, validation, validation_path or "the validation session")
        if note:
            notes.append(note)
        if is_fit_session(result, validation):
            notes.append(
                f"the validation session {validation_path} is the session the result was "
                "calibrated from: its figures are not an independent check"
            )

    unc = None
    try:
        unc = uncertainty.calibration_uncertainty(
            result,
            session,
            progress=(lambda done, total: progress("hessian", done, total)) if progress else None,
        )
    except replay.ModelUnavailableError as exc:
        notes.append(f"no uncertainty and no innovations: {exc}")
    except CalibrationError as exc:  # the filter breaks down at or next to the result
        notes.append(f"no uncertainty: {exc}")
    if unc is not None and result.method != "ml" and not unc.at_minimum:
        # Another method's estimate away from the ML minimum: the cost's curvature there is
        # its shape at that point, not the spread of that estimate, whose error is the
        # step to the minimum, so no σ rather than misleading ones. (An ML result is meant
        # to be the minimum: its non-positive-definite Hessian is reported as not
        # identifiable.)
        curving_down = (
            f", with negative curvature along {'; '.join(unc.null_directions)}"
            if unc.negative_curvature
            else ""
        )
        notes.append(
            f"no uncertainty: the result (method {result.method!r}) is not a minimum of the ML "
            f"cost on this session (a Newton step of {unc.newton_step_sigma:.3g} standard "
            f"deviations away{curving_down}), so its curvature says nothing about the "
            "estimate's spread; calibrate with --method ml for standard deviations"
        )
        unc = None
    if progress:
        progress("drawing the figures", 0, 1)
    fit = evaluate_session(result, session, session_path, "fit session")
    val = None
    if validation is not None:
        val = evaluate_session(
            result, validation, validation_path or "validation session", "validation session"
        )
    notes += fit.notes + (val.notes if val else [])
    created = datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    return Report(
        result=result,
        result_path=result_path,
        fit=fit,
        uncertainty=unc,
        validation=val,
        notes=notes,
        created=created,
    )
