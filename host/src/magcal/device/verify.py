# SPDX-License-Identifier: Apache-2.0
"""Checking the device's calibrated output: the field norm's spread and heading consistency.

:func:`verify` reads the device's active parameter set (``E_NO_PARAMS`` when there is none),
then

1. streams the **corrected** output (``corrected`` messages: ``m_b * 2^(out_exp - 31)``, the
   device's own fixed-point correction in the set's output unit; unit norm for a calibration
   from ``magcal calibrate``) and reports the spread of ``|m_b|`` (:func:`norm_spread`). Each
   message also carries its raw counts: the host recomputes the correction from the set it
   read (:func:`magcal.device.fixed_point.emulate`) and counts the messages that differ by
   more than 1 LSB (the device and the host must agree: a mismatch means the device does
   not use the set it reports);
2. unless disabled, streams **raw** samples for as long again, applies the same set on the host
   (bit-exact emulation) and measures heading consistency (:func:`heading_consistency`),
   which needs the accelerometer and gyroscope samples the corrected messages do not carry.

``--session``: the same heading measure on a recorded session (``magcal collect``'s file: µT
converted back to the device's counts), i.e. the active set applied to the data it was
calibrated from, or to a later recording.

**Heading consistency** (what it is, concretely). A calibration that is right makes the
tilt-compensated magnetic heading agree with the rotation the gyroscope measures. For each
window of ``window_s`` seconds the attitude at its first sample is found by TRIAD from the
accelerometer (up) and the corrected field; it is propagated through the window by
integrating the gyroscope; at every sample the TRIAD attitude from (acc, m_b) is compared with
the propagated one, and the heading error is the rotation between them about the vertical
(the yaw of ``C_mag C_gyro^T``; meaningful at any tilt, unlike the heading of one body axis).
Reported: the RMS and maximum over all samples, in degrees. What else enters, honestly: a
gyroscope bias b adds up to ``|b| * window_s`` (1 °/s over a 1 s window: up to 1°; a session
with a stationary start gives the bias, which is then removed); translational acceleration
tilts the TRIAD's vertical; and the field's horizontal part is only cos(dip) of it, so its
noise (and the accelerometer's, through the tilt) is amplified by about 1/cos(dip), 3 at a
dip of 72°. So it is a check with a floor of about a degree, not an accuracy
figure; a wrong calibration (an offset of 10 % of the field) gives several degrees. Also the
**dip** (the angle between the field and the horizontal plane) must be the same in every
orientation: its standard deviation is reported too.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from magcal.device import fixed_point
from magcal.device.client import (
    Corrected,
    DeviceClient,
    DeviceError,
    DeviceInfo,
    ParamWhich,
    Sample,
    StreamKind,
)
from magcal.device.collect import UT_PER_T_EXP10, scale_in, seq_gap
from magcal.device.generated import Status
from magcal.errors import MagcalError
from magcal.io.session import Session

log = logging.getLogger(__name__)

DEFAULT_SAMPLES = 500
#: Each message must arrive within this long (a device at 100 Hz sends one every 10 ms).
VERIFY_STREAM_TIMEOUT_S = 5.0
HEADING_WINDOW_S = 1.0
#: Rest at the start of a stream or session gives the gyroscope bias (rest_gyro_bias): the
#: first samples' median rate must be below REST_RATE_RAD_S, and the rest lasts at least
#: REST_MIN_SAMPLES.
REST_RATE_RAD_S = 0.05
REST_RATE_DEV_RAD_S = 0.03  # a MEMS gyroscope's noise is ~0.005 rad/s per axis at 100 Hz
REST_MARGIN_SAMPLES = 10
ACC_REST_TOL = 0.2
REST_MIN_SAMPLES = 20
#: Samples with |acc| outside g +- this (m/s^2) have no reliable vertical: skipped.
ACC_G_TOL = 1.5
STANDARD_GRAVITY = 9.80665


class VerifyError(MagcalError):
    """verify cannot run (no active parameter set, an unusable session)."""


@dataclass(frozen=True)
class NormSpread:
    """The field norm of the corrected output: n samples; mean, std, min, max in the output
    unit; rel_std = std/mean; rel_range = (max - min)/mean."""

    n: int
    mean: float
    std: float
    min: float
    max: float

    @property
    def rel_std(self) -> float:
        return self.std / self.mean if self.mean else math.inf

    @property
    def rel_range(self) -> float:
        return (self.max - self.min) / self.mean if self.mean else math.inf


@dataclass(frozen=True)
class HeadingConsistency:
    """rms_deg, max_deg : heading error (TRIAD vs gyro-propagated, module docstring);
    dip_mean_deg, dip_std_deg : the field's angle below the horizontal; n : samples used;
    windows : windows of window_s; gyro_bias : (3,) rad/s removed (zeros when no rest)."""

    n: int
    windows: int
    window_s: float
    rms_deg: float
    max_deg: float
    dip_mean_deg: float
    dip_std_deg: float
    gyro_bias: np.ndarray


@dataclass(frozen=True)
class VerifyReport:
    """norm : of the device's corrected stream; mismatches : corrected messages more than 1
    LSB from the host's emulation of the active set; dropped : seq gaps in the streams;
    heading : from the raw stream (None when skipped or not measurable, ``heading_note``
    says why); session_heading : from the --session file."""

    crc32: int
    params: fixed_point.DeviceParams
    norm: NormSpread
    mismatches: int
    dropped: int
    heading: HeadingConsistency | None
    heading_note: str
    session_heading: HeadingConsistency | None = None


# ----------------------------------------------------------------------------- measures
def norm_spread(m: np.ndarray) -> NormSpread:
    """The spread of |m| for m (N, 3) float, any unit (N >= 1)."""
    r = np.linalg.norm(np.asarray(m, dtype=np.float64).reshape(-1, 3), axis=1)
    if r.size == 0:
        raise VerifyError("verify: no samples to measure the field norm on")
    return NormSpread(int(r.size), float(r.mean()), float(r.std()), float(r.min()), float(r.max()))


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def triad(acc: np.ndarray, m: np.ndarray) -> np.ndarray:
    """(N, 3, 3) rotations C_nb (v_n = C v_b; n: x north, y west, z up) from the specific
    force acc (N, 3) (points up at rest) and the field m (N, 3) in the body frame."""
    up = _unit(acc)
    west = _unit(np.cross(up, m))  # up x field: the field's horizontal part turned +90°
    north = np.cross(west, up)
    return np.stack([north, west, up], axis=1)


def _rodrigues(w: np.ndarray) -> np.ndarray:
    """(3, 3) exp([w]x) for a rotation vector w (3,)."""
    th = float(np.linalg.norm(w))
    k = np.array([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]])
    if th < 1e-12:
        return np.eye(3) + k
    return np.eye(3) + math.sin(th) / th * k + (1 - math.cos(th)) / th**2 * (k @ k)


def rest_gyro_bias(gyr: np.ndarray, acc: np.ndarray) -> np.ndarray:
    """(3,) rad/s: the mean gyroscope reading over the rest at the start (zeros if none).

    The rest ends at the first sample whose rate differs from the first samples' median by
    more than REST_RATE_DEV_RAD_S or whose |acc| by more than ACC_REST_TOL; the last
    REST_MARGIN_SAMPLES before it are left out (a motion starts gently)."""
    if len(gyr) < REST_MIN_SAMPLES:
        return np.zeros(3)
    g0 = np.median(gyr[:REST_MIN_SAMPLES], axis=0)
    a = np.linalg.norm(acc, axis=1)
    a0 = np.median(a[:REST_MIN_SAMPLES])
    if np.linalg.norm(g0) > REST_RATE_RAD_S:  # moving from the start: no rest
        return np.zeros(3)
    moving = (np.linalg.norm(gyr - g0, axis=1) > REST_RATE_DEV_RAD_S) | (
        np.abs(a - a0) > ACC_REST_TOL
    )
    k = (int(np.argmax(moving)) if moving.any() else len(gyr)) - REST_MARGIN_SAMPLES
    return gyr[:k].mean(axis=0) if k >= REST_MIN_SAMPLES else np.zeros(3)


def heading_consistency(
    t: np.ndarray,
    acc: np.ndarray,
    gyr: np.ndarray,
    m: np.ndarray,
    window_s: float = HEADING_WINDOW_S,
) -> HeadingConsistency | None:
    """Heading consistency of a corrected field (module docstring).

    t : (N,) s; acc : (N, 3) m/s^2; gyr : (N, 3) rad/s; m : (N, 3) corrected field in the
    body frame (any unit). Returns None when fewer than two samples have a usable vertical.
    """
    t = np.asarray(t, dtype=np.float64)
    acc = np.asarray(acc, dtype=np.float64)
    gyr = np.asarray(gyr, dtype=np.float64)
    m = np.asarray(m, dtype=np.float64)
    bias = rest_gyro_bias(gyr, acc)
    w = gyr - bias
    c_mag = triad(acc, m)
    ok = np.abs(np.linalg.norm(acc, axis=1) - STANDARD_GRAVITY) < ACC_G_TOL
    errors: list[float] = []
    windows = 0
    k = 0
    n = len(t)
    while k < n:
        while k < n and not ok[k]:
            k += 1
        if k >= n:
            break
        end = int(np.searchsorted(t, t[k] + window_s, side="right"))
        c = c_mag[k]
        windows += 1
        for j in range(k + 1, end):
            # Rectangle rule on the mean rate of the step: C <- C exp([w dt]x).
            c = c @ _rodrigues(0.5 * (w[j - 1] + w[j]) * (t[j] - t[j - 1]))
            if ok[j]:
                d = c_mag[j] @ c.T
                errors.append(math.atan2(d[1, 0] - d[0, 1], d[0, 0] + d[1, 1]))
        k = max(end, k + 1)
    if len(errors) < 2:
        return None
    e = np.degrees(np.array(errors))
    up = _unit(acc[ok])
    dip = np.degrees(np.arcsin(np.clip(-np.einsum("ij,ij->i", up, _unit(m[ok])), -1, 1)))
    return HeadingConsistency(
        n=len(e),
        windows=windows,
        window_s=window_s,
        rms_deg=float(np.sqrt(np.mean(e**2))),
        max_deg=float(np.max(np.abs(e))),
        dip_mean_deg=float(dip.mean()),
        dip_std_deg=float(dip.std()),
        gyro_bias=bias,
    )


# ----------------------------------------------------------------------------- device
def read_active_params(client: DeviceClient) -> tuple[fixed_point.DeviceParams, int]:
    """The device's active set, decoded, and its CRC-32; VerifyError when there is none."""
    try:
        ps = client.param_get(ParamWhich.ACTIVE)
    except DeviceError as exc:
        if exc.status == Status.E_NO_PARAMS:
            raise VerifyError(
                f"verify on {client.url}: the device has no active parameter set "
                "(E_NO_PARAMS), so it has no corrected output to check: flash a calibration "
                "first (magcal flash RESULT.json --port URL)"
            ) from exc
        raise
    return fixed_point.decode(ps.blob), ps.crc32


def _stream(
    client: DeviceClient,
    kind: StreamKind,
    n: int | None,
    duration_s: float | None,
    clock: Callable[[], float],
) -> tuple[list, int]:
    """Messages of one stream (n of them, or for duration_s), and the seq gaps seen."""
    msgs: list = []
    gaps = 0
    client.stream_start(kind)
    try:
        start = clock()
        while (n is None or len(msgs) < n) and (duration_s is None or clock() - start < duration_s):
            msg = client.read_stream(VERIFY_STREAM_TIMEOUT_S)
            if msgs:
                gaps += seq_gap(msgs[-1].seq, msg.seq)
            msgs.append(msg)
    except BaseException as exc:
        # The error that stopped the reading is the one to report; a failed stop is logged.
        try:
            client.stream_stop()
        except (MagcalError, OSError) as stop_exc:
            log.warning(
                "verify on %s: could not stop the stream after %s (%s)",
                client.url,
                type(exc).__name__,
                stop_exc,
            )
        raise
    client.stream_stop()
    want = Corrected if kind == StreamKind.CORRECTED else Sample
    return [x for x in msgs if isinstance(x, want)], gaps


def verify(
    client: DeviceClient,
    info: DeviceInfo,
    *,
    n_samples: int | None = None,
    duration_s: float | None = None,
    heading: bool = True,
    session: Session | None = None,
    clock: Callable[[], float] = time.monotonic,
) -> VerifyReport:
    """Stream the corrected output and measure it (see the module docstring).

    n_samples / duration_s : how much of each stream (default DEFAULT_SAMPLES samples)
    heading : also stream raw samples for the heading consistency
    session : a recorded session (mag in uT) to measure the heading consistency on too
    """
    if n_samples is None and duration_s is None:
        n_samples = DEFAULT_SAMPLES
    # An unusable session is refused before anything is streamed.
    session_counts = session_mag_counts(info, session) if session is not None else None
    params, crc = read_active_params(client)
    cor, gaps = _stream(client, StreamKind.CORRECTED, n_samples, duration_s, clock)
    if not cor:
        raise VerifyError(f"verify on {client.url}: no corrected sample received")
    raw_mag = np.array([c.mag for c in cor], dtype=np.int64)
    out = np.array([c.m_b for c in cor], dtype=np.int64)
    exps = np.array([c.out_exp for c in cor], dtype=np.float64)
    m = np.ldexp(out.astype(np.float64), (exps - 31).astype(np.int64)[:, None])
    want = fixed_point.emulate(params, raw_mag).astype(np.int64)
    mismatches = int(
        np.count_nonzero((np.abs(out - want) > 1).any(axis=1) | (exps != params.out_exp))
    )
    head = None
    note = "skipped (--no-heading)"
    if heading:
        raw, raw_gaps = _stream(client, StreamKind.RAW, n_samples or len(cor), None, clock)
        gaps += raw_gaps
        head = _heading_of_counts(info, params, raw)
        note = "" if head is not None else "not measurable: no sample with |acc| near g"
    session_head = None
    if session is not None:
        session_head = _heading_of_session_counts(params, session, session_counts)
    return VerifyReport(crc, params, norm_spread(m), mismatches, gaps, head, note, session_head)


def _heading_of_counts(info: DeviceInfo, params, raw: list[Sample]) -> HeadingConsistency | None:
    if len(raw) < 2:
        return None
    t = np.array([s.t_us for s in raw], dtype=np.float64) / 1e6
    acc = info.sensor("acc").count_scale.counts_to_si(np.array([s.acc for s in raw]))
    gyr = info.sensor("gyr").count_scale.counts_to_si(np.array([s.gyr for s in raw]))
    mag = np.array([s.mag for s in raw], dtype=np.int64)
    m = fixed_point.output_to_float(params, fixed_point.emulate(params, mag))
    return heading_consistency(t, acc, gyr, m)


def heading_of_session(
    info: DeviceInfo, params: fixed_point.DeviceParams, session: Session
) -> HeadingConsistency | None:
    """Heading consistency of the active set applied to a session recorded by magcal
    collect (mag in uT, converted back to the device's counts: they must be whole counts)."""
    return _heading_of_session_counts(params, session, session_mag_counts(info, session))


def session_mag_counts(info: DeviceInfo, session: Session) -> np.ndarray:
    """(N, 3) int64: the session's magnetometer (µT, as magcal collect writes it) as this
    device's raw counts. VerifyError when its mag_unit is not uT or the values are not whole
    counts of this device's magnetometer."""
    unit = session.meta.get("mag_unit", "").strip()
    if unit != "uT":
        raise VerifyError(
            f"verify: the session's mag_unit is {unit or 'not given'!r}; the device's set "
            "applies to sessions in uT recorded with magcal collect"
        )
    per_count_ut = scale_in(info.sensor("mag").count_scale, UT_PER_T_EXP10).si
    counts = session.mag / per_count_ut
    rounded = np.rint(counts)
    if (
        np.max(np.abs(counts - rounded), initial=0.0) > 1e-3
        or np.max(np.abs(rounded), initial=0.0) > 32768
    ):
        raise VerifyError(
            "verify: the session's magnetometer values are not whole counts of this device's "
            "magnetometer: was it recorded from another device or sensor range?"
        )
    return rounded.astype(np.int64)


def _heading_of_session_counts(
    params: fixed_point.DeviceParams, session: Session, counts: np.ndarray
) -> HeadingConsistency | None:
    m = fixed_point.output_to_float(params, fixed_point.emulate(params, counts))
    return heading_consistency(session.t, session.acc, session.gyr, m)
