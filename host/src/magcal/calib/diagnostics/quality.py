# SPDX-License-Identifier: Apache-2.0
"""Quality figures of a calibration: innovation statistics, field norms, heading errors.

Pure functions on arrays. The heading error isolates the calibration from any filter:
noise-free raw fields ``y = D R_bn m_n + o`` at a fixed set of orientations are corrected
with the estimate, rotated back with the *true* attitude, and their heading (angle from
magnetic north in the horizontal plane) is compared with zero.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from magcal.calib import frames

#: Orientations used for the calibration-induced heading error: a super-Fibonacci grid,
#: fine enough that the RMS over it is stable to well under 1 %.
HEADING_GRID_SIZE = 2000


@dataclass(frozen=True)
class InnovationStats:
    """Statistics of normalised innovations (should be N(0, 1) for a good model)."""

    mean: float
    std: float
    fraction_outside_3: float

    def as_dict(self) -> dict:
        return {"mean": self.mean, "std": self.std, "fraction_outside_3": self.fraction_outside_3}


def innovation_stats(normalised: np.ndarray) -> InnovationStats:
    """normalised : (N, k) whitened innovations → mean, std, fraction with |x| > 3."""
    x = np.asarray(normalised, dtype=float).ravel()
    return InnovationStats(
        mean=float(np.mean(x)),
        std=float(np.std(x)),
        fraction_outside_3=float(np.mean(np.abs(x) > 3.0)),
    )


def norm_stats(v: np.ndarray) -> dict:
    """v : (N, 3) → mean and std of ‖v‖ (same unit as v)."""
    n = np.linalg.norm(np.asarray(v, dtype=float), axis=1)
    return {"mean": float(np.mean(n)), "std": float(np.std(n))}


def calibration_heading_errors(
    D_true: np.ndarray,
    o_true: np.ndarray,
    m_n_true: np.ndarray,
    D_est: np.ndarray,
    o_est: np.ndarray,
    q_nb: np.ndarray | None = None,
) -> np.ndarray:
    """Heading errors (rad) induced by a calibration, one per orientation.

    D_true, o_true : true distortion (3, 3) and offset (3,), magnetometer units
    m_n_true       : (3,) true unit field in n
    D_est, o_est   : the estimate, same units
    q_nb           : (K, 4) orientations; default a grid of :data:`HEADING_GRID_SIZE`
    """
    if q_nb is None:
        q_nb = frames.so3_grid(HEADING_GRID_SIZE)
    R_nb = frames.quat_to_matrix(q_nb)
    m_b = np.einsum("kji,j->ki", R_nb, m_n_true)  # R_bn m_n
    y = m_b @ np.asarray(D_true).T + o_true
    corrected = np.linalg.solve(D_est, (y - o_est).T).T
    back_n = np.einsum("kij,kj->ki", R_nb, corrected)
    return frames.wrap_angle(frames.heading_of(back_n))


def rms_deg(angles_rad: np.ndarray) -> float:
    return float(np.rad2deg(np.sqrt(np.mean(np.square(angles_rad)))))


def known_attitude_fit(
    mag: np.ndarray, q_nb: np.ndarray, m_n: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The known-attitude floor: least squares of ``y_t`` on ``[R_bn,t m_n, 1]``.

    mag : (N, 3) raw magnetometer; q_nb : (N, 4) TRUE attitude; m_n : (3,) TRUE field.
    Returns (D (3, 3), o (3,)). No estimator that must also find the attitude should beat
    this by much.
    """
    R_nb = frames.quat_to_matrix(q_nb)
    m_b = np.einsum("kji,j->ki", R_nb, m_n)
    X = np.hstack([m_b, np.ones((m_b.shape[0], 1))])
    coef, *_ = np.linalg.lstsq(X, np.asarray(mag, dtype=float), rcond=None)
    return coef[:3].T, coef[3]
