# SPDX-License-Identifier: Apache-2.0
"""What the attitude-independent methods (``ckf.py``, ``twostep.py``) share.

Both estimate the ellipsoid on which the raw readings lie,

    ‖T (y − b)‖ = 1,   A = Tᵀ T  (symmetric positive definite),

from the constant field norm alone (no gyroscope, no accelerometer). ``T`` is then the
symmetric square root of ``A`` (Zhao et al. eq. 19–20): the correction
``D_sym⁻¹ (y − b)`` with ``D_sym = T⁻¹``, which cannot see the rotation between the
magnetometer and the inertial axes. To give a full ``D``, ``o`` like Algorithm 1, the
ellipsoid is handed to the same alignment step as the initial estimate
(:func:`magcal.calib.initial.estimate.initial_estimate`, which runs ``align.py``) in the form of an
:class:`~magcal.calib.initial.ellipsoid.EllipsoidFit` (:func:`ellipsoid_fit_from`).

Units: ``A`` in (raw magnetometer units)⁻², ``b`` in raw units, the field norm is 1.
"""

from __future__ import annotations

import numpy as np

from magcal.calib.initial import ellipsoid
from magcal.calib.initial.ellipsoid import EllipsoidFit
from magcal.errors import CalibrationError, InsufficientDataError

#: Eigenvalues of ``A`` are floored at this fraction of the largest before taking ``T``: only
#: a forced fit on degenerate data comes near it (with a warning).
MIN_A_EIG_FRACTION = 1e-8
#: Fewest samples the attitude-independent methods accept (as the ellipsoid fit).
MIN_SAMPLES = ellipsoid.MIN_SAMPLES


def check_readings(mag: np.ndarray, who: str) -> np.ndarray:
    """``mag`` as an (N, 3) float array of finite values; raises naming ``who``."""
    mag = np.asarray(mag, dtype=float)
    if mag.ndim != 2 or mag.shape[1] != 3:
        raise ValueError(f"{who}: mag must have shape (N, 3), got {mag.shape}")
    if mag.shape[0] < MIN_SAMPLES:
        raise InsufficientDataError(
            f"{who}: {mag.shape[0]} magnetometer samples; at least {MIN_SAMPLES} are needed "
            "(in practice thousands): record longer while rotating the sensor"
        )
    if not np.all(np.isfinite(mag)):
        raise CalibrationError(
            f"{who}: the magnetometer data contain NaN or infinite values: remove or "
            "interpolate the bad samples first"
        )
    return mag


def planarity_problem(mag: np.ndarray, who: str) -> str | None:
    """A message if the readings (N, 3) lie close to a plane or a line, by the ellipsoid fit's
    own criterion (:data:`magcal.calib.initial.ellipsoid.MIN_DATA_EIG_RATIO`), else None."""
    eig = np.linalg.eigvalsh(np.cov(np.asarray(mag, dtype=float), rowvar=False))
    if eig[-1] > 0.0 and eig[0] >= ellipsoid.MIN_DATA_EIG_RATIO * eig[-1]:
        return None
    ratio = eig[0] / eig[-1] if eig[-1] > 0.0 else 0.0
    return (
        f"{who}: the magnetometer data lie close to a plane or a line (covariance eigenvalue "
        f"ratio {ratio:.2g} < {ellipsoid.MIN_DATA_EIG_RATIO:g}), which many ellipsoids fit "
        "equally well: the sensor was rotated too little; rotate it through all orientations "
        "(tilt it nose up/down and roll it over, not only yaw)"
    )


def symmetric_root(A: np.ndarray) -> tuple[np.ndarray, bool]:
    """``T = Q √Σ Qᵀ`` from ``A = Q Σ Qᵀ`` (Zhao et al. eq. 19–20), (3, 3).

    Returns ``(T, clipped)``: eigenvalues below :data:`MIN_A_EIG_FRACTION` of the largest
    (``A`` not positive definite: possible only on data that do not determine the ellipsoid)
    are raised to it, and ``clipped`` says so.
    """
    A = 0.5 * (np.asarray(A, dtype=float) + np.asarray(A, dtype=float).T)
    lam, Q = np.linalg.eigh(A)
    if not lam[-1] > 0.0:
        raise CalibrationError(
            "the estimated ellipsoid has no positive axis (A is negative semidefinite): the "
            "data do not determine a calibration; rotate the sensor through all orientations"
        )
    floor = MIN_A_EIG_FRACTION * lam[-1]
    clipped = bool(lam[0] < floor)
    lam = np.maximum(lam, floor)
    return (Q * np.sqrt(lam)) @ Q.T, clipped


def ellipsoid_fit_from(
    A: np.ndarray, b: np.ndarray, mag: np.ndarray, method: str, warnings: tuple[str, ...] = ()
) -> EllipsoidFit:
    """The ellipsoid ``(y − b)ᵀ A (y − b) = 1`` as Algorithm 1's step 1b would give it.

    A    : (3, 3) float, (raw units)⁻², symmetric positive definite (made so if need be)
    b    : (3,) float, raw units, the centre (hard-iron offset)
    mag  : (N, 3) float, raw units, the data (for ``radius_rms``)
    method : name recorded in the fit ("ckf", "two-step")

    Returns an EllipsoidFit: ``o = b``, ``D̃`` lower-triangular with ``D̃ D̃ᵀ = A⁻¹`` (the
    ``D Dᵀ`` of the model), the quadric ``yᵀA'y + b'ᵀy + c' = 0`` scaled to ``tr A' = 1``.
    """
    T, clipped = symmetric_root(A)
    A = T @ T  # the (possibly floored) A, exactly symmetric
    b = np.asarray(b, dtype=float)
    dd = np.linalg.inv(T)
    dd = dd @ dd  # A⁻¹ = D Dᵀ
    D_tilde = np.linalg.cholesky(0.5 * (dd + dd.T))
    tr = float(np.trace(A))
    calibrated = (np.asarray(mag, dtype=float) - b) @ T  # T symmetric: rows T (y − b)
    radius_rms = float(np.sqrt(np.mean((np.linalg.norm(calibrated, axis=1) - 1.0) ** 2)))
    eig = np.linalg.eigvalsh(A)
    notes = list(warnings)
    if clipped:
        notes.append(
            f"{method}: the estimated ellipsoid was not positive definite and was clipped: the "
            "data do not determine the calibration in every direction; rotate the sensor "
            "through all orientations"
        )
    return EllipsoidFit(
        A=A / tr,
        b=-2.0 * (A @ b) / tr,
        c=float(b @ A @ b - 1.0) / tr,
        o=b.copy(),
        D_tilde=D_tilde,
        method=method,
        radius_rms=radius_rms,
        a_eig_ratio=float(eig[0] / eig[-1]),
        warnings=tuple(notes),
    )
