# SPDX-License-Identifier: Apache-2.0
"""The multiplicative EKF for orientation (paper Section 5.2): the one place for the filter.

State: ``q̃_nb`` plus a navigation-frame orientation error ``η`` with covariance ``P``
(rad², 3×3); ``q_nb = exp_q(½ η) ⊙ q̃_nb``.

* Time update with the gyroscope as input, sample ``t−1`` → ``t``:
  ``q̃ ← q̃ ⊙ exp_q(½ T (y_ω − δ_ω))``, ``P ← P + T² R Σ_ω Rᵀ + v_t I`` with ``R = R(q̃)``
  and ``v_t`` rad² a data-only uncertainty of the turn, the rate having left a straight
  line within the step (``initial/sensor_levels.turn_variance``).
* Measurement ``y = (y_a, y_m)``: ``ŷ = (−R_bn g_n, D E R_bn m_n + o)``,
  ``H = (−R_bn [g_n×], D E R_bn [m_n×])``, ``S = H P Hᵀ + blockdiag(Σ_a,t, Σ_m)``.
  ``E = Exp(τ (y_ω,t−1 − δ_ω))`` carries the magnetometer's delay τ (``time_offset_s``): its
  sample at t measured the field at t − τ, when the body was turned back by the rate over
  τ (``E = I`` at τ = 0, the paper's model).
  ``Σ_a,t = Σ_a + c_t I`` where ``c_t`` (m/s²)² is a data-only inflation that makes the
  accelerometer count less at outliers (knocks; see
  ``initial/sensor_levels.accelerometer_extra_variance``).
* The first sample is only a measurement update from the given prior ``(q₀, P₀)``.
* Each sample is updated with the measurements present there (``FilterData.has_acc``,
  ``has_mag``): ``y``, ``H`` and ``S`` keep the rows of those only, and a sample with
  neither is a pure time update that adds nothing to the cost. This is how an IMU and a
  slower magnetometer share one time base: every IMU sample propagates, the magnetometer
  updates only where it measured.

Two implementations compute the same numbers:

* :func:`run_filter` calls the C kernel (``host/csrc/mekf_likelihood.c``), which works in
  information form (3×3 instead of 6×6 inverses) and also provides the exact reverse-mode
  gradient used by ``problem.py``;
* :func:`run_filter_reference` is a plain numpy loop with the textbook 6×6 innovation
  covariance. It is slow and exists to check the kernel.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from magcal.calib import frames
from magcal.calib.likelihood.params import ModelParams
from magcal.errors import CalibrationError, MagcalError

try:
    from magcal.calib.likelihood import _mekf
except ImportError as exc:  # pragma: no cover - depends on the build
    raise MagcalError(
        "the native EKF kernel magcal.calib.likelihood._mekf is not built: run `make setup` "
        "(or `pip install -e host`) to compile it"
    ) from exc

# Prior on the initial orientation error: ≈ 10° per axis. The initial attitude comes from
# the first samples and the initial calibration, so it is good to a few degrees; a prior
# this wide lets the first measurements correct it without a long transient in the cost.
INITIAL_ATTITUDE_SIGMA_RAD = np.deg2rad(10.0)
#: Samples averaged for the starting attitude of a filter (≈ 0.05 s at 100 Hz): enough to
#: average noise, short enough that motion at the start does not smear it.
INITIAL_ATTITUDE_SAMPLES = 5


@dataclass(frozen=True)
class FilterData:
    """Everything the filter consumes besides θ, on one time base.

    dt            : (N,) s; dt[0] is unused, dt[t] = time of sample t − time of sample t−1
    gyr, acc, mag : (N, 3) rad/s, m/s², normalised magnetometer units
    acc_extra_var : (N,) (m/s²)², data-only inflation c_t of Σ_a (zeros for none)
    g             : gravity magnitude, m/s²
    q0            : (4,) prior attitude q_nb at sample 0
    P0            : (3, 3) rad², prior covariance of the orientation error
    has_acc       : (N,) bool, the accelerometer measured at sample t
    has_mag       : (N,) bool, the magnetometer measured at sample t
    turn_var      : (N,) rad², data-only uncertainty of the turn integrated in the step to
                    sample t, added to P's diagonal there (None: none)

    Where a measurement is absent its values (``acc[t]`` and ``acc_extra_var[t]``;
    ``mag[t]``) are not read and may be NaN.
    """

    dt: np.ndarray
    gyr: np.ndarray
    acc: np.ndarray
    mag: np.ndarray
    acc_extra_var: np.ndarray
    g: float
    q0: np.ndarray
    P0: np.ndarray
    has_acc: np.ndarray
    has_mag: np.ndarray
    turn_var: np.ndarray | None = None

    def __len__(self) -> int:
        return int(self.dt.shape[0])


@dataclass(frozen=True)
class FilterOutput:
    """cost        : float, V(θ) of eq. (6) (without the constant 3 log 2π per sample)
    q_filt      : (N, 4) filtered attitude q_nb after each measurement update
    innovations : (N, 6) y_t − ŷ_t|t−1 (acc then mag)
    normalised  : (N, 6) L_t⁻¹ (y_t − ŷ_t|t−1), S_t = L_t L_tᵀ (Cholesky)

    In both, a measurement absent at sample t (``FilterData.has_acc``, ``has_mag``) has NaN,
    and the magnetometer's columns are 0 in a filter without magnetometer (``use_mag``
    false). At a sample with no measurement ``q_filt`` is the predicted attitude.
    """

    cost: float
    q_filt: np.ndarray
    innovations: np.ndarray
    normalised: np.ndarray

    def present_normalised(self) -> np.ndarray:
        """(M,) the normalised innovations of the measurements the samples had (those absent
        are left out). NaN remains only where the filter broke down (a non-positive pivot)."""
        return self.normalised[np.isfinite(self.innovations)]


def make_filter_data(
    t: np.ndarray,
    gyr: np.ndarray,
    acc: np.ndarray,
    mag: np.ndarray,
    q0: np.ndarray,
    *,
    acc_extra_var: np.ndarray | None = None,
    g: float | None = None,
    prior_sigma_rad: float = INITIAL_ATTITUDE_SIGMA_RAD,
    has_acc: np.ndarray | None = None,
    has_mag: np.ndarray | None = None,
    turn_var: np.ndarray | None = None,
) -> FilterData:
    """Assemble :class:`FilterData`; ``g`` defaults to the median accelerometer norm (over
    the samples with the accelerometer), so a small accelerometer scale error or local
    gravity does not bias the inclination. ``has_acc``, ``has_mag`` ((N,) bool) say which
    samples have each measurement; the default is every sample. ``turn_var`` (N,) rad²:
    :attr:`FilterData.turn_var` (default none)."""
    t = np.asarray(t, dtype=float)
    dt = np.empty_like(t)
    dt[0] = 0.0
    dt[1:] = np.diff(t)
    acc = np.ascontiguousarray(acc, dtype=float)
    has_acc = _mask(has_acc, len(t), "has_acc")
    has_mag = _mask(has_mag, len(t), "has_mag")
    if g is None:
        g = float(np.median(np.linalg.norm(acc[has_acc], axis=1)))
    if acc_extra_var is None:
        acc_extra_var = np.zeros(len(t))
    return FilterData(
        dt=dt,
        gyr=np.ascontiguousarray(gyr, dtype=float),
        acc=acc,
        mag=np.ascontiguousarray(mag, dtype=float),
        acc_extra_var=np.ascontiguousarray(acc_extra_var, dtype=float),
        g=float(g),
        q0=frames.quat_normalize(np.asarray(q0, dtype=float)),
        P0=np.eye(3) * prior_sigma_rad**2,
        has_acc=has_acc,
        has_mag=has_mag,
        turn_var=None if turn_var is None else np.ascontiguousarray(turn_var, dtype=float),
    )


def _mask(mask: np.ndarray | None, n: int, name: str) -> np.ndarray:
    """(n,) bool: ``mask``, or all True for None."""
    if mask is None:
        return np.ones(n, dtype=bool)
    mask = np.asarray(mask)
    if mask.shape != (n,) or mask.dtype != bool:
        raise ValueError(f"{name}: expected ({n},) bool, got {mask.shape} {mask.dtype}")
    return np.ascontiguousarray(mask)


# ---------------------------------------------------------------- the C kernel
# Conversions between ModelParams/FilterData and the kernel's flat float64 buffers.

#: Doubles of reverse-mode workspace per sample (the C kernel's MC_MEKF_TAPE_DOUBLES): a
#: tape for cost_and_model_gradient holds TAPE_DOUBLES_PER_SAMPLE · N float64.
TAPE_DOUBLES_PER_SAMPLE: int = _mekf.TAPE_DOUBLES_PER_SAMPLE

#: Doubles of the C kernel's model struct (MC_MEKF_MODEL_DOUBLES), in and out.
MODEL_DOUBLES: int = _mekf.MODEL_DOUBLES

# The fields of the C struct mc_mekf_model_t in order, named as in ModelGradient, with their
# shapes (matrices row-major). The gradient has the same layout.
_MODEL_FIELDS: tuple[tuple[str, tuple[int, ...]], ...] = (
    ("D", (3, 3)),
    ("o", (3,)),
    ("m", (3,)),
    ("gyro_bias", (3,)),
    ("Sigma_gyr", (3, 3)),
    ("Sigma_acc", (3, 3)),
    ("Sigma_mag", (3, 3)),
    ("time_offset_s", ()),
)
_MODEL_SLICES: dict[str, slice] = {}
_offset = 0
for _name, _shape in _MODEL_FIELDS:
    _MODEL_SLICES[_name] = slice(_offset, _offset + math.prod(_shape))
    _offset += math.prod(_shape)
if _offset != MODEL_DOUBLES:  # pragma: no cover - only with a stale build
    raise MagcalError(
        f"the native EKF kernel's model has {MODEL_DOUBLES} values but mekf.py lays out "
        f"{_offset}: rebuild it with `make setup`"
    )
del _offset, _name, _shape


def new_tape(n_samples: int) -> np.ndarray:
    """Workspace for :func:`cost_and_model_gradient` over ``n_samples`` samples."""
    return np.empty(TAPE_DOUBLES_PER_SAMPLE * n_samples)


@dataclass(frozen=True)
class ModelGradient:
    """∂V/∂(model quantity), same shapes as :class:`ModelParams` (m w.r.t. m_n)."""

    D: np.ndarray
    o: np.ndarray
    m: np.ndarray
    gyro_bias: np.ndarray
    Sigma_gyr: np.ndarray
    Sigma_acc: np.ndarray
    Sigma_mag: np.ndarray
    time_offset_s: np.ndarray  # 0-d


def _model_buffer(p: ModelParams) -> np.ndarray:
    values = {
        "D": p.D,
        "o": p.o,
        "m": p.m_n,
        "gyro_bias": p.gyro_bias,
        "Sigma_gyr": p.Sigma_gyr,
        "Sigma_acc": p.Sigma_acc,
        "Sigma_mag": p.Sigma_mag,
        "time_offset_s": p.time_offset_s,
    }
    buf = np.empty(MODEL_DOUBLES)
    for name, shape in _MODEL_FIELDS:
        buf[_MODEL_SLICES[name]] = np.asarray(values[name], dtype=float).reshape(shape).ravel()
    return buf


def _data_args(data: FilterData) -> tuple:
    """The kernel's data arguments, in its order (the masks and turn_var go separately:
    :func:`_optional_args`)."""
    return (
        np.ascontiguousarray(data.dt, dtype=float),
        np.ascontiguousarray(data.gyr, dtype=float),
        np.ascontiguousarray(data.acc, dtype=float),
        np.ascontiguousarray(data.mag, dtype=float),
        np.ascontiguousarray(data.acc_extra_var, dtype=float),
        float(data.g),
        np.ascontiguousarray(data.q0, dtype=float),
        np.ascontiguousarray(data.P0, dtype=float),
    )


def _optional_args(data: FilterData) -> tuple:
    """The kernel's (has_acc, has_mag, turn_var): None for a mask that is all True, which the
    kernel reads as present at every sample without loading a mask per sample, and for
    data without a turn variance."""
    masks = tuple(
        None if mask.all() else np.ascontiguousarray(mask, dtype=bool)
        for mask in (data.has_acc, data.has_mag)
    )
    turn = None if data.turn_var is None else np.ascontiguousarray(data.turn_var, dtype=float)
    return (*masks, turn)


def filter_pass(
    p: ModelParams,
    data: FilterData,
    use_mag: bool,
    q_filt: np.ndarray | None = None,
    innov: np.ndarray | None = None,
    normalised: np.ndarray | None = None,
) -> float:
    """Forward pass; fills the optional (N, 4), (N, 6), (N, 6) outputs. Returns V(θ)."""
    return _mekf.cost(
        _model_buffer(p),
        *_data_args(data),
        bool(use_mag),
        q_filt,
        innov,
        normalised,
        *_optional_args(data),
    )


def _check_tape(tape: np.ndarray, n_samples: int) -> None:
    want = (TAPE_DOUBLES_PER_SAMPLE * n_samples,)
    if not isinstance(tape, np.ndarray) or tape.dtype != np.float64:
        got = f"dtype {tape.dtype}" if isinstance(tape, np.ndarray) else type(tape).__name__
        raise TypeError(f"tape: expected a float64 array from new_tape({n_samples}), got {got}")
    if tape.shape != want:
        raise ValueError(
            f"tape: expected shape {want} (new_tape({n_samples}) for {n_samples} samples), "
            f"got {tape.shape}"
        )


def cost_and_model_gradient(
    p: ModelParams, data: FilterData, tape: np.ndarray | None = None
) -> tuple[float, ModelGradient]:
    """V(θ) and its exact gradient w.r.t. the model quantities (one forward + one reverse
    pass), with the magnetometer. ``tape`` (:func:`new_tape` for ``len(data)`` samples) may
    be passed in to reuse the workspace between calls; one of another size or dtype is an
    error. On a non-finite V the gradient is zero."""
    n = len(data)
    if tape is None:
        tape = new_tape(n)
    else:
        _check_tape(tape, n)
    grad = np.empty(MODEL_DOUBLES)
    cost = _mekf.cost_grad(
        _model_buffer(p), *_data_args(data), True, tape, grad, *_optional_args(data)
    )
    return cost, ModelGradient(
        **{name: grad[_MODEL_SLICES[name]].reshape(shape) for name, shape in _MODEL_FIELDS}
    )


#: Most directions :func:`fisher_information` takes in one call (the kernel's limit).
FISHER_MAX_DIRECTIONS: int = _mekf.FISHER_MAX_DIRECTIONS


def fisher_information(
    p: ModelParams, data: FilterData, directions: np.ndarray
) -> tuple[float, np.ndarray, np.ndarray]:
    """V(θ), the Fisher information (k, k) and ∂V (k,) along the k rows of ``directions``
    (k, MODEL_DOUBLES) in the model's flat layout (``params.model_vector``), by forward
    sensitivities of the filter (``host/csrc/mekf_fisher.c``), with the magnetometer.
    On a non-finite V both are zero."""
    directions = np.ascontiguousarray(directions, dtype=float)
    if directions.ndim != 2 or directions.shape[1] != MODEL_DOUBLES:
        raise ValueError(f"directions: expected (k, {MODEL_DOUBLES}), got {directions.shape}")
    k = directions.shape[0]
    info = np.empty((k, k))
    grad = np.empty(k)
    cost = _mekf.fisher(
        _model_buffer(p), *_data_args(data), True, directions, info, grad, *_optional_args(data)
    )
    return cost, info, grad


def _reference_steps(p: ModelParams, data: FilterData, use_mag: bool):
    """The textbook MEKF, one sample at a time: yields (t, rows, ε, S, q) after each sample's
    update, ``rows`` the measured rows of (acc, mag) (an empty array where there is none:
    ε and S are then None and q is the prediction)."""
    g_n = frames.gravity_n(data.g)
    m_n = p.m_n
    G = frames.skew(g_n)
    Mx = frames.skew(m_n)
    q = data.q0.copy()
    P = data.P0.copy()
    for t in range(len(data)):
        rate = data.gyr[max(t - 1, 0)] - p.gyro_bias
        E = frames.rotvec_to_matrix(p.time_offset_s * rate)  # its delay
        if t > 0:
            dt = data.dt[t]
            q = frames.quat_multiply(q, frames.quat_exp(0.5 * dt * (data.gyr[t - 1] - p.gyro_bias)))
            R = frames.quat_to_matrix(q)
            P = P + dt * dt * R @ p.Sigma_gyr @ R.T
            if data.turn_var is not None:
                P = P + data.turn_var[t] * np.eye(3)
        else:
            R = frames.quat_to_matrix(q)
        # The rows of y = (y_a, y_m) measured at t; absent ones are NaN in the outputs.
        rows = np.flatnonzero([data.has_acc[t]] * 3 + [use_mag and data.has_mag[t]] * 3)
        if rows.size == 0:  # no measurement: the prediction is carried on
            yield t, rows, None, None, q
            continue
        Rt = R.T
        y_pred = np.concatenate([-Rt @ g_n, p.D @ E @ Rt @ m_n + p.o])[rows]
        H = np.vstack([-Rt @ G, p.D @ E @ Rt @ Mx])[rows]
        Rm = np.zeros((6, 6))
        Rm[:3, :3] = p.Sigma_acc + data.acc_extra_var[t] * np.eye(3)
        Rm[3:, 3:] = p.Sigma_mag
        Rm = Rm[np.ix_(rows, rows)]
        y = np.concatenate([data.acc[t], data.mag[t]])[rows]
        eps = y - y_pred
        S = H @ P @ H.T + Rm
        L = np.linalg.cholesky(S)
        # K = P Hᵀ S⁻¹ by two triangular solves with the Cholesky factor already at hand, not
        # an explicit inverse (numpy's general solve: at 6 × 6 as exact as a triangular one).
        K = np.linalg.solve(L.T, np.linalg.solve(L, H @ P)).T
        eta = K @ eps
        # Joseph form keeps P symmetric positive definite in finite precision.
        IKH = np.eye(3) - K @ H
        P = IKH @ P @ IKH.T + K @ Rm @ K.T
        q = frames.quat_normalize(frames.quat_multiply(frames.quat_exp(0.5 * eta), q))
        yield t, rows, eps, S, q


def run_filter_reference(p: ModelParams, data: FilterData, use_mag: bool = True) -> FilterOutput:
    """Textbook MEKF with the full innovation covariance over the measurements present at
    each sample (6×6, 3×3 or none). Slow; for tests."""
    n = len(data)
    ny = 6 if use_mag else 3
    cost = 0.0
    q_filt = np.empty((n, 4))
    innov = np.zeros((n, 6))
    normed = np.zeros((n, 6))
    for t, rows, eps, S, q in _reference_steps(p, data, use_mag):
        q_filt[t] = q
        innov[t, :ny] = np.nan
        normed[t, :ny] = np.nan
        if rows.size == 0:
            continue
        L = np.linalg.cholesky(S)
        w = np.linalg.solve(L, eps)  # L⁻¹ε; L is lower-triangular, a general solve as exact
        cost += 0.5 * (w @ w + 2.0 * np.sum(np.log(np.diag(L))))
        innov[t, rows] = eps
        normed[t, rows] = w
    return FilterOutput(cost=float(cost), q_filt=q_filt, innovations=innov, normalised=normed)


def reference_innovations(p: ModelParams, data: FilterData) -> list[tuple]:
    """The textbook MEKF's (rows, ε, S) at every sample with a measurement, with the
    magnetometer: what the Fisher information is made of. Slow; for tests."""
    return [(rows, eps, S) for _, rows, eps, S, _ in _reference_steps(p, data, True) if rows.size]


def run_filter(p: ModelParams, data: FilterData, use_mag: bool = True) -> FilterOutput:
    """The C kernel's forward pass with all diagnostics (attitude, innovations)."""
    n = len(data)
    q_filt = np.empty((n, 4))
    innov = np.zeros((n, 6))
    normed = np.zeros((n, 6))
    cost = filter_pass(p, data, use_mag, q_filt, innov, normed)
    if not np.isfinite(cost):
        raise CalibrationError(
            "the orientation filter diverged (non-finite likelihood): check that the session's "
            "units are rad/s and m/s², and that the initial calibration is sensible"
        )
    return FilterOutput(cost=cost, q_filt=q_filt, innovations=innov, normalised=normed)
