"""A given calibration evaluated on a session: the ML cost's filter, field norms, inclination.

The calibration is *fixed* here (nothing is estimated): this is what a report shows for the
session a result was fitted on and for a second, validation session.

* :func:`likelihood_problem` sets up the ML cost V(θ) of eq. (6) at a result's parameters on
  a session, with the same data-only ingredients ``ml.py`` used (gravity magnitude,
  accelerometer outlier inflation, gyroscope noise prior). Only the magnetometer
  normalisation differs (centred on the result's ``o``, divided by ``|det D|^⅓``, instead of
  the initial estimate's): V changes by a constant and θ by an affine map, so gradients and
  curvature carry over exactly.
* :func:`inclination_dip_deg` is the dip angle each sample implies, a heading-free check of a
  calibration against the accelerometer: a good one gives the same angle at every
  orientation.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from magcal.calib.initial import rest
from magcal.calib.initial.estimate import starting_attitude
from magcal.calib.likelihood import mekf, params
from magcal.calib.likelihood.ml import Normalisation, gyro_noise_prior, parameter_scales
from magcal.calib.likelihood.params import ModelParams
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
    """The ML model of a result: D, o, dip, gyro bias and the three noise covariances.

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
    )


@dataclass(frozen=True)
class LikelihoodProblem:
    """The ML cost at a result's parameters on one session.

    data             : the filter's input, magnetometer normalised by ``norm``
    norm             : y' = (y − centre) / scale
    theta            : (34,) the result's parameters in the normalised units (params.py)
    scales           : (34,) rough 1-σ uncertainty of each θ component (``ml.parameter_scales``)
    prior_mean       : (34,) mean of the gyroscope noise prior ML used
    prior_precision  : (34,) its diagonal precision (zero outside the gyroscope noise)
    """

    data: mekf.FilterData
    norm: Normalisation
    theta: np.ndarray
    scales: np.ndarray
    prior_mean: np.ndarray
    prior_precision: np.ndarray

    @property
    def n_samples(self) -> int:
        return len(self.data)


def likelihood_problem(session: Session, p: ModelParams) -> LikelihoodProblem:
    """Set up V(θ) at ``p`` (raw magnetometer units) on ``session``.

    The data-only parts are computed as ``initial.initial_estimate`` computes them for the
    ML step: gravity magnitude (median accelerometer norm), the bump inflation of Σ_a with
    the accelerometer noise of the stationary stretch (or the prior), and the gyroscope
    noise prior centred on its measurement.
    """
    still = rest.find_stationary(session.t, session.gyr, session.acc, session.mag)
    noise = rest.initial_noise_and_bias(session.t, session.gyr, session.acc, session.mag, still)
    g = float(np.median(np.linalg.norm(session.acc, axis=1)))
    rate_hz = (len(session) - 1) / float(session.t[-1] - session.t[0])
    sigma_acc = float(np.sqrt(np.trace(noise.Sigma_acc) / 3.0))
    acc_extra_var = mekf.accelerometer_extra_variance(session.acc, g, sigma_acc, rate_hz)

    norm = Normalisation(
        centre=np.asarray(p.o, dtype=float).copy(),
        scale=float(abs(np.linalg.det(p.D)) ** (1.0 / 3.0)),
    )
    p_norm = p.scaled_magnetometer(norm.centre, norm.scale)
    mag_n = norm.apply(session.mag)
    q0 = starting_attitude(session.acc, mag_n, p_norm)
    data = mekf.make_filter_data(
        session.t, session.gyr, session.acc, mag_n, q0, acc_extra_var=acc_extra_var, g=g
    )
    theta = params.pack(p_norm)
    # The prior is centred on the gyroscope noise as measured, as in ml.maximum_likelihood.
    measured = theta.copy()
    measured[params.SLICE_CHOL_GYR] = params.cov_to_chol_params(noise.Sigma_gyr)
    n_still = 0 if still is None else still.stop - still.start
    prior_mean, prior_precision = gyro_noise_prior(measured, n_still)
    return LikelihoodProblem(
        data=data,
        norm=norm,
        theta=theta,
        scales=parameter_scales(p_norm, len(data)),
        prior_mean=prior_mean,
        prior_precision=prior_precision,
    )


def run_filter_at(session: Session, p: ModelParams) -> mekf.FilterOutput:
    """The ML filter at ``p`` on ``session``: innovations and normalised innovations."""
    problem = likelihood_problem(session, p)
    return mekf.run_filter(params.unpack(problem.theta), problem.data)


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
