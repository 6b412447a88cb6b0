"""World simulator for the SIL device: a simulated session turned into the sensor-feed lines.

The SIL executable (build/sil/magcal-sil) reads its sensors from a TCP "feed" socket, one text
line per event (firmware/port/posix/sensor_feed.h):

    S t_us mx my mz ax ay az gx gy gz     one acquired sample, int16 raw counts
    E t_us                                a failed read
    T t_us                                the clock moves

:func:`make_world` takes a session and its truth from ``magcal.sim`` (``simulate(preset(...),
seed)``) and the device's count scales (``DeviceInfo.sensor(kind).count_scale``) and gives the
raw counts the device's sensors would read:

- magnetometer: the session's reading (``D R_bn m_n + o`` plus noise, in field units since
  ``m_n`` is a unit vector) times ``field_t / field_scale`` tesla (default 50 uT), i.e. the
  distorted field in its own axes;
- accelerometer m/s^2 and gyroscope rad/s in the body frame, as simulated;
- each divided by the value of one count and rounded to the nearest integer (ties to even),
  saturated to int16; times in microseconds.

:class:`FeedClient` connects to the feed socket and sends the lines, optionally paced.
"""

from __future__ import annotations

import socket
import time
from dataclasses import dataclass

import numpy as np

from magcal.device import fixed_point
from magcal.device.client import DeviceInfo, Scale
from magcal.errors import MagcalError
from magcal.io.session import Session
from magcal.sim.model import ideal_measurements
from magcal.sim.scenarios import SimTruth

FIELD_STRENGTH_T = 50e-6  # local field magnitude, tesla (mid-latitude Earth field)
INT16_MIN, INT16_MAX = -(1 << 15), (1 << 15) - 1
FEED_CONNECT_TIMEOUT_S = 5.0
FEED_SEND_TIMEOUT_S = 5.0


class WorldError(MagcalError):
    """The world cannot be fed to the device (bad scales, non-finite values, socket)."""


def quantise(values_si: np.ndarray, scale: Scale) -> np.ndarray:
    """SI values -> int16 counts: round to nearest (ties to even), saturate.

    values_si : (...,) float, SI units of scale (T, m/s^2, rad/s). Returns int16, same shape.
    """
    v = np.asarray(values_si, dtype=np.float64)
    if not np.all(np.isfinite(v)):
        raise WorldError("quantise: non-finite value; check the simulated session")
    counts = np.rint(v / scale.si)
    return np.clip(counts, INT16_MIN, INT16_MAX).astype(np.int16)


@dataclass(frozen=True)
class World:
    """What the device's sensors read, sample by sample.

    t_us : (N,) int64, microseconds
    mag, acc, gyr : (N, 3) int16 raw counts
    mag_t : (N, 3) float, the magnetometer reading in tesla before quantisation
    acc_si, gyr_si : (N, 3) float, m/s^2 and rad/s before quantisation
    counts_per_unit : magnetometer counts per session field unit (k): the device sees
        ``y_counts = k (D R m + o)``, so the calibration in counts is ``(k D, k o)``
    """

    t_us: np.ndarray
    mag: np.ndarray
    acc: np.ndarray
    gyr: np.ndarray
    mag_t: np.ndarray
    acc_si: np.ndarray
    gyr_si: np.ndarray
    counts_per_unit: float
    truth: SimTruth

    def __len__(self) -> int:
        return int(self.t_us.shape[0])

    def lines(self, start: int = 0, stop: int | None = None) -> list[str]:
        """The S lines of samples [start, stop), each ending in a newline."""
        out = []
        for k in range(start, len(self) if stop is None else stop):
            vals = (*self.mag[k], *self.acc[k], *self.gyr[k])
            out.append(f"S {int(self.t_us[k])} " + " ".join(str(int(v)) for v in vals) + "\n")
        return out

    def device_params(self, **kw) -> fixed_point.DeviceParams:
        """The true calibration as the device's parameter set (raw counts in, unit-norm field
        out): ``from_calibration(D^-1, o)`` of the truth, with the counts scale."""
        s = self.truth.sensor
        return fixed_point.from_calibration(
            np.linalg.inv(s.D), np.asarray(s.o), unit_per_count=1.0 / self.counts_per_unit, **kw
        )


def make_world(
    session: Session,
    truth: SimTruth,
    info: DeviceInfo,
    *,
    field_t: float = FIELD_STRENGTH_T,
    noise: bool = True,
    t0_us: int = 0,
) -> World:
    """The raw counts of a simulated session for a device with ``info``'s count scales.

    noise : True uses the session's noisy readings; False the noise-free ones (needs the
        truth's trajectory)
    t0_us : time of the session's t = 0, microseconds
    """
    if noise:
        gyr, acc, mag = session.gyr, session.acc, session.mag
    else:
        if truth.trajectory is None:
            raise WorldError("make_world: noise=False needs the truth's trajectory")
        tr = truth.trajectory
        gyr, acc, mag = ideal_measurements(truth.sensor, tr.q_nb, tr.omega_b, tr.acc_n)
    field_scale = truth.scenario.field_scale if truth.scenario is not None else 1.0
    mag_t = np.asarray(mag) * (field_t / field_scale)
    s_mag = info.sensor("mag").count_scale
    t_us = t0_us + np.rint(np.asarray(session.t) * 1e6).astype(np.int64)
    if np.any(np.diff(t_us) <= 0) or t_us[0] < 0:
        raise WorldError("make_world: times must increase by at least 1 us and start >= 0")
    return World(
        t_us=t_us,
        mag=quantise(mag_t, s_mag),
        acc=quantise(acc, info.sensor("acc").count_scale),
        gyr=quantise(gyr, info.sensor("gyr").count_scale),
        mag_t=mag_t,
        acc_si=np.asarray(acc, dtype=np.float64),
        gyr_si=np.asarray(gyr, dtype=np.float64),
        counts_per_unit=field_t / field_scale / s_mag.si,
        truth=truth,
    )


class FeedClient:
    """The SIL's feed socket: sends S/E/T lines, optionally pace_s apart."""

    def __init__(self, host: str, port: int, timeout_s: float = FEED_CONNECT_TIMEOUT_S) -> None:
        try:
            self._sock = socket.create_connection((host, port), timeout=timeout_s)
        except OSError as exc:
            raise WorldError(
                f"feed: cannot connect to {host}:{port} ({exc}); is the SIL running with "
                "--feed-tcp?"
            ) from exc
        self._sock.settimeout(FEED_SEND_TIMEOUT_S)
        self._sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)

    def send_lines(self, lines: list[str], pace_s: float = 0.0) -> None:
        """Send lines; with pace_s > 0, one line every pace_s seconds, else all at once."""
        try:
            if pace_s <= 0:
                self._sock.sendall("".join(lines).encode("ascii"))
                return
            for line in lines:
                self._sock.sendall(line.encode("ascii"))
                time.sleep(pace_s)
        except OSError as exc:
            raise WorldError(f"feed: send failed ({exc}); did the SIL exit?") from exc

    def send_world(self, world: World, start: int = 0, stop: int | None = None, pace_s=0.0):
        self.send_lines(world.lines(start, stop), pace_s)

    def close(self) -> None:
        self._sock.close()

    def __enter__(self) -> FeedClient:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
