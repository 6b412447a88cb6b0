# SPDX-License-Identifier: Apache-2.0
"""Calibrations from the field norm alone, with no inertial data: Zhao et al.'s cubature
Kalman filter (``ckf``), Alonso & Shuster's TWO-STEP (``twostep``), and the live estimate a
recording shows (``live``). What they share is in ``norm_ellipsoid``."""
