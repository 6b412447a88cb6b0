# SPDX-License-Identifier: Apache-2.0
"""The error types of magcal.

Every error message names the operation that failed and says what to do about it, e.g.
"session has 210 samples; calibration needs at least 500: record longer".
"""


class MagcalError(Exception):
    """Base of all errors magcal raises on purpose."""


class SessionFormatError(MagcalError):
    """A session file cannot be read: bad header, bad value, time going backwards, ..."""


class ResultFormatError(MagcalError):
    """A result file does not follow ``magcal-result/1``."""


class InsufficientDataError(MagcalError):
    """The session is valid but cannot determine the calibration (too short, too little
    rotation, yaw-only motion, ...). ``--force`` turns it into a warning."""


class FieldChangedError(InsufficientDataError):
    """The field changed during the recording for too much of it to calibrate on the constant
    part (steel or a magnet nearby that does not move with the sensor). ``--force``
    calibrates on all of it, with a warning."""


class CalibrationError(MagcalError):
    """A numerical step failed (solver failure, non-finite cost, ...)."""


class ResultContradictedError(CalibrationError):
    """A finished calibration contradicts its own session (a gyroscope bias no gyroscope has,
    a collapsed ellipsoid, a worse field norm or dip than a plain fit, a field that changed
    during the recording). ``--force`` turns it into a warning."""
