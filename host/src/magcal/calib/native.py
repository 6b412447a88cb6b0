"""Thin wrapper around the C kernel ``magcal.calib._mekf`` (host/csrc/mekf_likelihood.c).

It only converts between :class:`ModelParams`/:class:`FilterData` and flat float64 buffers;
the filter itself is documented in ``ekf.py``.
"""

from __future__ import annotations

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
    return np.concatenate(
        [
            np.asarray(p.D, dtype=float).ravel(),
            p.o,
            p.m_n,
            p.gyro_bias,
            np.asarray(p.Sigma_gyr, dtype=float).ravel(),
            np.asarray(p.Sigma_acc, dtype=float).ravel(),
            np.asarray(p.Sigma_mag, dtype=float).ravel(),
        ]
    ).astype(float)


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


def cost_and_model_gradient(
    p: ModelParams, data: FilterData, use_mag: bool = True, tape: np.ndarray | None = None
) -> tuple[float, ModelGradient]:
    """V(θ) and its exact gradient w.r.t. the model quantities (one forward + one reverse
    pass). ``tape`` (:func:`new_tape`) may be passed in to reuse the workspace between calls."""
    if tape is None or tape.shape != (TAPE_DOUBLES_PER_SAMPLE * len(data),):
        tape = new_tape(len(data))
    grad = np.empty(45)
    cost = _mekf.cost_grad(_model_buffer(p), *_data_args(data), bool(use_mag), tape, grad)
    return cost, ModelGradient(
        D=grad[0:9].reshape(3, 3),
        o=grad[9:12],
        m=grad[12:15],
        gyro_bias=grad[15:18],
        Sigma_gyr=grad[18:27].reshape(3, 3),
        Sigma_acc=grad[27:36].reshape(3, 3),
        Sigma_mag=grad[36:45].reshape(3, 3),
    )
