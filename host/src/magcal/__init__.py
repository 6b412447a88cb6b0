# SPDX-License-Identifier: Apache-2.0
"""magcal: maximum-likelihood magnetometer calibration with inertial sensors."""

import os as _os

__version__ = "0.1.0"

# One BLAS thread unless the caller says otherwise, set before numpy loads its BLAS: the
# numerical core multiplies matrices of at most 35 × 35, where OpenBLAS's worker threads
# spin instead of helping and take the core the ML step's second starting point runs on
# (cold ML of broad35_magnet4cm 1.77 s with the default threads, 0.78 s with one).
for _variable in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    _os.environ.setdefault(_variable, "1")
