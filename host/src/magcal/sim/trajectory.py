# SPDX-License-Identifier: Apache-2.0
"""Simulated motion: attitude, body rate and translational acceleration at the sample times.

A trajectory is a stationary stretch followed by motion. The attitude during motion is a
cumulative cubic B-spline on SO(3) (Kim, Kim & Shin 1995) through control orientations:

    q(u) = c_i ⊙ Exp(B̃₁(u) Ω_i) ⊙ Exp(B̃₂(u) Ω_{i+1}) ⊙ Exp(B̃₃(u) Ω_{i+2}),
    Ω_k = Log(c_k* ⊙ c_{k+1}),  u = (τ − i Δ) / Δ ∈ [0, 1),

with ``Exp``/``Log`` the rotation-vector maps. The cumulative basis derivatives
``B̃₁' = (1−u)²/2``, ``B̃₂' = (1 + 2u − 2u²)/2``, ``B̃₃' = u²/2`` are non-negative and sum to
exactly 1, so the angular rate never exceeds ``max_k ‖Ω_k‖ / Δ``. Choosing the knot spacing
``Δ = step_max / max_rate`` with all control steps ``‖Ω_k‖ ≤ step_max`` therefore bounds the rate
by ``max_rate`` — on the continuous curve, and also for the per-sample rates below (the angle
between two samples is at most the integral of the rate). The first three controls are equal
(a clamped start), so the motion starts from rest with zero angular acceleration.

The body rate is *defined* from consecutive samples, ``ω_t = Log(q_t* ⊙ q_{t+1}) / T``, so the
paper's dynamics ``q_{t+1} = q_t ⊙ exp_q(½ T ω_t)`` hold exactly: a perfect gyroscope integrates
to the true attitude (up to float round-off). ``q_nb`` is kept sign-continuous
(``q_t · q_{t+1} ≥ 0``) for that reason; it is not in the canonical ``w ≥ 0`` form.

Motions:

* ``"tumble"``: controls on greedy nearest-neighbour tours through randomly rotated
  super-Fibonacci grids of SO(3) (:func:`magcal.calib.frames.so3_grid`), long hops subdivided
  to ``TUMBLE_STEP_RAD``. Each tour visits every grid orientation once, so the whole of SO(3) is
  covered at the grid's resolution; longer sessions repeat tours on freshly rotated grids.
  A session shorter than about two tours keeps the best of TUMBLE_CANDIDATES candidate tours
  by :func:`orientation_spread`. A tour needs path length: at 100 Hz, the paper's 300 rotating
  samples (3 s) need rates of several rad/s to visit diverse orientations.
* ``"yaw-only"``: rotation about the vertical only (body z stays along nav z).
* ``"small"``: a wobble of at most about ``small_amplitude_rad`` around one orientation.
* ``"swing"``: the tumble, with fast swings about the body's x axis on top
  (:data:`SWING_AMPLITUDE_RAD` at :data:`SWING_HZ`): the gyroscope turns mostly about one
  axis, as a sensor on a swinging arm or a pendulum does.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from magcal.calib import frames
from magcal.errors import MagcalError

MOTIONS = ("tumble", "yaw-only", "small", "swing")

# "swing": amplitude and frequency of the swing about body x. 40° at 1 Hz peaks at 4.4 rad/s,
# several times a hand's tumbling rate, so that most of the rotation is about x.
SWING_AMPLITUDE_RAD = np.deg2rad(40.0)
SWING_HZ = 1.0

# Largest angle between consecutive spline controls (rad) for "tumble" and "yaw-only".
TUMBLE_STEP_RAD = 1.0
YAW_STEP_RAD = 1.0
# Grid size of one "tumble" tour: fewer points for short sessions (so that one tour fits),
# at most this many (grid spacing ≈ 45°).
TUMBLE_LAP_MIN_POINTS = 8
TUMBLE_LAP_MAX_POINTS = 48
# Short "tumble" sessions keep the best of this many candidate tours, scored by
# orientation_spread on this many points of the motion. With 8, one of the 150 Table 2
# sessions (seed 97) covered so little that the magnetometer-coverage check refused it:
# not the "rotation through all orientations" the preset promises. 16 leaves none below
# the check (smallest coverage figure 0.035 against 0.03); 32 gains nothing more.
TUMBLE_CANDIDATES = 16
TUMBLE_SCORE_POINTS = 300
# Probability that a "yaw-only" control step reverses the turning direction.
YAW_REVERSAL_PROB = 0.15

# Translational acceleration: pass band of the random process and the raised-cosine ramp at
# the start and end of the motion.
ACC_BAND_HZ = (0.2, 2.0)
ACC_TAPER_S = 0.5

# Accelerometer bumps: length 1..BUMP_MAX_SAMPLES, magnitude uniform in the range, constant
# over the bump, one bump per slot of BUMP_SLOT_SAMPLES (so bumps never touch).
BUMP_MAX_SAMPLES = 3
BUMP_SLOT_SAMPLES = 4
BUMP_MIN_M_S2 = 5.0
BUMP_MAX_M_S2 = 20.0


@dataclass(frozen=True)
class Trajectory:
    """True motion at the sample times.

    t            : (N,) float, s, ``t_k = k / rate_hz``
    q_nb         : (N, 4) float, body→nav unit quaternions, sign-continuous
    omega_b      : (N, 3) float, rad/s, body rate over [t_k, t_{k+1}]:
                   ``q_{k+1} = q_k ⊙ exp_q(½ T ω_k)``
    acc_n        : (N, 3) float, m/s², translational acceleration in n (smooth part + bumps)
    bumps        : (K, 2) int, [first sample, length] of each accelerometer bump
    n_stationary : int, number of samples at rest at the start
    """

    t: np.ndarray
    q_nb: np.ndarray
    omega_b: np.ndarray
    acc_n: np.ndarray
    bumps: np.ndarray
    n_stationary: int

    def __len__(self) -> int:
        return int(self.t.shape[0])


def random_rotation(rng: np.random.Generator) -> np.ndarray:
    """A uniformly distributed unit quaternion (4,) (normalised 4-D Gaussian)."""
    return frames.quat_normalize(rng.standard_normal(4))


def _spread_directions() -> np.ndarray:
    """13 nav directions, one per antipodal pair: 3 axes, 6 face and 4 body diagonals."""
    v = [[1, 0, 0], [0, 1, 0], [0, 0, 1]]
    v += [[1, 1, 0], [1, -1, 0], [1, 0, 1], [1, 0, -1], [0, 1, 1], [0, 1, -1]]
    v += [[1, 1, 1], [1, 1, -1], [1, -1, 1], [1, -1, -1]]
    a = np.asarray(v, dtype=float)
    return a / np.linalg.norm(a, axis=-1, keepdims=True)


def orientation_spread(q_nb: np.ndarray) -> float:
    """How evenly orientations (N, 4) cover SO(3), in [0, 1/3].

    For each of 13 nav directions v (axes, face and body diagonals) take the smallest
    eigenvalue of the scatter ``mean(u uᵀ)`` of its body-frame images ``u = R_bn v``; return
    the smallest over v. 1/3 for a uniform cover of SO(3); 0 when some nav direction never
    leaves a plane of the body (yaw-only motion keeps ``R_bn e_z`` fixed).
    """
    R_nb = frames.quat_to_matrix(np.asarray(q_nb, dtype=float))
    u = np.einsum("kji,dj->dki", R_nb, _spread_directions())  # (13, N, 3): R_bn v
    scatter = np.einsum("dki,dkj->dij", u, u) / R_nb.shape[0]
    return float(np.linalg.eigvalsh(scatter)[:, 0].min())


def rotation_angle(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Angle (rad, [0, π]) of the rotation between unit quaternions p and q, (..., 4) → (...)."""
    d = np.abs(np.sum(np.asarray(p) * np.asarray(q), axis=-1))
    return 2.0 * np.arccos(np.clip(d, 0.0, 1.0))


def spline_so3(controls: np.ndarray, knot_s: float, tau: np.ndarray) -> np.ndarray:
    """Cumulative cubic B-spline on SO(3) (see module docstring).

    controls : (M, 4) unit quaternions, M ≥ 4
    knot_s   : knot spacing Δ, s
    tau      : (N,) times ≥ 0, s; segment i covers [iΔ, (i+1)Δ), times past the last segment
               extrapolate it
    returns  : (N, 4) unit quaternions
    """
    controls = np.asarray(controls, dtype=float)
    m = controls.shape[0]
    omega = frames.quat_to_rotvec(
        frames.quat_multiply(frames.quat_conjugate(controls[:-1]), controls[1:])
    )
    ug = np.asarray(tau, dtype=float) / knot_s
    i = np.clip(np.floor(ug).astype(np.int64), 0, m - 4)
    u = ug - i
    b1 = (5.0 + 3.0 * u - 3.0 * u**2 + u**3) / 6.0
    b2 = (1.0 + 3.0 * u + 3.0 * u**2 - 2.0 * u**3) / 6.0
    b3 = u**3 / 6.0
    q = controls[i]
    for k, b in enumerate((b1, b2, b3)):
        q = frames.quat_multiply(q, frames.rotvec_to_quat(b[:, None] * omega[i + k]))
    return q


def _make_sign_continuous(q: np.ndarray) -> np.ndarray:
    """Flip signs so that consecutive quaternions have a non-negative dot product."""
    flips = np.sum(q[:-1] * q[1:], axis=-1) < 0.0
    sign = np.concatenate([[1.0], np.where(np.cumsum(flips) % 2 == 1, -1.0, 1.0)])
    return q * sign[:, None]


def body_rates(q_nb: np.ndarray, rate_hz: float) -> np.ndarray:
    """``ω_k = Log(q_k* ⊙ q_{k+1}) · rate_hz``; q_nb (N+1, 4) → (N, 3) rad/s.

    Identical consecutive quaternions give exactly zero (no round-off rate at rest).
    """
    dq = frames.quat_multiply(frames.quat_conjugate(q_nb[:-1]), q_nb[1:])
    omega = frames.quat_to_rotvec(dq) * rate_hz
    same = np.all(q_nb[:-1] == q_nb[1:], axis=-1)
    omega[same] = 0.0
    return omega


def tumble_controls(
    rng: np.random.Generator, start: np.ndarray, count: int, step_max: float = TUMBLE_STEP_RAD
) -> np.ndarray:
    """``count`` control orientations (count, 4) after ``start`` touring SO(3).

    Tours: greedy nearest-neighbour order through a randomly rotated super-Fibonacci grid; the
    grid size is ``count // 2`` clipped to [TUMBLE_LAP_MIN_POINTS, TUMBLE_LAP_MAX_POINTS], so
    that a short session still makes about one full tour. Each hop between grid points is cut
    into equal geodesic steps of at most ``step_max`` rad.
    """
    lap = int(np.clip(count // 2, TUMBLE_LAP_MIN_POINTS, TUMBLE_LAP_MAX_POINTS))
    grid0 = frames.so3_grid(lap)
    waypoints = [np.asarray(start, dtype=float)[None]]
    n_sub: list[int] = []
    total = 0
    current = waypoints[0][0]
    while total < count:
        grid = frames.quat_multiply(random_rotation(rng), grid0)
        left = np.ones(lap, dtype=bool)
        while left.any() and total < count:  # the order only; no per-step maths here
            idx = np.flatnonzero(left)
            angle = rotation_angle(current, grid[idx])
            j = int(np.argmin(angle))
            left[idx[j]] = False
            n_sub.append(max(1, int(np.ceil(angle[j] / step_max))))
            total += n_sub[-1]
            current = grid[idx[j]]
            waypoints.append(current[None])
    w = np.concatenate(waypoints)
    n_sub_a = np.asarray(n_sub)
    # Geodesic subdivision, vectorised over all hops: step s of hop h is a_h ⊙ Exp(s/n_h φ_h).
    phi = frames.quat_to_rotvec(frames.quat_multiply(frames.quat_conjugate(w[:-1]), w[1:]))
    hop = np.repeat(np.arange(n_sub_a.size), n_sub_a)
    first = np.cumsum(n_sub_a) - n_sub_a
    frac = (np.arange(hop.size) - first[hop] + 1.0) / n_sub_a[hop]
    out = frames.quat_multiply(w[:-1][hop], frames.rotvec_to_quat(frac[:, None] * phi[hop]))
    return out[:count]


def yaw_controls(
    rng: np.random.Generator, yaw0: float, count: int, step_max: float = YAW_STEP_RAD
) -> np.ndarray:
    """``count`` yaw-only controls after yaw0: steps U(0.5, 1)·step_max, turning direction
    reversing with probability YAW_REVERSAL_PROB per step."""
    steps = rng.uniform(0.5, 1.0, count) * step_max
    reverse = rng.random(count) < YAW_REVERSAL_PROB
    direction = np.where(np.cumsum(reverse) % 2 == 1, -1.0, 1.0)
    yaw = yaw0 + np.cumsum(direction * steps)
    return frames.rotvec_to_quat(np.stack([np.zeros(count), np.zeros(count), yaw], -1))


def small_controls(
    rng: np.random.Generator, center: np.ndarray, count: int, amplitude_rad: float
) -> np.ndarray:
    """``count`` controls ``center ⊙ Exp(φ)`` with φ uniform in the ball ‖φ‖ ≤ amplitude_rad.

    Consecutive controls are at most ``2 · amplitude_rad`` apart.
    """
    d = rng.standard_normal((count, 3))
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    r = amplitude_rad * rng.random(count) ** (1.0 / 3.0)
    return frames.quat_multiply(center, frames.rotvec_to_quat(d * r[:, None]))


def band_limited_acceleration(
    rng: np.random.Generator, n: int, rate_hz: float, rms_m_s2: float
) -> np.ndarray:
    """(n, 3) zero-mean smooth random acceleration, m/s², pass band ACC_BAND_HZ.

    Gaussian random spectrum in the pass band, a raised-cosine ramp of ACC_TAPER_S (at most a
    quarter of the window) at both ends, then scaled so that ``sqrt(mean ‖a‖²)`` equals
    ``rms_m_s2`` exactly over the n samples.
    """
    if n == 0 or rms_m_s2 == 0.0:
        return np.zeros((n, 3))
    f = np.fft.rfftfreq(n, 1.0 / rate_hz)
    band = (f >= ACC_BAND_HZ[0]) & (f <= ACC_BAND_HZ[1])
    if not band.any():  # window too short to resolve the band: take its lowest frequency
        band = np.zeros_like(band)
        band[min(1, f.size - 1)] = True
    spec = rng.standard_normal((f.size, 3)) + 1j * rng.standard_normal((f.size, 3))
    spec[~band] = 0.0
    a = np.fft.irfft(spec, n=n, axis=0)
    ramp_n = int(min(ACC_TAPER_S * rate_hz, n // 4))
    if ramp_n > 0:
        ramp = 0.5 - 0.5 * np.cos(np.pi * (np.arange(ramp_n) + 0.5) / ramp_n)
        a[:ramp_n] *= ramp[:, None]
        a[n - ramp_n :] *= ramp[::-1, None]
    rms = np.sqrt(np.mean(np.sum(a * a, axis=-1)))
    if rms == 0.0:  # n == 1 with the only bin at DC
        return np.zeros((n, 3))
    return a * (rms_m_s2 / rms)


def accelerometer_bumps(
    rng: np.random.Generator, first: int, n: int, count: int
) -> tuple[np.ndarray, np.ndarray]:
    """``count`` short impulses in samples [first, first + n).

    Returns (bumps (K, 2) int [start, length], acc (n, 3) m/s² the impulses on that window).
    Each bump lasts 1..BUMP_MAX_SAMPLES samples, has a magnitude U(BUMP_MIN_M_S2,
    BUMP_MAX_M_S2) in a random direction, and starts at a random slot of BUMP_SLOT_SAMPLES.
    """
    acc = np.zeros((n, 3))
    if count == 0:
        return np.zeros((0, 2), dtype=np.int64), acc
    slots = n // BUMP_SLOT_SAMPLES
    if count > slots:
        raise MagcalError(
            f"simulate: {count} accelerometer bumps do not fit into {n} samples of motion "
            f"(at most {slots}): ask for fewer bumps or a longer motion"
        )
    start = np.sort(rng.choice(slots, size=count, replace=False)) * BUMP_SLOT_SAMPLES
    length = rng.integers(1, BUMP_MAX_SAMPLES + 1, size=count)
    d = rng.standard_normal((count, 3))
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    mag = rng.uniform(BUMP_MIN_M_S2, BUMP_MAX_M_S2, count)
    for s, ln, v in zip(start, length, d * mag[:, None], strict=True):  # K iterations
        acc[s : s + ln] = v
    return np.stack([start + first, length], axis=-1).astype(np.int64), acc


def make_trajectory(
    rng: np.random.Generator,
    rate_hz: float,
    stationary_s: float,
    duration_s: float,
    motion: str = "tumble",
    max_rate_rad_s: float = 1.0,
    small_amplitude_rad: float = np.deg2rad(10.0),
    acc_rms_m_s2: float = 0.0,
    n_bumps: int = 0,
) -> Trajectory:
    """A stationary stretch, then motion; see the module docstring.

    rate_hz             : sample rate, Hz
    stationary_s        : length of the rest at the start, s (0 = start moving at once)
    duration_s          : length of the motion, s
    motion              : "tumble", "yaw-only" or "small"
    max_rate_rad_s      : bound on the angular rate, rad/s
    small_amplitude_rad : wobble amplitude for "small", rad
    acc_rms_m_s2        : RMS of ‖a_n‖ over the motion, m/s² (0 = none; the rest has none)
    n_bumps             : number of accelerometer bumps during the motion

    Random numbers are drawn in a fixed order: start orientation, controls, acceleration,
    bumps.
    """
    if motion not in MOTIONS:
        raise MagcalError(f"simulate: unknown motion {motion!r}; use one of {', '.join(MOTIONS)}")
    for name, v in (("rate_hz", rate_hz), ("max_rate_rad_s", max_rate_rad_s)):
        if not np.isfinite(v) or v <= 0.0:
            raise MagcalError(f"simulate: {name} must be positive, got {v!r}")
    for name, v in (
        ("stationary_s", stationary_s),
        ("duration_s", duration_s),
        ("acc_rms_m_s2", acc_rms_m_s2),
    ):
        if not np.isfinite(v) or v < 0.0:
            raise MagcalError(f"simulate: {name} must be ≥ 0, got {v!r}")
    if motion == "small" and not small_amplitude_rad > 0.0:
        raise MagcalError(
            f"simulate: small_amplitude_rad must be positive, got {small_amplitude_rad!r}"
        )
    if n_bumps < 0:
        raise MagcalError(f"simulate: n_bumps must be ≥ 0, got {n_bumps}")
    n_s = int(round(stationary_s * rate_hz))
    n_m = int(round(duration_s * rate_hz))
    n = n_s + n_m
    if n < 2:
        raise MagcalError(
            f"simulate: {n} samples at {rate_hz} Hz; give at least 2 (longer duration_s)"
        )
    dt = 1.0 / rate_hz

    if motion in ("tumble", "swing"):
        start = random_rotation(rng)
        step = TUMBLE_STEP_RAD
    elif motion == "yaw-only":
        yaw0 = rng.uniform(-np.pi, np.pi)
        start = frames.rotvec_to_quat(np.array([0.0, 0.0, yaw0]))
        step = YAW_STEP_RAD
    else:
        start = random_rotation(rng)
        step = 2.0 * small_amplitude_rad
    knot_s = step / max_rate_rad_s
    # Controls: 3 copies of the start (clamped start), then enough to cover τ ∈ [0, n_m T].
    n_more = int(np.floor(n_m * dt / knot_s)) + 1
    clamp = np.repeat(start[None], 3, axis=0)
    if motion in ("tumble", "swing"):
        # Short sessions make only one or two tours, and a tour's spread of orientations varies
        # with the grid's random rotation: keep the best of a few candidate tours.
        n_cand = TUMBLE_CANDIDATES if n_more <= 2 * TUMBLE_LAP_MAX_POINTS else 1
        tau_score = np.linspace(0.0, n_m * dt, TUMBLE_SCORE_POINTS)
        best_score = -1.0
        for _ in range(n_cand):
            cand = np.concatenate([clamp, tumble_controls(rng, start, n_more, step)])
            score = orientation_spread(spline_so3(cand, knot_s, tau_score))
            if score > best_score:
                best_score, controls = score, cand
    elif motion == "yaw-only":
        controls = np.concatenate([clamp, yaw_controls(rng, yaw0, n_more, step)])
    else:
        controls = np.concatenate([clamp, small_controls(rng, start, n_more, small_amplitude_rad)])

    # N + 1 attitudes: the extra one defines the last sample's rate.
    k = np.arange(n + 1)
    tau = np.clip(k - n_s, 0, None) * dt
    q = spline_so3(controls, knot_s, tau)
    q[: n_s + 1] = start  # exactly at rest (the spline gives `start` there up to round-off)
    if motion == "swing":
        angle = SWING_AMPLITUDE_RAD * np.sin(2.0 * np.pi * SWING_HZ * tau)
        swing = frames.rotvec_to_quat(np.column_stack([angle, 0.0 * angle, 0.0 * angle]))
        q = frames.quat_multiply(q, swing)
    q = _make_sign_continuous(q)
    omega = body_rates(q, rate_hz)

    acc_n = np.zeros((n, 3))
    acc_n[n_s:] = band_limited_acceleration(rng, n_m, rate_hz, acc_rms_m_s2)
    bumps, bump_acc = accelerometer_bumps(rng, n_s, n_m, n_bumps)
    acc_n[n_s:] += bump_acc
    return Trajectory(
        t=k[:n] * dt,
        q_nb=q[:n],
        omega_b=omega,
        acc_n=acc_n,
        bumps=bumps,
        n_stationary=n_s,
    )
