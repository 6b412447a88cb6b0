# SPDX-License-Identifier: Apache-2.0
"""World simulator for the SIL device: a simulated session turned into the sensor-feed lines.

(In the package, not the tests, so that ``make demo`` can use it too; :func:`tumbling_session`
and :class:`WorldFeeder` are for feeding in real time.)

The SIL executable (build/sil/magcal-sil) reads its sensors from a TCP "feed" socket, one text
line per event (firmware/port/posix/sensor_feed.h):

    P t_us bx by bz ax ay az gx gy gz     one sample in physical units (T, m/s^2, rad/s)
    S t_us mx my mz ax ay az gx gy gz     one sample in int16 raw counts (tests that script
                                          exact counts write these themselves)
    E t_us                                a failed read
    T t_us                                the clock moves

The world sends P lines: what the sensors physically see. The device quantises them to raw
counts with its own count scales, as a sensor's ADC would; the world does not quantise.

:func:`make_world` takes a session and its truth from ``magcal.sim`` (``simulate(preset(...),
seed)``) and gives what the device's sensors see, sample by sample:

- magnetometer: the session's reading (``D R_bn m_n + o`` plus noise, in field units since
  ``m_n`` is a unit vector) times ``field_t / field_scale`` tesla (default 50 uT), i.e. the
  field distorted by soft iron, hard iron and misalignment, in the sensor's own axes;
- accelerometer m/s^2 and gyroscope rad/s in the body frame, as simulated (with noise);
- times in microseconds.

:func:`device_counts` predicts the counts the device makes of those values. It mirrors the
port's rule (mc_sensor_quantise in sensor_feed.c) operation for operation in IEEE-754
doubles, so the prediction is exact, not approximate: the value of a count
(:func:`count_si`: num / den, times or divided by 10^|exp10|, times the unit's factor as a
double), one division, round to nearest with halves away from zero, saturation at the int16
limits (not at the nominal full scale). The values go on the wire as Python's ``repr`` of
each float, which the device's strtod reads back to the same double.

:class:`FeedClient` connects to the feed socket and sends the lines, optionally paced.

For a live device (a ``magcal collect`` running against the SIL): :func:`tumbling_session`
draws a random distortion (soft iron x misalignment D and hard iron o, as the MEMS or
hand-held samplers of ``magcal.sim`` draw them, from the seed) and a tumbling motion;
:class:`WorldFeeder` feeds a :class:`World` from a thread, paced in real time or at a speed-up
(the device's clock is the feed's ``t_us``, so a speed-up of 4 makes 40 s of device time in
10 s), and can pause (the device's time then stands still), resume and switch to another
world with the same times (e.g. the noise-free readings of the same motion).
"""

from __future__ import annotations

import math
import socket
import threading
import time
from dataclasses import dataclass, replace

import numpy as np

from magcal.device import fixed_point
from magcal.device.client import DeviceInfo, Scale
from magcal.device.generated import Unit
from magcal.errors import MagcalError
from magcal.io.session import Session
from magcal.sim.model import ideal_measurements
from magcal.sim.scenarios import SimTruth, preset, simulate

__all__ = [
    "FEED_CONNECT_TIMEOUT_S",
    "FEED_SEND_TIMEOUT_S",
    "FIELD_STRENGTH_T",
    "FeedClient",
    "World",
    "WorldError",
    "WorldFeeder",
    "count_si",
    "device_counts",
    "make_world",
    "physical_line",
    "tumbling_session",
]

FIELD_STRENGTH_T = 50e-6  # local field magnitude, tesla (mid-latitude Earth field)
FEED_CONNECT_TIMEOUT_S = 5.0
FEED_SEND_TIMEOUT_S = 5.0


class WorldError(MagcalError):
    """The world cannot be fed to the device (bad scales, non-finite values, socket)."""


# The SI factor of each unit as the port has it: one double each (sensor_feed.c,
# unit_si_factor; its pi is math.pi, so pi / 180 is the same double).
_UNIT_FACTOR_DOUBLE: dict[Unit, float] = {
    Unit.TESLA: 1.0,
    Unit.GAUSS: 1e-4,
    Unit.METRE_PER_S2: 1.0,
    Unit.STANDARD_GRAVITY: 9.80665,
    Unit.RAD_PER_S: 1.0,
    Unit.DEG_PER_S: math.pi / 180.0,
}
SCALE_EXP10_MIN, SCALE_EXP10_MAX = -18, 18


def count_si(scale: Scale) -> float:
    """The value of one count in SI units exactly as the port computes it (a mirror of
    mc_sensor_count_si): ``num / den``, then times ``10**exp10`` (divided by ``10**-exp10``
    when negative; powers of ten up to 10^18 are exact doubles), then times the unit's factor,
    each one double operation. Within a few ulp of :attr:`Scale.si` (the exact value rounded
    once), but this is the one the device divides by."""
    factor = _UNIT_FACTOR_DOUBLE.get(scale.unit)
    if (
        factor is None
        or scale.num <= 0
        or scale.den <= 0
        or not SCALE_EXP10_MIN <= scale.exp10 <= SCALE_EXP10_MAX
    ):
        raise WorldError(f"count_si: {scale} is not a valid count scale; check the device info")
    v = float(scale.num) / float(scale.den)
    p10 = float(10 ** abs(scale.exp10))
    v = v / p10 if scale.exp10 < 0 else v * p10
    return v * factor


def device_counts(values_si: np.ndarray, scale: Scale) -> np.ndarray:
    """The int16 counts the SIL device makes of physical values (a mirror of the port's
    mc_sensor_quantise, firmware/port/posix/sensor_feed.h), exactly:

    q = value / count_si(scale); q >= 32767 -> 32767, q <= -32768 -> -32768 (saturation at the
    int16 register limits); otherwise the nearest integer, halves away from zero (0.5 -> 1,
    -2.5 -> -3), from the exact fraction ``|q| - trunc(|q|)`` (no ``q + 0.5`` rounding).

    values_si : (...,) float, SI units of scale (T, m/s^2, rad/s). Returns int16, same shape.
    Non-finite values raise WorldError (the device refuses such a line).
    """
    v = np.asarray(values_si, dtype=np.float64)
    if not np.all(np.isfinite(v)):
        raise WorldError("device_counts: non-finite value; check the simulated session")
    with np.errstate(over="ignore"):
        q = v / count_si(scale)  # may overflow to +-inf: saturates below
    a = np.abs(q)
    n = np.trunc(np.minimum(a, 32768.0))
    n = n + (a - n >= 0.5)
    c = np.where(q < 0.0, -n, n)
    c = np.where(q >= 32767.0, 32767.0, np.where(q <= -32768.0, -32768.0, c))
    return c.astype(np.int16)


def physical_line(t_us: int, mag_t, acc_si, gyr_si) -> str:
    """One P line (ending in a newline): magnetometer in tesla, accelerometer in m/s^2,
    gyroscope in rad/s, each value as Python's repr (exact: strtod reads back the same
    double). Non-finite values raise WorldError (the device would refuse the line)."""
    vals = [float(x) for x in (*mag_t, *acc_si, *gyr_si)]
    if len(vals) != 9:
        raise WorldError(f"physical_line: 9 values needed, got {len(vals)}")
    if not all(math.isfinite(x) for x in vals):
        raise WorldError("physical_line: non-finite value; the device would refuse the line")
    return f"P {int(t_us)} " + " ".join(repr(x) for x in vals) + "\n"


@dataclass(frozen=True)
class World:
    """What the device's sensors see, sample by sample, and the counts it will make of it.

    t_us : (N,) int64, microseconds
    mag_t : (N, 3) float, the magnetometer's field in tesla, its own axes (what is sent)
    acc_si, gyr_si : (N, 3) float, m/s^2 and rad/s, body frame (what is sent)
    mag, acc, gyr : (N, 3) int16, the raw counts the device will make of them
        (:func:`device_counts`, exact)
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
        """The P lines of samples [start, stop), each ending in a newline."""
        return [
            physical_line(self.t_us[k], self.mag_t[k], self.acc_si[k], self.gyr_si[k])
            for k in range(start, len(self) if stop is None else stop)
        ]

    def indices(self, t_us) -> np.ndarray:
        """The sample indices of device times ``t_us`` (each must be one of this world's
        times exactly; WorldError otherwise): how a streamed sample finds its truth."""
        t = np.asarray(t_us, dtype=np.int64)
        k = np.searchsorted(self.t_us, t)
        bad = (k >= len(self)) | (self.t_us[np.minimum(k, len(self) - 1)] != t)
        if np.any(bad):
            raise WorldError(
                f"world: {int(bad.sum())} device time(s) were never fed by this world, e.g. "
                f"{int(t[bad][0])} us"
            )
        return k

    def calibration_counts(self) -> tuple[np.ndarray, np.ndarray]:
        """The true (D, o) in the device's raw magnetometer counts: ``(k D, k o)`` with
        k = :attr:`counts_per_unit` (the device reads ``k (D R m + o)`` counts, unit m)."""
        s = self.truth.sensor
        k = self.counts_per_unit
        return k * np.asarray(s.D, dtype=np.float64), k * np.asarray(s.o, dtype=np.float64)

    def truth_counts(self) -> SimTruth:
        """The truth with its sensor's D and o in raw counts (:meth:`calibration_counts`),
        e.g. for ``magcal_evaluation.accuracy.heading_rms_deg`` against a result in counts."""
        D, o = self.calibration_counts()
        k = self.counts_per_unit
        sensor = replace(self.truth.sensor, D=D, o=o, Sigma_mag=k * k * self.truth.sensor.Sigma_mag)
        return replace(self.truth, sensor=sensor)

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
    """What the sensors of a device with ``info``'s count scales see during a simulated
    session, and the counts the device will make of it.

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
    acc_si = np.asarray(acc, dtype=np.float64)
    gyr_si = np.asarray(gyr, dtype=np.float64)
    return World(
        t_us=t_us,
        mag=device_counts(mag_t, s_mag),
        acc=device_counts(acc_si, info.sensor("acc").count_scale),
        gyr=device_counts(gyr_si, info.sensor("gyr").count_scale),
        mag_t=mag_t,
        acc_si=acc_si,
        gyr_si=gyr_si,
        counts_per_unit=field_t / field_scale / s_mag.si,
        truth=truth,
    )


class FeedClient:
    """The SIL's feed socket: sends P/S/E/T lines, optionally pace_s apart."""

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


def tumbling_session(
    duration_s: float,
    seed: int,
    *,
    kind: str = "mems",
    rate_hz: float = 100.0,
    stationary_s: float = 1.0,
    **overrides: object,
) -> tuple[Session, SimTruth]:
    """A tumbling session with a random distortion, for feeding a live device.

    kind : "mems" (moderate soft iron and misalignment, offsets comparable to the field) or
        "handheld" (a magnet next to the sensor: strong soft iron, offsets 3-6 times the
        field, fast motion with translational acceleration) -- the presets of
        ``magcal.sim.scenarios``; D (soft iron x misalignment), o and the noise are drawn
        from ``seed`` as their samplers draw them
    duration_s : length of the motion after stationary_s of rest, s
    overrides : further ScenarioConfig settings (e.g. ``max_rate_rad_s``)

    The session's field has magnitude 1 (``field_scale`` 1); :func:`make_world` turns it into
    tesla (default 50 uT).
    """
    if kind not in ("mems", "handheld"):
        raise WorldError(f"tumbling_session: kind must be 'mems' or 'handheld', got {kind!r}")
    config = preset(
        kind,
        duration_s=float(duration_s),
        stationary_s=float(stationary_s),
        rate_hz=float(rate_hz),
        motion="tumble",
        **overrides,
    )
    return simulate(config, seed)


#: How often the feeder thread wakes up to send what is due, s.
FEEDER_TICK_S = 0.005
#: How long WorldFeeder's waits may take by default, s.
FEEDER_WAIT_TIMEOUT_S = 10.0


class WorldFeeder:
    """Feeds a :class:`World` to the SIL's feed socket from a thread, paced.

    speedup : device seconds per wall-clock second (1 = real time); ``math.inf`` sends as
        fast as the socket takes it
    start : the first sample to feed

    The feeder starts paused: :meth:`resume` starts (or continues) feeding from the next
    sample, with the pacing re-anchored at that moment, so a pause does not make the device's
    clock jump. :meth:`pause` returns once nothing more is being sent. :meth:`switch` changes
    the world fed from the next sample on (another reading of the same motion: same times).
    :attr:`fed` is the number of samples sent so far (the next index). When the world runs
    out the feeder pauses and sets :attr:`exhausted`. A failure in the thread (the SIL exited)
    is kept and raised by the next call (:meth:`check`).
    """

    def __init__(
        self, world: World, feed: FeedClient, *, speedup: float = 1.0, start: int = 0
    ) -> None:
        if not speedup > 0:
            raise WorldError(f"WorldFeeder: speedup must be positive, got {speedup!r}")
        self._world = world
        self._feed = feed
        self.speedup = float(speedup)
        self._next = int(start)
        self._lock = threading.Lock()
        self._running = threading.Event()
        self._idle = threading.Event()
        self._idle.set()
        self._stop = threading.Event()
        self.exhausted = threading.Event()
        self._error: BaseException | None = None
        self._thread = threading.Thread(target=self._run, name="world-feeder", daemon=True)
        self._thread.start()

    @property
    def world(self) -> World:
        return self._world

    @property
    def fed(self) -> int:
        """How many samples have been sent (the index of the next one)."""
        with self._lock:
            return self._next

    def check(self) -> None:
        """Raise the thread's failure, if any (as WorldError)."""
        if self._error is not None:
            raise WorldError(f"world feeder failed: {self._error}") from self._error

    def resume(self) -> None:
        self.check()
        if self.exhausted.is_set():
            raise WorldError(
                f"world feeder: all {len(self._world)} samples were fed; make a longer world"
            )
        # Under the lock: the thread's "not running, so idle" is one step (see _run), so a
        # set() of _idle from before this resume cannot land after it.
        with self._lock:
            self._idle.clear()
            self._running.set()

    def pause(self, timeout_s: float = FEEDER_WAIT_TIMEOUT_S) -> None:
        """Stop sending (after the line being sent); returns when the thread is idle."""
        self._running.clear()
        if not self._idle.wait(timeout_s):
            raise WorldError(f"world feeder: did not pause within {timeout_s} s")
        self.check()

    def switch(self, world: World) -> None:
        """Feed ``world`` from the next sample on; its times must be this world's."""
        if not np.array_equal(world.t_us, self._world.t_us):
            raise WorldError("world feeder: switch needs a world with the same sample times")
        with self._lock:
            self._world = world

    def wait_fed(self, n: int, timeout_s: float = FEEDER_WAIT_TIMEOUT_S) -> None:
        """Wait until n samples have been fed (WorldError on timeout or exhaustion)."""
        deadline = time.monotonic() + timeout_s
        while self.fed < n:
            self.check()
            if self.exhausted.is_set():
                raise WorldError(f"world feeder: ran out at {self.fed} samples, {n} wanted")
            if time.monotonic() > deadline:
                raise WorldError(f"world feeder: {self.fed} of {n} samples fed in {timeout_s} s")
            time.sleep(FEEDER_TICK_S)

    def close(self, timeout_s: float = FEEDER_WAIT_TIMEOUT_S) -> None:
        """Stop the thread (does not close the feed socket)."""
        self._stop.set()
        self._running.set()  # wake it
        self._thread.join(timeout_s)
        if self._thread.is_alive():
            raise WorldError(f"world feeder: thread did not stop within {timeout_s} s")

    def __enter__(self) -> WorldFeeder:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _run(self) -> None:
        try:
            while not self._stop.is_set():
                # The check and the set() together, under resume()'s lock: idle is set only
                # while no resume() has come since the check (the only place it is set while
                # the thread runs).
                with self._lock:
                    running = self._running.is_set()
                    if not running:
                        self._idle.set()
                if not running:
                    self._running.wait()
                    continue
                self._feed_until_paused()
        except BaseException as exc:  # kept for the caller: check() raises it
            self._error = exc
            self._running.clear()
        finally:
            self._idle.set()

    def _feed_until_paused(self) -> None:
        with self._lock:
            first = self._next
        t0_us = int(self._world.t_us[first]) if first < len(self._world) else 0
        wall0 = time.monotonic()
        while self._running.is_set() and not self._stop.is_set():
            with self._lock:
                world, k = self._world, self._next
            n = len(world)
            if k >= n:
                self.exhausted.set()
                self._running.clear()
                break
            if math.isinf(self.speedup):
                due = min(n, k + 100)
            else:
                t_now_us = t0_us + (time.monotonic() - wall0) * self.speedup * 1e6
                due = int(np.searchsorted(world.t_us, t_now_us, side="right"))
            if due > k:
                self._feed.send_lines(world.lines(k, due))
                with self._lock:
                    self._next = due
            else:
                time.sleep(FEEDER_TICK_S)
