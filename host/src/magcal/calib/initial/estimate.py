# SPDX-License-Identifier: Apache-2.0
"""Algorithm 1, step 1: the initial estimate θ₀ (paper Section 6).

a. gyro bias and noise covariances (``rest.py``): from a detected stationary
   stretch, or conservative priors when there is none; with them the other data-only
   levels the filter needs (``sensor_levels.py``);
b. ellipsoid fit as an SDP (``ellipsoid.py``) → ``o``, ``D̃``;
c. misalignment ``R_D`` and ``m_z`` (``alignment.py``) using the inclination from the
   inertial-only EKF (``mekf.py`` with the magnetometer switched off).

Everything here works in raw magnetometer units; the likelihood problem
(``likelihood/problem.py``) normalises.
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass, field

import numpy as np

from magcal.calib import frames
from magcal.calib.initial.alignment import Alignment, acceleration_weights, estimate_alignment
from magcal.calib.initial.ellipsoid import EllipsoidFit, fit_ellipsoid_sdp
from magcal.calib.initial.sensor_levels import SensorLevels, measure_sensor_levels
from magcal.calib.likelihood import mekf
from magcal.calib.likelihood.params import ModelParams
from magcal.io.session import Session, site_latitude_deg


@dataclass(frozen=True)
class InitialEstimate:
    """θ₀ in model form (raw magnetometer units) and what produced it.

    ``q_inertial`` (N, 4) and ``acc_weights`` (N,) are step 1c's inputs on the session
    step 1 saw: the inertial-only filter's attitude and each sample's weight by its
    acceleration. They depend on the data alone, so :func:`with_ellipsoid` aligns another
    ellipsoid fit with them without running the filter again."""

    params: ModelParams
    ellipsoid: EllipsoidFit
    alignment: Alignment
    levels: SensorLevels
    seconds: dict = field(default_factory=dict)
    warnings: tuple[str, ...] = ()
    q_inertial: np.ndarray | None = None
    acc_weights: np.ndarray | None = None


def inertial_attitude(session: Session, levels: SensorLevels) -> np.ndarray:
    """(N, 4) attitude from gyro + accelerometer only (heading free, inclination good)."""
    k = min(mekf.INITIAL_ATTITUDE_SAMPLES, len(session))
    up_b = session.acc[:k].mean(axis=0)
    # Any heading will do: pick the one that makes body x horizontal-ish and well defined.
    helper = (
        np.array([1.0, 0.0, 0.0]) if abs(up_b[0]) < 0.9 * np.linalg.norm(up_b) else np.eye(3)[1]
    )
    q0 = frames.triad(up_b, helper, np.array([1.0, 0.0, 0.0]))
    data = mekf.make_filter_data(
        session.t,
        session.gyr,
        session.acc,
        session.mag,
        q0,
        acc_extra_var=levels.acc_extra_var,
        g=levels.g,
    )
    # The accelerometer noise alone, without the motion's share the ML step adds
    # (see ``sensor_levels.measure_sensor_levels``).
    noise = levels.noise
    p = ModelParams(
        D=np.eye(3),
        o=np.zeros(3),
        dip_rad=0.0,
        gyro_bias=noise.gyro_bias,
        Sigma_gyr=noise.Sigma_gyr,
        Sigma_acc=noise.Sigma_acc,
        Sigma_mag=np.eye(3),
    )
    return mekf.run_filter(p, data, use_mag=False).q_filt


def initial_estimate(session: Session, fit: EllipsoidFit | None = None) -> InitialEstimate:
    """Algorithm 1 step 1 on a whole session. ``fit`` is step 1b's result when the caller
    has it already (the pipeline fits before, to judge it); otherwise it is fitted here and
    raises on data that cannot determine it."""
    seconds = {}
    t0 = time.perf_counter()
    levels = measure_sensor_levels(session)
    noise = levels.noise
    seconds["noise"] = time.perf_counter() - t0

    if fit is None:
        t0 = time.perf_counter()
        fit = fit_ellipsoid_sdp(session.mag)
        seconds["ellipsoid"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    q_inertial = inertial_attitude(session, levels)
    weights = acceleration_weights(session.acc, g=levels.g)
    alignment = _aligned(session, fit, q_inertial, weights)
    seconds["alignment"] = time.perf_counter() - t0

    params = ModelParams(
        D=alignment.D0,
        o=fit.o,
        dip_rad=alignment.dip_rad,
        gyro_bias=noise.gyro_bias,
        Sigma_gyr=noise.Sigma_gyr,
        Sigma_acc=levels.Sigma_acc,
        Sigma_mag=noise.Sigma_mag,
    )
    warnings = list(fit.warnings) + list(alignment.warnings)
    if noise.source == "prior":
        warnings.append(
            "no stationary stretch found: gyro bias and noise levels start from conservative "
            "priors and are estimated by the ML step"
        )
    return InitialEstimate(
        params=params,
        ellipsoid=fit,
        alignment=alignment,
        levels=levels,
        seconds=seconds,
        warnings=tuple(warnings),
        q_inertial=q_inertial,
        acc_weights=weights,
    )


def _aligned(
    session: Session, fit: EllipsoidFit, q_inertial: np.ndarray, weights: np.ndarray
) -> Alignment:
    """Step 1c for the ellipsoid ``fit``: misalignment and dip against the inclination of
    the inertial-only attitude ``q_inertial`` (N, 4), samples weighted by ``weights`` (N,)."""
    return estimate_alignment(
        session.mag,
        fit.o,
        fit.D_tilde,
        q_inertial,
        weights,
        site_latitude_deg=site_latitude_deg(session.meta),
    )


def with_ellipsoid(session: Session, init: InitialEstimate, fit: EllipsoidFit) -> ModelParams:
    """``init``'s parameters with another ellipsoid ``fit`` (e.g. a norm-only fit's) in place
    of its own: o from ``fit``, and D and the dip from step 1c redone for it with ``init``'s
    inertial attitude and weights; the noise levels are ``init``'s. The same as
    :func:`initial_estimate` on ``session`` (the session step 1 saw) with ``fit``, without
    measuring the levels or running the inertial filter again."""
    if init.q_inertial is None or init.acc_weights is None:
        other = initial_estimate(session, fit)
        D, dip_rad = other.params.D, other.params.dip_rad
    else:
        alignment = _aligned(session, fit, init.q_inertial, init.acc_weights)
        D, dip_rad = alignment.D0, alignment.dip_rad
    return dataclasses.replace(init.params, D=D, o=fit.o, dip_rad=dip_rad)
