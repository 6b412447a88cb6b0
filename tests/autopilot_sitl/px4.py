# SPDX-License-Identifier: Apache-2.0
"""PX4 SITL with its built-in simulator SIH (``../shared/px4sitl`` beside the checkout) as a
test fixture.

:class:`Px4Sitl` unpacks ``px4-sih.tar.gz`` into a temporary directory (never into the shared
folder) and starts ``px4 -i I`` there in its own process group, the parameters given as
``PX4_PARAM_*`` (PX4's start-up script sets them before the simulator runs). The instance I is
one whose UDP ports are free, and an ``<airframe>.post`` hook (which PX4's start-up script
runs after its own MAVLink links) adds two links that send to ports of their own: one for
magcal (:attr:`Px4Sitl.url`) and one for the fixture's driver (parameters, streams, turning
the vehicle), so that runs side by side never see each other's vehicle on 14550. The process
group is always stopped: on ``close`` / leaving the ``with``, and at interpreter exit;
``close`` removes the unpacked PX4 and its flight logs and keeps ``run/px4.log``.

What SIH simulates (its README): the world magnetic model's field turned by the true attitude,
noise, and one sensor error, the offset ``SIM_MAG_OFFSET_X/Y/Z`` (gauss); the magnetometer is
internal (``CAL_MAG0_ROT`` −1, turned by ``SENS_BOARD_ROT``). The vehicle is turned on the
ground, disarmed, by ``MAV_CMD_ACTUATOR_TEST`` bursts on pairs of motors (:meth:`Px4Sitl.turn`).
"""

from __future__ import annotations

import math
import os
import shutil
import socket
import subprocess
import tarfile
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

from magcal.calib import frames
from tests.autopilot_sitl import processes

REPO = Path(__file__).resolve().parents[2]
PX4SITL_DIR = Path(os.environ.get("MAGCAL_PX4SITL_DIR", REPO.parent / "shared" / "px4sitl"))
TARBALL = PX4SITL_DIR / "px4-sih.tar.gz"
AIRFRAME = "10040_sihsim_quadx"
MAV_CMD_SET_MESSAGE_INTERVAL = 511
MAV_CMD_ACTUATOR_TEST = 310
HIL_STATE_QUATERNION_ID = 115
HIGHRES_IMU_ID = 105
#: Motor pairs whose bursts turn the quadrotor about different axes (README: 3 s bursts of
#: ≈ 0.05 turn it by 30–70°, and it stays where it ends).
MOTOR_PAIRS = ((1, 3), (2, 4), (1, 2), (3, 4), (1, 4), (2, 3))
#: Samples of the corrected field are compared with the true attitude below this rate, rad/s.
SLOW_RAD_S = 0.1
#: Slow samples a comparison of PX4's corrected field with the true attitude needs: 70 of
#: SIH's 20–30 mG noise resolve an offset to 3–10 mG against a known earth field
#: (:func:`residual_offset`; test_px4_sitl.COMPARISON_BOUND_G).
MIN_SLOW_SAMPLES = 70
#: How far apart a run's attitudes must be for :func:`residual_offsets` to tell an offset from
#: the earth field: 1 − the largest singular value of the mean R_nb (0 when every attitude
#: shares one axis, 1 when they cover every direction). Runs of SIH's vehicle turned about
#: two axes gave 0.013–0.05, runs where it only turned about one 0.0004.
MIN_ATTITUDE_SPREAD = 0.005


def _udp_free(port: int) -> bool:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        try:
            s.bind(("0.0.0.0", port))
        except OSError:
            return False
    return True


def _free_instance() -> tuple[int, list[int]]:
    """An instance I whose PX4 ports (px4-rc.mavlink: 18570, 14580, 14280, 13030, 19450 + I)
    are free, and four more free ports (the ports the two links send to, the driver's own)."""
    for instance in range(3, 40):
        own = [base + instance for base in (18570, 14580, 14280, 13030, 19450)]
        extra = [24500 + 10 * instance + k for k in range(4)]
        if all(_udp_free(p) for p in own + extra):
            return instance, extra
    raise RuntimeError("no free PX4 SITL instance ports")


def quat_to_matrix(q) -> np.ndarray:
    """R_nb (body → NED) of a MAVLink quaternion (w, x, y, z)."""
    return frames.quat_to_matrix(np.asarray(q, dtype=float))


def available() -> str | None:
    """None when PX4 SITL can run here, else why not (the skip message)."""
    return processes.missing(TARBALL, "PX4 SITL", "MAGCAL_PX4SITL_DIR")


class Px4Sitl:
    """PX4 SITL with SIH and ``params`` set at start (module docstring)."""

    def __init__(self, params: dict[str, float] | None = None) -> None:
        self.dir = Path(tempfile.mkdtemp(prefix="magcal-px4-"))
        with tarfile.open(TARBALL) as tar:
            tar.extractall(self.dir / "px4", filter="tar")
        self.instance, (magcal_local, magcal_remote, drv_local, drv_remote) = _free_instance()
        self.url = f"udpin:127.0.0.1:{magcal_remote}"
        post = self.dir / "px4" / "etc" / "init.d-posix" / "airframes" / f"{AIRFRAME}.post"
        gcs, payload = 18570 + self.instance, 14280 + self.instance
        # PX4 runs at most 6 links: the GCS link is started again sending to magcal's port
        # (as px4-rc.mavlink starts it, with -o), the camera payload link makes room for ours
        post.write_text(
            f"mavlink stop -u {gcs}\nmavlink stop -u {payload}\n"
            f"mavlink start -x -u {gcs} -r 4000000 -f -o {magcal_remote}\n"
            f"mavlink start -x -u {drv_local} -r 4000000 -o {drv_remote}\n"
        )
        run = self.dir / "run"
        run.mkdir()
        env = dict(os.environ)
        env |= {"PX4_SIM_MODEL": "sihsim_quadx", "PX4_SIMULATOR": "sihsim"}
        env |= {f"PX4_PARAM_{k}": f"{v:g}" for k, v in (params or {}).items()}
        self.log = open(run / "px4.log", "wb")
        self.proc = processes.start(
            [
                str(self.dir / "px4" / "bin" / "px4"),
                "-i",
                str(self.instance),
                "-d",
                "-w",
                str(run),
                str(self.dir / "px4" / "etc"),
            ],
            cwd=run,
            env=env,
            stdin=subprocess.DEVNULL,
            stdout=self.log,
            stderr=subprocess.STDOUT,
        )
        self.drv = None
        self._lock = threading.Lock()
        try:
            self.drv = self._connect(drv_remote)
        except BaseException:
            self.close()
            raise

    def _connect(self, port: int):
        from pymavlink import mavutil

        c = mavutil.mavlink_connection(
            f"udpin:127.0.0.1:{port}", source_system=250, source_component=191
        )
        deadline = time.monotonic() + 40.0
        while time.monotonic() < deadline:
            if self.proc.poll() is not None:
                raise RuntimeError(f"PX4 exited: {self.log_text()[-2000:]}")
            if c.wait_heartbeat(timeout=1) is not None:
                self.system = c.target_system
                # the start-up script (and so the added links) is done when its log says so
                while "Startup script returned successfully" not in self.log_text():
                    if time.monotonic() > deadline:
                        raise RuntimeError("PX4 start-up script never finished")
                    time.sleep(0.2)
                return c
        c.close()
        raise RuntimeError(f"no heartbeat from PX4 within 40 s: {self.log_text()[-2000:]}")

    def log_text(self) -> str:
        return (self.dir / "run" / "px4.log").read_text(errors="replace")

    # -- parameters (PX4 sends INT32 values as their raw bytes: read as floats here) --

    def get_wire(self, name: str):
        """The PARAM_VALUE message for ``name`` (its param_value as on the wire)."""
        for _ in range(10):
            self.drv.mav.param_request_read_send(self.system, 1, name.encode(), -1)
            deadline = time.monotonic() + 1.0
            while time.monotonic() < deadline:
                m = self.drv.recv_match(type="PARAM_VALUE", blocking=True, timeout=0.5)
                if m is not None and m.param_id == name:
                    return m
        raise RuntimeError(f"PX4: no value for {name}")

    def get(self, name: str) -> float:
        """A REAL32 parameter's value."""
        return float(self.get_wire(name).param_value)

    def set(self, name: str, value: float) -> None:
        """Set a REAL32 parameter and wait for its echo."""
        for _ in range(10):
            self.drv.mav.param_set_send(self.system, 1, name.encode(), value, 9)
            deadline = time.monotonic() + 1.0
            while time.monotonic() < deadline:
                m = self.drv.recv_match(type="PARAM_VALUE", blocking=True, timeout=0.5)
                if m is not None and m.param_id == name and abs(m.param_value - value) < 1e-6:
                    return
        raise RuntimeError(f"PX4: {name} not set to {value}")

    def drain(self) -> None:
        while self.drv.recv_match(blocking=False) is not None:
            pass

    def params(self, names) -> dict[str, float]:
        self.drain()
        return {n: self.get(n) for n in names}

    # -- streams and turning --

    def stream(self, message_id: int, rate_hz: float) -> None:
        self.drv.mav.command_long_send(
            self.system,
            1,
            MAV_CMD_SET_MESSAGE_INTERVAL,
            0,
            message_id,
            1e6 / rate_hz,
            0,
            0,
            0,
            0,
            0,
        )

    def burst(self, pair: tuple[int, int], value: float = 0.05, seconds: float = 3.0) -> None:
        """Spin two motors for ``seconds`` (MAV_CMD_ACTUATOR_TEST, param5 the motor)."""
        for motor in pair:
            self.drv.mav.command_long_send(
                self.system, 1, MAV_CMD_ACTUATOR_TEST, 0, value, seconds, 0, 0, motor, 0, 0
            )

    def turn(self, stop: threading.Event, seed: int, seconds: float = 3.0) -> None:
        """Bursts on random motor pairs until ``stop`` is set (run it in a thread; it sends
        only, so the caller may read the driver link meanwhile)."""
        rng = np.random.default_rng(seed)
        while not stop.is_set():
            self.burst(MOTOR_PAIRS[rng.integers(len(MOTOR_PAIRS))], seconds=seconds)
            stop.wait(seconds + 0.5)

    def slow_samples(
        self,
        seconds: float,
        seed: int,
        burst_s: float = 1.0,
        period_s: float = 4.0,
        spread: bool = False,
    ):
        """PX4's corrected field (HIGHRES_IMU, gauss, body frame) beside the true R_nb
        (HIL_STATE_QUATERNION, the latest before it) while bursts every ``period_s`` turn the
        vehicle, kept where the vehicle turns slower than SLOW_RAD_S (so that the pairing of
        the two streams costs nothing), for ``seconds`` and on until MIN_SLOW_SAMPLES are
        kept and, with ``spread``, the attitudes are MIN_ATTITUDE_SPREAD apart (at most three
        times as long: a vehicle that keeps spinning after a burst gives few samples, one
        that only yaws gives no spread). Returns fields (N, 3), R_nb (N, 3, 3)."""
        rng = np.random.default_rng(seed)
        self.stream(HIGHRES_IMU_ID, 50)
        self.stream(HIL_STATE_QUATERNION_ID, 50)
        self.drain()
        fields, attitudes = [], []
        state = None
        t0 = time.monotonic()
        next_burst = t0

        def wanting() -> bool:
            return len(fields) < MIN_SLOW_SAMPLES or (
                spread and attitude_spread(np.array(attitudes)) < MIN_ATTITUDE_SPREAD
            )

        while (elapsed := time.monotonic() - t0) < seconds or (elapsed < 3 * seconds and wanting()):
            if time.monotonic() >= next_burst:
                self.burst(MOTOR_PAIRS[rng.integers(len(MOTOR_PAIRS))], seconds=burst_s)
                next_burst += period_s
            m = self.drv.recv_match(
                type=["HIGHRES_IMU", "HIL_STATE_QUATERNION"], blocking=True, timeout=0.5
            )
            if m is None:
                continue
            if m.get_type() == "HIL_STATE_QUATERNION":
                state = m
            elif state is not None:
                rate = math.hypot(state.rollspeed, state.pitchspeed, state.yawspeed)
                if rate < SLOW_RAD_S:
                    fields.append((m.xmag, m.ymag, m.zmag))
                    attitudes.append(quat_to_matrix(state.attitude_quaternion))
        return np.array(fields), np.array(attitudes)

    def close(self) -> None:
        if self.drv is not None:
            try:
                self.drv.close()
            except OSError:
                pass
        processes.stop(self.proc, term_wait_s=5.0)
        self.log.close()
        # the unpacked PX4 and its flight logs go (≈ 20 MB a run); px4.log stays
        shutil.rmtree(self.dir / "px4", ignore_errors=True)
        shutil.rmtree(self.dir / "run" / "log", ignore_errors=True)

    def __enter__(self) -> Px4Sitl:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def residual_offsets(*runs) -> tuple[list[np.ndarray], np.ndarray]:
    """The body-frame offset e_r that PX4's corrected field still carries in each run of
    ``(fields, R_nb)`` (:meth:`Px4Sitl.slow_samples`), and the earth field b_n they share:
    ``field_k = R_nbᵀ_k · b_n + e_r`` solved by least squares (linear; the runs together need
    attitudes spread beyond one axis). Gauss."""
    blocks, rhs = [], []
    for r, (fields, R_nb) in enumerate(runs):
        for f, R in zip(fields, R_nb, strict=True):
            row = np.zeros((3, 3 + 3 * len(runs)))
            row[:, :3] = R.T
            row[:, 3 + 3 * r : 6 + 3 * r] = np.eye(3)
            blocks.append(row)
            rhs.append(f)
    x, *_ = np.linalg.lstsq(np.concatenate(blocks), np.concatenate(rhs), rcond=None)
    return [x[3 + 3 * r : 6 + 3 * r] for r in range(len(runs))], x[:3]


def attitude_spread(R_nb: np.ndarray) -> float:
    """1 − the largest singular value of the mean of ``R_nb`` (MIN_ATTITUDE_SPREAD); 0 for
    no attitudes."""
    if len(R_nb) == 0:
        return 0.0
    return float(1.0 - np.linalg.svd(np.mean(R_nb, axis=0), compute_uv=False)[0])


def earth_field(fields: np.ndarray, R_nb: np.ndarray, offset: np.ndarray) -> np.ndarray:
    """The earth field b_n (NED, gauss) from a run of :meth:`Px4Sitl.slow_samples` whose
    offset is known (no calibration in force: the simulated one): ``field_k = R_nbᵀ_k · b_n +
    offset`` by least squares, which for rotations is the mean of ``R_nb_k (field_k − offset)``.
    Unlike :func:`residual_offsets` it needs no attitudes spread beyond one axis."""
    return np.mean(np.einsum("kij,kj->ki", R_nb, fields - offset), axis=0)


def residual_offset(fields: np.ndarray, R_nb: np.ndarray, b_n: np.ndarray) -> np.ndarray:
    """The body-frame offset PX4's corrected field still carries in a run, against a known
    earth field b_n (:func:`earth_field`): the mean of ``field_k − R_nbᵀ_k · b_n``. Gauss."""
    return np.mean(fields - np.einsum("kji,j->ki", R_nb, b_n), axis=0)
