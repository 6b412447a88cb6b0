# SPDX-License-Identifier: Apache-2.0
"""A given calibration evaluated on a session: the ML cost's filter, field norms, inclination.

The calibration is *fixed* here (nothing is estimated): this is what a report shows for the
session a result was fitted on and for a second, validation session.

* :func:`model_params_from_result` is a result's ML model (D, o, dip, gyroscope bias, noise
  covariances); ``likelihood.problem.LikelihoodProblem.at_parameters`` sets up the ML cost
  there, and :func:`run_filter_at` runs its filter.
* :func:`inclination_dip_deg` is the dip angle each sample implies, a heading-free check of a
  calibration against the accelerometer: a good one gives the same angle at every
  orientation.
"""

from __future__ import annotations

import numpy as np

from magcal.calib.likelihood import mekf
from magcal.calib.likelihood.params import ModelParams
from magcal.calib.likelihood.problem import LikelihoodProblem
from magcal.errors import MagcalError
from magcal.io.result import CalibrationResult
from magcal.io.session import Session

#: Samples whose accelerometer norm is further than this from gravity do not measure the
#: inclination (the hand's acceleration tilts "up"), m/s². 0.5 m/s² tilts it by < 3°.
INCLINATION_ACC_TOL_M_S2 = 0.5
#: The result keys holding the noise covariances the filter needs, with their units.
NOISE_KEYS = (
    ("Sigma_gyr", "(rad/s)²"),
    ("Sigma_acc", "(m/s²)²"),
    ("Sigma_mag", "magnetometer units²"),
)


class ModelUnavailableError(MagcalError):
    """A result lacks what the ML filter needs (a method that does not estimate the noise
    covariances or the gyroscope bias)."""


def model_params_from_result(result: CalibrationResult) -> ModelParams:
    """The ML model of a result: D, o, dip, gyro bias, the three noise covariances, the time
    offset and the gyroscope gain error the filter allowed for (0 for results without).

    Raises :class:`ModelUnavailableError` naming what is missing or unusable.
    """
    if result.gyro_bias is None:
        raise ModelUnavailableError(
            f"the result (method {result.method!r}) has no gyroscope bias, which the ML filter "
            "needs: calibrate with --method ml or init"
        )
    covariances = {}
    for key, unit in NOISE_KEYS:
        value = result.extra.get(key)
        if value is None:
            raise ModelUnavailableError(
                f"the result (method {result.method!r}) has no noise covariance {key} "
                f"({unit}), which the ML filter needs: calibrate with --method ml or init"
            )
        try:
            cov = np.array(value, dtype=float)
        except (TypeError, ValueError):
            cov = np.full((0,), np.nan)
        if cov.shape != (3, 3) or not np.isfinite(cov).all():
            raise ModelUnavailableError(
                f"the result's {key} must be a 3×3 matrix of numbers ({unit}), got {value!r}"
            )
        try:
            np.linalg.cholesky(cov)
        except np.linalg.LinAlgError:
            raise ModelUnavailableError(
                f"the result's {key} is not positive definite: {cov.tolist()}; the file was "
                "edited or corrupted: recalibrate"
            ) from None
        covariances[key] = cov
    return ModelParams(
        D=np.array(result.D),
        o=np.array(result.o),
        dip_rad=float(np.deg2rad(result.dip_deg)),
        gyro_bias=np.array(result.gyro_bias),
        **covariances,
        time_offset_s=float(result.extra.get("time_offset_s", 0.0)),
        gyro_gain_error=float(result.extra.get("gyro_gain_error", 0.0)),
    )


def run_filter_at(session: Session, p: ModelParams) -> mekf.FilterOutput:
    """The ML filter at ``p`` on ``session``: innovations and normalised innovations.

    The problem is set up at ``p`` itself (``LikelihoodProblem.at_parameters``): the
    magnetometer centred on its o and divided by its ``|det D|^⅓``, with the data-only
    levels measured on the session as for the ML step.
    """
    problem = LikelihoodProblem.at_parameters(session, p)
    return problem.run_filter(problem.theta0)


def inclination_dip_deg(
    acc: np.ndarray, field_b: np.ndarray, g: float | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Dip angle (degrees, positive down) at each sample where the accelerometer reads
    gravity alone, from the angle between the field and "up".

    acc     : (N, 3) m/s², specific force (≈ up · g at rest)
    field_b : (N, 3) field in the accelerometer's frame, any scale (calibrated: D⁻¹(y − o))
    g       : gravity magnitude, m/s²; default the median accelerometer norm
    Returns (dip_deg (K,), used (N,) bool): the samples within
    :data:`INCLINATION_ACC_TOL_M_S2` of ``g``.

    With n z-up and ``m_n = (cos δ, 0, −sin δ)``: ``up_b · m_b = −sin δ``.
    """
    acc = np.asarray(acc, dtype=float)
    field_b = np.asarray(field_b, dtype=float)
    acc_norm = np.linalg.norm(acc, axis=1)
    field_norm = np.linalg.norm(field_b, axis=1)
    if g is None:
        g = float(np.median(acc_norm))
    used = (np.abs(acc_norm - g) <= INCLINATION_ACC_TOL_M_S2) & (field_norm > 0.0)
    cos_angle = np.einsum("ij,ij->i", acc[used], field_b[used]) / (
        acc_norm[used] * field_norm[used]
    )
    return np.rad2deg(-np.arcsin(np.clip(cos_angle, -1.0, 1.0))), used
