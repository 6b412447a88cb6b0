# SPDX-License-Identifier: Apache-2.0
"""Synthetic filter problems with known truth, shared by the filter-level tests."""

import dataclasses

import numpy as np

from magcal.calib import frames
from magcal.calib.likelihood import mekf, params


def synthetic_filter_problem(n=400, seed=0, rate_hz=100.0, inflation="mixed"):
    """A short, smoothly rotating session with known parameters (normalised field).

    ``inflation`` sets the accelerometer inflation c_t: "none" (all 0, the clean-session
    path with a constant Σa⁻¹), "all" (every sample > 0) or "mixed" (about one in five)."""
    rng = np.random.default_rng(seed)
    T = 1.0 / rate_hz
    t = np.arange(n) * T
    w = np.array([0.5, 1.0, -0.7]) + np.cumsum(rng.normal(size=(n, 3)), axis=0) * 0.02
    q = np.empty((n, 4))
    q[0] = frames.rotvec_to_quat(rng.normal(size=3))
    for k in range(1, n):
        q[k] = frames.quat_multiply(q[k - 1], frames.quat_exp(0.5 * T * w[k - 1]))
    R_nb = frames.quat_to_matrix(q)
    p = params.ModelParams(
        D=np.eye(3) + 0.1 * rng.normal(size=(3, 3)),
        o=0.2 * rng.normal(size=3),
        dip_rad=np.deg2rad(70.0),
        gyro_bias=np.array([0.01, -0.02, 0.005]),
        # Correlated axes on purpose (1e-6 everywhere): the off-diagonal paths get tested.
        Sigma_gyr=np.diag([2.5e-5, 3e-5, 2e-5]) + 1e-6,
        Sigma_acc=np.diag([0.0025, 0.003, 0.002]),
        Sigma_mag=np.diag([1e-4, 1.2e-4, 0.9e-4]),
    )
    g_n = frames.gravity_n()
    acc = -np.einsum("nji,j->ni", R_nb, g_n) + 0.05 * rng.normal(size=(n, 3))
    mag = np.einsum("ij,nkj,k->ni", p.D, R_nb, p.m_n) + p.o + 0.01 * rng.normal(size=(n, 3))
    gyr = w + p.gyro_bias + 0.005 * rng.normal(size=(n, 3))
    extra = 0.01 * np.abs(rng.normal(size=n))
    if inflation == "none":
        extra[:] = 0.0
    elif inflation == "mixed":
        extra[rng.random(n) > 0.2] = 0.0
    elif inflation != "all":
        raise ValueError(f"unknown inflation pattern {inflation!r}")
    q0 = frames.quat_multiply(frames.rotvec_to_quat([0.05, -0.03, 0.1]), q[0])
    data = mekf.make_filter_data(t, gyr, acc, mag, q0, acc_extra_var=extra, g=9.81)
    return p, data, q


def random_masks(n, seed):
    """About a third of the samples without accelerometer, half without magnetometer, and
    so some without either; sample 0 keeps both."""
    rng = np.random.default_rng(seed)
    has_acc = rng.random(n) > 0.35
    has_mag = rng.random(n) > 0.5
    has_acc[0] = has_mag[0] = True
    return has_acc, has_mag


def with_masks(data, has_acc, has_mag, *, blank=True):
    """``data`` with the masks; with ``blank`` the absent values are NaN (not read)."""
    acc, mag, extra = data.acc.copy(), data.mag.copy(), data.acc_extra_var.copy()
    if blank:
        acc[~has_acc] = np.nan
        extra[~has_acc] = np.nan
        mag[~has_mag] = np.nan
    return dataclasses.replace(
        data, acc=acc, mag=mag, acc_extra_var=extra, has_acc=has_acc, has_mag=has_mag
    )
