# SPDX-License-Identifier: Apache-2.0
"""ArduCopter SITL (``../shared/sitl`` beside the checkout) as a test fixture.

:class:`ArduPilotSitl` starts ``arducopter --model calibration`` in a temporary directory, in
its own process group, with the simulated compass errors given as a defaults file (so no
reboot is needed: a custom rotation is enabled at boot), drives the calibration stand and the
parameters over SERIAL1 (TCP 5762 + 10·I) and leaves SERIAL0 (5760 + 10·I) to magcal. The
process group is always stopped: on ``close`` / leaving the ``with``, and at interpreter exit.

:func:`heading_rms_deg` is the figure the tests and the benchmark compare: ArduPilot's
correction (``rotate_field`` with COMPASS_ORIENT, then ``correct_field``) with the parameters
read back from the vehicle, applied to the field the simulation makes of a true body field
(its README: ``inv(M_sim)·B − SIM_OFS``, rotated by the inverse of SIM_MAG1_ORIENT), against
that true field: the RMS heading error over an even grid of attitudes.
"""

from __future__ import annotations

import os
import socket
import subprocess
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from magcal.autopilot import mapping, rotations
from magcal.calib import frames
from tests.autopilot_sitl import processes

REPO = Path(__file__).resolve().parents[2]
SITL_DIR = Path(os.environ.get("MAGCAL_SITL_DIR", REPO.parent / "shared" / "sitl"))
BINARY = SITL_DIR / "arducopter"
#: ArduPilot's default home (README): the field there is about 580 mG, inclination −66°.
HOME = (-35.363261, 149.165230, 584.0)
MAV_CMD_DO_SET_SERVO = 183
STAND_AUTOMATIC_PWM = 1250
STAND_STOP_PWM = 1000


def available() -> str | None:
    """None when SITL can run here, else why not (the skip message)."""
    return processes.missing(BINARY, "ArduPilot SITL", "MAGCAL_SITL_DIR")


@dataclass(frozen=True)
class Truth:
    """The simulated compass 1: offsets (mG), M_sim (3, 3), and its mounting rotation."""

    ofs: np.ndarray
    M: np.ndarray
    rotation_deg: tuple[float, float, float] | None  # custom rotation 2 (roll, pitch, yaw)

    @property
    def R(self) -> np.ndarray:
        if self.rotation_deg is None:
            return np.eye(3)
        return rotations.euler_deg_to_matrix(*self.rotation_deg)

    def params(self) -> dict[str, float]:
        p = {f"SIM_MAG1_OFS_{a}": float(self.ofs[i]) for i, a in enumerate("XYZ")}
        p |= {f"SIM_MAG1_DIA_{a}": float(self.M[i, i]) for i, a in enumerate("XYZ")}
        p |= {
            "SIM_MAG1_ODI_X": float(self.M[0, 1]),
            "SIM_MAG1_ODI_Y": float(self.M[0, 2]),
            "SIM_MAG1_ODI_Z": float(self.M[1, 2]),
        }
        if self.rotation_deg is not None:
            roll, pitch, yaw = self.rotation_deg
            p |= {
                "CUST_ROT_ENABLE": 1.0,
                "CUST_ROT2_ROLL": roll,
                "CUST_ROT2_PITCH": pitch,
                "CUST_ROT2_YAW": yaw,
                "SIM_MAG1_ORIENT": 102.0,
            }
        return p


def random_truth(seed: int, misalignment_deg: tuple[float, float] | None = None) -> Truth:
    """Offsets 50–150 mG per axis, diagonal 0.9–1.1, off-diagonal ±0.05; with
    ``misalignment_deg`` (lo, hi) a mounting rotation of a random axis and an angle in it."""
    rng = np.random.default_rng(seed)
    ofs = rng.uniform(50.0, 150.0, 3) * rng.choice([-1.0, 1.0], 3)
    dia = rng.uniform(0.9, 1.1, 3)
    odi = rng.uniform(-0.05, 0.05, 3)
    M = np.array([[dia[0], odi[0], odi[1]], [odi[0], dia[1], odi[2]], [odi[1], odi[2], dia[2]]])
    rot = None
    if misalignment_deg is not None:
        axis = rng.standard_normal(3)
        angle = rng.uniform(*misalignment_deg)
        R = frames.quat_to_matrix(
            frames.rotvec_to_quat(np.deg2rad(angle) * axis / np.linalg.norm(axis))
        )
        rot = tuple(round(a, 3) for a in rotations.matrix_to_euler_deg(R))
    return Truth(ofs, M, rot)


def heading_rms_deg(truth: Truth, written: dict[str, float], inclination_deg: float) -> float:
    """RMS heading error of ArduPilot's correction with ``written`` (module docstring)."""
    m_n = frames.field_direction(np.deg2rad(inclination_deg))
    q = frames.so3_grid(2000)
    R_nb = np.array([frames.quat_to_matrix(x) for x in q])
    B_b = np.einsum("kji,j->ki", R_nb, m_n) * 580.0
    sensor = (np.linalg.solve(truth.M, B_b.T).T - truth.ofs) @ truth.R  # R_simᵀ applied
    corrected = mapping.ardupilot_correct(sensor, written, 1)
    err = frames.wrap_angle(
        frames.heading_of(np.einsum("kij,kj->ki", R_nb, corrected))
        - frames.heading_of(np.einsum("kij,kj->ki", R_nb, B_b))
    )
    return float(np.degrees(np.sqrt(np.mean(err**2))))


def _free_instance() -> int:
    """An -I instance whose ports 5760 + 10·I .. 5763 + 10·I are free."""
    for instance in range(3, 60):
        ports = [5760 + 10 * instance + k for k in (0, 2, 3)]
        try:
            for p in ports:
                with socket.socket() as s:
                    s.bind(("127.0.0.1", p))
        except OSError:
            continue
        return instance
    raise RuntimeError("no free SITL instance ports")


class ArduPilotSitl:
    """arducopter --model calibration with ``extra`` defaults (module docstring)."""

    def __init__(self, extra: dict[str, float], speedup: float = 1.0) -> None:
        self.dir = Path(tempfile.mkdtemp(prefix="magcal-sitl-"))
        self.instance = _free_instance()
        self.url = f"tcp:127.0.0.1:{5760 + 10 * self.instance}"
        self.speedup = speedup
        defaults = self.dir / "extra.parm"
        defaults.write_text("".join(f"{k} {v!r}\n" for k, v in extra.items()))
        self.log = open(self.dir / "sitl.log", "wb")
        self.proc = processes.start(
            [
                str(BINARY),
                "--model",
                "calibration",
                "--speedup",
                f"{speedup:g}",
                "-w",
                "--defaults",
                f"{SITL_DIR / 'copter.parm'},{defaults}",
                f"-I{self.instance}",
                "--serial0",
                "tcp:0",
                "--home",
                ",".join(f"{v:g}" for v in HOME) + ",0",
            ],
            cwd=self.dir,
            stdout=self.log,
            stderr=subprocess.STDOUT,
        )
        self.drv = None
        try:
            self.drv = self._connect(5762 + 10 * self.instance)
        except BaseException:
            self.close()
            raise

    def _connect(self, port: int):
        from pymavlink import mavutil

        deadline = time.monotonic() + 30.0
        while True:
            if self.proc.poll() is not None:
                raise RuntimeError(f"SITL exited: {(self.dir / 'sitl.log').read_text()[-2000:]}")
            try:
                c = mavutil.mavlink_connection(
                    f"tcp:127.0.0.1:{port}",
                    source_system=250,
                    source_component=191,
                    autoreconnect=False,
                )
                if c.wait_heartbeat(timeout=5):
                    return c
                c.close()
            except OSError:
                pass
            if time.monotonic() > deadline:
                raise RuntimeError("no heartbeat from SITL within 30 s")
            time.sleep(0.3)

    def get(self, name: str) -> float:
        for _ in range(10):
            self.drv.mav.param_request_read_send(self.drv.target_system, 1, name.encode(), -1)
            deadline = time.monotonic() + 1.0
            while time.monotonic() < deadline:
                m = self.drv.recv_match(type="PARAM_VALUE", blocking=True, timeout=0.5)
                if m is not None and m.param_id == name:
                    return float(m.param_value)
        raise RuntimeError(f"SITL: no value for {name}")

    def set(self, name: str, value: float) -> None:
        for _ in range(10):
            self.drv.mav.param_set_send(self.drv.target_system, 1, name.encode(), value, 9)
            deadline = time.monotonic() + 1.0
            while time.monotonic() < deadline:
                m = self.drv.recv_match(type="PARAM_VALUE", blocking=True, timeout=0.5)
                if (
                    m is not None
                    and m.param_id == name
                    and abs(m.param_value - value) <= 1e-6 * max(1, abs(value))
                ):
                    return
        raise RuntimeError(f"SITL: {name} not set to {value}")

    def stand(self, pwm: int) -> None:
        """SERVO5 of the calibration stand (README: 1250 automatic poses, < 1100 stop)."""
        for _ in range(5):
            self.drv.mav.command_long_send(
                self.drv.target_system, 1, MAV_CMD_DO_SET_SERVO, 0, 5, pwm, 0, 0, 0, 0, 0
            )
            if self.drv.recv_match(type="COMMAND_ACK", blocking=True, timeout=1.0) is not None:
                return
        raise RuntimeError("SITL: no ack for DO_SET_SERVO")

    def drain(self) -> None:
        """Drop what SERIAL1 queued while nobody read it (also PARAM_VALUEs that ArduPilot
        broadcast when magcal wrote: stale by the time they are read)."""
        while self.drv.recv_match(blocking=False) is not None:
            pass

    def params(self, names) -> dict[str, float]:
        self.drain()
        return {n: self.get(n) for n in names}

    def close(self) -> None:
        if self.drv is not None:
            try:
                self.drv.close()
            except OSError:
                pass
        processes.stop(self.proc)
        self.log.close()

    def __enter__(self) -> ArduPilotSitl:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
