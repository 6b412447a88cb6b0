# SPDX-License-Identifier: Apache-2.0
"""magcal against ArduPilot's on-board calibrator on ArduCopter SITL (``make bench-sitl``).

For each seed, the same set-up twice (tests/autopilot_sitl: a random SIM_MAG1_OFS/DIA/ODI,
a mounting rotation for the misaligned seeds, a wrong calibration in force, the stand in its
automatic pose sequence): once magcal's collect, calibrate and flash, once
MAV_CMD_DO_START_MAG_CAL (compass 1, autosave) until MAG_CAL_REPORT. Figures: the RMS heading
error of ArduPilot's correction with the values each wrote against the simulated truth, the
field-norm spread of that correction over the grid of attitudes, and the collection time
(simulated s). Nothing is asserted; the figures go to --out (JSON) and stdout.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from magcal.autopilot import mapping  # noqa: E402
from magcal.calib import frames  # noqa: E402
from tests.autopilot_sitl import ardupilot  # noqa: E402
from tests.autopilot_sitl.cases import (  # noqa: E402
    MISALIGNMENT_DEG,
    inclination_deg,
    magcal_case,
    written_params,
    wrong_calibration,
)

MAV_CMD_DO_START_MAG_CAL = 42424
ONBOARD_TIMEOUT_SIM_S = 600.0


def norm_spread(truth: ardupilot.Truth, written: dict[str, float], incl: float) -> float:
    """std/mean of the corrected field's norm over the attitude grid."""
    m_n = frames.field_direction(np.deg2rad(incl))
    q = frames.so3_grid(2000)
    R_nb = np.array([frames.quat_to_matrix(x) for x in q])
    B_b = np.einsum("kji,j->ki", R_nb, m_n) * 580.0
    sensor = (np.linalg.solve(truth.M, B_b.T).T - truth.ofs) @ truth.R
    n = np.linalg.norm(mapping.ardupilot_correct(sensor, written, 1), axis=1)
    return float(np.std(n) / np.mean(n))


def onboard_case(seed: int, misaligned: bool, speedup: float) -> dict:
    truth = ardupilot.random_truth(seed, MISALIGNMENT_DEG if misaligned else None)
    incl = inclination_deg()
    with ardupilot.ArduPilotSitl(truth.params(), speedup=speedup) as sitl:
        wrong_calibration(sitl, seed)
        sitl.stand(ardupilot.STAND_AUTOMATIC_PWM)
        drv = sitl.drv
        # refused (MAV_RESULT_FAILED) until the vehicle has finished starting: asked again
        t0 = time.monotonic()
        while time.monotonic() - t0 < 60.0:
            sitl.drain()
            drv.mav.command_long_send(
                drv.target_system, 1, MAV_CMD_DO_START_MAG_CAL, 0, 1, 0, 1, 0, 0, 0, 0
            )
            ack = drv.recv_match(type="COMMAND_ACK", blocking=True, timeout=1.0)
            if ack is not None and ack.command == MAV_CMD_DO_START_MAG_CAL and ack.result == 0:
                break
            time.sleep(1.0)
        # Done when MAG_CAL_REPORT arrives or, as it may not reach every link, when the
        # autosave replaces the offsets in force (polled once per wall second).
        before = [sitl.get(f"COMPASS_OFS_{a}") for a in "XYZ"]
        t0 = time.monotonic()
        report = None
        while time.monotonic() - t0 < ONBOARD_TIMEOUT_SIM_S / speedup:
            m = drv.recv_match(type="MAG_CAL_REPORT", blocking=True, timeout=1.0)
            if m is not None and m.compass_id == 0:
                report = m
                break
            if [sitl.get(f"COMPASS_OFS_{a}") for a in "XYZ"] != before:
                break
        elapsed = (time.monotonic() - t0) * speedup
        time.sleep(2.0 / speedup + 0.5)  # autosave
        written = written_params(sitl)
    status = None if report is None else int(report.cal_status)
    return {
        "seed": seed,
        "misalignment_deg": truth.rotation_deg,
        "cal_status": status,
        "orient": int(written["COMPASS_ORIENT"]),
        "heading_rms_deg": ardupilot.heading_rms_deg(truth, written, incl),
        "norm_spread": norm_spread(truth, written, incl),
        "collection_sim_s": elapsed,
    }


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", required=True)
    p.add_argument("--speedup", type=float, default=4.0)
    p.add_argument("--aligned", type=int, nargs="*", default=[1, 2, 3])
    p.add_argument("--misaligned", type=int, nargs="*", default=[4, 5, 6])
    args = p.parse_args()
    if ardupilot.available():
        print(f"bench-sitl: skipped: {ardupilot.available()}")
        return 0
    rows = []
    incl = inclination_deg()
    cases = [(s, False) for s in args.aligned] + [(s, True) for s in args.misaligned]
    for seed, mis in cases:
        with tempfile.TemporaryDirectory() as work:
            m = magcal_case(seed, mis, args.speedup, Path(work))
        truth = ardupilot.random_truth(seed, MISALIGNMENT_DEG if mis else None)
        m["norm_spread"] = norm_spread(truth, m["written"], incl)
        o = onboard_case(seed, mis, args.speedup)
        rows.append({"magcal": m, "onboard": o})
        print(
            f"seed {seed} {'misaligned' if mis else 'aligned   '}: magcal "
            f"{m['heading_rms_deg']:.3f}° (spread {100 * m['norm_spread']:.3f} %, "
            f"{m['collect_sim_s']:.0f} s, orient {m['orient']}), on-board "
            f"{o['heading_rms_deg']:.3f}° (spread {100 * o['norm_spread']:.3f} %, "
            f"{o['collection_sim_s']:.0f} s, orient {o['orient']}, status {o['cal_status']})",
            flush=True,
        )
    Path(args.out).write_text(json.dumps(rows, indent=1, default=str) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
