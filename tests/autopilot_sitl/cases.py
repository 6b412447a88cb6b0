# SPDX-License-Identifier: Apache-2.0
"""One SITL calibration case end to end through the real command line (tests and bench).

:func:`magcal_case`: a random compass error (and mounting rotation), a wrong calibration in
force, the stand in its automatic pose sequence, then ``magcal collect --mavlink``,
``magcal calibrate`` and ``magcal flash --location ... --session ...``; the parameters read
back from the vehicle give the heading error (``ardupilot.heading_rms_deg``).
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from magcal import cli
from magcal.autopilot import wmm
from magcal.io.result import read_result
from magcal.io.session import read_session
from tests.autopilot_sitl.ardupilot import (
    HOME,
    STAND_AUTOMATIC_PWM,
    ArduPilotSitl,
    heading_rms_deg,
    random_truth,
)

#: One automatic pose cycle of the stand (18 poses of 6 s) and a little more, simulated s.
COLLECT_SIM_S = 110.0
WRITTEN = [
    *(f"COMPASS_OFS_{a}" for a in "XYZ"),
    *(f"COMPASS_DIA_{a}" for a in "XYZ"),
    *(f"COMPASS_ODI_{a}" for a in "XYZ"),
    "COMPASS_SCALE",
    "COMPASS_ORIENT",
    "CUST_ROT_ENABLE",
]
MISALIGNMENT_DEG = (3.0, 8.0)


def inclination_deg() -> float:
    import datetime as dt

    f = wmm.wmm_field(HOME[0], HOME[1], HOME[2] / 1000.0, dt.date.today())
    return float(f.inclination_deg)


def wrong_calibration(sitl: ArduPilotSitl, seed: int) -> None:
    """A calibration in force that is off: offsets 20–60 mG away, no soft iron."""
    rng = np.random.default_rng(1000 + seed)
    for a in "XYZ":
        sitl.set(f"COMPASS_OFS_{a}", float(sitl.get(f"SIM_MAG1_OFS_{a}") + rng.uniform(20, 60)))
        sitl.set(f"COMPASS_DIA_{a}", 1.0)
        sitl.set(f"COMPASS_ODI_{a}", 0.0)


def written_params(sitl: ArduPilotSitl) -> dict[str, float]:
    p = sitl.params(WRITTEN)
    if int(p["COMPASS_ORIENT"]) in (101, 102):
        k = int(p["COMPASS_ORIENT"]) - 100
        p |= sitl.params([f"CUST_ROT{k}_{n}" for n in ("ROLL", "PITCH", "YAW")])
    return p


def magcal_case(seed: int, misaligned: bool, speedup: float, work: Path) -> dict:
    """The figures of one case: heading error before and after, the orientation written,
    collection time (wall and simulated), the session's counts."""
    truth = random_truth(seed, MISALIGNMENT_DEG if misaligned else None)
    work.mkdir(parents=True, exist_ok=True)
    session, result = work / f"s{seed}.csv", work / f"r{seed}.json"
    incl = inclination_deg()
    with ArduPilotSitl(truth.params(), speedup=speedup) as sitl:
        wrong_calibration(sitl, seed)
        before = heading_rms_deg(truth, written_params(sitl), incl)
        sitl.stand(STAND_AUTOMATIC_PWM)
        t0 = time.monotonic()
        code = cli.main(
            [
                "collect",
                "--mavlink",
                sitl.url,
                "-o",
                str(session),
                "--coverage",
                "off",
                "--duration",
                f"{COLLECT_SIM_S / speedup:g}",
            ]
        )
        collect_s = time.monotonic() - t0
        assert code == 0, f"collect exited {code}"
        assert cli.main(["calibrate", str(session), "-o", str(result)]) == 0
        location = f"{HOME[0]},{HOME[1]},{HOME[2] / 1000.0}"
        code = cli.main(
            [
                "flash",
                str(result),
                "--mavlink",
                sitl.url,
                "--location",
                location,
                "--session",
                str(session),
            ]
        )
        written = written_params(sitl)
    meta = read_session(session).meta
    res = read_result(result)
    return {
        "seed": seed,
        "misalignment_deg": truth.rotation_deg,
        "flash_exit": code,
        "heading_rms_before_deg": before,
        "heading_rms_deg": heading_rms_deg(truth, written, incl),
        "orient": int(written["COMPASS_ORIENT"]),
        "custom_rotation": int(written["COMPASS_ORIENT"]) in (101, 102),
        "collect_wall_s": collect_s,
        "collect_sim_s": COLLECT_SIM_S,
        "samples": int(meta["samples"]),
        "imu_rows": int(meta["imu_rows"]),
        "rejected_fast_turn": int(meta["magnetometer_fast_turn"]),
        "rejected_frozen": int(meta["magnetometer_frozen"]),
        "coverage": meta["coverage"],
        "live_estimate": meta.get("live_estimate", ""),
        "time_offset_s": res.extra.get("time_offset_s"),
        "written": written,
    }
