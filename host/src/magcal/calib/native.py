"""Thin wrapper around the C kernel ``magcal.calib._mekf`` (host/csrc/mekf_likelihood.c).

It only converts between :class:`ModelParams`/:class:`FilterData` and flat float64 buffers;
the filter itself is documented in ``ekf.py``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from magcal.calib.ekf import FilterData
from magcal.calib.params import ModelParams
from magcal.errors import MagcalError

try:
    from magcal.calib import _mekf
except ImportError as exc:  # pragma: no cover - depends on the build
    raise MagcalError(
        "the native EKF kernel magcal.calib._mekf is not built: run `make setup` (or "
        "`pip install -e host`) to compile it"
    ) from exc

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
)
_MODEL_SLICES: dict[str, slice] = {}
_offset = 0
for _name, _shape in _MODEL_FIELDS:
    _MODEL_SLICES[_name] = slice(_offset, _offset + math.prod(_shape))
    _offset += math.prod(_shape)
if _offset != MODEL_DOUBLES:  # pragma: no cover - only with a stale build
    raise MagcalError(
        f"the native EKF kernel's model has {MODEL_DOUBLES} values but native.py lays out "
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


def _model_buffer(p: ModelParams) -> np.ndarray:
    values = {
        "D": p.D,
        "o": p.o,
        "m": p.m_n,
        "gyro_bias": p.gyro_bias,
        "Sigma_gyr": p.Sigma_gyr,
        "Sigma_acc": p.Sigma_acc,
        "Sigma_mag": p.Sigma_mag,
    }
    buf = np.empty(MODEL_DOUBLES)
    for name, shape in _MODEL_FIELDS:
        buf[_MODEL_SLICES[name]] = np.asarray(values[name], dtype=float).reshape(shape).ravel()
    return buf


def _data_args(data: FilterData) -> tuple:
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


def filter_pass(
    p: ModelParams,
    data: FilterData,
    use_mag: bool,
    q_filt: np.ndarray | None = None,
    innov: np.ndarray | None = None,
    normalised: np.ndarray | None = None,
) -> float:
    """Forward pass; fills the optional (N, 4), (N, 6), (N, 6) outputs. Returns V(θ)."""
    return _mekf.cost(_model_buffer(p), *_data_args(data), bool(use_mag), q_filt, innov, normalised)


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
    cost = _mekf.cost_grad(_model_buffer(p), *_data_args(data), True, tape, grad)
    return cost, ModelGradient(
        **{name: grad[_MODEL_SLICES[name]].reshape(shape) for name, shape in _MODEL_FIELDS}
    )
