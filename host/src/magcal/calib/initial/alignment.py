# SPDX-License-Identifier: Apache-2.0
"""Step 1c of Kok & Schön (2016), Section 6.2: magnetometer-to-inertial misalignment.

The ellipsoid fit gives ``D̃`` with ``D = D̃ R_D`` for an unknown rotation ``R_D``. The body-
frame field ``m_b,t = R_Dᵀ D̃⁻¹(y_t − o)`` and the body-frame vertical
``v_b,t = R_bn,t v_n`` (``v_n = (0, 0, 1)``) have a constant inner product ``m_z`` (the
vertical component of the unit field in n), so (paper eq. 27)

    min over R_D ∈ SO(3), m_z  of  Σ_t w_t (m_z − v_b,tᵀ R_Dᵀ m̃_t)²,   m̃_t = D̃⁻¹(y_t − o).

Then ``D₀ = D̃ R_D`` and ``m_n₀ = (√(1 − m_z²), 0, m_z)``; with ``m_n = (cos δ, 0, −sin δ)``
the dip is ``δ = −asin m_z`` (positive down).

How it is solved here: ``v_bᵀ R_Dᵀ m̃ = m̃ᵀ R_D v_b = p_tᵀ r`` with ``p_t = vec(m̃_t v_b,tᵀ)``
and ``r = vec(R_D)`` (row-major). For fixed ``R_D`` the best ``m_z`` is the weighted mean
``p̄ᵀ r``, and the cost becomes ``rᵀ C r`` with ``C`` the 9 × 9 weighted covariance of the
``p_t``. One O(N) pass builds ``C``; everything after is independent of N:

1. global start: the best of (a) the smallest eigenvector of ``C`` (the relaxation
   ``‖r‖² = 3``) projected onto SO(3), and (b) the best points of a near-uniform grid on SO(3);
2. Gauss–Newton on a rotation-vector increment, ``R_D ← exp([φ×]) R_D``.

Note the cost is unchanged under ``(R_D, m_z) → (−R_D, −m_z)``; ``−R_D`` is a reflection,
so restricting to SO(3) picks the sign of ``m_z``. If the magnetometer axes are a mirror image
of the inertial axes (``det D < 0``), the SO(3) solution has the dip with the wrong sign; a
known hemisphere (``expected_dip_sign``) resolves it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from magcal.calib.frames import (
    GRAVITY_M_S2,
    nearest_rotation,
    quat_to_matrix,
    rotvec_to_matrix,
    skew,
    so3_grid,
)
from magcal.errors import CalibrationError, InsufficientDataError

#: Rotations in the global grid search (cost evaluations are 81 flops each; 1024 rotations
#: are about 15° apart, well inside Gauss–Newton's basin).
GRID_SIZE = 1024
#: Grid points refined besides the relaxation's start.
GRID_STARTS = 4
#: Gauss–Newton iteration cap and step tolerance (rad).
GN_MAX_ITER = 100
GN_STEP_TOL_RAD = 1e-13
#: Smallest eigenvalue of the Gauss–Newton Hessian ``JᵀJ`` (per unit weight,
#: dimensionless) below which the rotation is reported as poorly determined — e.g. yaw-only
#: motion, where the vertical does not change in the body frame. A tumbling session gives
#: values around 0.1.
MIN_HESSIAN_EIG = 1e-4
#: Acceleration weights: Cauchy weight ``1/(1 + (|‖a‖ − g|/s)²)`` with this scale, m/s².
#: A sample whose norm is off by 0.5 m/s² counts half.
ACC_WEIGHT_SCALE_M_S2 = 0.5
#: Fewest samples.
MIN_SAMPLES = 10
#: A dip is called negative (or of the unexpected sign) only when m_z is further than this
#: many standard errors from 0.
DIP_SIGN_SIGMAS = 5.0
#: m_z below this is 0 to rounding (the same margin as the |m_z| < 1 clip below).
DIP_SIGN_FLOOR = 1e-9
#: Latitude, degrees, beyond which a site's magnetic hemisphere (the sign of the dip) is
#: taken to be its geographic one: the dip equator strays from the geographic equator by
#: up to about 15° (over South America and South-East Asia).
HEMISPHERE_LATITUDE_DEG = 20.0

#: What turns the dip's sign, for the warnings: the data cannot tell these apart (each is
#: the true field with the world turned half a turn, about north or about the vertical).
DIP_SIGN_CAUSES = (
    "either the accelerometer's sign is flipped (level and at rest with z up it must read "
    "about +9.81 m/s² on z, the specific force, not −9.81) or the magnetometer's axes are "
    "mirrored against the inertial axes (one or three of them negated, or two swapped): "
    "check the axis mapping"
)


@dataclass(frozen=True, eq=False)
class Alignment:
    """Misalignment and field inclination.

    R_D          : (3, 3) float, rotation with ``D₀ = D̃ R_D`` (det +1, or −1 only when a
                   reflection was chosen through ``expected_dip_sign``)
    m_z          : float, vertical component of the unit field in n, in (−1, 1)
    dip_rad      : float, rad, ``−asin m_z`` (positive down)
    D0           : (3, 3) float, raw magnetometer units, ``D̃ R_D``
    m_n          : (3,) float, unit field in n, ``(√(1 − m_z²), 0, m_z)``
    residual_rms : float, dimensionless, weighted RMS of ``m_z − v_bᵀ m_b``
    hessian_min_eig : float, dimensionless, smallest eigenvalue of the Gauss–Newton Hessian
                   per unit weight (small: rotation poorly determined)
    warnings     : tuple of str, human-readable notes (poorly determined rotation, negative
                   dip, clipped ``m_z``)
    """

    R_D: np.ndarray
    m_z: float
    dip_rad: float
    D0: np.ndarray
    m_n: np.ndarray
    residual_rms: float
    hessian_min_eig: float
    warnings: tuple[str, ...] = ()


def acceleration_weights(
    acc: np.ndarray, g: float = GRAVITY_M_S2, scale: float = ACC_WEIGHT_SCALE_M_S2
) -> np.ndarray:
    """Per-sample weights in (0, 1] that down-weight accelerated samples.

    acc   : (N, 3) float, m/s², specific force
    g     : float, m/s², the accelerometer norm at rest (pass the median norm for an
            accelerometer with a scale error)
    scale : float, m/s², deviation at which a sample counts half

    Returns (N,) ``1 / (1 + ((‖a_t‖ − g)/scale)²)``: the norm deviation is a lower bound on
    the translational acceleration, which tilts the inertial-only attitude.
    """
    acc = np.asarray(acc, dtype=float)
    if acc.ndim != 2 or acc.shape[1] != 3:
        raise ValueError(f"acc must have shape (N, 3), got {acc.shape}")
    dev = (np.linalg.norm(acc, axis=1) - g) / scale
    return 1.0 / (1.0 + dev * dev)


def vertical_from_accelerometer(acc: np.ndarray) -> np.ndarray:
    """Body-frame "up" ``v_b = R_bn (0, 0, 1)`` from the accelerometer, (N, 3) unit vectors.

    acc : (N, 3) float, m/s². At rest ``acc = −R_bn g_n = g v_b``, so ``v_b = acc/‖acc‖``;
    under acceleration it is tilted — prefer an inertial EKF attitude when there is one.
    """
    acc = np.asarray(acc, dtype=float)
    norm = np.linalg.norm(acc, axis=1, keepdims=True)
    if np.any(norm == 0.0):
        raise CalibrationError(
            "alignment: some accelerometer samples are exactly zero (free fall or a dead "
            "sensor); remove them before calibrating"
        )
    return acc / norm


# Generators: vec([e_k×] R) for the left increment exp([φ×]) R.
_GENERATORS = skew(np.eye(3))  # (3, 3, 3), _GENERATORS[k] = [e_k×]


def _jacobian(L: np.ndarray, R: np.ndarray) -> np.ndarray:
    """``∂(L vec(exp([φ×]) R))/∂φ`` at φ = 0, (9, 3)."""
    return L @ np.stack([(G @ R).ravel() for G in _GENERATORS], axis=1)


def _refine(L: np.ndarray, R: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Gauss–Newton (Levenberg-damped when a step does not descend) on ``‖L vec(R)‖²`` over
    SO(3), with the left increment ``R ← exp([φ×]) R``. Returns (R, JᵀJ at the end)."""
    eye = np.eye(3)
    cost = float(np.sum((L @ R.ravel()) ** 2))
    mu = 0.0
    for _ in range(GN_MAX_ITER):
        J = _jacobian(L, R)
        H = J.T @ J
        grad = J.T @ (L @ R.ravel())
        damping_floor = 1e-9 * float(np.trace(H)) + 1e-300
        accepted = False
        for _ in range(40):
            try:
                phi = -np.linalg.solve(H + mu * eye, grad)
            except np.linalg.LinAlgError:
                phi = None
            if phi is not None and np.all(np.isfinite(phi)):
                R_new = rotvec_to_matrix(phi) @ R
                new_cost = float(np.sum((L @ R_new.ravel()) ** 2))
                if new_cost <= cost:
                    accepted = True
                    break
            mu = max(10.0 * mu, damping_floor)
        if not accepted:
            break
        R, cost = R_new, new_cost
        mu = mu / 10.0 if mu > damping_floor else 0.0
        if np.linalg.norm(phi) < GN_STEP_TOL_RAD:
            break
    J = _jacobian(L, R)
    return R, J.T @ J


def dip_sign_warnings(
    m_z: float, margin: float, site_latitude_deg: float | None = None
) -> list[str]:
    """The warning (a list of none or one) when the dip's sign is not the site's.

    m_z    : vertical component of the unit field in n (up positive; the dip is −asin m_z)
    margin : |m_z| below which the dip has no sign to judge
    site_latitude_deg : degrees north, or None when the site is unknown

    A flipped accelerometer and a mirrored magnetometer both turn the dip's sign, so the
    warning names both. With the site known (beyond ±HEMISPHERE_LATITUDE_DEG) it warns when
    the dip's sign is not the hemisphere's; without, when the dip is negative (the field
    pointing up), saying that the southern hemisphere is the innocent reading.
    """
    dip = float(np.degrees(-np.arcsin(np.clip(m_z, -1.0, 1.0))))
    if abs(m_z) <= margin:
        return []
    points = "up" if m_z > 0.0 else "down"
    if site_latitude_deg is not None and abs(site_latitude_deg) >= HEMISPHERE_LATITUDE_DEG:
        expected = "down" if site_latitude_deg > 0.0 else "up"
        if points == expected:
            return []
        hemisphere = "N" if site_latitude_deg > 0.0 else "S"
        return [
            f"alignment: the estimated dip is {dip:+.1f}° (the field points {points}), but at "
            f"the session's location, latitude {abs(site_latitude_deg):.1f}°{hemisphere}, it "
            f"points {expected}: {DIP_SIGN_CAUSES}"
        ]
    if points == "down":
        return []
    return [
        f"alignment: the estimated dip is negative ({dip:.1f}°: the field points up, as in the "
        "southern magnetic hemisphere); if the session was recorded in the northern "
        f"hemisphere, {DIP_SIGN_CAUSES}. A line '# location: LAT,LON' in the session tells a "
        "southern site from these faults"
    ]


def estimate_alignment_from_vertical(
    mag: np.ndarray,
    o: np.ndarray,
    D_tilde: np.ndarray,
    v_b: np.ndarray,
    weights: np.ndarray | None = None,
    *,
    expected_dip_sign: int | None = None,
    site_latitude_deg: float | None = None,
) -> Alignment:
    """Solve eq. 27 given the body-frame vertical directly.

    mag     : (N, 3) float, raw magnetometer units
    o       : (3,) float, raw units, offset from the ellipsoid fit
    D_tilde : (3, 3) float, raw units, lower-triangular factor from the ellipsoid fit
    v_b     : (N, 3) float, unit "up" in the body frame, ``R_bn,t (0, 0, 1)``
    weights : optional (N,) float ≥ 0, per-sample weights (e.g. :func:`acceleration_weights`)
    expected_dip_sign : optional +1 (field points down: northern magnetic hemisphere) or −1;
              when the SO(3) solution's dip has the other sign, the reflected solution
              ``−R_D`` (the magnetometer axes mirrored against the inertial axes) is returned
              with a warning.
    site_latitude_deg : optional, degrees north, where the session was recorded: only to
              word the warning about the dip's sign (:func:`dip_sign_warnings`).

    See the module docstring for the method. Raises :class:`InsufficientDataError` for too
    few samples or all-zero weights.
    """
    mag = np.asarray(mag, dtype=float)
    v_b = np.asarray(v_b, dtype=float)
    n = mag.shape[0]
    if mag.shape != (n, 3) or v_b.shape != (n, 3):
        raise ValueError(f"mag and v_b must both have shape (N, 3), got {mag.shape}, {v_b.shape}")
    if n < MIN_SAMPLES:
        raise InsufficientDataError(
            f"alignment: {n} samples; at least {MIN_SAMPLES} are needed (in practice "
            "thousands): record longer while rotating the sensor through all orientations"
        )
    if weights is None:
        w = np.full(n, 1.0 / n)
    else:
        w = np.asarray(weights, dtype=float)
        if w.shape != (n,):
            raise ValueError(f"weights must have shape ({n},), got {w.shape}")
        if np.any(w < 0.0) or not np.all(np.isfinite(w)) or not w.sum() > 0.0:
            raise InsufficientDataError(
                "alignment: the sample weights are all zero, negative or not finite: "
                "check the accelerometer data (every sample looked accelerated)"
            )
        w = w / w.sum()

    # D̃ is lower-triangular; at 3 × 3 numpy's general solve is as exact as a triangular one.
    m_tilde = np.linalg.solve(
        np.asarray(D_tilde, dtype=float), (mag - np.asarray(o, dtype=float)).T
    ).T
    # p_t = vec(m̃_t v_tᵀ), row-major; cost(R) = rᵀ C r with C the weighted covariance.
    p = (m_tilde[:, :, None] * v_b[:, None, :]).reshape(n, 9)
    p_mean = w @ p
    pc = p - p_mean
    C = (pc * w[:, None]).T @ pc
    C = 0.5 * (C + C.T)
    lam, vec = np.linalg.eigh(C)
    L = np.sqrt(np.clip(lam, 0.0, None))[:, None] * vec.T  # LᵀL = C

    # Global starts: the relaxation min rᵀCr s.t. ‖r‖² = 3, projected to SO(3) (both signs
    # of the eigenvector; the projection keeps det +1) ...
    starts = []
    x = vec[:, 0].reshape(3, 3)
    for s in (1.0, -1.0):
        starts.append(nearest_rotation(s * x))
    # ... and the best points of a grid over SO(3).
    grid = quat_to_matrix(so3_grid(GRID_SIZE)).reshape(GRID_SIZE, 9)
    grid_cost = np.einsum("ki,ij,kj->k", grid, C, grid)
    for k in np.argsort(grid_cost)[:GRID_STARTS]:
        starts.append(grid[k].reshape(3, 3))

    best = None
    for R0 in starts:
        R, H = _refine(L, R0)
        cost = float(R.ravel() @ C @ R.ravel())
        if best is None or cost < best[0]:
            best = (cost, R, H)
    cost, R_D, H = best

    warnings: list[str] = []
    m_z = float(p_mean @ R_D.ravel())
    # m_z is the weighted mean of the per-sample projections m̃_t · R_D v_t, whose weighted
    # variance is the cost: its standard error decides whether the dip's sign is known. A
    # dip within a few standard errors of 0° (at the magnetic equator) has no sign to
    # check. The samples' effective count comes from the weights; neighbouring samples are
    # correlated, so this error is a lower bound and the margin is generous.
    n_eff = 1.0 / float(np.sum(w * w))
    # The floor is rounding: noise-free data give a cost at the level of ε².
    m_z_margin = max(DIP_SIGN_SIGMAS * np.sqrt(max(cost, 0.0) / n_eff), DIP_SIGN_FLOOR)
    if expected_dip_sign is not None and expected_dip_sign * (-m_z) < -m_z_margin:
        R_D, m_z = -R_D, -m_z
        warnings.append(
            "alignment: the magnetometer axes appear mirrored against the inertial axes "
            "(det D < 0) given the expected sign of the dip, or the accelerometer's sign is "
            "flipped; check the axis mapping"
        )
    elif expected_dip_sign is None:
        warnings += dip_sign_warnings(m_z, m_z_margin, site_latitude_deg)
    limit = 1.0 - 1e-9
    if abs(m_z) > limit:
        warnings.append(
            f"alignment: |m_z| = {abs(m_z):.6f} ≥ 1 was clipped; the attitude or the "
            "ellipsoid fit is poor"
        )
        m_z = float(np.clip(m_z, -limit, limit))
    h_min = float(np.linalg.eigvalsh(H)[0])
    if h_min < MIN_HESSIAN_EIG:
        warnings.append(
            f"alignment: the magnetometer-to-inertial rotation is poorly determined "
            f"(Hessian eigenvalue {h_min:.2g} < {MIN_HESSIAN_EIG:g}): rotate the sensor "
            "through all orientations (tilt it nose up/down and roll it over, not only yaw)"
        )
    D_tilde = np.asarray(D_tilde, dtype=float)
    return Alignment(
        R_D=R_D,
        m_z=m_z,
        dip_rad=float(-np.arcsin(m_z)),
        D0=D_tilde @ R_D,
        m_n=np.array([np.sqrt(1.0 - m_z * m_z), 0.0, m_z]),
        residual_rms=float(np.sqrt(max(cost, 0.0))),
        hessian_min_eig=h_min,
        warnings=tuple(warnings),
    )


def estimate_alignment(
    mag: np.ndarray,
    o: np.ndarray,
    D_tilde: np.ndarray,
    q_nb: np.ndarray,
    weights: np.ndarray | None = None,
    *,
    expected_dip_sign: int | None = None,
    site_latitude_deg: float | None = None,
) -> Alignment:
    """Misalignment ``R_D`` and ``m_z`` (paper eq. 27) from an inertial-only attitude.

    mag     : (N, 3) float, raw magnetometer units
    o       : (3,) float, raw units, offset from the ellipsoid fit
    D_tilde : (3, 3) float, raw units, lower-triangular factor from the ellipsoid fit
    q_nb    : (N, 4) float, scalar-first unit quaternions body → nav (an EKF using gyro and
              accelerometer only: only the inclination matters, heading may drift)
    weights : optional (N,) float ≥ 0 (e.g. :func:`acceleration_weights`)
    expected_dip_sign, site_latitude_deg : see :func:`estimate_alignment_from_vertical`

    Only the vertical row of ``R_nb,t`` enters: ``v_b,t = R_bn,t (0, 0, 1)`` = the third row
    of ``R_nb,t``.
    """
    q_nb = np.asarray(q_nb, dtype=float)
    if q_nb.ndim != 2 or q_nb.shape[1] != 4:
        raise ValueError(f"q_nb must have shape (N, 4), got {q_nb.shape}")
    q = q_nb / np.linalg.norm(q_nb, axis=1, keepdims=True)
    w, x, y, z = q.T
    # Third row of R_nb = quat_to_matrix(q) (written out: the full (N, 3, 3) is not needed).
    v_b = np.column_stack(
        [2.0 * (x * z - w * y), 2.0 * (y * z + w * x), 1.0 - 2.0 * (x * x + y * y)]
    )
    return estimate_alignment_from_vertical(
        mag,
        o,
        D_tilde,
        v_b,
        weights,
        expected_dip_sign=expected_dip_sign,
        site_latitude_deg=site_latitude_deg,
    )
