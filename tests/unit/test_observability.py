# SPDX-License-Identifier: Apache-2.0
"""Tests of the observability check."""

from __future__ import annotations

import numpy as np
import pytest

from magcal.calib.diagnostics import observability as obs
from magcal.calib.diagnostics.observability import (
    ObservabilityReport,
    check_observability,
    raise_if_unobservable,
)
from magcal.calib.frames import (
    field_direction,
    gravity_n,
    quat_conjugate,
    quat_multiply,
    quat_to_matrix,
    quat_to_rotvec,
    rotvec_to_quat,
)
from magcal.errors import InsufficientDataError

FS_HZ = 100.0
DIP_RAD = np.radians(65.0)
D_TRUE = np.array([[1.2, 0.05, -0.03], [0.02, 0.9, 0.04], [-0.05, 0.01, 1.0]])
O_TRUE = np.array([3.0, 1.0, 2.0])


def _sensors(q_nb: np.ndarray, rng: np.random.Generator, acc_noise: float = 0.05):
    """Synthetic session from attitudes q_nb (N, 4): gyr from successive attitudes,
    acc = −R_bn g_n (+ noise), mag = D R_bn m_n + o."""
    n = q_nb.shape[0]
    t = np.arange(n) / FS_HZ
    R_bn = np.swapaxes(quat_to_matrix(q_nb), -1, -2)
    acc = -(R_bn @ gravity_n()) + acc_noise * rng.normal(size=(n, 3))
    mag = (R_bn @ field_direction(DIP_RAD)) @ D_TRUE.T + O_TRUE + 0.01 * rng.normal(size=(n, 3))
    dq = quat_multiply(quat_conjugate(q_nb[:-1]), q_nb[1:])
    gyr = quat_to_rotvec(dq) * FS_HZ
    gyr = np.vstack([gyr, gyr[-1:]])
    return gyr, acc, mag, t


def _times(seconds: float) -> np.ndarray:
    return np.arange(int(seconds * FS_HZ)) / FS_HZ


def _tumbling(seconds: float = 60.0) -> np.ndarray:
    t = _times(seconds)
    phi = np.stack(
        [2.5 * np.sin(0.31 * t), 2.5 * np.sin(0.23 * t + 1), 3 * np.sin(0.17 * t + 2)],
        1,
    )
    return rotvec_to_quat(phi)


def _yaw_only(seconds: float = 60.0) -> np.ndarray:
    t = _times(seconds)
    yaw = rotvec_to_quat(np.outer(3.0 * np.sin(0.2 * t), [0.0, 0.0, 1.0]))
    return quat_multiply(yaw, rotvec_to_quat([0.2, 0.1, 0.0]))


def _wobble(amplitude_deg: float, seconds: float = 60.0) -> np.ndarray:
    t = _times(seconds)
    a = np.radians(amplitude_deg)
    phi = a * np.stack([np.sin(1.9 * t), np.sin(2.3 * t + 1), np.sin(1.4 * t + 2)], 1)
    return rotvec_to_quat(phi)


def test_tumbling_is_ok():
    rng = np.random.default_rng(0)
    report = check_observability(*_sensors(_tumbling(), rng))
    assert isinstance(report, ObservabilityReport)
    assert report.ok, report.message
    assert report.problems == [] and report.message == ""
    assert report.n_samples == 6000 and report.duration_s == pytest.approx(59.99)
    assert report.gravity_eigenvalues[1] > 0.2
    assert report.gravity_eigenvalues.sum() == pytest.approx(1.0)
    assert report.mag_eig_ratio > 0.2
    assert report.mag_eigenvalues.sum() == pytest.approx(1.0)
    assert report.tilt_spread_deg > 90.0
    assert report.total_rotation_rad > 4 * np.pi
    assert raise_if_unobservable(report, force=False) == []


def test_yaw_only_is_refused():
    rng = np.random.default_rng(1)
    # Hand-held: accelerations of 1 m/s² RMS must not look like tilt.
    report = check_observability(*_sensors(_yaw_only(), rng, acc_noise=1.0))
    assert not report.ok
    assert report.gravity_eigenvalues[1] < obs.MIN_GRAVITY_SPREAD
    assert any("yaw" in p for p in report.problems)
    assert "not only yaw" in report.message
    assert "\n" not in report.message  # one paragraph
    with pytest.raises(InsufficientDataError, match="only turned about the vertical"):
        raise_if_unobservable(report, force=False)


def test_a_flight_is_told_what_a_flight_allows():
    rng = np.random.default_rng(1)
    report = check_observability(*_sensors(_yaw_only(), rng, acc_noise=1.0))
    with pytest.raises(InsufficientDataError) as refused:
        raise_if_unobservable(report, force=False, flight=True)
    message = str(refused.value)
    assert "only turned about the vertical" in message and "This is a flight" in message
    assert "import that stretch of the log" in message and "flat on a table" not in message
    assert "\n" not in message


def test_small_wobble_is_refused():
    rng = np.random.default_rng(2)
    report = check_observability(*_sensors(_wobble(15.0), rng))
    assert not report.ok
    assert report.mag_eig_ratio < obs.MIN_MAG_EIG_RATIO
    assert any("small part of the ellipsoid" in p for p in report.problems)
    with pytest.raises(InsufficientDataError, match="rotate|Rotate"):
        raise_if_unobservable(report, force=False)


def test_force_turns_refusal_into_warnings():
    rng = np.random.default_rng(3)
    report = check_observability(*_sensors(_wobble(15.0), rng))
    warnings = raise_if_unobservable(report, force=True)
    assert warnings and "forced" in warnings[0]
    assert "small part of the ellipsoid" in warnings[0]


def test_too_short_is_refused():
    rng = np.random.default_rng(4)
    report = check_observability(*_sensors(_tumbling(1.5), rng))
    assert not report.ok
    assert any("too short" in p for p in report.problems)


def test_too_little_total_rotation_is_refused():
    # A slow half turn: covers a band, but less than a full turn of rotation.
    rng = np.random.default_rng(5)
    t = _times(30.0)
    phi = np.outer(np.pi / 2 * t / t[-1], [1.0, 0.0, 0.0])
    report = check_observability(*_sensors(rotvec_to_quat(phi), rng))
    assert not report.ok
    assert any("turned through only" in p for p in report.problems)


def test_non_finite_values_are_refused():
    rng = np.random.default_rng(6)
    gyr, acc, mag, t = _sensors(_tumbling(), rng)
    mag[10, 0] = np.nan
    report = check_observability(gyr, acc, mag, t)
    assert not report.ok
    assert any("NaN" in p for p in report.problems)
    assert np.all(np.isfinite(report.mag_eigenvalues))


def test_moderate_wobble_warns_but_passes():
    rng = np.random.default_rng(7)
    report = check_observability(*_sensors(_wobble(45.0), rng))
    assert report.ok, report.message
    assert report.warnings
    assert raise_if_unobservable(report, force=False) == report.warnings


def test_shape_error():
    with pytest.raises(ValueError, match="acc"):
        check_observability(np.zeros((10, 3)), np.zeros((10, 2)), np.zeros((10, 3)), np.arange(10))
