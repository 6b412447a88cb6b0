# SPDX-License-Identifier: Apache-2.0
"""Frames, quaternions and rotations: the one place for attitude conventions.

Conventions (see also ``docs/contracts.md``):

* Quaternions are scalar-first, ``q = (w, x, y, z)``, Hamilton product ``⊙``.
* ``q_nb`` rotates body-frame vectors into the navigation frame: ``v_n = R(q_nb) v_b``.
  ``R_bn = R(q_nb)ᵀ``.
* Navigation frame: x to magnetic north, z up. Gravity ``g_n = (0, 0, -g)``; a level
  accelerometer at rest reads ``(0, 0, +g)``. Field ``m_n = (cos δ, 0, -sin δ)``.
* Gyroscope integration: ``q_{t+1} = q_t ⊙ exp_q(½ T ω_t)`` with ``ω`` in the body frame.
* The filters use a navigation-frame orientation error ``η``:
  ``q_nb = exp_q(½ η) ⊙ q̃_nb``.

All functions are pure and vectorised over leading axes where that is cheap.
"""

from __future__ import annotations

import itertools
import math

import numpy as np

GRAVITY_M_S2 = 9.81


def skew(v: np.ndarray) -> np.ndarray:
    """Cross-product matrix ``[v×]``; v : (..., 3) → (..., 3, 3)."""
    v = np.asarray(v, dtype=float)
    z = np.zeros(v.shape[:-1])
    return np.stack(
        [
            np.stack([z, -v[..., 2], v[..., 1]], axis=-1),
            np.stack([v[..., 2], z, -v[..., 0]], axis=-1),
            np.stack([-v[..., 1], v[..., 0], z], axis=-1),
        ],
        axis=-2,
    )


def quat_multiply(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Hamilton product ``p ⊙ q``; p, q : (..., 4) → (..., 4)."""
    p = np.asarray(p, dtype=float)
    q = np.asarray(q, dtype=float)
    pw, px, py, pz = np.moveaxis(p, -1, 0)
    qw, qx, qy, qz = np.moveaxis(q, -1, 0)
    return np.stack(
        [
            pw * qw - px * qx - py * qy - pz * qz,
            pw * qx + px * qw + py * qz - pz * qy,
            pw * qy - px * qz + py * qw + pz * qx,
            pw * qz + px * qy - py * qx + pz * qw,
        ],
        axis=-1,
    )


def quat_conjugate(q: np.ndarray) -> np.ndarray:
    """Conjugate (inverse of a unit quaternion); (..., 4) → (..., 4)."""
    q = np.asarray(q, dtype=float)
    return q * np.array([1.0, -1.0, -1.0, -1.0])


def quat_normalize(q: np.ndarray) -> np.ndarray:
    """Unit quaternion with non-negative scalar part (a canonical sign)."""
    q = np.asarray(q, dtype=float)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    return np.where(q[..., :1] < 0.0, -q, q)


def quat_exp(v: np.ndarray) -> np.ndarray:
    """``exp_q(v) = (cos‖v‖, sin‖v‖ v/‖v‖)``; v : (..., 3) rad (half the rotation angle)."""
    v = np.asarray(v, dtype=float)
    a = np.linalg.norm(v, axis=-1, keepdims=True)
    # sin(a)/a by its series where a is tiny, to keep full precision and no 0/0.
    safe = np.where(a < 1e-8, 1.0, a)
    sinc = np.where(a < 1e-8, 1.0 - a * a / 6.0, np.sin(safe) / safe)
    return np.concatenate([np.cos(a), sinc * v], axis=-1)


def quat_log(q: np.ndarray) -> np.ndarray:
    """Inverse of :func:`quat_exp` for unit quaternions; (..., 4) → (..., 3)."""
    q = quat_normalize(q)
    vnorm = np.linalg.norm(q[..., 1:], axis=-1, keepdims=True)
    angle = np.arctan2(vnorm, q[..., :1])
    safe = np.where(vnorm < 1e-12, 1.0, vnorm)
    scale = np.where(vnorm < 1e-12, 1.0, angle / safe)
    return scale * q[..., 1:]


def rotvec_to_quat(phi: np.ndarray) -> np.ndarray:
    """Rotation vector (axis × angle, rad) → unit quaternion."""
    return quat_exp(0.5 * np.asarray(phi, dtype=float))


def rotvec_to_matrix(phi: np.ndarray) -> np.ndarray:
    """Rotation vector(s) (..., 3) (axis × angle, rad) → rotation matrices (..., 3, 3)."""
    return quat_to_matrix(rotvec_to_quat(phi))


def quat_step(q: tuple[float, ...], phi: tuple[float, ...]) -> tuple[float, float, float, float]:
    """One gyroscope step on a single attitude in plain floats: ``q ⊙ exp_q(½ φ)``, unit.

    q : (w, x, y, z); phi : the rotation vector of the step (rad, body frame). For loops
    that take one sample at a time (a live stream), where numpy's per-call overhead costs
    ~30× the arithmetic; the same as ``quat_normalize(quat_multiply(q, rotvec_to_quat(phi)))``
    up to the sign, which is kept continuous here.
    """
    px, py, pz = (0.5 * float(c) for c in phi)
    a = math.sqrt(px * px + py * py + pz * pz)
    s = 1.0 - a * a / 6.0 if a < 1e-8 else math.sin(a) / a
    ew, ex, ey, ez = math.cos(a), s * px, s * py, s * pz
    qw, qx, qy, qz = q
    w = qw * ew - qx * ex - qy * ey - qz * ez
    x = qw * ex + qx * ew + qy * ez - qz * ey
    y = qw * ey - qx * ez + qy * ew + qz * ex
    z = qw * ez + qx * ey - qy * ex + qz * ew
    n = math.sqrt(w * w + x * x + y * y + z * z)
    return (w / n, x / n, y / n, z / n)


def quat_to_rotvec(q: np.ndarray) -> np.ndarray:
    """Unit quaternion → rotation vector (axis × angle, rad), angle in [0, π]."""
    return 2.0 * quat_log(q)


def integrate_rates(rates: np.ndarray, dt: np.ndarray) -> np.ndarray:
    """Attitudes q_k (N + 1, 4) from body rates: q_0 = 1, q_{k+1} = q_k ⊙ exp_q(½ rates_k dt_k).

    rates : (N, 3) rad/s, body frame, each held over its interval dt (N,) s.
    A prefix product in log₂ N vectorised passes (Hillis–Steele: the product is associative,
    and each pass keeps the earlier factor on the left), so long sessions cost no Python loop.
    """
    q = np.concatenate([[[1.0, 0.0, 0.0, 0.0]], rotvec_to_quat(rates * dt[:, None])])
    shift = 1
    while shift < q.shape[0]:
        q[shift:] = quat_multiply(q[:-shift], q[shift:])
        shift *= 2
    return quat_normalize(q)


def quat_to_matrix(q: np.ndarray) -> np.ndarray:
    """Rotation matrix of a unit quaternion; ``quat_to_matrix(q_nb) = R_nb``."""
    q = np.asarray(q, dtype=float)
    w, x, y, z = np.moveaxis(q, -1, 0)
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
            np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
            np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
        ],
        axis=-2,
    )


def matrix_to_quat(R: np.ndarray) -> np.ndarray:
    """Rotation matrix → unit quaternion (Shepperd's method, stable for all angles)."""
    R = np.asarray(R, dtype=float)
    flat = R.reshape(-1, 3, 3)
    out = np.empty((flat.shape[0], 4))
    for i, m in enumerate(flat):
        tr = np.trace(m)
        k = int(np.argmax([tr, m[0, 0], m[1, 1], m[2, 2]]))
        if k == 0:
            s = 2.0 * np.sqrt(1.0 + tr)
            out[i] = [
                0.25 * s,
                (m[2, 1] - m[1, 2]) / s,
                (m[0, 2] - m[2, 0]) / s,
                (m[1, 0] - m[0, 1]) / s,
            ]
        elif k == 1:
            s = 2.0 * np.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2])
            out[i] = [
                (m[2, 1] - m[1, 2]) / s,
                0.25 * s,
                (m[0, 1] + m[1, 0]) / s,
                (m[0, 2] + m[2, 0]) / s,
            ]
        elif k == 2:
            s = 2.0 * np.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2])
            out[i] = [
                (m[0, 2] - m[2, 0]) / s,
                (m[0, 1] + m[1, 0]) / s,
                0.25 * s,
                (m[1, 2] + m[2, 1]) / s,
            ]
        else:
            s = 2.0 * np.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1])
            out[i] = [
                (m[1, 0] - m[0, 1]) / s,
                (m[0, 2] + m[2, 0]) / s,
                (m[1, 2] + m[2, 1]) / s,
                0.25 * s,
            ]
    return quat_normalize(out).reshape(R.shape[:-2] + (4,))


def euler_zyx_to_matrix(yaw: float, pitch: float, roll: float) -> np.ndarray:
    """``R = Rz(yaw) Ry(pitch) Rx(roll)`` (aerospace z-y-x), angles in rad."""
    cy, sy = np.cos(yaw), np.sin(yaw)
    cp, sp = np.cos(pitch), np.sin(pitch)
    cr, sr = np.cos(roll), np.sin(roll)
    Rz = np.array([[cy, -sy, 0.0], [sy, cy, 0.0], [0.0, 0.0, 1.0]])
    Ry = np.array([[cp, 0.0, sp], [0.0, 1.0, 0.0], [-sp, 0.0, cp]])
    Rx = np.array([[1.0, 0.0, 0.0], [0.0, cr, -sr], [0.0, sr, cr]])
    return Rz @ Ry @ Rx


def field_direction(dip_rad: float) -> np.ndarray:
    """Unit local field in n: ``m_n = (cos δ, 0, -sin δ)``, δ positive down."""
    return np.array([np.cos(dip_rad), 0.0, -np.sin(dip_rad)])


def gravity_n(g: float = GRAVITY_M_S2) -> np.ndarray:
    """Gravity vector in n (z up): ``(0, 0, -g)``."""
    return np.array([0.0, 0.0, -g])


def heading_of(v_n: np.ndarray) -> np.ndarray:
    """Heading angle atan2(y, x) (rad) of n-frame vectors (..., 3), measured from north (x).

    For a calibrated field rotated back into n with the true attitude, the heading error is
    the angle of its horizontal part from the x axis (magnetic north).
    """
    v_n = np.asarray(v_n, dtype=float)
    return np.arctan2(v_n[..., 1], v_n[..., 0])


def wrap_angle(a: np.ndarray) -> np.ndarray:
    """Wrap angles (rad) to (-π, π]."""
    return -((-np.asarray(a) + np.pi) % (2.0 * np.pi) - np.pi)


def heading_error_between(q_est_nb: np.ndarray, q_ref_nb: np.ndarray) -> np.ndarray:
    """Heading part of ``Δq = q_est ⊙ q_ref*`` (paper eq. 33) as z-y-x yaw, rad, (...,)."""
    dq = quat_multiply(q_est_nb, quat_conjugate(q_ref_nb))
    w, x, y, z = np.moveaxis(dq, -1, 0)
    return np.arctan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))


def so3_grid(count: int) -> np.ndarray:
    """A deterministic, near-uniform set of ``count`` rotations as quaternions (count, 4).

    Uses the super-Fibonacci spiral (Alexa 2022), which covers SO(3) evenly for any count.
    """
    phi = np.sqrt(2.0)
    psi = 1.533751168755204288118041
    i = np.arange(count) + 0.5
    s = i / count
    r = np.sqrt(s)
    R = np.sqrt(1.0 - s)
    alpha = 2.0 * np.pi * i / phi
    beta = 2.0 * np.pi * i / psi
    q = np.stack([r * np.sin(alpha), r * np.cos(alpha), R * np.sin(beta), R * np.cos(beta)], -1)
    return quat_normalize(q)


def triad(up_b: np.ndarray, field_b: np.ndarray, field_n: np.ndarray) -> np.ndarray:
    """Attitude q_nb from the body-frame "up" (accelerometer direction at rest) and field,
    given the n-frame field (TRIAD, Shuster & Oh 1981, gravity as the exact vector)."""

    def frame(a: np.ndarray, b: np.ndarray) -> np.ndarray:
        t1 = a / np.linalg.norm(a)
        t2 = np.cross(t1, b)
        t2 = t2 / np.linalg.norm(t2)
        return np.column_stack([t1, t2, np.cross(t1, t2)])

    R_nb = frame(np.array([0.0, 0.0, 1.0]), field_n) @ frame(up_b, field_b).T
    return matrix_to_quat(R_nb)


def nearest_rotation(x: np.ndarray) -> np.ndarray:
    """(3, 3) the rotation nearest to a 3 × 3 matrix (Frobenius norm), via the SVD
    x = U S Vᵀ: U Vᵀ with its last axis flipped when needed for det +1. For det x > 0 it is
    the rotation R of the polar decomposition x = P R."""
    u, _, vt = np.linalg.svd(np.asarray(x, dtype=float))
    d = np.sign(np.linalg.det(u @ vt))
    return u @ np.diag([1.0, 1.0, d]) @ vt


def axis_permutation_rotations() -> np.ndarray:
    """(24, 3, 3) the rotations that map axes onto axes: every signed permutation matrix with
    determinant +1. A sensor is mounted as one of them (the autopilots' enumerated rotations
    hold these and more) plus a small misalignment."""
    out = []
    for perm in itertools.permutations(range(3)):
        for signs in itertools.product((1.0, -1.0), repeat=3):
            U = np.zeros((3, 3))
            U[np.arange(3), perm] = signs
            if np.linalg.det(U) > 0.0:
                out.append(U)
    return np.array(out)


def nearest_axis_permutation(R: np.ndarray) -> np.ndarray:
    """(3, 3) the axis-permutation rotation closest to the rotation R (largest trace(R Uᵀ))."""
    rotations = axis_permutation_rotations()
    return rotations[int(np.argmax(np.einsum("ij,kij->k", np.asarray(R, dtype=float), rotations)))]
