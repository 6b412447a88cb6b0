"""Algorithm 1, step 1: the initial estimate θ₀ (paper Section 6).

a. gyro bias and noise covariances (``rest.py``): from a detected stationary
   stretch, or conservative priors when there is none;
b. ellipsoid fit as an SDP (``ellipsoid.py``) → ``o``, ``D̃``;
c. misalignment ``R_D`` and ``m_z`` (``alignment.py``) using the inclination from the
   inertial-only EKF (``mekf.py`` with the magnetometer switched off).

Everything here works in raw magnetometer units; ``ml.py`` normalises.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from magcal.calib import frames
from magcal.calib.initial import rest
from magcal.calib.initial.alignment import Alignment, acceleration_weights, estimate_alignment
from magcal.calib.initial.ellipsoid import EllipsoidFit, fit_ellipsoid_sdp
from magcal.calib.likelihood import mekf
from magcal.calib.likelihood.params import ModelParams
from magcal.io.session import Session

#: Samples averaged for the starting attitude of a filter (≈ 0.05 s at 100 Hz): enough to
#: average noise, short enough that motion at the start does not smear it.
INITIAL_ATTITUDE_SAMPLES = 5


@dataclass(frozen=True)
class InitialEstimate:
    """θ₀ in model form (raw magnetometer units) and what produced it."""

    params: ModelParams
    ellipsoid: EllipsoidFit
    alignment: Alignment
    noise: rest.NoiseInit
    g: float
    acc_extra_var: np.ndarray
    seconds: dict = field(default_factory=dict)
    warnings: tuple[str, ...] = ()


def starting_attitude(acc: np.ndarray, mag: np.ndarray, p: ModelParams) -> np.ndarray:
    """q_nb at sample 0 by TRIAD from the first few samples and calibration ``p``."""
    k = min(INITIAL_ATTITUDE_SAMPLES, acc.shape[0])
    up_b = acc[:k].mean(axis=0)
    field_b = np.linalg.solve(p.D, mag[:k].mean(axis=0) - p.o)
    return frames.triad(up_b, field_b, p.m_n)


def inertial_attitude(
    session: Session, noise: rest.NoiseInit, g: float, acc_extra_var: np.ndarray
) -> np.ndarray:
    """(N, 4) attitude from gyro + accelerometer only (heading free, inclination good)."""
    k = min(INITIAL_ATTITUDE_SAMPLES, len(session))
    up_b = session.acc[:k].mean(axis=0)
    # Any heading will do: pick the one that makes body x horizontal-ish and well defined.
    helper = (
        np.array([1.0, 0.0, 0.0]) if abs(up_b[0]) < 0.9 * np.linalg.norm(up_b) else np.eye(3)[1]
    )
    q0 = frames.triad(up_b, helper, np.array([1.0, 0.0, 0.0]))
    data = mekf.make_filter_data(
        session.t, session.gyr, session.acc, session.mag, q0, acc_extra_var=acc_extra_var, g=g
    )
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
    still = rest.find_stationary(session.t, session.gyr, session.acc, session.mag)
    noise = rest.initial_noise_and_bias(session.t, session.gyr, session.acc, session.mag, still)
    g = float(np.median(np.linalg.norm(session.acc, axis=1)))
    rate_hz = (len(session) - 1) / float(session.t[-1] - session.t[0])
    sigma_acc = float(np.sqrt(np.trace(noise.Sigma_acc) / 3.0))
    acc_extra_var = mekf.accelerometer_extra_variance(session.acc, g, sigma_acc, rate_hz)
    # The ML step starts with e_a as sensor noise plus the acceleration of the motion (its
    # share on top of the noise measured at rest, isotropic). The inertial attitude below
    # keeps the noise alone: it down-weights accelerated samples itself, and with the
    # larger Σ_a its misalignment was worse on accelerated MEMS sessions (`make accuracy`,
    # init 0.11° → 0.16°) though better on hand-held ones (1.19° → 0.89°).
    shake = rest.motion_acceleration_variance(session.acc, g, noise.stationary)
    Sigma_acc = noise.Sigma_acc + max(0.0, shake - sigma_acc**2) * np.eye(3)
    seconds["noise"] = time.perf_counter() - t0

    if fit is None:
        t0 = time.perf_counter()
        fit = fit_ellipsoid_sdp(session.mag)
        seconds["ellipsoid"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    q_inertial = inertial_attitude(session, noise, g, acc_extra_var)
    weights = acceleration_weights(session.acc, g=g)
    alignment = estimate_alignment(session.mag, fit.o, fit.D_tilde, q_inertial, weights)
    seconds["alignment"] = time.perf_counter() - t0

    params = ModelParams(
        D=alignment.D0,
        o=fit.o,
        dip_rad=alignment.dip_rad,
        gyro_bias=noise.gyro_bias,
        Sigma_gyr=noise.Sigma_gyr,
        Sigma_acc=Sigma_acc,
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
        noise=noise,
        g=g,
        acc_extra_var=acc_extra_var,
        seconds=seconds,
        warnings=tuple(warnings),
    )
