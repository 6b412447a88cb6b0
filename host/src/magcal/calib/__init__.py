# SPDX-License-Identifier: Apache-2.0
"""The calibration: from a session's raw readings to D, o and the inertial alignment.

The folders follow the algorithm (Kok & Schön 2016, Algorithm 1; ``docs/algorithm.md``):

* :mod:`~magcal.calib.initial`: step 1, the initial estimate θ₀: rest detection (gyroscope
  bias and noise levels), the ellipsoid fit, and the alignment of the magnetometer with the
  inertial axes;
* :mod:`~magcal.calib.likelihood`: step 2, the maximum-likelihood estimate: the parameter
  vector θ, the orientation filter and its C kernel, the problem V(θ) with its priors and
  gradient, and the optimiser;
* :mod:`~magcal.calib.norm_only`: methods that use the field norm alone (Zhao et al.'s CKF,
  TWO-STEP) and the live estimate shown while a session is recorded;
* :mod:`~magcal.calib.diagnostics`: what is checked before and after: can the session
  determine a calibration, quality figures, the estimate's uncertainty, a fixed
  calibration replayed on a session.

:mod:`~magcal.calib.calibrate` runs them in order and is the one entry point for callers;
:mod:`~magcal.calib.frames` holds the frames and rotations everything here shares.
"""
