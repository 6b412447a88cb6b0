# SPDX-License-Identifier: Apache-2.0
"""Simulation scenarios: configuration, presets, the ``simulate`` entry point, truth files.

``simulate(preset("table2"), seed=3)`` returns a :class:`~magcal.io.session.Session` and the
:class:`SimTruth` it was made from. The same seed always gives the same session. The seed
feeds three independent streams (``SeedSequence(seed).spawn(3)``): sensor parameters, motion,
and measurement noise. So changing only the motion or the noise levels of a scenario keeps the
same sensor (D, o, bias), and changing only the noise keeps the same motion.
"""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from magcal.calib import frames
from magcal.errors import MagcalError
from magcal.io.session import Session, session_from_arrays
from magcal.sim.model import (
    DIP_LINKOPING_DEG,
    SensorTruth,
    ideal_magnetometer,
    measure,
    sample_handheld_magnet,
    sample_mems,
    sample_table2,
)
from magcal.sim.trajectory import MOTIONS, Trajectory, make_trajectory

TRUTH_FORMAT = "magcal-truth/1"
KINDS = ("table2", "mems", "handheld", "raw-counts")


class TruthFormatError(MagcalError):
    """A truth file does not follow ``magcal-truth/1``."""


@dataclass(frozen=True)
class ScenarioConfig:
    """Everything :func:`simulate` needs besides the seed.

    kind                  : sensor model: "table2" (paper Table 2, normalised field),
                            "mems", "handheld" (magnet next to the sensor), "raw-counts"
                            (the MEMS model in raw units)
    rate_hz               : sample rate of all three sensors, Hz
    duration_s            : length of the motion, s
    stationary_s          : rest before the motion, s (0 = none)
    motion                : "tumble", "yaw-only" or "small"
    max_rate_rad_s        : bound on the angular rate, rad/s
    small_amplitude_deg   : wobble amplitude of the "small" motion, degrees
    translational_acc_rms : RMS of ‖a_n‖ during the motion, m/s² (0 = pure rotation)
    n_bumps               : accelerometer bumps (1-3 samples, 5-20 m/s²) during the motion
    field_scale           : field magnitude in magnetometer units; scales D (and, for
                            "table2", also o and Σ_m)
    offset_scale          : offset size in magnetometer units (see the samplers); None = the
                            model's default; not used by "table2"
    dip_deg               : dip angle, degrees, positive down
    gyro_sigma            : if set, Σ_ω = gyro_sigma² I, rad/s (0 = noise-free)
    acc_sigma             : if set, Σ_a = acc_sigma² I, m/s²
    mag_sigma             : if set, Σ_m = mag_sigma² I, magnetometer units
    mag_rate_hz           : if set below ``rate_hz``, the magnetometer's own rate, Hz: it
                            samples at the IMU row nearest each multiple of 1/mag_rate_hz
                            and the other rows have none (a multi-rate session)
    mag_lag_s             : the magnetometer at time t shows the field at t − mag_lag_s, s
                            (the truth records it as ``time_offset_s``)
    """

    kind: str = "mems"
    rate_hz: float = 100.0
    duration_s: float = 60.0
    stationary_s: float = 2.0
    motion: str = "tumble"
    max_rate_rad_s: float = 1.0
    small_amplitude_deg: float = 10.0
    translational_acc_rms: float = 0.0
    n_bumps: int = 0
    field_scale: float = 1.0
    offset_scale: float | None = None
    dip_deg: float = DIP_LINKOPING_DEG
    gyro_sigma: float | None = None
    acc_sigma: float | None = None
    mag_sigma: float | None = None
    mag_rate_hz: float | None = None
    mag_lag_s: float = 0.0


PRESETS: dict[str, ScenarioConfig] = {
    # Paper Section 8 / Table 2: 100 stationary + 300 rotating samples, no acceleration. The
    # paper gives no sample rate; at 100 Hz the rotation lasts 3 s, so visiting diverse
    # orientations takes a fast rotation (up to 2π rad/s, about 3.6 rad/s on average).
    "table2": ScenarioConfig(
        kind="table2", rate_hz=100.0, stationary_s=1.0, duration_s=3.0, max_rate_rad_s=2 * np.pi
    ),
    # A MEMS unit turned slowly through all orientations, like the paper's experiments.
    "mems": ScenarioConfig(
        kind="mems", rate_hz=100.0, stationary_s=2.0, duration_s=60.0, max_rate_rad_s=1.0
    ),
    # Hand-held with a magnet a centimetre away: fast motion, no rest, 1 m/s² RMS
    # acceleration, a few knocks.
    "handheld": ScenarioConfig(
        kind="handheld",
        rate_hz=100.0,
        stationary_s=0.0,
        duration_s=60.0,
        max_rate_rad_s=3.0,
        translational_acc_rms=1.0,
        n_bumps=5,
    ),
    # Raw counts: field ≈ 50 counts, offsets up to 100 counts per axis, hand-held motion.
    "raw-counts": ScenarioConfig(
        kind="raw-counts",
        rate_hz=100.0,
        stationary_s=0.0,
        duration_s=60.0,
        max_rate_rad_s=2.0,
        translational_acc_rms=0.3,
        field_scale=50.0,
        offset_scale=100.0,
    ),
}


def preset(name: str, **overrides: object) -> ScenarioConfig:
    """The named preset (see ``PRESETS``) with some fields replaced.

    ``preset("mems", duration_s=20.0, motion="yaw-only")``
    """
    if name not in PRESETS:
        raise MagcalError(f"simulate: unknown preset {name!r}; use one of {', '.join(PRESETS)}")
    known = {f.name for f in dataclasses.fields(ScenarioConfig)}
    unknown = sorted(set(overrides) - known)
    if unknown:
        raise MagcalError(
            f"simulate: unknown scenario setting(s) {', '.join(unknown)}; "
            f"known: {', '.join(sorted(known))}"
        )
    return dataclasses.replace(PRESETS[name], **overrides)


@dataclass(frozen=True)
class SimTruth:
    """What a simulated session was made from.

    sensor     : the true parameters
    t          : (N,) float, s (same as the session's t)
    q_nb       : (N, 4) float, true body→nav attitude, sign-continuous
    scenario   : the configuration (None if unknown)
    seed       : the seed (None if unknown)
    trajectory : the full motion (rates, accelerations, bumps); None when read from a file
    """

    sensor: SensorTruth
    t: np.ndarray
    q_nb: np.ndarray
    scenario: ScenarioConfig | None = None
    seed: int | None = None
    trajectory: Trajectory | None = None


def sample_sensor(scenario: ScenarioConfig, rng: np.random.Generator) -> SensorTruth:
    """The scenario's sensor model drawn with ``rng``, with its noise overrides applied."""
    kind = scenario.kind
    if kind == "table2":
        if scenario.offset_scale is not None:
            raise MagcalError(
                "simulate: offset_scale is not used by kind 'table2' (o ~ U(-1, 1) · "
                "field_scale); leave it unset"
            )
        s = float(scenario.field_scale)
        if not np.isfinite(s) or s <= 0.0:
            raise MagcalError(f"simulate: field_scale must be positive, got {s!r}")
        base = sample_table2(rng, dip_deg=scenario.dip_deg)
        sensor = dataclasses.replace(
            base, D=s * base.D, o=s * base.o, Sigma_mag=s * s * base.Sigma_mag
        )
    elif kind in ("mems", "raw-counts"):
        sensor = sample_mems(rng, scenario.field_scale, scenario.offset_scale, scenario.dip_deg)
    elif kind == "handheld":
        sensor = sample_handheld_magnet(
            rng, scenario.field_scale, scenario.offset_scale, scenario.dip_deg
        )
    else:
        raise MagcalError(f"simulate: unknown kind {kind!r}; use one of {', '.join(KINDS)}")
    for attr, sigma in (
        ("Sigma_gyr", scenario.gyro_sigma),
        ("Sigma_acc", scenario.acc_sigma),
        ("Sigma_mag", scenario.mag_sigma),
    ):
        if sigma is not None:
            if not np.isfinite(sigma) or sigma < 0.0:
                raise MagcalError(f"simulate: noise sigma must be ≥ 0, got {sigma!r}")
            sensor = dataclasses.replace(sensor, **{attr: float(sigma) ** 2 * np.eye(3)})
    return sensor


def attitude_at(t: np.ndarray, q_nb: np.ndarray, when: np.ndarray) -> np.ndarray:
    """(K, 4) the attitude at times ``when`` (K,), spherically interpolated between the
    samples (t, q_nb); held at the ends."""
    when = np.clip(when, t[0], t[-1])
    i = np.clip(np.searchsorted(t, when, side="right") - 1, 0, t.size - 2)
    u = ((when - t[i]) / (t[i + 1] - t[i]))[:, None]
    step = frames.quat_log(frames.quat_multiply(frames.quat_conjugate(q_nb[i]), q_nb[i + 1]))
    return frames.quat_multiply(q_nb[i], frames.quat_exp(u * step))


def magnetometer_rows(t: np.ndarray, rate_hz: float, mag_rate_hz: float) -> np.ndarray:
    """(N,) bool: the rows at which a magnetometer at ``mag_rate_hz`` samples (the row
    nearest each multiple of its period; every row when it is not slower than the IMU)."""
    if not np.isfinite(mag_rate_hz) or mag_rate_hz <= 0.0:
        raise MagcalError(f"simulate: mag_rate_hz must be positive, got {mag_rate_hz!r}")
    rows = np.ones(t.size, dtype=bool)
    if mag_rate_hz >= rate_hz:
        return rows
    times = np.arange(t[0], t[-1], 1.0 / mag_rate_hz)
    rows[:] = False
    rows[np.unique(np.clip(np.searchsorted(t, times - 0.5 / rate_hz), 0, t.size - 1))] = True
    return rows


def simulate(scenario: ScenarioConfig, seed: int) -> tuple[Session, SimTruth]:
    """Simulate one session.

    scenario : what to simulate (see :func:`preset`)
    seed     : non-negative integer; equal seeds give identical sessions
    returns  : (Session with t s, gyr rad/s, acc m/s², mag magnetometer units; its SimTruth)
    """
    if isinstance(seed, bool) or not isinstance(seed, int | np.integer) or seed < 0:
        raise MagcalError(f"simulate: seed must be a non-negative integer, got {seed!r}")
    if scenario.motion not in MOTIONS:
        raise MagcalError(
            f"simulate: unknown motion {scenario.motion!r}; use one of {', '.join(MOTIONS)}"
        )
    rng_sensor, rng_motion, rng_noise = (
        np.random.default_rng(s) for s in np.random.SeedSequence(int(seed)).spawn(3)
    )
    sensor = sample_sensor(scenario, rng_sensor)
    traj = make_trajectory(
        rng_motion,
        rate_hz=scenario.rate_hz,
        stationary_s=scenario.stationary_s,
        duration_s=scenario.duration_s,
        motion=scenario.motion,
        max_rate_rad_s=scenario.max_rate_rad_s,
        small_amplitude_rad=np.deg2rad(scenario.small_amplitude_deg),
        acc_rms_m_s2=scenario.translational_acc_rms,
        n_bumps=int(scenario.n_bumps),
    )
    gyr, acc, mag = measure(sensor, traj.q_nb, traj.omega_b, traj.acc_n, rng_noise)
    lag = float(scenario.mag_lag_s)
    if not np.isfinite(lag) or abs(lag) >= traj.t[-1] - traj.t[0]:
        raise MagcalError(
            f"simulate: mag_lag_s must be finite and shorter than the session, got {lag!r}"
        )
    if lag != 0.0:
        # The same noise, on the field seen at t − lag.
        mag = (
            mag
            - ideal_magnetometer(sensor, frames.quat_to_matrix(traj.q_nb))
            + ideal_magnetometer(
                sensor, frames.quat_to_matrix(attitude_at(traj.t, traj.q_nb, traj.t - lag))
            )
        )
    if scenario.mag_rate_hz is not None:
        mag[~magnetometer_rows(traj.t, scenario.rate_hz, float(scenario.mag_rate_hz))] = np.nan
    meta = {
        "source": f"magcal simulate: kind {scenario.kind}, motion {scenario.motion}, seed {seed}",
        "mag_unit": f"simulated (field magnitude {scenario.field_scale:g})",
    }
    session = session_from_arrays(traj.t, gyr, acc, mag, meta)
    truth = SimTruth(
        sensor=sensor,
        t=traj.t,
        q_nb=traj.q_nb,
        scenario=scenario,
        seed=int(seed),
        trajectory=traj,
    )
    return session, truth


def truth_to_dict(truth: SimTruth) -> dict:
    """The ``magcal-truth/1`` JSON object of a truth (all arrays as nested lists).

    Keys: format, D, D_inv, o, m_n, dip_deg, gyro_bias (rad/s), Sigma_gyr, Sigma_acc,
    Sigma_mag, t, q_nb ([w, x, y, z] rows), scenario (settings or null), seed (or null),
    time_offset_s (the magnetometer's lag behind the IMU, s: it shows the field at t − lag), and,
    when the full trajectory is known, n_stationary and bumps ([first sample, length] rows).
    """
    s = truth.sensor
    d = {
        "format": TRUTH_FORMAT,
        "D": np.asarray(s.D).tolist(),
        "D_inv": np.linalg.inv(s.D).tolist(),
        "o": np.asarray(s.o).tolist(),
        "m_n": s.m_n.tolist(),
        "dip_deg": float(np.rad2deg(s.dip_rad)),
        "gyro_bias": np.asarray(s.gyro_bias).tolist(),
        "Sigma_gyr": np.asarray(s.Sigma_gyr).tolist(),
        "Sigma_acc": np.asarray(s.Sigma_acc).tolist(),
        "Sigma_mag": np.asarray(s.Sigma_mag).tolist(),
        "t": np.asarray(truth.t).tolist(),
        "q_nb": np.asarray(truth.q_nb).tolist(),
        "scenario": None if truth.scenario is None else dataclasses.asdict(truth.scenario),
        "seed": truth.seed,
        "time_offset_s": 0.0 if truth.scenario is None else float(truth.scenario.mag_lag_s),
    }
    if truth.trajectory is not None:
        d["n_stationary"] = int(truth.trajectory.n_stationary)
        d["bumps"] = truth.trajectory.bumps.tolist()
    return d


def write_truth(path: str | Path, truth: SimTruth) -> None:
    """Write ``truth`` as ``magcal-truth/1`` JSON to ``path``."""
    from magcal.io.session import os_error_advice

    text = json.dumps(truth_to_dict(truth))  # encode first: a failure leaves no partial file
    try:
        with open(path, "w", encoding="utf-8") as f:
            f.write(text + "\n")
    except OSError as e:
        raise TruthFormatError(
            f"writing truth {path}: {os_error_advice(e, path, writing=True)}"
        ) from e


def _array(d: dict, key: str, shape: tuple[int | None, ...], path: str) -> np.ndarray:
    if key not in d:
        raise TruthFormatError(f"reading truth {path}: missing key {key!r}; rewrite the file")
    try:
        a = np.asarray(d[key], dtype=float)
    except (TypeError, ValueError):
        raise TruthFormatError(
            f"reading truth {path}: {key!r} is not a numeric array; rewrite the file"
        ) from None
    if a.ndim != len(shape) or any(
        n is not None and n != m for n, m in zip(shape, a.shape, strict=True)
    ):
        want = "×".join("N" if n is None else str(n) for n in shape)
        raise TruthFormatError(
            f"reading truth {path}: {key!r} has shape {a.shape}, expected {want}"
        )
    if not np.all(np.isfinite(a)):
        raise TruthFormatError(f"reading truth {path}: {key!r} has non-finite values")
    return a


def read_truth(path: str | Path) -> SimTruth:
    """Read a ``magcal-truth/1`` file written by :func:`write_truth`.

    The result has ``trajectory=None`` (the file holds only t and q_nb of the motion).
    Unknown scenario settings (from newer versions) are ignored.
    """
    from magcal.io.session import os_error_advice

    p = str(path)
    try:
        with open(path, encoding="utf-8") as f:
            d = json.load(f)
    except json.JSONDecodeError as e:
        raise TruthFormatError(f"reading truth {p}: not JSON ({e}); rewrite the file") from None
    except UnicodeDecodeError as e:
        raise TruthFormatError(
            f"reading truth {p}: not UTF-8 text ({e}); is this a truth file from `magcal simulate`?"
        ) from None
    except (ValueError, RecursionError) as e:  # an int of > 4300 digits; absurd nesting
        raise TruthFormatError(f"reading truth {p}: not a usable JSON file ({e})") from None
    except OSError as e:
        raise TruthFormatError(
            f"reading truth {p}: {os_error_advice(e, path, writing=False)}"
        ) from e
    if not isinstance(d, dict) or d.get("format") != TRUTH_FORMAT:
        got = d.get("format") if isinstance(d, dict) else type(d).__name__
        raise TruthFormatError(
            f"reading truth {p}: format is {got!r}, expected {TRUTH_FORMAT!r}; "
            "is this a truth file from `magcal simulate`?"
        )
    if "dip_deg" not in d or not isinstance(d["dip_deg"], int | float):
        raise TruthFormatError(f"reading truth {p}: missing or non-numeric 'dip_deg'")
    try:  # float() of an int beyond float64 (10**400 is valid JSON) raises OverflowError
        dip_deg = float(d["dip_deg"])
        t = _array(d, "t", (None,), p)
        q_nb = _array(d, "q_nb", (t.shape[0], 4), p)
        sensor = SensorTruth(
            D=_array(d, "D", (3, 3), p),
            o=_array(d, "o", (3,), p),
            dip_rad=float(np.deg2rad(dip_deg)),
            gyro_bias=_array(d, "gyro_bias", (3,), p),
            Sigma_gyr=_array(d, "Sigma_gyr", (3, 3), p),
            Sigma_acc=_array(d, "Sigma_acc", (3, 3), p),
            Sigma_mag=_array(d, "Sigma_mag", (3, 3), p),
        )
    except OverflowError:
        raise TruthFormatError(
            f"reading truth {p}: a number is too large for a float64; rewrite the file"
        ) from None
    if not np.isfinite(dip_deg):
        raise TruthFormatError(f"reading truth {p}: 'dip_deg' is not finite ({dip_deg!r})")
    scenario = None
    if isinstance(d.get("scenario"), dict):
        known = {f.name for f in dataclasses.fields(ScenarioConfig)}
        scenario = ScenarioConfig(**{k: v for k, v in d["scenario"].items() if k in known})
    seed = d.get("seed")
    return SimTruth(
        sensor=sensor,
        t=t,
        q_nb=q_nb,
        scenario=scenario,
        seed=int(seed) if isinstance(seed, int) else None,
        trajectory=None,
    )
