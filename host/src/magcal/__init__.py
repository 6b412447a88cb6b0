# SPDX-License-Identifier: Apache-2.0
"""magcal: maximum-likelihood magnetometer calibration with inertial sensors."""

__version__ = "0.1.0"
