"""Checks around a calibration: whether a session can determine one (``observability``),
quality figures (``quality``), the estimate's uncertainty (``uncertainty``), and a fixed
calibration replayed on a session (``replay``)."""
