# SPDX-License-Identifier: Apache-2.0
"""magcal against ArduCopter SITL (``make test-sitl``; skipped when ``../shared/sitl`` is
absent): the real command line end to end on the calibration stand, checked with ArduPilot's
own correction of the values written against the simulated truth.

- an aligned compass with a random SIM_MAG1_OFS/DIA/ODI: ≤ ALIGNED_BOUND_DEG RMS heading
  error, and no custom rotation written (the estimate's rotation is the identity within its
  uncertainty);
- a compass mounted 3–8° off any enumerated rotation (a custom rotation in SITL): ≤
  MISALIGNED_BOUND_DEG, which the on-board calibrator cannot reach (``make bench``).

The simulation runs SPEEDUP times faster than real time; SITL is stopped whatever happens.
"""

from __future__ import annotations

import os

import pytest

from tests.autopilot_sitl import ardupilot
from tests.autopilot_sitl.cases import magcal_case

ALIGNED_BOUND_DEG = 0.1
MISALIGNED_BOUND_DEG = 0.3
SPEEDUP = float(os.environ.get("MAGCAL_SITL_SPEEDUP", "4"))

pytestmark = pytest.mark.skipif(
    ardupilot.available() is not None, reason=str(ardupilot.available())
)


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_aligned_compass_within_a_tenth_of_a_degree_without_a_custom_rotation(seed, tmp_path):
    r = magcal_case(seed, misaligned=False, speedup=SPEEDUP, work=tmp_path)
    print(r)
    assert r["heading_rms_before_deg"] > 1.0  # the calibration in force was wrong
    assert r["heading_rms_deg"] <= ALIGNED_BOUND_DEG, r
    assert not r["custom_rotation"] and r["orient"] == 0, r
    assert r["flash_exit"] == 0


@pytest.mark.parametrize("seed", [4, 5, 6])
def test_misaligned_compass_recovered_with_a_custom_rotation(seed, tmp_path):
    r = magcal_case(seed, misaligned=True, speedup=SPEEDUP, work=tmp_path)
    print(r)
    assert r["heading_rms_deg"] <= MISALIGNED_BOUND_DEG, r
    assert r["custom_rotation"], r
    assert r["flash_exit"] == 0
