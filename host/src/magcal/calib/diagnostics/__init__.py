# SPDX-License-Identifier: Apache-2.0
"""Checks around a calibration: whether a session's columns are in the format's units
(``units``), whether a session can determine one (``observability``), whether a finished
result agrees with its own session (``consistency``), quality figures (``quality``), the
estimate's uncertainty (``uncertainty``), and a fixed calibration replayed on a session
(``replay``)."""
