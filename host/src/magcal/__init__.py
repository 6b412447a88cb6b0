"""magcal: maximum-likelihood magnetometer calibration with inertial sensors."""

__version__ = "0.1.0"
